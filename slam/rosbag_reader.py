"""ROS 1 and ROS 2 bags (through the ``rosbags`` library, no ROS needed): laser scans with odometry.

What is read:
- scans: ``sensor_msgs/LaserScan`` on the scan topic (``scan_topic``, default: the bag's only LaserScan
  topic, or ``/scan`` when it has several), each with its own beam count, geometry and frame (slam.laserlog):
  an interlaced laser, a beam count that changes and two lasers publishing on one topic are read in full;
- odometry: ``nav_msgs/Odometry`` on the odometry topic (default: the only Odometry topic, or ``/odom``);
  without one, the ``tf2_msgs/TFMessage`` transforms on ``/tf`` whose child is the robot's base frame;
- the laser's pose on the robot, per laser frame: the chain of transforms from the scan's frame up to the base frame,
  projected to (x, y, yaw) (:class:`Mount`: a laser upside down, its z axis within TILT_LIMIT of straight down, has its
  beams mirrored; a link that tilts it farther from the floor's plane is refused). A link of the chain comes from
  ``/tf_static``, or from ``/tf`` when it holds one pose all through the bag (ROS 1 bags, and the static publishers of
  old, put the mount on ``/tf``). The base frame is the Odometry child frame (with an empty one, the laser's chain's
  frame below its first moving link, else its root); without an Odometry topic it is the child of the ``/tf`` link
  nearest the tree's root (moving, or fixed for a robot standing still) whose parent is no REP 105 global frame
  (``map``, ``world``, ``earth``: amcl's ``map`` -> ``odom`` corrects the odometry), so ``odom`` -> ``base_link``; else
  the chain's root. Frame names are taken as tf2 takes them, without ROS 1's leading slash; transforms that form a cycle
  are refused. When the chain of the frame most scans have does not reach the base frame, or moves on its way there (a
  laser on a moving joint), the bag is refused; a scan of another frame without one is skipped. A laser frame that no
  transform names at all is taken as the base frame itself (at the robot's origin, facing forwards), and the log's notes
  say so.

Each scan's odometry pose is interpolated at the scan's header stamp between the two odometry poses around
it (linear in x, y and unwrapped yaw; real bags publish odometry irregularly, the Intel lab's with gaps of
up to 3 s). A scan is skipped when those two are more than ``max_odom_gap`` seconds apart, or when it lies
outside the odometry's time span by more than ``max_odom_hold`` seconds (within that, the end pose is
held); likewise one that does not decode or is unusable in itself (:func:`wire_scan_problem`). Each skip records the
scan's 1-based message number (counting all messages of the topics read, in bag order) and the reason.
Readings at or above the scan's range_max become ``+inf`` (no return); a range_max of +inf (ROS 2's
pointcloud_to_laserscan states it by default) or beyond RANGE_MAX_CEILING (1 km, slam.laserlog) is read as 1 km. NaN
(an invalid reading) and -inf (too close to measure) say nothing about free space (REP 117), so they become 0, below
range_min, which every consumer skips; range_min is raised to MIN_RANGE_FLOOR (1 mm) when the bag gives 0, so that 0
lies below it. (Left as NaN, an invalid reading was skipped by grid FastSLAM but, as a beam with no return, cleared
free space up to range_max through whatever the laser could not measure in the mapper's fusion.)
Odometry poses and transforms that are not finite or lie beyond +-POSE_LIMIT (1e7 m; slam.laserlog) are
skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from slam.angles import wrap_angle
from slam.errors import LogFormatError
from slam.laserlog import (
    MAX_ODOM_GAP,
    MAX_ODOM_HOLD,
    PADDING,
    POSE_LIMIT,
    LaserLog,
    Skipped,
    bounded_range_max,
    geometry_problem,
    interpolate_poses,
    odometry_problem,
    plausible_pose,
)

#: the file suffixes rosbags reads a bag file by: ROS 1, and ROS 2's two storage formats
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
#: the file that makes a folder a ROS 2 bag: given itself, its folder is read
BAG_METADATA = "metadata.yaml"

#: the least range_min (m) a bag's laser gets: invalid readings are stored as 0, which must lie below it
MIN_RANGE_FLOOR = 1e-3

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


def header_stamp(header) -> float:
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


#: a quaternion whose squared norm is off 1 by more than this is normalised before it is read
UNIT_TOLERANCE = 1e-6


def _unit_quaternion(q) -> tuple[float, float, float, float] | None:
    """(w, x, y, z) of quaternion ``q`` scaled to unit norm (its largest component taken out first, so that no square
    overflows or underflows: a quaternion scaled by 0.5 read a yaw of pi/2 as 18 deg); the identity for a zero one;
    None for one with a component that is not finite."""
    parts = (float(q.w), float(q.x), float(q.y), float(q.z))
    if not all(math.isfinite(p) for p in parts):
        return None
    if abs(sum(p * p for p in parts) - 1.0) <= UNIT_TOLERANCE:
        return parts  # (as ROS writes a rotation: taken as it is)
    largest = max(abs(p) for p in parts)
    if largest == 0.0:
        return (1.0, 0.0, 0.0, 0.0)
    w, x, y, z = (p / largest for p in parts)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / norm, x / norm, y / norm, z / norm)


def quaternion_yaw(q) -> float:
    """Yaw (rad) of a quaternion: the heading of its x axis projected onto the plane (the rotation about z of a
    level frame; of one upside down, ``Rz(yaw) Rx(pi)``, too). One not of unit norm is normalised first; a zero one
    reads 0; one with a component that is not finite reads NaN, which the callers refuse as a pose."""
    unit = _unit_quaternion(q)
    if unit is None:
        return math.nan
    w, x, y, z = unit
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


#: a frame whose z axis lies within this of the vertical (rad), up or down, scans the floor's plane: level (+1) or
#: upside down (-1); one tilted farther (0) scans another plane, which a 2D map cannot take
TILT_LIMIT = math.radians(30.0)

#: a link's attitude: its child's z axis up (LEVEL), down (UPSIDE_DOWN: a laser mounted upside down, whose beams
#: turn the other way), or tilted past TILT_LIMIT (TILTED)
LEVEL, UPSIDE_DOWN, TILTED = 1, -1, 0


def quaternion_attitude(q) -> int:
    """LEVEL, UPSIDE_DOWN or TILTED: where a quaternion's rotation takes the z axis (the z component of R e_z,
    1 - 2 (x^2 + y^2) for a unit quaternion; normalised first, a zero quaternion taken as the identity). One with a
    component that is not finite says nothing of where the laser points: TILTED, which a mount refuses."""
    unit = _unit_quaternion(q)
    if unit is None:
        return TILTED
    _, x, y, _ = unit
    up = 1.0 - 2.0 * (x * x + y * y)
    if up >= math.cos(TILT_LIMIT):
        return LEVEL
    return UPSIDE_DOWN if up <= -math.cos(TILT_LIMIT) else TILTED


def _compose(
    a: tuple[float, float, float], a_attitude: int, b: tuple[float, float, float]
) -> tuple[float, float, float]:
    """Pose ``b`` (x m, y m, yaw rad) given in frame ``a`` (a pose of that attitude, LEVEL or UPSIDE_DOWN) in a's
    parent: an upside-down frame mirrors y and the turn (its rotation is Rz(yaw_a) Rx(pi))."""
    c, s = math.cos(a[2]), math.sin(a[2])
    x, y = b[0], a_attitude * b[1]
    yaw = (a[2] + a_attitude * b[2] + math.pi) % (2.0 * math.pi) - math.pi
    return (a[0] + c * x - s * y, a[1] + s * x + c * y, yaw)


def frame_name(name: str) -> str:
    """A tf frame's name as tf2 takes it: without the leading slash of ROS 1's names ('/laser' is 'laser')."""
    return name.lstrip("/")


def _pick_topic(connections, msgtype: str, wanted: str | None, usual: str, path: Path, what: str) -> str | None:
    topics = sorted({c.topic for c in connections if c.msgtype == msgtype})
    if wanted is not None:
        if wanted not in topics:
            raise LogFormatError(f"{path}: has no {msgtype} topic '{wanted}' (its {what} topics: {topics or 'none'})")
        return wanted
    if len(topics) == 1:
        return topics[0]
    if usual in topics:
        return usual
    if topics:
        option = "with --scan-topic" if msgtype == LASER_SCAN else f"or publish it as {usual}"
        raise LogFormatError(f"{path}: has several {what} topics {topics}; name one ({option})")
    return None


#: what :func:`open_bag` says it expected, by default
ANY_BAG = "a ROS 1 .bag file or a ROS 2 bag folder"


def open_bag(path: Path, expected: str = ANY_BAG):
    """An open rosbags reader of the bag at ``path`` (a ROS 1 .bag, a ROS 2 bag folder, its metadata.yaml or its
    storage file); LogFormatError naming ``expected`` when there is none."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    if path.name == BAG_METADATA and path.is_file():
        path = path.parent
    if not path.exists():
        raise LogFormatError(f"{path}: no such file or bag folder (expected {expected})")
    if path.is_dir() and not (path / BAG_METADATA).exists():
        raise LogFormatError(f"{path}: a folder without metadata.yaml, so not a ROS 2 bag (expected {expected})")
    if path.is_file() and path.suffix not in BAG_SUFFIXES:  # rosbags tells the formats apart by the suffix alone
        raise LogFormatError(
            f"{path}: not named as a bag: rosbags reads a ROS 1 bag named *.bag and a ROS 2 storage "
            "file named *.mcap or *.db3 (or give the ROS 2 bag's folder); rename or link it"
        )
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        reason = " ".join(str(exc).split())  # (a broken metadata.yaml's error spans lines)
        raise LogFormatError(f"{path}: not a readable ROS bag ({reason})") from None
    return reader


def read_rosbag(
    path: str | Path,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    max_odom_gap: float = MAX_ODOM_GAP,
    max_odom_hold: float = MAX_ODOM_HOLD,
) -> LaserLog:
    """Read a bag's laser scans with the robot's odometry pose at each scan (see the module docstring).

    ``path``: a ROS 1 ``.bag`` file or a ROS 2 bag folder; ``max_odom_gap`` and ``max_odom_hold`` in s. Raises
    :class:`LogFormatError` when the bag cannot be opened or yields no scan with odometry.
    """
    path = Path(path)
    reader = open_bag(path)
    try:
        return _read(reader, path, scan_topic, odom_topic, max_odom_gap, max_odom_hold)
    finally:
        reader.close()


def bag_records(reader, connections, skipped: list[Skipped]):
    """(connection, raw bytes) of the bag's messages in order; a bag that breaks off mid-way (a corrupt or
    truncated chunk) ends the iteration with one entry in ``skipped`` instead of an exception."""
    stream = reader.messages(connections=connections)
    count = 0
    while True:
        try:
            conn, _time, raw = next(stream)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - rosbags raises reader, decompression and struct errors there
            skipped.append(
                Skipped(count + 1, f"the bag breaks off here ({type(exc).__name__}: {exc}); reading stopped")
            )
            return
        count += 1
        yield conn, raw


#: a decoded scan: (message number, stamp s, ranges (B,) m, (angle_min, angle_increment, range_min, range_max, frame))
_DecodedScan = tuple[int, float, np.ndarray, tuple]


@dataclass
class _Decoded:
    """What the selected messages of a bag hold, in bag order, and the messages skipped so far."""

    scans: list[_DecodedScan] = field(default_factory=list)
    odom: list[tuple[float, tuple[float, float, float], str]] = field(default_factory=list)  # stamp, pose, child
    # stamp, parent, child, pose, attitude (quaternion_attitude)
    tf_dynamic: list[tuple[float, str, str, tuple[float, float, float], int]] = field(default_factory=list)
    # child: parent, pose, attitude
    tf_static: dict[str, tuple[str, tuple[float, float, float], int]] = field(default_factory=dict)
    skipped: list[Skipped] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def _read(reader, path: Path, scan_topic, odom_topic, max_odom_gap, max_odom_hold) -> LaserLog:
    """The LaserLog of an open bag (see :func:`read_rosbag`)."""
    scan_topic, odom_topic, selected = _select(reader.connections, path, scan_topic, odom_topic)
    got = _decode(reader, selected, scan_topic, odom_topic)
    if not got.scans:
        refused = [s.reason for s in got.skipped if s.reason.startswith(f"{scan_topic}:")]
        why = f" (the first: {refused[0]})" if refused else ""
        raise LogFormatError(f"{path}: no usable scan on {scan_topic}{why}")
    mounts, base_frame = _laser_mounts(got, (got.odom[0][2] or None) if got.odom else None, path)
    odom_stamps, odom_poses = _odometry(got, odom_topic, base_frame, path)
    kept = _kept_scans(got, mounts, odom_stamps, scan_topic, max_odom_gap, max_odom_hold)
    if not kept:
        raise LogFormatError(
            f"{path}: no scan on {scan_topic} has odometry around its stamp ({got.skipped[-1].reason})"
        )
    got.skipped.sort(key=lambda s: s.where)
    return _laser_log(path, kept, mounts, odom_stamps, odom_poses, got.skipped, got.notes)


def _select(connections, path: Path, scan_topic: str | None, odom_topic: str | None) -> tuple[str, str | None, list]:
    """The scan topic, the odometry topic (None: odometry from /tf) and the connections to read."""
    scan_topic = _pick_topic(connections, LASER_SCAN, scan_topic, "/scan", path, "LaserScan")
    if scan_topic is None:
        raise LogFormatError(f"{path}: has no sensor_msgs/LaserScan topic")
    odom_topic = _pick_topic(connections, ODOMETRY, odom_topic, "/odom", path, "Odometry")
    tf_topics = {c.topic for c in connections if c.msgtype == TF_MESSAGE}
    wanted = {scan_topic, odom_topic, "/tf_static", "/tf"}  # (/tf: the odometry without a topic, or a mount)
    selected = [c for c in connections if c.topic in wanted and (c.topic not in tf_topics or c.msgtype == TF_MESSAGE)]
    if odom_topic is None and "/tf" not in tf_topics:
        raise LogFormatError(f"{path}: has neither a nav_msgs/Odometry topic nor /tf transforms for odometry")
    return scan_topic, odom_topic, selected


def _decode(reader, selected: list, scan_topic: str, odom_topic: str | None) -> _Decoded:
    """Every selected message decoded and sorted into scans, odometry and transforms; one that does not
    decode or holds implausible values is skipped."""
    got = _Decoded()
    for number, (conn, raw) in enumerate(bag_records(reader, selected, got.skipped), start=1):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:  # noqa: BLE001 - the decoder raises many types on corrupt bytes: skip the message
            got.skipped.append(
                Skipped(number, f"{conn.topic}: does not decode as {conn.msgtype} ({type(exc).__name__})")
            )
            continue
        if conn.topic == scan_topic:
            _add_scan(got, number, msg, scan_topic)
        elif odom_topic is not None and conn.topic == odom_topic:
            _add_odometry(got, number, msg, odom_topic)
        else:
            _add_transforms(got, number, msg, conn.topic)
    return got


def _add_scan(got: _Decoded, number: int, msg, topic: str) -> None:
    """Add LaserScan message ``number`` to ``got.scans``, or a reason to ``got.skipped``."""
    geometry = scan_geometry(msg)
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    stamp = header_stamp(msg.header)
    if not (all(math.isfinite(g) for g in geometry) and math.isfinite(stamp)) or ranges.size == 0:
        got.skipped.append(Skipped(number, f"{topic}: no ranges, or a non-finite stamp or geometry"))
        return
    problem = wire_scan_problem(ranges, *geometry)
    if problem:
        got.skipped.append(Skipped(number, f"{topic}: {problem}"))
        return
    got.scans.append((number, stamp, ranges, (*geometry, frame_name(msg.header.frame_id))))


def _add_odometry(got: _Decoded, number: int, msg, topic: str) -> None:
    """Add Odometry message ``number`` to ``got.odom``, or a reason to ``got.skipped``."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    pose = (float(p.x), float(p.y), quaternion_yaw(q))
    stamp = header_stamp(msg.header)
    if not (plausible_pose(pose) and math.isfinite(stamp)):
        reason = f"{topic}: non-finite stamp, or a pose not finite or beyond +-{POSE_LIMIT:g} m"
        got.skipped.append(Skipped(number, reason))
        return
    got.odom.append((stamp, pose, frame_name(msg.child_frame_id)))


def _add_transforms(got: _Decoded, number: int, msg, topic: str) -> None:
    """Add the transforms of TFMessage ``number`` on /tf or /tf_static to ``got``, skipping implausible ones."""
    for tf in msg.transforms:
        t, q = tf.transform.translation, tf.transform.rotation
        pose = (float(t.x), float(t.y), quaternion_yaw(q))
        parent, child = frame_name(tf.header.frame_id), frame_name(tf.child_frame_id)
        if not plausible_pose(pose):
            link = f"{parent}->{child}"
            got.skipped.append(Skipped(number, f"{topic}: transform {link} not finite or beyond +-{POSE_LIMIT:g} m"))
        elif topic == "/tf_static":
            got.tf_static[child] = (parent, pose, quaternion_attitude(q))
        else:
            got.tf_dynamic.append((header_stamp(tf.header), parent, child, pose, quaternion_attitude(q)))


def _laser_mounts(got: _Decoded, base_frame: str | None, path: Path) -> tuple[dict[str, Mount | str], str]:
    """Per laser frame of the scans, its :class:`Mount` on the robot from the chain of transforms up to
    ``base_frame`` (None: with the odometry from /tf :func:`odometry_base`, from an Odometry topic whose child frame
    is empty, or when /tf names none, the root of the chain of the frame most scans have; a tie: the frame seen
    first), or, for a frame no chain links to it, the reason; and the base frame. Raises :class:`LogFormatError` when
    the frame most scans have is not linked."""
    counts: dict[str, int] = {}
    for scan in got.scans:
        counts[scan[3][4]] = counts.get(scan[3][4], 0) + 1
    frames = sorted(counts, key=lambda frame: -counts[frame])  # (a stable sort: ties keep their first sighting)
    links = frame_links(got.tf_static, got.tf_dynamic)
    try:
        if base_frame is None and not got.odom:  # (odometry from /tf: its own link names the base)
            base_frame = odometry_base(links)
        main, base_frame = mount_chain(links, frames[0], base_frame)
    except LogFormatError as exc:
        raise LogFormatError(f"{path}: {exc}") from None
    mounts: dict[str, Mount | str] = {frames[0]: main}
    for frame in frames[1:]:
        try:
            mounts[frame] = mount_chain(links, frame, base_frame)[0]
        except LogFormatError as exc:
            mounts[frame] = str(exc)
    for frame in frames:
        if frame != base_frame and frame not in links and not isinstance(mounts[frame], str):
            got.notes.append(
                f"no transform names the laser frame '{frame}' (on /tf_static or /tf): its scans are taken as "
                f"seen from the origin of the robot's base frame '{base_frame}', facing forwards"
            )
    return mounts, base_frame


#: a /tf link whose poses all lie this close to its first (m, and rad for the yaw) is fixed: a mount published again
#: and again, or a robot standing still (0.1 mm, 0.1 mrad: above a float32 round trip's noise, below any joint)
FIXED_LINK = 1e-4

#: what a frame's link to its parent is: from /tf_static, fixed on /tf (one pose all through), or moving on /tf
STATIC, FIXED, MOVING = "static", "fixed", "moving"

#: a frame's link: (parent, pose (x m, y m, yaw rad) of the child in the parent, kind, attitude)
Link = tuple[str, tuple[float, float, float], str, int]


def frame_links(tf_static: dict, tf_dynamic: list) -> dict[str, Link]:
    """Each child frame's link to its parent (:data:`Link`): from /tf_static (``tf_static``: child -> (parent,
    pose, attitude)), else from /tf (``tf_dynamic``: (stamp, parent, child, pose, attitude) records), the child's
    parent seen most often there, FIXED when all those poses lie within FIXED_LINK of the first and keep its
    attitude, else MOVING."""
    records: dict[tuple[str, str], list[tuple[tuple[float, float, float], int]]] = {}
    for _stamp, parent, child, pose, attitude in tf_dynamic:
        records.setdefault((child, parent), []).append((pose, attitude))
    links: dict[str, Link] = {}
    for (child, parent), seen in sorted(records.items(), key=lambda item: -len(item[1])):
        if child in links:
            continue  # (a frame has one parent in tf: its most frequent one is kept)
        poses = np.array([pose for pose, _ in seen])
        spread = np.abs(poses - poses[0])
        spread[:, 2] = np.abs(wrap_angle(spread[:, 2]))
        fixed = spread.max() <= FIXED_LINK and all(attitude == seen[0][1] for _, attitude in seen)
        links[child] = (parent, seen[0][0], FIXED if fixed else MOVING, seen[0][1])
    for child, (parent, pose, attitude) in tf_static.items():
        links[child] = (parent, pose, STATIC, attitude)
    return links


#: REP 105's frames above the odometry's: a /tf link from one of them (amcl's map -> odom) corrects the odometry, it
#: is not the odometry
GLOBAL_FRAMES = frozenset({"map", "world", "earth"})


def odometry_base(links: dict[str, Link]) -> str | None:
    """The robot's base frame as /tf gives it, for a bag whose odometry topic does not name it: the child of the /tf
    link nearest the tree's root (fewest links above it; of two, the one that moves, then by name) among those whose
    parent is no REP 105 global frame (:data:`GLOBAL_FRAMES`). So odom -> base_link, whether the robot moved or stood
    still, and not a laser's mount below it (fixed or wobbling) nor amcl's map -> odom above it. None when /tf has
    no such link. Raises :class:`LogFormatError` when the links form a cycle."""
    children = [
        child
        for child, (parent, _pose, kind, _attitude) in links.items()
        if kind != STATIC and parent not in GLOBAL_FRAMES
    ]
    if not children:
        return None
    return min(children, key=lambda child: (len(_up_from(links, child)), links[child][2] != MOVING, child))


def _up_from(links: dict[str, Link], frame: str) -> list[tuple[str, Link]]:
    """The links up from ``frame`` to its tree's root, (child, link) each; LogFormatError on a cycle."""
    chain: list[tuple[str, Link]] = []
    seen = {frame}
    while frame in links:
        chain.append((frame, links[frame]))
        frame = links[frame][0]
        if frame in seen:
            raise LogFormatError(f"the transforms form a cycle through the frame '{frame}'")
        seen.add(frame)
    return chain


class Mount(NamedTuple):
    """A laser's mount on the robot: its frame's pose (x m, y m, yaw rad) in the base frame, projected onto the
    plane, and whether it is upside down (its z axis down: a beam at angle a in the laser's frame points at yaw - a
    in the base frame, where a level laser's points at yaw + a)."""

    pose: tuple[float, float, float]
    upside_down: bool = False

    def beam_angles(self, angle_min: float, angle_increment: float) -> tuple[float, float]:
        """A scan's (angle_min, angle_increment) (rad) as a level laser at ``pose`` would give its beams."""
        return (-angle_min, -angle_increment) if self.upside_down else (angle_min, angle_increment)


#: the mount of a laser frame that is the base frame itself
AT_BASE = Mount((0.0, 0.0, 0.0))


def mount_chain(links: dict[str, Link], laser_frame: str, base_frame: str | None) -> tuple[Mount, str]:
    """The laser's :class:`Mount` in the base frame, composed from the links (:func:`frame_links`) up from
    ``laser_frame``, and the base frame's name: ``base_frame``, or when that is None the child of the chain's first
    MOVING link (the odometry's, on /tf), else the chain's root.

    Raises :class:`LogFormatError` when the chain does not reach ``base_frame``, has a MOVING link below it, tilts
    the laser's plane past TILT_LIMIT or runs in a cycle. A laser frame with no link at all is taken to be the base
    frame itself (zero offset)."""
    chain = _up_from(links, laser_frame)
    frames = [laser_frame] + [link[0] for _child, link in chain]  # the laser's frame, then each parent up
    if base_frame is None:  # (below the first link that moves, the odometry's if any, else the root)
        moving = [child for child, link in chain if link[2] == MOVING]
        base_frame = moving[0] if moving else frames[-1]
    if base_frame in frames:
        chain = chain[: frames.index(base_frame)]
    elif chain:
        raise LogFormatError(
            f"no chain of transforms (/tf_static, or fixed on /tf) links the laser frame '{laser_frame}' to the "
            f"odometry frame '{base_frame}'"
        )
    pose, attitude = (0.0, 0.0, 0.0), LEVEL
    for child, (parent, link, kind, link_attitude) in chain:
        if kind == MOVING:
            raise LogFormatError(
                f"the transform from '{parent}' to '{child}' on /tf, between the laser frame '{laser_frame}' and the "
                f"odometry frame '{base_frame}', moves during the bag: a laser on a moving joint is not read"
            )
        if link_attitude == TILTED:
            raise LogFormatError(
                f"the transform from '{parent}' to '{child}', between the laser frame '{laser_frame}' and the "
                f"odometry frame '{base_frame}', tilts the laser's scan plane more than "
                f"{math.degrees(TILT_LIMIT):.0f} deg from the floor's: a 2D map cannot take its scans (a laser "
                "upside down is read, its beams mirrored)"
            )
        pose, attitude = _compose(link, link_attitude, pose), link_attitude * attitude
    return Mount(pose, attitude == UPSIDE_DOWN), base_frame


def _odometry(got: _Decoded, odom_topic: str | None, base_frame: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Odometry stamps (K,) s and poses (K, 3) in time order: from the Odometry topic, or (None) the /tf
    transforms whose child is ``base_frame``."""
    odom = got.odom
    if odom_topic is None:
        odom = [(s, pose, child) for s, _parent, child, pose, _attitude in got.tf_dynamic if child == base_frame]
        if not odom:
            raise LogFormatError(f"{path}: /tf holds no transform to the base frame '{base_frame}'")
    odom = sorted(odom, key=lambda o: o[0])
    odom_stamps = np.array([o[0] for o in odom])
    odom_poses = np.array([o[1] for o in odom]).reshape(-1, 3)
    if not len(odom_stamps):
        raise LogFormatError(f"{path}: {odom_topic} holds no decodable odometry")
    return odom_stamps, odom_poses


def _kept_scans(
    got: _Decoded, mounts: dict, odom_stamps: np.ndarray, topic: str, max_odom_gap: float, max_odom_hold: float
) -> list[_DecodedScan]:
    """The scans whose laser frame is on the robot (``mounts``: :func:`_laser_mounts`) with odometry around
    their stamps (gap and hold in s); each other scan adds its reason to ``got.skipped``."""
    kept = []
    for scan in got.scans:
        number, stamp, _ranges, geometry = scan
        mount = mounts[geometry[4]]
        problem = mount if isinstance(mount, str) else odometry_problem(odom_stamps, stamp, max_odom_gap, max_odom_hold)
        if problem:
            got.skipped.append(Skipped(number, f"{topic}: {problem}"))
        else:
            kept.append(scan)
    return kept


def _laser_log(
    path: Path,
    kept: list[_DecodedScan],
    mounts: dict,
    odom_stamps: np.ndarray,
    odom_poses: np.ndarray,
    skipped: list[Skipped],
    notes: list[str],
) -> LaserLog:
    """The LaserLog of the kept scans, each with its own geometry (angle_min, angle_increment, range_min,
    range_max, frame) and its frame's pose on the robot (``mounts``); ranges cleaned as the module docstring
    says; ``notes``: what the reader took for granted."""
    beams = np.array([k[2].size for k in kept], dtype=np.int64)
    ranges = np.full((len(kept), int(beams.max())), PADDING, dtype=np.float32)
    for row, scan in zip(ranges, kept):
        row[: scan[2].size] = scan[2]
    geometry = np.array([k[3][:4] for k in kept], dtype=np.float64)  # (T, 4)
    for row, scan in zip(geometry, kept):  # (a laser upside down: its beams as a level one's)
        row[:2] = mounts[scan[3][4]].beam_angles(row[0], row[1])
    padding = np.arange(ranges.shape[1]) >= beams[:, None]
    ranges[ranges >= geometry[:, 3:4]] = np.inf
    ranges[(np.isnan(ranges) | np.isneginf(ranges)) & ~padding] = 0.0  # invalid, or too close: below range_min
    stamps = np.array([k[1] for k in kept])
    odometry = interpolate_poses(odom_stamps, odom_poses, stamps)
    return LaserLog(
        source=str(path),
        stamps=stamps,
        ranges=ranges,
        angle_min=geometry[:, 0],
        angle_increment=geometry[:, 1],
        range_min=np.maximum(geometry[:, 2], MIN_RANGE_FLOOR),
        range_max=geometry[:, 3],
        sensor_offset=np.array([mounts[k[3][4]].pose for k in kept], dtype=np.float64),
        odometry=odometry,
        poses=odometry.copy(),
        where=np.array([k[0] for k in kept], dtype=np.int64),
        odom_stamps=odom_stamps,
        odom_poses=odom_poses,
        skipped=tuple(skipped),
        notes=tuple(notes),
        unit="message",
        beams=beams,
    )


def scan_geometry(msg) -> tuple[float, float, float, float]:
    """(angle_min rad, angle_increment rad, range_min m, range_max m) of a ROS LaserScan, its range_max at most
    slam.laserlog.RANGE_MAX_CEILING (a scan stating +inf, as pointcloud_to_laserscan's default does, is read)."""
    range_max = bounded_range_max(float(msg.range_max))
    return (float(msg.angle_min), float(msg.angle_increment), float(msg.range_min), range_max)


def wire_scan_problem(
    ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float, range_max: float
) -> str:
    """Why a LaserScan (finite geometry; ranges m, angles rad) is not a scan the mapper can take, or "": the
    rules of the wire's LaserScan (schemas.messages), which the source would otherwise meet only when it
    publishes the scan, in the middle of a replay."""
    if not 0.0 <= range_min < range_max or range_max <= MIN_RANGE_FLOOR:
        return (
            f"range_min {range_min:g} m and range_max {range_max:g} m: need 0 <= range_min < range_max and "
            f"range_max > {MIN_RANGE_FLOOR:g} m"
        )
    problem = geometry_problem(ranges.size, angle_min, angle_increment, range_min, range_max)
    if problem:
        return problem
    negative = np.flatnonzero(ranges < 0)  # (-inf, "too close" in REP 117, is kept: it becomes 0, skipped)
    negative = negative[np.isfinite(ranges[negative])]
    if negative.size:
        return f"range {negative[0]} is {ranges[negative[0]]:g} m, below 0"
    return ""


def static_chain(tf_static: dict, laser_frame: str, base_frame: str | None) -> tuple[Mount, str]:
    """The laser's :class:`Mount` in the base frame from the static transforms alone (``tf_static``: child ->
    (parent, pose, attitude)), and the base frame's name (when ``base_frame`` is None, the chain's root):
    :func:`mount_chain`. A laser frame with no static parent is taken to be the base frame itself (zero offset)."""
    return mount_chain(frame_links(tf_static, []), laser_frame, base_frame)
