"""What a 2D laser log reader returns: scans with odometry, in arrays, plus what it had to skip.

Frames and units: ``odometry`` and ``poses`` are robot poses (x m, y m, yaw rad) in the log's odometry
frame (``poses``: the frame of whatever produced them, e.g. a SLAM-corrected map frame); ``sensor_offset`` is
the laser's (x m, y m, yaw rad) in the robot frame; ranges are metres along each beam from the laser,
``+inf`` where the log records no return (a reading at or beyond the scan's maximum range).

Every scan keeps its own geometry: its beam count, angle_min, angle_increment, range limits and the laser's
offset on the robot, so an interlaced laser (successive scans shifted by a fraction of a step), a laser whose
beam count changes and two lasers on one topic are all read in full. ``ranges`` is (T, Bmax), where Bmax is
the largest beam count; row t holds scan t's ``beams[t]`` readings first, then NaN padding that no consumer
reads (:meth:`LaserLog.scan_ranges` gives the scan's own readings).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from slam.angles import wrap_angle
from slam.errors import LogFormatError

#: a scan between two odometry records further apart than this (s) has no odometry pose (it is skipped)
MAX_ODOM_GAP = 5.0
#: a scan before the first or after the last odometry record by more than this (s) has no odometry pose
MAX_ODOM_HOLD = 0.5

#: the farthest a pose coordinate (m, and rad for yaw) may lie from the origin: 10 000 km. The same bound as the
#: wire's (schemas.messages.POSE_LIMIT), stated again here because slam/ does not import schemas/
POSE_LIMIT = 1e7


def plausible_pose(pose: tuple[float, float, float]) -> bool:
    """Whether a pose (x m, y m, yaw rad) is finite and within +-POSE_LIMIT (10 000 km) in
    every coordinate: the readers skip records beyond it, whose maps and covariances would overflow."""
    return all(math.isfinite(v) and abs(v) <= POSE_LIMIT for v in pose)


#: the longest range_max a scan is read with, m: no 2D laser measures a kilometre. A ROS LaserScan may state +inf (the
#: default of ROS 2's pointcloud_to_laserscan, whose range_max parameter defaults to the largest double, inf as the
#: message's float32) or a value beyond any laser; its readings up to this are returns, the rest no return.
RANGE_MAX_CEILING = 1000.0


def bounded_range_max(range_max: float) -> float:
    """A scan's range_max (m) as the readers take it: at most :data:`RANGE_MAX_CEILING` (+inf and any larger value
    become it; NaN stays NaN, for the geometry checks to refuse)."""
    return RANGE_MAX_CEILING if range_max > RANGE_MAX_CEILING else range_max


@dataclass(frozen=True)
class Skipped:
    """One input record a reader could not use: where it is (1-based line or message number) and why."""

    where: int
    reason: str


#: what the rows of ``LaserLog.ranges`` (and a posed-scan file's) hold past a scan's own beam count
PADDING = np.nan

#: a scan's laser geometry as one hashable key: (beams, angle_min rad, angle_increment rad, range_min m,
#: range_max m, offset x m, offset y m, offset yaw rad)
GeometryKey = tuple[int, float, float, float, float, float, float, float]


def geometry_problem(beams: int, angle_min: float, angle_increment: float, range_min: float, range_max: float) -> str:
    """Why a scan of ``beams`` beams with this geometry (rad, m) is unusable in itself, or "": a value that is not
    finite, range limits outside 0 <= range_min < range_max, no beam, an increment of 0 for several beams (every
    beam would point one way), an angle beyond a full turn (the beams' directions lose their precision), or beams
    that sweep more than a full turn (the wire and the posed-scan files refuse them: the map would see walls twice;
    a fan of exactly a turn, as some 360 deg scanners give, passes)."""
    values = (angle_min, angle_increment, range_min, range_max)
    if not all(math.isfinite(v) for v in values):
        return "its angle_min, angle_increment, range_min or range_max is not finite"
    if beams < 1:
        return "it has no beam"
    if not 0.0 <= range_min < range_max:
        return f"range_min {range_min:g} m and range_max {range_max:g} m: need 0 <= range_min < range_max"
    if angle_increment == 0.0 and beams > 1:
        return f"angle_increment is 0 for {beams} beams"
    if max(abs(angle_min), abs(angle_increment)) > 2 * math.pi:
        return "angle_min or angle_increment beyond a full turn"
    span = (beams - 1) * abs(angle_increment)
    if span > 2 * math.pi + 0.5 * abs(angle_increment):  # schemas.files.fan_past_a_turn's rule (slam cannot import it)
        return (
            f"{beams} beams {angle_increment:g} rad apart sweep {span:.6g} rad, more than a full turn (beams would "
            "repeat directions)"
        )
    return ""


def per_scan(value, steps: int, columns: int = 0) -> np.ndarray:
    """``value`` (a number, or one per scan) as a float64 array of one row per scan: (steps,), or (steps,
    columns) when ``columns`` (a (columns,) value is shared by every scan). Raises ValueError on another shape."""
    array = np.asarray(value, np.float64)
    shape = (steps, columns) if columns else (steps,)
    if array.shape not in (shape, shape[1:]):
        raise ValueError(f"expected one value per scan {shape} or one for all {shape[1:]}, got shape {array.shape}")
    return np.array(np.broadcast_to(array, shape))


@dataclass(frozen=True)
class LaserLog:
    """T laser scans in file order, each with its own geometry and the robot's odometry pose at the scan's time.

    The geometry fields may be given as one value for every scan (a number; (3,) for the offset) and are kept
    per scan; scan t's readings are ``ranges[t, :beams[t]]``, and ``beams`` defaults to every scan filling its row
    of ``ranges``."""

    source: str  # file the log came from, for messages
    stamps: np.ndarray  # float64 (T,) s
    ranges: np.ndarray  # float32 (T, Bmax) m; +inf = no return; PADDING (NaN) past beams[t]
    angle_min: np.ndarray  # float64 (T,) rad, laser frame
    angle_increment: np.ndarray  # float64 (T,) rad
    range_min: np.ndarray  # float64 (T,) m
    range_max: np.ndarray  # float64 (T,) m
    sensor_offset: np.ndarray  # float64 (T, 3): laser pose in the robot frame at each scan
    odometry: np.ndarray  # float64 (T, 3): robot odometry pose at each scan
    poses: np.ndarray  # float64 (T, 3): the robot pose the log states for each scan (corrected logs: SLAM pose)
    where: np.ndarray  # int64 (T,): the 1-based line or message number of each scan
    odom_stamps: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) s: separate odometry stream
    odom_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (K, 3)
    params: dict[str, str] = field(default_factory=dict)
    skipped: tuple[Skipped, ...] = ()
    notes: tuple[str, ...] = ()  # what the reader took for granted where the log is silent, one sentence each
    unit: str = "line"  # what `where` counts: "line" or "message"
    beams: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # int64 (T,); empty: whole rows

    def __post_init__(self) -> None:
        steps = len(self.stamps)
        for name in ("angle_min", "angle_increment", "range_min", "range_max"):
            object.__setattr__(self, name, per_scan(getattr(self, name), steps))
        object.__setattr__(self, "sensor_offset", per_scan(self.sensor_offset, steps, 3))
        width = self.ranges.shape[1] if self.ranges.ndim == 2 else 0
        beams = np.asarray(self.beams, np.int64)
        if beams.size == 0:  # (the default: every scan's readings fill its row)
            beams = np.full(steps, width, np.int64)
        if self.ranges.shape != (steps, width) or beams.shape != (steps,) or (beams > width).any():
            raise ValueError(f"ranges {self.ranges.shape} and beams {beams.shape} do not fit {steps} scans")
        object.__setattr__(self, "beams", beams)

    def __len__(self) -> int:
        return len(self.stamps)

    def scan_ranges(self, t: int) -> np.ndarray:
        """Scan t's own readings (beams[t],) in m."""
        return self.ranges[t, : self.scan_beams(t)]

    def scan_beams(self, t: int) -> int:
        """Scan t's beam count."""
        return int(self.beams[t])

    def beam_angles(self, t: int) -> np.ndarray:
        """Scan t's beam angles (beams[t],) in rad, laser frame."""
        return self.angle_min[t] + self.angle_increment[t] * np.arange(self.scan_beams(t))

    def geometry_key(self, t: int) -> GeometryKey:
        """Scan t's geometry as a hashable key (:data:`GeometryKey`): scans with equal keys share one laser."""
        x, y, yaw = self.sensor_offset[t].tolist()
        return (
            self.scan_beams(t),
            float(self.angle_min[t]),
            float(self.angle_increment[t]),
            float(self.range_min[t]),
            float(self.range_max[t]),
            x,
            y,
            yaw,
        )

    def select(self, index) -> LaserLog:
        """The log's scans that ``index`` (a slice, a boolean mask or indices) picks, each with its own geometry;
        the odometry stream, parameters and skipped records are kept."""
        beams = self.beams[index]
        width = int(beams.max()) if beams.size else 0
        return replace(
            self,
            stamps=self.stamps[index],
            ranges=self.ranges[index][:, :width],
            angle_min=self.angle_min[index],
            angle_increment=self.angle_increment[index],
            range_min=self.range_min[index],
            range_max=self.range_max[index],
            sensor_offset=self.sensor_offset[index],
            odometry=self.odometry[index],
            poses=self.poses[index],
            where=self.where[index],
            beams=beams,
        )

    def first(self, count: int) -> LaserLog:
        """The log's first ``count`` scans (the odometry stream, parameters and skipped records kept)."""
        return self.select(slice(0, count))

    def remarks(self) -> list[str]:
        """What a command says of the log before it uses it: each note, then what was skipped (nothing when
        nothing was)."""
        return [f"{self.source}: {note}" for note in self.notes] + ([self.skipped_summary()] if self.skipped else [])

    def skipped_summary(self, limit: int = 5) -> str:
        """One sentence naming how many records were skipped, the first few places and their reasons."""
        if not self.skipped:
            return f"{self.source}: read {len(self)} scans, skipped nothing"
        shown = "; ".join(f"{self.unit} {s.where}: {s.reason}" for s in self.skipped[:limit])
        more = f"; and {len(self.skipped) - limit} more" if len(self.skipped) > limit else ""
        return f"{self.source}: read {len(self)} scans, skipped {len(self.skipped)} {self.unit}s ({shown}{more})"


#: how far (m) a real laser's beams with no return clear free space unless the user says otherwise: nothing. A laser
#: gives no echo from dark or glancing surfaces close by as well as from empty space: on the shared logs 2 to 3 % of
#: the beams have none, many of them pointing at walls their neighbours hit, and cleared out to the stated 80 m they
#: wiped those walls and drew free space through the building's walls (docs/sensor_model.md, section 3). 0 holds on
#: any laser; the simulated laser, which misses nothing within its range, clears up to range_max.
NO_RETURN_RANGE = 0.0

#: a no-return range more than this many times a log's farthest return gets a warning from :func:`no_return_note`
NO_RETURN_NOTE_RATIO = 1.5


def no_return_note(log: LaserLog, no_return_range: float, reach: float = math.inf) -> str | None:
    """A sentence on a log's beams with no return (+inf, or above the scan's range_max) when they are mapped with a
    ``no_return_range`` (m) of 0 (they say nothing: how many there are, and how to let them clear) or of more than
    NO_RETURN_NOTE_RATIO times the farthest return the log has (they clear free space far past anything its laser
    returned, through whatever they met). ``reach`` (m): how far the map takes any beam (grid FastSLAM's
    --max-range), which caps the clearing said as the laser's range_max does. None when the log has no such beams,
    or no return, or the range lies within reach of its returns."""
    ranges = np.asarray(log.ranges, np.float64)
    stated = np.asarray(log.range_max, np.float64)[:, None]
    no_return = np.isposinf(ranges) | (np.isfinite(ranges) & (ranges > stated))
    returns = np.isfinite(ranges) & (ranges > 0.0) & (ranges <= stated)
    if not no_return.any() or not returns.any():
        return None
    farthest = float(ranges[returns].max())
    clears = float(min(no_return_range, float(stated.max()), reach))
    share = 100.0 * np.count_nonzero(no_return) / np.count_nonzero(~np.isnan(ranges))
    if clears == 0.0:
        return (
            f"{log.source}: {share:.1f} % of its beams have no return; they clear no free space (a laser misses dark "
            f"and glancing surfaces close by too), and --no-return-range METRES lets them clear up to METRES (its "
            f"farthest return is {farthest:.1f} m)"
        )
    if clears <= NO_RETURN_NOTE_RATIO * farthest:
        return None
    return (
        f"{log.source}: its laser returned at most {farthest:.1f} m, and {share:.1f} % of its beams have no return: "
        f"with --no-return-range {no_return_range:g} each of those clears free space out to {clears:g} m"
        + (" (--max-range)" if clears == reach < min(no_return_range, float(stated.max())) else "")
        + ", through whatever the beam met (docs/sensor_model.md, section 3)"
    )


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses (Q, 3) at the ``query`` stamps (s), linear in x, y and in unwrapped yaw between neighbours.

    ``stamps`` (K,) must be non-decreasing; queries outside [stamps[0], stamps[-1]] take the end pose.
    Yaw is unwrapped along the sequence first, so interpolation across +-pi takes the short way.
    """
    yaw = np.unwrap(poses[:, 2])
    out = np.empty((len(query), 3))
    out[:, 0] = np.interp(query, stamps, poses[:, 0])
    out[:, 1] = np.interp(query, stamps, poses[:, 1])
    out[:, 2] = wrap_angle(np.interp(query, stamps, yaw))
    return out


def check_scan_order(log: LaserLog) -> None:
    """Raise :class:`LogFormatError` unless the log's scan stamps increase (a filter takes the scans in order, and a
    replay paces them by their stamps)."""
    back = np.flatnonzero(np.diff(log.stamps) <= 0)
    if len(back):
        i = int(back[0])
        raise LogFormatError(
            f"{log.source}: scan stamps must increase, but the scan at {log.unit} {log.where[i + 1]} "
            f"({log.stamps[i + 1]:.6f} s) is not later than the one before ({log.stamps[i]:.6f} s)"
        )


def check_odometry_stream(log: LaserLog) -> None:
    """Raise :class:`LogFormatError` unless the log has a separate odometry stream in time order, which reading
    the odometry at other times than the scans' needs."""
    if not len(log.odom_stamps):
        raise LogFormatError(
            f"{log.source}: its odometry comes only with the scans, so it cannot be read at "
            "other times (an odometry delay needs a separate odometry stream: ODOM lines or a "
            "bag's odometry topic)"
        )
    back = np.flatnonzero(np.diff(log.odom_stamps) < 0)
    if len(back):
        raise LogFormatError(
            f"{log.source}: its odometry stream goes back in time after its record {back[0] + 1} "
            f"({log.odom_stamps[back[0]]:.6f} s, then {log.odom_stamps[back[0] + 1]:.6f} s), so it "
            "cannot be read at other times than the scans'"
        )


def odometry_problem(
    odom_stamps: np.ndarray, stamp: float, max_gap: float = MAX_ODOM_GAP, max_hold: float = MAX_ODOM_HOLD
) -> str:
    """Why the odometry (sorted stamps, s) cannot give a pose at ``stamp``, or "" when it can: the stamp lies
    more than ``max_hold`` s outside the odometry's span, or between two odometry records more than ``max_gap``
    s apart."""
    after = int(np.searchsorted(odom_stamps, stamp, side="left"))
    if after < len(odom_stamps) and odom_stamps[after] == stamp:
        return ""
    if after == 0 or after == len(odom_stamps):
        end = odom_stamps[0] if after == 0 else odom_stamps[-1]
        if abs(end - stamp) > max_hold:
            return f"{abs(end - stamp):.6g} s outside the odometry's time span (at most {max_hold} s)"
        return ""
    gap = odom_stamps[after] - odom_stamps[after - 1]
    if gap > max_gap:
        return f"the odometry messages around it are {gap:.6g} s apart (at most {max_gap} s)"
    return ""


def with_odometry_delay(log: LaserLog, delay: float) -> LaserLog:
    """The log with each scan's odometry read from the log's separate odometry stream at stamp + ``delay``
    (s; negative: earlier). For a laser whose stamps run late against its odometry's (Freiburg 079's bag:
    about 0.13 s), so that a scan is paired with the pose the robot had when it was taken. ``poses``, what
    the log states, is left as it is where it states poses of its own (a corrected log); where they are its
    odometry (a raw log, a bag), they stay its odometry, now the shifted one. A scan whose stamp + ``delay`` has
    no odometry around it (:func:`odometry_problem`: past the stream's ends, or in a long gap) is skipped, and
    listed in ``skipped``, as the readers do with the scans' own stamps. Raises :class:`LogFormatError` when the
    log has no separate odometry stream in time order (:func:`check_odometry_stream`; e.g. a CARMEN log whose
    odometry comes only inside the laser lines) or no scan keeps its odometry."""
    if delay == 0.0:
        return log
    check_odometry_stream(log)
    problems = [odometry_problem(log.odom_stamps, stamp + delay) for stamp in log.stamps.tolist()]
    kept = np.array([not problem for problem in problems], dtype=bool)
    if not kept.any():
        raise LogFormatError(
            f"{log.source}: with the odometry read {delay:+g} s from the scans' stamps, no scan "
            f"has odometry around it ({problems[-1]})"
        )
    dropped = [
        Skipped(int(where), f"with the odometry read {delay:+g} s from its stamp: {problem}")
        for where, problem in zip(log.where.tolist(), problems)
        if problem
    ]
    states_poses = not np.allclose(log.poses, log.odometry, atol=1e-6)  # (as slam.gridslam.health judges it)
    log = log.select(kept)
    odometry = interpolate_poses(log.odom_stamps, log.odom_poses, log.stamps + delay)
    return replace(
        log,
        odometry=odometry,
        poses=log.poses if states_poses else odometry,
        skipped=tuple(sorted(log.skipped + tuple(dropped), key=lambda s: s.where)),
    )
