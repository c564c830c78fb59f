"""Reader for the UTIAS Multi-Robot Cooperative Localization and Mapping (MRCLAM) dataset format.

A dataset folder holds, per robot K, ``RobotK_Odometry.dat`` (time s, forward velocity m/s, angular velocity
rad/s: the commanded velocities, about 67 Hz), ``RobotK_Measurement.dat`` (time s, barcode, range m, bearing
rad; the column headed "Subject #" holds barcode numbers), optionally ``RobotK_Groundtruth.dat`` (time s, x m,
y m, yaw rad), and ``Barcodes.dat`` (subject, barcode) and ``Landmark_Groundtruth.dat`` (subject, x m, y m,
std x m, std y m). Subjects 1-5 are robots, the others landmarks. All files have '#' header lines and
whitespace-separated numbers. Measurements of robots, of barcodes in no table and those stamped outside the
odometry's time span (no command to move the robot there) are skipped and counted.
Landmark positions are never used by the filters; Landmark_Groundtruth.dat is read for scoring only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.errors import LogFormatError
from slam.motion import VelocityMotionModel
from slam.range_bearing import BEARING_LIMIT, RangeBearingModel
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


def read_table(path: str | Path, kind: str, timed: bool = True) -> np.ndarray:
    """Rows of one MRCLAM text file as float64 (R, C); C from ``kind`` (a key of the column table).

    Lines starting with '#' and blank lines are skipped. A line with the wrong number of fields, a field that is
    not a finite number or (``timed``) a time earlier than the line before raises LogFormatError naming the
    file and the line number.
    """
    path = Path(path)
    columns = _COLUMNS[kind]
    n_cols = columns.count(",") + 1
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
    odometry = read_table(folder / f"Robot{robot}_Odometry.dat", "Odometry")
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


def read_groundtruth(path: str | Path) -> np.ndarray:
    """A RobotK_Groundtruth.dat file as (G, 4): time s, x m, y m, yaw rad (map frame)."""
    return read_table(path, "Groundtruth")


def calibrate_ranges(measurements: np.ndarray, coefficients: tuple[float, float]) -> np.ndarray:
    """Measurements (M, 2) (range m, bearing rad) with ranges divided by c0 + c2 bearing^2.

    MRCLAM's cameras measure range from the barcode's apparent size, and the ratio of measured to true range
    falls off towards the image edges; :data:`MRCLAM_RANGE_CALIBRATION` holds the fit (docs/slam.md).
    """
    c0, c2 = coefficients
    out = np.array(measurements, dtype=np.float64)
    out[:, 0] /= c0 + c2 * out[:, 1] ** 2
    return out


def mrclam_sequence(
    run: MrclamRobot,
    initial_pose: np.ndarray | None = None,
    period: float = 0.2,
    command_delay: float | None = None,
    range_calibration: tuple[float, float] | None = None,
    velocity_scale: tuple[float, float] | None = None,
) -> SlamSequence:
    """The filters' input for one MRCLAM robot.

    Start: at the first ground-truth pose and stamp (the dataset's custom), or at ``initial_pose`` (x m, y m,
    yaw rad) at the first odometry stamp. Steps: every distinct landmark-measurement stamp and a regular grid
    every ``period`` s, up to the last odometry stamp (:func:`read_mrclam` skips measurements outside the
    odometry's span; measurements stamped before the start are left out here). Controls: the velocity
    commands as (v, w, dt) pieces, each odometry row held until the next one (zero before the first), cut at
    the step stamps, each command taking effect ``command_delay`` s after its stamp (default
    :data:`MRCLAM_COMMAND_DELAY`), its (v, w) multiplied by ``velocity_scale`` (executed / commanded, e.g.
    :data:`MRCLAM_VELOCITY_SCALE`; None: as logged). Ranges are corrected by :func:`calibrate_ranges` with
    ``range_calibration`` (None: uncorrected). Landmark ids are MRCLAM subject numbers.
    """
    if command_delay is None:
        command_delay = MRCLAM_COMMAND_DELAY
    if initial_pose is None:
        if run.groundtruth is None:
            raise LogFormatError(f"robot {run.robot}: no ground truth to start from; give an initial pose (x,y,yaw)")
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
    if velocity_scale is not None:
        velocity = velocity * np.asarray(velocity_scale, dtype=np.float64)
    controls = np.column_stack([velocity, dt])
    piece_step = np.searchsorted(stamps, breaks[1:], side="left")
    control_ptr = np.searchsorted(piece_step, np.arange(len(stamps) + 1), side="left")
    meas_step = np.searchsorted(stamps, meas[:, 0], side="left")
    measurement_ptr = np.searchsorted(meas_step, np.arange(len(stamps) + 1), side="left")
    return SlamSequence(
        stamps=stamps,
        controls=controls,
        control_ptr=control_ptr,
        measurements=meas[:, 1:3] if range_calibration is None else calibrate_ranges(meas[:, 1:3], range_calibration),
        landmark_ids=subjects,
        measurement_ptr=measurement_ptr,
        initial_pose=initial,
        motion="velocity",
    )


#: s from a velocity command's stamp to the robot's response (cross-correlation with ground truth, docs/slam.md)
MRCLAM_COMMAND_DELAY = 0.2
#: executed / commanded (v, w): least squares of the ground truth's path length and yaw change against the
#: commanded ones (delayed by MRCLAM_COMMAND_DELAY) over 4 s windows, all five robots of dataset 7 pooled;
#: leaving out each robot in turn gives 0.915-0.926 and 0.953-0.962 (docs/slam.md)
MRCLAM_VELOCITY_SCALE = (0.918, 0.958)
#: range correction (c0, c2) of :func:`calibrate_ranges`: measured / true range = c0 + c2 bearing^2
MRCLAM_RANGE_CALIBRATION = (1.033, -0.46)
#: velocity-model noise for MRCLAM's commanded velocities (alphas and floor of slam.motion.VelocityMotionModel),
#: fitted to ground-truth increments (docs/slam.md): translation and the floor from 4 s windows, the rotation
#: term from 16 s windows (rotation errors persist over whole manoeuvres)
MRCLAM_VELOCITY_ALPHAS = (0.32, 0.086, 0.0, 0.5, 0.0, 0.0)
MRCLAM_VELOCITY_FLOOR = (0.0, 0.0035)
#: the motion model `posegrid slam` uses for MRCLAM
MRCLAM_MOTION = VelocityMotionModel(MRCLAM_VELOCITY_ALPHAS, floor=MRCLAM_VELOCITY_FLOOR)
#: landmark measurement noise for MRCLAM's cameras after the range calibration: the scatter fitted to ground
#: truth, inflated for the measurement errors' correlation in time (docs/slam.md)
MRCLAM_SENSOR = RangeBearingModel(sigma_range=0.05, sigma_bearing=0.02, range_fraction=0.07)
#: known ids: measurements beyond this squared Mahalanobis distance are outliers (chi-square(2) 0.9999)
MRCLAM_OUTLIER_GATE = 18.42
