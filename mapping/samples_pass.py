"""The samples pass: one compiled pass over all (sample, beam, cell) triples of a scan with M > 1 distinct pose
samples, then one that adds the touched cells into the tiles (the update is in :mod:`mapping.fusion`).

How the pass keeps the per-sample rule cheap: every value is l_free (the smallest a cell can take) plus an
excess d >= 0, and only cells near a return have d > 0. So y_ij = l_free + d_ij for the samples j that
touch cell i, and with W_i = sum of their weights, D1_i = sum_j w_j d_ij, D2_i = sum_j w_j d_ij^2:

    sum_j w_j y_ij = l_free W_i + D1_i        sum_j w_j y_ij^2 = l_free^2 W_i + 2 l_free D1_i + D2_i

A sample's touched cells are marked in a plane of one bit per window cell (idempotent, so a cell crossed by
several of the sample's beams is marked once; most of a beam's free stretch is marked as runs per grid row or column,
:mod:`mapping.free_runs`), and after the sample's beams the plane's set bits add its weight to W_i. The few
cells with an excess keep a per-sample record (the largest excess of the sample's beams, by stamp) for D1 and
D2. A second bit plane marks the cells listed in this scan.
"""

from __future__ import annotations

import math

import numpy as np
from numba.cpython.unsafe.numbers import trailing_zeros  # LLVM's cttz: the set bits of a word, one by one

from mapping.beam_model import BEAM_SKIP, segment_logodds
from mapping.free_runs import fold_columns, mark_free_runs, set_bit
from mapping.jit import kernel
from mapping.raytrace import dda_step
from mapping.window_walk import JUMP_MARGIN, beam_direction, jump_over_tile, ray_start, step_index

#: per-sample stamps are stored as float64 (exact below 2**53); the scratch is cleared and stamps restart here
STAMP_LIMIT = 2**52


@kernel(nogil=True, error_model="numpy", inline="always")
def add_sample_value(rec, c, sid, w, y):  # pragma: no cover - compiled
    """Give cell record rec[c] the value y from sample ``sid`` (weight w) under the one-value-per-sample
    rule: rec[c, 0] the stamp of the last sample that touched the cell, rec[c, 1] that sample's value so
    far (the max over its beams), rec[c, 2:4] the weighted moments sum_j w_j y_ij and sum_j w_j y_ij^2.
    When a later beam of the same sample raises the value, the moments are corrected by the difference,
    so each (sample, cell) contributes exactly once. A record from an earlier scan must be cleared first.
    Written with selects, not branches: whether a beam of the same sample came first is unpredictable."""
    first = rec[c, 0] != sid
    old = rec[c, 1]
    new = y if first else max(old, y)
    rec[c, 0] = sid
    rec[c, 1] = new
    rec[c, 2] += w * y if first else w * (new - old)
    rec[c, 3] += w * y * y if first else w * (new * new - old * old)


@kernel(nogil=True, error_model="numpy")
def _sweep_plane(
    plane,
    n_words,
    listed,
    weight_sum,
    w,
    scan_cells,
    n_scan,
    win_w,
    win_ix0,
    win_iy0,
    tile_touched,
    tile_shift,
    tx0,
    ty0,
):  # pragma: no cover - compiled
    """Add one sample's weight w to the weight sum of every cell its plane marks, and clear the plane. A cell
    not yet listed in this scan (its bit clear in ``listed``) is listed in scan_cells and its tile marked in
    tile_touched. Returns the new list length."""
    for i in range(n_words):
        bits = plane[i]
        if bits == 0:
            continue
        plane[i] = 0
        base = i << 6
        new = bits & ~listed[i]
        if new != 0:
            listed[i] |= new
            while new != 0:
                c = base + trailing_zeros(new)
                scan_cells[n_scan] = c
                n_scan += 1
                tile_touched[
                    ((c // win_w + win_iy0) >> tile_shift) - ty0, ((c % win_w + win_ix0) >> tile_shift) - tx0
                ] = True
                new &= new - np.uint64(1)
        while bits != 0:
            weight_sum[base + trailing_zeros(bits)] += w
            bits &= bits - np.uint64(1)
    return n_scan


@kernel(nogil=True, error_model="numpy")
def accumulate_scan(
    laser_x,
    laser_y,
    laser_yaw,
    weights,
    cos_angles,
    sin_angles,
    kind,
    z,
    r_stop,
    r_peak,
    a,
    b,
    s,
    g_peak,
    free_until,
    table,
    u0,
    du,
    res,
    p_miss,
    p_hit,
    l_free,
    win_ix0,
    win_iy0,
    win_w,
    win_h,
    tile_shift,
    tx0,
    ty0,
    owned,
    all_owned,
    plane,
    columns,
    col_stride,
    listed,
    weight_sum,
    excess,
    scan_cells,
    tile_touched,
    stamp_base,
):  # pragma: no cover - compiled
    """One pass over all (sample, beam, cell) triples; returns the number of distinct cells touched.

    Window cell (gx, gy) is global cell (win_ix0 + gx, win_iy0 + gy); its scratch entries are at
    c = gy * win_w + gx: bit c of plane (the cells the current sample touched) and of listed (the cells
    listed in this scan), both one bit per cell and zero between scans; weight_sum[c] (W; zero between
    scans), excess[c] (four float64 kept by :func:`add_sample_value` for d: the stamp, the current sample's
    largest d, D1, D2 (D1 and D2 zero between scans); sample j's stamp is stamp_base + j, so smaller stamps
    are from earlier scans). scan_cells lists the touched cells' c. See the module docstring.

    Each ray runs in two phases: the free phase, cells that end before the beam's free_until (most of
    them), which take l_free without evaluating the model; then the cells up to the ray's end, valued by
    :func:`segment_logodds`. When the shard owns every tile of the window, the free phase is marked as runs
    of cells per grid row or column (:func:`mapping.free_runs.mark_free_runs`; a steep ray's go into the
    column-major plane ``columns``, columns col_stride bits long) up to just before its end, and the walk
    resumes at the runs' last cell, stepping the scratch index itself (:func:`mapping.window_walk.step_index`);
    otherwise the walk keeps the cell's (ix, iy), looks ownership up per tile, and in another shard's tile jumps
    to the tile's exit. After a sample's beams its column plane is folded into ``plane`` and ``plane`` is swept
    into the weight sums.
    """
    n_scan = 0
    n_words = (win_w * win_h + 63) >> 6
    y_peak = math.log(p_hit) - math.log1p(-p_hit)
    exits = np.empty(max(win_w, win_h), np.int64)  # per grid line of a ray's runs (mapping.free_runs)
    entries = np.empty(max(win_w, win_h), np.int64)
    block = np.empty(64, np.uint64)  # 64 x 64 bits being folded from the column-major plane
    for j in range(laser_x.shape[0]):
        sid = float(stamp_base + j)
        w = weights[j]
        cos_yaw = math.cos(laser_yaw[j])
        sin_yaw = math.sin(laser_yaw[j])
        for k in range(cos_angles.shape[0]):
            beam_kind = kind[k]
            if beam_kind == BEAM_SKIP:
                continue
            # per-beam constants in locals: the compiler cannot hoist loads past the scratch writes
            stop = r_stop[k]
            peak_at = r_peak[k]
            z_k = z[k]
            a_k = a[k]
            b_k = b[k]
            s_k = s[k]
            g_peak_k = g_peak[k]
            free_until_k = free_until[k]
            dx, dy = beam_direction(cos_yaw, sin_yaw, cos_angles[k], sin_angles[k])
            inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = ray_start(
                laser_x[j], laser_y[j], dx, dy, stop, res, win_ix0, win_iy0, win_w, win_h
            )
            if not inside:
                continue
            r_in = 0.0
            mine = True
            cell_tx = tx0 - 1  # the tile whose ownership ``mine`` holds; none yet (no ray leaves the window)
            cell_ty = ty0 - 1
            ray_done = False
            ray_end = stop - tol  # a grid line crossed within tol of stop ends the ray: no sliver of a cell past it
            free_limit = min(free_until_k, ray_end)
            if all_owned:  # every tile owned: the free phase as runs, then the walk on the scratch index c
                runs_end = free_limit - JUMP_MARGIN * (1.0 + free_limit)
                if runs_end > 0.0:
                    first_ix, first_iy = ix, iy
                    if min(t_max_x, t_max_y) <= 0.0:  # the ray starts on its cell's edge and leaves it at once
                        first_ix, first_iy, _, _ = dda_step(
                            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol
                        )
                    end_ix, end_iy = mark_free_runs(
                        plane,
                        columns,
                        col_stride,
                        laser_x[j],
                        laser_y[j],
                        dx,
                        dy,
                        first_ix,
                        first_iy,
                        runs_end,
                        res,
                        tol,
                        win_ix0,
                        win_iy0,
                        win_w,
                        exits,
                        entries,
                    )
                    # the walk goes on from the runs' last cell, the grid lines crossed up to it counted; its r_in
                    # is taken as runs_end (segment_logodds reads r_in only past the peak, well beyond)
                    t_max_x += max((end_ix - ix) * step_x, 0) * t_delta_x
                    t_max_y += max((end_iy - iy) * step_y, 0) * t_delta_y
                    ix, iy = end_ix, end_iy
                    r_in = runs_end
                c = (iy - win_iy0) * win_w + ix - win_ix0
                row_step = step_y * win_w
                while True:  # what is left of the free phase (a cell or two)
                    r_out = min(t_max_x, t_max_y)
                    if r_out >= free_limit:
                        break
                    if r_out > r_in:
                        set_bit(plane, c)
                    r_in = r_out
                    c, t_max_x, t_max_y = step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
                while True:  # the cells from free_until to the ray's end
                    # (the four lines of a visit repeat the general loop's below: an inlined helper for them
                    # made the whole pass 1.14-1.18x slower, measured 2026-11-26)
                    r_out = min(t_max_x, t_max_y, stop)
                    if r_out > r_in:
                        d = (
                            segment_logodds(
                                r_in,
                                r_out,
                                beam_kind,
                                free_until_k,
                                z_k,
                                peak_at,
                                a_k,
                                b_k,
                                s_k,
                                g_peak_k,
                                table,
                                u0,
                                du,
                                p_miss,
                                p_hit,
                                l_free,
                                y_peak,
                            )
                            - l_free
                        )
                        set_bit(plane, c)
                        if d > 0.0:
                            add_sample_value(excess, np.uint64(c), sid, w, d)
                    if r_out >= ray_end:
                        break
                    r_in = r_out
                    c, t_max_x, t_max_y = step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
                continue
            # some tiles are another shard's: the walk keeps (ix, iy) to look ownership up per tile
            while True:  # the free phase
                r_out = min(t_max_x, t_max_y)
                if r_out >= free_limit:
                    break
                if (ix >> tile_shift) != cell_tx or (iy >> tile_shift) != cell_ty:
                    cell_tx = ix >> tile_shift
                    cell_ty = iy >> tile_shift
                    mine = owned[cell_ty - ty0, cell_tx - tx0]
                if not mine:
                    jumped_from = r_in
                    ix, iy, t_max_x, t_max_y, r_in, t_exit = jump_over_tile(
                        ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift
                    )
                    if t_exit >= ray_end:
                        ray_done = True
                        break
                    if r_in > jumped_from:
                        continue  # look at the cell the jump landed in
                elif r_out > r_in:
                    set_bit(plane, (iy - win_iy0) * win_w + ix - win_ix0)
                r_in = r_out
                ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
            while not ray_done:  # the cells from free_until to the ray's end
                if (ix >> tile_shift) != cell_tx or (iy >> tile_shift) != cell_ty:
                    cell_tx = ix >> tile_shift
                    cell_ty = iy >> tile_shift
                    mine = owned[cell_ty - ty0, cell_tx - tx0]
                if not mine:
                    ix, iy, t_max_x, t_max_y, r_in, t_exit = jump_over_tile(
                        ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift
                    )
                    if t_exit >= ray_end:
                        break
                r_out = min(t_max_x, t_max_y, stop)
                if r_out > r_in and mine:
                    d = (
                        segment_logodds(
                            r_in,
                            r_out,
                            beam_kind,
                            free_until_k,
                            z_k,
                            peak_at,
                            a_k,
                            b_k,
                            s_k,
                            g_peak_k,
                            table,
                            u0,
                            du,
                            p_miss,
                            p_hit,
                            l_free,
                            y_peak,
                        )
                        - l_free
                    )
                    c = (iy - win_iy0) * win_w + ix - win_ix0
                    set_bit(plane, c)
                    if d > 0.0:
                        add_sample_value(excess, np.uint64(c), sid, w, d)
                if r_out >= ray_end:
                    break
                r_in = r_out
                ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
        if all_owned:
            fold_columns(columns, col_stride, plane, win_w, win_h, block)
        n_scan = _sweep_plane(
            plane,
            n_words,
            listed,
            weight_sum,
            w,
            scan_cells,
            n_scan,
            win_w,
            win_ix0,
            win_iy0,
            tile_touched,
            tile_shift,
            tx0,
            ty0,
        )
    return n_scan


@kernel(nogil=True, error_model="numpy")
def apply_scan(
    scan_cells,
    n_scan,
    listed,
    weight_sum,
    excess,
    stamp_base,
    l_free,
    win_w,
    win_ix0,
    win_iy0,
    tile_shift,
    tx0,
    ty0,
    slot_map,
    logodds,
    variance,
    observed,
    l_min,
    l_max,
):  # pragma: no cover
    """Add the scan's weighted mean to each touched cell (clamped) and its spread to the variance layer, from
    the moments l_free W + D1 and l_free^2 W + 2 l_free D1 + D2; clear the cells' listed bits and weight sums
    for the next scan."""
    for q in range(n_scan):
        c = scan_cells[q]
        ix = c % win_w + win_ix0
        iy = c // win_w + win_iy0
        slot = slot_map[(iy >> tile_shift) - ty0, (ix >> tile_shift) - tx0]
        in_tile = (1 << tile_shift) - 1
        ly = iy & in_tile
        lx = ix & in_tile
        listed[c >> 6] = 0
        moment1 = l_free * weight_sum[c]
        weight_sum[c] = 0.0
        moment2 = l_free * moment1
        if excess[c, 0] >= stamp_base:
            moment1 += excess[c, 2]
            moment2 += 2.0 * l_free * excess[c, 2] + excess[c, 3]
            excess[c, 2] = 0.0
            excess[c, 3] = 0.0
        mean = moment1
        spread = moment2 - mean * mean
        if spread < 0.0:
            spread = 0.0
        updated = logodds[slot, ly, lx] + mean
        if updated < l_min:
            updated = l_min
        elif updated > l_max:
            updated = l_max
        logodds[slot, ly, lx] = updated
        variance[slot, ly, lx] += spread
        observed[slot, ly, lx] = True
