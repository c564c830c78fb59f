"""`posegrid ros2`: one robot's ROS 2 topics on Zenoh in, posegrid's keys out, and the map back (docs/ros2.md).

In: the robot's ``sensor_msgs/LaserScan``, ``nav_msgs/Odometry`` and ``tf2_msgs/TFMessage`` (or its own pose
distribution) become posegrid's LaserScan, Odometry, prior and pose messages on pg/<robot>/* (what
:mod:`services.ros2.ingest` decides), answered again from the bridge's history on pg/<robot>/history/** as a
source's are. Out: the map's tile updates (pg/map/<map>/tile/0/*/*) become ``nav_msgs/OccupancyGrid`` on ``map``
(TRANSIENT_LOCAL, at most every ``map_period`` s) and ``map_variance``, and ``map_msgs/OccupancyGridUpdate`` on
``map_updates`` per tile update; the poses on pg/<robot>/pose become a ``geometry_msgs/PoseArray`` on
``particle_cloud`` and a ``PoseWithCovarianceStamped`` on ``pose``. Everything is stamped from the scan it came
from, in frame ``map``.

Zenoh callbacks only queue what arrives; one thread decodes, converts and publishes. A sample that does not
decode, has the wrong type or type hash, lacks rmw_zenoh's attachment, or that posegrid cannot take is counted per
topic and kind (logged once per kind) and dropped; the bridge never exits for it. Counts answer a query on
pg/<robot>/ros2/stats (JSON).
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from schemas.messages import MAX_POSE_SAMPLES, MessageError, PoseGaussian, PoseSamples, TileUpdate, decode_message
from schemas.wire import Message
from services import history, keys
from services.fair_queue import FairQueue
from services.map_client import MapReader
from services.process import RejectCounter, get_logger
from services.ros2 import convert, names
from services.ros2 import types as rt
from services.ros2.endpoint import Received, RosNode, RosPublisher
from services.ros2.ingest import Ingest, IngestConfig
from services.ros2.mapout import MapMirror, MapStamp
from services.zenoh_config import undeclare_all

#: the largest sample the bridge takes from a ROS topic, bytes (a LaserScan of a million beams is 4 MB)
MAX_INPUT_BYTES = 8 << 20
#: samples, and bytes of their payloads, that may wait for the bridge's thread
QUEUE_CAPACITY = 8192
QUEUE_BYTES = 256 << 20
#: bytes of published messages the history keeps (the newest; the prior always), as a SLAM node keeps its poses
HISTORY_BYTES = 64 << 20
#: scans whose stamps the bridge remembers, to stamp the map with the scan a tile update came from
STAMPS_KEPT = 65536
#: s the bridge waits for the shards' tiles at start
CATCH_UP_TIMEOUT = 10.0


#: bytes a pose takes in CDR (position, then orientation: seven float64), and a particle (a pose and its weight), and
#: what a PoseArray's or ParticleCloud's header may add: a message past these holds more than MAX_POSE_SAMPLES poses,
#: refused before it is decoded
CDR_POSE_BYTES = {rt.POSE_ARRAY: 56, rt.PARTICLE_CLOUD: 64}
CDR_HEADROOM = 4096


@dataclass(frozen=True)
class Topics:
    """The ROS topics the bridge reads and writes (relative names resolve in the namespace). ``pose_in`` and
    ``particles_in`` (None: not read) take the robot's own poses instead of odometry; ``particles_type``: a
    ``nav2_msgs/msg/ParticleCloud`` or a ``geometry_msgs/msg/PoseArray``."""

    scan: str = "scan"
    odom: str = "odom"
    tf: str = "tf"
    tf_static: str = "tf_static"
    pose_in: str | None = None
    particles_in: str | None = None
    particles_type: str = rt.PARTICLE_CLOUD
    map: str = "map"
    map_updates: str = "map_updates"
    map_variance: str = "map_variance"
    particle_cloud: str = "particle_cloud"
    pose: str = "pose"


@dataclass(frozen=True)
class BridgeOptions:
    """Who the bridge is in both worlds and how often it sends the whole map (``map_period``, s)."""

    robot: str
    map_name: str = "main"
    mode: str = names.RMW
    domain: int = 0
    namespace: str = "/"
    node: str = "posegrid"
    frame: str = "map"
    topics: Topics = field(default_factory=Topics)
    map_period: float = 1.0
    variance_scale: float = 1.0
    wait_mappers: int = 0
    wait_slam: bool = False
    ingest: IngestConfig | None = None  # None: IngestConfig(robot) with poses when a pose topic is read

    @property
    def takes_poses(self) -> bool:
        return self.topics.pose_in is not None or self.topics.particles_in is not None


class History:
    """What the bridge has published on pg/<robot>/*, for the history queries (services.history): the prior and
    each scan's messages in the order they went out, the newest HISTORY_BYTES of them."""

    def __init__(self, limit: int = HISTORY_BYTES):
        self.limit = limit
        self.prior: bytes | None = None
        self.messages: deque[tuple[int, str, bytes]] = deque()  # (seq, stream, payload)
        self.bytes = 0
        self.lock = threading.Lock()

    def add(self, stream: str, message: Message, payload: bytes) -> None:
        with self.lock:
            if stream == keys.PRIOR:
                self.prior = payload
                return
            self.messages.append((getattr(message, "seq", 0), stream, payload))
            self.bytes += len(payload)
            while self.bytes > self.limit:
                self.bytes -= len(self.messages.popleft()[2])

    def select(self, request: history.HistoryRequest) -> list[tuple[str, bytes]]:
        with self.lock:
            out = [(keys.PRIOR, self.prior)] if self.prior is not None and keys.PRIOR in request.streams else []
            return out + [(s, p) for seq, s, p in self.messages if s in request.streams and request.wants(seq)]


class Bridge:
    """The running bridge on an open session; use :meth:`run`."""

    def __init__(self, session: zenoh.Session, options: BridgeOptions):
        self.session = session
        self.options = options
        self.log = get_logger(f"ros2[{options.robot}]")
        self.rejects = RejectCounter(self.log)
        ingest = options.ingest or IngestConfig(options.robot, poses=options.takes_poses)
        self.ingest = Ingest(ingest, self.rejects)
        self.mirror = MapMirror(options.variance_scale)
        self.history = History()
        # (kind, item, label): the ROS side's samples and posegrid's tiles and poses take turns (a flood of either
        # side's, legal or not, delays the other's by one of its own)
        self.queue: FairQueue[tuple[str, Any, str]] = FairQueue(QUEUE_CAPACITY, QUEUE_BYTES)
        self.received: Counter[str] = Counter()
        self.published: Counter[str] = Counter()
        self.bytes_out: Counter[str] = Counter()
        self.map_stamp = MapStamp(STAMPS_KEPT)  # the stamp of the latest scan (by seq) fused into the map
        self.last_map = -float("inf")  # time.monotonic() of the last whole map published
        self._pg: dict[str, zenoh.Publisher] = {}
        self._ros: dict[str, RosPublisher] = {}
        self._declared: list[Any] = []
        self.node: RosNode | None = None
        self.ros_types: dict[str, rt.MessageType] = {}  # fully qualified topic -> the type read on it
        self.lock = threading.Lock()  # guards the counters the stats query reads
        self._failed: set[str] = set()  # the keys whose failures were logged with a traceback

    # ------------------------------------------------------------------------------- callbacks (zenoh threads)
    def _offer(self, kind: str, item: Any, size: int, label: str) -> None:
        """Queue ``item`` (``size`` bytes of payload) for the working thread, the ROS side's and posegrid's taking
        turns (services.fair_queue), unless QUEUE_CAPACITY items or QUEUE_BYTES bytes wait already; what is refused,
        or evicted for the other side, is counted as "overflow" under its ``label``."""
        offered = self.queue.offer("ros" if kind == "ros" else "posegrid", (kind, item, label), size)
        full = f"more than {QUEUE_CAPACITY} samples or {QUEUE_BYTES} bytes waited for the bridge"
        for _, _, evicted_label in offered.evicted:
            self.rejects.count(evicted_label, "overflow", f"{full}: evicted for the other side's")
        if not offered.queued:
            self.rejects.count(label, "overflow", full)

    def _on_ros(self, received: Received) -> None:
        self._offer("ros", received, len(received.payload), received.topic)

    def _on_posegrid(self, kind: str, sample: zenoh.Sample) -> None:
        """A tile update or pose on posegrid's keys: queued like a ROS sample, up to MAX_INPUT_BYTES."""
        key, size = str(sample.key_expr), len(sample.payload)
        if size > MAX_INPUT_BYTES:
            self.rejects.count(key, "size", f"{size} bytes, more than the {MAX_INPUT_BYTES} the bridge takes")
            return
        self._offer(kind, (key, sample.payload.to_bytes()), size, key)

    def _on_stats(self, query: zenoh.Query) -> None:
        query.reply(keys.ros2_stats_key(self.options.robot), json.dumps(self.stats()).encode())

    def _on_history(self, query: zenoh.Query) -> None:
        request = history.parse_request(query, self.options.robot, self.rejects)
        if request is None:
            return
        answerer = history.Answerer(str(self.session.info.zid()), self.options.map_name, False)
        for stream, payload in self.history.select(request):
            history.reply(query, answerer, self.options.robot, stream, payload)

    def stats(self) -> dict[str, Any]:
        """What the bridge has received, refused and published, by topic or key (the stats query's answer)."""
        with self.lock:
            return {
                "robot": self.options.robot,
                "mode": self.options.mode,
                "received": dict(self.received),
                "rejected": self.rejects.snapshot(),
                "rejected_kinds": self.rejects.kinds(),
                "published": dict(self.published),
                "bytes_published": dict(self.bytes_out),
                "scans": self.ingest.seq,
                "unposed": self.ingest.unposed,
            }

    # ------------------------------------------------------------------------------- the work (one thread)
    def _handle(self, kind: str, item: Any, _label: str) -> None:  # (the label counts what the queue refuses)
        if kind == "ros":
            self._guarded(item.topic, self._take_ros, item)
        elif kind == "tile":
            self._guarded(item[0], self._take_tile, *item)
        else:
            self._guarded(item[0], self._take_pose, *item)

    def _guarded(self, key: str, take: Callable[..., object], *args: Any) -> None:
        """``take(*args)`` for a message on ``key``; an exception it raises (a message the checks let through that
        still fails) is counted (``error``; the first per key logged with its traceback), and the bridge goes on."""
        try:
            take(*args)
        except Exception as exc:
            if key not in self._failed:
                self._failed.add(key)
                self.log.error("a message on %s could not be taken; the bridge goes on", key, exc_info=exc)
            self.rejects.count(key, "error", f"{type(exc).__name__}: {exc}")

    def _take_ros(self, received: Received) -> None:
        topic = received.topic
        with self.lock:
            self.received[topic] += 1
        message_type = self.ros_types[topic]
        problem = self._sample_problem(received, message_type)
        if problem:
            self.rejects.count(topic, *problem)
            return
        try:
            msg = message_type.decode(received.payload)
        except rt.CdrError as exc:
            self.rejects.count(topic, "cdr", str(exc))
            return
        try:
            self._dispatch(topic, message_type, msg)
        except convert.ConversionError as exc:
            self.rejects.count(topic, exc.kind, str(exc))
        except (AttributeError, TypeError, ValueError, OverflowError) as exc:  # fields a decoded message lacks
            self.rejects.count(topic, "cdr", f"{type(exc).__name__}: {exc}"[:300])

    def _sample_problem(self, received: Received, message_type: rt.MessageType) -> tuple[str, str] | None:
        """(kind, detail) of why a sample is refused before decoding: its size, key, type or attachment."""
        if received.size > MAX_INPUT_BYTES:
            return "size", f"{received.size} bytes, more than the {MAX_INPUT_BYTES} the bridge takes"
        per_pose = CDR_POSE_BYTES.get(message_type.name)
        if per_pose is not None and received.size > MAX_POSE_SAMPLES * per_pose + CDR_HEADROOM:
            return "pose", (  # (decoded and converted first, 100 000 poses held the robot's scans 0.7 s each)
                f"{received.size} bytes, more than {MAX_POSE_SAMPLES} poses of {per_pose} bytes take: more than "
                "the poses a message may carry"
            )
        node = self.node
        assert node is not None
        parsed = names.parse_topic_key(received.key, node.graph, received.topic)
        if parsed is None:
            return "key", f"a sample on {received.key[:200]!r}, no key of topic {received.topic}"
        if node.graph.mode == names.RMW:
            if parsed != (message_type.dds_name, message_type.type_hash):
                return "type", f"type {parsed[0]} {parsed[1]}, not {message_type.dds_name} {message_type.type_hash}"
            if received.attachment is None or names.decode_attachment(received.attachment) is None:
                return "attachment", "no rmw_zenoh attachment (sequence number, source timestamp, GID)"
        return None

    def _dispatch(self, topic: str, message_type: rt.MessageType, msg: Any) -> None:
        node, topics, robot = self.node, self.options.topics, self.options.robot
        assert node is not None
        if message_type.name == rt.LASER_SCAN:
            self.ingest.on_scan(topic, msg)
        elif message_type.name == rt.ODOMETRY:
            self.ingest.on_odometry(topic, msg)
        elif message_type.name == rt.TF_MESSAGE:
            self.ingest.on_transforms(topic, msg, static=topic == node.resolve(topics.tf_static))
        elif message_type.name == rt.POSE_COVARIANCE:
            self.ingest.on_pose(topic, convert.to_gaussian(msg, robot, 0))
        else:
            self.ingest.on_pose(
                topic, convert.to_samples(msg, robot, 0, weighted=message_type.name == rt.PARTICLE_CLOUD)
            )

    def _take_tile(self, key: str, payload: bytes) -> None:
        with self.lock:  # (counted under the subscription's key: a peer making up tile keys makes no new counters)
            self.received[keys.tile_key(self.options.map_name, 0, "*", "*")] += 1
        try:
            tile = decode_message(payload, TileUpdate)
        except MessageError as exc:
            self.rejects.count(key, exc.reason, str(exc))
            return
        problem = self.mirror.check(tile) or ("" if tile.map == self.options.map_name else f"a tile of map {tile.map}")
        if problem:
            self.rejects.count(key, "tile", problem)
            return
        if tile.robot == self.options.robot:
            self.map_stamp.fused(tile.seq)
        patch = self.mirror.apply(tile)
        if patch is not None:
            update = convert.grid_update(patch.values, patch.x, patch.y, self.map_stamp.stamp, self.options.frame)
            self._publish_ros("map_updates", update)

    def _take_pose(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.received[key] += 1
        try:
            pose = decode_message(payload, PoseSamples, PoseGaussian)
        except MessageError as exc:
            self.rejects.count(key, exc.reason, str(exc))
            return
        if pose.seq >= self.ingest.seq:  # (a flood of forged 10 000-sample poses held ROS's map updates for 45 s)
            self.rejects.count(
                key, "ahead", f"pose seq {pose.seq}: this bridge has sent scans of seqs below {self.ingest.seq} only"
            )
            return
        frame = self.options.frame
        if isinstance(pose, PoseSamples):
            self._publish_ros("particle_cloud", convert.pose_array(pose, frame))
        self._publish_ros("pose", convert.pose_with_covariance(pose, frame))

    def _publish_ros(self, role: str, message: Any) -> None:
        publisher = self._ros[role]
        size = publisher.put(message)
        with self.lock:
            self.published[publisher.fqn] += 1
            self.bytes_out[publisher.fqn] += size

    def _publish_pg(self, stream: str, message: Message) -> None:
        payload = message.encode()
        if stream not in self._pg:
            self._pg[stream] = self.session.declare_publisher(
                keys.robot_key(self.options.robot, stream), congestion_control=zenoh.CongestionControl.BLOCK
            )
        if stream == keys.SCAN:
            self.map_stamp.published(message.seq, message.stamp)  # type: ignore[attr-defined]
        self.history.add(stream, message, payload)
        self._pg[stream].put(payload)
        with self.lock:
            self.published[keys.robot_key(self.options.robot, stream)] += 1

    def _maybe_publish_map(self) -> None:
        now = time.monotonic()
        if not self.mirror.dirty or now - self.last_map < self.options.map_period:
            return
        self.last_map = now
        self._guarded(keys.tile_key(self.options.map_name, 0, "*", "*"), self._publish_map)

    def _publish_map(self) -> None:
        """The whole grid on map and map_variance, when the mirror can make it."""
        raster = self.mirror.raster()
        if raster is None:
            return
        frame, stamp = self.options.frame, self.map_stamp.stamp
        self._publish_ros(
            "map", convert.occupancy_grid(raster.occupancy, raster.origin, raster.resolution, stamp, frame)
        )
        self._publish_ros(
            "map_variance", convert.occupancy_grid(raster.variance, raster.origin, raster.resolution, stamp, frame)
        )

    def step(self, timeout: float) -> None:
        """Take what waits (up to ``timeout`` s for the first), publish what is ready."""
        try:
            waiting = self.queue.take(timeout)
        except queue.Empty:
            pass
        else:
            self._handle(*waiting)
            for _ in range(256):  # what else waits, before the map goes out
                try:
                    waiting = self.queue.take(0.0)
                except queue.Empty:
                    break
                self._handle(*waiting)
        for stream, message in self.ingest.ready():
            self._publish_pg(stream, message)
        self._maybe_publish_map()

    # ------------------------------------------------------------------------------- lifecycle
    def _declare_ros(self) -> None:
        opts, topics = self.options, self.options.topics
        node = self.node = RosNode(self.session, opts.mode, opts.domain, opts.namespace, opts.node)
        outputs = [
            ("map", topics.map, rt.OCCUPANCY_GRID, names.MAP_QOS),
            ("map_variance", topics.map_variance, rt.OCCUPANCY_GRID, names.MAP_QOS),
            ("map_updates", topics.map_updates, rt.GRID_UPDATE, names.STREAM_QOS),
        ]
        if not opts.takes_poses:
            outputs += [
                ("particle_cloud", topics.particle_cloud, rt.POSE_ARRAY, names.STREAM_QOS),
                ("pose", topics.pose, rt.POSE_COVARIANCE, names.STREAM_QOS),
            ]
        for role, topic, type_name, qos in outputs:
            self._ros[role] = node.publisher(topic, rt.MessageType(type_name), qos)
        for topic, type_name, qos in self._inputs():
            self.ros_types[node.resolve(topic)] = rt.MessageType(type_name)
            node.subscription(topic, rt.MessageType(type_name), qos, self._on_ros, max_bytes=MAX_INPUT_BYTES)

    def _inputs(self) -> list[tuple[str, str, names.QoS]]:
        topics = self.options.topics
        inputs = [
            (topics.scan, rt.LASER_SCAN, names.SENSOR_QOS),
            (topics.tf_static, rt.TF_MESSAGE, names.TF_STATIC_QOS),
        ]
        if self.options.takes_poses:
            if topics.pose_in is not None:
                inputs.append((topics.pose_in, rt.POSE_COVARIANCE, names.STREAM_QOS))
            if topics.particles_in is not None:
                inputs.append((topics.particles_in, topics.particles_type, names.STREAM_QOS))
        else:
            inputs += [(topics.odom, rt.ODOMETRY, names.STREAM_QOS), (topics.tf, rt.TF_MESSAGE, names.TF_QOS)]
        return inputs

    def _declare_posegrid(self) -> None:
        opts, session = self.options, self.session
        self._declared.append(session.declare_queryable(keys.history_key(opts.robot), self._on_history))
        self._declared.append(session.declare_queryable(keys.ros2_stats_key(opts.robot), self._on_stats))
        tiles = keys.tile_key(opts.map_name, 0, "*", "*")
        self._declared.append(session.declare_subscriber(tiles, lambda sample: self._on_posegrid("tile", sample)))
        if not opts.takes_poses:
            poses = keys.robot_key(opts.robot, keys.POSE)
            self._declared.append(session.declare_subscriber(poses, lambda sample: self._on_posegrid("pose", sample)))
        self._declared.append(session.liveliness().declare_token(keys.robot_alive_key(opts.robot, "source")))

    def _wait_for_subscribers(self, stop: threading.Event) -> bool:
        """Wait for ``wait_mappers`` shards of the map and, with ``wait_slam``, the robot's SLAM node; False when
        ``stop`` is set first."""
        opts = self.options
        shards = MapReader(self.session, opts.map_name)
        while opts.wait_mappers and len(shards.tokens(timeout=2.0)) < opts.wait_mappers:
            if stop.wait(0.1):
                return False
        slam = keys.robot_alive_key(opts.robot, "slam")
        while opts.wait_slam and not any(r.ok is not None for r in self.session.liveliness().get(slam, timeout=2.0)):
            if stop.wait(0.1):
                return False
        return True

    def _catch_up(self) -> None:
        """The map's tiles so far, from the shards' tile queries (services.map_client)."""
        for tile in MapReader(self.session, self.options.map_name).tiles(timeout=CATCH_UP_TIMEOUT):
            if not self.mirror.check(tile):
                self._guarded(keys.tile_key(tile.map, tile.z, tile.tx, tile.ty), self.mirror.apply, tile)

    def run(self, stop: threading.Event) -> int:
        """Bridge until ``stop`` is set; returns the exit code (0)."""
        opts = self.options
        self._declare_posegrid()
        try:
            if not self._wait_for_subscribers(stop):
                return 0
            self._catch_up()
            self._declare_ros()
            assert self.node is not None
            self.log.info(
                "up (%s, domain %d, namespace %s): reading %s; map on %s",
                opts.mode,
                opts.domain,
                opts.namespace,
                ", ".join(sorted(self.ros_types)),
                self._ros["map"].key,
            )
            while not stop.is_set():
                self.step(0.05)
        finally:
            if self.node is not None:
                self.node.close()
            undeclare_all(self._declared)
        self.log.info("stopped after %d scans; %s", self.ingest.seq, self._losses())
        return 0

    def _losses(self) -> str:
        """The messages the bridge did not pass on, for its exit line: refusals by kind, and the scans dropped for
        want of a pose (not refusals: the robot's localisation publishes less often than its laser)."""
        stats = self.stats()
        rejected, unposed = stats["rejected_kinds"], stats["unposed"]
        said = f"refused {json.dumps(rejected)}" if rejected else "none refused"
        if unposed:
            said += f"; {unposed} scan(s) dropped with no pose within --odom-wait s"
        return said
