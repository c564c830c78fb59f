"""Compiled inner loops of grid FastSLAM: scan insertion into each particle's tiled grid, the scan likelihood,
the scan matcher and the improved proposal. Each loops over particles and beams inside numba.

Shared arguments: ``pool`` (C, S, S, 4) float32 tiles of cells (log-odds, summed end-point offsets x and
y, end-point count; slam.gridslam.tiles; S = 2**shift), ``table`` (M, NY, NX) int32 tile ids per
particle (-1: none) over tile coordinates (tx0 + u, ty0 + v), ``res`` the cell size (m); cells follow the
global lattice of mapping.raytrace (cell (ix, iy) covers [ix*res, (ix+1)*res) x [iy*res, (iy+1)*res)).
Poses are robot poses (x m, y m, yaw rad) in the map frame; ``offset`` (3,) is the laser's pose in the
robot frame; beams are given by their direction in the laser frame (``cos_b``, ``sin_b``) and range (m).

Inside, the helpers take these bundled in tuples: ``grid`` (pool, table, tx0, ty0, shift, res), ``beams``
(offset, cos_b, sin_b, rng), ``field`` (the likelihood field: cells searched around a beam's end, 1 / 2 s_m^2
and 1 / 2 s_l^2 in m^-2, log p_rand, p_rand; :func:`_likelihood_field`) and ``prior`` (predicted (M, 3),
q_inv (M, 3, 3), prior_cap, gain; :func:`_objective`).
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel
from mapping.raytrace import trace_ray

#: hill-climbing refinements (the last ones, with the smallest steps) that use every beam
FINE_REFINEMENTS = 3
#: the most hill-climbing moves at one step size
MAX_CLIMB_MOVES = 64


@kernel(nogil=True, inline="always")
def _tile_coords(tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    """Table entry (u, v) of the tile holding cell (ix, iy); it may lie outside the table (:func:`_outside`)."""
    return (ix >> shift) - tx0, (iy >> shift) - ty0


@kernel(nogil=True, inline="always")
def _outside(table, u, v):  # pragma: no cover - compiled
    """Whether entry (u, v) lies outside the table (NY x NX entries per particle)."""
    return u < 0 or v < 0 or u >= table.shape[2] or v >= table.shape[1]


@kernel(nogil=True, inline="always")
def _tile_id(table, j, tx0, ty0, shift, ix, iy):  # pragma: no cover - compiled
    """Pool tile of particle j holding cell (ix, iy), -1 where it has none."""
    u, v = _tile_coords(tx0, ty0, shift, ix, iy)
    if _outside(table, u, v):
        return -1
    return table[j, v, u]


@kernel(nogil=True, inline="always")
def _value(grid, j, ix, iy):  # pragma: no cover - compiled
    """Log-odds of cell (ix, iy) in particle j's grid (0 where it has no tile)."""
    pool, table, tx0, ty0, shift, _res = grid
    tid = _tile_id(table, j, tx0, ty0, shift, ix, iy)
    if tid < 0:
        return 0.0
    mask = (1 << shift) - 1
    return pool[tid, iy & mask, ix & mask, 0]


@kernel(nogil=True, inline="always")
def _laser_pose(x, y, th, offset):  # pragma: no cover - compiled
    """The laser's position (m, map frame) and the cosine and sine of its heading, for robot pose (x, y, th)."""
    c, s = math.cos(th), math.sin(th)
    lth = th + offset[2]
    return x + c * offset[0] - s * offset[1], y + s * offset[0] + c * offset[1], math.cos(lth), math.sin(lth)


@kernel(nogil=True, inline="always")
def _beam_direction(cl, sl, cos_b, sin_b, i):  # pragma: no cover - compiled
    """Unit direction (map frame) of beam i from a laser heading with cosine cl and sine sl."""
    return cl * cos_b[i] - sl * sin_b[i], sl * cos_b[i] + cl * sin_b[i]


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
def insert_scan(pool, refcount, free_stack, n_free, table, frame, scan, update, resume, counters):  # pragma: no cover
    """Insert one scan into every particle's grid, particle j seeing it from ``poses[j]``.

    ``frame`` is (tx0, ty0, shift, res), ``scan`` (poses (M, 3), offset, cos_b, sin_b, r_stop, hit) and
    ``update`` (l_occ, l_free, l_min, l_max). Adds ``l_free`` to every cell a beam crosses before its end and
    ``l_occ`` to its end cell when ``hit[i]`` (also adding the end point to the cell's end-point sums);
    log-odds stay in [l_min, l_max]. ``r_stop`` (B,) m is each beam's length (NaN: beam unused). A tile a
    particle shares or lacks is made its own first (:func:`own_tile`). When the free list runs dry the kernel
    stops, stores where it was in ``resume`` (particle, beam, cell) and returns False; called again with a
    grown pool and the same ``resume`` it continues there. ``counters`` accumulates (cell updates, tiles
    copied). True when done.
    """
    tx0, ty0, shift, res = frame
    poses, offset, cos_b, sin_b, r_stop, hit = scan
    l_occ, l_free, l_min, l_max = update
    _check_rows(table, poses, cos_b, sin_b, r_stop)
    if hit.shape[0] != cos_b.shape[0]:
        raise ValueError("hit must have one entry per beam")
    m = table.shape[0]
    longest = np.nanmax(r_stop) if r_stop.shape[0] else 0.0  # NaN when no beam is used
    cap = int(math.ceil(longest * math.sqrt(2.0) / res)) + 3 if longest > 0.0 else 3
    bix = np.empty(cap, np.int64)
    biy = np.empty(cap, np.int64)
    brin = np.empty(cap, np.float64)
    brout = np.empty(cap, np.float64)
    mask = (1 << shift) - 1
    for j in range(resume[0], m):
        lx, ly, cl, sl = _laser_pose(poses[j, 0], poses[j, 1], poses[j, 2], offset)
        first_beam = resume[1] if j == resume[0] else 0
        for i in range(first_beam, cos_b.shape[0]):
            if not r_stop[i] > 0.0:
                continue
            dx, dy = _beam_direction(cl, sl, cos_b, sin_b, i)
            n = trace_ray(lx, ly, dx, dy, r_stop[i], res, bix, biy, brin, brout)
            ex, ey = lx + r_stop[i] * dx, ly + r_stop[i] * dy
            first_cell = resume[2] if (j == resume[0] and i == resume[1]) else 0
            last_u, last_v, tid = -1, -1, -1
            for k in range(first_cell, n):
                u, v = _tile_coords(tx0, ty0, shift, bix[k], biy[k])
                if _outside(table, u, v):
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
                    pool[tid, cy, cx, 1] += ex - bix[k] * res
                    pool[tid, cy, cx, 2] += ey - biy[k] * res
                    pool[tid, cy, cx, 3] += 1.0
                counters[0] += 1
    resume[0], resume[1], resume[2] = m, 0, 0
    return True


@kernel(nogil=True, inline="always")
def _candidate(grid, j, ex, ey, dx, dy, ix, iy, tid, best):  # pragma: no cover - compiled
    """best, lowered to the squared distance (m^2) from (ex, ey) to the mean end point of cell (ix, iy)
    (in pool tile ``tid``) when that cell is occupied (log-odds > 0) and the point one cell back along the
    beam (dx, dy) is not."""
    if tid < 0:
        return best
    pool, _table, _tx0, _ty0, shift, res = grid
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
    d2 = (px - ex) * (px - ex) + (py - ey) * (py - ey)
    if d2 >= best:  # (the cell behind is looked up only for a cell that would be the nearest)
        return best
    fx = int(math.floor((px - dx * res) / res))
    fy = int(math.floor((py - dy * res) / res))
    if (fx ^ ix) >> shift == 0 and (fy ^ iy) >> shift == 0:  # in the same tile (the usual case): no table look-up
        behind = pool[tid, fy & mask, fx & mask, 0]
    else:
        behind = _value(grid, j, fx, fy)
    if behind > 0.0:
        return best
    return d2


@kernel(nogil=True, inline="always")
def _nearest_end(grid, j, ex, ey, dx, dy, radius, inv_res):  # pragma: no cover - compiled
    """Squared distance (m^2) from a beam's end (ex, ey) along (dx, dy) to the nearest :func:`_candidate`
    cell within ``radius`` cells of it in particle j's grid (inf: none); inv_res is 1 / res (1/m)."""
    _pool, table, tx0, ty0, shift, _res = grid
    side = 1 << shift
    mask = side - 1
    cx = int(math.floor(ex * inv_res))
    cy = int(math.floor(ey * inv_res))
    best = np.inf
    tid = _tile_id(table, j, tx0, ty0, shift, cx, cy)
    ox = cx & mask
    oy = cy & mask
    if radius <= ox < side - radius and radius <= oy < side - radius:
        # the whole neighbourhood lies in one tile
        if tid >= 0:
            for b in range(-radius, radius + 1):
                for a in range(-radius, radius + 1):
                    best = _candidate(grid, j, ex, ey, dx, dy, cx + a, cy + b, tid, best)
    else:
        for b in range(-radius, radius + 1):
            for a in range(-radius, radius + 1):
                cell_tid = _tile_id(table, j, tx0, ty0, shift, cx + a, cy + b)
                best = _candidate(grid, j, ex, ey, dx, dy, cx + a, cy + b, cell_tid, best)
    return best


@kernel(nogil=True, inline="always")
def _likelihood_field(radius, sigma_match, sigma_like, p_rand):  # pragma: no cover - compiled
    """The ``field`` tuple of the likelihood field: cells searched around a beam's end, 1 / 2 s_m^2 and
    1 / 2 s_l^2 (m^-2) from the sigmas (m), log p_rand and p_rand."""
    return radius, 0.5 / sigma_match**2, 0.5 / sigma_like**2, math.log(p_rand), p_rand


@kernel(nogil=True)
def _evaluate(grid, j, x, y, th, beams, field, stride, with_loglik):  # pragma: no cover - compiled
    """(match score, log-likelihood) of the beams (offset, cos_b, sin_b, rng) from robot pose (x, y, th) on
    particle j's grid. For each beam end the nearest mean end point of an occupied cell (log-odds > 0)
    within ``field[0]`` cells whose neighbour one cell back towards the laser is not occupied gives the
    distance d (m); the score adds exp(-d^2 / 2 s_m^2), the log-likelihood
    log(p_rand + (1 - p_rand) exp(-d^2 / 2 s_l^2)) (log p_rand when there is no such cell; 0 without
    ``with_loglik``, a constant at every call site: the search needs the score only). Only every
    ``stride``-th beam is used."""
    offset, cos_b, sin_b, rng = beams
    radius, inv2s2_match, inv2s2_like, log_p_rand, p_rand = field
    lx, ly, cl, sl = _laser_pose(x, y, th, offset)
    inv_res = 1.0 / grid[5]
    score = 0.0
    loglik = 0.0
    for i in range(0, cos_b.shape[0], stride):
        dx, dy = _beam_direction(cl, sl, cos_b, sin_b, i)
        best = _nearest_end(grid, j, lx + rng[i] * dx, ly + rng[i] * dy, dx, dy, radius, inv_res)
        if best < np.inf:
            score += math.exp(-best * inv2s2_match)
            if with_loglik:
                loglik += math.log(p_rand + (1.0 - p_rand) * math.exp(-best * inv2s2_like))
        elif with_loglik:
            loglik += log_p_rand
    return score, loglik


@kernel(nogil=True, inline="always")
def _objective(grid, j, x, y, th, beams, field, prior, stride):  # pragma: no cover - compiled
    """(match score / gain + log of the motion density, up to a constant; match score) at pose (x, y, th)
    for particle j; ``prior`` is (predicted (M, 3), q_inv (M, 3, 3), prior_cap, gain). The score stands in
    for the log-likelihood in the search (each beam's term exp(-d^2 / 2 s_m^2) is about the log-likelihood's
    change between a matched and an unmatched beam, and it locates the optimum more precisely: on a synthetic
    room within 1 cm where the log-likelihood strays 5 cm). With ``stride`` > 1 the score of the beams used
    is scaled up to all beams."""
    predicted, q_inv, prior_cap, gain = prior
    score, _loglik = _evaluate(grid, j, x, y, th, beams, field, stride, False)
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
    grid = (pool, table, tx0, ty0, shift, res)
    beams = (offset, cos_b, sin_b, rng)
    field = _likelihood_field(kernel, sigma_match, sigma_like, p_rand)
    m = poses.shape[0]
    loglik = np.empty(m)
    score = np.empty(m)
    for j in range(m):
        score[j], loglik[j] = _evaluate(grid, j, poses[j, 0], poses[j, 1], poses[j, 2], beams, field, 1, True)
    return loglik, score


@kernel(nogil=True)
def _search_yaws(grid, j, beams, field, prior, starts, ang_step, yaw_search, stride):  # pragma: no cover
    """The best (objective, score, x, y, yaw) of the yaws predicted[j] + k ang_step, |k ang_step| <=
    ``yaw_search`` rad, each tried at the predicted position and at the positions ``starts[j]`` (S, 2) m."""
    predicted = prior[0]
    bx, by, bt = predicted[j, 0], predicted[j, 1], predicted[j, 2]
    best, score = _objective(grid, j, bx, by, bt, beams, field, prior, stride)
    turns = int(yaw_search / ang_step)
    start_t = bt
    for st in range(starts.shape[1] + 1):
        sx, sy = (predicted[j, 0], predicted[j, 1]) if st == 0 else (starts[j, st - 1, 0], starts[j, st - 1, 1])
        for k in range(-turns, turns + 1):
            if k == 0 and st == 0:
                continue
            f, s = _objective(grid, j, sx, sy, start_t + k * ang_step, beams, field, prior, stride)
            if f > best:
                best, score, bx, by, bt = f, s, sx, sy, start_t + k * ang_step
    return best, score, bx, by, bt


@kernel(nogil=True, inline="always")
def _neighbour(x, y, th, move, lin, ang):  # pragma: no cover - compiled
    """Pose (x, y, th) moved by hill-climbing move 0..5: +lin, -lin m in x, then in y; +ang, -ang rad in yaw."""
    if move == 0:
        return x + lin, y, th
    if move == 1:
        return x - lin, y, th
    if move == 2:
        return x, y + lin, th
    if move == 3:
        return x, y - lin, th
    if move == 4:
        return x, y, th + ang
    return x, y, th - ang


@kernel(nogil=True)
def _climb(grid, j, beams, field, prior, stride, lin, ang, found):  # pragma: no cover - compiled
    """Hill climbing from ``found`` (objective, score, x, y, yaw): take the best of the six moves of +-lin m
    in x and y and +-ang rad in yaw while it raises the objective, at most :data:`MAX_CLIMB_MOVES` times. The move
    back to where the last move came from is not tried: its objective is below the current one (moves are taken only
    when they raise it), so it could not be taken."""
    best, score, bx, by, bt = found
    taken = -1
    for _it in range(MAX_CLIMB_MOVES):
        cand_x, cand_y, cand_t, cand_f, cand_s = bx, by, bt, best, score
        cand_move = -1
        for move in range(6):
            if taken >= 0 and move == (taken ^ 1):  # moves 2k and 2k + 1 undo each other
                continue
            tx, ty, tt = _neighbour(bx, by, bt, move, lin, ang)
            f, s = _objective(grid, j, tx, ty, tt, beams, field, prior, stride)
            if f > cand_f:
                cand_x, cand_y, cand_t, cand_f, cand_s, cand_move = tx, ty, tt, f, s, move
        if cand_f > best:
            bx, by, bt, best, score, taken = cand_x, cand_y, cand_t, cand_f, cand_s, cand_move
        else:
            break
    return best, score, bx, by, bt


@kernel(nogil=True)
def _match(grid, j, beams, field, prior, starts, search):  # pragma: no cover - compiled
    """Particle j's scan match (objective, score, x, y, yaw): :func:`_search_yaws`, then :func:`_climb` with
    the steps of ``search`` (lin_step m, ang_step rad, refinements, yaw_search rad) halved ``refinements``
    times. The yaw search and all but the last :data:`FINE_REFINEMENTS` refinements use every second beam."""
    lin, ang, refinements, yaw_search = search
    stride = 2 if refinements > FINE_REFINEMENTS else 1
    found = _search_yaws(grid, j, beams, field, prior, starts, ang, yaw_search, stride)
    for r in range(refinements):
        if stride == 2 and r >= refinements - FINE_REFINEMENTS:
            stride = 1
            _, _, bx, by, bt = found
            best, score = _objective(grid, j, bx, by, bt, beams, field, prior, stride)
            found = (best, score, bx, by, bt)
        found = _climb(grid, j, beams, field, prior, stride, lin, ang, found)
        lin *= 0.5
        ang *= 0.5
    return found


@kernel(nogil=True)
def _laplace(coef, gain, predicted, q_inv, q_logdet, bx, by, bt):  # pragma: no cover - compiled
    """The improved proposal around the match (bx, by, bt) of one particle (see :func:`match_and_propose`)
    from the fitted quadratic ``coef`` (10,), the prediction (3,) and the motion model's information
    q_inv (3, 3) and log det Q: (mean x, y, yaw, covariance (3, 3), log eta)."""
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
    d[0] = predicted[0] - bx
    d[1] = predicted[1] - by
    d[2] = (predicted[2] - bt + math.pi) % (2.0 * math.pi) - math.pi
    qd = q_inv @ d
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
    precision = hess + q_inv
    covariance = np.linalg.inv(precision)
    shift = covariance @ pull
    _sign, logdet_p = np.linalg.slogdet(precision)
    log_eta = coef[0] / gain - 0.5 * q_logdet - 0.5 * logdet_p - 0.5 * (d @ qd - pull @ shift)
    return bx + shift[0], by + shift[1], bt + shift[2], covariance, log_eta


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
    grid = (pool, table, tx0, ty0, shift, res)
    beams = (offset, cos_b, sin_b, rng)
    field = _likelihood_field(kernel, sigma_match, sigma_like, p_rand)
    prior = (predicted, q_inv, prior_cap, gain)
    search = (lin_step, ang_step, refinements, yaw_search)
    m = predicted.shape[0]
    matched = np.empty((m, 3))
    scores = np.empty(m)
    mean = np.empty((m, 3))
    cov = np.empty((m, 3, 3))
    log_eta = np.empty(m)
    ll_k = np.empty(stencil.shape[0])
    for j in range(m):
        _, scores[j], bx, by, bt = _match(grid, j, beams, field, prior, starts, search)
        matched[j, 0], matched[j, 1], matched[j, 2] = bx, by, bt
        for k in range(stencil.shape[0]):
            _, ll_k[k] = _evaluate(
                grid, j, bx + stencil[k, 0], by + stencil[k, 1], bt + stencil[k, 2], beams, field, 1, True
            )
        mx, my, mt, cov[j], log_eta[j] = _laplace(fit @ ll_k, gain, predicted[j], q_inv[j], q_logdet[j], bx, by, bt)
        mean[j, 0], mean[j, 1], mean[j, 2] = mx, my, mt
    return matched, scores, mean, cov, log_eta
