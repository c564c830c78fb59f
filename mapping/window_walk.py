"""The one ray walk of every compiled pass: a ray's start in a scan's scratch window, its steps, the jump over a
tile another shard owns, and the two phases in which the passes visit its cells (:func:`walk_ray`).

A window is a rectangle of global cells (:class:`Window`: ix0, iy0, w, h) that covers every ray of one scan
with a cell to spare; window cell (gx, gy) is global cell (ix0 + gx, iy0 + gy), and its row-major index is
c = gy * w + gx. Ranges (m) are along the ray from the laser, as in :mod:`mapping.raytrace`.

The walk visits a ray's cells in order, each with positive length, and hands each to the pass's visitors:
first the *free phase*, the cells that end before the beam's free limit (``visit_free(ctx, carry, ix, iy)``:
the cell's value is l_free and needs no model), then the cells up to the ray's end (``visit_near(ctx, beam,
carry, ix, iy, r_in, r_out)``). ``ctx`` is the pass's tuple of scratch arrays and constants, ``beam`` the ray's
:class:`mapping.beam_model.Beam`, and ``carry`` a value the visitors thread through the walk and hand back
(their running state). The visitors are compiled into the walk (``inline="always"``), so each pass gets its own
loops; the kernels that use the walk are compiled without reference counting (``mapping.jit.kernel``'s
``refcounted=False``), so that handing tuples of arrays to the visitors costs nothing per cell.

A cell is a pair (p, q) stepped by (step_x, step_y) as :func:`mapping.raytrace.dda_step` steps (ix, iy). The
passes walk global cells, (ix, iy); a pass that owns every tile may walk the window index instead, starting
from (c, 0) with steps (step_x, step_y * w), so that the cell's index is p + q (:func:`index_ray`).

How the walk is compiled matters for speed as much as what it does (docs/performance.md): a pass calls it once
with tiles whose all_owned is the constant True (the ownership look-ups compiled out) and once with the constant
False, rather than with a value known only at run time.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from mapping.beam_model import BEAM_SKIP, beam_at
from mapping.jit import kernel
from mapping.raytrace import FAR, corner_tol, dda_start, dda_step


class Window(NamedTuple):
    """A scan's scratch window: global cells ix0 <= ix < ix0 + w, iy0 <= iy < iy0 + h."""

    ix0: int
    iy0: int
    w: int
    h: int


class Tiles(NamedTuple):
    """The tiles over a window (2**shift cells a side; tile (tx0 + i, ty0 + j) is entry [j, i]) and which of them
    the shard owns: owned (bool, (tiles down, tiles across)), all_owned whether every one."""

    owned: np.ndarray
    all_owned: bool
    shift: int
    tx0: int
    ty0: int


class Ray(NamedTuple):
    """A ray's traversal state (:func:`mapping.raytrace.dda_start`) and its corner tolerance tol (m)."""

    ix: int
    iy: int
    step_x: int
    step_y: int
    t_max_x: float
    t_max_y: float
    t_delta_x: float
    t_delta_y: float
    tol: float


#: a shard jumps over another shard's tile to this far (relative, m) before the tile's exit, then steps
JUMP_MARGIN = 1e-9


@kernel(nogil=True, error_model="numpy", inline="always")
def just_before(r):  # pragma: no cover - compiled
    """The range (m) JUMP_MARGIN (relative) short of r: where a jump over a tile, or runs that must stop short of a
    range, end."""
    return r - JUMP_MARGIN * (1.0 + r)


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
    t_jump = just_before(t_exit)
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
def ownership_constants(tiles):  # pragma: no cover - compiled
    """The :class:`Tiles` twice, with all_owned the constant True and the constant False: a pass calls the walk with
    the one its shard's ownership asks for, so that each call compiles with the look-ups or without them."""
    return (
        Tiles(tiles.owned, True, tiles.shift, tiles.tx0, tiles.ty0),
        Tiles(tiles.owned, False, tiles.shift, tiles.tx0, tiles.ty0),
    )


@kernel(nogil=True, error_model="numpy", inline="always")
def beam_ray(laser, heading, directions, beam, k, res, window):  # pragma: no cover - compiled
    """Start the ray of beam k (a :class:`mapping.beam_model.Beam`, up to its r_stop) of a laser at pose (x m, y m,
    yaw rad) with heading (cos yaw, sin yaw), the beams' directions (cosines, sines) in the laser frame: returns
    (inside, ray, dx, dy) as :func:`ray_start`, inside false also for a skipped beam."""
    dx, dy = beam_direction(heading[0], heading[1], directions[0][k], directions[1][k])
    inside, ray = ray_start(laser[0], laser[1], dx, dy, beam.r_stop, res, window)
    return inside and beam.kind != BEAM_SKIP, ray, dx, dy


@kernel(nogil=True, error_model="numpy", inline="always")
def ray_start(x0, y0, dx, dy, stop, res, window):  # pragma: no cover - compiled
    """Start a ray of length stop (m) from (x0, y0) (m, map frame) along the unit direction (dx, dy) on cells of
    res (m): returns (inside, :class:`Ray`).

    inside is false when an end cell of the ray is not inside the :class:`Window` with a cell to spare. The window
    covers every ray's reach with a cell to spare, so this never skips; it guards the scratch memory once per ray
    (a segment's cells lie between its end cells, give or take a rounding)."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(x0, y0, dx, dy, res)
    end_gx = math.floor((x0 + stop * dx) / res) - window.ix0
    end_gy = math.floor((y0 + stop * dy) / res) - window.iy0
    inside = not (
        min(ix - window.ix0, iy - window.iy0, end_gx, end_gy) < 1
        or max(ix - window.ix0, end_gx) >= window.w - 1
        or max(iy - window.iy0, end_gy) >= window.h - 1
    )
    return inside, Ray(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, corner_tol(stop))


@kernel(nogil=True, error_model="numpy", inline="always")
def index_ray(ray, window):  # pragma: no cover - compiled
    """The ray in cell (ix, iy) of the window as a walk on the window's row-major index (module docstring): from
    (c, 0) with steps (step_x, step_y * w), the cell's index is p + q."""
    c = (ray.iy - window.iy0) * window.w + ray.ix - window.ix0
    return Ray(c, 0, ray.step_x, ray.step_y * window.w, ray.t_max_x, ray.t_max_y, ray.t_delta_x, ray.t_delta_y, ray.tol)


@kernel(nogil=True, error_model="numpy", inline="always")
def walk_ray(
    ray, r_in, free_until, stop, tiles, visit_free, visit_near, ctx, beam_ref, carry, jumps
):  # pragma: no cover
    """Walk ``ray`` from the range r_in (m) to its end at ``stop`` (m), visiting each cell of positive length in the
    tiles the shard owns (``tiles``, a :class:`Tiles`); returns the visitors' carry (module docstring).

    Cells that end before free_until (m) go to visit_free, the rest to visit_near, which is handed the beam
    beam_at(*beam_ref) (beam_ref: a :class:`mapping.beam_model.BeamTable` and the beam's index), read after the
    free phase (in registers for the cells near the return, not across the free phase's loop). A grid line crossed
    within the ray's corner tolerance of stop ends the ray: no sliver of a cell past it. In another shard's tile
    where the ray ends the walk ends; in one it goes on from, with ``jumps`` (a constant for the compiler) it jumps
    to just before the tile's exit (:func:`jump_over_tile`), else it steps through the tile's cells, visiting none,
    so that the cells after it are those of a single shard's walk bit for bit (the jump's ranges are products, the
    steps' sums, and where a ray runs along cell corners the two can part by more than its corner tolerance). It
    looks ownership up once per tile entered (:func:`_tile_owner`)."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = ray
    ray_end = stop - tol
    free_limit = min(free_until, ray_end)
    owner = (tiles.tx0 - 1, tiles.ty0 - 1, True)  # the tile looked up last; none yet (no ray leaves the window)
    ray_done = False
    while True:  # the free phase
        r_out = min(t_max_x, t_max_y)
        if r_out >= free_limit:
            break
        owner = _tile_owner(ix, iy, tiles, owner)
        if not owner[2]:
            jumped_from = r_in
            ix, iy, t_max_x, t_max_y, r_in, ray_done = _past_other_tile(
                (ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol), r_in, ray_end, tiles, jumps
            )
            if ray_done:
                break
            if r_in > jumped_from:
                continue  # look at the cell the jump landed in
        elif r_out > r_in:
            carry = visit_free(ctx, carry, ix, iy)
        r_in = r_out
        ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    beam = beam_at(beam_ref[0], beam_ref[1])
    while not ray_done:  # the cells from the free limit to the ray's end
        owner = _tile_owner(ix, iy, tiles, owner)
        mine = owner[2]
        if not mine:
            ix, iy, t_max_x, t_max_y, r_in, ends = _past_other_tile(
                (ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol), r_in, ray_end, tiles, jumps
            )
            if ends:
                break
        r_out = min(t_max_x, t_max_y, stop)
        if r_out > r_in and mine:
            carry = visit_near(ctx, beam, carry, ix, iy, r_in, r_out)
        if r_out >= ray_end:
            break
        r_in = r_out
        ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    return carry


@kernel(nogil=True, error_model="numpy", inline="always")
def _past_other_tile(ray, r_in, ray_end, tiles, jumps):  # pragma: no cover - compiled
    """What the walk does in another shard's tile, the ray in cell (ix, iy) of it with its crossings (``ray``, a
    :class:`Ray`), entered at r_in (m): (ix, iy, t_max_x, t_max_y, r_in, ends), ends when the ray ends (at ray_end, m)
    before it leaves the tile. With ``jumps`` the ray moved to just before the tile's exit (:func:`jump_over_tile`),
    else as it was (the walk steps on through the tile's cells, visiting none)."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, _ = ray
    if not jumps:
        t_exit = tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tiles.shift)
        return ix, iy, t_max_x, t_max_y, r_in, t_exit >= ray_end
    ix, iy, t_max_x, t_max_y, r_in, t_exit = jump_over_tile(
        ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tiles.shift
    )
    return ix, iy, t_max_x, t_max_y, r_in, t_exit >= ray_end


@kernel(nogil=True, error_model="numpy", inline="always")
def _tile_owner(ix, iy, tiles, owner):  # pragma: no cover - compiled
    """(tx, ty, mine) of the tile of cell (ix, iy), from ``owner``, that of the cell before: looked up when the cell
    lies in another tile. With tiles.all_owned, ``owner`` (mine stays True). The tile's indices are taken afresh
    each cell, not only when they change: so they stay in the same registers from one cell to the next."""
    if tiles.all_owned:
        return owner
    tx, ty, mine = owner
    cell_tx = ix >> tiles.shift
    cell_ty = iy >> tiles.shift
    if cell_tx != tx or cell_ty != ty:
        mine = tiles.owned[cell_ty - tiles.ty0, cell_tx - tiles.tx0]
    return cell_tx, cell_ty, mine
