"""Sending on Zenoh from a test as the project's own publishers send: with congestion control BLOCK.

Zenoh's default for a put, DROP, lets it drop a message when the session's queue is full, which happens now and
then on a busy machine: a test that counts what arrives (or proves that something does not) would then fail, or
pass, for the wrong reason. Every source, SLAM node and shard of the project publishes with BLOCK.
"""

from __future__ import annotations

from typing import Any

import zenoh

BLOCK = zenoh.CongestionControl.BLOCK


def put(session: zenoh.Session, key: str, payload: bytes, **options: Any) -> None:
    """``session.put(key, payload, **options)`` with congestion control BLOCK."""
    session.put(key, payload, congestion_control=BLOCK, **options)
