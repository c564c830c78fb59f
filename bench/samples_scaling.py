"""How the exact Monte Carlo fusion's cost grows with the pose samples per scan: the simulated office (361 beams over
180 deg, 12 m, 0.05 m cells), one thread, M = 1, 10, 60, 100, 500 and 1 000 equal-weight samples drawn from the
same honest pose distributions (`bench.scenarios.honest_posed_scans`, the same seed for every M).

`python -m bench.run samples_scaling`. Each M fuses the first scans of one office run into a grid of its own: WARM
scans that compile the kernels and grow the scratch, then the timed ones (the slow M time fewer of them). The figure
is scans per CPU second of the process (time.process_time over the timed scans), so other processes taking turns on
the core slow the wall clock and not the figure. Beside it, the CPU microseconds per sample of a scan: a cost linear
in the samples keeps it flat, and the coherence of real samples (most put a beam's end in the same few cells) is
what could make it fall.
"""

from __future__ import annotations

import time

from bench.scenarios import honest_posed_scans, office_run
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from slam.simulator import SimRun

RESOLUTION = 0.05
#: samples per scan, and how many scans each is timed on (fewer for the slow ones)
COUNTS = {1: 300, 10: 300, 60: 200, 100: 150, 500: 40, 1000: 20}
WARM = 20  # scans fused before timing: the kernels compile and the scratch grows to the run's windows


def cpu_seconds_per_scan(run: SimRun, samples: int, scans: int, seed: int = 1) -> float:
    """CPU s per scan of one thread fusing the first ``scans`` scans of ``run`` after WARM, ``samples`` samples each."""
    posed = honest_posed_scans(run, seed=seed, particles=samples)
    draws, weights = posed.poses.weighted_samples()
    items = [(posed.scan_ranges(t), draws[t], weights[t]) for t in range(WARM + scans)]
    fusion = MonteCarloFusion(TiledGrid(RESOLUTION), SensorModel(resolution=RESOLUTION), *posed.single_geometry())
    fusion.fuse_many(items[:WARM])
    start = time.process_time()
    fusion.fuse_many(items[WARM:])
    return (time.process_time() - start) / scans


def run() -> dict:
    """Scans per CPU second and CPU us per sample for every M of :data:`COUNTS`, on the same office run."""
    office = office_run(seed=0, steps=WARM + max(COUNTS.values()))
    figures: dict = {"resolution_m": RESOLUTION}
    for samples, scans in COUNTS.items():
        seconds = cpu_seconds_per_scan(office, samples, scans)
        figures[f"m{samples}_scans_per_cpu_s"] = 1.0 / seconds
        figures[f"m{samples}_cpu_us_per_sample"] = 1e6 * seconds / samples
        figures[f"m{samples}_timed_scans"] = scans
    return figures
