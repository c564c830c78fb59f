"""Run grid FastSLAM over a laser log and return every scan's particle poses along the final particles' paths.

Output poses are *smoothed* by ancestry: row t holds, for each final particle j, the pose that j's
ancestor had at scan t, and every row carries the final normalised weights: samples of the filter's posterior
over whole trajectories p(x_1:T | z, u), the distribution each final particle's grid was built from. Early rows
would collapse to few distinct poses where the particles share ancestors, a certainty the filter does not have,
so each trajectory but the best carries the filter's covariance at each scan as a smooth offset
(slam.gridslam.honesty.spread_trajectories; config.keep_spread): fusing them (posegrid fuse) gives the map with
the uncertainty the filter has.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slam.gridslam.config import GridSlamConfig
from slam.gridslam.filter import GridFastSLAM, Laser
from slam.gridslam.health import ScanHealth
from slam.gridslam.honesty import spread_trajectories
from slam.gridslam.loops import LoopCloser
from slam.gridslam.tiles import TileMaps
from slam.laserlog import GeometryKey, LaserLog
from slam.motion import rotate_covariance
from slam.posegraph import apply_transform


@dataclass(frozen=True)
class GridSlamResult:
    """Per scan t of the log: stamps (T,) s, samples (T, M, 3) robot poses in the map frame (smoothed, see
    the module docstring), weights (M,) final normalised weights, integrated (T,) bool (the scan went into
    the grids), covariance (T, 3, 3) the filter's covariance at each scan (m, rad; slam.gridslam.honesty).
    Per integrated scan: ess (I,) N_eff before resampling, resampled (I,) bool, seconds (I,) processing time,
    health (I,) (slam.gridslam.health.ScanHealth). maps: the filter's grids at the end
    (slam.gridslam.tiles.TileMaps). loops: the loop closer's counts (:func:`loop_summary`)."""

    stamps: np.ndarray
    samples: np.ndarray
    weights: np.ndarray
    integrated: np.ndarray
    ess: np.ndarray
    resampled: np.ndarray
    seconds: np.ndarray
    fallbacks: int
    maps: TileMaps
    covariance: np.ndarray
    health: tuple[ScanHealth, ...]
    loops: dict[str, float]

    @property
    def best(self) -> int:
        """Index of the final particle with the largest weight."""
        return int(np.argmax(self.weights))


def _backtrack(poses: list[np.ndarray], parents: list[np.ndarray | None]) -> np.ndarray:
    """(T, M, 3): per row the poses of the final particles' ancestors."""
    steps, m = len(poses), len(poses[-1])
    out = np.empty((steps, m, 3))
    index = np.arange(m)
    out[-1] = poses[-1]
    for t in range(steps - 2, -1, -1):
        parent = parents[t]
        if parent is not None:
            index = parent[index]
        out[t] = poses[t][index]
    return out


#: distinct laser geometries whose beam directions a run keeps at once (a log whose geometry changes every scan
#: computes them again when they return)
LASERS_KEPT = 64


class _Lasers:
    """Each scan's :class:`Laser`, computed once per distinct geometry of the log (an interlaced laser has a few)."""

    def __init__(self, log: LaserLog, config: GridSlamConfig) -> None:
        self.log, self.config = log, config
        self.kept: dict[GeometryKey, Laser] = {}

    def of(self, t: int) -> Laser:
        """Scan t's laser."""
        key = self.log.geometry_key(t)
        laser = self.kept.get(key)
        if laser is None:
            if len(self.kept) >= LASERS_KEPT:
                self.kept.clear()
            log = self.log
            laser = Laser.of(self.config, log.beam_angles(t), log.sensor_offset[t], log.range_min[t], log.range_max[t])
            self.kept[key] = laser
        return laser


def run_gridslam(
    log: LaserLog,
    config: GridSlamConfig = GridSlamConfig(),
    seed: int = 0,
    initial_pose: np.ndarray | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> GridSlamResult:
    """Grid FastSLAM over every scan of ``log`` in file order, each scan with its own laser geometry.

    initial_pose (3,): where every particle starts in the map frame (default: the first scan's odometry
    pose, so the map frame is the odometry frame at the start). Beams are used up to the smaller of
    config.max_range and the scan's range_max. progress(scans, ess) is called after each
    scan with the number of scans done since the last call and the current N_eff.
    """
    start = log.odometry[0] if initial_pose is None else np.asarray(initial_pose, np.float64)
    lasers = _Lasers(log, config)
    slam = GridFastSLAM(config, log.beam_angles(0), log.sensor_offset[0], log.range_min[0], start, seed)
    poses: list[np.ndarray] = []
    parents: list[np.ndarray | None] = []
    integrated = np.zeros(len(log), bool)
    ess, resampled, seconds = [], [], []
    covariance: list[np.ndarray] = []
    health: list[ScanHealth] = []
    fallbacks = 0
    weights = slam.weights
    current_ess = float(config.particles)
    for t in range(len(log)):
        odometry = log.odometry[t]
        if slam.due(odometry):
            began = time.perf_counter()
            pose_t, weights, parent_t, report = slam.integrate(odometry, log.scan_ranges(t), lasers.of(t))
            seconds.append(time.perf_counter() - began)
            ess.append(report.ess)
            resampled.append(report.resampled)
            fallbacks += report.fallbacks
            integrated[t] = True
            current_ess = report.ess
            covariance.append(slam.last_covariance)
            health.append(report.health)
        else:
            pose_t, parent_t = slam.follow(odometry), None
            weights = slam.weights
            covariance.append(slam.covariance(pose_t))
        poses.append(pose_t)
        parents.append(parent_t)
        if progress is not None:
            progress(1, current_ess)
    samples = _backtrack(poses, parents)
    covariances = np.array(covariance)
    best = int(np.argmax(weights))
    if config.keep_spread:
        spread_rng = np.random.default_rng([seed, 1])  # apart from the filter's, which it would shift
        samples = spread_trajectories(samples, weights, covariances, best, spread_rng)
    if slam.loops is not None:
        samples, covariances = _onto_graph(slam.loops, best, integrated, samples, covariances)
    return GridSlamResult(
        stamps=log.stamps.copy(),
        samples=samples,
        weights=weights,
        integrated=integrated,
        ess=np.array(ess),
        resampled=np.array(resampled, bool),
        seconds=np.array(seconds),
        fallbacks=fallbacks,
        maps=slam.maps,
        covariance=covariances,
        health=tuple(health),
        loops=loop_summary(slam.loops),
    )


def _onto_graph(
    loops: LoopCloser, best: int, integrated: np.ndarray, samples: np.ndarray, covariances: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Samples (T, M, 3) and covariances (T, 3, 3) moved onto the pose graph solved along final particle ``best``'s
    lineage: each scan's by the transform of its node (an integrated scan's own, the scans after it by the node's
    frame after a rebuild)."""
    recorded, after = loops.corrections(best)
    node = np.cumsum(integrated) - 1
    transforms = np.where(integrated[:, None], recorded[node], after[node])
    moved = apply_transform(transforms, samples)
    return moved, rotate_covariance(covariances, transforms[:, 2])


def loop_summary(loops: LoopCloser | None) -> dict[str, float]:
    """The loop closer's counts: searches made, closures taken, grid rebuilds, and the CPU seconds it took (all 0
    without loop closure)."""
    if loops is None:
        return {"searches": 0, "closures": 0, "rebuilds": 0, "cpu_seconds": 0.0}
    counts = {"searches": loops.searches, "closures": len(loops.closures), "rebuilds": loops.rebuilds}
    return {**counts, "cpu_seconds": round(loops.seconds, 3)}
