"""What the API knows about each map: its shards (alive or not), its level-0 tiles and their versions.

Versions: every change of a level-0 tile (a tile update from its shard, or a tile first seen) takes the
next value of one counter shared by all maps, so a larger version is always a later change. The version of
a level-z tile (x, y) is the largest version among the level-0 tiles it covers (0 when it covers none that
exist): any change below it gives it a new, larger version. Versions of all levels are kept up to date on
every change, so reading one is a dictionary look-up.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

from mapping.pyramid import children_of, tile_range, top_level
from services.api.limits import MAX_MAPS, MAX_PENDING
from services.map_client import ShardAnswers
from services.state.ownership import tile_owner

TileKey = tuple[int, int]

#: levels whose versions are kept (a level-32 tile spans 2^32 level-0 tiles per side)
MAX_LEVEL = 32


@dataclass
class MapInfo:
    """One map as seen from the API. Mutated only under :attr:`MapRegistry.lock`."""

    name: str
    resolution: float | None = None  # m per level-0 cell; None until the first tile is seen
    tile_size: int | None = None  # cells per tile side
    shards: int | None = None  # shard count the shards report in their stats
    alive: set[int] = field(default_factory=set)  # verified shards whose liveliness token is up
    pending: dict[int, float] = field(default_factory=dict)  # shard -> time.monotonic() its token appeared, while
    # the shard has not yet answered its stats query (services.api.mappers verifies it)
    verified: bool = False  # whether a shard of the map ever proved itself; only such maps are served
    last_update: dict[int, float] = field(default_factory=dict)  # shard -> time.monotonic() of its last tile update
    updates_received: dict[int, int] = field(default_factory=dict)  # shard -> tile updates received from it
    levels: list[dict[TileKey, int]] = field(default_factory=lambda: [{} for _ in range(MAX_LEVEL + 1)])
    x_range: tuple[int, int] | None = None  # level-0 tile columns spanned (inclusive)
    y_range: tuple[int, int] | None = None
    synced: bool = False  # whether the tiles the shards hold have been asked for since they came up
    duplicated: set[int] = field(default_factory=set)  # shards two processes answered for in the last stats query
    answerers: dict[int, str] = field(default_factory=dict)  # shard -> the Zenoh session id whose stats were taken
    conflict: str | None = None  # the first tile whose geometry is not the map's: its shards are no one map
    incomplete: str | None = None  # why the API's last fetch of every tile of the map fell short; None when it did not

    @property
    def tiles(self) -> dict[TileKey, int]:
        """Level-0 tiles that exist, with their versions."""
        return self.levels[0]

    @property
    def top_level(self) -> int | None:
        """The coarsest zoom level served (mapping.pyramid.top_level); None while the map has no tiles."""
        if self.x_range is None or self.y_range is None:  # set together: both or neither
            return None
        return top_level(self.x_range, self.y_range)

    def level_range(self, z: int) -> tuple[tuple[int, int], tuple[int, int]] | None:
        """(x range, y range), inclusive, of the level-z tiles that cover the map; None without tiles."""
        if self.x_range is None or self.y_range is None:  # set together: both or neither
            return None
        return tile_range(*self.x_range, z), tile_range(*self.y_range, z)


class MapRegistry:
    """Every map the API has heard of, thread-safe (Zenoh callbacks write, HTTP handlers read).

    A shard's liveliness token only makes the shard *pending* (:meth:`token_up`); the shard becomes alive when
    it answers its stats query with valid stats for that map and index (:meth:`record_stats`). A map is served
    (:meth:`names`, :meth:`served`) once one of its shards has; a map none of whose shards ever did is
    forgotten when its last pending token goes away or expires. At most ``max_maps`` maps are held, and at most
    ``max_pending`` pending tokens in all; tokens beyond either are refused (the caller counts them).
    """

    def __init__(self, max_maps: int = MAX_MAPS, max_pending: int = MAX_PENDING) -> None:
        self.lock = threading.Lock()
        self._maps: dict[str, MapInfo] = {}
        self._counter = 0
        self.max_maps = max_maps
        self.max_pending = max_pending

    def names(self) -> list[str]:
        """The maps a shard has proved (the ones the API serves)."""
        with self.lock:
            return sorted(name for name, info in self._maps.items() if info.verified)

    def get(self, name: str) -> MapInfo | None:
        """The map, verified or not (:meth:`served` for the maps the API serves)."""
        return self._maps.get(name)

    def served(self, name: str) -> MapInfo | None:
        """The map if a shard of it has proved itself, else None."""
        info = self._maps.get(name)
        return info if info is not None and info.verified else None

    def token_up(self, name: str, shard: int) -> str | None:
        """Record shard ``shard`` of map ``name``'s liveliness token as pending verification (nothing to do
        when the shard is alive already); returns why it was refused (None when taken): too many maps or
        pending tokens."""
        with self.lock:
            info = self._maps.get(name)
            if info is None and len(self._maps) >= self.max_maps:
                return f"the API already holds {self.max_maps} maps (--max-maps)"
            if info is not None and (shard in info.alive or shard in info.pending):
                return None
            if sum(len(i.pending) for i in self._maps.values()) >= self.max_pending:
                return f"{self.max_pending} shard tokens already wait for their shard to answer"
            self._info(name).pending[shard] = time.monotonic()
            return None

    def token_down(self, name: str, shard: int) -> None:
        """Record shard ``shard`` of map ``name``'s liveliness token going away."""
        with self.lock:
            info = self._maps.get(name)
            if info is not None:
                info.alive.discard(shard)
                info.pending.pop(shard, None)
                self._forget_unproved(name)

    def pending(self) -> list[str]:
        """Maps with shards waiting for verification."""
        with self.lock:
            return sorted(name for name, info in self._maps.items() if info.pending)

    def tokens(self, name: str) -> set[int]:
        """The shards of map ``name`` whose liveliness token is up (alive or pending)."""
        with self.lock:
            info = self._maps.get(name)
            return set() if info is None else info.alive | set(info.pending)

    def record_stats(self, name: str, answers: ShardAnswers) -> None:
        """Take a round of the map's shards' stats (services.map_client.sort_answers: of the shards whose token is
        up), and the shards more than one process answered for: record the duplicates, and, from a round that can be
        trusted (no duplicate, one shard count), the shard count and who answers for each shard; a duplicated
        shard answers for no tile until one process is left (a peer answering as a live shard with a longer uptime
        had its tiles served, and its made-up count of 64 shards taken). Every pending shard that answered becomes
        alive."""
        stats = answers.stats
        if not stats:
            return
        with self.lock:
            info = self._maps.get(name)
            if info is None:
                return
            info.duplicated = set(answers.duplicated)
            for shard in answers.duplicated:
                info.answerers.pop(shard, None)
            if not answers.problems:
                info.answerers.update(answers.answerers)
                info.shards = max(s.shards for s in stats.values())
            for shard in [s for s in info.pending if s in stats]:
                del info.pending[shard]
                info.alive.add(shard)
                info.verified, info.synced = True, False  # a shard that comes up asks for a sync

    def expire_pending(self, window: float) -> list[tuple[str, int]]:
        """Forget the tokens pending for more than ``window`` s (and the maps left with no proved shard);
        returns the (map, shard) forgotten."""
        now, gone = time.monotonic(), []
        with self.lock:
            for name, info in list(self._maps.items()):
                for shard, since in list(info.pending.items()):
                    if now - since > window:
                        del info.pending[shard]
                        gone.append((name, shard))
                self._forget_unproved(name)
        return gone

    def _forget_unproved(self, name: str) -> None:
        """Drop map ``name`` if no shard of it ever proved itself and none is pending (holding the lock)."""
        info = self._maps.get(name)
        if info is not None and not info.verified and not info.pending:
            del self._maps[name]

    def _info(self, name: str) -> MapInfo:
        info = self._maps.get(name)
        if info is None:
            info = self._maps[name] = MapInfo(name)
        return info

    def tiles(self, name: str) -> dict[TileKey, int]:
        """A copy of map ``name``'s level-0 tiles and their versions (empty for an unknown map)."""
        with self.lock:
            info = self._maps.get(name)
            return dict(info.tiles) if info else {}

    def shard_alive(self, name: str, shard: int, alive: bool) -> None:
        """Record a proved shard coming up or going away; a shard that comes up asks for a sync."""
        with self.lock:
            info = self._info(name)
            if alive:
                info.alive.add(shard)
                info.verified, info.synced = True, False
            else:
                info.alive.discard(shard)

    def set_shards(self, name: str, shards: int) -> None:
        with self.lock:
            self._info(name).shards = shards

    def mark_synced(self, name: str) -> None:
        with self.lock:
            self._info(name).synced = True

    def check_sender(self, name: str, shard: int, tile: TileKey) -> str | None:
        """Why a tile update that says it comes from ``shard`` for level-0 ``tile`` of map ``name`` is not to be
        trusted (None when it is): no live shard serves the map, that shard is not alive, or, once the shard
        count is known, the tile is another shard's (services.state.ownership)."""
        with self.lock:
            info = self._maps.get(name)
            if info is None or not (info.alive or info.pending):
                return f"no live shard serves map {name!r}"
            if shard not in info.alive and shard not in info.pending:  # a pending shard's first updates count
                return f"shard {shard} of map {name!r} is not alive (alive: {sorted(info.alive)})"
            shards = info.shards
        if shards is not None:
            if shard >= shards:
                return f"map {name!r} has {shards} shard(s), so no shard {shard}"
            owner = tile_owner(tile, range(shards))
            if owner != shard:
                return f"tile {tile} of map {name!r} belongs to shard {owner}, not to shard {shard}"
        return None

    def check_answerer(self, name: str, shard: int, sender: str) -> str | None:
        """Why a tile that Zenoh session ``sender`` sent in reply for ``shard`` of map ``name`` is not to be trusted
        (None when it is): another session answered that shard's stats."""
        with self.lock:
            info = self._maps.get(name)
            answerer = None if info is None else info.answerers.get(shard)
        if answerer != sender:
            return f"a tile of shard {shard} of map {name!r} from a process that does not answer as that shard"
        return None

    def check_geometry(self, name: str, resolution: float, tile_size: int) -> str | None:
        """Why a tile of this geometry does not belong to map ``name`` (None when it does)."""
        info = self._maps.get(name)
        if info is None or info.resolution is None:
            return None
        if (info.resolution, info.tile_size) != (resolution, tile_size):
            return (
                f"map {name!r} has {info.tile_size}-cell tiles of {info.resolution} m cells, "
                f"not {tile_size} of {resolution} m"
            )
        return None

    def note_conflict(self, name: str, why: str) -> None:
        """Keep ``why`` (a tile of another geometry, from the process that answers as its shard: never a peer's
        forgery, which must not degrade /health) as map ``name``'s conflict, until :meth:`clear_conflict`."""
        with self.lock:
            info = self._maps.get(name)
            if info is not None and info.conflict is None:
                info.conflict = f"its shards publish tiles of two geometries: {why}"

    def clear_conflict(self, name: str) -> None:
        """Forget map ``name``'s conflict: a fetch of every shard's tiles found one geometry only (the shard of
        another --resolution was replaced)."""
        with self.lock:
            info = self._maps.get(name)
            if info is not None:
                info.conflict = None

    def repin_geometry(self, name: str, resolution: float, tile_size: int) -> None:
        """Give map ``name`` a new geometry (m per cell, cells per tile side) and forget its tiles, every level: every
        shard of the map now holds tiles of that geometry only (a new run under the map's name, with another
        --resolution), so none of the tiles of the old one is held any more. The conflict goes with them."""
        with self.lock:
            info = self._maps.get(name)
            if info is None:
                return
            info.resolution, info.tile_size = resolution, tile_size
            info.levels = [{} for _ in range(MAX_LEVEL + 1)]
            info.x_range = info.y_range = None
            info.conflict = None

    def tile_changed(self, name: str, tile: TileKey, resolution: float, tile_size: int) -> int:
        """Record a change (or the discovery) of level-0 tile ``tile`` of map ``name``; returns its new version."""
        with self.lock:
            info = self._info(name)
            if info.resolution is None:
                info.resolution, info.tile_size = resolution, tile_size
            self._counter += 1
            version = self._counter
            tx, ty = tile
            for z, level in enumerate(info.levels):
                level[(tx >> z, ty >> z)] = version
            info.x_range = (tx, tx) if info.x_range is None else (min(info.x_range[0], tx), max(info.x_range[1], tx))
            info.y_range = (ty, ty) if info.y_range is None else (min(info.y_range[0], ty), max(info.y_range[1], ty))
            return version

    def forget_tiles(self, name: str, tiles: set[TileKey]) -> None:
        """Drop level-0 ``tiles`` of map ``name`` that no shard holds (lost with a restarted shard, or announced by
        an update no shard stands behind). Every coarser tile above them takes a new version, or goes when no
        level-0 tile is left below it, so no cached tile that showed them is served again."""
        with self.lock:
            info = self._maps.get(name)
            if info is None or not tiles:
                return
            self._counter += 1
            for tile in tiles:
                info.levels[0].pop(tile, None)
            below = set(tiles)
            for z in range(1, MAX_LEVEL + 1):
                above = {(tx >> 1, ty >> 1) for tx, ty in below}
                for parent in above:
                    if any(child in info.levels[z - 1] for child in children_of(*parent)):
                        info.levels[z][parent] = self._counter
                    else:
                        info.levels[z].pop(parent, None)
                below = above
            if info.tiles:
                columns, rows = zip(*info.tiles)
                info.x_range, info.y_range = (min(columns), max(columns)), (min(rows), max(rows))
            else:
                info.x_range = info.y_range = None

    def sync_done(self, name: str, incomplete: str | None) -> None:
        """Record how the last fetch of every tile of map ``name`` went: ``incomplete`` says why it fell short (the
        tiles are then asked again before they are next served), None when it was complete."""
        with self.lock:
            info = self._maps.get(name)
            if info is not None:
                info.incomplete = incomplete
                if incomplete is not None:
                    info.synced = False

    def request_sync(self, name: str) -> None:
        """Have the tiles of map ``name`` asked from its shards again before they are next served."""
        with self.lock:
            info = self._maps.get(name)
            if info is not None:
                info.synced = False

    def owner_alive(self, name: str, tile: TileKey) -> bool:
        """Whether the shard that owns level-0 ``tile`` of map ``name`` is alive (False while the shard count
        is unknown)."""
        with self.lock:
            info = self._maps.get(name)
            if info is None or info.shards is None:
                return False
            shards, alive = info.shards, set(info.alive)
        return tile_owner(tile, range(shards)) in alive

    def update_received(self, name: str, shard: int) -> None:
        """Count a tile update published by ``shard`` (before its :meth:`tile_changed`)."""
        with self.lock:
            info = self._info(name)
            info.last_update[shard] = time.monotonic()
            info.updates_received[shard] = info.updates_received.get(shard, 0) + 1

    def version(self, name: str, z: int, x: int, y: int) -> int:
        """The version of level-z tile (x, y) of map ``name`` (0: no level-0 tile below it exists)."""
        info = self._maps.get(name)
        if info is None or not 0 <= z <= MAX_LEVEL:
            return 0
        return info.levels[z].get((x, y), 0)
