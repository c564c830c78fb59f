"""One scan's evidence for the adaptive grid, gathered in one compiled pass over (sample, beam, finest cell).

Each ray under each pose sample is traversed at the finest resolution with the shared Amanatides-Woo helpers
(:func:`mapping.raytrace.dda_start`, :func:`mapping.raytrace.dda_step`). The pass records

* per finest cell, the regular grid's Monte Carlo evidence (paper, eq. 9), computed exactly as
  :mod:`mapping.fusion`'s kernel does: a beam gives the cell the model's largest value over its segment
  inside the cell, one sample gives the cell the largest value any of its beams proposes, and the cell
  gets the weighted moments sum_j w_j y_ij and sum_j w_j y_ij^2;
* per cell of every level, one weighted count of each ray's outcome (paper, section VI.A): a *hit* if the
  ray's return lies in the cell, a *miss* if the ray leaves the cell before its return, an *unknown* if the
  ray's return lies before the cell (the cell is behind an obstacle along that beam). The finest cells a
  ray crosses form, at level k, consecutive *runs* inside one level-k cell (a ray crosses a square once);
  each run of a ray of sample j adds w_j to one of the three counts of its cell. A beam without a return is
  a miss everywhere up to range_max.

Unknowns are counted only where the split test reads them: at levels >= 1 (the finest cells are never
split) and in cells that the scan also gives hits or misses (a cell is tested only when the scan sees it).
They are counted in a second loop that follows each ray from its return through level-1 cells, so the long
stretches behind the returns cost little.

Nothing here depends on which cells are active, so after the pass the split test can descend through any
level and the update can aggregate the finest evidence into whatever cells are active.

Evidence lives in scratch windows that cover the scan's reach: the finest window for the log-odds records,
and per level k the level-k cells over it for the counts, flattened into one array with per-level offsets.
Records carry stamps, as in the regular kernel, so the scratch is reused without clearing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapping.beam_model import BEAM_HIT, BEAM_SKIP, TABLE_DU, TABLE_U0, BeamTable, segment_logodds
from mapping.jit import kernel
from mapping.raytrace import FAR, corner_tol, dda_start, dda_step
from mapping.samples_pass import STAMP_LIMIT, add_sample_value
from mapping.scan_input import check_window

#: columns of a count record: [stamp, hits, misses, unknowns]
HIT, MISS, UNKNOWN = 1, 2, 3


@kernel(nogil=True, error_model="numpy", inline="always")
def _bit_length(v):  # pragma: no cover - compiled
    n = 0
    while v > 0:
        v >>= 1
        n += 1
    return n


@kernel(nogil=True, error_model="numpy")
def _scan_evidence(
    laser_x,
    laser_y,
    laser_yaw,
    weights,
    angles,
    kind,
    z,
    r_stop,
    r_count,
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
    lv_x0,
    lv_y0,
    lv_w,
    lv_h,
    lv_off,
    rec,
    cnt,
    seen,
    touched,
    stamp_base,
    count_unknowns,
):  # pragma: no cover - compiled
    """The pass; returns how many finest cells got log-odds evidence (listed in ``touched``).

    Finest window cell (gx, gy) = global (lv_x0[0] + gx, lv_y0[0] + gy) has record rec[gy * lv_w[0] + gx] =
    [stamp of the last sample that touched it, that sample's value, sum_j w_j y, sum_j w_j y^2, hits,
    misses]; the stamps are stamp_base + j, smaller ones are from earlier scans. Level-k cell (ax, ay), k >= 1,
    has count record q = lv_off[k] + (ay - lv_y0[k]) * lv_w[k] + ax - lv_x0[k], cnt[q] = [stamp_base, hits,
    misses, unknowns], and seen[q] = 1 once the scan gave it a hit or a miss (``seen`` must be all 0 on entry).

    First every ray is followed up to r_stop for the values, hits and misses. Then, with ``count_unknowns``,
    every ray with a return is followed from its return up to r_count through level-1 cells, and each cell of
    level >= 1 it enters adds an unknown, if the scan has seen that cell: the split test reads unknowns only
    in cells with hits or misses, and skipping the others keeps the long stretches behind the returns cheap.
    """
    n_levels = lv_x0.shape[0]
    run_hit = np.zeros(n_levels, np.bool_)  # per level, the open run holds the return
    run_len = np.zeros(n_levels, np.bool_)  # the open run has positive length
    n_touched = 0
    y_peak = math.log(p_hit) - math.log1p(-p_hit)
    for j in range(laser_x.shape[0]):
        sid = float(stamp_base + j)
        w = weights[j]
        for k in range(angles.shape[0]):
            beam_kind = kind[k]
            if beam_kind == BEAM_SKIP:
                continue
            theta = laser_yaw[j] + angles[k]
            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(
                laser_x[j], laser_y[j], math.cos(theta), math.sin(theta), res
            )
            stop = r_stop[k]
            z_hit = z[k] if beam_kind == BEAM_HIT else FAR
            for lvl in range(n_levels):
                run_hit[lvl] = False
                run_len[lvl] = False
            hit_passed = False
            r_in = 0.0
            tol = corner_tol(stop)
            while True:
                r_out = min(t_max_x, t_max_y, stop)
                gx = ix - lv_x0[0]
                gy = iy - lv_y0[0]
                # the window covers every ray's reach, so the guard never fires; it protects the scratch memory
                finished = gx < 0 or gy < 0 or gx >= lv_w[0] or gy >= lv_h[0]
                if not finished and r_out > r_in:
                    run_len[0] = True
                    if not hit_passed and z_hit < r_out:
                        run_hit[0] = True
                        hit_passed = True
                    y = segment_logodds(
                        r_in,
                        r_out,
                        beam_kind,
                        free_until[k],
                        z[k],
                        r_peak[k],
                        a[k],
                        b[k],
                        s[k],
                        g_peak[k],
                        table,
                        u0,
                        du,
                        p_miss,
                        p_hit,
                        l_free,
                        y_peak,
                    )
                    c = gy * lv_w[0] + gx
                    if rec[c, 0] < stamp_base:  # first touch in this scan
                        rec[c, 2] = 0.0
                        rec[c, 3] = 0.0
                        rec[c, 4] = 0.0
                        rec[c, 5] = 0.0
                        touched[n_touched] = c
                        n_touched += 1
                    add_sample_value(rec, c, sid, w, y)
                next_ix, next_iy = ix, iy
                if finished or r_out >= stop - tol:  # (as in the fusion passes: no sliver past the end)
                    finished = True
                    top = n_levels
                else:
                    r_in = r_out
                    next_ix, next_iy, t_max_x, t_max_y = dda_step(
                        ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol
                    )
                    moved = (next_ix ^ ix) | (next_iy ^ iy)
                    top = n_levels if moved < 0 else min(_bit_length(moved), n_levels)
                # close the runs that end here (levels 0..top-1, finest first): fold each into its parent run,
                # count a hit or a miss (a run that began beyond the return is left to the unknowns' pass),
                # and open the next run
                for lvl in range(top):
                    if run_len[lvl] and (run_hit[lvl] or not hit_passed):
                        if lvl + 1 < n_levels:
                            run_len[lvl + 1] = True
                            if run_hit[lvl]:
                                run_hit[lvl + 1] = True
                        if lvl == 0:  # a finest run is the cell just recorded: its counts share the record
                            rec[gy * lv_w[0] + gx, 4 if run_hit[0] else 5] += w
                        else:
                            q = lv_off[lvl] + ((iy >> lvl) - lv_y0[lvl]) * lv_w[lvl] + ((ix >> lvl) - lv_x0[lvl])
                            if cnt[q, 0] != stamp_base:
                                cnt[q, 0] = stamp_base
                                cnt[q, 1] = 0.0
                                cnt[q, 2] = 0.0
                                cnt[q, 3] = 0.0
                            cnt[q, HIT if run_hit[lvl] else MISS] += w
                            seen[q] = 1
                    run_hit[lvl] = False
                    run_len[lvl] = False
                if finished:
                    break
                ix = next_ix
                iy = next_iy
    if not count_unknowns or n_levels < 2:
        return n_touched
    for j in range(laser_x.shape[0]):
        w = weights[j]
        for k in range(angles.shape[0]):
            if kind[k] != BEAM_HIT or r_count[k] <= z[k]:
                continue
            theta = laser_yaw[j] + angles[k]
            dx = math.cos(theta)
            dy = math.sin(theta)
            # ranges from the return; its level-1 cell holds the hit, every cell entered after it is unknown
            ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y = dda_start(
                laser_x[j] + z[k] * dx, laser_y[j] + z[k] * dy, dx, dy, 2.0 * res
            )
            stop = r_count[k] - z[k]
            tol = corner_tol(stop)
            while min(t_max_x, t_max_y) < stop:
                next_ix, next_iy, t_max_x, t_max_y = dda_step(
                    ix, iy, step_x, step_y, t_max_x, t_max_y, t_delta_x, t_delta_y, tol
                )
                gx = next_ix - lv_x0[1]
                gy = next_iy - lv_y0[1]
                if gx < 0 or gy < 0 or gx >= lv_w[1] or gy >= lv_h[1]:
                    break  # cannot happen, as above
                moved = (next_ix ^ ix) | (next_iy ^ iy)
                top = n_levels if moved < 0 else min(1 + _bit_length(moved), n_levels)
                for lvl in range(1, top):
                    q = (
                        lv_off[lvl]
                        + ((next_iy >> (lvl - 1)) - lv_y0[lvl]) * lv_w[lvl]
                        + ((next_ix >> (lvl - 1)) - lv_x0[lvl])
                    )
                    if seen[q]:
                        cnt[q, UNKNOWN] += w
                ix = next_ix
                iy = next_iy
    return n_touched


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
        table: np.ndarray,
        resolution: float,
        p_miss: float,
        p_hit: float,
        l_free: float,
    ) -> ScanEvidence:
        """Gather the evidence of one scan.

        lasers: (M, 3) laser poses (x m, y m, yaw rad) in the map frame; weights: (M,) summing to 1;
        angles: (B,) beam angles in rad, laser frame; beams: the scan's beam table; r_count: (B,) m, how far
        each ray is followed for counting (>= beams.r_stop); table: the constant-sigma log-odds table or empty;
        resolution: the finest cell size in m; p_miss, p_hit, l_free: the sensor model's.
        """
        res = resolution
        reach = float(r_count.max()) + res
        (x_lo, y_lo), (x_hi, y_hi) = lasers[:, :2].min(axis=0).tolist(), lasers[:, :2].max(axis=0).tolist()
        check_window(x_lo, y_lo, x_hi, y_hi, reach, res)
        ix0 = math.floor((x_lo - reach) / res)
        iy0 = math.floor((y_lo - reach) / res)
        ix1 = math.floor((x_hi + reach) / res)
        iy1 = math.floor((y_hi + reach) / res)
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
        if self._stamp_next + len(lasers) >= STAMP_LIMIT:
            self._rec[:] = 0
            self._cnt[:] = 0
            self._stamp_next = 1
        stamp_base = self._stamp_next
        self._stamp_next += len(lasers)
        n = _scan_evidence(
            lasers[:, 0].copy(),
            lasers[:, 1].copy(),
            lasers[:, 2].copy(),
            weights,
            angles,
            beams.kind,
            beams.z,
            beams.r_stop,
            r_count,
            beams.r_peak,
            beams.a,
            beams.b,
            beams.s,
            beams.g_peak,
            beams.free_until,
            table,
            TABLE_U0,
            TABLE_DU,
            res,
            p_miss,
            p_hit,
            l_free,
            x0,
            y0,
            w,
            h,
            off,
            self._rec,
            self._cnt,
            self._seen,
            self._touched,
            stamp_base,
            self.count_unknowns,
        )
        return ScanEvidence(x0, y0, w, h, off, self._rec, self._cnt, self._touched[:n].copy(), stamp_base)
