"""Commits a shard's changes to its store on a thread of its own (:class:`Persister`), so that fusion goes on while a
batch is compressed and written.

At most one batch is in flight: the next one is built only once the previous one has committed or failed, so the
store always holds a prefix of the run (a batch holds every tile changed since the last commit that succeeded).
A batch whose commit fails (disk full, I/O error, the store's size limit) goes back into the shard's journal, the
shard goes on serving from memory, reports ``persist: failing`` in its stats, and tries again ``every_s`` later.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

from services.state.store.db import Batch, ShardStore, StoredState, StoreWriteError
from services.state.store.journal import Journal

#: the default commit interval: a commit at least every this many scans fused or given up ...
DEFAULT_COMMIT_SCANS = 256
#: ... or once the oldest change not committed is this many s old (docs/persistence.md has the measurement)
DEFAULT_COMMIT_INTERVAL = 2.0


class Journaled(Protocol):
    """What the persister needs of a shard (services.state.shard.MapShard)."""

    journal: Journal | None

    def batch(self) -> Batch: ...


@dataclass(frozen=True)
class PersistReport:
    """What a shard's stats say of its store: state "off", "ok" or "failing"; scans fused or given up (by robot) as of
    the last commit; s since that commit (-1: none)."""

    state: str
    committed: dict[str, int]
    age: float


#: the report of a shard with no store
NO_STORE = PersistReport("off", {}, -1.0)


class Persister:
    """Commits a shard's journal (:class:`services.state.store.journal.Journal`) to ``store`` at least every
    ``every_scans`` scans or ``every_s`` s. :meth:`step` and :meth:`finish` are called by the thread that owns the
    shard, with the shard's lock held for :meth:`step`."""

    def __init__(
        self,
        store: ShardStore,
        every_scans: int,
        every_s: float,
        log: logging.Logger,
        clock: Callable[[], float] = time.monotonic,
    ):
        self.store = store
        self.every_scans = every_scans
        self.every_s = every_s
        self.log = log
        self._clock = clock
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="store")
        self._flight: tuple[Batch, Future[float]] | None = None
        self._retry_at = 0.0  # clock time before which no commit is tried after a failure, s
        self.failing: str | None = None  # why the last commit failed (None: it did not)
        self.committed: dict[str, int] = {}
        self.committed_at: float | None = None  # Unix time of the last commit, s

    def resumed(self, state: StoredState) -> None:
        """What the store held when the shard started on it: the last commit's scans and time."""
        self.committed = {r.robot: r.fused + r.discarded for r in state.robots.values()}
        self.committed_at = state.committed_at

    def report(self) -> PersistReport:
        age = -1.0 if self.committed_at is None else max(0.0, time.time() - self.committed_at)
        return PersistReport("failing" if self.failing else "ok", dict(self.committed), age)

    def step(self, shard: Journaled) -> None:
        """Collect the batch in flight if it is done; hand the next one to the writer thread if a commit is due."""
        journal = shard.journal
        assert journal is not None  # a persisted shard keeps a journal
        if self._flight is not None:
            if not self._flight[1].done():
                return
            self._collect(journal)
        now = self._clock()
        if now >= self._retry_at and journal.due(self.every_scans, self.every_s, now):
            batch = shard.batch()
            self._flight = (batch, self._pool.submit(self.store.commit, batch))

    def _collect(self, journal: Journal) -> bool:
        """Take the result of the batch in flight; whether it committed."""
        assert self._flight is not None
        batch, future = self._flight
        self._flight = None
        try:
            self.committed_at = future.result()
        except StoreWriteError as exc:
            journal.put_back(batch, self._clock())
            self._retry_at = self._clock() + self.every_s
            if self.failing is None:
                self.log.error(
                    "%s; the shard goes on serving from memory and tries again every %g s (persist: failing)",
                    exc,
                    self.every_s,
                )
            self.failing = str(exc)
            return False
        if self.failing is not None:
            self.log.info("commits to %s succeed again", self.store.path)
        self.failing = None
        self.committed = {r.robot: r.fused + r.discarded for r in batch.robots}
        return True

    def abandon(self) -> None:
        """Close the store keeping only what is committed (the batch in flight is let finish): what a crash leaves."""
        self._pool.shutdown(wait=True)
        self.store.close()

    def finish(self, shard: Journaled) -> bool:
        """Wait for the batch in flight, commit what is left, close the store; whether everything is committed.
        Called once, when the shard stops."""
        journal = shard.journal
        assert journal is not None
        try:
            if self._flight is not None:
                self._flight[1].exception()  # (waits)
                self._collect(journal)
            if journal.changes or journal.tiles:
                batch = shard.batch()
                self._flight = (batch, self._pool.submit(self.store.commit, batch))
                self._flight[1].exception()
                if not self._collect(journal):
                    return False
            self.log.info("stopped with %d scan(s) committed to %s", sum(self.committed.values()), self.store.path)
            return True
        finally:
            self._pool.shutdown(wait=True)
            self.store.close()
