"""Exact 2-D ray traversal (Amanatides & Woo, 1987) on the unbounded global grid.

The global grid has its origin at map-frame (0, 0): cell (ix, iy) covers x in [ix*res, (ix+1)*res) and
y in [iy*res, (iy+1)*res). A ray from (x0, y0) along the unit direction (dx, dy) visits every cell it
crosses with positive length, in order, each once, together with the ranges r_in < r_out (m from the
ray origin) over which it lies inside that cell. Rays passing exactly through a cell corner do not visit
the cells they only touch in a point (crossings closer than CORNER_EPS count as one corner).

The corner tolerance is fixed per ray (it scales with the ray's length), which keeps it off the chain of
dependent operations from one cell to the next. The compiled fusion kernels inline :func:`dda_start` and
:func:`dda_step` so there is one traversal in the code base.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.errors import InputError
from mapping.jit import kernel

#: crossings of the two grid-line families closer than this (relative, m) are one corner crossing
CORNER_EPS = 1e-12

#: stands for "never" in the stepping arithmetic (inf would give 0 * inf = NaN in the branch-free steps)
FAR = 1e300


#: cell indices stay within this many cells of the map origin (the kernels take them as int64, and a ray's ranges
#: keep their precision: from a point 1e20 m out a ray's steps no longer moved it, and its walk never ended)
MAX_CELL_INDEX = 1 << 40


def max_cells(r_stop: float, resolution: float) -> int:
    """An upper bound on the cells one ray of length r_stop can visit (|dx| + |dy| <= sqrt(2))."""
    return int(math.ceil(r_stop * math.sqrt(2.0) / resolution)) + 3


@kernel(nogil=True, error_model="numpy", inline="always")
def dda_start(x0, y0, dx, dy, res):  # pragma: no cover - compiled
    """Start cell and stepping state of a ray: (ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y).

    t_max_*: range at which the ray crosses the next vertical / horizontal grid line; t_delta_*: range
    between two such crossings.
    """
    ix = int(math.floor(x0 / res))
    iy = int(math.floor(y0 / res))
    step_x, t_max_x, t_delta_x = _axis_start(ix, x0, dx, res)
    step_y, t_max_y, t_delta_y = _axis_start(iy, y0, dy, res)
    return ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y


@kernel(nogil=True, error_model="numpy", inline="always")
def _axis_start(i, origin, d, res):  # pragma: no cover - compiled
    """Along one axis, a ray from ``origin`` (m, in cell i) with direction component d: (step, t_max, t_delta)."""
    if d > 0.0:
        return 1, ((i + 1) * res - origin) / d, res / d
    if d < 0.0:
        return -1, (i * res - origin) / d, -res / d
    return 0, FAR, FAR


@kernel(nogil=True, error_model="numpy", inline="always")
def corner_tol(r_stop):  # pragma: no cover - compiled
    """The corner tolerance (m) of a ray of length r_stop: crossings closer than this are one corner."""
    return CORNER_EPS * (1.0 + r_stop)


@kernel(nogil=True, error_model="numpy", inline="always")
def dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol):  # pragma: no cover - compiled
    """Move to the next cell: returns (ix, iy, t_max_x, t_max_y). The new cell's r_in is the old
    min(t_max_x, t_max_y); tol is the ray's :func:`corner_tol`."""
    if t_max_y > t_max_x + tol:  # the vertical grid line first
        return ix + step_x, iy, t_max_x + t_delta_x, t_max_y
    if t_max_x > t_max_y + tol:  # the horizontal one first
        return ix, iy + step_y, t_max_x, t_max_y + t_delta_y
    return ix + step_x, iy + step_y, t_max_x + t_delta_x, t_max_y + t_delta_y  # both at a corner: diagonally


@kernel(nogil=True, error_model="numpy")
def trace_ray(x0, y0, dx, dy, r_stop, res, out_ix, out_iy, out_rin, out_rout):  # pragma: no cover - compiled
    """Fill the out_* buffers with the cells the ray crosses up to r_stop; return how many.

    x0, y0: ray origin (m, map frame); dx, dy: unit direction; r_stop: ray length (m); res: cell size (m).
    The buffers must hold max_cells(r_stop, res) entries.
    """
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(x0, y0, dx, dy, res)
    n = 0
    r = 0.0
    tol = corner_tol(r_stop)
    while n < out_ix.shape[0]:
        r_out = min(t_max_x, t_max_y, r_stop)
        if r_out > r:
            out_ix[n] = ix
            out_iy[n] = iy
            out_rin[n] = r
            out_rout[n] = r_out
            n += 1
        if r_out >= r_stop:
            break
        r = max(r, r_out)  # an origin within rounding of a grid line can give a first crossing at r < 0
        ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    return n


def traverse(x0: float, y0: float, angle: float, r_stop: float, resolution: float) -> tuple[np.ndarray, ...]:
    """The cells a ray crosses: (ix, iy, r_in, r_out) arrays, in order from the origin.

    x0, y0: origin in m (map frame); angle: direction in rad from +x; r_stop: length in m. InputError for values that
    are not finite, a resolution (m) not > 0, or a ray reaching past MAX_CELL_INDEX cells from the origin.
    """
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise InputError(f"resolution must be a finite number of metres > 0, got {resolution}")
    if not (math.isfinite(angle) and 0.0 <= r_stop < math.inf):
        raise InputError(f"need a finite angle (rad) and a length 0 <= r_stop < inf (m), got {angle} and {r_stop}")
    if not (max(abs(x0), abs(y0)) + r_stop) / resolution <= MAX_CELL_INDEX:  # (also NaN)
        raise InputError(
            f"a ray from ({x0}, {y0}) m, {r_stop} m long, reaches beyond the {MAX_CELL_INDEX * resolution:.3g} m "
            f"that {resolution} m cells cover"
        )
    size = max_cells(r_stop, resolution)
    ix = np.empty(size, np.int64)
    iy = np.empty(size, np.int64)
    r_in = np.empty(size, np.float64)
    r_out = np.empty(size, np.float64)
    n = trace_ray(
        float(x0), float(y0), math.cos(angle), math.sin(angle), float(r_stop), float(resolution), ix, iy, r_in, r_out
    )
    return ix[:n], iy[:n], r_in[:n], r_out[:n]
