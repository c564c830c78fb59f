"""The adaptive grid against the fine regular grid built from the same scans (paper, Fig. 4(b)).

On the simulated office with honest pose distributions (bench/scenarios.py), both grids fuse the same scans
and the same pose samples. The regular grid's thresholded occupancy (p > 1/2 over its observed cells) is the
label set; the adaptive map, rasterised at the finest resolution, is scored by ROC AUC against it, with and
without unknowns in the split test. Budgets: active cells and bytes as fractions of the regular grid's
observed cells and bytes. A sweep over the split test's significance traces AUC against the cell budget for
both rules, so they can be compared at the same budget (linear interpolation along the rule without
unknowns). ``claimed_free_m2`` is the paper's Fig. 3 error made measurable: area that the regular grid never
observed but that the adaptive map shows as free to a planner (p <= map_server's free threshold).
Speeds are scans per second, single-threaded, after a warm-up scan that compiles the kernels: wall-clock, and
per second of this process's CPU time (steadier when other work shares the machine).
"""
from __future__ import annotations

import time

import numpy as np

from bench.scenarios import honest_posed_scans, office_run
from mapping.adaptive import AdaptiveFusion, AdaptiveGrid, AdaptiveParams
from mapping.evaluation import sample_map, score_map
from mapping.export import FREE_THRESH
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel

SAMPLES = 30
RESOLUTION = 0.05
#: significance levels of the split test, the default (0.01) first
SIGNIFICANCES = (0.01, 1e-6, 0.9)


def _fuse(posed, make_fusion) -> tuple[float, float, object]:
    """Wall and CPU seconds to fuse every scan with the fusion ``make_fusion()`` returns (after a warm-up on a
    copy), and the grid."""
    make_fusion().fuse(posed.ranges[0], posed.poses.samples[0], posed.poses.weights[0])
    fusion = make_fusion()
    wall, cpu = time.perf_counter(), time.process_time()
    for t in range(len(posed.stamps)):
        fusion.fuse(posed.ranges[t], posed.poses.samples[t], posed.poses.weights[t])
    return time.perf_counter() - wall, time.process_time() - cpu, fusion.grid


def claimed_free_m2(adaptive: dict, regular: dict) -> float:
    """Area (m^2) of finest cells the regular raster never observed that the adaptive raster shows as free."""
    rows, cols = np.nonzero(adaptive["observed"] & (adaptive["probability"] <= FREE_THRESH))
    res = float(adaptive["resolution"])
    x = adaptive["origin"][0] + (cols + 0.5) * res
    y = adaptive["origin"][1] + (rows + 0.5) * res
    seen = sample_map(regular["observed"].astype(float), regular["origin"], float(regular["resolution"]), x, y) > 0.5
    return float((~seen).sum() * res * res)


def free_space_labels(regular: dict) -> dict:
    """Truth for the planner's question "may I drive here?": over the whole extent of the regular raster,
    a cell counts as free only where the regular grid observed it and found it free (p < 1/2); occupied and
    never-observed cells alike are "not free" (the truth's ``occupied``). Scored with the occupancy as the
    score, an adaptive map loses AUC where it shows unseen space as free (the paper's Fig. 3 error), which the
    occupancy labels over observed cells cannot see."""
    free = regular["observed"] & (regular["probability"] < 0.5)
    return {"occupied": ~free, "visible": np.ones_like(free), "origin": regular["origin"],
            "resolution": regular["resolution"]}


def run(steps: int = 400) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    sim = office_run(seed=0, steps=steps)
    posed = honest_posed_scans(sim, seed=1, particles=SAMPLES)
    model = SensorModel(resolution=RESOLUTION)
    scans = len(posed.stamps)
    out: dict = {"scans": scans, "beams": int(posed.ranges.shape[1]), "samples": SAMPLES,
                 "resolution_m": RESOLUTION, "start_cell_m": RESOLUTION * (1 << AdaptiveParams().start_level)}

    def regular():
        return MonteCarloFusion(TiledGrid(RESOLUTION), model, posed.beam_angles, posed.range_min, posed.range_max,
                                posed.sensor_offset)

    seconds, cpu, fine = _fuse(posed, regular)
    raster = fine.rasterize()
    labels = {"occupied": raster["probability"] > 0.5, "visible": raster["observed"], "origin": raster["origin"],
              "resolution": raster["resolution"]}
    free_labels = free_space_labels(raster)
    observed = fine.observed_cells()
    out.update(regular_scans_per_s=scans / seconds, regular_scans_per_cpu_s=scans / cpu,
               regular_observed_cells=observed, regular_bytes_per_observed_cell=fine.nbytes / observed)

    sweeps: dict[str, list[tuple[float, float]]] = {}
    free_sweeps: dict[str, list[tuple[float, float]]] = {}
    for name, unknowns in (("unknowns", True), ("no_unknowns", False)):
        sweeps[name] = []
        free_sweeps[name] = []
        for alpha in SIGNIFICANCES:
            params = AdaptiveParams(unknowns=unknowns, significance=alpha)

            def adaptive(params=params):
                return AdaptiveFusion(AdaptiveGrid(RESOLUTION), model, posed.beam_angles, posed.range_min,
                                      posed.range_max, posed.sensor_offset, params)

            seconds, cpu, grid = _fuse(posed, adaptive)
            tree = grid.rasterize()
            cells = grid.active_cells / observed
            sweeps[name].append((cells, score_map(tree, labels)["auc"]))
            free_sweeps[name].append((cells, score_map(tree, free_labels)["auc"]))
            key = name if alpha == SIGNIFICANCES[0] else f"{name}_alpha_{alpha:g}"
            out.update({f"{key}_auc": sweeps[name][-1][1], f"{key}_free_space_auc": free_sweeps[name][-1][1],
                        f"{key}_cells_fraction": cells, f"{key}_claimed_free_m2": claimed_free_m2(tree, raster)})
            if alpha == SIGNIFICANCES[0]:
                out.update({f"{name}_active_cells": grid.active_cells,
                            f"{name}_bytes_fraction": grid.nbytes / fine.nbytes,
                            f"{name}_bytes_per_observed_cell": grid.nbytes / observed,
                            f"{name}_scans_per_s": scans / seconds, f"{name}_scans_per_cpu_s": scans / cpu})
    # the rule without unknowns at the budgets the rule with unknowns used (NaN outside its sweep)
    for score, curves in (("auc", sweeps), ("free_space_auc", free_sweeps)):
        cells_without, auc_without = zip(*sorted(curves["no_unknowns"]))
        for alpha, (cells, _) in zip(SIGNIFICANCES, curves["unknowns"]):
            key = "unknowns" if alpha == SIGNIFICANCES[0] else f"unknowns_alpha_{alpha:g}"
            inside = cells_without[0] <= cells <= cells_without[-1]
            auc = float(np.interp(cells, cells_without, auc_without)) if inside else float("nan")
            out[f"no_unknowns_{score}_at_{key}_cells"] = auc
    return out
