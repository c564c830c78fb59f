"""What the two landmark filters, :class:`slam.ekf.EKFSLAM` and :class:`slam.fastslam.FastSLAM`, share: the motion
and range-bearing models, how measurements meet landmarks, the outlier gate, the consistency watch and the map
scale's uncertainty. `posegrid slam` builds one :class:`LandmarkOptions` and gives it to either filter."""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from slam.consistency import ConsistencyMonitor
from slam.motion import MotionModel
from slam.range_bearing import RangeBearingModel


class LandmarkOptions(TypedDict, total=False):
    """The options both landmark filters take, every key optional (defaults in :class:`LandmarkFilter`)."""

    known_correspondences: bool  # measurements carry landmark ids; else each filter associates them itself
    outlier_gate: float | None  # squared Mahalanobis distance beyond which a measurement updates nothing; None: none
    adaptive: bool  # the consistency watch (slam.consistency) scales the noise while innovations show overconfidence
    scale_sd: float  # relative sd of the map's scale about the start (slam.calibration), 0 for none
    heading_sd: float  # sd (rad) of the drive angle, added to the headings given out (slam.calibration), 0 for none


class LandmarkFilter:
    """The state both landmark filters keep beside their own: ``motion`` and ``sensor`` models, ``known``
    correspondences, ``outlier_gate``, the map scale's sd ``scale_sd`` and the ``origin`` (2,) m it is uncertain
    about (the start position of ``initial_pose`` (3,): x m, y m, yaw rad, map frame), the drive angle's sd
    ``heading_sd`` (rad), and the consistency ``monitor``."""

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
        heading_sd: float = 0.0,
    ) -> None:
        self.motion, self.sensor = motion, sensor
        self.known, self.outlier_gate = known_correspondences, outlier_gate
        self.scale_sd, self.heading_sd = scale_sd, heading_sd
        self.origin = np.asarray(initial_pose, dtype=np.float64)[:2].copy()
        self.monitor = ConsistencyMonitor(adaptive=adaptive)  # NIS watch and noise scale (slam.consistency)
