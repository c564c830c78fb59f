"""Runs the API under uvicorn on one Zenoh session until SIGINT/SIGTERM or the launcher's death.

The application stack, outermost first: the Host and token checks (services.api.guard), HEAD as GET
(services.api.head), cached tiles (services.api.fastpath), FastAPI (services.api.app); under uvicorn with the
request deadline of services.api.protocol, the keep-alive timeout and a cap on open connections.
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass, field

import uvicorn
import zenoh

from services.api.app import create_app
from services.api.backend import Backend
from services.api.fastpath import CachedTiles
from services.api.guard import Guard, allowed_hosts
from services.api.head import HeadAsGet
from services.api.limits import (
    KEEP_ALIVE,
    MAX_CONNECTIONS,
    MAX_MAPS,
    MAX_ROBOTS,
    REQUEST_TIMEOUT,
    STRAY_TTL,
    VERIFY_WINDOW,
    HttpLimits,
    Tally,
    fit_connections,
)
from services.api.protocol import timed_protocol
from services.api.routes.events import CLIENT_GONE
from services.process import get_logger, install_stop_event
from services.zenoh_config import close_session, open_session

#: seconds open connections (event streams) get to finish when the server stops
GRACEFUL_SHUTDOWN = 2.0


@dataclass(frozen=True)
class ServeOptions:
    """Everything `posegrid api` takes beyond the address and the Zenoh session (docs/api.md)."""

    cache_bytes: int = 256 << 20
    query_timeout: float = 10.0  # s
    token: str | None = None
    allowed_hosts: tuple[str, ...] = ()
    limits: HttpLimits = field(default_factory=HttpLimits)
    max_connections: int = MAX_CONNECTIONS
    keep_alive: float = KEEP_ALIVE  # s
    request_timeout: float = REQUEST_TIMEOUT  # s
    max_maps: int = MAX_MAPS
    max_robots: int = MAX_ROBOTS
    stray_ttl: float = STRAY_TTL  # s
    verify_window: float = VERIFY_WINDOW  # s


class _Server(uvicorn.Server):
    """uvicorn's server that also ends the event streams when it is told to exit."""

    def __init__(self, config: uvicorn.Config, backend: Backend) -> None:
        super().__init__(config)
        self.backend = backend

    def handle_exit(self, sig, frame) -> None:
        self.backend.hub.close()
        super().handle_exit(sig, frame)


#: what uvicorn logs (logger "uvicorn.error") for every connection it answers 503 at --max-connections
OVER_LIMIT = "Exceeded concurrency limit."


class CountOverLimit(logging.Filter):
    """Counts uvicorn's line for a connection refused at --max-connections in ``refused`` ("connections", /health)
    and says it once, instead of a warning a connection (20 000 lines in 12 s of a probe's load)."""

    def __init__(self, refused: Tally, log: logging.Logger, limit: int) -> None:
        super().__init__()
        self.refused, self.log, self.limit = refused, log, limit
        self._said = False

    def filter(self, record: logging.LogRecord) -> bool:
        if record.getMessage() != OVER_LIMIT:
            return True
        self.refused.add("connections")
        if not self._said:
            self._said = True
            self.log.warning(
                "more than %d connections at once: the others are answered 503 (counted in /health, refused "
                "connections; --max-connections)",
                self.limit,
            )
        return False


#: what uvicorn logs (logger "uvicorn.error") for a response that ended before its last part
UNFINISHED = "ASGI callable returned without completing response."


class QuietGoneClients(logging.Filter):
    """Drops uvicorn's ERROR line for a response that ended unfinished when it is an event stream whose client had
    gone (services.api.routes.events.CLIENT_GONE, set in that request's context, where uvicorn logs the line): a
    probe's dashboard left 204 such lines in 18 minutes, none of them an error of the API's. Any other unfinished
    response is still said."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (record.getMessage() == UNFINISHED and CLIENT_GONE.get())


def serve(
    host: str,
    port: int,
    zenoh_config: zenoh.Config,
    options: ServeOptions = ServeOptions(),
    listener: socket.socket | None = None,
) -> int:
    """Serve the API and the viewer on http://host:port/ until stopped; returns the exit code. ``listener``: the socket
    already bound to host:port and listening (services.commands.api.listen_on), served on; None: uvicorn binds."""
    log = get_logger("api")
    stop = install_stop_event("api")  # uvicorn takes over SIGINT/SIGTERM while it runs; this keeps the parent watch
    session = open_session(zenoh_config, "the API", stop)
    try:
        backend = Backend.open(
            session,
            options.cache_bytes,
            options.query_timeout,
            options.max_maps,
            options.max_robots,
            options.stray_ttl,
            options.verify_window,
        )
        connections = fit_connections(options.max_connections, log)
        over_limit = CountOverLimit(backend.link.refused, log, connections)
        quiet = QuietGoneClients()
        for log_filter in (over_limit, quiet):
            logging.getLogger("uvicorn.error").addFilter(log_filter)
        try:
            app = Guard(
                HeadAsGet(
                    CachedTiles(create_app(backend, options.limits, token=options.token is not None), backend.tiles)
                ),
                allowed_hosts(host, list(options.allowed_hosts)),
                options.token,
            )
            config = uvicorn.Config(
                app,
                host=host,
                port=port,
                log_level="warning",
                access_log=False,
                lifespan="on",
                # uvicorn annotates both timeouts int but hands them to asyncio (wait_for, call_later): seconds
                # as float work, and the options are fractional seconds
                timeout_graceful_shutdown=GRACEFUL_SHUTDOWN,  # type: ignore[arg-type]  # float s: see above
                http=timed_protocol(options.request_timeout, backend.link.refused),
                timeout_keep_alive=options.keep_alive,  # type: ignore[arg-type]  # float s: see above
                # uvicorn refuses when the open connections, this one included, reach the limit
                limit_concurrency=connections + 1,
            )
            server = _Server(config, backend)

            def exit_when_stopped() -> None:
                stop.wait()
                backend.hub.close()
                server.should_exit = True

            threading.Thread(target=exit_when_stopped, daemon=True, name="api-stop").start()
            at = f"[{host}]" if ":" in host else host  # (an IPv6 address in a URL is bracketed)
            log.info(
                "serving on http://%s:%d/ (viewer), http://%s:%d/openapi.json (OpenAPI); maps known: %s",
                at,
                port,
                at,
                port,
                ", ".join(backend.registry.names()) or "none yet",
            )
            server.run(sockets=None if listener is None else [listener])
            return 0 if server.started else 1
        finally:
            for log_filter in (over_limit, quiet):
                logging.getLogger("uvicorn.error").removeFilter(log_filter)
            backend.close()
    finally:
        close_session(session, "the API")
