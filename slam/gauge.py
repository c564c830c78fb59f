"""The gauge of a landmark map: where a map sits and how it is turned in the world frame (2-D rigid motions).

Range-bearing measurements and robot-frame motion are unchanged when a robot pose and its map are moved
together by one rigid motion, so a SLAM filter learns a map's gauge only from where it started. These
helpers measure the gauge of many maps against one reference and move maps between gauges, all vectorised
over the maps. Angles in rad, positions in m, all in the world frame.
"""

from __future__ import annotations

import numpy as np


def map_gauges(maps: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gauge of each of ``maps`` (N, L, 2), L >= 2 distinct points: its turn (N,) rad against the
    ``weights``-weighted (N,) mean map and its centroid (N, 2) m.

    The turn is the least-squares rotation about the centroids (2-D Procrustes): with a_l, b_l the points of the
    mean map and of a map less their centroids, the angle of (sum_l a_l . b_l, sum_l a_l x b_l). So
    maps[n] ~ R(turn[n]) (mean map - its centroid) + centroid[n].
    """
    mean_map = np.einsum("n,nli->li", weights, maps)
    centroids = maps.mean(axis=1)
    a = mean_map - mean_map.mean(axis=0)
    b = maps - centroids[:, None, :]
    dot = np.einsum("li,nli->n", a, b)
    cross = np.einsum("l,nl->n", a[:, 0], b[:, :, 1]) - np.einsum("l,nl->n", a[:, 1], b[:, :, 0])
    return np.arctan2(cross, dot), centroids


def regauge_points(points: np.ndarray, turn: np.ndarray, centre_from: np.ndarray, centre_to: np.ndarray) -> np.ndarray:
    """Points (N, ..., 2) moved by p -> R(turn) (p - centre_from) + centre_to: turned by turn (N,) rad about
    centre_from (N, 2) m, which goes to centre_to (N, 2) m; one motion per leading index n."""
    flat = points.reshape(len(points), -1, 2) - centre_from[:, None, :]
    c, s = np.cos(turn)[:, None], np.sin(turn)[:, None]
    x, y = flat[..., 0], flat[..., 1]
    moved = np.empty_like(flat)  # (R p written out: an einsum over the 2 x 2 blocks took 4 times as long)
    moved[..., 0] = c * x - s * y + centre_to[:, None, 0]
    moved[..., 1] = s * x + c * y + centre_to[:, None, 1]
    return moved.reshape(points.shape)


def turn_covariances(cov: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Symmetric 2x2 covariances (N, ..., 2, 2) in m^2 turned by turn (N,) rad: R cov R^T, one turn per
    leading index n, written out element by element (a broadcast matmul of the 2x2 blocks took 2.1 ms against
    0.19 ms for N = 500 particles of 16 landmarks, 2026-11-26)."""
    shape = (len(turn),) + (1,) * (cov.ndim - 3)
    c, s = np.cos(turn).reshape(shape), np.sin(turn).reshape(shape)
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    cs, cc, ss = c * s, c * c, s * s
    off = cs * (a - d) + (cc - ss) * b
    out = np.empty_like(cov)
    out[..., 0, 0] = cc * a - 2.0 * cs * b + ss * d
    out[..., 1, 1] = ss * a + 2.0 * cs * b + cc * d
    out[..., 0, 1] = off
    out[..., 1, 0] = off
    return out
