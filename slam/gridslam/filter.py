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
   ``resample_threshold`` * M (low-variance resampling), or when KLD-sampling (slam.gridslam.health.kld_count)
   asks for more particles than there are; the new count is KLD-sampling's, within [particles, particle_cap];
   maps are shared, not copied;
5. honesty (slam.gridslam.honesty): each particle keeps a covariance of the spread resampling lost, carried
   along as it moves and lowered when the robot is back where it was long ago; the filter's covariance at a
   scan is the particles' weighted spread plus their kept covariance;
6. health (slam.gridslam.health): the best particle's matched-beam fraction and its z against the recent scans;
   a match that fails does not weigh the particles, and the next scan's proposal is wider;
7. loop closure (config.loop_closure, on by default; slam.gridslam.loops): the scan is a node of a pose graph and is
   searched for, every few scans, in an old submap over a wide window; a closure that moves the graph rebuilds the
   grids from it and moves the particles onto it.

A scan is integrated when the odometry has moved ``linear_update`` m or turned ``angular_update`` rad
since the last integrated one (and always the first); in between, particles follow the odometry
deterministically, so every scan still gets every particle's pose.

The scan likelihood p(z | m, x) is a product over beams of p_rand + (1 - p_rand) exp(-d^2 / 2 sigma^2)
with d the distance from the beam's end to the nearest occupied cell near it (the likelihood field,
evaluated on the grid itself), tempered by 1/gain because neighbouring beams are not independent.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from slam.angles import wrap_angle
from slam.consistency import scaled_motion
from slam.errors import InputError, check_within, finite_array
from slam.gridslam.config import GridSlamConfig
from slam.gridslam.health import HealthWatch, ScanHealth, kld_count, spreads
from slam.gridslam.honesty import (
    Revisits,
    cloud_covariance,
    exploration_covariance,
    resampled_drift,
    transport,
    weighted_covariance,
)
from slam.gridslam.kernels import log_likelihoods, match_and_propose
from slam.gridslam.loops import LoopCloser
from slam.gridslam.tiles import TileMaps
from slam.laserlog import POSE_LIMIT
from slam.motion import OdometryMotionModel, OmniOdometryMotionModel, odometry_controls, rotate_covariance
from slam.posegraph import apply_transform
from slam.resampling import effective_sample_size, low_variance_resample, normalize_log_weights
from slam.stats import sample_gaussian


@dataclass(frozen=True)
class StepReport:
    """What one integrated scan did: N_eff after weighting (before resampling), whether it resampled,
    how many particles fell back to the motion model, and its health (slam.gridslam.health)."""

    ess: float
    resampled: bool
    fallbacks: int
    health: ScanHealth


def proposal_stencil(xy: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The 27 offsets (dx m, dy m, dyaw rad) of a 3 x 3 x 3 grid around a pose, and the (10, 27) matrix
    giving the least-squares quadratic [c, g0, g1, g2, a00, a11, a22, a01, a02, a12] through values there
    (see kernels.match_and_propose)."""
    steps = np.array([-1.0, 0.0, 1.0])
    gx, gy, gt = np.meshgrid(steps * xy, steps * xy, steps * yaw, indexing="ij")
    d = np.column_stack([gx.ravel(), gy.ravel(), gt.ravel()])
    design = np.column_stack([np.ones(len(d)), d, 0.5 * d**2, d[:, 0] * d[:, 1], d[:, 0] * d[:, 2], d[:, 1] * d[:, 2]])
    return d, np.linalg.pinv(design)


def travelled(before: np.ndarray, after: np.ndarray) -> tuple[float, float]:
    """How far odometry pose ``after`` (3,) lies from ``before`` (3,): the distance (m) and the net turn's size
    (rad, at most pi)."""
    moved = float(np.hypot(after[0] - before[0], after[1] - before[1]))
    return moved, abs(float(wrap_angle(after[2] - before[2])))


def motion_steps(moved: float, config: GridSlamConfig) -> float:
    """How many drives of config.motion_step m, which config.motion_alphas then describe, a drive of ``moved`` m
    between two integrated scans holds: at least 1, and 1 where config.motion_step is None.

    The odometry model's variances grow with the square of a move, so a log that integrates a scan every metre
    (the corrected Intel log's scans lie 0.7 to 1 m apart) gets ten times the variance per metre of one that
    integrates every 0.1 m: sd 0.22 m and 0.22 rad for each metre at the default alphas. A drive of k steps is taken
    as k drives of a step, whose errors are independent: its variances are the model's divided by k. Turns count no
    steps: a turn's error (wheel slip) grows with the turn whether or not scans come in between. Not for a dense
    log: the Intel bag's longer drives are its odometry's gaps, where the odometry is read across up to 3 s and
    errs more than a drive it counted (docs/gridslam.md, "Sparse logs")."""
    if config.motion_step is None:
        return 1.0
    return max(1.0, moved / config.motion_step)


@dataclass(frozen=True)
class Laser:
    """One scan's laser as the filter takes it: the beams' directions (cosines and sines (B,) of their angles in
    the laser frame), the laser's pose (x m, y m, yaw rad) on the robot, and the readings it uses: those in
    [range_min, max_range] m mark their end cell, longer ones only clear space up to max_range."""

    cos_b: np.ndarray
    sin_b: np.ndarray
    offset: np.ndarray
    range_min: float
    max_range: float

    @classmethod
    def of(
        cls,
        config: GridSlamConfig,
        beam_angles: np.ndarray,
        sensor_offset: np.ndarray,
        range_min: float,
        range_max: float = math.inf,
    ) -> Laser:
        """A scan's laser (beam angles (B,) rad, offset (3,), the sensor's range limits m) within the config's
        min_range and max_range. InputError for angles that are not one finite value per beam, an offset that is not
        three finite values, or a range_min (m) that is not finite and >= 0."""
        angles = finite_array("beam_angles", beam_angles, (None,), " (one angle per beam, rad in the laser frame)")
        sensor_offset = finite_array("sensor_offset", sensor_offset, (3,), " (x m, y m, yaw rad on the robot)")
        check_within("range_min", range_min, (0.0, math.inf), "m")
        return cls(
            np.cos(angles),
            np.sin(angles),
            # contiguous: a strided row (a column slice's) would compile every kernel it reaches a second time
            np.ascontiguousarray(sensor_offset, np.float64),
            max(float(range_min), config.min_range),
            min(float(range_max), config.max_range),
        )

    @property
    def reach(self) -> float:
        """How far (m) from the robot a beam of this laser reaches at most."""
        return self.max_range + float(np.hypot(self.offset[0], self.offset[1]))


def _checked_pose(name: str, pose: np.ndarray) -> np.ndarray:
    """``pose`` (x m, y m, yaw rad) as float64 (3,), finite and within POSE_LIMIT m of the origin; InputError else
    (a NaN start pose made the grid's insertion loop for ever, in compiled code past Ctrl-C)."""
    pose = finite_array(name, pose, (3,), " (x m, y m, yaw rad)")
    check_within(f"{name} x and y", pose[:2], (-POSE_LIMIT, POSE_LIMIT), "m")
    return pose


class GridFastSLAM:
    """The filter's state: M poses, log weights and grids; feed it scans in time order, each with its laser."""

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
        range_min m (the sensor's): the laser of the scans :meth:`integrate` is given without one;
        initial_pose (3,) where every particle starts (map frame)."""
        config.validate()
        self.config = config
        self.rng = np.random.default_rng(seed)
        self.use_laser(Laser.of(config, beam_angles, sensor_offset, range_min))
        m = config.particles
        self.poses = np.tile(_checked_pose("initial_pose", initial_pose), (m, 1))
        self.log_w = np.zeros(m)
        self.maps = TileMaps(m, config.resolution, config.tile_cells)
        model = OmniOdometryMotionModel if config.holonomic else OdometryMotionModel
        self.motion = model(alphas=config.motion_alphas)
        self.stencil, self.fit = proposal_stencil(config.stencil_xy, config.stencil_yaw)
        self.odometry_ref: np.ndarray | None = None  # odometry at the last integrated scan
        self.drift = np.zeros((m, 3, 3))  # per particle: the covariance kept beyond the set's spread (honesty)
        self.watch = HealthWatch()
        self.widen = False  # whether the next proposal is widened (the last match failed)
        self.last_z = math.nan  # the last scan's matched-beam z (HealthWatch)
        self.last_covariance = np.zeros((3, 3))  # the filter's covariance at the last integrated scan
        self.revisits = Revisits(config.revisit_gap, config.revisit_radius)
        self.loops = LoopCloser(config) if config.loop_closure else None

    def use_laser(self, laser: Laser) -> None:
        """Take the scans that follow with ``laser``'s geometry (every scan of a log may have its own)."""
        self.laser = laser
        self.cos_b, self.sin_b, self.offset = laser.cos_b, laser.sin_b, laser.offset
        self.range_min, self.max_range, self.reach = laser.range_min, laser.max_range, laser.reach

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights (M,)."""
        return normalize_log_weights(self.log_w)

    def _beams(self, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Insertion ranges r_stop (B,) (NaN: unused), hit flags (B,), and the matching beams' indices."""
        cfg = self.config
        r = np.asarray(ranges, np.float64)
        usable = ~np.isnan(r) & (r >= self.range_min)
        hit = usable & (r <= self.max_range)
        r_stop = np.where(usable, np.minimum(r, self.max_range), np.nan)
        idx = np.flatnonzero(hit)
        if len(idx) > cfg.match_beams:
            idx = idx[np.unique(np.round(np.linspace(0, len(idx) - 1, cfg.match_beams)).astype(np.int64))]
        return r_stop, hit, idx

    def due(self, odometry: np.ndarray) -> bool:
        """Whether a scan taken at this odometry pose (3,) should be integrated."""
        if self.odometry_ref is None:
            return True
        moved, turned = travelled(self.odometry_ref, odometry)
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

    def covariance(self, poses: np.ndarray) -> np.ndarray:
        """The filter's covariance (3, 3) (m, rad) of particle poses (M, 3) under the current weights, the spread
        kept for what resampling lost included (slam.gridslam.honesty.cloud_covariance)."""
        return cloud_covariance(poses, self.weights, self.drift)

    def _propose(
        self, control: np.ndarray, steps: float, r_stop: np.ndarray, idx: np.ndarray, widen: bool = False
    ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]:
        """New poses (M, 3), log weight factors (M,), the number of motion-model fallbacks, the match scores (M,)
        and the covariances (M, 3, 3) the poses were drawn with (m, rad). ``steps``: the move's :func:`motion_steps`,
        which divides the motion model's variances. ``widen``: the motion model's variances and the yaw search's
        are config.widen times larger."""
        cfg, maps = self.config, self.maps
        scale = cfg.widen if widen else 1.0
        motion = scaled_motion(self.motion, scale / steps)
        predicted, _, q = motion.linearize(self.poses, control)
        q = q + scale * np.diag([cfg.motion_floor_xy**2, cfg.motion_floor_xy**2, cfg.motion_floor_yaw**2])
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
            cfg.yaw_search * np.sqrt(scale),
            cfg.prior_cap,
            self.stencil,
            self.fit,
        )
        good = score >= cfg.min_match * max(len(idx), 1)
        poses = np.empty_like(predicted)
        floor = np.diag([cfg.proposal_floor_xy**2, cfg.proposal_floor_xy**2, cfg.proposal_floor_yaw**2])
        drawn = np.where(good[:, None, None], cov + floor, q)
        if good.any():
            poses[good] = sample_gaussian(mean[good], drawn[good], self.rng)
        if (~good).any():
            poses[~good] = motion.sample(self.poses[~good], control, self.rng)
            own_maps = (maps.pool, maps.table[~good], maps.tx0, maps.ty0, maps.shift, cfg.resolution)
            loglik, _ = log_likelihoods(
                *own_maps, poses[~good], self.offset, *beams, cfg.kernel, cfg.sigma_match, cfg.sigma_like, cfg.p_rand
            )
            log_eta[~good] = loglik / cfg.gain
        poses[:, 2] = wrap_angle(poses[:, 2])
        return poses, log_eta, int((~good).sum()), score, drawn

    def integrate(
        self, odometry: np.ndarray, ranges: np.ndarray, laser: Laser | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, StepReport]:
        """Integrate one scan (ranges (B,) m) taken at odometry pose (3,) by ``laser`` (None: the last one).

        Returns the particles' poses (M, 3) and normalised weights (M,) at this scan (before resampling),
        the parents (N,) of the set that follows, resampled or split (particle j continues particle parents[j]),
        or None, and a report.
        """
        if laser is not None:
            self.use_laser(laser)
        odometry = _checked_pose("odometry", odometry)
        ranges = np.asarray(ranges)
        if ranges.dtype.kind not in "iuf" or ranges.shape != self.cos_b.shape:
            raise InputError(
                f"ranges must be one real number (m) per beam, {self.cos_b.shape}, got {ranges.dtype} {ranges.shape}"
            )
        r_stop, hit, idx = self._beams(ranges)
        fallbacks, matched, widened, failed = 0, math.nan, self.widen, False
        moves = np.zeros((len(self.poses), 3, 3))  # each move's covariance (for the loop closer's graph)
        if self.odometry_ref is not None:
            control = odometry_controls(np.stack([self.odometry_ref, odometry]))[0]
            steps = motion_steps(travelled(self.odometry_ref, odometry)[0], self.config)
            before = self.poses
            self.poses, log_eta, fallbacks, score, drawn = self._propose(control, steps, r_stop, idx, widened)
            fractions = score / max(len(idx), 1)
            reach = float(np.mean(r_stop[idx])) if len(idx) else self.max_range
            if self.config.keep_spread:
                explored = exploration_covariance(fractions, self.config.resolution, reach)
                self.drift = transport(self.drift, before, self.poses) + explored
            matched, failed = self._weigh(log_eta, fractions)
            # (what the proposal drew with, and a cell's precision on top)
            moves = drawn + exploration_covariance(np.zeros(1), self.config.resolution, reach)[0]
        else:
            self._cover(self.poses)
        self.odometry_ref = odometry
        self._insert(self.poses, r_stop, hit)
        weights = self.weights
        ess = effective_sample_size(weights)
        poses = self.poses.copy()
        best = poses[int(np.argmax(weights))]
        if self.config.keep_spread and not (math.isnan(matched) or failed):
            self.drift = self.revisits.shrink(self.drift, best)
        self.last_covariance = self.covariance(poses)
        self.revisits.add(best, self.last_covariance)
        if self.loops is not None:
            self._close_loops(poses, moves, r_stop, hit, matched if not failed else math.nan)
        parents, resampled = self._resample(weights, ess)
        if self.loops is not None:
            self.loops.link(parents)
        health = self._health(poses, weights, (matched, ess, fallbacks, failed, widened), resampled)
        return poses, weights, parents, StepReport(ess, resampled, fallbacks, health)

    def _close_loops(
        self, poses: np.ndarray, moves: np.ndarray, r_stop: np.ndarray, hit: np.ndarray, matched: float
    ) -> None:
        """Add this scan (the particles' poses (M, 3) and the covariances (M, 3, 3) of their moves) to the loop
        closer's graph (slam.gridslam.loops) and search for a loop closure unless its match failed (``matched``, the
        best particle's matched-beam fraction on its own map, NaN); when the solved graph moves the current pose,
        rebuild the grids from the graph and move the particles with it."""
        assert self.loops is not None
        began = time.process_time()
        laser = (self.cos_b, self.sin_b, self.offset)
        best = int(np.argmax(self.weights))
        node = self.loops.add(poses, best, moves, self.last_covariance, r_stop, hit, laser)
        closure = None if math.isnan(matched) else self.loops.close(node, matched)
        if closure is not None and closure.rebuild:
            self._rebuild(closure.transform)
        self.loops.seconds += time.process_time() - began

    def _rebuild(self, transform: np.ndarray) -> None:
        """Every particle's grid becomes one map built from every node's scan at the graph's poses (shared, copy on
        write), and the particles move by ``transform`` (3,), the best one onto the graph's pose."""
        assert self.loops is not None
        cfg = self.config
        maps = TileMaps(1, cfg.resolution, cfg.tile_cells)
        poses = self.loops.solved
        reach = cfg.max_range + max(float(np.hypot(*scan.offset[:2])) for scan in self.loops.scans)
        lo, hi = poses[:, :2].min(axis=0) - reach, poses[:, :2].max(axis=0) + reach
        maps.cover(lo[0], lo[1], hi[0], hi[1])
        for pose, scan in zip(poses, self.loops.scans):  # one compiled insertion per node's scan
            maps.insert(
                pose[None],
                scan.offset,
                scan.cos_b,
                scan.sin_b,
                scan.r_stop,
                scan.hit,
                cfg.l_occ,
                cfg.l_free,
                cfg.l_clamp,
            )
        maps.resample(np.zeros(len(self.poses), np.int64))
        self.maps = maps
        self.poses = apply_transform(transform, self.poses)
        turn = np.full(len(self.drift), float(transform[2]))
        self.drift = rotate_covariance(self.drift, turn)
        self.last_covariance = rotate_covariance(self.last_covariance, turn[:1])[0]
        self.revisits.moved(poses)
        self.loops.rebuilt(transform)

    def _weigh(self, log_eta: np.ndarray, matched: np.ndarray) -> tuple[float, bool]:
        """Weigh the particles by log_eta (M,) unless the best particle's match failed (config.recovery: its
        matched-beam fraction below fail_match or its z against the recent scans below fail_z; a scan nobody
        explains says nothing about which particle is right; the next proposal is widened where config.widen > 1).
        Returns the best particle's matched-beam fraction (matched (M,): each particle's) and whether its match
        failed."""
        cfg = self.config
        best = int(np.argmax(self.log_w + log_eta / cfg.weight_temper))
        self.last_z = self.watch.zscore(float(matched[best]))
        self.watch.add(float(matched[best]))
        failed = bool(matched[best] < cfg.fail_match or self.last_z < cfg.fail_z)
        self.widen = failed and cfg.recovery and cfg.widen > 1.0
        if not (failed and cfg.recovery):
            self.log_w = self.log_w + log_eta / cfg.weight_temper
            self.log_w -= self.log_w.max()
        return float(matched[best]), failed

    def _resample(self, weights: np.ndarray, ess: float) -> tuple[np.ndarray | None, bool]:
        """Resample (low variance) to KLD-sampling's count (slam.gridslam.health.kld_count, within [particles,
        particle_cap]) when N_eff < resample_threshold times the particles. Otherwise, when KLD-sampling asks for
        more particles than there are, split: every particle stays, with the weights, and the new ones are copies
        drawn from the weights, a particle and its copies sharing its weight, so the weighted set is unchanged
        and nothing is thrown away. Returns the parents (particle j continues parents[j]) or None, and whether
        it resampled."""
        cfg = self.config
        m = len(self.poses)
        count = cfg.particles
        if cfg.particle_cap > cfg.particles:
            limits = (cfg.particles, cfg.particle_cap)
            bins = (cfg.kld_bin_xy, cfg.kld_bin_yaw)
            count = kld_count(self.poses, weights, self.rng, limits, bins, cfg.kld_epsilon, cfg.kld_delta)
        resample = ess < cfg.resample_threshold * m
        if not (resample or count > m):
            return None, False
        if resample:
            parents = low_variance_resample(weights, self.rng, count)
            lost = resampled_drift(self.drift, self.poses, weights, parents) if cfg.keep_spread else None
            self.drift = self.drift[parents] if lost is None else lost
            self.log_w = np.zeros(count)
        else:
            parents = np.concatenate([np.arange(m), low_variance_resample(weights, self.rng, count - m)])
            self.log_w = (self.log_w - np.log(np.bincount(parents, minlength=m)))[parents]
            self.drift = self.drift[parents]
        self.maps.resample(parents)
        self.poses = self.poses[parents]
        return parents, resample

    def _health(
        self, poses: np.ndarray, weights: np.ndarray, scan: tuple[float, float, int, bool, bool], resampled: bool
    ) -> ScanHealth:
        """The :class:`ScanHealth` of the scan just integrated: particles poses (M, 3) of weights (M,) before
        resampling, scan = (matched, ess, fallbacks, failed, widened), whether it resampled."""
        matched, ess, fallbacks, failed, widened = scan
        own = spreads(weighted_covariance(poses, weights))
        total = spreads(self.last_covariance)
        return ScanHealth(
            matched=matched,
            score_z=self.last_z if not math.isnan(matched) else math.nan,
            ess=ess,
            particles=len(poses),
            spread_xy=own[0],
            spread_yaw=own[1],
            sigma_xy=total[0],
            sigma_yaw=total[1],
            fallbacks=fallbacks,
            failed=failed,
            widened=widened,
            resampled=resampled,
            next_particles=len(self.poses),
        )
