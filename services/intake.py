"""The bounded queue between a process's Zenoh callbacks and its one working thread (a mapper shard's fusion, a
SLAM node's filter): callbacks only check a publication's key and size and copy its payload in; the working
thread takes them out robot by robot in turn, each robot's in arrival order.

A publication is refused, counted by the process's :class:`services.process.RejectCounter` and never queued, when
its key is no robot stream the process reads (kind "key", under keys.INVALID_KEY:
:func:`services.state.checks.robot_stream`), when it is larger than any message the process takes (kind "size"),
or when the queue is full, by count or by bytes (kind "overflow", also counted in :attr:`Intake.overflow`), or
its robot is new when ``--max-robots`` robots have messages waiting (kind "robots").

**Fair to each robot** (:class:`services.fair_queue.FairQueue`, each robot an owner): the robots with messages
waiting take turns, one message each, so a peer that floods one robot's streams (scans at the limits cost about 1 s
of a core each) delays another robot's next message by one of its own, not by all it has queued; and when the queue
is full, a message of a robot holding a smaller share of it (of its count or its bytes) than another makes room by
evicting that other robot's newest messages (counted as its "overflow"): a flood fills the queue with its own
messages and then only displaces its own.

**In the order published**: a process reads its robots' streams through one subscriber on pg/<robot>/* (or pg/*/*,
:meth:`Intake.subscribe`), never one per stream. zenoh-python runs each subscriber's callbacks on a thread of its own,
so messages taken by several subscribers reach the queue out of the order they went out in (three subscribers, 50
bursts of 20 scans, 20 poses and a StreamEnd: the end comes before some of its burst in 28 of them); one subscriber's
callbacks run on one thread, in the order the messages came off the link. services.nodes.source.took_end relies on
it: a shard that has taken a run's end has taken the whole run.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING

from services import keys
from services.fair_queue import FairQueue
from services.process import RejectCounter
from services.state.checks import robot_stream
from services.state.limits import ShardLimits

if TYPE_CHECKING:
    import zenoh

#: publications that may wait in the queue
DEFAULT_CAPACITY = 4096
#: the limits of a process that sets none: a mapper's defaults (a SLAM node takes what a shard takes)
DEFAULT_LIMITS = ShardLimits()


class Intake:
    """The queue, with its checks. Thread-safe: Zenoh callbacks call :meth:`on_sample` (or :meth:`offer`) from their
    threads, the working thread :meth:`next`.

    streams: the key chunks the process reads (pg/<robot>/<stream>); robot: the one robot it reads, None for any;
    limits: ``message_bytes()`` bounds one payload, ``intake_bytes`` the payloads waiting (bytes); capacity: how many
    may wait."""

    def __init__(
        self,
        streams: Iterable[str],
        rejects: RejectCounter,
        limits: ShardLimits = DEFAULT_LIMITS,
        robot: str | None = None,
        capacity: int = DEFAULT_CAPACITY,
    ):
        self.streams = tuple(streams)
        self.rejects = rejects
        self.limits = limits
        self.robot = robot
        self.capacity = capacity
        self._queue: FairQueue[tuple[str, bytes]] = FairQueue(capacity, limits.intake_bytes, limits.max_robots)
        self.overflow = 0  # publications refused, or evicted, because the queue was full
        self._overflow_lock = threading.Lock()  # (callbacks of several Zenoh threads add to it)

    @property
    def bytes_waiting(self) -> int:
        """Bytes of the payloads waiting."""
        return self._queue.bytes

    def subscribe(self, session: zenoh.Session) -> zenoh.Subscriber:
        """Declare the one subscriber that feeds this queue (see the module): on pg/<robot>/*, every robot's when the
        intake takes any (pg/*/*)."""
        return session.declare_subscriber(keys.robot_key(self.robot or "*", "*"), self.on_sample)

    def on_sample(self, sample: zenoh.Sample) -> None:
        """A Zenoh subscriber's callback: :meth:`offer` the sample's key and payload, except a publication on a robot
        stream this process does not read (a robot's odometry at a shard, which the subscriber on pg/<robot>/* gets
        too): another process's, passed over without a count."""
        key = str(sample.key_expr)
        parsed = keys.parse_robot_key(key)
        if parsed is not None and parsed[1] not in self.streams:
            return
        self.offer(key, sample.payload)

    def offer(self, key: str, payload: zenoh.ZBytes | bytes) -> bool:
        """Queue a copy of ``payload``, received on ``key``, unless it is refused (counted, see the module);
        whether it was queued."""
        parsed = robot_stream(key, self.streams, self.rejects, self.robot)
        if parsed is None:
            return False
        limits = self.limits
        size = len(payload)
        if size > limits.message_bytes():
            self.rejects.count(
                key,
                "size",
                f"a message of {size} bytes, more than a scan of --max-beams "
                f"{limits.max_beams} beams may take ({limits.message_bytes()} bytes)",
            )
            return False
        offered = self._queue.offer(
            parsed[0], (key, payload if isinstance(payload, bytes) else payload.to_bytes()), size
        )
        if offered.owners_full:
            self.rejects.count(key, "robots", f"more than --max-robots {limits.max_robots} robots' messages waited")
            return False
        queued, evicted = offered.queued, offered.evicted
        with self._overflow_lock:
            self.overflow += len(evicted) + (not queued)
        full = f"the intake queue ({self.capacity} messages, {limits.intake_bytes} bytes) was full"
        for evicted_key, _ in evicted:
            self.rejects.count(evicted_key, "overflow", f"{full}: evicted for a robot holding a smaller share")
        if not queued:
            self.rejects.count(key, "overflow", full)
        return queued

    def next(self, timeout: float) -> tuple[str, bytes]:
        """The next waiting (key, payload): the oldest of the robot whose turn it is; raises queue.Empty after
        ``timeout`` s."""
        return self._queue.take(timeout)

    def empty(self) -> bool:
        """Whether nothing waits."""
        return self._queue.empty()
