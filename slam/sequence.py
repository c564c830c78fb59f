"""The input every SLAM filter consumes and the pose track it produces, and the loop that joins them.

A :class:`SlamSequence` is a list of T steps. Step t has a stamp (s), the controls applied since step t-1
(rows of three numbers whose meaning the motion model defines, see slam.motion) and the landmark
measurements taken at the stamp (range m, bearing rad, landmark id). Both are stored flat with pointer
arrays: the controls of step t are ``controls[control_ptr[t]:control_ptr[t + 1]]``, likewise measurements.
Step 0 usually has no controls: the filter starts at ``initial_pose`` at ``stamps[0]``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from slam.errors import LogFormatError


@dataclass(frozen=True)
class SlamSequence:
    """Controls and landmark measurements for T steps (see the module docstring for the layout)."""

    stamps: np.ndarray  # float64 (T,) s
    controls: np.ndarray  # float64 (K, 3), meaning set by `motion`
    control_ptr: np.ndarray  # int64 (T + 1,)
    measurements: np.ndarray  # float64 (O, 2): range m, bearing rad (robot frame)
    landmark_ids: np.ndarray  # int64 (O,): landmark id (ignored by filters that associate on their own)
    measurement_ptr: np.ndarray  # int64 (T + 1,)
    initial_pose: np.ndarray  # float64 (3,): x m, y m, yaw rad in the map frame at stamps[0]
    motion: str  # "velocity" (controls are v m/s, w rad/s, dt s) or "odometry" (rot1 rad, trans m, rot2 rad)

    def __len__(self) -> int:
        return len(self.stamps)

    def validate(self, source: str) -> None:
        """Raise LogFormatError naming ``source`` when the arrays do not fit together."""
        steps = len(self.stamps)
        for name, ptr, rows in (
            ("control", self.control_ptr, len(self.controls)),
            ("measurement", self.measurement_ptr, len(self.measurements)),
        ):
            if ptr.shape != (steps + 1,) or ptr[0] != 0 or ptr[-1] != rows or np.any(np.diff(ptr) < 0):
                raise LogFormatError(f"{source}: the {name} pointers do not index {rows} rows over {steps} steps")
        if self.landmark_ids.shape != (len(self.measurements),):
            raise LogFormatError(
                f"{source}: {len(self.landmark_ids)} landmark ids for {len(self.measurements)} measurements"
            )
        if self.motion not in ("velocity", "odometry"):
            raise LogFormatError(f"{source}: unknown motion kind '{self.motion}' (velocity or odometry)")
        for name, values in (
            ("stamps", self.stamps),
            ("controls", self.controls),
            ("measurements", self.measurements),
            ("initial pose", self.initial_pose),
        ):
            if not np.all(np.isfinite(values)):
                raise LogFormatError(f"{source}: the {name} hold NaN or inf")
        if steps == 0:
            raise LogFormatError(f"{source}: has no steps")
        if np.any(np.diff(self.stamps) < 0):
            raise LogFormatError(
                f"{source}: the step stamps go backwards at step {int(np.argmax(np.diff(self.stamps) < 0)) + 1}"
            )


@dataclass(frozen=True)
class PoseTrack:
    """A filter's pose distribution at every step, in the map frame: Gaussian or weighted particles.

    Exactly one form is set: ``mean`` (T, 3) and ``cov`` (T, 3, 3), or ``samples`` (T, N, 3) (x m, y m,
    yaw rad) and ``weights`` (T, N) summing to 1 per row (taken before any resampling at that step).
    """

    stamps: np.ndarray
    mean: np.ndarray | None = None
    cov: np.ndarray | None = None
    samples: np.ndarray | None = None
    weights: np.ndarray | None = None

    @property
    def is_gaussian(self) -> bool:
        return self.mean is not None


class Filter(Protocol):
    """What :func:`run_filter` drives: one call per step returning the pose distribution at that step."""

    gaussian: bool

    def step(
        self, controls: np.ndarray, measurements: np.ndarray, landmark_ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Apply controls (K, 3), then measurements (O, 2) with ids (O,); return (mean, cov) or (samples, weights)."""


def run_filter(slam_filter: Filter, sequence: SlamSequence, progress: Callable[[int], None] | None = None) -> PoseTrack:
    """Run ``slam_filter`` over every step of ``sequence``; ``progress(k)`` is called after every k steps done."""
    first, second = [], []
    cptr, mptr = sequence.control_ptr, sequence.measurement_ptr
    for t in range(len(sequence)):
        a, b = slam_filter.step(
            sequence.controls[cptr[t] : cptr[t + 1]],
            sequence.measurements[mptr[t] : mptr[t + 1]],
            sequence.landmark_ids[mptr[t] : mptr[t + 1]],
        )
        first.append(a)
        second.append(b)
        if progress is not None:
            progress(1)
    if slam_filter.gaussian:
        return PoseTrack(stamps=sequence.stamps.copy(), mean=np.array(first), cov=np.array(second))
    return PoseTrack(stamps=sequence.stamps.copy(), samples=np.array(first), weights=np.array(second))
