"""Odometry that jumps (slam.odometry_jumps): the rule the live SLAM node and `posegrid slam --algo gridslam` share.

A probe fed `posegrid slam --algo gridslam` a log whose odometry was offset by 100 m from its 30th scan on (an
odometry driver restarting its frame): the command exited 0 with a healthy health line and a map holding a second copy
of the room 100 m away, where the live node refused the jump and took the reset as one."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam.carmen import write_carmen_scans
from slam.gridslam.simlogs import sim_log
from slam.laserlog import LaserLog
from slam.odometry_jumps import REBASE_STEPS, OdometryJumps, Verdict, joined_odometry


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose b (3,) seen from pose a (3,): the motion from a to b in a's frame, written out by hand."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    turn = (b[2] - a[2] + math.pi) % (2 * math.pi) - math.pi
    return np.array([c * dx + s * dy, -s * dx + c * dy, turn])


def _log(odometry: np.ndarray) -> LaserLog:
    """A log of one-beam scans 0.1 s apart at ``odometry`` (T, 3), its poses the odometry (a raw log)."""
    steps = len(odometry)
    return LaserLog(
        source="jumps.clf",
        stamps=0.1 * np.arange(steps),
        ranges=np.full((steps, 1), 2.0, np.float32),
        angle_min=0.0,
        angle_increment=0.01,
        range_min=0.0,
        range_max=10.0,
        sensor_offset=np.zeros(3),
        odometry=odometry,
        poses=odometry.copy(),
        where=np.arange(1, steps + 1),
    )


def _drive(steps: int) -> np.ndarray:
    """Odometry (steps, 3) of a robot driving a gentle curve, 0.1 m a step."""
    yaw = 0.05 * np.arange(steps)
    xy = np.cumsum(0.1 * np.stack([np.cos(yaw), np.sin(yaw)], axis=1), axis=0)
    return np.column_stack([xy, yaw])


def test_a_jump_is_refused_a_spike_leaves_the_frame_and_a_reset_is_taken_at_its_third_step():
    jumps = OdometryJumps(max_step=5.0)
    verdicts = [jumps.check(np.array(pose, float)) for pose in [(0, 0, 0), (1, 0, 0), (9, 0, 0), (2, 0, 0)]]
    assert verdicts == [Verdict.STEP, Verdict.STEP, Verdict.REFUSED, Verdict.STEP]  # 8 m from (1, 0): a spike
    assert jumps.reason == ""  # (the last step a move)
    reset = [jumps.check(np.array((100.0 + k, 0.0, 0.0))) for k in range(REBASE_STEPS)]
    assert reset == [Verdict.REFUSED] * (REBASE_STEPS - 1) + [Verdict.REBASE]
    assert "taken as a reset of the odometry, the robot not having moved across it" in jumps.reason
    assert jumps.check(np.array((103.0, 0.0, 0.0))) is Verdict.STEP  # (from the new frame)
    assert jumps.check(np.array((300.0, 0.0, 0.0))) is Verdict.REFUSED
    assert "moved 197 m since the last step, more than the 5 m a step may" in jumps.reason
    # jumps that do not agree with each other start the count again: never a reset
    wild = [jumps.check(np.array((1000.0 * k, 0.0, 0.0))) for k in range(2, 8)]
    assert wild == [Verdict.REFUSED] * 6
    with pytest.raises(ValueError, match="max_step"):
        OdometryJumps(float("nan"))


def test_a_step_faster_than_a_robot_is_a_jump_though_under_the_step_limit():
    """A probe: a reset of 30 m between scans 0.1 s apart (300 m/s) passed the 50 m limit, and grid FastSLAM drew a
    second copy of the map 30 m away. A step's time bounds it too: at most 50 m/s, never less than 2 m (stamps jitter
    by milliseconds)."""
    cases = [  # (move m, dt s, verdict)
        (30.0, 0.1, Verdict.REFUSED),  # 300 m/s
        (30.0, 1.0, Verdict.STEP),  # 30 m/s
        (4.0, 0.1, Verdict.STEP),  # 40 m/s
        (6.0, 0.1, Verdict.REFUSED),  # 60 m/s
        (1.9, 0.001, Verdict.STEP),  # under the floor: stamps that jitter
        (2.5, 0.001, Verdict.REFUSED),
        (30.0, -0.1, Verdict.STEP),  # stamps that run backwards: the step limit alone
        (30.0, math.nan, Verdict.STEP),
        (60.0, 5.0, Verdict.REFUSED),  # past the step limit however slow
    ]
    for move, dt, verdict in cases:
        jumps = OdometryJumps(max_step=50.0)
        jumps.check(np.zeros(3), 10.0)
        assert jumps.check(np.array([move, 0.0, 0.0]), 10.0 + dt) is verdict, (move, dt, jumps.reason)
    jumps = OdometryJumps(max_step=50.0)
    jumps.check(np.zeros(3), 0.0)
    jumps.check(np.array([30.0, 0.0, 0.0]), 0.1)
    assert jumps.reason.startswith("the odometry moved 30 m in 0.1 s since the last step, more than the 5 m a robot")
    # a reset: its steps agree with each other at the robot's speed, and the third is the new frame
    assert [jumps.check(np.array([30.0 + 0.1 * k, 0.0, 0.0]), 0.1 * (k + 2)) for k in range(2)] == [
        Verdict.REFUSED,
        Verdict.REBASE,
    ]


def test_a_reset_is_joined_to_the_odometry_before_and_its_jumped_scans_are_skipped():
    raw = _drive(12)
    raw[6:] = raw[6:] @ np.diag([1.0, -1.0, -1.0]) + np.array([100.0, -40.0, 0.0])  # another frame from scan 6 on
    joined = joined_odometry(_log(raw), max_step=50.0)
    kept = [i for i in range(12) if i not in (6, 7)]  # the reset's first two scans are refused, the third rebases
    assert joined.where.tolist() == [i + 1 for i in kept]
    assert [s.where for s in joined.skipped] == [7, 8]
    assert (
        "moved 108 m in 0.1 s since the last step, more than the 5 m a robot moves at 50 m/s"
        in joined.skipped[0].reason
    )
    assert any("line 9:" in note and "reset of the odometry" in note for note in joined.notes)
    np.testing.assert_array_equal(joined.odometry[:6], raw[:6])  # before the reset: as read
    steps = [_relative(joined.odometry[k], joined.odometry[k + 1]) for k in range(len(kept) - 1)]
    for k, step in enumerate(steps):
        a, b = kept[k], kept[k + 1]
        expected = np.zeros(3) if (a, b) == (5, 8) else _relative(raw[a], raw[b])  # no move across the reset
        np.testing.assert_allclose(step, expected, atol=1e-12)
    np.testing.assert_array_equal(joined.poses, joined.odometry)  # a raw log's poses are its odometry


def test_a_spike_leaves_out_one_scan_and_a_log_without_jumps_is_kept_as_it_is():
    raw = _drive(8)
    log = _log(raw)
    assert joined_odometry(log) is log
    raw[3] = raw[3] + np.array([0.0, 80.0, 0.0])
    joined = joined_odometry(_log(raw))
    assert joined.where.tolist() == [1, 2, 3, 5, 6, 7, 8] and [s.where for s in joined.skipped] == [4]
    np.testing.assert_array_equal(joined.odometry, np.delete(raw, 3, axis=0))
    assert joined.notes == ()


def test_posegrid_slam_takes_an_odometry_reset_as_the_live_node_does(tmp_path, capsys):
    """The probe's case on a simulated room: the odometry 100 m off from the 20th scan on. The command says so and
    the best particle ends where the robot is (before: 100 m away, on a second copy of the room)."""
    from schemas.files import load_pose_distribution
    from services.cli import main

    log = sim_log("room", seed=1)
    steps = len(log.stamps)
    odometry = log.odometry.copy()
    odometry[20:] += np.array([100.0, 0.0, 0.0])
    path = tmp_path / "reset.clf"
    write_carmen_scans(path, log, odometry=odometry)
    out = tmp_path / "o.npz"
    argv = ["slam", "--algo", "gridslam", str(path), "-o", str(out), "--particles", "8", "--particle-cap", "8"]
    assert main([*argv, "--odom-delay", "0", "--loop-closure", "off"]) == 0
    err = capsys.readouterr().err
    assert "taken as a reset of the odometry" in err and "more than the 5 m a robot moves at 50 m/s" in err, err
    dist = load_pose_distribution(tmp_path / "o.poses.npz")
    assert len(dist.stamps) == steps - (REBASE_STEPS - 1)
    best = dist.poses.samples[-1, int(np.argmax(dist.poses.weights[-1]))]
    assert np.hypot(*(best[:2] - log.true_poses[steps - 1, :2])) < 0.5, (best, log.true_poses[steps - 1])
