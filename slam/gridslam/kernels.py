"""Compiled inner loops of grid FastSLAM: scan insertion into each particle's tiled grid, the scan likelihood,
the scan matcher and the improved proposal. Each loops over particles and beams inside numba.

Shared arguments: ``pool`` (C, S, S, 4) float32 tiles of cells (log-odds, summed end-point offsets x and
y, end-point count; slam.gridslam.tiles; S = 2**shift), ``table`` (M, NY, NX) int32 tile ids per
particle (-1: none) over tile coordinates (tx0 + u, ty0 + v), ``res`` the cell size (m); cells follow the
global lattice of mapping.raytrace (cell (ix, iy) covers [ix*res, (ix+1)*res) x [iy*res, (iy+1)*res)).
Poses are robot poses (x m, y m, yaw rad) in the map frame; ``offset`` (3,) is the laser's pose in the
robot frame; beams are given by their direction in the laser frame (``cos_b``, ``sin_b``) and range (m).
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel
from mapping.raytrace import trace_ray

#: hill-climbing refinements (the last ones, with the smallest steps) that use every beam
FINE_REFINEMENTS = 3


@kernel(nogil=True, inline="always")
def _tile_id(table, j, tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    u = (ix >> shift) - tx0
    v = (iy >> shift) - ty0
    if u < 0 or v < 0 or v >= table.shape[1] or u >= table.shape[2]:
        return -1
    return table[j, v, u]


@kernel(nogil=True, inline="always")
def _value(pool, table, j, tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    tid = _tile_id(table, j, tx0, ty0, shift, ix, iy)
    if tid < 0:
        return 0.0
    mask = (1 << shift) - 1
    return pool[tid, iy & mask, ix & mask, 0]


@kernel(nogil=True, inline="always")
def _laser_pose(x, y, th, offset):  # pragma: no cover - compiled
    c, s = math.cos(th), math.sin(th)
    return x + c * offset[0] - s * offset[1], y + s * offset[0] + c * offset[1], th + offset[2]


@kernel(nogil=True)
def _check_rows(table, poses, cos_b, sin_b, rng):  # pragma: no cover - compiled
    if poses.shape[0] != table.shape[0]:
        raise ValueError("poses must have one row per particle (the table's first axis)")
    if sin_b.shape[0] != cos_b.shape[0] or rng.shape[0] != cos_b.shape[0]:
        raise ValueError("cos_b, sin_b and the ranges must have one entry per beam")


@kernel(nogil=True, inline="always")
def own_tile(pool, refcount, free_stack, n_free, table, j, v, u):  # pragma: no cover - compiled
    """The pool tile particle j may write at table entry (v, u): its own tile, or a fresh zero tile where it
    has none, or a private copy of a shared one (copy-on-write). -1 when the free list is empty (the caller
    grows the pool and retries). Returns (tile, 1 if a tile was copied else 0)."""
    tid = table[j, v, u]
    if tid >= 0 and refcount[tid] == 1:
        return tid, 0
    if n_free[0] == 0:
        return -1, 0
    n_free[0] -= 1
    new = free_stack[n_free[0]]
    copied = 0
    if tid < 0:
        pool[new, :, :, :] = 0.0
    else:
        pool[new, :, :, :] = pool[tid, :, :, :]
        refcount[tid] -= 1
        copied = 1
    refcount[new] = 1
    table[j, v, u] = new
    return new, copied


@kernel(nogil=True)
def insert_scan(
    pool,
    refcount,
    free_stack,
    n_free,
    table,
    tx0,
    ty0,
    shift,
    res,
    poses,
    offset,
    cos_b,
    sin_b,
    r_stop,
    hit,
    l_occ,
    l_free,
    l_min,
    l_max,
    resume,
    counters,
):  # pragma: no cover - compiled
    """Insert one scan into every particle's grid, particle j seeing it from ``poses[j]``.

    Adds ``l_free`` to every cell a beam crosses before its end and ``l_occ`` to its end cell when
    ``hit[i]`` (also adding the end point to the cell's end-point sums); log-odds stay in [l_min, l_max].
    ``r_stop`` (B,) m is each beam's length (NaN: beam unused). A tile a particle shares or lacks is made
    its own first (:func:`own_tile`). When the free list runs dry the kernel stops, stores where it was in
    ``resume`` (particle, beam, cell) and returns False; called again with a grown pool and the same
    ``resume`` it continues there. ``counters`` accumulates (cell updates, tiles copied). True when done.
    """
    _check_rows(table, poses, cos_b, sin_b, r_stop)
    if hit.shape[0] != cos_b.shape[0]:
        raise ValueError("hit must have one entry per beam")
    m, ny, nx = table.shape
    longest = np.nanmax(r_stop) if r_stop.shape[0] else 0.0  # NaN when no beam is used
    cap = int(math.ceil(longest * math.sqrt(2.0) / res)) + 3 if longest > 0.0 else 3
    bix = np.empty(cap, np.int64)
    biy = np.empty(cap, np.int64)
    brin = np.empty(cap, np.float64)
    brout = np.empty(cap, np.float64)
    mask = (1 << shift) - 1
    for j in range(resume[0], m):
        lx, ly, lth = _laser_pose(poses[j, 0], poses[j, 1], poses[j, 2], offset)
        cl, sl = math.cos(lth), math.sin(lth)
        first_beam = resume[1] if j == resume[0] else 0
        for i in range(first_beam, cos_b.shape[0]):
            if not r_stop[i] > 0.0:
                continue
            dx = cl * cos_b[i] - sl * sin_b[i]
            dy = sl * cos_b[i] + cl * sin_b[i]
            n = trace_ray(lx, ly, dx, dy, r_stop[i], res, bix, biy, brin, brout)
            first_cell = resume[2] if (j == resume[0] and i == resume[1]) else 0
            last_u, last_v, tid = -1, -1, -1
            for k in range(first_cell, n):
                u = (bix[k] >> shift) - tx0
                v = (biy[k] >> shift) - ty0
                if u < 0 or v < 0 or u >= nx or v >= ny:
                    continue
                if u != last_u or v != last_v:
                    tid, copied = own_tile(pool, refcount, free_stack, n_free, table, j, v, u)
                    if tid < 0:
                        resume[0], resume[1], resume[2] = j, i, k
                        return False
                    counters[1] += copied
                    last_u, last_v = u, v
                cy = biy[k] & mask
                cx = bix[k] & mask
                end = hit[i] and k == n - 1
                value = pool[tid, cy, cx, 0] + (l_occ if end else l_free)
                pool[tid, cy, cx, 0] = min(max(value, l_min), l_max)
                if end:
                    pool[tid, cy, cx, 1] += lx + r_stop[i] * dx - bix[k] * res
                    pool[tid, cy, cx, 2] += ly + r_stop[i] * dy - biy[k] * res
                    pool[tid, cy, cx, 3] += 1.0
                counters[0] += 1
    resume[0], resume[1], resume[2] = m, 0, 0
    return True


@kernel(nogil=True, inline="always")
def _candidate(pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, ix, iy, tid, best):  # pragma: no cover
    """best, lowered to the squared distance (m^2) from (ex, ey) to the mean end point of cell (ix, iy)
    (in pool tile ``tid``) when that cell is occupied (log-odds > 0) and the point one cell back along the
    beam (dx, dy) is not."""
    if tid < 0:
        return best
    mask = (1 << shift) - 1
    oy = iy & mask
    ox = ix & mask
    if pool[tid, oy, ox, 0] <= 0.0:
        return best
    hits = pool[tid, oy, ox, 3]
    if hits > 0.0:
        px = ix * res + pool[tid, oy, ox, 1] / hits
        py = iy * res + pool[tid, oy, ox, 2] / hits
    else:
        px = (ix + 0.5) * res
        py = (iy + 0.5) * res
    fx = int(math.floor((px - dx * res) / res))
    fy = int(math.floor((py - dy * res) / res))
    if _value(pool, table, j, tx0, ty0, shift, fx, fy) > 0.0:
        return best
    d2 = (px - ex) * (px - ex) + (py - ey) * (py - ey)
    return d2 if d2 < best else best


@kernel(nogil=True)
def _evaluate(
    pool,
    table,
    j,
    tx0,
    ty0,
    shift,
    res,
    x,
    y,
    th,
    offset,
    cos_b,
    sin_b,
    rng,
    kernel,
    inv2s2_match,
    inv2s2_like,
    log_p_rand,
    p_rand,
    stride=1,
):  # pragma: no cover - compiled
    """(match score, log-likelihood) of the beams (cos_b, sin_b, rng) from robot pose (x, y, th) on
    particle j's grid. For each beam end the nearest mean end point of an occupied cell (log-odds > 0)
    within ``kernel`` cells whose neighbour one cell back towards the laser is not occupied gives the
    distance d (m); the score adds
    exp(-d^2 / 2 s_m^2), the log-likelihood log(p_rand + (1 - p_rand) exp(-d^2 / 2 s_l^2)) (log p_rand
    when there is no such cell). Only every ``stride``-th beam is used."""
    lx, ly, lth = _laser_pose(x, y, th, offset)
    cl, sl = math.cos(lth), math.sin(lth)
    side = 1 << shift
    mask = side - 1
    inv_res = 1.0 / res
    score = 0.0
    loglik = 0.0
    for i in range(0, cos_b.shape[0], stride):
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
            # the whole neighbourhood lies in one tile
            if tid >= 0:
                for b in range(-kernel, kernel + 1):
                    for a in range(-kernel, kernel + 1):
                        best = _candidate(
                            pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, cx + a, cy + b, tid, best
                        )
        else:
            for b in range(-kernel, kernel + 1):
                for a in range(-kernel, kernel + 1):
                    cell_tid = _tile_id(table, j, tx0, ty0, shift, cx + a, cy + b)
                    best = _candidate(
                        pool, table, j, tx0, ty0, shift, res, ex, ey, dx, dy, cx + a, cy + b, cell_tid, best
                    )
        if best < np.inf:
            score += math.exp(-best * inv2s2_match)
            loglik += math.log(p_rand + (1.0 - p_rand) * math.exp(-best * inv2s2_like))
        else:
            loglik += log_p_rand
    return score, loglik


@kernel(nogil=True, inline="always")
def _objective(
    pool,
    table,
    j,
    tx0,
    ty0,
    shift,
    res,
    x,
    y,
    th,
    offset,
    cos_b,
    sin_b,
    rng,
    kernel,
    inv_m,
    inv_l,
    log_pr,
    p_rand,
    stride,
    gain,
    predicted,
    q_inv,
    prior_cap,
):  # pragma: no cover - compiled
    """(match score / gain + log of the motion density, up to a constant; match score) at pose (x, y, th)
    for particle j. The score stands in for the log-likelihood in the search (each beam's term exp(-d^2 /
    2 s_m^2) is about the log-likelihood's change between a matched and an unmatched beam, and it locates
    the optimum more precisely: on a synthetic room within 1 cm where the log-likelihood strays 5 cm).
    With ``stride`` > 1 the score of the beams used is scaled up to all beams."""
    score, _loglik = _evaluate(
        pool,
        table,
        j,
        tx0,
        ty0,
        shift,
        res,
        x,
        y,
        th,
        offset,
        cos_b,
        sin_b,
        rng,
        kernel,
        inv_m,
        inv_l,
        log_pr,
        p_rand,
        stride,
    )
    ex = x - predicted[j, 0]
    ey = y - predicted[j, 1]
    et = (th - predicted[j, 2] + math.pi) % (2.0 * math.pi) - math.pi
    maha = (
        ex * (q_inv[j, 0, 0] * ex + q_inv[j, 0, 1] * ey + q_inv[j, 0, 2] * et)
        + ey * (q_inv[j, 1, 0] * ex + q_inv[j, 1, 1] * ey + q_inv[j, 1, 2] * et)
        + et * (q_inv[j, 2, 0] * ex + q_inv[j, 2, 1] * ey + q_inv[j, 2, 2] * et)
    )
    return score * stride / gain - 0.5 * min(maha, prior_cap), score * stride


@kernel(nogil=True)
def log_likelihoods(
    pool, table, tx0, ty0, shift, res, poses, offset, cos_b, sin_b, rng, kernel, sigma_match, sigma_like, p_rand
):  # pragma: no cover - compiled
    """Scan log-likelihood (M,) of each particle's pose on its own grid, and match score (M,)."""
    _check_rows(table, poses, cos_b, sin_b, rng)
    m = poses.shape[0]
    loglik = np.empty(m)
    score = np.empty(m)
    for j in range(m):
        score[j], loglik[j] = _evaluate(
            pool,
            table,
            j,
            tx0,
            ty0,
            shift,
            res,
            poses[j, 0],
            poses[j, 1],
            poses[j, 2],
            offset,
            cos_b,
            sin_b,
            rng,
            kernel,
            0.5 / sigma_match**2,
            0.5 / sigma_like**2,
            math.log(p_rand),
            p_rand,
        )
    return loglik, score


@kernel(nogil=True)
def match_and_propose(
    pool,
    table,
    tx0,
    ty0,
    shift,
    res,
    predicted,
    starts,
    q_inv,
    q_logdet,
    offset,
    cos_b,
    sin_b,
    rng,
    kernel,
    sigma_match,
    sigma_like,
    p_rand,
    gain,
    lin_step,
    ang_step,
    refinements,
    yaw_search,
    prior_cap,
    stencil,
    fit,
):  # pragma: no cover - compiled
    """Scan-match every particle on its own grid, then fit the improved proposal around the match.

    For particle j the match maximises score(x)/gain - min(m(x), prior_cap)/2, m the squared Mahalanobis
    distance of x from the prediction under Q_j and the score standing in for the log-likelihood (see
    _objective): near the prediction a scan's fit must outweigh the odometry to pull the pose away, but
    the prior stops growing at prior_cap, because real odometry is sometimes simply wrong (the Freiburg
    079 odometry reports 10 cm forward per scan where the robot backs up): first the best of the yaws
    predicted[j] + k ang_step, |k ang_step| <= ``yaw_search`` rad (odometry can misjudge a fast turn by tens
    of degrees, more than hill climbing recovers), each tried at the predicted position and at the
    positions ``starts`` (M, S, 2) m (S >= 0; the filter passes the particle's last position and the
    odometry's move mirrored behind it: wheel slip and a lost sign put the truth there, beyond hill
    climbing's reach from the prediction), then hill climbing (moves of +-lin_step m in x and y and +-ang_step rad in
    yaw, halved ``refinements`` times). The yaw search and all but the last :data:`FINE_REFINEMENTS` refinements use
    every second beam (half the cost; the coarse steps need no more).

    The improved proposal is then the Laplace approximation of p(z | m, x)^(1/gain) N(x; x'_j, Q_j): the
    log-likelihood at the stencil points (K, 3) around the match x^ is fitted by a quadratic (``fit``
    (10, K) maps the K values to [c, g (3), a00, a11, a22, a01, a02, a12], the least-squares coefficients
    of c + g.d + a00 d0^2/2 + a11 d1^2/2 + a22 d2^2/2 + a01 d0 d1 + a02 d0 d2 + a12 d1 d2); H = -A/gain,
    clipped to be positive semi-definite, is the likelihood's information and g/gain its slope at x^ (not
    zero: x^ maximises the likelihood times the capped prior; kept only along H's positive eigenvectors). With the
    motion model's information Q^-1 (``q_inv`` (M, 3, 3), log det Q ``q_logdet`` (M,)) and b = g/gain + Q^-1 d the
    proposal is N(x^ + P^-1 b, P^-1), P = H + Q^-1, and the weight factor eta is the Gaussian integral of likelihood
    times motion model: log eta = c/gain - log|Q|/2 - log|P|/2 - (d'Q^-1 d - b'P^-1 b)/2,
    d = x' - x^. Along a direction the scan does not fix (a corridor's axis) H vanishes and the particles
    spread as the odometry says; across it they follow the scan.

    Returns the match (M, 3), its match score (M,; the fallback test), the proposal's mean (M, 3) and covariance
    (M, 3, 3), and log eta (M,).
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
    ll_k = np.empty(k_count)
    for j in range(m):
        bx, by, bt = predicted[j, 0], predicted[j, 1], predicted[j, 2]
        stride = 2 if refinements > FINE_REFINEMENTS else 1
        best, score = _objective(
            pool,
            table,
            j,
            tx0,
            ty0,
            shift,
            res,
            bx,
            by,
            bt,
            offset,
            cos_b,
            sin_b,
            rng,
            kernel,
            inv_m,
            inv_l,
            log_pr,
            p_rand,
            stride,
            gain,
            predicted,
            q_inv,
            prior_cap,
        )
        turns = int(yaw_search / ang_step)
        start_t = bt
        for st in range(starts.shape[1] + 1):
            sx, sy = (predicted[j, 0], predicted[j, 1]) if st == 0 else (starts[j, st - 1, 0], starts[j, st - 1, 1])
            for k in range(-turns, turns + 1):
                if k == 0 and st == 0:
                    continue
                f, s = _objective(
                    pool,
                    table,
                    j,
                    tx0,
                    ty0,
                    shift,
                    res,
                    sx,
                    sy,
                    start_t + k * ang_step,
                    offset,
                    cos_b,
                    sin_b,
                    rng,
                    kernel,
                    inv_m,
                    inv_l,
                    log_pr,
                    p_rand,
                    stride,
                    gain,
                    predicted,
                    q_inv,
                    prior_cap,
                )
                if f > best:
                    best, score, bx, by, bt = f, s, sx, sy, start_t + k * ang_step
        lin, ang = lin_step, ang_step
        for r in range(refinements):
            if stride == 2 and r >= refinements - FINE_REFINEMENTS:
                stride = 1
                best, score = _objective(
                    pool,
                    table,
                    j,
                    tx0,
                    ty0,
                    shift,
                    res,
                    bx,
                    by,
                    bt,
                    offset,
                    cos_b,
                    sin_b,
                    rng,
                    kernel,
                    inv_m,
                    inv_l,
                    log_pr,
                    p_rand,
                    stride,
                    gain,
                    predicted,
                    q_inv,
                    prior_cap,
                )
            for _it in range(64):
                cand_x, cand_y, cand_t, cand_f, cand_s = bx, by, bt, best, score
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
                    f, s = _objective(
                        pool,
                        table,
                        j,
                        tx0,
                        ty0,
                        shift,
                        res,
                        tx,
                        ty,
                        tt,
                        offset,
                        cos_b,
                        sin_b,
                        rng,
                        kernel,
                        inv_m,
                        inv_l,
                        log_pr,
                        p_rand,
                        stride,
                        gain,
                        predicted,
                        q_inv,
                        prior_cap,
                    )
                    if f > cand_f:
                        cand_x, cand_y, cand_t, cand_f, cand_s = tx, ty, tt, f, s
                if cand_f > best:
                    bx, by, bt, best, score = cand_x, cand_y, cand_t, cand_f, cand_s
                else:
                    break
            lin *= 0.5
            ang *= 0.5
        matched[j, 0], matched[j, 1], matched[j, 2] = bx, by, bt
        scores[j] = score
        for k in range(k_count):
            _, ll_k[k] = _evaluate(
                pool,
                table,
                j,
                tx0,
                ty0,
                shift,
                res,
                bx + stencil[k, 0],
                by + stencil[k, 1],
                bt + stencil[k, 2],
                offset,
                cos_b,
                sin_b,
                rng,
                kernel,
                inv_m,
                inv_l,
                log_pr,
                p_rand,
            )
        coef = fit @ ll_k
        # Hessian of the tempered log-likelihood at the match, made positive semi-definite
        curv = np.empty((3, 3))
        curv[0, 0], curv[1, 1], curv[2, 2] = -coef[4], -coef[5], -coef[6]
        curv[0, 1] = curv[1, 0] = -coef[7]
        curv[0, 2] = curv[2, 0] = -coef[8]
        curv[1, 2] = curv[2, 1] = -coef[9]
        eigval, eigvec = np.linalg.eigh(curv / gain)
        hess = (eigvec * np.maximum(eigval, 0.0)) @ eigvec.T
        # the prediction relative to the match (yaw wrapped)
        d = np.empty(3)
        d[0] = predicted[j, 0] - bx
        d[1] = predicted[j, 1] - by
        d[2] = (predicted[j, 2] - bt + math.pi) % (2.0 * math.pi) - math.pi
        qd = q_inv[j] @ d
        # the match maximises likelihood times (capped) prior, so the likelihood's own slope there is not
        # zero: keep the fitted gradient, or the prior would be counted twice
        # (only where the fit curves down: along a direction it does not, the quadratic says nothing)
        slope = np.empty(3)
        slope[0], slope[1], slope[2] = coef[1] / gain, coef[2] / gain, coef[3] / gain
        along = eigvec.T @ slope
        for e in range(3):
            if eigval[e] <= 0.0:
                along[e] = 0.0
        pull = eigvec @ along + qd
        precision = hess + q_inv[j]
        covariance = np.linalg.inv(precision)
        shift_local = covariance @ pull
        mean[j, 0], mean[j, 1], mean[j, 2] = bx + shift_local[0], by + shift_local[1], bt + shift_local[2]
        cov[j] = covariance
        _sign, logdet_p = np.linalg.slogdet(precision)
        log_eta[j] = coef[0] / gain - 0.5 * q_logdet[j] - 0.5 * logdet_p - 0.5 * (d @ qd - pull @ shift_local)
    return matched, scores, mean, cov, log_eta
