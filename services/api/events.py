"""The server-sent event stream (GET /events): tile changes and poses, batched for the viewer.

Zenoh callbacks (any thread) only record what changed; a task on the event loop flushes every
``interval`` seconds, so a tile that changes 50 times a second is announced at most once per flush and a
robot's pose at most once (the latest). Events (``event:`` name, ``data:`` one JSON object):

- ``hello``: ``{"epoch": ...}`` first, once per connection;
- ``tiles``: ``{"map": name, "tiles": [[tx, ty, version], ...]}``: level-0 tiles that changed, with
  their new versions (a level-z tile (x, y) changed when a changed tile has (tx >> z, ty >> z) == (x, y));
- ``pose``: ``{"robot", "seq", "stamp", "mean", "covariance", "samples", "weights"}`` with at most
  :data:`EVENT_SAMPLES` samples (services.api.robots.reduce_samples);
- ``resync``: ``{}``: this client fell more than ``backlog`` flushes behind and missed events; reload.

A comment line is sent every :data:`KEEPALIVE` seconds of silence, so proxies keep the connection open.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator

from services.api.robots import PoseSummary, reduce_samples

#: samples a pose event carries at most
EVENT_SAMPLES = 200
#: seconds of silence after which a keep-alive comment is sent: so proxies keep the connection open, and so that a
#: client that left with a request queued behind its stream, which the server does not see go (it reads no more of
#: that connection), gives its --max-event-clients slot back within that time (at 15 s, 32 such clients locked every
#: viewer of an idle map out for 15 s)
KEEPALIVE = 2.0


def sse(event: str, data: dict) -> str:
    """One server-sent event."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def pose_event(summary: PoseSummary) -> dict:
    samples, weights = reduce_samples(summary.samples, summary.weights, EVENT_SAMPLES)
    return {
        "robot": summary.robot,
        "seq": summary.seq,
        "stamp": summary.stamp,
        "mean": summary.mean.tolist(),
        "covariance": summary.cov.tolist(),
        "samples": samples.round(4).tolist(),
        "weights": weights.tolist(),
    }


class EventHub:
    """Collects changes from any thread and fans them out to every connected client."""

    def __init__(self, epoch: str, interval: float = 0.25, backlog: int = 64) -> None:
        self.epoch = epoch
        self.interval = interval
        self.backlog = backlog
        self._lock = threading.Lock()
        self._tiles: dict[str, dict[tuple[int, int], int]] = {}
        self._poses: dict[str, PoseSummary] = {}
        self._clients: set[asyncio.Queue] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = asyncio.Event()

    # ---------------------------------------------------------------------------- any thread
    def tile_changed(self, map_name: str, tile: tuple[int, int], version: int) -> None:
        with self._lock:
            self._tiles.setdefault(map_name, {})[tile] = version

    def pose(self, summary: PoseSummary) -> None:
        with self._lock:
            self._poses[summary.robot] = summary

    def close(self) -> None:
        """End every stream (safe from any thread and from a signal handler)."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._closed.set)

    # ---------------------------------------------------------------------------- event loop
    async def run(self) -> None:
        """Flush every ``interval`` seconds until cancelled (started by the app's lifespan)."""
        self._loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(self.interval)
            self.flush()

    def flush(self) -> None:
        with self._lock:
            tiles, self._tiles = self._tiles, {}
            poses, self._poses = self._poses, {}
        if not self._clients:
            return
        events = [
            sse("tiles", {"map": name, "tiles": [[tx, ty, v] for (tx, ty), v in sorted(changed.items())]})
            for name, changed in sorted(tiles.items())
        ]
        events += [sse("pose", pose_event(summary)) for _, summary in sorted(poses.items())]
        if not events:
            return
        batch = "".join(events)
        for queue in self._clients:
            if queue.full():
                while not queue.empty():
                    queue.get_nowait()
                queue.put_nowait(sse("resync", {}))
            else:
                queue.put_nowait(batch)

    async def stream(self) -> AsyncIterator[str]:
        """One client's events, until the hub closes or the client goes away (the generator is closed)."""
        queue: asyncio.Queue[str] = asyncio.Queue(self.backlog)
        self._clients.add(queue)
        closed = asyncio.ensure_future(self._closed.wait())
        getter: asyncio.Future | None = None
        try:
            yield "retry: 2000\n\n" + sse("hello", {"epoch": self.epoch})
            while not self._closed.is_set():
                getter = asyncio.ensure_future(queue.get())
                done, _ = await asyncio.wait({getter, closed}, timeout=KEEPALIVE, return_when=asyncio.FIRST_COMPLETED)
                if getter in done:
                    yield getter.result()
                else:
                    getter.cancel()
                    if not done:
                        yield ": keep-alive\n\n"
        finally:  # a client gone inside asyncio.wait leaves its getter pending: cancel it with the rest
            closed.cancel()
            if getter is not None:
                getter.cancel()
            self._clients.discard(queue)

    @property
    def clients(self) -> int:
        return len(self._clients)
