"""Compiled inner loops of grid FastSLAM: scan insertion into each particle's tiled grid, the scan likelihood,
the scan matcher and the improved proposal. Each loops over particles and beams inside numba.

Shared arguments: ``pool`` (C, S, S) float32 log-odds tiles (S = 2**shift), ``table`` (M, NY, NX) int32 tile ids per
particle (-1: none) over tile coordinates (tx0 + u, ty0 + v), ``res`` the cell size (m); cells follow the
global lattice of mapping.raytrace (cell (ix, iy) covers [ix*res, (ix+1)*res) x [iy*res, (iy+1)*res)).
Poses are robot poses (x m, y m, yaw rad) in the map frame; ``offset`` (3,) is the laser's pose in the
robot frame; beams are given by their direction in the laser frame (``cos_b``, ``sin_b``) and range (m).
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from mapping.raytrace import trace_ray


@nb.njit(cache=True, nogil=True, inline="always")
def _tile_id(table, j, tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    u = (ix >> shift) - tx0
    v = (iy >> shift) - ty0
    if u < 0 or v < 0 or v >= table.shape[1] or u >= table.shape[2]:
        return -1
    return table[j, v, u]


@nb.njit(cache=True, nogil=True, inline="always")
def _value(pool, table, j, tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    tid = _tile_id(table, j, tx0, ty0, shift, ix, iy)
    if tid < 0:
        return 0.0
    mask = (1 << shift) - 1
    return pool[tid, iy & mask, ix & mask]


@nb.njit(cache=True, nogil=True, inline="always")
def _laser_pose(x, y, th, offset):  # pragma: no cover - compiled
    c, s = math.cos(th), math.sin(th)
    return x + c * offset[0] - s * offset[1], y + s * offset[0] + c * offset[1], th + offset[2]


@nb.njit(cache=True, nogil=True)
def _check_rows(table, poses, cos_b, sin_b, rng):  # pragma: no cover - compiled
    if poses.shape[0] != table.shape[0]:
        raise ValueError("poses must have one row per particle (the table's first axis)")
    if sin_b.shape[0] != cos_b.shape[0] or rng.shape[0] != cos_b.shape[0]:
        raise ValueError("cos_b, sin_b and the ranges must have one entry per beam")


@nb.njit(cache=True, nogil=True)
def touched_tiles(table, tx0, ty0, shift, res, poses, offset, cos_b, sin_b, r_stop):  # pragma: no cover - compiled
    """(particle, v, u) rows (K, 3) of every table entry a scan insertion at ``poses`` (M, 3) writes:
    the tiles of every cell the beams cross up to ``r_stop`` (B,) m (NaN: beam unused)."""
    _check_rows(table, poses, cos_b, sin_b, r_stop)
    m, ny, nx = table.shape
    mark = np.zeros((m, ny, nx), np.uint8)
    count = 0
    cap = int(math.ceil(np.nanmax(r_stop) * math.sqrt(2.0) / res)) + 3 if r_stop.shape[0] else 3
    bix = np.empty(cap, np.int64)
    biy = np.empty(cap, np.int64)
    brin = np.empty(cap, np.float64)
    brout = np.empty(cap, np.float64)
    for j in range(m):
        lx, ly, lth = _laser_pose(poses[j, 0], poses[j, 1], poses[j, 2], offset)
        cl, sl = math.cos(lth), math.sin(lth)
        for i in range(cos_b.shape[0]):
            if not r_stop[i] > 0.0:
                continue
            dx = cl * cos_b[i] - sl * sin_b[i]
            dy = sl * cos_b[i] + cl * sin_b[i]
            n = trace_ray(lx, ly, dx, dy, r_stop[i], res, bix, biy, brin, brout)
            for k in range(n):
                u = (bix[k] >> shift) - tx0
                v = (biy[k] >> shift) - ty0
                if 0 <= u < nx and 0 <= v < ny and mark[j, v, u] == 0:
                    mark[j, v, u] = 1
                    count += 1
    out = np.empty((count, 3), np.int64)
    k = 0
    for j in range(m):
        for v in range(ny):
            for u in range(nx):
                if mark[j, v, u]:
                    out[k, 0] = j
                    out[k, 1] = v
                    out[k, 2] = u
                    k += 1
    return out


@nb.njit(cache=True, nogil=True)
def insert_scan(pool, table, tx0, ty0, shift, res, poses, offset, cos_b, sin_b, r_stop, hit,
                l_occ, l_free, l_min, l_max):  # pragma: no cover - compiled
    """Add ``l_free`` to every cell each beam crosses before its end and ``l_occ`` to its end cell when
    ``hit[i]``; values stay in [l_min, l_max]. Every touched tile must be owned (TileMaps.own) first.
    Returns the number of cell updates."""
    _check_rows(table, poses, cos_b, sin_b, r_stop)
    if hit.shape[0] != cos_b.shape[0]:
        raise ValueError("hit must have one entry per beam")
    m = table.shape[0]
    cap = int(math.ceil(np.nanmax(r_stop) * math.sqrt(2.0) / res)) + 3 if r_stop.shape[0] else 3
    bix = np.empty(cap, np.int64)
    biy = np.empty(cap, np.int64)
    brin = np.empty(cap, np.float64)
    brout = np.empty(cap, np.float64)
    updates = 0
    mask = (1 << shift) - 1
    for j in range(m):
        lx, ly, lth = _laser_pose(poses[j, 0], poses[j, 1], poses[j, 2], offset)
        cl, sl = math.cos(lth), math.sin(lth)
        for i in range(cos_b.shape[0]):
            if not r_stop[i] > 0.0:
                continue
            dx = cl * cos_b[i] - sl * sin_b[i]
            dy = sl * cos_b[i] + cl * sin_b[i]
            n = trace_ray(lx, ly, dx, dy, r_stop[i], res, bix, biy, brin, brout)
            for k in range(n):
                tid = _tile_id(table, j, tx0, ty0, shift, bix[k], biy[k])
                if tid < 0:
                    continue
                cy = biy[k] & mask
                cx = bix[k] & mask
                add = l_occ if (hit[i] and k == n - 1) else l_free
                value = pool[tid, cy, cx] + add
                pool[tid, cy, cx] = min(max(value, l_min), l_max)
                updates += 1
    return updates


@nb.njit(cache=True, nogil=True, inline="always")
def _candidate(pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, ix, iy, value, best):  # pragma: no cover
    """best, lowered to the squared distance (m^2) from (ex, ey) to cell (ix, iy)'s centre when that cell is
    occupied (``value`` > 0) and its neighbour one cell back along the beam (dx, dy) is not."""
    if value <= 0.0:
        return best
    px = (ix + 0.5) * res
    py = (iy + 0.5) * res
    fx = int(math.floor((px - dx * res) / res))
    fy = int(math.floor((py - dy * res) / res))
    if _value(pool, table, j, tx0, ty0, shift, fx, fy) > 0.0:
        return best
    d2 = (px - ex) * (px - ex) + (py - ey) * (py - ey)
    return d2 if d2 < best else best


@nb.njit(cache=True, nogil=True)
def _evaluate(pool, table, j, tx0, ty0, shift, res, x, y, th, offset, cos_b, sin_b, rng, kernel,
              inv2s2_match, inv2s2_like, log_p_rand, p_rand):  # pragma: no cover - compiled
    """(match score, log-likelihood) of the beams (cos_b, sin_b, rng) from robot pose (x, y, th) on
    particle j's grid. For each beam end the nearest occupied cell (log-odds > 0) within ``kernel`` cells
    whose neighbour one cell back towards the laser is not occupied gives the distance d (m); the score adds
    exp(-d^2 / 2 s_m^2), the log-likelihood log(p_rand + (1 - p_rand) exp(-d^2 / 2 s_l^2)) (log p_rand
    when there is no such cell)."""
    lx, ly, lth = _laser_pose(x, y, th, offset)
    cl, sl = math.cos(lth), math.sin(lth)
    side = 1 << shift
    mask = side - 1
    inv_res = 1.0 / res
    score = 0.0
    loglik = 0.0
    for i in range(cos_b.shape[0]):
        dx = cl * cos_b[i] - sl * sin_b[i]
        dy = sl * cos_b[i] + cl * sin_b[i]
        ex = lx + rng[i] * dx
        ey = ly + rng[i] * dy
        cx = int(math.floor(ex * inv_res))
        cy = int(math.floor(ey * inv_res))
        best = np.inf
        tid = _tile_id(table, j, tx0, ty0, shift, cx, cy)
        ox = cx & mask
        oy = cy & mask
        if kernel <= ox < side - kernel and kernel <= oy < side - kernel:
            # the whole neighbourhood lies in one tile: read it directly
            if tid >= 0:
                for b in range(-kernel, kernel + 1):
                    for a in range(-kernel, kernel + 1):
                        best = _candidate(pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, cx + a, cy + b,
                                          pool[tid, oy + b, ox + a], best)
        else:
            for b in range(-kernel, kernel + 1):
                for a in range(-kernel, kernel + 1):
                    value = _value(pool, table, j, tx0, ty0, shift, cx + a, cy + b)
                    best = _candidate(pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, cx + a, cy + b, value, best)
        if best < np.inf:
            score += math.exp(-best * inv2s2_match)
            loglik += math.log(p_rand + (1.0 - p_rand) * math.exp(-best * inv2s2_like))
        else:
            loglik += log_p_rand
    return score, loglik


@nb.njit(cache=True, nogil=True)
def log_likelihoods(pool, table, tx0, ty0, shift, res, poses, offset, cos_b, sin_b, rng, kernel,
                    sigma_match, sigma_like, p_rand):  # pragma: no cover - compiled
    """Scan log-likelihood (M,) of each particle's pose on its own grid, and match score (M,)."""
    _check_rows(table, poses, cos_b, sin_b, rng)
    m = poses.shape[0]
    loglik = np.empty(m)
    score = np.empty(m)
    for j in range(m):
        score[j], loglik[j] = _evaluate(pool, table, j, tx0, ty0, shift, res, poses[j, 0], poses[j, 1], poses[j, 2],
                                        offset, cos_b, sin_b, rng, kernel, 0.5 / sigma_match**2,
                                        0.5 / sigma_like**2, math.log(p_rand), p_rand)
    return loglik, score


@nb.njit(cache=True, nogil=True)
def match_and_propose(pool, table, tx0, ty0, shift, res, predicted, q_inv, q_logdet, offset, cos_b, sin_b, rng,
                      kernel, sigma_match, sigma_like, p_rand, gain, lin_step, ang_step, refinements,
                      stencil):  # pragma: no cover - compiled
    """Scan-match every particle on its own grid, then fit the improved proposal around the match.

    For particle j: hill climbing on the match score from ``predicted[j]`` (moves of +-lin_step m in x
    and y and +-ang_step rad in yaw, halved ``refinements`` times); then at the stencil points (K, 3)
    around the match, tau_k = loglik_k / gain + log N(x_k; predicted_j, Q_j) (Q_j^-1 ``q_inv`` (M, 3, 3),
    log det ``q_logdet`` (M,)). Returns the match (M, 3), its score (M,), the tau-weighted mean (M, 3) and
    covariance (M, 3, 3) and log sum_k tau_k (M,) (the particle's weight factor, eta).
    """
    _check_rows(table, predicted, cos_b, sin_b, rng)
    if q_inv.shape[0] != predicted.shape[0] or q_logdet.shape[0] != predicted.shape[0]:
        raise ValueError("q_inv and q_logdet must have one entry per particle")
    m = predicted.shape[0]
    inv_m = 0.5 / sigma_match**2
    inv_l = 0.5 / sigma_like**2
    log_pr = math.log(p_rand)
    matched = np.empty((m, 3))
    scores = np.empty(m)
    mean = np.empty((m, 3))
    cov = np.empty((m, 3, 3))
    log_eta = np.empty(m)
    k_count = stencil.shape[0]
    tau = np.empty(k_count)
    pts = np.empty((k_count, 3))
    for j in range(m):
        bx, by, bt = predicted[j, 0], predicted[j, 1], predicted[j, 2]
        best, _ = _evaluate(pool, table, j, tx0, ty0, shift, res, bx, by, bt, offset, cos_b, sin_b, rng, kernel,
                            inv_m, inv_l, log_pr, p_rand)
        lin, ang = lin_step, ang_step
        for _r in range(refinements):
            for _it in range(64):
                cand_x, cand_y, cand_t, cand_s = bx, by, bt, best
                for move in range(6):
                    tx, ty, tt = bx, by, bt
                    if move == 0:
                        tx += lin
                    elif move == 1:
                        tx -= lin
                    elif move == 2:
                        ty += lin
                    elif move == 3:
                        ty -= lin
                    elif move == 4:
                        tt += ang
                    else:
                        tt -= ang
                    s, _ = _evaluate(pool, table, j, tx0, ty0, shift, res, tx, ty, tt, offset, cos_b, sin_b, rng,
                                     kernel, inv_m, inv_l, log_pr, p_rand)
                    if s > cand_s:
                        cand_x, cand_y, cand_t, cand_s = tx, ty, tt, s
                if cand_s > best:
                    bx, by, bt, best = cand_x, cand_y, cand_t, cand_s
                else:
                    break
            lin *= 0.5
            ang *= 0.5
        matched[j, 0], matched[j, 1], matched[j, 2] = bx, by, bt
        scores[j] = best
        top = -np.inf
        for k in range(k_count):
            px, py, pt = bx + stencil[k, 0], by + stencil[k, 1], bt + stencil[k, 2]
            pts[k, 0], pts[k, 1], pts[k, 2] = px, py, pt
            _, ll = _evaluate(pool, table, j, tx0, ty0, shift, res, px, py, pt, offset, cos_b, sin_b, rng, kernel,
                              inv_m, inv_l, log_pr, p_rand)
            ex = px - predicted[j, 0]
            ey = py - predicted[j, 1]
            et = (pt - predicted[j, 2] + math.pi) % (2.0 * math.pi) - math.pi
            maha = 0.0
            for a in range(3):
                ea = ex if a == 0 else (ey if a == 1 else et)
                for b in range(3):
                    eb = ex if b == 0 else (ey if b == 1 else et)
                    maha += ea * q_inv[j, a, b] * eb
            tau[k] = ll / gain - 0.5 * maha - 0.5 * q_logdet[j] - 1.5 * math.log(2.0 * math.pi)
            if tau[k] > top:
                top = tau[k]
        total = 0.0
        for k in range(k_count):
            tau[k] = math.exp(tau[k] - top)
            total += tau[k]
        log_eta[j] = top + math.log(total)
        for a in range(3):
            acc = 0.0
            for k in range(k_count):
                acc += tau[k] * pts[k, a]
            mean[j, a] = acc / total
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for k in range(k_count):
                    acc += tau[k] * (pts[k, a] - mean[j, a]) * (pts[k, b] - mean[j, b])
                cov[j, a, b] = acc / total
    return matched, scores, mean, cov, log_eta
