"""Reader for the UTIAS Multi-Robot Cooperative Localization and Mapping (MRCLAM) dataset format.

A dataset folder holds, per robot K, ``RobotK_Odometry.dat`` (time s, forward velocity m/s, angular velocity
rad/s: the commanded velocities, about 67 Hz), ``RobotK_Measurement.dat`` (time s, barcode, range m, bearing
rad; the column headed "Subject #" holds barcode numbers), optionally ``RobotK_Groundtruth.dat`` (time s, x m,
y m, yaw rad), and ``Barcodes.dat`` (subject, barcode) and ``Landmark_Groundtruth.dat`` (subject, x m, y m,
std x m, std y m). Subjects 1-5 are robots, the others landmarks. All files have '#' header lines and
whitespace-separated numbers. Measurements of robots, of barcodes in no table and those stamped outside the
odometry's time span (no command to move the robot there) are skipped and counted.
Landmark positions are never used by the filters; Landmark_Groundtruth.dat is read for scoring only.
The data are read as logged: no dataset's calibration is applied unless one is given (:func:`read_sequence`,
slam.calibration; profile ``mrclam7`` is dataset 7's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.calibration import Calibration
from slam.errors import LogFormatError, refuse_special_file
from slam.motion import VELOCITY_LIMIT
from slam.range_bearing import BEARING_LIMIT
from slam.sequence import SlamSequence

#: subjects 1..ROBOT_SUBJECTS are robots; larger subjects are landmarks
ROBOT_SUBJECTS = 5

_COLUMNS = {
    "Odometry": "time s, forward velocity m/s, angular velocity rad/s",
    "Measurement": "time s, barcode, range m, bearing rad",
    "Groundtruth": "time s, x m, y m, orientation rad",
    "Barcodes": "subject, barcode",
    "Landmark_Groundtruth": "subject, x m, y m, x std-dev m, y std-dev m",
}


def read_table(
    path: str | Path, kind: str, timed: bool = True, bound: tuple[int, ...] = (), limit: float = math.inf
) -> np.ndarray:
    """Rows of one MRCLAM text file as float64 (R, C); C from ``kind`` (a key of the column table).

    Lines starting with '#' and blank lines are skipped. A line with the wrong number of fields, a field that is
    not a finite number, a field of the columns ``bound`` beyond +-``limit`` or (``timed``) a time earlier than
    the line before raises LogFormatError naming the file and the line number.
    """
    path = Path(path)
    columns = _COLUMNS[kind]
    n_cols = columns.count(",") + 1
    refuse_special_file(path, f"MRCLAM {kind} table")
    try:
        text = path.read_text(encoding="ascii", errors="strict")
    except FileNotFoundError:
        raise LogFormatError(f"{path}: no such file (an MRCLAM folder needs it)") from None
    except UnicodeDecodeError as exc:
        raise LogFormatError(
            f"{path}: not an ASCII text file (byte {exc.start} is {exc.object[exc.start]:#x})"
        ) from None
    except OSError as exc:
        raise LogFormatError(f"{path}: cannot be read ({exc.strerror})") from None
    rows: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != n_cols:
            raise LogFormatError(
                f"{path.name} line {number}: expected {n_cols} numbers ({columns}), got {len(fields)} fields"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise LogFormatError(
                f"{path.name} line {number}: expected {n_cols} numbers ({columns}), got '{line.strip()}'"
            ) from None
        if not all(np.isfinite(values)):
            raise LogFormatError(f"{path.name} line {number}: a value is NaN or inf")
        for column in bound:
            if abs(values[column]) > limit:
                name, unit = columns.split(", ")[column].rsplit(" ", 1)
                raise LogFormatError(
                    f"{path.name} line {number}: {name} {values[column]:g} {unit} is beyond +-{limit:g} {unit}"
                )
        if timed and rows and values[0] < rows[-1][0]:
            raise LogFormatError(f"{path.name} line {number}: time {values[0]} s is earlier than the line before")
        rows.append(values)
    if not rows:
        raise LogFormatError(f"{path}: holds no data lines ({columns})")
    return np.array(rows, dtype=np.float64)


@dataclass(frozen=True)
class MrclamRobot:
    """One robot's log from an MRCLAM folder, measurements reduced to landmarks."""

    robot: int
    odometry: np.ndarray  # (K, 3): time s, v m/s, w rad/s
    measurements: np.ndarray  # (M, 3): time s, range m, bearing rad (landmarks only)
    subjects: np.ndarray  # (M,) int: landmark subject of each measurement
    groundtruth: np.ndarray | None  # (G, 4): time s, x m, y m, yaw rad; None when the folder has none
    landmark_truth: np.ndarray | None  # (L, 3): subject, x m, y m (scoring only)
    skipped_robots: int  # measurements of other robots
    skipped_unknown: int  # measurements of barcodes in no table
    skipped_outside: int  # landmark measurements stamped before the first or after the last odometry row
    skipped_invalid: int  # landmark measurements with a range <= 0 m or |bearing| > BEARING_LIMIT rad


def find_robots(folder: str | Path) -> list[int]:
    """Robot numbers K with a RobotK_Odometry.dat in ``folder``."""
    found = []
    for path in Path(folder).glob("Robot*_Odometry.dat"):
        number = path.name[len("Robot") : -len("_Odometry.dat")]
        if number.isdigit():
            found.append(int(number))
    return sorted(found)


def is_mrclam_folder(folder: str | Path) -> bool:
    """Whether ``folder`` looks like an MRCLAM dataset (Barcodes.dat and at least one robot's odometry)."""
    return (Path(folder) / "Barcodes.dat").is_file() and bool(find_robots(folder))


def read_mrclam(folder: str | Path, robot: int) -> MrclamRobot:
    """Read robot ``robot``'s odometry, landmark measurements and (if present) ground truth from ``folder``."""
    folder = Path(folder)
    if not (folder / f"Robot{robot}_Odometry.dat").is_file():
        robots = find_robots(folder)
        raise LogFormatError(f"{folder}: has no Robot{robot}_Odometry.dat (robots here: {robots or 'none'})")
    barcodes = read_table(folder / "Barcodes.dat", "Barcodes", timed=False)
    subject_of = {int(barcode): int(subject) for subject, barcode in barcodes}
    raw = read_table(folder / f"Robot{robot}_Measurement.dat", "Measurement")
    subjects = np.array([subject_of.get(int(b), -1) for b in raw[:, 1]], dtype=np.int64)
    odometry = read_table(folder / f"Robot{robot}_Odometry.dat", "Odometry", bound=(1, 2), limit=VELOCITY_LIMIT)
    is_landmark = subjects > ROBOT_SUBJECTS
    inside = (raw[:, 0] >= odometry[0, 0]) & (raw[:, 0] <= odometry[-1, 0])
    valid = (raw[:, 2] > 0.0) & (np.abs(raw[:, 3]) <= BEARING_LIMIT)
    kept = is_landmark & inside & valid
    gt_path = folder / f"Robot{robot}_Groundtruth.dat"
    lm_path = folder / "Landmark_Groundtruth.dat"
    landmark_truth = read_table(lm_path, "Landmark_Groundtruth", timed=False)[:, :3] if lm_path.is_file() else None
    return MrclamRobot(
        robot=robot,
        odometry=odometry,
        measurements=raw[kept][:, [0, 2, 3]],
        subjects=subjects[kept],
        groundtruth=read_groundtruth(gt_path) if gt_path.is_file() else None,
        landmark_truth=landmark_truth,
        skipped_robots=int(np.sum((subjects >= 1) & (subjects <= ROBOT_SUBJECTS))),
        skipped_unknown=int(np.sum(subjects < 0)),
        skipped_outside=int(np.sum(is_landmark & ~inside)),
        skipped_invalid=int(np.sum(is_landmark & inside & ~valid)),
    )


def table_kind(path: str | Path) -> str | None:
    """The kind of MRCLAM table (a key of the column table) a file's name says it is: RobotK_KIND.dat or KIND.dat;
    None for a name of no table."""
    name = Path(path).name
    if not name.endswith(".dat"):
        return None
    stem = name[: -len(".dat")]
    robot, _, rest = stem.partition("_")
    kind = rest if robot.startswith("Robot") and robot[len("Robot") :].isdigit() else stem
    return kind if kind in _COLUMNS else None


def read_groundtruth(path: str | Path) -> np.ndarray:
    """A RobotK_Groundtruth.dat file as (G, 4): time s, x m, y m, yaw rad (map frame). LogFormatError for a file
    named as another MRCLAM table (a Measurement.dat read as ground truth said it "holds two poses at ... s"), and
    for a yaw beyond a full turn: radians are expected, as the pose files' (a ground truth in degrees was scored:
    heading error 2.04 rad and NEES 41 018, exit 0)."""
    kind = table_kind(path)
    if kind is not None and kind != "Groundtruth":
        raise LogFormatError(f"{path}: an MRCLAM {kind} table, not a robot's ground truth (RobotK_Groundtruth.dat)")
    return read_table(path, "Groundtruth", bound=(3,), limit=math.tau)  # (the yaw: a full turn at most)


def mrclam_sequence(
    run: MrclamRobot,
    initial_pose: np.ndarray | None = None,
    period: float = 0.2,
    command_delay: float = 0.0,
) -> SlamSequence:
    """The filters' input for one MRCLAM robot.

    Start: at the first ground-truth pose and stamp (the dataset's custom), or at ``initial_pose`` (x m, y m,
    yaw rad) at the first odometry stamp. Steps: every distinct landmark-measurement stamp and a regular grid
    every ``period`` s, up to the last odometry stamp (:func:`read_mrclam` skips measurements outside the
    odometry's span; measurements stamped before the start are left out here). Controls: the velocity
    commands as (v, w, dt) pieces, each odometry row held until the next one (zero before the first), cut at
    the step stamps, each command taking effect ``command_delay`` s after its stamp (default 0: as logged).
    Commands and measurements are as logged (slam.calibration corrects them). Landmark ids are MRCLAM subject
    numbers.
    """
    if initial_pose is None:
        if run.groundtruth is None:
            raise LogFormatError(
                f"robot {run.robot}: no ground truth to start from; give an initial pose (--initial X,Y,YAW: m, m, rad)"
            )
        start, initial = run.groundtruth[0, 0], run.groundtruth[0, 1:4]
    else:
        start = run.odometry[0, 0]
        initial = np.asarray(initial_pose, dtype=np.float64)
    end = run.odometry[-1, 0]
    keep = run.measurements[:, 0] >= start
    meas, subjects = run.measurements[keep], run.subjects[keep]
    grid = start + period * np.arange(int(np.floor((end - start) / period)) + 1)
    stamps = np.unique(np.concatenate([[start], grid, meas[:, 0]]))

    odo_t = run.odometry[:, 0] + command_delay
    breaks = np.unique(np.concatenate([stamps, odo_t[(odo_t > start) & (odo_t < stamps[-1])]]))
    dt = np.diff(breaks)
    active = np.searchsorted(odo_t, breaks[:-1], side="right") - 1
    velocity = np.where(active[:, None] >= 0, run.odometry[np.maximum(active, 0), 1:3], 0.0)
    controls = np.column_stack([velocity, dt])
    piece_step = np.searchsorted(stamps, breaks[1:], side="left")
    control_ptr = np.searchsorted(piece_step, np.arange(len(stamps) + 1), side="left")
    meas_step = np.searchsorted(stamps, meas[:, 0], side="left")
    measurement_ptr = np.searchsorted(meas_step, np.arange(len(stamps) + 1), side="left")
    return SlamSequence(
        stamps=stamps,
        controls=controls,
        control_ptr=control_ptr,
        measurements=meas[:, 1:3],
        landmark_ids=subjects,
        measurement_ptr=measurement_ptr,
        initial_pose=initial,
        motion="velocity",
    )


def read_sequence(
    folder: str | Path,
    robot: int,
    calibration: Calibration | None = None,
    initial_pose: np.ndarray | None = None,
    period: float = 0.2,
) -> tuple[MrclamRobot, SlamSequence]:
    """Robot ``robot`` of an MRCLAM folder and its filter input: as logged without a ``calibration``, else with
    its command delay and its corrections of the commands and measurements applied (slam.calibration)."""
    run = read_mrclam(folder, robot)
    delay = 0.0 if calibration is None else calibration.command_delay
    sequence = mrclam_sequence(run, initial_pose=initial_pose, period=period, command_delay=delay)
    return run, sequence if calibration is None else calibration.apply(sequence)
