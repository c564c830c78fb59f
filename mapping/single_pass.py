"""The one-sample pass: a scan with one distinct pose sample (M = 1 after merging identical samples: a single
pose, or a particle set whose particles are all the same) gives the same map as the samples pass
(:mod:`mapping.samples_pass`) for about half the time.

With one sample of weight w a cell's update is w l_free + w d (d its largest excess, 0 in free space; the
samples pass's sum l_free W + D1) and its spread is 0, so the pass keeps no masks, weight sums or per-sample
records: per 8 x 8 block of the window one 64-bit set of the touched cells (a free-space visit sets one bit
in a small array) and one of the cells with an excess, whose largest excess is kept per cell. The second
pass (:func:`apply_single`) walks the touched blocks, adds w (l_free + d) to each touched cell, leaves the
variance layer alone (spread 0) and clears the bits. The rays are walked exactly as in the samples pass
(same helpers, window, free phase and shards' tiles).
"""

from __future__ import annotations

import math

import numpy as np

from mapping.beam_model import BEAM_SKIP, segment_logodds
from mapping.jit import kernel
from mapping.raytrace import dda_step
from mapping.window_walk import beam_direction, jump_over_tile, ray_start


@kernel(nogil=True, error_model="numpy", inline="always")
def _record_index(gx, gy, blocks_w):  # pragma: no cover - compiled
    """Place of window cell (gx, gy) in the one-sample pass's per-cell excess: 8 x 8 blocks, so a ray's
    neighbouring cells share cache lines; block index * 64 + the cell's bit in the block's bit sets (the
    samples pass's scratch is row-major instead, c = gy * win_w + gx)."""
    return ((gy >> 3) * blocks_w + (gx >> 3)) * 64 + ((gy & 7) << 3) + (gx & 7)


@kernel(nogil=True, error_model="numpy", inline="always")
def _raise_excess(touched, raised, excess, gx, gy, d, blocks_w):  # pragma: no cover - compiled
    """One-sample pass: mark window cell (gx, gy) touched and keep its largest excess d > 0 (see
    :func:`accumulate_single` for the arrays)."""
    block = (gy >> 3) * blocks_w + (gx >> 3)
    bit = np.int64(1) << (((gy & 7) << 3) | (gx & 7))
    touched[block] |= bit
    if d > 0.0:
        c = _record_index(gx, gy, blocks_w)
        seen = raised[block]
        if seen & bit == 0:
            raised[block] = seen | bit
            excess[c] = d
        elif d > excess[c]:
            excess[c] = d


@kernel(nogil=True, error_model="numpy", inline="always")
def _bit_count(bits):  # pragma: no cover - compiled
    """The number of set bits of an int64 (one loop iteration per set bit)."""
    n = 0
    while bits != 0:
        bits &= bits - 1
        n += 1
    return n


@kernel(nogil=True, error_model="numpy")
def accumulate_single(
    laser_x,
    laser_y,
    laser_yaw,
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
    touched,
    raised,
    excess,
    blocks_w,
    blocks_h,
    tile_touched,
):  # pragma: no cover - compiled
    """The pass for one pose sample (laser at laser_x, laser_y m, heading laser_yaw rad): every (beam, cell)
    pair; returns the number of distinct cells touched and marks their tiles in tile_touched.

    Same walk as :func:`mapping.samples_pass.accumulate_scan` (window, two phases, shards' tiles), but with one sample
    the cell just keeps the largest excess d of the beams that touch it. The window's origin is a multiple of 8 cells,
    so its 8 x 8 blocks are blocks of the global grid. Per block (index (gy >> 3) * blocks_w + (gx >> 3)),
    touched[block] and raised[block] (int64) hold bit (gy & 7) * 8 + (gx & 7) for the cells touched in this
    scan and for those with an excess d > 0, whose largest d is excess[c] (c from :func:`_record_index`, valid
    only where the raised bit is set). Free-phase visits only set a bit: no write to the large excess array.
    The bits are zero between scans (:func:`apply_single` clears them)."""
    y_peak = math.log(p_hit) - math.log1p(-p_hit)
    cos_yaw = math.cos(laser_yaw)
    sin_yaw = math.sin(laser_yaw)
    for k in range(cos_angles.shape[0]):
        beam_kind = kind[k]
        if beam_kind == BEAM_SKIP:
            continue
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
            laser_x, laser_y, dx, dy, stop, res, win_ix0, win_iy0, win_w, win_h
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
        held_block = 0  # the block whose bits held_bits gathers (a store per block, not one per cell)
        held_bits = np.int64(0)
        while all_owned:  # the free phase, every tile owned (the same walk without the ownership checks)
            r_out = min(t_max_x, t_max_y)
            if r_out >= free_limit:
                break
            if r_out > r_in:
                gx = ix - win_ix0
                gy = iy - win_iy0
                block = (gy >> 3) * blocks_w + (gx >> 3)
                if block != held_block:
                    touched[held_block] |= held_bits
                    held_block = block
                    held_bits = np.int64(0)
                held_bits |= np.int64(1) << (((gy & 7) << 3) | (gx & 7))
            r_in = r_out
            ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
        touched[held_block] |= held_bits
        # the shard's walk below is written out as in accumulate_scan: helpers for the ownership look-up and
        # the jump, returning tuples, slowed the passes (docs/performance.md, "Tried and dropped")
        while not all_owned:  # the free phase, some tiles another shard's
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
                gx = ix - win_ix0
                gy = iy - win_iy0
                touched[(gy >> 3) * blocks_w + (gx >> 3)] |= np.int64(1) << (((gy & 7) << 3) | (gx & 7))
            r_in = r_out
            ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
        while not ray_done:  # the cells from free_until to the ray's end
            if not all_owned and ((ix >> tile_shift) != cell_tx or (iy >> tile_shift) != cell_ty):
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
                _raise_excess(touched, raised, excess, ix - win_ix0, iy - win_iy0, d, blocks_w)
            if r_out >= ray_end:
                break
            r_in = r_out
            ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    n_cells = 0
    for block in range(blocks_w * blocks_h):
        bits = touched[block]
        if bits == 0:
            continue
        n_cells += _bit_count(bits)
        bx = (block % blocks_w) * 8 + win_ix0
        by = (block // blocks_w) * 8 + win_iy0
        if tile_shift >= 3:  # the block lies in one tile
            tile_touched[(by >> tile_shift) - ty0, (bx >> tile_shift) - tx0] = True
        else:
            for bit in range(64):
                if (bits >> bit) & 1:
                    tile_touched[((by + (bit >> 3)) >> tile_shift) - ty0, ((bx + (bit & 7)) >> tile_shift) - tx0] = True
    return n_cells


@kernel(nogil=True, error_model="numpy")
def apply_single(
    touched,
    raised,
    excess,
    blocks_w,
    blocks_h,
    w,
    l_free,
    win_ix0,
    win_iy0,
    tile_shift,
    tx0,
    ty0,
    slot_map,
    logodds,
    observed,
    l_min,
    l_max,
):  # pragma: no cover - compiled
    """Add the one-sample scan to each touched cell: w (l_free + d) as the multi-sample moments give it,
    l_free W + D1 with W = w and D1 = w d (d the cell's largest excess, 0 where none), clamped to [l_min,
    l_max]; mark the cell observed. The spread of one sample is 0, so the variance layer is left as it is.
    Block by block, so neighbouring cells are written together; clears the blocks' bits for the next scan."""
    in_tile = (1 << tile_shift) - 1
    base = l_free * w
    for block in range(blocks_w * blocks_h):
        bits = touched[block]
        if bits == 0:
            continue
        up = raised[block]
        touched[block] = 0
        raised[block] = 0
        bx = (block % blocks_w) * 8 + win_ix0
        by = (block // blocks_w) * 8 + win_iy0
        if tile_shift >= 3:  # the block lies in one tile: its rows are 8 cells of a tile row, taken without branches
            slot = slot_map[(by >> tile_shift) - ty0, (bx >> tile_shift) - tx0]
            lx = bx & in_tile
            for row in range(8):
                row_bits = (bits >> (8 * row)) & 255
                if row_bits == 0:
                    continue
                row_up = (up >> (8 * row)) & 255
                ly = (by + row) & in_tile
                for col in range(8):
                    on = (row_bits >> col) & 1 == 1
                    mean = base + w * excess[block * 64 + 8 * row + col] if (row_up >> col) & 1 == 1 else base
                    old = logodds[slot, ly, lx + col]
                    updated = min(max(old + mean, l_min), l_max)
                    logodds[slot, ly, lx + col] = updated if on else old
                    observed[slot, ly, lx + col] |= on
            continue
        for row in range(8):
            if (bits >> (8 * row)) & 255 == 0:
                continue
            iy = by + row
            for col in range(8):
                bit = 8 * row + col
                if (bits >> bit) & 1 == 0:
                    continue
                ix = bx + col
                slot = slot_map[(iy >> tile_shift) - ty0, (ix >> tile_shift) - tx0]
                mean = base
                if (up >> bit) & 1:
                    mean = base + w * excess[block * 64 + bit]
                updated = logodds[slot, iy & in_tile, ix & in_tile] + mean
                if updated < l_min:
                    updated = l_min
                elif updated > l_max:
                    updated = l_max
                logodds[slot, iy & in_tile, ix & in_tile] = updated
                observed[slot, iy & in_tile, ix & in_tile] = True
