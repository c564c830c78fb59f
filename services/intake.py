"""The bounded queue between a process's Zenoh callbacks and its one working thread (a mapper shard's fusion, a
SLAM node's filter): callbacks only check a publication's key and size and copy its payload in; the working
thread takes them out in arrival order.

A publication is refused, counted by the process's :class:`services.process.RejectCounter` and never queued, when
its key is no robot stream the process reads (kind "key", under keys.INVALID_KEY:
:func:`services.state.checks.robot_stream`), when it is larger than any message the process takes (kind "size"),
or when the queue is full, by count or by bytes (kind "overflow", also counted in :attr:`Intake.overflow`).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING

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
        self._queue: queue.Queue[tuple[str, bytes]] = queue.Queue(capacity)
        self._lock = threading.Lock()  # guards bytes and overflow
        self.bytes = 0  # bytes of the payloads waiting
        self.overflow = 0  # publications refused because the queue was full

    def on_sample(self, sample: zenoh.Sample) -> None:
        """A Zenoh subscriber's callback: :meth:`offer` the sample's key and payload."""
        self.offer(str(sample.key_expr), sample.payload)

    def offer(self, key: str, payload: zenoh.ZBytes | bytes) -> bool:
        """Queue a copy of ``payload``, received on ``key``, unless it is refused (counted, see the module);
        whether it was queued."""
        if robot_stream(key, self.streams, self.rejects, self.robot) is None:
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
        with self._lock:
            room = self.bytes + size <= limits.intake_bytes
            if room:
                self.bytes += size
        if room:
            try:
                self._queue.put_nowait((key, payload if isinstance(payload, bytes) else payload.to_bytes()))
                return True
            except queue.Full:
                with self._lock:
                    self.bytes -= size
        with self._lock:
            self.overflow += 1
        self.rejects.count(
            key, "overflow", f"the intake queue ({self._queue.maxsize} messages, {limits.intake_bytes} bytes) was full"
        )
        return False

    def next(self, timeout: float) -> tuple[str, bytes]:
        """The oldest waiting (key, payload), its bytes released; raises queue.Empty after ``timeout`` s."""
        key, payload = self._queue.get(timeout=timeout)
        with self._lock:
            self.bytes -= len(payload)
        return key, payload

    def empty(self) -> bool:
        """Whether nothing waits."""
        return self._queue.empty()
