"""`posegrid ros2 play BAG`: a ROS 2 bag's messages published on its topics over Zenoh, as a robot on rmw_zenoh (or
behind zenoh-bridge-ros2dds) would publish them: a stand-in for a robot in tests and demos (docs/ros2.md).

Each message's CDR bytes go out as recorded, on its topic placed under ``namespace`` (``/scan`` in ``/robot1``:
``/robot1/scan``), paced by the bag's timestamps at ``rate`` times real time (None: as fast as the subscribers
take; every sample goes out reliably with congestion control BLOCK). ``/tf_static`` (any topic named
``tf_static``) is TRANSIENT_LOCAL, as robot_state_publisher's is; the others are volatile. Topics of types the
type store does not know are left out (said once on stderr). With ``wait`` > 0, publishing starts once every
played topic has a subscription (its liveliness token), or after ``wait`` s.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from services.errors import UsageError
from services.ros2 import names
from services.ros2.endpoint import RosNode, RosPublisher
from services.ros2.types import MessageType, typestore
from slam.laserlog import Skipped
from slam.rosbag_reader import bag_records, open_bag

#: what ``posegrid ros2 play`` says it expected when given no bag
ROS2_BAG = "a ROS 2 bag: its folder with metadata.yaml, or its .mcap or .db3 file"

#: ns per s
NS = 1_000_000_000


@dataclass(frozen=True)
class PlayOptions:
    """mode: names.RMW or names.BRIDGE; rate: factor of real time, None for as fast as possible; topics: the bag's
    topics to play (None: all of known types); wait: s to wait for subscriptions before the first message."""

    mode: str = names.RMW
    domain: int = 0
    namespace: str = "/"
    node: str = "posegrid_play"
    rate: float | None = 1.0
    topics: tuple[str, ...] | None = None
    wait: float = 0.0


def placed(topic: str, namespace: str) -> str:
    """A bag topic (absolute) placed under ``namespace``."""
    topic = "/" + topic.lstrip("/")
    return topic if namespace == "/" else namespace.rstrip("/") + topic


def _qos(topic: str) -> names.QoS:
    return names.TF_STATIC_QOS if topic.rstrip("/").endswith("tf_static") else names.STREAM_QOS


def subscription_pattern(graph: names.Graph, fqn: str) -> str:
    """A key expression matching every subscription token of topic ``fqn`` (rmw_zenoh's, or the bridge's)."""
    if graph.mode == names.BRIDGE:
        return f"@/*/{names.ADMIN_SPACE}/{names.SUBSCRIPTION}/{fqn.lstrip('/').replace('/', '§')}/**"
    return f"{names.ADMIN_SPACE}/{graph.domain}/*/*/*/{names.SUBSCRIPTION}/*/*/*/{names.mangle(fqn)}/**"


class Player:
    """Plays one bag on ``session`` (open when :meth:`run` is called); use :meth:`check`, then :meth:`run`."""

    def __init__(self, session: zenoh.Session | None, path: Path, options: PlayOptions):
        self.session = session
        self.path = path
        self.options = options
        self.published = 0

    def _connections(self, reader, quiet: bool = False) -> list:
        """The connections to play: ROS 2 only, of known types, among ``topics`` (what is left out is said on
        stderr unless ``quiet``); UsageError when the bag has none to play."""
        if not reader.is2:
            raise UsageError(f"{self.path}: a ROS 1 bag; `posegrid ros2 play` replays ROS 2 bags (CDR as recorded)")
        known = typestore().types
        wanted = self.options.topics
        if wanted is not None:
            missing = sorted(set(wanted) - {c.topic for c in reader.connections})
            if missing:
                raise UsageError(f"{self.path}: has no topic(s) {', '.join(missing)}")
        chosen = [c for c in reader.connections if wanted is None or c.topic in wanted]
        unknown = sorted({f"{c.topic} ({c.msgtype})" for c in chosen if c.msgtype not in known})
        if unknown and not quiet:
            print(f"posegrid ros2 play: note: left out, of types not known here: {', '.join(unknown)}", file=sys.stderr)
        chosen = [c for c in chosen if c.msgtype in known]
        if not chosen:
            raise UsageError(f"{self.path}: no topic to play")
        return chosen

    def check(self) -> None:
        """Raise UsageError or slam.errors.LogFormatError (exit 2) when the bag cannot be played; call before the
        session is opened, so that a wrong bag is said at once."""
        reader = open_bag(self.path, ROS2_BAG)
        try:
            self._connections(reader, quiet=True)
        finally:
            reader.close()

    def _wait_for_subscriptions(
        self, node: RosNode, publishers: dict[str, RosPublisher], stop: threading.Event
    ) -> None:
        deadline = time.monotonic() + self.options.wait
        waiting = {p.fqn for p in publishers.values()}
        while waiting and time.monotonic() < deadline and not stop.is_set():
            for fqn in sorted(waiting):
                pattern = subscription_pattern(node.graph, fqn)
                if any(reply.ok is not None for reply in node.session.liveliness().get(pattern, timeout=1.0)):
                    waiting.discard(fqn)
            if waiting:
                stop.wait(0.1)

    def run(self, stop: threading.Event) -> int:
        """Publish the bag's messages until its end or ``stop``; returns the exit code (0)."""
        opts, session = self.options, self.session
        if session is None:
            raise RuntimeError("the player needs an open session to run")
        reader = open_bag(self.path, ROS2_BAG)
        node = RosNode(session, opts.mode, opts.domain, opts.namespace, opts.node)
        try:
            connections = self._connections(reader)
            publishers = {
                c.id: node.publisher(placed(c.topic, opts.namespace), MessageType(c.msgtype), _qos(c.topic))
                for c in connections
            }
            if opts.wait > 0:
                self._wait_for_subscriptions(node, publishers, stop)
            skipped: list[Skipped] = []
            started, first = time.monotonic(), None
            for conn, timestamp, raw in _timed_records(reader, connections, skipped):
                first = timestamp if first is None else first
                if opts.rate is not None:
                    delay = started + (timestamp - first) / NS / opts.rate - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                if stop.is_set():
                    break
                publishers[conn.id].put_cdr(bytes(raw))
                self.published += 1
            for problem in skipped:
                print(f"posegrid ros2 play: note: {problem.reason}", file=sys.stderr)
        finally:
            node.close()
            reader.close()
        print(f"posegrid ros2 play: published {self.published} messages from {self.path}", flush=True)
        return 0


def _timed_records(reader, connections, skipped: list[Skipped]):
    """(connection, bag time ns, raw bytes) of the chosen connections' messages in bag order; a bag that breaks off
    ends the iteration with a note in ``skipped`` (slam.rosbag_reader.bag_records, which this reuses)."""
    for conn, (timestamp, raw) in bag_records(_Timed(reader), connections, skipped):
        yield conn, timestamp, raw


class _Timed:
    """A bag reader whose messages carry their bag time along with the raw bytes, for bag_records (which passes on only
    the connection and the raw bytes)."""

    def __init__(self, reader):
        self.reader = reader

    def messages(self, connections):
        for conn, timestamp, raw in self.reader.messages(connections=connections):
            yield conn, timestamp, (timestamp, raw)
