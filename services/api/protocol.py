"""uvicorn's HTTP protocol (httptools) with a deadline for each request to arrive whole.

uvicorn closes a keep-alive connection that stays idle for ``timeout_keep_alive`` s, but once a byte of a
request has arrived it waits for the rest for ever: a client that sends half a request line, or one header every
few seconds (slowloris), holds its connection, and a file descriptor, as long as it likes. uvicorn 0.54 has no
option for it (``timeout_keep_alive`` covers only the idle time between requests; ``limit_concurrency`` counts
connections but answers only complete requests; ``h11_max_incomplete_event_size`` bounds the size of a partial
request, not its duration, and only under h11). So this protocol closes a connection whose request has not
arrived whole (request line, headers and body) within ``request_timeout`` s of the connection opening or of
the previous response ending. A request that has arrived is never cut off, however long its answer takes (an
event stream, an export).

Nor does httptools bound a request's line and headers: uvicorn keeps every header it is given, so one client sent
400 MB of headers in 1.6 s and the API held 540 MB. This protocol answers 431 and closes the connection once the
request line and headers pass :data:`MAX_HEAD_BYTES`. The errors it answers itself (that one, and uvicorn's 400
for a request httptools cannot parse) are ``{"detail": ...}`` as the API's own are, not plain text.
"""

from __future__ import annotations

import asyncio
import json

from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol

from services.api.limits import Tally

#: bytes: the most a request's line and headers may take together (name, value and 4 bytes a header). The API's
#: requests take well under 4 KB; nginx's default takes 4 buffers of 8 KB for a large header, Node.js 16 KB in all
MAX_HEAD_BYTES = 64 * 1024


class HeadTooLarge(Exception):
    """A request's line and headers passed :data:`MAX_HEAD_BYTES` (raised in httptools' callback: it stops the
    parser, and :meth:`TimedHttpToolsProtocol.send_400_response` answers 431)."""


class TimedHttpToolsProtocol(HttpToolsProtocol):
    """HttpToolsProtocol with the request deadline of the module docstring; see :func:`timed_protocol`."""

    request_timeout: float = 10.0
    refused: Tally | None = None  # where a request refused for its head's size is counted ("request_head")
    _deadline: asyncio.TimerHandle | None = None
    _head_bytes = 0  # of the request being read
    _too_large = False

    def _arm(self) -> None:
        self._disarm()
        self._deadline = self.loop.call_later(self.request_timeout, self._expire)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expire(self) -> None:
        self._deadline = None
        if not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def on_message_begin(self) -> None:
        self._head_bytes = 0
        super().on_message_begin()

    def _count_head(self, size: int) -> None:
        self._head_bytes += size
        if self._head_bytes > MAX_HEAD_BYTES:
            self._too_large = True
            raise HeadTooLarge

    def on_url(self, url: bytes) -> None:
        self._count_head(len(url))
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._count_head(len(name) + len(value) + 4)
        super().on_header(name, value)

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to a request httptools refused (its message: "Invalid HTTP request received."), or 431
        for one whose head passed MAX_HEAD_BYTES, as ``{"detail": ...}``; the connection is closed."""
        if self._too_large:
            status, detail = 431, f"the request line and headers are over {MAX_HEAD_BYTES} bytes"
            if self.refused is not None:
                self.refused.add("request_head")
        else:
            status, detail = 400, f"{msg.rstrip('.')}: not an HTTP/1.1 request this server can read"
        body = json.dumps({"detail": detail}).encode()
        head = [STATUS_LINE[status]]
        for name, value in self.server_state.default_headers:
            head += [name, b": ", value, b"\r\n"]
        head += [b"content-type: application/json\r\n", b"content-length: %d\r\n" % len(body), b"connection: close\r\n"]
        self.transport.write(b"".join([*head, b"\r\n", body]))
        self.transport.close()

    def on_message_complete(self) -> None:
        self._disarm()  # the request is in: its answer may take as long as it takes
        super().on_message_complete()

    def on_response_complete(self) -> None:
        waiting = bool(self.pipeline)  # a request already in starts next: nothing to wait for
        super().on_response_complete()
        if not waiting and not self.transport.is_closing():
            self._arm()


def timed_protocol(request_timeout: float, refused: Tally | None = None) -> type[TimedHttpToolsProtocol]:
    """The protocol class to give uvicorn.Config(http=...), with a deadline of ``request_timeout`` s, counting the
    requests refused for their head's size in ``refused``."""
    attributes = {"request_timeout": request_timeout, "refused": refused}
    return type("TimedHttpToolsProtocol", (TimedHttpToolsProtocol,), attributes)
