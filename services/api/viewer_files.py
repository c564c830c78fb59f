"""The browser viewer's files (services/api/static/), served whole whatever a request's Range header asks.

Starlette's FileResponse answers byte ranges, and a Range it cannot parse (a unit other than bytes, a range that
ends before it starts) with a plain-text 400, where HTTP says a server must ignore a unit it does not know (RFC
9110, section 14.2) and the API's errors are JSON. The viewer's files are a few KB, so the server takes HTTP's other
choice: it ignores Range (and If-Range) on them and answers 200 with the whole file.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import Any

from fastapi.responses import Response
from fastapi.staticfiles import StaticFiles

Scope = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[MutableMapping[str, Any]]]
Send = Callable[[MutableMapping[str, Any]], Awaitable[None]]
AsgiApp = Callable[[Scope, Receive, Send], Awaitable[None]]

RANGE_HEADERS = (b"range", b"if-range")
ACCEPT_RANGES = b"accept-ranges"

FOLDER = Path(__file__).resolve().parent / "static"


class WholeFiles:
    """The ASGI app ``app`` with a request's Range and If-Range headers dropped before it sees them, and its
    answer's Accept-Ranges header too (FileResponse offers ranges the files are not served in)."""

    def __init__(self, app: AsgiApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = [(key, value) for key, value in scope["headers"] if key.lower() not in RANGE_HEADERS]

        async def send_whole(message: MutableMapping[str, Any]) -> None:
            if message["type"] == "http.response.start":
                kept = [(key, value) for key, value in message.get("headers", []) if key.lower() != ACCEPT_RANGES]
                message = {**message, "headers": kept}
            await send(message)

        await self.app({**scope, "headers": headers}, receive, send_whole)


#: the viewer's page, read once: a FileResponse sent its headers and then opened the file, so where the process had
#: no file descriptor left a 200 went out with its body cut off
INDEX = (FOLDER / "index.html").read_bytes()


async def _index(scope: Scope, receive: Receive, send: Send) -> None:
    await Response(INDEX, media_type="text/html; charset=utf-8")(scope, receive, send)


def viewer_page() -> WholeFiles:
    """The viewer's page (index.html), for the route ``/``."""
    return WholeFiles(_index)


def viewer_assets() -> WholeFiles:
    """The viewer's scripts and styles, for the mount ``/static``."""
    return WholeFiles(StaticFiles(directory=FOLDER))
