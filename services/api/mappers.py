"""The API's Zenoh side: what it subscribes to and what it asks the mapper shards (docs/keys.md).

Subscriptions (callbacks run on Zenoh's threads and only record; they never query):
- liveliness pg/map/*/alive/*: which shards of which maps are up. A token only makes its shard pending: the
  shard is alive once it has answered its stats query (pg/map/<map>/stats/*) with valid stats for that map and
  index (shard < shards), and a map is known once a shard of it is. A thread of this class asks the pending
  shards, at once and then every VERIFY_INTERVAL s; a token still unproved after ``verify_window`` s is
  forgotten and counted as rejected (kind "unverified"), so a peer's made-up token lists no map;
- liveliness pg/*/alive/*: which robot processes (source, SLAM node) are up; a robot with such a token is
  vouched for (services.api.robots.RobotTracker);
- pg/map/*/tile/0/*/*: tile updates; each gives its level-0 tile a new version (services.api.registry)
  and a ``tiles`` event; the window's values are not kept (the tile is asked for when someone wants it);
- pg/*/pose: pose distributions, for /robots and ``pose`` events.

Queries (from HTTP handler threads): one level-0 tile (pg/map/<map>/tile/0/<tx>/<ty>; only the owning
shard answers), all tiles of a map (pg/map/<map>/tile/0/*/*), the shards' stats, the whole map for export
(services.map_client.MapReader).

Whatever arrives is decoded and validated (schemas.messages); a message that does not decode, or whose
contents contradict its key, is dropped and counted by key in :attr:`MapperLink.rejects`, never trusted.
"""

from __future__ import annotations

import contextlib
import math
import queue
import threading
import time
from collections import Counter
from collections.abc import Iterator

import numpy as np
import zenoh

from mapping.grid import TiledGrid
from schemas.messages import POSE_TYPES, MessageError, ShardStats, TileUpdate, decode_message
from services import history, keys
from services.api.events import EventHub
from services.api.limits import MAX_PROCESSES, VERIFY_WINDOW, Tally
from services.api.registry import MapRegistry, TileKey
from services.api.robots import TRAJECTORY_LENGTH, PoseRefused, RobotTracker, trajectory_row
from services.map_client import MapReader, sort_answers
from services.process import RejectCounter, Stopped, get_logger
from services.zenoh_config import is_timeout_reply, replier, undeclare_all

#: s to wait for the shards' stats: a shard answers them from its Zenoh thread in milliseconds, and /health, which
#: asks for them, must answer while a stalled shard is still alive to the router (up to its Zenoh lease)
STATS_TIMEOUT = 2.0
#: s between two rounds of asking the pending shards for their stats
VERIFY_INTERVAL = 1.0
#: s between two fetches of every shard's tiles that a shard's tile of another geometry asks for (a shard left on
#: another --resolution keeps publishing: each of its updates would otherwise make the next request fetch the map)
CONFLICT_RESYNC_INTERVAL = 10.0


#: robots whose trajectories wait to be filled from their histories (a robot past it is filled by none)
BACKFILL_QUEUE = 1024
#: bytes of a robot's earlier poses one fill takes from its histories (a SLAM node keeps 64 MiB of them)
BACKFILL_BYTES = 64 << 20
#: bytes of one reply the API takes: a whole tile of the largest size (1 024 x 1 024 cells, 9 bytes a cell) with room
MAX_REPLY_BYTES = 16 << 20


class MapperLink:
    """Subscriptions and queries on an open Zenoh session. Call :meth:`start`, later :meth:`close`."""

    def __init__(
        self,
        session: zenoh.Session,
        registry: MapRegistry,
        robots: RobotTracker,
        hub: EventHub,
        query_timeout: float = 10.0,
        verify_window: float = VERIFY_WINDOW,
    ) -> None:
        self.session = session
        self.registry = registry
        self.robots = robots
        self.hub = hub
        self.query_timeout = query_timeout
        self.verify_window = verify_window
        self.log = get_logger("api")
        self.rejects = RejectCounter(self.log)
        self.refused = Tally()  # tokens and poses refused because a limit was reached, by what
        self.processes: set[str] = set()  # "<robot>/<process>" whose liveliness token is up
        self._declared: list = []
        self._wake, self._stopping = threading.Event(), threading.Event()
        self._verifier: threading.Thread | None = None
        self._conflict_synced: dict[str, float] = {}  # map -> time.monotonic() a conflict last asked for a fetch
        # (robot, seq of the first pose taken): trajectories to fill from the histories, on a thread of their own
        self._backfills: queue.Queue[tuple[str, int]] = queue.Queue(maxsize=BACKFILL_QUEUE)
        self._backfiller: threading.Thread | None = None

    # ---------------------------------------------------------------------------- subscriptions
    def start(self) -> None:
        """Declare the subscriptions, then read the liveliness tokens already up (so the maps and shards
        alive are known before the first request)."""
        liveliness = self.session.liveliness()
        shard_tokens, process_tokens = keys.shard_alive_key("*", "*"), keys.robot_alive_key("*", "*")
        self._declared += [
            liveliness.declare_subscriber(shard_tokens, self._guard(self._on_shard_token)),
            liveliness.declare_subscriber(process_tokens, self._guard(self._on_process_token)),
            self.session.declare_subscriber(keys.tile_key("*", 0, "*", "*"), self._guard(self._on_tile_update)),
            self.session.declare_subscriber(keys.robot_key("*", keys.POSE), self._guard(self._on_pose)),
        ]
        for key, callback in ((shard_tokens, self._on_shard_token), (process_tokens, self._on_process_token)):
            for reply in liveliness.get(key, timeout=self.query_timeout):
                if reply.ok is not None:
                    self._guard(callback)(reply.ok)
        self.verify_pending()
        self._verifier = threading.Thread(target=self._verify_loop, daemon=True, name="api-verify")
        self._verifier.start()
        self._backfiller = threading.Thread(target=self._backfill_loop, daemon=True, name="api-backfill")
        self._backfiller.start()

    def close(self) -> None:
        self._stopping.set()
        self._wake.set()
        with contextlib.suppress(queue.Full):
            self._backfills.put_nowait(("", 0))  # (wakes the backfiller to see the stop)
        for thread in (self._verifier, self._backfiller):
            if thread is not None:
                thread.join()
        undeclare_all(self._declared)

    def _backfill_loop(self) -> None:
        """Fill each new robot's trajectory with the poses before its first one this API took, from its histories
        (the SLAM node's: services.state.pose_history), one robot at a time."""
        while not self._stopping.is_set():
            robot, first = self._backfills.get()
            if self._stopping.is_set():
                return
            try:
                self._backfill(robot, first)
            except Stopped:
                return
            except Exception:  # the thread must outlive any one robot's question (logged, not swallowed)
                self.log.exception("filling the trajectory of robot %r from its histories failed", robot)

    def _backfill(self, robot: str, first: int) -> None:
        """Ask the robot's histories for the poses before ``first`` that its trajectory has room for, at most
        BACKFILL_BYTES of them (a re-probe: 6 000 poses of 10 000 samples each took the API to 3.9 GB), and put them
        at the start of its trajectory: each seq once, in order (a seq two replies give differently is left out)."""
        asked = {"streams": keys.POSE, "from": str(max(0, first - TRAJECTORY_LENGTH)), "to": str(first)}
        messages = history.ask_counted(
            self.session, robot, asked, self.query_timeout, self.rejects, stop=self._stopping, max_bytes=BACKFILL_BYTES
        )
        rows: dict[int, tuple[int, float, float, float, float] | None] = {}  # seq -> row (None: given two ways)
        for _, _, payload in messages:
            try:
                message = decode_message(payload, *POSE_TYPES)
            except MessageError as exc:
                self.rejects.count(keys.history_key(robot), exc.reason, str(exc))
                continue
            if message.robot == robot and first - TRAJECTORY_LENGTH <= message.seq < first:
                row = trajectory_row(message)
                rows[message.seq] = row if rows.get(message.seq, row) == row else None
        twice = sorted(seq for seq, row in rows.items() if row is None)
        if twice:
            self.rejects.count(
                keys.history_key(robot),
                "history",
                f"{len(twice)} pose seq(s) of robot {robot!r} (the first {twice[0]}) given two ways by its histories; "
                "left out of its trajectory",
            )
        kept = [row for _, row in sorted(rows.items()) if row is not None]
        taken = self.robots.backfill(robot, np.array(kept, float).reshape(-1, 5))
        if taken:
            self.log.info("robot %r: %d earlier pose(s) of its trajectory taken from its histories", robot, taken)

    def _verify_loop(self) -> None:
        """Ask the pending shards for their stats when a token appears and every VERIFY_INTERVAL s while some
        wait; forget the tokens unproved for longer than ``verify_window``."""
        while not self._stopping.is_set():
            self._wake.wait(VERIFY_INTERVAL)
            self._wake.clear()
            if not self._stopping.is_set():
                try:
                    self.verify_pending()
                except Exception:  # the thread must outlive any one round (logged, not swallowed)
                    self.log.exception("verifying shard tokens failed; trying again")

    def verify_pending(self) -> None:
        """One round: the stats of every map with pending shards, asked at once (proving the shards that answer),
        then the expiry of the tokens pending too long."""
        try:
            self.stats_of(self.registry.pending())
        except zenoh.ZError as exc:  # the session is closing
            self.log.debug("verifying shard tokens: %s", exc)
        for name, shard in self.registry.expire_pending(self.verify_window):
            self.rejects.count(
                keys.shard_alive_key(name, shard),
                "unverified",
                f"shard {shard} of map {name!r} "
                f"did not answer its stats query within {self.verify_window:g} s of its liveliness "
                "token, which is ignored",
            )

    def _guard(self, callback):
        """``callback`` with any exception counted as a rejected message instead of escaping into Zenoh."""

        def guarded(sample: zenoh.Sample) -> None:
            try:
                callback(sample)
            except Exception as exc:  # noqa: BLE001 - a bad message must never stop the subscription
                self.rejects.count(str(sample.key_expr), "error", f"{type(exc).__name__}: {exc}")

        return guarded

    def _on_shard_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parsed = keys.parse_shard_alive_key(key)
        if parsed is None:
            self.rejects.count(
                keys.INVALID_KEY, "key", f"a shard liveliness token on {key[:200]!r}, not pg/map/<map>/alive/<shard>"
            )
            return
        name, shard = parsed
        if sample.kind != zenoh.SampleKind.PUT:
            self.registry.token_down(name, shard)
            return
        refusal = self.registry.token_up(name, shard)
        if refusal is None:
            self._wake.set()
        else:
            self.refused.add("shard_tokens")
            self.rejects.count(key, "capacity", refusal)

    def _on_process_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parsed = keys.parse_process_alive_key(key)
        if parsed is None:
            if sample.kind == zenoh.SampleKind.PUT:
                self.rejects.count(
                    keys.INVALID_KEY,
                    "key",
                    f"a process liveliness token on {key[:200]!r}, not pg/<robot>/alive/<process> (a robot may not "
                    "be called map)",
                )
            return
        robot, process = parsed
        name = f"{robot}/{process}"
        if sample.kind != zenoh.SampleKind.PUT:
            self.processes.discard(name)
            return
        if len(self.processes) >= MAX_PROCESSES and name not in self.processes:
            self.refused.add("processes")
            self.rejects.count(key, "capacity", f"{MAX_PROCESSES} process liveliness tokens are held already")
        elif not self.robots.vouch(robot):
            self.refused.add("robots")
            self.rejects.count(
                key, "capacity", f"{self.robots.max_robots} robots are vouched for already (--max-robots)"
            )
        else:
            self.processes.add(name)

    def _on_tile_update(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            update = decode_message(sample.payload.to_bytes(), TileUpdate)
        except MessageError as exc:
            self.rejects.count(key, exc.reason, str(exc))
            return
        problem = (
            self._foreign_tile(key, update)
            or self.registry.check_sender(update.map, update.shard, (update.tx, update.ty))
            or self._geometry_problem(update)
        )
        if problem:
            self.rejects.count(key, "key", problem)
            return
        tile = (update.tx, update.ty)
        self.registry.update_received(update.map, update.shard)
        version = self.registry.tile_changed(update.map, tile, update.resolution, update.tile_size)
        self.hub.tile_changed(update.map, tile, version)

    def _on_pose(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            message = decode_message(sample.payload.to_bytes(), *POSE_TYPES)
        except MessageError as exc:
            self.rejects.count(key, exc.reason, str(exc))
            return
        parsed = keys.parse_robot_key(key, {keys.POSE})
        if parsed is None or message.robot != parsed[0]:
            self.rejects.count(
                key if parsed else keys.INVALID_KEY, "robot", f"a pose of robot {message.robot!r} arrived on {key}"
            )
            return
        fresh = not self.robots.tracked(message.robot)
        try:
            summary = self.robots.update(message)
        except PoseRefused as refused:
            if refused.kind == "capacity":
                self.refused.add("robots")
            self.rejects.count(key, refused.kind, str(refused))
            return
        self.hub.pose(summary)
        if fresh and message.seq > 0:  # (poses before it: the robot's histories hold them, e.g. for a restarted API)
            with contextlib.suppress(queue.Full):
                self._backfills.put_nowait((message.robot, message.seq))

    def _foreign_tile(self, key: str, update: TileUpdate) -> str | None:
        """Why ``update`` does not belong on ``key`` (None when it does): another tile's key, or a zoom level other
        than 0."""
        expected = keys.tile_key(update.map, update.z, update.tx, update.ty)
        if key != expected or update.z != 0:
            return f"a TileUpdate for {expected} arrived on {key}"
        return None

    def _geometry_problem(self, update: TileUpdate) -> str | None:
        """Why a tile from the process that answers as its shard does not fit its map (None when it does): a tile
        size or resolution other than the map's (a tile query's reply of another geometry was served as it came, and
        the coarser levels made of it failed). Kept as the map's conflict: its shards disagree. Checked only after
        the sender, so that a peer's forged tile is refused without touching the map's health."""
        why = self.registry.check_geometry(update.map, update.resolution, update.tile_size)
        if why is not None:
            self.registry.note_conflict(update.map, why)
            now = time.monotonic()  # (every shard's tiles of the new geometry: the map takes it; at most so often)
            if now - self._conflict_synced.get(update.map, -math.inf) >= CONFLICT_RESYNC_INTERVAL:
                self._conflict_synced[update.map] = now
                self.registry.request_sync(update.map)
        return why

    # ---------------------------------------------------------------------------- queries
    def _get(self, selector: str, timeout: float | None = None):
        """Send a query to every matching queryable; returns the reply handler (iterating it waits, at most
        ``timeout`` s, by default the query timeout)."""
        return self.session.get(
            selector,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=self.query_timeout if timeout is None else timeout,
        )

    def _query(self, selector: str, timeout: float | None = None) -> list[tuple[str, bytes, str]]:
        return list(self._replies(selector, self._get(selector, timeout)))

    def _replies(self, selector: str, handler) -> Iterator[tuple[str, bytes, str]]:
        """(key, payload, the sender's Zenoh session id) of each good reply as it arrives; the handler ends when
        every queryable has answered or the query timed out."""
        for reply in handler:
            if reply.ok is None:
                if is_timeout_reply(reply):  # (zenoh's own: a stalled shard did not answer in time; /health says so)
                    continue
                self.rejects.count(selector, "error_reply", "a queryable answered with an error")
            elif len(reply.ok.payload) > MAX_REPLY_BYTES:  # (dropped as it comes: a peer's 30 x 100 MB took 3.5 GB)
                size = len(reply.ok.payload)
                self.rejects.count(
                    selector, "size", f"a reply of {size} bytes, more than the {MAX_REPLY_BYTES} a tile takes"
                )
            else:
                yield str(reply.ok.key_expr), reply.ok.payload.to_bytes(), replier(reply)

    def _whole_tiles(
        self, map_name: str, replies: list[tuple[str, bytes, str]], any_geometry: bool = False
    ) -> list[TileUpdate]:
        """The replies that are whole level-0 tiles of the map, from the process that answers as their shard; of the
        map's geometry, unless ``any_geometry`` (a fetch of every tile: services.api.tiles.TileService.sync weighs
        the geometries it finds, and takes a new one that every shard holds)."""
        tiles = []
        for key, payload, sender in replies:
            try:
                update = decode_message(payload, TileUpdate)
            except MessageError as exc:
                self.rejects.count(key, exc.reason, str(exc))
                continue
            problem = self._foreign_tile(key, update)
            if not problem and update.map != map_name:
                problem = f"a tile of map {update.map!r} answered a query about map {map_name!r}"
            if not problem and not update.is_whole():
                problem = "a tile query was answered with a partial window"
            if not problem:
                problem = (
                    self.registry.check_sender(map_name, update.shard, (update.tx, update.ty))
                    or self.registry.check_answerer(map_name, update.shard, sender)
                    or (None if any_geometry else self._geometry_problem(update))
                )
            if problem:
                self.rejects.count(key, "key", problem)
                continue
            tiles.append(update)
        return tiles

    def fetch_tiles(self, map_name: str, tiles: list[TileKey]) -> dict[TileKey, TileUpdate]:
        """Whole level-0 tiles from their shards, asked all at once; tiles that did not come back are absent.

        A tile's query reaches every shard's tile queryable and ends only when all of them have answered, though
        only the owner replies. So each query is left as soon as its tile is in: a shard that is stalled (alive
        to the router until its Zenoh lease runs out) holds up only the tiles it owns, not every tile request
        until the query timeout."""
        wanted = set(tiles)
        selectors = {tile: keys.tile_key(map_name, 0, *tile) for tile in tiles}
        handlers = [(tile, selector, self._get(selector)) for tile, selector in selectors.items()]
        found = {}
        for tile, selector, handler in handlers:
            for reply in self._replies(selector, handler):
                for update in self._whole_tiles(map_name, [reply]):
                    if (update.tx, update.ty) in wanted:
                        found[(update.tx, update.ty)] = update
                if tile in found:
                    break
        return found

    def fetch_all(self, map_name: str) -> tuple[list[TileUpdate], str | None]:
        """Every whole level-0 tile of the map, from every shard, and why that is not known to be all the map has
        (None when it is): every shard answered its stats and sent at least as many tiles as its stats count. Only then
        is a tile that did not come back one that no shard holds."""
        stats = self.stats(map_name)
        tiles = self._whole_tiles(map_name, self._query(keys.tile_key(map_name, 0, "*", "*")), any_geometry=True)
        shards = max((s.shards for s in stats.values()), default=0)
        sent = Counter(tile.shard for tile in tiles)
        if not stats:
            return tiles, "the API's fetch of its tiles had no shard's stats in time"
        silent = sorted(set(range(shards)) - set(stats))
        # (fewer than its stats held: more may come, made since the stats, as a query is let in between two scans)
        short = {shard: (sent[shard], s.tiles_owned) for shard, s in stats.items() if sent[shard] < s.tiles_owned}
        strangers = sorted(set(sent) - set(stats))
        if not (silent or short or strangers):
            return tiles, None
        parts = [f"shard(s) {', '.join(map(str, silent))} did not answer"] if silent else []
        parts += [f"shard {shard} sent {got} of its {held} tiles" for shard, (got, held) in sorted(short.items())[:4]]
        if strangers:
            parts.append(f"tiles came from shard(s) {', '.join(map(str, strangers))}, which sent no stats")
        return tiles, (
            f"the API's last fetch of its tiles fell short ({'; '.join(parts)}; --query-timeout "
            f"{self.query_timeout:g} s): it serves part of the map and asks again"
        )

    def stats(self, map_name: str) -> dict[int, ShardStats]:
        """The stats of every shard of the map that answers within STATS_TIMEOUT, by shard index (records the
        shard count and proves the pending shards that answered: services.api.registry)."""
        return self.stats_of([map_name])[map_name]

    def stats_of(self, names: list[str]) -> dict[str, dict[int, ShardStats]]:
        """:meth:`stats` of several maps, asked at once (so the wait is one STATS_TIMEOUT, not one per map)."""
        timeout = min(self.query_timeout, STATS_TIMEOUT)
        selectors = [(name, keys.stats_key(name, "*")) for name in names]
        handlers = [(name, selector, self._get(selector, timeout)) for name, selector in selectors]
        out: dict[str, dict[int, ShardStats]] = {}
        for name, selector, handler in handlers:
            replies = []
            for key, payload, sender in self._replies(selector, handler):
                try:
                    replies.append((key, sender, decode_message(payload, ShardStats)))
                except MessageError as exc:
                    self.rejects.count(key, exc.reason, str(exc))
            answers = sort_answers(name, replies, self.registry.tokens(name))  # (of two for one shard: the elder's)
            for key, kind, why in answers.left_out:
                self.rejects.count(key, kind, why)
            for shard in sorted(answers.duplicated):
                self.rejects.count(
                    keys.stats_key(name, shard), "duplicate", f"two processes answer as shard {shard} of map {name!r}"
                )
            out[name] = answers.stats
            self.registry.record_stats(name, answers)
        return out

    def assemble(self, map_name: str, shards: int, resolution: float) -> TiledGrid:
        """The whole map from all shards, checked against their tile counts (services.map_client);
        raises services.map_client.IncompleteMap when a shard is missing or a tile is missing or doubled."""
        reader = MapReader(self.session, map_name)
        try:
            return reader.assemble(
                shards, resolution, timeout=self.query_timeout, tokens=self.registry.tokens(map_name)
            )
        finally:
            for _ in range(reader.rejected):
                self.rejects.count(
                    keys.tile_key(map_name, 0, "*", "*"), "export", "a reply to the export query did not decode"
                )
