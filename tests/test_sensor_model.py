"""The inverse sensor model against a numerical convolution and the OctoMap increments."""

import math
import re
import warnings

import numpy as np
import pytest
from scipy.special import logit as sp_logit

from mapping.beam_model import TABLE_DU, TABLE_U0, logodds_table
from mapping.errors import InputError
from mapping.sensor_model import SensorModel, erf


def ideal(s: np.ndarray, z: float, l: float) -> np.ndarray:
    """The ideal model: 0 before the peak, 1 over [z - l/2, z + l/2), 1/2 beyond."""
    return np.where(s < z - l / 2, 0.0, np.where(s < z + l / 2, 1.0, 0.5))


@pytest.mark.parametrize("sigma0, z", [(0.03, 2.0), (0.3, 2.0), (0.01, 5.0), (0.1, 0.7)])
def test_closed_form_matches_numerical_convolution(sigma0, z):
    model = SensorModel(sigma0=sigma0)
    step = sigma0 / 400
    s = np.arange(-12 * sigma0, 12 * sigma0 + step / 2, step)
    kernel = np.exp(-0.5 * (s / sigma0) ** 2)
    kernel /= kernel.sum()
    r = np.arange(z - 1.5, z + 1.5, step)
    padded = np.concatenate([np.zeros(len(s) // 2), ideal(r, z, model.l), np.full(len(s) // 2, 0.5)])
    numeric = np.convolve(padded, kernel[::-1], mode="valid")[: len(r)]
    # the zero/0.5 padding is exact because the ideal model is constant beyond the plotted range
    closed = model.probability(r, z)
    assert np.max(np.abs(numeric - closed)) < 2e-3


def test_printed_equation_4_is_wrong_and_ours_is_not():
    """At r = z the paper's eq. (4) gives 0 (A = erf(-z/..) = -1, B = erf(-z + l/2) ~ -1); ours is high."""
    model = SensorModel(sigma0=0.3, peak_width=0.5)
    z, l, s = 2.0, model.l, math.sqrt(2) * 0.3
    a_term, b_term = math.erf(-z / s), math.erf((z - 2 * z + l / 2) / s)
    printed = -0.5 * a_term + 0.5 * b_term
    assert printed == pytest.approx(0.0, abs=0.02)
    assert model.probability(z, z) > 0.5


def test_octomap_increments_and_zero_at_half():
    model = SensorModel()
    assert model.l_free == pytest.approx(sp_logit(0.4))
    assert model.l_hit == pytest.approx(sp_logit(0.7))
    assert model.l_min == pytest.approx(sp_logit(0.12))
    assert model.l_max == pytest.approx(sp_logit(0.97))
    z = 4.0
    # far in free space: the miss increment; at the model's peak: the hit increment
    assert float(model.logodds(1.0, z)) == pytest.approx(sp_logit(0.4), abs=1e-9)
    assert float(model.logodds(model.peak_range(z), z)) == pytest.approx(sp_logit(0.7), abs=1e-12)
    # p = 1/2 maps to exactly 0 log-odds
    assert float(model.squashed(0.5, model.peak(z))) == 0.5
    # far beyond the return the model tends to unknown
    assert abs(float(model.logodds(z + 1.0, z))) < 1e-9


def test_peak_range_is_the_maximum():
    model = SensorModel(sigma0=0.05)
    z = 3.0
    r = np.linspace(z - 0.3, z + 0.3, 200001)
    g = model.probability(r, z)
    assert r[np.argmax(g)] == pytest.approx(float(model.peak_range(z)), abs=1e-5)


@pytest.mark.parametrize(
    "kind, kwargs, z, expected",
    [
        ("constant", {"sigma0": 0.02}, 7.0, 0.02),
        ("linear", {"sigma0": 0.01, "sigma_slope": 0.01}, 4.0, 0.05),
        ("stereo", {"baseline_focal": 100.0}, 5.0, 0.25),
    ],
)
def test_sigma_models(kind, kwargs, z, expected):
    assert float(SensorModel(sigma=kind, **kwargs).sigma_at(z)) == pytest.approx(expected)


def test_constant_sigma_table_matches_the_closed_form():
    model = SensorModel(sigma0=0.02)
    table = logodds_table(model)
    u = TABLE_U0 + TABLE_DU * np.arange(len(table))
    z = 3.3
    # interpolate halfway between table nodes: the worst case for linear interpolation; the squashing
    # has a kink at g = 1/2 where the error peaks, elsewhere it is far smaller
    mid = 0.5 * (table[:-1] + table[1:])
    exact = model.logodds(z + (u[:-1] + TABLE_DU / 2) * model.sigma0, z)
    assert np.max(np.abs(mid - exact)) < 2e-4
    assert np.median(np.abs(mid - exact)) < 1e-6


@pytest.mark.parametrize(
    "kwargs",
    [
        {"resolution": 0.0},
        {"sigma": "cubic"},
        {"sigma0": -1.0},
        {"sigma": "stereo"},
        {"p_hit": 0.4},
        {"p_min": 0.5},
        {"peak_width": 0.0},
    ],
)
def test_bad_parameters_are_rejected(kwargs):
    with pytest.raises(InputError):
        SensorModel(**kwargs)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"sigma": "linear", "sigma_slope": -0.01},  # a noise that shrinks with range
        {"p_hit": 0.8, "p_max": 0.75},  # the clamp below the hit increment
    ],
)
def test_more_bad_parameters_are_rejected(kwargs):
    with pytest.raises(InputError):
        SensorModel(**kwargs)


@pytest.mark.parametrize(
    "kwargs, phrase",
    [  # past these the model's squares and erf arguments overflowed: warnings, and a map of NaN or nothing
        ({"sigma0": 1e308}, "sigma0 must be > 0 m and at most 10000 m"),
        ({"peak_width": 1e308}, "peak_width must be > 0 m and at most 10000 m"),
        ({"sigma": "linear", "sigma_slope": 1e300}, "sigma_slope must be 0 to 10"),
        ({"sigma": "stereo", "baseline_focal": 1e-300}, "needs baseline_focal (b*f) >= 0.001 m px"),
    ],
)
def test_parameters_beyond_any_sensor_are_rejected(kwargs, phrase):
    with pytest.raises(InputError, match=re.escape(phrase)):
        SensorModel(**kwargs)


def test_the_largest_accepted_parameters_stay_finite():
    """At the bounds the model is still a probability, with no overflow on the way (warnings are errors here)."""
    z = np.array([0.5, 30.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for model in (
            SensorModel(sigma0=1e4, peak_width=1e4),
            SensorModel(sigma="linear", sigma_slope=10.0),
            SensorModel(sigma="stereo", baseline_focal=1e-3),
        ):
            g = model.probability(model.peak_range(z), z)
            assert np.all(np.isfinite(g)) and np.all((g >= 0) & (g <= 1))


def test_default_peak_width_is_the_cell_diagonal():
    assert SensorModel(resolution=0.1).l == pytest.approx(0.1 * math.sqrt(2))
    assert SensorModel(resolution=0.1, peak_width=0.3).l == 0.3


def test_stereo_sigma_is_floored_at_a_micrometre():
    # z = 0 would give sigma 0 and a 0/0 model; the floor keeps it finite
    model = SensorModel(sigma="stereo", baseline_focal=100.0)
    assert float(model.sigma_at(0.0)) == 1e-6
    assert float(model.sigma_at(0.001)) == 1e-6  # 1e-6 / 100 = 1e-8, below the floor


def test_squashing_is_capped_at_the_hit_probability():
    # g above the beam's peak (only numerically possible) still gives p_hit, never more
    assert float(SensorModel().squashed(0.9, 0.8)) == pytest.approx(0.7)


def test_a_peak_within_peak_eps_of_one_half_gives_no_occupied_evidence():
    # g_peak - 1/2 = 5e-10 <= PEAK_EPS: the beam's noise swamps its peak, so p is exactly 1/2 at g >= 1/2
    assert float(SensorModel().squashed(0.5 + 4e-10, 0.5 + 5e-10)) == 0.5


def test_erf_is_maths_erf_element_by_element_in_any_shape():
    """The compiled erf the model uses equals math.erf at every element of a 0-d, a 1-d and a strided 2-d array."""
    values = np.random.default_rng(3).normal(0.0, 2.0, size=(7, 9))
    for x in (np.asarray(0.3), values[0], values[:, ::2], np.array([0.0, -np.inf, np.inf, 1e-300, -8.0])):
        out = erf(x)
        assert out.shape == x.shape
        np.testing.assert_array_equal(out, np.vectorize(math.erf)(x))
