"""Grid-based FastSLAM: a Rao-Blackwellized particle filter whose particles each carry an occupancy grid.

Per integrated scan (Grisetti, Stachniss, Burgard 2007, 'Improved techniques for grid mapping with
Rao-Blackwellized particle filters'):
1. every particle's pose moves by the odometry since the last integrated scan (slam.motion's odometry
   model gives the predicted pose x'_j and its covariance Q_j);
2. improved proposal: the scan is matched against the particle's own grid starting from x'_j; the
   product p(z | m_j, x)^(1/gain) N(x; x'_j, Q_j) is approximated by a Gaussian around the match (a
   quadratic fitted to the log-likelihood on a 3 x 3 x 3 stencil gives its curvature: the Laplace
   approximation, see kernels.match_and_propose), the new pose is drawn from it and the weight is
   multiplied by its integral eta_j. A particle whose match scores too low falls back to sampling the
   motion model and is weighted by its scan likelihood;
3. the scan is inserted into every particle's grid (log-odds, copy-on-write tiles, slam.gridslam.tiles);
4. selective resampling: only when the effective sample size N_eff = 1 / sum w^2 falls below
   ``resample_threshold`` * M (low-variance resampling); maps are shared, not copied.

A scan is integrated when the odometry has moved ``linear_update`` m or turned ``angular_update`` rad
since the last integrated one (and always the first); in between, particles follow the odometry
deterministically, so every scan still gets every particle's pose.

The scan likelihood p(z | m, x) is a product over beams of p_rand + (1 - p_rand) exp(-d^2 / 2 sigma^2)
with d the distance from the beam's end to the nearest occupied cell near it (the likelihood field,
evaluated on the grid itself), tempered by 1/gain because neighbouring beams are not independent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam.angles import wrap_angle
from slam.gridslam.config import GridSlamConfig
from slam.gridslam.kernels import log_likelihoods, match_and_propose
from slam.gridslam.tiles import TileMaps
from slam.motion import OdometryMotionModel, odometry_controls
from slam.resampling import effective_sample_size, low_variance_resample, normalize_log_weights
from slam.stats import sample_gaussian


@dataclass(frozen=True)
class StepReport:
    """What one integrated scan did: N_eff after weighting (before resampling), whether it resampled,
    and how many particles fell back to the motion model."""

    ess: float
    resampled: bool
    fallbacks: int


def proposal_stencil(xy: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The 27 offsets (dx m, dy m, dyaw rad) of a 3 x 3 x 3 grid around a pose, and the (10, 27) matrix
    giving the least-squares quadratic [c, g0, g1, g2, a00, a11, a22, a01, a02, a12] through values there
    (see kernels.match_and_propose)."""
    steps = np.array([-1.0, 0.0, 1.0])
    gx, gy, gt = np.meshgrid(steps * xy, steps * xy, steps * yaw, indexing="ij")
    d = np.column_stack([gx.ravel(), gy.ravel(), gt.ravel()])
    design = np.column_stack([np.ones(len(d)), d, 0.5 * d**2, d[:, 0] * d[:, 1], d[:, 0] * d[:, 2], d[:, 1] * d[:, 2]])
    return d, np.linalg.pinv(design)


class GridFastSLAM:
    """The filter's state: M poses, log weights and grids; feed it scans in time order."""

    def __init__(
        self,
        config: GridSlamConfig,
        beam_angles: np.ndarray,
        sensor_offset: np.ndarray,
        range_min: float,
        initial_pose: np.ndarray,
        seed: int,
    ) -> None:
        """beam_angles (B,) rad in the laser frame; sensor_offset (3,) laser pose in the robot frame;
        range_min m (the sensor's); initial_pose (3,) where every particle starts (map frame)."""
        config.validate()
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.cos_b = np.cos(beam_angles)
        self.sin_b = np.sin(beam_angles)
        self.offset = np.asarray(sensor_offset, np.float64)
        self.range_min = max(float(range_min), config.min_range)
        m = config.particles
        self.poses = np.tile(np.asarray(initial_pose, np.float64), (m, 1))
        self.log_w = np.zeros(m)
        self.maps = TileMaps(m, config.resolution, config.tile_cells)
        self.motion = OdometryMotionModel(alphas=config.motion_alphas)
        self.stencil, self.fit = proposal_stencil(config.stencil_xy, config.stencil_yaw)
        self.odometry_ref: np.ndarray | None = None  # odometry at the last integrated scan
        self.reach = config.max_range + float(np.hypot(self.offset[0], self.offset[1]))

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (M,)."""
        return normalize_log_weights(self.log_w)

    def _beams(self, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Insertion ranges r_stop (B,) (NaN: unused), hit flags (B,), and the matching beams' indices."""
        cfg = self.config
        r = np.asarray(ranges, np.float64)
        usable = ~np.isnan(r) & (r >= self.range_min)
        hit = usable & (r <= cfg.max_range)
        r_stop = np.where(usable, np.minimum(r, cfg.max_range), np.nan)
        idx = np.flatnonzero(hit)
        if len(idx) > cfg.match_beams:
            idx = idx[np.unique(np.round(np.linspace(0, len(idx) - 1, cfg.match_beams)).astype(np.int64))]
        return r_stop, hit, idx

    def due(self, odometry: np.ndarray) -> bool:
        """Whether a scan taken at this odometry pose (3,) should be integrated."""
        if self.odometry_ref is None:
            return True
        moved = float(np.hypot(*(odometry[:2] - self.odometry_ref[:2])))
        turned = abs(float(wrap_angle(odometry[2] - self.odometry_ref[2])))
        return moved >= self.config.linear_update or turned >= self.config.angular_update

    def follow(self, odometry: np.ndarray) -> np.ndarray:
        """Particle poses (M, 3) at a scan that is not integrated: the last poses moved by the odometry."""
        if self.odometry_ref is None:
            return self.poses.copy()
        return self.motion.predict(self.poses, odometry_controls(np.stack([self.odometry_ref, odometry]))[0])

    def _cover(self, poses: np.ndarray) -> None:
        lo = poses[:, :2].min(axis=0) - self.reach
        hi = poses[:, :2].max(axis=0) + self.reach
        self.maps.cover(lo[0], lo[1], hi[0], hi[1])

    def _insert(self, poses: np.ndarray, r_stop: np.ndarray, hit: np.ndarray) -> None:
        cfg = self.config
        self.maps.insert(poses, self.offset, self.cos_b, self.sin_b, r_stop, hit, cfg.l_occ, cfg.l_free, cfg.l_clamp)

    def _propose(self, control: np.ndarray, r_stop: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """New poses (M, 3), log weight factors (M,) and the number of motion-model fallbacks."""
        cfg, maps = self.config, self.maps
        predicted, _, q = self.motion.linearize(self.poses, control)
        q = q + np.diag([cfg.motion_floor_xy**2, cfg.motion_floor_xy**2, cfg.motion_floor_yaw**2])
        self._cover(predicted)
        q_inv = np.linalg.inv(q)
        q_logdet = np.linalg.slogdet(q)[1]
        beams = (self.cos_b[idx], self.sin_b[idx], r_stop[idx])
        grid = (maps.pool, maps.table, maps.tx0, maps.ty0, maps.shift, cfg.resolution)
        # other places to start the match from: where the particle stood (the wheels slipped) and as far
        # backwards as the odometry says forwards (a log that drops the sign of a backward move)
        moved = predicted[:, :2] - self.poses[:, :2]
        starts = (
            np.stack([self.poses[:, :2], self.poses[:, :2] - moved], axis=1)
            if cfg.slip_starts
            else np.zeros((len(predicted), 0, 2))
        )
        _, score, mean, cov, log_eta = match_and_propose(
            *grid,
            predicted,
            starts,
            q_inv,
            q_logdet,
            self.offset,
            *beams,
            cfg.kernel,
            cfg.sigma_match,
            cfg.sigma_like,
            cfg.p_rand,
            cfg.gain,
            cfg.lin_step,
            cfg.ang_step,
            cfg.refinements,
            cfg.yaw_search,
            cfg.prior_cap,
            self.stencil,
            self.fit,
        )
        good = score >= cfg.min_match * max(len(idx), 1)
        poses = np.empty_like(predicted)
        floor = np.diag([cfg.proposal_floor_xy**2, cfg.proposal_floor_xy**2, cfg.proposal_floor_yaw**2])
        if good.any():
            poses[good] = sample_gaussian(mean[good], cov[good] + floor, self.rng)
        if (~good).any():
            poses[~good] = self.motion.sample(self.poses[~good], control, self.rng)
            own_maps = (maps.pool, maps.table[~good], maps.tx0, maps.ty0, maps.shift, cfg.resolution)
            loglik, _ = log_likelihoods(
                *own_maps, poses[~good], self.offset, *beams, cfg.kernel, cfg.sigma_match, cfg.sigma_like, cfg.p_rand
            )
            log_eta[~good] = loglik / cfg.gain
        poses[:, 2] = wrap_angle(poses[:, 2])
        return poses, log_eta, int((~good).sum())

    def integrate(
        self, odometry: np.ndarray, ranges: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, StepReport]:
        """Integrate one scan (ranges (B,) m) taken at odometry pose (3,).

        Returns the particles' poses (M, 3) and normalised weights (M,) at this scan (before resampling),
        the resampling parents (M,) (particle j continues particle parents[j]) or None, and a report.
        """
        r_stop, hit, idx = self._beams(ranges)
        odometry = np.asarray(odometry, np.float64)
        fallbacks = 0
        if self.odometry_ref is not None:
            control = odometry_controls(np.stack([self.odometry_ref, odometry]))[0]
            self.poses, log_eta, fallbacks = self._propose(control, r_stop, idx)
            self.log_w = self.log_w + log_eta / self.config.weight_temper
            self.log_w -= self.log_w.max()
        else:
            self._cover(self.poses)
        self.odometry_ref = odometry
        self._insert(self.poses, r_stop, hit)
        weights = self.weights
        ess = effective_sample_size(weights)
        poses = self.poses.copy()
        parents = None
        if ess < self.config.resample_threshold * self.config.particles:
            parents = low_variance_resample(weights, self.rng)
            self.maps.resample(parents)
            self.poses = self.poses[parents]
            self.log_w = np.zeros(self.config.particles)
        return poses, weights, parents, StepReport(ess=ess, resampled=parents is not None, fallbacks=fallbacks)
