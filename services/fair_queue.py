"""A bounded queue shared fairly among its owners (a shard's robots; a ROS 2 bridge's two sides), between the
threads that offer items (Zenoh callbacks) and the one thread that takes them.

Each owner's items wait in arrival order, and the owners with items waiting take turns, one item each (round robin):
an owner that floods the queue delays another owner's next item by one of its own, not by all it has queued. The
queue holds at most ``capacity`` items and ``max_bytes`` bytes (each item's size as offered); when it is full, an
item of an owner holding a smaller share of it than another (of its count or its bytes, whichever is larger) makes
room by evicting that other owner's newest items, so a flood that fills the queue then displaces only its own. The
caller counts what is refused and what is evicted.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Offered(Generic[T]):
    """What :meth:`FairQueue.offer` did: whether the item was queued, the items evicted for it (newest first), and
    whether it was refused because ``max_owners`` owners have items waiting already."""

    queued: bool
    evicted: list[T]
    owners_full: bool = False


class FairQueue(Generic[T]):
    """The queue (module docstring). Thread-safe: any thread may :meth:`offer`, one thread :meth:`take`.
    ``max_owners``: how many owners may have items waiting at once (None: any); it bounds the work of making room,
    which weighs every owner's share (a flood of 4 096 made-up robot names took 0.9 ms an offer)."""

    def __init__(self, capacity: int, max_bytes: int, max_owners: int | None = None):
        self.capacity = capacity
        self.max_bytes = max_bytes
        self.max_owners = max_owners
        self._waiting: dict[str, _Owned[T]] = {}  # owner -> its items waiting, oldest first
        self._turns: deque[str] = deque()  # the owners with items waiting, the next to take one first
        self._count = 0  # items waiting
        self._bytes = 0  # their bytes
        self._changed = threading.Condition()  # guards all the above; notified when an item comes

    @property
    def bytes(self) -> int:
        """Bytes of the items waiting."""
        return self._bytes

    def offer(self, owner: str, item: T, size: int) -> Offered[T]:
        """Queue ``item`` (``size`` bytes) of ``owner`` unless the queue is full after making what room it may
        (module docstring), or ``owner`` is new and ``max_owners`` owners have items waiting."""
        with self._changed:
            if owner not in self._waiting and self.max_owners is not None and len(self._waiting) >= self.max_owners:
                return Offered(False, [], owners_full=True)
            evicted = self._make_room(owner, size)
            queued = self._count < self.capacity and self._bytes + size <= self.max_bytes
            if queued:
                owned = self._waiting.get(owner)
                if owned is None:
                    owned = self._waiting[owner] = _Owned()
                    self._turns.append(owner)
                owned.items.append((item, size))
                owned.bytes += size
                self._count += 1
                self._bytes += size
                self._changed.notify()
        return Offered(queued, evicted)

    def _share(self, items: int, size: int) -> float:
        """The part of the queue ``items`` items of ``size`` bytes in all take: of its count or of its bytes,
        whichever is larger (a flood of small items fills the count, one of large ones the bytes)."""
        return max(items / self.capacity, size / self.max_bytes)

    def _make_room(self, owner: str, size: int) -> list[T]:
        """While there is no room for an item of ``size`` bytes, evict the newest item of the owner holding the
        largest share (:meth:`_share`), when that is another owner holding a larger share than ``owner`` would with
        this item (called holding the lock)."""
        evicted: list[T] = []
        while self._count >= self.capacity or self._bytes + size > self.max_bytes:
            mine = self._waiting.get(owner)
            held = self._share(1, size) if mine is None else self._share(len(mine.items) + 1, mine.bytes + size)
            shares = {other: self._share(len(o.items), o.bytes) for other, o in self._waiting.items()}
            largest = max(shares, key=shares.__getitem__, default=None)
            if largest is None or largest == owner or shares[largest] <= held:
                break
            evicted.append(self._remove(largest, newest=True))
        return evicted

    def _remove(self, owner: str, newest: bool = False) -> T:
        """Remove ``owner``'s oldest (or newest) item and return it (called holding the lock)."""
        owned = self._waiting[owner]
        item, size = owned.items.pop() if newest else owned.items.popleft()
        owned.bytes -= size
        self._count -= 1
        self._bytes -= size
        if not owned.items:
            del self._waiting[owner]
            self._turns.remove(owner)
        return item

    def take(self, timeout: float) -> T:
        """The next item: the oldest of the owner whose turn it is; raises queue.Empty after ``timeout`` s (0: at
        once)."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._count > 0, timeout):
                raise queue.Empty
            owner = self._turns[0]
            self._turns.rotate(-1)  # (the owner's next item after every other owner's)
            return self._remove(owner)

    def empty(self) -> bool:
        """Whether nothing waits."""
        with self._changed:
            return self._count == 0


class _Owned(Generic[T]):
    """One owner's items waiting ((item, size), oldest first) and their bytes."""

    def __init__(self) -> None:
        self.items: deque[tuple[T, int]] = deque()
        self.bytes = 0
