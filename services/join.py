"""Pairs each laser scan with its pose distribution by (robot, seq), however the two streams interleave.

A robot's scans come from one publisher (the source) and its poses from one (the SLAM node, or the source for
a posed-scan file), each in seq order over a reliable channel (schemas.messages: scans are numbered 0, 1,
2, ...). So a seq that a stream skips never comes: the scan was lost in transit (a network gap, a shard stalled
past its Zenoh lease, a full intake queue), or the SLAM node gave up on the step. The buffer then gives up on the
seq's other half at once, and counts the scans that never arrived, instead of holding halves whose partner cannot
come (a source waiting for every scan to be accounted for would wait for ever). The end of the scan stream
(:meth:`JoinBuffer.end`) says how many scans there were, which shows a gap at its tail; the caller decides when
the stream is over (the end mark itself may overtake the last scans: services.shard waits for quiet).

The buffer holds the halves still waiting for their partner, at most ``capacity`` of them; when it is full
the oldest waiting half is evicted. Every half given up on is returned as :class:`GivenUp`, so the caller
counts it (nothing is dropped silently). :class:`SeqLedger` remembers which (robot, seq) pairs were already
fused, so that a re-sent pair is refused instead of fused twice.
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


#: why halves are given up on (:class:`GivenUp`)
OVERFLOW = "overflow"  # evicted from a full buffer
MISSING = "missing"  # scans that never came: their stream went past their seqs
ORPHANED = "orphaned"  # its partner never comes: the partner's stream went past its seq without it
LATE = "late"  # it came after its own stream had passed its seq (a re-sent message): refused
JUMP = "jump"  # its seq lies more than MAX_GAP past its stream's last: refused as implausible

#: what each reason means, for the logs
GIVEN_UP_BECAUSE = {
    OVERFLOW: "the join buffer was full; given up on without its partner",
    MISSING: "never reached this shard (lost in transit: a network gap, a shard stalled past its Zenoh lease or a "
             "full intake queue); the map lacks them",
    ORPHANED: "given up on: its partner never comes (the partner's stream went past its seq)",
    LATE: "came after its stream had gone past its seq (a re-sent message); refused",
    JUMP: "its seq jumps implausibly far past its stream's last; refused",
}

#: the largest gap in a stream taken as scans lost in transit (about 12 days of a 10 Hz laser); a larger jump
#: is refused (a stream cannot have lost that much), except on a stream's first message, where it starts there
MAX_GAP = 10 ** 7


@dataclass(frozen=True)
class GivenUp:
    """``count`` halves of ``robot`` with consecutive seqs from ``first``, scans (else poses), given up for
    ``reason`` (:data:`OVERFLOW`, :data:`MISSING`, :data:`ORPHANED`, :data:`LATE` or :data:`JUMP`)."""

    robot: str
    first: int
    count: int
    scans: bool
    reason: str

    def describe(self) -> str:
        """E.g. "scans 120-308 of robot 'r'"."""
        what = "scan" if self.scans else "pose"
        seqs = str(self.first) if self.count == 1 else f"{self.first}-{self.first + self.count - 1}"
        return f"{what}{'s' if self.count > 1 else ''} {seqs} of robot {self.robot!r}"


class JoinBuffer(Generic[ScanT, PoseT]):
    """A bounded scan/pose join; see the module docstring."""

    def __init__(self, capacity: int):
        if capacity < 1:
            raise ValueError(f"join buffer capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self._pending: OrderedDict[JoinKey, _Pending] = OrderedDict()
        self._last: dict[tuple[str, bool], int] = {}  # (robot, scans?) -> the last seq its stream has passed

    def __len__(self) -> int:
        return len(self._pending)

    def add_scan(self, key: JoinKey, scan: ScanT) -> tuple[tuple[ScanT, PoseT] | None, list[GivenUp]]:
        """Offer a scan; returns the completed (scan, pose) pair or None, and the halves given up on."""
        return self._add(key, scan, is_scan=True)

    def add_pose(self, key: JoinKey, pose: PoseT) -> tuple[tuple[ScanT, PoseT] | None, list[GivenUp]]:
        """Offer a pose; returns the completed (scan, pose) pair or None, and the halves given up on."""
        return self._add(key, pose, is_scan=False)

    def end(self, robot: str, scans: int) -> list[GivenUp]:
        """The robot's scan stream has ended after ``scans`` scans (seqs 0 .. scans-1): the scans after the last
        one seen never come. Returns the halves given up on."""
        last = self._last.get((robot, True), -1)
        if scans - last - 1 > MAX_GAP:  # implausible: the stream stays open (and the end unacknowledged)
            return []
        return self._pass(robot, True, last + 1, scans, max(last, scans - 1))

    def give_up(self, robot: str) -> list[GivenUp]:
        """Give up on every half of ``robot`` still waiting (its streams have gone quiet after their end)."""
        keys = [key for key in self._pending if key[0] == robot]
        gone = [GivenUp(robot, seq, 1, self._pending[(robot, seq)].scan is not None, ORPHANED) for _, seq in keys]
        for key in keys:
            del self._pending[key]
        return gone

    def _pass(self, robot: str, is_scan: bool, skipped_from: int, skipped_to: int, new_last: int) -> list[GivenUp]:
        """Move the robot's scan (or pose) stream on to ``new_last``; seqs skipped_from .. skipped_to-1 never
        came: counted when they are scans, and the partners waiting for them are given up."""
        self._last[(robot, is_scan)] = new_last
        if skipped_to <= skipped_from:
            return []
        gone = [GivenUp(robot, skipped_from, skipped_to - skipped_from, True, MISSING)] if is_scan else []
        for key in [k for k in self._pending if k[0] == robot and skipped_from <= k[1] < skipped_to]:
            gone.append(GivenUp(robot, key[1], 1, not is_scan, ORPHANED))
            del self._pending[key]
        return gone

    def _add(self, key: JoinKey, item, is_scan: bool):
        robot, seq = key
        last = self._last.get((robot, is_scan))
        if last is not None and seq <= last:
            return None, [GivenUp(robot, seq, 1, is_scan, LATE)]
        start = -1 if last is None else last
        if seq - start - 1 > MAX_GAP:
            if last is not None:
                return None, [GivenUp(robot, seq, 1, is_scan, JUMP)]
            start = seq - 1  # a stream first seen far in: it starts here
        gone = self._pass(robot, is_scan, start + 1, seq, seq)
        entry = self._pending.get(key)
        if entry is None:
            if seq <= self._last.get((robot, not is_scan), -1):  # the partner's stream passed it: never comes
                return None, gone + [GivenUp(robot, seq, 1, is_scan, ORPHANED)]
            while len(self._pending) >= self.capacity:
                (old_robot, old_seq), old = self._pending.popitem(last=False)
                gone.append(GivenUp(old_robot, old_seq, 1, old.scan is not None, OVERFLOW))
            entry = self._pending[key] = _Pending()
        if is_scan:
            entry.scan = item
        else:
            entry.pose = item
        if entry.scan is not None and entry.pose is not None:
            del self._pending[key]
            return (entry.scan, entry.pose), gone
        return None, gone


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
