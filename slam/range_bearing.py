"""Range-bearing landmark measurement model, vectorised over poses and landmarks.

A measurement z = (r, phi) of a point landmark m = (mx, my) from a robot pose x = (x, y, theta):
r = |m - (x, y)| (m), phi = atan2(my - y, mx - x) - theta (rad, robot frame, counter-clockwise from the
heading), with additive Gaussian noise of covariance R = diag(sigma_r^2, sigma_bearing^2), where sigma_r may grow with
the range (see :class:`RangeBearingModel`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam.angles import wrap_angle
from slam.errors import InputError, check_within

#: accepted (low, high) of :class:`RangeBearingModel`'s parameters. Below 1 mm / 1 mrad (better than any
#: landmark sensor) the EKF's covariance stops being positive definite in double precision; above 1 km / pi rad
#: a measurement says nothing, and far beyond, its squared noise overflows.
SIGMA_RANGE_LIMITS = (1e-3, 1e3)
SIGMA_BEARING_LIMITS = (1e-3, math.pi)
#: range std growth in m per m of range: at most 1 (a std as large as the range itself)
RANGE_FRACTION_LIMITS = (0.0, 1.0)
#: rad: a measured bearing beyond a full turn either way is no bearing (the logs' readers refuse or skip it)
BEARING_LIMIT = 2.0 * math.pi


@dataclass(frozen=True)
class RangeBearingModel:
    """Noise of the range-bearing sensor: the range std is sigma_range + range_fraction * r (m, with r the
    measured range in m), the bearing std sigma_bearing (rad)."""

    sigma_range: float = 0.1
    sigma_bearing: float = 0.035
    range_fraction: float = 0.0

    def __post_init__(self) -> None:
        """InputError for a negative or non-finite noise (0 is a noise-free simulated sensor; what a filter needs on
        top: :func:`check_sensor_limits`)."""
        values = (self.sigma_range, self.sigma_bearing, self.range_fraction)
        try:
            ok = all(math.isfinite(v) and v >= 0.0 for v in values)
        except TypeError:
            ok = False
        if not ok:
            raise InputError(
                "RangeBearingModel: sigma_range (m), sigma_bearing (rad) and range_fraction must be finite numbers "
                f">= 0, got {values!r}"
            )

    def covariance(self, z: np.ndarray) -> np.ndarray:
        """Measurement-noise covariance R (2, 2) of one measurement z = (range m, bearing rad)."""
        sigma_r = self.sigma_range + self.range_fraction * float(z[0])
        return np.diag([sigma_r**2, self.sigma_bearing**2])


def check_sensor_limits(sensor: RangeBearingModel) -> None:
    """InputError unless ``sensor`` is a :class:`RangeBearingModel` within :data:`SIGMA_RANGE_LIMITS`,
    :data:`SIGMA_BEARING_LIMITS` and :data:`RANGE_FRACTION_LIMITS`: the noise a filter can use (the file readers
    refuse the same; a zero noise makes FastSLAM's likelihoods NaN)."""
    if not isinstance(sensor, RangeBearingModel):
        raise InputError(f"sensor must be a slam.range_bearing.RangeBearingModel, got {type(sensor).__name__}")
    check_within("RangeBearingModel.sigma_range", sensor.sigma_range, SIGMA_RANGE_LIMITS, "m")
    check_within("RangeBearingModel.sigma_bearing", sensor.sigma_bearing, SIGMA_BEARING_LIMITS, "rad")
    check_within("RangeBearingModel.range_fraction", sensor.range_fraction, RANGE_FRACTION_LIMITS, "m per m")


def predict_measurement(poses: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected measurement and Jacobians for matching rows of poses (..., 3) and landmarks (..., 2).

    Returns z_hat (..., 2) (m, rad), H_x = dz/dpose (..., 2, 3) and H_m = dz/dlandmark (..., 2, 2).
    """
    dx = landmarks[..., 0] - poses[..., 0]
    dy = landmarks[..., 1] - poses[..., 1]
    q = np.maximum(dx * dx + dy * dy, 1e-18)
    r = np.sqrt(q)
    z_hat = np.stack([r, wrap_angle(np.arctan2(dy, dx) - poses[..., 2])], axis=-1)
    h_m = np.stack([np.stack([dx / r, dy / r], -1), np.stack([-dy / q, dx / q], -1)], -2)
    zeros = np.zeros_like(dx)
    h_x = np.stack([np.stack([-dx / r, -dy / r, zeros], -1), np.stack([dy / q, -dx / q, zeros - 1.0], -1)], -2)
    return z_hat, h_x, h_m


def inverse_measurement(poses: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Landmark position (..., 2) in the map frame from poses (..., 3) and measurements (..., 2).

    Also returns the Jacobians dm/dz (..., 2, 2) and dm/dpose (..., 2, 3), to initialise landmark covariances.
    """
    z = np.broadcast_to(z, np.broadcast_shapes(z.shape[:-1], poses.shape[:-1]) + (2,))
    r, phi = z[..., 0], z[..., 1]
    angle = poses[..., 2] + phi
    c, s = np.cos(angle), np.sin(angle)
    landmark = np.stack([poses[..., 0] + r * c, poses[..., 1] + r * s], axis=-1)
    j_z = np.stack([np.stack([c, -r * s], -1), np.stack([s, r * c], -1)], -2)
    ones, zeros = np.ones_like(r), np.zeros_like(r)
    j_x = np.stack([np.stack([ones, zeros, -r * s], -1), np.stack([zeros, ones, r * c], -1)], -2)
    return landmark, j_z, j_x
