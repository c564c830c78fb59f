"""Run grid FastSLAM over a laser log and return every scan's particle poses along the final particles' paths.

Output poses are *smoothed* by ancestry: row t holds, for each final particle j, the pose that j's
ancestor had at scan t, and every row carries the final normalised weights. These are the samples of the
filter's posterior over whole trajectories p(x_1:T | z, u), the distribution each final particle's grid
was built from, so fusing them (posegrid fuse) gives the map the filter believes in. Early rows collapse
to few distinct poses where the particles share ancestors; that is the filter's real uncertainty, not
a loss.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from slam.gridslam.config import GridSlamConfig
from slam.gridslam.filter import GridFastSLAM
from slam.gridslam.tiles import TileMaps
from slam.laserlog import LaserLog


@dataclass(frozen=True)
class GridSlamResult:
    """Per scan t of the log: stamps (T,) s, samples (T, M, 3) robot poses in the map frame (smoothed, see
    the module docstring), weights (M,) final normalised weights, integrated (T,) bool (the scan went into
    the grids). Per integrated scan: ess (I,) N_eff before resampling, resampled (I,) bool, seconds (I,)
    processing time. maps: the filter's grids at the end (slam.gridslam.tiles.TileMaps)."""

    stamps: np.ndarray
    samples: np.ndarray
    weights: np.ndarray
    integrated: np.ndarray
    ess: np.ndarray
    resampled: np.ndarray
    seconds: np.ndarray
    fallbacks: int
    maps: TileMaps

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


def run_gridslam(
    log: LaserLog,
    config: GridSlamConfig = GridSlamConfig(),
    seed: int = 0,
    initial_pose: np.ndarray | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> GridSlamResult:
    """Grid FastSLAM over every scan of ``log`` in file order.

    initial_pose (3,): where every particle starts in the map frame (default: the first scan's odometry
    pose, so the map frame is the odometry frame at the start). Beams are used up to the smaller of
    config.max_range and the log's range_max. progress(scans, ess) is called after each
    scan with the number of scans done since the last call and the current N_eff.
    """
    start = log.odometry[0] if initial_pose is None else np.asarray(initial_pose, np.float64)
    config = replace(config, max_range=min(config.max_range, log.range_max))
    slam = GridFastSLAM(config, log.beam_angles, log.sensor_offset, log.range_min, start, seed)
    poses: list[np.ndarray] = []
    parents: list[np.ndarray | None] = []
    integrated = np.zeros(len(log), bool)
    ess, resampled, seconds = [], [], []
    fallbacks = 0
    weights = slam.weights
    current_ess = float(config.particles)
    for t in range(len(log)):
        odometry = log.odometry[t]
        if slam.due(odometry):
            began = time.perf_counter()
            pose_t, weights, parent_t, report = slam.integrate(odometry, log.ranges[t])
            seconds.append(time.perf_counter() - began)
            ess.append(report.ess)
            resampled.append(report.resampled)
            fallbacks += report.fallbacks
            integrated[t] = True
            current_ess = report.ess
        else:
            pose_t, parent_t = slam.follow(odometry), None
            weights = slam.weights
        poses.append(pose_t)
        parents.append(parent_t)
        if progress is not None:
            progress(1, current_ess)
    return GridSlamResult(
        stamps=log.stamps.copy(),
        samples=_backtrack(poses, parents),
        weights=weights,
        integrated=integrated,
        ess=np.array(ess),
        resampled=np.array(resampled, bool),
        seconds=np.array(seconds),
        fallbacks=fallbacks,
        maps=slam.maps,
    )
