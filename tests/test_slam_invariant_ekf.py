"""The right-invariant error of slam.ekf against finite differences, sampled motion and the unobservable motions.

The error of an estimate X^ = (theta^, p^, m^_i) against the truth X is defined here, independently of the
filter's code, to first order: theta^ = theta + xi_theta, p^ = Rot(xi_theta) p + xi_p,
m^_i = Rot(xi_theta) m_i + xi_mi.
"""

from __future__ import annotations

import numpy as np
import pytest

from slam.angles import wrap_angle
from slam.ekf import EKFSLAM
from slam.motion import VelocityMotionModel
from slam.range_bearing import RangeBearingModel, predict_measurement

MODEL = VelocityMotionModel(alphas=(0.02, 0.01, 0.01, 0.05, 0.002, 0.002))
SENSOR = RangeBearingModel(0.05, 0.02)


def _rot(angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])


def _perturbed(state: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """The estimate whose invariant error against ``state`` is ``xi`` (first order)."""
    rot = _rot(xi[2])
    points = np.concatenate([state[None, :2], state[3:].reshape(-1, 2)]) @ rot.T
    points += np.concatenate([xi[None, :2], xi[3:].reshape(-1, 2)])
    return np.concatenate([points[0], [wrap_angle(state[2] + xi[2])], points[1:].ravel()])


def _error(estimate: np.ndarray, state: np.ndarray) -> np.ndarray:
    """xi of ``estimate`` against ``state``, inverting :func:`_perturbed`."""
    angle = float(wrap_angle(estimate[2] - state[2]))
    rotated = np.concatenate([state[None, :2], state[3:].reshape(-1, 2)]) @ _rot(angle).T
    shifts = np.concatenate([estimate[None, :2], estimate[3:].reshape(-1, 2)]) - rotated
    return np.concatenate([shifts[0], [angle], shifts[1:].ravel()])


def _plain_map(state: np.ndarray, about: np.ndarray) -> np.ndarray:
    """d(plain error)/d(xi) for the whole state, xi_theta a rotation about the point ``about`` (the filter's start):
    dp = xi_p + xi_theta J (p - about), dm = xi_m + xi_theta J (m - about)."""
    n = len(state)
    a = np.eye(n)
    points = np.concatenate([state[None, :2], state[3:].reshape(-1, 2)]) - about
    j_points = np.column_stack([-points[:, 1], points[:, 0]])
    a[0:2, 2] = j_points[0]
    a[3:, 2] = j_points[1:].ravel()
    return a


def _filter_with_landmarks(seed: int) -> EKFSLAM:
    """A filter far from the map origin that has seen three landmarks and moved, so Sigma is full rank."""
    rng = np.random.default_rng(seed)
    ekf = EKFSLAM(MODEL, SENSOR, np.array([12.0, -7.0, 0.9]))
    for landmark_id in range(3):
        ekf.update(np.array([rng.uniform(1.0, 4.0), rng.uniform(-1.0, 1.0)]), landmark_id, set())
    for _ in range(20):
        ekf.predict(np.array([0.4, rng.uniform(-0.5, 0.5), 0.1]))
    return ekf


@pytest.mark.parametrize("seed", range(4))
def test_measurement_jacobian_matches_finite_differences(seed):
    # the innovation of an estimate whose invariant error is xi is H xi to first order: no heading column
    rng = np.random.default_rng(seed)
    truth = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-np.pi, np.pi), *rng.uniform(-20, 20, 4)])
    truth[3:5] = truth[:2] + rng.uniform(1, 5, 2)
    xi = rng.normal(size=7) * 1e-5
    ekf = EKFSLAM(MODEL, SENSOR, np.zeros(3))
    ekf.mu = _perturbed(truth, xi)
    ekf.sigma = np.eye(7)  # so that H Sigma is H
    ekf.slot_of, ekf.ids = {0: 0, 1: 1}, [0, 1]
    z_true = predict_measurement(truth[:3], truth[3:5])[0]
    nu, h, _ = ekf._innovation(0, z_true, np.eye(2))
    np.testing.assert_allclose(nu, h @ xi, rtol=1e-3, atol=1e-10)
    np.testing.assert_array_equal(h[:, 2], 0.0)


@pytest.mark.parametrize("control", [(1.0, 0.5, 0.1), (0.5, 0.0, 0.1), (0.2, -1.2, 0.3)])
def test_prediction_leaves_the_invariant_error_unchanged(control):
    # F = I: the true state and the estimate moved by the same command keep the same error
    rng = np.random.default_rng(7)
    truth = np.array([15.0, -4.0, 2.0, 3.0, 8.0])
    xi = rng.normal(size=5) * 1e-3
    ekf = EKFSLAM(MODEL, SENSOR, np.zeros(3))
    ekf.mu = _perturbed(truth, xi)
    ekf.sigma = np.zeros((5, 5))
    ekf.predict(np.array(control))
    moved = truth.copy()
    moved[:3] = MODEL.predict(truth[None, :3], np.array(control))[0]
    np.testing.assert_allclose(_error(ekf.mu, moved), xi, atol=1e-9)


def test_predicted_covariance_matches_sampled_motion():
    # 30 noisy commands from a pose 25 m from the origin: the filter's plain pose covariance against 20 000
    # sampled paths; a landmark's plain covariance is untouched by the motion (the landmark does not move)
    start = np.array([20.0, -15.0, 0.7])
    controls = [np.array([0.6, 0.8 * np.sin(k / 5.0), 0.1]) for k in range(30)]
    ekf = EKFSLAM(MODEL, SENSOR, start)
    ekf.update(np.array([3.0, 0.4]), 0, set())
    landmark_cov = (_plain_map(ekf.mu, start[:2]) @ ekf.sigma @ _plain_map(ekf.mu, start[:2]).T)[3:, 3:]
    rng = np.random.default_rng(11)
    draws = np.repeat(start[None], 20_000, axis=0)
    for control in controls:
        ekf.predict(control)
        draws = MODEL.sample(draws, control, rng)
    residual = draws - ekf.mu[:3]
    residual[:, 2] = wrap_angle(residual[:, 2])
    sample_cov = residual.T @ residual / len(residual)
    plain = _plain_map(ekf.mu, start[:2]) @ ekf.sigma @ _plain_map(ekf.mu, start[:2]).T
    np.testing.assert_allclose(plain[:3, :3], sample_cov, atol=0.05 * np.abs(sample_cov).max())
    np.testing.assert_allclose(ekf.pose_covariance(), plain[:3, :3], atol=1e-12)
    np.testing.assert_allclose(plain[3:, 3:], landmark_cov, atol=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_update_adds_no_information_along_the_unobservable_motions(seed):
    # landmarks tell nothing about a rotation of robot and map about the origin or a common shift: the
    # information an update adds, inv(Sigma+) - inv(Sigma), is zero along those directions of xi
    ekf = _filter_with_landmarks(seed)
    before = np.linalg.inv(ekf.sigma)
    ekf.update(np.array([2.5, 0.3]), 1, set())
    gained = np.linalg.inv(ekf.sigma) - before
    n = len(ekf.mu)
    rotation = np.zeros(n)
    rotation[2] = 1.0
    shift_x, shift_y = np.zeros(n), np.zeros(n)
    shift_x[[0, *range(3, n, 2)]] = 1.0
    shift_y[[1, *range(4, n, 2)]] = 1.0
    assert np.abs(gained).max() > 1.0  # the update did add information
    for direction in (rotation, shift_x, shift_y):
        np.testing.assert_allclose(gained @ direction, 0.0, atol=1e-6 * np.abs(gained).max())


@pytest.mark.parametrize("known", [True, False])
def test_a_run_in_utm_coordinates_is_the_run_at_the_origin_shifted(known):
    """A probe: EKF-SLAM on a simulated run shifted to UTM coordinates (4.5e5, 5.4e6) m failed at step 1011 with a
    covariance no longer positive semi-definite (at 9e6 m at step 1), its covariance 1 % off the origin run's from
    the first steps: the invariant error rotated about the map origin, so sigma held terms of 1e13 whose differences
    were the pose's 1e-4 m^2. About the start, the shifted run is the run at the origin, shifted, to rounding."""
    from dataclasses import replace

    from slam.sequence import run_filter
    from slam.simulator import simulate_office

    log = simulate_office(seed=1, steps=1200).log()
    shift = np.array([4.5e5, 5.4e6, 0.0])
    far = replace(log, initial_pose=log.initial_pose + shift, odometry=log.odometry + shift)
    tracks = []
    for each in (log, far):
        ekf = EKFSLAM(each.velocity_model, each.sensor, each.initial_pose, known_correspondences=known)
        tracks.append(run_filter(ekf, each.sequence()))
    near, shifted = tracks
    np.testing.assert_allclose(shifted.mean[:, :2] - shift[:2], near.mean[:, :2], atol=1e-6)
    np.testing.assert_allclose(wrap_angle(shifted.mean[:, 2] - near.mean[:, 2]), 0.0, atol=1e-7)
    np.testing.assert_allclose(shifted.cov, near.cov, rtol=1e-6, atol=1e-9)
