"""FastSLAM 1.0 and 2.0 (Montemerlo, Thrun, Koller, Wegbreit 2002/2003; PR chapter 13), vectorised over particles.

Each of N particles holds a pose (x, y, theta) in the map frame and one 2-D EKF per landmark. The landmark
EKFs of all particles live in arrays: means ``mu`` (N, L, 2) in m, covariances ``sigma`` (N, L, 2, 2) in m^2
and ``seen`` (N, L); every per-step operation works on all particles at once (no loop over particles).

- Version 1: the pose is drawn from the motion model alone; the weight is the measurement likelihood
  N(z; z_hat, H_m Sigma H_m^T + R).
- Version 2: the pose is drawn from the proposal that also conditions on the measurements. The controls since
  the last step are linearised into a Gaussian N(x_hat, P) per particle (one linearisation in the robot frame,
  rotated to each particle's heading); each measurement of a known landmark
  refines it by a Kalman update (the gain P H_x^T S^-1, which stays finite when P = 0) and multiplies the
  weight by N(z; z_hat, H_x P H_x^T + H_m Sigma H_m^T + R); then one pose is sampled per particle.
After the pose, each landmark EKF is updated with the measurement (or initialised on first sight).

Correspondences: known (one landmark slot per id, shared by all particles) or unknown (per-particle
maximum-likelihood association, each landmark taking at most one measurement per step; a measurement whose
best likelihood is below p0 starts a new landmark in that particle, and the weight takes p0). With known ids,
``outlier_gate`` (a squared Mahalanobis distance) makes a measurement beyond it update nothing in that particle
and caps its likelihood at the gate's value, so one wild measurement cannot wipe out the particles that explain
the rest.

Measurements taken while the robot has not moved since the last update are skipped (unless
``update_while_stationary``): a standing robot has no motion noise to renew the particles, so repeated
measurements with correlated errors would resample the set down to one particle (PR section 4.3.4).

Output per step: the poses (N, 3) and normalised importance weights (N,) before resampling; then, when the
effective sample size falls under ``resample_threshold * N``, low-variance resampling.

Gauge-preserving resampling (known correspondences, ``preserve_gauge``; docs/slam.md, "FastSLAM's gauge").
Moving a particle's pose and map together by one rigid motion (its gauge: where its map sits in the world)
changes none of its future weights, as measurements and robot-frame motion do not see it. Plain resampling
is then neutral drift on the gauge: copying particles with replacement loses gauge diversity at every
resampling until all particles share one gauge, the map's uncertainty in the world frame is gone and the
cloud measures only the pose relative to that map (FastSLAM's long-run overconfidence, Bailey et al. 2006).
So the gauge is resampled without replacement: each particle's gauge is its map's least-squares rigid
alignment to the weighted mean map, the shapes (pose relative to map) are resampled by weight as usual, and
the offspring take the parents' gauges in a random permutation, so the set of gauges survives unchanged. This
is exact when gauge and shape are independent in the posterior, and an approximation otherwise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from slam.angles import wrap_angle
from slam.consistency import scaled_motion
from slam.errors import InputError, check_count, check_within
from slam.gauge import map_gauges, regauge_points, turn_covariances
from slam.kernels import _mixture_nis, _predict_particles, fastslam_known_update
from slam.landmark_filter import LandmarkFilter, LandmarkOptions
from slam.motion import MotionModel, local_motion
from slam.range_bearing import RangeBearingModel, inverse_measurement, predict_measurement
from slam.resampling import effective_sample_size, low_variance_resample, normalize_log_weights
from slam.stats import inv2, sample_gaussian

if TYPE_CHECKING:
    from typing_extensions import Unpack

#: chi-square(2) quantile 0.9999: with unknown correspondences, the default p0 is the likelihood at this
#: squared Mahalanobis distance under the measurement noise alone
CHI2_2_9999 = 18.4207


def _t(mat: np.ndarray) -> np.ndarray:
    return np.swapaxes(mat, -1, -2)


class FastSLAM(LandmarkFilter):
    """A Rao-Blackwellised particle filter over poses with per-particle landmark EKFs (``options``: the shared
    :class:`slam.landmark_filter.LandmarkOptions`)."""

    gaussian = False

    def __init__(
        self,
        motion: MotionModel,
        sensor: RangeBearingModel,
        initial_pose: np.ndarray,
        n_particles: int = 100,
        version: int = 2,
        seed: int = 0,
        resample_threshold: float = 0.5,
        new_landmark_loglik: float | None = None,
        update_while_stationary: bool = False,
        preserve_gauge: bool = True,
        **options: Unpack[LandmarkOptions],
    ) -> None:
        if version not in (1, 2):
            raise InputError(f"FastSLAM version must be 1 or 2, got {version}")
        check_count("n_particles", n_particles)
        check_within("resample_threshold (a share of the particles)", resample_threshold, (0.0, 1.0))
        if new_landmark_loglik is not None:
            check_within("new_landmark_loglik", new_landmark_loglik, (-np.inf, np.inf))
        super().__init__(motion, sensor, initial_pose, **options)
        self.version = version
        self.rng = np.random.default_rng(seed)
        self.resample_threshold = resample_threshold
        if new_landmark_loglik is None:
            new_landmark_loglik = (
                -0.5 * CHI2_2_9999 - 0.5 * np.log(np.linalg.det(sensor.covariance(np.zeros(2)))) - np.log(2 * np.pi)
            )
        self.log_p0 = float(new_landmark_loglik)
        n = n_particles
        self.rows = np.arange(n)
        self.poses = np.tile(self.start, (n, 1))
        self.pose_cov = np.zeros((n, 3, 3))  # version 2: covariance P of the motion prior since the last sample
        self.log_w = np.zeros(n)
        self.mu = np.zeros((n, 4, 2))
        self.sigma = np.zeros((n, 4, 2, 2))
        self.seen = np.zeros((n, 4), dtype=bool)
        self.taken = np.zeros((n, 4), dtype=bool)  # unknown correspondences: slots matched in this step
        self.count = np.zeros(n, dtype=np.int64)  # landmark slots in use per particle
        self.slot_of: dict[int, int] = {}  # known correspondences: landmark id -> slot
        self.resamplings = 0
        self.preserve_gauge = preserve_gauge and self.known  # unknown ids: slots differ per particle
        self.update_while_stationary = update_while_stationary
        self.moved = True  # since the last measurement update (the first measurements are always used)
        self.stationary_skipped = 0  # measurements not used because the robot had not moved
        # each particle's map scale about the start (1 + e, e ~ N(0, scale_sd^2)): no measurement or motion shows
        # it, so it only spreads the poses given out; it stays with the particle's index, as a gauge does
        self.scales = 1.0 + self.scale_sd * np.random.default_rng([seed, 1]).standard_normal(n)
        # each particle's error of the drive angle (e ~ N(0, drive_angle_sd^2), rad), which no data show: it turns the
        # positions given out about the start by e, and stays with the particle's index too
        self.drive_offsets = self.drive_angle_sd * np.random.default_rng([seed, 2]).standard_normal(n)

    # ------------------------------------------------------------------------------------------- state

    def _ensure_capacity(self, needed: int) -> None:
        capacity = self.mu.shape[1]
        if needed <= capacity:
            return
        extra = max(needed, 2 * capacity) - capacity
        self.mu = np.concatenate([self.mu, np.zeros((len(self.rows), extra, 2))], axis=1)
        self.sigma = np.concatenate([self.sigma, np.zeros((len(self.rows), extra, 2, 2))], axis=1)
        self.seen = np.concatenate([self.seen, np.zeros((len(self.rows), extra), dtype=bool)], axis=1)
        self.taken = np.concatenate([self.taken, np.zeros((len(self.rows), extra), dtype=bool)], axis=1)

    def landmarks(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Slots (L,) and landmark means (L, 2) in m of one particle (known ids: slot k holds the k-th id seen)."""
        slots = np.flatnonzero(self.seen[particle])
        return slots, self.mu[particle, slots].copy()

    # ------------------------------------------------------------------------------------------- models

    def _innovation(self, poses, pose_cov, mu, sigma, z, noise):
        """Innovation nu, its covariance S = H_x P H_x^T + H_m Sigma H_m^T + R and H_x, for broadcast stacks."""
        z_hat, h_x, h_m = predict_measurement(poses, mu)
        s = h_x @ pose_cov @ _t(h_x) + h_m @ sigma @ _t(h_m) + noise
        nu = z - z_hat
        nu[..., 1] = wrap_angle(nu[..., 1])
        return nu, s, h_x

    def _associate(self, z: np.ndarray, noise: np.ndarray):
        """Unknown ids: slot (N,) and is-new (N,) of measurement z in each particle (maximum likelihood among the
        landmarks not yet matched in this step), with nu, S^-1, det S, H_x and d^2 at that slot."""
        nu, s, _ = self._innovation(self.poses[:, None, :], self.pose_cov[:, None], self.mu, self.sigma, z, noise)
        s_inv, det = inv2(s)
        d2 = np.einsum("nli,nlij,nlj->nl", nu, s_inv, nu)
        loglik = np.where(self.seen & ~self.taken, -0.5 * d2 - 0.5 * np.log(np.abs(det)) - np.log(2 * np.pi), -np.inf)
        best = np.argmax(loglik, axis=1)
        is_new = loglik[self.rows, best] < self.log_p0
        slot = np.where(is_new, self.count, best)
        self.count = self.count + is_new
        self._ensure_capacity(int(self.count.max()))
        self.taken[self.rows, slot] = True
        nu, s, h_x = self._innovation(
            self.poses, self.pose_cov, self.mu[self.rows, slot], self.sigma[self.rows, slot], z, noise
        )
        s_inv, det = inv2(s)
        d2 = np.einsum("ni,nij,nj->n", nu, s_inv, nu)
        return slot, is_new, nu, s_inv, det, h_x, d2

    def _slots(self, landmark_ids: np.ndarray) -> np.ndarray:
        """Known ids: the landmark slot (O,) of each id, new ids getting the next free slots."""
        for landmark_id in landmark_ids:
            if int(landmark_id) not in self.slot_of:
                self.slot_of[int(landmark_id)] = len(self.slot_of)
        self._ensure_capacity(len(self.slot_of))
        return np.array([self.slot_of[int(i)] for i in landmark_ids], dtype=np.int64)

    def predict(self, controls: np.ndarray) -> None:
        """Move every particle by the controls (K, 3) of one step: one sample per control (version 1), or the
        Gaussian prior N(x (+) delta, R P_local R^T) of the whole step (version 2; see slam.motion.local_motion);
        the motion noise times the consistency monitor's noise scale."""
        scale = self.monitor.scale
        if self.version == 1:
            motion = scaled_motion(self.motion, scale)
            for control in controls:
                self.poses = motion.sample(self.poses, control, self.rng)
            return
        if len(controls) == 0:
            return
        delta, cov_local = local_motion(self.motion, controls)
        _predict_particles(self.poses, self.pose_cov, delta, cov_local * scale)

    def update(self, measurements: np.ndarray, landmark_ids: np.ndarray) -> None:
        """Weight by, sample with (version 2) and fuse the measurements (O, 2) of one step; each measurement of a
        landmark some particle has mapped gives its NIS under the particles' mixture to the consistency monitor."""
        measurements = np.ascontiguousarray(measurements, dtype=np.float64).reshape(-1, 2)
        if not self.known:
            nis = self._update_unknown(measurements)
        else:
            slots = self._slots(landmark_ids)  # first: it may grow the landmark arrays
            scale = self.monitor.scale
            sd_range = self.sensor.sigma_range + self.sensor.range_fraction * measurements[:, 0]
            noise = np.column_stack([sd_range**2, np.full(len(measurements), self.sensor.sigma_bearing**2)]) * scale
            normals = self.rng.standard_normal(self.poses.shape) if self.version == 2 else np.zeros(self.poses.shape)
            nis = np.empty(len(measurements))
            gate = np.inf if self.outlier_gate is None else float(self.outlier_gate)
            fastslam_known_update(
                self.version, self.poses, self.pose_cov, self.mu, self.sigma, self.seen, self.log_w, measurements,
                slots, noise, gate, self.log_p0, normals, nis,
            )  # fmt: skip
        for value in nis:
            factor = self.monitor.add(float(value), self.outlier_gate is not None and value > self.outlier_gate)
            if factor is not None:
                self._rescale(factor)

    def _rescale(self, factor: float) -> None:
        """The consistency watch multiplied the noise by ``factor``: multiply the landmark covariances by it too,
        and the particles' spread about their weighted mean pose by its square root, each particle's pose and
        map moved together by one rigid motion (as gauge-preserving resampling moves them: no weight changes), so
        the set's covariance scales as a Gaussian filter's would."""
        self.sigma *= factor
        weights = normalize_log_weights(self.log_w)
        centre = weights @ self.poses[:, :2]
        heading = float(np.angle(weights @ np.exp(1j * self.poses[:, 2])))
        grow = math.sqrt(factor) - 1.0
        turn = grow * wrap_angle(self.poses[:, 2] - heading)
        target = self.poses[:, :2] + grow * (self.poses[:, :2] - centre)
        self._regauge(turn, self.poses[:, :2].copy(), target)

    def _update_unknown(self, measurements: np.ndarray) -> np.ndarray:
        """:meth:`update` with unknown ids, vectorised over particles; returns each measurement's mixture NIS."""
        pending = []
        nis = np.full(len(measurements), np.nan)
        self.taken[:] = False
        for k, z in enumerate(measurements):
            noise = self.sensor.covariance(z) * self.monitor.scale
            before = self.log_w.copy()
            slot, is_new, nu, s_inv, det, h_x, d2 = self._associate(z, noise)
            inlier = ~is_new
            loglik = -0.5 * d2 - 0.5 * np.log(np.abs(det)) - np.log(2 * np.pi)
            self.log_w += np.where(is_new, self.log_p0, loglik)
            s = (
                s_inv[:, [1, 0, 0], [1, 1, 0]] * np.array([1.0, -1.0, 1.0]) * det[:, None]
            )  # S from S^-1: (s00, s01, s11)
            nis[k] = _mixture_nis(before, inlier, np.ascontiguousarray(nu), np.ascontiguousarray(s))
            if self.version == 2:
                gain = self.pose_cov @ _t(h_x) @ s_inv  # (N, 3, 2)
                step = np.einsum("nij,nj->ni", gain, nu)
                self.poses = np.where(inlier[:, None], self.poses + step, self.poses)
                self.poses[:, 2] = wrap_angle(self.poses[:, 2])
                shrink = gain @ h_x @ self.pose_cov
                self.pose_cov = np.where(inlier[:, None, None], self.pose_cov - shrink, self.pose_cov)
            pending.append((z, noise, slot, is_new, inlier))
        if self.version == 2:
            cov = 0.5 * (self.pose_cov + _t(self.pose_cov))
            self.poses = sample_gaussian(self.poses, cov, self.rng)
            self.poses[:, 2] = wrap_angle(self.poses[:, 2])
            self.pose_cov = np.zeros_like(self.pose_cov)
        for z, noise, slot, is_new, inlier in pending:
            self._fuse_landmark(z, noise, slot, is_new, inlier)
        return nis

    def _fuse_landmark(
        self, z: np.ndarray, noise: np.ndarray, slot: np.ndarray, is_new: np.ndarray, inlier: np.ndarray
    ) -> None:
        """EKF update of each particle's landmark at ``slot`` from its pose, or its initialisation when new."""
        mu = self.mu[self.rows, slot]
        sigma = self.sigma[self.rows, slot]
        z_hat, _, h_m = predict_measurement(self.poses, mu)
        nu = z - z_hat
        nu[:, 1] = wrap_angle(nu[:, 1])
        q_inv, _ = inv2(h_m @ sigma @ _t(h_m) + noise)
        gain = sigma @ _t(h_m) @ q_inv
        updated_mu = mu + np.einsum("nij,nj->ni", gain, nu)
        updated_sigma = sigma - gain @ h_m @ sigma
        init_mu, j_z, _ = inverse_measurement(self.poses, z)
        init_sigma = j_z @ noise @ _t(j_z)
        new_mu = np.where(is_new[:, None], init_mu, np.where(inlier[:, None], updated_mu, mu))
        new_sigma = np.where(is_new[:, None, None], init_sigma, np.where(inlier[:, None, None], updated_sigma, sigma))
        self.mu[self.rows, slot] = new_mu
        self.sigma[self.rows, slot] = 0.5 * (new_sigma + _t(new_sigma))
        self.seen[self.rows, slot] |= is_new

    def resample_if_degenerate(self, weights: np.ndarray) -> None:
        """Low-variance resampling when N_eff < resample_threshold * N; else keep the weights."""
        if effective_sample_size(weights) >= self.resample_threshold * len(weights):
            self.log_w = np.log(np.maximum(weights, 1e-300))
            return
        keep = low_variance_resample(weights, self.rng)
        gauges = self._gauges(weights)
        self.poses = self.poses[keep]
        self.pose_cov = self.pose_cov[keep]
        self.mu = self.mu[keep]
        self.sigma = self.sigma[keep]
        self.seen = self.seen[keep]
        self.count = self.count[keep]
        if gauges is not None:  # offspring n takes the gauge of particle donor[n], each gauge once
            turn, centre = gauges
            donor = self.rng.permutation(len(weights))
            self._regauge(turn[donor] - turn[keep], centre[keep], centre[donor])
        self.log_w = np.zeros(len(weights))
        self.resamplings += 1

    def _gauges(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Each particle's gauge (slam.gauge.map_gauges: turn (N,) rad, centroid (N, 2) m of its mapped landmarks);
        None when the gauge is not preserved or fewer than two landmarks are mapped."""
        if not self.preserve_gauge:
            return None
        slots = np.flatnonzero(self.seen.all(axis=0))
        if len(slots) < 2:
            return None
        return map_gauges(self.mu[:, slots], weights)

    def _regauge(self, turn: np.ndarray, centre_from: np.ndarray, centre_to: np.ndarray) -> None:
        """Move each particle's pose and map by x -> R(turn) (x - centre_from) + centre_to (one motion each).
        ``pose_cov`` is zero between steps, so there is nothing of it to turn."""
        self.poses[:, :2] = regauge_points(self.poses[:, :2], turn, centre_from, centre_to)
        self.poses[:, 2] = wrap_angle(self.poses[:, 2] + turn)
        self.mu = regauge_points(self.mu, turn, centre_from, centre_to)
        self.sigma = turn_covariances(self.sigma, turn)

    def step(
        self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Predict through controls (K, 3), update with measurements (O, 2) of landmarks ``landmark_ids`` (O,); return
        poses (N, 3) and weights (N,). InputError for inputs :meth:`checked_step` refuses, before any state changes."""
        controls, measurements, landmark_ids = self.checked_step(controls, measurements, landmark_ids)
        self.predict(controls)
        self.moved = self.moved or any(self.motion.moves(control) for control in controls)
        if len(measurements) and not (self.moved or self.update_while_stationary):
            self.stationary_skipped += len(measurements)
            measurements, landmark_ids = measurements[:0], landmark_ids[:0]
        elif len(measurements):
            self.moved = False
        self.update(measurements, landmark_ids)
        weights = normalize_log_weights(self.log_w)
        samples = self.poses.copy()
        lever = self.scales[:, None] * (samples[:, :2] - self.origin)
        if self.drive_angle_sd > 0.0:
            c, s = np.cos(self.drive_offsets), np.sin(self.drive_offsets)
            lever = np.column_stack([c * lever[:, 0] - s * lever[:, 1], s * lever[:, 0] + c * lever[:, 1]])
        samples[:, :2] = self.origin + lever
        samples[:, 2] = self.body_heading(samples[:, 2])
        self.resample_if_degenerate(weights)
        return samples, weights
