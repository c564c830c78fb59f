"""Odometry-only dead reckoning: the motion model's mean and linearised covariance, measurements ignored.

The baseline every SLAM filter must beat; its covariance grows without bound, as it should.
"""

from __future__ import annotations

import numpy as np

from slam.angles import wrap_angle
from slam.calibration import DRIVE_ANGLE_LIMITS
from slam.errors import check_within, finite_array
from slam.motion import MotionModel, check_controls, check_motion_limits


class DeadReckoning:
    """Gaussian pose (mean (3,), cov (3, 3)) propagated through the controls alone (the EKF prediction step).

    ``drive_angle`` (rad): the robot drives at this angle to its heading (slam.calibration); the pose is propagated in
    the drive's frame, from ``initial_pose`` (x m, y m, yaw rad) turned by it, and given out with the heading less it,
    as the landmark filters do (slam.landmark_filter)."""

    gaussian = True

    def __init__(self, motion: MotionModel, initial_pose: np.ndarray, drive_angle: float = 0.0) -> None:
        check_motion_limits(motion)
        check_within("drive_angle", drive_angle, DRIVE_ANGLE_LIMITS, "rad")
        self.motion = motion
        self.drive_angle = drive_angle
        self.mean = finite_array("initial_pose", initial_pose, (3,), " (x m, y m, yaw rad in the map frame)").copy()
        self.mean[2] = wrap_angle(self.mean[2] + drive_angle)
        self.cov = np.zeros((3, 3))

    def step(
        self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Propagate through controls (K, 3); measurements are ignored. Returns (mean (3,), cov (3, 3)). InputError
        for controls :func:`slam.motion.check_controls` refuses, before the pose changes."""
        for control in check_controls(controls, self.motion):
            mean, jac_g, q = self.motion.linearize(self.mean[None, :], control)
            self.mean = mean[0]
            self.cov = jac_g[0] @ self.cov @ jac_g[0].T + q[0]
        mean = self.mean.copy()
        mean[2] = wrap_angle(mean[2] - self.drive_angle)
        return mean, self.cov.copy()
