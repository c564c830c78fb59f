"""Fusion of a modern lidar in the simulated warehouse (issue 34): speed, shards' CPU and memory, in one run.

The scans are `bench.scenarios.warehouse_run`'s (slam.warehouse: a 100 m x 100 m hall, a 1081-beam lidar over 270
deg to 30 m at 40 Hz, the robot at up to 1.5 m/s), fused into 0.05 m cells on one thread with honest pose
distributions (`honest_posed_scans`): 100 and 500 equal-weight particles, and the Gaussians with the sample count
the fusion derives from each covariance (`services.fusion_runner.PoseSampling`, as `posegrid fuse` draws them; 36
to 200 samples at 30 m).

- speed: scans/s of each, in turns on the same scans (`bench.fusion._interleaved_seconds`: CHUNK scans of each in
  turn, so the machine's drift falls on all alike); the 500-particle fusion takes every EVERY_500-th scan of the
  turns. OctoMap (pyoctomap, the bench extra; skipped without it) is fed the same particles, one point cloud per
  particle, on a few scans only (OCTOMAP_EVERY): it takes tens of seconds a scan. Its ratio is over the scans it was
  fed.
- shards: the total CPU time (each fusion's thread time) of fusing the same scans (every SHARD_EVERY-th, 100
  particles) with 1, 2 and 4 in-process shards, each a `MonteCarloFusion` owning the tiles the project's
  rendezvous rule (services.state.ownership) gives it, in turns; the ratio to one shard's, the busiest shard's CPU
  over one shard's (what shards on machines of their own would be held to); and whether the 2 shards' maps joined
  equal the one shard's map bit for bit (`shards_cpu`, which the pipeline bench uses too).
- memory: bytes per observed cell of the 100-particle map (the tiles' layers over its observed cells) and of
  OctoMap (its memoryUsage() over its leaf nodes, the tree fed every few scans' first particle: the same area); the
  bytes allocated during a scan (tracemalloc's peak above the level before it, scans that grow the tile storage
  apart) early and late in the run; the bench process's peak RSS (every fusion above with its scratch).
"""

from __future__ import annotations

import functools
import resource
import time
import tracemalloc
from collections.abc import Callable

import numpy as np

from bench.fusion import _interleaved_seconds, _octomap_steps
from bench.scenarios import honest_posed_scans, warehouse_run
from mapping.bundling import RECOMMENDED_TOLERANCE
from mapping.fusion import MonteCarloFusion
from mapping.grid import TILE_SIZE, TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans
from services.fusion_runner import PoseSampling
from services.state.ownership import owns_tile

STEPS = 400
RESOLUTION = 0.05
#: scans per turn
CHUNK = 4
#: the 500-particle fusion takes every this-many-th scan of the turns
EVERY_500 = 4
#: OctoMap is fed every this-many-th scan, by particle count (it takes about 27 s a scan at 100 particles and 95 s at
#: 500 here); the tree for its memory figure takes every OCTOMAP_MEMORY_EVERY-th scan's first particle
OCTOMAP_EVERY = {100: 100, 500: 200}
OCTOMAP_MEMORY_EVERY = 4
#: the shard runs take every this-many-th scan; shard counts
SHARD_EVERY = 2
SHARD_COUNTS = (1, 2, 4)

Picks = list[tuple[np.ndarray, np.ndarray]]


def _fusion(
    posed: PosedScans,
    owner: Callable[[int, int], bool] | None = None,
    bundle: float = 0.0,
    tile_size: int = TILE_SIZE,
) -> MonteCarloFusion:
    """A fusion of the scans' laser into a fresh grid of RESOLUTION m cells in tiles of ``tile_size`` cells (owning
    the tiles ``owner`` accepts; its samples bundled with tolerance ``bundle`` m, mapping.bundling)."""
    return MonteCarloFusion(
        TiledGrid(RESOLUTION, tile_size),
        SensorModel(resolution=RESOLUTION),
        *posed.single_geometry(),
        owner,
        bundle=bundle,
    )


def _particles(posed: PosedScans) -> Picks:
    """Each scan's particles and weights."""
    samples, weights = posed.poses.weighted_samples()
    return [(samples[t], weights[t]) for t in range(len(posed.stamps))]


def _gaussian_draws(posed: PosedScans) -> Picks:
    """Each scan's Gaussian pose drawn as `posegrid fuse` draws it: as many samples as the accuracy rule asks for
    (one cell), seeded by the scan's seq (drawn here, before any timing)."""
    sampling = PoseSampling("mc", None, 0, RESOLUTION)
    mean, cov = posed.poses.gaussian()
    range_max = posed.single_geometry().range_max
    return [sampling.draw(t, range_max, mean=mean[t], cov=cov[t]) for t in range(len(posed.stamps))]


def _steps(fusion: MonteCarloFusion, posed: PosedScans, picks: Picks, every: int = 1) -> list:
    """Per scan a callable fusing it with its picks, for every ``every``-th scan (None for the others)."""
    return [
        functools.partial(fusion.fuse, posed.ranges[t], *picks[t]) if t % every == 0 else None
        for t in range(len(picks))
    ]


def _cpu_timed(step: Callable[[], object], spent: np.ndarray, t: int) -> None:
    """Run ``step``, adding the thread's CPU seconds it took to spent[t]."""
    start = time.thread_time()
    step()
    spent[t] += time.thread_time() - start


def _speed(posed100: PosedScans, posed500: PosedScans, gaussian: PosedScans) -> dict:
    """Scans/s of 100 and 500 particles (exact and bundled with the recommended tolerance, mapping.bundling) and of
    the Gaussians, in turns, against OctoMap fed the same particles."""
    scans = len(posed100.stamps)
    _fusion(posed100).fuse(posed100.ranges[0], *_particles(posed100)[0])  # compile the kernels
    draws = _gaussian_draws(gaussian)
    ours = {
        "mc100": _steps(_fusion(posed100), posed100, _particles(posed100)),
        "mc500": _steps(_fusion(posed500), posed500, _particles(posed500), EVERY_500),
        "gaussian": _steps(_fusion(gaussian), gaussian, draws),
        "bundled100": _steps(_fusion(posed100, bundle=RECOMMENDED_TOLERANCE), posed100, _particles(posed100)),
        "bundled500": _steps(
            _fusion(posed500, bundle=RECOMMENDED_TOLERANCE), posed500, _particles(posed500), EVERY_500
        ),
    }
    cpu = {name: np.zeros(scans) for name in ours}
    lists = {
        name: [
            None if step is None else functools.partial(_cpu_timed, step, cpu[name], t) for t, step in enumerate(steps)
        ]
        for name, steps in ours.items()
    }
    for count, posed in ((100, posed100), (500, posed500)):
        octo = _octomap_steps(posed, "mc", every=OCTOMAP_EVERY[count])
        if octo is not None:
            lists[f"octomap{count}"] = octo[0]
    seconds = dict(zip(lists, _interleaved_seconds(*lists.values(), chunk=CHUNK)))
    beams = posed100.ranges.shape[1]
    counts = np.array([len(w) for _, w in draws])
    every500 = len(range(0, scans, EVERY_500))
    fused = {"mc100": scans, "mc500": every500, "gaussian": scans, "bundled100": scans, "bundled500": every500}
    out: dict = {"mc500_scans": fused["mc500"]}
    for name, count in fused.items():
        out[f"{name}_scans_per_s"] = count / seconds[name].sum()
        out[f"{name}_scans_per_cpu_s"] = count / cpu[name].sum()
    out.update(
        {
            "mc100_sample_rays_per_s": scans * 100 * beams / seconds["mc100"].sum(),
            "mc100_sample_rays_per_cpu_s": scans * 100 * beams / cpu["mc100"].sum(),
            "gaussian_samples_mean": float(counts.mean()),
            "gaussian_samples_min": int(counts.min()),
            "gaussian_samples_max": int(counts.max()),
            "bundled100_speedup": seconds["mc100"].sum() / seconds["bundled100"].sum(),
            "bundled500_speedup": seconds["mc500"].sum() / seconds["bundled500"].sum(),
        }
    )
    if "octomap100" not in lists:
        out["octomap"] = "skipped: pyoctomap (the bench extra) is not installed"
        return out
    for count in (100, 500):
        fed = np.arange(0, scans, OCTOMAP_EVERY[count])
        octomap_s = seconds[f"octomap{count}"][fed].sum()
        out[f"octomap{count}_scans_fed"] = len(fed)
        out[f"octomap{count}_scans_per_s"] = len(fed) / octomap_s
        out[f"mc{count}_vs_octomap_same_particles"] = octomap_s / seconds[f"mc{count}"][fed].sum()
    return out


def shards_cpu(
    posed: PosedScans, counts: tuple[int, ...] = SHARD_COUNTS, every: int = SHARD_EVERY, tile_size: int = TILE_SIZE
) -> dict:
    """Total CPU seconds of 1 in-process shard and of each of ``counts`` shards (tiles of ``tile_size`` cells, owned by
    the rendezvous rule) on every ``every``-th scan, in turns, and their ratios to one shard's; the busiest shard's
    share of the total and its CPU over one shard's; whether 2 shards' maps joined equal one shard's (when 2 is among
    the counts)."""
    counts = tuple(sorted({1, *counts}))
    picks = _particles(posed)
    fusions = {
        (count, shard): _fusion(posed, None if count == 1 else owns_tile(shard, count), tile_size=tile_size)
        for count in counts
        for shard in range(count)
    }
    cpu = {key: np.zeros(len(picks)) for key in fusions}
    lists = [
        [None if step is None else functools.partial(_cpu_timed, step, cpu[key], t) for t, step in enumerate(steps)]
        for key, steps in ((key, _steps(fusion, posed, picks, every)) for key, fusion in fusions.items())
    ]
    _interleaved_seconds(*lists, chunk=CHUNK)
    fed = len(range(0, len(picks), every))
    one = cpu[(1, 0)].sum()
    out: dict = {"shard_scans": fed}
    for count in counts:
        total = sum(cpu[(count, shard)].sum() for shard in range(count))
        out[f"shards{count}_cpu_s"] = total
        out[f"shards{count}_cpu_ratio_to_one"] = total / one
        busiest = max(cpu[(count, shard)].sum() for shard in range(count))
        out[f"shards{count}_busiest_share"] = busiest / total
        out[f"shards{count}_busiest_ratio_to_one"] = busiest / one  # (on machines of their own: below 1 divides)
    if 2 in counts:
        parts = [fusions[(2, shard)].grid for shard in range(2)]
        out["shards2_joined_equals_one"] = _joined_equals(fusions[(1, 0)].grid, parts)
    return out


def _joined_equals(whole: TiledGrid, parts: list[TiledGrid]) -> bool:
    """Whether the shards' grids hold, between them, exactly the whole grid's tiles, bit for bit."""
    keys = [key for part in parts for key in part.keys()]  # noqa: SIM118  # a TiledGrid, not a dict: it has no __iter__
    if sorted(keys) != sorted(whole.keys()):
        return False
    return all(
        all(np.array_equal(a, b) for a, b in zip(part.tile_arrays(key), whole.tile_arrays(key)))
        for part in parts
        for key in part.keys()  # noqa: SIM118
    )


def _allocations(posed: PosedScans) -> tuple[dict, TiledGrid]:
    """Bytes allocated during a scan (tracemalloc's peak above the level before it): in the first scan (the fusion's
    scratch), the median over the scans, the most in any scan of the last quarter of the run, and how many scans
    allocate more than a MB (the scratch grows with the window, that is with the pose samples' spread, not with the
    map), the scans that grow the tile storage (it doubles) left out; and how many do. And the map."""
    fusion = _fusion(posed)
    picks = _particles(posed)
    extra, grew = [], []
    tracemalloc.start()
    try:
        for t, pick in enumerate(picks):
            capacity = fusion.grid.logodds.shape[0]
            before = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            fusion.fuse(posed.ranges[t], *pick)
            extra.append(tracemalloc.get_traced_memory()[1] - before)
            grew.append(fusion.grid.logodds.shape[0] != capacity)
    finally:
        tracemalloc.stop()
    kept = np.array([bytes_ for bytes_, growth in zip(extra[1:], grew[1:]) if not growth])
    figures = {
        "scan_alloc_bytes_first_scan": int(extra[0]),
        "scan_alloc_bytes_median": int(np.median(kept)),
        "scan_alloc_bytes_last_quarter_max": int(kept[-max(len(kept) // 4, 1) :].max()),
        "scans_allocating_over_1mb": int((kept > 2**20).sum()),
        "tile_storage_growths": int(sum(grew)),
    }
    return figures, fusion.grid


def _memory(posed100: PosedScans, grid: TiledGrid) -> dict:
    """Bytes per observed cell of the 100-particle map ``grid`` and of OctoMap fed every OCTOMAP_MEMORY_EVERY-th
    scan's first particle (the same area)."""
    observed = grid.observed_cells()
    out: dict = {
        "observed_cells": observed,
        "tiles": len(grid.keys()),
        "grid_bytes": grid.nbytes,
        "bytes_per_observed_cell": grid.nbytes / observed,
    }
    octo = _octomap_steps(posed100, "ml", every=OCTOMAP_MEMORY_EVERY)
    if octo is None:
        out["octomap_memory"] = "skipped: pyoctomap (the bench extra) is not installed"
        return out
    for step in octo[0]:
        if step is not None:
            step()
    tree = octo[1]
    out["octomap_leaves"] = int(tree.getNumLeafNodes())
    out["octomap_bytes"] = int(tree.memoryUsage())
    out["octomap_bytes_per_leaf"] = out["octomap_bytes"] / out["octomap_leaves"]
    return out


def run(steps: int = STEPS) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    sim = warehouse_run(seed=0, steps=steps)
    posed100 = honest_posed_scans(sim, seed=1, particles=100)
    posed500 = honest_posed_scans(sim, seed=1, particles=500)
    gaussian = honest_posed_scans(sim, seed=1)
    out: dict = {
        "scans": steps,
        "beams": int(sim.ranges.shape[1]),
        "range_max_m": sim.range_max,
        "laser_hz": 1.0 / float(sim.stamps[1] - sim.stamps[0]),
        "resolution_m": RESOLUTION,
        "path_m": float(np.hypot(*np.diff(sim.true_poses[:, :2], axis=0).T).sum()),
    }
    out.update(_speed(posed100, posed500, gaussian))
    out.update(shards_cpu(posed100))
    allocations, grid = _allocations(posed100)
    out.update(_memory(posed100, grid))
    out.update(allocations)
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out
