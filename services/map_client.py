"""Reading a sharded map over Zenoh: the shards' stats, their tiles, and the map assembled from them.

Used by the launcher (progress, export), the source (flow control) and the benchmark. Replies that do
not decode are skipped and counted in :attr:`MapReader.rejected`, never trusted.
"""

from __future__ import annotations

import zenoh

from mapping.grid import TiledGrid
from schemas.messages import MessageError, ShardStats, TileUpdate, decode_message
from services import keys


class IncompleteMap(RuntimeError):
    """The tiles received do not add up to what the shards say they hold."""


class MapReader:
    """Queries the shards of map ``map_name`` on an open session."""

    def __init__(self, session: zenoh.Session, map_name: str):
        self.session = session
        self.map_name = map_name
        self.rejected = 0

    def _replies(self, selector: str, expected, timeout: float) -> list:
        messages = []
        handler = self.session.get(
            selector,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=timeout,
        )
        for reply in handler:
            if reply.ok is None:
                self.rejected += 1
                continue
            try:
                messages.append(decode_message(reply.ok.payload.to_bytes(), expected))
            except MessageError:
                self.rejected += 1
        return messages

    def stats(self, timeout: float = 5.0) -> dict[int, ShardStats]:
        """Every reachable shard's stats, by shard index."""
        replies = self._replies(keys.stats_key(self.map_name, "*"), ShardStats, timeout)
        return {s.shard: s for s in replies if s.map == self.map_name}

    def tiles(self, timeout: float = 60.0) -> list[TileUpdate]:
        """Every tile of zoom level 0 from every shard (whole tiles)."""
        replies = self._replies(keys.tile_key(self.map_name, 0, "*", "*"), TileUpdate, timeout)
        return [t for t in replies if t.map == self.map_name]

    def assemble(self, shards: int, resolution: float, timeout: float = 60.0) -> TiledGrid:
        """The whole map as one grid of cells ``resolution`` m, checked against the shards' own tile counts.

        Raises :class:`IncompleteMap` when a shard does not answer or says the map has another number of shards, or a
        tile is missing (fewer of a shard's arrive than its stats held; more may, made since) or duplicated.
        """
        stats = self.stats()
        if sorted(stats) != list(range(shards)):
            raise IncompleteMap(f"expected shards 0..{shards - 1} of map {self.map_name!r}, got {sorted(stats)}")
        for shard, shard_stats in stats.items():
            if shard_stats.shards != shards:
                raise IncompleteMap(
                    f"shard {shard} says map {self.map_name!r} has {shard_stats.shards} shard(s), not {shards}"
                )
        tiles = self.tiles(timeout)
        per_shard = dict.fromkeys(range(shards), 0)
        seen = set()
        for tile in tiles:
            if (tile.tx, tile.ty) in seen:
                raise IncompleteMap(f"tile ({tile.tx}, {tile.ty}) came from two shards")
            seen.add((tile.tx, tile.ty))
            per_shard[tile.shard] = per_shard.get(tile.shard, 0) + 1
        for shard, count in per_shard.items():  # (asked after the stats: a shard may have made tiles meanwhile)
            owned = stats[shard].tiles_owned if shard in stats else 0
            if count < owned:
                raise IncompleteMap(f"shard {shard} holds {owned} tiles but {count} arrived")
        if not tiles:
            return TiledGrid(resolution)
        grid = TiledGrid(resolution, tiles[0].tile_size)
        for tile in tiles:
            if tile.resolution != resolution:
                raise IncompleteMap(
                    f"the shards map at {tile.resolution} m (tile {tile.tx}, {tile.ty}), not {resolution} m"
                )
            if tile.z != 0 or not tile.is_whole() or tile.tile_size != grid.tile_size:
                raise IncompleteMap(
                    f"tile ({tile.tx}, {tile.ty}) arrived as a partial window or at zoom level {tile.z}"
                )
            grid.set_tile((tile.tx, tile.ty), *tile.whole_layers())
        return grid
