"""Odometry that jumps: a step too long to be a move, and a reset of the odometry's frame (grid FastSLAM).

A robot's odometry moves a few centimetres to a few metres between two scans. A step of tens of metres is no move:
a corrupt message, or the odometry's driver restarting its frame (at zero, or wherever it starts). Grid FastSLAM
fed such a step moves every particle with it and starts a second copy of the map there. :class:`OdometryJumps`
decides, step by step, as the live SLAM node (services.state.slam.GridDriver) and ``posegrid slam --algo gridslam``
(:func:`joined_odometry`) both use it: a step of more than ``max_step`` m from the last step taken, or faster than
:data:`MAX_ODOMETRY_SPEED` (past :data:`JUMP_FLOOR`), is refused, unless it is the :data:`REBASE_STEPS`-th such step
in a row, each a move from the one before: then the odometry was reset, and the step is taken as its new frame, the
robot not having moved across the reset.
"""

from __future__ import annotations

import enum
import math
from dataclasses import replace

import numpy as np

from slam.angles import wrap_angle
from slam.laserlog import LaserLog, Skipped

#: the farthest the odometry may move from one step to the next, m (a scan every 5 s at 10 m/s): one odometry
#: message moved 3 km took a grid FastSLAM node to 13 GB, as every particle's tile table spans the particles' box
MAX_ODOMETRY_STEP = 50.0

#: the fastest a robot's odometry may move, m/s (180 km/h), and the least a step is allowed whatever its time (stamps
#: of a log jitter by milliseconds: 0.17 m in 1.7 ms in the Intel lab's bag): a step past both is no move
MAX_ODOMETRY_SPEED = 50.0
JUMP_FLOOR = 2.0

#: consecutive steps that agree with each other but not with the odometry before them after which they are taken
#: as the odometry's new frame (a reset of the robot's odometry), not as a jump
REBASE_STEPS = 3


class Verdict(enum.Enum):
    """What to do with one step's odometry pose."""

    STEP = "step"  # a move from the last step taken
    REFUSED = "refused"  # a jump: leave the step out
    REBASE = "rebase"  # the odometry's new frame: take it, the robot not having moved across the reset


class OdometryJumps:
    """The jump rule of the module docstring, fed one odometry pose (x m, y m, yaw rad) a step, with its stamp (s).

    A step may move at most ``max_step`` m, and, when it comes ``dt`` s after the last step taken, at most
    max(:data:`JUMP_FLOOR`, :data:`MAX_ODOMETRY_SPEED` dt) m: a reset of 30 m between two scans 0.1 s apart is no
    move, though under 50 m. (Stamps that run backwards or are missing give no speed: ``max_step`` alone.)"""

    def __init__(self, max_step: float = MAX_ODOMETRY_STEP) -> None:
        if not max_step > 0 or not math.isfinite(max_step):
            raise ValueError(f"max_step must be a finite distance > 0 m, got {max_step}")
        self.max_step = max_step
        self._last: tuple[np.ndarray, float] | None = None  # the odometry pose (3,) and stamp of the last step taken
        self._jumped: list[tuple[np.ndarray, float]] = []  # the steps refused since, each near the one before
        self.reason = ""  # why the last step was refused or rebased ("" for a move)

    def limit(self, dt: float) -> float:
        """The farthest a step ``dt`` s after another may move, m."""
        if not dt > 0 or not math.isfinite(dt):
            return self.max_step
        return min(self.max_step, max(JUMP_FLOOR, MAX_ODOMETRY_SPEED * dt))

    def _jump(self, pose: np.ndarray, stamp: float, since: tuple[np.ndarray, float]) -> str:
        """Why ``pose`` at ``stamp`` is no move from ``since`` ("" when it is one)."""
        moved = float(np.hypot(*(pose[:2] - since[0][:2])))
        dt = stamp - since[1]
        limit = self.limit(dt)
        if moved <= limit:
            return ""
        if limit == self.max_step:
            return f"the odometry moved {moved:.3g} m since the last step, more than the {limit:g} m a step may"
        return (
            f"the odometry moved {moved:.3g} m in {dt:.3g} s since the last step, more than the {limit:.3g} m a robot "
            f"moves at {MAX_ODOMETRY_SPEED:g} m/s"
        )

    def check(self, pose: np.ndarray, stamp: float = math.nan) -> Verdict:
        """The verdict on the next step's odometry ``pose`` (3,) at ``stamp`` (s; NaN: not known); :attr:`reason`
        says why for a jump or a reset."""
        pose = np.asarray(pose, np.float64)
        verdict = Verdict.STEP
        self.reason = ""
        why = "" if self._last is None else self._jump(pose, stamp, self._last)
        if why:
            near_run = bool(self._jumped) and not self._jump(pose, stamp, self._jumped[-1])
            self._jumped = [*self._jumped, (pose.copy(), stamp)] if near_run else [(pose.copy(), stamp)]
            if len(self._jumped) < REBASE_STEPS:
                self.reason = f"{why} (taken as a reset of the odometry after {REBASE_STEPS} such steps in a row)"
                return Verdict.REFUSED
            self.reason = (
                f"{why.replace('the last step', 'the last step taken')}, and the {REBASE_STEPS} steps from there "
                "agree: taken as a reset of the odometry, the robot not having moved across it"
            )
            verdict = Verdict.REBASE
        self._jumped = []
        self._last = (pose.copy(), stamp)
        return verdict


def joined_odometry(log: LaserLog, max_step: float = MAX_ODOMETRY_STEP) -> LaserLog:
    """``log`` with :class:`OdometryJumps` applied to its scans' odometry in file order: a refused scan is left out
    (listed in ``skipped`` with the reason), and from a reset on the odometry is carried over into the frame before
    it (the robot not having moved from the last scan kept to the reset's first), with a note. ``poses`` follow
    where they are the odometry (a raw log). The log itself when nothing jumps."""
    jumps = OdometryJumps(max_step)
    kept = np.ones(len(log), bool)
    odometry = log.odometry.copy()
    dropped: list[Skipped] = []
    notes: list[str] = []
    last_kept: int | None = None
    for t in range(len(log)):
        verdict = jumps.check(log.odometry[t], float(log.stamps[t]))
        if verdict is Verdict.REFUSED:
            kept[t] = False
            dropped.append(Skipped(int(log.where[t]), jumps.reason))
            continue
        if verdict is Verdict.REBASE and last_kept is not None:
            odometry[t:] = _carried(log.odometry[t:], log.odometry[t], odometry[last_kept])
            notes.append(f"{log.unit} {int(log.where[t])}: {jumps.reason}")
        last_kept = t
    if not dropped and not notes:
        return log
    states_poses = not np.allclose(log.poses, log.odometry, atol=1e-6)  # (as slam.gridslam.health judges it)
    joined = replace(log, odometry=odometry, poses=log.poses if states_poses else odometry).select(kept)
    return replace(
        joined,
        skipped=tuple(sorted(log.skipped + tuple(dropped), key=lambda s: s.where)),
        notes=log.notes + tuple(notes),
    )


def _carried(poses: np.ndarray, origin: np.ndarray, onto: np.ndarray) -> np.ndarray:
    """Poses (N, 3) in the frame where ``origin`` (3,) stands, moved rigidly so that ``origin`` lands on ``onto``."""
    turn = float(onto[2] - origin[2])
    c, s = math.cos(turn), math.sin(turn)
    dx, dy = poses[:, 0] - origin[0], poses[:, 1] - origin[1]
    return np.stack(
        [onto[0] + c * dx - s * dy, onto[1] + s * dx + c * dy, wrap_angle(poses[:, 2] + turn)],
        axis=1,
    )
