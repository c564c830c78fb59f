"""GET /maps/{map}/export: the whole map (or a window of it) as npz, a zipped PGM + YAML, or PNG.

The raster is sized from the tiles before any is fetched, and again from the tiles as assembled before the
raster is allocated: beyond --max-export-cells the answer is 413 (services.api.export). At most --max-exports
are built at once; the next is 503 with Retry-After.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query
from fastapi.responses import Response

from mapping.errors import InputError
from services.api.export import Window, covered, raster_shape, windowed
from services.api.limits import EXPORT_BYTES_PER_CELL
from services.api.render import export_body
from services.api.routes.common import Api, ApiDep, MapName, PlainReal, busy, errors, known_map

router = APIRouter()

WindowEdge = Annotated[
    float | None,
    Query(
        allow_inf_nan=False,
        description="export window edge, m in the map frame; give all four of x_min, y_min, x_max, y_max or none",
    ),
    PlainReal,
]


Edges = tuple[float, float, float, float]


def check_layer(fmt: str, layer: str | None) -> None:
    """422 for a layer the format cannot hold."""
    if fmt == "pgm" and layer not in (None, "probability"):
        raise HTTPException(
            422, f"layer={layer}: a pgm export is map_server's occupancy image; export the {layer} layer as png or npz"
        )


def window_edges(x_min: float | None, y_min: float | None, x_max: float | None, y_max: float | None) -> Edges | None:
    """The window's (x_min, y_min, x_max, y_max), m; None without one; 422 for some of them only, or an empty
    window."""
    if x_min is None and y_min is None and x_max is None and y_max is None:
        return None
    if x_min is None or y_min is None or x_max is None or y_max is None:
        raise HTTPException(422, "a window needs all four of x_min, y_min, x_max and y_max (m), or none of them")
    if not (x_min < x_max and y_min < y_max):
        raise HTTPException(
            422, f"the window must have x_min < x_max and y_min < y_max, got x {x_min}..{x_max} m, y {y_min}..{y_max} m"
        )
    return x_min, y_min, x_max, y_max


def check_export_size(api: Api, name: str, tiles_read: list, tile_size: int, resolution: float, window: bool) -> None:
    """413 when the raster an export of ``tiles_read`` allocates exceeds the limit (nothing allocated yet)."""
    limit = api.limits.export_cells
    width, height = raster_shape(tiles_read, tile_size)
    if width * height <= limit:
        return
    cells, span = width * height, tile_size * resolution
    x0, y0 = min(t[0] for t in tiles_read) * span, min(t[1] for t in tiles_read) * span
    raise HTTPException(
        413,
        f"the export of {'this window of ' if window else ''}map {name!r} would be a "
        f"raster of {width} x {height} = {cells} cells ({cells * EXPORT_BYTES_PER_CELL} bytes as "
        f"npz; its tiles span x {x0:.6g}..{x0 + width * resolution:.6g} m, y "
        f"{y0:.6g}..{y0 + height * resolution:.6g} m), more than this API's limit of "
        f"{limit} cells (--max-export-cells); export a smaller window with x_min, "
        "y_min, x_max, y_max (m), or read the map tile by tile",
    )


def shard_count(api: Api, name: str) -> int:
    """The map's shard count, once every shard has answered its stats query; 503 naming those that did not."""
    stats = api.backend.link.stats(name)
    if not stats:
        raise HTTPException(503, f"no shard of map {name!r} answered")
    shards = max(s.shards for s in stats.values())
    silent = sorted(set(range(shards)) - set(stats))
    if silent:  # checked before "no tiles yet": the tiles may all lie on them
        raise HTTPException(503, f"shard(s) {silent} of map {name!r} did not answer; the export would miss their tiles")
    return shards


def build_export(api: Api, name: str, fmt: str, layer: str | None, edges: Edges | None) -> Response:
    """The export of map ``name`` (cropped to ``edges`` = x_min, y_min, x_max, y_max in m when given)."""
    backend = api.backend
    info = known_map(api, name)
    shards = shard_count(api, name)
    # the tiles the registry lists, and the map's geometry, which an API that has seen no tile update since it
    # started learns only here: the size is checked before any tile is fetched
    backend.tiles.sync(name)
    if info.resolution is None or info.tile_size is None:
        raise HTTPException(409, f"map {name!r} has no tiles yet")
    window = None if edges is None else Window.of(*edges, info.resolution)
    check_export_size(
        api,
        name,
        covered(backend.registry.tiles(name), info.tile_size, window),
        info.tile_size,
        info.resolution,
        window is not None,
    )
    grid = backend.link.assemble(name, shards, info.resolution)
    check_export_size(
        api, name, covered(grid.keys(), grid.tile_size, window), grid.tile_size, grid.resolution, window is not None
    )  # the tiles as assembled, before the raster is allocated
    try:
        raster = windowed(grid, window).rasterize()
    except InputError as exc:
        raise HTTPException(413, f"map {name!r} is too large to export: {exc}") from None
    if not raster["observed"].any():
        raise HTTPException(409, f"map {name!r} has no observed cells {'in the window ' if window else ''}yet")
    body, media, filename = export_body(raster, name, fmt, layer)
    return Response(body, media_type=media, headers={"Content-Disposition": f'attachment; filename="{filename}"'})


@router.get(
    "/maps/{map}/export",
    tags=["maps"],
    response_class=Response,
    responses={
        200: {
            "description": "npz: a map file (docs/formats.md), or with layer only that layer, observed, origin and "
            "resolution; pgm: a zip of MAP.pgm and MAP.yaml for ROS map_server; png: an image, north up",
            "content": {"application/octet-stream": {}, "application/zip": {}, "image/png": {}},
        },
        **errors(404, 409, 413, 422, 503),
    },
)
def export(
    api: ApiDep,
    map: MapName,
    format: Annotated[
        Literal["npz", "pgm", "png"], Query(description="npz (a map file), pgm (with its YAML, zipped) or png")
    ],
    layer: Annotated[
        Literal["probability", "logodds", "variance"] | None,
        Query(
            description="png: the layer drawn (default probability; variance is scaled to its 99th "
            "percentile); npz: omit for a complete map file, or give one to get only that layer with observed, "
            "origin (m) and resolution (m), as a tile's npz; pgm: map_server's occupancy image, so omit it or "
            "give probability (another layer is 422)"
        ),
    ] = None,
    x_min: WindowEdge = None,
    y_min: WindowEdge = None,
    x_max: WindowEdge = None,
    y_max: WindowEdge = None,
) -> Response:
    """The map assembled from every shard's tiles now, cropped to the observed cells; with a window
    (x_min, y_min, x_max, y_max, m, all four), only its cells that overlap the window. The raster is sized from
    the tiles before it is built: beyond --max-export-cells the answer is 413, and a window makes it smaller.
    At most --max-exports are built at once; the next is 503 with Retry-After."""
    check_layer(format, layer)
    edges = window_edges(x_min, y_min, x_max, y_max)
    if not api.export_slots.take():
        api.backend.link.refused.add("exports")
        raise busy("exports", api.limits.exports, "--max-exports")
    try:
        return build_export(api, map, format, layer, edges)
    finally:
        api.export_slots.give_back()
