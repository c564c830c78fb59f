"""Exact 2-D ray traversal (Amanatides & Woo, 1987) on the unbounded global grid.

The global grid has its origin at map-frame (0, 0): cell (ix, iy) covers x in [ix*res, (ix+1)*res) and
y in [iy*res, (iy+1)*res). A ray from (x0, y0) along the unit direction (dx, dy) visits every cell it
crosses with positive length, in order, each once, together with the ranges r_in < r_out (m from the
ray origin) over which it lies inside that cell. Rays passing exactly through a cell corner do not visit
the cells they only touch in a point
(crossings closer than CORNER_EPS count as one corner).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np


#: crossings of the two grid-line families closer than this (relative, m) are one corner crossing
CORNER_EPS = 1e-12


def max_cells(r_stop: float, resolution: float) -> int:
    """An upper bound on the cells one ray of length r_stop can visit (|dx| + |dy| <= sqrt(2))."""
    return int(math.ceil(r_stop * math.sqrt(2.0) / resolution)) + 3


@nb.njit(cache=True, nogil=True, error_model="numpy")
def trace_ray(x0, y0, dx, dy, r_stop, res, out_ix, out_iy, out_rin, out_rout):  # pragma: no cover - compiled
    """Fill the out_* buffers with the cells the ray crosses up to r_stop; return how many.

    x0, y0: ray origin (m, map frame); dx, dy: unit direction; r_stop: ray length (m); res: cell size (m).
    The buffers must hold max_cells(r_stop, res) entries.
    """
    ix = int(math.floor(x0 / res))
    iy = int(math.floor(y0 / res))
    inf = math.inf
    if dx > 0.0:
        step_x = 1
        t_max_x = ((ix + 1) * res - x0) / dx
        t_delta_x = res / dx
    elif dx < 0.0:
        step_x = -1
        t_max_x = (ix * res - x0) / dx
        t_delta_x = -res / dx
    else:
        step_x = 0
        t_max_x = inf
        t_delta_x = inf
    if dy > 0.0:
        step_y = 1
        t_max_y = ((iy + 1) * res - y0) / dy
        t_delta_y = res / dy
    elif dy < 0.0:
        step_y = -1
        t_max_y = (iy * res - y0) / dy
        t_delta_y = -res / dy
    else:
        step_y = 0
        t_max_y = inf
        t_delta_y = inf
    n = 0
    r = 0.0
    capacity = out_ix.shape[0]
    while n < capacity:
        r_out = min(t_max_x, t_max_y, r_stop)
        if r_out > r:
            out_ix[n] = ix
            out_iy[n] = iy
            out_rin[n] = r
            out_rout[n] = r_out
            n += 1
        if r_out >= r_stop:
            break
        if abs(t_max_x - t_max_y) <= CORNER_EPS * (1.0 + r):
            # through a corner: step diagonally, the two side cells are touched only in a point
            ix += step_x
            iy += step_y
            r = min(t_max_x, t_max_y)
            t_max_x += t_delta_x
            t_max_y += t_delta_y
        elif t_max_x < t_max_y:
            ix += step_x
            r = t_max_x
            t_max_x += t_delta_x
        else:
            iy += step_y
            r = t_max_y
            t_max_y += t_delta_y
    return n


def traverse(x0: float, y0: float, angle: float, r_stop: float, resolution: float) -> tuple[np.ndarray, ...]:
    """The cells a ray crosses: (ix, iy, r_in, r_out) arrays, in order from the origin.

    x0, y0: origin in m (map frame); angle: direction in rad from +x; r_stop: length in m.
    """
    size = max_cells(r_stop, resolution)
    ix = np.empty(size, np.int64)
    iy = np.empty(size, np.int64)
    r_in = np.empty(size, np.float64)
    r_out = np.empty(size, np.float64)
    n = trace_ray(float(x0), float(y0), math.cos(angle), math.sin(angle), float(r_stop), float(resolution),
                  ix, iy, r_in, r_out)
    return ix[:n], iy[:n], r_in[:n], r_out[:n]
