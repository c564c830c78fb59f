"""Walking one ray through a scan's scratch window: its start, its steps on a row-major window index, and
the jump over a tile another shard owns.

A window is a rectangle of global cells (win_ix0, win_iy0, win_w, win_h) that covers every ray of one scan
with a cell to spare; window cell (gx, gy) is global cell (win_ix0 + gx, win_iy0 + gy), and its row-major
index is c = gy * win_w + gx. Ranges (m) are along the ray from the laser, as in :mod:`mapping.raytrace`.
"""

from __future__ import annotations

import math

from mapping.jit import kernel
from mapping.raytrace import FAR, corner_tol, dda_start, dda_step

#: a shard jumps over another shard's tile to this far (relative, m) before the tile's exit, then steps
JUMP_MARGIN = 1e-9


@kernel(nogil=True, error_model="numpy", inline="always")
def _axis_exit(i, step, t_max, t_delta, tile_shift):  # pragma: no cover - compiled
    """Along one axis: the range at which a ray in cell index i, stepping by ``step`` (-1, 0, 1), crosses the
    last grid line of i's tile (tiles of 2**tile_shift cells); FAR when it does not move along the axis."""
    first = (i >> tile_shift) << tile_shift
    if step > 0:
        return t_max + (first + (1 << tile_shift) - 1 - i) * t_delta
    if step < 0:
        return t_max + (i - first) * t_delta
    return FAR


@kernel(nogil=True, error_model="numpy", inline="always")
def tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tile_shift):  # pragma: no cover
    """Range at which a ray in cell (ix, iy) leaves that cell's tile (tiles of 2**tile_shift cells)."""
    return min(
        _axis_exit(ix, step_x, t_max_x, t_delta_x, tile_shift), _axis_exit(iy, step_y, t_max_y, t_delta_y, tile_shift)
    )


@kernel(nogil=True, error_model="numpy", inline="always")
def jump_over_tile(
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift
):  # pragma: no cover - compiled
    """Move a ray in another shard's tile to just before it leaves the tile (the work divides among
    shards); the normal steps then cross into the next tile exactly. Returns (ix, iy, t_max_x, t_max_y,
    r_in, t_exit) with t_exit the range (m) at which the ray leaves the tile."""
    t_exit = tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tile_shift)
    t_jump = t_exit - JUMP_MARGIN * (1.0 + t_exit)
    if t_jump > r_in:
        if t_max_x <= t_jump:
            crossings = int((t_jump - t_max_x) / t_delta_x) + 1
            ix += crossings * step_x
            t_max_x += crossings * t_delta_x
        if t_max_y <= t_jump:
            crossings = int((t_jump - t_max_y) / t_delta_y) + 1
            iy += crossings * step_y
            t_max_y += crossings * t_delta_y
        r_in = t_jump
    return ix, iy, t_max_x, t_max_y, r_in, t_exit


@kernel(nogil=True, error_model="numpy", inline="always")
def beam_direction(cos_yaw, sin_yaw, cos_angle, sin_angle):  # pragma: no cover - compiled
    """The unit direction (dx, dy) of a beam at angle a (rad, laser frame) from a laser heading yaw (rad, map
    frame), from the cosines and sines of both: no trigonometric call per ray."""
    return cos_yaw * cos_angle - sin_yaw * sin_angle, sin_yaw * cos_angle + cos_yaw * sin_angle


@kernel(nogil=True, error_model="numpy", inline="always")
def ray_start(x0, y0, dx, dy, stop, res, win_ix0, win_iy0, win_w, win_h):  # pragma: no cover - compiled
    """Start a ray of length stop (m) from (x0, y0) (m, map frame) along the unit direction (dx, dy): returns
    (inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol), the traversal state of
    :func:`mapping.raytrace.dda_start` and the ray's :func:`mapping.raytrace.corner_tol`.

    inside is false when an end cell of the ray is not inside the window (win_ix0, win_iy0, win_w, win_h)
    with a cell to spare. The window covers every ray's reach with a cell to spare, so this never skips; it
    guards the scratch memory once per ray (a segment's cells lie between its end cells, give or take a
    rounding)."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(x0, y0, dx, dy, res)
    end_gx = math.floor((x0 + stop * dx) / res) - win_ix0
    end_gy = math.floor((y0 + stop * dy) / res) - win_iy0
    inside = not (
        min(ix - win_ix0, iy - win_iy0, end_gx, end_gy) < 1
        or max(ix - win_ix0, end_gx) >= win_w - 1
        or max(iy - win_iy0, end_gy) >= win_h - 1
    )
    return inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, corner_tol(stop)


@kernel(nogil=True, error_model="numpy", inline="always")
def step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol):  # pragma: no cover - compiled
    """:func:`mapping.raytrace.dda_step` on a row-major window index c (row_step = step_y * window width):
    returns (c, t_max_x, t_max_y). Handed (c, 0) and (step_x, row_step), dda_step returns c's move along the
    row and across rows, which add up to the next cell's index."""
    along, across, t_max_x, t_max_y = dda_step(c, 0, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    return along + across, t_max_x, t_max_y
