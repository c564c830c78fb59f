"""Answers repeated tile requests straight from the encoded-tile cache, in front of FastAPI.

A cached tile costs a regular-expression match, a dictionary look-up and two ASGI messages; going through
FastAPI's routing and parameter validation would cost several times that. Only requests the cache can
answer exactly are taken: a GET of /maps/<map>/tiles/<z>/<x>/<y>.<png|npz> whose query string holds
nothing but well-formed ``layer`` and ``vmax`` values (and, for a variance PNG, an explicit ``vmax``), whose
encoded tile is cached at the tile's current version. Everything else, including every request that would
fail, goes on to FastAPI, which validates it, answers it and fills the cache; both build the response with
:func:`tile_response`, so a client cannot tell which one answered.
"""

from __future__ import annotations

import math
import re
from urllib.parse import parse_qsl

from services.api.render import LAYERS
from services.api.tiles import Rendered, TileService, render_key

# ASCII digits only ([0-9], not \d, which also matches Arabic-Indic and fullwidth digits that int() and float()
# take but FastAPI refuses): every request the fast path takes, FastAPI would answer alike
TILE_PATH = re.compile(
    r"^/maps/([A-Za-z0-9][A-Za-z0-9_.-]{0,63})/tiles/([0-9]{1,2})/(-?[0-9]{1,12})/(-?[0-9]{1,12})\.(png|npz)$"
)
#: a number parameter as written in a URL: a decimal or exponent form in ASCII digits, no "_" or spaces (float() takes
#: "1_0" as 10); the fast path reads ``vmax`` so (others go to FastAPI, whose routes refuse them: routes.common)
PLAIN_REAL = re.compile(r"[+-]?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][+-]?[0-9]{1,3})?")


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """Whether an If-None-Match header value names ``etag`` (or is ``*``)."""
    if not if_none_match:
        return False
    candidates = [part.strip() for part in if_none_match.split(",")]
    return "*" in candidates or etag in candidates or f"W/{etag}" in candidates


def tile_response(rendered: Rendered, if_none_match: str | None) -> tuple[int, list[tuple[str, str]], bytes]:
    """(status, headers, body) of a tile response: 304 without a body when the client's ETag is current."""
    headers = [("etag", rendered.etag), ("cache-control", "no-cache")]
    if etag_matches(if_none_match, rendered.etag):
        return 304, headers, b""
    return 200, [("content-type", rendered.media_type), *headers], rendered.body


class CachedTiles:
    """ASGI middleware: answer cached tiles, pass everything else to ``app``."""

    def __init__(self, app, tiles: TileService) -> None:
        self.app = app
        self.tiles = tiles

    def _lookup(self, scope) -> Rendered | None:
        match = TILE_PATH.fullmatch(scope["path"])
        if match is None:
            return None
        name, z, x, y, fmt = match.groups()
        params: dict[str, str] = {}
        for key, value in parse_qsl(scope["query_string"].decode("latin-1"), keep_blank_values=True):
            if key not in ("layer", "vmax") or key in params:
                return None
            params[key] = value
        layer = params.get("layer")
        if layer is not None and layer not in LAYERS:
            return None
        vmax = None
        if "vmax" in params:
            if PLAIN_REAL.fullmatch(params["vmax"]) is None:
                return None
            vmax = float(params["vmax"])
            if not (math.isfinite(vmax) and vmax > 0):
                return None
        if fmt == "png" and layer == "variance" and vmax is None:
            return None
        return self.tiles.cached(render_key(name, int(z), int(x), int(y), fmt, layer, vmax))

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http" and scope["method"] == "GET":
            rendered = self._lookup(scope)
            if rendered is not None:
                if_none_match = next((v.decode("latin-1") for k, v in scope["headers"] if k == b"if-none-match"), None)
                status, headers, body = tile_response(rendered, if_none_match)
                raw = [(k.encode(), v.encode()) for k, v in headers]
                if status == 200:
                    raw.append((b"content-length", str(len(body)).encode()))
                await send({"type": "http.response.start", "status": status, "headers": raw})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)
