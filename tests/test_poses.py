"""Pose samples for one scan: Gaussian draws, the sample-count rule, ml selection."""

import math

import numpy as np
import pytest

from mapping.errors import InputError
from mapping.poses import DEFAULT_MAX_SAMPLES, Z95, gaussian_samples, samples_for_accuracy, scan_samples


def test_gaussian_samples_have_the_requested_moments():
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.01]])
    mean = np.array([1.0, -2.0, 0.5])
    draws = gaussian_samples(mean, cov, 200_000, np.random.default_rng(0))
    np.testing.assert_allclose(draws.mean(axis=0), mean, atol=3e-3)
    np.testing.assert_allclose(np.cov(draws.T), cov, atol=2e-3)


def test_semidefinite_covariance_is_sampled():
    cov = np.diag([0.01, 0.0, 0.0])  # Cholesky fails; the eigen factor still samples it
    draws = gaussian_samples(np.zeros(3), cov, 1000, np.random.default_rng(1))
    assert np.all(draws[:, 1:] == 0.0) and draws[:, 0].std() == pytest.approx(0.1, rel=0.1)


def test_gaussian_scan_samples_are_seeded_by_seed_and_seq():
    mean, cov = np.zeros(3), np.eye(3) * 0.01
    a = scan_samples("mc", mean=mean, cov=cov, n_samples=10, seed=4, seq=9)
    b = scan_samples("mc", mean=mean, cov=cov, n_samples=10, seed=4, seq=9)
    c = scan_samples("mc", mean=mean, cov=cov, n_samples=10, seed=4, seq=10)
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.array_equal(a[0], c[0])
    np.testing.assert_allclose(a[1], 0.1)


def test_sample_count_rule_by_hand():
    # v = max eigenvalue of the xy block (0.09) + (R sigma_yaw)^2 = 0.09 + (10 * 0.01)^2 = 0.1
    cov = np.diag([0.04, 0.09, 1e-4])
    expected = math.ceil(Z95**2 * 0.1 / 0.1**2)  # 39
    assert samples_for_accuracy(cov, range_max=10.0, accuracy=0.1) == expected
    assert samples_for_accuracy(np.zeros((3, 3)), 10.0, 0.05) == 1
    assert samples_for_accuracy(np.eye(3), 10.0, 0.01, max_samples=50) == 50


def test_ml_picks_the_most_likely_particle_or_the_mean():
    samples = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]])
    s, w = scan_samples("ml", samples=samples, weights=np.array([0.2, 0.5, 0.3]))
    np.testing.assert_array_equal(s, samples[1:2])
    assert w.tolist() == [1.0]
    s, w = scan_samples("ml", mean=np.array([3.0, 4, 5]), cov=np.eye(3))
    np.testing.assert_array_equal(s, [[3.0, 4, 5]])


def test_mode_is_checked():
    with pytest.raises(InputError, match="mode"):
        scan_samples("best", samples=np.zeros((1, 3)), weights=np.ones(1))


def test_sample_count_rule_holds_at_the_ends_of_the_float_range():
    """A huge accuracy needs one sample; a spread past what floats hold needs the most (no OverflowError)."""
    assert samples_for_accuracy(np.eye(3), 12.0, 1e300) == 1
    assert samples_for_accuracy(np.eye(3) * 1e300, 1e200, 0.05) == DEFAULT_MAX_SAMPLES


def test_sample_count_rule_takes_the_xy_block_only():
    """v = lambda_max of the xy block (0.01) + (R sigma_yaw)^2 = 0.01 + 1 * 0.04 = 0.05; the yaw variance (0.04)
    exceeds the xy ones, so an eigenvalue over the whole 3x3 covariance (0.04) would give v = 0.08."""
    cov = np.diag([0.01, 0.01, 0.04])
    assert samples_for_accuracy(cov, range_max=1.0, accuracy=0.1) == math.ceil(Z95**2 * 0.05 / 0.1**2)  # 20


@pytest.mark.parametrize("accuracy", [0.0, -0.1, float("nan")])
def test_accuracy_must_be_positive(accuracy):
    with pytest.raises(InputError, match="accuracy must be > 0"):
        samples_for_accuracy(np.eye(3), 10.0, accuracy)


def test_ml_takes_the_first_of_equal_weights():
    samples = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    s, w = scan_samples("ml", samples=samples, weights=np.array([0.4, 0.2, 0.4]))
    np.testing.assert_array_equal(s, samples[0:1])
    assert w.tolist() == [1.0]


def test_mc_particles_are_merged_with_summed_weights():
    samples = np.array([[1.0, 2.0, 0.1], [0.0, 0.0, 0.0], [1.0, 2.0, 0.1]])
    s, w = scan_samples("mc", samples=samples, weights=np.array([0.25, 0.25, 0.5]))
    np.testing.assert_array_equal(s, samples[:2])
    np.testing.assert_allclose(w, [0.75, 0.25])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(mean=np.zeros(3)), "needs both mean and cov"),
        (dict(samples=np.zeros((1, 3))), "needs samples and weights"),
        (dict(weights=np.ones(1)), "needs samples and weights"),
    ],
)
@pytest.mark.parametrize("mode", ["mc", "ml"])
def test_incomplete_pose_inputs_are_refused(kwargs, message, mode):
    with pytest.raises(InputError, match=message):
        scan_samples(mode, **kwargs)


def test_mc_refuses_zero_gaussian_samples():
    # (ml takes the mean whatever n_samples says)
    with pytest.raises(InputError, match="n_samples must be >= 1"):
        scan_samples("mc", mean=np.zeros(3), cov=np.eye(3), n_samples=0)
