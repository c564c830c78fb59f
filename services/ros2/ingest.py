"""What the bridge makes of one robot's ROS 2 topics (no networking here): posegrid's LaserScan, Odometry, prior and
pose messages, with seqs 0, 1, 2 ... in the order the scans go out.

**With odometry** (a ``nav_msgs/Odometry`` topic, or the ``/tf`` transforms to the robot's base frame when no
Odometry has come), each scan waits until odometry at or after its stamp has come (per topic it arrives in stamp
order), then goes out with the odometry pose interpolated at its stamp, exactly as the bag reader reads a bag
(slam.rosbag_reader: linear in x, y and in yaw unwrapped along the whole odometry stream; a scan between two
odometry poses more than ``max_odom_gap`` s apart, or more than ``max_odom_hold`` s before the first, is refused).
When no later odometry comes within ``wait`` s (wall clock), the last pose is held if the scan lies within
``max_odom_hold`` s of it, as the bag reader does at a bag's end. The first scan's odometry pose goes out first as
the prior (where the SLAM filter starts). A replayed bag thus gives the very messages `posegrid source --bag` sends.

**With the robot's own poses** (``IngestConfig.poses``: an amcl or slam_toolbox pose, a particle cloud), a pose
is joined with the waiting scan nearest its stamp within ``pose_tolerance`` s; scans no pose comes for are
dropped after ``wait`` s (counted in :attr:`Ingest.unposed`: the robot's localisation publishes less often than
its laser), and so are poses no scan matches (counted as "join").

The base frame is ``base_frame`` when given, else the Odometry's child frame, else (odometry on /tf, or poses) the
root of the laser frame's chain of static transforms. The laser's mount is that chain's pose, from ``/tf_static``;
a scan whose frame no static chain links to the base frame within ``wait`` s is refused as "transform".

Refusals are counted per ROS topic and kind (:class:`services.process.RejectCounter`): "geometry" (a scan the wire
refuses: NaN geometry, no ranges, ...), "transform", "odometry" (no odometry around the scan), "order" (odometry or a
transform older than one before it), "pose" (a pose or covariance posegrid cannot take), "join", "overflow" (more
than ``capacity`` scans or poses waiting).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from schemas.messages import Odometry, PoseGaussian, PoseSamples
from schemas.wire import Message
from services import keys
from services.process import RejectCounter
from services.ros2.convert import (
    ConversionError,
    encoded,
    pose_of,
    scan_problem,
    stamp_of,
    to_laser_scan,
    transform_pose,
)
from slam.errors import LogFormatError
from slam.laserlog import (
    MAX_ODOM_GAP,
    MAX_ODOM_HOLD,
    NO_RETURN_RANGE,
    interpolate_poses,
    odometry_problem,
    plausible_pose,
)
from slam.rosbag_reader import AT_BASE, Mount, quaternion_attitude, static_chain

#: odometry records a track keeps (the newest): about 80 s of odometry at 50 Hz
TRACK_RECORDS = 4096
#: child frames of /tf whose transforms are tracked (odometry from /tf): past it, a new frame replaces the one updated
#: longest ago that no scan has taken as its base (a peer making up frames gets no more memory, and cannot push out
#: the robot's base frame, which its scans name and which moves at the odometry's rate)
MAX_TF_FRAMES = 64
#: child frames of /tf_static kept (a robot_state_publisher's fixed joints): a peer making up frames gets no more
MAX_STATIC_FRAMES = 1024
#: base frames remembered as the scans' (the newest), whose /tf tracks are never replaced
MAX_BASE_FRAMES = 8
#: odometry records in a row, each at or after the one before, that a track takes as a clock that went back (a
#: robot's clock set back, or one record stamped far ahead), starting over from them instead of refusing them all
RESTART_RECORDS = 3

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class IngestConfig:
    """robot: posegrid's robot name; no_return_range: how far (m) the laser's beams with no return clear free space
    (slam.laserlog.NO_RETURN_RANGE); base_frame: the robot's base frame (None: see the module); max_odom_gap,
    max_odom_hold, wait, pose_tolerance: s; poses: join the robot's own poses instead of odometry; capacity: scans
    (and poses) that may wait."""

    robot: str
    no_return_range: float = NO_RETURN_RANGE
    base_frame: str | None = None
    max_odom_gap: float = MAX_ODOM_GAP
    max_odom_hold: float = MAX_ODOM_HOLD
    wait: float = 2.0
    poses: bool = False
    pose_tolerance: float = 0.05
    capacity: int = 256


class OdometryTrack:
    """Odometry poses (x m, y m, yaw rad) in stamp order, the newest :data:`TRACK_RECORDS` of them, with yaw unwrapped
    as ``np.unwrap`` unwraps the whole stream (the same floating-point steps, one record at a time), so that an
    interpolation gives the bag reader's very value."""

    def __init__(self, records: int = TRACK_RECORDS):
        self._stamps: deque[float] = deque(maxlen=records)
        self._poses: deque[tuple[float, float, float]] = deque(maxlen=records)
        self._raw_yaw = 0.0  # the last record's yaw as it came
        self._correction = 0.0  # the running sum of np.unwrap's corrections
        self._arrays: tuple[np.ndarray, np.ndarray] | None = None
        self._behind: list[tuple[float, Pose]] = []  # the records refused since the last taken, each in order
        self.restarts = 0  # times the track started over (RESTART_RECORDS)

    def __len__(self) -> int:
        return len(self._stamps)

    @property
    def last_stamp(self) -> float:
        return self._stamps[-1] if self._stamps else -math.inf

    def add(self, stamp: float, pose: Pose) -> bool:
        """Append a record; False (nothing appended) when ``stamp`` (s) is before the last one's, unless it is the
        RESTART_RECORDS-th such record in a row, each at or after the one before: then the clock went back (or the
        last record was stamped ahead), and the track starts over from those records (:attr:`restarts`)."""
        if self._stamps and stamp < self._stamps[-1]:
            in_order = bool(self._behind) and stamp >= self._behind[-1][0]
            self._behind = [*self._behind, (stamp, pose)] if in_order else [(stamp, pose)]
            if len(self._behind) < RESTART_RECORDS:
                return False
            behind, self._behind = self._behind, []
            self._stamps.clear()
            self._poses.clear()
            self._correction = 0.0
            self.restarts += 1
            for record in behind:
                self._append(*record)
            return True
        self._behind = []
        self._append(stamp, pose)
        return True

    def _append(self, stamp: float, pose: Pose) -> None:
        """Append a record at or after the last (the first of a track as np.unwrap starts a stream)."""
        yaw = pose[2]
        if self._stamps:
            self._correction += _unwrap_correction(yaw - self._raw_yaw)
            unwrapped = yaw + self._correction
        else:
            unwrapped = yaw
        self._raw_yaw = yaw
        self._stamps.append(stamp)
        self._poses.append((pose[0], pose[1], unwrapped))
        self._arrays = None

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (K,) s, poses (K, 3) with unwrapped yaw)."""
        if self._arrays is None:
            self._arrays = (np.array(self._stamps, dtype=np.float64), np.array(self._poses, dtype=np.float64))
        return self._arrays

    def problem(self, stamp: float, max_gap: float, max_hold: float) -> str:
        """slam.laserlog.odometry_problem at ``stamp`` (s) over the records."""
        return odometry_problem(self.arrays()[0], stamp, max_gap, max_hold)

    def pose_at(self, stamp: float) -> np.ndarray:
        """The pose (3,) interpolated at ``stamp`` (s) as slam.laserlog.interpolate_poses gives it."""
        stamps, poses = self.arrays()
        return interpolate_poses(stamps, poses, np.array([stamp]))[0]


def _unwrap_correction(dd: float) -> float:
    """np.unwrap's correction of one step ``dd`` (rad) between consecutive raw angles (period 2 pi, discont pi):
    its formula for one element, so that summing the corrections in order gives its cumulative sum."""
    period = 2.0 * np.pi
    ddmod = float(np.mod(np.float64(dd) + np.pi, period) - np.pi)
    if ddmod == -np.pi and dd > 0:
        ddmod = float(np.pi)
    return 0.0 if abs(dd) < np.pi else ddmod - dd


@dataclass
class _Waiting:
    """A ROS LaserScan waiting for its odometry, transform or pose; ``since``: clock time it came, s."""

    topic: str
    msg: Any
    stamp: float
    frame: str
    since: float


@dataclass
class _PoseWaiting:
    topic: str
    pose: PoseGaussian | PoseSamples  # (seq 0 until it is joined)
    since: float


class Ingest:
    """The state of the in-direction. Feed it decoded ROS messages (``on_*``); :meth:`ready` returns what may go
    out now. Not thread-safe: one thread drives it. ``clock``: s, for tests."""

    def __init__(self, config: IngestConfig, rejects: RejectCounter, clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.rejects = rejects
        self.clock = clock
        # child frame -> (parent frame, pose in the parent, attitude: slam.rosbag_reader.quaternion_attitude)
        self.static: dict[str, tuple[str, Pose, int]] = {}
        self.odom = OdometryTrack()
        self.odom_child: str | None = None  # the child frame of the Odometry messages: the robot's base
        self.tf_tracks: OrderedDict[str, OdometryTrack] = OrderedDict()  # /tf transforms by child, updated last last
        self.bases: OrderedDict[str, None] = OrderedDict()  # the base frames scans took, the newest last
        self.scans: deque[_Waiting] = deque()
        self.poses: deque[_PoseWaiting] = deque()
        self.seq = 0  # the next scan's seq
        self.prior_sent = False
        self.unposed = 0  # scans dropped for want of a pose (with poses)
        self._out: list[tuple[str, Message]] = []  # (stream: keys.PRIOR, SCAN, ODOM or POSE, message)

    # ------------------------------------------------------------------------------------ input
    def on_scan(self, topic: str, msg: Any) -> None:
        """A decoded ``sensor_msgs/LaserScan`` from ``topic``."""
        problem = scan_problem(msg)
        if problem:
            self.rejects.count(topic, "geometry", problem)
            return
        if len(self.scans) >= self.config.capacity:
            dropped = self.scans.popleft()
            self.rejects.count(dropped.topic, "overflow", f"more than {self.config.capacity} scans waited")
        self.scans.append(_Waiting(topic, msg, stamp_of(msg.header), str(msg.header.frame_id), self.clock()))

    def on_odometry(self, topic: str, msg: Any) -> None:
        """A decoded ``nav_msgs/Odometry``: its pose is the robot's odometry pose at its stamp."""
        pose, stamp = pose_of(msg.pose.pose), stamp_of(msg.header)
        if not (plausible_pose(pose) and math.isfinite(stamp)):
            self.rejects.count(topic, "pose", "an odometry pose or stamp that is not finite or beyond the pose limit")
            return
        if not self._add(self.odom, topic, "odometry", stamp, pose):
            return
        if self.odom_child is None:
            self.odom_child = str(msg.child_frame_id)

    def on_transforms(self, topic: str, msg: Any, static: bool) -> None:
        """A decoded ``tf2_msgs/TFMessage`` from /tf (``static`` False) or /tf_static."""
        for tf in msg.transforms:
            pose, child = transform_pose(tf.transform), str(tf.child_frame_id)
            if not plausible_pose(pose):
                self.rejects.count(topic, "pose", f"transform to {child} not finite or beyond the pose limit")
            elif static:
                if child not in self.static and len(self.static) >= MAX_STATIC_FRAMES:
                    self.rejects.count(topic, "overflow", f"more than {MAX_STATIC_FRAMES} frames on /tf_static")
                    continue
                self.static[child] = (str(tf.header.frame_id), pose, quaternion_attitude(tf.transform.rotation))
            else:
                track = self._tf_track(topic, child)
                if track is not None:
                    self._add(track, topic, f"the transform to {child}", stamp_of(tf.header), pose)

    def _tf_track(self, topic: str, child: str) -> OdometryTrack | None:
        """The /tf track of ``child``, made when new: past MAX_TF_FRAMES it replaces the track updated longest ago
        that is no scan's base (counted as "overflow"); None, counted, when every track is a base's."""
        track = self.tf_tracks.get(child)
        if track is not None:
            self.tf_tracks.move_to_end(child)
            return track
        if len(self.tf_tracks) >= MAX_TF_FRAMES:
            unused = next((frame for frame in self.tf_tracks if frame not in self.bases), None)
            if unused is None:
                self.rejects.count(topic, "overflow", f"more than {MAX_TF_FRAMES} frames on /tf, each a base's")
                return None
            del self.tf_tracks[unused]
            self.rejects.count(topic, "overflow", f"more than {MAX_TF_FRAMES} frames on /tf: {unused!r} dropped")
        track = self.tf_tracks[child] = OdometryTrack()
        return track

    def _add(self, track: OdometryTrack, topic: str, what: str, stamp: float, pose: Pose) -> bool:
        """``track.add`` with what it refuses counted as "order", and a restart as "clock"; whether it took it."""
        restarts = track.restarts
        if not track.add(stamp, pose):
            self.rejects.count(topic, "order", f"{what} at {stamp:.6f} s came after a later one")
            return False
        if track.restarts > restarts:
            self.rejects.count(
                topic,
                "clock",
                f"{what}'s stamps went back ({RESTART_RECORDS} in a row before the last taken): its track started "
                "over from them",
            )
        return True

    def on_pose(self, topic: str, pose: PoseGaussian | PoseSamples) -> None:
        """The robot's own pose distribution (converted, seq 0), to be joined with a scan by stamp."""
        if len(self.poses) >= self.config.capacity:
            dropped = self.poses.popleft()
            self.rejects.count(dropped.topic, "overflow", f"more than {self.config.capacity} poses waited")
        self.poses.append(_PoseWaiting(topic, pose, self.clock()))

    # ------------------------------------------------------------------------------------ output
    def ready(self) -> list[tuple[str, Message]]:
        """(stream, message) of the messages that may go out now, in order (the prior first, on keys.PRIOR; per scan
        its LaserScan, then its Odometry or pose); call after every input and now and then (scans time out)."""
        if self.config.poses:
            self._join_poses()
        else:
            self._join_odometry()
        out, self._out = self._out, []
        return out

    def _root(self, frame: str) -> str:
        """The root of ``frame``'s chain of static transforms."""
        try:
            return static_chain(self.static, frame, None)[1]
        except LogFormatError:  # (a cycle: unreachable with base None)
            return frame

    def _pose_base(self, frame: str) -> str | None:
        """The base frame of a scan from laser ``frame`` joined with the robot's own poses (which name no base
        frame): the root of the laser's static chain when /tf_static gives it a parent; the laser frame itself when
        the robot names it as a frame of its own (its odometry's child, a frame /tf moves, a parent on /tf_static:
        a scan made in base_link, as pointcloud_to_laserscan's target_frame gives it); else None (a laser frame no
        transform names: its mount is unknown, not the base's origin)."""
        if frame in self.static:
            return self._root(frame)
        named = frame == self.odom_child or frame in self.tf_tracks
        return frame if named or any(parent == frame for parent, _, _ in self.static.values()) else None

    @staticmethod
    def _unplaced(frame: str) -> str:
        """Why a scan from laser ``frame``, which no transform names (:meth:`_pose_base`), has no mount."""
        return (
            f"no /tf_static chain links the laser frame {frame!r} to the robot, and no transform names it the "
            f"robot's own: publish its mount on /tf_static, or give --base-frame {frame} if it is the robot's base"
        )

    def _mount(self, frame: str, base: str) -> Mount | str:
        """The laser frame's mount on ``base`` from the static transforms, or why there is none (while no chain
        links them, or one that tilts the laser's scan plane)."""
        if frame == base:
            return AT_BASE
        if frame not in self.static:
            return f"no /tf_static chain links the laser frame {frame!r} to {base!r}"
        try:
            return static_chain(self.static, frame, base)[0]
        except LogFormatError as exc:
            return str(exc)

    def _track(self, frame: str) -> tuple[OdometryTrack, str] | None:
        """The odometry a scan from laser ``frame`` takes and the base frame: the Odometry topic's, else /tf's
        transforms to the base frame; None while there is none."""
        if len(self.odom):
            base = self.config.base_frame or self.odom_child or self._root(frame)
            return self.odom, base
        base = self.config.base_frame or self._root(frame)
        self.bases[base] = None  # (its /tf track is kept)
        self.bases.move_to_end(base)
        if len(self.bases) > MAX_BASE_FRAMES:
            self.bases.popitem(last=False)
        track = self.tf_tracks.get(base)
        return (track, base) if track is not None and len(track) else None

    def _join_odometry(self) -> None:
        config, now = self.config, self.clock()
        while self.scans:
            head = self.scans[0]
            late = now - head.since > config.wait
            found = self._track(head.frame)
            if found is None or found[0].last_stamp < head.stamp:
                if not late:
                    return  # later odometry may still come
                if found is None:
                    self.scans.popleft()
                    self.rejects.count(head.topic, "odometry", f"no odometry came within {config.wait:g} s")
                    continue
            track, base = found
            mount = self._mount(head.frame, base)
            if isinstance(mount, str):
                if not late:
                    return
                self.scans.popleft()
                self.rejects.count(head.topic, "transform", mount)
                continue
            self.scans.popleft()
            problem = track.problem(head.stamp, config.max_odom_gap, config.max_odom_hold)
            if problem:
                self.rejects.count(head.topic, "odometry", problem)
                continue
            self._emit_odometry(head, mount, track.pose_at(head.stamp))

    def _emit_odometry(self, head: _Waiting, mount: Mount, pose: np.ndarray) -> None:
        robot, seq = self.config.robot, self.seq
        try:
            scan = to_laser_scan(head.msg, robot, seq, mount, self.config.no_return_range)
            encoded(scan, "geometry")
        except ConversionError as exc:
            self.rejects.count(head.topic, exc.kind, str(exc))
            return
        if not self.prior_sent:
            prior = PoseGaussian(robot=robot, seq=0, stamp=scan.stamp, mean=pose.copy(), cov=np.zeros((3, 3)))
            self._out.append((keys.PRIOR, prior))
            self.prior_sent = True
        odometry = Odometry(
            robot=robot, seq=seq, stamp=scan.stamp, pose=pose[None, :].copy(), commands=np.zeros((0, 3))
        )
        self._out += [(keys.SCAN, scan), (keys.ODOM, odometry)]
        self.seq += 1

    def _join_poses(self) -> None:
        config, now = self.config, self.clock()
        while self.poses:
            waiting = self.poses[0]
            stamp = waiting.pose.stamp
            matches = [i for i, scan in enumerate(self.scans) if abs(scan.stamp - stamp) <= config.pose_tolerance]
            if not matches:
                if now - waiting.since <= config.wait:
                    break
                self.poses.popleft()
                self.rejects.count(waiting.topic, "join", f"no scan within {config.pose_tolerance:g} s of the pose")
                continue
            best = min(matches, key=lambda i: abs(self.scans[i].stamp - stamp))
            scan = self.scans[best]
            base = config.base_frame or self._pose_base(scan.frame)
            mount = self._mount(scan.frame, base) if base is not None else self._unplaced(scan.frame)
            if isinstance(mount, str) and now - scan.since <= config.wait:
                break
            self.poses.popleft()
            for _ in range(best):
                self.scans.popleft()
                self.unposed += 1
            self.scans.popleft()
            if isinstance(mount, str):
                self.rejects.count(scan.topic, "transform", mount)
                continue
            self._emit_posed(scan, mount, waiting.pose)
        while self.scans and now - self.scans[0].since > config.wait:
            self.scans.popleft()
            self.unposed += 1

    def _emit_posed(self, head: _Waiting, mount: Mount, pose: PoseGaussian | PoseSamples) -> None:
        seq = self.seq
        try:
            scan = to_laser_scan(head.msg, self.config.robot, seq, mount, self.config.no_return_range)
            encoded(scan, "geometry")
        except ConversionError as exc:
            self.rejects.count(head.topic, exc.kind, str(exc))
            return
        self._out += [(keys.SCAN, scan), (keys.POSE, dataclasses.replace(pose, seq=seq))]
        self.seq += 1
