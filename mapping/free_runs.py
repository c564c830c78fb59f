"""A ray's free stretch marked as runs of cells in one-bit-per-cell planes, with no steps from cell to cell.

The cells a ray crosses within one grid row are a contiguous run of columns, from the column where it enters the
row to the column where it leaves it, and likewise within one grid column. Both ends come straight from the ray's
line at the row's (column's) edges, so a run costs a few independent operations however many cells it holds,
where the traversal of :mod:`mapping.raytrace` takes one dependent step per cell (docs/performance.md). A shallow
ray (|dx| >= |dy|) is marked per row in the row-major plane, a steep one per column in the column-major plane;
each run is then one or two word ORs. The runs give the cells the traversal visits, under its corner rule: where
the ray crosses a row (column) edge within the ray's corner tolerance of a column (row) edge, it passes
diagonally through the corner and neither cell beside the corner is marked.

The row-major plane covers the scan's window (mapping.window_walk): cell c = gy * win_w + gx is bit c % 64 of
word c // 64. The column-major plane holds cell (gx, gy) at bit gx * col_stride + gy, col_stride a multiple of
64 (a word belongs to one column); :func:`fold_columns` moves its bits into the row-major plane by 64 x 64 bit
transposes, for which the window's width is a multiple of 64 too. Marking is idempotent, so the runs of one pose
sample's beams may overlap.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel

ALL_BITS = np.uint64(0xFFFFFFFFFFFFFFFF)


@kernel(nogil=True, error_model="numpy", inline="always")
def set_bit(plane, c):  # pragma: no cover - compiled
    """Mark cell c in a plane."""
    plane[np.uint64(c >> 6)] |= np.uint64(1) << np.uint64(c & 63)


@kernel(nogil=True, error_model="numpy", inline="always")
def set_run(plane, c_lo, c_hi):  # pragma: no cover - compiled
    """Mark bits c_lo..c_hi (inclusive, c_lo <= c_hi) of a plane. Without a branch on whether the run ends in
    the word it starts in (unpredictable): both end words are ORed, with the other end's bits when they are one."""
    w_lo = np.uint64(c_lo >> 6)  # unsigned indices: no test for a negative index per access
    w_hi = np.uint64(c_hi >> 6)
    lo_bits = ALL_BITS << np.uint64(c_lo & 63)
    hi_bits = ALL_BITS >> np.uint64(63 - (c_hi & 63))
    one_word = w_lo == w_hi
    plane[w_lo] |= lo_bits & (hi_bits if one_word else ALL_BITS)
    plane[w_hi] |= hi_bits & (lo_bits if one_word else ALL_BITS)
    for w in range((c_lo >> 6) + 1, c_hi >> 6):
        plane[np.uint64(w)] = ALL_BITS


@kernel(nogil=True, error_model="numpy", inline="always")
def set_short_run(plane, c_lo, c_hi):  # pragma: no cover - compiled
    """:func:`set_run` for the runs of a ray's own rows, which mostly lie in one word (a few cells a row beyond the
    fans, :mod:`mapping.fan_runs`): a branch on it, which those runs predict, and then one OR where set_run makes two
    to the same word, the second waiting on the first's store: about 5 % of the warehouse's walk (docs/performance.md,
    "How the fusion pass is built"). The fans' runs, long, keep set_run: whether one ends in its first word does not
    repeat from run to run."""
    if c_lo >> 6 == c_hi >> 6:
        plane[np.uint64(c_lo >> 6)] |= (ALL_BITS << np.uint64(c_lo & 63)) & (ALL_BITS >> np.uint64(63 - (c_hi & 63)))
    else:
        set_run(plane, c_lo, c_hi)


@kernel(nogil=True, error_model="numpy", inline="always")
def run_lines(line, cell, r_end, res, tol):  # pragma: no cover - compiled
    """Where a ray crosses the lines of constant v, as :func:`_mark_runs` marks its runs: line = (u0, v0, du, dv) (m,
    |du| >= |dv|), from cell = (iu, iv), its first cell of positive length, up to the range r_end (m); tol its corner
    tolerance (m). Returns (v_step, tol_u, n_lines, edge0, edge_step): the direction it crosses the lines in (+1 or -1),
    the corner tolerance along u in grid units, how many lines it crosses after its first row, and u (grid units)
    where it leaves its k-th row, edge0 + k * edge_step, for k = 0 .. n_lines - 1.

    The v lines are crossed where the traversal crosses them: at the ranges it computes (in m, from the range to the
    first, :func:`mapping.raytrace.dda_start`, in steps of res / |dv|). So the two agree on the row of every cell even
    for a ray that runs along a grid line within rounding, where a crossing moves by decimetres with the last bit of
    v0."""
    u0, v0, du, dv = line
    iv = cell[1]
    v_step, exit_edge = (1, 1) if dv > 0.0 else (-1, 0)  # line v is left at its edge v + exit_edge
    per_cell = 1.0 / res
    tol_u = tol * abs(du) * per_cell  # the corner tolerance along u, in grid units
    n_lines = 0  # the lines after the first
    edge0 = 0.0  # u where the ray leaves its first line
    slope = 0.0
    if dv != 0.0:
        t_first = ((iv + exit_edge) * res - v0) / dv  # the range to the first line crossed
        if r_end > t_first:
            n_lines = math.ceil((r_end - t_first) * abs(dv) * per_cell)
        slope = du / dv
        edge0 = (u0 + t_first * du) * per_cell
    return v_step, tol_u, n_lines, edge0, v_step * slope


@kernel(nogil=True, error_model="numpy", inline="always")
def line_cells(edge, tol_u, forward):  # pragma: no cover - compiled
    """(exit, entry): the last cell (u) of the row a ray leaves at a line it crosses at u = edge (grid units) and the
    first of the row it enters, ``forward`` for du > 0, tol_u its corner tolerance along u: at a corner within tol_u
    it passes diagonally, and neither cell beside the corner is either."""
    if forward:
        return math.ceil(edge - tol_u) - 1, math.floor(edge + tol_u)
    return math.floor(edge + tol_u), math.ceil(edge - tol_u) - 1


@kernel(nogil=True, error_model="numpy", inline="always")
def row_run(edge0, edge_step, k, tol_u, forward):  # pragma: no cover - compiled
    """The run (lo, hi) of u cells a ray marks in its k-th row, 1 <= k < its n_lines (:func:`run_lines`), as
    :func:`_mark_runs` marks it: from the cell it enters the row in, past line k - 1, to the cell it leaves it from,
    at line k; ``forward``: du > 0."""
    _, entry = line_cells(edge0 + (k - 1) * edge_step, tol_u, forward)
    exit_cell, _ = line_cells(edge0 + k * edge_step, tol_u, forward)
    if forward:
        return entry, max(exit_cell, entry)
    return min(exit_cell, entry), entry


@kernel(nogil=True, error_model="numpy", inline="always")
def run_end_col(end_u, col, forward):  # pragma: no cover - compiled
    """The last cell (u) of a ray's runs, its last row entered at ``col`` and the runs' end at u = end_u (grid units):
    the cell the ray is in just before the end, and at least the row's entry cell; ``forward``: du > 0."""
    if forward:
        return max(math.ceil(end_u) - 1, col)
    return min(math.floor(end_u), col)


@kernel(nogil=True, error_model="numpy", inline="always")
def runs_last_cell(line, cell, r_end, res, tol):  # pragma: no cover - compiled
    """The last cell (ix, iy) that :func:`mark_free_runs` marks for the ray line = (x0, y0, dx, dy) from its first
    cell ``cell`` to r_end (m), tol its corner tolerance (m), found with the same arithmetic and nothing marked."""
    steep, line_uv, cell_uv, crossings = plane_crossings(line, cell, r_end, res, tol)
    u0, _, du, _ = line_uv
    v_step, tol_u, n_lines, edge0, edge_step = crossings
    forward = du > 0.0
    col = cell_uv[0] if n_lines == 0 else line_cells(edge0 + (n_lines - 1) * edge_step, tol_u, forward)[1]
    u = run_end_col((u0 + r_end * du) * (1.0 / res), col, forward)
    v = cell_uv[1] + n_lines * v_step
    return (v, u) if steep else (u, v)


@kernel(nogil=True, error_model="numpy", inline="always")
def _mark_runs(plane, stride, win_u0, win_v0, line, cell, r_end, res, crossings, lines, skip):  # pragma: no cover
    """Mark, one run per line of constant v, the cells a ray crosses from (u0, v0) (m) along the unit direction
    (du, dv), line = (u0, v0, du, dv) with |du| >= |dv|, up to the range r_end (m), in the plane that holds cell
    (u, v) at bit (v - win_v0) * stride + u - win_u0; its rows 1 .. skip are left out (marked elsewhere:
    :mod:`mapping.fan_runs`).

    cell = (iu, iv) is the ray's first cell of positive length; res is the cell size (m); crossings are where it
    crosses the lines, :func:`run_lines` of (line, cell, r_end, res, its corner tolerance); lines (int64, (2, n)) is
    scratch for the lines' exit and entry cells (as many as the window has lines). The last cell, returned as (u,
    v), is the one the ray is in just before the end point. A line the ray crosses holds at least its entry cell
    (rounding may put the exit before it)."""
    u0, _, du, _ = line
    iu, iv = cell
    exits, entries = lines[0], lines[1]
    v_step, tol_u, n_lines, edge0, edge_step = crossings
    end_u = (u0 + r_end * du) * (1.0 / res)
    base = (iv - win_v0) * stride - win_u0
    base_step = v_step * stride
    col = iu
    # first the cells at the exit edges needed (line 0 and lines skip .. n_lines - 1: a loop with no branch and no
    # carried state, it vectorises; its indices unsigned, since numba tests a signed one for a negative value, and
    # with skip not a constant that test kept the loop scalar), then the runs, each from the cell the line is entered
    # at to its exit cell
    if du > 0.0:
        for k in range(skip, n_lines):
            exits[np.uint64(k)], entries[np.uint64(k)] = line_cells(edge0 + k * edge_step, tol_u, True)
        if n_lines > 0:
            exits[0], _ = line_cells(edge0, tol_u, True)
            set_short_run(plane, base + col, base + max(exits[0], col))
            col = entries[np.uint64(skip)]
            base += (skip + 1) * base_step
        for k in range(skip + 1, n_lines):
            set_short_run(plane, base + col, base + max(exits[np.uint64(k)], col))
            col = entries[np.uint64(k)]
            base += base_step
        end_col = run_end_col(end_u, col, True)
        set_short_run(plane, base + col, base + end_col)
    else:
        for k in range(skip, n_lines):
            exits[np.uint64(k)], entries[np.uint64(k)] = line_cells(edge0 + k * edge_step, tol_u, False)
        if n_lines > 0:
            exits[0], _ = line_cells(edge0, tol_u, False)
            set_short_run(plane, base + min(exits[0], col), base + col)
            col = entries[np.uint64(skip)]
            base += (skip + 1) * base_step
        for k in range(skip + 1, n_lines):
            set_short_run(plane, base + min(exits[np.uint64(k)], col), base + col)
            col = entries[np.uint64(k)]
            base += base_step
        end_col = run_end_col(end_u, col, False)
        set_short_run(plane, base + end_col, base + col)
    return end_col, iv + n_lines * v_step


@kernel(nogil=True, error_model="numpy", inline="always")
def plane_coordinates(line, cell):  # pragma: no cover - compiled
    """(steep, line, cell) of a ray, line = (x0, y0, dx, dy) from its first cell (ix, iy), in the coordinates (u, v)
    of the plane its runs go into: a shallow ray (|dx| >= |dy|) the row-major plane's, as it is; a steep one the
    column-major plane's, x and y swapped."""
    x0, y0, dx, dy = line
    if abs(dx) >= abs(dy):
        return False, line, cell
    return True, (y0, x0, dy, dx), (cell[1], cell[0])


@kernel(nogil=True, error_model="numpy", inline="always")
def mark_free_runs(rows, columns, col_stride, window, line, cell, r_end, res, tol, lines, skip=0):  # pragma: no cover
    """Mark the cells the ray from (x0, y0) (m, map frame) along the unit direction (dx, dy), line = (x0, y0, dx,
    dy), crosses before r_end (m): the cells :func:`mapping.raytrace.trace_ray` visits with r_in < r_end, give or
    take the one holding r_end. Returns the last cell marked (ix, iy): the one the ray is in just before r_end. A
    shallow ray goes into the row-major plane ``rows`` of the :class:`mapping.window_walk.Window`, a steep one into the
    column-major plane ``columns`` (module docstring).

    cell = (ix, iy) is the ray's first cell of positive length (the traversal's start cell, or its second when
    the ray starts on the start cell's edge and leaves it at once); tol is the ray's corner tolerance (m,
    :func:`mapping.raytrace.corner_tol`), tol |dx| / res across columns and tol |dy| / res across rows in grid
    units. Every cell must lie in the window (ray_start checks the end cells). lines (int64, (2, n)) is scratch
    for n = max(w, window height) values. The ray's rows (columns, for a steep ray) 1 .. skip are left out: marked by
    :mod:`mapping.fan_runs` with its neighbours'.
    """
    steep, line_uv, cell_uv, crossings = plane_crossings(line, cell, r_end, res, tol)
    ray_uv = (steep, line_uv, cell_uv)
    return mark_plane_runs(rows, columns, col_stride, window, ray_uv, r_end, res, crossings, lines, skip)


@kernel(nogil=True, error_model="numpy", inline="always")
def plane_crossings(line, cell, r_end, res, tol):  # pragma: no cover - compiled
    """(steep, line, cell, crossings) of a ray, line = (x0, y0, dx, dy) from its first cell (ix, iy) to the range
    r_end (m), tol its corner tolerance (m): its plane and its line and cell in that plane's coordinates
    (:func:`plane_coordinates`), and where it crosses the plane's lines (:func:`run_lines`)."""
    steep, line_uv, cell_uv = plane_coordinates(line, cell)
    return steep, line_uv, cell_uv, run_lines(line_uv, cell_uv, r_end, res, tol)


@kernel(nogil=True, error_model="numpy", inline="always")
def mark_plane_runs(rows, columns, col_stride, window, ray_uv, r_end, res, crossings, lines, skip):  # pragma: no cover
    """:func:`mark_free_runs` for a ray already in its plane's coordinates, ray_uv = (steep, line, cell) as
    :func:`plane_coordinates` gives them, with its crossings of the plane's lines as :func:`run_lines` gives them
    (:func:`plane_crossings`; mapping.samples_pass keeps them from its fans' records, so that a ray's divisions are
    made once). Returns the last cell marked, (ix, iy)."""
    steep, line, cell = ray_uv
    if not steep:
        return _mark_runs(rows, window.w, window.ix0, window.iy0, line, cell, r_end, res, crossings, lines, skip)
    last_iy, last_ix = _mark_runs(
        columns, col_stride, window.iy0, window.ix0, line, cell, r_end, res, crossings, lines, skip
    )
    return last_ix, last_iy


@kernel(nogil=True, error_model="numpy", inline="always")
def transpose64(block):  # pragma: no cover - compiled
    """Transpose a 64 x 64 bit matrix in place: bit b of block[i] becomes bit i of block[b]. Six rounds, each
    swapping the off-diagonal halves of every 2w x 2w sub-block (w = 32, 16, ..., 1) with shifts and masks."""
    _transpose_round(block, 32, np.uint64(0x00000000FFFFFFFF))
    _transpose_round(block, 16, np.uint64(0x0000FFFF0000FFFF))
    _transpose_round(block, 8, np.uint64(0x00FF00FF00FF00FF))
    _transpose_round(block, 4, np.uint64(0x0F0F0F0F0F0F0F0F))
    _transpose_round(block, 2, np.uint64(0x3333333333333333))
    _transpose_round(block, 1, np.uint64(0x5555555555555555))


@kernel(nogil=True, error_model="numpy", inline="always")
def _transpose_round(block, width, mask):  # pragma: no cover - compiled
    """One round of :func:`transpose64`: swap the off-diagonal width x width halves of every 2 width x 2 width
    sub-block (``width`` a constant where it is inlined, so that the inner loop over a group's rows vectorises)."""
    shift = np.uint64(width)
    for group in range(0, 64, 2 * width):
        for k in range(group, group + width):
            swapped = ((block[k] >> shift) ^ block[k + width]) & mask
            block[k + width] ^= swapped
            block[k] ^= swapped << shift


@kernel(nogil=True, error_model="numpy", inline="always")
def fold_block(columns, words_per_col, rows, row_words, win_h, block, b, k):  # pragma: no cover - compiled
    """Move the bits of the column-major plane's 64 x 64 block of columns 64 b .. 64 b + 63 and rows 64 k .. 64 k + 63
    into the row-major plane and clear them: the 64 columns' words, transposed, are the 64 rows' words (see
    :func:`fold_columns`)."""
    any_bits = np.uint64(0)
    for i in range(64):
        word = columns[(64 * b + i) * words_per_col + k]
        block[i] = word
        any_bits |= word
    if any_bits == 0:
        return
    for i in range(64):
        columns[(64 * b + i) * words_per_col + k] = 0
    transpose64(block)
    for i in range(min(64, win_h - 64 * k)):
        rows[(64 * k + i) * row_words + b] |= block[i]


@kernel(nogil=True, error_model="numpy")
def fold_columns(columns, col_stride, rows, win_w, win_h, block):  # pragma: no cover - compiled
    """Move every bit of the column-major plane into the row-major one and clear it, 64 x 64 cells at a time
    (:func:`fold_block`). win_w (cells) must be a multiple of 64, so that a row's 64-cell blocks are words of the
    row-major plane; block is scratch for 64 words."""
    words_per_col = col_stride >> 6
    row_words = win_w >> 6
    for b in range(row_words):  # columns 64 b .. 64 b + 63
        for k in range(words_per_col):  # rows 64 k .. 64 k + 63
            fold_block(columns, words_per_col, rows, row_words, win_h, block, b, k)
