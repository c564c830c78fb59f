"""Motion and measurement models, Gaussian helpers and resampling (slam.motion, slam.range_bearing,
slam.stats, slam.resampling) against hand-computed values, finite differences and sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.angles import wrap_angle
from slam.motion import (
    OdometryMotionModel,
    OmniOdometryMotionModel,
    VelocityMotionModel,
    compose,
    local_motion,
    odometry_controls,
    rotate_covariance,
    sideways_watch,
    split_odometry_motion,
)
from slam.range_bearing import RangeBearingModel, inverse_measurement, predict_measurement
from slam.resampling import effective_sample_size, low_variance_resample, normalize_log_weights
from slam.stats import inv2, psd_cholesky, sample_gaussian

angles = st.floats(-math.pi, math.pi)
coords = st.floats(-10.0, 10.0)


@given(st.floats(-1e4, 1e4))
def test_wrap_angle_lands_in_half_open_range_and_keeps_the_direction(angle):
    wrapped = float(wrap_angle(angle))
    assert -math.pi <= wrapped < math.pi
    assert math.cos(wrapped) == pytest.approx(math.cos(angle), abs=1e-9)
    assert math.sin(wrapped) == pytest.approx(math.sin(angle), abs=1e-9)


def test_wrap_angle_folds_the_rounded_up_end_to_minus_pi():
    # (-4e-16 + pi) - pi: the remainder of -4e-16 by 2 pi rounds to 2 pi, which gave +pi
    np.testing.assert_array_equal(
        wrap_angle(np.array([-math.pi - 4e-16, math.pi, -math.pi, 3 * math.pi])),
        [-math.pi, -math.pi, -math.pi, -math.pi],
    )


# ------------------------------------------------------------------------------------------- velocity model


def test_velocity_model_straight_line_by_hand():
    pose = np.array([[1.0, 2.0, math.pi / 2]])
    moved = VelocityMotionModel().predict(pose, np.array([1.0, 0.0, 2.0]))
    np.testing.assert_allclose(moved, [[1.0, 4.0, math.pi / 2]], atol=1e-12)


def test_velocity_model_quarter_circle_by_hand():
    # v = 1 m/s, w = pi/2 rad/s for 1 s from the origin: a quarter circle of radius 2/pi
    moved = VelocityMotionModel().predict(np.zeros((1, 3)), np.array([1.0, math.pi / 2, 1.0]))
    radius = 2.0 / math.pi
    np.testing.assert_allclose(moved, [[radius, radius, math.pi / 2]], atol=1e-12)


def test_velocity_model_turn_on_the_spot_by_hand():
    moved = VelocityMotionModel().predict(np.array([[3.0, -1.0, 0.5]]), np.array([0.0, -1.0, 0.25]))
    np.testing.assert_allclose(moved, [[3.0, -1.0, 0.25]], atol=1e-12)


def test_velocity_sample_without_noise_is_the_prediction():
    model = VelocityMotionModel(alphas=(0.0,) * 6)
    poses = np.array([[0.0, 0.0, 0.3], [1.0, -2.0, -2.0]])
    control = np.array([0.7, 0.4, 0.5])
    np.testing.assert_allclose(
        model.sample(poses, control, np.random.default_rng(0)), model.predict(poses, control), atol=1e-12
    )


@settings(max_examples=40, deadline=None)
@given(x=coords, y=coords, theta=angles, v=st.floats(-2, 2), w=st.floats(-3, 3), dt=st.floats(0.01, 1.0))
def test_velocity_jacobian_matches_finite_differences(x, y, theta, v, w, dt):
    model = VelocityMotionModel()
    pose = np.array([[x, y, theta]])
    control = np.array([v, w, dt])
    _, jac_g, _ = model.linearize(pose, control)
    eps = 1e-6
    for k in range(3):
        step = np.zeros((1, 3))
        step[0, k] = eps
        diff = model.predict(pose + step, control) - model.predict(pose - step, control)
        diff[:, 2] = wrap_angle(diff[:, 2])
        np.testing.assert_allclose(diff[0] / (2 * eps), jac_g[0, :, k], atol=1e-6)


@pytest.mark.parametrize("control", [(1.0, 0.5, 0.1), (0.5, 0.0, 0.1), (0.2, -1.2, 0.1)])
def test_velocity_process_noise_matches_samples(control):
    # Q = V M V^T of the linearisation against the sample covariance of 40 000 noisy moves
    model = VelocityMotionModel(alphas=(0.01, 0.005, 0.01, 0.01, 0.002, 0.002))
    pose = np.array([[0.5, -0.3, 0.8]])
    control = np.array(control)
    mean, _, q = model.linearize(pose, control)
    draws = model.sample(np.repeat(pose, 40_000, axis=0), control, np.random.default_rng(1))
    residual = draws - mean
    residual[:, 2] = wrap_angle(residual[:, 2])
    sample_cov = residual.T @ residual / len(residual)
    np.testing.assert_allclose(sample_cov, q[0], atol=0.05 * np.abs(q[0]).max())


def test_velocity_noise_is_rate_independent():
    # ten commands of 0.01 s accumulate the same heading variance as one of 0.1 s (PR's per-step noise would not)
    model = VelocityMotionModel(alphas=(0.0, 0.0, 0.01, 0.01, 0.0, 0.0), dt_ref=0.1)
    _, coarse = local_motion(model, np.array([[1.0, 0.0, 0.1]]))
    _, fine = local_motion(model, np.tile([1.0, 0.0, 0.01], (10, 1)))
    assert coarse[2, 2] == pytest.approx(fine[2, 2], rel=1e-9)


def test_velocity_noise_floor_applies_only_to_moving_commands():
    model = VelocityMotionModel(alphas=(0.0,) * 6, dt_ref=0.1, floor=(0.01, 0.02))
    np.testing.assert_allclose(model.velocity_variances(0.5, 0.0, 0.05), [0.02, 0.04, 0.0])
    np.testing.assert_array_equal(model.velocity_variances(0.0, 0.0, 0.05), 0.0)
    assert model.moves(np.array([0.0, 0.1, 0.1])) and not model.moves(np.array([0.0, 0.0, 0.1]))


# ------------------------------------------------------------------------------------------- odometry model


def test_odometry_controls_by_hand():
    readings = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, math.pi / 2], [1.0, 1.0, 0.0]])
    controls = odometry_controls(readings)
    np.testing.assert_allclose(controls[0], [math.pi / 4, math.sqrt(2), math.pi / 4], atol=1e-12)
    # a turn on the spot: no translation, the whole rotation in delta_rot2
    np.testing.assert_allclose(controls[1], [0.0, 0.0, -math.pi / 2], atol=1e-12)
    # 2 mm backwards, heading pi/2, slightly to the left of straight back: a small turn and a negative translation
    back = odometry_controls(np.array([[1.0, 1.0, math.pi / 2], [1.001, 1.0 - math.sqrt(3) / 1000, math.pi / 2]]))
    np.testing.assert_allclose(back[0], [math.pi / 6, -0.002, -math.pi / 6], atol=1e-9)
    # rotation noise a1 (pi / 6)^2 = 0.0014 rad^2, not a1 (5 pi / 6)^2 = 0.034
    assert OdometryMotionModel().motion_variances(back[0])[0] == pytest.approx(
        0.005 * (math.pi / 6) ** 2 + 0.005 * 4e-6
    )


def test_odometry_model_step_by_hand():
    moved = OdometryMotionModel().predict(
        np.array([[2.0, 0.0, math.pi / 2]]), np.array([math.pi / 4, math.sqrt(2), math.pi / 4])
    )
    np.testing.assert_allclose(moved[0, :2], [1.0, 1.0], atol=1e-12)
    assert abs(wrap_angle(moved[0, 2] - math.pi)) < 1e-12


def test_odometry_variances_by_hand():
    variances = OdometryMotionModel(alphas=(0.1, 0.2, 0.3, 0.4)).motion_variances(np.array([0.5, 2.0, -1.0]))
    np.testing.assert_allclose(variances, [0.1 * 0.25 + 0.2 * 4, 0.3 * 4 + 0.4 * 1.25, 0.1 * 1 + 0.2 * 4])


def test_split_odometry_motion_by_hand():
    pieces = split_odometry_motion(np.array([0.3, 2.0, -0.1]), 4)
    np.testing.assert_allclose(pieces, [[0.3, 0.5, 0.0], [0.0, 0.5, 0.0], [0.0, 0.5, 0.0], [0.0, 0.5, -0.1]])
    np.testing.assert_allclose(split_odometry_motion(np.array([0.3, 2.0, -0.1]), 1), [[0.3, 2.0, -0.1]])
    # a straight motion: translation variance a3 (2/4)^2 per piece, 4 a3 / 4 in all, a quarter of a3 2^2
    variances = OdometryMotionModel(alphas=(0.1, 0.2, 0.3, 0.4)).motion_variances(
        split_odometry_motion(np.array([0.0, 2.0, 0.0]), 4)
    )
    assert variances[:, 1].sum() == pytest.approx(0.3 * 4 / 4)
    with pytest.raises(ValueError):
        split_odometry_motion(np.array([0.0, 1.0, 0.0]), 0)


@settings(max_examples=40, deadline=None)
@given(x=coords, y=coords, theta=angles, rot1=angles, trans=st.floats(-2, 2), rot2=angles, pieces=st.integers(1, 50))
def test_split_odometry_motion_composes_to_the_motion(x, y, theta, rot1, trans, rot2, pieces):
    model = OdometryMotionModel()
    pose = np.array([[x, y, theta]])
    whole = model.predict(pose, np.array([rot1, trans, rot2]))
    for piece in split_odometry_motion(np.array([rot1, trans, rot2]), pieces):
        pose = model.predict(pose, piece)
    np.testing.assert_allclose(pose[0, :2], whole[0, :2], atol=1e-9)
    assert abs(wrap_angle(pose[0, 2] - whole[0, 2])) < 1e-9


@settings(max_examples=40, deadline=None)
@given(
    x=coords,
    y=coords,
    theta=angles,
    rot1=st.floats(-math.pi, math.pi),
    trans=st.one_of(st.just(0.0), st.floats(1e-4, 2), st.floats(-2, -1e-4)),
    rot2=st.floats(-1.5, 1.5),
)
def test_odometry_controls_invert_the_motion(x, y, theta, rot1, trans, rot2):
    # (translations under MIN_TRANSLATION = 1e-6 m count as turns on the spot, so none are drawn; forwards or
    # backwards in any direction)
    start = np.array([[x, y, theta]])
    end = OdometryMotionModel().predict(start, np.array([rot1, trans, rot2]))
    recovered = OdometryMotionModel().predict(start, odometry_controls(np.vstack([start, end]))[0])
    np.testing.assert_allclose(recovered[0, :2], end[0, :2], atol=1e-9)
    assert abs(wrap_angle(recovered[0, 2] - end[0, 2])) < 1e-9


def test_odometry_process_noise_matches_samples():
    model = OdometryMotionModel(alphas=(0.02, 0.01, 0.02, 0.01))
    pose = np.array([[1.0, 2.0, -0.4]])
    control = np.array([0.3, 0.5, -0.2])
    mean, _, q = model.linearize(pose, control)
    draws = model.sample(np.repeat(pose, 40_000, axis=0), control, np.random.default_rng(2))
    residual = draws - mean
    residual[:, 2] = wrap_angle(residual[:, 2])
    np.testing.assert_allclose(residual.T @ residual / len(residual), q[0], atol=0.05 * np.abs(q[0]).max())


def test_omni_odometry_process_noise_matches_samples_and_hand_variances():
    model = OmniOdometryMotionModel(alphas=(0.02, 0.01, 0.03, 0.04))
    pose = np.array([[1.0, 2.0, -0.4]])
    control = np.array([1.2, 0.5, -0.2])  # a travel 1.2 rad off the heading, a turn of 1.0 rad
    # along and across the travel: a3 0.5^2 + a4 1.0^2; the heading: a1 1.0^2 + a2 0.5^2
    np.testing.assert_allclose(model.travel_variances(control), [0.0475, 0.0475, 0.0225])
    mean, _, q = model.linearize(pose, control)
    np.testing.assert_allclose(mean, OdometryMotionModel().predict(pose, control))
    draws = model.sample(np.repeat(pose, 40_000, axis=0), control, np.random.default_rng(2))
    residual = draws - mean
    residual[:, 2] = wrap_angle(residual[:, 2])
    np.testing.assert_allclose(residual.T @ residual / len(residual), q[0], atol=0.05 * np.abs(q[0]).max())


@settings(max_examples=60, deadline=None)
@given(
    x=coords,
    y=coords,
    theta=angles,
    travel=st.floats(0.001, 2.0),
    bearing=angles,
    turn=st.floats(-1.5, 1.5),
    frame=angles,
)
def test_omni_odometry_noise_does_not_depend_on_where_the_robot_frame_points(x, y, theta, travel, bearing, turn, frame):
    """The same motion in the world (a travel of ``travel`` m at world bearing ``bearing``, a turn of ``turn``),
    logged by a robot frame turned ``frame`` rad (a holonomic base, or x not the driving direction): the omni model
    gives the same pose noise in the world, which the differential drive's model (rot1 a turn) does not."""
    start = np.array([x, y, theta])
    end = np.array([x + travel * math.cos(bearing), y + travel * math.sin(bearing), theta + turn])
    shifted = start + [0.0, 0.0, frame], end + [0.0, 0.0, frame]
    model = OmniOdometryMotionModel(alphas=(0.02, 0.01, 0.03, 0.04))
    _, _, q = model.linearize(start[None], odometry_controls(np.stack([start, end]))[0])
    _, _, q_turned = model.linearize(shifted[0][None], odometry_controls(np.stack(shifted))[0])
    np.testing.assert_allclose(q_turned, q, rtol=1e-9, atol=1e-12)


def test_the_differential_drive_model_makes_a_move_sideways_a_turn():
    """What the omni model is for: a 0.5 m move sideways, at alphas 0.05, is given 0.52 rad of heading noise by the
    differential drive's model (rot1 = pi/2 and rot2 = -pi/2, each a turn) and 0.11 by the omni model."""
    control = odometry_controls(np.array([[0.0, 0.0, 0.0], [0.0, 0.5, 0.0]]))[0]
    pose = np.zeros((1, 3))
    heading_sd = {
        name: math.sqrt(model.linearize(pose, control)[2][0, 2, 2])
        for name, model in (
            ("diff", OdometryMotionModel((0.05,) * 4)),
            ("omni", OmniOdometryMotionModel((0.05,) * 4)),
        )
    }
    assert heading_sd["diff"] == pytest.approx(math.sqrt(2 * (0.05 * (math.pi / 2) ** 2 + 0.05 * 0.25)))
    assert heading_sd["omni"] == pytest.approx(math.sqrt(0.05 * 0.25))


def test_sideways_share_by_hand():
    # heading 0 throughout: 1 m forwards, 1 m to the left, 2 m backwards, then 3 m forwards at 30 deg off the heading
    odometry = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 1, 0], [-1 + 1.5 * math.sqrt(3), 2.5, 0]], float)
    assert sideways_watch(odometry).share() == pytest.approx(1 / 7) and sideways_watch(odometry).verdict() is False
    turned = odometry + [0.0, 0.0, math.pi / 2]  # the same travel logged by a frame turned 90 deg
    assert sideways_watch(turned).share() == pytest.approx(6 / 7) and sideways_watch(turned).verdict() is True
    assert sideways_watch(np.zeros((3, 3))).share() == 0.0 and sideways_watch(np.zeros((3, 3))).verdict() is None


def test_a_reset_or_a_robot_standing_still_is_no_sideways_travel():
    """A re-probe: one odometry reset 60 m sideways in a log driven forwards made auto pick the omni model (56 %), and
    a robot standing still with 2 mm of odometry jitter did in 15 of 40 seeds. A jump past SIDEWAYS_RESET is no
    travel, and jitter does not add up to a stretch of travel."""
    forwards = np.column_stack([np.linspace(0.0, 3.0, 301), np.zeros(301), np.zeros(301)])
    jumped = forwards.copy()
    jumped[150:, 1] += 60.0
    assert sideways_watch(jumped).share() == 0.0 and sideways_watch(jumped).verdict() is False
    for seed in range(40):
        still = np.random.default_rng(seed).normal(0.0, 0.002, (3000, 3)) * [1.0, 1.0, 0.0]  # 5 min at 10 Hz
        assert sideways_watch(np.vstack([still, forwards + still[-1]])).verdict() is False, seed


# ------------------------------------------------------------------------------------------- composition


@settings(max_examples=30, deadline=None)
@given(x=coords, y=coords, theta=angles, seed=st.integers(0, 1000))
def test_local_motion_equals_sequential_linearisation(x, y, theta, seed):
    # one linearisation in the robot frame, rotated to the heading, equals propagating from the actual pose
    model = VelocityMotionModel()
    rng = np.random.default_rng(seed)
    controls = np.column_stack([rng.uniform(-1, 1, 6), rng.uniform(-1, 1, 6), rng.uniform(0.01, 0.2, 6)])
    pose = np.array([[x, y, theta]])
    cov = np.zeros((3, 3))
    for control in controls:
        pose, jac_g, q = model.linearize(pose, control)
        cov = jac_g[0] @ cov @ jac_g[0].T + q[0]
    delta, local_cov = local_motion(model, controls)
    composed = compose(np.array([[x, y, theta]]), delta)
    np.testing.assert_allclose(composed[0, :2], pose[0, :2], atol=1e-9)
    assert abs(wrap_angle(composed[0, 2] - pose[0, 2])) < 1e-9
    np.testing.assert_allclose(rotate_covariance(local_cov, np.array([theta]))[0], cov, atol=1e-12)


# ------------------------------------------------------------------------------------------- range-bearing


def test_range_bearing_by_hand():
    z, h_x, h_m = predict_measurement(np.array([1.0, 1.0, math.pi / 2]), np.array([4.0, 5.0]))
    np.testing.assert_allclose(z, [5.0, math.atan2(4, 3) - math.pi / 2])
    np.testing.assert_allclose(h_m, [[0.6, 0.8], [-4 / 25, 3 / 25]])
    np.testing.assert_allclose(h_x, [[-0.6, -0.8, 0.0], [4 / 25, -3 / 25, -1.0]])


@settings(max_examples=40, deadline=None)
@given(x=coords, y=coords, theta=angles, r=st.floats(0.2, 10), phi=st.floats(-3.0, 3.0))
def test_inverse_measurement_round_trip_and_jacobian(x, y, theta, r, phi):
    pose = np.array([x, y, theta])
    z = np.array([r, phi])
    landmark, j_z, j_x = inverse_measurement(pose, z)
    back, h_x, h_m = predict_measurement(pose, landmark)
    assert back[0] == pytest.approx(r, abs=1e-9)
    assert abs(wrap_angle(back[1] - phi)) < 1e-9
    # the inverse's Jacobian in z is the inverse of the measurement's Jacobian in the landmark
    np.testing.assert_allclose(j_z @ h_m, np.eye(2), atol=1e-7)
    # and dm/dx = -H_m^-1 H_x (the landmark moves with the pose at fixed z)
    np.testing.assert_allclose(j_x, -np.linalg.solve(h_m, h_x), atol=1e-7)


def test_range_noise_grows_with_range():
    model = RangeBearingModel(sigma_range=0.1, sigma_bearing=0.02, range_fraction=0.05)
    np.testing.assert_allclose(model.covariance(np.array([4.0, 0.3])), np.diag([0.3**2, 0.02**2]))


# ------------------------------------------------------------------------------------------- helpers


def test_psd_cholesky_handles_zero_and_singular_covariances():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(50, 3, 2))
    singular = a @ a.transpose(0, 2, 1)  # rank 2
    full = singular + np.eye(3)
    stack = np.concatenate([singular, full, np.zeros((1, 3, 3))])
    root = psd_cholesky(stack)
    np.testing.assert_allclose(root @ root.transpose(0, 2, 1), stack, atol=1e-10)
    np.testing.assert_array_equal(root[-1], 0.0)
    assert np.all(np.triu(root, 1) == 0)


def test_sample_gaussian_moments():
    cov = np.array([[0.5, 0.2, 0.0], [0.2, 0.3, 0.1], [0.0, 0.1, 0.2]])
    draws = sample_gaussian(
        np.tile([1.0, -2.0, 0.5], (50_000, 1)), np.tile(cov, (50_000, 1, 1)), np.random.default_rng(5)
    )
    # bounds of 5 standard errors: sqrt(0.5 / 50 000) = 0.0032 for the mean, about 0.003 for the covariances
    np.testing.assert_allclose(draws.mean(axis=0), [1.0, -2.0, 0.5], atol=0.016)
    np.testing.assert_allclose(np.cov(draws.T), cov, atol=0.015)


def test_inv2_by_hand():
    inverse, det = inv2(np.array([[[2.0, 1.0], [1.0, 3.0]]]))
    np.testing.assert_allclose(det, [5.0])
    np.testing.assert_allclose(inverse[0], np.array([[3.0, -1.0], [-1.0, 2.0]]) / 5.0)


def test_low_variance_resampling_copies_floor_or_ceil_of_n_w():
    weights = np.array([0.5, 0.25, 0.125, 0.125, 0.0])
    for seed in range(20):
        counts = np.bincount(low_variance_resample(weights, np.random.default_rng(seed)), minlength=5)
        expected = 5 * weights
        assert np.all(counts >= np.floor(expected)) and np.all(counts <= np.ceil(expected))
        assert counts[4] == 0


def test_effective_sample_size_and_normalisation():
    assert effective_sample_size(np.full(8, 1 / 8)) == pytest.approx(8.0)
    assert effective_sample_size(np.array([1.0, 0, 0])) == pytest.approx(1.0)
    weights = normalize_log_weights(np.array([-1000.0, -1000.0 + math.log(3)]))
    np.testing.assert_allclose(weights, [0.25, 0.75])
