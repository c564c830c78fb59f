"""Free TCP ports on loopback: for a router told to listen on port 0, `posegrid run`'s router, and the tests'
processes. A module of its own so that `posegrid router` does not import the launcher (and numba with it)."""

from __future__ import annotations

import socket


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]
