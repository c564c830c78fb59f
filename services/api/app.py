"""The HTTP routes of `posegrid api` (docs/api.md): maps, tiles, export, stats, health, robots, events and
the viewer. Every failure the client can cause or fix is a 4xx with ``{"detail": one sentence}``; a shard
that does not answer is a 503 with the same form.

Handlers that ask the shards over Zenoh are plain functions (FastAPI runs them in its thread pool); the tile
handlers are coroutines that answer from the cache at once and hand a miss to worker threads of their own, at
most TILE_THREADS at a time, so a flood of tile requests waiting on a stalled shard leaves the thread pool to
the other routes. The robot routes read only what the API holds and are coroutines: they never wait.
"""
from __future__ import annotations

import asyncio
import contextlib
import io
import secrets
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path as FilePath
from typing import Annotated, Literal

import anyio.to_thread
import zenoh
from fastapi import FastAPI, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles

from mapping.errors import InputError
from mapping.export import render_pgm
from schemas.messages import ShardStats
from services.api import models
from services.api.events import EventHub
from services.api.export import Window, covered, raster_shape, windowed
from services.api.fastpath import tile_response
from services.api.limits import (EXPORT_BYTES_PER_CELL, MAX_MAPS, MAX_ROBOTS, RETRY_AFTER, STRAY_TTL, VERIFY_WINDOW,
                                 HttpLimits, Slots)
from services.api.mappers import MapperLink
from services.api.registry import MAX_LEVEL, MapInfo, MapRegistry
from services.api.render import npz_bytes, png_bytes
from services.api.robots import RobotTracker, reduce_samples
from services.api.tiles import TileService, TileUnavailable, render_key
from services.map_client import IncompleteMap

STATIC = FilePath(__file__).resolve().parent / "static"
#: s without progress on a robot's lagging scans, its source gone, before /health calls them stranded
STRANDED_AFTER = 5.0
#: tile requests that may fetch or render at once (their own worker threads; FastAPI's pool keeps its 40)
TILE_THREADS = 16

DESCRIPTION = """\
Occupancy maps built by posegrid's mapper shards, read over Zenoh: map summaries, tiles at every zoom level,
whole-map exports, shard statistics, robot poses and a live event stream, plus a browser viewer at `/`.

Units: metres, radians, seconds. Poses are (x, y, yaw) of the robot in the map frame. Tiles: tile_size x
tile_size cells; at zoom level z a cell is 2^z level-0 cells wide and tile (x, y) covers map-frame
x in [x * tile_size * 2^z * resolution, (x + 1) * ...) m, likewise y. A level-z cell combines its four
level-(z-1) cells: observed = any observed; log-odds and variance = the mean over the observed ones.

Errors: `{"detail": "one sentence"}` with 400 (a Host header the API does not answer to), 401 (no or a wrong
access token, when the API has one), 404 (unknown map or robot, tile outside the map), 409 (nothing to export
yet), 413 (an export whose raster would exceed the API's --max-export-cells: export a window), 422 (a malformed
or out-of-range parameter) or 503 (a shard holding the data did not answer, or every slot for event streams or
exports is taken: retry after the Retry-After header's seconds).
"""

ERRORS = {
    404: "unknown map or robot, or a tile outside the map's range",
    409: "the map (or the window) has nothing to export yet",
    413: "the export's raster would span more cells than the API's --max-export-cells; export a window "
         "(x_min, y_min, x_max, y_max)",
    422: "a parameter is malformed or out of its range (layer, format, z < 0, vmax <= 0, ...)",
    503: "a shard holding the data did not answer, or every export slot is taken (see Retry-After)",
}


def errors(*codes: int) -> dict:
    return {code: {"model": models.Problem, "description": ERRORS[code]} for code in codes}


MapName = Annotated[str, Path(description="map name, e.g. main (GET /maps lists them)")]
Robot = Annotated[str, Path(description="robot name, e.g. robot0 (GET /robots lists them)")]
Z = Annotated[int, Path(ge=0, le=MAX_LEVEL, description="zoom level: 0 = the finest (cells of the map's "
                        "resolution); each level doubles the cell side; at most the map's max_zoom")]
TileX = Annotated[int, Path(description="tile column at level z: map-frame x in [x*T*2^z*r, (x+1)*T*2^z*r) m "
                            "(T = tile_size, r = resolution); may be negative")]
TileY = Annotated[int, Path(description="tile row at level z: map-frame y in [y*T*2^z*r, (y+1)*T*2^z*r) m; "
                            "may be negative")]
WindowEdge = Annotated[float | None, Query(allow_inf_nan=False, description="export window edge, m in the map "
                                          "frame; give all four of x_min, y_min, x_max, y_max or none")]
Vmax = Annotated[float | None, Query(gt=0, allow_inf_nan=False,
                                     description="variance layer: the variance (log-odds squared) drawn at the top "
                                     "of the colour ramp; default the map's variance_scale")]

TILE_CONTENT = {
    200: {"description": "the tile", "headers": {"ETag": {"description": "changes when the tile changes",
                                                          "schema": {"type": "string"}}}},
    304: {"description": "the tile has not changed since the ETag given in If-None-Match"},
}


@dataclass
class Backend:
    """Everything the routes use."""

    registry: MapRegistry
    tiles: TileService
    robots: RobotTracker
    hub: EventHub
    link: MapperLink
    started: float

    @classmethod
    def open(cls, session: zenoh.Session, cache_bytes: int, query_timeout: float, max_maps: int = MAX_MAPS,
             max_robots: int = MAX_ROBOTS, stray_ttl: float = STRAY_TTL,
             verify_window: float = VERIFY_WINDOW) -> "Backend":
        """Wire the parts on an open Zenoh session and start listening (limits: services.api.registry,
        services.api.robots, services.api.mappers; stray_ttl and verify_window in s)."""
        epoch = secrets.token_hex(4)
        registry = MapRegistry(max_maps)
        robots, hub = RobotTracker(max_robots=max_robots, stray_ttl=stray_ttl), EventHub(epoch)
        link = MapperLink(session, registry, robots, hub, query_timeout, verify_window)
        tiles = TileService(registry, link, epoch, cache_bytes, on_change=hub.tile_changed)
        link.start()
        return cls(registry, tiles, robots, hub, link, time.monotonic())

    def close(self) -> None:
        self.link.close()


#: the kinds of refusal (ShardStats.refused) that say a peer sends what it should not, and what each means
DISTRUSTED = {
    "ahead": "messages with seqs or ends beyond the seq window (forged or stray seqs; held, never fused)",
    "key": "messages on keys that are no posegrid key (wildcards, made-up streams)",
    "duplicate": "scans or poses that differ from the ones fused for the same seq (two publishers for one robot?)",
    "robots": "messages of robots past the shards' --max-robots",
    "size": "messages larger than the limits allow",
    "work": "scans whose fusion would cost more than --max-work",
    "bound": "scans posed beyond --map-bound",
    "extent": "scans reaching more cells than --max-scan-cells",
}


def distrust(refused: dict[str, int]) -> list[str]:
    """One sentence per kind of refusal in ``refused`` (by kind, summed over a map's shards) that :data:`DISTRUSTED`
    names, e.g. "4 messages with seqs or ends beyond the seq window (...)"."""
    return [f"{refused[kind]} {text}" for kind, text in DISTRUSTED.items() if refused.get(kind)]


def _extent(x0: float, y0: float, x1: float, y1: float) -> models.Extent:
    return models.Extent(x_min=x0, y_min=y0, x_max=x1, y_max=y1)


def busy(what: str, limit: int, option: str) -> HTTPException:
    """The 503 for a request that finds every one of ``limit`` slots taken."""
    return HTTPException(503, f"{limit} {what} are in progress, the most this API runs at once ({option}); retry "
                         f"in {RETRY_AFTER} s", headers={"Retry-After": str(RETRY_AFTER)})


def create_app(backend: Backend, limits: HttpLimits = HttpLimits()) -> FastAPI:
    """The FastAPI application over ``backend``, within ``limits``."""
    registry, tiles, robots, hub, link = backend.registry, backend.tiles, backend.robots, backend.hub, backend.link
    tile_limiter = anyio.CapacityLimiter(TILE_THREADS)
    export_slots, event_slots = Slots(limits.exports), Slots(limits.event_clients)
    limit_values = {"maps": registry.max_maps, "robots": robots.max_robots, "event_clients": limits.event_clients,
                    "exports": limits.exports, "export_cells": limits.export_cells}

    async def tile_work(function, *args):
        return await anyio.to_thread.run_sync(function, *args, limiter=tile_limiter)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        flusher = asyncio.create_task(hub.run())
        yield
        hub.close()
        flusher.cancel()

    app = FastAPI(title="posegrid API", version="1", description=DESCRIPTION, lifespan=lifespan)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = [f"{error['loc'][0]} parameter {'.'.join(map(str, error['loc'][1:]))!r}: {error['msg']}"
                 for error in exc.errors()]
        return JSONResponse({"detail": "; ".join(parts)}, status_code=422)

    @app.exception_handler(TileUnavailable)
    @app.exception_handler(IncompleteMap)
    async def unavailable(request: Request, exc: Exception) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    progress: dict[tuple[str, str], tuple[int, float]] = {}  # (map, robot) -> (scans done, when that last changed)

    def known_map(name: str) -> MapInfo:
        info = registry.served(name)
        if info is None:
            raise HTTPException(404, f"unknown map {name!r}; known maps: {', '.join(registry.names()) or 'none'}")
        return info

    def synced_map(name: str) -> MapInfo:
        info = known_map(name)
        tiles.sync(name)
        return info

    def down_shards(info: MapInfo) -> list[int]:
        """The shards of the map that hold no liveliness token now (none while their count is unknown)."""
        return sorted(set(range(info.shards or 0)) - set(info.alive))

    def check_tile(info: MapInfo, z: int, x: int, y: int) -> None:
        if info.x_range is None:
            down = down_shards(info)
            if down:  # its tiles may all lie on a shard that is down
                raise HTTPException(503, f"map {info.name!r} has no tiles from its live shards, and shard(s) "
                                    f"{down} are down")
            raise HTTPException(404, f"map {info.name!r} has no tiles yet")
        if z > info.top_level:
            raise HTTPException(404, f"zoom level {z} is beyond the coarsest level of map {info.name!r}, "
                                f"{info.top_level}")
        (x0, x1), (y0, y1) = info.level_range(z)
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise HTTPException(404, f"tile ({x}, {y}) is outside map {info.name!r} at zoom level {z}: x must be "
                                f"in {x0}..{x1} and y in {y0}..{y1}")

    def summary(info: MapInfo) -> models.MapSummary:
        """The map's summary; what needs every tile (observed cells, the variance scale) is null while a shard
        that holds some does not answer, so that one shard down does not take the list of maps down with it."""
        try:
            content = tiles.content(info.name)
        except TileUnavailable:
            content = None
        size, res = info.tile_size, info.resolution
        bounds = extent = observed = None
        if info.x_range is not None:
            (x0, x1), (y0, y1) = info.x_range, info.y_range
            span = size * res
            bounds = models.TileBounds(x_min=x0, x_max=x1, y_min=y0, y_max=y1)
            extent = _extent(x0 * span, y0 * span, (x1 + 1) * span, (y1 + 1) * span)
        if content is not None and content.bounds is not None:
            ix0, iy0, ix1, iy1 = content.bounds
            observed = _extent(ix0 * res, iy0 * res, (ix1 + 1) * res, (iy1 + 1) * res)
        per_tile = (size or 0) ** 2
        return models.MapSummary(
            name=info.name, resolution=res, tile_size=size, shards=info.shards, shards_alive=sorted(info.alive),
            tiles=len(info.tiles), tile_bounds=bounds, extent=extent, observed_extent=observed,
            max_zoom=info.top_level,
            cells=models.CellCounts(per_tile=per_tile, total=per_tile * len(info.tiles),
                                    observed=None if content is None else content.observed),
            variance_scale=None if content is None else content.variance_scale)

    # ------------------------------------------------------------------------------- maps
    @app.get("/maps", response_model=list[models.MapSummary], tags=["maps"])
    def list_maps() -> list[models.MapSummary]:
        """Every map a shard has proved (its liveliness token, then valid stats), with extent and cell counts."""
        out = []
        for name in registry.names():
            link.stats(name)
            out.append(summary(synced_map(name)))
        return out

    @app.get("/maps/{map}", response_model=models.MapSummary, tags=["maps"], responses=errors(404, 422))
    def get_map(map: MapName) -> models.MapSummary:
        """One map: resolution, tile size, extent (m), zoom levels, cell counts, shards."""
        info = synced_map(map)
        link.stats(map)
        return summary(info)

    async def tile(request: Request, name: str, z: int, x: int, y: int, fmt: str, layer: str | None,
                   vmax: float | None) -> Response:
        info = known_map(name)
        if not info.synced:
            await tile_work(tiles.sync, name)
        check_tile(info, z, x, y)
        if fmt == "png" and layer == "variance" and vmax is None:
            vmax = (await tile_work(tiles.content, name)).variance_scale
        key = render_key(name, z, x, y, fmt, layer, vmax)
        rendered = tiles.cached(key) or await tile_work(tiles.rendered, key)
        status, headers, body = tile_response(rendered, request.headers.get("if-none-match"))
        return Response(body, status_code=status, headers=dict(headers))

    @app.get("/maps/{map}/tiles/{z}/{x}/{y}.png", tags=["tiles"], response_class=Response,
             responses={**TILE_CONTENT, 200: {**TILE_CONTENT[200], "content": {"image/png": {}}},
                        **errors(404, 422, 503)})
    async def tile_png(request: Request, map: MapName, z: Z, x: TileX, y: TileY,
                       layer: Annotated[Literal["probability", "logodds", "variance"], Query(
                           description="probability: grey level 1 - p (free light, occupied black); logodds: "
                           "grey, linear over the clamping range; variance: black-red-yellow over variance / vmax, "
                           "where pose uncertainty blurred the map. Unobserved cells are pale blue-grey.")
                       ] = "probability",
                       vmax: Vmax = None) -> Response:
        """One tile as a PNG, north up, one pixel per cell. Send If-None-Match with the ETag to get 304
        while the tile is unchanged."""
        return await tile(request, map, z, x, y, "png", layer, vmax)

    @app.get("/maps/{map}/tiles/{z}/{x}/{y}.npz", tags=["tiles"], response_class=Response,
             responses={**TILE_CONTENT, 200: {**TILE_CONTENT[200], "content": {"application/octet-stream": {}}},
                        **errors(404, 422, 503)})
    async def tile_npz(request: Request, map: MapName, z: Z, x: TileX, y: TileY,
                       layer: Annotated[Literal["probability", "logodds", "variance"] | None, Query(
                           description="omit for a complete map file (docs/formats.md: logodds, probability, "
                           "observed, variance, origin, resolution); give one to get only that layer with "
                           "observed, origin (m) and resolution (m)")] = None) -> Response:
        """One tile as NumPy .npz in the map-file format, its origin the tile's lower-left corner (m) and its
        resolution 2^z times the map's."""
        return await tile(request, map, z, x, y, "npz", layer, None)

    @app.get("/maps/{map}/tiles/{z}/{x}/{name}", include_in_schema=False)
    def tile_bad_format(map: str, z: str, x: str, name: str) -> None:
        raise HTTPException(404, f"tiles are served as .png or .npz, not {name!r}")

    @app.get("/maps/{map}/export", tags=["maps"], response_class=Response, responses={
        200: {"description": "npz: a map file (docs/formats.md), or with layer only that layer, observed, origin and "
              "resolution; pgm: a zip of MAP.pgm and MAP.yaml for ROS map_server; png: an image, north up",
              "content": {"application/octet-stream": {}, "application/zip": {}, "image/png": {}}},
        **errors(404, 409, 413, 422, 503)})
    def export(map: MapName,
               format: Annotated[Literal["npz", "pgm", "png"], Query(
                   description="npz (a map file), pgm (with its YAML, zipped) or png")],
               layer: Annotated[Literal["probability", "logodds", "variance"] | None, Query(
                   description="png: the layer drawn (default probability; variance is scaled to its 99th "
                   "percentile); npz: omit for a complete map file, or give one to get only that layer with observed, "
                   "origin (m) and resolution (m), as a tile's npz; pgm: map_server's occupancy image, so omit it or "
                   "give probability (another layer is 422)")] = None,
               x_min: WindowEdge = None, y_min: WindowEdge = None, x_max: WindowEdge = None,
               y_max: WindowEdge = None) -> Response:
        """The map assembled from every shard's tiles now, cropped to the observed cells; with a window
        (x_min, y_min, x_max, y_max, m, all four), only its cells that overlap the window. The raster is sized from
        the tiles before it is built: beyond --max-export-cells the answer is 413, and a window makes it smaller.
        At most --max-exports are built at once; the next is 503 with Retry-After."""
        if format == "pgm" and layer not in (None, "probability"):
            raise HTTPException(422, f"layer={layer}: a pgm export is map_server's occupancy image; export the "
                                f"{layer} layer as png or npz")
        edges = (x_min, y_min, x_max, y_max)
        if None in edges and edges != (None,) * 4:
            raise HTTPException(422, "a window needs all four of x_min, y_min, x_max and y_max (m), or none of them")
        if x_min is not None and not (x_min < x_max and y_min < y_max):
            raise HTTPException(422, f"the window must have x_min < x_max and y_min < y_max, got x {x_min}..{x_max} "
                                f"m, y {y_min}..{y_max} m")
        if not export_slots.take():
            link.refused.add("exports")
            raise busy("exports", limits.exports, "--max-exports")
        try:
            return build_export(map, format, layer, None if x_min is None else edges)
        finally:
            export_slots.give_back()

    def check_export_size(name: str, tiles_read: list, tile_size: int, resolution: float, window: bool) -> None:
        """413 when the raster an export of ``tiles_read`` allocates exceeds the limit (nothing allocated yet)."""
        width, height = raster_shape(tiles_read, tile_size)
        if width * height <= limits.export_cells:
            return
        cells, span = width * height, tile_size * resolution
        x0, y0 = min(t[0] for t in tiles_read) * span, min(t[1] for t in tiles_read) * span
        raise HTTPException(413, f"the export of {'this window of ' if window else ''}map {name!r} would be a "
                            f"raster of {width} x {height} = {cells} cells ({cells * EXPORT_BYTES_PER_CELL} bytes as "
                            f"npz; its tiles span x {x0:.6g}..{x0 + width * resolution:.6g} m, y "
                            f"{y0:.6g}..{y0 + height * resolution:.6g} m), more than this API's limit of "
                            f"{limits.export_cells} cells (--max-export-cells); export a smaller window with x_min, "
                            "y_min, x_max, y_max (m), or read the map tile by tile")

    def build_export(name: str, fmt: str, layer: str | None, edges: tuple[float, ...] | None) -> Response:
        info = known_map(name)
        stats = link.stats(name)
        if not stats:
            raise HTTPException(503, f"no shard of map {name!r} answered")
        shards = max(s.shards for s in stats.values())
        silent = sorted(set(range(shards)) - set(stats))
        if silent:  # checked before "no tiles yet": the tiles may all lie on them
            raise HTTPException(503, f"shard(s) {silent} of map {name!r} did not answer; the export would miss "
                                "their tiles")
        if info.resolution is None:
            raise HTTPException(409, f"map {name!r} has no tiles yet")
        window = None if edges is None else Window.of(*edges, info.resolution)
        tiles.sync(name)  # the tiles the registry lists: the size is checked before any tile is fetched
        check_export_size(name, covered(registry.tiles(name), info.tile_size, window), info.tile_size, info.resolution,
                          window is not None)
        grid = link.assemble(name, shards, info.resolution)
        check_export_size(name, covered(grid.keys(), grid.tile_size, window), grid.tile_size, grid.resolution,
                          window is not None)  # the tiles as assembled, before the raster is allocated
        try:
            raster = windowed(grid, window).rasterize()
        except InputError as exc:
            raise HTTPException(413, f"map {name!r} is too large to export: {exc}") from None
        if not raster["observed"].any():
            raise HTTPException(409, f"map {name!r} has no observed cells {'in the window ' if window else ''}yet")
        layers = (raster["logodds"], raster["variance"], raster["observed"])
        if fmt == "npz":
            body = npz_bytes(layers, layer, raster["origin"], float(raster["resolution"]))
            media, filename = "application/octet-stream", f"{name}.npz"
        elif fmt == "pgm":
            pgm, yaml = render_pgm(raster, image_name=f"{name}.pgm")
            buffer = io.BytesIO()
            with zipfile.ZipFile(buffer, "w") as archive:
                archive.writestr(zipfile.ZipInfo(f"{name}.pgm", date_time=(1980, 1, 1, 0, 0, 0)), pgm)
                archive.writestr(zipfile.ZipInfo(f"{name}.yaml", date_time=(1980, 1, 1, 0, 0, 0)), yaml)
            body, media, filename = buffer.getvalue(), "application/zip", f"{name}.zip"
        else:
            body = png_bytes(layers, layer or "probability", None)
            media, filename = "image/png", f"{name}.png"
        return Response(body, media_type=media, headers={"Content-Disposition": f'attachment; filename="{filename}"'})

    # ------------------------------------------------------------------------------- stats
    def map_stats(name: str) -> models.MapStats:
        info = known_map(name)
        stats = link.stats(name)
        latest = robots.latest_seqs(vouched_only=True)  # stray poses make no lag (services.api.robots)
        now = time.monotonic()
        shard_ids = sorted(set(range(info.shards or 0)) | info.alive | set(stats))
        per_shard, rejected = [], dict(link.rejects.snapshot())
        for shard in shard_ids:
            s = stats.get(shard)
            age = info.last_update.get(shard)
            status = models.ShardStatus(shard=shard, alive=shard in info.alive, answered=s is not None,
                                        tile_updates_received=info.updates_received.get(shard, 0),
                                        last_tile_update_age_s=None if age is None else now - age,
                                        **({} if s is None else _shard_fields(s, latest)))
            per_shard.append(status)
            for key, count in (s.rejected.items() if s else ()):
                rejected[key] = rejected.get(key, 0) + count
        answered = [s for s in per_shard if s.answered]
        robots_seen = sorted({r for s in answered for r in s.scans_fused} | set(latest))
        fused = {r: min(s.scans_fused.get(r, 0) for s in answered) for r in robots_seen} if answered else {}
        discarded = {r: max(s.scans_discarded.get(r, 0) for s in answered) for r in robots_seen} if answered else {}
        lag = {r: max(s.lag_scans.get(r, 0) for s in answered) for r in robots_seen if r in latest} if answered else {}
        refused: dict[str, int] = {}
        for s in stats.values():
            for kind, count in s.refused.items():
                refused[kind] = refused.get(kind, 0) + count
        return models.MapStats(map=name, shards=info.shards, shards_alive=sorted(info.alive), scans_fused=fused,
                               scans_discarded=discarded, lag_scans=lag, rejected=rejected, refused=refused,
                               per_shard=per_shard)

    @app.get("/maps/{map}/stats", response_model=models.MapStats, tags=["status"], responses=errors(404, 422))
    def get_stats(map: MapName) -> models.MapStats:
        """Per shard: liveliness, scans fused, messages received and rejected by key, lag behind SLAM."""
        return map_stats(map)

    @app.get("/health", response_model=models.Health, tags=["status"])
    def health() -> models.Health:
        """Shards alive and answering, scans fused and lag per map, the API's own rejected messages and what it
        refused at its limits. Degraded too while a robot's scans lag, its source is gone, a shard has counted
        scans of it and the shards have made no progress on them for STRANDED_AFTER s: they cannot come any more
        (a shard restarted after the source ended finds no history to take them from), and nothing else would say
        so. Only robots a process liveliness token vouched for have a lag (services.api.robots)."""
        maps, ok = {}, bool(registry.names())
        sources = {process.split("/", 1)[0] for process in list(link.processes) if process.endswith("/source")}
        now = time.monotonic()
        for name in registry.names():
            s = map_stats(name)
            maps[name] = models.MapHealth(shards=s.shards, shards_alive=s.shards_alive, scans_fused=s.scans_fused,
                                          scans_discarded=s.scans_discarded, lag_scans=s.lag_scans,
                                          distrust=distrust(s.refused))
            stranded = False
            counted = {robot for p in s.per_shard for robot, n in {**(p.scans_fused or {}), **(p.scans_discarded or {}),
                                                                   **(p.scans_announced or {})}.items() if n}
            for robot, lag in s.lag_scans.items():
                done = s.scans_fused.get(robot, 0) + s.scans_discarded.get(robot, 0)
                if progress.get((name, robot), (None,))[0] != done:  # still moving (a source that did not wait
                    progress[(name, robot)] = (done, now)  # for the shards exits while they catch up)
                stranded |= (lag > 0 and robot in counted and robot not in sources
                             and now - progress[(name, robot)][1] >= STRANDED_AFTER)
            ok = ok and s.shards is not None and all(p.alive and p.answered for p in s.per_shard) and \
                len(s.per_shard) >= s.shards and not stranded
        return models.Health(status="ok" if ok else "degraded", uptime_s=time.monotonic() - backend.started,
                             maps=maps, robots=robots.robots(), processes_alive=sorted(link.processes),
                             rejected=link.rejects.snapshot(), event_clients=hub.clients,
                             exports_running=export_slots.taken, refused=link.refused.snapshot(),
                             limits=limit_values)

    # ------------------------------------------------------------------------------- robots
    def latest(robot: str):
        summary = robots.latest(robot)
        if summary is None:
            raise HTTPException(404, f"no pose of robot {robot!r} has arrived; robots: "
                                f"{', '.join(robots.robots()) or 'none'}")
        return summary

    @app.get("/robots", response_model=list[models.RobotSummary], tags=["robots"])
    async def list_robots() -> list[models.RobotSummary]:
        """Robots whose poses the API has received."""
        processes = [p.split("/", 1) for p in sorted(link.processes)]  # a copy: Zenoh's threads change the set
        out = []
        for robot in robots.robots():
            s = robots.latest(robot)
            out.append(models.RobotSummary(robot=robot, seq=s.seq, stamp=s.stamp, form=s.form, processes_alive=[
                process for owner, process in processes if owner == robot]))
        return out

    @app.get("/robots/{robot}/pose", response_model=models.Pose, tags=["robots"], responses=errors(404, 422))
    async def pose(robot: Robot, max_samples: Annotated[int | None, Query(
            ge=1, description="return at most this many samples, reduced by systematic resampling "
            "(equal weights); default all")] = None) -> models.Pose:
        """The latest pose distribution: samples with weights, and their mean and covariance."""
        s = latest(robot)
        samples, weights = (s.samples, s.weights) if max_samples is None else \
            reduce_samples(s.samples, s.weights, max_samples)
        return models.Pose(robot=robot, seq=s.seq, stamp=s.stamp, received=s.received, form=s.form,
                           samples=samples.tolist(), weights=weights.tolist(), samples_total=len(s.weights),
                           mean=s.mean.tolist(), covariance=s.cov.tolist())

    @app.get("/robots/{robot}/trajectory", response_model=models.Trajectory, tags=["robots"],
             responses=errors(404, 422))
    async def trajectory(robot: Robot) -> models.Trajectory:
        """The robot's mean poses since the API started, oldest first."""
        latest(robot)
        rows = robots.trajectory(robot)
        return models.Trajectory(robot=robot, seq=rows[:, 0].astype(int).tolist(), stamp=rows[:, 1].tolist(),
                                 x=rows[:, 2].tolist(), y=rows[:, 3].tolist(), yaw=rows[:, 4].tolist())

    # ------------------------------------------------------------------------------- events, viewer
    @app.get("/events", tags=["status"], response_class=StreamingResponse, responses={200: {
        "description": "server-sent events: hello, tiles ({map, tiles: [[tx, ty, version], ...]}, level-0 "
        "tiles that changed), pose ({robot, seq, stamp, mean, covariance, samples, weights}), resync",
        "content": {"text/event-stream": {}}},
        503: {"model": models.Problem, "description": "every event-stream slot is taken (--max-event-clients); "
              "retry after Retry-After s"}})
    async def events() -> StreamingResponse:
        """A stream of tile-changed and pose events, batched every 0.25 s (docs/api.md); at most
        --max-event-clients at once."""
        if not event_slots.take():  # on the event loop: no other request takes a slot between check and take
            link.refused.add("event_clients")
            raise busy("event streams", limits.event_clients, "--max-event-clients")
        return SlotStream(hub.stream(), event_slots, media_type="text/event-stream",
                          headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    @app.get("/", include_in_schema=False)
    async def viewer() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


class SlotStream(StreamingResponse):
    """A streaming response that gives its slot back when it ends, however it ends (a client gone before the
    first event included)."""

    def __init__(self, content, slots: Slots, **kwargs) -> None:
        super().__init__(content, **kwargs)
        self.slots = slots

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.slots.give_back()


def _shard_fields(s: ShardStats, latest: dict[str, int]) -> dict:
    """ShardStatus fields from a shard's stats; lag against the latest pose seq of each robot."""
    lag = {r: max(0, seq + 1 - s.fused.get(r, 0) - s.discarded.get(r, 0)) for r, seq in latest.items()}
    return dict(scans_fused=s.fused, scans_discarded=s.discarded, scans_announced=s.ended, tiles_owned=s.tiles_owned,
                cells_updated=s.cells_updated, tile_updates=s.tile_updates, join_pending=s.join_pending,
                uptime_s=s.uptime, received=s.received, resent=s.resent, rejected=s.rejected, overflow=s.overflow,
                lag_scans=lag)

