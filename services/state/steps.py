"""Gathers the messages of each seq (scan, odometry, landmarks) and hands whole steps out in seq order.

A SLAM filter must see its steps in order. Parts may arrive in any order across keys; a step is complete
when every part the filter needs is there. Complete steps are released strictly in seq order; a seq that
never completes is skipped (and reported) once ``reorder`` later steps are complete and waiting, or when
the stream has ended; before that, the assembler's ``recover`` (if given) may supply the missing parts (the SLAM
node asks the source's history for them), and at the end it is asked for every step from the first not yet
released (the last steps may have been lost, e.g. while the router was down). A part whose seq was already
released or skipped arrives *out of order*: it is reported and dropped. At most ``capacity`` incomplete steps
are held; beyond that the one of the highest seq is evicted (the next steps are those the stream needs first:
parts forged for seqs ahead within the window evicted every real step when the oldest went).

A live part more than ``window`` seqs beyond the next step to release is not believed on its own word (a peer
forging a step far ahead would make the assembler skip every real step up to it): it is held apart, at most
FAR_KEPT seqs of them, and filed once the released steps get within the window of it, or once CONFIRM_RUN
consecutive far seqs are complete and ``recover`` (the source's history) gives the first of them, the same parts
(the stream really jumped; without ``recover`` the run alone is believed). Parts from the history are trusted.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from services.state.join import CONFIRM_RUN, DEFAULT_SEQ_WINDOW, FAR_KEPT

PartT = TypeVar("PartT")


class OutOfOrder(Exception):
    """A part of a step whose seq is at or below one already processed."""


@dataclass
class Released:
    """Complete steps in order, seqs skipped on the way (runs (first seq, count)), and incomplete steps evicted
    for space."""

    steps: list[tuple[int, dict]] = field(default_factory=list)
    skipped: list[tuple[int, int]] = field(default_factory=list)
    evicted: int = 0
    ahead: int = 0  # parts held beyond the seq window (counted when they come)


class StepAssembler(Generic[PartT]):
    """See the module docstring. ``needs``: the parts a step must have, e.g. {"odom", "landmarks"}; a part is a
    ``PartT`` (a message)."""

    def __init__(
        self,
        needs: set[str] | frozenset[str],
        capacity: int = 256,
        reorder: int = 16,
        recover: Callable[[int, int | None], Mapping[int, Mapping[str, PartT]]] | None = None,
        window: int = DEFAULT_SEQ_WINDOW,
        same: Callable[[PartT, PartT], bool] = lambda a, b: a == b,
    ):
        """``recover(first, last)``: the parts {seq: {part: message}} it can find of seqs first..last (inclusive;
        last None: every seq from first on, at the end of the stream), which are about to be skipped; what it
        returns fills them in. ``window``: seqs beyond the next step that a live part may lie."""
        self.needs = frozenset(needs)
        self.capacity = capacity
        self.reorder = reorder
        self.recover = recover
        self.window = window
        self._same = same
        self._far: dict[int, dict[str, PartT]] = {}  # seq -> parts, held beyond the window
        self._asked_through = -1  # the last seq recover was asked for
        self.next_seq = 0
        self._pending: dict[int, dict[str, PartT]] = {}

    def beyond_window(self, seq: int) -> bool:
        """Whether ``seq`` lies more than the window beyond the next step to release."""
        return seq > self.next_seq + self.window

    def add(self, part: str, seq: int, message: PartT, trusted: bool = False) -> Released:
        """Store one part; returns what it releases. Raises :class:`OutOfOrder` for a seq already passed.
        ``trusted``: it came from the source's history, and the seq window does not apply."""
        if seq < self.next_seq:
            raise OutOfOrder(f"{part} seq {seq} arrived after seq {self.next_seq - 1} was processed")
        released = Released()
        if not trusted and self.beyond_window(seq):
            released.ahead = 1
            self._far.setdefault(seq, {})[part] = message
            while len(self._far) > FAR_KEPT:
                del self._far[max(self._far)]
            if not self._far_run_complete(seq):
                return released
        else:
            self._pending.setdefault(seq, {})[part] = message
        while len(self._pending) > self.capacity:  # the farthest step goes first: the next ones are the stream's
            del self._pending[max(self._pending)]  # (a flood of parts for later seqs evicted every real step)
            released.evicted += 1
        self._release(released, flush=False)
        return released

    def flush(self, tail: bool = True) -> Released:
        """At the end of the stream: take what ``recover`` finds from the first step not yet released on (unless
        not ``tail``), then release every complete step, skipping the gaps."""
        if self.recover is not None and tail:
            self._fill(self.recover(self.next_seq, None), self.next_seq, None)
        released = Released()
        self._release(released, flush=True)
        return released

    def _far_run_complete(self, seq: int) -> bool:
        """Whether ``seq`` is in a run of CONFIRM_RUN consecutive complete far seqs; if so, the run is filed (the
        stream really jumped; the steps before it are recovered or skipped as for any gap)."""

        def complete(other: int) -> bool:
            return other in self._far and self.needs <= self._far[other].keys()

        if not complete(seq):
            return False
        first, last = seq, seq
        while complete(first - 1):
            first -= 1
        while complete(last + 1):
            last += 1
        if last - first + 1 < CONFIRM_RUN or (last - first + 1) % CONFIRM_RUN or not self._vouched(first):
            return False
        for other in range(first, last + 1):
            self._pending[other] = self._far.pop(other)
        return True

    def _vouched(self, seq: int) -> bool:
        """Whether ``recover`` gives the far step ``seq``'s parts, the same as those held (True without it)."""
        if self.recover is None:
            return True
        found = self.recover(seq, seq).get(seq, {})
        held = self._far[seq]
        return all(part in found and self._same(found[part], message) for part, message in held.items())

    def _refile_far(self) -> None:
        """File the far parts that the released steps have got within the window of."""
        for seq in sorted(seq for seq in self._far if not self.beyond_window(seq)):
            parts = self._far.pop(seq)
            if seq >= self.next_seq:
                self._pending.setdefault(seq, {}).update(parts)

    def _complete(self, seq: int) -> bool:
        return seq in self._pending and self.needs <= self._pending[seq].keys()

    def _release(self, released: Released, flush: bool) -> None:
        while True:
            if self._far and not flush:
                self._refile_far()
            if self._complete(self.next_seq):
                released.steps.append((self.next_seq, self._pending.pop(self.next_seq)))
                self.next_seq += 1
                continue
            waiting = sorted(s for s in self._pending if self._complete(s))
            if not waiting or (not flush and len(waiting) < self.reorder):
                return
            if self.recover is not None and self.next_seq > self._asked_through:  # each seq is asked for once
                self._fill(self.recover(self.next_seq, waiting[0] - 1), self.next_seq, waiting[0])
                self._asked_through = waiting[0] - 1
                waiting = sorted(s for s in self._pending if self._complete(s))  # now from the first recovered
            for seq in [seq for seq in self._pending if seq < waiting[0]]:  # not per skipped seq: a stream that
                del self._pending[seq]  # jumps 10^12 ahead took that many steps (and a list of them) before
            if waiting[0] > self.next_seq:
                released.skipped.append((self.next_seq, waiting[0] - self.next_seq))
            self.next_seq = waiting[0]

    def _fill(self, found: Mapping[int, Mapping[str, PartT]], first: int, stop: int | None) -> None:
        """File the parts ``recover`` found of seqs first .. stop-1 (stop None: no end)."""
        for seq, parts in found.items():
            if first <= seq and (stop is None or seq < stop):
                self._pending.setdefault(seq, {}).update(parts)
