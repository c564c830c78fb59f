"""The poses a SLAM node has published, kept for its history (pg/<robot>/history/pose, services.history).

The one part of a node's state that its Zenoh callbacks read while the node's thread works: a question for the
poses is answered at once, whatever the filter is doing (a step, or a question of its own to the source's history
that may wait 35 s). A CI run of the suite: the node asked the source's history for the tail of an ended stream
while holding its lock, and a question for its poses, waiting on that lock, got nothing in 30 s.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable


class PoseHistory:
    """Published poses (encoded) by seq, in the order published, within ``max_bytes`` (the oldest go first).
    Thread-safe: one thread keeps, any reads."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._poses: OrderedDict[int, bytes] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()  # held only to file or copy out: never while waiting

    def keep(self, seq: int, payload: bytes) -> None:
        """Keep the pose of ``seq`` (one published again replaces the first, and moves to the end)."""
        with self._lock:
            old = self._poses.pop(seq, None)
            self._bytes += len(payload) - (0 if old is None else len(old))
            self._poses[seq] = payload
            while self._bytes > self.max_bytes:
                self._bytes -= len(self._poses.popitem(last=False)[1])

    def poses(self, wants: Callable[[int], bool]) -> list[bytes]:
        """The poses kept whose seq ``wants`` takes, in the order they were published."""
        with self._lock:
            kept = list(self._poses.items())
        return [payload for seq, payload in kept if wants(seq)]
