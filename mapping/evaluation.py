"""Scoring a map against a truth raster (DESIGN.md, "Evaluation protocol").

Over the truth cells a perfect sensor would have seen from the true poses (``visible``), the map's
occupancy probability (0.5 where the map has nothing) is scored against ``occupied`` by ROC AUC, Brier
score and negative log-likelihood (natural log, per cell).

Each truth cell takes the map's probability averaged over the cell's area (:func:`probability_on_raster`), so
the two rasters may differ in origin, extent and resolution. Sampling the map at each truth cell's centre
instead made the scores depend on rounding: the simulator's truth cells are centred on the grid lines of every
fused map (walls on round coordinates run through truth cell centres and along map cell borders), and moving a
map's origin by 1e-9 m, or storing it as float32, moved AUC from 0.841 to 0.798.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import sparse
from scipy.stats import rankdata

from mapping.errors import InputError
from mapping.map_arrays import check_raster

#: probabilities are clipped to [EPS, 1 - EPS] for the NLL so a confident mistake costs a finite amount
NLL_EPS = 1e-6
#: a truth cell is informed when observed map cells cover more than this share of it
INFORMED_SHARE = 1e-6

#: scores equal to this many decimals are ties for the AUC. A truth cell's probability is an area-weighted mean of
#: map cells, and the same map and truth moved by (4.5e5, 5.4e6) m gave cells that were exact ties (free cells at
#: the clamp) values a rounding apart, in an order the rounding chose: AUC 0.8021 at the origin, 0.8081 and 0.8006 moved
#: (Brier and NLL within 1e-10). Rounded, 0.8036 for all three.
TIE_DECIMALS = 9

#: a truth cell edge within this many map cells of a map cell edge lies on it, so aligned rasters match cell for
#: cell and half-offset ones split cells in exact halves: an origin summed from steps, or stored as float32 (6e-8
#: relative: 1e-3 of a 0.05 m cell at 800 m), is off by less
EDGE_SNAP = 1e-3


def sample_map(
    probability: np.ndarray, origin: np.ndarray, resolution: float, x: np.ndarray, y: np.ndarray
) -> np.ndarray:
    """The map's probability at map-frame points (x, y) in m; 0.5 outside the raster. For points well inside
    cells (the centres of another raster aligned with the map's cells); scoring averages over cells instead
    (:func:`probability_on_raster`)."""
    col = np.floor((x - origin[0]) / resolution).astype(np.int64)
    row = np.floor((y - origin[1]) / resolution).astype(np.int64)
    inside = (row >= 0) & (col >= 0) & (row < probability.shape[0]) & (col < probability.shape[1])
    out = np.full(x.shape, 0.5)
    out[inside] = probability[row[inside], col[inside]]
    return out


def _overlap_weights(
    t_origin: float, t_res: float, t_count: int, m_origin: float, m_res: float, m_count: int
) -> sparse.csr_matrix:
    """Along one axis: the fraction of each truth interval [t_origin + k t_res, t_origin + (k + 1) t_res) (m)
    that each map interval [m_origin + j m_res, ...) covers, as a (t_count, m_count) matrix. Parts of a truth
    interval outside the map get no weight. Work and memory grow with the overlapping (truth, map) pairs, at most
    t_count + m_count of them."""
    edges = (t_origin + np.arange(t_count + 1) * t_res - m_origin) / m_res  # in map cells
    nearest = np.round(edges)
    edges = np.where(np.abs(edges - nearest) <= EDGE_SNAP, nearest, edges)
    low, high = edges[:-1], edges[1:]
    length = high - low
    if not (length > 0).all():
        raise InputError(f"truth cells of {t_res} m are too small to score against map cells of {m_res} m")
    first = np.clip(np.floor(low), 0, m_count).astype(np.int64)  # the map cells each truth interval overlaps
    stop = np.clip(np.ceil(high), 0, m_count).astype(np.int64)
    counts = np.maximum(stop - first, 0)
    rows = np.repeat(np.arange(t_count), counts)
    cols = np.arange(rows.size) - np.repeat(np.cumsum(counts) - counts, counts) + first[rows]
    weights = (np.minimum(high[rows], cols + 1) - np.maximum(low[rows], cols)) / length[rows]
    keep = weights > 0
    return sparse.csr_matrix((weights[keep], (rows[keep], cols[keep])), shape=(t_count, m_count))


def probability_on_raster(
    map_arrays: dict, origin: np.ndarray, resolution: float, shape: tuple[int, int]
) -> np.ndarray:
    """The map's occupancy probability averaged over each cell of another raster, (H, W) float64.

    map_arrays: map-file keys (``probability``, ``origin``, ``resolution``, and ``observed`` if present: an
    unobserved cell counts as 0.5 whatever its probability says). origin (m, map frame), resolution (m) and shape
    (H, W) define the other raster, with the map file's row order. Parts of a cell the map does not cover count
    as 0.5. Both axes are separable, so the average is ``Wy (P - 1/2) Wx^T + 1/2`` with sparse overlap matrices,
    taken over the part of the map the raster overlaps only.
    """
    probability = np.asarray(map_arrays["probability"])
    observed = map_arrays.get("observed")

    def deviation(rows: slice, cols: slice) -> np.ndarray:
        values = np.asarray(probability[rows, cols], np.float32) - np.float32(0.5)
        if observed is not None:
            values[~np.asarray(observed, bool)[rows, cols]] = 0.0
        return values

    return 0.5 + _averaged(deviation, probability.shape, map_arrays, origin, resolution, shape)


def observed_on_raster(map_arrays: dict, origin: np.ndarray, resolution: float, shape: tuple[int, int]) -> np.ndarray:
    """The share (0 .. 1) of each cell of another raster (as :func:`probability_on_raster`'s) that observed map
    cells cover (every cell of a map without an ``observed`` layer counts as observed)."""
    shape_of_map = np.asarray(map_arrays["probability"]).shape
    observed = map_arrays.get("observed")

    def covered(rows: slice, cols: slice) -> np.ndarray:
        if observed is None:
            return np.ones((rows.stop - rows.start, cols.stop - cols.start), np.float32)
        return np.asarray(observed, bool)[rows, cols].astype(np.float32)

    return _averaged(covered, shape_of_map, map_arrays, origin, resolution, shape)


def _averaged(
    layer: Callable[[slice, slice], np.ndarray],
    map_shape: tuple[int, ...],
    map_arrays: dict,
    origin: np.ndarray,
    resolution: float,
    shape: tuple[int, int],
) -> np.ndarray:
    """``Wy L Wx^T``: a map layer averaged over each cell of another raster (origin m, resolution m, shape (H, W)),
    0 where the map does not reach; ``layer(rows, cols)`` gives the layer's values over the map's rows and columns
    the raster overlaps (float32)."""
    m_origin = np.asarray(map_arrays["origin"], np.float64)
    m_res = float(map_arrays["resolution"])
    height, width = shape
    along_x = _overlap_weights(float(origin[0]), resolution, width, m_origin[0], m_res, map_shape[1])
    along_y = _overlap_weights(float(origin[1]), resolution, height, m_origin[1], m_res, map_shape[0])
    if along_x.nnz == 0 or along_y.nnz == 0:  # no overlap at all
        return np.zeros(shape)
    x0, x1 = along_x.indices.min(), along_x.indices.max() + 1
    y0, y1 = along_y.indices.min(), along_y.indices.max() + 1
    rows_done = along_y[:, y0:y1] @ layer(slice(y0, y1), slice(x0, x1))  # (H, x1 - x0)
    return np.asarray((along_x[:, x0:x1] @ rows_done.T).T, np.float64)


def roc_auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney U with mid-ranks for ties); NaN if a class is empty. Scores are
    rounded to :data:`TIE_DECIMALS` decimals first, so that values the same evidence gives are ties whatever the
    rounding of the arithmetic that made them."""
    labels = labels.astype(bool)
    n_pos = int(labels.sum())
    n_neg = labels.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(np.round(scores, TIE_DECIMALS))
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
    check_raster(map_arrays)
    visible = np.asarray(truth_arrays["visible"], bool)
    if not visible.any():
        raise InputError("the truth raster has no visible cells to score")
    rows, cols = np.nonzero(visible)
    t_res = float(truth_arrays["resolution"])
    corner = np.asarray(truth_arrays["origin"], float) + np.array([cols.min(), rows.min()]) * t_res
    box = (rows.max() - rows.min() + 1, cols.max() - cols.min() + 1)  # the visible cells' bounding box
    p = probability_on_raster(map_arrays, corner, t_res, box)[rows - rows.min(), cols - cols.min()]
    scores = score_probabilities(p, np.asarray(truth_arrays["occupied"], bool)[rows, cols])
    covered = observed_on_raster(map_arrays, corner, t_res, box)[rows - rows.min(), cols - cols.min()]
    # scored cells the map observed (a sliver of a cell under EDGE_SNAP's size is none: float rounding); it counted the
    # cells whose probability is not 0.5, and a map that observed every cell at 0.5 was said to have observed none
    scores["informed"] = int(np.count_nonzero(covered > INFORMED_SHARE))
    return scores
