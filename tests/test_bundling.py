"""Pose bundles (mapping.bundling, `--bundle`): the bundling against a slow reference, its stated bound, and the
map it gives against the exact fusion's on the office benchmark (within 0.001 AUC and 1 % Brier score at the
recommended tolerance); exact at 0, the same on any thread count; the options refused where they would do nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.scenarios import honest_posed_scans, office_run, truth_arrays
from mapping.bundling import RECOMMENDED_TOLERANCE, bundle_samples
from mapping.errors import InputError
from mapping.evaluation import score_map
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import save_posed_scans
from services.fusion_runner import fuse_posed_scans
from test_cli_mapping import posegrid

RES = 0.05
MODEL = SensorModel(resolution=RES)


def reference_bundles(lasers: np.ndarray, weights: np.ndarray, tolerance: float, reach: float):
    """The rule of mapping.bundling written plainly: by decreasing weight (ties in order), each sample joins the
    first leader within the tolerance, else leads."""
    order = sorted(range(len(weights)), key=lambda j: (-weights[j], j))
    leaders: list[int] = []
    summed: list[float] = []
    for j in order:
        for k, lead in enumerate(leaders):
            turn = abs(math.remainder(lasers[j, 2] - lasers[lead, 2], 2 * math.pi))
            if math.dist(lasers[j, :2], lasers[lead, :2]) + reach * turn <= tolerance:
                summed[k] += weights[j]
                break
        else:
            leaders.append(j)
            summed.append(weights[j])
    return leaders, summed


def separation(a: np.ndarray, b: np.ndarray, reach: float) -> float:
    return math.dist(a[:2], b[:2]) + reach * abs(math.remainder(a[2] - b[2], 2 * math.pi))


clouds = st.integers(2, 40).flatmap(
    lambda m: st.tuples(
        st.lists(st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.1, 0.1)), min_size=m, max_size=m),
        st.lists(st.integers(1, 5), min_size=m, max_size=m),
    )
)


@settings(max_examples=150, deadline=None)
@given(clouds, st.floats(0.0, 0.5), st.floats(0.5, 30.0), st.floats(-math.pi, math.pi))
def test_bundles_follow_the_rule_and_keep_every_sample_within_the_tolerance(cloud, tolerance, reach, heading):
    poses, counts = cloud
    lasers = np.array(poses, float)
    lasers[:, 2] = np.array([math.remainder(heading + yaw, 2 * math.pi) for yaw in lasers[:, 2]])  # (across +-pi)
    weights = np.array(counts, float) / sum(counts)
    leaders, summed = bundle_samples(lasers, weights, tolerance, reach)
    expected, expected_sums = reference_bundles(lasers, weights, tolerance, reach)
    np.testing.assert_array_equal(leaders, lasers[expected])
    np.testing.assert_allclose(summed, expected_sums, rtol=0, atol=1e-12)
    assert math.isclose(summed.sum(), 1.0, abs_tol=1e-12)
    for pose in lasers:  # the bound: every sample has a leader within the tolerance
        assert min(separation(pose, leader, reach) for leader in leaders) <= tolerance
    for a in range(len(leaders)):  # and no leader lies within it of an earlier one
        for b in range(a):
            assert separation(leaders[a], leaders[b], reach) > tolerance


def test_a_tolerance_of_zero_keeps_every_distinct_sample():
    lasers = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1e-12], [1e-9, 0.0, 0.0], [0.0, 0.0, 0.0]])
    leaders, summed = bundle_samples(lasers, np.full(4, 0.25), 0.0, 10.0)
    assert len(leaders) == 3 and summed.tolist() == [0.5, 0.25, 0.25]


@pytest.fixture(scope="module")
def office():
    """The office benchmark's run (bench.fusion, bench.samples_scaling): 400 scans."""
    return office_run(steps=400)


def _fuse(posed, bundle: float, threads: int = 1) -> TiledGrid:
    return fuse_posed_scans(posed, model=MODEL, bundle=bundle, threads=threads)


def test_the_recommended_tolerance_keeps_the_office_map_within_its_bound_of_the_exact_map(office):
    """The office benchmark, 60 samples per scan from honest pose distributions (sigmas 3-15 cm, 0.3-1.7 deg): with
    the recommended tolerance the map's AUC moves by at most 0.001 and its Brier score and NLL by at most 1 % against
    the exact fusion's, while the scans walk under half of their samples. (On a shorter run the same tolerance can
    move the AUC more: docs/performance.md, "Bundled samples".)"""
    posed = honest_posed_scans(office, seed=1, particles=60)
    truth = truth_arrays(office)
    samples, weights = posed.poses.weighted_samples()
    scans = [(posed.scan_ranges(t), samples[t], weights[t]) for t in range(len(posed.stamps))]
    maps, walked = {}, {}
    for bundle in (0.0, RECOMMENDED_TOLERANCE):
        grid = TiledGrid(RES)
        fusion = MonteCarloFusion(grid, MODEL, *posed.single_geometry(), bundle=bundle)
        walked[bundle] = np.mean([outcome.samples_walked for outcome in fusion.fuse_many(scans)])
        maps[bundle] = score_map(grid.rasterize(), truth)
    exact, bundled = maps[0.0], maps[RECOMMENDED_TOLERANCE]
    assert abs(bundled["auc"] - exact["auc"]) <= 0.001, (bundled, exact)
    assert abs(bundled["brier"] - exact["brier"]) <= 0.01 * exact["brier"], (bundled, exact)
    assert abs(bundled["nll"] - exact["nll"]) <= 0.01 * exact["nll"], (bundled, exact)
    assert walked[0.0] == 60 and walked[RECOMMENDED_TOLERANCE] < 0.5 * 60, walked


def test_no_tolerance_is_the_exact_fusion_and_bundles_give_one_map_on_any_thread_count(office):
    posed = honest_posed_scans(office, seed=2, particles=30).select(slice(0, 40))  # (the first 40 scans)
    exact, zero = _fuse(posed, 0.0).rasterize(), _fuse(posed, 0.0, threads=2).rasterize()
    one, two = _fuse(posed, 0.1).rasterize(), _fuse(posed, 0.1, threads=2).rasterize()
    for name in ("logodds", "variance", "observed"):
        np.testing.assert_array_equal(zero[name], exact[name])
        np.testing.assert_array_equal(two[name], one[name])
    assert not np.array_equal(one["logodds"], exact["logodds"])  # (the bundles do walk fewer samples)


@pytest.mark.parametrize("bundle", [-0.1, math.nan, math.inf])
def test_the_library_refuses_a_tolerance_that_is_not_a_distance(bundle):
    with pytest.raises(InputError, match="bundle tolerance"):
        MonteCarloFusion(TiledGrid(RES), MODEL, np.zeros(3), 0.1, 5.0, bundle=bundle)


def test_posegrid_fuse_bundles_and_refuses_a_bundle_that_would_do_nothing(office, tmp_path):
    posed = tmp_path / "office.npz"
    save_posed_scans(posed, honest_posed_scans(office, particles=20).select(slice(0, 10)))  # (the first 10 scans)
    output = tmp_path / "map.npz"
    result = posegrid("fuse", str(posed), "-o", str(output), "--bundle", "0.1")
    assert result.returncode == 0 and output.exists(), result.stderr
    refused = {
        ("--bundle", "-1"): "--bundle",
        ("--bundle", "x"): "--bundle",
        ("--bundle", "0.1", "--mode", "ml"): "ml walks the mean pose only",
        ("--bundle", "0.1", "--grid", "adaptive"): "adaptive grid",
    }
    for options, reason in refused.items():
        result = posegrid("fuse", str(posed), "-o", str(tmp_path / "no.npz"), *options)
        lines = result.stderr.strip().splitlines()  # (argparse's own refusals come after its usage lines)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert reason in lines[-1] and not (tmp_path / "no.npz").exists()


def test_the_mapper_and_run_refuse_bundles_with_the_mean_pose(tmp_path):
    for command in (
        ["mapper", "--shard", "0", "--shards", "1"],
        ["run", "--no-api", "--export", str(tmp_path / "m.npz")],
    ):
        result = posegrid(*command, "--mode", "ml", "--bundle", "0.1")
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1, result.stderr
        assert "ml walks the mean pose only" in lines[0]
