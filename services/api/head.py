"""HEAD requests answered as the GET of the same URL would be, without the body (RFC 9110, 9.3.2).

FastAPI routes declared with GET answer HEAD with 405, so ``curl -I``, uptime monitors and caches that check a
tile or an export with HEAD were refused. This middleware hands the application a GET and sends the client
only the response's start (status and headers, Content-Length included) and an empty end. Once that is out
the request is over for the application: its body messages are dropped, and a streaming response
(``/events``) is stopped as if the client had gone. Under ASGI 2.3 (uvicorn's) Starlette listens for
http.disconnect, which receive then answers, and cancels the stream, closing its generator; under 2.4 it
waits instead for a send to raise OSError, which the stream's next send then does. (Raising under 2.3 too
ended the stream before the cancellation and left its generator, and an event-hub client, to the garbage
collector: an audit counted up to 9 such clients after 100 HEADs.)
"""

from __future__ import annotations

from starlette.requests import ClientDisconnect


class HeadAsGet:
    """ASGI middleware: answer HEAD like GET, with the headers and no body."""

    def __init__(self, app) -> None:
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope["method"] == "GET":
            await self.app(scope, receive, send)
            return
        if scope["method"] != "HEAD":  # (FastAPI's 405 lists the routes' GET only: RFC 9110 asks for every method)
            await self.app(scope, receive, _allowing_head(send))
            return
        answered = False
        version = tuple(int(part) for part in scope.get("asgi", {}).get("spec_version", "2.0").split("."))
        raise_when_gone = version >= (2, 4)

        async def send_start_only(message) -> None:
            nonlocal answered
            if message["type"] == "http.response.start" and not answered:
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                answered = True
            elif answered and raise_when_gone and message.get("more_body", False):  # a stream, under ASGI 2.4
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


def _allowing_head(send):
    """``send`` with HEAD added to a 405's ``Allow`` where it lists GET (this middleware answers HEAD wherever GET
    is)."""

    async def sending(message) -> None:
        if message["type"] == "http.response.start" and message["status"] == 405:
            message = {**message, "headers": [_with_head(name, value) for name, value in message.get("headers", [])]}
        await send(message)

    return sending


def _with_head(name: bytes, value: bytes) -> tuple[bytes, bytes]:
    """A response header, with HEAD added to an ``Allow`` that lists GET and not HEAD."""
    methods = [m.strip() for m in value.decode("latin-1").split(",")] if name.lower() == b"allow" else []
    if "GET" in methods and "HEAD" not in methods:
        return name, ", ".join([*methods, "HEAD"]).encode("latin-1")
    return name, value
