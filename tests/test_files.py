"""The file loaders' checks (schemas.files), each on a file that breaks exactly one rule of docs/formats.md;
the phrase expected is the one the contract names."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.errors import FormatError
from schemas.files import load_map, load_pose_distribution, load_posed_scans, load_truth


def posed(**override):
    arrays = dict(
        ranges=np.ones((2, 3), np.float32),
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.1,
        range_max=5.0,
        stamps=np.arange(2.0),
        samples=np.zeros((2, 1, 3)),
        weights=np.ones((2, 1)),
    )
    arrays.update(override)
    return {k: v for k, v in arrays.items() if v is not None}


def gaussian(**override):
    return posed(
        **{"samples": None, "weights": None, "mean": np.zeros((2, 3)), "cov": np.stack([np.eye(3)] * 2), **override}
    )


def a_map(**override):
    logodds = np.array([[0.0, 1.0], [-1.0, 2.0]], np.float32)
    arrays = dict(
        logodds=logodds,
        probability=(1 / (1 + np.exp(-logodds.astype(float)))).astype(np.float32),
        observed=np.ones((2, 2), bool),
        variance=np.zeros((2, 2), np.float32),
        origin=np.zeros(2),
        resolution=0.05,
    )
    arrays.update(override)
    return arrays


def _write(tmp_path, arrays):
    path = tmp_path / "f.npz"
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize(
    "arrays, phrase",
    [
        (posed(range_min=-0.5), "0 <= range_min < range_max"),
        (posed(angle_increment=0.0), "'angle_increment' is 0 but the scans have 3 beams"),
        (posed(range_max=np.inf), "'range_max' must be finite"),
        (posed(sensor_offset=np.array([0.0, np.nan, 0.0])), "'sensor_offset' holds NaN or inf"),  # (said "shape")
        (posed(sensor_offset=np.zeros(2)), "'sensor_offset' must be 3 finite numbers"),
        (
            posed(sensor_offset=np.array([0.1, 0.0, 90.0])),
            "'sensor_offset' holds a yaw of 90 rad at step 0, more than a full turn",
        ),
        (posed(samples=np.zeros((3, 1, 3)), weights=np.ones((3, 1))), "'samples' must have shape (2, M, 3)"),
        (posed(weights=np.ones((2, 2)) * 0.5, samples=np.zeros((2, 1, 3))), "'weights' must have shape (2, 1)"),
        (posed(weights=np.array([[1.5, -0.5], [0.5, 0.5]]), samples=np.zeros((2, 2, 3))), "negative, NaN or inf"),
        (gaussian(cov=np.stack([np.eye(3), np.diag([1.0, -0.1, 1.0])])), "not positive semi-definite at step 1"),
        (
            gaussian(cov=np.stack([np.eye(3), np.eye(3) + np.triu(np.ones((3, 3)), 1) * 1e-3])),
            "not symmetric at step 1",
        ),
        (gaussian(mean=np.zeros((3, 3))), "'mean' must have shape (2, 3)"),
        # yaws in degrees (a probe's file: fused at exit 0 into a map of AUC 0.61 against 0.94)
        (gaussian(mean=np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 90.0]])), "'mean' holds a yaw of 90 rad at step 1"),
        (
            posed(samples=np.array([[[0, 0, 0.1]], [[0, 0, -6.3]]]), weights=np.ones((2, 1))),
            "'samples' holds a yaw of -6.3 rad at step 1, more than a full turn",
        ),
    ],
)
def test_posed_scan_files_that_break_one_rule_are_refused(tmp_path, arrays, phrase):
    with pytest.raises(FormatError) as info:
        load_posed_scans(_write(tmp_path, arrays))
    assert phrase in str(info.value)


def test_yaws_of_up_to_a_full_turn_either_way_are_taken(tmp_path):
    """Headings wrapped to [-pi, pi) or to [0, 2 pi) are both radians."""
    turn = 2 * np.pi
    loaded = load_posed_scans(_write(tmp_path, gaussian(mean=np.array([[0.0, 0.0, turn], [0.0, 0.0, -turn]]))))
    assert loaded.poses.mean[:, 2].tolist() == [turn, -turn]  # (kept as given: the fusion takes any angle)
    loaded = load_posed_scans(
        _write(tmp_path, posed(samples=np.array([[[0, 0, 6.28]], [[0, 0, -3.14]]]), weights=np.ones((2, 1))))
    )
    assert loaded.poses.samples[:, 0, 2].tolist() == [6.28, -3.14]


def test_pose_distribution_files_check_the_poses_too(tmp_path):
    arrays = {"stamps": np.arange(2.0), "samples": np.zeros((2, 2, 3)), "weights": np.array([[2.0, -1.0], [0.5, 0.5]])}
    with pytest.raises(FormatError, match="negative, NaN or inf"):
        load_pose_distribution(_write(tmp_path, arrays))


@pytest.mark.parametrize(
    "arrays, phrase",
    [
        (a_map(observed=np.ones((2, 3), bool)), "'observed' has shape (2, 3), 'logodds' has (2, 2)"),
        (a_map(resolution=5000.0), "'resolution' must be in [1e-06, 1000] m"),
        (
            a_map(probability=np.array([[0.5, 0.7311], [0.2689, 0.8900]], np.float32)),
            "not the logistic",
        ),  # 0.881 -> 0.890
    ],
)
def test_map_files_that_break_one_rule_are_refused(tmp_path, arrays, phrase):
    with pytest.raises(FormatError) as info:
        load_map(_write(tmp_path, arrays))
    assert phrase in str(info.value)


def test_a_map_whose_probability_is_the_logistic_to_float32_precision_loads(tmp_path):
    assert load_map(_write(tmp_path, a_map())).probability.shape == (2, 2)


def test_truth_layers_of_two_shapes_are_refused(tmp_path):
    arrays = dict(occupied=np.zeros((2, 2), bool), visible=np.ones((2, 3), bool), origin=np.zeros(2), resolution=0.1)
    with pytest.raises(FormatError, match="must be 2-D of one shape"):
        load_truth(_write(tmp_path, arrays))
