"""EKF-SLAM with range-bearing landmarks (PR chapter 10), known or unknown correspondences.

State: mu = (x, y, theta, m1x, m1y, ..., mLx, mLy) in the map frame (m, rad), covariance Sigma
((3 + 2L) x (3 + 2L)). Landmarks are added the first time they are seen, initialised by inverting the
measurement at the current pose with the covariance that inversion implies (correlated with the pose).

Known correspondences: every measurement carries the landmark's id. Unknown correspondences: each
measurement goes to the landmark of smallest Mahalanobis distance d^2 when d^2 is under
``association_gate``; it starts a new landmark when every d^2 exceeds ``new_landmark_gate``; in between it
is ambiguous and dropped. With known ids, ``outlier_gate`` (if set) drops a measurement whose d^2 exceeds it.

Output per step: the robot pose mean (3,) and covariance (3, 3), landmarks marginalised out (which for a
Gaussian is taking the pose block).
"""
from __future__ import annotations

import numpy as np

from slam.angles import wrap_angle
from slam.motion import MotionModel
from slam.range_bearing import RangeBearingModel, inverse_measurement, predict_measurement

#: chi-square(2) quantiles: 0.99 for association, 0.9999 before a new landmark is started
CHI2_2_99 = 9.2103
CHI2_2_9999 = 18.4207


class EKFSLAM:
    """EKF-SLAM over a pose and a growing list of point landmarks."""

    gaussian = True

    def __init__(
        self,
        motion: MotionModel,
        sensor: RangeBearingModel,
        initial_pose: np.ndarray,
        known_correspondences: bool = True,
        outlier_gate: float | None = None,
        association_gate: float = CHI2_2_99,
        new_landmark_gate: float = CHI2_2_9999,
    ) -> None:
        self.motion = motion
        self.sensor = sensor
        self.known = known_correspondences
        self.outlier_gate = outlier_gate
        self.association_gate = association_gate
        self.new_landmark_gate = new_landmark_gate
        self.mu = np.asarray(initial_pose, dtype=np.float64).copy()
        self.sigma = np.zeros((3, 3))
        self.ids: list[int] = []  # landmark id of each landmark slot (known correspondences), else slot number
        self.slot_of: dict[int, int] = {}
        self.rejected = 0  # measurements dropped by a gate

    @property
    def n_landmarks(self) -> int:
        return (len(self.mu) - 3) // 2

    def landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids (L,) and estimated positions (L, 2) in the map frame (m)."""
        return np.array(self.ids, dtype=np.int64), self.mu[3:].reshape(-1, 2).copy()

    def predict(self, control: np.ndarray) -> None:
        """EKF prediction: only the pose block and the pose-landmark cross terms change."""
        mean, jac_g, q = self.motion.linearize(self.mu[None, :3], control)
        g = jac_g[0]
        self.mu[:3] = mean[0]
        self.sigma[:3, :] = g @ self.sigma[:3, :]
        self.sigma[:, :3] = self.sigma[:, :3] @ g.T
        self.sigma[:3, :3] += q[0]

    def _innovation(self, j: int, z: np.ndarray, noise: np.ndarray):
        """Innovation, H Sigma (2, n) and innovation covariance S (2, 2) of measurement z of landmark slot j,
        with measurement-noise covariance ``noise`` (2, 2)."""
        idx = 3 + 2 * j
        z_hat, h_x, h_m = predict_measurement(self.mu[:3], self.mu[idx:idx + 2])
        h_sigma = h_x @ self.sigma[:3, :] + h_m @ self.sigma[idx:idx + 2, :]
        s = h_sigma[:, :3] @ h_x.T + h_sigma[:, idx:idx + 2] @ h_m.T + noise
        nu = z - z_hat
        nu[1] = wrap_angle(nu[1])
        return nu, h_sigma, s

    def _correct(self, nu: np.ndarray, h_sigma: np.ndarray, s: np.ndarray) -> None:
        gain = np.linalg.solve(s, h_sigma).T  # Sigma H^T S^-1, (n, 2)
        self.mu += gain @ nu
        self.mu[2] = wrap_angle(self.mu[2])
        self.sigma -= gain @ h_sigma
        self.sigma = 0.5 * (self.sigma + self.sigma.T)

    def _add_landmark(self, z: np.ndarray, noise: np.ndarray, landmark_id: int) -> None:
        m, j_z, j_x = inverse_measurement(self.mu[:3], z)
        n = len(self.mu)
        cross = j_x @ self.sigma[:3, :]  # (2, n)
        sigma = np.zeros((n + 2, n + 2))
        sigma[:n, :n] = self.sigma
        sigma[n:, :n] = cross
        sigma[:n, n:] = cross.T
        sigma[n:, n:] = j_x @ self.sigma[:3, :3] @ j_x.T + j_z @ noise @ j_z.T
        self.sigma = sigma
        self.mu = np.concatenate([self.mu, m])
        self.slot_of[landmark_id] = len(self.ids)
        self.ids.append(landmark_id)

    def _associate(self, z: np.ndarray, noise: np.ndarray, taken: set[int]) -> tuple[int | None, float]:
        """Slot of the nearest landmark in Mahalanobis distance (vectorised over landmarks) and its d^2;
        landmarks in ``taken`` (already matched to a measurement of this step) are not candidates."""
        count = self.n_landmarks
        if count == 0:
            return None, np.inf
        poses = np.broadcast_to(self.mu[:3], (count, 3))
        z_hat, h_x, h_m = predict_measurement(poses, self.mu[3:].reshape(count, 2))
        s_rr = self.sigma[:3, :3]
        s_rm = self.sigma[:3, 3:].reshape(3, count, 2).transpose(1, 0, 2)  # (L, 3, 2)
        block = self.sigma[3:, 3:].reshape(count, 2, count, 2)
        s_mm = block[np.arange(count), :, np.arange(count), :]  # (L, 2, 2)
        cross = h_x @ s_rm @ h_m.transpose(0, 2, 1)
        s = h_x @ s_rr @ h_x.transpose(0, 2, 1) + cross + cross.transpose(0, 2, 1) + h_m @ s_mm @ h_m.transpose(0, 2, 1) + noise
        nu = z - z_hat
        nu[:, 1] = wrap_angle(nu[:, 1])
        d2 = np.einsum("li,lij,lj->l", nu, np.linalg.inv(s), nu)
        d2[list(taken)] = np.inf
        best = int(np.argmin(d2))
        return best, float(d2[best])

    def update(self, z: np.ndarray, landmark_id: int, taken: set[int]) -> None:
        """Fuse one measurement z = (range m, bearing rad); ``landmark_id`` is used with known correspondences
        only; unknown correspondences add the matched landmark to ``taken`` (one measurement per landmark
        and step)."""
        noise = self.sensor.covariance(z)
        if self.known:
            if landmark_id not in self.slot_of:
                self._add_landmark(z, noise, landmark_id)
                return
            nu, h_sigma, s = self._innovation(self.slot_of[landmark_id], z, noise)
            if self.outlier_gate is not None and nu @ np.linalg.solve(s, nu) > self.outlier_gate:
                self.rejected += 1
                return
            self._correct(nu, h_sigma, s)
            return
        slot, d2 = self._associate(z, noise, taken)
        if slot is not None and d2 < self.association_gate:
            self._correct(*self._innovation(slot, z, noise))
            taken.add(slot)
        elif d2 > self.new_landmark_gate:
            taken.add(self.n_landmarks)
            self._add_landmark(z, noise, self.n_landmarks)
        else:
            self.rejected += 1

    def step(self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Predict through controls (K, 3), fuse measurements (O, 2); return pose mean (3,) and cov (3, 3)."""
        for control in controls:
            self.predict(control)
        taken: set[int] = set()
        for z, landmark_id in zip(measurements, landmark_ids):
            self.update(np.asarray(z, dtype=np.float64), int(landmark_id), taken)
        return self.mu[:3].copy(), self.sigma[:3, :3].copy()
