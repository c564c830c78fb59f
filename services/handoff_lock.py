"""A lock that one working thread holds over long stretches and hands to the threads waiting for it at the points it
names: a mapper shard's main thread holds it over a batch of scans (up to 16 per fusion thread, about 0.25 s of
warehouse scans on two threads) and hands it, between two scans, to the tile queries that wait for it, so that a query
waits for one scan's fusion rather than the batch's.

A plain lock let go and taken again at once is no hand-off: the thread that lets it go runs on and takes it back
before a waiter wakes. So :meth:`HandoffLock.hand_off` lets it go only when a thread waits for it, and takes it back
once every thread that was waiting then has had it; threads that come later wait for the next hand-off (a stream of
queries cannot hold the working thread up)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

#: s between two looks, while the working thread waits for the waiters to take the lock, at whether they all did (a
#: waiter notifies as it takes it; this bounds the wait should a notification come before the wait begins)
WAIT_STEP = 0.05
#: s the working thread waits at most at one hand-off for the waiters to have had the lock: a waiter that has not taken
#: it by then takes it after (it waits for the lock as any thread does), and the working thread goes on meanwhile
HANDOFF_LIMIT = 1.0


class HandoffLock:
    """``with lock:`` (or :meth:`acquire`, :meth:`release`) as a plain lock, for the working thread and the waiters
    alike; :meth:`waiter` for a thread that should be let in at the next :meth:`hand_off` (a query's callback)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = threading.Condition(threading.Lock())  # (guards the two counts below)
        self._arrived = 0  # waiters that began to wait for the lock, ever
        self._entered = 0  # waiters that took it, ever
        self._holder: int | None = None  # threading.get_ident() of the thread that holds it (None: free)

    def acquire(self) -> bool:
        self._lock.acquire()
        self._holder = threading.get_ident()
        return True

    def release(self) -> None:
        self._holder = None
        self._lock.release()

    def locked(self) -> bool:
        return self._lock.locked()

    def __enter__(self) -> HandoffLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    @property
    def waiting(self) -> int:
        """Waiters that wait for the lock now (read without a lock: a hint, which :meth:`hand_off` checks again)."""
        return self._arrived - self._entered

    @contextlib.contextmanager
    def waiter(self) -> Iterator[None]:
        """Hold the lock as a waiter: taken as soon as it is free, or at the holder's next :meth:`hand_off`."""
        with self._counts:
            self._arrived += 1
        self.acquire()
        with self._counts:
            self._entered += 1
            self._counts.notify_all()
        try:
            yield
        finally:
            self.release()

    def hand_off(self) -> None:
        """Let the waiters waiting now take the lock, each in turn, and take it back after them, or after HANDOFF_LIMIT
        s (the holder's thread, holding it; RuntimeError from another thread: it would let go of a lock it does not
        hold); nothing when none waits."""
        if self._holder != threading.get_ident():
            raise RuntimeError("HandoffLock.hand_off from a thread that does not hold the lock")
        with self._counts:
            due = self._arrived
            if self._entered >= due:
                return
        self.release()
        try:
            deadline = time.monotonic() + HANDOFF_LIMIT
            with self._counts:
                while self._entered < due and time.monotonic() < deadline:
                    self._counts.wait(WAIT_STEP)
        finally:
            self.acquire()
