"""GET /maps/{map}/tiles/{z}/{x}/{y}.png and .npz: one tile at any zoom level.

The handlers are coroutines that answer from the cache at once and hand a miss to worker threads of their own,
at most TILE_THREADS (services.api.limits) at a time, so a flood of tile requests waiting on a stalled shard
leaves FastAPI's thread pool to the other routes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Literal

import anyio.to_thread
from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import Response

from services.api.fastpath import tile_response
from services.api.registry import MAX_LEVEL, MapInfo
from services.api.routes.common import Api, ApiDep, MapName, PlainInteger, PlainReal, errors, known_map
from services.api.tiles import render_key

router = APIRouter()

Z = Annotated[
    int,
    Path(
        ge=0,
        le=MAX_LEVEL,
        description="zoom level: 0 = the finest (cells of the map's "
        "resolution); each level doubles the cell side; at most the map's max_zoom",
    ),
    PlainInteger,
]
TileX = Annotated[
    int,
    Path(
        description="tile column at level z: map-frame x in [x*T*2^z*r, (x+1)*T*2^z*r) m "
        "(T = tile_size, r = resolution); may be negative"
    ),
    PlainInteger,
]
TileY = Annotated[
    int,
    Path(description="tile row at level z: map-frame y in [y*T*2^z*r, (y+1)*T*2^z*r) m; may be negative"),
    PlainInteger,
]
Vmax = Annotated[
    float | None,
    Query(
        gt=0,
        allow_inf_nan=False,
        description="variance layer: the variance (log-odds squared) drawn at the top "
        "of the colour ramp; default the map's variance_scale",
    ),
    PlainReal,
]


@dataclass(frozen=True)
class TileAt:
    """Which tile a request names in its path: map ``map``, zoom level ``z``, column ``x``, row ``y``."""

    map: MapName
    z: Z
    x: TileX
    y: TileY


#: a route parameter that FastAPI fills from the tile's path
TileDep = Annotated[TileAt, Depends()]

TILE_CONTENT: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the tile",
        "headers": {"ETag": {"description": "changes when the tile changes", "schema": {"type": "string"}}},
    },
    304: {"description": "the tile has not changed since the ETag given in If-None-Match"},
}


def down_shards(info: MapInfo) -> list[int]:
    """The shards of the map that hold no liveliness token now (none while their count is unknown)."""
    return sorted(set(range(info.shards or 0)) - set(info.alive))


def check_tile(info: MapInfo, z: int, x: int, y: int) -> None:
    """404 for a tile outside the map at level ``z`` (503 when the map has no tiles and a shard is down)."""
    top, ranges = info.top_level, info.level_range(z)
    if top is None or ranges is None:
        down = down_shards(info)
        if down:  # its tiles may all lie on a shard that is down
            raise HTTPException(
                503, f"map {info.name!r} has no tiles from its live shards, and shard(s) {down} are down"
            )
        raise HTTPException(404, f"map {info.name!r} has no tiles yet")
    if z > top:
        raise HTTPException(404, f"zoom level {z} is beyond the coarsest level of map {info.name!r}, {top}")
    (x0, x1), (y0, y1) = ranges
    if not (x0 <= x <= x1 and y0 <= y <= y1):
        raise HTTPException(
            404,
            f"tile ({x}, {y}) is outside map {info.name!r} at zoom level {z}: x must be "
            f"in {x0}..{x1} and y in {y0}..{y1}",
        )


async def tile_work(api: Api, function, *args):
    """``function(*args)`` on one of the tile worker threads."""
    return await anyio.to_thread.run_sync(function, *args, limiter=api.tile_limiter)


async def tile(api: Api, request: Request, at: TileAt, fmt: str, layer: str | None, vmax: float | None) -> Response:
    """The tile response (200 with the encoded tile and its ETag, or 304) of either format."""
    name, z, x, y = at.map, at.z, at.x, at.y
    tiles = api.backend.tiles
    info = known_map(api, name)
    if not info.synced:
        await tile_work(api, tiles.sync, name)
    check_tile(info, z, x, y)
    if fmt == "png" and layer == "variance" and vmax is None:
        vmax = (await tile_work(api, tiles.content, name, True)).variance_scale  # (best effort: a stalled shard)
    key = render_key(name, z, x, y, fmt, layer, vmax)
    rendered = tiles.cached(key) or await tile_work(api, tiles.rendered, key)
    status, headers, body = tile_response(rendered, request.headers.get("if-none-match"))
    return Response(body, status_code=status, headers=dict(headers))


@router.get(
    "/maps/{map}/tiles/{z}/{x}/{y}.png",
    tags=["tiles"],
    response_class=Response,
    responses={**TILE_CONTENT, 200: {**TILE_CONTENT[200], "content": {"image/png": {}}}, **errors(404, 422, 503)},
)
async def tile_png(
    api: ApiDep,
    request: Request,
    at: TileDep,
    layer: Annotated[
        Literal["probability", "logodds", "variance"],
        Query(
            description="probability: grey level 1 - p (free light, occupied black); logodds: "
            "grey, linear over the clamping range; variance: black-red-yellow over variance / vmax, "
            "where pose uncertainty blurred the map. Unobserved cells are pale blue-grey."
        ),
    ] = "probability",
    vmax: Vmax = None,
) -> Response:
    """One tile as a PNG, north up, one pixel per cell. Send If-None-Match with the ETag to get 304
    while the tile is unchanged."""
    return await tile(api, request, at, "png", layer, vmax)


@router.get(
    "/maps/{map}/tiles/{z}/{x}/{y}.npz",
    tags=["tiles"],
    response_class=Response,
    responses={
        **TILE_CONTENT,
        200: {**TILE_CONTENT[200], "content": {"application/octet-stream": {}}},
        **errors(404, 422, 503),
    },
)
async def tile_npz(
    api: ApiDep,
    request: Request,
    at: TileDep,
    layer: Annotated[
        Literal["probability", "logodds", "variance"] | None,
        Query(
            description="omit for a complete map file (docs/formats.md: logodds, probability, "
            "observed, variance, origin, resolution); give one to get only that layer with "
            "observed, origin (m) and resolution (m)"
        ),
    ] = None,
) -> Response:
    """One tile as NumPy .npz in the map-file format, its origin the tile's lower-left corner (m) and its
    resolution 2^z times the map's."""
    return await tile(api, request, at, "npz", layer, None)


@router.get("/maps/{map}/tiles/{z}/{x}/{name}", include_in_schema=False)
def tile_bad_format(map: str, z: str, x: str, name: str) -> None:
    """404 for a tile of any other format, or a tile's file name without its row y."""
    _, dot, suffix = name.rpartition(".")
    if dot and suffix in ("png", "npz"):
        raise HTTPException(404, f"a tile's file name is its row y, then .png or .npz (as 0.png, -3.npz), not {name!r}")
    raise HTTPException(404, f"tiles are served as .png or .npz, not {name!r}")
