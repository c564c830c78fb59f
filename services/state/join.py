"""Pairs each laser scan with its pose distribution by (robot, seq), however the two streams interleave.

A robot's scans come from one publisher (the source) and its poses from one (the SLAM node, or the source for
a posed-scan file), each in seq order over a reliable channel (schemas.messages: scans are numbered 0, 1,
2, ...). So a seq that a stream skips never comes: the scan was lost in transit (a network gap, a shard stalled
past its Zenoh lease, a full intake queue), or the SLAM node gave up on the step. Such a gap is believed once
a later message of the stream lies beyond it; until then the message past the gap is held, and if the stream
goes on below it instead, the held one was a stray (another process on the robot's keys) and is refused as a
jump. Once a gap is believed, the buffer's ``recover`` (if given) is asked for the messages the gap skipped
(services.state.shard asks the source's and the SLAM node's histories); what it returns is taken as if it had come,
and so are the partners ``recover`` finds for it where their own stream has not got there yet (a gap larger
than the buffer is then paired at once, not evicted; the partner's stream later passes them as taken).
The scans that still never came are counted as given up and so are the halves waiting for a partner the gap
skipped, at once, instead of holding halves whose partner cannot come (a source waiting for every scan to be
accounted for would wait for ever). :meth:`JoinBuffer.settle` ends a
robot's streams after the source's count of scans; the caller decides when (the end mark itself can overtake
the last scans: services.state.shard waits for quiet).

The buffer holds the halves still waiting for their partner, at most ``capacity`` of them; when it is full
the oldest waiting half is evicted. With ``recover``, an evicted half is only remembered by its seq and digest (at
most :data:`EVICTED_LIMIT` of them) and asked for again when its partner comes: a SLAM node down for
longer than the buffer lasts then costs no scan, as the source's history still holds them. Without
``recover``, or when the history no longer holds it, it is given up. Every half given up on is returned as
:class:`GivenUp`, so the caller counts it (nothing is dropped silently). :class:`SeqLedger` remembers which
(robot, seq) pairs were already fused, so that a re-sent pair is refused instead of fused twice.
"""

from __future__ import annotations

from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Generic, TypeVar

ScanT = TypeVar("ScanT")
PoseT = TypeVar("PoseT")
NoteT = TypeVar("NoteT")
JoinKey = tuple[str, int]  # (robot, seq)


@dataclass
class _Pending(Generic[ScanT, PoseT]):
    scan: ScanT | None = None
    pose: PoseT | None = None

    def half(self) -> ScanT | PoseT:
        """The one half an entry waits with (:meth:`JoinBuffer._place` files it with the other)."""
        half = self.scan if self.scan is not None else self.pose
        assert half is not None
        return half


#: why halves are given up on (:class:`GivenUp`)
OVERFLOW = "overflow"  # evicted from a full buffer
MISSING = "missing"  # scans that never came: their stream went past their seqs
ORPHANED = "orphaned"  # its partner never comes: the partner's stream went past its seq without it
LATE = "late"  # it came after its own stream had passed its seq (a re-sent message not fused yet): refused
JUMP = "jump"  # it jumped past a gap that its stream's next message did not confirm (a stray): refused
AHEAD = "ahead"  # it lies more than the window beyond what its stream has shown: held until the stream gets near
STRAY = "stray"  # a scan refused as a jump whose seq its stream then passed: the map lacks it (counted as refused)

#: evicted halves remembered, to be asked for again when their partner comes (only their seqs and 16-byte digests:
#: about 250 bytes each); 13.6 min of a 10 Hz robot's scans
EVICTED_LIMIT = 8192
#: evicted halves of one stream asked for at once: the partners of the ones after the first come next
REFETCH_BATCH = 32
#: seqs beyond the last one its stream has passed that a live message may lie and still be taken (a gap larger
#: than this is believed only as below): 25 s of a 40 Hz laser. A peer that forges a scan and a pose far ahead
#: would otherwise make the stream pass every real seq up to them, given up as missing and then refused as late
DEFAULT_SEQ_WINDOW = 1024
#: messages beyond the window held per stream, lowest seqs kept: taken once the stream gets within the window
FAR_KEPT = 64
#: consecutive seqs beyond the window after which a jump is checked: believed when ``recover`` (the histories)
#: holds the first of them, the same as the one held (a stream that really skipped more than the window, e.g. a
#: shard cut off for minutes, goes on from the far side, and its publisher's history has it); without ``recover``,
#: believed on the run alone. A peer forging a run of seqs is never in the real publisher's history, and a peer
#: answering as a history of its own is caught with it (:meth:`JoinBuffer._vouched`)
CONFIRM_RUN = 16

#: seqs of scans refused as a jump remembered per stream, the newest kept, so that when the stream passes them they
#: are told apart from scans that never came (:data:`STRAY`, not :data:`MISSING`); beyond it, older ones are counted
#: as missing too
STRAYS_KEPT = 1024

#: the share of ``max_bytes`` the join evicts down to once its halves pass it
BYTES_AFTER_EVICTION = 0.9

#: what each reason means, for the logs
GIVEN_UP_BECAUSE = {
    OVERFLOW: "the join buffer was full, and it was past what the buffer remembers to ask the histories for again "
    "or they no longer hold it; given up on without its partner",
    MISSING: "never reached this shard (lost in transit: a network gap, a shard stalled past its Zenoh lease or a "
    "full intake queue) and no history holds them; the map lacks them",
    ORPHANED: "given up on: its partner never comes (the partner's stream went past its seq)",
    LATE: "came after its stream had gone past its seq (a re-sent message); refused",
    JUMP: "jumped past a gap that the next message of its stream did not confirm (a stray message); refused",
    AHEAD: "lies beyond the seq window of what its stream has shown (a forged or stray seq?); held, and taken only "
    "if the stream gets within the window of it or goes on in order from it",
    STRAY: "refused as a jump (counted there), and its stream has now passed its seq: the map lacks it",
}


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

    def __init__(
        self,
        capacity: int,
        recover: Callable[..., Mapping[int, ScanT | PoseT]] | None = None,
        window: int = DEFAULT_SEQ_WINDOW,
        max_bytes: int | None = None,
        size: Callable[[ScanT | PoseT], int] = lambda item: 0,
        digest: Callable[[ScanT | PoseT], bytes] | None = None,
    ):
        """``recover(robot, scans, first, last)``: what it can find of the robot's scans (else poses) with seqs
        first..last (inclusive), which its stream skipped, as {seq: scan or pose}. ``window``: seqs beyond its stream's
        last one that a live message may lie (:data:`DEFAULT_SEQ_WINDOW`). ``max_bytes``: bytes (as ``size`` measures a
        half) the waiting halves of every robot together may hold; beyond, the oldest of the robot holding the most are
        evicted as when the buffer is full (None: no bound). ``digest(half)``: a few bytes that stand for a half: two
        halves with the same digest are the same message (a far run is believed when ``recover`` gives its first
        message, the same as the one held), and an evicted half's digest is kept with its seq (:meth:`evicted_digest`)
        so that a copy of it sent again can be told from another message of that seq (None: halves compared with ==, and
        no digest kept)."""
        self.capacity = _at_least_one(capacity, "join buffer capacity")
        self.recover = recover
        self.window = _at_least_one(window, "seq window")
        self.max_bytes = max_bytes
        self._size = size
        # at least the bytes of the halves waiting here: their count when last counted, and every half offered since
        self._bound = 0
        self._digest = digest
        # (robot, scans?) -> {seq: item} beyond the window
        self._far: dict[tuple[str, bool], dict[int, ScanT | PoseT]] = {}
        self._pending: OrderedDict[JoinKey, _Pending[ScanT, PoseT]] = OrderedDict()
        self._last: dict[tuple[str, bool], int] = {}  # (robot, scans?) -> the last seq its stream has passed
        # (robot, scans?) -> (seq, item) past a gap
        self._held: dict[tuple[str, bool], tuple[int, ScanT | PoseT]] = {}
        self._ahead: dict[tuple[str, bool], set[int]] = {}  # (robot, scans?) -> seqs recovered before it got there
        # (robot, seq, scan?) -> the half's digest (None without ``digest``), oldest first
        self._evicted: OrderedDict[tuple[str, int, bool], bytes | None] = OrderedDict()
        # (robot, scans?) -> evicted halves asked for again ahead of need, by seq (the last batch of that stream)
        self._fetched: dict[tuple[str, bool], dict[int, ScanT | PoseT]] = {}
        # robot -> seqs of its scans refused as a jump and not yet passed, in the order refused (STRAYS_KEPT at most)
        self._strays: dict[str, OrderedDict[int, None]] = {}

    def __len__(self) -> int:
        return len(self._pending) + len(self._held)

    def held_bytes(self, robot: str | None = None) -> int:
        """Bytes (as ``size`` measures them) of ``robot``'s halves waiting here (for a partner, past a gap, or
        beyond the window); of every robot's with None."""
        held = self._bytes_by_robot()
        return held[robot] if robot is not None else sum(held.values())

    def _bytes_by_robot(self) -> Counter[str]:
        """Bytes of the halves waiting here, by robot."""
        held: Counter[str] = Counter()
        for (robot, _), entry in self._pending.items():
            for half in (entry.scan, entry.pose):
                if half is not None:
                    held[robot] += self._size(half)
        for (robot, _), (_, item) in self._held.items():
            held[robot] += self._size(item)
        for (robot, _), far in self._far.items():
            held[robot] += sum(self._size(item) for item in far.values())
        return held

    def waiting(self, key: JoinKey, is_scan: bool) -> ScanT | PoseT | None:
        """The scan (else pose) of ``key`` that waits here: for its partner, or held past a gap in its stream until
        the stream's next message confirms the gap; None when none does."""
        entry = self._pending.get(key)
        if entry is not None:
            return entry.scan if is_scan else entry.pose
        held = self._held.get((key[0], is_scan))
        return held[1] if held is not None and held[0] == key[1] else None

    def evicted_digest(self, key: JoinKey, is_scan: bool) -> bytes | None:
        """The digest of the scan (else pose) of ``key`` when it was evicted for room and is remembered, to be asked
        for again when its partner comes; None otherwise (or without ``digest``)."""
        return self._evicted.get((key[0], key[1], is_scan))

    def add_scan(
        self, key: JoinKey, scan: ScanT, trusted: bool = False
    ) -> tuple[list[tuple[ScanT, PoseT]], list[GivenUp]]:
        """Offer a scan; returns the completed (scan, pose) pairs (none, one, or two when it confirms a gap) and
        the halves given up on. ``trusted``: it came from a history, so the seq window does not apply."""
        return self._offer(key, scan, True, trusted)

    def add_pose(
        self, key: JoinKey, pose: PoseT, trusted: bool = False
    ) -> tuple[list[tuple[ScanT, PoseT]], list[GivenUp]]:
        """Offer a pose; returns what :meth:`add_scan` returns."""
        return self._offer(key, pose, False, trusted)

    def start_after(self, robot: str, seq: int) -> None:
        """Both of the robot's streams have passed ``seq`` already (a shard resuming from its store has fused or
        given up on every seq up to it): the next message of each is ``seq`` + 1, and what lies below is late."""
        for is_scan in (True, False):
            self._last[(robot, is_scan)] = max(self._last.get((robot, is_scan), -1), seq)

    def passed(self, robot: str, is_scan: bool) -> int:
        """The last seq the robot's scan (else pose) stream has passed (-1: none)."""
        return self._last.get((robot, is_scan), -1)

    def beyond_window(self, robot: str, is_scan: bool, seq: int) -> bool:
        """Whether ``seq`` lies more than the window beyond the last seq the robot's scan (else pose) stream has
        passed."""
        return seq > self.passed(robot, is_scan) + self.window

    def _offer(self, key: JoinKey, item, is_scan: bool, trusted: bool):
        """:meth:`_add`, unless a live ``item`` lies beyond the seq window: then it is held with the stream's other
        far messages (the lowest FAR_KEPT), and taken once the stream gets within the window of it, or once
        CONFIRM_RUN consecutive seqs are held (the stream really jumped)."""
        robot, seq = key
        stream = (robot, is_scan)
        if self.max_bytes is not None:
            self._bound += self._size(item)
        if trusted or not self.beyond_window(robot, is_scan, seq):
            pairs, gone = self._add(key, item, is_scan)
        else:
            far = self._far.setdefault(stream, {})
            far[seq] = item
            while len(far) > FAR_KEPT:
                del far[max(far)]
            pairs, gone = [], [GivenUp(robot, seq, 1, is_scan, AHEAD)]
            run = _run_through(far, seq) if seq in far else []
            if len(run) < CONFIRM_RUN or len(run) % CONFIRM_RUN or not self._vouched(robot, is_scan, run[0], far):
                return pairs, gone + self._within_bytes()  # (held far messages count in the bound too)
            for other in run:  # the stream goes on in order from the far side: its jump is real
                more_pairs, more = self._add((robot, other), far.pop(other), is_scan, confirmed=True)
                pairs, gone = pairs + more_pairs, gone + more
        more_pairs, more = self._reoffer(robot, is_scan)
        return pairs + more_pairs, gone + more + self._within_bytes()

    def _vouched(self, robot: str, is_scan: bool, seq: int, far: dict[int, ScanT | PoseT]) -> bool:
        """Whether the far message ``seq`` is vouched for: ``recover`` gives the same message for it (or there is no
        ``recover`` to ask), asked in one question with the last seq the stream has passed. So the real history,
        which holds that one, answers the question too: where a peer answers the far seq as a history of its own,
        two answer for the stream and neither is taken (services.history.ask), and the jump is not believed (a
        hostile-peer probe: a forged run at seq 100 000 vouched for by a peer's queryable made a shard give up 99 832
        real scans). A real publisher whose history no longer holds the passed seq answers the far one alone."""
        if self.recover is None:
            return True
        passed = max(self.passed(robot, is_scan), 0)
        found = self.recover(robot, is_scan, passed, seq, (passed, seq)).get(seq)
        return found is not None and self._same(found, far[seq])

    def _same(self, a: ScanT | PoseT, b: ScanT | PoseT) -> bool:
        """Whether two halves are the same message (by ``digest``, else ==)."""
        return a == b if self._digest is None else self._digest(a) == self._digest(b)

    def _reoffer(self, robot: str, is_scan: bool) -> tuple[list[tuple[ScanT, PoseT]], list[GivenUp]]:
        """Take the far messages of the stream that now lie within the window, in seq order."""
        far = self._far.get((robot, is_scan))
        pairs: list[tuple[ScanT, PoseT]] = []
        gone: list[GivenUp] = []
        while far:
            seq = min(far)
            if self.beyond_window(robot, is_scan, seq):
                break
            more_pairs, more = self._add((robot, seq), far.pop(seq), is_scan)
            pairs, gone = pairs + more_pairs, gone + more
        return pairs, gone

    def _within_bytes(self) -> list[GivenUp]:
        """Evict waiting halves while every robot's together hold more than ``max_bytes``: one at a time from the
        robot that holds the most (so that a robot flooding the buffer loses its own halves, not another's), down to
        :data:`BYTES_AFTER_EVICTION` of the bound, so that the halves are counted again only after that much more
        has come (a count walks every half waiting: 7.8 ms with 9 216 of them)."""
        gone: list[GivenUp] = []
        if self.max_bytes is None or self._bound <= self.max_bytes:
            return gone
        held = self._bytes_by_robot()
        if sum(held.values()) > self.max_bytes:
            target = int(self.max_bytes * BYTES_AFTER_EVICTION)
            while sum(held.values()) > target:
                for robot, _ in held.most_common():
                    evicted = self._evict_one(robot)
                    if evicted is not None:
                        break
                else:
                    break  # (only halves held past a gap are left: each stream holds one at most)
                held[robot] -= evicted[0]
                gone += evicted[1]
        self._bound = sum(held.values())
        return gone

    def _evict_one(self, robot: str) -> tuple[int, list[GivenUp]] | None:
        """Evict one of ``robot``'s waiting halves for room: its furthest message beyond the window (the least likely
        to be needed; counted as ahead when it came), else its oldest half waiting for a partner (:meth:`_evict`).
        Returns the bytes freed and the halves given up; None when it holds neither."""
        for stream in ((robot, True), (robot, False)):
            far = self._far.get(stream)
            if far:
                return self._size(far.pop(max(far))), []
        oldest = next((key for key in self._pending if key[0] == robot), None)
        if oldest is None:
            return None
        entry = self._pending.pop(oldest)
        half = entry.half()
        return self._size(half), self._evict(robot, oldest[1], entry.scan is not None, half)

    def settle(self, robot: str, scans: int) -> tuple[list[tuple[ScanT, PoseT]], list[GivenUp]]:
        """End the robot's streams after ``scans`` scans (seqs 0 .. scans-1): a held message within them is taken
        (nothing more will confirm its gap), one beyond them refused; the scans after the last one seen never
        come; every half still waiting is given up. Returns the pairs completed and the halves given up on."""
        pairs, gone = [], []
        for is_scan in (True, False):
            held = self._held.pop((robot, is_scan), None)
            if held is None:
                continue
            if held[0] < scans:
                pair, more = self._take(robot, held[0], held[1], is_scan)
                pairs += pair
                gone += more
            else:
                gone.append(GivenUp(robot, held[0], 1, is_scan, JUMP))
        for is_scan in (True, False):  # the tails after the last message seen: what the histories still hold
            more_pairs, more = self._pass(robot, is_scan, self._last.get((robot, is_scan), -1) + 1, scans)
            pairs += more_pairs
            gone += more
        for is_scan in (True, False):  # held beyond the window and never reached: counted as ahead already
            self._far.pop((robot, is_scan), None)
        waiting = [key for key in self._pending if key[0] == robot]
        gone += [
            GivenUp(robot, seq, 1, self._pending.pop((robot, seq)).scan is not None, ORPHANED) for _, seq in waiting
        ]
        gone += self._forget_evicted(lambda key: key[0] == robot)
        return pairs, gone

    def _add(self, key: JoinKey, item, is_scan: bool, confirmed: bool = False):
        """File a message of its stream: taken when it is the stream's next, else held past a gap until the
        stream's next message confirms it (``confirmed``: taken at once, the gap is believed)."""
        robot, seq = key
        stream = (robot, is_scan)
        last = self._last.get(stream, -1)
        if seq <= last:
            return [], [GivenUp(robot, seq, 1, is_scan, LATE)]
        held = self._held.pop(stream, None)
        if confirmed:  # a message held past a gap lies below the run: the stream went past it, its gap is real
            pairs, gone = [], []
            if held is not None:
                pairs, gone = self._take(robot, held[0], held[1], is_scan)
            more_pairs, more = self._take(robot, seq, item, is_scan)
            return pairs + more_pairs, gone + more
        if seq == last + 1:  # the stream goes on: a message held past a gap was a stray
            stray = [] if held is None else [self._jumped(robot, held[0], is_scan)]
            pairs, gone = self._take(robot, seq, item, is_scan)
            return pairs, stray + gone
        pairs, gone = [], []
        if held is not None and seq > held[0]:  # the stream went past the held message: its gap is real
            pairs, gone = self._take(robot, held[0], held[1], is_scan)
            if seq == held[0] + 1:  # ... and goes on from it
                more_pairs, more = self._take(robot, seq, item, is_scan)
                return pairs + more_pairs, gone + more
        elif held is not None:  # below the held message: the stream never went there, the held one was a stray
            gone = [self._jumped(robot, held[0], is_scan)]
        self._held[stream] = (seq, item)  # past a gap (another one): wait for the next message to confirm it
        return pairs, gone

    def _jumped(self, robot: str, seq: int, is_scan: bool) -> GivenUp:
        """Refuse the half held past a gap at ``seq`` as a jump; a scan's seq is remembered (:data:`STRAYS_KEPT`), so
        that when its stream passes it, it is given up as a stray, not as missing."""
        if is_scan:
            strays = self._strays.setdefault(robot, OrderedDict())
            strays[seq] = None
            while len(strays) > STRAYS_KEPT:
                strays.popitem(last=False)
        return GivenUp(robot, seq, 1, is_scan, JUMP)

    def _take(self, robot: str, seq: int, item, is_scan: bool):
        """Accept ``item`` as its stream's next message, after any gap since the stream's last seq."""
        pairs, gone = self._pass(robot, is_scan, self._last.get((robot, is_scan), -1) + 1, seq)
        self._last[(robot, is_scan)] = seq
        ahead = self._ahead.get((robot, is_scan), set())
        if seq in ahead:  # recovered with its partner while this copy was held: taken already
            ahead.discard(seq)
            return pairs, gone
        more_pairs, more = self._place(robot, seq, item, is_scan)
        return pairs + more_pairs, gone + more

    def _place(self, robot: str, seq: int, item, is_scan: bool):
        """File ``item``, a message its stream has passed, with its partner, or wait for the partner."""
        key = (robot, seq)
        entry = self._pending.get(key)
        gone = []
        if entry is None:
            if (robot, seq, not is_scan) in self._evicted:  # the partner came and was evicted: ask for it again
                del self._evicted[(robot, seq, not is_scan)]
                partner = self._refetch(robot, seq, not is_scan)
                if partner is None:
                    return [], [
                        GivenUp(robot, seq, 1, not is_scan, OVERFLOW),
                        GivenUp(robot, seq, 1, is_scan, ORPHANED),
                    ]
                return [(item, partner) if is_scan else (partner, item)], []
            if seq <= self._last.get((robot, not is_scan), -1):  # the partner's stream passed it: never comes
                return [], [GivenUp(robot, seq, 1, is_scan, ORPHANED)]
            while len(self._pending) >= self.capacity:
                (old_robot, old_seq), old = self._pending.popitem(last=False)
                gone += self._evict(old_robot, old_seq, old.scan is not None, old.half())
            entry = self._pending[key] = _Pending()
        if is_scan:
            entry.scan = item
        else:
            entry.pose = item
        if entry.scan is not None and entry.pose is not None:
            del self._pending[key]
            return [(entry.scan, entry.pose)], gone
        return [], gone

    def _pass(self, robot: str, is_scan: bool, skipped_from: int, skipped_to: int):
        """Seqs skipped_from .. skipped_to-1 of the robot's scan (or pose) stream did not come: what ``recover``
        finds of them is taken; the rest are counted when they are scans, and the partners waiting for them are
        given up. Returns the pairs completed and the halves given up on."""
        if skipped_to <= skipped_from:
            return [], []
        stream, partner = (robot, is_scan), (robot, not is_scan)
        self._last[stream] = max(self._last.get(stream, -1), skipped_to - 1)
        ahead = self._ahead.get(stream, set())
        taken = {seq for seq in ahead if seq < skipped_to}  # recovered with their partners already
        ahead -= taken
        found = self._recovered(robot, is_scan, skipped_from, skipped_to, taken)
        gone: list[GivenUp] = []
        if is_scan:
            strays = self._strays.get(robot, OrderedDict())
            passed = {seq for seq in strays if skipped_from <= seq < skipped_to and seq not in found}
            for seq in [seq for seq in strays if seq < skipped_to]:
                del strays[seq]
            gone += [GivenUp(robot, first, count, True, STRAY) for first, count in _present_runs(passed)]
            gone += [
                GivenUp(robot, first, count, True, MISSING)
                for first, count in _absent_runs(skipped_from, skipped_to, found.keys() | taken | passed)
            ]
        for key in [
            k for k in self._pending if k[0] == robot and skipped_from <= k[1] < skipped_to and k[1] not in found
        ]:
            gone.append(GivenUp(robot, key[1], 1, not is_scan, ORPHANED))
            del self._pending[key]
        gone += self._forget_evicted(
            lambda key: (
                key[0] == robot and key[2] != is_scan and skipped_from <= key[1] < skipped_to and key[1] not in found
            )
        )
        # their partners too, where the partner's stream has not got there yet: paired at once, a gap larger than
        # the buffer does not overflow it (a shard restarted late in a run); and the partners of the halves
        # waiting below the gap (evicted ones included), so that the pairs come out in seq order; none at or past
        # the partner stream's held message, which is taken first
        held, partner_last = self._held.get(partner, (None,))[0], self._last.get(partner, -1)
        below = skipped_from if held is None else min(skipped_from, held)
        waiting = [k[1] for k in self._pending if k[0] == robot and partner_last < k[1] < below]
        waiting += [k[1] for k in self._evicted if k[0] == robot and k[2] == is_scan and partner_last < k[1] < below]
        lacking = waiting + [
            seq
            for seq in found
            if (robot, seq) not in self._pending and seq > partner_last and (held is None or seq < held)
        ]
        partners = self._recovered(robot, not is_scan, min(lacking), max(lacking) + 1, set()) if lacking else {}
        pairs = []
        for seq in sorted({*found, *waiting}):
            more_pairs, more = self._place(robot, seq, found[seq], is_scan) if seq in found else ([], [])
            if seq in partners:
                self._ahead.setdefault(partner, set()).add(seq)
                also_pairs, also = self._place(robot, seq, partners[seq], not is_scan)
                more_pairs, more = more_pairs + also_pairs, more + also
            pairs += more_pairs
            gone += more
        return pairs, gone

    def _evict(self, robot: str, seq: int, is_scan: bool, half: ScanT | PoseT) -> list[GivenUp]:
        """Make room: ``half``, (robot, seq)'s, leaves the buffer. With ``recover`` only its seq (and digest) is kept,
        to ask for it again when its partner comes (the oldest such seq beyond the limit is given up); without, it is
        given up."""
        if self.recover is None:
            return [GivenUp(robot, seq, 1, is_scan, OVERFLOW)]
        self._evicted[(robot, seq, is_scan)] = None if self._digest is None else self._digest(half)
        if len(self._evicted) <= EVICTED_LIMIT:
            return []
        (old_robot, old_seq, old_is_scan), _ = self._evicted.popitem(last=False)
        return [GivenUp(old_robot, old_seq, 1, old_is_scan, OVERFLOW)]

    def _refetch(self, robot: str, seq: int, is_scan: bool):
        """The evicted half (robot, seq) from ``recover``, or None when it no longer has it. The evicted seqs right
        after it are asked for in the same request and kept for when their partners come."""
        item = self._fetched.get((robot, is_scan), {}).pop(seq, None)
        if item is not None:
            return item
        stop = seq + 1
        while stop - seq < REFETCH_BATCH and (robot, stop, is_scan) in self._evicted:
            stop += 1
        found = self._recovered(robot, is_scan, seq, stop, set())
        self._fetched[(robot, is_scan)] = {other: got for other, got in found.items() if other != seq}
        return found.get(seq)

    def _forget_evicted(self, which: Callable[[tuple[str, int, bool]], bool]) -> list[GivenUp]:
        """Give up the evicted halves ``which`` picks: their partners never come."""
        keys = [key for key in self._evicted if which(key)]
        for robot, seq, is_scan in keys:
            del self._evicted[(robot, seq, is_scan)]
            self._fetched.get((robot, is_scan), {}).pop(seq, None)
        return [GivenUp(robot, seq, 1, is_scan, ORPHANED) for robot, seq, is_scan in keys]

    def _recovered(self, robot: str, is_scan: bool, first: int, stop: int, taken: set[int]) -> dict[int, ScanT | PoseT]:
        """What ``recover`` finds of the robot's scans (else poses) first .. stop-1, less ``taken``."""
        while first < stop and first in taken:
            first += 1
        while stop > first and stop - 1 in taken:
            stop -= 1
        if self.recover is None or first >= stop:
            return {}
        return {
            seq: item
            for seq, item in self.recover(robot, is_scan, first, stop - 1).items()
            if first <= seq < stop and seq not in taken
        }


def _at_least_one(value: int, what: str) -> int:
    """``value``, a count that must be >= 1; ValueError naming ``what`` otherwise."""
    if value < 1:
        raise ValueError(f"{what} must be >= 1, got {value}")
    return value


def _run_through(seqs: Mapping[int, object], seq: int) -> list[int]:
    """The run of consecutive seqs of ``seqs`` that holds ``seq``, ascending."""
    first, last = seq, seq
    while first - 1 in seqs:
        first -= 1
    while last + 1 in seqs:
        last += 1
    return list(range(first, last + 1))


def _present_runs(seqs: Iterable[int]) -> list[tuple[int, int]]:
    """``seqs`` as runs (first, count) of consecutive ones, lowest first."""
    runs: list[tuple[int, int]] = []
    for seq in sorted(seqs):
        if runs and runs[-1][0] + runs[-1][1] == seq:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((seq, 1))
    return runs


def _absent_runs(first: int, stop: int, present: Iterable[int]) -> list[tuple[int, int]]:
    """The seqs first .. stop-1 that are not in ``present``, as runs (first, count) of consecutive ones. The work
    grows with ``present``, not with the span: a stream that jumps 10^12 seqs ahead costs no more than one that
    jumps 2 (a loop over the span froze the shard)."""
    runs = []
    for seq in sorted(seq for seq in present if first <= seq < stop):
        if seq > first:
            runs.append((first, seq - first))
        first = seq + 1
    if stop > first:
        runs.append((first, stop - first))
    return runs


class SeqLedger(Generic[NoteT]):
    """The seqs of each robot already fused (or given up on at fusion), each with a note of what was fused
    (e.g. digests of the scan and the pose, so that a message sent again can be told from a conflicting one).

    Only the seqs within ``horizon`` of a robot's highest are kept; an older seq counts as done, with no note,
    so the memory stays bounded on runs of any length. A robot that starts again from seq 0 under the same
    name therefore finds its seqs done: streams are numbered once per robot name (schemas.messages).
    """

    def __init__(self, horizon: int):
        self.horizon = _at_least_one(horizon, "seq ledger horizon")
        self._seqs: dict[str, dict[int, NoteT | None]] = {}
        self._highest: dict[str, int] = {}

    def done(self, robot: str, seq: int) -> bool:
        """Whether ``robot``'s ``seq`` was fused already (or lies more than ``horizon`` below its highest)."""
        highest = self._highest.get(robot)
        return highest is not None and (seq <= highest - self.horizon or seq in self._seqs[robot])

    def note(self, robot: str, seq: int) -> NoteT | None:
        """What :meth:`mark` recorded with ``robot``'s ``seq``; None when it is not kept (not done, or older than
        the horizon)."""
        highest = self._highest.get(robot)
        return None if highest is None or seq <= highest - self.horizon else self._seqs[robot].get(seq)

    def mark(self, robot: str, seq: int, note: NoteT | None = None) -> None:
        """Record ``robot``'s ``seq`` as done, with ``note``."""
        seqs = self._seqs.setdefault(robot, {})
        seqs[seq] = note
        highest = self._highest[robot] = max(self._highest.get(robot, seq), seq)
        if len(seqs) > 2 * self.horizon:  # drop the seqs that ``done`` no longer reads (amortised)
            self._seqs[robot] = {s: n for s, n in seqs.items() if s > highest - self.horizon}
