"""The FastAPI application of `posegrid api` (docs/api.md): the routers of services.api.routes (maps, tiles,
export, stats, health, robots, events) over one backend, the viewer and its static files, and the exception
handlers. Every failure the client can cause or fix is a 4xx with ``{"detail": one sentence}``; a shard that does
not answer is a 503 with the same form.

Handlers that ask the shards over Zenoh are plain functions (FastAPI runs them in its thread pool); the tile
handlers are coroutines that answer from the cache at once and hand a miss to worker threads of their own
(services.api.routes.tiles). The robot routes read only what the API holds and are coroutines: they never wait.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from starlette.routing import Route

from services.api.backend import Backend
from services.api.guard import COOKIE
from services.api.limits import HttpLimits
from services.api.models import Problem
from services.api.routes import ROUTERS
from services.api.routes.common import Api
from services.api.routes.status import watch
from services.api.tiles import TileUnavailable
from services.api.viewer_files import viewer_assets, viewer_page
from services.map_client import IncompleteMap

__all__ = ["Backend", "create_app"]

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


async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with one sentence per invalid parameter: where it is, its name and what is wrong with it."""
    parts = [
        f"{error['loc'][0]} parameter {'.'.join(map(str, error['loc'][1:]))!r}: {error['msg']}"
        for error in exc.errors()
    ]
    return JSONResponse({"detail": "; ".join(parts)}, status_code=422)


async def unavailable(request: Request, exc: Exception) -> JSONResponse:
    """503 for a shard that holds the data and did not answer."""
    return JSONResponse({"detail": str(exc)}, status_code=503)


#: the errors services.api.guard answers before any route, on every route (OpenAPI ``responses``)
GUARD_ERRORS = {
    400: {"model": Problem, "description": "the Host header names a host the API does not answer to (--allowed-host)"},
    401: {
        "model": Problem,
        "description": "the API has an access token and the request carries none or a wrong one",
        "headers": {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}},
    },
}

#: how a request gives the access token (services.api.guard), as OpenAPI security schemes
TOKEN_SCHEMES = {
    "bearer": {"type": "http", "scheme": "bearer", "description": "Authorization: Bearer TOKEN"},
    "query": {"type": "apiKey", "in": "query", "name": "token", "description": "?token=TOKEN (EventSource)"},
    "cookie": {"type": "apiKey", "in": "cookie", "name": COOKIE, "description": "set by opening /?token=TOKEN"},
}


def _with_guard(app: FastAPI, token: bool) -> Callable[[], dict[str, Any]]:
    """``app``'s OpenAPI generator with the guard's schemes: every route may answer 400 and 401 (GUARD_ERRORS, given
    to FastAPI), and with ``token`` the document asks for the token in any of TOKEN_SCHEMES."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = get_openapi(
                title=app.title,
                version=app.version,
                description=app.description,
                routes=app.routes,
            )
            if token:
                schema.setdefault("components", {})["securitySchemes"] = TOKEN_SCHEMES
                schema["security"] = [{name: []} for name in TOKEN_SCHEMES]
            app.openapi_schema = schema
        return app.openapi_schema

    return openapi


def create_app(backend: Backend, limits: HttpLimits | None = None, token: bool = False) -> FastAPI:
    """The FastAPI application over ``backend``, within ``limits`` (None: the defaults of HttpLimits); ``token``:
    whether the guard in front of it asks for an access token (its OpenAPI document then says how to give it)."""

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        flusher = asyncio.create_task(backend.hub.run())
        watcher = asyncio.create_task(watch(app.state.api))
        yield
        watcher.cancel()
        backend.hub.close()
        flusher.cancel()

    app = FastAPI(
        title="posegrid API",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        exception_handlers={RequestValidationError: invalid, TileUnavailable: unavailable, IncompleteMap: unavailable},
        responses=GUARD_ERRORS,  # type: ignore[arg-type]  # FastAPI annotates dict[int | str, dict[str, Any]]
    )
    app.openapi = _with_guard(app, token)  # type: ignore[method-assign]  # FastAPI's documented way to extend it
    app.state.api = Api(backend, limits or HttpLimits())
    for router in ROUTERS:
        app.include_router(router)
    app.router.routes.append(Route("/", viewer_page(), methods=["GET"], include_in_schema=False))
    app.mount("/static", viewer_assets(), name="static")
    return app
