"""Fusion on several threads (mapping.fusion.FusionThreads): scans/s on the simulated office (400 scans, 60 weighted
samples a scan, 0.05 m cells) and on the warehouse (figures prefixed ``warehouse_``: its first 200 scans, 100
particles, the 1 081-beam 30 m lidar) with one thread and with two (and with every core this process may use, when
that is more), in turns on the same scans, and the ratio.

Each thread count fuses into a grid of its own, turn by turn: TURN scans with one thread, the same TURN scans with two
threads, and so on over the run, so that the machine's drift (tens of percent within a minute on a shared machine)
falls on both sides alike. A turn's scans are one ``fuse_many`` call, as `posegrid fuse` hands a fusion every scan
and a shard the scans its intake holds. The speed-up is the median over the turns of one thread's time over the
other's. Beside it, the process's CPU time per scan (what threading costs in all) and its CPU time over its wall
time while fusing (how many cores it had: on a shared machine, fewer than its threads when others are busy). The
maps are checked to be the same bit for bit at the end.

Then the same in turns with each scan fused alone (``fuse_many`` of one scan, figures prefixed ``lone_``), as a live
shard fuses a scan as it comes: one thread walks it, two or more walk its samples in parts at once. Each scan's wall
time (median, p99) per thread count, and the median over the turns of one thread's time over the other's: what the
threads buy a scan's latency. Its maps too are checked against the others, bit for bit.
"""

from __future__ import annotations

import time

import numpy as np

from bench.scenarios import honest_posed_scans, office_run, warehouse_run
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans
from services.commands.mapping import available_cores

SAMPLES = 60
WAREHOUSE_PARTICLES = 100
RESOLUTION = 0.05
#: scans per turn
TURN = 40


def _fusions(posed: PosedScans, counts: list[int]) -> list[MonteCarloFusion]:
    """One fusion per thread count, each into a grid of its own, its kernels compiled and its threads started (two
    scans fused into a scratch grid)."""
    model = SensorModel(resolution=RESOLUTION)
    samples, weights = posed.poses.weighted_samples()
    fusions = []
    for count in counts:
        MonteCarloFusion(TiledGrid(RESOLUTION), model, *posed.single_geometry(), threads=count).fuse_many(
            [(posed.scan_ranges(t), samples[t], weights[t]) for t in (0, 1)]
        )
        fusions.append(MonteCarloFusion(TiledGrid(RESOLUTION), model, *posed.single_geometry(), threads=count))
    return fusions


def _turns(
    posed: PosedScans, fusions: list[MonteCarloFusion], lone: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall seconds and the process's CPU seconds (all its threads) per turn (rows) and thread count (columns), the
    counts in turns on each turn's scans; and each scan's wall seconds (rows) per thread count (columns) when
    ``lone`` (each scan fused alone, as a live shard fuses a scan as it comes: its samples walked in parts on the
    threads), else an empty array."""
    samples, weights = posed.poses.weighted_samples()
    scans = [(posed.scan_ranges(t), samples[t], weights[t]) for t in range(len(posed.stamps))]
    wall: list[list[float]] = []
    cpu: list[list[float]] = []
    per_scan: list[list[float]] = [[] for _ in fusions]
    for first in range(0, len(scans), TURN):
        turn = scans[first : first + TURN]
        wall.append([])
        cpu.append([])
        for column, fusion in enumerate(fusions):
            start, start_cpu = time.perf_counter(), time.process_time()
            if lone:
                for scan in turn:
                    scan_start = time.perf_counter()
                    fusion.fuse_many([scan])
                    per_scan[column].append(time.perf_counter() - scan_start)
            else:
                fusion.fuse_many(turn)
            wall[-1].append(time.perf_counter() - start)
            cpu[-1].append(time.process_time() - start_cpu)
    return np.array(wall), np.array(cpu), np.array(per_scan).T if lone else np.zeros(0)


def _same_maps(grids: list[TiledGrid]) -> bool:
    """Whether every grid holds the first one's tiles, slot by slot, bit for bit."""
    n = len(grids[0].keys())
    return all(
        grid.keys() == grids[0].keys()
        and all(
            np.array_equal(getattr(grid, layer)[:n], getattr(grids[0], layer)[:n])
            for layer in ("logodds", "variance", "observed")
        )
        for grid in grids[1:]
    )


def run(steps: int = 400, warehouse_steps: int = 200) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    office = honest_posed_scans(office_run(seed=0, steps=steps), seed=1, particles=SAMPLES)
    out = _threads(office)
    warehouse = honest_posed_scans(warehouse_run(seed=0, steps=warehouse_steps), seed=1, particles=WAREHOUSE_PARTICLES)
    out.update({f"warehouse_{name}": value for name, value in _threads(warehouse).items()})
    return out


def _threads(posed: PosedScans) -> dict:
    """The figures of one scenario: scans/s, CPU per scan and cores busy per thread count, speed-ups, same maps."""
    cores = available_cores()
    counts = sorted({1, 2, cores})
    fusions = _fusions(posed, counts)
    seconds, cpu, _ = _turns(posed, fusions)
    scans = len(posed.stamps)
    samples = posed.poses.weighted_samples()[1].shape[1]
    out: dict = {"scans": scans, "samples": samples, "resolution_m": RESOLUTION, "cores": cores, "turn_scans": TURN}
    for column, count in enumerate(counts):
        out[f"threads_{count}_scans_per_s"] = scans / seconds[:, column].sum()
        out[f"threads_{count}_cpu_ms_per_scan"] = 1e3 * cpu[:, column].sum() / scans
        out[f"threads_{count}_cores_busy"] = cpu[:, column].sum() / seconds[:, column].sum()
        if count > 1:
            out[f"threads_{count}_speedup_median"] = float(np.median(seconds[:, 0] / seconds[:, column]))
            out[f"threads_{count}_speedup_min"] = float(np.min(seconds[:, 0] / seconds[:, column]))
            out[f"threads_{count}_speedup_max"] = float(np.max(seconds[:, 0] / seconds[:, column]))
    out["turns"] = len(seconds)
    lone = _fusions(posed, counts)
    lone_seconds, _, per_scan = _turns(posed, lone, lone=True)
    for column, count in enumerate(counts):
        out[f"lone_threads_{count}_ms_per_scan_median"] = 1e3 * float(np.median(per_scan[:, column]))
        out[f"lone_threads_{count}_ms_per_scan_p99"] = 1e3 * float(np.percentile(per_scan[:, column], 99))
        if count > 1:
            out[f"lone_threads_{count}_speedup_median"] = float(np.median(lone_seconds[:, 0] / lone_seconds[:, column]))
    out["maps_identical"] = _same_maps([fusion.grid for fusion in fusions + lone])
    widest = fusions[-1].threads
    out["scratch_mb_each"] = widest.nbytes / widest.scratches / 1e6
    out["scratch_mb_total"] = widest.nbytes / 1e6
    return out
