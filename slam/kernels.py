"""Compiled (numba) inner loops of the landmark filters: the velocity model over one step's controls and over the
self-calibration's windows, the invariant EKF's likelihood pass for self-calibration, and FastSLAM's per-step
update with known ids.

Units as everywhere in slam/: metres, radians, seconds; poses (x, y, theta). Each kernel is the only
implementation of what it computes; the filters in slam/ekf.py, slam/fastslam.py and slam/selfcal.py call them.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel

#: log(2 pi)
LOG_2PI = math.log(2.0 * math.pi)


@kernel()
def _wrap(angle):  # pragma: no cover - compiled
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@kernel()
def _sinc_and_derivative(a):  # pragma: no cover - compiled
    """sin(a)/a and its derivative, with Taylor series near 0 (as slam.motion's _sinc and _dsinc)."""
    if a == 0.0:
        return 1.0, 0.0
    s = math.sin(a) / a
    if abs(a) < 1e-3:
        return s, -a / 3.0 + a**3 / 30.0
    return s, (a * math.cos(a) - math.sin(a)) / (a * a)


@kernel(inline="always")
def _arc(th, v, w, dt):  # pragma: no cover - compiled
    """One control (v m/s, w rad/s, dt s) of the velocity model from heading th (rad): sinc(w dt / 2) and its
    derivative, the chord length v dt sinc (m), and the cosine and sine of the chord's heading th + w dt / 2. The
    pose moves by the chord along that heading and turns by w dt."""
    half = w * dt / 2.0
    s, ds = _sinc_and_derivative(half)
    return s, ds, v * dt * s, math.cos(th + half), math.sin(th + half)


@kernel()
def velocity_local_motion(controls, alphas, floor, dt_ref, delta, cov):  # pragma: no cover - compiled
    """The velocity model (slam.motion.VelocityMotionModel) over the controls (K, 3) (v m/s, w rad/s, dt s) of
    one step, from a pose at the origin: writes the noise-free end pose ``delta`` (3,) and its linearised
    covariance ``cov`` (3, 3), both in the start frame (cov <- G cov G^T + V M V^T per control)."""
    x = y = th = 0.0
    for i in range(3):
        delta[i] = 0.0
        for j in range(3):
            cov[i, j] = 0.0
    jac_v = np.zeros((3, 3))
    tmp = np.zeros((3, 3))
    for k in range(controls.shape[0]):
        v, w, dt = controls[k, 0], controls[k, 1], controls[k, 2]
        if dt <= 0.0:
            continue
        moving = v != 0.0 or w != 0.0
        scale = dt_ref / dt
        var0 = (alphas[0] * v * v + alphas[1] * w * w + (floor[0] if moving else 0.0)) * scale
        var1 = (alphas[2] * v * v + alphas[3] * w * w + (floor[1] if moving else 0.0)) * scale
        var2 = (alphas[4] * v * v + alphas[5] * w * w) * scale
        s, ds, dist, ch, sh = _arc(th, v, w, dt)
        g02, g12 = -dist * sh, dist * ch
        # cov <- G cov G^T with G = I + g02 e0 e2^T + g12 e1 e2^T
        for j in range(3):
            cov[0, j] += g02 * cov[2, j]
            cov[1, j] += g12 * cov[2, j]
        for i in range(3):
            cov[i, 0] += g02 * cov[i, 2]
            cov[i, 1] += g12 * cov[i, 2]
        jac_v[0, 0], jac_v[1, 0], jac_v[2, 0] = dt * s * ch, dt * s * sh, 0.0
        jac_v[0, 1] = (v * dt * ds * ch - dist * sh) * (dt / 2.0)
        jac_v[1, 1] = (v * dt * ds * sh + dist * ch) * (dt / 2.0)
        jac_v[2, 1] = dt
        jac_v[0, 2], jac_v[1, 2], jac_v[2, 2] = 0.0, 0.0, dt
        for i in range(3):
            tmp[i, 0] = jac_v[i, 0] * var0
            tmp[i, 1] = jac_v[i, 1] * var1
            tmp[i, 2] = jac_v[i, 2] * var2
        for i in range(3):
            for j in range(3):
                cov[i, j] += tmp[i, 0] * jac_v[j, 0] + tmp[i, 1] * jac_v[j, 1] + tmp[i, 2] * jac_v[j, 2]
        x += dist * ch
        y += dist * sh
        th += w * dt
    delta[0], delta[1], delta[2] = x, y, _wrap(th)


@kernel()
def window_commands(controls, corrected, first, last, yaw_scale, out):  # pragma: no cover - compiled
    """Per window w, the controls controls[first[w]:last[w]] (K, 3) (v m/s, w rad/s, dt s) as logged and
    ``corrected`` (the same rows with a calibration's corrections): out[w] (6,) = the noise-free end pose (x, y) m
    in the window's start frame of the commands with only their yaw rate scaled by ``yaw_scale`` (integrated as
    velocity_local_motion does), the commanded yaw change sum(w dt) rad as logged, the time spent moving sum(dt)
    s, and the corrected sum(v^2 dt) ((m/s)^2 s) and sum(w^2 dt) ((rad/s)^2 s)."""
    for n in range(first.shape[0]):
        x = y = th = 0.0
        turn = moving = v2 = w2 = 0.0
        for k in range(first[n], last[n]):
            v, w, dt = controls[k, 0], controls[k, 1], controls[k, 2]
            turn += w * dt
            if v != 0.0 or w != 0.0:
                moving += dt
            v2 += corrected[k, 0] * corrected[k, 0] * dt
            w2 += corrected[k, 1] * corrected[k, 1] * dt
            if dt <= 0.0:
                continue
            w = w * yaw_scale
            _s, _ds, dist, ch, sh = _arc(th, v, w, dt)
            x += dist * ch
            y += dist * sh
            th += w * dt
        out[n, 0], out[n, 1], out[n, 2], out[n, 3], out[n, 4], out[n, 5] = x, y, turn, moving, v2, w2


@kernel()
def _turn_covariance(cov, c, s, out):  # pragma: no cover - compiled
    """out = R cov R^T for R the rotation by the angle of (cos c, sin s) in the (x, y) block (3x3, symmetric)."""
    out[0, 0] = c * c * cov[0, 0] - 2.0 * c * s * cov[0, 1] + s * s * cov[1, 1]
    out[1, 1] = s * s * cov[0, 0] + 2.0 * c * s * cov[0, 1] + c * c * cov[1, 1]
    out[0, 1] = out[1, 0] = c * s * (cov[0, 0] - cov[1, 1]) + (c * c - s * s) * cov[0, 1]
    out[0, 2] = out[2, 0] = c * cov[0, 2] - s * cov[1, 2]
    out[1, 2] = out[2, 1] = s * cov[0, 2] + c * cov[1, 2]
    out[2, 2] = cov[2, 2]


# ------------------------------------------------------------------------------------- invariant EKF pass


@kernel()
def _ekf_predict(mu, sigma, seen, delta, cov_local, column):  # pragma: no cover - compiled
    """Move the pose by ``delta`` (start frame) and add the step's noise B q B^T in invariant coordinates (q:
    cov_local turned to the world frame; B as slam.ekf.EKFSLAM.predict builds it at the new pose)."""
    n = mu.shape[0]
    c, s = math.cos(mu[2]), math.sin(mu[2])
    q = np.empty((3, 3))
    _turn_covariance(cov_local, c, s, q)
    mu[0] += c * delta[0] - s * delta[1]
    mu[1] += s * delta[0] + c * delta[1]
    mu[2] = _wrap(mu[2] + delta[2])
    # column = B[:, 2]: (y, -x, 1) for the pose, (m_y, -m_x) for each seen landmark, 0 for the others
    column[:] = 0.0
    column[0], column[1], column[2] = mu[1], -mu[0], 1.0
    for j in range(seen.shape[0]):
        if seen[j]:
            column[3 + 2 * j] = mu[4 + 2 * j]
            column[4 + 2 * j] = -mu[3 + 2 * j]
    # B q B^T with B = [e0, e1, column]
    for a in range(n):
        ba0 = 1.0 if a == 0 else 0.0
        ba1 = 1.0 if a == 1 else 0.0
        row0 = ba0 * q[0, 0] + ba1 * q[1, 0] + column[a] * q[2, 0]
        row1 = ba0 * q[0, 1] + ba1 * q[1, 1] + column[a] * q[2, 1]
        row2 = ba0 * q[0, 2] + ba1 * q[1, 2] + column[a] * q[2, 2]
        if row0 == 0.0 and row1 == 0.0 and row2 == 0.0:
            continue
        sigma[a, 0] += row0
        sigma[a, 1] += row1
        for b in range(n):
            sigma[a, b] += row2 * column[b]


@kernel()
def _ekf_retract(mu, seen, xi):  # pragma: no cover - compiled
    """X^ <- exp(-xi) X^ (slam.ekf.EKFSLAM._retract)."""
    angle = -xi[2]
    c, s = math.cos(angle), math.sin(angle)
    if abs(angle) < 1e-9:
        v00, v01, v10, v11 = 1.0, 0.0, 0.0, 1.0
    else:
        sa, ca = math.sin(angle), math.cos(angle)
        v00, v01, v10, v11 = sa / angle, (ca - 1.0) / angle, (1.0 - ca) / angle, sa / angle
    px, py = mu[0], mu[1]
    mu[0] = c * px - s * py - (v00 * xi[0] + v01 * xi[1])
    mu[1] = s * px + c * py - (v10 * xi[0] + v11 * xi[1])
    for j in range(seen.shape[0]):
        if seen[j]:
            i = 3 + 2 * j
            mx, my = mu[i], mu[i + 1]
            mu[i] = c * mx - s * my - (v00 * xi[i] + v01 * xi[i + 1])
            mu[i + 1] = s * mx + c * my - (v10 * xi[i] + v11 * xi[i + 1])
    mu[2] = _wrap(mu[2] + angle)


@kernel()
def _ekf_add_landmark(mu, sigma, seen, j, r, phi, r00, r11):  # pragma: no cover - compiled
    """Start landmark slot j from measurement (r, phi) with noise diag(r00, r11) (slam.ekf's _add_landmark)."""
    i = 3 + 2 * j
    angle = mu[2] + phi
    c, s = math.cos(angle), math.sin(angle)
    mu[i] = mu[0] + r * c
    mu[i + 1] = mu[1] + r * s
    n = mu.shape[0]
    for b in range(n):
        sigma[i, b] = sigma[0, b]
        sigma[i + 1, b] = sigma[1, b]
    for a in range(n):
        sigma[a, i] = sigma[a, 0]
        sigma[a, i + 1] = sigma[a, 1]
    # + J_z R J_z^T with J_z = [[c, -r s], [s, r c]]
    sigma[i, i] = sigma[0, 0] + c * c * r00 + r * r * s * s * r11
    sigma[i, i + 1] = sigma[0, 1] + c * s * r00 - r * r * s * c * r11
    sigma[i + 1, i] = sigma[i, i + 1]
    sigma[i + 1, i + 1] = sigma[1, 1] + s * s * r00 + r * r * c * c * r11
    seen[j] = True


@kernel()
def _ekf_update(mu, sigma, seen, j, r_meas, phi, r00, r11, huber, h_sigma, gain):  # pragma: no cover - compiled
    """Fuse the measurement (r_meas, phi) of landmark slot j (noise diag(r00, r11)) as slam.ekf.EKFSLAM does, with
    S inflated by sqrt(d^2 / huber) beyond the Huber bound; ``h_sigma`` (2, n) and ``gain`` (n, 2) are scratch.
    Returns d^2, log det S and the innovation (nu0, nu1), all with the plain S."""
    n = mu.shape[0]
    i = 3 + 2 * j
    dx, dy = mu[i] - mu[0], mu[i + 1] - mu[1]
    q = max(dx * dx + dy * dy, 1e-18)
    r = math.sqrt(q)
    h00, h01, h10, h11 = dx / r, dy / r, -dy / q, dx / q
    for b in range(n):  # H Sigma, H = h_m on xi_p and -h_m on xi_mj
        d0 = sigma[0, b] - sigma[i, b]
        d1 = sigma[1, b] - sigma[i + 1, b]
        h_sigma[0, b] = h00 * d0 + h01 * d1
        h_sigma[1, b] = h10 * d0 + h11 * d1
    a00, a01 = h_sigma[0, 0] - h_sigma[0, i], h_sigma[0, 1] - h_sigma[0, i + 1]
    a10, a11 = h_sigma[1, 0] - h_sigma[1, i], h_sigma[1, 1] - h_sigma[1, i + 1]
    s00 = a00 * h00 + a01 * h01 + r00
    s01 = a00 * h10 + a01 * h11
    s11 = a10 * h10 + a11 * h11 + r11
    nu0 = r_meas - r
    nu1 = _wrap(phi - (math.atan2(dy, dx) - mu[2]))
    det = s00 * s11 - s01 * s01
    d2 = (s11 * nu0 * nu0 - 2.0 * s01 * nu0 * nu1 + s00 * nu1 * nu1) / det
    inflate = math.sqrt(d2 / huber) if d2 > huber else 1.0
    edet = det * inflate * inflate
    i00, i01, i11 = s11 * inflate / edet, -s01 * inflate / edet, s00 * inflate / edet
    for b in range(n):  # gain = (S^-1 H Sigma)^T
        gain[b, 0] = i00 * h_sigma[0, b] + i01 * h_sigma[1, b]
        gain[b, 1] = i01 * h_sigma[0, b] + i11 * h_sigma[1, b]
    _ekf_retract(mu, seen, gain[:, 0] * nu0 + gain[:, 1] * nu1)
    for a in range(n):
        for b in range(a, n):
            value = sigma[a, b] - (gain[a, 0] * h_sigma[0, b] + gain[a, 1] * h_sigma[1, b])
            sigma[a, b] = value
            sigma[b, a] = value
    return d2, math.log(det), nu0, nu1


@kernel()
def ekf_likelihood_pass(
    controls,
    control_ptr,
    z,
    slot,
    measurement_ptr,
    initial_pose,
    n_slots,
    alphas,
    floor,
    dt_ref,
    sensor,
    huber,
    out_d2,
    out_logdet,
    out_nu,
    out_pose,
    out_map,
):  # pragma: no cover - compiled
    """Run the right-invariant EKF-SLAM (slam.ekf) with known ids over a sequence and record, per measurement, its
    squared Mahalanobis distance ``out_d2`` (O,), log det S ``out_logdet`` (O,) and innovation ``out_nu`` (O, 2);
    NaN for a measurement that starts a landmark; the pose after each step's updates ``out_pose`` (T, 3) and the
    final landmark positions ``out_map`` (n_slots, 2) (NaN: never seen). ``slot`` (O,) maps measurements to
    landmark slots 0..n_slots-1.
    Noise: the velocity model's ``alphas`` (6,), ``floor`` (2,), ``dt_ref`` s; ``sensor`` (sigma_r m, range
    fraction, sigma_bearing rad). A measurement with d^2 > ``huber`` is fused with its S inflated by
    sqrt(d^2 / huber), the Huber weight, so that outliers bend the estimate less (no gate: the likelihood stays
    continuous in the parameters)."""
    n = 3 + 2 * n_slots
    mu = np.zeros(n)
    # (positions relative to the start, as slam.ekf.EKFSLAM rotates its error about it: the same filter, without
    # the 1e13 terms a start 5e6 m from the map origin would put in sigma)
    ox, oy = initial_pose[0], initial_pose[1]
    mu[2] = initial_pose[2]
    sigma = np.zeros((n, n))
    seen = np.zeros(n_slots, dtype=np.bool_)
    delta = np.zeros(3)
    cov_local = np.zeros((3, 3))
    column = np.zeros(n)
    h_sigma = np.zeros((2, n))
    gain = np.zeros((n, 2))
    for t in range(control_ptr.shape[0] - 1):
        if control_ptr[t + 1] > control_ptr[t]:
            velocity_local_motion(
                controls[control_ptr[t] : control_ptr[t + 1]], alphas, floor, dt_ref, delta, cov_local
            )
            _ekf_predict(mu, sigma, seen, delta, cov_local, column)
        for k in range(measurement_ptr[t], measurement_ptr[t + 1]):
            j = slot[k]
            r_meas, phi = z[k, 0], z[k, 1]
            sd_r = sensor[0] + sensor[1] * r_meas
            r00, r11 = sd_r * sd_r, sensor[2] * sensor[2]
            if not seen[j]:
                _ekf_add_landmark(mu, sigma, seen, j, r_meas, phi, r00, r11)
                out_d2[k] = np.nan
                out_logdet[k] = np.nan
                out_nu[k, 0] = np.nan
                out_nu[k, 1] = np.nan
                continue
            d2, logdet, nu0, nu1 = _ekf_update(mu, sigma, seen, j, r_meas, phi, r00, r11, huber, h_sigma, gain)
            out_d2[k], out_logdet[k], out_nu[k, 0], out_nu[k, 1] = d2, logdet, nu0, nu1
        out_pose[t, 0], out_pose[t, 1], out_pose[t, 2] = mu[0] + ox, mu[1] + oy, mu[2]
    for j in range(n_slots):
        out_map[j, 0] = mu[3 + 2 * j] + ox if seen[j] else np.nan
        out_map[j, 1] = mu[4 + 2 * j] + oy if seen[j] else np.nan


# ---------------------------------------------------------------------------------------- FastSLAM


@kernel()
def _cholesky3_draw(p, normal, out):  # pragma: no cover - compiled
    """out = L normal with L L^T = p (3x3, positive semi-definite; a zero pivot gives a zero column)."""
    root = np.zeros((3, 3))
    for j in range(3):
        pivot = p[j, j]
        for k in range(j):
            pivot -= root[j, k] * root[j, k]
        diag = math.sqrt(pivot) if pivot > 0.0 else 0.0
        root[j, j] = diag
        for i in range(j + 1, 3):
            below = p[i, j]
            for k in range(j):
                below -= root[i, k] * root[j, k]
            root[i, j] = below / diag if diag > 1e-150 else 0.0
    for i in range(3):
        out[i] = root[i, 0] * normal[0] + root[i, 1] * normal[1] + root[i, 2] * normal[2]


@kernel()
def _predict_particles(poses, pose_cov, delta, cov_local):  # pragma: no cover - compiled
    """Version 2's prior: each pose moved by delta in its own frame, P = R cov_local R^T at its old heading."""
    for n in range(poses.shape[0]):
        c, s = math.cos(poses[n, 2]), math.sin(poses[n, 2])
        _turn_covariance(cov_local, c, s, pose_cov[n])
        poses[n, 0] += c * delta[0] - s * delta[1]
        poses[n, 1] += s * delta[0] + c * delta[1]
        poses[n, 2] = _wrap(poses[n, 2] + delta[2])


@kernel()
def _mixture_nis(log_w_before, known, nus, s_stack):  # pragma: no cover - compiled
    """NIS of a measurement under the particles' predictive mixture: nu_bar^T S_bar^-1 nu_bar with the weighted
    mean innovation and covariance (each particle's S plus the spread of the innovations). NaN: no particle knows
    the landmark yet."""
    top = -np.inf
    for n in range(known.shape[0]):
        if known[n] and log_w_before[n] > top:
            top = log_w_before[n]
    if top == -np.inf:
        return np.nan
    total = m0 = m1 = c00 = c01 = c11 = 0.0
    for n in range(known.shape[0]):
        if not known[n]:
            continue
        w = math.exp(log_w_before[n] - top)
        total += w
        m0 += w * nus[n, 0]
        m1 += w * nus[n, 1]
        c00 += w * (s_stack[n, 0] + nus[n, 0] * nus[n, 0])
        c01 += w * (s_stack[n, 1] + nus[n, 0] * nus[n, 1])
        c11 += w * (s_stack[n, 2] + nus[n, 1] * nus[n, 1])
    m0, m1 = m0 / total, m1 / total
    c00, c01, c11 = c00 / total - m0 * m0, c01 / total - m0 * m1, c11 / total - m1 * m1
    det = c00 * c11 - c01 * c01
    return (c11 * m0 * m0 - 2.0 * c01 * m0 * m1 + c00 * m1 * m1) / det


@kernel()
def _landmark_jacobian(pose, m0, m1):  # pragma: no cover - compiled
    """dx, dy, range, q = range^2 and H_m = [[h00, h01], [h10, h11]] of a landmark (m0, m1) seen from pose."""
    dx, dy = m0 - pose[0], m1 - pose[1]
    q = max(dx * dx + dy * dy, 1e-18)
    r = math.sqrt(q)
    return dx, dy, r, q, dx / r, dy / r, -dy / q, dx / q


@kernel()
def _sandwich2(h00, h01, h10, h11, cov):  # pragma: no cover - compiled
    """(H cov H^T)_00, _01, _11 for a 2x2 H and a symmetric 2x2 cov."""
    a, b, d = cov[0, 0], 0.5 * (cov[0, 1] + cov[1, 0]), cov[1, 1]
    u0, u1 = a * h00 + b * h01, b * h00 + d * h01
    w0, w1 = a * h10 + b * h11, b * h10 + d * h11
    return h00 * u0 + h01 * u1, h00 * w0 + h01 * w1, h10 * w0 + h11 * w1


@kernel()
def _kalman_step(pose, p, ph0, ph1, i00, i01, i11, nu0, nu1):  # pragma: no cover - compiled
    """In place: pose (3,) += K nu and P (3, 3) -= K (P H^T)^T, with K = (P H^T) S^-1; ph0, ph1 the columns of
    P H^T (3,), (i00, i01, i11) the symmetric S^-1 and (nu0, nu1) the innovation (m, rad). The heading is wrapped."""
    for a in range(3):
        k0 = ph0[a] * i00 + ph1[a] * i01
        k1 = ph0[a] * i01 + ph1[a] * i11
        pose[a] += k0 * nu0 + k1 * nu1
        for b in range(3):
            p[a, b] -= k0 * ph0[b] + k1 * ph1[b]
    pose[2] = _wrap(pose[2])


@kernel()
def _weigh_and_refine(version, n, poses, pose_cov, mu, sigma, j, z, r00, r11, gate):  # pragma: no cover - compiled
    """Particle n, measurement z of landmark slot j: innovation, S = H_x P H_x^T + H_m Sigma H_m^T + R, d^2, the
    capped log likelihood and (version 2, inlier) the Kalman refinement of the pose prior. Returns (nu0, nu1, s00,
    s01, s11, d2, loglik). H_x = -[H_m | (0, 1)^T] (the bearing falls as the heading grows)."""
    pose, p = poses[n], pose_cov[n]
    dx, dy, r, _, h00, h01, h10, h11 = _landmark_jacobian(pose, mu[n, j, 0], mu[n, j, 1])
    x00, x01, x10, x11 = -h00, -h01, -h10, -h11  # H_x's position columns; its heading column is (0, -1)
    ph0 = np.empty(3)  # P H_x^T, rows of P times H_x's two rows
    ph1 = np.empty(3)
    for a in range(3):
        ph0[a] = p[a, 0] * x00 + p[a, 1] * x01
        ph1[a] = p[a, 0] * x10 + p[a, 1] * x11 - p[a, 2]
    m00, m01, m11 = _sandwich2(h00, h01, h10, h11, sigma[n, j])
    s00 = x00 * ph0[0] + x01 * ph0[1] + m00 + r00
    s01 = x00 * ph1[0] + x01 * ph1[1] + m01
    s11 = x10 * ph1[0] + x11 * ph1[1] - ph1[2] + m11 + r11
    nu0 = z[0] - r
    nu1 = _wrap(z[1] - (math.atan2(dy, dx) - pose[2]))
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    d2 = i00 * nu0 * nu0 + 2.0 * i01 * nu0 * nu1 + i11 * nu1 * nu1
    loglik = -0.5 * min(d2, gate) - 0.5 * math.log(abs(det)) - LOG_2PI
    if version == 2 and d2 <= gate:
        _kalman_step(pose, p, ph0, ph1, i00, i01, i11, nu0, nu1)
    return nu0, nu1, s00, s01, s11, d2, loglik


@kernel()
def _fuse(poses, mu, sigma, n, j, z, r00, r11, new):  # pragma: no cover - compiled
    """Particle n's landmark slot j: EKF update with z from its (sampled) pose, or its start when ``new``."""
    r_meas, phi = z[0], z[1]
    cov = sigma[n, j]
    if new:
        angle = poses[n, 2] + phi
        c, s = math.cos(angle), math.sin(angle)
        mu[n, j, 0] = poses[n, 0] + r_meas * c
        mu[n, j, 1] = poses[n, 1] + r_meas * s
        cov[0, 0] = c * c * r00 + r_meas * r_meas * s * s * r11
        cov[0, 1] = cov[1, 0] = c * s * r00 - r_meas * r_meas * s * c * r11
        cov[1, 1] = s * s * r00 + r_meas * r_meas * c * c * r11
        return
    dx, dy, r, _, h00, h01, h10, h11 = _landmark_jacobian(poses[n], mu[n, j, 0], mu[n, j, 1])
    a, b, d = cov[0, 0], 0.5 * (cov[0, 1] + cov[1, 0]), cov[1, 1]
    sh00, sh01 = a * h00 + b * h01, a * h10 + b * h11  # Sigma H_m^T
    sh10, sh11 = b * h00 + d * h01, b * h10 + d * h11
    q00 = h00 * sh00 + h01 * sh10 + r00
    q01 = h00 * sh01 + h01 * sh11
    q11 = h10 * sh01 + h11 * sh11 + r11
    det = q00 * q11 - q01 * q01
    i00, i01, i11 = q11 / det, -q01 / det, q00 / det
    nu0 = r_meas - r
    nu1 = _wrap(phi - (math.atan2(dy, dx) - poses[n, 2]))
    k00, k01 = sh00 * i00 + sh01 * i01, sh00 * i01 + sh01 * i11
    k10, k11 = sh10 * i00 + sh11 * i01, sh10 * i01 + sh11 * i11
    mu[n, j, 0] += k00 * nu0 + k01 * nu1
    mu[n, j, 1] += k10 * nu0 + k11 * nu1
    # Sigma - K H_m Sigma = Sigma - K (Sigma H_m^T)^T
    cov[0, 0] = a - (k00 * sh00 + k01 * sh01)
    cov[1, 1] = d - (k10 * sh10 + k11 * sh11)
    cov[0, 1] = cov[1, 0] = b - 0.5 * ((k00 * sh10 + k01 * sh11) + (k10 * sh00 + k11 * sh01))


@kernel()
def fastslam_known_update(
    version, poses, pose_cov, mu, sigma, seen, log_w, z, slot, noise, gate, log_p0, normals, out_nis
):  # pragma: no cover - compiled
    """A FastSLAM step's measurement update with known ids (slam.fastslam.FastSLAM), all particles: each
    measurement z (O, 2) of landmark slot (O,) with noise diag(noise (O, 2)) weighs every particle (log_w +=
    its log likelihood capped at the ``gate``, or log_p0 for a landmark it has not seen) and, version 2, refines its
    proposal N(pose, pose_cov); then version 2 draws one pose per particle from its proposal (``normals`` (N, 3),
    standard normal) and zeroes pose_cov, and each particle's landmark EKFs are updated (inliers) or started.
    ``out_nis`` (O,): each measurement's NIS under the particles' predictive mixture (NaN when no particle knows
    the landmark)."""
    count, measured = poses.shape[0], z.shape[0]
    new = np.zeros((count, measured), dtype=np.bool_)
    inlier = np.zeros((count, measured), dtype=np.bool_)
    before = np.empty(count)
    nus = np.zeros((count, 2))
    s_stack = np.zeros((count, 3))
    for k in range(measured):
        j = slot[k]
        for n in range(count):
            before[n] = log_w[n]
            if not seen[n, j]:
                new[n, k] = True
                log_w[n] += log_p0
                continue
            nu0, nu1, s00, s01, s11, d2, loglik = _weigh_and_refine(
                version, n, poses, pose_cov, mu, sigma, j, z[k], noise[k, 0], noise[k, 1], gate
            )
            nus[n, 0], nus[n, 1] = nu0, nu1
            s_stack[n, 0], s_stack[n, 1], s_stack[n, 2] = s00, s01, s11
            log_w[n] += loglik
            inlier[n, k] = d2 <= gate
        out_nis[k] = _mixture_nis(before, np.logical_not(new[:, k]), nus, s_stack)
    draw = np.zeros(3)
    for n in range(count):
        if version == 2:
            sym = 0.5 * (pose_cov[n] + pose_cov[n].T)
            _cholesky3_draw(sym, normals[n], draw)
            poses[n, 0] += draw[0]
            poses[n, 1] += draw[1]
            poses[n, 2] = _wrap(poses[n, 2] + draw[2])
            pose_cov[n, :, :] = 0.0
        for k in range(measured):
            if new[n, k] or inlier[n, k]:
                _fuse(poses, mu, sigma, n, slot[k], z[k], noise[k, 0], noise[k, 1], new[n, k])
                seen[n, slot[k]] = True


# ------------------------------------------------------------------------------- localisation smoother


@kernel()
def _localisation_update(x, p, m0, m1, r_meas, phi, r00, r11, huber):  # pragma: no cover - compiled
    """Kalman update of pose x (3,), covariance p (3, 3) with a measurement (r_meas, phi) of the fixed landmark
    (m0, m1), its S inflated by sqrt(d^2 / huber) beyond the Huber bound (as ekf_likelihood_pass)."""
    dx, dy, r, _, h00, h01, h10, h11 = _landmark_jacobian(x, m0, m1)
    x00, x01, x10, x11 = -h00, -h01, -h10, -h11
    ph0 = np.empty(3)
    ph1 = np.empty(3)
    for a in range(3):
        ph0[a] = p[a, 0] * x00 + p[a, 1] * x01
        ph1[a] = p[a, 0] * x10 + p[a, 1] * x11 - p[a, 2]
    s00 = x00 * ph0[0] + x01 * ph0[1] + r00
    s01 = x00 * ph1[0] + x01 * ph1[1]
    s11 = x10 * ph1[0] + x11 * ph1[1] - ph1[2] + r11
    nu0 = r_meas - r
    nu1 = _wrap(phi - (math.atan2(dy, dx) - x[2]))
    det = s00 * s11 - s01 * s01
    d2 = (s11 * nu0 * nu0 - 2.0 * s01 * nu0 * nu1 + s00 * nu1 * nu1) / det
    inflate = math.sqrt(d2 / huber) if d2 > huber else 1.0
    det *= inflate * inflate
    i00, i01, i11 = s11 * inflate / det, -s01 * inflate / det, s00 * inflate / det
    _kalman_step(x, p, ph0, ph1, i00, i01, i11, nu0, nu1)


@kernel()
def smooth_localisation(
    controls,
    control_ptr,
    z,
    slot,
    measurement_ptr,
    initial_pose,
    landmarks,
    alphas,
    floor,
    dt_ref,
    sensor,
    huber,
    out_poses,
    out_cov,
):  # pragma: no cover - compiled
    """The robot's poses (T, 3) given a fixed map ``landmarks`` (n_slots, 2) (NaN rows: unknown, their
    measurements unused): an EKF over the pose alone forward (velocity model per step, as ekf_likelihood_pass;
    measurements with the Huber-inflated update), then the Rauch-Tung-Striebel smoother backward. Written to
    ``out_poses`` (T, 3) and their covariances ``out_cov`` (T, 3, 3)."""
    steps = control_ptr.shape[0] - 1
    filtered = np.zeros((steps, 3))
    filtered_cov = np.zeros((steps, 3, 3))
    predicted = np.zeros((steps, 3))
    predicted_cov = np.zeros((steps, 3, 3))
    jacobian = np.zeros((steps, 3, 3))
    x = initial_pose.copy()
    p = np.zeros((3, 3))
    delta = np.zeros(3)
    cov_local = np.zeros((3, 3))
    q = np.zeros((3, 3))
    for t in range(steps):
        f = np.eye(3)
        if control_ptr[t + 1] > control_ptr[t]:
            velocity_local_motion(
                controls[control_ptr[t] : control_ptr[t + 1]], alphas, floor, dt_ref, delta, cov_local
            )
            c, s = math.cos(x[2]), math.sin(x[2])
            _turn_covariance(cov_local, c, s, q)
            wx, wy = c * delta[0] - s * delta[1], s * delta[0] + c * delta[1]
            f[0, 2], f[1, 2] = -wy, wx
            x[0] += wx
            x[1] += wy
            x[2] = _wrap(x[2] + delta[2])
            p = f @ p @ f.T + q
        jacobian[t] = f
        predicted[t] = x
        predicted_cov[t] = p
        for k in range(measurement_ptr[t], measurement_ptr[t + 1]):
            j = slot[k]
            if np.isnan(landmarks[j, 0]):
                continue
            sd_r = sensor[0] + sensor[1] * z[k, 0]
            _localisation_update(
                x, p, landmarks[j, 0], landmarks[j, 1], z[k, 0], z[k, 1], sd_r * sd_r, sensor[2] ** 2, huber
            )
        p = 0.5 * (p + p.T)
        filtered[t] = x
        filtered_cov[t] = p
    out_poses[steps - 1] = filtered[steps - 1]
    out_cov[steps - 1] = filtered_cov[steps - 1]
    for t in range(steps - 2, -1, -1):
        nxt = predicted_cov[t + 1]
        if abs(np.linalg.det(nxt)) < 1e-300:
            out_poses[t] = filtered[t]
            out_cov[t] = filtered_cov[t]
            continue
        gain = filtered_cov[t] @ jacobian[t + 1].T @ np.linalg.inv(nxt)
        diff = out_poses[t + 1] - predicted[t + 1]
        diff[2] = _wrap(diff[2])
        out_poses[t] = filtered[t] + gain @ diff
        out_poses[t, 2] = _wrap(out_poses[t, 2])
        out_cov[t] = filtered_cov[t] + gain @ (out_cov[t + 1] - nxt) @ gain.T
