"""The split test: the noise spill against simulation, the minimum X^2 against brute force and scipy."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2, chisquare

from mapping.adaptive.splitting import HIT, MISS, UNKNOWN, SplitTest, min_chi_square, outside_fraction, spill
from mapping.errors import InputError


def test_outside_fraction_matches_simulation():
    rng = np.random.default_rng(0)
    sigma = 0.03
    for chord in (0.01, 0.05, 0.2, 1.0):
        x = rng.uniform(0, chord, 400_000)
        measured = x + rng.normal(0, sigma, x.size)
        simulated = np.mean((measured < 0) | (measured > chord))
        assert outside_fraction(chord, sigma) == pytest.approx(simulated, abs=3e-3)
    assert outside_fraction(0.0, sigma) == 1.0


def test_spill_matches_simulation_over_random_lines():
    """Lines with uniform direction and uniform offset (the invariant measure), a return uniform along the
    chord inside the cell, Gaussian range noise: the share measured beyond one side, one way."""
    rng = np.random.default_rng(1)
    d, sigma, n = 0.4, 0.03, 600_000
    theta = rng.uniform(0, math.pi, n)
    normal = np.stack([-np.sin(theta), np.cos(theta)], axis=1)
    along = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    p = rng.uniform(-d, d, n)  # offsets from the cell centre; lines that miss the cell are dropped
    point = p[:, None] * normal + d / 2
    # slab intersection with [0, d]^2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (0 - point) / along
        t2 = (d - point) / along
    t_lo = np.nanmax(np.minimum(t1, t2), axis=1)
    t_hi = np.nanmin(np.maximum(t1, t2), axis=1)
    chord = t_hi - t_lo
    crossing = chord > 0
    chord = chord[crossing]
    x = rng.uniform(0, chord)
    measured = x + rng.normal(0, sigma, chord.size)
    simulated = np.mean(measured > chord)  # carried beyond the exit side
    assert spill(d, sigma) == pytest.approx(simulated, rel=0.03)
    # a larger cell loses a smaller share; the share grows with the noise
    assert spill(0.8, sigma) < spill(0.4, sigma) < spill(0.4, 2 * sigma)


def test_min_chi_square_of_a_point_family_is_pearsons():
    # two outcomes, the second bounded by 0.1 and observed above it: the closest p is (0.9, 0.1)
    counts = np.array([[30.0, 10.0]])
    got = min_chi_square(counts, 0, np.array([np.inf, 0.1]))
    assert got[0] == pytest.approx(chisquare([30, 10], [36, 4]).statistic)
    # inside the family: no evidence against it
    assert min_chi_square(np.array([[38.0, 2.0]]), 0, np.array([np.inf, 0.1]))[0] == 0.0
    assert min_chi_square(np.zeros((1, 3)), 1, np.array([0.1, np.inf, 0.1]))[0] == 0.0


@settings(max_examples=60, deadline=None)
@given(
    counts=st.lists(st.floats(0, 50), min_size=3, max_size=3).filter(lambda c: sum(c) > 0.5),
    bounds=st.lists(st.floats(0.005, 0.4), min_size=2, max_size=2),
    dominant=st.integers(0, 2),
)
def test_min_chi_square_matches_brute_force(counts, bounds, dominant):
    counts = np.array(counts)
    b = np.insert(np.array(bounds), dominant, np.inf)
    got = min_chi_square(counts[None, :], dominant, b)[0]
    n = counts.sum()
    others = [i for i in range(3) if i != dominant]
    # the optimum often sits on a bound or at the observed shares
    grid = np.union1d(np.linspace(1e-6, 1, 1201), np.clip(np.concatenate([b[others], counts[others] / n]), 1e-6, 1))
    best = np.inf
    for p1 in grid[grid <= b[others[0]]]:
        p2 = grid[(grid <= b[others[1]]) & (grid < 1 - p1)]
        p = np.zeros((p2.size, 3))
        p[:, others[0]], p[:, others[1]] = p1, p2
        p[:, dominant] = 1 - p1 - p2
        best = min(best, float(np.min(np.sum((counts - n * p) ** 2 / (n * p), axis=1))))
    assert got <= best + 1e-9 * (1 + best)
    assert got == pytest.approx(best, rel=2e-2, abs=2e-2)


def test_a_tiny_significance_keeps_a_finite_threshold():
    """A probe: --significance 1e-17 gave an infinite threshold (chi2.ppf(1 - 1e-17): 1 - 1e-17 is 1.0 in floating
    point), and no cell split (77 active cells against 902). The chi-square distribution with 2 degrees of freedom has
    the upper tail exp(-x / 2), so its 1e-17 quantile is -2 ln(1e-17) = 78.28 (hand-computed)."""
    test = SplitTest(resolution=0.05, sigma=0.03, significance=1e-17, unknowns=True, floor=0.01)
    assert test.threshold == pytest.approx(-2.0 * math.log(1e-17), rel=1e-12)


def test_families_and_degrees_of_freedom():
    with_unknowns = SplitTest(resolution=0.05, sigma=0.03, significance=0.05, unknowns=True, floor=0.01)
    without = SplitTest(resolution=0.05, sigma=0.03, significance=0.05, unknowns=False, floor=0.01)
    assert with_unknowns.threshold == pytest.approx(chi2.ppf(0.95, 2))
    assert without.threshold == pytest.approx(chi2.ppf(0.95, 1))
    e4 = spill(0.8, 0.03) + 0.01
    families = with_unknowns.families(np.array([4]))
    assert [dominant for dominant, _ in families] == [MISS, HIT, UNKNOWN]
    np.testing.assert_allclose(families[0][1][0], [e4, np.inf, 0.01])
    np.testing.assert_allclose(families[1][1][0], [np.inf, e4, e4])
    np.testing.assert_allclose(families[2][1][0], [e4, 0.01, np.inf])
    level = np.full(4, 4)
    # homogeneous counts pass; half free, half hidden (the paper's Fig. 3) fails only with unknowns
    counts = np.array([[0.0, 40.0, 0.0], [40.0, 0.0, 0.0], [0.0, 0.0, 40.0], [0.0, 20.0, 20.0]])
    assert with_unknowns.reject(level, counts).tolist() == [False, False, False, True]
    assert without.reject(level, counts).tolist() == [False, False, False, False]
    # half hits, half misses fails both
    assert with_unknowns.reject(level[:1], np.array([[20.0, 20.0, 0.0]]))[0]
    assert without.reject(level[:1], np.array([[20.0, 20.0, 0.0]]))[0]
    with pytest.raises(InputError):
        SplitTest(resolution=0.05, sigma=0.03, significance=1.5)
    assert UNKNOWN == 2


@pytest.mark.parametrize(
    "kwargs", [dict(sigma=0.0), dict(sigma=-0.03), dict(floor=0.0), dict(floor=0.25), dict(resolution=0.0)]
)
def test_split_test_parameters_are_checked(kwargs):
    with pytest.raises(InputError):
        SplitTest(**{"resolution": 0.05, "sigma": 0.03, **kwargs})
