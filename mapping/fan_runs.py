"""A pose sample's free space near the laser marked row by row for fans of neighbouring rays, not ray by ray.

Near the laser, neighbouring beams of one pose sample pass less than a cell apart, so within a grid row the runs
their free phases mark (:mod:`mapping.free_runs`) overlap or touch, and the cells the whole fan marks in that row
are one run: from the lowest cell of its outermost rays' runs to the highest. :func:`fan_hulls` marks that run once
per row for the fan instead of once per ray, and each ray then marks only the rows no fan covered for it (its first
row and the rows beyond its fans: ``skip`` of :func:`mapping.free_runs.mark_free_runs`). The planes it leaves are
the same bit for bit as the rays' own runs (``tests/test_fan_runs.py``).

**When a fan's runs join.** Two rays A and B of a sample that mark the same plane (both shallow, or both steep),
cross the lines of constant v in the same direction and start in the same cell leave their k-th row at u = e_A(k)
and e_B(k) = edge0 + k * edge_step (grid units, :func:`mapping.free_runs.run_lines`). Row k >= 1 of a ray is marked
from floor(e(k - 1) + tol) to ceil(e(k) - tol) - 1 (going up in u; mirrored going down), tol its corner tolerance
along u. With A the ray whose run lies lower in u, B's run starts at most one cell past A's end when
e_B(k - 1) + tol_B <= e_A(k) - tol_A, that is when

    |e_B(k - 1) - e_A(k - 1)| <= min(|edge_step_A|, |edge_step_B|) - tol_A - tol_B

(floor(x) <= ceil(y) for x <= y; either ray's step bounds A's). Rays from one point spread linearly:
|e_B(j) - e_A(j)| <= |e_B(0) - e_A(0)| + j |edge_step_B - edge_step_A|, so the condition holds for every row up to
a last one, :func:`_link_rows`, taken FAN_MARGIN short (the edges' rounding is far smaller) and no further than
either ray's full rows (rows 1 .. n_lines - 1: the last row ends at the free phase's end, not at a line). Two
neighbouring beams joined that way are a link; a run of links is a fan, and in each row the rays' runs are ordered
by their edges, so the fan's run is spanned by its two outermost rays' runs (:func:`mapping.free_runs.row_run`, the
same arithmetic as the rays' own). Its outermost rays are its end rays while its beams turn one way (every scan of
angle_min + i * angle_increment); a link whose beams turn the other way from the link before it is not made
(:func:`_link_turn`: beam angles in any order, or repeated, give the rays' own cells).

Nearer than about res / dtheta (11 m for 0.25 deg beams and 0.05 m cells, less for rays along a diagonal) the
neighbouring beams that reach past a row are joined in it; a shorter beam between them breaks the fan there, and
farther out the links break and each ray marks its own rows.
"""

from __future__ import annotations

import numpy as np

from mapping.free_runs import row_run, set_run
from mapping.jit import kernel

#: grid units (cells) by which a link's joining condition is taken short: the edges' rounding (about 1e-12 cells
#: at 1 000 km from the origin) is far smaller
FAN_MARGIN = 1e-6

#: rows of the fan scratch's int64 records (one column per beam): the ray's key (0: no runs to share; else which
#: plane and direction), its first cell (iu, iv) in plane coordinates, its lines (n_lines), the rows its link to the
#: next beam joins, the rows of it the fans mark (its ``skip``), what the walk's bound says of it (REACH of
#: mapping.samples_pass: a shard's fans join only rays that cross its own tiles alone); then :func:`fan_hulls`'s
#: bookkeeping: the next link joining as far, a run of joined links' first link (kept at its last) and last link
#: (kept at its first), and the fans (their first links) with each one's place in that list; then the ray's start
#: for the walk (mapping.samples_pass keeps it, so that a ray is started once): whether it started inside the window,
#: its cell and steps (mapping.window_walk.Ray); and what the walk's bound says of the beam's rays under every sample
#: of the scan at once (mapping.samples_pass.scan_reach)
KEY, IU, IV, LINES, LINK, SKIP, REACH, NEXT, RUN_LEFT, RUN_RIGHT, FANS, FAN_AT = range(12)
STARTED, RAY_IX, RAY_IY, RAY_STEP_X, RAY_STEP_Y = range(12, 17)
SCAN_REACH = 17
FAN_INTS = 18
#: rows of its float64 records: edge0, edge_step, tol (grid units; mapping.free_runs.run_lines); then the ray's start:
#: its traversal's ranges (m), corner tolerance (m) and unit direction (dx, dy)
EDGE0, EDGE_STEP, TOL = range(3)
RAY_T_MAX_X, RAY_T_MAX_Y, RAY_T_DELTA_X, RAY_T_DELTA_Y, RAY_TOL, RAY_DX, RAY_DY = range(3, 10)
FAN_FLOATS = 10


def fan_scratch(beams: int) -> tuple[np.ndarray, np.ndarray]:
    """The fan scratch for scans of ``beams`` beams: (int64 (FAN_INTS, beams), float64 (FAN_FLOATS, beams))."""
    return np.zeros((FAN_INTS, beams), np.int64), np.zeros((FAN_FLOATS, beams), np.float64)


@kernel(nogil=True, error_model="numpy", inline="always")
def fan_key(steep, du, dv):  # pragma: no cover - compiled
    """The key of a ray whose runs go into the row plane (steep False) or the column plane, along (du, dv) in that
    plane's coordinates: rays with the same key and first cell mark the same rows the same way."""
    return 1 + 4 * int(steep) + 2 * int(du > 0.0) + int(dv > 0.0)


@kernel(nogil=True, error_model="numpy", inline="always")
def key_parts(key):  # pragma: no cover - compiled
    """(steep, forward, up) of a ray's key (> 0, :func:`fan_key`): its runs go into the column plane, along
    increasing u, along increasing v."""
    bits = key - 1
    return bits >= 4, (bits & 2) != 0, (bits & 1) != 0


@kernel(nogil=True, error_model="numpy", inline="always")
def record_crossings(ints, floats, k, steep, line, cell, crossings):  # pragma: no cover - compiled
    """Record ray k's plane (steep), its line and first cell in that plane's coordinates and its crossings of the
    plane's lines (:func:`mapping.free_runs.plane_crossings`) for the fans, and for the ray's own runs
    (:func:`recorded_crossings`)."""
    _, tol_u, n_lines, edge0, edge_step = crossings
    ints[KEY, k] = fan_key(steep, line[2], line[3])
    ints[IU, k], ints[IV, k], ints[LINES, k] = cell[0], cell[1], n_lines
    floats[EDGE0, k], floats[EDGE_STEP, k], floats[TOL, k] = edge0, edge_step, tol_u


@kernel(nogil=True, error_model="numpy", inline="always")
def recorded_crossings(ints, floats, k):  # pragma: no cover - compiled
    """Ray k's plane, first cell and crossings of the plane's lines as :func:`record_crossings` kept them (KEY > 0):
    (steep, (iu, iv), crossings), crossings as :func:`mapping.free_runs.run_lines` returns them."""
    steep, _, up = key_parts(ints[KEY, k])
    crossings = (1 if up else -1, floats[TOL, k], ints[LINES, k], floats[EDGE0, k], floats[EDGE_STEP, k])
    return steep, (ints[IU, k], ints[IV, k]), crossings


@kernel(nogil=True, error_model="numpy", inline="always")
def _link_rows(ints, floats, a, b):  # pragma: no cover - compiled
    """The last row (>= 1; 0: none) up to which the runs of rays a and b join (module docstring)."""
    if ints[KEY, a] == 0 or ints[KEY, a] != ints[KEY, b] or ints[IU, a] != ints[IU, b] or ints[IV, a] != ints[IV, b]:
        return 0
    full = min(ints[LINES, a], ints[LINES, b]) - 1  # rows 1 .. n_lines - 1 end at a line
    if full < 1:
        return 0
    room = min(abs(floats[EDGE_STEP, a]), abs(floats[EDGE_STEP, b])) - floats[TOL, a] - floats[TOL, b] - FAN_MARGIN
    room -= abs(floats[EDGE0, b] - floats[EDGE0, a])
    if room < 0.0:
        return 0
    spread = abs(floats[EDGE_STEP, b] - floats[EDGE_STEP, a])
    if spread * full <= room:
        return full
    return min(1 + int(room / spread), full)


@kernel(nogil=True, error_model="numpy", inline="always")
def _link_turn(floats, k):  # pragma: no cover - compiled
    """Which way ray k + 1 lies from ray k of a link (1, -1; 0 for the same direction): the sign of their edges'
    difference in every row, their edge steps' (rays from one point with the same first cell: edge0 = u0 + d * step
    and the k-th edge edge0 + k * step, for the same d)."""
    step = floats[EDGE_STEP, k + 1] - floats[EDGE_STEP, k]
    return 1 if step > 0.0 else (-1 if step < 0.0 else 0)


@kernel(nogil=True, error_model="numpy", inline="always")
def _mark_fan(planes, window, ints, floats, a, c, row):  # pragma: no cover - compiled
    """Mark in its plane the run the rays a .. c (a fan: each joined to the next) mark together in their row ``row``."""
    steep, forward, up = key_parts(ints[KEY, a])
    if steep:
        plane, stride, win_u0, win_v0 = planes[1], planes[2], window.iy0, window.ix0
    else:
        plane, stride, win_u0, win_v0 = planes[0], window.w, window.ix0, window.iy0
    lo_a, hi_a = row_run(floats[EDGE0, a], floats[EDGE_STEP, a], row, floats[TOL, a], forward)
    lo_c, hi_c = row_run(floats[EDGE0, c], floats[EDGE_STEP, c], row, floats[TOL, c], forward)
    base = (ints[IV, a] + (row if up else -row) - win_v0) * stride - win_u0
    set_run(plane, base + min(lo_a, lo_c), base + max(hi_a, hi_c))


@kernel(nogil=True, error_model="numpy", refcounted=False)
def fan_hulls(planes, window, ints, floats, count, heads):  # pragma: no cover - compiled
    """Mark the rows that fans of the ``count`` rays recorded in ints and floats (the fan scratch, one column per
    beam in beam order; mapping.samples_pass fills it) share, into planes = (row plane, column plane, column stride),
    and set each ray's SKIP: its rows 1 .. SKIP are marked (module docstring). heads: int64 scratch, longer than any
    ray's lines.

    The fans of row k are the runs of links that join up to row k or further. Going from the farthest row in, links
    join the runs beside them (their ends kept at each other's), and each row marks the fans it has: work in
    proportion to the links and the fans' rows."""
    top = 0
    turn = 0  # the way link k - 1 turns (_link_turn; compared only when that link was kept)
    for k in range(count):
        link = _link_rows(ints, floats, k, k + 1) if k + 1 < count else 0
        if link > 0:
            way = _link_turn(floats, k)
            if k > 0 and ints[LINK, k - 1] > 0 and way != turn:
                link = 0  # (the beams turn back: a fan's outermost rays would not be its ends)
            turn = way
        ints[LINK, k] = link
        ints[RUN_LEFT, k] = -1  # (not joined yet)
        top = max(top, link)
    for k in range(count):
        ints[SKIP, k] = max(ints[LINK, k], ints[LINK, k - 1] if k > 0 else 0)
    for row in range(top + 1):
        heads[row] = -1
    for k in range(count):  # the links by the rows they join to
        if ints[LINK, k] > 0:
            ints[NEXT, k] = heads[ints[LINK, k]]
            heads[ints[LINK, k]] = k
    fans = 0
    for row in range(top, 0, -1):
        m = heads[row]
        while m >= 0:  # link m joins from this row in
            first, last = m, m
            if m > 0 and ints[RUN_LEFT, m - 1] >= 0:  # (m - 1 ends a run)
                first = ints[RUN_LEFT, m - 1]
            else:
                ints[FANS, fans] = m
                ints[FAN_AT, m] = fans
                fans += 1
            if m + 1 < count and ints[RUN_LEFT, m + 1] >= 0:  # (m + 1 starts a run: its fan is now first's)
                last = ints[RUN_RIGHT, m + 1]
                fans -= 1
                moved = ints[FANS, fans]
                ints[FANS, ints[FAN_AT, m + 1]] = moved
                ints[FAN_AT, moved] = ints[FAN_AT, m + 1]
            ints[RUN_LEFT, m] = first
            ints[RUN_RIGHT, first] = last
            ints[RUN_LEFT, last] = first
            m = ints[NEXT, m]
        for f in range(fans):
            first = ints[FANS, f]
            _mark_fan(planes, window, ints, floats, first, ints[RUN_RIGHT, first] + 1, row)
