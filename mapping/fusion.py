"""Monte Carlo fusion of one scan under M weighted pose samples (paper, section V, eq. 9).

For a scan with pose samples x_j and weights w_j (sum 1), every cell i touched under any sample gets

    l_i <- clamp(l_i + sum_j w_j y_ij)            variance_i <- variance_i + sum_j w_j y_ij^2 - (sum_j w_j y_ij)^2

where y_ij is the cell's log-odds under sample j (0 where sample j does not touch the cell; the prior
log-odds is 0, so nothing is subtracted).

Rule for one cell, one scan, one sample (docs/sensor_model.md): every beam that crosses the cell proposes
the model's largest value over the beam's segment inside the cell, and the cell takes the largest of those
proposals. A beam ending in the cell therefore always beats a beam passing through it: occupied wins over
free, as in OctoMap's per-scan update.

The whole scan is one compiled pass over all (sample, beam, cell) triples, written into a scratch window
that covers the scan (its origin a multiple of 8 cells), followed by one compiled pass that adds the
window's touched cells into the tiles. No Python loop runs per sample, beam or cell.

How the pass keeps the per-sample rule cheap: every value is l_free (the smallest a cell can take) plus an
excess d >= 0, and only cells near a return have d > 0. So y_ij = l_free + d_ij for the samples j that
touch cell i, and with W_i = sum of their weights, D1_i = sum_j w_j d_ij, D2_i = sum_j w_j d_ij^2:

    sum_j w_j y_ij = l_free W_i + D1_i        sum_j w_j y_ij^2 = l_free^2 W_i + 2 l_free D1_i + D2_i

A cell in free space (most visits) only sets sample j's bit in a 64-bit mask (which samples touched it:
idempotent, no per-sample record); W_i is summed from the mask's bits once per scan. The few cells with an
excess keep a per-sample record (the largest excess of the sample's beams, by stamp) for D1 and D2.
Samples go through in chunks of MASK_SAMPLES; the mask's top bit marks a cell listed in this scan.

One distinct sample (M = 1 after merging identical samples: a single pose, or a particle set whose particles
are all the same) has its own pass, :func:`_accumulate_single`, which gives the same map for about half the
time. With one sample of weight w a cell's update is w l_free + w d (d its largest excess, 0 in free space;
the same sum l_free W + D1 as above) and its spread is 0, so the pass keeps no masks, weight sums or
per-sample records: per 8 x 8 block of the window one 64-bit set of the touched cells (a free-space visit sets
one bit in a small array) and one of the cells with an excess, whose largest excess is kept per cell. The
second pass (:func:`_apply_single`) walks the touched blocks, adds w (l_free + d) to each touched cell,
leaves the variance layer alone (spread 0) and clears the bits. The rays are walked exactly as in the samples
pass (same helpers, window, free phase and shards' tiles).
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numba as nb
import numpy as np

from mapping.errors import InputError
from mapping.grid import TiledGrid
from mapping.raytrace import FAR, corner_tol, dda_start, dda_step
from mapping.sensor_model import PEAK_EPS, TAIL_SIGMAS, SensorModel

#: per-sample stamps are stored as float64 (exact below 2**53); the scratch is cleared and stamps restart here
STAMP_LIMIT = 2**52

#: samples per chunk: one bit each in a cell's 64-bit mask; the top bit marks a cell already listed
MASK_SAMPLES = 63
LISTED = np.uint64(1) << np.uint64(63)

#: a shard jumps over another shard's tile to this far (relative, m) before the tile's exit, then steps
JUMP_MARGIN = 1e-9

#: beam kinds in the compiled kernel
BEAM_SKIP, BEAM_HIT, BEAM_NO_RETURN = 0, 1, 2

#: the most cells one scan's scratch window may span. The samples pass keeps 56 bytes a cell, so this is about
#: 0.9 GB; it holds a 100 m laser's reach at 0.05 m cells. Pose samples spread wider than that (a diverged
#: estimate) are refused, not allocated.
MAX_WINDOW_CELLS = 1 << 24
#: window cell indices stay within this many cells of the map origin (the kernels take them as int64)
MAX_CELL_INDEX = 1 << 40

#: cells whose segment ends this many sigma before the peak take the free value without evaluating erf
#: (the model differs from 0 by < 3e-7 there)
FREE_SHORTCUT_SIGMAS = 5.0

SQRT2 = math.sqrt(2.0)

#: constant-sigma models read the log-odds from a table over u = (r - z) / sigma, from the free shortcut to
#: the traversal's end, with linear interpolation (error < 2e-4 in log-odds at the squashing's kink, far less elsewhere; tested)
TABLE_DU = 0.002
TABLE_U0 = -(FREE_SHORTCUT_SIGMAS + 1.0) - 8.0  # covers l/2 up to 8 sigma before the return
TABLE_U1 = 3.5  # past the traversal's end at 3 sigma


def logodds_table(model: SensorModel) -> np.ndarray:
    """y(u) on u = TABLE_U0 + i * TABLE_DU up to TABLE_U1 for a constant-sigma model.

    Before the peak only the rising side is read and after it only the falling side, as in
    :func:`cell_logodds`; values at u are the model's log-odds at r = z + u * sigma.
    """
    u = np.arange(TABLE_U0, TABLE_U1 + TABLE_DU, TABLE_DU)
    z = 10.0  # any range: with constant sigma the model depends on r - z only
    r = z + u * model.sigma0
    return np.ascontiguousarray(model.logodds(r, z), dtype=np.float64)


@dataclass(frozen=True)
class FuseResult:
    """What one scan changed: the number of distinct cells updated and the tiles they lie in."""

    cells_updated: int
    tiles_changed: list[tuple[int, int]]


@dataclass(frozen=True)
class BeamTable:
    """Per-beam quantities that do not depend on the pose sample (all ranges in m)."""

    kind: np.ndarray  # int8 (B,): BEAM_SKIP, BEAM_HIT or BEAM_NO_RETURN
    z: np.ndarray  # float64 (B,): the return's range (hits), 0 otherwise
    r_stop: np.ndarray  # float64 (B,): where the traversal ends: z + 3 sigma for hits, range_max otherwise
    r_peak: np.ndarray  # float64 (B,): r*, where the model is largest
    a: np.ndarray  # float64 (B,): start of the occupied peak, z - l/2
    b: np.ndarray  # float64 (B,): end of the occupied peak, z + l/2
    s: np.ndarray  # float64 (B,): sqrt(2) * sigma(z)
    g_peak: np.ndarray  # float64 (B,): the model at the return
    free_until: np.ndarray  # float64 (B,): cells that end before this take l_free (FREE_SHORTCUT_SIGMAS before
    # the peak for hits; r_stop for beams with no return, which are free throughout)


@functools.lru_cache(maxsize=16)
def _constant_sigma_peak(model: SensorModel) -> tuple[float, float]:
    """For a constant-sigma model: r* - z (m), the same for every return, and g(r*), the model's maximum.

    r* - z is computed by the model itself (at z = 0), so z + (r* - z) rounds exactly as
    :meth:`SensorModel.peak_range` does per beam; g(r*) does not depend on z either (up to rounding), and
    the kernels read log-odds from the table for these models, not from g_peak."""
    return float(model.peak_range(np.zeros(1))[0]), float(model.peak(np.ones(1))[0])


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _constant_sigma_beams(ranges, range_min, range_max, sigma0, half, peak_offset, peak):  # pragma: no cover
    """The fields of :class:`BeamTable` for a constant-sigma model, one pass over the beams (the same
    arithmetic as :func:`beam_table`'s array expressions, so the same bits)."""
    n = ranges.shape[0]
    kind = np.empty(n, np.int8)
    fields = np.empty((8, n))  # z, r_stop, r_peak, a, b, s, g_peak, free_until
    for k in range(n):
        r = ranges[k]
        no_return = not math.isfinite(r) or r > range_max
        hit = not no_return and r >= range_min
        kind[k] = BEAM_HIT if hit else (BEAM_NO_RETURN if no_return else BEAM_SKIP)
        z = r if hit else 0.0
        sigma = sigma0 if hit else 1.0
        r_stop = z + TAIL_SIGMAS * sigma if hit else (range_max if no_return else 0.0)
        fields[0, k] = z
        fields[1, k] = r_stop
        fields[2, k] = z + peak_offset if hit else 0.0
        fields[3, k] = z - half
        fields[4, k] = z + half
        fields[5, k] = SQRT2 * sigma
        fields[6, k] = peak if hit else 1.0
        fields[7, k] = z - half - FREE_SHORTCUT_SIGMAS * sigma if hit else r_stop
    return kind, fields


def beam_table(ranges: np.ndarray, model: SensorModel, range_min: float, range_max: float) -> BeamTable:
    """Classify the beams of one scan and precompute their model parameters.

    A range that is NaN, inf or > range_max is "no return": free space up to range_max, no hit.
    A range below range_min is not trusted and the beam is skipped.
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    half = model.l / 2
    if model.sigma == "constant":  # the same sigma, peak offset and peak value for every beam: one compiled pass
        kind, fields = _constant_sigma_beams(ranges, float(range_min), float(range_max), float(model.sigma0), half,
                                             *_constant_sigma_peak(model))
        return BeamTable(kind, *fields)
    no_return = ~np.isfinite(ranges) | (ranges > range_max)
    hit = ~no_return & (ranges >= range_min)
    kind = np.where(hit, BEAM_HIT, np.where(no_return, BEAM_NO_RETURN, BEAM_SKIP)).astype(np.int8)
    z = np.where(hit, ranges, 0.0)
    z_safe = np.where(hit, z, 1.0)
    sigma = np.where(hit, model.sigma_at(z_safe), 1.0)
    r_peak = np.where(hit, model.peak_range(z_safe), 0.0)
    g_peak = np.where(hit, model.peak(z_safe), 1.0)
    r_stop = np.where(hit, z + TAIL_SIGMAS * sigma, np.where(no_return, range_max, 0.0))
    free_until = np.where(hit, z - half - FREE_SHORTCUT_SIGMAS * sigma, r_stop)
    return BeamTable(kind, z, r_stop, r_peak, z - half, z + half, SQRT2 * sigma, g_peak, free_until)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _model_g(r, a, b, s):  # pragma: no cover - compiled
    return 0.25 + 0.25 * math.erf((b - r) / s) - 0.5 * math.erf((a - r) / s)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _squash_logodds(g, g_peak, p_miss, p_hit):  # pragma: no cover - compiled
    if g < 0.5:
        p = 0.5 - (0.5 - p_miss) * (1.0 - 2.0 * g)
    else:
        span = g_peak - 0.5
        fraction = (g - 0.5) / span if span > PEAK_EPS else 0.0
        p = 0.5 + (p_hit - 0.5) * min(fraction, 1.0)
    return math.log(p) - math.log1p(-p)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def cell_logodds(r_in, r_out, r_peak, a, b, s, g_peak, p_miss, p_hit):  # pragma: no cover - compiled
    """The log-odds a hit beam gives a cell it crosses over [r_in, r_out]: the model's maximum there.

    g rises up to r_peak and falls after it, so the maximum is at r_out, at r_in or at r_peak.
    """
    if r_out <= r_peak:
        g = _model_g(r_out, a, b, s)
    elif r_in >= r_peak:
        g = _model_g(r_in, a, b, s)
    else:
        g = g_peak
    return _squash_logodds(g, g_peak, p_miss, p_hit)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _table_logodds(r, z, inv_sigma, table, u0, du):  # pragma: no cover - compiled
    """Linear interpolation in a table of y over u = (r - z) / sigma (constant-sigma models). Multiplies by
    inv_sigma = 1 / sigma and 1 / du: the compiler hoists those divisions out of a ray's loop, and a
    division per cell near the return cost about a tenth of the whole scan."""
    x = ((r - z) * inv_sigma - u0) * (1.0 / du)
    if x <= 0.0:
        return table[0]
    i = int(x)
    if i >= table.shape[0] - 1:
        return table[table.shape[0] - 1]
    t = x - i
    return table[i] + t * (table[i + 1] - table[i])


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def segment_logodds(r_in, r_out, beam_kind, free_until, z, r_peak, a, b, s, g_peak, table, u0, du, p_miss, p_hit,
                    l_free, y_peak):  # pragma: no cover - compiled
    """The value one beam gives a cell it crosses over [r_in, r_out] (m): free before free_until (and for
    beams with no return), else the model's largest value over the segment, from the table when there is one."""
    if r_out < free_until or beam_kind == BEAM_NO_RETURN:
        return l_free
    if table.shape[0] > 0:
        if r_out <= r_peak:
            return _table_logodds(r_out, z, SQRT2 / s, table, u0, du)
        if r_in >= r_peak:
            return _table_logodds(r_in, z, SQRT2 / s, table, u0, du)
        return y_peak
    return cell_logodds(r_in, r_out, r_peak, a, b, s, g_peak, p_miss, p_hit)


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tile_shift):  # pragma: no cover
    """Range at which a ray in cell (ix, iy) leaves that cell's tile (tiles of 2**tile_shift cells)."""
    first_x = (ix >> tile_shift) << tile_shift
    first_y = (iy >> tile_shift) << tile_shift
    last = (1 << tile_shift) - 1
    if step_x > 0:
        exit_x = t_max_x + (first_x + last - ix) * t_delta_x
    elif step_x < 0:
        exit_x = t_max_x + (ix - first_x) * t_delta_x
    else:
        exit_x = FAR
    if step_y > 0:
        exit_y = t_max_y + (first_y + last - iy) * t_delta_y
    elif step_y < 0:
        exit_y = t_max_y + (iy - first_y) * t_delta_y
    else:
        exit_y = FAR
    return min(exit_x, exit_y)


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
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


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _record_index(gx, gy, blocks_w):  # pragma: no cover - compiled
    """Place of window cell (gx, gy) in the one-sample pass's per-cell excess: 8 x 8 blocks, so a ray's
    neighbouring cells share cache lines; block index * 64 + the cell's bit in the block's bit sets (the
    samples pass's scratch is row-major instead, c = gy * win_w + gx)."""
    return ((gy >> 3) * blocks_w + (gx >> 3)) * 64 + ((gy & 7) << 3) + (gx & 7)


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _mark(mask, c, bit, scan_cells, n_scan):  # pragma: no cover - compiled
    """Set a sample's bit in cell c's mask (c = gy * win_w + gx, row-major in the window); a cell touched for
    the first time in this scan is listed in scan_cells. Returns the new list length. As little as possible
    happens here (it runs once per free-space visit): tiles are marked when the masks are folded."""
    seen = mask[c]
    mask[c] = seen | bit
    if seen == 0:
        scan_cells[n_scan] = c
        return n_scan + 1
    return n_scan


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _fold_masks(mask, weight_sum, scan_cells, n_scan, weights, first, n_marked, win_w, win_ix0, win_iy0,
                tile_touched, tile_shift, tx0, ty0):  # pragma: no cover - compiled
    """Add to each listed cell's weight sum the weights of the chunk's samples (first, first + 1, ...)
    whose bits its mask holds, and leave only the LISTED bit. The sum is taken a byte at a time from
    tables of every byte's weight sums (one lookup per byte that holds samples). Marks the tiles of the
    cells listed since the last fold (scan_cells[n_marked:n_scan]) in tile_touched."""
    for q in range(n_marked, n_scan):
        c = scan_cells[q]
        tile_touched[((c // win_w + win_iy0) >> tile_shift) - ty0, ((c % win_w + win_ix0) >> tile_shift) - tx0] = True
    samples = min(MASK_SAMPLES, weights.shape[0] - first)
    n_bytes = (samples + 7) // 8
    sums = np.zeros((n_bytes, 256))
    for byte in range(n_bytes):
        for bit in range(8):
            j = 8 * byte + bit
            w = weights[first + j] if j < samples else 0.0
            top = 1 << bit  # the values whose highest bit is this one: the sum without it, plus w
            for value in range(top, 2 * top):
                sums[byte, value] = sums[byte, value - top] + w
    for q in range(n_scan):
        c = scan_cells[q]
        bits = mask[c]
        total = 0.0
        for byte in range(n_bytes):
            total += sums[byte, (bits >> np.uint64(8 * byte)) & np.uint64(255)]
        weight_sum[c] += total
        mask[c] = LISTED


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _jump_over_tile(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in,
                    tile_shift):  # pragma: no cover - compiled
    """Move a ray in another shard's tile to just before it leaves the tile (the work divides among
    shards); the normal steps then cross into the next tile exactly. Returns (ix, iy, t_max_x, t_max_y,
    r_in, t_exit) with t_exit the range (m) at which the ray leaves the tile."""
    t_exit = _tile_exit(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tile_shift)
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


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _ray_start(x0, y0, theta, stop, res, win_ix0, win_iy0, win_w, win_h):  # pragma: no cover - compiled
    """Start a ray of length stop (m) from (x0, y0) (m, map frame) at theta (rad): returns (inside, ix, iy,
    step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol), the traversal state of
    :func:`mapping.raytrace.dda_start` and the ray's :func:`mapping.raytrace.corner_tol`.

    inside is false when an end cell of the ray is not inside the window (win_ix0, win_iy0, win_w, win_h)
    with a cell to spare. The window covers every ray's reach with a cell to spare, so this never skips; it
    guards the scratch memory once per ray (a segment's cells lie between its end cells, give or take a
    rounding)."""
    dx = math.cos(theta)
    dy = math.sin(theta)
    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(x0, y0, dx, dy, res)
    end_gx = math.floor((x0 + stop * dx) / res) - win_ix0
    end_gy = math.floor((y0 + stop * dy) / res) - win_iy0
    inside = not (min(ix - win_ix0, iy - win_iy0, end_gx, end_gy) < 1 or max(ix - win_ix0, end_gx) >= win_w - 1
                  or max(iy - win_iy0, end_gy) >= win_h - 1)
    return inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, corner_tol(stop)


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol):  # pragma: no cover - compiled
    """:func:`mapping.raytrace.dda_step` on a row-major window index c (row_step = step_y * window width):
    returns (c, t_max_x, t_max_y). Handed (c, 0) and (step_x, row_step), dda_step returns c's move along the
    row and across rows, which add up to the next cell's index."""
    along, across, t_max_x, t_max_y = dda_step(c, 0, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y, tol)
    return along + across, t_max_x, t_max_y


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _accumulate_scan(laser_x, laser_y, laser_yaw, weights, angles, kind, z, r_stop, r_peak, a, b, s, g_peak,
                     free_until, table, u0, du, res, p_miss, p_hit, l_free, win_ix0, win_iy0, win_w, win_h, tile_shift,
                     tx0, ty0, owned, all_owned, mask, weight_sum, excess, scan_cells, tile_touched,
                     stamp_base):  # pragma: no cover - compiled
    """One pass over all (sample, beam, cell) triples; returns the number of distinct cells touched.

    Window cell (gx, gy) is global cell (win_ix0 + gx, win_iy0 + gy); its scratch entries are at
    c = gy * win_w + gx: mask[c] (uint64, the chunk's samples that touched it; zero between scans),
    weight_sum[c] (W; zero between scans), excess[c] (four float64 kept by :func:`add_sample_value` for d: the
    stamp, the current sample's largest d, D1, D2 (D1 and D2 zero between scans); sample j's stamp is
    stamp_base + j, so smaller stamps are from earlier scans). scan_cells lists the touched cells' c. See the
    module docstring.

    Each ray runs in two phases: the free phase, cells that end before the beam's free_until (most of
    them), which take l_free without evaluating the model; then the cells up to the ray's end, valued by
    :func:`segment_logodds`. When the shard owns every tile of the window both phases step the scratch
    index itself (:func:`_step_index`); otherwise the walk keeps the cell's (ix, iy), looks ownership up per
    tile, and in another shard's tile jumps to the tile's exit.
    """
    n_scan = 0
    n_marked = 0  # scan_cells[:n_marked] have their tiles marked
    y_peak = math.log(p_hit) - math.log1p(-p_hit)
    for first in range(0, laser_x.shape[0], MASK_SAMPLES):
        for j in range(first, min(first + MASK_SAMPLES, laser_x.shape[0])):
            bit = np.uint64(1) << np.uint64(j - first)
            sid = float(stamp_base + j)
            w = weights[j]
            for k in range(angles.shape[0]):
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
                inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = _ray_start(
                    laser_x[j], laser_y[j], laser_yaw[j] + angles[k], stop, res, win_ix0, win_iy0, win_w, win_h)
                if not inside:
                    continue
                r_in = 0.0
                mine = True
                cell_tx = tx0 - 1  # the tile whose ownership ``mine`` holds; none yet (no ray leaves the window)
                cell_ty = ty0 - 1
                ray_done = False
                free_limit = min(free_until_k, stop)
                if all_owned:  # every tile owned: both phases walk the scratch index c, no ownership checks
                    c = (iy - win_iy0) * win_w + ix - win_ix0
                    row_step = step_y * win_w
                    while True:  # the free phase
                        r_out = min(t_max_x, t_max_y)
                        if r_out >= free_limit:
                            break
                        if r_out > r_in:
                            n_scan = _mark(mask, c, bit, scan_cells, n_scan)
                        r_in = r_out
                        c, t_max_x, t_max_y = _step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y,
                                                          tol)
                    while True:  # the cells from free_until to the ray's end
                        # (the four lines of a visit repeat the general loop's below: an inlined helper for them
                        # made the whole pass 1.14-1.18x slower, measured 2026-11-26)
                        r_out = min(t_max_x, t_max_y, stop)
                        if r_out > r_in:
                            d = segment_logodds(r_in, r_out, beam_kind, free_until_k, z_k, peak_at, a_k, b_k, s_k,
                                                g_peak_k, table, u0, du, p_miss, p_hit, l_free, y_peak) - l_free
                            n_scan = _mark(mask, c, bit, scan_cells, n_scan)
                            if d > 0.0:
                                add_sample_value(excess, c, sid, w, d)
                        if r_out >= stop:
                            break
                        r_in = r_out
                        c, t_max_x, t_max_y = _step_index(c, step_x, row_step, t_max_x, t_max_y, t_delta_x, t_delta_y,
                                                          tol)
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
                        ix, iy, t_max_x, t_max_y, r_in, t_exit = _jump_over_tile(
                            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift)
                        if t_exit >= stop:
                            ray_done = True
                            break
                        if r_in > jumped_from:
                            continue  # look at the cell the jump landed in
                    elif r_out > r_in:
                        n_scan = _mark(mask, (iy - win_iy0) * win_w + ix - win_ix0, bit, scan_cells, n_scan)
                    r_in = r_out
                    ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x,
                                                        t_delta_y, tol)
                while not ray_done:  # the cells from free_until to the ray's end
                    if (ix >> tile_shift) != cell_tx or (iy >> tile_shift) != cell_ty:
                        cell_tx = ix >> tile_shift
                        cell_ty = iy >> tile_shift
                        mine = owned[cell_ty - ty0, cell_tx - tx0]
                    if not mine:
                        ix, iy, t_max_x, t_max_y, r_in, t_exit = _jump_over_tile(
                            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift)
                        if t_exit >= stop:
                            break
                    r_out = min(t_max_x, t_max_y, stop)
                    if r_out > r_in and mine:
                        d = segment_logodds(r_in, r_out, beam_kind, free_until_k, z_k, peak_at, a_k, b_k, s_k, g_peak_k,
                                            table, u0, du, p_miss, p_hit, l_free, y_peak) - l_free
                        c = (iy - win_iy0) * win_w + ix - win_ix0
                        n_scan = _mark(mask, c, bit, scan_cells, n_scan)
                        if d > 0.0:
                            add_sample_value(excess, c, sid, w, d)
                    if r_out >= stop:
                        break
                    r_in = r_out
                    ix, iy, t_max_x, t_max_y = dda_step(ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x,
                                                        t_delta_y, tol)
        _fold_masks(mask, weight_sum, scan_cells, n_scan, weights, first, n_marked, win_w, win_ix0, win_iy0,
                    tile_touched, tile_shift, tx0, ty0)
        n_marked = n_scan
    return n_scan


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _raise_excess(touched, raised, excess, gx, gy, d, blocks_w):  # pragma: no cover - compiled
    """One-sample pass: mark window cell (gx, gy) touched and keep its largest excess d > 0 (see
    :func:`_accumulate_single` for the arrays)."""
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


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bit_count(bits):  # pragma: no cover - compiled
    """The number of set bits of an int64 (one loop iteration per set bit)."""
    n = 0
    while bits != 0:
        bits &= bits - 1
        n += 1
    return n


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _accumulate_single(laser_x, laser_y, laser_yaw, angles, kind, z, r_stop, r_peak, a, b, s, g_peak, free_until, table,
                       u0, du, res, p_miss, p_hit, l_free, win_ix0, win_iy0, win_w, win_h, tile_shift, tx0, ty0, owned,
                       all_owned, touched, raised, excess, blocks_w, blocks_h,
                       tile_touched):  # pragma: no cover - compiled
    """The pass for one pose sample (laser at laser_x, laser_y m, heading laser_yaw rad): every (beam, cell)
    pair; returns the number of distinct cells touched and marks their tiles in tile_touched.

    Same walk as :func:`_accumulate_scan` (window, two phases, shards' tiles), but with one sample the cell
    just keeps the largest excess d of the beams that touch it. The window's origin is a multiple of 8 cells,
    so its 8 x 8 blocks are blocks of the global grid. Per block (index (gy >> 3) * blocks_w + (gx >> 3)),
    touched[block] and raised[block] (int64) hold bit (gy & 7) * 8 + (gx & 7) for the cells touched in this
    scan and for those with an excess d > 0, whose largest d is excess[c] (c from :func:`_record_index`, valid
    only where the raised bit is set). Free-phase visits only set a bit: no write to the large excess array.
    The bits are zero between scans (:func:`_apply_single` clears them)."""
    y_peak = math.log(p_hit) - math.log1p(-p_hit)
    for k in range(angles.shape[0]):
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
        inside, ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol = _ray_start(
            laser_x, laser_y, laser_yaw + angles[k], stop, res, win_ix0, win_iy0, win_w, win_h)
        if not inside:
            continue
        r_in = 0.0
        mine = True
        cell_tx = tx0 - 1  # the tile whose ownership ``mine`` holds; none yet (no ray leaves the window)
        cell_ty = ty0 - 1
        ray_done = False
        free_limit = min(free_until_k, stop)
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
        # the shard's walk below is written out as in _accumulate_scan: helpers for the ownership look-up and
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
                ix, iy, t_max_x, t_max_y, r_in, t_exit = _jump_over_tile(
                    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift)
                if t_exit >= stop:
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
                ix, iy, t_max_x, t_max_y, r_in, t_exit = _jump_over_tile(
                    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, r_in, tile_shift)
                if t_exit >= stop:
                    break
            r_out = min(t_max_x, t_max_y, stop)
            if r_out > r_in and mine:
                d = segment_logodds(r_in, r_out, beam_kind, free_until_k, z_k, peak_at, a_k, b_k, s_k, g_peak_k, table,
                                    u0, du, p_miss, p_hit, l_free, y_peak) - l_free
                _raise_excess(touched, raised, excess, ix - win_ix0, iy - win_iy0, d, blocks_w)
            if r_out >= stop:
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


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _apply_scan(scan_cells, n_scan, mask, weight_sum, excess, stamp_base, l_free, win_w, win_ix0, win_iy0,
                tile_shift, tx0, ty0, slot_map, logodds, variance, observed, l_min, l_max):  # pragma: no cover
    """Add the scan's weighted mean to each touched cell (clamped) and its spread to the variance layer, from
    the moments l_free W + D1 and l_free^2 W + 2 l_free D1 + D2; clear the cells' masks and weight sums for
    the next scan."""
    for q in range(n_scan):
        c = scan_cells[q]
        ix = c % win_w + win_ix0
        iy = c // win_w + win_iy0
        slot = slot_map[(iy >> tile_shift) - ty0, (ix >> tile_shift) - tx0]
        in_tile = (1 << tile_shift) - 1
        ly = iy & in_tile
        lx = ix & in_tile
        mask[c] = 0
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


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _apply_single(touched, raised, excess, blocks_w, blocks_h, w, l_free, win_ix0, win_iy0, tile_shift, tx0, ty0,
                  slot_map, logodds, observed, l_min, l_max):  # pragma: no cover - compiled
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


@nb.njit(cache=True, nogil=True)
def _finite_weighted(samples, weights):  # pragma: no cover - compiled
    """Whether every sample coordinate and weight is finite and every weight >= 0, and the weights' sum."""
    for j in range(samples.shape[0]):
        for i in range(3):
            if not math.isfinite(samples[j, i]):
                return False, 0.0
    total = 0.0
    for w in weights:
        if not (math.isfinite(w) and w >= 0.0):
            return False, 0.0
        total += w
    return True, total


def check_scan(ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray,
               beams: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate one scan's inputs and return them as arrays: ranges (B,), samples (M, 3), weights (M,)."""
    ranges = np.asarray(ranges)
    samples = np.asarray(samples, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64).reshape(-1)
    if ranges.shape != (beams,):
        raise InputError(f"scan has {ranges.shape} ranges but the laser has {beams} beams")
    if samples.shape == (3,):  # one pose
        samples = samples[None]
    if samples.ndim != 2 or samples.shape[1] != 3 or samples.shape[0] == 0 or weights.shape[0] != samples.shape[0]:
        raise InputError(f"need M >= 1 samples (M, 3) and weights (M,), got {samples.shape} and {weights.shape}")
    finite, total = _finite_weighted(samples, weights)
    if not finite:
        raise InputError("pose samples and weights must be finite and the weights non-negative")
    if abs(total - 1.0) > 1e-4:
        raise InputError(f"weights must sum to 1, got {total:.6g}")
    return ranges, samples, weights


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _laser_poses(samples, ox, oy, oyaw):  # pragma: no cover - compiled
    poses = np.empty((samples.shape[0], 3))
    for j in range(samples.shape[0]):
        x, y, yaw = samples[j, 0], samples[j, 1], samples[j, 2]
        c = math.cos(yaw)
        s = math.sin(yaw)
        poses[j, 0] = x + c * ox - s * oy
        poses[j, 1] = y + s * ox + c * oy
        poses[j, 2] = yaw + oyaw
    return poses


def check_window(x_lo: float, y_lo: float, x_hi: float, y_hi: float, reach: float, resolution: float) -> None:
    """Refuse a scan whose scratch window cannot be held, before any cell index is computed from it: one that
    reaches beyond MAX_CELL_INDEX cells from the origin, or spans more than MAX_WINDOW_CELLS cells. The laser
    poses lie in [x_lo, x_hi] x [y_lo, y_hi] (m) and ``reach`` (m) is the rays' longest reach."""
    farthest = max(abs(x_lo), abs(x_hi), abs(y_lo), abs(y_hi))
    if not (farthest + reach) / resolution <= MAX_CELL_INDEX:  # also NaN and inf
        raise InputError(f"a scan {farthest:.6g} m from the map origin with rays {reach:.6g} m long reaches beyond "
                         f"the {MAX_CELL_INDEX * resolution:.3g} m that {resolution} m cells cover")
    width = (x_hi - x_lo + 2 * reach) / resolution + 9  # + the 8-cell alignment and a cell to spare
    height = (y_hi - y_lo + 2 * reach) / resolution + 9
    if width * height > MAX_WINDOW_CELLS:
        raise InputError(f"one scan would span about {width:.0f} x {height:.0f} cells of {resolution} m, more than the "
                         f"{MAX_WINDOW_CELLS} a scan may: its pose samples spread over {x_hi - x_lo:.4g} m x "
                         f"{y_hi - y_lo:.4g} m and its rays reach {reach:.4g} m (a diverged pose estimate, or a range "
                         f"limit too long for this resolution?)")


def laser_poses(samples: np.ndarray, sensor_offset: np.ndarray) -> np.ndarray:
    """Laser poses (M, 3) in the map frame from robot poses (M, 3) and the laser's (x, y, yaw) in the robot frame
    (compiled: the dozen array operations this takes in numpy cost a tenth of a one-pose scan)."""
    ox, oy, oyaw = np.asarray(sensor_offset, dtype=np.float64).tolist()
    return _laser_poses(np.ascontiguousarray(samples, dtype=np.float64), ox, oy, oyaw)


def merge_duplicates(samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge identical pose samples (summing their weights) and drop zero-weight ones.

    Resampled particle filters repeat many particles; merging them before ray casting gives the same map
    for less work. Order: first occurrence of each distinct pose.
    """
    if len(weights) == 1 and weights[0] > 0:
        return samples, weights
    keep = weights > 0
    samples, weights = samples[keep], weights[keep]
    if len(samples) == 1 or np.unique(samples[:, 0]).size == len(samples):  # distinct x: distinct poses (fast)
        return samples, weights
    unique, first, inverse = np.unique(samples, axis=0, return_index=True, return_inverse=True)
    if len(unique) == len(samples):
        return samples, weights
    merged = np.bincount(inverse.ravel(), weights=weights, minlength=len(unique))
    order = np.argsort(first)
    return unique[order], merged[order]


class MonteCarloFusion:
    """Fuses scans of one laser into a :class:`TiledGrid`, one compiled pass per scan.

    beam_angles: (B,) rad in the laser frame; range_min, range_max: m; sensor_offset: the laser's
    (x m, y m, yaw rad) in the robot frame; owns_tile: optional (tx, ty) -> bool, for a shard that fuses
    only its own tiles (the cells of other tiles are skipped); merge_identical: merge identical pose
    samples before ray casting (on by default; off only to measure what merging saves).
    """

    def __init__(
        self,
        grid: TiledGrid,
        model: SensorModel,
        beam_angles: np.ndarray,
        range_min: float,
        range_max: float,
        sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        owns_tile: Callable[[int, int], bool] | None = None,
        merge_identical: bool = True,
    ) -> None:
        if not np.isclose(grid.resolution, model.resolution):
            raise InputError(f"grid resolution {grid.resolution} m differs from the sensor model's {model.resolution} m")
        if not 0 <= range_min < range_max or not np.isfinite(range_max):
            raise InputError(f"need 0 <= range_min < range_max < inf, got {range_min} and {range_max}")
        self.grid = grid
        self.model = model
        self.angles = np.ascontiguousarray(beam_angles, dtype=np.float64)
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.sensor_offset = np.asarray(sensor_offset, dtype=np.float64)
        self.owns_tile = owns_tile
        self.merge_identical = merge_identical
        self._owned_cache: dict[tuple[int, int], bool] = {}
        self._owned_windows: dict[tuple[int, int, int, int], tuple[np.ndarray, bool]] = {}
        self._stamp_next = 1
        self._scratch_size = 0
        self._single_blocks = 0
        self._table = logodds_table(model) if model.sigma == "constant" else np.zeros(0)
        self._l_free, self._l_min, self._l_max = model.l_free, model.l_min, model.l_max  # (properties: computed)

    def _scratch(self, cells: int) -> None:
        if cells <= self._scratch_size:
            return
        self._scratch_size = cells
        # per cell (see _accumulate_scan): the samples' mask, the weight sum, the excess record
        self._mask = np.zeros(cells, np.uint64)
        self._weight_sum = np.zeros(cells, np.float64)
        self._excess = np.zeros((cells, 4), np.float64)
        self._scan_cells = np.zeros(cells, np.int64)

    def _single_scratch(self, blocks: int) -> None:
        if blocks <= self._single_blocks:
            return
        self._single_blocks = blocks
        # per 8 x 8 block and per cell (see _accumulate_single): touched and raised bits, the largest excess
        self._touched_bits = np.zeros(blocks, np.int64)
        self._raised_bits = np.zeros(blocks, np.int64)
        self._largest = np.zeros(blocks * 64, np.float64)

    def _owned_mask(self, tx0: int, ty0: int, ntx: int, nty: int) -> tuple[np.ndarray, bool]:
        """Which tiles of the window's ntx x nty tiles from (tx0, ty0) the shard owns, and whether all; kept
        per window (the kernels only read it)."""
        key = (tx0, ty0, ntx, nty)
        window = self._owned_windows.get(key)
        if window is None:
            owned = np.ones((nty, ntx), np.bool_)
            if self.owns_tile is not None:
                for j in range(nty):
                    for i in range(ntx):
                        tile = (tx0 + i, ty0 + j)
                        if tile not in self._owned_cache:
                            self._owned_cache[tile] = bool(self.owns_tile(*tile))
                        owned[j, i] = self._owned_cache[tile]
            window = self._owned_windows[key] = (owned, bool(owned.all()))
        return window

    def _tile_slots(self, touched: np.ndarray, tx0: int, ty0: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
        """The grid slot of each touched tile of the window (tiles created as needed; -1 elsewhere), and the
        touched tiles' keys in row order."""
        slot_map = np.full(touched.shape, -1, np.int64)
        changed = []
        for j, i in zip(*(index.tolist() for index in np.nonzero(touched))):
            key = (tx0 + i, ty0 + j)
            slot_map[j, i] = self.grid.slot(key)
            changed.append(key)
        return slot_map, changed

    def fuse(self, ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray) -> FuseResult:
        """Fuse one scan: ranges (B,) m, robot pose samples (M, 3) map frame, weights (M,) summing to 1.

        One distinct sample (after merging) takes the one-sample pass (:func:`_accumulate_single`), which gives
        the same map as the samples pass for less work."""
        ranges, samples, weights = check_scan(ranges, samples, weights, self.angles.shape[0])
        if self.merge_identical:
            samples, weights = merge_duplicates(samples, weights)
        beams = beam_table(ranges, self.model, self.range_min, self.range_max)
        if not (beams.kind != BEAM_SKIP).any():
            return FuseResult(0, [])
        lasers = laser_poses(samples, self.sensor_offset)

        grid = self.grid
        res = grid.resolution
        reach = float(beams.r_stop.max()) + res
        if len(lasers) == 1:  # (reductions cost a few microseconds each)
            (x_lo, y_lo, _), = lasers.tolist()
            x_hi, y_hi = x_lo, y_lo
        else:
            (x_lo, y_lo), (x_hi, y_hi) = lasers[:, :2].min(axis=0).tolist(), lasers[:, :2].max(axis=0).tolist()
        check_window(x_lo, y_lo, x_hi, y_hi, reach, res)
        win_ix0 = math.floor((x_lo - reach) / res) & ~7  # a multiple of 8: the scratch's 8 x 8 blocks are the grid's
        win_iy0 = math.floor((y_lo - reach) / res) & ~7
        win_w = math.floor((x_hi + reach) / res) - win_ix0 + 1
        win_h = math.floor((y_hi + reach) / res) - win_iy0 + 1
        shift = grid.tile_shift
        tx0, ty0 = win_ix0 >> shift, win_iy0 >> shift
        ntx = ((win_ix0 + win_w - 1) >> shift) - tx0 + 1
        nty = ((win_iy0 + win_h - 1) >> shift) - ty0 + 1
        blocks_w, blocks_h = -(-win_w // 8), -(-win_h // 8)
        owned, all_owned = self._owned_mask(tx0, ty0, ntx, nty)
        touched = np.zeros((nty, ntx), np.bool_)
        model = self.model
        if len(samples) == 1:
            self._single_scratch(blocks_w * blocks_h)
            x, y, yaw = lasers[0].tolist()
            n_scan = _accumulate_single(
                x, y, yaw, self.angles, beams.kind, beams.z, beams.r_stop, beams.r_peak, beams.a, beams.b, beams.s,
                beams.g_peak, beams.free_until, self._table, TABLE_U0, TABLE_DU, res, model.p_miss, model.p_hit,
                self._l_free, win_ix0, win_iy0, win_w, win_h, shift, tx0, ty0, owned, all_owned, self._touched_bits,
                self._raised_bits, self._largest, blocks_w, blocks_h, touched,
            )
            slot_map, changed = self._tile_slots(touched, tx0, ty0)
            _apply_single(self._touched_bits, self._raised_bits, self._largest, blocks_w, blocks_h, float(weights[0]),
                          self._l_free, win_ix0, win_iy0, shift, tx0, ty0, slot_map, grid.logodds, grid.observed,
                          self._l_min, self._l_max)
            return FuseResult(int(n_scan), changed)

        self._scratch(win_w * win_h)
        if self._stamp_next + len(samples) >= STAMP_LIMIT:
            self._excess[:] = 0
            self._stamp_next = 1
        stamp_base = self._stamp_next
        self._stamp_next += len(samples)
        n_scan = _accumulate_scan(
            lasers[:, 0].copy(), lasers[:, 1].copy(), lasers[:, 2].copy(), weights, self.angles,
            beams.kind, beams.z, beams.r_stop, beams.r_peak, beams.a, beams.b, beams.s, beams.g_peak,
            beams.free_until, self._table, TABLE_U0, TABLE_DU, res, model.p_miss, model.p_hit, self._l_free,
            win_ix0, win_iy0, win_w, win_h, shift, tx0, ty0, owned, all_owned,
            self._mask, self._weight_sum, self._excess, self._scan_cells, touched, stamp_base,
        )
        slot_map, changed = self._tile_slots(touched, tx0, ty0)
        _apply_scan(self._scan_cells, n_scan, self._mask, self._weight_sum, self._excess, stamp_base, self._l_free,
                    win_w, win_ix0, win_iy0, shift, tx0, ty0, slot_map, grid.logodds, grid.variance, grid.observed,
                    self._l_min, self._l_max)
        return FuseResult(int(n_scan), changed)
