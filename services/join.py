"""Pairs each laser scan with its pose distribution by (robot, seq), whatever order they arrive in.

The buffer holds the halves still waiting for their partner, at most ``capacity`` of them; when it is full
the oldest waiting half is evicted and returned, so the caller counts it (overflow is never silent).
:class:`SeqLedger` remembers which (robot, seq) pairs were already fused, so that a re-sent pair is refused
instead of fused twice.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Generic, TypeVar

ScanT = TypeVar("ScanT")
PoseT = TypeVar("PoseT")
JoinKey = tuple[str, int]  # (robot, seq)


@dataclass
class _Pending(Generic[ScanT, PoseT]):
    scan: ScanT | None = None
    pose: PoseT | None = None


@dataclass(frozen=True)
class Evicted:
    """A half given up on: its key and whether it was the scan (else the pose)."""

    key: JoinKey
    was_scan: bool


class JoinBuffer(Generic[ScanT, PoseT]):
    """A bounded scan/pose join; see the module docstring."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f"join buffer capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._pending: OrderedDict[JoinKey, _Pending] = OrderedDict()

    def __len__(self) -> int:
        return len(self._pending)

    def add_scan(self, key: JoinKey, scan: ScanT) -> tuple[tuple[ScanT, PoseT] | None, list[Evicted]]:
        """Offer a scan; returns the completed (scan, pose) pair or None, and what had to be evicted."""
        return self._add(key, scan, is_scan=True)

    def add_pose(self, key: JoinKey, pose: PoseT) -> tuple[tuple[ScanT, PoseT] | None, list[Evicted]]:
        """Offer a pose; returns the completed (scan, pose) pair or None, and what had to be evicted."""
        return self._add(key, pose, is_scan=False)

    def _add(self, key: JoinKey, item, is_scan: bool):
        entry = self._pending.get(key)
        if entry is None:
            evicted = []
            while len(self._pending) >= self.capacity:
                old_key, old = self._pending.popitem(last=False)
                evicted.append(Evicted(old_key, old.scan is not None))
            entry = self._pending[key] = _Pending()
        else:
            evicted = []
        if is_scan:
            entry.scan = item
        else:
            entry.pose = item
        if entry.scan is not None and entry.pose is not None:
            del self._pending[key]
            return (entry.scan, entry.pose), evicted
        return None, evicted


class SeqLedger:
    """The seqs of each robot already fused (or given up on at fusion).

    Only the seqs within ``horizon`` of a robot's highest are kept; an older seq counts as done, so the memory
    stays bounded on runs of any length. A robot that starts again from seq 0 under the same name therefore
    finds its seqs done: streams are numbered once per robot name (schemas.messages).
    """

    def __init__(self, horizon: int):
        if horizon < 1:
            raise ValueError(f"seq ledger horizon must be >= 1, got {horizon}")
        self.horizon = horizon
        self._seqs: dict[str, set[int]] = {}
        self._highest: dict[str, int] = {}

    def done(self, robot: str, seq: int) -> bool:
        """Whether ``robot``'s ``seq`` was fused already (or lies more than ``horizon`` below its highest)."""
        highest = self._highest.get(robot)
        return highest is not None and (seq <= highest - self.horizon or seq in self._seqs[robot])

    def mark(self, robot: str, seq: int) -> None:
        """Record ``robot``'s ``seq`` as done."""
        seqs = self._seqs.setdefault(robot, set())
        seqs.add(seq)
        highest = self._highest[robot] = max(self._highest.get(robot, seq), seq)
        if len(seqs) > 2 * self.horizon:  # drop the seqs that ``done`` no longer reads (amortised)
            self._seqs[robot] = {s for s in seqs if s > highest - self.horizon}
