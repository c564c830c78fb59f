"""What the two landmark filters, :class:`slam.ekf.EKFSLAM` and :class:`slam.fastslam.FastSLAM`, share: the motion
and range-bearing models, how measurements meet landmarks, the outlier gate, the consistency watch and the map
scale's uncertainty. `posegrid slam` builds one :class:`LandmarkOptions` and gives it to either filter."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from slam.angles import wrap_angle
from slam.consistency import ConsistencyMonitor
from slam.motion import MotionModel
from slam.range_bearing import RangeBearingModel


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
    :meth:`turn_covariance` is that turn's covariance of the positions given out."""

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
        self.motion, self.sensor = motion, sensor
        self.known, self.outlier_gate = known_correspondences, outlier_gate
        self.scale_sd, self.drive_angle, self.drive_angle_sd = scale_sd, drive_angle, drive_angle_sd
        self.origin = np.asarray(initial_pose, dtype=np.float64)[:2].copy()
        self.start = np.asarray(initial_pose, dtype=np.float64).copy()
        self.start[2] = wrap_angle(self.start[2] + drive_angle)
        self.monitor = ConsistencyMonitor(adaptive=adaptive)  # NIS watch and noise scale (slam.consistency)

    def body_heading(self, heading: np.ndarray) -> np.ndarray:
        """Headings (rad) of the drive's frame as given out: less the drive angle."""
        return wrap_angle(heading - self.drive_angle) if self.drive_angle != 0.0 else heading

    def turn_covariance(self, position: np.ndarray) -> np.ndarray:
        """(2, 2) m^2: the covariance that a turn of the path about its start with sd ``drive_angle_sd`` (rad) gives
        the position (2,) m: sd^2 (J d)(J d)^T, d = position - origin, J the quarter turn."""
        lever = np.asarray(position, dtype=np.float64) - self.origin
        across = np.array([-lever[1], lever[0]])
        return self.drive_angle_sd**2 * np.outer(across, across)
