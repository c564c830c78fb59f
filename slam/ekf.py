"""EKF-SLAM with range-bearing landmarks, known or unknown correspondences, in the right-invariant form.

The state is the estimate mu = (x, y, theta, m1x, m1y, ..., mLx, mLy) in the map frame (m, rad) and the
covariance Sigma ((3 + 2L) x (3 + 2L)) of its **right-invariant error** (Barrau, Bonnabel, "An EKF-SLAM
algorithm with consistency properties", arXiv:1510.06263, 2015) rather than of the plain difference. With
the true state X = (R, p, m_i) and the estimate X^ the error is X^ X^-1, linearised as
xi = (xi_p (2), xi_theta, xi_m1 (2), ...):

    theta^ = theta + xi_theta,   p^ = Rot(xi_theta) p + xi_p,   m^_i = Rot(xi_theta) m_i + xi_mi,

so xi_theta rotates robot and map together about a fixed point and a common xi_p = xi_mi shifts them together:
exactly the motions that landmarks cannot observe. The point is the start position (the filter's ``origin``), with
every position taken relative to it: the map origin would do in exact arithmetic (a change of the fixed point maps
the errors linearly, and the estimates are the same), but with a start in UTM coordinates, 5e6 m from it, the
covariance held terms of 1e13 whose differences were the pose's 1e-4 m^2, and the filter failed within a run
(a covariance no longer positive semi-definite). In these coordinates

* a motion given in the robot frame (both motion models) leaves xi unchanged (F = I); its noise, given as a
  pose covariance q in plain coordinates by the motion model, enters as B q B^T where the heading noise
  reaches the position and every landmark through -J p and -J m (J the rotation by +90 deg);
* a measurement depends on the pose and landmark only through xi_m - xi_p, so its Jacobian has no
  heading column and no component along the unobservable motions: an update adds no information about
  them. The textbook EKF (PR chapter 10) gains such spurious information through its linearisation and
  becomes overconfident about the heading (MRCLAM robot 1, commands as logged: inside95 0.04, here
  0.75; docs/slam.md);
* a correction xi^ = K nu is applied on the group, X^ <- exp(-xi^) X^.

Landmarks are added the first time they are seen at m = p + Rot(theta) (r cos phi, r sin phi); their error
is xi_p + (dm/dz) n, correlated with the pose through xi_p only.

Known correspondences: every measurement carries the landmark's id. Unknown correspondences: each
measurement goes to the landmark of smallest Mahalanobis distance d^2 among those no earlier measurement of
the step went to, when that d^2 is under ``association_gate``; it starts a new landmark when every landmark's
d^2 (those already matched in the step included) exceeds ``new_landmark_gate``; otherwise it is ambiguous and
dropped. With known ids, ``outlier_gate`` (if set) drops a measurement whose d^2 exceeds it.

Output per step: the robot pose mean (3,) and its covariance (3, 3) in plain (x, y, theta) coordinates,
A Sigma_pose A^T with A = d(x, y, theta)/d(xi_p, xi_theta), the landmarks marginalised out, then moment-matched to
the turn the heading error makes (slam.turn_moments: the linearised strip misses the pull towards the turn's
centre, which a heading sd of 0.2 rad makes many times the strip's width).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from slam.angles import wrap_angle
from slam.landmark_filter import LandmarkFilter, LandmarkOptions, check_gate
from slam.motion import MotionModel, compose, local_motion, rotate_covariance
from slam.range_bearing import RangeBearingModel, inverse_measurement, predict_measurement
from slam.turn_moments import turned_moments

if TYPE_CHECKING:
    from typing_extensions import Unpack

#: chi-square(2) quantiles: 0.99 for association, 0.9999 before a new landmark is started
CHI2_2_99 = 9.2103
CHI2_2_9999 = 18.4207


def invariant_to_plain(pose: np.ndarray, about: np.ndarray) -> np.ndarray:
    """A (3, 3) with (dx, dy, dtheta) = A (xi_px, xi_py, xi_theta) to first order at ``pose`` (x, y, theta):
    a rotation xi_theta about the point ``about`` (2,) moves the position by xi_theta J (p - about)."""
    x, y = pose[0] - about[0], pose[1] - about[1]
    return np.array([[1.0, 0.0, -y], [0.0, 1.0, x], [0.0, 0.0, 1.0]])


def _rotation_left_jacobian(angle: float) -> np.ndarray:
    """V (2, 2) of SE(2)'s exponential: exp(angle, t) translates by V t; the identity at angle 0."""
    if abs(angle) < 1e-9:
        return np.eye(2)
    s, c = np.sin(angle), np.cos(angle)
    return np.array([[s, c - 1.0], [1.0 - c, s]]) / angle


class EKFSLAM(LandmarkFilter):
    """Right-invariant EKF-SLAM over a pose and a growing list of point landmarks (``options``: the shared
    :class:`slam.landmark_filter.LandmarkOptions`)."""

    gaussian = True

    def __init__(
        self,
        motion: MotionModel,
        sensor: RangeBearingModel,
        initial_pose: np.ndarray,
        association_gate: float = CHI2_2_99,
        new_landmark_gate: float = CHI2_2_9999,
        **options: Unpack[LandmarkOptions],
    ) -> None:
        super().__init__(motion, sensor, initial_pose, **options)
        check_gate("association_gate", association_gate)
        check_gate("new_landmark_gate", new_landmark_gate)
        self.association_gate = association_gate
        self.new_landmark_gate = new_landmark_gate
        self.mu = self.start.copy()
        self.sigma = np.zeros((3, 3))  # covariance of xi = (xi_p, xi_theta, xi_m1, ...)
        self.ids: list[int] = []  # landmark id of each landmark slot (known correspondences), else slot number
        self.slot_of: dict[int, int] = {}
        self.rejected = 0  # measurements dropped by a gate

    @property
    def n_landmarks(self) -> int:
        return (len(self.mu) - 3) // 2

    def landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """Landmark ids (L,) and estimated positions (L, 2) in the map frame (m)."""
        return np.array(self.ids, dtype=np.int64), self.mu[3:].reshape(-1, 2).copy()

    def pose_covariance(self) -> np.ndarray:
        """Covariance (3, 3) of the pose (x m, y m, theta rad) in plain coordinates, with the map scale's relative
        uncertainty ``scale_sd`` added: scaling map and path about the start by 1 + e moves the position by
        e (p - start), which no measurement or motion shows (slam.calibration, ``scale_sd``); and the drive angle's:
        an error e in it turns the path about the start by e (slam.landmark_filter, ``turn_covariance``)."""
        a = invariant_to_plain(self.mu[:3], self.origin)
        cov = a @ self.sigma[:3, :3] @ a.T
        lever = self.mu[:2] - self.origin
        cov[:2, :2] += self.scale_sd**2 * np.outer(lever, lever) + self.turn_covariance(self.mu[:2])
        return cov

    def _points(self) -> np.ndarray:
        """Robot position and landmarks as rows (1 + L, 2) relative to ``origin``, the point about which the error's
        rotation moves them."""
        return np.concatenate([self.mu[None, :2], self.mu[3:].reshape(-1, 2)]) - self.origin

    def predict(self, controls: np.ndarray) -> None:
        """Move the mean through one step's controls (K, 3); xi is unchanged (F = I) and gains the step's motion
        noise B q B^T, q the step's pose covariance (slam.motion.local_motion, turned to the map frame, times the
        noise scale) and B taken at the new pose. One control (3,) is a step of one control."""
        controls = np.asarray(controls, dtype=np.float64).reshape(-1, 3)
        if len(controls) == 0:
            return
        delta, cov_local = local_motion(self.motion, controls)
        q = rotate_covariance(cov_local, self.mu[2:3])[0] * self.monitor.scale
        self.mu[:3] = compose(self.mu[None, :3], delta)[0]
        points = self._points()
        noise_map = np.zeros((len(self.mu), 3))  # B = d xi / d(plain pose noise)
        noise_map[0, 0] = noise_map[1, 1] = noise_map[2, 2] = 1.0
        minus_j_points = np.column_stack([points[:, 1], -points[:, 0]])
        noise_map[0:2, 2] = minus_j_points[0]
        noise_map[3:, 2] = minus_j_points[1:].ravel()
        self.sigma += noise_map @ q @ noise_map.T

    def _innovation(self, j: int, z: np.ndarray, noise: np.ndarray):
        """Innovation, H Sigma (2, n) and innovation covariance S (2, 2) of measurement z of landmark slot j,
        with measurement-noise covariance ``noise`` (2, 2). H is h_m on xi_p and -h_m on xi_mj."""
        idx = 3 + 2 * j
        z_hat, _, h_m = predict_measurement(self.mu[:3], self.mu[idx : idx + 2])
        h_sigma = h_m @ (self.sigma[0:2, :] - self.sigma[idx : idx + 2, :])
        s = (h_sigma[:, 0:2] - h_sigma[:, idx : idx + 2]) @ h_m.T + noise
        nu = z - z_hat
        nu[1] = wrap_angle(nu[1])
        return nu, h_sigma, s

    def _correct(self, nu: np.ndarray, h_sigma: np.ndarray, s: np.ndarray) -> None:
        gain = np.linalg.solve(s, h_sigma).T  # Sigma H^T S^-1, (n, 2)
        self._retract(gain @ nu)
        self.sigma -= gain @ h_sigma
        self.sigma = 0.5 * (self.sigma + self.sigma.T)

    def _retract(self, xi: np.ndarray) -> None:
        """X^ <- exp(-xi) X^: rotate robot and landmarks about ``origin`` by -xi_theta, then shift each by
        -V(-xi_theta) xi_p or -V xi_mi."""
        angle = -float(xi[2])
        c, s = np.cos(angle), np.sin(angle)
        shifts = np.concatenate([xi[None, :2], xi[3:].reshape(-1, 2)])
        moved = self._points() @ np.array([[c, s], [-s, c]]) - shifts @ _rotation_left_jacobian(angle).T
        moved += self.origin
        self.mu[:2] = moved[0]
        self.mu[3:] = moved[1:].ravel()
        self.mu[2] = wrap_angle(self.mu[2] + angle)

    def _add_landmark(self, z: np.ndarray, noise: np.ndarray, landmark_id: int) -> None:
        m, j_z, _ = inverse_measurement(self.mu[:3], z)
        n = len(self.mu)
        sigma = np.zeros((n + 2, n + 2))
        sigma[:n, :n] = self.sigma
        sigma[n:, :n] = self.sigma[0:2, :]
        sigma[:n, n:] = self.sigma[:, 0:2]
        sigma[n:, n:] = self.sigma[0:2, 0:2] + j_z @ noise @ j_z.T
        self.sigma = sigma
        self.mu = np.concatenate([self.mu, m])
        self.slot_of[landmark_id] = len(self.ids)
        self.ids.append(landmark_id)

    def _associate(self, z: np.ndarray, noise: np.ndarray, taken: set[int]) -> tuple[int | None, float, float]:
        """Slot of the nearest landmark in Mahalanobis distance (vectorised over landmarks) and its d^2, and the
        smallest d^2 over every landmark. Landmarks in ``taken`` (already matched to a measurement of this step)
        are not candidates for the match, but they count for the smallest d^2: a measurement that falls in
        their gate is not a new landmark."""
        count = self.n_landmarks
        if count == 0:
            return None, np.inf, np.inf
        poses = np.broadcast_to(self.mu[:3], (count, 3))
        z_hat, _, h_m = predict_measurement(poses, self.mu[3:].reshape(count, 2))
        s_pp = self.sigma[0:2, 0:2]
        s_pm = self.sigma[0:2, 3:].reshape(2, count, 2).transpose(1, 0, 2)  # (L, 2, 2)
        block = self.sigma[3:, 3:].reshape(count, 2, count, 2)
        s_mm = block[np.arange(count), :, np.arange(count), :]  # (L, 2, 2)
        difference = s_pp - s_pm - s_pm.transpose(0, 2, 1) + s_mm  # covariance of xi_p - xi_m
        s = h_m @ difference @ h_m.transpose(0, 2, 1) + noise
        nu = z - z_hat
        nu[:, 1] = wrap_angle(nu[:, 1])
        d2 = np.einsum("li,lij,lj->l", nu, np.linalg.inv(s), nu)
        nearest_any = float(d2.min())
        d2[list(taken)] = np.inf
        best = int(np.argmin(d2))
        return best, float(d2[best]), nearest_any

    def _watch(self, d2: float, gated: bool) -> None:
        """Give one NIS to the consistency monitor; scale the covariance when it changes the noise scale."""
        factor = self.monitor.add(d2, gated)
        if factor is not None:
            self.sigma *= factor

    def update(self, z: np.ndarray, landmark_id: int, taken: set[int]) -> None:
        """Fuse one measurement z = (range m, bearing rad); ``landmark_id`` is used with known correspondences
        only; unknown correspondences add the matched landmark to ``taken`` (one measurement per landmark
        and step). Each measurement of a mapped landmark gives its NIS to the consistency monitor."""
        noise = self.sensor.covariance(z) * self.monitor.scale
        if self.known:
            if landmark_id not in self.slot_of:
                self._add_landmark(z, noise, landmark_id)
                return
            nu, h_sigma, s = self._innovation(self.slot_of[landmark_id], z, noise)
            d2 = float(nu @ np.linalg.solve(s, nu))
            gated = self.outlier_gate is not None and d2 > self.outlier_gate
            if gated:
                self.rejected += 1
            else:
                self._correct(nu, h_sigma, s)
            self._watch(d2, gated)
            return
        slot, d2, nearest_any = self._associate(z, noise, taken)
        if slot is not None and d2 < self.association_gate:
            self._correct(*self._innovation(slot, z, noise))
            taken.add(slot)
            self._watch(d2, False)
        elif nearest_any > self.new_landmark_gate:
            taken.add(self.n_landmarks)
            self._add_landmark(z, noise, self.n_landmarks)
        else:
            self.rejected += 1
            self._watch(nearest_any, True)

    def step(
        self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predict through controls (K, 3), fuse measurements (O, 2) of landmarks ``landmark_ids`` (O,); return pose
        mean (3,) and cov (3, 3). InputError for inputs :meth:`checked_step` refuses, before any state changes."""
        controls, measurements, landmark_ids = self.checked_step(controls, measurements, landmark_ids)
        self.predict(controls)
        taken: set[int] = set()
        for z, landmark_id in zip(measurements, landmark_ids, strict=True):
            self.update(np.asarray(z, dtype=np.float64), int(landmark_id), taken)
        mean = self.mu[:3].copy()
        mean[2] = self.body_heading(mean[2])
        return turned_moments(mean, self.pose_covariance())
