"""Tiles of every zoom level: level-0 tiles fetched from their shards, coarser ones combined from their
children (mapping.pyramid), rendered to PNG or .npz, and cached until they change.

Two caches, both keyed by the tile's version (services.api.registry), so nothing stale is ever served:
- layers (logodds, variance, observed) per (map, z, x, y): level-0 tiles as their shard sent them, coarser
  levels as combined, so a change below a tile recomputes only the path from that change up;
- encoded bytes per (map, z, x, y, format, layer, vmax), with their ETag: a repeated request costs a
  dictionary look-up (services.api.fastpath answers it before FastAPI is even involved).

A level-0 tile that the registry does not list is empty (nobody has mapped there); one it lists is asked
from its shard, and a shard that does not answer makes the request fail with :class:`TileUnavailable`. When
the owning shard is up but does not hold the tile (it restarted, or the update that announced the tile came from
no shard), every shard is asked what it holds, and listed tiles that none holds are dropped.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mapping.pyramid import TileLayers, children_of, combine_children
from schemas.messages import TileUpdate
from services.api.cache import ByteLRU
from services.api.registry import MapRegistry, TileKey
from services.api.render import empty_layers, npz_bytes, png_bytes
from services.process import get_logger

MEDIA_TYPES = {"png": "image/png", "npz": "application/octet-stream"}
#: s between two fetches of every tile of a map while they fall short (a shard slow to answer, or holding more tiles
#: than come back in --query-timeout): each fetch asks the whole map again
RESYNC_SHORT = 2.0

#: cells of level-0 tiles asked from the shards at once (a map's summary and a coarse tile fetch every level-0 tile
#: they lack, part after part: asked all at once, the 2 045 tiles a shard holds at its --max-map-cells took the API
#: to 2.3 GB, against --cache-mb 256); 4 M cells, 64 tiles of 256 x 256, about 36 MB of layers
FETCH_CELLS = 1 << 22

#: (map, z, x, y, format, layer or None, vmax or None): what identifies one encoded tile
RenderKey = tuple[str, int, int, int, str, "str | None", "float | None"]


class TileUnavailable(RuntimeError):
    """A level-0 tile the map has could not be fetched from its shard (the message says which)."""


class TileSource(Protocol):
    """Where level-0 tiles come from (services.api.mappers.MapperLink over Zenoh)."""

    def fetch_tiles(self, map_name: str, tiles: list[TileKey]) -> dict[TileKey, TileUpdate]:
        """Whole level-0 tiles, by key; a tile that did not come back is absent."""

    def fetch_all(self, map_name: str) -> tuple[list[TileUpdate], str | None]:
        """Every whole level-0 tile every shard of the map holds, and why that is not known to be all of them (None
        when it is)."""


@dataclass(frozen=True)
class TileFacts:
    """What a level-0 tile contributes to its map's summary."""

    observed: int  # observed cells
    variance_p99: float  # 99th percentile of the variance of its observed cells (0 when none)
    bounds: tuple[int, int, int, int] | None  # global cells (ix_min, iy_min, ix_max, iy_max) observed, inclusive


@dataclass(frozen=True)
class MapContent:
    """A map's cells as of the versions it was computed for."""

    observed: int
    variance_scale: float  # the default top of the variance ramp: see variance_scale()
    bounds: tuple[int, int, int, int] | None  # global cells observed (inclusive), None when none


@dataclass(frozen=True)
class Rendered:
    """An encoded tile."""

    version: int
    etag: str
    body: bytes
    media_type: str


def variance_scale(p99: float) -> float:
    """The default top of the variance ramp: the largest per-tile 99th percentile of observed variance,
    rounded up to a power of two (so it changes rarely while a map grows); 1 when there is no variance."""
    return 2.0 ** math.ceil(math.log2(p99)) if p99 > 0 else 1.0


def render_key(name: str, z: int, x: int, y: int, fmt: str, layer: str | None, vmax: float | None) -> RenderKey:
    """The canonical cache key of a tile request (layer and vmax dropped where they do not matter)."""
    if fmt == "png":
        layer = layer or "probability"
        if layer != "variance":
            vmax = None
        elif vmax is None:  # the callers fill in the map's default (MapContent.variance_scale) first
            raise TypeError("a variance PNG's render key needs vmax")
        else:
            vmax = float(vmax)
    else:
        vmax = None
    return name, z, x, y, fmt, layer, vmax


def tile_facts(tile: TileKey, layers: TileLayers) -> TileFacts:
    _, variance, observed = layers
    seen = variance[observed]
    if not seen.size:
        return TileFacts(0, 0.0, None)
    size = observed.shape[0]
    rows = np.flatnonzero(observed.any(axis=1))
    cols = np.flatnonzero(observed.any(axis=0))
    x0, y0 = tile[0] * size, tile[1] * size
    return TileFacts(
        int(seen.size),
        float(np.percentile(seen, 99)),
        (x0 + int(cols[0]), y0 + int(rows[0]), x0 + int(cols[-1]), y0 + int(rows[-1])),
    )


class TileService:
    """Tiles of every level of every map. Thread-safe."""

    def __init__(
        self,
        registry: MapRegistry,
        source: TileSource,
        epoch: str,
        cache_bytes: int,
        on_change: Callable[[str, TileKey, int], None] = lambda name, tile, version: None,
    ) -> None:
        self.registry = registry
        self.source = source
        self.epoch = epoch
        self.on_change = on_change
        self._layers: ByteLRU[tuple[TileLayers, TileFacts | None]] = ByteLRU(cache_bytes * 3 // 4)
        self._rendered: ByteLRU[Rendered] = ByteLRU(cache_bytes // 4)
        self._content: dict[str, tuple[int, MapContent]] = {}
        # map -> level-0 tile -> the facts of its last version fetched (content(best_effort=True) when it cannot be)
        self._last_facts: dict[str, dict[TileKey, TileFacts]] = {}
        self._sync_lock = threading.Lock()
        self._short_at: dict[str, float] = {}  # map -> time.monotonic() of its last fetch of every tile that fell short
        self.log = get_logger("api")

    # ---------------------------------------------------------------------------- level 0
    def _store(self, name: str, tile: TileKey, version: int, update: TileUpdate) -> tuple[TileLayers, TileFacts]:
        layers = update.whole_layers()
        entry = (layers, tile_facts(tile, layers))
        self._layers.put((name, 0, *tile), version, entry, _nbytes(layers))
        self._last_facts.setdefault(name, {})[tile] = entry[1]
        return entry

    def sync(self, name: str) -> None:
        """Ask every shard of map ``name`` for all its tiles, unless done since the shards came up.

        Tiles new to the registry, or that differ from what is cached, get a new version (and an event)."""
        with self._sync_lock:
            info = self.registry.get(name)
            if info is None or info.synced:
                return
            if info.incomplete is not None and time.monotonic() - self._short_at.get(name, -math.inf) < RESYNC_SHORT:
                return  # (a fetch that fell short: what it gave is served, and asked again at most so often)
            self.registry.mark_synced(name)  # a shard appearing during the fetch asks for another sync
            before = self.registry.tiles(name)
            updates, shortfall = self.source.fetch_all(name)
            complete = shortfall is None
            self.registry.sync_done(name, shortfall)
            if shortfall is not None:
                self._short_at[name] = time.monotonic()
                if shortfall != info.incomplete:  # (said once, not at every try)
                    self.log.warning("map %r: %s", name, shortfall)
            if complete and self._repinned(name, updates):
                before = {}
            mixed = False
            for update in updates:
                tile = (update.tx, update.ty)
                why = self.registry.check_geometry(name, update.resolution, update.tile_size)
                if why is not None:  # (the source's tiles come from their shards: TileSource)
                    self.registry.note_conflict(name, why)
                    mixed = True
                    continue
                known = before.get(tile, 0)
                if self.registry.version(name, 0, *tile) != known:
                    continue  # an update arrived meanwhile; it is at least as new as this reply
                cached = self._layers.get((name, 0, *tile), known) if known else None
                if cached is not None and _same(cached[0], update.whole_layers()):
                    continue
                version = self.registry.tile_changed(name, tile, update.resolution, update.tile_size)
                self._store(name, tile, version, update)
                self.on_change(name, tile, version)
            if complete and not mixed:  # every shard answered with the map's geometry: a conflict seen before is over
                self.registry.clear_conflict(name)
            if complete:  # tiles listed before the sync that no shard holds: lost with a restarted shard, or bogus
                held = {(update.tx, update.ty) for update in updates}
                gone = {
                    tile
                    for tile, version in before.items()
                    if tile not in held and self.registry.version(name, 0, *tile) == version
                }
                if gone:
                    self.log.warning(
                        "map %r: %d tile(s) listed that no shard holds, now dropped: %s",
                        name,
                        len(gone),
                        ", ".join(map(str, sorted(gone)[:4])),
                    )
                    self.registry.forget_tiles(name, gone)
                    self._content.pop(name, None)
                    for tile in gone:
                        self._last_facts.get(name, {}).pop(tile, None)

    def _repinned(self, name: str, updates: list[TileUpdate]) -> bool:
        """Whether every shard of map ``name`` answered a complete fetch with ``updates`` of one geometry other than
        the map's, which the map then takes, dropping the tiles of the old one (none of which any shard holds): a new
        run under the map's name with another --resolution. Else the API kept the first geometry for as long as it
        ran and refused every tile of the new run as a conflict."""
        geometries = {(update.resolution, update.tile_size) for update in updates}
        if len(geometries) != 1:
            return False
        (resolution, tile_size), *_ = geometries
        info = self.registry.get(name)
        if info is None or self.registry.check_geometry(name, resolution, tile_size) is None:
            return False
        self.log.warning(
            "map %r: every shard now holds %d-cell tiles of %s m cells, not %s of %s m: a new run under the map's "
            "name; the old run's tiles are dropped",
            name,
            tile_size,
            resolution,
            info.tile_size,
            info.resolution,
        )
        self.registry.repin_geometry(name, resolution, tile_size)
        self._content.pop(name, None)
        self._last_facts.pop(name, None)
        return True

    def _fetch(self, name: str, wanted: dict[TileKey, int]) -> dict[TileKey, tuple[TileLayers, TileFacts]]:
        """Fetch level-0 tiles ``wanted`` (key -> the version read before asking), cache and return them."""
        got = self.source.fetch_tiles(name, sorted(wanted))
        missing = sorted(set(wanted) - set(got))
        if missing and all(self.registry.owner_alive(name, tile) for tile in missing):
            # their shards are up but did not send them: ask every shard what it holds, which drops the tiles
            # that none holds (lost with a restarted shard, or announced by an update no shard stands behind)
            self.registry.request_sync(name)
            self.sync(name)
            missing = [tile for tile in missing if self.registry.version(name, 0, *tile)]
        if missing:
            info = self.registry.get(name)
            raise TileUnavailable(
                f"map {name!r}: level-0 tile(s) {', '.join(map(str, missing[:4]))} did not come "
                f"back from their shard (shards alive: {sorted(info.alive) if info else []})"
            )
        return {tile: self._store(name, tile, wanted[tile], update) for tile, update in got.items()}

    def _parts(self, name: str, wanted: dict[TileKey, int]) -> list[dict[TileKey, int]]:
        """``wanted`` (level-0 tile -> version) in parts of at most FETCH_CELLS cells, in tile order."""
        info = self.registry.get(name)
        size = info.tile_size if info is not None and info.tile_size else 1
        per_part = max(1, FETCH_CELLS // (size * size))
        tiles = sorted(wanted.items())
        return [dict(tiles[start : start + per_part]) for start in range(0, len(tiles), per_part)]

    def _stale_below(self, name: str, z: int, x: int, y: int, out: dict[TileKey, int]) -> None:
        version = self.registry.version(name, z, x, y)
        if version == 0 or self._layers.get((name, z, x, y), version) is not None:
            return
        if z == 0:
            out[(x, y)] = version
            return
        for child in children_of(x, y):
            self._stale_below(name, z - 1, *child, out)

    # ---------------------------------------------------------------------------- any level
    def layers(self, name: str, z: int, x: int, y: int) -> TileLayers | None:
        """Level-z tile (x, y) of map ``name``; None when no level-0 tile below it exists."""
        stale: dict[TileKey, int] = {}
        self._stale_below(name, z, x, y, stale)
        for part in self._parts(name, stale):  # (into the cache; _build fetches again any it has let go since)
            self._fetch(name, part)
        info = self.registry.get(name)
        if info is None or info.tile_size is None:  # unknown map, or none of its tiles seen: no tile below
            return None
        return self._build(name, info.tile_size, z, x, y)

    def _build(self, name: str, tile_size: int, z: int, x: int, y: int) -> TileLayers | None:
        version = self.registry.version(name, z, x, y)
        if version == 0:
            return None
        entry = self._layers.get((name, z, x, y), version)
        if entry is None and z == 0:  # changed since it was fetched a moment ago: fetch it again
            entry = self._fetch(name, {(x, y): version}).get((x, y))
            if entry is None:  # no shard holds it: dropped from the map meanwhile
                return None
        if entry is not None:
            return entry[0]
        children = [self._build(name, tile_size, z - 1, *child) for child in children_of(x, y)]
        layers = combine_children(children, tile_size)
        self._layers.put((name, z, x, y), version, (layers, None), _nbytes(layers))
        return layers

    def content(self, name: str, best_effort: bool = False) -> MapContent:
        """Observed cells, default variance scale and observed bounds of the whole map (fetches every
        level-0 tile not cached at its current version). ``best_effort`` (the variance scale of a PNG, which must not
        hang on one shard): a tile that cannot be fetched (its shard stalled or gone) counts with the facts of its
        last version fetched, or not at all, and the result is not kept; else TileUnavailable."""
        tiles = self.registry.tiles(name)
        latest = max(tiles.values(), default=0)
        known = self._content.get(name)
        if known is not None and known[0] == latest:
            return known[1]
        by_tile: dict[TileKey, TileFacts] = {}
        stale: dict[TileKey, int] = {}
        for tile, version in tiles.items():
            entry = self._layers.get((name, 0, *tile), version)
            known_facts = None if entry is None else entry[1]  # level-0 entries always have their facts
            if known_facts is None:
                stale[tile] = version
            else:
                by_tile[tile] = known_facts
        partial = False
        if stale and best_effort:
            reachable = {tile: version for tile, version in stale.items() if self.registry.owner_alive(name, tile)}
            fetched: dict[TileKey, TileFacts] = {}
            for part in self._parts(name, reachable):
                try:
                    fetched.update((tile, entry[1]) for tile, entry in self._fetch(name, part).items())
                except TileUnavailable:
                    continue
            by_tile.update(fetched)
            older = self._last_facts.get(name, {})
            by_tile.update((tile, older[tile]) for tile in stale.keys() - fetched.keys() if tile in older)
            partial = len(fetched) < len(stale)
        else:
            for part in self._parts(name, stale):  # (each tile's facts kept, its layers left to the cache)
                by_tile.update((tile, entry[1]) for tile, entry in self._fetch(name, part).items())
        facts = list(by_tile.values())
        boxes = np.array([f.bounds for f in facts if f.bounds is not None]).reshape(-1, 4)
        bounds: tuple[int, int, int, int] | None = None
        if len(boxes):
            (x_min, y_min), (x_max, y_max) = boxes[:, :2].min(axis=0), boxes[:, 2:].max(axis=0)
            bounds = (int(x_min), int(y_min), int(x_max), int(y_max))
        result = MapContent(
            sum(f.observed for f in facts), variance_scale(max((f.variance_p99 for f in facts), default=0.0)), bounds
        )
        if not partial:
            self._content[name] = (latest, result)
        return result

    # ---------------------------------------------------------------------------- encoded tiles
    def cached(self, key: RenderKey) -> Rendered | None:
        """The encoded tile for ``key`` if it is cached at the tile's current version."""
        return self._rendered.get(key, self.registry.version(*key[:4]))

    def rendered(self, key: RenderKey) -> Rendered:
        """The encoded tile for ``key`` (a canonical :func:`render_key`), from the cache or made now."""
        name, z, x, y, fmt, layer, vmax = key
        version = self.registry.version(name, z, x, y)
        hit = self._rendered.get(key, version)
        if hit is not None:
            return hit
        info = self.registry.get(name)
        if info is None or info.resolution is None or info.tile_size is None:
            raise TileUnavailable(f"map {name!r} has no tiles now (it went away while the tile was asked for)")
        layers = self.layers(name, z, x, y) or empty_layers(info.tile_size)
        if fmt == "png":
            body = png_bytes(layers, layer or "probability", vmax if vmax is not None else 1.0)
        else:
            cell = info.resolution * 2**z
            span = cell * info.tile_size
            body = npz_bytes(layers, layer, (x * span, y * span), cell)
        digest = hashlib.blake2b(repr(key).encode(), digest_size=6).hexdigest()
        rendered = Rendered(version, f'"{self.epoch}-{version}-{digest}"', body, MEDIA_TYPES[fmt])
        self._rendered.put(key, version, rendered, len(body))
        return rendered


def _nbytes(layers: TileLayers) -> int:
    return sum(layer.nbytes for layer in layers)


def _same(a: TileLayers, b: TileLayers) -> bool:
    return all(np.array_equal(p, q) for p, q in zip(a, b))
