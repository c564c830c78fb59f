"""CARMEN reader on hand-written lines (good and broken), the writer's round trip, and the real logs."""

from __future__ import annotations

import bz2
import gzip
import lzma
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_file
from slam.carmen import read_carmen, write_carmen
from slam.errors import LogFormatError

GOOD_FLASER = "FLASER 3 1.0 2.5 81.91 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5"


def write(tmp_path: Path, lines: list[str], name: str = "log.clf") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_flaser_fields_geometry_and_no_return(tmp_path):
    log = read_carmen(write(tmp_path, ["# comment", GOOD_FLASER]))
    assert len(log) == 1 and log.skipped == ()
    # 3 beams (odd): both ends of the default 180 deg are included, so the step is 90 deg
    assert log.angle_min == pytest.approx(-math.pi / 2)
    assert log.angle_increment == pytest.approx(math.pi / 2)
    assert log.range_max == 80.0
    np.testing.assert_array_equal(log.ranges[0], np.array([1.0, 2.5, np.inf], np.float32))
    np.testing.assert_allclose(log.poses[0], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(log.odometry[0], [1.1, 1.2, 1.3])
    assert log.stamps[0] == 100.5
    assert log.where.tolist() == [2]
    np.testing.assert_array_equal(log.sensor_offset, [[0.0, 0.0, 0.0]])


def test_even_beam_count_drops_one_end(tmp_path):
    log = read_carmen(write(tmp_path, ["FLASER 4 1 1 1 1 0 0 0 0 0 0 5.0 h 5.0"]))
    assert log.angle_increment == pytest.approx(math.pi / 4)
    np.testing.assert_allclose(log.beam_angles(0), [-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4])


def test_params_set_geometry_offset_and_range_max(tmp_path):
    lines = [
        "PARAM laser_front_laser_fov 90 1.0 h 1.0",
        "PARAM laser_front_laser_resolution 45 1.0 h 1.0",
        "PARAM robot_front_laser_max 2.0 1.0 h 1.0",
        "PARAM robot_frontlaser_offset 0.25 1.0 h 1.0",
        GOOD_FLASER,
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.angle_min == pytest.approx(-math.pi / 4)
    assert log.angle_increment == pytest.approx(math.pi / 4)
    assert log.range_max == 2.0
    # 2.5 >= 2.0 is a max reading now
    np.testing.assert_array_equal(log.ranges[0], np.array([1.0, np.inf, np.inf], np.float32))
    np.testing.assert_allclose(log.sensor_offset, [[0.25, 0.0, 0.0]])
    assert log.params["robot_frontlaser_offset"] == "0.25"


def test_what_the_reader_assumes_of_silent_flaser_lines_is_noted_with_the_param_that_says_it(tmp_path):
    """A probe's finding: FLASER lines of a 1081-beam laser in a log with no PARAMs were read as sweeping 180 deg,
    and a 4 m laser's no-return readings (written as 4.0) as walls under the 80 m default: grid FastSLAM was then
    confidently wrong (NEES 501 and 223), with no word, though docs/gridslam.md says the readers note what they take
    for granted. Each assumption is now a note naming the PARAM line that would say otherwise."""
    rng = np.random.default_rng(3)
    lines = []
    for t in range(20):
        ranges = np.where(rng.random(9) < 0.4, 4.0, rng.uniform(0.5, 4.01, 9))
        lines.append(f"FLASER 9 {' '.join(f'{r:.3f}' for r in ranges)} 0 0 0 0 0 0 {t}.0 host {t}.0")
    notes = read_carmen(write(tmp_path, lines)).notes
    assert len(notes) == 2
    assert "(9 beams a line) are taken to sweep 180 deg" in notes[0]
    assert "'PARAM laser_front_laser_fov DEG'" in notes[0]
    assert "maximum range is taken as 80 m" in notes[1] and "'PARAM robot_front_laser_max 4'" in notes[1]
    said = read_carmen(write(tmp_path, ["PARAM laser_front_laser_fov 270 1.0 h 1.0", *lines], "fov.clf")).notes
    assert len(said) == 1 and "taken as 80 m" in said[0]
    params = ["PARAM laser_front_laser_fov 270 1.0 h 1.0", "PARAM robot_front_laser_max 4.0 1.0 h 1.0"]
    assert read_carmen(write(tmp_path, [*params, *lines], "both.clf")).notes == ()
    spread = [GOOD_FLASER.replace("100.5", f"{100.5 + t}") for t in range(5)]  # no reading stands out: no guess
    assert "to the log" not in read_carmen(write(tmp_path, spread, "spread.clf")).notes[1]


def test_broken_lines_are_skipped_with_line_numbers_and_never_shift(tmp_path):
    lines = [
        GOOD_FLASER,  # 1
        "FLASER 3 1.0 2.5 0.1 0.2 0.3 1.1 1.2 1.3 101.0 host 1.0",  # 2: a range is missing
        "FLASER 3 1.0 abc 3.0 0.1 0.2 0.3 1.1 1.2 1.3 102.0 host 2.0",  # 3: not a number
        "FLASER 3 1.0 nan -inf 0.1 0.2 0.3 1.1 1.2 1.3 103.0 host 3.0",  # 4: NaN, -inf: no reading, kept
        "FLASER 3 1.0 -2 3.0 0.1 0.2 0.3 1.1 1.2 1.3 104.0 host 4.0",  # 5: negative range
        "FLASER x 1.0 2.0 3.0 0.1 0.2 0.3 1.1 1.2 1.3 105.0 host 5.0",  # 6: beam count not an integer
        "FLASER 4 1.0 2.0 3.0 4.0 0.1 0.2 0.3 1.1 1.2 1.3 106.0 host 6.0",  # 7: another beam count: kept
        "FLASER 3 1.0 2.0 3.0 0.1 0.2 inf 1.1 1.2 1.3 107.0 host 7.0",  # 8: pose not finite
        "ODOM 1 2 3 0 0 0 108.0 host",  # 9: ODOM one field short
        "PARAM lonely",  # 10: PARAM without a value
        "FLASER 3 4.0 5.0 6.0 7.1 7.2 7.3 8.1 8.2 8.3 109.0 host 9.0",  # 11: good
        "FLASER",  # 12: nothing
        "",
        "NEFF 12",  # another record type: passed over
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [1, 4, 7, 11]
    assert [s.where for s in log.skipped] == [2, 3, 5, 6, 8, 9, 10, 12]
    reasons = {s.where: s.reason for s in log.skipped}
    assert "needs 14 fields, has 13" in reasons[2]
    assert "'abc' is not a number" in reasons[3]
    assert "range 2 is -2.0" in reasons[5]
    assert reasons[9].startswith("ODOM")
    # a probe: one NaN beam (an invalid reading, REP 117) dropped its whole scan; 2 % of such beams lost 404 of 420
    np.testing.assert_array_equal(log.ranges[1, :3], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(log.ranges[3, :3], [4.0, 5.0, 6.0])
    np.testing.assert_allclose(log.poses[3], [7.1, 7.2, 7.3])
    np.testing.assert_allclose(log.odometry[3], [8.1, 8.2, 8.3])
    assert log.stamps.tolist() == [100.5, 103.0, 106.0, 109.0]
    # the 4-beam scan keeps its own count (its step follows from it: 180 / 4 deg), the others theirs
    assert log.beams.tolist() == [3, 3, 4, 3]
    assert log.angle_increment == pytest.approx([math.pi / 2, math.pi / 2, math.pi / 4, math.pi / 2])
    assert np.isnan(log.ranges[0, 3]) and log.scan_ranges(0).tolist() == [1.0, 2.5, np.inf]
    summary = log.skipped_summary(limit=2)
    assert "skipped 8 lines" in summary and "line 2:" in summary and "and 6 more" in summary


def robotlaser(
    start=-1.0,
    res=1.0,
    max_range=10.0,
    ranges=(1.0, 2.0, 12.0),
    remissions=(),
    laser=(1.0, 2.3, math.pi / 2),
    robot=(1.0, 2.0, math.pi / 2),
    stamp=50.25,
) -> str:
    fields = [
        "ROBOTLASER1",
        "0",
        start,
        2.0,
        res,
        max_range,
        0.01,
        0,
        len(ranges),
        *ranges,
        len(remissions),
        *remissions,
        *laser,
        *robot,
        0,
        0,
        0,
        0,
        0,
        stamp,
        "host",
        0.5,
    ]
    return " ".join(str(f) for f in fields)


def test_robotlaser_fields_and_offset(tmp_path):
    log = read_carmen(write(tmp_path, [robotlaser(remissions=(0.5, 0.7, 0.9))]))
    assert log.skipped == ()
    assert log.angle_min == -1.0 and log.angle_increment == 1.0 and log.range_max == 10.0
    np.testing.assert_array_equal(log.ranges[0], np.array([1.0, 2.0, np.inf], np.float32))
    np.testing.assert_allclose(log.odometry[0], [1.0, 2.0, math.pi / 2])
    # the laser is 0.3 m along world +y from a robot facing +y: 0.3 m ahead in the robot frame
    np.testing.assert_allclose(log.sensor_offset, [[0.3, 0.0, 0.0]], atol=1e-12)
    assert log.stamps[0] == 50.25


def test_robotlaser_preferred_over_flaser_and_each_line_keeps_its_geometry(tmp_path):
    lines = [
        GOOD_FLASER,
        robotlaser(),
        robotlaser(res=0.5),
        robotlaser(ranges=(1.0, 2.0)),
        robotlaser(remissions=(1.0,))[:-4],
        robotlaser(res=0.0),  # every beam one way: unusable in itself
        robotlaser(start=7.0),  # beyond a full turn
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [2, 3, 4]
    assert log.angle_increment.tolist() == [1.0, 0.5, 1.0] and log.beams.tolist() == [3, 3, 2]
    np.testing.assert_allclose(log.beam_angles(1), [-1.0, -0.5, 0.0])
    reasons = {s.where: s.reason for s in log.skipped}
    assert set(reasons) == {5, 6, 7}
    assert "needs 28 fields, has 27" in reasons[5]
    assert "angle_increment is 0 for 3 beams" in reasons[6]
    assert "beyond a full turn" in reasons[7]


def test_gzip_and_truncated_gzip(tmp_path):
    lines = [GOOD_FLASER.replace("100.5", f"{100 + i}") for i in range(2000)]
    text = ("\n".join(lines) + "\n").encode()
    full = tmp_path / "log.gz"
    full.write_bytes(gzip.compress(text))
    log = read_carmen(full)
    assert len(log) == 2000 and log.skipped == ()
    cut = tmp_path / "cut.gz"
    blob = gzip.compress(text)
    cut.write_bytes(blob[: len(blob) // 2])
    log = read_carmen(cut)
    assert 0 < len(log) < 2000
    assert len(log.skipped) == 1 and "truncated or corrupt" in log.skipped[0].reason
    # every scan that was read is whole and in order
    np.testing.assert_array_equal(log.stamps, 100 + np.arange(len(log)))


def test_unusable_inputs_raise_log_format_error(tmp_path):
    with pytest.raises(LogFormatError, match="no such file"):
        read_carmen(tmp_path / "missing.clf")
    with pytest.raises(LogFormatError, match=r"no usable front laser scan.*line 1"):
        read_carmen(write(tmp_path, ["FLASER 3 1 2", "ODOM 0 0 0 0 0 0 1 h 1"]))
    with pytest.raises(LogFormatError, match="not a number"):
        read_carmen(write(tmp_path, ["PARAM robot_front_laser_max big 0 h 0", GOOD_FLASER]))
    (tmp_path / "binary.clf").write_bytes(bytes(range(256)) * 10)
    with pytest.raises(LogFormatError):
        read_carmen(tmp_path / "binary.clf")


@pytest.mark.parametrize(
    ("pack", "said"),
    [
        (bz2.compress, r"compressed with bzip2, and only gzip is read: unpack it first \(bunzip2\)"),
        (lzma.compress, r"compressed with xz, .* \(unxz\)"),
        (lambda data: gzip.compress(gzip.compress(data)), r"compressed with gzip twice, .* \(gunzip\)"),
        (lambda data: data.decode().encode("utf-16"), "UTF-16 text, and a CARMEN log is ASCII"),
        (lambda data: data.decode().encode("utf-16-le"), "UTF-16 text, and a CARMEN log is ASCII"),
        (
            lambda data: gzip.compress(bz2.compress(data)),
            r"compressed with gzip around bzip2, .* \(gunzip, then bunzip2\)",
        ),
        (lambda data: b"", "empty, so no CARMEN log"),
        (lambda data: gzip.compress(b""), "empty once gunzipped, so no CARMEN log"),
        (lambda data: data[:40] + bytes(range(256)), r"not a text file \(a NUL byte in its first 296 bytes\)"),
    ],
)
def test_a_log_in_a_form_not_read_says_what_it_is(tmp_path, pack, said):
    """A log compressed with another tool than gzip, compressed twice, in UTF-16 or not text at all is named as
    what it is (with how to unpack it), not as a log without laser lines."""
    path = tmp_path / "log.clf"
    path.write_bytes(pack((GOOD_FLASER + "\n").encode()))
    with pytest.raises(LogFormatError, match=f"^{path}: {said}"):
        read_carmen(path)


def test_odom_stream_kept_in_file_order(tmp_path):
    lines = ["ODOM 1 2 0.5 0 0 0 10.0 h 10.0", GOOD_FLASER, "ODOM 3 4 0.6 0 0 0 0 h 0"]
    log = read_carmen(write(tmp_path, lines))
    assert log.odom_stamps.tolist() == [10.0, 0.0]
    np.testing.assert_allclose(log.odom_poses, [[1, 2, 0.5], [3, 4, 0.6]])


@pytest.mark.parametrize("record,suffix", [("ROBOTLASER1", ".clf"), ("FLASER", ".gz")])
def test_writer_round_trip(tmp_path, record, suffix):
    rng = np.random.default_rng(4)
    steps, beams = 7, 9
    ranges = rng.uniform(0.2, 7.9, (steps, beams))
    ranges[0, 3] = np.inf
    ranges[2, 0] = np.nan
    ranges[4, 8] = 9.5  # beyond range_max
    odometry = np.column_stack([rng.normal(size=(steps, 2)) * 10, rng.uniform(-3, 3, steps)])
    stamps = 1000.0 + np.cumsum(rng.uniform(0.1, 0.3, steps))
    offset = np.array([0.2, 0.0, 0.0]) if record == "FLASER" else np.array([0.2, -0.1, 0.05])
    angle_min, step = -math.radians(60.0), math.radians(15.0)
    path = tmp_path / f"sim{suffix}"
    write_carmen(path, stamps, ranges, odometry, angle_min, step, 8.0, offset, record=record)
    log = read_carmen(path)
    assert len(log) == steps and log.skipped == ()
    assert log.angle_min == pytest.approx(angle_min) and log.angle_increment == pytest.approx(step)
    assert (log.range_max == 8.0).all()
    np.testing.assert_allclose(log.stamps, stamps, atol=1e-6)
    np.testing.assert_allclose(log.odometry, odometry, atol=1e-6)
    np.testing.assert_allclose(log.sensor_offset, np.tile(offset, (steps, 1)), atol=1e-5)
    expected = np.where(np.isfinite(ranges) & (ranges < 8.0), ranges, np.inf)
    np.testing.assert_allclose(log.ranges, expected, atol=1e-5)


def test_writer_rejects_flaser_with_sideways_laser(tmp_path):
    with pytest.raises(ValueError, match="x axis"):
        write_carmen(
            tmp_path / "x.clf",
            np.zeros(1),
            np.ones((1, 3)),
            np.zeros((1, 3)),
            -1.0,
            1.0,
            5.0,
            np.array([0.0, 0.1, 0.0]),
            record="FLASER",
        )


def test_real_mit_csail_clf():
    log = read_carmen(shared_file("mit-csail", "mit-csail.clf"))
    assert log.ranges.shape == (1988, 361) and log.skipped == ()
    assert log.angle_increment == pytest.approx(math.pi / 360)
    np.testing.assert_allclose(log.poses[0], [576.536523, 0.106594, -2.255213])
    assert log.stamps[0] == pytest.approx(1134864629.895182, abs=1e-6)
    assert np.isinf(log.ranges).any() and np.nanmin(log.ranges) == pytest.approx(0.27, abs=1e-6)


@pytest.mark.parametrize(
    "name,scans,beams,odom,offset,stepped_back",
    [
        ("intel-lab/intel-corrected.log.gz", 906, 180, 14541, 0.0, [5647, 10805, 11190, 12936]),
        ("fr079/freiburg-079-corrected.log.gz", 4791, 360, 9725, -0.04, []),
    ],
)
def test_real_corrected_logs(name, scans, beams, odom, offset, stepped_back):
    """The corrected Intel log's clock steps back at 4 of its 910 scans (by 0.05 to 0.86 s): those are skipped."""
    log = read_carmen(shared_file(name))
    assert log.ranges.shape == (scans, beams) and [s.where for s in log.skipped] == stepped_back
    assert np.all(np.diff(log.stamps) > 0)
    assert len(log.odom_stamps) == odom
    assert log.sensor_offset[:, 0] == pytest.approx(offset)
    # corrected logs repeat the pose: x y theta equals odom_*
    np.testing.assert_array_equal(log.poses, log.odometry)


def test_poses_and_ranges_beyond_the_pose_limit_are_skipped(tmp_path):
    # finite but absurd values (1e300 m) once made grid FastSLAM overflow and hang (schemas.messages.POSE_LIMIT)
    lines = [
        GOOD_FLASER,
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1e300 1.2 1.3 101.0 host 1.0",  # odometry x
        "FLASER 3 1.0 2e7 3.0 0.1 0.2 0.3 1.1 1.2 1.3 102.0 host 2.0",  # a range
        "ODOM 1 2e300 0.5 0 0 0 103.0 h 103.0",
        "FLASER 3 1.0 2.5 inf 0.1 0.2 0.3 1.1 1.2 1.3 104.0 host 4.0",  # inf: no return, kept
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [1, 5] and len(log.odom_stamps) == 0
    reasons = {s.where: s.reason for s in log.skipped}
    assert "odometry pose is not finite or beyond +-1e+07" in reasons[2]
    assert "range 2 is 20000000.0, expected a number in [0, 1e+07] m, inf or nan" in reasons[3]
    assert reasons[4].startswith("ODOM") and "beyond +-1e+07" in reasons[4]


def test_a_flaser_line_with_a_field_too_many_is_skipped_not_shifted(tmp_path):
    lines = [
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5",  # 1: good
        "FLASER 3 1.0 2.5 3.0 4.0 0.1 0.2 0.3 1.1 1.2 1.3 101.5 host 1.5",  # 2: four ranges under "3"
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [1]
    assert [s.where for s in log.skipped] == [2]
    assert "needs 14 fields, has 15" in log.skipped[0].reason


def test_the_rear_laser_faces_backwards(tmp_path):
    lines = [
        "PARAM robot_rearlaser_offset -0.2 0 host 0",
        "RLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5",
        "FLASER 3 9.0 9.0 9.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5",  # the front laser: not read
    ]
    log = read_carmen(write(tmp_path, lines), laser="rear")
    assert log.where.tolist() == [2]
    np.testing.assert_allclose(log.sensor_offset, [[-0.2, 0.0, math.pi]])
    np.testing.assert_array_equal(log.ranges[0], [1.0, 2.0, 3.0])


def test_robotlaser_offset_is_the_median_over_the_scans(tmp_path):
    # laser 0.9 m ahead in the first scan (an outlier), 0.3 m in the two others: the median is 0.3
    lines = [
        robotlaser(ranges=(1.0, 2.0, 3.0), laser=(0.9, 0.0, 0.0), robot=(0.0, 0.0, 0.0), stamp=1.0),
        robotlaser(ranges=(1.0, 2.0, 3.0), laser=(1.3, 0.0, 0.0), robot=(1.0, 0.0, 0.0), stamp=2.0),
        robotlaser(ranges=(1.0, 2.0, 3.0), laser=(2.3, 0.0, 0.0), robot=(2.0, 0.0, 0.0), stamp=3.0),
    ]
    log = read_carmen(write(tmp_path, lines))
    assert len(log) == 3
    np.testing.assert_allclose(log.sensor_offset, [[0.3, 0.0, 0.0]] * 3, atol=1e-12)


def test_a_non_positive_flaser_resolution_is_a_log_format_error(tmp_path):
    lines = [
        "PARAM laser_front_laser_resolution 0 0 host 0",
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5",
    ]
    with pytest.raises(LogFormatError, match="resolution and maximum range must be positive"):
        read_carmen(write(tmp_path, lines))


def test_a_scan_with_a_non_finite_stamp_is_skipped(tmp_path):
    lines = [
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5",
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1.1 1.2 1.3 nan host 1.5",
        "FLASER 3 1.0 2.5 3.0 0.1 0.2 0.3 1.1 1.2 1.3 inf host 2.5",
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [1]
    assert [(s.where, "timestamp is not finite" in s.reason) for s in log.skipped] == [(2, True), (3, True)]


def test_rawlaser_lines_are_placed_by_the_odom_lines(tmp_path):
    """A log of RAWLASER1 and ODOM lines only (the laser and the base logged apart): each scan keeps its own geometry,
    takes the odometry interpolated at its stamp, and the laser sits where the PARAMs put it; a scan beyond the
    odometry's span is skipped with the reason."""
    raw = "RAWLASER1 0 -1.5 3.0 0.5 20.0 0.01 0 {n} {ranges} 0 {stamp} host {stamp}"
    lines = [
        "PARAM robot_frontlaser_offset 0.25 0 host 0",
        "PARAM robot_frontlaser_side_offset -0.05 0 host 0",
        *(f"ODOM {t} 0 {0.1 * t} 0 0 0 {t} host {t}" for t in range(4)),
        raw.format(n=7, ranges=" ".join(["2.0"] * 7), stamp=0.5),
        raw.format(n=7, ranges="1 2 3 4 5 6 25", stamp=1.25),
        raw.replace("-1.5 3.0", "-1.25 2.5").format(n=6, ranges=" ".join(["3.0"] * 6), stamp=2.5),
        raw.format(n=7, ranges=" ".join(["2.0"] * 7), stamp=9.0),
    ]
    log = read_carmen(write(tmp_path, lines))
    assert log.where.tolist() == [7, 8, 9]
    np.testing.assert_allclose(log.odometry, [[0.5, 0, 0.05], [1.25, 0, 0.125], [2.5, 0, 0.25]], atol=1e-12)
    np.testing.assert_allclose(log.poses, log.odometry)
    np.testing.assert_allclose(log.sensor_offset, [[0.25, -0.05, 0.0]] * 3)
    assert log.beams.tolist() == [7, 7, 6] and log.angle_min.tolist() == [-1.5, -1.5, -1.25]
    assert log.ranges[1, 6] == np.inf  # (beyond the 20 m maximum: no return)
    ((where, reason),) = [(s.where, s.reason) for s in log.skipped]
    assert where == 10 and "RAWLASER1: 6 s outside the odometry's time span" in reason
    with pytest.raises(LogFormatError, match="its 1 RAWLASER1 lines carry no pose, and it has no ODOM line"):
        read_carmen(write(tmp_path, [raw.format(n=1, ranges="2.0", stamp=0.5)], name="noodom.clf"))


def test_a_log_of_another_lasers_lines_only_says_which_it_has(tmp_path):
    lines = ["RLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 1.1 1.2 1.3 100.5 host 0.5"] * 2
    with pytest.raises(LogFormatError, match=r"no usable front laser scan .*; it has 2 RLASER lines, not read as the"):
        read_carmen(write(tmp_path, lines))


def test_a_utf8_byte_order_mark_hides_no_line(tmp_path):
    """Some editors start a UTF-8 file with a byte order mark: the first line (here the PARAM that places the laser)
    is read as it is, not passed over as an unknown record."""
    path = tmp_path / "bom.clf"
    path.write_bytes(b"\xef\xbb\xbfPARAM robot_frontlaser_offset 0.2 0 host 0\n" + (GOOD_FLASER + "\n").encode())
    log = read_carmen(path)
    assert log.params == {"robot_frontlaser_offset": "0.2"} and log.sensor_offset.tolist() == [[0.2, 0.0, 0.0]]


def test_a_rear_lasers_angular_offset_param_is_its_heading_as_carmen_takes_it(tmp_path):
    raw = "RAWLASER2 0 -1.5 3.0 0.5 20.0 0.01 0 7 2 2 2 2 2 2 2 0 {stamp} host {stamp}"
    lines = ["PARAM robot_rearlaser_offset -0.2 0 host 0", "PARAM robot_rearlaser_angular_offset 3.1 0 host 0"]
    lines += [f"ODOM {t} 0 0 0 0 0 {t} host {t}" for t in range(3)] + [raw.format(stamp=0.5), raw.format(stamp=1.5)]
    np.testing.assert_allclose(read_carmen(write(tmp_path, lines), laser="rear").sensor_offset, [[-0.2, 0, 3.1]] * 2)
    np.testing.assert_allclose(
        read_carmen(write(tmp_path, lines[:1] + lines[2:]), laser="rear").sensor_offset[0], [-0.2, 0, math.pi]
    )


def test_a_logs_beams_with_no_return_are_noted_by_what_they_clear(tmp_path):
    """A real log's beams with no return say nothing by default: the note gives their share and the farthest return,
    and how to let them clear. Let clear (--no-return-range) more than 1.5 times the farthest return, they get a
    warning that they clear through whatever they met; within that, nothing is said, nor for a log whose every beam
    returned."""
    import dataclasses

    from bench.gridslam import write_sim_log
    from slam.gridslam.simlogs import sim_log
    from slam.laserlog import no_return_note

    write_sim_log(sim_log("room", 1), tmp_path / "room.clf")
    log = read_carmen(tmp_path / "room.clf")
    ranges = log.ranges.copy()
    ranges[:, ::10] = np.inf  # every 10th beam: no return
    farthest = float(ranges[np.isfinite(ranges)].max())
    stated = dataclasses.replace(log, ranges=ranges, range_max=np.full(len(log), 80.0))
    share = 100.0 * np.isinf(ranges).sum() / ranges.size
    said = no_return_note(stated, 0.0)
    assert said is not None
    assert f"{share:.1f} % of its beams have no return; they clear no free space" in said
    assert f"its farthest return is {farthest:.1f} m" in said and "--no-return-range METRES" in said
    assert no_return_note(stated, 1.5 * farthest) is None
    said = no_return_note(stated, 1.6 * farthest)
    assert said is not None and f"clears free space out to {1.6 * farthest:g} m" in said
    said = no_return_note(stated, 500.0)  # (the laser's stated range bounds it)
    assert said is not None and "out to 80 m" in said and f"returned at most {farthest:.1f} m" in said
    said = no_return_note(stated, 50.0, 30.0)  # (and grid FastSLAM's --max-range: a probe was told 50 m for 30)
    assert said is not None and "out to 30 m (--max-range)" in said
    assert "(--max-range)" not in (no_return_note(stated, 25.0, 30.0) or "")
    assert no_return_note(dataclasses.replace(stated, ranges=np.minimum(log.ranges, 0.9 * farthest)), 0.0) is None


@pytest.mark.parametrize("clears", [None, 80.0])
def test_posegrid_source_notes_the_real_logs_beams_with_no_return(capsys, clears):
    """The corrected Intel log states 80 m (the reader's default: no PARAM gives it), returns at most 25.4 m, and
    2.6 % of its beams have no return: the source says so before it publishes (`posegrid run` through its source),
    and warns when they are let clear to 80 m."""
    import argparse

    from services.commands.pipeline import _laser_log

    args = argparse.Namespace(
        carmen=shared_file("intel-lab", "intel-corrected.log.gz"),
        bag=None,
        scan_topic=None,
        odom_delay=0.0,
        no_return_range=clears,
    )
    _laser_log(args, "source")
    said = [line for line in capsys.readouterr().err.splitlines() if "beams have no return" in line]
    expected = (
        f"posegrid source: note: {args.carmen}: 2.6 % of its beams have no return; they clear no free space (a laser "
        "misses dark and glancing surfaces close by too), and --no-return-range METRES lets them clear up to METRES "
        "(its farthest return is 25.4 m)"
        if clears is None
        else f"posegrid source: note: {args.carmen}: its laser returned at most 25.4 m, and 2.6 % of its beams have "
        "no return: with --no-return-range 80 each of those clears free space out to 80 m, through whatever the "
        "beam met (docs/sensor_model.md, section 3)"
    )
    assert said == [expected]
