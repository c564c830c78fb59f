"""The adaptive grid against the fine regular grid built from the same scans (paper, Fig. 4(b)).

On the simulated office with honest pose distributions (bench/scenarios.py), both grids fuse the same scans
and the same pose samples. The regular grid's thresholded occupancy (p > 1/2 over its observed cells) is the
label set; the adaptive map, rasterised at the finest resolution, is scored by ROC AUC against it, with and
without unknowns in the split test. Budgets: active cells and bytes as fractions of the regular grid's
observed cells and bytes. A sweep over the split test's significance traces AUC against the cell budget for
both rules, so they can be compared at the same budget (linear interpolation along the rule without
unknowns). ``claimed_free_m2`` is the paper's Fig. 3 error made measurable: area that the regular grid never
observed but that the adaptive map shows as free to a planner (p <= map_server's free threshold).
``tree_oracle_auc`` scores the same tree with each active cell given the regular grid's mean log-odds under it:
what the tree's cell sizes allow, so the gap to ``auc`` is what the cells' history costs.
``label_pure_cells_fraction`` is the fewest cells, none coarser than the start cells, that any quadtree needs to
hold the labels exactly (`label_pure_cells`): what the quadtree itself allows, whatever its split rule.
`compare_rules` does all of this for any posed scans; bench/adaptive_real.py runs it on real laser logs.
Speeds are scans per second, single-threaded, after a warm-up scan that compiles the kernels: wall-clock, and
per second of this process's CPU time (steadier when other work shares the machine).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol, TypeVar

import numpy as np

from bench.scenarios import honest_posed_scans, office_run
from mapping.adaptive import AdaptiveFusion, AdaptiveGrid, AdaptiveParams
from mapping.evaluation import sample_map, score_map
from mapping.export import FREE_THRESH
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans

SAMPLES = 30
RESOLUTION = 0.05
#: significance levels of the split test, the default (0.01) first
SIGNIFICANCES = (0.01, 1e-6, 0.9)


GridT = TypeVar("GridT", covariant=True)


class _Fusion(Protocol[GridT]):
    """What `_fuse` needs of MonteCarloFusion and AdaptiveFusion: their grid and their per-scan fuse."""

    @property
    def grid(self) -> GridT: ...

    def fuse(self, ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray) -> object: ...


def _fuse(posed: PosedScans, make_fusion: Callable[[], _Fusion[GridT]]) -> tuple[float, float, GridT]:
    """Wall and CPU seconds to fuse every scan with the fusion ``make_fusion()`` returns (after a warm-up on a
    copy), and the grid."""
    samples, weights = posed.poses.weighted_samples()
    make_fusion().fuse(posed.ranges[0], samples[0], weights[0])
    fusion = make_fusion()
    wall, cpu = time.perf_counter(), time.process_time()
    for t in range(len(posed.stamps)):
        fusion.fuse(posed.ranges[t], samples[t], weights[t])
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
    return {
        "occupied": ~free,
        "visible": np.ones_like(free),
        "origin": regular["origin"],
        "resolution": regular["resolution"],
    }


def regular_labels(raster: dict) -> dict:
    """The paper's Fig. 4(b) labels: the regular grid's thresholded occupancy (p > 1/2) over its observed cells."""
    return {
        "occupied": raster["probability"] > 0.5,
        "visible": raster["observed"],
        "origin": raster["origin"],
        "resolution": raster["resolution"],
    }


def tree_oracle_logodds(tree: dict, regular: dict) -> np.ndarray:
    """Log-odds on the raster of ``tree`` (an adaptive raster with ``level``): each active cell given the mean
    log-odds of the ``regular`` raster's observed cells under it (0 where none), the best values the tree's
    cell sizes allow. Both rasters share the finest resolution and the world frame's cell boundaries."""
    res = float(tree["resolution"])
    rows, cols = np.nonzero(tree["level"] >= 0)
    level = tree["level"][rows, cols].astype(np.int64)
    gx = (int(round(tree["origin"][0] / res)) + cols) >> level  # the active cell's index at its level
    gy = (int(round(tree["origin"][1] / res)) + rows) >> level
    gx, gy = gx - gx.min(), gy - gy.min()
    cell = (gx * (gy.max() + 1) + gy) * 16 + level  # one key per active cell
    x, y = tree["origin"][0] + (cols + 0.5) * res, tree["origin"][1] + (rows + 0.5) * res
    where = (regular["origin"], float(regular["resolution"]), x, y)
    fine = sample_map(regular["logodds"], *where)
    seen = sample_map(regular["observed"].astype(float), *where) == 1.0  # 0.5 off the raster
    keys, index = np.unique(cell, return_inverse=True)
    total = np.bincount(index[seen], fine[seen], len(keys))
    count = np.bincount(index[seen], None, len(keys))
    logodds = np.zeros(tree["level"].shape)
    logodds[rows, cols] = (total / np.maximum(count, 1))[index]
    return logodds


def label_pure_cells(raster: dict, start_level: int) -> int:
    """Cells of the coarsest world-aligned quadtree, cells at most 2**start_level fine cells wide, in which every
    cell is label-pure: the fine cells under it that the regular ``raster`` observed are all occupied (p > 1/2)
    or all free. Only cells over at least one observed fine cell are counted. With each cell given the mean
    log-odds under it (as the tree oracle does), such a tree ranks the labels perfectly (AUC 1). So this is the
    fewest cells, none coarser than a start cell, in which a quadtree can hold the fine grid's labels, whatever
    evidence its splits see (merging past the start cells, as the adaptive grid may, could only use fewer).
    Blocks merge bottom-up: a block is one cell when its four children each are and it is pure."""
    res = float(raster["resolution"])
    side = 1 << start_level
    pad_x, pad_y = (int(round(value / res)) % side for value in raster["origin"])  # fine cells to the block edge
    h, w = raster["observed"].shape
    observed = np.zeros((-(-(h + pad_y) // side) * side, -(-(w + pad_x) // side) * side), bool)
    occupied = np.zeros_like(observed)
    observed[pad_y : pad_y + h, pad_x : pad_x + w] = raster["observed"]
    occupied[pad_y : pad_y + h, pad_x : pad_x + w] = raster["observed"] & (raster["probability"] > 0.5)
    free = observed & ~occupied
    count = observed.astype(np.int64)  # per block of the current level: its cells over observed fine cells
    merged = np.ones_like(observed)  # per block: it is one cell

    def quads(a):  # the four children of each block of the next level
        return a.reshape(a.shape[0] // 2, 2, a.shape[1] // 2, 2)

    for _ in range(start_level):
        occupied, free = quads(occupied).any(axis=(1, 3)), quads(free).any(axis=(1, 3))
        merged = quads(merged).all(axis=(1, 3)) & ~(occupied & free)
        count = np.where(merged, occupied | free, quads(count).sum(axis=(1, 3)))
    return int(count.sum())


def tree_oracle_auc(tree: dict, regular: dict, labels: dict) -> float:
    """AUC against ``labels`` of the tree with `tree_oracle_logodds`' values. Its gap to the adaptive map's
    own AUC is what the cells' history costs (a child inherits its parent's log-odds), not their size."""
    logodds = tree_oracle_logodds(tree, regular)
    return score_map(dict(tree, logodds=logodds, probability=1.0 / (1.0 + np.exp(-logodds))), labels)["auc"]


def compare_rules(posed: PosedScans, model: SensorModel, sweep: dict[str, AdaptiveParams]) -> dict:
    """Fuse ``posed`` into the fine regular grid and into one adaptive grid per entry of ``sweep`` (figure
    prefix -> parameters); score each against the regular grid. Per prefix: ``cells_fraction`` (active cells
    over the regular grid's observed cells), ``bytes_fraction``, ``auc``, ``tree_oracle_auc``,
    ``free_space_auc``, ``claimed_free_m2``, ``scans_per_s`` and ``scans_per_cpu_s``. Then, for every prefix
    that counts unknowns, the AUCs of the rule without unknowns interpolated to its cell budget
    (``no_unknowns_auc_at_PREFIX_cells``, NaN outside the sweep without unknowns) and the lead of unknowns
    over them (``PREFIX_auc_lead_at_same_cells``; the same for the free-space AUC)."""
    scans = len(posed.stamps)

    def regular() -> MonteCarloFusion:
        return MonteCarloFusion(TiledGrid(RESOLUTION), model, *posed.single_geometry())

    seconds, cpu, fine = _fuse(posed, regular)
    raster = fine.rasterize()
    labels = regular_labels(raster)
    free_labels = free_space_labels(raster)
    observed = fine.observed_cells()
    out: dict = {
        "regular_scans_per_s": scans / seconds,
        "regular_scans_per_cpu_s": scans / cpu,
        "regular_observed_cells": observed,
        "regular_bytes_per_observed_cell": fine.nbytes / observed,
        "label_pure_cells_fraction": label_pure_cells(raster, AdaptiveParams().start_level) / observed,
    }
    curves: dict[bool, list[tuple[float, float, float]]] = {True: [], False: []}
    for prefix, params in sweep.items():

        def adaptive(params: AdaptiveParams = params) -> AdaptiveFusion:
            return AdaptiveFusion(AdaptiveGrid(RESOLUTION), model, *posed.single_geometry(), params)

        seconds, cpu, grid = _fuse(posed, adaptive)
        tree = grid.rasterize()
        cells = grid.active_cells / observed
        auc, free_auc = score_map(tree, labels)["auc"], score_map(tree, free_labels)["auc"]
        curves[params.unknowns].append((cells, auc, free_auc))
        out.update(
            {
                f"{prefix}_cells_fraction": cells,
                f"{prefix}_active_cells": grid.active_cells,
                f"{prefix}_bytes_fraction": grid.nbytes / fine.nbytes,
                f"{prefix}_bytes_per_observed_cell": grid.nbytes / observed,
                f"{prefix}_auc": auc,
                f"{prefix}_tree_oracle_auc": tree_oracle_auc(tree, raster, labels),
                f"{prefix}_free_space_auc": free_auc,
                f"{prefix}_claimed_free_m2": claimed_free_m2(tree, raster),
                f"{prefix}_scans_per_s": scans / seconds,
                f"{prefix}_scans_per_cpu_s": scans / cpu,
            }
        )
    without = sorted(curves[False])
    for prefix, params in sweep.items():
        if not params.unknowns or not without:
            continue
        cells = out[f"{prefix}_cells_fraction"]
        inside = without[0][0] <= cells <= without[-1][0]
        for column, score in ((1, "auc"), (2, "free_space_auc")):
            value = np.interp(cells, [c[0] for c in without], [c[column] for c in without]) if inside else np.nan
            out[f"no_unknowns_{score}_at_{prefix}_cells"] = float(value)
            out[f"{prefix}_{score}_lead_at_same_cells"] = out[f"{prefix}_{score}"] - float(value)
    return out


def significance_sweep() -> dict[str, AdaptiveParams]:
    """Figure prefix -> parameters: both split rules at every significance of SIGNIFICANCES (the default's
    prefix is the rule's name alone)."""
    sweep = {}
    for name, unknowns in (("unknowns", True), ("no_unknowns", False)):
        for alpha in SIGNIFICANCES:
            prefix = name if alpha == SIGNIFICANCES[0] else f"{name}_alpha_{alpha:g}"
            sweep[prefix] = AdaptiveParams(unknowns=unknowns, significance=alpha)
    return sweep


def run(steps: int = 400) -> dict:
    """Measure; returns a flat dict of figures (also printed by bench.run)."""
    sim = office_run(seed=0, steps=steps)
    posed = honest_posed_scans(sim, seed=1, particles=SAMPLES)
    out: dict = {
        "scans": len(posed.stamps),
        "beams": int(posed.ranges.shape[1]),
        "samples": SAMPLES,
        "resolution_m": RESOLUTION,
        "start_cell_m": RESOLUTION * (1 << AdaptiveParams().start_level),
    }
    out.update(compare_rules(posed, SensorModel(resolution=RESOLUTION), significance_sweep()))
    return out
