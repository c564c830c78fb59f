"""Fusion speed, memory and map quality on the simulated office (issue: the mapping core's benchmark).

Speed figures are ratios measured in one run on one machine: posegrid "mc" (60 samples) and "ml" (1 pose)
against OctoMap 1.10 through pyoctomap fed the same scans (the OctoMap columns are skipped when pyoctomap,
a bench-only extra, is not installed), and against a plain compiled ray loop with a simple sensor model on
the same sample rays (the yardstick the issue's 150 scans/s target was set against: about 5 million
sample-rays per second on the machine it was measured on). The plain loop walks the exact traversal
posegrid uses; a second one walks Bresenham's line, which skips the cells a ray crosses near a corner (about
60 cells a ray against 82) and reaches 3.6 to 4.1 million here. All single-threaded.

Merging identical particles before ray casting is measured on three particle sets: a resampled copy of the
office's samples (as a filter that reports its particles after resampling gives them), and the outputs of
the project's two FastSLAMs (`_fastslam_outputs`). Each is fused with merging and without, in turns.

Each comparison runs in turns of a few scans (posegrid's, then the baseline's same scans, ...), so the
machine's drift, tens of percent within a minute on a shared machine, falls on both sides of a ratio alike.
"""

from __future__ import annotations

import functools
import math
import tempfile
import time
from typing import Any

import numpy as np

from bench.run import run_cli
from bench.scenarios import MIT_CSAIL, honest_posed_scans, office_run, resampled_particles, truth_arrays
from mapping.evaluation import score_map
from mapping.fusion import MonteCarloFusion, laser_poses
from mapping.grid import TiledGrid
from mapping.jit import kernel
from mapping.raytrace import corner_tol, dda_start, dda_step
from mapping.sensor_model import SensorModel
from schemas.files import load_posed_scans
from services.fusion_runner import fuse_posed_scans

SAMPLES = 60
#: grid FastSLAM's output for the merging figures: the first this many scans of the MIT CSAIL log
GRIDSLAM_SCANS = 600
RESOLUTION = 0.05


def _fusion_steps(posed, mode: str, merge_identical: bool = True) -> tuple[list, TiledGrid]:
    """One callable per scan that fuses it ("mc": all samples; "ml": the most likely one) into a fresh grid,
    after a warm-up scan into another grid that compiles the kernels; and that grid."""
    model = SensorModel(resolution=RESOLUTION)
    grid = TiledGrid(RESOLUTION)
    angles, range_min, range_max, offset = posed.single_geometry()
    fusion = MonteCarloFusion(grid, model, angles, range_min, range_max, offset, merge_identical=merge_identical)
    poses = posed.poses
    picks = []
    for t in range(len(posed.stamps)):
        if mode == "ml":
            best = int(np.argmax(poses.weights[t]))
            picks.append((poses.samples[t, best : best + 1], np.ones(1)))
        else:
            picks.append((poses.samples[t], poses.weights[t]))
    MonteCarloFusion(TiledGrid(RESOLUTION), model, angles, range_min, range_max).fuse(posed.ranges[0], *picks[0])
    steps = [functools.partial(fusion.fuse, posed.ranges[t], *picks[t]) for t in range(len(posed.stamps))]
    return steps, grid


def _fastslam_outputs() -> dict:
    """Figure prefix -> the posed-scan file of a FastSLAM, made through the command line as a user would:
    landmark FastSLAM 2.0 on the simulated office (SAMPLES particles, seed 0; it reports each scan's particles
    after the motion step, before any resampling) and grid FastSLAM on the first GRIDSLAM_SCANS scans of the MIT
    CSAIL log (30 particles, seed 0; it reports the final particles' trajectories, whose ancestries
    coalesce). The log is skipped when ../shared/data lacks it."""
    outputs = {}
    with tempfile.TemporaryDirectory() as tmp:
        run_cli(["simulate", f"{tmp}/sim", "--seed", "0"])
        run_cli(
            [
                "slam",
                "--algo",
                "fastslam2",
                f"{tmp}/sim",
                "--particles",
                str(SAMPLES),
                "--seed",
                "0",
                "-o",
                f"{tmp}/fastslam2.npz",
            ]
        )
        outputs["fastslam2_office"] = load_posed_scans(f"{tmp}/fastslam2.npz")
        if MIT_CSAIL.is_file():
            run_cli(
                [
                    "slam",
                    "--algo",
                    "gridslam",
                    str(MIT_CSAIL),
                    "--seed",
                    "0",
                    "--scans",
                    str(GRIDSLAM_SCANS),
                    "-o",
                    f"{tmp}/gridslam.npz",
                ]
            )
            outputs["gridslam_mit_csail"] = load_posed_scans(f"{tmp}/gridslam.npz")
    return outputs


def _interleaved_seconds(*step_lists: list, chunk: int) -> list[np.ndarray]:
    """Seconds per scan of each list of per-scan callables (None: a scan that list skips), run in turns of
    ``chunk`` scans (list 0's scans t..t+chunk-1, then list 1's, ...), so that the machine's drift falls on
    all of them alike while each side keeps its caches warm within a turn (scan-by-scan turns made a 0.4 ms
    ml scan 40 % slower after every OctoMap insertion)."""
    seconds = [np.zeros(len(steps)) for steps in step_lists]
    for first in range(0, len(step_lists[0]), chunk):
        for steps, spent in zip(step_lists, seconds):
            for t in range(first, min(first + chunk, len(steps))):
                if steps[t] is not None:
                    start = time.perf_counter()
                    steps[t]()
                    spent[t] = time.perf_counter() - start
    return seconds


@kernel(nogil=True, inline="always")
def _sample_ray(laser_yaw, angles, ranges, range_max, j, k):  # pragma: no cover - compiled
    """Beam k from laser pose j: (whether its reading is a return, where the ray stops in m: the reading, or
    range_max without a return, its heading in rad in the map frame)."""
    z = ranges[k]
    hit = z <= range_max
    return hit, z if hit else range_max, laser_yaw[j] + angles[k]


@kernel(nogil=True)
def _plain_ray_loop(
    laser_x, laser_y, laser_yaw, angles, ranges, range_max, res, l_free, l_occ, grid, ix0, iy0
):  # pragma: no cover - compiled
    """The yardstick: every sample ray walked cell by cell with the shared traversal, l_free added to each
    cell before the return and l_occ to the cell holding it, into one dense float32 grid (global cell
    (ix0 + i, iy0 + j) is grid[j, i]). No per-cell rule, no moments, no variance; returns the cells visited."""
    visits = 0
    for j in range(laser_x.shape[0]):
        for k in range(angles.shape[0]):
            hit, stop, theta = _sample_ray(laser_yaw, angles, ranges, range_max, j, k)
            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(
                laser_x[j], laser_y[j], math.cos(theta), math.sin(theta), res
            )
            tol = corner_tol(stop)
            while min(t_max_x, t_max_y) < stop:
                grid[iy - iy0, ix - ix0] += l_free
                visits += 1
                ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
            grid[iy - iy0, ix - ix0] += l_occ if hit else l_free
            visits += 1
    return visits


@kernel(nogil=True)
def _bresenham_ray_loop(
    laser_x, laser_y, laser_yaw, angles, ranges, range_max, res, l_free, l_occ, grid, ix0, iy0
):  # pragma: no cover - compiled
    """A cheaper yardstick than :func:`_plain_ray_loop`, the same arguments: each sample ray as Bresenham's
    8-connected integer line from the sensor's cell to the end cell (it steps diagonally through corners, so
    it skips cells the ray crosses: not the exact traversal the issue requires); l_free before the end cell,
    l_occ (hit) or l_free (no return) at it. Returns the cells visited."""
    visits = 0
    for j in range(laser_x.shape[0]):
        for k in range(angles.shape[0]):
            hit, stop, theta = _sample_ray(laser_yaw, angles, ranges, range_max, j, k)
            x = int(math.floor(laser_x[j] / res))
            y = int(math.floor(laser_y[j] / res))
            x_end = int(math.floor((laser_x[j] + stop * math.cos(theta)) / res))
            y_end = int(math.floor((laser_y[j] + stop * math.sin(theta)) / res))
            dx = abs(x_end - x)
            dy = -abs(y_end - y)
            step_x = 1 if x < x_end else -1
            step_y = 1 if y < y_end else -1
            err = dx + dy
            while x != x_end or y != y_end:
                grid[y - iy0, x - ix0] += l_free
                visits += 1
                twice = 2 * err
                if twice >= dy:
                    err += dy
                    x += step_x
                if twice <= dx:
                    err += dx
                    y += step_y
            grid[y_end - iy0, x_end - ix0] += l_occ if hit else l_free
            visits += 1
    return visits


def _plain_loop_steps(posed, loop=_plain_ray_loop) -> tuple[list, list[int]]:
    """One callable per scan running ``loop`` (:func:`_plain_ray_loop` or :func:`_bresenham_ray_loop`) over
    the scan's sample rays (compiled first), and a one-element list that counts the cells they visit."""
    model = SensorModel(resolution=RESOLUTION)
    geometry = posed.single_geometry()
    lasers = [laser_poses(posed.poses.samples[t], geometry.sensor_offset) for t in range(len(posed.stamps))]
    ranges = np.where(np.isfinite(posed.ranges), posed.ranges, np.inf).astype(np.float64)
    reach = geometry.range_max + 1.0
    all_xy = np.concatenate(lasers)[:, :2]
    ix0, iy0 = (np.floor((all_xy.min(axis=0) - reach) / RESOLUTION)).astype(int)
    ix1, iy1 = (np.floor((all_xy.max(axis=0) + reach) / RESOLUTION)).astype(int)
    grid = np.zeros((iy1 - iy0 + 1, ix1 - ix0 + 1), np.float32)
    args = (geometry.beam_angles, geometry.range_max, RESOLUTION, model.l_free, model.l_hit)
    loop(
        lasers[0][:1, 0].copy(),
        lasers[0][:1, 1].copy(),
        lasers[0][:1, 2].copy(),
        args[0],
        ranges[0],
        *args[1:],
        grid,
        ix0,
        iy0,
    )  # compile
    visits = [0]

    def step(t: int) -> None:
        laser = lasers[t]
        visits[0] += loop(
            laser[:, 0].copy(), laser[:, 1].copy(), laser[:, 2].copy(), args[0], ranges[t], *args[1:], grid, ix0, iy0
        )

    return [functools.partial(step, t) for t in range(len(lasers))], visits


def _octomap_steps(posed, mode: str, every: int = 1) -> tuple[list, Any] | None:
    """Per scan a callable inserting it into an OctoMap tree, one point cloud per pose sample, for every
    ``every``-th scan (None for the others); and the tree (a pyoctomap.OcTree, untyped: Any; for its
    memoryUsage()). None when pyoctomap is not installed."""
    try:
        import pyoctomap
    except ImportError:
        return None
    tree = pyoctomap.OcTree(RESOLUTION)
    geometry = posed.single_geometry()
    angles, range_max = geometry.beam_angles, geometry.range_max
    ranges = posed.ranges.astype(np.float64)
    # no return: a point beyond max_range, so OctoMap marks free space up to max_range and no hit
    ranges = np.where(np.isfinite(ranges) & (ranges <= range_max), ranges, range_max + 1.0)
    clouds = {}
    for t in range(0, len(posed.stamps), every):
        samples = posed.poses.samples[t]
        if mode == "ml":
            samples = samples[int(np.argmax(posed.poses.weights[t]))][None]
        lasers = laser_poses(samples, geometry.sensor_offset)
        clouds[t] = [
            (
                np.column_stack(
                    [x + ranges[t] * np.cos(yaw + angles), y + ranges[t] * np.sin(yaw + angles), np.zeros_like(angles)]
                ),
                np.array([x, y, 0.0]),
            )
            for x, y, yaw in lasers
        ]

    def step(t: int) -> None:
        for points, origin in clouds[t]:
            tree.insertPointCloud(points, origin, max_range=range_max)

    return [functools.partial(step, t) if t in clouds else None for t in range(len(posed.stamps))], tree


def run(steps: int = 400, octomap_mc_every: int = 1) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    sim = office_run(seed=0, steps=steps)
    posed = honest_posed_scans(sim, seed=1, particles=SAMPLES)
    scans = len(posed.stamps)
    rays_per_scan = SAMPLES * posed.ranges.shape[1]
    out: dict = {
        "scans": scans,
        "beams": int(posed.ranges.shape[1]),
        "samples": SAMPLES,
        "resolution_m": RESOLUTION,
        "range_max_m": posed.single_geometry().range_max,
    }

    # each baseline runs in turns with posegrid on the same scans (_interleaved_seconds). OctoMap fed 60 samples
    # takes about 0.18 s a scan; it is fed every scan (octomap_mc_every = 1), as posegrid is: fed every 20th scan
    # only, its smaller tree takes 6 % less time a scan (0.166 against 0.177 s, the same 10 scans), which would
    # flatter it
    mc_steps, grid_mc = _fusion_steps(posed, "mc")
    plain_steps, visits = _plain_loop_steps(posed)
    bresenham_steps, bresenham_visits = _plain_loop_steps(posed, _bresenham_ray_loop)
    octo_mc = _octomap_steps(posed, "mc", every=octomap_mc_every)
    seconds = _interleaved_seconds(mc_steps, plain_steps, bresenham_steps, *([octo_mc[0]] if octo_mc else []), chunk=5)
    mc_s, plain_s, bresenham_s = seconds[0].sum(), seconds[1].sum(), seconds[2].sum()
    out["mc_scans_per_s"] = scans / mc_s
    out["mc_sample_rays_per_s"] = scans * rays_per_scan / mc_s
    out["plain_loop_sample_rays_per_s"] = scans * rays_per_scan / plain_s
    out["plain_loop_cells_per_sample_ray"] = visits[0] / (scans * rays_per_scan)
    out["mc_vs_plain_loop"] = plain_s / mc_s
    out["bresenham_loop_sample_rays_per_s"] = scans * rays_per_scan / bresenham_s
    out["bresenham_loop_cells_per_sample_ray"] = bresenham_visits[0] / (scans * rays_per_scan)
    out["mc_vs_bresenham_loop"] = bresenham_s / mc_s
    observed = grid_mc.observed_cells()
    out["observed_cells"] = observed
    out["bytes_per_observed_cell"] = grid_mc.nbytes / observed

    ml_steps, grid_ml = _fusion_steps(posed, "ml")
    octo_ml = _octomap_steps(posed, "ml")
    seconds_ml = _interleaved_seconds(ml_steps, *([octo_ml[0]] if octo_ml else []), chunk=50)
    out["ml_scans_per_s"] = scans / seconds_ml[0].sum()

    particle_sets = {"resampled": resampled_particles(posed, seed=2), **_fastslam_outputs()}
    if "gridslam_mit_csail" not in particle_sets:
        out["gridslam_mit_csail"] = f"skipped: the log is not present ({MIT_CSAIL})"
    for label, particles in particle_sets.items():
        distinct = [len(np.unique(s, axis=0)) for s in particles.poses.samples]
        merged_s, unmerged_s = _interleaved_seconds(
            _fusion_steps(particles, "mc", merge_identical=True)[0],
            _fusion_steps(particles, "mc", merge_identical=False)[0],
            chunk=5,
        )
        out[f"{label}_distinct_particles_mean"] = float(np.mean(distinct))
        out[f"{label}_scans_with_repeats"] = int(np.sum(np.array(distinct) < particles.poses.samples.shape[1]))
        out[f"{label}_merge_speedup"] = unmerged_s.sum() / merged_s.sum()

    if octo_mc is not None and octo_ml is not None:  # both or neither: pyoctomap is installed or not
        fed = np.arange(0, scans, octomap_mc_every)  # mc's time on the very scans OctoMap was fed
        out["octomap_ml_scans_per_s"] = scans / seconds_ml[1].sum()
        octomap_s = seconds[3].sum()
        out["octomap_mc_scans_per_s"] = len(fed) / octomap_s
        out["mc_vs_octomap_same_samples"] = octomap_s / seconds[0][fed].sum()
        out["plain_loop_vs_octomap_same_samples"] = octomap_s / seconds[1][fed].sum()
        out["bresenham_loop_vs_octomap_same_samples"] = octomap_s / seconds[2][fed].sum()
        out["ml_vs_octomap_single_pose"] = seconds_ml[1].sum() / seconds_ml[0].sum()
        out["octomap_bytes_per_observed_cell"] = int(octo_ml[1].memoryUsage()) / grid_ml.observed_cells()
    else:
        out["octomap"] = "skipped: pyoctomap (the bench extra) is not installed"

    truth = truth_arrays(sim)
    gaussian = honest_posed_scans(sim, seed=1)
    for mode in ("mc", "ml"):
        grid = fuse_posed_scans(gaussian, mode=mode, n_samples=SAMPLES if mode == "mc" else None, seed=0)
        for key, value in score_map(grid.rasterize(), truth).items():
            out[f"quality_{mode}_{key}"] = value
    return out
