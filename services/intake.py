"""The bounded queue between a process's Zenoh callbacks and its one working thread (a mapper shard's fusion, a
SLAM node's filter): callbacks only check a publication's key and size and copy its payload in; the working
thread takes them out robot by robot in turn, each robot's in arrival order.

A publication is refused, counted by the process's :class:`services.process.RejectCounter` and never queued, when
its key is no robot stream the process reads (kind "key", under keys.INVALID_KEY:
:func:`services.state.checks.robot_stream`), when it is larger than any message the process takes (kind "size"),
or when the queue is full, by count or by bytes (kind "overflow", also counted in :attr:`Intake.overflow`).

**Fair to each robot.** The robots with messages waiting take turns, one message each (round robin), so a peer that
floods one robot's streams (scans at the limits cost about 1 s of a core each) delays another robot's next message
by one of its own, not by all it has queued; and when the queue is full, a message of a robot holding fewer bytes
than another makes room by evicting that other robot's newest messages (counted as its "overflow"): a flood fills
the queue with its own messages and then only displaces its own.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
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
        self.capacity = capacity
        self._waiting: dict[str, _Waiting] = {}  # robot -> its messages waiting, oldest first
        self._turns: deque[str] = deque()  # the robots with messages waiting, the next to take one first
        self._count = 0  # messages waiting
        self._changed = threading.Condition()  # guards all the above, bytes and overflow; notified on a message
        self.bytes = 0  # bytes of the payloads waiting
        self.overflow = 0  # publications refused, or evicted, because the queue was full

    def on_sample(self, sample: zenoh.Sample) -> None:
        """A Zenoh subscriber's callback: :meth:`offer` the sample's key and payload."""
        self.offer(str(sample.key_expr), sample.payload)

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
        robot = parsed[0]
        data = payload if isinstance(payload, bytes) else payload.to_bytes()
        with self._changed:
            evicted = self._make_room(robot, size)
            queued = self._count < self.capacity and self.bytes + size <= limits.intake_bytes
            if queued:
                waiting = self._waiting.get(robot)
                if waiting is None:
                    waiting = self._waiting[robot] = _Waiting()
                    self._turns.append(robot)
                waiting.messages.append((key, data))
                waiting.bytes += size
                self._count += 1
                self.bytes += size
                self._changed.notify()
            self.overflow += len(evicted) + (not queued)
        full = f"the intake queue ({self.capacity} messages, {limits.intake_bytes} bytes) was full"
        for evicted_key in evicted:
            self.rejects.count(evicted_key, "overflow", f"{full}: evicted for a robot holding fewer bytes")
        if not queued:
            self.rejects.count(key, "overflow", full)
        return queued

    def _make_room(self, robot: str, size: int) -> list[str]:
        """While the queue has no room for ``size`` more bytes of ``robot``'s, evict the newest message of the robot
        holding the most bytes, when that is another robot holding more than ``robot`` would with this message;
        the keys of those evicted (called holding the lock)."""
        evicted: list[str] = []
        while self._count >= self.capacity or self.bytes + size > self.limits.intake_bytes:
            mine = self._waiting.get(robot)
            held = (0 if mine is None else mine.bytes) + size
            largest = max(self._waiting, key=lambda other: self._waiting[other].bytes, default=None)
            if largest is None or largest == robot or self._waiting[largest].bytes <= held:
                break
            evicted.append(self._take(largest, newest=True)[0])
        return evicted

    def _take(self, robot: str, newest: bool = False) -> tuple[str, bytes]:
        """Remove ``robot``'s oldest (or newest) waiting message and return it (called holding the lock)."""
        waiting = self._waiting[robot]
        key, payload = waiting.messages.pop() if newest else waiting.messages.popleft()
        waiting.bytes -= len(payload)
        self._count -= 1
        self.bytes -= len(payload)
        if not waiting.messages:
            del self._waiting[robot]
            self._turns.remove(robot)
        return key, payload

    def next(self, timeout: float) -> tuple[str, bytes]:
        """The next waiting (key, payload): the oldest of the robot whose turn it is, its bytes released; raises
        queue.Empty after ``timeout`` s."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._count > 0, timeout):
                raise queue.Empty
            robot = self._turns[0]
            self._turns.rotate(-1)  # (the robot's next message after every other robot's)
            return self._take(robot)

    def empty(self) -> bool:
        """Whether nothing waits."""
        with self._changed:
            return self._count == 0


class _Waiting:
    """One robot's messages waiting in an :class:`Intake` ((key, payload), oldest first) and their bytes."""

    def __init__(self) -> None:
        self.messages: deque[tuple[str, bytes]] = deque()
        self.bytes = 0
