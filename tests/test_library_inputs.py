"""A library user's mistakes at the mapping and file API: each is refused with a message naming what was wrong,
where the code before gave a silently wrong result, a file its own loader refuses, or an error from deep inside.

Found by a probe calling the public functions as a notebook would (transposed samples, a covariance that is not
one, NaN beam angles, a map built in code with a NaN resolution)."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.errors import InputError
from mapping.evaluation import score_map
from mapping.export import crop_to_occupied, render_pgm, render_rgb
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.poses import gaussian_samples, scan_samples
from mapping.sensor_model import SensorModel
from schemas.errors import FormatError
from schemas.files import (
    MapFile,
    PosedScans,
    PoseSet,
    TruthRaster,
    load_map,
    load_posed_scans,
    save_map,
    save_posed_scans,
    save_truth,
)

SAMPLES = np.array([[1.0, 2.0, 0.3], [1.1, 2.1, 0.31], [0.9, 1.9, 0.29], [1.05, 2.0, 0.3]])
COV = np.diag([0.01, 0.04, 0.001])


# ------------------------------------------------------------------------------------------------ pose samples


def test_transposed_samples_are_refused_not_reshaped_into_other_poses():
    weights = np.full(4, 0.25)
    samples, _ = scan_samples("mc", samples=SAMPLES, weights=weights)
    assert samples.shape == (4, 3)  # (the right shape passes)
    with pytest.raises(InputError, match=r"samples \(M, 3\).*\(3, 4\)"):
        scan_samples("mc", samples=SAMPLES.T, weights=weights)
    with pytest.raises(InputError, match="finite"):
        scan_samples("ml", samples=SAMPLES, weights=np.array([np.nan, 0.5, 0.25, 0.25]))


@pytest.mark.parametrize(
    "cov, message",
    [
        (COV + np.array([[0, 0.005, 0], [0, 0, 0], [0, 0, 0]]), "not symmetric"),
        (np.diag([0.01, -0.04, 0.001]), "not positive semi-definite"),
        (np.diag([0.01, np.nan, 0.001]), "finite"),
        (np.eye(2), r"cov \(3, 3\)"),
    ],
    ids=["asymmetric", "indefinite", "nan", "2x2"],
)
def test_a_covariance_that_is_not_one_is_refused(cov, message):
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match=message):
        gaussian_samples(np.zeros(3), cov, 5, rng)
    with pytest.raises(InputError, match=message):
        scan_samples("mc", mean=np.zeros(3), cov=cov, n_samples=5)
    with pytest.raises(InputError, match=message):
        scan_samples("ml", mean=np.zeros(3), cov=cov)


def test_a_singular_covariance_still_draws_along_its_free_axes():
    """Semi-definite is a pose known exactly along an axis: drawn, that coordinate constant."""
    cov = np.diag([0.01, 0.0, 0.001])
    drawn = gaussian_samples(np.array([1.0, 2.0, 0.0]), cov, 200, np.random.default_rng(1))
    assert np.all(drawn[:, 1] == 2.0) and drawn[:, 0].std() > 0.05


# ------------------------------------------------------------------------------------------------ the fusion


BEAMS = np.linspace(-1.0, 1.0, 5)


def _fusion(angles=BEAMS, offset=(0.0, 0.0, 0.0), threads=1) -> MonteCarloFusion:
    return MonteCarloFusion(TiledGrid(0.05), SensorModel(resolution=0.05), angles, 0.0, 8.0, offset, threads=threads)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"angles": np.array([0.0, np.nan, 0.2])}, "beam angle 1 is NaN or inf"),
        ({"angles": np.linspace(-1.0, 1.0, 5)[None]}, r"shape \(B,\), got shape \(1, 5\)"),
        ({"offset": (0.1, 0.0)}, "sensor offset"),
        ({"offset": (0.1, np.nan, 0.0)}, "sensor offset"),
        ({"threads": 1.5}, "whole number of threads"),
    ],
    ids=["nan-angle", "2d-angles", "short-offset", "nan-offset", "half-thread"],
)
def test_a_laser_that_cannot_be_fused_is_refused_when_the_fusion_is_made(kwargs, message):
    with pytest.raises(InputError, match=message):
        _fusion(**kwargs)


@pytest.mark.parametrize(
    "ranges",
    [np.array([True] * 5), np.array(["1.0"] * 5), np.array([None] * 5), np.full(5, 2.0 + 1.0j)],
    ids=["bool", "str", "none", "complex"],
)
def test_ranges_that_are_not_real_numbers_are_refused(ranges):
    """True and "1.0" were taken as a 1 m return, None as none, and a complex range lost its imaginary part."""
    with pytest.raises(InputError, match="ranges must be real numbers"):
        _fusion().fuse(ranges, np.zeros((1, 3)), np.ones(1))
    assert _fusion().fuse(np.full(5, 2), np.zeros((1, 3)), np.ones(1)) is not None  # (integer metres are numbers)


@pytest.mark.parametrize(
    "samples, weights, message",
    [
        (np.array([["0", "0", "0"]]), np.ones(1), "pose samples must be real numbers"),
        (np.zeros((1, 3)), np.array(["1.0"]), "weights must be real numbers"),
        (np.zeros((1, 3)) + 1j, np.ones(1), "pose samples must be real numbers"),
    ],
    ids=["str-samples", "str-weights", "complex-samples"],
)
def test_samples_and_weights_that_are_not_real_numbers_are_refused(samples, weights, message):
    with pytest.raises(InputError, match=message):
        _fusion().fuse(np.full(5, 2.0), samples, weights)


def test_a_masked_scan_is_refused_not_fused_as_if_unmasked():
    """np.asarray drops a mask: a scan whose every beam was masked was fused as five 2 m returns."""
    masked = np.ma.masked_array(np.full(5, 2.0), mask=[True, False, False, False, True])
    with pytest.raises(InputError, match="masked array"):
        _fusion().fuse(masked, np.zeros((1, 3)), np.ones(1))
    assert _fusion().fuse(np.ma.masked_array(np.full(5, 2.0)), np.zeros((1, 3)), np.ones(1)) is not None


def test_bundling_refuses_poses_and_weights_of_two_lengths():
    """The compiled leader search read past the shorter array: one bundle of four poses weighing 1, bundle weights
    summing to 0.4, and with a million weights against two poses a crash of the interpreter."""
    from mapping.bundling import bundle_samples

    for lasers, weights in ((np.zeros((4, 2)), np.full(4, 0.25)), (np.zeros((2, 3)), np.full(5, 0.2))):
        with pytest.raises(InputError, match=r"need laser poses \(M, 3\) and weights \(M,\)"):
            bundle_samples(lasers, weights, 0.1, 1.0)
    with pytest.raises(InputError, match="finite"):
        bundle_samples(np.array([[0.0, 0.0, np.nan], [0.0, 0.0, 0.0]]), np.full(2, 0.5), 0.1, 1.0)
    leaders, summed = bundle_samples(np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]), np.array([0.4, 0.6]), 0.1, 1.0)
    np.testing.assert_array_equal(leaders, [[0.01, 0.0, 0.0]])  # (the heavier leads, with both weights)
    np.testing.assert_allclose(summed, [1.0])


@pytest.mark.parametrize(
    "x0, angle, r_stop, resolution", [(np.nan, 0.3, 1.0, 0.05), (1e20, 0.3, 1.0, 0.05), (0.0, np.inf, 1.0, 0.05),
                                      (0.0, 0.3, np.inf, 0.05), (0.0, 0.3, 1.0, 0.0)],
)  # fmt: skip
def test_a_ray_that_cannot_be_walked_is_refused_not_walked_for_ever(x0, angle, r_stop, resolution):
    """From x0 = NaN, inf or 1e20 m the walk never ended (in compiled code, past Ctrl-C)."""
    from mapping.raytrace import traverse

    with pytest.raises(InputError):
        traverse(x0, 0.0, angle, r_stop, resolution)
    ix, iy, _, r_out = traverse(0.01, 0.01, 0.0, 0.12, 0.05)
    assert ix.tolist() == [0, 1, 2] and iy.tolist() == [0, 0, 0] and r_out[-1] == pytest.approx(0.12)


def test_the_grid_and_model_refuse_an_infinite_cell_or_a_tile_past_its_bound():
    with pytest.raises(InputError, match="> 0 m and finite"):
        TiledGrid(np.inf)
    with pytest.raises(InputError, match="> 0 m and finite"):
        SensorModel(resolution=np.inf)
    for size in (2.0, 1 << 20, 3):
        with pytest.raises(InputError, match="power of two up to 4096"):
            TiledGrid(0.05, tile_size=size)  # type: ignore[arg-type]
    assert TiledGrid(0.05, tile_size=4096).tile_size == 4096


# ------------------------------------------------------------------------------------------------ maps in code


def _map_arrays(**changes) -> dict:
    probability = np.full((4, 6), 0.5, np.float32)
    probability[1, 2] = 0.9
    arrays = {
        "probability": probability,
        "observed": np.ones((4, 6), bool),
        "variance": np.full((4, 6), 0.1, np.float32),
        "origin": np.array([0.0, 0.0]),
        "resolution": 0.05,
    }
    return {**arrays, **changes}


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"resolution": np.nan}, "resolution > 0"),
        ({"origin": np.array([np.inf, 0.0])}, "finite origin"),
        ({"probability": np.full((4, 6), 1.5, np.float32)}, r"holds 1.5 at \(0, 0\)"),
        ({"probability": np.full((4, 6), np.nan, np.float32)}, "holds nan"),
        ({"observed": np.ones((6, 4), bool)}, "one shape"),
    ],
    ids=["nan-resolution", "inf-origin", "p-1.5", "p-nan", "transposed"],
)
def test_a_map_built_in_code_with_wrong_values_is_neither_drawn_nor_scored(changes, message):
    arrays = _map_arrays(**changes)
    truth = {
        "occupied": np.zeros((4, 6), bool),
        "visible": np.ones((4, 6), bool),
        "origin": np.array([0.0, 0.0]),
        "resolution": 0.05,
    }
    truth["occupied"][1, 2] = True
    assert score_map(_map_arrays(), truth)["auc"] == 1.0  # (the right map scores)
    for call in (lambda: render_pgm(arrays), lambda: crop_to_occupied(arrays, 0.1), lambda: score_map(arrays, truth)):
        with pytest.raises(InputError, match=message):
            call()
    if "probability" in changes or "observed" in changes:
        with pytest.raises(InputError, match=message):
            render_rgb(arrays)


def test_a_nan_margin_or_variance_scale_is_refused():
    with pytest.raises(InputError, match="margin"):
        crop_to_occupied(_map_arrays(), np.nan)
    with pytest.raises(InputError, match="variance scale"):
        render_rgb(_map_arrays(), "variance", variance_scale=np.nan)
    assert render_rgb(_map_arrays(), "variance", variance_scale=0.0).shape == (4, 6, 3)


# ------------------------------------------------------------------------------------------------ files written


def _map_file(**changes) -> MapFile:
    logodds = np.zeros((4, 6), np.float32)
    fields = {
        "logodds": logodds,
        "probability": np.full((4, 6), 0.5, np.float32),
        "observed": np.ones((4, 6), bool),
        "origin": np.array([0.0, 0.0]),
        "resolution": 0.05,
    }
    return MapFile(**{**fields, **changes})


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"resolution": 0.0}, "'resolution' must be in"),
        ({"resolution": np.nan}, "'resolution' must be finite"),
        ({"origin": np.array([0.0, 0.0, 0.0])}, "'origin' must be 2"),
        ({"probability": np.full((4, 6), 0.9, np.float32)}, "not the logistic of 'logodds'"),
        ({"variance": np.full((4, 6), -1.0, np.float32)}, "'variance' holds -1.0"),
        ({"level": np.full((4, 6), 200)}, "'level' holds 200"),
        ({"observed": np.ones((4, 5), bool)}, "'observed' has shape"),
    ],
    ids=["zero-resolution", "nan-resolution", "3d-origin", "p-not-logistic", "negative-variance", "level-200", "shape"],
)
def test_save_map_refuses_what_load_map_would_and_writes_nothing(tmp_path, changes, message):
    good = tmp_path / "good.npz"
    save_map(good, _map_file())
    assert load_map(good).logodds.shape == (4, 6)  # (a right map round-trips)
    path = tmp_path / "map.npz"
    with pytest.raises(FormatError, match=message):
        save_map(path, _map_file(**changes))
    assert not path.exists()


def _posed(**changes) -> PosedScans:
    steps, beams = 3, 5
    fields = {
        "ranges": np.full((steps, beams), 2.0, np.float32),
        "angle_min": -0.5,
        "angle_increment": 0.25,
        "range_min": 0.1,
        "range_max": 8.0,
        "stamps": np.arange(steps, dtype=float),
        "sensor_offset": np.zeros(3),
        "poses": PoseSet(samples=np.zeros((steps, 1, 3)), weights=np.ones((steps, 1))),
    }
    return PosedScans(**{**fields, **changes})


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"angle_increment": 0.0}, "'angle_increment' is 0"),
        ({"angle_increment": np.nan}, "'angle_increment' holds nan"),
        ({"angle_min": 1e6}, "more than a full turn"),
        ({"range_max": 0.05}, "range_min < range_max"),
        ({"stamps": np.array([0.0, np.nan, 2.0])}, "stamps"),
    ],
    ids=["zero-increment", "nan-increment", "angle-1e6", "max-below-min", "nan-stamp"],
)
def test_save_posed_scans_refuses_what_its_loader_would_and_writes_nothing(tmp_path, changes, message):
    good = tmp_path / "good.npz"
    save_posed_scans(good, _posed())
    assert load_posed_scans(good).ranges.shape == (3, 5)
    path = tmp_path / "posed.npz"
    with pytest.raises(FormatError, match=message):
        save_posed_scans(path, _posed(**changes))
    assert not path.exists()


def test_save_truth_refuses_a_resolution_of_zero_and_layers_of_two_shapes(tmp_path):
    path = tmp_path / "truth.npz"
    origin = np.zeros(2)
    with pytest.raises(FormatError, match="'resolution' must be in"):
        save_truth(path, TruthRaster(np.zeros((3, 3), bool), np.ones((3, 3), bool), origin, 0.0))
    with pytest.raises(FormatError, match="of one shape"):
        save_truth(path, TruthRaster(np.zeros((3, 3), bool), np.ones((3, 4), bool), origin, 0.05))
    assert not path.exists()


def test_set_tile_refuses_layers_no_map_holds():
    """NaN log-odds, a variance of -1 and `observed` of 7.0 were stored: the map rasterized to NaN probabilities over
    65 536 "observed" cells; a key of (0.5, "a") failed later in rasterize."""
    grid = TiledGrid(0.05, tile_size=8)
    zeros, ones = np.zeros((8, 8), np.float32), np.ones((8, 8), bool)
    for logodds, variance, observed, message in (
        (np.full((8, 8), np.nan, np.float32), zeros, ones, "'logodds' must be finite"),
        (zeros, np.full((8, 8), -1.0, np.float32), ones, "'variance' finite and >= 0"),
        (zeros, zeros, np.full((8, 8), 7.0), "'observed' must be booleans"),
    ):
        with pytest.raises(InputError, match=message):
            grid.set_tile((0, 0), logodds, variance, observed)
    with pytest.raises(InputError, match="a tile key must be two whole numbers"):
        grid.set_tile((0.5, "a"), zeros, zeros, ones)  # type: ignore[arg-type]
    assert grid.tile_count == 0
    grid.set_tile((0, 1), zeros, zeros, np.ones((8, 8), np.uint8))  # (0 and 1 as integers are booleans)
    assert grid.tile_count == 1 and grid.rasterize()["observed"].sum() == 64


def test_the_adaptive_grid_refuses_parameters_it_cannot_use():
    """sigma=inf was taken (no cell ever split), start_level=1.5 and tile_size=64.0 raised numpy or operator errors,
    merge=None an AttributeError once a scan came, and level_for_cell_size(0.4, 0.0) divided by zero."""
    from mapping.adaptive.fusion import AdaptiveFusion, AdaptiveParams, level_for_cell_size
    from mapping.adaptive.tree import AdaptiveGrid

    for given, message in (
        ({"sigma": np.inf}, "sigma must be a finite number"),
        ({"start_level": 1.5}, "start_level must be a whole number"),
        ({"merge": None}, "merge must be MergeRules"),
    ):
        with pytest.raises(InputError, match=message):
            AdaptiveParams(**given)
    with pytest.raises(InputError, match="params must be AdaptiveParams"):
        AdaptiveFusion(AdaptiveGrid(0.05), SensorModel(resolution=0.05), BEAMS, 0.0, 8.0, params={})  # type: ignore[arg-type]
    for resolution, tile_size in ((np.inf, 256), (0.05, 64.0)):
        with pytest.raises(InputError):
            AdaptiveGrid(resolution, tile_size)  # type: ignore[arg-type]
    for sizes in ((0.4, 0.0), (-0.4, -0.05), (0.4, np.nan)):
        with pytest.raises(InputError, match="the finest resolution must be finite and > 0"):
            level_for_cell_size(*sizes)
    assert level_for_cell_size(0.4, 0.05) == 3
