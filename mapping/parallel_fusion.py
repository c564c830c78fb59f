"""Scans fused on several threads into one map, the same bit for bit as fused one after the other.

A scan's fusion (:class:`mapping.fusion.MonteCarloFusion`) takes three steps:

* prepare: check the scan and its pose samples, build its beam table and its scratch window (Python, tens of us);
* walk: the compiled pass over all (sample, beam, cell) triples into a scratch window (85 to 90 % of a scan's
  time); it reads nothing of the map;
* apply: add the window's touched cells into the tiles, creating the tiles it needs; the only step that writes
  the map.

:func:`in_scan_order` walks up to T scans at once on a pool of T threads, each scan into a scratch of its own, and
applies them on the calling thread strictly in scan order. A scratch holds nothing from one scan to the next (each
pass clears what it set; records of earlier scans are told apart by stamps), so a scan's walk gives the same
scratch contents whichever scratch it takes, and each cell of the map sees the same float operations in the same
order as with one thread: the map is the same bit for bit for any T. The kernels release the GIL (``nogil``), so
plain threads run them side by side. Preparing and applying stay on the calling thread, in scan order, so tiles are
created in the same order as well.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, wait
from dataclasses import dataclass
from typing import Generic, TypeVar

from mapping.errors import InputError

Scan = TypeVar("Scan")  # what the caller hands in for one scan
Ready = TypeVar("Ready")  # a prepared scan, to walk
Scratch = TypeVar("Scratch")  # one walk's working memory
Walked = TypeVar("Walked")  # a walked scan, to apply
Result = TypeVar("Result")  # what applying a scan gives

#: scans prepared ahead per scratch at most (a run of scans with nothing to walk is not pulled in without bound)
LOOK_AHEAD = 2


@dataclass(frozen=True)
class _Turn(Generic[Scratch, Walked, Result]):
    """One scan's place in the queue: its walk in flight on ``scratch``, or its outcome known when it was pulled
    (a result with nothing to walk, or the InputError that refused it), or an error to raise when its turn comes."""

    job: Future[Walked] | None = None
    scratch: Scratch | None = None
    outcome: Result | InputError | None = None
    failure: BaseException | None = None


@dataclass
class _Queue(Generic[Scan, Ready, Scratch, Walked, Result]):
    """The scans pulled and not yet handed out, in scan order, and the scratches free for a walk."""

    source: Iterator[Scan]
    prepare: Callable[[Scan], Ready | None]
    walk: Callable[[Ready, Scratch], Walked]
    pool: Executor
    empty: Result
    free: list[Scratch]
    limit: int
    turns: deque[_Turn[Scratch, Walked, Result]]
    more: bool = True

    def fill(self) -> None:
        """Pull and prepare scans while a scratch is free (and the look-ahead allows), each walk sent to the pool."""
        while self.more and self.free and len(self.turns) < self.limit:
            self.more = self._pull()

    def _pull(self) -> bool:
        """Pull, prepare and queue the next scan; whether to go on pulling (not after the last scan, nor after an
        error other than InputError: a scan after it would not have been fused one thread)."""
        try:
            scan = next(self.source)
        except StopIteration:
            return False
        except Exception as exc:  # noqa: BLE001 - the caller's iterator failed: raised again at this scan's turn
            self.turns.append(_Turn(failure=exc))
            return False
        try:
            ready = self.prepare(scan)
        except InputError as exc:
            self.turns.append(_Turn(outcome=exc))
            return True
        except Exception as exc:  # noqa: BLE001 - raised again at this scan's turn, after the earlier scans
            self.turns.append(_Turn(failure=exc))
            return False
        if ready is None:
            self.turns.append(_Turn(outcome=self.empty))
            return True
        scratch = self.free.pop()
        self.turns.append(_Turn(job=self.pool.submit(self.walk, ready, scratch), scratch=scratch))
        return True

    def settle(self, turn: _Turn[Scratch, Walked, Result], apply: Callable[[Walked], Result]) -> Result | InputError:
        """The outcome of the scan at the head of the queue: its walk waited for and applied (its scratch freed), or
        the outcome it had; its error raised."""
        if turn.failure is not None:
            raise turn.failure
        if turn.job is None:
            assert turn.outcome is not None  # (a turn holds a job, an outcome or a failure)
            return turn.outcome
        result = apply(turn.job.result())
        assert turn.scratch is not None  # (a job runs on a scratch)
        self.free.append(turn.scratch)
        return result

    def drain(self) -> None:
        """Wait for every walk still in flight (their scratches must be idle before anyone uses them again)."""
        wait([turn.job for turn in self.turns if turn.job is not None])


def in_scan_order(
    scans: Iterable[Scan],
    prepare: Callable[[Scan], Ready | None],
    walk: Callable[[Ready, Scratch], Walked],
    apply: Callable[[Walked], Result],
    scratches: Sequence[Scratch],
    pool: Executor,
    empty: Result,
) -> Iterator[Result | InputError]:
    """Each scan's outcome, in scan order: ``apply(walk(prepare(scan), scratch))``, the walks of up to
    len(scratches) scans on ``pool`` at once (each on a scratch of its own, one of ``scratches``, which nobody else
    may use meanwhile), the prepares and applies on the calling thread in scan order. ``prepare`` gives None for a
    scan with nothing to walk (its outcome is ``empty``) and raises InputError for a scan it refuses (the outcome is
    that InputError; the map is left as it was and the next scans go on). Any other error, of ``prepare``, ``walk``,
    ``apply`` or the ``scans`` iterator, is raised at its scan's turn, after every earlier scan was applied and with
    none of the later ones applied, as one thread fusing the scans one by one would. Closing the iterator early (or
    an error) waits for the walks in flight, so the scratches are idle once it returns."""
    queue: _Queue[Scan, Ready, Scratch, Walked, Result] = _Queue(
        iter(scans), prepare, walk, pool, empty, list(scratches), LOOK_AHEAD * len(scratches), deque()
    )
    try:
        queue.fill()
        while queue.turns:
            outcome = queue.settle(queue.turns.popleft(), apply)
            queue.fill()  # (the next walks start before the caller takes this outcome)
            yield outcome
    finally:
        queue.drain()
