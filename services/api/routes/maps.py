"""GET /maps and GET /maps/{map}: every map a shard has proved, and one map, with extent and cell counts."""

from __future__ import annotations

from fastapi import APIRouter

from services.api import models
from services.api.registry import MapInfo
from services.api.routes.common import Api, ApiDep, MapName, errors, synced_map
from services.api.tiles import MapContent, TileUnavailable

router = APIRouter()


def extent(x0: float, y0: float, x1: float, y1: float) -> models.Extent:
    """The rectangle [x0, x1] x [y0, y1] of the map frame, m."""
    return models.Extent(x_min=x0, y_min=y0, x_max=x1, y_max=y1)


def summary(info: MapInfo, content: MapContent | None) -> models.MapSummary:
    """The map's summary; ``content`` (what needs every tile: observed cells, the variance scale) is None while a
    shard that holds some does not answer, and those fields are then null, so that one shard down does not take
    the list of maps down with it."""
    size, res = info.tile_size, info.resolution
    bounds = area = observed = None
    if info.x_range is not None and info.y_range is not None and size is not None and res is not None:
        (x0, x1), (y0, y1) = info.x_range, info.y_range
        span = size * res
        bounds = models.TileBounds(x_min=x0, x_max=x1, y_min=y0, y_max=y1)
        area = extent(x0 * span, y0 * span, (x1 + 1) * span, (y1 + 1) * span)
    if content is not None and content.bounds is not None and res is not None:
        ix0, iy0, ix1, iy1 = content.bounds
        observed = extent(ix0 * res, iy0 * res, (ix1 + 1) * res, (iy1 + 1) * res)
    per_tile = (size or 0) ** 2
    return models.MapSummary(
        name=info.name,
        resolution=res,
        tile_size=size,
        shards=info.shards,
        shards_alive=sorted(info.alive),
        tiles=len(info.tiles),
        tile_bounds=bounds,
        extent=area,
        observed_extent=observed,
        max_zoom=info.top_level,
        cells=models.CellCounts(
            per_tile=per_tile, total=per_tile * len(info.tiles), observed=None if content is None else content.observed
        ),
        variance_scale=None if content is None else content.variance_scale,
    )


def summary_now(api: Api, info: MapInfo) -> models.MapSummary:
    """:func:`summary` with the map's content as the shards answer now (None when one holding tiles does not)."""
    try:
        content = api.backend.tiles.content(info.name)
    except TileUnavailable:
        content = None
    return summary(info, content)


@router.get("/maps", response_model=list[models.MapSummary], tags=["maps"])
def list_maps(api: ApiDep) -> list[models.MapSummary]:
    """Every map a shard has proved (its liveliness token, then valid stats), with extent and cell counts."""
    out = []
    for name in api.backend.registry.names():
        api.backend.link.stats(name)
        out.append(summary_now(api, synced_map(api, name)))
    return out


@router.get("/maps/{map}", response_model=models.MapSummary, tags=["maps"], responses=errors(404, 422))
def get_map(api: ApiDep, map: MapName) -> models.MapSummary:
    """One map: resolution, tile size, extent (m), zoom levels, cell counts, shards."""
    info = synced_map(api, map)
    api.backend.link.stats(map)
    return summary_now(api, info)
