"""Runs the API under uvicorn on one Zenoh session until SIGINT/SIGTERM or the launcher's death."""
from __future__ import annotations

import threading

import uvicorn
import zenoh

from services.api.app import Backend, create_app
from services.api.fastpath import CachedTiles
from services.api.head import HeadAsGet
from services.process import get_logger, install_stop_event
from services.zenoh_config import open_session

#: seconds open connections (event streams) get to finish when the server stops
GRACEFUL_SHUTDOWN = 2.0


class _Server(uvicorn.Server):
    """uvicorn's server that also ends the event streams when it is told to exit."""

    def __init__(self, config: uvicorn.Config, backend: Backend) -> None:
        super().__init__(config)
        self.backend = backend

    def handle_exit(self, sig, frame) -> None:
        self.backend.hub.close()
        super().handle_exit(sig, frame)


def serve(host: str, port: int, zenoh_config: zenoh.Config, cache_bytes: int, query_timeout: float) -> int:
    """Serve the API and the viewer on http://host:port/ until stopped; returns the exit code."""
    log = get_logger("api")
    stop = install_stop_event()  # uvicorn takes over SIGINT/SIGTERM while it runs; this keeps the parent watch
    session = open_session(zenoh_config, "the API")
    try:
        backend = Backend.open(session, cache_bytes, query_timeout)
        try:
            config = uvicorn.Config(HeadAsGet(CachedTiles(create_app(backend), backend.tiles)), host=host, port=port,
                                    log_level="warning", access_log=False, lifespan="on",
                                    timeout_graceful_shutdown=GRACEFUL_SHUTDOWN)
            server = _Server(config, backend)

            def exit_when_stopped() -> None:
                stop.wait()
                backend.hub.close()
                server.should_exit = True

            threading.Thread(target=exit_when_stopped, daemon=True, name="api-stop").start()
            log.info("serving on http://%s:%d/ (viewer), http://%s:%d/openapi.json (OpenAPI); maps known: %s",
                     host, port, host, port, ", ".join(backend.registry.names()) or "none yet")
            server.run()
            return 0 if server.started else 1
        finally:
            backend.close()
    finally:
        session.close()
