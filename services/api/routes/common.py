"""What every route module shares: the per-application state they are built over (:class:`Api`, a FastAPI
dependency read from ``app.state.api``), the error responses they document, the ``map`` path parameter and the
map look-ups that answer 404 for an unknown map.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Annotated

import anyio
from fastapi import Depends, HTTPException, Path, Request
from pydantic import BeforeValidator

from schemas.wire import NAME_PATTERN, NAME_RULE
from services.api import models
from services.api.backend import Backend
from services.api.fastpath import PLAIN_REAL
from services.api.limits import RETRY_AFTER, TILE_THREADS, HttpLimits, Slots
from services.api.registry import MapInfo
from services.api.status import Progress

ERRORS = {
    404: "unknown map or robot, or a tile outside the map's range",
    409: "the map (or the window) has nothing to export yet",
    413: "the export's raster would span more cells than the API's --max-export-cells; export a window "
    "(x_min, y_min, x_max, y_max)",
    422: "a parameter is malformed or out of its range (layer, format, z outside 0..32, vmax <= 0, ...)",
    503: "a shard holding the data did not answer, or every export slot is taken (see Retry-After)",
}


def errors(*codes: int) -> dict:
    """The OpenAPI ``responses`` entries of these error status codes (body: models.Problem)."""
    return {code: error_response(code, ERRORS[code]) for code in codes}


def error_response(code: int, description: str) -> dict:
    """One OpenAPI ``responses`` entry: body models.Problem; a 503 says it may carry Retry-After."""
    entry: dict = {"model": models.Problem, "description": description}
    if code == 503:
        entry["headers"] = {
            "Retry-After": {"description": "s to wait, when every slot is taken", "schema": {"type": "integer"}}
        }
    return entry


#: an integer parameter as written: ASCII digits after an optional minus (int() also takes "1_0", " 1" and "+1":
#: a probe's tile x of "1_0" was served as tile 10); a number's form is services.api.fastpath.PLAIN_REAL
PLAIN_INTEGER = re.compile(r"-?[0-9]{1,18}")


def _plain(pattern: re.Pattern[str], what: str) -> BeforeValidator:
    def check(value: object) -> object:
        if isinstance(value, str) and pattern.fullmatch(value) is None:
            raise ValueError(f"must be {what}")
        return value

    return BeforeValidator(check)


#: the validators of an integer and a number parameter written as above (FastAPI's 422 when not)
PlainInteger = _plain(PLAIN_INTEGER, "an integer of at most 18 ASCII digits (an optional minus, then digits)")
PlainReal = _plain(PLAIN_REAL, "a number in ASCII digits, as 2, -0.5 or 1e3")

MapName = Annotated[
    str,
    Path(
        description=f"map name, e.g. main (GET /maps lists them): {NAME_RULE}",
        pattern=NAME_PATTERN,
    ),
]


@dataclass
class Api:
    """What the routes of one application are built over: the backend, the limits they enforce, and the state
    they keep between requests (slots, the tile worker limiter, /health's record of progress)."""

    backend: Backend
    limits: HttpLimits
    tile_limiter: anyio.CapacityLimiter = field(default_factory=lambda: anyio.CapacityLimiter(TILE_THREADS))
    progress: Progress = field(default_factory=Progress)

    def __post_init__(self) -> None:
        self.export_slots = Slots(self.limits.exports)
        self.event_slots = Slots(self.limits.event_clients)

    def limit_values(self) -> dict[str, int]:
        """The limits /health shows."""
        return {
            "maps": self.backend.registry.max_maps,
            "robots": self.backend.robots.max_robots,
            "event_clients": self.limits.event_clients,
            "exports": self.limits.exports,
            "export_cells": self.limits.export_cells,
        }


async def get_api(request: Request) -> Api:
    """The :class:`Api` of the application serving ``request`` (a coroutine, so that it runs on the event loop and
    the tile routes never wait for a thread)."""
    return request.app.state.api


ApiDep = Annotated[Api, Depends(get_api)]


def busy(what: str, limit: int, option: str) -> HTTPException:
    """The 503 for a request that finds every one of ``limit`` slots taken."""
    return HTTPException(
        503,
        f"{limit} {what} are in progress, the most this API runs at once ({option}); retry in {RETRY_AFTER} s",
        headers={"Retry-After": str(RETRY_AFTER)},
    )


def known_map(api: Api, name: str) -> MapInfo:
    """The served map ``name``; 404 naming the known maps when there is none."""
    registry = api.backend.registry
    info = registry.served(name)
    if info is None:
        raise HTTPException(404, f"unknown map {name!r}; known maps: {', '.join(registry.names()) or 'none'}")
    return info


def synced_map(api: Api, name: str) -> MapInfo:
    """:func:`known_map`, after the API has asked the shards for the map's tiles (once; blocks)."""
    info = known_map(api, name)
    api.backend.tiles.sync(name)
    return info
