"""Pairs each laser scan with its pose distribution by (robot, seq), whatever order they arrive in.

The buffer holds the halves still waiting for their partner, at most ``capacity`` of them; when it is full
the oldest waiting half is evicted and returned, so the caller counts it (overflow is never silent).
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
