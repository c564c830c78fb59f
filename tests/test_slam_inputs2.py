"""Bad inputs to self-calibration (slam.selfcal), calibrations (slam.calibration), the pose graph (slam.posegraph)
and the relation score (slam.relations) are refused with a clear error before any compiled kernel or solver sees
them: never a segfault, a NaN result or a calibration file that cannot be read back."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slam import selfcal
from slam.calibration import GENERIC, MRCLAM7, Calibration, calibration_to_json, load_calibration, save_calibration
from slam.errors import InputError, LogFormatError
from slam.motion import VelocityMotionModel
from slam.posegraph import PoseGraph
from slam.range_bearing import RangeBearingModel
from slam.relations import Relations, Trajectory, poses_at, score_relations
from slam.selfcal import FitData, NotEnoughData, likelihood_pass, self_calibrate
from slam.sequence import SlamSequence


def _constant_drive(steps: int) -> SlamSequence:
    """``steps`` steps of 0.1 s under the one command (0.3 m/s, 0.1 rad/s), the same landmark measured at (2 m,
    0.5 rad) at every step: nothing in it tells the speed scale."""
    return SlamSequence(
        stamps=np.arange(steps) * 0.1,
        controls=np.tile([0.3, 0.1, 0.1], (steps - 1, 1)),
        control_ptr=np.r_[0, np.arange(steps)].astype(np.int64),
        measurements=np.tile([2.0, 0.5], (steps, 1)),
        landmark_ids=np.zeros(steps, np.int64),
        measurement_ptr=np.arange(steps + 1, dtype=np.int64),
        initial_pose=np.zeros(3),
        motion="velocity",
    )


def _overrunning_pointers(steps: int) -> SlamSequence:
    """Measurement pointers that index 1000 rows a step over ``steps`` measurements."""
    return replace(_constant_drive(steps), measurement_ptr=np.r_[np.arange(steps) * 1000, steps * 1000])


# ------------------------------------------------------------------------------------------ self-calibration


def test_pointers_beyond_the_measurements_are_refused_before_the_compiled_pass():
    # a child process: on the old code the compiled pass read past the arrays and the interpreter died (SIGSEGV)
    script = textwrap.dedent(
        """
        import sys
        sys.path.insert(0, {tests!r})
        from test_slam_inputs2 import _overrunning_pointers
        from slam.calibration import GENERIC
        from slam.errors import LogFormatError
        from slam.selfcal import FitData, likelihood_pass, self_calibrate
        try:
            likelihood_pass(FitData.of(_overrunning_pointers(400)), GENERIC)
        except LogFormatError as exc:
            print("refused:", exc)
        try:
            self_calibrate(lambda delay: _overrunning_pointers(600))
        except LogFormatError as exc:
            print("refused:", exc)
        """
    ).format(tests=str(Path(__file__).parent))
    done = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert len(lines) == 2 and all("measurement pointers do not index" in line for line in lines), done.stdout


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"controls": np.zeros((5, 2))}, r"controls must have shape \(N, 3\)"),
        ({"measurement_ptr": np.arange(11) * 1.0}, "measurement_ptr must hold whole numbers"),
        ({"initial_pose": np.array([0.0, np.nan, 0.0])}, "initial_pose must be finite"),
        ({"controls": np.tile([0.3, 0.1, -0.1], (9, 1))}, "control dt"),
    ],
)
def test_fit_data_refuses_a_sequence_the_compiled_pass_cannot_read(change, words):
    with pytest.raises(LogFormatError, match=words):
        FitData.of(replace(_constant_drive(10), **change))


def test_a_nan_measurement_is_refused_up_front_naming_it():
    sequence = _constant_drive(600)
    sequence.measurements[300, 0] = np.nan
    with pytest.raises(LogFormatError, match=r"measurements must be finite, got nan at index \(300, 0\)"):
        self_calibrate(lambda delay: sequence)


def test_a_fit_the_data_cannot_determine_says_so_and_writes_nothing(tmp_path):
    words = r"velocity_scale k_v .* the data cannot determine it"
    with pytest.raises(selfcal.UndeterminedParameter, match=words) as caught:
        self_calibrate(lambda delay: _constant_drive(600))
    assert isinstance(caught.value, NotEnoughData)  # callers that fall back on too little data fall back here too


def test_a_fit_that_runs_away_round_after_round_is_undetermined():
    """A probe's finding: on 450 s of an MRCLAM robot the rounds' a1 went 2.48, 7.13, 18.2, 50.6 (its speed scale
    0.96 to 0.67), and that calibration was used without a word (EKF inside95 0.48 where the generic noise gives
    0.73). A motion noise that grew in every round, by more than a factor of 2 in the last, ran away; settled fits
    move by 0.67 to 1.08 in their last round, and a noise near 0 may jump about without running away."""
    runaway = [{"a1": 2.48, "a4": 0.51}, {"a1": 7.13, "a4": 0.60}, {"a1": 18.2, "a4": 0.83}, {"a1": 50.6, "a4": 0.83}]
    with pytest.raises(selfcal.UndeterminedParameter, match=r"not settle: motion noise a1 went 2\.48, 7\.13"):
        selfcal.check_settled(runaway)
    settled = [{"a1": 2.18, "a4": 0.59}, {"a1": 1.07, "a4": 0.67}, {"a1": 0.806, "a4": 0.64}, {"a1": 0.817, "a4": 0.65}]
    selfcal.check_settled(settled)
    selfcal.check_settled(settled[:1])
    near_zero = [{"a1": a1, "a4": 0.3} for a1 in (0.0592, 0.0, 0.00456, 0.0379)]  # a simulated robot's, x8.3 last
    selfcal.check_settled(near_zero)
    a4_away = [{"a1": 0.8, "a4": a4} for a4 in (0.1, 0.25, 0.6)]
    with pytest.raises(selfcal.UndeterminedParameter, match=r"motion noise a4 went 0\.1, 0\.25, 0\.6"):
        selfcal.check_settled(a4_away)


def test_valid_fit_data_still_runs_the_pass():
    result = likelihood_pass(FitData.of(_constant_drive(50)), GENERIC)
    assert np.isfinite(result.poses).all()


# -------------------------------------------------------------------------------------------- calibration


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"range_calibration": (0.0, 0.0)}, r"range_calibration\[0\] must be finite and within \[0.1, 10\]"),
        ({"velocity_scale": (np.nan, 1.0)}, "velocity_scale must be finite"),
        ({"velocity_scale": (1.2e-4, 1e-6)}, r"velocity_scale\[0\] must be finite and within \[0.1, 10\]"),
        ({"velocity_scale": (1.0, 1.0, 1.0)}, r"velocity_scale must have shape \(2,\)"),
        ({"command_delay": -1.0}, r"command_delay must be finite and within \[0, 5\] s"),
        ({"bearing_bias": 1.0}, "bearing_bias"),
        ({"drive_angle": np.inf}, "drive_angle"),
        ({"velocity_bias": (0.0, 2.0)}, "velocity_bias"),
        ({"outlier_gate": 0.0}, "outlier_gate"),
        ({"scale_sd": np.nan}, "scale_sd"),
        ({"drive_angle_sd": -0.1}, "drive_angle_sd"),
        ({"motion": VelocityMotionModel(alphas=(2e3,) * 6)}, "alphas must be finite and within"),
        ({"sensor": RangeBearingModel(sigma_range=0.0)}, "sigma_range"),
        ({"command_delay": "soon"}, "must be a number"),
    ],
)
def test_a_calibration_refuses_what_its_file_could_not_hold(fields, words):
    with pytest.raises(InputError, match=words):
        Calibration(**fields)


def test_a_calibration_is_never_saved_unreadable_and_valid_ones_read_back(tmp_path):
    path = tmp_path / "c.json"
    for calibration in (GENERIC, MRCLAM7, Calibration(velocity_scale=(0.1, 10.0), range_calibration=(10.0, -2.0))):
        save_calibration(path, calibration)
        assert load_calibration(path) == calibration
    with pytest.raises(InputError, match="not written"):
        save_calibration(tmp_path / "d.json", replace(GENERIC, diagnostics={"object": object()}))
    assert not (tmp_path / "d.json").exists()


def test_the_file_reader_still_names_the_file_and_field(tmp_path):
    document = calibration_to_json(GENERIC)
    document["velocity_scale"] = [1.2e-4, 1e-6]
    path = tmp_path / "c.json"
    path.write_text(json.dumps(document))
    with pytest.raises(LogFormatError, match=r"'velocity_scale' must be in \[0.1, 10\]"):
        load_calibration(path)


def test_valid_corrections_are_unchanged():
    z = Calibration(range_calibration=(1.1, -0.4), bearing_bias=0.1).correct_measurements(np.array([[2.0, 0.6]]))
    np.testing.assert_allclose(z, [[2.0 / (1.1 - 0.4 * 0.5**2), 0.5]], rtol=1e-12)


# ---------------------------------------------------------------------------------------------- pose graph


def _three_nodes() -> PoseGraph:
    graph = PoseGraph()
    for pose in ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 0.0]):
        graph.add_node(np.array(pose))
    return graph


def test_a_node_no_edge_ties_to_the_anchor_is_refused_not_turned_nan():
    graph = _three_nodes()
    graph.add_edge(0, 1, np.array([1.0, 0.0, 0.0]), np.eye(3) * 0.01)
    with pytest.raises(InputError, match=r"nodes 2\) are tied to node 0 by no chain of edges"):
        graph.optimize()
    assert np.isfinite(graph.poses).all()
    graph.add_edge(1, 2, np.array([1.0, 0.0, 0.0]), np.eye(3) * 0.01)
    assert graph.optimize() >= 1
    np.testing.assert_allclose(graph.poses, [[0, 0, 0], [1, 0, 0], [2, 0, 0]], atol=1e-9)


@pytest.mark.parametrize(
    ("edge", "words"),
    [
        ((0.5, 0, [1.0, 0, 0], np.eye(3)), "must be whole numbers"),
        ((1, 1, [1.0, 0, 0], np.eye(3)), "two different existing nodes"),
        ((0, 3, [1.0, 0, 0], np.eye(3)), "two different existing nodes"),
        ((0, 1, [1.0, 0, np.nan], np.eye(3)), "z must be finite"),
        ((0, 1, [1.0, 0, 0], np.diag([1.0, np.nan, 1.0])), "covariance must be finite"),
        ((0, 1, [1.0, 0, 0], -np.eye(3)), "not positive semi-definite"),
        ((0, 1, [1.0, 0, 0], np.eye(3) + np.triu(np.ones((3, 3)), 1)), "not symmetric"),
        ((0, 1, [1.0, 0, 0], np.diag([1.0, 1.0, 0.0])), "covariance is singular"),
        ((0, 1, [1.0, 0, 0], np.eye(2)), r"covariance must have shape \(3, 3\)"),
    ],
)
def test_an_edge_the_solver_cannot_use_is_refused(edge, words):
    graph = _three_nodes()
    with pytest.raises(InputError, match=words):
        graph.add_edge(*edge)
    graph.add_edge(0, 1, np.array([1.0, 0.0, 0.0]), np.eye(3))
    assert graph.chi2().shape == (1,)  # the refused edge was not stored


def test_pose_graph_counts_and_nodes_are_checked():
    graph = _three_nodes()
    with pytest.raises(InputError, match="pose must be finite"):
        graph.add_node(np.array([np.nan, 0.0, 0.0]))
    for i, j in ((0, 1), (1, 2), (0, 2)):
        graph.add_edge(i, j, np.array([1.0, 0.0, 0.0]), np.eye(3))
    with pytest.raises(InputError, match="cannot remove 5 edges, the graph has 3"):
        graph.remove_last_edges(5)
    with pytest.raises(InputError, match="count must be a whole number >= 0"):
        graph.remove_last_edges(-1)
    assert len(graph.chi2()) == 3
    with pytest.raises(InputError, match="iterations must be a whole number >= 1"):
        graph.optimize(iterations=-3)
    with pytest.raises(InputError, match="tolerance"):
        graph.optimize(tolerance=np.nan)
    graph.remove_last_edges(1)
    assert len(graph.chi2()) == 2


# ------------------------------------------------------------------------------------------------ relations

TRAJ = Trajectory(np.array([0.0, 1.0, 2.0]), np.array([[0, 0, 0], [1, 0, np.pi / 2], [1, 1, np.pi / 2]], float))
RELATIONS = Relations(np.array([0.0, 1.0]), np.array([1.0, 2.0]), np.array([[1.0, 0, 0], [1, 0, 0]]), np.array([1, 2]))


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: Trajectory(np.array([0.0, 1.0, 2.0]), np.full((3, 3), np.nan)), "Trajectory.poses must be finite"),
        (lambda: Trajectory(np.array([0.0, np.nan, 2.0]), np.zeros((3, 3))), "Trajectory.stamps must be finite"),
        (lambda: Trajectory(np.array([0.0, 2.0, 1.0]), np.zeros((3, 3))), "must be in order"),
        (lambda: Trajectory.sorted(np.arange(3.0), np.zeros((5, 3))), r"poses must have shape \(3, 3\), got \(5, 3\)"),
        (lambda: score_relations(Trajectory(np.zeros(0), np.zeros((0, 3))), RELATIONS), "trajectory has no poses"),
        (lambda: Relations(np.array([np.nan, 1.0]), np.array([1.0, 2.0]), np.zeros((2, 3)), np.array([1, 2])), "t1"),
        (lambda: score_relations(TRAJ, RELATIONS, tolerance=np.nan), "tolerance must be a number of seconds"),
        (lambda: score_relations(TRAJ, RELATIONS, max_gap=-1.0), "max_gap must be a number of seconds"),
        (lambda: poses_at(TRAJ, np.array([np.nan])), "query stamps must be finite"),
    ],
)
def test_relation_scoring_refuses_what_would_score_nan_or_mislead(make, words):
    with pytest.raises(InputError, match=words):
        make()


def test_valid_relations_score_as_before():
    summary = score_relations(TRAJ, RELATIONS).summary()
    assert summary["relations_used"] == 2
    assert summary["trans_mean_m"] == pytest.approx(0.0, abs=1e-12)
