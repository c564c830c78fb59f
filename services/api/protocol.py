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
"""

from __future__ import annotations

import asyncio

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol


class TimedHttpToolsProtocol(HttpToolsProtocol):
    """HttpToolsProtocol with the request deadline of the module docstring; see :func:`timed_protocol`."""

    request_timeout: float = 10.0
    _deadline: asyncio.TimerHandle | None = None

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

    def on_message_complete(self) -> None:
        self._disarm()  # the request is in: its answer may take as long as it takes
        super().on_message_complete()

    def on_response_complete(self) -> None:
        waiting = bool(self.pipeline)  # a request already in starts next: nothing to wait for
        super().on_response_complete()
        if not waiting and not self.transport.is_closing():
            self._arm()


def timed_protocol(request_timeout: float) -> type[TimedHttpToolsProtocol]:
    """The protocol class to give uvicorn.Config(http=...), with a deadline of ``request_timeout`` s."""
    return type("TimedHttpToolsProtocol", (TimedHttpToolsProtocol,), {"request_timeout": request_timeout})
