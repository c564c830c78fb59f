"""Relation reader, relation errors against hand-computed values, clock alignment, and `posegrid eval-relations`."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_file
from schemas.files import PoseDistributionFile, PoseSet, save_pose_distribution
from services.cli import main
from slam.carmen import write_carmen
from slam.errors import LogFormatError
from slam.laserlog import LaserLog, with_odometry_delay
from slam.relations import Trajectory, poses_at, read_relations, score_relations, trajectory_from_log
from slam.timealign import bursty_stamps, odometry_delay, time_map, to_reference_time

# x(0) = (0, 0, 0), x(1) = (1, 0, pi/2), x(2) = (1, 1, pi/2)
TRAJ = Trajectory(np.array([0.0, 1.0, 2.0]), np.array([[0, 0, 0], [1, 0, math.pi / 2], [1, 1, math.pi / 2]], float))
# x(0.5) interpolates to (0.5, 0, pi/4); from there to x(2) the motion is (1.5/sqrt2, 0.5/sqrt2, pi/4)
R3 = (1.5 / math.sqrt(2) - 0.3, 0.5 / math.sqrt(2) + 0.4)
RELATION_LINES = [
    "# t1 t2 dx dy dz roll pitch yaw",
    "0 1 1.0 0.1 0 0 0 1.5707963267948966",  # trans 0.1, rot 0
    "1 2 1.0 0.0 0 0 0 0.2",  # trans 0, rot 0.2
    f"0.5 2 {R3[0]!r} {R3[1]!r} 0 0 0 0.7853981633974483",  # trans 0.5 (a 3-4-5 triangle), rot 0
    "5 6 1 0 0 0 0 0",  # no pose at 5 or 6: skipped
    f"0.0004 1  1.0 0.0 0.00000  0.0 0.0 {math.pi / 2 - 2 * math.pi + 0.3!r}",  # within 1 ms of 0; rot 0.3 over -pi
]


def write(tmp_path: Path, name: str, lines: list[str]) -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_hand_computed_relation_errors(tmp_path):
    relations = read_relations(write(tmp_path, "r.relations", RELATION_LINES))
    assert len(relations) == 5 and relations.skipped == ()
    assert relations.lines.tolist() == [2, 3, 4, 5, 6]
    score = score_relations(TRAJ, relations)
    assert score.used.tolist() == [True, True, True, False, True]
    np.testing.assert_allclose(score.trans_error, [0.1, 0.0, 0.5, 0.0], atol=1e-12)
    np.testing.assert_allclose(score.rot_error, [0.0, 0.2, 0.0, 0.3], atol=1e-12)
    s = score.summary()
    assert s["relations_used"] == 4 and s["relations_total"] == 5
    assert s["trans_mean_m"] == pytest.approx(0.15)
    assert s["trans_std_m"] == pytest.approx(math.sqrt(0.26 / 4 - 0.15**2))
    assert s["rot_mean_rad"] == pytest.approx(0.125)
    assert s["rot_mean_deg"] == pytest.approx(math.degrees(0.125))
    assert s["trans_sq_mean_m2"] == pytest.approx(0.26 / 4)


def test_poses_at_tolerance_and_gap():
    traj = Trajectory(np.array([0.0, 1.0, 11.0]), np.array([[0, 0, 3.0], [1, 0, -3.0], [2, 0, 0.0]]))
    poses, ok = poses_at(traj, np.array([0.0005, 0.5, 6.0, 11.0009, -0.5, 12.0]), tolerance=1e-3, max_gap=5.0)
    assert ok.tolist() == [True, True, False, True, False, False]
    np.testing.assert_allclose(poses[0], [0, 0, 3.0])
    # halfway from yaw 3 to yaw -3 the short way, across pi
    np.testing.assert_allclose(poses[1], [0.5, 0, -math.pi], atol=1e-12)
    np.testing.assert_allclose(poses[3], [2, 0, 0])


def test_relation_file_bad_lines(tmp_path):
    lines = [
        "1 2 0 0 0 0 0 0",
        "1 2 3",
        "a 2 0 0 0 0 0 0",
        "1 nan 0 0 0 0 0 0",
        "3 3 0 0 0 0 0 0",
        "",
        "4 5 1 1 0 0 0 1",
        "6 7 1e308 0 0 0 0 0",  # finite, but its squared error overflows the scores
    ]
    relations = read_relations(write(tmp_path, "r", lines))
    assert relations.lines.tolist() == [1, 7]
    assert [s.where for s in relations.skipped] == [2, 3, 4, 5, 8]
    np.testing.assert_array_equal(relations.delta[1], [1, 1, 1])
    with pytest.raises(LogFormatError, match="holds no relation"):
        read_relations(write(tmp_path, "empty", ["# nothing"]))
    with pytest.raises(LogFormatError, match="no relation matches"):
        score_relations(Trajectory(np.array([100.0, 101.0]), np.zeros((2, 3))), relations)
    # a file in degrees (a probe's: scored at exit 0, 91.9 deg of rotational error) is refused, not half skipped
    degrees = ["1 2 0.5 0 0 0 0 0.5", "3 4 0.5 0 0 0 0 -45.0", "5 6 0.5 0 0 0 0 2.0"]
    with pytest.raises(LogFormatError, match=r"r-deg:2: an angle of -45 is more than a full turn.*in rad"):
        read_relations(write(tmp_path, "r-deg", degrees))
    assert read_relations(write(tmp_path, "r-rad", ["1 2 0.5 0 0 0 0 -6.28", "3 4 0 0 0 0 0 3.14"])).lines.size == 2


def small_log(stamps, ranges, poses=None, odom_stamps=(), odom_poses=()) -> LaserLog:
    n = len(stamps)
    poses = np.zeros((n, 3)) if poses is None else np.asarray(poses, float)
    return LaserLog(
        source="mem",
        stamps=np.asarray(stamps, float),
        ranges=np.asarray(ranges, np.float32),
        angle_min=-1.0,
        angle_increment=1.0,
        range_min=0.0,
        range_max=80.0,
        sensor_offset=np.zeros(3),
        odometry=poses,
        poses=poses,
        where=np.arange(1, n + 1),
        odom_stamps=np.asarray(odom_stamps, float),
        odom_poses=np.asarray(odom_poses, float).reshape(-1, 3),
    )


def test_trajectory_from_log_merges_odometry():
    log = small_log(
        [1.0, 2.0],
        np.ones((2, 3)),
        poses=[[1, 1, 0], [2, 2, 0]],
        odom_stamps=[0.0, 1.5, 2.0, 0.5],
        odom_poses=[[9, 9, 9], [1.5, 1.5, 0], [8, 8, 8], [0.5, 0.5, 0]],
    )
    traj = trajectory_from_log(log)
    # the stamp-0 ODOM repeat is dropped, the ODOM at a scan's stamp yields to the scan
    np.testing.assert_array_equal(traj.stamps, [0.5, 1.0, 1.5, 2.0])
    np.testing.assert_array_equal(traj.poses[:, 0], [0.5, 1, 1.5, 2])


def test_clock_alignment_by_shared_scans():
    rows = np.arange(1.0, 6.0)[:, None] * np.array([1.0, 2.0, 3.0])  # five distinct scans r0..r4
    log = small_log([0.0, 1.0, 2.0, 3.0], rows[:4])
    ref = small_log([99.0, 100.0, 101.2, 102.0, 102.1, 103.5], [rows[4], rows[0], rows[1], rows[2], rows[2], rows[3]])
    stamps, offsets = time_map(log, ref)
    # r2 occurs twice in the reference: not a pair
    np.testing.assert_allclose(stamps, [0.0, 1.0, 3.0])
    np.testing.assert_allclose(offsets, [100.0, 100.2, 100.5])
    np.testing.assert_allclose(to_reference_time(np.array([2.0, -1.0, 9.0]), stamps, offsets), [102.35, 99.0, 109.5])
    with pytest.raises(LogFormatError, match="share 0 scans"):
        time_map(log, small_log([0.0], np.full((1, 3), 7.0)))


def test_cli_eval_relations_on_a_pose_file_and_a_log(tmp_path, capsys):
    rel = write(tmp_path, "r.relations", RELATION_LINES)
    # a particle file: the best particle follows TRAJ, a light one is far off
    samples = np.stack([TRAJ.poses, TRAJ.poses + [5.0, 5.0, 0.5]], axis=1)  # (yaws within a turn)
    weights = np.tile([0.7, 0.3], (3, 1))
    npz = tmp_path / "poses.npz"
    save_pose_distribution(npz, PoseDistributionFile(TRAJ.stamps, PoseSet(samples=samples, weights=weights)))
    out = tmp_path / "score.json"
    assert main(["eval-relations", str(npz), str(rel), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["relations_used"] == 4 and result["trans_mean_m"] == pytest.approx(0.15)
    printed = capsys.readouterr().out
    assert "4 of 5 relations" in printed and "0.1500" in printed
    # the same trajectory as a CARMEN log's scan poses
    clf = tmp_path / "t.clf"
    write_carmen(clf, TRAJ.stamps, np.ones((3, 5)), TRAJ.poses, -1.0, 0.5, 10.0)
    assert main(["eval-relations", str(clf), str(rel), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["rot_mean_rad"] == pytest.approx(0.125, abs=1e-5)


def test_cli_eval_relations_scores_a_pose_file_of_a_restamped_log_on_the_raw_logs_clock(tmp_path, capsys):
    """`posegrid slam` of a corrected log stamps its poses with that log's clock (the Intel one runs 976052857 s
    from its bag's): --stamped-by names that log, whose scans --align-to matches with the raw log's, and the poses
    score as they would on the raw clock. Either option alone is refused, saying what the other is for."""
    rel = write(tmp_path, "r.relations", RELATION_LINES)
    samples = np.stack([TRAJ.poses, TRAJ.poses + [5.0, 5.0, 0.5]], axis=1)
    weights = np.tile([0.7, 0.3], (3, 1))
    ranges = np.arange(1.0, 16.0).reshape(3, 5)  # three distinct scans, shared by both logs
    restamped = TRAJ.stamps + 1000.0
    corrected, raw = tmp_path / "corrected.clf", tmp_path / "raw.clf"
    write_carmen(corrected, restamped, ranges, TRAJ.poses, -1.0, 0.5, 20.0)
    write_carmen(raw, TRAJ.stamps, ranges, TRAJ.poses, -1.0, 0.5, 20.0)
    npz = tmp_path / "corrected.poses.npz"
    save_pose_distribution(npz, PoseDistributionFile(restamped, PoseSet(samples=samples, weights=weights)))
    out = tmp_path / "score.json"
    assert main(["eval-relations", str(npz), str(rel)]) == 2  # (no relation lies on its clock)
    assert "same time base" in capsys.readouterr().err
    argv = ["eval-relations", str(npz), str(rel), "--align-to", str(raw), "--stamped-by", str(corrected)]
    assert main([*argv, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["relations_used"] == 4 and result["trans_mean_m"] == pytest.approx(0.15)
    assert f"(stamped by {corrected}) to {raw} by 3 shared scans" in capsys.readouterr().err
    assert main(argv[:5]) == 2
    assert "name the log its stamps come from with --stamped-by LOG" in capsys.readouterr().err
    assert main([*argv[:3], *argv[5:]]) == 2
    assert "give both" in capsys.readouterr().err
    # a log as POSES with --stamped-by said "give both" though both were given (a probe's): it says POSES is a log
    assert main(["eval-relations", str(raw), str(rel), "--align-to", str(raw), "--stamped-by", str(corrected)]) == 2
    assert f"but POSES {raw} is a log: drop --stamped-by" in capsys.readouterr().err
    # --scan-topic with a pose .npz and no log to read was ignored, exit 0 (a probe's): it is refused
    assert main(["eval-relations", str(npz), str(rel), "--scan-topic", "/x"]) == 2
    assert "no log is read here" in capsys.readouterr().err


def test_cli_eval_relations_reads_a_bag_of_two_scan_topics_with_scan_topic(tmp_path, capsys):
    """A bag with two LaserScan topics: its odometry is scored once --scan-topic names one (the reader's refusal
    names the option, which eval-relations has as slam, run and source have it)."""
    from bags import BagBuilder

    bag = BagBuilder()
    for stamp, (x, y, yaw) in zip(TRAJ.stamps, TRAJ.poses):
        bag.odom(float(stamp), float(x), float(y), float(yaw))
    for topic in ("/front", "/rear"):
        for stamp in TRAJ.stamps:
            bag.scan(float(stamp) + 1e-4, [1.0, 2.0, 3.0], topic=topic)
    path = bag.write(tmp_path / "two.bag")
    rel = write(tmp_path, "r.relations", RELATION_LINES)
    assert main(["eval-relations", str(path), str(rel)]) == 2
    assert "name one (with --scan-topic)" in capsys.readouterr().err
    assert main(["eval-relations", str(path), str(rel), "--scan-topic", "/front"]) == 0
    assert "relations matched" in capsys.readouterr().out


def test_cli_eval_relations_bad_input(tmp_path, capsys):
    rel = write(tmp_path, "r.relations", RELATION_LINES)
    assert main(["eval-relations", str(tmp_path / "nope.npz"), str(rel)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err
    bad = write(tmp_path, "bad.relations", ["1 2 3"])
    clf = tmp_path / "t.clf"
    write_carmen(clf, TRAJ.stamps, np.ones((3, 5)), TRAJ.poses, -1.0, 0.5, 10.0)
    assert main(["eval-relations", str(clf), str(bad)]) == 2
    assert "holds no relation" in capsys.readouterr().err


def test_real_relations_corrected_fr079_aligned_to_its_bag(tmp_path):
    """The GMapping-corrected Freiburg 079 log, put on the bag's clock, scores like the paper's RBPF
    (Kuemmerle et al. 2009 report 0.06 +- 0.044 m); its raw odometry is two orders of magnitude worse."""
    rel = shared_file("fr079", "fr079.relations")
    corrected = shared_file("fr079", "freiburg-079-corrected.log.gz")
    bag = shared_file("fr079", "fr079.orig.bag")
    out = tmp_path / "s.json"
    assert main(["eval-relations", str(corrected), str(rel), "--align-to", str(bag), "--json", str(out)]) == 0
    s = json.loads(out.read_text())
    assert s["relations_used"] == s["relations_total"] == 1685
    assert 0.03 < s["trans_mean_m"] < 0.09
    assert main(["eval-relations", str(bag), str(rel), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["trans_mean_m"] > 1.0


def test_odometry_read_later_or_earlier_than_the_scans():
    """with_odometry_delay reads the ODOM stream at stamp + delay (yaw unwrapped across +-pi). Poses a log states
    of its own (a corrected log's) stay; where its stated poses are its odometry (a raw log, a bag) they follow
    the shifted odometry, so nothing later takes the raw odometry for a reference to judge the run by."""
    stream_t = np.arange(0.0, 10.0, 0.5)
    stream = np.column_stack([stream_t, 2 * stream_t, 3.0 + 0.1 * stream_t])  # yaw crosses pi at t = 1.42
    log = small_log([2.0, 4.0], np.ones((2, 3)), odom_stamps=stream_t, odom_poses=stream)
    shifted = with_odometry_delay(log, -0.25)
    np.testing.assert_allclose(shifted.odometry[:, :2], [[1.75, 3.5], [3.75, 7.5]])
    np.testing.assert_allclose(np.cos(shifted.odometry[:, 2]), np.cos([3.175, 3.375]))
    np.testing.assert_array_equal(shifted.poses, shifted.odometry)  # the log stated only its odometry
    corrected = replace(log, poses=np.array([[5.0, 6.0, 0.1], [7.0, 8.0, 0.2]]))
    np.testing.assert_array_equal(with_odometry_delay(corrected, -0.25).poses, corrected.poses)
    assert with_odometry_delay(log, 0.0) is log
    with pytest.raises(LogFormatError, match="separate odometry stream"):
        with_odometry_delay(small_log([1.0], np.ones((1, 3))), 0.1)


def test_a_delay_past_the_odometry_skips_the_scans_it_leaves_without_odometry():
    """A scan whose stamp + delay lies more than 0.5 s past the odometry's ends, or between odometry records more
    than 5 s apart, is skipped and listed as the readers list their own (it used to take the end pose: an
    --odom-delay of 5 s gave every scan of a 4 s bag the same pose)."""
    stream_t = np.array([0.0, 0.5, 1.0, 7.0, 7.5, 8.0])
    stream = np.column_stack([stream_t, stream_t, np.zeros(6)])
    log = small_log([0.2, 0.6, 3.0, 7.9, 8.4], np.ones((5, 3)), odom_stamps=stream_t, odom_poses=stream)
    shifted = with_odometry_delay(log, 0.3)  # 0.5, 0.9, 3.3 (in a 6 s gap), 8.2, 8.7 (0.7 s past the end)
    np.testing.assert_array_equal(shifted.where, [1, 2, 4])
    np.testing.assert_allclose(shifted.odometry[:, 0], [0.5, 0.9, 8.0])
    assert [s.where for s in shifted.skipped] == [3, 5]
    assert "6 s apart" in shifted.skipped[0].reason and "0.7 s outside" in shifted.skipped[1].reason
    with pytest.raises(LogFormatError, match="no scan has odometry around it"):
        with_odometry_delay(log, -5.0)


def test_stamps_in_bursts_cannot_time_an_odometry_delay():
    """Scans two at a time 1 ms apart, every 0.2 s (the Intel bag's way): more than 5 % of the intervals are under a
    fifth of the median, so the stamps are said to come in bursts; regular scans with odometry at twice their rate
    are not, and odometry records in bursts beside regular scans are."""
    regular = np.arange(0.0, 20.0, 0.1)
    bursts = np.sort(np.concatenate([np.arange(0.0, 20.0, 0.2), np.arange(0.0, 20.0, 0.2) + 0.001]))
    odometry = np.arange(0.0, 20.0, 0.05)
    assert bursty_stamps(regular, odometry) == ""
    assert "scans come in bursts" in bursty_stamps(bursts, odometry)
    assert "odometry records come in bursts" in bursty_stamps(
        regular, np.sort(np.concatenate([regular, regular + 1e-4]))
    )
    one_late = regular.copy()
    one_late[50] = one_late[49] + 0.001  # one short interval in 199: 0.5 %, no burst
    assert bursty_stamps(one_late, odometry) == ""
    # a probe's finding: odometry at 100 Hz (ROS's 50-100 Hz beside a 10 Hz laser) was said to come in bursts, all
    # its intervals being under a fifth of the scans'; the delay went untimed (inside95 0.50 where it is 0.99)
    for rate in (50.0, 100.0, 1000.0):
        assert bursty_stamps(regular, np.arange(0.0, 20.0, 1.0 / rate)) == ""
    doubled = np.sort(np.concatenate([np.arange(0.0, 20.0, 0.01), np.arange(0.0, 20.0, 0.01) + 1e-4]))
    assert "odometry records come in bursts" in bursty_stamps(regular, doubled)  # (in pairs, at 100 Hz)


@pytest.mark.parametrize("true_delay", [-0.13, 0.0, 0.07])
def test_odometry_delay_is_recovered_from_turns(true_delay):
    """A trajectory that turns back and forth, seen through a laser clock that runs late (or early): the
    scan-matched heading at stamp t is the odometry's at t + true_delay."""
    rng = np.random.default_rng(4)
    odom_t = np.arange(0.0, 60.0, 0.02)
    heading = lambda t: 0.8 * np.sin(1.3 * t) + 0.4 * np.sin(3.1 * t + 1.0) + 0.05 * t  # noqa: E731
    scan_t = np.arange(1.0, 59.0, 0.2)
    matched = heading(scan_t + true_delay) + rng.normal(0, 0.005, scan_t.size)
    delay, mismatch = odometry_delay(scan_t, matched, odom_t, heading(odom_t))
    assert delay == pytest.approx(true_delay, abs=0.011)
    assert mismatch < 0.03  # rad per 0.5 s: the noise and the 0.2 s sampling
    with pytest.raises(ValueError, match="longer"):
        odometry_delay(scan_t[:3], matched[:3], odom_t, heading(odom_t))


def test_cli_eval_relations_reads_an_uppercase_npz_as_a_pose_file(tmp_path, capsys):
    rel = write(tmp_path, "r.relations", RELATION_LINES)
    npz = tmp_path / "POSES.NPZ"
    save_pose_distribution(npz, PoseDistributionFile(TRAJ.stamps, PoseSet(mean=TRAJ.poses, cov=np.zeros((3, 3, 3)))))
    assert main(["eval-relations", str(npz), str(rel)]) == 0
    assert "4 of 5 relations" in capsys.readouterr().out
    # a pose file is no log to align: refused in one sentence, not read as a CARMEN log without scans
    clf = tmp_path / "t.clf"
    write_carmen(clf, TRAJ.stamps, np.ones((3, 5)), TRAJ.poses, -1.0, 0.5, 10.0)
    assert main(["eval-relations", str(clf), str(rel), "--align-to", str(npz)]) == 2
    err = capsys.readouterr().err
    assert "POSES.NPZ: a .npz file, not a laser log" in err and err.count("\n") == 1


def test_a_stamp_exactly_tolerance_away_still_matches():
    # |-0.001 - 0.0| == 1e-3 exactly; the next stamp is 10 s away, too far to interpolate, so only the
    # inclusive tolerance ("within tolerance") can match it
    traj = Trajectory(np.array([0.0, 10.0]), np.array([[1.0, 2.0, 0.5], [9.0, 9.0, 0.0]]))
    poses, ok = poses_at(traj, np.array([-0.001]), tolerance=1e-3, max_gap=5.0)
    assert ok.tolist() == [True]
    np.testing.assert_array_equal(poses[0], [1.0, 2.0, 0.5])


def test_poses_exactly_max_gap_apart_are_interpolated():
    # "at most max_gap seconds apart": a 5 s gap with max_gap = 5 is bridged
    traj = Trajectory(np.array([0.0, 5.0]), np.array([[0.0, 0.0, 0.0], [2.0, 4.0, 1.0]]))
    poses, ok = poses_at(traj, np.array([2.5]), tolerance=1e-3, max_gap=5.0)
    assert ok.tolist() == [True]
    np.testing.assert_allclose(poses[0], [1.0, 2.0, 0.5])


def test_a_relation_file_or_log_that_is_a_fifo_or_folder_says_so(tmp_path):
    """Not "no such file": the path exists, it is no regular file (a FIFO would also wait for a writer)."""
    import os

    from slam.carmen import read_carmen

    os.mkfifo(tmp_path / "fifo.txt")
    (tmp_path / "folder.clf").mkdir()
    with pytest.raises(LogFormatError, match="is a FIFO, not a regular file; give the path of the relation file"):
        read_relations(tmp_path / "fifo.txt")
    with pytest.raises(LogFormatError, match="is a folder, not a regular file; give the path of the CARMEN log"):
        read_carmen(tmp_path / "folder.clf")
