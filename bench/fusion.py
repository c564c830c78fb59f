"""Fusion speed, memory and map quality on the simulated office (issue: the mapping core's benchmark).

Speed figures are ratios measured in one run on one machine: posegrid "mc" (60 samples) and "ml" (1 pose)
against OctoMap 1.10 through pyoctomap fed the same scans (the OctoMap columns are skipped when pyoctomap,
a bench-only extra, is not installed), and against a plain compiled ray loop with a simple sensor model on
the same sample rays (the yardstick the issue's 150 scans/s target was set against: about 5 million
sample-rays per second on the machine it was measured on). All single-threaded.
"""
from __future__ import annotations

import math
import time

import numba as nb
import numpy as np

from bench.scenarios import honest_posed_scans, office_run, resampled_particles, truth_arrays
from mapping.evaluation import score_map
from mapping.fusion import MonteCarloFusion, laser_poses
from mapping.grid import TiledGrid
from mapping.raytrace import corner_tol, dda_start, dda_step
from mapping.sensor_model import SensorModel
from services.fusion_runner import fuse_posed_scans

SAMPLES = 60
RESOLUTION = 0.05


def _time_fusion(posed, mode: str, merge_identical: bool = True, scans: int | None = None) -> tuple[float, TiledGrid]:
    """Seconds to fuse the first ``scans`` scans (after a warm-up scan that compiles the kernels)."""
    model = SensorModel(resolution=RESOLUTION)
    grid = TiledGrid(RESOLUTION)
    fusion = MonteCarloFusion(grid, model, posed.beam_angles, posed.range_min, posed.range_max, posed.sensor_offset,
                              merge_identical=merge_identical)
    count = scans or len(posed.stamps)
    poses = posed.poses
    picks = []
    for t in range(count):
        if mode == "ml":
            best = int(np.argmax(poses.weights[t]))
            picks.append((poses.samples[t, best:best + 1], np.ones(1)))
        else:
            picks.append((poses.samples[t], poses.weights[t]))
    MonteCarloFusion(TiledGrid(RESOLUTION), model, posed.beam_angles, posed.range_min, posed.range_max).fuse(
        posed.ranges[0], *picks[0])
    start = time.perf_counter()
    for t in range(count):
        fusion.fuse(posed.ranges[t], *picks[t])
    return time.perf_counter() - start, grid


@nb.njit(cache=True, nogil=True)
def _plain_ray_loop(laser_x, laser_y, laser_yaw, angles, ranges, range_max, res, l_free, l_occ, grid,
                    ix0, iy0):  # pragma: no cover - compiled
    """The yardstick: every sample ray walked cell by cell with the shared traversal, l_free added to each
    cell before the return and l_occ to the cell holding it, into one dense float32 grid (global cell
    (ix0 + i, iy0 + j) is grid[j, i]). No per-cell rule, no moments, no variance; returns the cells visited."""
    visits = 0
    for j in range(laser_x.shape[0]):
        for k in range(angles.shape[0]):
            z = ranges[k]
            hit = z <= range_max
            stop = z if hit else range_max
            theta = laser_yaw[j] + angles[k]
            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(
                laser_x[j], laser_y[j], math.cos(theta), math.sin(theta), res)
            tol = corner_tol(stop)
            while min(t_max_x, t_max_y) < stop:
                grid[iy - iy0, ix - ix0] += l_free
                visits += 1
                ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y,
                                                    tol)
            grid[iy - iy0, ix - ix0] += l_occ if hit else l_free
            visits += 1
    return visits


def _plain_loop_seconds(posed) -> tuple[float, int]:
    """Seconds for :func:`_plain_ray_loop` over every scan's sample rays, and the cells it visited."""
    model = SensorModel(resolution=RESOLUTION)
    lasers = [laser_poses(posed.poses.samples[t], posed.sensor_offset) for t in range(len(posed.stamps))]
    ranges = np.where(np.isfinite(posed.ranges), posed.ranges, np.inf).astype(np.float64)
    reach = posed.range_max + 1.0
    all_xy = np.concatenate(lasers)[:, :2]
    ix0, iy0 = (np.floor((all_xy.min(axis=0) - reach) / RESOLUTION)).astype(int)
    ix1, iy1 = (np.floor((all_xy.max(axis=0) + reach) / RESOLUTION)).astype(int)
    grid = np.zeros((iy1 - iy0 + 1, ix1 - ix0 + 1), np.float32)
    args = (posed.beam_angles, posed.range_max, RESOLUTION, model.l_free, model.l_hit)
    _plain_ray_loop(lasers[0][:1, 0].copy(), lasers[0][:1, 1].copy(), lasers[0][:1, 2].copy(), args[0], ranges[0],
                    *args[1:], grid, ix0, iy0)  # compile
    visits = 0
    start = time.perf_counter()
    for t, laser in enumerate(lasers):
        visits += _plain_ray_loop(laser[:, 0].copy(), laser[:, 1].copy(), laser[:, 2].copy(), args[0], ranges[t],
                                  *args[1:], grid, ix0, iy0)
    return time.perf_counter() - start, visits


def _octomap_seconds(posed, mode: str, scans: int) -> tuple[float, int] | None:
    """Seconds for OctoMap to insert ``scans`` scans (one point cloud per pose sample), and its memoryUsage()."""
    try:
        import pyoctomap
    except ImportError:
        return None
    tree = pyoctomap.OcTree(RESOLUTION)
    angles = posed.beam_angles
    ranges = posed.ranges.astype(np.float64)
    # no return: a point beyond max_range, so OctoMap marks free space up to max_range and no hit
    ranges = np.where(np.isfinite(ranges) & (ranges <= posed.range_max), ranges, posed.range_max + 1.0)
    clouds = []
    for t in range(scans):
        samples = posed.poses.samples[t]
        if mode == "ml":
            samples = samples[int(np.argmax(posed.poses.weights[t]))][None]
        lasers = laser_poses(samples, posed.sensor_offset)
        for x, y, yaw in lasers:
            points = np.column_stack([x + ranges[t] * np.cos(yaw + angles), y + ranges[t] * np.sin(yaw + angles),
                                      np.zeros_like(angles)])
            clouds.append((points, np.array([x, y, 0.0])))
    start = time.perf_counter()
    for points, origin in clouds:
        tree.insertPointCloud(points, origin, max_range=posed.range_max)
    return time.perf_counter() - start, int(tree.memoryUsage())


def run(steps: int = 400, octomap_mc_scans: int = 20) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    sim = office_run(seed=0, steps=steps)
    posed = honest_posed_scans(sim, seed=1, particles=SAMPLES)
    scans = len(posed.stamps)
    rays_per_scan = SAMPLES * posed.ranges.shape[1]
    out: dict = {"scans": scans, "beams": int(posed.ranges.shape[1]), "samples": SAMPLES,
                 "resolution_m": RESOLUTION, "range_max_m": float(posed.range_max)}

    seconds_mc, grid_mc = _time_fusion(posed, "mc")
    seconds_ml, grid_ml = _time_fusion(posed, "ml")
    out["mc_scans_per_s"] = scans / seconds_mc
    out["mc_sample_rays_per_s"] = scans * rays_per_scan / seconds_mc
    out["ml_scans_per_s"] = scans / seconds_ml
    seconds_plain, visits = _plain_loop_seconds(posed)
    out["plain_loop_sample_rays_per_s"] = scans * rays_per_scan / seconds_plain
    out["plain_loop_cells_per_sample_ray"] = visits / (scans * rays_per_scan)
    out["mc_vs_plain_loop"] = seconds_plain / seconds_mc
    observed = grid_mc.observed_cells()
    out["observed_cells"] = observed
    out["bytes_per_observed_cell"] = grid_mc.nbytes / observed

    resampled = resampled_particles(posed, seed=2)
    distinct = np.mean([len(np.unique(s, axis=0)) for s in resampled.poses.samples])
    merged_s, _ = _time_fusion(resampled, "mc", merge_identical=True)
    unmerged_s, _ = _time_fusion(resampled, "mc", merge_identical=False)
    out["resampled_distinct_particles_mean"] = float(distinct)
    out["merge_speedup"] = unmerged_s / merged_s

    octo_ml = _octomap_seconds(posed, "ml", scans)
    if octo_ml is not None:
        octo_mc = _octomap_seconds(posed, "mc", octomap_mc_scans)
        out["octomap_ml_scans_per_s"] = scans / octo_ml[0]
        out["octomap_mc_scans_per_s"] = octomap_mc_scans / octo_mc[0]
        out["mc_vs_octomap_same_samples"] = out["mc_scans_per_s"] / out["octomap_mc_scans_per_s"]
        out["ml_vs_octomap_single_pose"] = out["ml_scans_per_s"] / out["octomap_ml_scans_per_s"]
        out["octomap_bytes_per_observed_cell"] = octo_ml[1] / grid_ml.observed_cells()
    else:
        out["octomap"] = "skipped: pyoctomap (the bench extra) is not installed"

    truth = truth_arrays(sim)
    gaussian = honest_posed_scans(sim, seed=1)
    for mode in ("mc", "ml"):
        grid = fuse_posed_scans(gaussian, mode=mode, n_samples=SAMPLES if mode == "mc" else None, seed=0)
        for key, value in score_map(grid.rasterize(), truth).items():
            out[f"quality_{mode}_{key}"] = value
    return out
