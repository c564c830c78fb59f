"""Scoring a map against a truth raster (DESIGN.md, "Evaluation protocol").

Over the truth cells a perfect sensor would have seen from the true poses (``visible``), the map's
occupancy probability (0.5 where the map has nothing) is scored against ``occupied`` by ROC AUC, Brier
score and negative log-likelihood (natural log, per cell). The map is sampled at each truth cell's centre,
so the two rasters may differ in origin, extent and resolution.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import rankdata

from mapping.errors import InputError

#: probabilities are clipped to [EPS, 1 - EPS] for the NLL so a confident mistake costs a finite amount
NLL_EPS = 1e-6


def sample_map(probability: np.ndarray, origin: np.ndarray, resolution: float,
               x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The map's probability at map-frame points (x, y) in m; 0.5 outside the raster."""
    col = np.floor((x - origin[0]) / resolution).astype(np.int64)
    row = np.floor((y - origin[1]) / resolution).astype(np.int64)
    inside = (row >= 0) & (col >= 0) & (row < probability.shape[0]) & (col < probability.shape[1])
    out = np.full(x.shape, 0.5)
    out[inside] = probability[row[inside], col[inside]]
    return out


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney U with mid-ranks for ties); NaN if a class is empty."""
    labels = labels.astype(bool)
    n_pos = int(labels.sum())
    n_neg = labels.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(scores)
    return float((ranks[labels].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def score_probabilities(p: np.ndarray, occupied: np.ndarray) -> dict[str, float]:
    """AUC, Brier score and NLL of probabilities p against boolean labels."""
    truth = occupied.astype(float)
    clipped = np.clip(p, NLL_EPS, 1 - NLL_EPS)
    return {
        "auc": roc_auc(p, occupied),
        "brier": float(np.mean((p - truth) ** 2)),
        "nll": float(-np.mean(truth * np.log(clipped) + (1 - truth) * np.log1p(-clipped))),
        "n": int(p.size),
    }


def score_map(map_arrays: dict, truth_arrays: dict) -> dict[str, float]:
    """Score a map (map-file keys) against a truth raster (truth keys); see the module docstring."""
    visible = np.asarray(truth_arrays["visible"], bool)
    if not visible.any():
        raise InputError("the truth raster has no visible cells to score")
    rows, cols = np.nonzero(visible)
    t_res = float(truth_arrays["resolution"])
    t_origin = np.asarray(truth_arrays["origin"], float)
    x = t_origin[0] + (cols + 0.5) * t_res
    y = t_origin[1] + (rows + 0.5) * t_res
    p = sample_map(np.asarray(map_arrays["probability"]), np.asarray(map_arrays["origin"], float),
                   float(map_arrays["resolution"]), x, y)
    return score_probabilities(p, np.asarray(truth_arrays["occupied"], bool)[rows, cols])
