"""The UTIAS MRCLAM reader (slam.mrclam) on hand-written samples and, when present, on dataset 7."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import DATA as SHARED_DATA
from slam.calibration import MRCLAM7, Calibration
from slam.errors import LogFormatError
from slam.mrclam import (
    find_robots,
    is_mrclam_folder,
    mrclam_sequence,
    read_mrclam,
    read_sequence,
    read_table,
)

DATA = SHARED_DATA / "mrclam7"

HEADER = (
    "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\r\n"
    "# produced by Keith Leung (keith.leung@robotics.utias.utoronto.ca) 2009\r\n"
    "# {what} Data Fomat:\r\n"
    "# {columns} \r\n"
)


def _write(folder: Path, name: str, what: str, columns: str, rows: list[tuple]) -> None:
    lines = [" \t ".join(str(v) for v in row) + " \r\n" for row in rows]
    (folder / name).write_text(HEADER.format(what=what, columns=columns) + "".join(lines), newline="")


@pytest.fixture()
def sample(tmp_path: Path) -> Path:
    _write(tmp_path, "Barcodes.dat", "Barcode", "Subject #    Barcode #", [(1, 5), (2, 14), (6, 63), (7, 81)])
    _write(
        tmp_path,
        "Landmark_Groundtruth.dat",
        "Landmark Groundtruth",
        "Subject #    x [m]    y [m]    x std-dev [m]    y std-dev [m]",
        [(6, 1.0, 2.0, 0.001, 0.001), (7, -1.0, 0.5, 0.001, 0.001)],
    )
    _write(
        tmp_path,
        "Robot1_Odometry.dat",
        "Odometry",
        "Time [s]    forward velocity [m/s]    angular velocity[rad/s]",
        [(100.05, 0.5, 0.0), (100.25, 0.0, 0.2), (100.45, 0.1, -0.1)],
    )
    _write(
        tmp_path,
        "Robot1_Measurement.dat",
        "Measurement",
        "Time [s]    Subject #    range [m]    bearing [rad]",
        [(100.1, 63, 2.0, 0.1), (100.1, 14, 3.0, 0.0), (100.3, 81, 1.5, -0.2), (100.3, 34, 1.0, 0.0)],
    )
    _write(
        tmp_path,
        "Robot1_Groundtruth.dat",
        "Robot Groundtruth",
        "Time [s]    x [m]    y [m]    orientation [rad]",
        [(100.0, 0.5, 0.25, 0.1), (100.5, 0.7, 0.25, 0.15)],
    )
    return tmp_path


def test_reader_maps_barcodes_and_counts_skipped(sample):
    assert is_mrclam_folder(sample) and find_robots(sample) == [1]
    run = read_mrclam(sample, 1)
    # barcode 63 -> subject 6, 81 -> 7; barcode 14 is robot 2; barcode 34 is in no table
    np.testing.assert_array_equal(run.subjects, [6, 7])
    np.testing.assert_allclose(run.measurements, [[100.1, 2.0, 0.1], [100.3, 1.5, -0.2]])
    assert run.skipped_robots == 1 and run.skipped_unknown == 1
    np.testing.assert_allclose(run.odometry[:, 1], [0.5, 0.0, 0.1])
    np.testing.assert_allclose(run.groundtruth[0], [100.0, 0.5, 0.25, 0.1])
    np.testing.assert_allclose(run.landmark_truth, [[6, 1.0, 2.0], [7, -1.0, 0.5]])


def test_sequence_steps_controls_and_measurements_by_hand(sample):
    run = read_mrclam(sample, 1)
    seq = mrclam_sequence(run, period=0.2, command_delay=0.0)
    seq.validate("sample")
    # start at the first ground truth (100.0, pose 0.5, 0.25, 0.1); steps: the 0.2 s grid and the two measurement stamps
    np.testing.assert_allclose(seq.initial_pose, [0.5, 0.25, 0.1])
    np.testing.assert_allclose(seq.stamps, [100.0, 100.1, 100.2, 100.3, 100.4])
    # the commands, held from their stamps, cut at every step: zero before 100.05, then 0.5 m/s until 100.25 ...
    expected = [
        [],
        [[0.0, 0.0, 0.05], [0.5, 0.0, 0.05]],
        [[0.5, 0.0, 0.1]],
        [[0.5, 0.0, 0.05], [0.0, 0.2, 0.05]],
        [[0.0, 0.2, 0.1]],
    ]
    for t, rows in enumerate(expected):
        got = seq.controls[seq.control_ptr[t] : seq.control_ptr[t + 1]]
        np.testing.assert_allclose(got.reshape(-1, 3), np.array(rows).reshape(-1, 3), atol=1e-9)
    np.testing.assert_array_equal(np.diff(seq.measurement_ptr), [0, 1, 0, 1, 0])
    np.testing.assert_array_equal(seq.landmark_ids, [6, 7])


def test_velocity_scale_multiplies_v_and_w_only_and_the_bias_moves_only_moving_commands(sample):
    run = read_mrclam(sample, 1)
    raw = mrclam_sequence(run, period=0.2)
    scaled = Calibration(velocity_scale=(0.5, 2.0)).apply(raw)
    np.testing.assert_allclose(scaled.controls, raw.controls * [0.5, 2.0, 1.0])
    np.testing.assert_array_equal(scaled.control_ptr, raw.control_ptr)
    biased = Calibration(velocity_bias=(0.0, -0.01)).apply(raw).controls
    moving = (raw.controls[:, 0] != 0.0) | (raw.controls[:, 1] != 0.0)
    assert not moving.all() and moving.any()  # the sample stands still before its first command
    np.testing.assert_allclose(biased[:, 1], np.where(moving, raw.controls[:, 1] - 0.01, 0.0))


def test_command_delay_and_initial_pose(sample):
    run = read_mrclam(sample, 1)
    seq = mrclam_sequence(run, initial_pose=np.array([1.0, 2.0, 0.5]), period=0.2, command_delay=0.1)
    np.testing.assert_allclose(seq.initial_pose, [1.0, 2.0, 0.5])
    assert seq.stamps[0] == pytest.approx(100.05)  # the first odometry stamp
    total = seq.controls[:, 2].sum()
    assert total == pytest.approx(seq.stamps[-1] - seq.stamps[0])
    # the 0.5 m/s command now runs from 100.15 to 100.35
    moving = seq.controls[seq.controls[:, 0] == 0.5]
    assert moving[:, 2].sum() == pytest.approx(0.2)


def test_range_calibration_and_bearing_bias_by_hand():
    z = Calibration(range_calibration=(1.0, -0.4)).correct_measurements(np.array([[2.0, 0.0], [2.0, 0.5]]))
    np.testing.assert_allclose(z, [[2.0, 0.0], [2.0 / 0.9, 0.5]])
    # the bias comes off the bearing first; the range factor is taken at the corrected bearing
    z = Calibration(range_calibration=(1.1, -0.4), bearing_bias=0.1).correct_measurements(np.array([[2.0, 0.6]]))
    np.testing.assert_allclose(z, [[2.0 / (1.1 - 0.4 * 0.25), 0.5]])


def test_reading_gives_the_data_as_logged_and_the_profile_corrects_them(sample):
    """No dataset's calibration is a default: the reader gives the file's values; profile mrclam7 gives them
    delayed by 0.2 s, scaled to the executed speeds (0.918, 0.958) and the ranges divided by 1.033 - 0.46 b^2."""
    _, logged = read_sequence(sample, 1)
    _, corrected = read_sequence(sample, 1, MRCLAM7)
    np.testing.assert_allclose(logged.measurements, [[2.0, 0.1], [1.5, -0.2]])  # as in Robot1_Measurement.dat
    np.testing.assert_allclose(
        corrected.measurements, [[2.0 / (1.033 - 0.46 * 0.1**2), 0.1], [1.5 / (1.033 - 0.46 * 0.2**2), -0.2]]
    )
    np.testing.assert_array_equal(corrected.stamps, logged.stamps)
    # as logged: 0.5 m/s from 100.05 s; corrected: from 100.25 s, at 0.918 x 0.5 m/s
    first = lambda seq: seq.controls[seq.controls[:, 0] > 0][0, 0]  # noqa: E731
    start = lambda seq: 100.0 + seq.controls[: np.argmax(seq.controls[:, 0] > 0), 2].sum()  # noqa: E731
    assert first(logged) == 0.5 and start(logged) == pytest.approx(100.05)
    assert first(corrected) == pytest.approx(0.918 * 0.5) and start(corrected) == pytest.approx(100.25)
    # the 0.5 m/s command is held 100.05-100.25 s as logged, and from 100.25 s to the last step (100.4 s) corrected
    held = lambda seq: seq.controls[seq.controls[:, 0] > 0, 2].sum()  # noqa: E731
    assert held(logged) == pytest.approx(0.2) and held(corrected) == pytest.approx(0.15)


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("100.5 \t 0.1\r\n", "line 8: expected 3 numbers"),
        ("100.5 \t abc \t 0.1\r\n", "line 8: expected 3 numbers"),
        ("100.5 \t nan \t 0.1\r\n", "line 8: a value is NaN or inf"),
        ("99.0 \t 0.1 \t 0.1\r\n", "line 8: time 99.0 s is earlier"),
        # velocities no robot has: 1e300 overflowed the filters into NaN poses blamed on the output file
        ("100.5 \t 1e300 \t 0.1\r\n", r"line 8: forward velocity 1e\+300 m/s is beyond \+-1000 m/s"),
        ("100.5 \t 0.1 \t -2e3\r\n", r"line 8: angular velocity -2000 rad/s is beyond \+-1000 rad/s"),
    ],
)
def test_bad_lines_name_file_and_line(sample, line, message):
    path = sample / "Robot1_Odometry.dat"
    path.write_bytes(path.read_bytes() + line.encode("ascii"))
    with pytest.raises(LogFormatError, match=message) as info:
        read_mrclam(sample, 1)
    assert "Robot1_Odometry.dat" in str(info.value) and "\n" not in str(info.value)


def test_missing_robot_and_files(sample):
    with pytest.raises(LogFormatError, match=r"no Robot3_Odometry\.dat"):
        read_mrclam(sample, 3)
    (sample / "Robot1_Measurement.dat").unlink()
    with pytest.raises(LogFormatError, match=r"Robot1_Measurement\.dat: no such file"):
        read_mrclam(sample, 1)
    with pytest.raises(LogFormatError, match="holds no data lines"):
        (sample / "empty.dat").write_text("# nothing\n")
        read_table(sample / "empty.dat", "Odometry")


def test_no_ground_truth_needs_an_initial_pose(sample):
    (sample / "Robot1_Groundtruth.dat").unlink()
    run = read_mrclam(sample, 1)
    assert run.groundtruth is None
    with pytest.raises(LogFormatError, match="initial pose"):
        mrclam_sequence(run)


@pytest.mark.skipif(not DATA.is_dir(), reason="MRCLAM dataset 7 not present (../shared/data/mrclam7)")
def test_dataset7_counts():
    run = read_mrclam(DATA, 1)
    assert len(run.odometry) == 58_598 and len(run.measurements) + run.skipped_robots == 3_228
    assert run.skipped_robots == 650 and run.skipped_unknown == 0
    assert set(np.unique(run.subjects)) <= set(range(6, 21))
    assert read_mrclam(DATA, 3).skipped_unknown == 9  # barcodes 34 and 52 are in no table
    seq = mrclam_sequence(run)
    seq.validate(str(DATA))
    assert seq.controls[:, 2].sum() == pytest.approx(seq.stamps[-1] - seq.stamps[0])
    assert np.diff(seq.stamps).max() <= 0.2 + 1e-6  # stamps near 1.2e9 s carry about 1e-7 s of rounding


def test_measurements_with_no_range_or_no_bearing_are_skipped_and_counted(sample):
    """A landmark seen at a range <= 0 m or a bearing beyond a full turn is no measurement: skipped, counted."""
    path = sample / "Robot1_Measurement.dat"
    path.write_text(
        path.read_text() + "100.35 \t 63 \t -2.0 \t 0.1\r\n100.4 \t 81 \t 0.0 \t 0.0\r\n"
        "100.4 \t 63 \t 1.0 \t 7.0\r\n100.4 \t 81 \t 1.2 \t -6.0\r\n",
        newline="",
    )
    run = read_mrclam(sample, 1)
    assert run.skipped_invalid == 3
    np.testing.assert_allclose(run.measurements, [[100.1, 2.0, 0.1], [100.3, 1.5, -0.2], [100.4, 1.2, -6.0]])


def test_measurements_outside_the_odometry_are_skipped_and_counted(sample):
    # odometry 100.05-100.45 s: a landmark seen at 100.0 or 101.0 has no command to move the robot there
    path = sample / "Robot1_Measurement.dat"
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    lines.insert(4, "100.0 \t 63 \t 2.0 \t 0.1\r\n")
    path.write_text("".join(lines) + "101.0 \t 81 \t 1.5 \t -0.2\r\n", newline="")
    run = read_mrclam(sample, 1)
    assert run.skipped_outside == 2
    np.testing.assert_allclose(run.measurements[:, 0], [100.1, 100.3])
    seq = mrclam_sequence(run, initial_pose=np.zeros(3), period=0.2, command_delay=0.0)
    assert seq.stamps[0] == pytest.approx(100.05) and seq.stamps[-1] <= 100.45
