"""The samples pass: one compiled pass over all (sample, beam, cell) triples of a scan with M > 1 distinct pose
samples, then one that adds the touched cells into the tiles (the update is in :mod:`mapping.fusion`).

How the pass keeps the per-sample rule cheap: every value is l_free (the smallest a cell can take) plus an
excess d >= 0, and only cells near a return have d > 0. So y_ij = l_free + d_ij for the samples j that
touch cell i, and with W_i = sum of their weights, D1_i = sum_j w_j d_ij, D2_i = sum_j w_j d_ij^2:

    sum_j w_j y_ij = l_free W_i + D1_i        sum_j w_j y_ij^2 = l_free^2 W_i + 2 l_free D1_i + D2_i

A sample's touched cells are marked in a plane of one bit per window cell (idempotent, so a cell crossed by several of
the sample's beams is marked once; most of a beam's free stretch is marked as runs per grid row or column,
:mod:`mapping.free_runs`), and the set bits add the sample's weight to W_i (a group of GROUP samples' planes swept
together: each sample of a group marks a plane of its own). The few cells with an excess keep a per-sample record (the
largest excess of the sample's beams, by stamp) for D1 and D2. One more bit plane marks the cells listed in this scan.
The rays are walked by :func:`mapping.window_walk.walk_ray`, with this pass's visitors (:func:`_mark_free`,
:func:`_mark_near`).

**Equal weights are counted, not summed.** When every sample has the same weight w (particles after resampling,
Gaussian draws), W_i depends only on how many samples touched cell i: it is the sum w + w + ... taken that many times,
in sample order. The sweep then adds a group's plane words into a bit-sliced counter of its 64 cells: the number of
the group's words with each bit set, in binary digits from carry-save adders, added level by level with a ripple carry
over COUNT_LEVELS words that stops at the first level the carry clears (samples that agree, as most do, leave the low
digits clear, and those levels untouched), instead of adding w once per set bit, and the apply reads W from the table
of those sums (``sums[n]``, summed in the same order: the same float64 bit for bit). Other weights take the per-bit
sums.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros  # LLVM's ctlz, cttz: a word's set bits

from mapping.beam_model import BeamTable, LogOddsModel, beam_at, segment_logodds
from mapping.fan_runs import (
    KEY,
    RAY_DX,
    RAY_DY,
    RAY_IX,
    RAY_IY,
    RAY_STEP_X,
    RAY_STEP_Y,
    RAY_T_DELTA_X,
    RAY_T_DELTA_Y,
    RAY_T_MAX_X,
    RAY_T_MAX_Y,
    RAY_TOL,
    REACH,
    SCAN_REACH,
    SKIP,
    STARTED,
    fan_hulls,
    record_crossings,
    recorded_crossings,
)
from mapping.fixed_point import WEIGHT_SCALE, to_fixed
from mapping.free_runs import (
    ALL_BITS,
    fold_block,
    fold_columns,
    mark_plane_runs,
    plane_crossings,
    runs_last_cell,
    set_bit,
)
from mapping.jit import kernel
from mapping.raytrace import dda_step
from mapping.tile_boxes import widen_box
from mapping.tile_changes import update_cell
from mapping.window_walk import (
    Ray,
    Tiles,
    Window,
    beam_direction,
    beam_ray,
    index_ray,
    jump_over_tile,
    just_before,
    ownership_constants,
    tile_exit,
    walk_ray,
)

#: per-sample stamps are stored as float64 (exact below 2**53); the scratch is cleared and stamps restart here
STAMP_LIMIT = 2**52

#: samples walked into planes of their own before their planes are swept into the weight sums together (the sweep,
#: :func:`_sweep_word`, and its adders, :func:`_count_group`, are written for four)
GROUP = 4

#: the bit-sliced counters' levels per 64-cell word: equal weights are counted for up to 2**COUNT_LEVELS - 1 samples
COUNT_LEVELS = 16

#: bit i of a byte b spread to the lowest bit of byte i: BYTE_SPREAD[b] (the apply reads eight cells' counts of up to
#: 8 levels at once, one byte a cell: :func:`_counts_in_bytes`)
BYTE_SPREAD = np.array([sum(((b >> i) & 1) << (8 * i) for i in range(8)) for b in range(256)], np.uint64)
#: room the apply needs per thread: a word's COUNT_LEVELS levels of counts, then its 64 cells' counts as bytes
APPLY_HELD = COUNT_LEVELS + 8


class SamplesScratch(NamedTuple):
    """The samples pass's scratch over a scan's window (cell c = gy * w + gx; see :func:`accumulate_scan`).

    plane, listed: one bit per cell (uint64 words), the current sample's touched cells and the cells any sample
    touched in this scan; columns: the column-major plane of :mod:`mapping.free_runs`, columns col_stride bits long;
    weight_sum: W per cell (int64, in steps of 1 / mapping.fixed_point.WEIGHT_SCALE); excess: (cells, 4) float64
    records of :func:`add_sample_excess`, whose moments (columns 2 and 3) are int64 steps read and written through
    ``moments``, the same memory viewed as int64; tile_touched: (bool, per tile of the window) the tiles of the listed
    cells; lines: (2, max(w, h)) int64, a ray's exit and entry cells per grid line (:mod:`mapping.free_runs`);
    block: 64 uint64, the 64 x 64 bits being folded from the column-major plane; counts: (COUNT_LEVELS, words) uint64,
    bit k of counts[l, i] is bit l of the number of samples that touched cell 64 i + k (equal weights only, zero
    between scans; level after level, so that the sweep's adds, which seldom pass the first levels, read and write a
    few dense rows); sums: the table W = sums[n] for n samples of equal weight, empty when the weights differ (then W
    is summed per cell); fan_ints, fan_floats: the records of a sample's rays for :func:`mapping.fan_runs.fan_hulls`
    (its ``fan_scratch``); group_planes: (GROUP - 1, words) uint64, as plane, the touched cells of a group's samples
    after its first (:func:`accumulate_scan`); moments: ``excess`` viewed as int64; boxes: per tile of the window, the
    bounding box of its listed cells (:func:`listed_boxes`, after the samples); raised: one bit per cell, the cells
    with an excess record of this scan (zero between scans), so that the apply and the merge read the records of
    those cells only (an eighth of a warehouse scan's listed cells), not every listed cell's stamp.
    """

    plane: np.ndarray
    columns: np.ndarray
    col_stride: int
    listed: np.ndarray
    weight_sum: np.ndarray
    excess: np.ndarray
    tile_touched: np.ndarray
    lines: np.ndarray
    block: np.ndarray
    counts: np.ndarray
    sums: np.ndarray
    fan_ints: np.ndarray
    fan_floats: np.ndarray
    group_planes: np.ndarray
    moments: np.ndarray
    boxes: np.ndarray
    raised: np.ndarray


class _Marks(NamedTuple):
    """What the samples pass's visitors write: the sample's plane and the excess records, their moments and the
    plane of the cells that have one (cell c = (q - q0) * qw + p - p0 for a walk cell (p, q), frame = (p0, q0, qw)),
    read from the model, for sample stamp sid, weight times the moments' scale ws."""

    plane: np.ndarray
    excess: np.ndarray
    moments: np.ndarray
    raised: np.ndarray
    frame: tuple[int, int, int]
    model: LogOddsModel
    sid: float
    ws: float


@kernel(nogil=True, error_model="numpy", inline="always")
def raise_sample_value(rec, c, sid, y):  # pragma: no cover - compiled
    """Give cell record rec[c] the value y from sample ``sid`` under the one-value-per-sample rule: rec[c, 0] the
    stamp of the last sample that touched the cell, rec[c, 1] that sample's value so far (the max over its beams).
    Returns (first, old, new): whether y is the sample's first value for the cell, its value before (meaningless when
    first) and after. Written with selects, not branches: whether a beam of the same sample came first is
    unpredictable."""
    first = rec[c, 0] != sid
    old = rec[c, 1]
    new = y if first else max(old, y)
    rec[c, 0] = sid
    rec[c, 1] = new
    return first, old, new


@kernel(nogil=True, error_model="numpy", inline="always")
def add_sample_value(rec, c, sid, w, y):  # pragma: no cover - compiled
    """:func:`raise_sample_value` with the weighted moments sum_j w_j y_ij and sum_j w_j y_ij^2 in rec[c, 2:4]
    (float64, summed in sample order). When a later beam of the same sample raises the value, the moments are
    corrected by the difference, so each (sample, cell) contributes exactly once. A record from an earlier scan must
    be cleared first."""
    first, old, new = raise_sample_value(rec, c, sid, y)
    rec[c, 2] += w * y if first else w * (new - old)
    rec[c, 3] += w * y * y if first else w * (new * new - old * old)


@kernel(nogil=True, error_model="numpy", inline="always")
def add_sample_excess(rec, moments, c, sid, ws, d):  # pragma: no cover - compiled
    """:func:`raise_sample_value` with the excess moments D1 = sum_j w_j d_ij and D2 = sum_j w_j d_ij^2 in
    moments[c, 2:4], int64 steps of mapping.fixed_point (``moments``: ``rec`` viewed as int64; ``ws``: the sample's
    weight times the moments' scale). A later beam of the same sample that raises the value swaps the sample's old
    terms for its new ones, so the sums hold each (sample, cell)'s term exactly once, whatever the order of the beams
    and the samples. D1 and D2 are zero between scans."""
    first, old, new = raise_sample_value(rec, c, sid, d)
    moments[c, 2] += to_fixed(ws * new) - (0 if first else to_fixed(ws * old))
    moments[c, 3] += to_fixed(ws * new * new) - (0 if first else to_fixed(ws * old * old))


@kernel(nogil=True, error_model="numpy", inline="always")
def _cell_index(frame, p, q):  # pragma: no cover - compiled
    return (q - frame[1]) * frame[2] + p - frame[0]


@kernel(nogil=True, error_model="numpy", inline="always")
def _mark_free(marks, carry, p, q):  # pragma: no cover - compiled
    """A free-phase visit: the cell takes l_free, its bit in the sample's plane."""
    set_bit(marks.plane, _cell_index(marks.frame, p, q))
    return carry


@kernel(nogil=True, error_model="numpy", inline="always")
def _mark_near(marks, beam, carry, p, q, r_in, r_out):  # pragma: no cover - compiled
    """A visit near the return: the cell's bit, and its excess d over l_free kept by the per-sample rule."""
    d = segment_logodds(r_in, r_out, beam, marks.model) - marks.model.l_free
    c = _cell_index(marks.frame, p, q)
    set_bit(marks.plane, c)
    if d > 0.0:
        add_sample_excess(marks.excess, marks.moments, np.uint64(c), marks.sid, marks.ws, d)
        set_bit(marks.raised, c)
    return carry


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _plane_runs(planes, lines, window, ray_uv, runs_end, res, crossings, skip):  # pragma: no cover - compiled
    """:func:`mapping.free_runs.mark_plane_runs` into the samples pass's planes = (plane, columns, col_stride) and
    line buffer: ray_uv = (steep, line, cell) in its plane's coordinates, to just before ``runs_end`` (m), with its
    crossings of the plane's lines, its rows (columns) 1 .. skip left out; returns the runs' last cell (ix, iy).

    A call, not inlined: the pass reaches it from three places, and inlining the runs once more took accumulate_scan's
    compile from 38.6 to 51.7 s and 0.64 to 1.4 GB, with no gain. It takes the arrays it writes, not the whole
    scratch: numba hands a tuple's arrays over member by member, and with the scratch a call cost the warehouse's walk
    about a tenth of its time (docs/performance.md, "How the fusion pass is built")."""
    plane, columns, col_stride = planes
    return mark_plane_runs(plane, columns, col_stride, window, ray_uv, runs_end, res, crossings, lines, skip)


@kernel(nogil=True, error_model="numpy", inline="always")
def _scratch_plane_runs(scratch, window, ray_uv, runs_end, res, crossings, skip):  # pragma: no cover - compiled
    """:func:`_plane_runs` into the scratch's planes and line buffer."""
    planes = (scratch.plane, scratch.columns, scratch.col_stride)
    return _plane_runs(planes, scratch.lines, window, ray_uv, runs_end, res, crossings, skip)


@kernel(nogil=True, error_model="numpy", inline="always")
def _scratch_runs(scratch, window, line, first, runs_end, res, tol, skip):  # pragma: no cover - compiled
    """:func:`mapping.free_runs.mark_free_runs` into the samples pass's planes and line buffer (:func:`_plane_runs`):
    line = (x0, y0, dx, dy), from cell ``first`` (ix, iy) to just before ``runs_end`` (m), its rows (columns) 1 ..
    skip left out; returns the runs' last cell."""
    steep, line_uv, cell_uv, crossings = plane_crossings(line, first, runs_end, res, tol)
    return _scratch_plane_runs(scratch, window, (steep, line_uv, cell_uv), runs_end, res, crossings, skip)


@kernel(nogil=True, error_model="numpy", inline="always")
def _runs_start(ray, free_limit):  # pragma: no cover - compiled
    """Where a ray's free runs end (m: free_limit less JUMP_MARGIN, relative; <= 0 for no runs) and the first cell
    (ix, iy) of positive length they start from."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = ray
    first_ix, first_iy = ix, iy
    if min(t_max_x, t_max_y) <= 0.0:  # the ray starts on its cell's edge and leaves it at once
        first_ix, first_iy, _, _ = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    return just_before(free_limit), (first_ix, first_iy)


@kernel(nogil=True, error_model="numpy", inline="always")
def _free_runs(x0, y0, dx, dy, ray, free_limit, res, window, scratch, k):  # pragma: no cover - compiled
    """Mark ray k's free phase as runs (:func:`mapping.free_runs.mark_free_runs`) up to just before free_limit (m),
    its rows (columns) 1 .. SKIP left out (marked by its fans, :func:`mapping.fan_runs.fan_hulls`), and return (ray,
    r_in): the ray moved to the runs' last cell, the grid lines crossed up to it counted, and the range the walk goes
    on from. Its r_in is taken as the runs' end (:func:`segment_logodds` reads r_in only past the peak, well beyond).
    Without runs (a short free phase) the ray as it was, from 0.

    The ray's first cell and its crossings of its plane's lines are those :func:`_fan_lines` recorded for the fans
    (the same free limit, so the same runs' end; key 0 where there are no runs): its divisions are made once."""
    ints, floats = scratch.fan_ints, scratch.fan_floats
    if ints[KEY, k] == 0:
        return ray, 0.0
    runs_end = just_before(free_limit)
    steep, cell, crossings = recorded_crossings(ints, floats, k)
    line = (y0, x0, dy, dx) if steep else (x0, y0, dx, dy)
    end = _scratch_plane_runs(scratch, window, (steep, line, cell), runs_end, res, crossings, ints[SKIP, k])
    return _ray_moved_to(ray, end), runs_end


@kernel(nogil=True, error_model="numpy", inline="always")
def _ray_moved_to(ray, cell):  # pragma: no cover - compiled
    """``ray`` (as it started) moved on to the cell (ix, iy) its runs ended in, the grid lines crossed up to it
    counted from the cells' indices (a product, not a sum per line: the whole window's walk and a shard's take the
    same arithmetic)."""
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = ray
    t_max_x += max((cell[0] - ix) * step_x, 0) * t_delta_x
    t_max_y += max((cell[1] - iy) * step_y, 0) * t_delta_y
    return Ray(cell[0], cell[1], step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)


@kernel(nogil=True, error_model="numpy", inline="always")
def _owned_free_runs(x0, y0, dx, dy, ray, free_limit, res, window, tiles, scratch):  # pragma: no cover - compiled
    """A shard's :func:`_free_runs`: the ray's free phase marked as runs up to just before free_limit (m) in the
    tiles the shard owns; it jumps over the other shards' tiles (:func:`jump_over_tile`) and marks nothing there,
    so the work a ray's free phase costs divides among the shards by the tiles each owns. One stretch of runs per
    stretch of owned tiles along the ray: from the cell the ray enters the first in to just before it leaves the
    last (:func:`_close_stretch`), or to a tile corner it passes with another shard's tile beside it
    (:func:`_past_other_corner`).

    Returns (ray, r_in, tile_end) for the walk to go on from: the ray at the last cell of the whole ray's runs
    (:func:`mapping.free_runs.runs_last_cell`, wherever the free phase ends) and r_in the runs' end, as
    :func:`_free_runs` gives them (the same arithmetic, so that the walk, stepping through other shards' tiles, visits
    the cells near the return with the whole window's values), and tile_end the range (m) at which the ray leaves the
    tile the free phase ends in when the shard owns it, else 0."""
    runs_end = just_before(free_limit)
    if runs_end <= 0.0:
        return ray, 0.0, 0.0
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = ray
    if min(t_max_x, t_max_y) <= 0.0:  # the ray starts on its cell's edge and leaves it at once
        ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    first = (ix, iy)
    shift = tiles.shift
    r_in = 0.0
    stretch = (ix, iy)  # the cell the current stretch of owned tiles starts in
    last = (ix, iy)  # the last cell of the tile before this one
    mine = False  # whether the ray is in a stretch of owned tiles
    while True:  # one turn per tile the free phase crosses: (ix, iy) is the cell the ray enters it in, at r_in
        owned = tiles.owned[(iy >> shift) - tiles.ty0, (ix >> shift) - tiles.tx0]
        if owned and not mine:
            stretch = (ix, iy)
        elif mine and not owned:
            _close_stretch((x0, y0, dx, dy), stretch, last, r_in, res, tol, window, scratch)
        mine = owned
        t_exit = tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, shift)
        if t_exit >= runs_end:
            break
        ix, iy, t_max_x, t_max_y, _, _ = jump_over_tile(
            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, shift
        )
        r_in = min(t_max_x, t_max_y)
        last = (ix, iy)
        ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
        if mine and _past_other_corner(last, (ix, iy), tiles):
            _close_stretch((x0, y0, dx, dy), stretch, last, r_in, res, tol, window, scratch)
            mine = False
    # the walk goes on from the last cell of the whole ray's runs (those of a stretch from its first cell)
    if mine:
        end = _scratch_runs(scratch, window, (x0, y0, dx, dy), stretch, runs_end, res, tol, 0)
        if stretch[0] != first[0] or stretch[1] != first[1]:
            end = runs_last_cell((x0, y0, dx, dy), first, runs_end, res, tol)
        return _ray_moved_to(ray, end), runs_end, t_exit
    return _ray_moved_to(ray, runs_last_cell((x0, y0, dx, dy), first, runs_end, res, tol)), runs_end, 0.0


@kernel(nogil=True, error_model="numpy", inline="always")
def _past_other_corner(last, cell, tiles):  # pragma: no cover - compiled
    """Whether a step from cell ``last`` to ``cell`` (ix, iy) goes diagonally through a tile's corner with a tile
    the shard does not own beside it. The step is the traversal's (a corner crossed within the ray's tolerance:
    :func:`mapping.raytrace.dda_step`), but a stretch's runs follow the ray's line, and within that tolerance they may
    take a sliver of either cell beside the corner: a stretch of owned tiles ends at such a corner (its runs stop
    short of it) and the next starts beyond it, so that a shard marks its own tiles' cells only."""
    shift = tiles.shift
    tx0, ty0, tx1, ty1 = last[0] >> shift, last[1] >> shift, cell[0] >> shift, cell[1] >> shift
    if tx0 == tx1 or ty0 == ty1:
        return False
    return not (tiles.owned[ty0 - tiles.ty0, tx1 - tiles.tx0] and tiles.owned[ty1 - tiles.ty0, tx0 - tiles.tx0])


@kernel(nogil=True, error_model="numpy", inline="always")
def _close_stretch(line, stretch, last, r_next, res, tol, window, scratch):  # pragma: no cover - compiled
    """Mark a ray's cells from ``stretch`` (the cell it entered its stretch of owned tiles in) to ``last`` (the last
    cell of the stretch), line = (x0, y0, dx, dy) as for :func:`mark_free_runs`, the next tile entered at the range
    r_next (m): runs to just before r_next, and ``last`` itself (the runs stop short of a last cell shorter than
    their margin)."""
    _scratch_runs(scratch, window, line, stretch, just_before(r_next), res, tol, 0)
    set_bit(scratch.plane, (last[1] - window.iy0) * window.w + last[0] - window.ix0)


#: what :func:`owned_reach` says of a ray: it crosses none of the shard's tiles, it may cross some, it crosses only
#: the shard's tiles
REACH_NONE, REACH_SOME, REACH_ALL = 0, 1, 2
#: cells (a fraction of one) by which :func:`owned_reach` widens a ray's box before flooring its ends: the box's
#: cells come from x * (1 / res), which may differ from the walk's x / res in the last bits (by about 1e-10 cells
#: 1 000 km from the origin at 0.01 m cells)
BOX_ROUNDING = 1e-6


def owned_table(owned: np.ndarray) -> np.ndarray:
    """The summed-area table of a window's owned tiles (bool, (tiles down, tiles across)): entry [j, i] (int32,
    (tiles down + 1, tiles across + 1)) counts the owned tiles of rows < j and columns < i, so that
    :func:`owned_reach` counts a box's in four reads."""
    table = np.zeros((owned.shape[0] + 1, owned.shape[1] + 1), np.int32)
    table[1:, 1:] = owned.astype(np.int32).cumsum(axis=0).cumsum(axis=1)
    return table


@kernel(nogil=True, error_model="numpy", inline="always")
def _owned_in(owned_sum, i0, i1, j0, j1):  # pragma: no cover - compiled
    """How many tiles the shard owns among the window's tile columns i0 <= i < i1 and rows j0 <= j < j1, from their
    :func:`owned_table`: four reads."""
    return owned_sum[j1, i1] - owned_sum[j0, i1] - owned_sum[j1, i0] + owned_sum[j0, i0]


@kernel(nogil=True, error_model="numpy", inline="always")
def owned_reach(laser, heading, directions, k, stop, inv_res, tiles, owned_sum):  # pragma: no cover - compiled
    """The cheap bound that sorts a shard's rays before walking them, from the bounding box of the ray of beam k (its
    start and end cells, the end at ``stop`` m, and a cell more on every side: a ray starting on a grid line, or
    ending within rounding of one, crosses into the cell beyond), which holds every cell the ray visits: REACH_NONE
    when no tile the shard owns meets the box (the ray is skipped), REACH_ALL when the shard owns every tile that
    meets it (the ray is walked as a shard owning the whole window walks it), REACH_SOME otherwise. The box's owned
    tiles are counted from ``owned_sum`` (:func:`owned_table`): four reads whatever its size. laser, heading,
    directions: as for :func:`mapping.window_walk.beam_ray`; inv_res: 1 / the cell size (1/m).
    """
    dx, dy = beam_direction(heading[0], heading[1], directions[0][k], directions[1][k])
    xa, ya = laser[0] * inv_res, laser[1] * inv_res
    xb, yb = xa + stop * inv_res * dx, ya + stop * inv_res * dy
    return _box_reach((min(xa, xb), max(xa, xb), min(ya, yb), max(ya, yb)), 1.0 + BOX_ROUNDING, tiles, owned_sum)


@kernel(nogil=True, error_model="numpy", inline="always")
def _box_reach(box, margin, tiles, owned_sum):  # pragma: no cover - compiled
    """What the tiles say of a box of cells, box = (x_lo, x_hi, y_lo, y_hi) (cell units: x / res) widened by margin
    cells on every side: REACH_NONE when the shard owns none of the tiles it meets, REACH_ALL when it owns all of them,
    else REACH_SOME; counted from ``owned_sum`` (:func:`owned_table`) in four reads."""
    x_lo, x_hi, y_lo, y_hi = box
    shift = tiles.shift
    tx_lo = (math.floor(x_lo - margin) >> shift) - tiles.tx0
    tx_hi = (math.floor(x_hi + margin) >> shift) - tiles.tx0
    ty_lo = (math.floor(y_lo - margin) >> shift) - tiles.ty0
    ty_hi = (math.floor(y_hi + margin) >> shift) - tiles.ty0
    # (the window holds a ray's cells with a cell to spare, ray_start checks; the box is clamped to the window's tiles
    # so that no read falls outside the table, and a box clamped is not all owned)
    nty, ntx = tiles.owned.shape
    i0, i1 = max(tx_lo, 0), min(tx_hi, ntx - 1) + 1
    j0, j1 = max(ty_lo, 0), min(ty_hi, nty - 1) + 1
    owned = _owned_in(owned_sum, i0, i1, j0, j1) if i0 < i1 and j0 < j1 else 0
    if owned == 0:
        return REACH_NONE
    if owned == (tx_hi - tx_lo + 1) * (ty_hi - ty_lo + 1):
        return REACH_ALL
    return REACH_SOME


#: cells by which :func:`scan_reach` widens a beam's box beyond :func:`owned_reach`'s widening, for its own rounding:
#: a bound of the directions from the cosines and sines of the yaws' ends rather than each sample's products
SCAN_BOX_SLACK = 1e-6
#: the widest spread of the samples' yaws (rad) over which :func:`scan_reach` bounds a beam's rays at once
SCAN_YAW_SPREAD = 0.5 * math.pi


@kernel(nogil=True, error_model="numpy", inline="always")
def _cos_range(lo, hi):  # pragma: no cover - compiled
    """(min, max) of cos over the angles lo .. hi (rad, hi - lo < 2 pi), widened by a rounding's allowance."""
    c_lo, c_hi = min(math.cos(lo), math.cos(hi)), max(math.cos(lo), math.cos(hi))
    width = hi - lo
    if (0.0 - lo) % (2.0 * math.pi) <= width:  # (an angle 0 mod 2 pi inside)
        c_hi = 1.0
    if (math.pi - lo) % (2.0 * math.pi) <= width:
        c_lo = -1.0
    return c_lo - 1e-9, c_hi + 1e-9


@kernel(nogil=True, error_model="numpy", inline="always")
def _heading_angle(yaw):  # pragma: no cover - compiled
    """The angle (rad, in (-pi, pi]) of the heading (cos yaw, sin yaw) a ray of that yaw is walked along."""
    return math.atan2(math.sin(yaw), math.cos(yaw))


@kernel(nogil=True, error_model="numpy")
def scan_reach(lasers, directions, beams, inv_res, tiles, owned_sum, out):  # pragma: no cover - compiled
    """What :func:`owned_reach` says of beam k's rays under every laser pose of the scan at once, into out[k]: the
    box that holds every pose's ray box (the poses' positions, and their ends along any heading between the smallest
    and the largest yaw, each ``beams.r_stop[k]`` m on, widened as owned_reach widens a ray's and by SCAN_BOX_SLACK
    more). REACH_NONE or REACH_ALL for that box hold for each ray in it (a ray's box lies inside: none of its tiles
    owned, or all of them); REACH_SOME says to ask per ray. Every beam REACH_SOME when the yaws spread wider than
    SCAN_YAW_SPREAD. lasers (M, 3): (x m, y m, yaw rad); directions: the beams' (cosines, sines) in the laser frame;
    inv_res: 1 / the cell size (1/m).

    The yaws are taken as the angles of the headings the walk uses (cos yaw, sin yaw), in (-pi, pi]: a yaw of any
    size (1e7 rad passes the wire's bound) then bounds the rays to the last bits, where yaw + a beam's angle, or the
    yaws' differences modulo a rounded 2 pi, would lose whole cells far from the origin of angles."""
    m = lasers.shape[0]
    x_lo, x_hi = lasers[0, 0], lasers[0, 0]
    y_lo, y_hi = lasers[0, 1], lasers[0, 1]
    yaw0 = _heading_angle(lasers[0, 2])
    turn_lo = turn_hi = 0.0  # the yaws' spread about the first one (rad)
    for j in range(m):
        x_lo, x_hi = min(x_lo, lasers[j, 0]), max(x_hi, lasers[j, 0])
        y_lo, y_hi = min(y_lo, lasers[j, 1]), max(y_hi, lasers[j, 1])
        turn = (_heading_angle(lasers[j, 2]) - yaw0 + math.pi) % (2.0 * math.pi) - math.pi
        turn_lo, turn_hi = min(turn_lo, turn), max(turn_hi, turn)
    margin = 1.0 + BOX_ROUNDING + SCAN_BOX_SLACK  # (a cell, as owned_reach widens a ray's box, and the slack)
    for k in range(beams.kind.shape[0]):
        out[k] = REACH_SOME
        if turn_hi - turn_lo > SCAN_YAW_SPREAD:
            continue
        angle = yaw0 + math.atan2(directions[1][k], directions[0][k])
        c_lo, c_hi = _cos_range(angle + turn_lo, angle + turn_hi)
        s_lo, s_hi = _cos_range(angle + turn_lo - 0.5 * math.pi, angle + turn_hi - 0.5 * math.pi)  # (sin = cos - pi/2)
        stop = beams.r_stop[k]
        box = (
            min(x_lo, x_lo + stop * c_lo) * inv_res,
            max(x_hi, x_hi + stop * c_hi) * inv_res,
            min(y_lo, y_lo + stop * s_lo) * inv_res,
            max(y_hi, y_hi + stop * s_hi) * inv_res,
        )
        out[k] = _box_reach(box, margin, tiles, owned_sum)


@kernel(nogil=True, error_model="numpy", inline="always")
def _keep_ray(ints, floats, k, inside, ray, dx, dy):  # pragma: no cover - compiled
    """Keep ray k's start (:func:`mapping.window_walk.beam_ray`'s inside, ray, dx, dy) in the fan scratch's records."""
    ints[STARTED, k] = inside
    ints[RAY_IX, k], ints[RAY_IY, k], ints[RAY_STEP_X, k], ints[RAY_STEP_Y, k] = ray.ix, ray.iy, ray.step_x, ray.step_y
    floats[RAY_T_MAX_X, k], floats[RAY_T_MAX_Y, k] = ray.t_max_x, ray.t_max_y
    floats[RAY_T_DELTA_X, k], floats[RAY_T_DELTA_Y, k] = ray.t_delta_x, ray.t_delta_y
    floats[RAY_TOL, k], floats[RAY_DX, k], floats[RAY_DY, k] = ray.tol, dx, dy


@kernel(nogil=True, error_model="numpy", inline="always")
def _kept_ray(ints, floats, k):  # pragma: no cover - compiled
    """Ray k's start as :func:`_keep_ray` kept it: (inside, ray, dx, dy)."""
    ray = Ray(
        ints[RAY_IX, k],
        ints[RAY_IY, k],
        ints[RAY_STEP_X, k],
        ints[RAY_STEP_Y, k],
        floats[RAY_T_MAX_X, k],
        floats[RAY_T_MAX_Y, k],
        floats[RAY_T_DELTA_X, k],
        floats[RAY_T_DELTA_Y, k],
        floats[RAY_TOL, k],
    )
    return ints[STARTED, k] != 0, ray, floats[RAY_DX, k], floats[RAY_DY, k]


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _fan_lines(laser, heading, directions, beams, res, window, tiles, owned_sum, scratch):  # pragma: no cover
    """Record, for :func:`mapping.fan_runs.fan_hulls`, where each ray of one sample (laser pose (x m, y m, yaw rad),
    heading (cos yaw, sin yaw)) crosses the lines of the plane its free runs go into, as
    :func:`mapping.free_runs.mark_free_runs` will mark them (:func:`_free_runs`), and what the bound says of it
    (REACH_ALL where the shard owns every tile of the window; else the beam's under every sample, :func:`scan_reach`,
    and where that leaves it open the ray's own, :func:`owned_reach`), and keep each ray's start for the walk
    (:func:`_keep_ray`: a ray is started once); key 0 for a ray with no runs, or one that may cross another shard's
    tiles (a fan's run lies in its rays' runs, so a fan of rays in the shard's own tiles marks only cells of its
    own)."""
    ints, floats = scratch.fan_ints, scratch.fan_floats
    inv_res = 1.0 / res
    for k in range(beams.kind.shape[0]):
        ints[KEY, k] = 0
        beam = beam_at(beams, k)
        reach = REACH_ALL
        if not tiles.all_owned:
            reach = ints[SCAN_REACH, k]  # (scan_reach: the bound of the beam's rays under every sample at once)
            if reach == REACH_SOME:
                reach = owned_reach(laser, heading, directions, k, beam.r_stop, inv_res, tiles, owned_sum)
        ints[REACH, k] = reach
        if reach == REACH_NONE:
            continue
        inside, ray, dx, dy = beam_ray(laser, heading, directions, beam, k, res, window)
        _keep_ray(ints, floats, k, inside, ray, dx, dy)
        if not inside or reach != REACH_ALL:
            continue
        runs_end, first = _runs_start(ray, min(beam.free_until, beam.r_stop - ray.tol))
        if runs_end <= 0.0:
            continue
        steep, line, cell, crossings = plane_crossings((laser[0], laser[1], dx, dy), first, runs_end, res, ray.tol)
        record_crossings(ints, floats, k, steep, line, cell, crossings)


@kernel(nogil=True, error_model="numpy", inline="always")
def _walk_sample(laser, sid, ws, directions, beams, model, res, window, tiles, owned_sum, scratch):  # pragma: no cover
    """Walk every beam of one sample (laser pose (x m, y m, yaw rad), stamp sid, weight times the moments' scale ws)
    into its plane and the excess records.

    The rows (columns) that fans of neighbouring rays share near the laser are marked first, once a fan and row
    (:mod:`mapping.fan_runs`; :func:`_fan_lines` records where the rays cross the lines, and sorts them by the bound,
    :func:`scan_reach` and :func:`owned_reach`: a shard's fans join the rays that cross its own tiles alone), and each
    ray leaves them out of its own runs. A ray that crosses only tiles the shard owns (every ray, when it owns every
    tile of the window) has its free phase marked as runs, and the walk goes on from their last cell on the window's
    index (:func:`mapping.window_walk.index_ray`), with no ownership look-ups. A ray that crosses none is skipped. Any
    other has its free phase marked as runs in the shard's own tiles (:func:`_owned_free_runs`); the walk goes on
    as above where the rest of the ray lies in one tile the shard owns, else on the global cells, looking ownership
    up per tile."""
    heading = (math.cos(laser[2]), math.sin(laser[2]))
    records = (scratch.plane, scratch.excess, scratch.moments, scratch.raised)
    by_index = _Marks(*records, (0, 0, 1), model, sid, ws)
    by_cell = _Marks(*records, (window.ix0, window.iy0, window.w), model, sid, ws)
    every_tile, some_tiles = ownership_constants(tiles)
    # the rows that fans of neighbouring rays share, marked once a fan (mapping.fan_runs), and each ray's bound
    _fan_lines(laser, heading, directions, beams, res, window, tiles, owned_sum, scratch)
    fan_hulls(
        (scratch.plane, scratch.columns, scratch.col_stride),
        window,
        scratch.fan_ints,
        scratch.fan_floats,
        beams.kind.shape[0],
        scratch.lines[0],
    )
    for k in range(beams.kind.shape[0]):
        reach = scratch.fan_ints[REACH, k]
        if reach == REACH_NONE:
            continue  # a ray that crosses none of the shard's tiles
        beam = beam_at(beams, k)
        inside, ray, dx, dy = _kept_ray(scratch.fan_ints, scratch.fan_floats, k)  # (started by _fan_lines)
        if not inside:
            continue  # a skipped beam
        free_limit = min(beam.free_until, beam.r_stop - ray.tol)
        if reach == REACH_ALL:
            ray, r_in = _free_runs(laser[0], laser[1], dx, dy, ray, free_limit, res, window, scratch, k)
            tile_end = beam.r_stop  # (the rest of the ray lies in the shard's tiles)
        else:
            ray, r_in, tile_end = _owned_free_runs(
                laser[0], laser[1], dx, dy, ray, free_limit, res, window, tiles, scratch
            )
        if tile_end >= beam.r_stop:
            walk_ray(
                index_ray(ray, window),
                r_in,
                beam.free_until,
                beam.r_stop,
                every_tile,
                _mark_free,
                _mark_near,
                by_index,
                (beams, k),
                0,
                True,
            )
        else:  # (stepping through the other shards' tiles: its cells are a single shard's bit for bit)
            walk_ray(
                ray,
                r_in,
                beam.free_until,
                beam.r_stop,
                some_tiles,
                _mark_free,
                _mark_near,
                by_cell,
                (beams, k),
                0,
                False,
            )


@kernel(nogil=True, error_model="numpy", refcounted=False)
def accumulate_scan(
    lasers, weights, directions, beams, model, res, window, tiles, owned_sum, scratch, stamp_base, moment_scale
):  # pragma: no cover
    """One pass over all (sample, beam, cell) triples into the scratch (:func:`apply_scan` adds it into the tiles).

    lasers: (M, 3) laser poses (x m, y m, yaw rad), weights (M,); directions: the beams' (cosines, sines) in the
    laser frame; beams: a :class:`BeamTable`, model a :class:`LogOddsModel`, window a :class:`Window` (w a
    multiple of 64 cells), tiles a :class:`Tiles`, scratch a :class:`SamplesScratch`, all as plain tuples; owned_sum:
    the tiles' :func:`owned_table`; res: the cell size (m); moment_scale: the steps per unit of the excess moments
    (:func:`mapping.fixed_point.moment_scale` of the model).

    Window cell (gx, gy) is global cell (ix0 + gx, iy0 + gy); its scratch entries are at c = gy * w + gx: bit c of
    plane (the cells the current sample touched) and of listed (the cells any sample touched in this scan), both zero
    between scans; weight_sum[c] (W in int64 steps; zero between scans), excess[c] (kept by :func:`add_sample_excess`
    for d: the stamp, the current sample's largest d, D1, D2, the moments in int64 steps, zero between scans; sample
    j's stamp is stamp_base + j, so smaller stamps are from earlier scans) and bit c of raised (the cell has a record
    of this scan; zero between scans); tile_touched marks the tiles of the listed cells. W, D1 and D2 are sums of
    whole steps (:mod:`mapping.fixed_point`), the same in any order of the samples: a scan's samples may be walked in
    parts, each part into a scratch of its own, and the parts' scratches added up (:func:`merge_scan`) before the
    apply. See the module docstring.

    Each ray is walked by :func:`mapping.window_walk.walk_ray` in two phases: the free phase, cells that end before
    the beam's free_until, which take l_free without evaluating the model; then the cells up to the ray's end,
    valued by :func:`segment_logodds`. The free phase is marked as runs of cells per grid row or column (a steep
    ray's go into the column-major plane) up to just before its end (:func:`_free_runs`), by a shard that does not
    own every tile of the window in its own tiles only, skipping the rays that reach none of them and taking those
    that reach no other tile as a shard owning every tile does (:func:`_walk_sample`).
    After a sample's beams its column plane is folded into its row plane (``plane`` for the first sample of a group of
    GROUP, ``group_planes`` for the others: :func:`_in_group`), and after each group (and a last group of fewer
    samples, the planes past them clear) its planes are swept into the weight sums, sample after sample
    (:func:`_sweep_word`): a sweep over the window, whose words are mostly clear, every GROUP samples. A shard that
    does not own every tile of the window folds and sweeps only where its tiles lie (:func:`_fold_owned`,
    :func:`_sweep_owned`).
    """
    beams, model, window, tiles = BeamTable(*beams), LogOddsModel(*model), Window(*window), Tiles(*tiles)
    scratch = SamplesScratch(*scratch)
    m = lasers.shape[0]
    if not tiles.all_owned:
        scan_reach(lasers, directions, beams, 1.0 / res, tiles, owned_sum, scratch.fan_ints[SCAN_REACH])
    w0 = w1 = w2 = w3 = np.int64(0)  # the group's samples' weights in steps (0 past the last group's last sample)
    for j in range(m):
        slot = j % GROUP
        marks = _in_group(scratch, slot)
        _walk_sample(
            lasers[j],
            float(stamp_base + j),
            weights[j] * moment_scale,
            directions,
            beams,
            model,
            res,
            window,
            tiles,
            owned_sum,
            marks,
        )
        if tiles.all_owned:
            fold_columns(marks.columns, marks.col_stride, marks.plane, window.w, window.h, marks.block)
        else:
            _fold_owned(marks, window, tiles, owned_sum)
        w = to_fixed(weights[j] * WEIGHT_SCALE)
        if slot == 0:
            w0, w1, w2, w3 = w, np.int64(0), np.int64(0), np.int64(0)
        elif slot == 1:
            w1 = w
        elif slot == 2:
            w2 = w
        else:
            w3 = w
        if slot < GROUP - 1 and j + 1 < m:
            continue  # (swept with the group's next samples)
        group_weights = (w0, w1, w2, w3)
        if tiles.all_owned:
            _sweep_planes(scratch, group_weights, window, tiles)
        else:
            _sweep_owned(scratch, group_weights, window, tiles, owned_sum)
    listed_boxes(scratch.listed, window, tiles, scratch.boxes)


@kernel(nogil=True, error_model="numpy", inline="always")
def _in_group(scratch, slot):  # pragma: no cover - compiled
    """The scratch the group's sample ``slot`` walks into: ``scratch`` with its plane that slot's."""
    return SamplesScratch(
        scratch.plane if slot == 0 else scratch.group_planes[slot - 1],
        scratch.columns,
        scratch.col_stride,
        scratch.listed,
        scratch.weight_sum,
        scratch.excess,
        scratch.tile_touched,
        scratch.lines,
        scratch.block,
        scratch.counts,
        scratch.sums,
        scratch.fan_ints,
        scratch.fan_floats,
        scratch.group_planes,
        scratch.moments,
        scratch.boxes,
        scratch.raised,
    )


@kernel(nogil=True, error_model="numpy", inline="always")
def _word_origin(i, window):  # pragma: no cover - compiled
    """The global cell (ix, iy) of bit 0 of word i of a row-major plane (window.w a multiple of 64: a word lies in
    one row). One division a word, not one a cell."""
    row_words = window.w >> 6
    gy = i // row_words
    return ((i - gy * row_words) << 6) + window.ix0, gy + window.iy0


@kernel(nogil=True, error_model="numpy", inline="always")
def _touch_tiles(scratch, i, new, window, tiles):  # pragma: no cover - compiled
    """Mark in tile_touched the tiles of the cells of word i whose bit is set in ``new``: one step per tile the word
    meets (a word holds 64 cells of one row)."""
    ix0, iy = _word_origin(i, window)
    ty = (iy >> tiles.shift) - tiles.ty0
    while new != 0:
        tx = (ix0 + trailing_zeros(new)) >> tiles.shift
        scratch.tile_touched[ty, tx - tiles.tx0] = True
        past = ((tx + 1) << tiles.shift) - ix0  # the word's first cell in the next tile
        if past >= 64:
            return
        new &= ~((np.uint64(1) << np.uint64(past)) - np.uint64(1))


@kernel(nogil=True, error_model="numpy", refcounted=False)
def listed_boxes(listed, window, tiles, boxes):  # pragma: no cover - compiled
    """Widen each window tile's box (:mod:`mapping.tile_boxes`) to hold the cells set in ``listed`` (a walk's listed
    plane, once its samples are swept): a word's cells lie in one row, so one widening per tile the word's set bits
    meet. A pass of its own after the walk: the same widening in the sweep, where cells enter the listed plane, made
    the warehouse's walk 10 % slower, and marking the tiles here instead of in the sweep (:func:`_touch_tiles`, one
    such loop over a word's tiles fewer) made it 3 to 5 % slower."""
    window, tiles = Window(*window), Tiles(*tiles)
    in_tile = (1 << tiles.shift) - 1
    for i in range((window.w * window.h + 63) >> 6):
        bits = listed[i]
        if bits == 0:
            continue
        word_ix, iy = _word_origin(i, window)
        ty = (iy >> tiles.shift) - tiles.ty0
        ly = iy & in_tile
        while bits != 0:
            first = trailing_zeros(bits)
            tx = (word_ix + first) >> tiles.shift
            past = ((tx + 1) << tiles.shift) - word_ix  # the word's first cell in the next tile (> first)
            here = bits if past >= 64 else bits & ((np.uint64(1) << np.uint64(past)) - np.uint64(1))
            last = 63 - leading_zeros(here)
            widen_box(boxes, ty, tx - tiles.tx0, ly, (word_ix + first) & in_tile, ly, (word_ix + last) & in_tile)
            bits ^= here


@kernel(nogil=True, error_model="numpy", inline="always")
def _sweep_word(scratch, i, group_weights, window, tiles, counted):  # pragma: no cover - compiled
    """Add a group of samples' weights (int64 steps, group_weights[s] sample s's) to the weight sum of every cell
    word i of their planes marks (plane: sample 0's; group_planes[s - 1]: sample s's, clear past the group's last),
    sample after sample (``counted``, equal weights: the number of planes with the bit set to its count,
    :func:`_count_group`), and clear the words. A cell new to this scan (its bit clear in ``listed``) gets its bit in
    ``listed`` and its tile marked in tile_touched."""
    a = scratch.plane[i]
    b = scratch.group_planes[0, i]
    c = scratch.group_planes[1, i]
    d = scratch.group_planes[2, i]
    bits = a | b | c | d
    if bits == 0:
        return
    scratch.plane[i] = 0
    scratch.group_planes[0, i] = 0
    scratch.group_planes[1, i] = 0
    scratch.group_planes[2, i] = 0
    new = bits & ~scratch.listed[i]
    if new != 0:
        scratch.listed[i] |= new
        _touch_tiles(scratch, i, new, window, tiles)
    if counted:
        _count_group(scratch.counts, i, a, b, c, d)
        return
    base = i << 6
    _add_weight(scratch.weight_sum, base, a, group_weights[0])
    _add_weight(scratch.weight_sum, base, b, group_weights[1])
    _add_weight(scratch.weight_sum, base, c, group_weights[2])
    _add_weight(scratch.weight_sum, base, d, group_weights[3])


@kernel(nogil=True, error_model="numpy", inline="always")
def _add_weight(weight_sum, base, word, w):  # pragma: no cover - compiled
    """Add w to the weight sums of the cells base + k whose bit k is set in ``word``."""
    while word != 0:
        weight_sum[base + trailing_zeros(word)] += w
        word &= word - np.uint64(1)


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _sweep_planes(scratch, group_weights, window, tiles):  # pragma: no cover - compiled
    """:func:`_sweep_word` over a group's whole planes, word after word."""
    counted = scratch.sums.shape[0] > 0
    for i in range((window.w * window.h + 63) >> 6):
        _sweep_word(scratch, i, group_weights, window, tiles, counted)


@kernel(nogil=True, error_model="numpy", inline="always")
def _block_owned(b, k, window, tiles, owned_sum):  # pragma: no cover - compiled
    """Whether the window's 64 x 64 block of cells 64 b .. 64 b + 63 across and 64 k .. 64 k + 63 down meets a tile
    the shard owns (the tiles' :func:`owned_table`). A block starts inside the window's tiles; its end is clamped to
    them (the planes' width and height are padded to whole words)."""
    nty, ntx = tiles.owned.shape
    i0 = ((window.ix0 + 64 * b) >> tiles.shift) - tiles.tx0
    j0 = ((window.iy0 + 64 * k) >> tiles.shift) - tiles.ty0
    i1 = min(((window.ix0 + 64 * b + 63) >> tiles.shift) - tiles.tx0, ntx - 1) + 1
    j1 = min(((window.iy0 + 64 * k + 63) >> tiles.shift) - tiles.ty0, nty - 1) + 1
    return _owned_in(owned_sum, i0, i1, j0, j1) > 0


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _fold_owned(scratch, window, tiles, owned_sum):  # pragma: no cover - compiled
    """For a shard that does not own every tile of the window: fold (:func:`mapping.free_runs.fold_block`) only the
    64 x 64 blocks that meet its tiles, the rest of its column plane being clear (its walk marks its own tiles'
    cells only)."""
    row_words = window.w >> 6
    words_per_col = scratch.col_stride >> 6
    for k in range(words_per_col):  # rows 64 k .. 64 k + 63
        for b in range(row_words):  # columns 64 b .. 64 b + 63
            if _block_owned(b, k, window, tiles, owned_sum):
                fold_block(scratch.columns, words_per_col, scratch.plane, row_words, window.h, scratch.block, b, k)


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _sweep_owned(scratch, group_weights, window, tiles, owned_sum):  # pragma: no cover - compiled
    """For a shard that does not own every tile of the window: sweep (:func:`_sweep_word`) a group's planes in the
    64 x 64 blocks that meet its tiles only, block after block."""
    counted = scratch.sums.shape[0] > 0
    row_words = window.w >> 6
    for k in range(scratch.col_stride >> 6):  # rows 64 k .. 64 k + 63
        for b in range(row_words):  # columns 64 b .. 64 b + 63
            if _block_owned(b, k, window, tiles, owned_sum):
                for row in range(64 * k, min(64 * k + 64, window.h)):
                    _sweep_word(scratch, row * row_words + b, group_weights, window, tiles, counted)


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_group(counts, i, a, b, c, d):  # pragma: no cover - compiled
    """Add to the bit-sliced counts of the cells of word i the number of the words a, b, c, d with its bit set (0 to
    4): that number's binary digits per bit (carry-save adders), added level by level from level 0 with a ripple
    carry; a level whose digit and carry are both clear is left alone (samples that agree leave the low digits
    clear)."""
    s1 = a ^ b
    s2 = c ^ d
    c1 = a & b
    c2 = c & d
    c3 = s1 & s2
    digit0 = s1 ^ s2
    digit1 = c1 ^ c2 ^ c3
    digit2 = c1 & c2  # (c3 needs a ^ b and c ^ d set, so c1 and c2 clear: it carries nothing)
    carry = _add_digit(counts, i, 0, digit0, np.uint64(0))
    carry = _add_digit(counts, i, 1, digit1, carry)
    carry = _add_digit(counts, i, 2, digit2, carry)
    if carry != 0:
        _carry_from(counts, i, carry, 3)


@kernel(nogil=True, error_model="numpy", inline="always")
def _add_digit(counts, i, level, digit, carry):  # pragma: no cover - compiled
    """Add the bits of ``digit`` and ``carry`` to level ``level`` of word i's bit-sliced counts (a full adder per
    bit); the carry into the next level. Left alone when both are clear."""
    if digit | carry == 0:
        return carry
    held = counts[level, i]
    counts[level, i] = held ^ digit ^ carry
    return (held & digit) | (carry & (held ^ digit))


@kernel(nogil=True, error_model="numpy", inline="always")
def _carry_from(counts, i, carry, start):  # pragma: no cover - compiled
    """Add the bits of ``carry`` to the bit-sliced counts of word i at level ``start``: a ripple carry up the levels,
    which ends where the carry clears (COUNT_LEVELS bounds it: no cell is counted more than 2**COUNT_LEVELS - 1
    times)."""
    for level in range(start, COUNT_LEVELS):
        held = counts[level, i]
        counts[level, i] = held ^ carry
        carry &= held
        if carry == 0:
            return


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_of(counts, k, levels):  # pragma: no cover - compiled
    """The count of cell k (0 .. 63) of a word from the word's bit-sliced counts (their ``levels`` lowest levels)."""
    at = np.uint64(k)
    n = np.uint64(0)
    for level in range(levels):
        n |= ((counts[level] >> at) & np.uint64(1)) << np.uint64(level)
    return n


@kernel(nogil=True, error_model="numpy", inline="always")
def _counts_in_bytes(held, levels, bits):  # pragma: no cover - compiled
    """The counts of a word's cells (its bit-sliced counts in held[:levels], levels <= 8) as bytes, eight cells a
    uint64 in held[COUNT_LEVELS + j] for cells 8 j .. 8 j + 7 (cell k's count: :func:`_byte_count`), for the bytes
    of ``bits`` (the cells to read) that are not clear: a table read a level and byte rather than a level a cell."""
    for j in range(8):
        at = np.uint64(8 * j)
        if (bits >> at) & np.uint64(0xFF) == 0:
            continue
        lanes = np.uint64(0)
        for level in range(levels):
            lanes |= BYTE_SPREAD[(held[level] >> at) & np.uint64(0xFF)] << np.uint64(level)
        held[COUNT_LEVELS + j] = lanes


@kernel(nogil=True, error_model="numpy", inline="always")
def _byte_count(held, k):  # pragma: no cover - compiled
    """The count of cell k (0 .. 63) of a word that :func:`_counts_in_bytes` put in bytes."""
    return (held[COUNT_LEVELS + (k >> 3)] >> np.uint64((k & 7) << 3)) & np.uint64(0xFF)


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_levels(sums):  # pragma: no cover - compiled
    """The counts' levels in use: those of the largest count, len(sums) - 1 (0 when the weights are summed)."""
    levels = 0
    while sums.shape[0] > 0 and (1 << levels) < sums.shape[0]:
        levels += 1
    return levels


@kernel(nogil=True, error_model="numpy", refcounted=False)
def merge_scan(into, part, words):  # pragma: no cover - compiled
    """Add a part of a scan's samples, walked by :func:`accumulate_scan` into scratch ``part``, to another part walked
    into scratch ``into`` (the same window, beams and weight table): the listed cells, the counts (a bit-sliced add)
    or weight sums, the excess moments and the raised cells. All are whole numbers (:mod:`mapping.fixed_point`), so
    ``into`` then holds what walking both parts' samples into it would have given, whatever the parts; the caller ors
    the parts' tile_touched. Clears what it read of ``part`` (as :func:`apply_scan` does), word after word of part's
    listed plane, from word words[0] to words[1] - 1 (64 cells a word: bands of words may be merged on different
    threads at once)."""
    into, part = SamplesScratch(*into), SamplesScratch(*part)
    counted = into.sums.shape[0] > 0
    count_levels = _count_levels(into.sums)
    for i in range(words[0], words[1]):
        bits = part.listed[i]
        if bits == 0:
            continue
        part.listed[i] = 0
        into.listed[i] |= bits
        raised = part.raised[i]
        part.raised[i] = 0
        into.raised[i] |= raised
        if counted:
            carry = np.uint64(0)
            for level in range(count_levels):  # (no count passes len(sums) - 1: no carry out of the top level)
                carry = _add_digit(into.counts, i, level, part.counts[level, i], carry)
                part.counts[level, i] = 0
        base = i << 6
        if not counted:
            while bits != 0:
                c = base + trailing_zeros(bits)
                bits &= bits - np.uint64(1)
                into.weight_sum[c] += part.weight_sum[c]
                part.weight_sum[c] = 0
        while raised != 0:  # (the cells with moments only)
            c = base + trailing_zeros(raised)
            raised &= raised - np.uint64(1)
            into.moments[c, 2] += part.moments[c, 2]
            into.moments[c, 3] += part.moments[c, 3]
            part.moments[c, 2] = 0
            part.moments[c, 3] = 0


@kernel(nogil=True, error_model="numpy", refcounted=False)
def apply_scan(
    scratch, window, tiles, slot_map, layers, levels, moment_scale, words, held
):  # pragma: no cover - compiled
    """Add the scan's weighted mean to each touched cell (clamped to [l_min, l_max]) and its spread to the variance
    layer, from the moments l_free W + D1 and l_free^2 W + 2 l_free D1 + D2 (W: the cell's weight sum, or with equal
    weights the sums' entry of its count; D1 and D2 for the cells raised in this scan); clear the cells' listed and
    raised bits, weight sums or counts and moments for the next scan. Returns the number of cells touched.

    The cells are taken in memory order, word after word of the listed plane: each cell's update is its own, so the
    order changes nothing in the map, and the scratch and the tiles are read in the order they lie (a list of the
    cells in the order the samples first touched them made this pass 2.3 times as slow on the warehouse).

    scratch: the :class:`SamplesScratch` of :func:`accumulate_scan`, window and tiles as there (plain tuples);
    slot_map: the grid slot of each tile of the window; layers: the grid's (logodds, variance, observed, changed);
    levels:
    the model's (l_free, l_min, l_max); moment_scale: as for :func:`accumulate_scan`; words: the scratch words
    (64 cells each) words[0] .. words[1] - 1 to apply (bands of words may be applied on different threads at once:
    they hold different cells); held: APPLY_HELD uint64 of room for a word's counts (one per thread), read as bytes
    (:func:`_counts_in_bytes`) when they have at most 8 levels (counts below 256). W, D1 and D2 are taken from their
    int64 steps, each rounded once to float64."""
    scratch, window, tiles = SamplesScratch(*scratch), Window(*window), Tiles(*tiles)
    weight_sum, moments, sums = scratch.weight_sum, scratch.moments, scratch.sums
    steps = (1.0 / WEIGHT_SCALE, 1.0 / moment_scale)  # (the steps' sizes, powers of two: exact)
    counted = sums.shape[0] > 0
    count_levels = _count_levels(sums)
    in_bytes = count_levels <= 8
    counting = (counted, in_bytes, count_levels)
    in_tile = (1 << tiles.shift) - 1
    n_scan = 0
    for i in range(words[0], words[1]):
        bits = scratch.listed[i]
        if bits == 0:
            continue
        scratch.listed[i] = 0
        raised = scratch.raised[i]
        scratch.raised[i] = 0
        word_ix, iy = _word_origin(i, window)
        ty = (iy >> tiles.shift) - tiles.ty0
        ly = iy & in_tile
        base = i << 6
        # (held: the word's counts, read once and cleared for the next scan, then read per cell)
        if counted:
            for level in range(count_levels):
                held[level] = scratch.counts[level, i]
                scratch.counts[level, i] = 0
            if in_bytes:
                _counts_in_bytes(held, count_levels, bits)
        cells = (held, raised, base, weight_sum, moments, sums)
        if bits == ALL_BITS and (word_ix >> tiles.shift) == ((word_ix + 63) >> tiles.shift):
            # (a word whose 64 cells are all listed and lie in one tile, as most are: a plain loop over them)
            slot = slot_map[ty, (word_ix >> tiles.shift) - tiles.tx0]
            at = (slot, ly, word_ix & in_tile)
            for k in range(64):
                _apply_cell(cells, k, layers, (at[0], at[1], at[2] + k), steps, levels, counting)
            n_scan += 64
            continue
        while bits != 0:
            k = trailing_zeros(bits)
            bits &= bits - np.uint64(1)
            ix = word_ix + k
            slot = slot_map[ty, (ix >> tiles.shift) - tiles.tx0]
            _apply_cell(cells, k, layers, (slot, ly, ix & in_tile), steps, levels, counting)
            n_scan += 1
    return n_scan


@kernel(nogil=True, error_model="numpy", inline="always")
def _apply_cell(cells, k, layers, at, steps, levels, counting):  # pragma: no cover - compiled
    """:func:`apply_scan`'s update of cell k of a word: its weighted mean added to the tile's log-odds at ``at``
    (slot, row, column; clamped to [l_min, l_max]), its spread to the variance, the cell observed and, in a grid that
    tracks them, marked changed where a value changed (layers: the grid's logodds, variance, observed, changed); its
    weight sum, or its count's entry of the sums, and its moments (read and cleared where the word's raised bits say
    it has some). cells: the word's (held counts, raised bits, first cell, weight_sum, moments, sums); steps: the
    sizes of the weight and moment steps; levels: the model's (l_free, l_min, l_max); counting: (counted, in_bytes,
    count_levels) as the apply reads the counts."""
    held, raised, base, weight_sum, moments, sums = cells
    l_free, l_min, l_max = levels
    counted, in_bytes, count_levels = counting
    c = base + k
    if counted:
        n = _byte_count(held, k) if in_bytes else _count_of(held, k, count_levels)
        moment1 = l_free * sums[n]
    else:
        moment1 = l_free * (weight_sum[c] * steps[0])
        weight_sum[c] = 0
    moment2 = l_free * moment1
    if (raised >> np.uint64(k)) & np.uint64(1):
        d1 = moments[c, 2] * steps[1]
        moment1 += d1
        moment2 += 2.0 * l_free * d1 + moments[c, 3] * steps[1]
        moments[c, 2] = 0
        moments[c, 3] = 0
    spread = moment2 - moment1 * moment1
    if spread < 0.0:
        spread = 0.0
    update_cell(layers, at, moment1, spread, l_min, l_max)
