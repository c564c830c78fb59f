"""HEAD requests answered as the GET of the same URL would be, without the body (RFC 9110, 9.3.2).

FastAPI routes declared with GET answer HEAD with 405, so ``curl -I``, uptime monitors and caches that check a
tile or an export with HEAD were refused. This middleware hands the application a GET and sends the client
only the response's start (status and headers, Content-Length included) and an empty end. Once that is out
the request is over for the application: its one body message is dropped, and a streaming response
(``/events``) is stopped as if the client had gone: its next send raises OSError (ASGI 2.4's sign of a gone
client) and its receive answers http.disconnect (what Starlette listens for under ASGI 2.3).
"""
from __future__ import annotations

from starlette.requests import ClientDisconnect


class HeadAsGet:
    """ASGI middleware: answer HEAD like GET, with the headers and no body."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return
        answered = False

        async def send_start_only(message) -> None:
            nonlocal answered
            if message["type"] == "http.response.start" and not answered:
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                answered = True
            elif answered and message.get("more_body", False):  # a stream: stop it, as a gone client would
                raise OSError("HEAD: the response's headers have been sent, and no body follows")

        async def receive_until_answered():
            if answered:
                return {"type": "http.disconnect"}
            return await receive()

        try:
            await self.app({**scope, "method": "GET"}, receive_until_answered, send_start_only)
        except (OSError, ClientDisconnect):
            if not answered:
                raise
