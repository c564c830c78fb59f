"""The state of one mapper shard, without any networking: it decodes what arrives, joins scans with their
poses, fuses the cells of its own tiles, and says which tile windows to publish and when.

Fusion is exactly `posegrid fuse`'s per-scan path (services.fusion_runner): the same sensor model, the
same :class:`mapping.fusion.MonteCarloFusion`, and the pose samples of :class:`services.fusion_runner.PoseSampling`
(Gaussian draws seeded by (seed, seq)); so the union of all shards' tiles equals the in-process map when the
scans arrive in seq order (log-odds clamping makes fusion order matter; a shard fuses each scan as soon as its
pose is there, or, when its caller hands it several messages at once, with the other pairs they complete, on
ShardConfig.threads threads and in join order: the same map).
"""

from __future__ import annotations

import math
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from mapping.beam_model import farthest_walk
from mapping.errors import InputError
from mapping.fusion import FuseResult, FusionThreads, MonteCarloFusion
from mapping.grid import TILE_SIZE, TiledGrid
from mapping.sensor_model import SensorModel
from mapping.tile_boxes import join_windows
from schemas.messages import POSE_TYPES, LaserScan, PoseDistribution, PoseGaussian, ShardStats, StreamEnd, TileUpdate
from schemas.wire import Message
from services import keys
from services.fusion_runner import FUSIONS_KEPT, PoseSampling
from services.handoff_lock import HandoffLock
from services.process import RejectCounter, get_logger
from services.state.checks import decode_of_robot, history_reply, robot_stream
from services.state.join import (
    EVICTED_LIMIT,
    GIVEN_UP_BECAUSE,
    MISSING,
    ORPHANED,
    OVERFLOW,
    STRAY,
    GivenUp,
    JoinBuffer,
    SeqLedger,
)
from services.state.limits import ShardLimits, reach_tiles
from services.state.ownership import owns_tile
from services.state.store.db import Batch, LedgerEntry, RobotState, StoredState, TileState
from services.state.store.journal import SEED_ROBOT, Journal
from services.state.store.writer import NO_STORE, PersistReport

TileKey = tuple[int, int]
TileWindow = tuple[int, int, int, int]  # (row0, col0, rows, cols): tile-local cells

#: a fused seq more than this many times the join capacity (and twice the evicted halves the join may still ask
#: the histories for: services.state.join.EVICTED_LIMIT) below a robot's highest counts as done
SEQ_HORIZON_JOINS = 8
#: s after an ended robot's last taken scan or pose at which its streams are settled: what is still missing or
#: waiting is given up (:meth:`MapShard.settle`)
SETTLE_AFTER = 15.0
#: s after an ended robot's last taken scan or pose at which the scans and poses between the last each stream passed
#: and the end are asked of the histories (a router restart lost them, and the end came after): nothing is given up
#: then, and the end may overtake the last scans on the way in only by milliseconds
TAIL_AFTER = 1.0


@dataclass(frozen=True)
class ShardConfig:
    """What a shard needs to know. mode/n_samples/seed/accuracy mean what they mean for `posegrid fuse`;
    publish_interval (s) is the shortest time between two updates of one tile; join_capacity bounds the
    scans and poses waiting for their partner; threads: how many of the scans ready at once are walked side by
    side (mapping.parallel_fusion; the map is the same for any count)."""

    map_name: str
    shard: int
    shards: int
    model: SensorModel
    mode: str = "mc"
    n_samples: int | None = None
    seed: int = 0
    accuracy: float | None = None
    tile_size: int = TILE_SIZE
    publish_interval: float = 0.05
    join_capacity: int = 512
    limits: ShardLimits = ShardLimits()
    threads: int = 1
    bundle: float = 0.0  # m: the pose bundles' tolerance (mapping.bundling; 0: every sample walks its rays)


#: what a shard joins: a scan or the pose distribution of its seq
ScanOrPose = LaserScan | PoseDistribution
#: the streams a shard joins, and the message types each may carry
JOINED_STREAMS: dict[str, tuple[type[ScanOrPose], ...]] = {keys.SCAN: (LaserScan,), keys.POSE: POSE_TYPES}
#: the streams a shard subscribes to, and the message types each may carry
SHARD_STREAMS: dict[str, tuple[type[ScanOrPose | StreamEnd], ...]] = {**JOINED_STREAMS, keys.END: (StreamEnd,)}


def message_bytes(message: object) -> int:
    """Bytes the arrays of a decoded message hold (what it costs to keep it waiting)."""
    return sum(value.nbytes for value in vars(message).values() if isinstance(value, np.ndarray))


def warm_fusion(model: SensorModel, tile_size: int, threads: FusionThreads | None = None) -> None:
    """Fuse a three-beam scan at two poses into a scratch grid of ``tile_size``-cell tiles with ``model`` and take its
    changed cells, so that the fusion's and the tile updates' compiled kernels are loaded, or compiled and cached where
    they are not yet (mapping.jit). The scratch fusion owns every tile, so every kernel runs (a shard owning none of
    these tiles would skip the last one). With ``threads`` of more than one thread, the scan again at 16 poses, alone
    on them: in parts (its adding up)."""
    scratch = TiledGrid(model.resolution, tile_size, track_changes=True)
    angles, ranges = np.array([-0.5, 0.0, 0.5]), np.array([1.0, np.inf, 2.0])
    fusion = MonteCarloFusion(scratch, model, angles, 0.1, 5.0)
    fusion.fuse(ranges, np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]]), np.array([0.5, 0.5]))
    for key in scratch.keys():  # noqa: SIM118 - a TiledGrid, not a dict (the kernels that take a tile's cells)
        scratch.take_changes(key, (0, 0, tile_size, tile_size))
    if threads is not None and threads.count > 1:
        poses = np.column_stack([np.linspace(0.0, 0.15, 16), np.zeros(16), np.zeros(16)])
        MonteCarloFusion(scratch, model, angles, 0.1, 5.0, threads=threads).fuse_many(
            [(ranges, poses, np.full(16, 1 / 16))]
        )


class TileSnapshot(NamedTuple):
    """A copy of one tile's layers (log-odds, variance, observed; each (T, T), row = y) and its reply's fields."""

    layers: tuple[np.ndarray, np.ndarray, np.ndarray]
    fields: dict[str, Any]


def whole_tile(snapshot: TileSnapshot) -> TileUpdate:
    """The reply to a tile query for ``snapshot``'s tile: every value of every cell."""
    return TileUpdate.of_window(snapshot.layers, None, **snapshot.fields)


class MapShard:
    """One shard's grid and bookkeeping. Not thread-safe: callers serialise access (services.nodes.mapper)."""

    def __init__(
        self,
        config: ShardConfig,
        rejects: RejectCounter,
        clock: Callable[[], float] = time.monotonic,
        history: Callable[..., list[bytes]] | None = None,
    ):
        """``history(robot, stream, first, last[, seqs])``: the encoded messages of the robot's ``stream`` (keys.SCAN or
        keys.POSE) with seqs first..last that the processes which published them still hold (services.nodes.mapper
        asks pg/<robot>/history/**); the join takes them for messages lost in transit."""
        self.config = config
        self.grid = TiledGrid(config.model.resolution, config.tile_size, track_changes=True)
        self.owns = owns_tile(config.shard, config.shards)
        self.rejects = rejects
        self.sampling = PoseSampling(
            config.mode,
            config.n_samples,
            config.seed,
            config.accuracy if config.accuracy is not None else config.model.resolution,
        )
        self._fusions: OrderedDict[tuple, MonteCarloFusion] = OrderedDict()
        self._threads = FusionThreads(config.threads)  # (shared by the fusions of every laser geometry)
        # pairs joined and not yet fused, in join order, with their digests (scan, pose)
        self._ready: list[tuple[LaserScan, PoseDistribution, tuple[bytes, bytes]]] = []
        self._history = history
        self._history_high: dict[tuple[str, str], int] = {}  # (robot, stream) -> highest seq a history gave
        limits = config.limits
        self._join: JoinBuffer[LaserScan, PoseDistribution] = JoinBuffer(
            config.join_capacity,
            None if history is None else self._recover,
            window=limits.seq_window,
            max_bytes=limits.join_bytes,
            size=message_bytes,
            digest=lambda half: half.digest(),
        )
        # (robot, seq) -> digests of the scan and the pose fused
        self._fused_seqs: SeqLedger[tuple[bytes, bytes]] = SeqLedger(
            max(SEQ_HORIZON_JOINS * config.join_capacity, 2 * EVICTED_LIMIT)
        )
        self.log = get_logger(f"mapper[{config.shard}]")  # the logger services.nodes.mapper.Mapper writes to
        self._robots: set[str] = set()  # robots this shard keeps state for (at most limits.max_robots)
        self.received: Counter[str] = Counter()
        self.resent: Counter[str] = Counter()  # by key: messages of fused seqs, the same as those fused
        self.fused: Counter[str] = Counter()
        self.discarded: Counter[str] = Counter()
        self.ended: dict[str, int] = {}
        self._clock = clock
        self._heard: dict[str, float] = {}  # robot -> when its last scan or pose was taken, or its end came (clock s)
        self._unsettled: set[str] = set()  # robots whose stream has ended and that have had news since
        self._tails_asked: set[str] = set()  # of those, the robots whose tails were asked since their last news
        self._past_end_said: dict[str, int] = {}  # robot -> the end a scan or pose came past, said once (_past_end)
        self.join_overflow = 0
        self.cells_updated = 0
        self.tile_updates = 0
        self.started = time.monotonic()
        # per tile changed since it was last published, the window (row0, col0, rows, cols) that holds the changes
        self._dirty: dict[TileKey, TileWindow] = {}
        self._last_sent: dict[TileKey, float] = {}
        self._last_scan: dict[TileKey, tuple[str, int]] = {}
        self.journal: Journal | None = None  # what changed since the last commit, for a shard with a store
        # the lock the mapper's main thread holds while this shard fuses (None: no one else reads the shard): between
        # two scans of a batch it is handed to the tile queries waiting for it
        self.handoff: HandoffLock | None = None

    # ------------------------------------------------------------------------------- intake
    def handle(self, key: str, payload: bytes, defer: bool = False) -> None:
        """Decode one message received on ``key`` (pg/<robot>/<stream>) and act on it (:meth:`take`, ``defer`` as
        there); a bad one is counted and dropped."""
        message = self.decode(key, payload)
        if message is not None:
            self.take(key, message, defer=defer)

    def decode(self, key: str, payload: bytes) -> ScanOrPose | StreamEnd | None:
        """The message ``payload`` received on ``key`` (pg/<robot>/<stream>) holds; None after counting why it
        is refused (a key that is no robot stream of a shard's, e.g. a wildcard; a robot past the limit; malformed;
        the wrong type for the key; another robot's; a scan of more beams than the limit)."""
        parsed = robot_stream(key, SHARD_STREAMS, self.rejects)
        if parsed is None:
            return None
        robot, stream = parsed
        if robot not in self._robots and len(self._robots) >= self.config.limits.max_robots:
            self.rejects.count(
                keys.INVALID_KEY,
                "robots",
                f"a message of robot {robot!r}: this shard keeps "
                f"{self.config.limits.max_robots} robots already (--max-robots)",
            )
            return None
        self.received[key] += 1
        message = decode_of_robot(key, robot, payload, SHARD_STREAMS[stream], self.rejects)
        if message is None or self._too_many_beams(key, message):
            return None
        self._robots.add(robot)
        return message

    def _too_many_beams(self, key: str, message: Message) -> bool:
        """Whether ``message`` is a scan of more beams than the limit (counted under ``key`` when it is)."""
        if isinstance(message, LaserScan) and message.ranges.shape[0] > self.config.limits.max_beams:
            self.rejects.count(
                key,
                "size",
                f"a scan of {message.ranges.shape[0]} beams, more than the limit "
                f"{self.config.limits.max_beams} (--max-beams)",
            )
            return True
        return False

    def in_seq_order(self, replies: Iterable[tuple[str, bytes]]) -> list[tuple[str, ScanOrPose]]:
        """The scans and poses that histories gave, as (key, payload) pairs with key pg/<robot>/scan or
        pg/<robot>/pose, decoded (a bad one counted) and put in seq order for :meth:`take`. Each history
        answers in the order it published, one after the other (the source's scans, then the SLAM node's
        poses): taken in that order, the scans of a run longer than the join buffer would overflow it while
        their poses waited further down the list. In seq order, a scan and its pose come together."""
        taken = []
        for key, payload in replies:
            if key.rsplit("/", 1)[-1] not in (keys.SCAN, keys.POSE):
                self.rejects.count(key, "history", f"a history answered on {key}: only scans and poses are asked for")
                continue
            message = self.decode(key, payload)
            if message is not None:
                assert not isinstance(message, StreamEnd)  # decoded as its key's stream: a scan or a pose
                taken.append((key, message))
        taken.sort(key=lambda item: item[1].seq)  # (stable: a seq's scan and pose keep the order they came in)
        return taken

    def take(self, key: str, message: ScanOrPose | StreamEnd, from_history: bool = False, defer: bool = False) -> None:
        """Act on a decoded ``message`` received on ``key``: note an end, or join a scan or pose and fuse what
        pairs up. ``from_history``: it came from a history at startup (:meth:`services.nodes.mapper.Mapper.catch_up`),
        and a live copy of it, or of an earlier message of its stream, is then dropped without a word. ``defer``: keep
        the pairs for :meth:`fuse_ready` (which the caller calls before anyone else looks at the shard), so that the
        pairs of several messages are fused together on the shard's threads."""
        stream = key.rsplit("/", 1)[-1]
        if isinstance(message, StreamEnd):
            self.fuse_ready()  # (the end is checked against the scans fused so far, the deferred pairs too)
            accounted = self.fused[message.robot] + self.discarded[message.robot]
            if message.scans < accounted:
                self.rejects.count(
                    key,
                    "end",
                    f"an end of the stream of robot {message.robot!r} announcing "
                    f"{message.scans} scans, where this shard has fused or given up {accounted}: "
                    "another run's end (a robot name belongs to one run at a time)",
                )
                return
            if self._join.beyond_window(message.robot, True, message.scans - 1):
                self.rejects.count(
                    key,
                    "ahead",
                    f"an end of the stream of robot {message.robot!r} announcing "
                    f"{message.scans} scans, more than the seq window "
                    f"({self.config.limits.seq_window}) beyond the scans this shard has seen: "
                    "a forged or stray end",
                )
                return
            if message.robot not in self.ended:  # the first end is news: the last poses may still come (the source
                self._heard[message.robot] = self._clock()  # repeats it, and a repeat is no news)
            if self.journal is not None and self.ended.get(message.robot) != message.scans:
                self.journal.noted(self._clock())
            self.ended[message.robot] = max(message.scans, self.ended.get(message.robot, 0))
            self._unsettled.add(message.robot)
            return
        caught_up_to = self._history_high.get((message.robot, stream), -1)
        if from_history:
            self._history_high[(message.robot, stream)] = max(caught_up_to, message.seq)
        if self._fused_seqs.done(message.robot, message.seq):
            self._refuse_fused(key, stream, message)
            return
        join_key = (message.robot, message.seq)
        is_scan = isinstance(message, LaserScan)
        held = self._held_digest(join_key, is_scan)
        if not from_history and message.seq <= caught_up_to:  # (the histories' copy was taken)
            if held == message.digest():
                self._count_resent(key, message)
            else:
                self._refuse_taken(key, message, held is not None)
            return
        self._heard[message.robot] = self._clock()
        self._past_end(key, message)
        if message.robot in self.ended:  # (a late pose after the end: settle again once it is quiet)
            self._unsettled.add(message.robot)
            if not from_history:
                self._tails_asked.discard(message.robot)
        if held == message.digest():
            self._count_resent(key, message)
            return
        if isinstance(message, LaserScan):
            pairs, gone = self._join.add_scan(join_key, message, trusted=from_history)
        else:
            pairs, gone = self._join.add_pose(join_key, message, trusted=from_history)
        self._give_up(gone)
        self._ready_to_fuse(pairs)
        if not defer:
            self.fuse_ready()

    def _past_end(self, key: str, message: ScanOrPose) -> None:
        """Say, once per robot and end, a scan or pose of a seq at or past the end of its stream that this shard took
        (an end inside the seq window is taken on its word): the end or the message was forged or stray. Both are
        kept: raising the end to the message would let one forged scan hold back the source that waits for its
        shards to account for its end, and the message is fused or given up as any other."""
        end = self.ended.get(message.robot)
        if end is None or message.seq < end or self._past_end_said.get(message.robot) == end:
            return
        self._past_end_said[message.robot] = end
        self.log.warning(
            "%s seq %d came past the end of robot %r's stream announced earlier (%d scans, seqs 0-%d): that end, or "
            "this message, was forged or stray (two runs under one robot name?); both kept, said once per end",
            key,
            message.seq,
            message.robot,
            end,
            end - 1,
        )

    def _refuse_fused(self, key: str, stream: str, message: ScanOrPose) -> None:
        """Drop a scan or pose of a seq this shard has fused. One identical to the message fused is sent again (a
        restarted SLAM node publishes the run's poses again as it catches up; a seeded filter gives the same ones):
        counted under ``resent``, logged once per key. One that differs (two SLAM nodes for one robot, a stale
        run under the robot's name) is a rejection, ``duplicate``; so is one older than the seqs the ledger keeps
        digests for, which cannot be compared (``old``)."""
        fused = self._fused_seqs.note(message.robot, message.seq)  # (scan digest, pose digest) or None
        if fused is None:
            self.rejects.count(
                key,
                "old",
                f"a {message.TYPE} of robot {message.robot!r} for seq {message.seq}, which "
                f"this shard has fused already, more than {self._fused_seqs.horizon} seqs ago: too old "
                "to be compared with the one fused (a re-sent or out-of-date message)",
            )
        elif fused[1 if stream == keys.POSE else 0] == message.digest():
            self._count_resent(key, message)
        else:
            self.rejects.count(
                key,
                "duplicate",
                f"a {message.TYPE} of robot {message.robot!r} for seq {message.seq}, "
                "which this shard has fused already, differs from the one fused (two publishers for "
                "one robot, or a stale run under its name); the first one stands",
            )

    def _held_digest(self, join_key: tuple[str, int], is_scan: bool) -> bytes | None:
        """The digest of the copy of a scan (or pose) the join holds for ``join_key`` (robot, seq): waiting for its
        partner (or past a gap), or evicted for room and to be asked of the histories again; None for none."""
        waiting = self._join.waiting(join_key, is_scan)
        return self._join.evicted_digest(join_key, is_scan) if waiting is None else waiting.digest()

    def _refuse_taken(self, key: str, message: ScanOrPose, differs: bool) -> None:
        """Refuse a live scan or pose of a seq that the histories gave this shard already (their copy was taken:
        fused, waiting, or given up with its partner), and that is not the same as a copy it holds (``differs``:
        it holds one, and this is another; else it holds none to compare with): ``taken``."""
        held = "differs from the copy it holds" if differs else "cannot be compared with it"
        self.rejects.count(
            key,
            "taken",
            f"a {message.TYPE} of robot {message.robot!r} for seq {message.seq}, which the histories gave this shard "
            f"already (their copy was taken); this one {held}",
        )

    def _count_resent(self, key: str, message: ScanOrPose) -> None:
        """Count a scan or pose that came again, the same as the copy fused or waiting (for its pair, or past a gap in
        its stream); log the first per key."""
        self.resent[key] += 1
        if self.resent[key] == 1:
            self.log.info(
                "a %s of robot %r for seq %d came again, the same as the copy this shard has (a restarted "
                "SLAM node or source catching up): ignored; further ones on %s are only counted (resent)",
                message.TYPE,
                message.robot,
                message.seq,
                key,
            )

    def _recover(
        self, robot: str, is_scan: bool, first: int, last: int, seqs: tuple[int, ...] | None = None
    ) -> dict[int, ScanOrPose]:
        """Scans (else poses) first..last (of them only ``seqs`` when given) of ``robot`` that its stream skipped,
        from the history; each checked as a received message is, and for its seq (a bad one counted under the
        history's key)."""
        assert self._history is not None  # the join is given this method only with a history
        stream = keys.SCAN if is_scan else keys.POSE
        key = keys.history_key(robot, stream)
        found: dict[int, ScanOrPose] = {}
        asked = (
            self._history(robot, stream, first, last)
            if seqs is None
            else self._history(robot, stream, first, last, seqs)
        )
        for payload in asked:
            message = history_reply(key, robot, payload, JOINED_STREAMS[stream], first, last, self.rejects)
            if (
                message is not None
                and not self._too_many_beams(key, message)
                and not self._fused_seqs.done(robot, message.seq)
            ):
                found[message.seq] = message
        if found:
            self.log.info(
                "took %d %s(s) of robot %r in seqs %d-%d from the history (lost in transit, or dropped "
                "from a full join buffer)",
                len(found),
                stream,
                robot,
                first,
                last,
            )
        return found

    def _give_up(self, gone: list[GivenUp]) -> None:
        """Count the halves the join gave up on (services.state.join): scans that never came or whose pose never
        comes are discarded scans; every half is counted under join/<robot> by reason, the first logged."""
        for half in gone:
            if half.scans and half.reason in (OVERFLOW, MISSING, ORPHANED, STRAY):
                self.discarded[half.robot] += half.count
                if self.journal is not None:
                    self.journal.gave_up(half.robot, half.first + half.count - 1, half.count, self._clock())
            if half.reason == STRAY:  # (refused as a jump when it came, and counted then)
                continue
            if half.reason == OVERFLOW:
                self.join_overflow += half.count
            self.rejects.count(
                f"join/{half.robot}",
                half.reason,
                f"{half.describe()}: {GIVEN_UP_BECAUSE[half.reason]}",
                times=half.count,
            )

    # ------------------------------------------------------------------------------- fusion
    def warm_up(self) -> None:
        """Load the compiled fusion kernels (:func:`warm_fusion`) before the first real scan arrives; otherwise that
        scan's tile update carries the load (0.4 to 0.5 s in `make bench`). The shard's own grid and counters are
        not touched."""
        warm_fusion(self.config.model, self.config.tile_size, self._threads)

    def _fusion_for(self, scan: LaserScan) -> MonteCarloFusion:
        geometry = (
            scan.angle_min,
            scan.angle_increment,
            scan.ranges.shape[0],
            scan.range_min,
            scan.range_max,
            tuple(scan.sensor_offset.tolist()),
            scan.no_return_range,
        )
        fusion = self._fusions.get(geometry)
        if fusion is None:
            beam_angles = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.shape[0])
            fusion = MonteCarloFusion(
                self.grid,
                self.config.model,
                beam_angles,
                scan.range_min,
                scan.range_max,
                scan.sensor_offset,
                self.owns,
                threads=self._threads,
                bundle=self.config.bundle,
                no_return_range=scan.no_return_range,
            )
            self._fusions[geometry] = fusion
            while len(self._fusions) > FUSIONS_KEPT:
                self._fusions.popitem(last=False)
        else:
            self._fusions.move_to_end(geometry)
        return fusion

    def pose_samples(self, scan: LaserScan, pose: PoseDistribution) -> tuple[np.ndarray, np.ndarray]:
        """(samples (M, 3), weights (M,)) to fuse ``scan`` with, as `posegrid fuse` draws them."""
        if isinstance(pose, PoseGaussian):
            return self.sampling.draw(scan.seq, scan.range_max, mean=pose.mean, cov=pose.cov)
        return self.sampling.draw(scan.seq, scan.range_max, samples=pose.samples, weights=pose.weights)

    def _ready_to_fuse(self, pairs: list[tuple[LaserScan, PoseDistribution]]) -> None:
        """Mark joined pairs fused (a copy that comes again is dropped from now on) and keep them for
        :meth:`fuse_ready`, in join order."""
        for scan, pose in pairs:
            digests = (scan.digest(), pose.digest())
            self._fused_seqs.mark(scan.robot, scan.seq, digests)
            self._ready.append((scan, pose, digests))

    def fuse_ready(self) -> None:
        """Fuse the pairs kept by :meth:`_ready_to_fuse`, in join order (or count those that cannot be fused as given
        up), noting each in the journal. The scans of one laser geometry next to each other are fused together, on the
        fusion's threads (:meth:`mapping.fusion.MonteCarloFusion.fuse_iter`): the map is the one they give fused one
        by one."""
        ready, self._ready = self._ready, []
        tiles = self._fuse_pairs([(scan, pose) for scan, pose, _ in ready])
        if self.journal is not None:
            for (scan, _, digests), changed in zip(ready, tiles):
                self.journal.fused(LedgerEntry(scan.robot, scan.seq, *digests), changed, self._clock())

    def _fuse_pairs(self, pairs: list[tuple[LaserScan, PoseDistribution]]) -> list[list[TileKey]]:
        """Fuse ``pairs`` into the owned tiles, in order; the tiles each changed (none for one refused)."""
        tiles: list[list[TileKey]] = [[] for _ in pairs]
        drawn, reaches = [], []  # (index, scan, samples, weights) of the pairs to fuse; (m, cells) each reaches
        for index, (scan, pose) in enumerate(pairs):
            got = self._draw(scan, pose)
            if got is not None:
                drawn.append((index, scan, got[0], got[1]))
                reaches.append(got[2])
        drawn = self._within_map_limit(drawn, reaches)
        outcomes: list[FuseResult | Exception] = []
        counted = 0
        for outcome in self._fuse_drawn(drawn):
            outcomes.append(outcome)
            if self.handoff is not None and self.handoff.waiting:  # (a tile query: the map whole, its tiles tagged)
                counted = self._count_outcomes(drawn, outcomes, counted, tiles)
                self.handoff.hand_off()
        self._count_outcomes(drawn, outcomes, counted, tiles)
        return tiles

    def _count_outcomes(
        self,
        drawn: list[tuple[int, LaserScan, np.ndarray, np.ndarray]],
        outcomes: list[FuseResult | Exception],
        counted: int,
        tiles: list[list[TileKey]],
    ) -> int:
        """Count the outcomes of the scans of ``drawn`` from ``counted`` on (``outcomes`` has theirs) and note in
        ``tiles`` the tiles each changed; how many are counted now. Taken after the batch, or before a hand-off, not
        scan by scan: counting between two of the fusion's scans made the office's batches 9 % slower on two threads
        (0.383 against 0.352 s for 200 scans, in one process in turns; the count itself takes 5 us a scan)."""
        for (index, scan, _, _), outcome in zip(drawn[counted:], outcomes[counted:]):
            tiles[index] = self._count_outcome(scan, outcome)
        return len(outcomes)

    def _draw(self, scan: LaserScan, pose: PoseDistribution) -> tuple[np.ndarray, np.ndarray, tuple[float, int]] | None:
        """The pose samples and weights to fuse ``scan`` with, and how far from the samples its beams may reach: m
        (the sensor model's reach for the farthest its beams are walked, mapping.beam_model.farthest_walk and
        mapping.sensor_model.SensorModel.beam_reach, not for its range_max, which may state 1 km; and the length of
        the sensor offset) and the cells of the tiles within that reach (services.state.limits.reach_cells); None after
        counting why it is refused. A failure of the checks themselves (a value they were not written for) is
        counted and logged as a failed fusion is: nothing of the scan reached the map, and the shard goes on."""
        cfg = self.config
        try:
            samples, weights = self.pose_samples(scan, pose)
            sensor_reach = math.hypot(float(scan.sensor_offset[0]), float(scan.sensor_offset[1]))
            walked = farthest_walk(scan.ranges, scan.range_min, scan.range_max, scan.no_return_range)
            reach = cfg.model.beam_reach(walked)
            refused, cells = cfg.limits.check_scan(
                samples, scan.ranges.shape[0], reach, cfg.model.resolution, cfg.tile_size, sensor_reach
            )
        except Exception as exc:  # noqa: BLE001 - counted and logged with its traceback (_count_outcome)
            self._count_outcome(scan, exc)
            return None
        if refused is not None:
            self._refuse(scan, *refused)
            return None
        return samples, weights, (reach + sensor_reach, cells)

    def _refuse(self, scan: LaserScan, kind: str, why: str) -> None:
        """Count ``scan`` as given up, refused by a limit (``kind``; ``why``, one sentence)."""
        self.discarded[scan.robot] += 1
        self.rejects.count(f"fuse/{scan.robot}", kind, f"scan seq {scan.seq} of robot {scan.robot!r} refused: {why}")

    def _within_map_limit(
        self, drawn: list[tuple[int, LaserScan, np.ndarray, np.ndarray]], reaches: list[tuple[float, int]]
    ) -> list[tuple[int, LaserScan, np.ndarray, np.ndarray]]:
        """The scans of ``drawn`` ((index, scan, samples, weights) each, in fusion order; ``reaches``: how far each
        scan's beams reach from its samples, m, and the cells of the tiles within that reach, :meth:`_draw`) that
        --max-map-cells lets this shard fuse; the others are counted as
        refused ("map"). A batch's scans are all checked before any is fused, so the tiles its earlier scans may add
        count for the later ones. When the tiles within reach of every scan (their count, an upper bound) fit, all
        may be fused; else each scan's new tiles are listed, the owned tiles within its reach that neither the grid
        nor an earlier scan of the batch holds (:func:`services.state.limits.reach_tiles`)."""
        cfg = self.config
        per_tile = cfg.tile_size * cfg.tile_size
        resolution = cfg.model.resolution
        limit = cfg.limits.max_map_cells // per_tile  # (tiles)
        counts = [cells // per_tile for _, cells in reaches]
        if self.grid.tile_count + sum(counts) <= limit:
            return drawn
        kept = []
        adding: set[TileKey] = set()
        unlisted = 0  # tiles of the kept scans too wide to list, counted
        for item, (reach, _), count in zip(drawn, reaches, counts):
            listed = reach_tiles(item[2], reach, resolution, cfg.tile_size)
            new = None
            if listed is not None:
                new = {(tx, ty) for tx, ty in listed.tolist() if (tx, ty) not in self.grid and self.owns(tx, ty)}
                new -= adding
            more = count if new is None else len(new)
            held = self.grid.tile_count + len(adding) + unlisted
            if held + more > limit:
                self._refuse(
                    item[1],
                    "map",
                    f"it may add {more} tile(s) of {per_tile} cells to the {held} this shard holds or is adding, past "
                    f"the limit of {cfg.limits.max_map_cells:.3g} cells (--max-map-cells; raise it, or run more "
                    "shards)",
                )
                continue
            kept.append(item)
            if new is None:
                unlisted += count
            else:
                adding |= new
        return kept

    def _fuse_drawn(
        self, drawn: list[tuple[int, LaserScan, np.ndarray, np.ndarray]]
    ) -> Iterator[FuseResult | Exception]:
        """The outcome of fusing each scan of ``drawn`` ((index, scan, samples, weights) each) with the fusion of its
        laser geometry, in order, on the shard's threads, each as soon as its scan is in the map: a FuseResult, the
        InputError that refused it, or the error it failed with (logged; the scans after it are fused all the same).
        Several scans are walked side by side, a lone scan (a live laser's, fused as it comes) in parts on all the
        threads (mapping.fusion.FusionThreads)."""
        given = 0  # outcomes yielded
        while given < len(drawn):
            scans = (
                (self._fusion_for(scan), (scan.ranges, samples, weights)) for _, scan, samples, weights in drawn[given:]
            )
            failed: Exception | None = None
            try:
                lone = len(drawn) - given == 1  # a lone scan, as a list: walked in parts on all the threads
                for outcome in self._threads.fuse_iter(list(scans) if lone else scans):
                    given += 1
                    yield outcome
            except Exception as exc:  # noqa: BLE001 - counted and logged with its traceback (_count_outcome)
                failed = exc  # (the scan whose turn it was; an InputError: a geometry no fusion takes)
            if failed is not None:
                given += 1
                yield failed

    def _count_outcome(self, scan: LaserScan, outcome: FuseResult | Exception) -> list[TileKey]:
        """Count how fusing ``scan`` went (fused; refused, an InputError; failed, another error, logged with its
        traceback); the tiles it changed."""
        if isinstance(outcome, InputError):
            self.discarded[scan.robot] += 1
            self.rejects.count(f"fuse/{scan.robot}", "input", f"scan seq {scan.seq} could not be fused: {outcome}")
            return []
        if isinstance(outcome, Exception):
            self.discarded[scan.robot] += 1
            self.log.error(
                "scan seq %d of robot %r failed to fuse; the shard goes on", scan.seq, scan.robot, exc_info=outcome
            )
            self.rejects.count(
                f"fuse/{scan.robot}", "error", f"scan seq {scan.seq} failed: {type(outcome).__name__}: {outcome}"
            )
            return []
        self.fused[scan.robot] += 1
        self.cells_updated += outcome.cells_updated
        for tile, window in zip(outcome.tiles_changed, outcome.windows, strict=True):
            self._changed(tile, window)
            self._last_scan[tile] = (scan.robot, scan.seq)
        return outcome.tiles_changed

    # ------------------------------------------------------------------------------- progress
    def settle(self) -> None:
        """Once a robot's stream has ended and no scan or pose of it has been taken for SETTLE_AFTER s, settle it
        (:meth:`services.state.join.JoinBuffer.settle`): a message held past a gap is taken, the scans after the last
        one seen (lost in transit with the end of the stream, say while this shard was cut off) and the scans still
        waiting for a pose (lost too, or the SLAM node gave up on the last steps: a pose stream has no end mark)
        are given up. Counted as discarded, so the shard catches up. (The end of a stream can overtake its last
        scans on the way in, so it is not taken as proof that they are lost.)"""
        now = self._clock()
        quiet = [r for r in self._unsettled if r not in self._tails_asked and now - self._heard[r] > TAIL_AFTER]
        for robot in quiet:
            self._tails_asked.add(robot)
            self._take_tails(robot)
        for robot in [r for r in self._unsettled if now - self._heard[r] > SETTLE_AFTER]:
            self._unsettled.discard(robot)
            self._tails_asked.discard(robot)
            pairs, gone = self._join.settle(robot, self.ended[robot])
            self._give_up(gone)
            self._ready_to_fuse(pairs)
        self.fuse_ready()

    def _take_tails(self, robot: str) -> None:
        """Take the ended robot's scans and poses after the last seq each stream has passed, up to its end, from the
        histories, as if they had come (a router restart lost them and the end came after: without this they waited
        for :meth:`settle` SETTLE_AFTER s later); nothing is given up here."""
        if self._history is None:
            return
        found: list[tuple[str, ScanOrPose]] = []
        for is_scan, stream in ((True, keys.SCAN), (False, keys.POSE)):
            first, last = self._join.passed(robot, is_scan) + 1, self.ended[robot] - 1
            if first <= last:
                found += [
                    (keys.robot_key(robot, stream), m) for m in self._recover(robot, is_scan, first, last).values()
                ]
        heard = self._heard[robot]
        for key, message in sorted(found, key=lambda item: item[1].seq):  # (a seq's scan and pose together)
            self.take(key, message, from_history=True, defer=True)
        self._heard[robot] = heard  # (what the histories gave is no news: the streams settle when they would have)

    def caught_up(self) -> bool:
        """Whether every ended stream has all its scans fused or discarded."""
        return bool(self.ended) and all(self.fused[r] + self.discarded[r] >= n for r, n in self.ended.items())

    def stats(self, overflow: dict[str, int], persist: PersistReport = NO_STORE) -> ShardStats:
        """This shard's statistics; ``overflow`` counts the intake queue's drops and ``persist`` says how its store
        does (both kept by the caller)."""
        cfg = self.config
        return ShardStats(
            map=cfg.map_name,
            shard=cfg.shard,
            shards=cfg.shards,
            tiles_owned=len(self.grid.keys()),
            cells_updated=self.cells_updated,
            tile_updates=self.tile_updates,
            join_pending=len(self._join),
            uptime=time.monotonic() - self.started,
            fused=dict(self.fused),
            discarded=dict(self.discarded),
            ended=dict(self.ended),
            received=dict(self.received),
            resent=dict(self.resent),
            rejected=self.rejects.snapshot(),
            overflow={**overflow, "join": self.join_overflow},
            refused=self.rejects.kinds(),
            persist=persist.state,
            committed=persist.committed,
            commit_age=persist.age,
        )

    # ------------------------------------------------------------------------------- durable state
    def batch(self) -> Batch:
        """What a commit of the journal's changes writes (services.state.store): copies of the tiles changed, every
        robot's counts, the new ledger entries; the journal starts afresh."""
        journal = self.journal
        assert journal is not None  # (a shard with a store keeps one)
        changed, ledger, changes = journal.take()
        tiles = []
        for key in changed:
            logodds, variance, observed = self.grid.tile_arrays(key)
            robot, seq = self._last_scan.get(key, (SEED_ROBOT, 0))
            tiles.append(TileState(key, logodds.copy(), variance.copy(), observed.copy(), robot, seq))
        robots = [
            RobotState(r, self.fused[r], self.discarded[r], self.ended.get(r), journal.high.get(r, -1) + 1)
            for r in sorted({*self.fused, *self.discarded, *self.ended, *journal.high})
        ]
        horizon = self._fused_seqs.horizon
        keep_from = {robot: high - horizon + 1 for robot, high in journal.fused_high.items()}
        return Batch(tiles, robots, ledger, keep_from, self.cells_updated, changes)

    def resume(self, state: StoredState) -> None:
        """Start from a store's state: its tiles (published again once the shard is up), and for each robot of its
        session the counts, the digests of the seqs fused and the seq its streams go on after; a robot whose stream
        had ended is settled again (what the histories still hold of it is taken, the rest given up)."""
        for tile in state.tiles:
            self.grid.set_tile(tile.key, tile.logodds, tile.variance, tile.observed)
            self._last_scan[tile.key] = (tile.robot, tile.seq)
            self._changed(tile.key)
        for entry in state.ledger:
            self._fused_seqs.mark(entry.robot, entry.seq, (entry.scan, entry.pose))
        now = self._clock()
        for robot in state.robots.values():
            name = robot.robot
            self._robots.add(name)
            for counter, count in ((self.fused, robot.fused), (self.discarded, robot.discarded)):
                if count:
                    counter[name] = count
            if robot.ended is not None:
                self.ended[name] = robot.ended
                self._heard[name] = now
                self._unsettled.add(name)
            if robot.next_seq > 0:
                self._join.start_after(name, robot.next_seq - 1)
        self.cells_updated = state.cells_updated
        if self.journal is not None:
            self.journal.resumed(state)

    def resume_points(self) -> dict[str, int]:
        """By robot this shard resumed: the seq its streams go on from (every seq below is fused or given up)."""
        if self.journal is None:
            return {}
        return {robot: high + 1 for robot, high in self.journal.high.items()}

    def seed(self, tiles: dict[TileKey, tuple[np.ndarray, np.ndarray, np.ndarray]]) -> int:
        """Start from an exported map's tiles (services.state.store.journal.tiles_of_map) as a prior: those this
        shard owns replace its own; returns how many."""
        owned = [key for key in tiles if self.owns(*key)]
        for key in owned:
            self.grid.set_tile(key, *tiles[key])
            self._last_scan[key] = (SEED_ROBOT, 0)
            self._changed(key)
        if self.journal is not None and owned:
            self.journal.noted(self._clock(), owned)
        return len(owned)

    # ------------------------------------------------------------------------------- tiles
    def tiles(self) -> list[TileKey]:
        return self.grid.keys()

    def tile_snapshot(self, tile: TileKey) -> TileSnapshot:
        """A copy of the whole tile's layers and the fields of its reply (:func:`whole_tile` makes the reply, a tile
        query's): taken while the shard's lock is held, about 0.04 ms a 256-cell tile, where making the reply takes 0.3
        (and encoding it 0.5, done after either way)."""
        logodds, variance, observed = (np.array(layer) for layer in self.grid.tile_arrays(tile))
        return TileSnapshot((logodds, variance, observed), self._update_fields(tile, 0, 0))

    def _update_fields(self, tile: TileKey, row0: int, col0: int) -> dict[str, Any]:
        """A TileUpdate's fields but its window's size and cells: its tile, map, shard, window origin and last scan."""
        robot, seq = self._last_scan[tile]
        return dict(
            map=self.config.map_name,
            shard=self.config.shard,
            z=0,
            tx=tile[0],
            ty=tile[1],
            tile_size=self.grid.tile_size,
            resolution=self.grid.resolution,
            row0=row0,
            col0=col0,
            robot=robot,
            seq=seq,
            published=time.time(),
        )

    def due_updates(self, now: float, flush: bool = False) -> tuple[list[TileUpdate], float | None]:
        """The updates of the tiles :meth:`due_tiles` gives (:meth:`take_update`), and when the next held-back tile
        falls due."""
        due, next_due = self.due_tiles(now, flush)
        updates = [self.take_update(tile, window, now) for tile, window in due]
        return [update for update in updates if update is not None], next_due

    def due_tiles(self, now: float, flush: bool = False) -> tuple[list[tuple[TileKey, TileWindow]], float | None]:
        """The changed tiles whose last update is at least publish_interval old (all with ``flush``), each with the
        window that holds its changes (row0, col0, rows, cols: the fusions' windows of the cells they updated,
        mapping.tile_boxes, joined; the whole tile for one set whole from a store or a seed), no longer held as
        changed; and the monotonic time the next held-back tile falls due (None when none is held back). Their
        updates are made by :meth:`take_update`, one by one, so that a caller can send each while it makes the
        next."""
        due, next_due = [], None
        for tile, window in list(self._dirty.items()):
            at = self._last_sent.get(tile, -np.inf) + self.config.publish_interval
            if not flush and now < at:
                next_due = at if next_due is None else min(next_due, at)
                continue
            del self._dirty[tile]
            due.append((tile, window))
        return due, next_due

    def take_update(self, tile: TileKey, window: TileWindow, now: float) -> TileUpdate | None:
        """The update of a due ``tile`` (:meth:`due_tiles`): the cells one of whose values changed since it was last
        published, and of each the values that changed (mapping.grid's changed cells, looked for in ``window``), in
        the smallest window that holds them; None when none of its cells changed (it is not published). ``now``:
        the monotonic time it is sent, s."""
        cells = self.grid.take_changes(tile, window)
        if cells is None:
            return None  # (every cell the fusions updated kept its values: clamped, with no spread)
        fields = self._update_fields(tile, cells.window[0], cells.window[1])
        logodds, variance = (cells.logodds_cells, cells.logodds), (cells.variance_cells, cells.variance)
        self._last_sent[tile] = now
        self.tile_updates += 1
        return TileUpdate.of_cells(cells.given, cells.observed, logodds, variance, **fields)

    def _changed(self, tile: TileKey, window: TileWindow | None = None) -> None:
        """Note that ``window`` (row0, col0, rows, cols; default the whole tile) of ``tile`` changed: the tile's
        window due for publication grows to hold it."""
        size = self.grid.tile_size
        window = window or (0, 0, size, size)
        held = self._dirty.get(tile)
        self._dirty[tile] = window if held is None else join_windows(held, window)
