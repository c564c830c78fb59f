"""How the Monte Carlo fusion's cost grows with the pose samples per scan, exact and with the samples bundled
(mapping.bundling, the recommended tolerance): the simulated office (361 beams over 180 deg, 12 m, 0.05 m cells),
one thread, M = 1, 10, 60, 100, 500 and 1 000 equal-weight samples drawn from the same honest pose distributions
(`bench.scenarios.honest_posed_scans`, the same seed for every M).

`python -m bench.run samples_scaling`. Each M fuses the first scans of the office benchmark's run (400 scans) into a
grid of its own: WARM scans that compile the kernels and grow the scratch, then the timed ones (the slow M time fewer
of them). The figure is scans per CPU second of the process (time.process_time over the timed scans), so other
processes taking turns on the core slow the wall clock and not the figure. Beside it, the CPU microseconds per sample
of a scan (flat: a cost linear in the samples) and, bundled, the samples a scan walked. For M in QUALITY_COUNTS the
whole run is fused both ways and scored against the truth (AUC, Brier, NLL): what the bundles cost the map.
"""

from __future__ import annotations

import time

from bench.scenarios import honest_posed_scans, office_run, truth_arrays
from mapping.bundling import RECOMMENDED_TOLERANCE
from mapping.evaluation import score_map
from mapping.fusion import FuseResult, MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from slam.simulator import SimRun

RESOLUTION = 0.05
#: samples per scan, and how many scans each is timed on (fewer for the slow ones)
COUNTS = {1: 300, 10: 300, 60: 200, 100: 150, 500: 40, 1000: 20}
WARM = 20  # scans fused before timing: the kernels compile and the scratch grows to the run's windows


QUALITY_COUNTS = (60, 100, 500)  # M whose maps are scored exact and bundled
STEPS = 400  # the office benchmark's run (bench.fusion)


def _fusion(run: SimRun, samples: int, scans: int, bundle: float, seed: int = 1) -> tuple[MonteCarloFusion, list]:
    """A fusion of ``run``'s office into a fresh grid and its first ``scans`` scans with ``samples`` samples each."""
    posed = honest_posed_scans(run, seed=seed, particles=samples)
    draws, weights = posed.poses.weighted_samples()
    items = [(posed.scan_ranges(t), draws[t], weights[t]) for t in range(scans)]
    grid = TiledGrid(RESOLUTION)
    return MonteCarloFusion(grid, SensorModel(resolution=RESOLUTION), *posed.single_geometry(), bundle=bundle), items


def cpu_seconds_per_scan(run: SimRun, samples: int, scans: int, bundle: float = 0.0) -> tuple[float, float]:
    """(CPU s per scan, mean samples walked per scan) of one thread fusing ``scans`` scans of ``run`` after WARM,
    ``samples`` samples each, bundled with tolerance ``bundle`` m (0: exact)."""
    fusion, items = _fusion(run, samples, WARM + scans, bundle)
    fusion.fuse_many(items[:WARM])
    start = time.process_time()
    outcomes = fusion.fuse_many(items[WARM:])
    seconds = (time.process_time() - start) / scans
    walked = [outcome.samples_walked for outcome in outcomes if isinstance(outcome, FuseResult)]
    if len(walked) < scans:
        raise RuntimeError(f"the fusion refused {scans - len(walked)} of the office's scans")
    return seconds, sum(walked) / scans


def map_scores(run: SimRun, samples: int, bundle: float) -> dict[str, float]:
    """AUC, Brier score and NLL of the whole run fused with ``samples`` samples, bundled with tolerance ``bundle``."""
    fusion, items = _fusion(run, samples, len(run.stamps), bundle)
    fusion.fuse_many(items)
    scores = score_map(fusion.grid.rasterize(), truth_arrays(run))
    return {name: scores[name] for name in ("auc", "brier", "nll")}


def run() -> dict:
    """Scans per CPU second and CPU us per sample for every M of :data:`COUNTS`, exact and bundled, on the same office
    run; the maps' scores for every M of :data:`QUALITY_COUNTS`."""
    office = office_run(seed=0, steps=STEPS)
    figures: dict = {"resolution_m": RESOLUTION, "bundle_tolerance_m": RECOMMENDED_TOLERANCE}
    for samples, scans in COUNTS.items():
        seconds, _ = cpu_seconds_per_scan(office, samples, scans)
        bundled_seconds, walked = cpu_seconds_per_scan(office, samples, scans, RECOMMENDED_TOLERANCE)
        figures[f"m{samples}_scans_per_cpu_s"] = 1.0 / seconds
        figures[f"m{samples}_cpu_us_per_sample"] = 1e6 * seconds / samples
        figures[f"m{samples}_bundled_scans_per_cpu_s"] = 1.0 / bundled_seconds
        figures[f"m{samples}_bundled_samples_walked"] = walked
        figures[f"m{samples}_bundled_speedup"] = seconds / bundled_seconds
        figures[f"m{samples}_timed_scans"] = scans
    for samples in QUALITY_COUNTS:
        exact, bundled = map_scores(office, samples, 0.0), map_scores(office, samples, RECOMMENDED_TOLERANCE)
        for name in exact:
            figures[f"m{samples}_exact_{name}"] = exact[name]
            figures[f"m{samples}_bundled_{name}"] = bundled[name]
        figures[f"m{samples}_bundled_auc_change"] = bundled["auc"] - exact["auc"]
        figures[f"m{samples}_bundled_brier_change_rel"] = bundled["brier"] / exact["brier"] - 1.0
        figures[f"m{samples}_bundled_nll_change_rel"] = bundled["nll"] / exact["nll"] - 1.0
    return figures
