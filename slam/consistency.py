"""Consistency watch and adaptive noise for the landmark filters: the normalised innovation squared (NIS) over a
sliding window, and one noise scale that follows it.

Every landmark measurement a filter predicts (a landmark it has mapped) gives an NIS, nu^T S^-1 nu (2 degrees of
freedom; for particles, under the particles' predictive mixture), gated or not. For an honest filter NIS is
chi-square(2), median ``CHI2_2_MEDIAN``. The monitor keeps the last ``window`` of them; when the window is full it
compares their median with that: the ratio m estimates by how much the filter understates (m > 1) or overstates
(m < 1) its innovations' spread. Beyond ``[1 / threshold, threshold]`` the filter's noise scale (one factor on
the motion-noise and the measurement-noise covariances, within ``limits``) is multiplied by m, the filter is told to
multiply its current covariances by m too (:meth:`ConsistencyMonitor.add` returns m; with a common factor on all
noise a linear-Gaussian filter's covariance scales by it exactly), and the window starts afresh; otherwise the older
half of the window is dropped and the watch goes on. The median, not the mean: one wild measurement (which the
gate drops) moves it little, but a gate that drops most of a window's measurements puts it beyond the gate, and
the noise grows until the measurements fit again.

With ``window`` 60 the median of an honest filter's NIS has a relative spread of about 19 %, and ``threshold`` 1.6
(2.5 such spreads in log) is crossed by chance in about 1 % of the windows.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import overload

import numpy as np

from slam.motion import MotionModel, OdometryMotionModel, OmniOdometryMotionModel, VelocityMotionModel
from slam.range_bearing import RangeBearingModel

#: median of chi-square(2): 2 ln 2
CHI2_2_MEDIAN = 2.0 * math.log(2.0)
#: measurements per window, and the factor beyond which the median NIS / CHI2_2_MEDIAN changes the noise
DEFAULT_WINDOW = 60
DEFAULT_THRESHOLD = 1.6
#: the noise scale stays within these factors of the configured noise
DEFAULT_LIMITS = (1.0, 1e4)


@dataclass(frozen=True)
class ConsistencyStats:
    """What the monitor has seen and done: ``noise_scale`` (the factor on the configured noise covariances),
    ``nis_ratio`` (the latest window's median NIS / the chi-square(2) median; NaN before the first full window),
    ``measurements`` (NIS values seen), ``gated`` (of them, dropped by a gate), ``inflations`` and ``deflations``
    (times the scale grew or shrank)."""

    noise_scale: float
    nis_ratio: float
    measurements: int
    gated: int
    inflations: int
    deflations: int

    def summary(self) -> str:
        """One phrase for a command's output line."""
        ratio = "n/a" if math.isnan(self.nis_ratio) else f"{self.nis_ratio:.2f}"
        return (
            f"noise scale {self.noise_scale:.3g} ({self.inflations} inflations, {self.deflations} deflations; "
            f"latest median NIS / chi2(2) median {ratio})"
        )


class ConsistencyMonitor:
    """The sliding-window NIS watch of one filter (see the module docstring); ``adaptive`` False only watches."""

    def __init__(
        self,
        adaptive: bool = True,
        window: int = DEFAULT_WINDOW,
        threshold: float = DEFAULT_THRESHOLD,
        limits: tuple[float, float] = DEFAULT_LIMITS,
    ):
        if window < 2 or threshold <= 1.0 or not 0.0 < limits[0] <= 1.0 <= limits[1]:
            raise ValueError(
                f"need window >= 2, threshold > 1 and limits around 1, got {window}, {threshold}, {limits}"
            )
        self.adaptive = adaptive
        self.window = window
        self.threshold = threshold
        self.limits = limits
        self.scale = 1.0
        self._values: deque[float] = deque()
        self.nis_ratio = math.nan
        self.measurements = 0
        self.gated = 0
        self.inflations = 0
        self.deflations = 0

    def add(self, nis: float, gated: bool = False) -> float | None:
        """Take one measurement's NIS (NaN: none, ignored). Returns the factor m the noise scale was just multiplied
        by, for the filter to scale its covariances by, or None when the scale is unchanged."""
        if not math.isfinite(nis):
            return None
        self.measurements += 1
        self.gated += int(gated)
        self._values.append(nis)
        if len(self._values) < self.window:
            return None
        ratio = float(np.median(np.fromiter(self._values, dtype=np.float64))) / CHI2_2_MEDIAN
        self.nis_ratio = ratio
        if self.adaptive and not 1.0 / self.threshold <= ratio <= self.threshold:
            scale = min(max(self.scale * ratio, self.limits[0]), self.limits[1])
            factor = scale / self.scale
            self._values.clear()
            if factor != 1.0:
                self.inflations += int(factor > 1.0)
                self.deflations += int(factor < 1.0)
                self.scale = scale
                return factor
            return None
        for _ in range(self.window // 2):
            self._values.popleft()
        return None

    def stats(self) -> ConsistencyStats:
        return ConsistencyStats(
            self.scale, self.nis_ratio, self.measurements, self.gated, self.inflations, self.deflations
        )


@overload
def scaled_motion(motion: VelocityMotionModel, scale: float) -> VelocityMotionModel: ...
@overload
def scaled_motion(motion: OdometryMotionModel, scale: float) -> OdometryMotionModel: ...
@overload
def scaled_motion(motion: OmniOdometryMotionModel, scale: float) -> OmniOdometryMotionModel: ...
@overload
def scaled_motion(motion: MotionModel, scale: float) -> MotionModel: ...
def scaled_motion(motion: MotionModel, scale: float) -> MotionModel:
    """``motion`` with every noise variance multiplied by ``scale`` (every model's variances are linear in its
    alphas and floor)."""
    if scale == 1.0:
        return motion
    if isinstance(motion, VelocityMotionModel):
        a = motion.alphas
        alphas = (scale * a[0], scale * a[1], scale * a[2], scale * a[3], scale * a[4], scale * a[5])
        return replace(motion, alphas=alphas, floor=(scale * motion.floor[0], scale * motion.floor[1]))
    b = motion.alphas
    return replace(motion, alphas=(scale * b[0], scale * b[1], scale * b[2], scale * b[3]))


def scaled_sensor(sensor: RangeBearingModel, scale: float) -> RangeBearingModel:
    """``sensor`` with its noise covariance multiplied by ``scale`` (every std by sqrt(scale))."""
    if scale == 1.0:
        return sensor
    root = math.sqrt(scale)
    return replace(
        sensor,
        sigma_range=sensor.sigma_range * root,
        sigma_bearing=sensor.sigma_bearing * root,
        range_fraction=sensor.range_fraction * root,
    )
