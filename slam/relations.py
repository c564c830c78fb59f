"""The SLAM benchmark's relation error (Kuemmerle et al. 2009, 'On measuring the accuracy of SLAM algorithms').

A relation file holds one relation per line, ``t1 t2 dx dy dz roll pitch yaw``: the true motion from the
robot's pose at time t1 to its pose at t2, expressed in the frame of the pose at t1 (m, rad). Only the
planar part (dx, dy, yaw) is used. For an estimated trajectory x(t) the estimated relation is
delta = x(t1)^-1 (+) x(t2), and its error against the true delta* is split into a translational part
|t(delta) - t(delta*)| (m; the norm of the translation of delta (-) delta*, which rotation does not
change) and a rotational part |wrap(yaw(delta) - yaw(delta*))| (rad). The score is the mean and standard
deviation of both over the relations, and of their squares (the paper reports both).

Matching relations to the trajectory by time: a relation stamp takes the trajectory pose whose stamp is
within ``tolerance`` seconds (default 1 ms; the benchmark's stamps are scan stamps printed to 1 us or
10 us); otherwise the pose is interpolated linearly (x, y, unwrapped yaw) between the two trajectory poses
around it when those are at most ``max_gap`` seconds apart (default 5 s, the longest odometry gaps of
the logs). A relation with an endpoint that matches neither way is skipped and counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.angles import wrap_angle
from slam.errors import InputError, LogFormatError, finite_array, refuse_special_file
from slam.laserlog import LaserLog, Skipped

#: a relation stamp and a trajectory stamp closer than this (s) are the same instant
DEFAULT_TOLERANCE = 1e-3
#: interpolate a pose only between trajectory stamps at most this far apart (s)
DEFAULT_MAX_GAP = 5.0
#: m: a relation's displacement beyond this is no robot's (its squared error would overflow the scores)
MAX_DISPLACEMENT = 1e6


@dataclass(frozen=True)
class Relations:
    """N relative-pose relations: true motion ``delta`` (dx m, dy m, dyaw rad) from t1 to t2 in t1's frame."""

    t1: np.ndarray  # float64 (N,) s
    t2: np.ndarray  # float64 (N,) s
    delta: np.ndarray  # float64 (N, 3)
    lines: np.ndarray  # int64 (N,): 1-based line number of each relation
    skipped: tuple[Skipped, ...] = ()

    def __post_init__(self) -> None:
        """InputError unless t1, t2 (N,) s and delta (N, 3) are finite and lines (N,) matches them: a NaN stamp
        would match no pose and leave its relation silently unscored. O(N)."""
        count = len(finite_array("Relations.t1", self.t1, (None,), " (s)"))
        finite_array("Relations.t2", self.t2, (count,), " (s; one per t1)")
        finite_array("Relations.delta", self.delta, (count, 3), " (dx m, dy m, dyaw rad; one row per t1)")
        if np.shape(self.lines) != (count,):
            raise InputError(
                f"Relations.lines must have shape ({count},) (one line number per t1), got {np.shape(self.lines)}"
            )

    def __len__(self) -> int:
        return len(self.t1)


@dataclass(frozen=True)
class Trajectory:
    """Timed robot poses (x m, y m, yaw rad) in one frame, sorted by stamp (s)."""

    stamps: np.ndarray  # float64 (K,)
    poses: np.ndarray  # float64 (K, 3)

    def __post_init__(self) -> None:
        """InputError unless the stamps (K,) s and poses (K, 3) are finite, one pose per stamp, and the stamps in
        order (:meth:`sorted` sorts records): a NaN pose would make every score NaN. O(K)."""
        stamps = _checked_records(self.stamps, self.poses)
        if np.any(np.diff(stamps) < 0.0):
            at = int(np.argmax(np.diff(stamps) < 0.0)) + 1
            raise InputError(
                f"Trajectory.stamps must be in order: stamp {at} ({stamps[at]:.6f} s) is earlier than stamp {at - 1} "
                f"({stamps[at - 1]:.6f} s); build it with Trajectory.sorted"
            )

    @staticmethod
    def sorted(stamps: np.ndarray, poses: np.ndarray) -> Trajectory:
        """A trajectory from unsorted records: stamps (K,) s, poses (K, 3) (x m, y m, yaw rad), finite, one pose
        per stamp (else InputError); a stable sort, so equal stamps keep their order."""
        _checked_records(stamps, poses)
        order = np.argsort(stamps, kind="stable")
        return Trajectory(np.asarray(stamps, np.float64)[order], np.asarray(poses, np.float64)[order])


def _checked_records(stamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """``stamps`` as float64 (K,), InputError unless they and ``poses`` (K, 3) are finite and as many."""
    stamps = finite_array("Trajectory.stamps", stamps, (None,), " (s)")
    finite_array(
        "Trajectory.poses", poses, (len(stamps), 3), f" (x m, y m, yaw rad: one row per stamp, {len(stamps)} stamps)"
    )
    return stamps


def _check_seconds(name: str, value: float) -> None:
    """InputError unless ``value`` is a number of seconds >= 0 (inf: no bound)."""
    try:
        ok = float(value) >= 0.0  # NaN fails
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"{name} must be a number of seconds >= 0 (inf: no bound), got {value!r}")


@dataclass(frozen=True)
class RelationScore:
    """Per-relation errors over the relations that could be matched, and what could not."""

    trans_error: np.ndarray  # (U,) m
    rot_error: np.ndarray  # (U,) rad
    used: np.ndarray  # bool (N,): relation i was matched and scored
    total: int  # N

    def summary(self) -> dict[str, float]:
        """Mean and std (population) of the absolute and squared errors, m, rad and degrees."""
        t, r = self.trans_error, self.rot_error
        return {
            "relations_used": int(self.used.sum()),
            "relations_total": self.total,
            "trans_mean_m": float(t.mean()),
            "trans_std_m": float(t.std()),
            "rot_mean_rad": float(r.mean()),
            "rot_std_rad": float(r.std()),
            "rot_mean_deg": math.degrees(float(r.mean())),
            "rot_std_deg": math.degrees(float(r.std())),
            "trans_sq_mean_m2": float((t * t).mean()),
            "trans_sq_std_m2": float((t * t).std()),
            "rot_sq_mean_deg2": float((np.degrees(r) ** 2).mean()),
            "rot_sq_std_deg2": float((np.degrees(r) ** 2).std()),
        }


def read_relations(path: str | Path) -> Relations:
    """Read a relation file (``t1 t2 dx dy dz roll pitch yaw`` per line, white-space separated).

    Blank and ``#`` lines are passed over; a line with another field count, a field that is not a finite
    number, t1 == t2, or a displacement beyond :data:`MAX_DISPLACEMENT` is skipped and recorded with its line
    number. Raises :class:`LogFormatError` when the file cannot be read, holds no relation, or an angle of more than a
    full turn (a file in degrees: a probe's scored with exit 0, its rotational error 91.9 deg).
    """
    path = Path(path)
    refuse_special_file(path, "relation file")
    if not path.is_file():
        raise LogFormatError(f"{path}: no such file (expected a relation file)")
    rows, lines, skipped = [], [], []
    with path.open("rt", encoding="ascii", errors="replace") as stream:
        for number, text in enumerate(stream, start=1):
            tokens = text.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            if len(tokens) != 8:
                skipped.append(Skipped(number, f"has {len(tokens)} fields, a relation needs 8"))
                continue
            try:
                values = [float(t) for t in tokens]
            except ValueError:
                skipped.append(Skipped(number, "a field is not a number"))
                continue
            if not all(math.isfinite(v) for v in values):
                skipped.append(Skipped(number, "a field is not finite"))
            elif values[0] == values[1]:
                skipped.append(Skipped(number, "t1 equals t2"))
            elif max(abs(v) for v in values[2:5]) > MAX_DISPLACEMENT:
                skipped.append(Skipped(number, f"a displacement beyond {MAX_DISPLACEMENT:g} m"))
            elif max(abs(v) for v in values[5:8]) > 2.0 * math.pi:  # (a file in degrees: not one line's fault)
                raise LogFormatError(
                    f"{path}:{number}: an angle of {max(values[5:8], key=abs):g} is more than a full turn: a relation "
                    "file's roll, pitch and yaw are in rad"
                )
            else:
                rows.append(values)
                lines.append(number)
    if not rows:
        raise LogFormatError(f"{path}: holds no relation (lines 't1 t2 dx dy dz roll pitch yaw')")
    data = np.array(rows)
    return Relations(
        t1=data[:, 0], t2=data[:, 1], delta=data[:, [2, 3, 7]], lines=np.array(lines, np.int64), skipped=tuple(skipped)
    )


def trajectory_from_log(log: LaserLog) -> Trajectory:
    """The timed poses a log states: each scan's pose, plus its odometry stream where that has a stamp.

    Raw logs state odometry; SLAM-corrected CARMEN logs state the corrected pose in their laser lines and
    odometry carried forward from it in their ODOM lines. ODOM lines stamped exactly 0 (corrected logs use
    them to repeat the corrected pose) carry no time and are left out; where an ODOM record and a scan
    share a stamp, the scan's pose is used.
    """
    odom_ok = log.odom_stamps != 0.0
    odom_stamps = log.odom_stamps[odom_ok]
    odom_poses = log.odom_poses[odom_ok]
    shadowed = np.isin(odom_stamps, log.stamps)
    stamps = np.concatenate([log.stamps, odom_stamps[~shadowed]])
    poses = np.concatenate([log.poses, odom_poses[~shadowed]]).reshape(-1, 3)
    return Trajectory.sorted(stamps, poses)


def poses_at(
    trajectory: Trajectory, query: np.ndarray, tolerance: float = DEFAULT_TOLERANCE, max_gap: float = DEFAULT_MAX_GAP
) -> tuple[np.ndarray, np.ndarray]:
    """Poses (Q, 3) of ``trajectory`` at the ``query`` stamps (s) and a mask (Q,) of those it has.

    A stamp within ``tolerance`` of a trajectory stamp takes that pose (the nearest); one between two
    trajectory stamps at most ``max_gap`` apart takes the linear interpolation; others are not had. InputError for
    an empty trajectory, a query stamp that is not finite, or a tolerance or max_gap (s) that is NaN or negative.
    """
    stamps = trajectory.stamps
    if len(stamps) == 0:
        raise InputError("the trajectory has no poses: give one with at least one timed pose")
    _check_seconds("tolerance", tolerance)
    _check_seconds("max_gap", max_gap)
    query = finite_array("query stamps", query, (None,), " (s)")
    right = (
        np.clip(np.searchsorted(stamps, query), 1, len(stamps) - 1) if len(stamps) > 1 else np.zeros(len(query), int)
    )
    left = np.maximum(right - 1, 0)
    nearest = np.where(np.abs(stamps[left] - query) <= np.abs(stamps[right] - query), left, right)
    exact = np.abs(stamps[nearest] - query) <= tolerance
    inside = (stamps[left] <= query) & (query <= stamps[right]) & (stamps[right] - stamps[left] <= max_gap)
    out = np.where(exact[:, None], trajectory.poses[nearest], np.nan)
    between = inside & ~exact
    if between.any():
        pair_t = np.stack([stamps[left[between]], stamps[right[between]]], axis=1)
        pair_p = np.stack([trajectory.poses[left[between]], trajectory.poses[right[between]]], axis=1)
        frac = (query[between] - pair_t[:, 0]) / (pair_t[:, 1] - pair_t[:, 0])
        dyaw = wrap_angle(pair_p[:, 1, 2] - pair_p[:, 0, 2])
        out[between, :2] = pair_p[:, 0, :2] + frac[:, None] * (pair_p[:, 1, :2] - pair_p[:, 0, :2])
        out[between, 2] = wrap_angle(pair_p[:, 0, 2] + frac * dyaw)
    return out, exact | between


def relative_motion(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a^-1 (+) b for pose rows (N, 3): the motion from a to b in a's frame (dx m, dy m, dyaw rad)."""
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[:, 2] - a[:, 2])], axis=1)


def score_relations(
    trajectory: Trajectory,
    relations: Relations,
    tolerance: float = DEFAULT_TOLERANCE,
    max_gap: float = DEFAULT_MAX_GAP,
) -> RelationScore:
    """Translational (m) and rotational (rad) error of every relation the trajectory can be matched to.

    Raises :class:`LogFormatError` when no relation matches (usually: the stamps are in another time base),
    InputError for no relations, an empty trajectory or a tolerance or max_gap (s) that is NaN or negative.
    """
    if len(relations) == 0:
        raise InputError("relations: there are none to score; give at least one relation")
    p1, ok1 = poses_at(trajectory, relations.t1, tolerance, max_gap)
    p2, ok2 = poses_at(trajectory, relations.t2, tolerance, max_gap)
    used = ok1 & ok2
    if not used.any():
        span = f"{trajectory.stamps[0]:.6f} .. {trajectory.stamps[-1]:.6f} s" if len(trajectory.stamps) else "empty"
        raise LogFormatError(
            f"no relation matches the trajectory's stamps (relations {relations.t1.min():.6f} .. "
            f"{relations.t2.max():.6f} s, trajectory {span}); are they in the same time base?"
        )
    estimate = relative_motion(p1[used], p2[used])
    truth = relations.delta[used]
    trans = np.hypot(estimate[:, 0] - truth[:, 0], estimate[:, 1] - truth[:, 1])
    rot = np.abs(wrap_angle(estimate[:, 2] - truth[:, 2]))
    return RelationScore(trans_error=trans, rot_error=rot, used=used, total=len(relations))
