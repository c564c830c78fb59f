"""What one beam of a scan gives each cell it crosses, as the compiled passes read it.

:func:`beam_table` classifies a scan's beams (hit, no return, skipped) and precomputes, per beam, the sensor
model's parameters (docs/sensor_model.md; ranges in m along the beam). :func:`segment_logodds` is the value a
beam gives a cell it crosses over [r_in, r_out]: l_free before the beam's free shortcut, else the model's
largest value over the segment, read from a table over u = (r - z) / sigma for constant-sigma models
(:func:`logodds_table`) or evaluated in closed form otherwise. Used by the regular grid's passes
(:mod:`mapping.samples_pass`, :mod:`mapping.single_pass`) and by the adaptive grid's evidence pass.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from mapping.jit import kernel
from mapping.sensor_model import PEAK_EPS, TAIL_SIGMAS, SensorModel

#: beam kinds in the compiled kernel
BEAM_SKIP, BEAM_HIT, BEAM_NO_RETURN = 0, 1, 2


#: cells whose segment ends this many sigma before the peak take the free value without evaluating erf
#: (the model differs from 0 by < 3e-7 there)
FREE_SHORTCUT_SIGMAS = 5.0

SQRT2 = math.sqrt(2.0)

#: constant-sigma models read the log-odds from a table over u = (r - z) / sigma, from the free shortcut to
#: the traversal's end, with linear interpolation (error < 2e-4 in log-odds at the squashing's kink, far less
#: elsewhere; tested)
TABLE_DU = 0.002
#: the widest peak the table covers: l/2 up to this many sigma (the free shortcut then starts above TABLE_U0)
TABLE_PEAK_SIGMAS = 8.0
TABLE_U0 = -(FREE_SHORTCUT_SIGMAS + 1.0) - TABLE_PEAK_SIGMAS
TABLE_U1 = 3.5  # past the traversal's end at 3 sigma


def logodds_table(model: SensorModel) -> np.ndarray:
    """y(u) on u = TABLE_U0 + i * TABLE_DU up to TABLE_U1 for a constant-sigma model whose peak half-width l/2 is
    at most TABLE_PEAK_SIGMAS sigma; an empty table otherwise, and the kernels evaluate the closed form (sigma
    that varies with the range, or a peak so wide against sigma, e.g. 0.2 m cells and sigma 0.01 m, that the
    cells before it would read the table below its start and get a value from inside the peak).

    Before the peak only the rising side is read and after it only the falling side, as in
    :func:`cell_logodds`; values at u are the model's log-odds at r = z + u * sigma.
    """
    if model.sigma != "constant" or model.l / 2 > TABLE_PEAK_SIGMAS * model.sigma0:
        return np.zeros(0)
    u = np.arange(TABLE_U0, TABLE_U1 + TABLE_DU, TABLE_DU)
    z = 10.0  # any range: with constant sigma the model depends on r - z only
    r = z + u * model.sigma0
    return np.ascontiguousarray(model.logodds(r, z), dtype=np.float64)


class BeamTable(NamedTuple):
    """Per-beam quantities that do not depend on the pose sample (all ranges in m). A kernel takes it as a plain
    tuple (``tuple(beams)``: numba's dispatcher types a plain tuple in C, a named one through Python) and names
    it again inside (``BeamTable(*beams)``)."""

    kind: np.ndarray  # int8 (B,): BEAM_SKIP, BEAM_HIT or BEAM_NO_RETURN
    z: np.ndarray  # float64 (B,): the return's range (hits), 0 otherwise
    r_stop: np.ndarray  # float64 (B,): where the traversal ends: z + 3 sigma for hits, the no-return range otherwise
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


@kernel(nogil=True, error_model="numpy")
def _constant_sigma_beams(ranges, range_min, range_max, clear, sigma0, half, peak_offset, peak):  # pragma: no cover
    """The fields of :class:`BeamTable` for a constant-sigma model, one pass over the beams (the same
    arithmetic as :func:`beam_table`'s array expressions, so the same bits); ``clear``: how far a beam with no
    return clears (m; 0: it is skipped)."""
    n = ranges.shape[0]
    kind = np.empty(n, np.int8)
    fields = np.empty((8, n))  # z, r_stop, r_peak, a, b, s, g_peak, free_until
    for k in range(n):
        r = ranges[k]
        no_return = r != r or r > range_max  # NaN, +inf or beyond; -inf (too close) is below range_min
        hit = not no_return and r >= range_min and r > 0.0  # (0: no reading, whatever range_min)
        clears = no_return and clear > 0.0
        kind[k] = BEAM_HIT if hit else (BEAM_NO_RETURN if clears else BEAM_SKIP)
        z = r if hit else 0.0
        sigma = sigma0 if hit else 1.0
        r_stop = z + TAIL_SIGMAS * sigma if hit else (clear if clears else 0.0)
        fields[0, k] = z
        fields[1, k] = r_stop
        fields[2, k] = z + peak_offset if hit else 0.0
        fields[3, k] = z - half
        fields[4, k] = z + half
        fields[5, k] = SQRT2 * sigma
        fields[6, k] = peak if hit else 1.0
        fields[7, k] = z - half - FREE_SHORTCUT_SIGMAS * sigma if hit else r_stop
    return kind, fields


def beam_table(
    ranges: np.ndarray, model: SensorModel, range_min: float, range_max: float, no_return_range: float | None = None
) -> BeamTable:
    """Classify the beams of one scan and precompute their model parameters.

    A range that is NaN, +inf or > range_max is "no return": free space up to ``no_return_range`` (m, at most
    range_max; None: range_max), no hit; with a no_return_range of 0 such a beam is skipped (it says nothing: a real
    laser's missing echo may come from a dark or glancing surface near it, docs/sensor_model.md).
    A range below range_min is not trusted and the beam is skipped; so is -inf, a reading too close to measure
    (REP 117), which says nothing of the space along the beam, and 0 with a range_min of 0 (no laser sees an obstacle
    at its own window; drivers and CARMEN logs write 0 for no reading, which was fused as a hit in the laser's cell).
    """
    ranges = np.asarray(ranges, dtype=np.float64)
    half = model.l / 2
    clear = float(range_max if no_return_range is None else no_return_range)
    if model.sigma == "constant":  # the same sigma, peak offset and peak value for every beam: one compiled pass
        kind, fields = _constant_sigma_beams(
            ranges, float(range_min), float(range_max), clear, float(model.sigma0), half, *_constant_sigma_peak(model)
        )
        return BeamTable(kind, *fields)
    hit, no_return = _hits_and_no_returns(ranges, range_min, range_max)
    no_return &= clear > 0.0
    kind = np.where(hit, BEAM_HIT, np.where(no_return, BEAM_NO_RETURN, BEAM_SKIP)).astype(np.int8)
    z = np.where(hit, ranges, 0.0)
    z_safe = np.where(hit, z, 1.0)
    sigma = np.where(hit, model.sigma_at(z_safe), 1.0)
    r_peak = np.where(hit, model.peak_range(z_safe), 0.0)
    g_peak = np.where(hit, model.peak(z_safe), 1.0)
    r_stop = np.where(hit, z + TAIL_SIGMAS * sigma, np.where(no_return, clear, 0.0))
    free_until = np.where(hit, z - half - FREE_SHORTCUT_SIGMAS * sigma, r_stop)
    return BeamTable(kind, z, r_stop, r_peak, z - half, z + half, SQRT2 * sigma, g_peak, free_until)


def _hits_and_no_returns(ranges: np.ndarray, range_min: float, range_max: float) -> tuple[np.ndarray, np.ndarray]:
    """(hit, no_return) masks of a scan's ranges (m, float64), as :func:`beam_table` classifies them (its compiled
    constant-sigma pass makes the same test beam by beam): NaN or beyond range_max is no return; a hit lies in
    [range_min, range_max] and above 0; the rest (below range_min, -inf, 0) is skipped."""
    no_return = np.isnan(ranges) | (ranges > range_max)
    return ~no_return & (ranges >= range_min) & (ranges > 0.0), no_return


def farthest_walk(
    ranges: np.ndarray, range_min: float, range_max: float, no_return_range: float | None = None
) -> float:
    """How far (m) from the laser :func:`beam_table` walks a scan's beams before their tails: its longest hit (a
    range in [range_min, range_max], above 0), and ``no_return_range`` (None: range_max) when a beam has no return
    (NaN, or beyond range_max) and such beams clear; 0 when no beam is used. ``SensorModel.beam_reach`` of it bounds
    the cells the scan's fusion may reach (its tails included), however far the laser's range_max lies."""
    ranges = np.asarray(ranges, dtype=np.float64)
    clear = float(range_max if no_return_range is None else no_return_range)
    hit, no_return = _hits_and_no_returns(ranges, range_min, range_max)
    farthest = float(ranges[hit].max(initial=0.0))
    if clear > 0.0 and bool(no_return.any()):
        farthest = max(farthest, clear)
    return farthest


@kernel(nogil=True, error_model="numpy")
def _model_g(r, a, b, s):  # pragma: no cover - compiled
    return 0.25 + 0.25 * math.erf((b - r) / s) - 0.5 * math.erf((a - r) / s)


@kernel(nogil=True, error_model="numpy")
def _squash_logodds(g, g_peak, p_miss, p_hit):  # pragma: no cover - compiled
    if g < 0.5:
        p = 0.5 - (0.5 - p_miss) * (1.0 - 2.0 * g)
    else:
        span = g_peak - 0.5
        fraction = (g - 0.5) / span if span > PEAK_EPS else 0.0
        p = 0.5 + (p_hit - 0.5) * min(fraction, 1.0)
    return math.log(p) - math.log1p(-p)


@kernel(nogil=True, error_model="numpy")
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


@kernel(nogil=True, error_model="numpy")
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


class LogOddsModel(NamedTuple):
    """What the kernels read of a sensor model: the constant-sigma table (:func:`logodds_table`, or empty) over u
    from u0 in steps of du, p_miss and p_hit, l_free (the free cell's log-odds) and y_peak (the log-odds at the
    peak, logit(p_hit)); built once per fusion by :func:`logodds_model`."""

    table: np.ndarray
    u0: float
    du: float
    p_miss: float
    p_hit: float
    l_free: float
    y_peak: float


@kernel(nogil=True, error_model="numpy")
def _logit(p):  # pragma: no cover - compiled
    return math.log(p) - math.log1p(-p)


def logodds_model(model: SensorModel) -> LogOddsModel:
    """The :class:`LogOddsModel` of a sensor model (y_peak computed by numba, as the kernels computed it)."""
    return LogOddsModel(
        logodds_table(model), TABLE_U0, TABLE_DU, model.p_miss, model.p_hit, model.l_free, _logit(model.p_hit)
    )


class Beam(NamedTuple):
    """One beam's entries of a :class:`BeamTable`, as the passes and :func:`segment_logodds` read them (ranges in m)."""

    kind: int
    r_stop: float
    free_until: float
    z: float
    r_peak: float
    a: float
    b: float
    s: float
    g_peak: float


@kernel(nogil=True, error_model="numpy", inline="always")
def beam_at(beams, k):  # pragma: no cover - compiled
    """Beam k of a :class:`BeamTable`, in locals: the compiler cannot hoist loads past a pass's scratch writes."""
    return Beam(
        beams.kind[k],
        beams.r_stop[k],
        beams.free_until[k],
        beams.z[k],
        beams.r_peak[k],
        beams.a[k],
        beams.b[k],
        beams.s[k],
        beams.g_peak[k],
    )


@kernel(nogil=True, error_model="numpy", inline="always")
def segment_logodds(r_in, r_out, beam, model):  # pragma: no cover - compiled
    """The value one :class:`Beam` gives a cell it crosses over [r_in, r_out] (m): free before free_until (and for
    beams with no return), else the model's largest value over the segment, from the table when there is one
    (``model``: a :class:`LogOddsModel`)."""
    if r_out < beam.free_until or beam.kind == BEAM_NO_RETURN:
        return model.l_free
    if model.table.shape[0] > 0:
        if r_out <= beam.r_peak:
            return _table_logodds(r_out, beam.z, SQRT2 / beam.s, model.table, model.u0, model.du)
        if r_in >= beam.r_peak:
            return _table_logodds(r_in, beam.z, SQRT2 / beam.s, model.table, model.u0, model.du)
        return model.y_peak
    return cell_logodds(r_in, r_out, beam.r_peak, beam.a, beam.b, beam.s, beam.g_peak, model.p_miss, model.p_hit)
