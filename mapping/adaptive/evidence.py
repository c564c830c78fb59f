"""One scan's evidence for the adaptive grid, gathered in one compiled pass over (sample, beam, finest cell).

Each ray under each pose sample is walked at the finest resolution by the ray walk of the regular grid's passes
(:func:`mapping.window_walk.walk_ray`, every tile owned and no free phase). The pass records

* per finest cell, the regular grid's Monte Carlo evidence (paper, eq. 9), computed exactly as
  :mod:`mapping.fusion`'s kernel does: a beam gives the cell the model's largest value over its segment
  inside the cell, one sample gives the cell the largest value any of its beams proposes, and the cell
  gets the weighted moments sum_j w_j y_ij and sum_j w_j y_ij^2;
* per cell of every level, one weighted count of each ray's outcome (paper, section VI.A): a *hit* if the
  ray's return lies in the cell, a *miss* if the ray leaves the cell before its return, an *unknown* if the
  ray's return lies before the cell (the cell is behind an obstacle along that beam). The finest cells a
  ray crosses form, at level k, consecutive *runs* inside one level-k cell (a ray crosses a square once);
  each run of a ray of sample j adds w_j to one of the three counts of its cell. A beam without a return is
  a miss everywhere up to its laser's no-return range (range_max unless the fusion is told otherwise).

Unknowns are counted only where the split test reads them: at levels >= 1 (the finest cells are never
split) and in cells that the scan also gives hits or misses (a cell is tested only when the scan sees it).
They are counted in a second loop that walks each ray from its return through level-1 cells (the same walk on
cells twice as wide), so the long stretches behind the returns cost little.

Nothing here depends on which cells are active, so after the pass the split test can descend through any
level and the update can aggregate the finest evidence into whatever cells are active.

Evidence lives in scratch windows that cover the scan's reach: the finest window for the log-odds records,
and per level k the level-k cells over it for the counts, flattened into one array with per-level offsets.
Records carry stamps, as in the regular kernel, so the scratch is reused without clearing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from mapping.beam_model import BEAM_HIT, BEAM_SKIP, BeamTable, LogOddsModel, beam_at, segment_logodds
from mapping.jit import kernel
from mapping.raytrace import FAR
from mapping.samples_pass import STAMP_LIMIT, add_sample_value
from mapping.scan_input import check_window
from mapping.window_walk import Tiles, Window, ray_start, walk_ray

#: columns of a count record: [stamp, hits, misses, unknowns]
HIT, MISS, UNKNOWN = 1, 2, 3


class Levels(NamedTuple):
    """The scratch windows per level k (int64 arrays, one entry a level): level-k cells ax in [x0[k], x0[k] + w[k]),
    ay in [y0[k], y0[k] + h[k]); the counts of level k >= 1 start at off[k] in the count records."""

    x0: np.ndarray
    y0: np.ndarray
    w: np.ndarray
    h: np.ndarray
    off: np.ndarray


class EvidenceScratch(NamedTuple):
    """rec: (finest window cells, 6) records; cnt: (counted cells, 4) count records; seen: (counted cells,) uint8;
    touched: the finest cells with log-odds evidence (see :func:`_scan_evidence`); run_hit, run_len: (levels,)
    bool, per level whether the open run of a ray holds its return and whether it has positive length; owned:
    a (1, 1) True, the tiles of a walk that owns every tile."""

    rec: np.ndarray
    cnt: np.ndarray
    seen: np.ndarray
    touched: np.ndarray
    run_hit: np.ndarray
    run_len: np.ndarray
    owned: np.ndarray


class _Runs(NamedTuple):
    """What the evidence visitors read and write: the scratch, the levels' windows, the model, the sample's stamp
    sid and weight w, and the scan's stamp_base."""

    scratch: EvidenceScratch
    levels: Levels
    model: LogOddsModel
    sid: float
    w: float
    stamp_base: int


class _Unknowns(NamedTuple):
    """What the unknowns' visitor reads and writes: ``seen`` and the count records, the levels' windows, and the
    sample's weight w."""

    seen: np.ndarray
    cnt: np.ndarray
    levels: Levels
    w: float


@kernel(nogil=True, error_model="numpy", inline="always")
def _bit_length(v):  # pragma: no cover - compiled
    n = 0
    while v > 0:
        v >>= 1
        n += 1
    return n


@kernel(nogil=True, error_model="numpy", inline="always")
def _direction(theta):  # pragma: no cover - compiled
    """The unit direction of a ray at heading theta (rad, map frame), from a cos and a sin of the heading. (The
    regular grid's passes compose it from the cosines and sines of the laser's heading and the beam's angle,
    :func:`mapping.window_walk.beam_direction`, which differs in the last bits.)"""
    return math.cos(theta), math.sin(theta)


@kernel(nogil=True, error_model="numpy", inline="always")
def _levels_left(ix, iy, prev_ix, prev_iy, n_levels):  # pragma: no cover - compiled
    """How many levels (from the finest) of cell (prev_ix, prev_iy) the step to (ix, iy) leaves."""
    moved = (ix ^ prev_ix) | (iy ^ prev_iy)
    return n_levels if moved < 0 else min(_bit_length(moved), n_levels)


@kernel(nogil=True, error_model="numpy", inline="always")
def _close_runs(runs, top, ix, iy, hit_passed):  # pragma: no cover - compiled
    """Close the runs of levels 0..top-1 that end in cell (ix, iy), finest first: fold each into its parent run,
    count a hit or a miss (a run that began beyond the return is left to the unknowns' pass), and open the next."""
    rec, cnt, seen = runs.scratch.rec, runs.scratch.cnt, runs.scratch.seen
    lv, run_hit, run_len = runs.levels, runs.scratch.run_hit, runs.scratch.run_len
    n_levels = lv.x0.shape[0]
    for lvl in range(top):
        if run_len[lvl] and (run_hit[lvl] or not hit_passed):
            if lvl + 1 < n_levels:
                run_len[lvl + 1] = True
                if run_hit[lvl]:
                    run_hit[lvl + 1] = True
            if lvl == 0:  # a finest run is the cell just recorded: its counts share the record
                rec[(iy - lv.y0[0]) * lv.w[0] + ix - lv.x0[0], 4 if run_hit[0] else 5] += runs.w
            else:
                q = lv.off[lvl] + ((iy >> lvl) - lv.y0[lvl]) * lv.w[lvl] + ((ix >> lvl) - lv.x0[lvl])
                if cnt[q, 0] != runs.stamp_base:
                    cnt[q, 0] = runs.stamp_base
                    cnt[q, 1] = 0.0
                    cnt[q, 2] = 0.0
                    cnt[q, 3] = 0.0
                cnt[q, HIT if run_hit[lvl] else MISS] += runs.w
                seen[q] = 1
        run_hit[lvl] = False
        run_len[lvl] = False


@kernel(nogil=True, error_model="numpy", inline="always")
def _no_free_phase(runs, carry, ix, iy):  # pragma: no cover - compiled
    return carry


@kernel(nogil=True, error_model="numpy", inline="always")
def _record_cell(runs, beam, carry, ix, iy, r_in, r_out):  # pragma: no cover - compiled
    """A finest cell the ray crosses over [r_in, r_out] (m): close the runs the step from the previous cell left,
    then give the cell its value and open its run. carry: (previous cell's ix, iy, whether the ray passed its
    return, cells listed in touched)."""
    prev_ix, prev_iy, hit_passed, n_touched = carry
    _close_runs(runs, _levels_left(ix, iy, prev_ix, prev_iy, runs.levels.x0.shape[0]), prev_ix, prev_iy, hit_passed)
    runs.scratch.run_len[0] = True
    z_hit = beam.z if beam.kind == BEAM_HIT else FAR
    if not hit_passed and z_hit < r_out:
        runs.scratch.run_hit[0] = True
        hit_passed = True
    y = segment_logodds(r_in, r_out, beam, runs.model)
    rec, lv = runs.scratch.rec, runs.levels
    c = (iy - lv.y0[0]) * lv.w[0] + ix - lv.x0[0]
    if rec[c, 0] < runs.stamp_base:  # first touch in this scan
        rec[c, 2] = 0.0
        rec[c, 3] = 0.0
        rec[c, 4] = 0.0
        rec[c, 5] = 0.0
        runs.scratch.touched[n_touched] = c
        n_touched += 1
    add_sample_value(rec, c, runs.sid, runs.w, y)
    return ix, iy, hit_passed, n_touched


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_unknown(unknowns, beam, carry, ix, iy, r_in, r_out):  # pragma: no cover - compiled
    """A level-1 cell (ix, iy) the ray enters behind its return: an unknown for each level >= 1 the step from the
    previous cell (carry) enters anew, in the cells the scan has seen."""
    prev_ix, prev_iy = carry
    lv = unknowns.levels
    top = min(1 + _levels_left(ix, iy, prev_ix, prev_iy, lv.x0.shape[0]), lv.x0.shape[0])
    for lvl in range(1, top):
        q = lv.off[lvl] + ((iy >> (lvl - 1)) - lv.y0[lvl]) * lv.w[lvl] + ((ix >> (lvl - 1)) - lv.x0[lvl])
        if unknowns.seen[q]:
            unknowns.cnt[q, UNKNOWN] += unknowns.w
    return ix, iy


@kernel(nogil=True, error_model="numpy", refcounted=False)
def _scan_evidence(
    lasers, weights, angles, beams, r_count, model, res, levels, scratch, stamp_base, count_unknowns
):  # pragma: no cover - compiled
    """The pass; returns how many finest cells got log-odds evidence (listed in ``touched``).

    lasers: (M, 3) laser poses (x m, y m, yaw rad), weights (M,); angles: (B,) beam angles (rad, laser frame);
    beams: a :class:`BeamTable`, model a :class:`LogOddsModel`, levels a :class:`Levels`, scratch an
    :class:`EvidenceScratch` (plain tuples); r_count: (B,) m; res: the finest cell size (m).

    Finest window cell (gx, gy) = global (x0[0] + gx, y0[0] + gy) has record rec[gy * w[0] + gx] =
    [stamp of the last sample that touched it, that sample's value, sum_j w_j y, sum_j w_j y^2, hits,
    misses]; the stamps are stamp_base + j, smaller ones are from earlier scans. Level-k cell (ax, ay), k >= 1,
    has count record q = off[k] + (ay - y0[k]) * w[k] + ax - x0[k], cnt[q] = [stamp_base, hits,
    misses, unknowns], and seen[q] = 1 once the scan gave it a hit or a miss (``seen`` must be all 0 on entry).

    First every ray is followed up to r_stop for the values, hits and misses. Then, with ``count_unknowns``,
    every ray with a return is followed from its return up to r_count through level-1 cells, and each cell of
    level >= 1 it enters adds an unknown, if the scan has seen that cell: the split test reads unknowns only
    in cells with hits or misses, and skipping the others keeps the long stretches behind the returns cheap.
    """
    beams, model, levels, scratch = BeamTable(*beams), LogOddsModel(*model), Levels(*levels), EvidenceScratch(*scratch)
    n_levels = levels.x0.shape[0]
    every_tile = Tiles(scratch.owned, True, 0, 0, 0)
    finest = Window(levels.x0[0], levels.y0[0], levels.w[0], levels.h[0])
    run_hit, run_len = scratch.run_hit, scratch.run_len
    n_touched = 0
    for j in range(lasers.shape[0]):
        runs = _Runs(scratch, levels, model, float(stamp_base + j), weights[j], stamp_base)
        for k in range(angles.shape[0]):
            beam = beam_at(beams, k)
            if beam.kind == BEAM_SKIP:
                continue
            dx, dy = _direction(lasers[j, 2] + angles[k])
            inside, ray = ray_start(lasers[j, 0], lasers[j, 1], dx, dy, beam.r_stop, res, finest)
            if not inside:
                continue  # (the window covers every ray's reach with cells to spare: this guards the memory)
            run_hit[:] = False
            run_len[:] = False
            carry = (ray.ix, ray.iy, False, n_touched)
            carry = walk_ray(
                ray,
                0.0,
                -math.inf,
                beam.r_stop,
                every_tile,
                _no_free_phase,
                _record_cell,
                runs,
                (beams, k),
                carry,
                True,
            )
            prev_ix, prev_iy, hit_passed, n_touched = carry
            _close_runs(runs, n_levels, prev_ix, prev_iy, hit_passed)
    if count_unknowns and n_levels >= 2:
        _count_unknowns(lasers, weights, angles, beams, r_count, res, levels, scratch, every_tile)
    return n_touched


@kernel(nogil=True, error_model="numpy", inline="always")
def _count_unknowns(lasers, weights, angles, beams, r_count, res, levels, scratch, every_tile):  # pragma: no cover
    """The unknowns' pass of :func:`_scan_evidence`: every ray with a return walked from it up to r_count through
    level-1 cells (the return's level-1 cell holds the hit, every cell entered after it is unknown)."""
    coarse = Window(levels.x0[1], levels.y0[1], levels.w[1], levels.h[1])
    for j in range(lasers.shape[0]):
        unknowns = _Unknowns(scratch.seen, scratch.cnt, levels, weights[j])
        for k in range(angles.shape[0]):
            if beams.kind[k] != BEAM_HIT or r_count[k] <= beams.z[k]:
                continue
            dx, dy = _direction(lasers[j, 2] + angles[k])
            z = beams.z[k]
            stop = r_count[k] - z  # ranges from the return
            inside, ray = ray_start(lasers[j, 0] + z * dx, lasers[j, 1] + z * dy, dx, dy, stop, 2.0 * res, coarse)
            if inside:
                start = (ray.ix, ray.iy)
                walk_ray(
                    ray,
                    0.0,
                    -math.inf,
                    stop,
                    every_tile,
                    _no_free_phase,
                    _count_unknown,
                    unknowns,
                    (beams, k),
                    start,
                    True,
                )


@dataclass(frozen=True)
class ScanEvidence:
    """What one scan says: log-odds moments of the finest cells it touched, outcome counts at every level.

    Level k's window covers the level-k cells ax in [x0[k], x0[k] + w[k]), ay in [y0[k], y0[k] + h[k]).
    """

    x0: np.ndarray
    y0: np.ndarray
    w: np.ndarray
    h: np.ndarray
    off: np.ndarray
    rec: np.ndarray
    cnt: np.ndarray
    touched_index: np.ndarray
    stamp_base: int

    @property
    def levels(self) -> int:
        return int(self.x0.size)

    def fine(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(ix, iy, sum_j w_j y, sum_j w_j y^2 - (sum_j w_j y)^2 clipped at 0) of the touched finest cells."""
        index = self.touched_index
        record = self.rec[index]
        first = record[:, 2]
        return (
            index % self.w[0] + self.x0[0],
            index // self.w[0] + self.y0[0],
            first,
            np.maximum(record[:, 3] - first * first, 0.0),
        )

    def counts(self, level: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
        """(N, 3) weighted hits, misses and unknowns of cells (level, ax, ay); zeros where the scan has none
        (unknowns only in cells of level >= 1 with hits or misses, see the module docstring)."""
        level = np.asarray(level, np.int64)
        lv = np.clip(level, 0, self.levels - 1)
        gx = np.asarray(ax, np.int64) - self.x0[lv]
        gy = np.asarray(ay, np.int64) - self.y0[lv]
        inside = (level >= 0) & (level < self.levels) & (gx >= 0) & (gy >= 0) & (gx < self.w[lv]) & (gy < self.h[lv])
        out = np.zeros((level.size, 3))
        finest = inside & (level == 0)
        record = self.rec[np.where(finest, gy * self.w[0] + gx, 0)]
        fresh = finest & (record[:, 0] >= self.stamp_base)
        out[fresh, :2] = record[fresh, 4:6]
        coarse = inside & (level > 0)
        record = self.cnt[np.where(coarse, self.off[lv] + gy * self.w[lv] + gx, 0)]
        fresh = coarse & (record[:, 0] == self.stamp_base)
        out[fresh] = record[fresh, HIT : UNKNOWN + 1]
        return out


class EvidenceScanner:
    """Runs the compiled pass for one laser and keeps its scratch between scans.

    levels: count outcomes at levels 0..levels-1; count_unknowns: count unknowns (else only hits and misses).
    """

    def __init__(self, levels: int, count_unknowns: bool) -> None:
        self.levels = int(levels)
        self.count_unknowns = bool(count_unknowns)
        self._stamp_next = 1
        self._rec = np.zeros((0, 6))
        self._cnt = np.zeros((1, 4))
        self._seen = np.zeros(0, np.uint8)
        self._touched = np.zeros(0, np.int64)

    def scan(
        self,
        lasers: np.ndarray,
        weights: np.ndarray,
        angles: np.ndarray,
        beams: BeamTable,
        r_count: np.ndarray,
        model: LogOddsModel,
        resolution: float,
    ) -> ScanEvidence:
        """Gather the evidence of one scan.

        lasers: (M, 3) laser poses (x m, y m, yaw rad) in the map frame; weights: (M,) summing to 1;
        angles: (B,) beam angles in rad, laser frame; beams: the scan's beam table; r_count: (B,) m, how far
        each ray is followed for counting (>= beams.r_stop); model: what the kernels read of the sensor model
        (:func:`mapping.beam_model.logodds_model`); resolution: the finest cell size in m.
        """
        levels = self._windows(lasers, float(r_count.max()) + resolution, resolution)
        stamp_base = self._stamps(len(lasers))
        flags = np.zeros(self.levels, np.bool_)
        scratch = (self._rec, self._cnt, self._seen, self._touched, flags, flags.copy(), np.ones((1, 1), np.bool_))
        n = _scan_evidence(
            lasers,
            weights,
            angles,
            tuple(beams),
            r_count,
            tuple(model),
            resolution,
            tuple(levels),
            scratch,
            stamp_base,
            self.count_unknowns,
        )
        return ScanEvidence(*levels, self._rec, self._cnt, self._touched[:n].copy(), stamp_base)

    def _windows(self, lasers: np.ndarray, reach: float, res: float) -> Levels:
        """The scratch windows of every level over the rays of laser poses (M, 3) that reach ``reach`` m (cells of
        res m), each with two finest cells to spare on every side beyond the reach (a level-1 cell at least, as
        the walk's start checks), and scratch that holds them, the count records' ``seen`` cleared."""
        (x_lo, y_lo), (x_hi, y_hi) = lasers[:, :2].min(axis=0).tolist(), lasers[:, :2].max(axis=0).tolist()
        check_window(x_lo, y_lo, x_hi, y_hi, reach, res)
        ix0 = math.floor((x_lo - reach) / res) - 2
        iy0 = math.floor((y_lo - reach) / res) - 2
        ix1 = math.floor((x_hi + reach) / res) + 2
        iy1 = math.floor((y_hi + reach) / res) + 2
        shifts = np.arange(self.levels)
        x0, y0 = np.int64(ix0) >> shifts, np.int64(iy0) >> shifts
        w = (np.int64(ix1) >> shifts) - x0 + 1
        h = (np.int64(iy1) >> shifts) - y0 + 1
        sizes = w * h
        fine = int(sizes[0])
        sizes[0] = 0  # the finest cells' counts live in their log-odds records
        off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        counted = int(sizes.sum())
        if fine > self._rec.shape[0]:
            self._rec = np.zeros((fine, 6))
            self._touched = np.zeros(fine, np.int64)
        if counted > self._cnt.shape[0]:
            self._cnt = np.zeros((counted, 4))
            self._seen = np.zeros(counted, np.uint8)
        self._seen[:counted] = 0
        return Levels(x0, y0, w, h, off)

    def _stamps(self, samples: int) -> int:
        """The stamp of the scan's first sample (the scratch cleared when the stamps run out)."""
        if self._stamp_next + samples >= STAMP_LIMIT:
            self._rec[:] = 0
            self._cnt[:] = 0
            self._stamp_next = 1
        stamp_base = self._stamp_next
        self._stamp_next += samples
        return stamp_base
