"""`posegrid mapper --shard I --shards N`: one map shard as a Zenoh process.

Subscribes to every robot's scans, poses and end-of-stream marks (pg/*/scan, pg/*/pose, pg/*/end), fuses
the cells of the tiles it owns (services.state.shard), publishes tile updates at a bounded rate on
pg/map/<map>/tile/0/<tx>/<ty>, answers tile queries (pg/map/<map>/tile/**, whole tiles) and stats queries
(pg/map/<map>/stats/<I>), and holds the liveliness token pg/map/<map>/alive/<I> while it is up.

With a state directory (``--state-dir``, docs/persistence.md) the shard starts from its store (services.state.store),
takes from the histories only what came after it, and commits its changes there on a writer thread of its own
(services.state.store.writer), everything when it stops.

Threads: Zenoh callbacks only copy payloads into a bounded intake queue (services.intake: a full queue drops
the message and counts it, never silently) or answer queries; one main thread decodes, fuses and publishes. With
``--threads T`` > 1 the main thread takes up to TAKEN_PER_THREAD * T messages that wait in the queue at once (never
waiting for more) and fuses the pairs they complete together, their walks on T fusion threads
(mapping.parallel_fusion); the map is the one the scans give fused one by one. A lock serialises the main thread
and the tile queries around the shard's state; the main thread lets it go while it waits for a history's answer
(up to 35 s), so tile queries never wait on the network, and hands it to the tile queries waiting for it after
each scan of a batch (services.handoff_lock), so a query waits for one scan's fusion, not the batch's. Stats queries
are answered from a snapshot the main thread refreshes after every message, or messages taken at once (and at least
every 0.2 s), so they never wait for a scan's fusion (15 to 20 ms): the source's flow control and the HTTP API poll
them.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import zenoh

from schemas.messages import TileUpdate
from services import history, keys
from services.handoff_lock import HandoffLock
from services.intake import DEFAULT_CAPACITY, Intake
from services.process import RejectCounter, Stopped, get_logger, until_stopped
from services.state.shard import SHARD_STREAMS, MapShard, ShardConfig, whole_tile
from services.state.store.db import ShardStore, StoredState, StoreError, StoreIdentity
from services.state.store.journal import Journal, tiles_of_map
from services.state.store.writer import DEFAULT_COMMIT_INTERVAL, DEFAULT_COMMIT_SCANS, NO_STORE, Persister
from services.zenoh_config import close_session, open_session, undeclare_all

#: messages that may wait in the intake queue between the network and the fusion thread
DEFAULT_INTAKE_CAPACITY = DEFAULT_CAPACITY
#: s to wait for the histories of scans and poses that never reached the shard (it waits meanwhile)
HISTORY_TIMEOUT = 5.0
#: how long a robot's histories are not asked again after a question that no one answered before HISTORY_TIMEOUT
#: (s): the question waits on the shard's main thread, and a peer that declares a history and never answers (a
#: stranger robot's gaps, one per 2 scans) held every robot's fusion for 5 s a gap
HISTORY_QUIET = 30.0
#: s: the timeout of a question while the questions no history answered have held the shard HISTORY_TIMEOUT s or
#: more in the last HISTORY_QUIET s (a peer's silent histories under robot name after robot name held every robot's
#: fusion for good); robots whose histories have never answered this shard are not asked at all then
HISTORY_SHORT_TIMEOUT = 1.0
#: robots a shard remembers as having had their histories answer it
MAX_ANSWERED_ROBOTS = 4096
#: s to wait at startup for the histories of every robot's run so far
CATCH_UP_TIMEOUT = 60.0
#: s to wait for the liveliness tokens of the robots' processes (which robots a resumed shard asks the histories of)
ROBOTS_TIMEOUT = 2.0
#: messages the main thread takes from the intake queue at once per fusion thread (a scan and its pose per pair:
#: eight scans a thread to walk). A batch ends with its last walks and applies while a thread idles, then the tile
#: updates with every thread idle: on the warehouse (1081 beams, 100 particles) one shard of two threads fused 1.24 to
#: 1.35x the in-process rate taking two scans a thread, 1.45 to 1.56x taking eight (docs/performance.md, "Threads"),
#: so a backlog drains faster; a tile query waits for the scan under way, not the batch (services.handoff_lock)
TAKEN_PER_THREAD = 16


@dataclass(frozen=True)
class PersistOptions:
    """A shard's durable state (docs/persistence.md): its state directory (None: the map lives in memory only), the
    session it writes (None: the store's latest, or a new one), a commit at least every ``commit_scans`` scans or
    ``commit_interval`` s, the most bytes its database may take (None: no limit), and an exported map to start from
    (``load``: its tiles this shard owns, as a prior)."""

    state_dir: Path | None = None
    session: str | None = None
    commit_scans: int = DEFAULT_COMMIT_SCANS
    commit_interval: float = DEFAULT_COMMIT_INTERVAL
    max_bytes: int | None = None
    load: Path | None = None
    run_id: str | None = None  # the `posegrid run` the store belongs to (None: not checked)


@dataclass
class Durable:
    """A shard's opened store, what it held, and the map to seed from (:meth:`open`)."""

    options: PersistOptions
    store: ShardStore | None
    stored: StoredState | None
    seed: dict | None  # tiles of --load

    @classmethod
    def open(cls, config: ShardConfig, options: PersistOptions) -> Durable:
        """Open the store and read --load; StoreError (or a map file's FormatError) says why they cannot be used."""
        store = stored = None
        if options.state_dir is not None:
            identity = StoreIdentity(
                config.map_name, config.shard, config.shards, config.tile_size, config.model.resolution
            )
            store = ShardStore.open(options.state_dir, identity, options.session, options.max_bytes, options.run_id)
            try:
                stored = store.load()
            except BaseException:
                store.close()
                raise
        seed = None
        if options.load is not None:
            try:
                seed = _seed_tiles(config, options.load, stored)
            except BaseException:
                if store is not None:
                    store.close()
                raise
        return cls(options, store, stored, seed)


def _seed_tiles(config: ShardConfig, path: Path, stored: StoredState | None) -> dict:
    """The tiles of the exported map ``path`` (every tile; the shard takes those it owns); StoreError when the store
    holds a map already or the map does not fit the shard's grid."""
    from schemas.files import load_map

    if stored is not None and (stored.tiles or stored.robots):
        raise StoreError(
            f"--load {path} seeds a new map, but the state directory holds one already ({len(stored.tiles)} tiles); "
            "leave out --load to resume it"
        )
    return tiles_of_map(load_map(path), config.model.resolution, config.tile_size, str(path))


class Mapper:
    """A running shard: Zenoh declarations around a :class:`MapShard`. Use :meth:`run`."""

    def __init__(
        self,
        config: ShardConfig,
        session: zenoh.Session,
        stop: threading.Event,
        intake_capacity: int = DEFAULT_INTAKE_CAPACITY,
        durable: Durable | None = None,
    ):
        self.config = config
        self.session = session
        self.stop = stop  # set when the process is asked to stop (services.process.install_stop_event)
        self.log = get_logger(f"mapper[{config.shard}]")
        self.rejects = RejectCounter(self.log)
        self.shard = MapShard(config, self.rejects, history=self._history)
        self.persister = None if durable is None else self._start_from(durable)
        self.lock = HandoffLock()  # (the main thread's over a batch; a tile query's between two scans)
        self.shard.handoff = self.lock
        self.intake = Intake(SHARD_STREAMS, self.rejects, config.limits, capacity=intake_capacity)
        self._declared: list = []  # what declare() declared, undeclared in reverse order
        self._stats_lock = threading.Lock()  # guards _stats_payload only
        self._stats_payload = b""
        self._history_quiet: dict[str, float] = {}  # robot -> time.monotonic() until which it is not asked
        self._silent: deque[tuple[float, float]] = deque()  # (when, s waited) of questions no history answered
        self._answered: set[str] = set()  # robots whose histories gave this shard a message

    def _start_from(self, durable: Durable) -> Persister | None:
        """Resume the shard from its store and seed it from --load; the persister of the store (None without one)."""
        persister = None
        if durable.store is not None:
            assert durable.stored is not None  # (loaded with the store)
            stored, options = durable.stored, durable.options
            self.shard.journal = Journal()
            self.shard.resume(stored)
            persister = Persister(durable.store, options.commit_scans, options.commit_interval, self.log)
            persister.resumed(stored)
            scans = sum(r.fused + r.discarded for r in stored.robots.values())
            given_up = sum(r.discarded for r in stored.robots.values())
            self.log.info(
                "state in %s, session %s: %s",
                durable.store.path,
                stored.session,
                f"resumed {len(stored.tiles)} tile(s) and {scans} scan(s) of {len(stored.robots)} robot(s)"
                + (f", of those scans {given_up} given up (not in the map)" if given_up else "")
                if stored.tiles or stored.robots
                else "a new map",
            )
        if durable.seed is not None:
            owned = self.shard.seed(durable.seed)
            self.log.info(
                "started from %s: %d of its %d tile(s) are this shard's", durable.options.load, owned, len(durable.seed)
            )
        return persister

    # ---------------------------------------------------------------------------- zenoh callbacks
    def _on_tile_query(self, query: zenoh.Query) -> None:
        wanted = query.key_expr
        with self.lock.waiter():  # (let in between two scans of a batch: HandoffLock; copies only, the replies after)
            snapshots = [
                self.shard.tile_snapshot(tile)
                for tile in self.shard.tiles()
                if wanted.intersects(keys.tile_key(self.config.map_name, 0, *tile))
            ]
        for message in map(whole_tile, snapshots):
            query.reply(keys.tile_key(self.config.map_name, 0, message.tx, message.ty), message.encode())

    def _on_stats_query(self, query: zenoh.Query) -> None:
        with self._stats_lock:
            payload = self._stats_payload
        query.reply(keys.stats_key(self.config.map_name, self.config.shard), payload)

    def _refresh_stats(self) -> None:
        """Snapshot the shard's stats for the stats queries (main thread, holding ``lock``)."""
        persist = NO_STORE if self.persister is None else self.persister.report()
        payload = self.shard.stats({"intake": self.intake.overflow}, persist).encode()
        with self._stats_lock:
            self._stats_payload = payload

    def _taken_at_once(self) -> int:
        """How many messages the main thread takes before it fuses what they complete (1 with one fusion thread)."""
        threads = self.config.threads
        return 1 if threads == 1 else TAKEN_PER_THREAD * threads

    def _handle_waiting(self, key: str, payload: bytes) -> None:
        """Handle the message (``key``, ``payload``) just taken from the intake and the ones waiting behind it, up to
        :meth:`_taken_at_once` (none is waited for), then fuse the pairs they complete together (main thread, holding
        ``lock``)."""
        limit = self._taken_at_once()
        try:
            self.shard.handle(key, payload, defer=limit > 1)
            for _ in range(limit - 1):
                try:
                    key, payload = self.intake.next(0.0)
                except queue.Empty:
                    break
                self.shard.handle(key, payload, defer=True)
        finally:
            self.shard.fuse_ready()

    def _ours(self, answerer: history.Answerer) -> bool:
        """Whether a history's answerer publishes for this shard's map (a SLAM node publishes for any): the only
        answers a shard takes when it catches up at its start, when it cannot tell a run going on from a stale one (an
        earlier run's source under the robot's name, stalled waiting for a shard it lost, gave a new map its scans)."""
        return answerer.map in (None, self.config.map_name)

    def _ours_or_live(self, answerer: history.Answerer) -> bool:
        """Whether to take a history's answers for a gap in a robot's live stream: :meth:`_ours`, or a source of
        another map that is still publishing. Every map fuses every robot's live scans, so a shard that restarted
        while another map's robot drove gave that robot's first scans up as lost (the map lacked 22 of 60); the
        robot's live scans show it is this run's, and two sources answering for it (a stale one beside the real one)
        are both refused (services.history)."""
        return self._ours(answerer) or not answerer.ended

    def _history(
        self, robot: str, stream: str, first: int, last: int, seqs: tuple[int, ...] | None = None
    ) -> list[bytes]:
        """The robot's ``stream`` messages first..last (of them only ``seqs`` when given) from the histories
        (services.history): the source's for scans (and poses of a posed-scan file), the SLAM node's for poses."""
        asked = {"streams": stream, "from": str(first), "to": str(last + 1)}
        if seqs is not None:
            asked["seqs"] = ",".join(map(str, seqs))
        began = time.monotonic()
        if began < self._history_quiet.get(robot, 0.0):
            self.rejects.count(
                keys.history_key(robot),
                "history",
                f"seqs {first}-{last} of {stream} not asked for: the robot's histories did not finish answering in "
                f"{HISTORY_TIMEOUT:g} s, so they are left alone for {HISTORY_QUIET:g} s",
            )
            return []
        silent = self._silent_seconds(began)
        if silent >= 2 * HISTORY_TIMEOUT or (silent >= HISTORY_TIMEOUT and robot not in self._answered):
            self.rejects.count(
                keys.history_key(robot),
                "history",
                f"seqs {first}-{last} of {stream} not asked for: histories that did not answer held this shard "
                f"{silent:.1f} s in the last {HISTORY_QUIET:g} s (robot {robot!r}'s have not answered it in time, or "
                f"that is twice {HISTORY_TIMEOUT:g} s)",
            )
            return []
        strained = silent >= HISTORY_TIMEOUT  # (then a short timeout and no more time for a history cut off)
        timeout = HISTORY_SHORT_TIMEOUT if strained else HISTORY_TIMEOUT
        # a far run's vouching question (seqs given, services.state.join) counts every answerer, of any map: the real
        # source of another map answers its passed seq too, so a peer answering as this map's is not alone (a
        # re-probe: a second map's shard gave up 99 892 scans)
        accept = self._ours_or_live if seqs is None else (lambda answerer: True)
        with self._lock_released():
            # (more time for a history cut off as it answered only where the robot's histories have answered this
            # shard in time before: a peer's late reply under a new name bought 5 + 10 + 20 s a question)
            retry = not strained and robot in self._answered
            messages = history.ask_counted(
                self.session, robot, asked, timeout, self.rejects, accept, self.stop, retry=retry
            )
        waited = time.monotonic() - began
        # a question that ran its time out held the shard, whatever came (a re-probe: one reply and then nothing,
        # under a robot name after another, held every robot's fusion for good): the robot's histories are left
        # alone for HISTORY_QUIET s. One asked while the session reached no router or peer went nowhere, and says
        # nothing of the histories (a router restart must not leave them alone)
        if waited >= 0.9 * timeout and history.reachable(self.session):
            self._silent.append((time.monotonic(), waited))
            self._history_quiet[robot] = time.monotonic() + HISTORY_QUIET
            self._answered.discard(robot)  # (a re-probe: names that answered once, then stalled one after another)
        elif messages:
            self._remember_answered([robot])
        return [payload for _, got, payload in messages if got == stream]  # (history.ask checks the reply keys)

    def _silent_seconds(self, now: float) -> float:
        """s the questions no history answered have held this shard in the last HISTORY_QUIET s."""
        while self._silent and now - self._silent[0][0] > HISTORY_QUIET:
            self._silent.popleft()
        return sum(waited for _, waited in self._silent)

    def _remember_answered(self, robots: Iterable[str]) -> None:
        """Note that the histories of ``robots`` gave this shard messages (at most MAX_ANSWERED_ROBOTS robots)."""
        for robot in robots:
            if len(self._answered) < MAX_ANSWERED_ROBOTS:
                self._answered.add(robot)

    @contextlib.contextmanager
    def _lock_released(self) -> Iterator[None]:
        """``lock`` let go while the main thread waits on the network: the shard asks the histories from inside
        :meth:`MapShard.handle`, ``settle`` and ``take``, which the main thread runs holding it, and a question may
        wait 5 + 10 + 20 s for a history that does not finish answering; the tile queries, which read the tiles
        only, are answered meanwhile (nothing of the shard changes while it waits: the fusion runs on the main
        thread's call, after)."""
        if not self.lock.locked():
            raise RuntimeError("the shard asked a history outside the main thread's hold of its lock")
        self.lock.release()
        try:
            yield
        finally:
            self.lock.acquire()

    def catch_up(self) -> None:
        """Take every robot's scans and poses published before this shard subscribed, from the histories
        (services.history), in seq order (:meth:`MapShard.in_seq_order`), as if they had arrived live: a shard
        that starts late or restarts builds the map of the run so far. It otherwise waits for a gap to show, and
        none shows while a source holds back for the shards (``--rate max``) or has ended. Stats are refreshed as
        it goes (the source's flow control reads them). Nothing happens when nobody answers. A shard resumed from its
        store asks only for what comes after its ledger (:meth:`_resumed_replies`)."""
        starts = self.shard.resume_points()
        if starts:
            replies = self._resumed_replies(starts)
        else:
            asked = {"streams": f"{keys.SCAN},{keys.POSE}"}
            replies = history.ask_counted(
                self.session, "*", asked, CATCH_UP_TIMEOUT, self.rejects, self._ours, self.stop
            )
        self._remember_answered({robot for robot, _, _ in replies})
        with self.lock:
            taken = self.shard.in_seq_order(
                (keys.robot_key(robot, stream), payload) for robot, stream, payload in replies
            )
        chunk = self._taken_at_once()
        for first in range(0, len(taken), chunk):
            if self.stop.is_set():  # (what is fused so far is committed as the shard stops)
                self.log.info("stopped taking the histories after %d of %d message(s)", first, len(taken))
                return
            with self.lock:
                try:
                    for key, message in taken[first : first + chunk]:
                        self.shard.take(key, message, from_history=True, defer=chunk > 1)
                finally:
                    self.shard.fuse_ready()
                if self.persister is not None:
                    self.persister.step(self.shard)
                self._refresh_stats()
        if replies:
            scans = sum(stream == keys.SCAN for _, stream, _ in replies)
            self.log.info(
                "took %d scan(s) and %d pose(s) published before this shard was up from the histories",
                scans,
                len(replies) - scans,
            )

    def _resumed_replies(self, starts: dict[str, int]) -> list[tuple[str, str, bytes]]:
        """The histories' scans and poses of each robot from the seq its streams resume at (``starts``; 0 for a robot
        the store does not know whose source or SLAM node is alive), robot by robot."""
        robots = dict.fromkeys(self._robots_alive(), 0) | starts
        replies = []
        for robot, first in sorted(robots.items()):
            asked = {"streams": f"{keys.SCAN},{keys.POSE}", "from": str(first)}
            replies += history.ask_counted(
                self.session, robot, asked, CATCH_UP_TIMEOUT, self.rejects, self._ours, self.stop
            )
        return replies

    def _robots_alive(self) -> set[str]:
        """The robots whose source or SLAM node holds its liveliness token (pg/<robot>/alive/<process>)."""
        robots = set()
        for reply in self.session.liveliness().get(keys.robot_alive_key("*", "*"), timeout=ROBOTS_TIMEOUT):
            parsed = keys.parse_process_alive_key(str(reply.ok.key_expr)) if reply.ok is not None else None
            if parsed is not None:
                robots.add(parsed[0])
        return robots

    # ---------------------------------------------------------------------------- lifecycle
    def declare(self) -> None:
        """Subscribers and queryables first, the liveliness token last: once a source sees the token,
        this shard already receives what it publishes."""
        session, name = self.session, self.config.map_name
        self._declared.append(self.intake.subscribe(session))  # (one for every stream: services.intake)
        self._declared.append(session.declare_queryable(keys.tiles_key(name), self._on_tile_query))
        self._declared.append(session.declare_queryable(keys.stats_key(name, self.config.shard), self._on_stats_query))
        self._declared.append(session.liveliness().declare_token(keys.shard_alive_key(name, self.config.shard)))

    def run(self) -> int:
        """Fuse and publish until the stop flag is set; returns the exit code (0). The liveliness token is
        declared once the kernels are warm, so whoever waits for it sees the shard's steady latency. Stopped while
        the kernels load (a compile, on a fresh install) or a question to the histories waits (the router gone
        first), it leaves the store as a crash would: what was committed stays, and the histories give the rest on
        the next start."""
        cfg = self.config
        try:
            # (a minute of compiling on a fresh install)
            until_stopped(self.shard.warm_up, self.stop, "loading the fusion kernels")
            with self.lock:
                self._refresh_stats()
            self.declare()
            self.log.info(
                "shard %d of %d of map %r up; tiles on %s",
                cfg.shard,
                cfg.shards,
                cfg.map_name,
                keys.tile_key(cfg.map_name, 0, "*", "*"),
            )
            self.catch_up()
            self._serve()
        except Stopped as exc:
            self._undeclare()
            if self.persister is None:
                self.log.info("%s", exc)
            else:
                self.log.info("%s; the store keeps its last commit", exc)
                self.persister.abandon()
            return 0
        self._undeclare()
        self.log.info("stopped after fusing %d scans", sum(self.shard.fused.values()))
        if self.persister is not None and not self.persister.finish(self.shard):
            self.log.error("the last changes could not be committed (%s)", self.persister.failing)
            return 1
        return 0

    def _serve(self) -> None:
        """Take messages from the intake, fuse them and publish the tiles due, until the stop flag is set."""
        cfg = self.config
        next_due = None
        while not self.stop.is_set():
            timeout = 0.2 if next_due is None else min(0.2, max(0.0, next_due - time.monotonic()))
            try:
                key, payload = self.intake.next(timeout)
            except queue.Empty:
                pass
            else:
                with self.lock:
                    self._handle_waiting(key, payload)
            with self.lock:
                self.shard.settle()
                if self.persister is not None:
                    self.persister.step(self.shard)
                self._refresh_stats()
                flush = self.shard.caught_up() and self.intake.empty()
                now = time.monotonic()
                due, next_due = self.shard.due_tiles(now, flush=flush)
            for tile, window in due:  # each sent as soon as it is made: the next made while zenoh carries it
                with self.lock:
                    update = self.shard.take_update(tile, window, now)
                if update is not None:
                    self.session.put(
                        keys.tile_key(cfg.map_name, 0, update.tx, update.ty),
                        sent_payload(update),
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )

    def _undeclare(self) -> None:
        undeclare_all(self._declared)


def sent_payload(update: TileUpdate, clock: Callable[[], float] = time.time) -> bytes:
    """``update`` encoded as it is sent, its ``published`` the Unix time now (s, ``clock``): a warehouse scan's 22
    updates take 10 to 15 ms to make, encode and put one after the other (docs/performance.md, "Over Zenoh"), so
    the time the shard fused their scan is not when they were sent."""
    return replace(update, published=clock()).encode()


def run_mapper(
    config: ShardConfig,
    zenoh_config: zenoh.Config,
    stop: threading.Event,
    intake_capacity: int = DEFAULT_INTAKE_CAPACITY,
    persist: PersistOptions | None = None,
) -> int:
    """Open the shard's store (``persist``; StoreError before anything else when it cannot be used) and a session,
    and run one shard until ``stop`` is set."""
    durable = None if persist is None else Durable.open(config, persist)
    try:
        session = open_session(zenoh_config, f"mapper shard {config.shard}", stop)
    except BaseException:
        if durable is not None and durable.store is not None:
            durable.store.close()
        raise
    try:
        return Mapper(config, session, stop, intake_capacity, durable).run()
    finally:
        close_session(session, f"mapper shard {config.shard}")
