"""Where the Monte Carlo map's AUC differs from the most-likely-pose map's (docs/quality.md).

Truth cells are grouped by their distance to the nearest truth wall cell and by the pose uncertainty of
the scans that saw them; per group the mean occupancy probability of each map, and the AUC each map
reaches when only the wall cells and that group's free cells are ranked.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt

from bench.scenarios import honest_covariances, honest_posed_scans, office_run, truth_arrays
from mapping.evaluation import probability_on_raster, roc_auc, score_map
from services.fusion_runner import fuse_posed_scans

SAMPLES = 60


def run(steps: int = 400) -> dict:
    sim = office_run(seed=0, steps=steps)
    truth = truth_arrays(sim)
    posed = honest_posed_scans(sim, seed=1)
    maps = {
        mode: fuse_posed_scans(posed, mode=mode, n_samples=SAMPLES if mode == "mc" else None).rasterize()
        for mode in ("mc", "ml")
    }
    visible, occupied = truth["visible"], truth["occupied"]
    rows, cols = np.nonzero(visible)
    p = {
        mode: probability_on_raster(m, truth["origin"], float(truth["resolution"]), visible.shape)[rows, cols]
        for mode, m in maps.items()
    }
    labels = occupied[rows, cols]
    distance = distance_transform_edt(~occupied)[rows, cols]  # in cells, 0 on walls
    out: dict = {}
    for mode in maps:
        for key, value in score_map(maps[mode], truth).items():
            out[f"{mode}_{key}"] = value
    groups = {
        "wall": labels,
        "free_1cell": (distance > 0) & (distance <= 1.5),
        "free_2-3cells": (distance > 1.5) & (distance <= 3.5),
        "free_far": distance > 3.5,
    }
    for name, mask in groups.items():
        out[f"cells_{name}"] = int(mask.sum())
        for mode in maps:
            out[f"{mode}_mean_p_{name}"] = float(p[mode][mask].mean())
        if name != "wall":
            ranked = labels | mask
            for mode in maps:
                out[f"{mode}_auc_wall_vs_{name}"] = roc_auc(p[mode][ranked], labels[ranked])
    # the free cells next to walls that mc ranks above some wall cells: how uncertain were the poses there?
    sigma_xy = np.sqrt(honest_covariances(len(posed.stamps))[:, 0, 0])
    out["pose_sigma_xy_m_min"] = float(sigma_xy.min())
    out["pose_sigma_xy_m_max"] = float(sigma_xy.max())
    near = groups["free_1cell"]
    out["mc_minus_ml_p_free_1cell"] = float((p["mc"] - p["ml"])[near].mean())
    out["mc_minus_ml_p_wall"] = float((p["mc"] - p["ml"])[labels].mean())
    for mode in maps:
        out[f"{mode}_wall_cells_below_half"] = float((p[mode][labels] < 0.5).mean())
        out[f"{mode}_far_free_cells_above_half"] = float((p[mode][groups["free_far"]] > 0.5).mean())
    return out
