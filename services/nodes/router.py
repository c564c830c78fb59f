"""`posegrid router`: a Zenoh router inside a Python process, for machines without a zenohd binary.

The router holds no posegrid state; it routes publications, queries and liveliness between the other
processes, which connect to it as Zenoh clients (services/zenoh_config.py). With RUST_LOG set, zenoh's own
log goes to stderr: RUST_LOG=zenoh::net::routing::interceptor::access_control=trace shows every access control
decision of a secured router (docs/security.md).
"""

from __future__ import annotations

import os
import threading

import zenoh

from services.process import get_logger
from services.zenoh_config import close_session, open_session, read_key


def run_router(config: zenoh.Config, stop: threading.Event) -> int:
    """Route until ``stop`` is set, then close the session. Returns the exit code (0)."""
    log = get_logger("router")
    if os.environ.get("RUST_LOG"):
        zenoh.try_init_log_from_env()
    session = open_session(config, "the router")
    log.info("routing; listening on %s", ", ".join(read_key(config, "listen/endpoints") or []))
    try:
        while not stop.wait(0.5):
            pass
    finally:
        close_session(session, "the router")
    log.info("stopped")
    return 0
