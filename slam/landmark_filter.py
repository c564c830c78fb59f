"""What the two landmark filters, :class:`slam.ekf.EKFSLAM` and :class:`slam.fastslam.FastSLAM`, share: the motion
and range-bearing models, how measurements meet landmarks, the outlier gate, the consistency watch and the map
scale's uncertainty. `posegrid slam` builds one :class:`LandmarkOptions` and gives it to either filter."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from slam.angles import wrap_angle
from slam.calibration import DRIVE_ANGLE_LIMITS, DRIVE_ANGLE_SD_LIMITS, SCALE_SD_LIMITS
from slam.consistency import ConsistencyMonitor
from slam.errors import InputError, check_within, finite_array
from slam.laserlog import POSE_LIMIT
from slam.motion import MotionModel, check_controls, check_motion_limits
from slam.range_bearing import BEARING_LIMIT, RangeBearingModel, check_sensor_limits

#: the largest |landmark id|: ids are names, and beyond 2^53 a float id no longer names one integer
MAX_LANDMARK_ID = 2**53


def check_gate(name: str, gate: float) -> None:
    """InputError unless ``gate`` (a squared Mahalanobis distance) is a number > 0; inf is no gate."""
    try:
        ok = float(gate) > 0.0  # NaN fails
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"{name} must be a squared Mahalanobis distance > 0 (inf: no gate), got {gate!r}")


class LandmarkOptions(TypedDict, total=False):
    """The options both landmark filters take, every key optional (defaults in :class:`LandmarkFilter`)."""

    known_correspondences: bool  # measurements carry landmark ids; else each filter associates them itself
    outlier_gate: float | None  # squared Mahalanobis distance beyond which a measurement updates nothing; None: none
    adaptive: bool  # the consistency watch (slam.consistency) scales the noise while innovations show overconfidence
    scale_sd: float  # relative sd of the map's scale about the start (slam.calibration), 0 for none
    drive_angle: float  # rad: the robot drives at this angle to its heading (slam.calibration); the filter's frame
    drive_angle_sd: float  # sd (rad) of the drive angle: the path's turn about its start (slam.calibration), 0: none


class LandmarkFilter:
    """The state both landmark filters keep beside their own: ``motion`` and ``sensor`` models, ``known``
    correspondences, ``outlier_gate``, the map scale's sd ``scale_sd`` and the ``origin`` (2,) m it is uncertain
    about (the start position of ``initial_pose`` (3,): x m, y m, yaw rad, map frame), the ``drive_angle`` (rad)
    and its sd ``drive_angle_sd`` (rad), and the consistency ``monitor``.

    A filter runs in the drive's frame (its bearings are corrected by the drive angle too, slam.calibration): it
    starts at :attr:`start`, ``initial_pose`` turned by the drive angle, and gives out its heading less it
    (:meth:`body_heading`). An error e in the drive angle turns the path about its start by e, which no data show:
    :meth:`turn_covariance` is that turn's covariance of the positions given out.

    The constructor refuses (InputError) models outside the limits the file readers apply
    (slam.motion.check_motion_limits, slam.range_bearing.check_sensor_limits), a non-finite ``initial_pose`` and options
    outside slam.calibration's limits; :meth:`checked_step` checks what a filter's ``step`` is given."""

    def __init__(
        self,
        motion: MotionModel,
        sensor: RangeBearingModel,
        initial_pose: np.ndarray,
        *,
        known_correspondences: bool = True,
        outlier_gate: float | None = None,
        adaptive: bool = True,
        scale_sd: float = 0.0,
        drive_angle: float = 0.0,
        drive_angle_sd: float = 0.0,
    ) -> None:
        check_motion_limits(motion)
        check_sensor_limits(sensor)
        initial_pose = finite_array("initial_pose", initial_pose, (3,), " (x m, y m, yaw rad in the map frame)")
        check_within("scale_sd", scale_sd, SCALE_SD_LIMITS)
        check_within("drive_angle", drive_angle, DRIVE_ANGLE_LIMITS, "rad")
        check_within("drive_angle_sd", drive_angle_sd, DRIVE_ANGLE_SD_LIMITS, "rad")
        if outlier_gate is not None:
            check_gate("outlier_gate", outlier_gate)
        self.motion, self.sensor = motion, sensor
        self.known, self.outlier_gate = known_correspondences, outlier_gate
        self.scale_sd, self.drive_angle, self.drive_angle_sd = scale_sd, drive_angle, drive_angle_sd
        self.origin = np.asarray(initial_pose, dtype=np.float64)[:2].copy()
        self.start = np.asarray(initial_pose, dtype=np.float64).copy()
        self.start[2] = wrap_angle(self.start[2] + drive_angle)
        self.monitor = ConsistencyMonitor(adaptive=adaptive)  # NIS watch and noise scale (slam.consistency)

    def checked_step(
        self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A step's inputs as float64 controls (K, 3), measurements (O, 2) and int64 landmark ids (O,), or InputError
        saying what is wrong: a value that is not finite, controls not of the current motion model's kind (velocity:
        (v m/s, w rad/s, dt s) with |v|, |w| <= VELOCITY_LIMIT and dt >= 0), ranges (m) outside [0, POSE_LIMIT],
        bearings (rad) beyond a full turn, ids that are not whole numbers or not one per measurement (with unknown
        correspondences ids are ignored and may be left empty). One control (3,) is a step of one control. O(K + O),
        vectorised."""
        controls = check_controls(controls, self.motion)
        measurements = np.asarray(measurements, dtype=np.float64)
        measurements = measurements.reshape(-1, 2) if measurements.size == 0 else measurements
        measurements = finite_array("measurements", measurements, (None, 2), " (rows of range m, bearing rad)")
        if len(measurements):
            check_within("measured range", measurements[:, 0], (0.0, POSE_LIMIT), "m")
            check_within("measured bearing", measurements[:, 1], (-BEARING_LIMIT, BEARING_LIMIT), "rad")
        ids = np.asarray(landmark_ids)
        count = len(measurements)
        if not self.known and ids.size == 0:
            return controls, measurements, np.full(count, -1, dtype=np.int64)
        if ids.shape != (count,):
            raise InputError(
                f"landmark_ids must hold one id per measurement, ({count},), got shape {ids.shape}"
                + ("" if self.known else " (unknown correspondences ignore them: pass none)")
            )
        if ids.dtype.kind not in "iuf" or (
            ids.dtype.kind == "f" and not np.all((ids == np.round(ids)) & (np.abs(ids) <= MAX_LANDMARK_ID))
        ):
            bad = ids if ids.dtype.kind not in "iuf" else ids[ids != np.round(ids)]
            raise InputError(f"landmark_ids must be whole numbers (ids name landmarks), got {bad[:3].tolist()}")
        return controls, measurements, ids.astype(np.int64)

    def body_heading(self, heading: np.ndarray) -> np.ndarray:
        """Headings (rad) of the drive's frame as given out: less the drive angle."""
        return wrap_angle(heading - self.drive_angle) if self.drive_angle != 0.0 else heading

    def turn_covariance(self, position: np.ndarray) -> np.ndarray:
        """(2, 2) m^2: the covariance that a turn of the path about its start with sd ``drive_angle_sd`` (rad) gives
        the position (2,) m: sd^2 (J d)(J d)^T, d = position - origin, J the quarter turn."""
        lever = np.asarray(position, dtype=np.float64) - self.origin
        across = np.array([-lever[1], lever[0]])
        return self.drive_angle_sd**2 * np.outer(across, across)
