"""Exact 2-D ray casting against line segments, vectorised over rays x segments with NumPy."""

from __future__ import annotations

import numpy as np

#: rays per chunk, so the (rays, segments) work arrays stay a few MB
CHUNK_RAYS = 8192


def cast_rays(origins: np.ndarray, angles: np.ndarray, segments: np.ndarray, max_range: float) -> np.ndarray:
    """Distance (R,) in m from each ray's origin (R, 2) along its angle (R,) (rad, map frame) to the
    nearest segment (S, 4) (x0, y0, x1, y1); inf where nothing lies within ``max_range`` m.

    Solves origin + t d = a + u (b - a) for every ray and segment; a hit needs 0 <= t and 0 <= u <= 1.
    Rays parallel to a segment never hit it.
    """
    origins = np.asarray(origins, dtype=np.float64)
    out = np.full(len(origins), np.inf)
    a = segments[:, :2]
    e = segments[:, 2:] - a
    for start in range(0, len(origins), CHUNK_RAYS):
        p = origins[start : start + CHUNK_RAYS, None, :]
        theta = angles[start : start + CHUNK_RAYS]
        d = np.stack([np.cos(theta), np.sin(theta)], axis=-1)[:, None, :]
        denom = d[..., 0] * e[None, :, 1] - d[..., 1] * e[None, :, 0]
        ap = a[None] - p
        parallel = np.abs(denom) < 1e-12
        safe = np.where(parallel, 1.0, denom)
        t = (ap[..., 0] * e[None, :, 1] - ap[..., 1] * e[None, :, 0]) / safe
        u = (ap[..., 0] * d[..., 1] - ap[..., 1] * d[..., 0]) / safe
        hit = ~parallel & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
        nearest = np.where(hit, t, np.inf).min(axis=1)
        out[start : start + CHUNK_RAYS] = np.where(nearest <= max_range, nearest, np.inf)
    return out


def segments_block(starts: np.ndarray, ends: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Whether the segment from each start (R, 2) to its end (R, 2) crosses any segment (S, 4), (R,) bool.

    Solves start + t (end - start) = a + u (b - a); a crossing needs 0 < t < 1 (touching at either end of the
    sight line, within 1e-9, does not count, so a point placed on a wall is not hidden by that wall) and
    0 <= u <= 1.
    """
    out = np.zeros(len(starts), dtype=bool)
    a = segments[:, :2]
    e = segments[:, 2:] - a
    eps = 1e-9
    for start in range(0, len(starts), CHUNK_RAYS):
        p = starts[start : start + CHUNK_RAYS, None, :]
        d = (ends[start : start + CHUNK_RAYS] - starts[start : start + CHUNK_RAYS])[:, None, :]
        denom = d[..., 0] * e[None, :, 1] - d[..., 1] * e[None, :, 0]
        parallel = np.abs(denom) < 1e-12
        safe = np.where(parallel, 1.0, denom)
        ap = a[None] - p
        t = (ap[..., 0] * e[None, :, 1] - ap[..., 1] * e[None, :, 0]) / safe
        u = (ap[..., 0] * d[..., 1] - ap[..., 1] * d[..., 0]) / safe
        crossing = ~parallel & (t > eps) & (t < 1.0 - eps) & (u > -eps) & (u < 1.0 + eps)
        out[start : start + CHUNK_RAYS] = crossing.any(axis=1)
    return out
