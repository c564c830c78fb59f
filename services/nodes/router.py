"""`posegrid router`: a Zenoh router inside a Python process, for machines without a zenohd binary.

The router holds no posegrid state; it routes publications, queries and liveliness between the other
processes, which connect to it as Zenoh clients (services/zenoh_config.py). With RUST_LOG set, zenoh's own
log goes to stderr: RUST_LOG=zenoh::net::routing::interceptor::access_control=trace shows every access control
decision of a secured router (docs/security.md).

On a stop it closes its session for at most CLOSE_TIMEOUT s. A close that takes longer (seen on a loaded 2-core
machine: the router still closing after the launcher's 15 s grace, which then killed it and failed a run whose map
was already exported) is said in one line, and the process ends at once with exit code 0: the router holds no
state, so nothing is lost, and its clients see the link drop as they would at a clean close.
"""

from __future__ import annotations

import os
import sys
import threading

import zenoh

from services.process import get_logger
from services.security import stale_roles
from services.zenoh_config import close_session, open_session, read_key

#: seconds the router waits for its zenoh session to close on a stop before it ends without waiting further
CLOSE_TIMEOUT = 5.0


def run_router(config: zenoh.Config, stop: threading.Event) -> int:
    """Route until ``stop`` is set, then close the session (CLOSE_TIMEOUT at most). Returns the exit code (0)."""
    log = get_logger("router")
    if os.environ.get("RUST_LOG"):
        zenoh.try_init_log_from_env()
    stale = stale_roles(read_key(config, "access_control"))
    if stale:
        log.warning(
            "the access rules of %s in this router's config are not the ones this posegrid writes (material made by "
            "an older posegrid?): the router would deny what their processes declare now, and they would wait for "
            "messages that never come; make the material again with `posegrid secure-init --force` "
            "(docs/security.md)",
            ", ".join(stale),
        )
    session = open_session(config, "the router")
    log.info("routing; listening on %s", ", ".join(read_key(config, "listen/endpoints") or []))
    try:
        while not stop.wait(0.5):
            pass
    finally:
        closer = threading.Thread(target=close_session, args=(session, "the router"), name="close", daemon=True)
        closer.start()
        closer.join(CLOSE_TIMEOUT)
        if closer.is_alive():
            log.warning(
                "zenoh's session close did not end within %g s; stopping without it (the router holds no state)",
                CLOSE_TIMEOUT,
            )
            _end_now(0)
    log.info("stopped")
    return 0


def _end_now(code: int) -> None:
    """End the process with ``code`` at once, its output flushed, without the interpreter's shutdown: that would
    wait on (or tear down under) the thread still inside zenoh's close."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
