"""The latest pose distribution and the trajectory of every robot, from its pg/<robot>/pose messages.

Poses are (x m, y m, yaw rad) in the map frame. A weighted-sample message is summarised by its weighted
mean (yaw: the circular mean atan2(sum w sin, sum w cos)) and weighted covariance (yaw residuals wrapped
to [-pi, pi)); a Gaussian message keeps its mean and covariance and gets :data:`DRAWN_SAMPLES` samples
drawn from it (seeded by the scan's seq, so the same message always gives the same cloud) for display.
The trajectory is the sequence of mean poses.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from schemas.messages import PoseGaussian, PoseSamples
from services.api.limits import MAX_ROBOTS, STRAY_TTL
from slam.angles import wrap_angle

#: samples drawn from a Gaussian pose for display
DRAWN_SAMPLES = 100
#: mean poses kept per robot
TRAJECTORY_LENGTH = 100_000
#: mean poses kept of all robots together (40 bytes each: 80 MB); past it the robot holding the most lets its oldest
#: go. A peer's poses under 50 robot names took 140 MB in 80 s when each was a tuple of 280 bytes, and the API's
#: 256 robots could have held 7 GB
TRAJECTORY_POSES = 2_000_000
#: a pose at most this many seqs after a robot's latest is taken (a pose or a failed step lost between): a forged
#: one there holds the real ones back for that many seqs at most
GAP_TAKE = 4
#: a pose further on is taken when it follows the pose that opened the gap by at most this many seqs (a real gap is
#: followed by the next poses; a forged seq alone is not); the pose that opened it is not taken
GAP_FOLLOW = 8


@dataclass(frozen=True)
class PoseSummary:
    """One pose distribution, both as samples and as mean + covariance."""

    robot: str
    seq: int
    stamp: float  # sensor time of the scan, s
    received: float  # Unix time the API received it, s
    form: Literal["samples", "gaussian"]  # "samples" (particles from SLAM) or "gaussian" (mean + covariance from SLAM)
    samples: np.ndarray  # (M, 3)
    weights: np.ndarray  # (M,), sums to 1
    mean: np.ndarray  # (3,)
    cov: np.ndarray  # (3, 3)


def weighted_mean_cov(samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (3,) and covariance (3, 3) of poses (M, 3); yaw averaged on the circle."""
    weights = np.asarray(weights, float) / np.sum(weights)
    yaw = np.arctan2(weights @ np.sin(samples[:, 2]), weights @ np.cos(samples[:, 2]))
    mean = np.array([weights @ samples[:, 0], weights @ samples[:, 1], yaw])
    residual = samples - mean
    residual[:, 2] = wrap_angle(residual[:, 2])
    cov = (residual * weights[:, None]).T @ residual
    return mean, 0.5 * (cov + cov.T)


def reduce_samples(samples: np.ndarray, weights: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``count`` samples: systematic resampling (pointers (k + 1/2) / count on the cumulative
    weights) when there are more, giving equal weights; the input unchanged otherwise."""
    if len(weights) <= count:
        return samples, weights
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    picks = np.minimum(np.searchsorted(cumulative, (np.arange(count) + 0.5) / count, side="right"), len(weights) - 1)
    return samples[picks], np.full(count, 1.0 / count)


def summarize(message: PoseSamples | PoseGaussian, received: float) -> PoseSummary:
    """The :class:`PoseSummary` of a decoded pose message."""
    if isinstance(message, PoseGaussian):
        rng = np.random.default_rng(message.seq)
        samples = rng.multivariate_normal(message.mean, message.cov, DRAWN_SAMPLES, method="eigh")
        weights = np.full(DRAWN_SAMPLES, 1.0 / DRAWN_SAMPLES)
        return PoseSummary(
            message.robot,
            message.seq,
            message.stamp,
            received,
            "gaussian",
            samples,
            weights,
            np.asarray(message.mean, float),
            np.asarray(message.cov, float),
        )
    mean, cov = weighted_mean_cov(message.samples, message.weights)
    return PoseSummary(
        message.robot,
        message.seq,
        message.stamp,
        received,
        "samples",
        np.asarray(message.samples, float),
        np.asarray(message.weights, float),
        mean,
        cov,
    )


def trajectory_row(message: PoseSamples | PoseGaussian) -> tuple[int, float, float, float, float]:
    """A pose message's row of the trajectory: (seq, stamp s, mean x m, y m, yaw rad)."""
    if isinstance(message, PoseGaussian):
        mean = np.asarray(message.mean, float)
    else:
        mean = weighted_mean_cov(message.samples, message.weights)[0]
    return message.seq, message.stamp, float(mean[0]), float(mean[1]), float(mean[2])


class PoseRefused(Exception):
    """A pose :meth:`RobotTracker.update` did not take: ``kind`` (the rejection counter's) and why."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(detail)
        self.kind = kind


class Track:
    """A robot's mean poses, rows (seq, stamp s, x m, y m, yaw rad), oldest first, in a ring of at most ``length``
    rows (float64: seqs below 2^53 are exact) that grows as it fills."""

    def __init__(self, length: int) -> None:
        self.length = length
        self._rows = np.empty((min(length, 1024), 5))
        self._start = 0  # the ring's row of the oldest pose
        self.count = 0

    def append(self, row: tuple[int, float, float, float, float]) -> None:
        """Add ``row`` as the newest; at ``length`` rows, the oldest goes."""
        capacity = len(self._rows)
        if self.count == capacity and capacity < self.length:
            self._rows = np.concatenate([self.rows(), np.empty((min(capacity, self.length - capacity), 5))])
            self._start, capacity = 0, len(self._rows)
        if self.count == capacity:
            self._rows[self._start] = row
            self._start = (self._start + 1) % capacity
        else:
            self._rows[(self._start + self.count) % capacity] = row
            self.count += 1

    def prepend(self, rows: np.ndarray) -> int:
        """Put ``rows`` (N, 5), older than every row held, before them, as many as ``length`` leaves room for (the
        newest of them); how many went in."""
        room = max(0, self.length - self.count)
        taken = rows[len(rows) - room :] if room < len(rows) else rows
        merged = np.concatenate([taken, self.rows()])
        self._rows = np.concatenate([merged, np.empty((max(0, min(self.length, 1024) - len(merged)), 5))])
        self._start, self.count = 0, len(merged)
        return len(taken)

    def drop_oldest(self, count: int) -> int:
        """Let the ``count`` oldest rows go (at most all of them); how many went."""
        dropped = min(count, self.count)
        self._start = (self._start + dropped) % len(self._rows)
        self.count -= dropped
        return dropped

    def rows(self) -> np.ndarray:
        """A copy of the rows, oldest first, (count, 5)."""
        end = self._start + self.count
        if end <= len(self._rows):
            return self._rows[self._start : end].copy()
        return np.concatenate([self._rows[self._start :], self._rows[: end - len(self._rows)]])


class RobotTracker:
    """Thread-safe: Zenoh callbacks call :meth:`update` and :meth:`vouch`, HTTP handlers read.

    A robot is *vouched for* once a liveliness token of one of its processes (pg/<robot>/alive/<process>: its
    source or SLAM node) has been seen; it is then kept until the API stops. Poses of a robot nobody vouched
    for are *stray*: the robot is listed, but :meth:`latest_seqs` leaves it out unless asked, and it is forgotten
    ``stray_ttl`` s after its last pose. At most ``max_robots`` robots are tracked and ``max_robots`` names
    vouched for; a pose or token beyond that is refused (the caller counts it).
    """

    def __init__(
        self,
        trajectory_length: int = TRAJECTORY_LENGTH,
        max_robots: int = MAX_ROBOTS,
        stray_ttl: float = STRAY_TTL,
        gap_follow: int = GAP_FOLLOW,
        trajectory_poses: int = TRAJECTORY_POSES,
    ) -> None:
        self._lock = threading.Lock()
        self._latest: dict[str, PoseSummary] = {}
        self._trajectory: dict[str, Track] = {}
        self._poses = 0  # rows of every track
        self._poses_limit = trajectory_poses
        self._heard: dict[str, float] = {}  # robot -> time.monotonic() of its latest pose
        self._vouched: set[str] = set()
        self._ahead: dict[str, int] = {}  # robot -> the last pose seq refused as too far ahead (a gap, if followed)
        self.gap_follow = gap_follow
        self._length = trajectory_length
        self.max_robots = max_robots
        self.stray_ttl = stray_ttl

    def update(self, message: PoseSamples | PoseGaussian) -> PoseSummary:
        """Take a new pose message; returns its summary. Raises PoseRefused for a robot not tracked yet while
        ``max_robots`` are (``capacity``), for a pose whose seq is not above the robot's latest (``stale``: a
        restarted SLAM node publishing the run again, or a second node under the robot's name), so that the latest
        pose never goes back and the trajectory holds each seq once, in order, as the first publisher gave it; and
        for one more than GAP_TAKE after the latest (``ahead``), unless it follows such a pose within ``gap_follow``
        seqs (a real gap is followed by the next poses; a forged seq alone is not), so that one forged pose ahead
        cannot make the real ones stale for more than GAP_TAKE seqs."""
        now = time.monotonic()
        with self._lock:
            self._check_known(message, now)  # (before the summary's work: a refused flood costs little)
        summary = summarize(message, time.time())
        with self._lock:
            self._check_known(message, now)  # (again: another callback may have taken a pose of the robot meanwhile)
            self._check_gap(message)
            self._latest[summary.robot] = summary
            self._heard[summary.robot] = now
            track = self._trajectory.setdefault(summary.robot, Track(self._length))
            x, y, yaw = (float(v) for v in summary.mean)  # mean: (3,)
            before = track.count
            track.append((summary.seq, summary.stamp, x, y, yaw))
            self._poses += track.count - before
            if self._poses > self._poses_limit:
                self._let_oldest_go()
        return summary

    def backfill(self, robot: str, rows: np.ndarray) -> int:
        """Put the poses ``rows`` (N, 5: seq, stamp, x, y, yaw, in seq order) that came before the robot's first
        pose this process took (from its histories: a restarted API) at the start of its trajectory; rows not
        before that first pose are left out. How many went in (0 for a robot not tracked)."""
        with self._lock:
            track = self._trajectory.get(robot)
            if track is None or track.count == 0 or len(rows) == 0:
                return 0
            first = track.rows()[0, 0]
            earlier = rows[rows[:, 0] < first]
            taken = track.prepend(earlier)
            self._poses += taken
            if self._poses > self._poses_limit:
                self._let_oldest_go()
            return taken

    def _let_oldest_go(self) -> None:
        """Past ``trajectory_poses`` rows in all, the robot holding the most lets its oldest go: the excess, and a
        sixteenth of the limit more (so that the robots are not looked over at every pose), holding the lock."""
        largest = max(self._trajectory.values(), key=lambda track: track.count)
        self._poses -= largest.drop_oldest(self._poses - self._poses_limit + self._poses_limit // 16)

    def _check_known(self, message: PoseSamples | PoseGaussian, now: float) -> None:
        """:meth:`update`'s refusals that change nothing (capacity, stale), holding the lock."""
        latest = self._latest.get(message.robot)
        if latest is None:
            self._expire(now)
            if len(self._latest) >= self.max_robots:
                raise PoseRefused("capacity", f"{self.max_robots} robots are tracked already (--max-robots)")
        elif message.seq <= latest.seq:
            raise PoseRefused(
                "stale",
                f"a pose of robot {message.robot!r} for seq {message.seq}, not after its latest, seq {latest.seq} (a "
                "restarted SLAM node publishing the run again, or a second SLAM node under the robot's name): the "
                "latest pose and the trajectory keep the poses they have",
            )

    def _check_gap(self, message: PoseSamples | PoseGaussian) -> None:
        """:meth:`update`'s refusal of a pose past a gap (ahead), holding the lock, after :meth:`_check_known`: it
        notes the seq that opened a gap, so it runs once a pose."""
        latest = self._latest.get(message.robot)
        if latest is not None and message.seq > latest.seq + GAP_TAKE:
            held = self._ahead.get(message.robot)
            self._ahead[message.robot] = message.seq
            if held is None or not 0 < message.seq - held <= self.gap_follow:
                raise PoseRefused(
                    "ahead",
                    f"a pose of robot {message.robot!r} for seq {message.seq}, past its latest, seq {latest.seq}, with "
                    "a gap (lost poses, or a stray or forged seq, which would make the real poses stale): taken once "
                    f"the next pose follows it within {self.gap_follow} seqs",
                )
        self._ahead.pop(message.robot, None)

    def vouch(self, robot: str) -> bool:
        """Record that a process of ``robot`` declared its liveliness token; False when refused (``max_robots``
        names are vouched for already)."""
        with self._lock:
            if robot not in self._vouched and len(self._vouched) >= self.max_robots:
                return False
            self._vouched.add(robot)
            return True

    def vouched(self) -> set[str]:
        """The robots a process liveliness token vouched for."""
        with self._lock:
            return set(self._vouched)

    def expire(self) -> None:
        """Forget the stray robots whose last pose is more than ``stray_ttl`` s old."""
        with self._lock:
            self._expire(time.monotonic())

    def _expire(self, now: float) -> None:
        """:meth:`expire` holding the lock."""
        for robot in [r for r, heard in self._heard.items() if r not in self._vouched and now - heard > self.stray_ttl]:
            self._poses -= self._trajectory[robot].count
            del self._latest[robot], self._trajectory[robot], self._heard[robot]

    def robots(self) -> list[str]:
        """Every robot tracked (stray ones whose time is up are forgotten first)."""
        with self._lock:
            self._expire(time.monotonic())
            return sorted(self._latest)

    def tracked(self, robot: str) -> bool:
        """Whether ``robot`` has a pose tracked now (no expiry walk: asked once a pose message)."""
        with self._lock:
            return robot in self._latest

    def latest(self, robot: str) -> PoseSummary | None:
        """The robot's latest pose; None for a robot not tracked (or a stray one whose time is up)."""
        with self._lock:
            self._expire(time.monotonic())
            return self._latest.get(robot)

    def latest_seqs(self, vouched_only: bool = False) -> dict[str, int]:
        """The seq of the latest pose of every robot (only of those vouched for, with ``vouched_only``)."""
        with self._lock:
            return {
                robot: summary.seq
                for robot, summary in self._latest.items()
                if not vouched_only or robot in self._vouched
            }

    def trajectory(self, robot: str) -> np.ndarray:
        """Rows (seq, stamp s, x m, y m, yaw rad) of the robot's mean poses, oldest first; (0, 5) if unknown."""
        with self._lock:
            track = self._trajectory.get(robot)
            return np.empty((0, 5)) if track is None else track.rows()
