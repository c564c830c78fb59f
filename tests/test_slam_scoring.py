"""Trajectory scoring (slam.scoring) against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam.scoring import CHI2_3_95, fit_gaussian, interpolate_poses, score_trajectory


def test_score_by_hand():
    truth = np.zeros((4, 3))
    mean = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0]])
    cov = np.tile(np.eye(3), (4, 1, 1))
    score = score_trajectory(mean, cov, truth)
    assert score.ate_rmse_m == pytest.approx(math.sqrt(25 / 4))
    assert score.heading_mae_rad == pytest.approx(0.25)
    # NEES with identity covariance is |error|^2: 25, 0.25, 0.25, 0 (plus the 1e-6 truth-accuracy floor)
    assert score.nees_mean == pytest.approx((25 + 0.25 + 0.25) / 4, rel=1e-5)
    assert score.inside95 == pytest.approx(0.75)
    assert score.steps == 4


def test_heading_error_wraps():
    score = score_trajectory(
        np.array([[0.0, 0.0, math.pi - 0.1]]), np.tile(np.eye(3), (1, 1, 1)), np.array([[0.0, 0.0, -math.pi + 0.1]])
    )
    assert score.heading_mae_rad == pytest.approx(0.2)


def test_inside95_of_a_calibrated_gaussian_is_95_percent():
    rng = np.random.default_rng(0)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.005], [0.0, 0.005, 0.01]])
    errors = rng.multivariate_normal(np.zeros(3), cov, size=20_000)
    score = score_trajectory(errors, np.tile(cov, (20_000, 1, 1)), np.zeros((20_000, 3)))
    assert score.inside95 == pytest.approx(0.95, abs=0.006)
    assert score.nees_mean == pytest.approx(3.0, abs=0.06)
    overconfident = score_trajectory(errors, np.tile(cov / 9, (20_000, 1, 1)), np.zeros((20_000, 3)))
    assert overconfident.inside95 < 0.35


def test_fit_gaussian_by_hand_and_across_pi():
    samples = np.array([[[1.0, 0.0, math.pi - 0.1], [-1.0, 2.0, -math.pi + 0.1]]])
    mean, cov = fit_gaussian(samples, np.array([[0.5, 0.5]]))
    np.testing.assert_allclose(mean[0, :2], [0.0, 1.0])
    assert abs(abs(mean[0, 2]) - math.pi) < 1e-9  # the circular mean, not 0
    np.testing.assert_allclose(cov[0], [[1.0, -1.0, -0.1], [-1.0, 1.0, 0.1], [-0.1, 0.1, 0.01]], atol=1e-12)
    weighted, _ = fit_gaussian(samples, np.array([[0.75, 0.25]]))
    np.testing.assert_allclose(weighted[0, :2], [0.5, 0.5])


def test_interpolate_poses_turns_the_short_way():
    stamps = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, math.pi - 0.1], [2.0, -2.0, -math.pi + 0.1]])
    got = interpolate_poses(np.array([-1.0, 0.5, 3.0]), stamps, poses)
    np.testing.assert_allclose(got[1, :2], [1.0, -1.0])
    assert abs(abs(got[1, 2]) - math.pi) < 1e-12
    np.testing.assert_allclose(got[0], poses[0])  # clamped before the start
    np.testing.assert_allclose(got[2, :2], poses[1, :2])


def test_chi2_quantile():
    from scipy.stats import chi2

    assert pytest.approx(chi2.ppf(0.95, 3), abs=1e-4) == CHI2_3_95


def test_fit_gaussian_normalises_the_weights():
    """Weights 1 and 3 are weights 0.25 and 0.75: mean x = 0.25 * 1 + 0.75 * (-1) = -0.5, var x = 0.75."""
    samples = np.array([[[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]])
    mean, cov = fit_gaussian(samples, np.array([[1.0, 3.0]]))
    np.testing.assert_allclose(mean[0], [-0.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(cov[0, 0, 0], 0.25 * 1.5**2 + 0.75 * 0.5**2)


def test_interpolated_yaw_is_wrapped_into_minus_pi_pi():
    """Unwrapped, the yaw after pi - 0.1 that reads -pi + 0.1 is pi + 0.1; the result is wrapped back."""
    poses = np.array([[0.0, 0.0, math.pi - 0.1], [2.0, -2.0, -math.pi + 0.1]])
    got = interpolate_poses(np.array([0.75, 3.0]), np.array([0.0, 1.0]), poses)
    np.testing.assert_allclose(got[:, 2], [-math.pi + 0.05, -math.pi + 0.1], atol=1e-12)
