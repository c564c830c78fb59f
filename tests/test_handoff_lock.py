"""The mapper's lock (services.handoff_lock.HandoffLock): a tile query that waits for it while the main thread fuses a
batch of scans is let in between two scans, and sees the map of the scans fused so far, whole."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from bench.scenarios import honest_posed_scans, office_run
from services.handoff_lock import HandoffLock
from services.state.shard import MapShard, whole_tile
from test_threads import _messages, _shard


@pytest.fixture(scope="module")
def particles():
    """Office scans under 30 particles."""
    return honest_posed_scans(office_run(steps=16), particles=30)


def _wait_until(condition, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"gave up waiting for {what}"
        time.sleep(0.001)


def _waiter(lock: HandoffLock, events: list[str], name: str) -> threading.Thread:
    """A thread that takes ``lock`` as a waiter and notes ``name`` in ``events`` while it holds it; started, and
    waiting once this returns."""

    def take() -> None:
        with lock.waiter():
            events.append(name)

    thread = threading.Thread(target=take, daemon=True)
    before = lock.waiting
    thread.start()
    _wait_until(lambda: lock.waiting > before, f"{name} to wait for the lock")
    return thread


def test_a_hand_off_lets_the_waiters_in_before_the_holder_goes_on():
    """The holder's hand-off returns only after each thread then waiting has held the lock, and holding it again. A
    lock let go and taken back at once let the holder in first (the waiter slept on)."""
    lock, events = HandoffLock(), []
    with lock:
        threads = [_waiter(lock, events, "first"), _waiter(lock, events, "second")]
        lock.hand_off()
        assert sorted(events) == ["first", "second"]  # (in the order the lock gave it them)
        events.append("holder")
        assert lock.locked() and lock.waiting == 0
    for thread in threads:
        thread.join(10)
    assert events[-1] == "holder"


def test_a_hand_off_with_no_waiter_keeps_the_lock_and_a_later_waiter_waits_for_the_next():
    lock, events = HandoffLock(), []
    with lock:
        lock.hand_off()  # (none waits: the lock is kept)
        assert lock.locked() and events == []
        thread = _waiter(lock, events, "late")
        events.append("holder")
    thread.join(10)
    assert events == ["holder", "late"]


def test_a_hand_off_waits_for_the_waiters_at_most_its_limit(monkeypatch):
    """A waiter counted that has not taken the lock by HANDOFF_LIMIT s (made here by counting one that never asks)
    holds the holder up no longer: the hand-off returns holding the lock."""
    from services import handoff_lock

    monkeypatch.setattr(handoff_lock, "HANDOFF_LIMIT", 0.2)
    lock = HandoffLock()
    with lock:
        lock._arrived += 1  # (a waiter that never takes the lock)
        lock.hand_off()
        assert lock.locked() and lock.waiting == 1


def test_only_the_holder_may_hand_off():
    lock = HandoffLock()
    with pytest.raises(RuntimeError, match="does not hold"):
        lock.hand_off()  # (free)
    with lock:
        errors = []

        def other() -> None:
            try:
                lock.hand_off()
            except RuntimeError as exc:
                errors.append(str(exc))

        thread = threading.Thread(target=other)
        thread.start()
        thread.join(10)
        assert errors and lock.locked()


def _tiles(shard: MapShard) -> dict:
    """Each tile's whole values as a tile query's reply gives them."""
    replies = {tile: whole_tile(shard.tile_snapshot(tile)) for tile in shard.tiles()}
    return {tile: message.whole_layers() for tile, message in replies.items()}


def _same(got: dict, expected: dict) -> bool:
    return got.keys() == expected.keys() and all(
        np.array_equal(a, b, equal_nan=True) for tile in got for a, b in zip(got[tile], expected[tile], strict=True)
    )


def test_a_tile_query_during_a_batch_is_answered_between_two_scans_with_the_map_so_far(particles):
    """A shard on two threads fuses 8 scans together (the mapper's batch, holding the lock) while a tile query waits
    for the lock: it is answered at the first hand-off, after the first scan, with exactly the map of that scan alone
    (its tiles, each cell's log-odds, variance and observed, bit for bit, as a one-thread shard fused with that scan
    only gives them); the shard's counts hold that scan then; the batch's map is that of the 8 scans one by one."""
    messages = _messages(particles)[:16]  # (8 scans, each followed by its pose)
    alone, whole = _shard(1), _shard(1)
    for key, payload in messages[:2]:
        alone.handle(key, payload)
    for key, payload in messages:
        whole.handle(key, payload)

    lock, shard, seen = HandoffLock(), _shard(2), {}
    shard.handoff = lock

    def query() -> None:
        with lock.waiter():
            seen.update(_tiles(shard))
            seen["fused"] = dict(shard.fused)

    with lock:
        for key, payload in messages:
            shard.handle(key, payload, defer=True)
        thread = threading.Thread(target=query, daemon=True)
        thread.start()
        _wait_until(lambda: lock.waiting == 1, "the query to wait for the lock")
        shard.fuse_ready()
    thread.join(10)
    assert seen.pop("fused", None) == {"r": 1}, "the query did not come in after the first scan"
    assert _same(seen, _tiles(alone)), "the query did not see the map of the first scan alone"
    assert not _same(seen, _tiles(whole))
    assert _same(_tiles(shard), _tiles(whole)) and shard.fused == whole.fused == {"r": 8}
