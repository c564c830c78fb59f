"""HEAD requests answered as the GET of the same URL would be, without the body (RFC 9110, 9.3.2).

FastAPI routes declared with GET answer HEAD with 405, so ``curl -I``, uptime monitors and caches that check a
tile or an export with HEAD were refused. This middleware hands the application a GET and sends the client
only the response's start (status and headers, Content-Length included). Once the start is out the request
is over for the application: a streaming response (``/events``) is told the client has gone, so it stops.
"""
from __future__ import annotations


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
            if answered:
                return
            if message["type"] == "http.response.start":
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                answered = True

        async def receive_until_answered():
            if answered:
                return {"type": "http.disconnect"}
            return await receive()

        await self.app({**scope, "method": "GET"}, receive_until_answered, send_start_only)
