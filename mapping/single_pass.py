"""The one-sample pass: a scan with one distinct pose sample (M = 1 after merging identical samples: a single
pose, or a particle set whose particles are all the same) gives the same map as the samples pass
(:mod:`mapping.samples_pass`) for about half the time.

With one sample of weight w a cell's update is w l_free + w d (d its largest excess, 0 in free space; the
samples pass's sum l_free W + D1) and its spread is 0, so the pass keeps no masks, weight sums or per-sample
records: per 8 x 8 block of the window one 64-bit set of the touched cells (a free-space visit sets one bit
in a small array) and one of the cells with an excess, whose largest excess is kept per cell. The second
pass (:func:`apply_single`) walks the touched blocks, adds w (l_free + d) to each touched cell, leaves the
variance layer alone (spread 0) and clears the bits. The rays are walked by the samples pass's walk
(:func:`mapping.window_walk.walk_ray`: window, free phase and shards' tiles), with this pass's visitors.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros  # LLVM's ctlz, cttz

from mapping.beam_model import BeamTable, LogOddsModel, beam_at, segment_logodds
from mapping.jit import kernel
from mapping.tile_boxes import widen_box
from mapping.tile_changes import LOGODDS_CHANGED, OBSERVED_CHANGED, update_cell
from mapping.window_walk import Tiles, Window, beam_ray, ownership_constants, walk_ray


class SingleScratch(NamedTuple):
    """The one-sample pass's scratch over a scan's window, per 8 x 8 block of cells (see :func:`accumulate_single`):
    touched, raised (int64 bit sets per block), excess (a float64 per cell), the window's blocks_w x blocks_h
    blocks, tile_touched (bool, per tile of the window) and boxes (per tile of the window, the bounding box of its
    touched cells: :mod:`mapping.tile_boxes`)."""

    touched: np.ndarray
    raised: np.ndarray
    excess: np.ndarray
    blocks_w: int
    blocks_h: int
    tile_touched: np.ndarray
    boxes: np.ndarray


class _Blocks(NamedTuple):
    """What the one-sample pass's visitors write: the bit sets and excess of :class:`SingleScratch`, for a window
    from global cell (ix0, iy0), read from the model."""

    touched: np.ndarray
    raised: np.ndarray
    excess: np.ndarray
    blocks_w: int
    ix0: int
    iy0: int
    model: LogOddsModel


@kernel(nogil=True, error_model="numpy", inline="always")
def _block_bit(gx, gy, blocks_w):  # pragma: no cover - compiled
    """Window cell (gx, gy)'s 8 x 8 block (index (gy >> 3) * blocks_w + (gx >> 3)) and its bit there."""
    return (gy >> 3) * blocks_w + (gx >> 3), np.int64(1) << (((gy & 7) << 3) | (gx & 7))


@kernel(nogil=True, error_model="numpy", inline="always")
def _record_index(gx, gy, blocks_w):  # pragma: no cover - compiled
    """Place of window cell (gx, gy) in the one-sample pass's per-cell excess: 8 x 8 blocks, so a ray's
    neighbouring cells share cache lines; block index * 64 + the cell's bit in the block's bit sets (the
    samples pass's scratch is row-major instead, c = gy * win_w + gx)."""
    return ((gy >> 3) * blocks_w + (gx >> 3)) * 64 + ((gy & 7) << 3) + (gx & 7)


@kernel(nogil=True, error_model="numpy", inline="always")
def _raise_excess(touched, raised, excess, gx, gy, d, blocks_w):  # pragma: no cover - compiled
    """One-sample pass: mark window cell (gx, gy) touched and keep its largest excess d > 0 (see
    :func:`accumulate_single` for the arrays). Block indices are unsigned: no test for a negative index."""
    block, bit = _block_bit(gx, gy, blocks_w)
    block = np.uint64(block)
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


@kernel(nogil=True, error_model="numpy", inline="always")
def _hold_free(blocks, carry, ix, iy):  # pragma: no cover - compiled
    """A free-phase visit: the cell's bit in its block, gathered in carry = (held block, its bits) and stored when
    the walk leaves the block (a store per block, not one per cell, where the walk owns every tile)."""
    held_block, held_bits = carry
    block, bit = _block_bit(ix - blocks.ix0, iy - blocks.iy0, blocks.blocks_w)
    if block != held_block:
        blocks.touched[np.uint64(held_block)] |= held_bits
        held_block = block
        held_bits = np.int64(0)
    return held_block, held_bits | bit


@kernel(nogil=True, error_model="numpy", inline="always")
def _mark_free(blocks, carry, ix, iy):  # pragma: no cover - compiled
    """A free-phase visit of a shard's walk: the cell's bit stored at once (gathering the bits per block, as
    :func:`_hold_free` does, made this walk slower: docs/performance.md)."""
    block, bit = _block_bit(ix - blocks.ix0, iy - blocks.iy0, blocks.blocks_w)
    blocks.touched[np.uint64(block)] |= bit
    return carry


@kernel(nogil=True, error_model="numpy", inline="always")
def _raise_near(blocks, beam, carry, ix, iy, r_in, r_out):  # pragma: no cover - compiled
    """A visit near the return: the cell touched, and its largest excess over l_free kept."""
    d = segment_logodds(r_in, r_out, beam, blocks.model) - blocks.model.l_free
    _raise_excess(blocks.touched, blocks.raised, blocks.excess, ix - blocks.ix0, iy - blocks.iy0, d, blocks.blocks_w)
    return carry


@kernel(nogil=True, error_model="numpy", refcounted=False)
def accumulate_single(laser, directions, beams, model, res, window, tiles, scratch):  # pragma: no cover - compiled
    """The pass for one pose sample (laser at (x m, y m, yaw rad)): every (beam, cell) pair; returns the number of
    distinct cells touched and marks their tiles in tile_touched. The arguments are as for
    :func:`mapping.samples_pass.accumulate_scan`, scratch a :class:`SingleScratch` (plain tuples).

    Same walk as the samples pass (:func:`mapping.window_walk.walk_ray`: window, two phases, shards' tiles), but
    with one sample the cell just keeps the largest excess d of the beams that touch it. The window's origin is a
    multiple of 8 cells, so its 8 x 8 blocks are blocks of the global grid. Per block (index (gy >> 3) * blocks_w +
    (gx >> 3)), touched[block] and raised[block] (int64) hold bit (gy & 7) * 8 + (gx & 7) for the cells touched
    in this scan and for those with an excess d > 0, whose largest d is excess[c] (c from :func:`_record_index`,
    valid only where the raised bit is set). Free-phase visits only set a bit: no write to the large excess array.
    The bits are zero between scans (:func:`apply_single` clears them)."""
    beams, model, window, tiles = BeamTable(*beams), LogOddsModel(*model), Window(*window), Tiles(*tiles)
    scratch = SingleScratch(*scratch)
    blocks = _Blocks(scratch.touched, scratch.raised, scratch.excess, scratch.blocks_w, window.ix0, window.iy0, model)
    every_tile, some_tiles = ownership_constants(tiles)
    heading = (math.cos(laser[2]), math.sin(laser[2]))
    for k in range(beams.kind.shape[0]):
        beam = beam_at(beams, k)
        inside, ray, _, _ = beam_ray(laser, heading, directions, beam, k, res, window)
        free_until, stop = beam.free_until, beam.r_stop
        if inside and tiles.all_owned:  # (a skipped beam is not inside)
            held_block, held_bits = walk_ray(
                ray,
                0.0,
                free_until,
                stop,
                every_tile,
                _hold_free,
                _raise_near,
                blocks,
                (beams, k),
                (0, np.int64(0)),
                True,
            )
            scratch.touched[np.uint64(held_block)] |= held_bits
        elif inside:
            walk_ray(ray, 0.0, free_until, stop, some_tiles, _mark_free, _raise_near, blocks, (beams, k), 0, True)
    return _count_touched(scratch, window, tiles)


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_touched(scratch, window, tiles):  # pragma: no cover - compiled
    """The number of cells the scan touched; marks their tiles in tile_touched and widens the tiles' boxes to hold
    them (per block: its first and last rows and columns with a touched cell)."""
    shift, tx0, ty0 = tiles.shift, tiles.tx0, tiles.ty0
    in_tile = (1 << shift) - 1
    n_cells = 0
    for block in range(scratch.blocks_w * scratch.blocks_h):
        bits = scratch.touched[block]
        if bits == 0:
            continue
        n_cells += _bit_count(bits)
        bx = (block % scratch.blocks_w) * 8 + window.ix0
        by = (block // scratch.blocks_w) * 8 + window.iy0
        if shift >= 3:  # the block lies in one tile
            ty, tx = (by >> shift) - ty0, (bx >> shift) - tx0
            scratch.tile_touched[ty, tx] = True
            word = np.uint64(bits)
            columns = word | (word >> np.uint64(32))
            columns |= columns >> np.uint64(16)
            columns |= columns >> np.uint64(8)
            columns &= np.uint64(255)  # (bit c: a touched cell in column c)
            ly, lx = by & in_tile, bx & in_tile
            rows = (trailing_zeros(word) >> 3, (63 - leading_zeros(word)) >> 3)
            cols = (trailing_zeros(columns), 63 - leading_zeros(columns))
            widen_box(scratch.boxes, ty, tx, ly + rows[0], lx + cols[0], ly + rows[1], lx + cols[1])
        else:
            for bit in range(64):
                if (bits >> bit) & 1:
                    iy, ix = by + (bit >> 3), bx + (bit & 7)
                    ty, tx = (iy >> shift) - ty0, (ix >> shift) - tx0
                    scratch.tile_touched[ty, tx] = True
                    widen_box(scratch.boxes, ty, tx, iy & in_tile, ix & in_tile, iy & in_tile, ix & in_tile)
    return n_cells


@kernel(nogil=True, error_model="numpy", refcounted=False)
def apply_single(scratch, w, window, tiles, slot_map, layers, levels):  # pragma: no cover - compiled
    """Add the one-sample scan (its sample's weight w) to each touched cell: w (l_free + d) as the multi-sample
    moments give it, l_free W + D1 with W = w and D1 = w d (d the cell's largest excess, 0 where none), clamped to
    [l_min, l_max]; mark the cell observed. The spread of one sample is 0, so the variance layer is left as it is.
    Block by block, so neighbouring cells are written together; clears the blocks' bits for the next scan.

    scratch, window, tiles: as for :func:`accumulate_single`; slot_map: the grid slot of each tile of the window;
    layers: the grid's (logodds, variance, observed, changed: the layers whose value changed marked, in a grid that
    tracks them); levels: the model's (l_free, l_min, l_max)."""
    scratch, window, tiles = SingleScratch(*scratch), Window(*window), Tiles(*tiles)
    touched, raised, blocks_w = scratch.touched, scratch.raised, scratch.blocks_w
    for block in range(blocks_w * scratch.blocks_h):
        bits = touched[block]
        if bits == 0:
            continue
        up = raised[block]
        touched[block] = 0
        raised[block] = 0
        bx = (block % blocks_w) * 8 + window.ix0
        by = (block // blocks_w) * 8 + window.iy0
        if tiles.shift >= 3:  # the block lies in one tile
            _apply_block(scratch.excess, block, bits, up, bx, by, w, tiles, slot_map, layers, levels)
        else:
            _apply_cells(scratch.excess, block, bits, up, bx, by, w, tiles, slot_map, layers, levels)


@kernel(nogil=True, error_model="numpy", inline="always")
def _apply_block(excess, block, bits, up, bx, by, w, tiles, slot_map, layers, levels):  # pragma: no cover
    """:func:`apply_single` for a block that lies in one tile (cells from global (bx, by); touched bits ``bits``,
    raised bits ``up``): its rows are 8 cells of a tile row, taken without branches."""
    logodds, _, observed, changed = layers
    track = changed.shape[0] > 0  # (a grid that tracks its changed cells, mapping.grid)
    l_free, l_min, l_max = levels
    in_tile = (1 << tiles.shift) - 1
    base = l_free * w
    slot = slot_map[(by >> tiles.shift) - tiles.ty0, (bx >> tiles.shift) - tiles.tx0]
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
            if track:
                was = observed[slot, ly, lx + col]
                changed[slot, ly, lx + col] |= (on & (logodds[slot, ly, lx + col] != old)) * LOGODDS_CHANGED | (
                    on & (not was)
                ) * OBSERVED_CHANGED
            observed[slot, ly, lx + col] |= on


@kernel(nogil=True, error_model="numpy", inline="always")
def _apply_cells(excess, block, bits, up, bx, by, w, tiles, slot_map, layers, levels):  # pragma: no cover
    """:func:`apply_single` for a block over several tiles (tiles smaller than 8 cells), cell by cell."""
    l_free, l_min, l_max = levels
    in_tile = (1 << tiles.shift) - 1
    base = l_free * w
    for row in range(8):
        if (bits >> (8 * row)) & 255 == 0:
            continue
        iy = by + row
        for col in range(8):
            bit = 8 * row + col
            if (bits >> bit) & 1 == 0:
                continue
            ix = bx + col
            slot = slot_map[(iy >> tiles.shift) - tiles.ty0, (ix >> tiles.shift) - tiles.tx0]
            mean = base
            if (up >> bit) & 1:
                mean = base + w * excess[block * 64 + bit]
            update_cell(layers, (slot, iy & in_tile, ix & in_tile), mean, 0.0, l_min, l_max)  # (one pose: no spread)
