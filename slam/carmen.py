"""CARMEN log files (``.clf``/``.log``, plain or gzip): read laser scans with odometry, write simulated runs.

Record types read (one record per line, fields separated by white space, ``#`` starts a comment line):

``PARAM name value [ipc_ts host logger_ts]``
``ODOM x y theta tv rv accel ipc_ts host logger_ts``
``FLASER|RLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_ts host logger_ts``
``ROBOTLASER1|ROBOTLASER2 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
n r_1..r_n m e_1..e_m laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv forward_safety
side_safety turn_axis ipc_ts host logger_ts``
``RAWLASER1|RAWLASER2 laser_type start_angle fov angular_resolution max_range accuracy remission_mode
n r_1..r_n m e_1..e_m ipc_ts host logger_ts``

Units are metres, radians and seconds. The stamp of a record is its ``ipc_ts`` field. Other record types
(NEFF, TRUEPOS, SYNC, RAWLASER3 ...) are valid CARMEN and are passed over without comment.

Conventions this reader fixes (the old FLASER/RLASER lines carry no laser geometry):
- a FLASER/RLASER scan spans the PARAM ``laser_<front|rear>_laser_fov`` (degrees, default 180) starting at
  -fov/2; its step is PARAM ``laser_<front|rear>_laser_resolution`` (degrees) when given, else fov/(n-1)
  for an odd beam count n (both ends included: 181, 361) and fov/n for an even one (180, 360);
- its maximum range is PARAM ``robot_<front|rear>_laser_max`` when given, else 80 m (a SICK LMS); the
  laser sits at x = PARAM ``robot_<front|rear>laser_offset`` metres in the robot frame, the rear one facing
  backwards;
- readings at or beyond the maximum range (81.91 in many logs) mean "no return" and become ``+inf``;
- FLASER ``x y theta`` is the pose the log states (raw logs: odometry, corrected logs: the SLAM pose) and
  ``odom_*`` the odometry; ROBOTLASER lines carry the robot pose, used as both, and the laser pose, from
  which the sensor offset follows (median over the scans);
- RAWLASER lines carry their geometry but no pose: each scan's odometry is interpolated from the ODOM lines at its
  stamp (linear, as a bag's; slam.laserlog), a scan without ODOM lines close around it is skipped, and the laser
  sits where the PARAMs say, as a FLASER line's (with ``robot_<front|rear>laser_side_offset`` and
  ``..._angular_offset`` when given).

One laser is read (``laser="front"``: ROBOTLASER1 lines when the log has any, else FLASER, else RAWLASER1;
``"rear"``: ROBOTLASER2, else RLASER, else RAWLASER2). Every scan keeps its own beam count and geometry
(slam.laserlog): a ROBOTLASER or RAWLASER line's are its own fields, so an interlaced laser or one whose beam count
changes is read in full; a
FLASER/RLASER line carries only its beam count, and its geometry follows from that count by the rules above
(an interlaced laser's shifted starts cannot be told from such a line: its scans share one geometry). The
laser's offset on the robot is one for the whole log (ROBOTLASER: the median over the scans, as the lines
print it to 6 decimals). A range that is NaN (an invalid reading) or -inf (too close to measure) is read as 0,
no reading, which every consumer skips (REP 117, as the bag reader reads it). A line that does not parse, declares a
beam count its fields do not match, holds a range that is negative or finite beyond POSE_LIMIT (1e7 m;
slam.laserlog), a non-finite stamp, a pose not
finite or beyond +-POSE_LIMIT, or a ROBOTLASER geometry that is unusable in itself
(:func:`slam.laserlog.geometry_problem`: an increment of 0 for several beams, an angle beyond a full turn) is
skipped and recorded with its line number and reason in :attr:`LaserLog.skipped`; nothing is ever shifted
into a neighbouring field.
"""

from __future__ import annotations

import gzip
import math
import zlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from slam.angles import wrap_angle
from slam.errors import LogFormatError, refuse_special_file
from slam.laserlog import (
    PADDING,
    POSE_LIMIT,
    LaserLog,
    Skipped,
    geometry_problem,
    interpolate_poses,
    odometry_problem,
    per_scan,
    plausible_pose,
)
from slam.motion import compose

#: maximum range assumed for FLASER/RLASER lines when no PARAM gives one (m)
DEFAULT_RANGE_MAX = 80.0
#: field of view assumed for FLASER/RLASER lines when no PARAM gives one (deg)
DEFAULT_FOV_DEG = 180.0
#: with no PARAM for the maximum range, a log whose most common reading is at least this share of its readings and
#: at the top of them (the 90th percentile or above) is said to write its no-return readings as that value (a
#: laser's maximum range, below DEFAULT_RANGE_MAX)
MAX_READING_SHARE = 0.02

_FRONT = {"old": "FLASER", "new": "ROBOTLASER1", "raw": "RAWLASER1", "param": "front"}
_REAR = {"old": "RLASER", "new": "ROBOTLASER2", "raw": "RAWLASER2", "param": "rear"}


@dataclass
class _Scan:
    line: int
    stamp: float
    ranges: list[float]
    pose: tuple[float, float, float]  # RAWLASER: from the ODOM lines, once they are read
    odometry: tuple[float, float, float]
    geometry: tuple[float, ...]  # ROBOTLASER, RAWLASER: (start_angle, angular_resolution, max_range); FLASER: ()
    laser_pose: tuple[float, float, float] | None  # ROBOTLASER only


class _BadLine(ValueError):
    """A line that cannot be used; the message is the reason recorded in LaserLog.skipped."""


def _floats(tokens: list[str], what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise _BadLine(f"{what} field '{bad[:20]}' is not a number") from None
    return values


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _pose(values: list[float], what: str) -> tuple[float, float, float]:
    pose = (values[0], values[1], values[2])
    if not plausible_pose(pose):
        raise _BadLine(f"{what} is not finite or beyond +-{POSE_LIMIT:g} m (rad)")
    return pose


def _stamp(token: str) -> float:
    stamp = _floats([token], "timestamp")[0]
    if not math.isfinite(stamp):
        raise _BadLine("timestamp is not finite")
    return stamp


def _count(token: str, what: str, minimum: int = 1) -> int:
    try:
        n = int(token)
    except ValueError:
        raise _BadLine(f"{what} '{token[:20]}' is not an integer") from None
    if n < minimum:
        raise _BadLine(f"{what} is {n}, expected at least {minimum}")
    return n


def _ranges(tokens: list[str]) -> list[float]:
    """A line's ranges (m); NaN (an invalid reading) and -inf (too close to measure) as 0, no reading (REP 117, as
    the bag reader takes them: such a beam says nothing of the space along it, and the scan's other beams are kept)."""
    values = _floats(tokens, "range")
    for i, value in enumerate(values):
        if value != value or value == -math.inf:
            values[i] = 0.0
        elif not (0 <= value <= POSE_LIMIT or value == math.inf):
            raise _BadLine(f"range {i + 1} is {value}, expected a number in [0, {POSE_LIMIT:g}] m, inf or nan")
    return values


def _parse_flaser(tokens: list[str], line: int) -> _Scan:
    if len(tokens) < 2:
        raise _BadLine("no beam count")
    n = _count(tokens[1], "beam count")
    if len(tokens) != n + 11:
        raise _BadLine(f"declares {n} beams so needs {n + 11} fields, has {len(tokens)}")
    ranges = _ranges(tokens[2 : 2 + n])
    numbers = _floats(tokens[2 + n : 8 + n], "pose")
    return _Scan(
        line=line,
        stamp=_stamp(tokens[8 + n]),
        ranges=ranges,
        pose=_pose(numbers[0:3], "pose"),
        odometry=_pose(numbers[3:6], "odometry pose"),
        geometry=(),
        laser_pose=None,
    )


def _laser_header(tokens: list[str], fields: int) -> tuple[tuple[float, float, float], int, int]:
    """A ROBOTLASER or RAWLASER line's geometry (start_angle rad, angular_resolution rad, max_range m), its beam count
    n and its remission count m (the line has ``fields`` fields besides the beams and remissions)."""
    if len(tokens) < 10:
        raise _BadLine(f"has {len(tokens)} fields, a {tokens[0]} line needs at least {fields}")
    header = _floats(tokens[2:8], "laser parameter")
    start_angle, resolution, max_range = header[0], header[2], header[3]  # header[1], the fov, follows from n
    if not all(math.isfinite(v) for v in header[:4]) or max_range <= 0:
        raise _BadLine("laser parameters (start angle, fov, resolution, max range) are not finite and positive")
    n = _count(tokens[8], "beam count")
    problem = geometry_problem(n, start_angle, resolution, 0.0, max_range)
    if problem:
        raise _BadLine(f"laser parameters unusable: {problem}")
    if len(tokens) < n + fields:
        raise _BadLine(f"declares {n} beams so needs at least {n + fields} fields, has {len(tokens)}")
    m = _count(tokens[9 + n], "remission count", minimum=0)
    if len(tokens) != n + m + fields:
        raise _BadLine(f"declares {n} beams and {m} remissions so needs {n + m + fields} fields, has {len(tokens)}")
    return (start_angle, resolution, max_range), n, m


def _parse_rawlaser(tokens: list[str], line: int) -> _Scan:
    geometry, n, m = _laser_header(tokens, 13)
    nowhere = (math.nan, math.nan, math.nan)  # (placed by the ODOM lines: _placed_raw_scans)
    return _Scan(line, _stamp(tokens[10 + n + m]), _ranges(tokens[9 : 9 + n]), nowhere, nowhere, geometry, None)


def _parse_robotlaser(tokens: list[str], line: int) -> _Scan:
    geometry, n, m = _laser_header(tokens, 24)
    at = 10 + n + m
    numbers = _floats(tokens[at : at + 6], "pose")
    robot = _pose(numbers[3:6], "robot pose")
    return _Scan(
        line=line,
        stamp=_stamp(tokens[at + 11]),
        ranges=_ranges(tokens[9 : 9 + n]),
        pose=robot,
        odometry=robot,
        geometry=geometry,
        laser_pose=_pose(numbers[0:3], "laser pose"),
    )


def _parse_odom(tokens: list[str]) -> tuple[float, tuple[float, float, float]]:
    if len(tokens) != 10:
        raise _BadLine(f"has {len(tokens)} fields, an ODOM line needs 10")
    return _stamp(tokens[7]), _pose(_floats(tokens[1:4], "pose"), "pose")


#: a gzip file's first bytes: such a log is read gunzipped
GZIP_MAGIC = b"\x1f\x8b"
#: the first bytes of the compressed formats a log may come in that this reader does not unpack (gzip's inside
#: gzip among them), and how to unpack each
COMPRESSED = {
    b"BZh": ("bzip2", "bunzip2"),
    b"\xfd7zXZ\x00": ("xz", "unxz"),
    b"PK\x03\x04": ("zip", "unzip"),
    b"PK\x05\x06": ("zip (an empty archive)", "unzip"),
    b"\x28\xb5\x2f\xfd": ("zstd", "unzstd"),
    b"7z\xbc\xaf\x27\x1c": ("7-Zip", "7z x"),
    GZIP_MAGIC: ("gzip twice", "gunzip"),
}


def _open_text(path: Path):
    """The log as text, gunzipped when it is gzip; LogFormatError when its first bytes are another compression's
    or hold a NUL byte (not a text file)."""
    with path.open("rb") as probe:
        gzipped = probe.read(2) == GZIP_MAGIC
    try:
        with gzip.open(path, "rb") if gzipped else path.open("rb") as opened:
            head = opened.read(4096)
    except (EOFError, zlib.error, gzip.BadGzipFile):
        head = None  # (a gzip that breaks off at once: the read below records it as the truncated stream)
    if head is None:
        return gzip.open(path, "rt", encoding="ascii", errors="replace")
    for start, (what, tool) in COMPRESSED.items():
        if head.startswith(start):
            around = gzipped and start != GZIP_MAGIC  # (another compression inside gzip: two steps to unpack)
            how = f"gunzip, then {tool}" if around else tool
            inside = "gzip around " if around else ""
            raise LogFormatError(
                f"{path}: compressed with {inside}{what}, and only gzip is read: unpack it first ({how})"
            )
    if head.startswith((b"\xff\xfe", b"\xfe\xff")) or _utf16_without_mark(head):
        raise LogFormatError(f"{path}: UTF-16 text, and a CARMEN log is ASCII: save it as ASCII or UTF-8")
    if b"\x00" in head:
        raise LogFormatError(f"{path}: not a text file (a NUL byte in its first {len(head)} bytes), so no CARMEN log")
    if not head:
        raise LogFormatError(f"{path}: empty{' once gunzipped' if gzipped else ''}, so no CARMEN log")
    # (a UTF-8 byte order mark, as some editors write, is dropped: it would hide the first line's record type)
    encoding = "utf-8-sig" if head.startswith(b"\xef\xbb\xbf") else "ascii"
    if gzipped:
        return gzip.open(path, "rt", encoding=encoding, errors="replace")
    return path.open("rt", encoding=encoding, errors="replace")


def _utf16_without_mark(head: bytes) -> bool:
    """Whether ``head`` reads as ASCII text in UTF-16 with no byte order mark: every other byte NUL."""
    pairs = len(head) // 2
    if pairs < 4:
        return False
    return head[1 : 2 * pairs : 2].count(0) == pairs or head[0 : 2 * pairs : 2].count(0) == pairs


def _scan_lines(path: Path, kinds: dict[str, str]):
    """Parse the file; return (scans by record type, odometry records, params, skipped records, and the count of
    each other laser record type's lines, read as another laser's or not at all)."""
    scans: dict[str, list[_Scan]] = {kinds["old"]: [], kinds["new"]: [], kinds["raw"]: []}
    other_lasers: dict[str, int] = {}
    odom: list[tuple[float, tuple[float, float, float]]] = []
    params: dict[str, str] = {}
    skipped: list[Skipped] = []
    line_no = 0
    try:
        with _open_text(path) as stream:
            for line_no, text in enumerate(stream, start=1):
                tokens = text.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                kind = tokens[0]
                try:
                    if kind == kinds["old"]:
                        scans[kind].append(_parse_flaser(tokens, line_no))
                    elif kind == kinds["new"]:
                        scans[kind].append(_parse_robotlaser(tokens, line_no))
                    elif kind == kinds["raw"]:
                        scans[kind].append(_parse_rawlaser(tokens, line_no))
                    elif kind == "ODOM":
                        odom.append(_parse_odom(tokens))
                    elif kind == "PARAM":
                        if len(tokens) < 3:
                            raise _BadLine("a PARAM line needs a name and a value")
                        params[tokens[1]] = tokens[2]
                    elif "LASER" in kind:
                        other_lasers[kind] = other_lasers.get(kind, 0) + 1
                except _BadLine as exc:
                    skipped.append(Skipped(line_no, f"{kind}: {exc}"))
    except (EOFError, OSError, zlib.error) as exc:
        if isinstance(exc, FileNotFoundError | IsADirectoryError | PermissionError):
            raise LogFormatError(f"{path}: cannot open the log ({exc.strerror})") from None
        skipped.append(Skipped(line_no + 1, f"the compressed stream is truncated or corrupt ({exc}); reading stopped"))
    return scans, odom, params, skipped, other_lasers


def _param_float(params: dict[str, str], name: str, default: float, path: Path) -> float:
    if name not in params:
        return default
    try:
        value = float(params[name])
    except ValueError:
        raise LogFormatError(f"{path}: PARAM {name} is '{params[name]}', not a number") from None
    if not math.isfinite(value):
        raise LogFormatError(f"{path}: PARAM {name} is {value}, not a finite number")
    return value


def _flaser_geometry(params: dict[str, str], side: str, beams: int, path: Path) -> tuple[float, float, float]:
    """(angle_min rad, angle_increment rad, range_max m) for FLASER/RLASER lines of ``beams`` beams."""
    fov = math.radians(_param_float(params, f"laser_{side}_laser_fov", DEFAULT_FOV_DEG, path))
    default_step = fov / (beams - 1) if beams % 2 == 1 and beams > 1 else fov / beams
    step = math.radians(_param_float(params, f"laser_{side}_laser_resolution", math.degrees(default_step), path))
    range_max = _param_float(params, f"robot_{side}_laser_max", DEFAULT_RANGE_MAX, path)
    if step <= 0 or range_max <= 0:
        raise LogFormatError(f"{path}: the {side} laser's resolution and maximum range must be positive")
    problem = geometry_problem(beams, -0.5 * fov, step, 0.0, range_max)
    if problem:
        raise LogFormatError(f"{path}: the {side} laser's PARAMs give scans of {beams} beams, unusable: {problem}")
    return -0.5 * fov, step, range_max


def _param_offset(params: dict[str, str], side: str, path: Path) -> np.ndarray:
    """The laser's pose on the robot (x m, y m, yaw rad) from the PARAMs: ``robot_<side>laser_offset`` ahead,
    ``..._side_offset`` to the left, ``..._angular_offset`` its heading on the robot, as CARMEN's robot module takes
    them (0 when not given, pi for the rear laser, which faces back)."""
    forward = _param_float(params, f"robot_{side}laser_offset", 0.0, path)
    left = _param_float(params, f"robot_{side}laser_side_offset", 0.0, path)
    yaw = _param_float(params, f"robot_{side}laser_angular_offset", 0.0 if side == "front" else math.pi, path)
    return np.array([forward, left, yaw if abs(yaw) <= math.pi else wrap_angle(yaw)])


def _placed_raw_scans(
    scans: list[_Scan], odom: list[tuple[float, tuple[float, float, float]]], kind: str, skipped: list, path: Path
) -> list[_Scan]:
    """RAWLASER scans with the odometry pose interpolated from the ODOM lines at each one's stamp; a scan the
    ODOM lines do not hold closely enough (slam.laserlog.odometry_problem) is added to ``skipped``."""
    if not odom:
        raise LogFormatError(
            f"{path}: its {len(scans)} {kind} lines carry no pose, and it has no ODOM line to place them by"
        )
    ordered = sorted(odom, key=lambda o: o[0])
    stamps = np.array([o[0] for o in ordered])
    poses = np.array([o[1] for o in ordered], dtype=np.float64)
    kept = []
    for scan in scans:
        problem = odometry_problem(stamps, scan.stamp)
        if problem:
            skipped.append(Skipped(scan.line, f"{kind}: {problem}"))
        else:
            kept.append(scan)
    at = interpolate_poses(stamps, poses, np.array([scan.stamp for scan in kept])).tolist()
    return [replace(scan, pose=tuple(pose), odometry=tuple(pose)) for scan, pose in zip(kept, at)]


def _robot_to_laser_offsets(scans: list[_Scan]) -> np.ndarray:
    """Per scan, the laser pose in the robot frame: robot^-1 (+) laser, (N, 3)."""
    robot = np.array([s.pose for s in scans])
    laser = np.array([s.laser_pose for s in scans])
    dx, dy = laser[:, 0] - robot[:, 0], laser[:, 1] - robot[:, 1]
    c, s = np.cos(robot[:, 2]), np.sin(robot[:, 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(laser[:, 2] - robot[:, 2])], axis=1)


def _in_time_order(scans: list[_Scan], skipped: list[Skipped]) -> list[_Scan]:
    """The scans, in file order, but those stamped earlier than a scan kept before them, which are added to
    ``skipped``. A logger's clock that steps back for a scan (the corrected Intel log's does at 4 of its 910 scans,
    by 0.05 to 0.86 s) would otherwise make the whole log unusable: a filter takes the scans in order, and a replay
    paces them by their stamps. Scans stamped alike are kept (what a command makes of them is its own check:
    slam.laserlog.check_scan_order)."""
    kept: list[_Scan] = []
    for scan in scans:
        if kept and scan.stamp < kept[-1].stamp:
            reason = f"its stamp {scan.stamp:.6f} s is earlier than the scan's before it ({kept[-1].stamp:.6f} s)"
            skipped.append(Skipped(scan.line, reason))
            continue
        kept.append(scan)
    return kept


def read_carmen(path: str | Path, laser: str = "front") -> LaserLog:
    """Read one laser's scans (with odometry), the ODOM stream and the PARAMs of a CARMEN log.

    ``path``: a CARMEN log, plain text or gzip (detected from the content). ``laser``: "front" or "rear".
    Raises :class:`LogFormatError` when the file cannot be opened or holds no usable scan of that laser;
    everything else that is wrong is skipped and listed in the result's ``skipped``, a scan stamped earlier than the
    scan before it included (so the scans' stamps never decrease).
    """
    if laser not in ("front", "rear"):
        raise LogFormatError(f"laser must be 'front' or 'rear', got '{laser}'")
    path = Path(path)
    refuse_special_file(path, "CARMEN log")
    if not path.is_file():
        raise LogFormatError(f"{path}: no such file (expected a CARMEN log)")
    kinds = _FRONT if laser == "front" else _REAR
    scans_by_kind, odom, params, skipped, other_lasers = _scan_lines(path, kinds)
    kind = next((kinds[k] for k in ("new", "old", "raw") if scans_by_kind[kinds[k]]), kinds["new"])
    scans = scans_by_kind[kind]
    if kind == kinds["raw"]:
        scans = _placed_raw_scans(scans, odom, kind, skipped, path)
    scans = _in_time_order(scans, skipped)
    if not scans:
        others = ", ".join(f"{count} {other} lines" for other, count in sorted(other_lasers.items()))
        raise LogFormatError(
            f"{path}: holds no usable {laser} laser scan ({kinds['new']}, {kinds['old']} or {kinds['raw']} line)"
            + (f"; first problem at line {skipped[0].where}: {skipped[0].reason}" if skipped else "")
            + (f"; it has {others}, not read as the {laser} laser's" if others else "")
        )
    side = kinds["param"]
    if scans[0].laser_pose is not None:
        offset = np.median(_robot_to_laser_offsets(scans), axis=0)
    else:
        offset = _param_offset(params, side, path)
    if scans[0].geometry:
        geometry = np.array([s.geometry for s in scans], dtype=np.float64)
    else:
        by_count = {n: _flaser_geometry(params, side, n, path) for n in {len(s.ranges) for s in scans}}
        geometry = np.array([by_count[len(s.ranges)] for s in scans], dtype=np.float64)
    beams = np.array([len(s.ranges) for s in scans], dtype=np.int64)
    ranges = np.full((len(scans), int(beams.max())), PADDING, dtype=np.float32)
    for row, scan in zip(ranges, scans):
        row[: len(scan.ranges)] = scan.ranges
    notes = [] if scans[0].geometry else _assumed_geometry(params, side, sorted(set(beams.tolist())), ranges)
    ranges[ranges >= geometry[:, 2:3]] = np.inf  # (the NaN padding compares false: it stays)
    skipped.sort(key=lambda s: s.where)
    return LaserLog(
        source=str(path),
        stamps=np.array([s.stamp for s in scans], dtype=np.float64),
        ranges=ranges,
        angle_min=geometry[:, 0],
        angle_increment=geometry[:, 1],
        range_min=np.zeros(len(scans)),
        range_max=geometry[:, 2],
        sensor_offset=np.asarray(offset, dtype=np.float64),
        odometry=np.array([s.odometry for s in scans], dtype=np.float64),
        poses=np.array([s.pose for s in scans], dtype=np.float64),
        where=np.array([s.line for s in scans], dtype=np.int64),
        odom_stamps=np.array([o[0] for o in odom], dtype=np.float64),
        odom_poses=np.array([o[1] for o in odom], dtype=np.float64).reshape(-1, 3),
        params=params,
        skipped=tuple(skipped),
        notes=tuple(notes),
        unit="line",
        beams=beams,
    )


def _assumed_geometry(params: dict[str, str], side: str, beams: list[int], ranges: np.ndarray) -> list[str]:
    """What the reader takes for granted of FLASER/RLASER lines whose PARAMs are silent (one sentence each, with the
    PARAM line that would say it): the field of view (DEFAULT_FOV_DEG) and the maximum range (DEFAULT_RANGE_MAX),
    naming a reading that looks like the laser's own maximum (``ranges`` (T, B) m as read, NaN padding)."""
    notes = []
    if f"laser_{side}_laser_fov" not in params and f"laser_{side}_laser_resolution" not in params:
        notes.append(
            f"its {side} laser's scans ({', '.join(map(str, beams))} beams a line) are taken to sweep "
            f"{DEFAULT_FOV_DEG:g} deg, as no PARAM laser_{side}_laser_fov says: a laser that sweeps another angle "
            f"(270 deg, as most of 541 or 1081 beams do) needs a line 'PARAM laser_{side}_laser_fov DEG' in the log"
        )
    if f"robot_{side}_laser_max" not in params:
        note = (
            f"its {side} laser's maximum range is taken as {DEFAULT_RANGE_MAX:g} m, as no PARAM robot_{side}_laser_max "
            "says (readings at or beyond it are no return)"
        )
        readings = ranges[np.isfinite(ranges) & (ranges > 0)]
        readings = readings[:: max(1, readings.size // 200_000)]  # (a sample is enough to find the common value)
        if readings.size:
            values, counts = np.unique(readings, return_counts=True)
            common, share = float(values[counts.argmax()]), float(counts.max() / readings.size)
            if share >= MAX_READING_SHARE and np.quantile(readings, 0.9) <= common < DEFAULT_RANGE_MAX:
                note += (
                    f"; {100 * share:.0f} % of its readings are {common:g} m, at the top of its readings: if that is "
                    f"the laser's maximum range (its reading for no return, taken as a wall here), add 'PARAM "
                    f"robot_{side}_laser_max {common:g}' to the log"
                )
        notes.append(note)
    return notes


def write_carmen(
    path: str | Path,
    stamps: np.ndarray,
    ranges: np.ndarray,
    odometry: np.ndarray,
    angle_min: float | np.ndarray,
    angle_increment: float | np.ndarray,
    range_max: float | np.ndarray,
    sensor_offset: np.ndarray | None = None,
    poses: np.ndarray | None = None,
    record: str = "ROBOTLASER1",
    host: str = "posegrid",
    beams: np.ndarray | None = None,
) -> None:
    """Write scans with odometry as a CARMEN log that :func:`read_carmen` reads back (gzip for a .gz path).

    ``stamps`` (T,) s; ``ranges`` (T, B) m, NaN/inf/above ``range_max`` written as the max-range reading;
    ``odometry`` (T, 3) robot odometry poses; beam i of scan t points at ``angle_min + i*angle_increment`` (rad,
    laser frame); ``sensor_offset`` (3,) laser pose in the robot frame. ``angle_min``, ``angle_increment`` and
    ``range_max`` are one number for every scan or one per scan (T,), ``sensor_offset`` (3,) or (T, 3), and
    ``beams`` (T,) the beam count of each scan (default: all B), its readings the first of its row.
    ``record`` "ROBOTLASER1" stores each scan's geometry in its line; "FLASER" stores one geometry in PARAM
    lines (the beam count may change from scan to scan), needs a laser facing forwards on the robot's x axis
    and ``angle_min`` = -fov/2, and also stores ``poses`` (T, 3) (default: the odometry) as the line's pose.
    Numbers are written with 6 decimals.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    odometry = np.asarray(odometry, dtype=np.float64)
    poses = odometry if poses is None else np.asarray(poses, dtype=np.float64)
    steps, width = ranges.shape
    if stamps.shape != (steps,) or odometry.shape != (steps, 3) or poses.shape != (steps, 3):
        raise ValueError("stamps (T,), ranges (T, B), odometry (T, 3) and poses (T, 3) must agree on T")
    if record not in ("ROBOTLASER1", "FLASER"):
        raise ValueError(f"record must be 'ROBOTLASER1' or 'FLASER', got '{record}'")
    geometry = np.column_stack([per_scan(v, steps) for v in (angle_min, angle_increment, range_max)])
    offset = per_scan(np.zeros(3) if sensor_offset is None else sensor_offset, steps, 3)
    counts = np.full(steps, width, np.int64) if beams is None else np.asarray(beams, np.int64)
    clean = np.where(np.isfinite(ranges) & (ranges <= geometry[:, 2:3]), ranges, geometry[:, 2:3])
    lines = ["# written by posegrid (slam.carmen.write_carmen)"]
    if record == "FLASER":
        lines += _flaser_params(geometry, offset, host)
    laser = compose(odometry, offset.T)  # laser poses in the odometry frame (delta (3, T): one offset per scan)
    for t in range(steps):
        n = int(counts[t])
        values = " ".join(f"{r:.6f}" for r in clean[t, :n])
        stamp = f"{stamps[t]:.6f}"
        if record == "FLASER":
            pose = " ".join(f"{v:.6f}" for v in (*poses[t], *odometry[t]))
            lines.append(f"FLASER {n} {values} {pose} {stamp} {host} {stamp}")
        else:
            first, step, far = geometry[t].tolist()
            head = f"ROBOTLASER1 0 {first:.17g} {step * (n - 1):.17g} {step:.17g} {far:.17g} 0.01 0"
            pose = " ".join(f"{v:.6f}" for v in (*laser[t], *odometry[t]))
            lines.append(f"{head} {n} {values} 0 {pose} 0 0 0 0 0 {stamp} {host} {stamp}")
    text = "\n".join(lines) + "\n"
    path = Path(path)
    if path.suffix.lower() == ".gz":
        with gzip.open(path, "wt", encoding="ascii") as stream:
            stream.write(text)
    else:
        path.write_text(text, encoding="ascii")


class LaserScans(Protocol):
    """What :func:`write_carmen_scans` reads of a log: a :class:`slam.laserlog.LaserLog`, a simulated run
    (slam.simulator.SimRun, slam.gridslam.simlogs.SimLaserLog) or anything with these fields: stamps (T,) s,
    ranges (T, B) m, odometry (T, 3) robot poses, angle_min and angle_increment (rad) and range_max (m), each one
    number or one per scan (T,), and sensor_offset (3,) or (T, 3), the laser pose in the robot frame."""

    @property
    def stamps(self) -> np.ndarray: ...
    @property
    def ranges(self) -> np.ndarray: ...
    @property
    def odometry(self) -> np.ndarray: ...
    @property
    def angle_min(self) -> Any: ...
    @property
    def angle_increment(self) -> Any: ...
    @property
    def range_max(self) -> Any: ...
    @property
    def sensor_offset(self) -> np.ndarray: ...


def write_carmen_scans(
    path: str | Path,
    scans: LaserScans,
    *,
    odometry: np.ndarray | None = None,
    stamps: np.ndarray | None = None,
    **options,
) -> None:
    """:func:`write_carmen` for the scans, geometry and odometry of ``scans``; ``odometry`` (T, 3) and ``stamps``
    (T,) s replace the log's own, and ``options`` (poses, record, host, beams) go to :func:`write_carmen`."""
    write_carmen(
        path,
        scans.stamps if stamps is None else stamps,
        scans.ranges,
        scans.odometry if odometry is None else odometry,
        scans.angle_min,
        scans.angle_increment,
        scans.range_max,
        scans.sensor_offset,
        **options,
    )


def _flaser_params(geometry: np.ndarray, offset: np.ndarray, host: str) -> list[str]:
    """The PARAM lines that give FLASER lines their geometry: ``geometry`` (T, 3) per scan (angle_min rad,
    angle_increment rad, range_max m) and ``offset`` (T, 3) must be one for all scans, the laser facing forwards
    on the robot's x axis (ValueError otherwise)."""
    if not len(geometry):
        return []
    if (offset[:, 1:] != 0).any() or (offset != offset[0]).any():
        raise ValueError("a FLASER log can only hold a laser on the robot's x axis facing forwards")
    if (geometry != geometry[0]).any():
        raise ValueError("a FLASER log holds one laser geometry (PARAM lines); write per-scan geometry as ROBOTLASER1")
    angle_min, angle_increment, range_max = geometry[0].tolist()
    return [
        f"PARAM laser_front_laser_fov {math.degrees(-2.0 * angle_min):.17g} 0 {host} 0",
        f"PARAM laser_front_laser_resolution {math.degrees(angle_increment):.17g} 0 {host} 0",
        f"PARAM robot_front_laser_max {range_max:.17g} 0 {host} 0",
        f"PARAM robot_frontlaser_offset {offset[0, 0]:.17g} 0 {host} 0",
    ]
