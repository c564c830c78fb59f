"""What the API holds at most, and the counters of what it refused for that (shown in /health).

Every limit is a `posegrid api` option (docs/api.md): maps and robots tracked (a peer making up map or robot
names must not grow the API's memory without bound), concurrent event streams and exports (each holds memory
or a thread while it runs), and the cells of one export's raster (allocated whole while it is built).
"""

from __future__ import annotations

import logging
import resource
import threading
from collections import Counter
from dataclasses import dataclass

#: concurrent GET /events streams (`--max-event-clients`)
MAX_EVENT_CLIENTS = 32
#: concurrent exports (`--max-exports`)
MAX_EXPORTS = 2
#: cells the raster of one export may span (`--max-export-cells`): 4096 x 4096, 205 m square at 0.05 m; the npz
#: carries EXPORT_BYTES_PER_CELL bytes a cell (about 218 MB at the limit)
MAX_EXPORT_CELLS = 1 << 24
#: bytes a cell of an npz export carries: log-odds, probability and variance (float32 each) and observed (bool)
EXPORT_BYTES_PER_CELL = 13
#: s a client refused for a busy slot is told to wait before it tries again (Retry-After)
RETRY_AFTER = 5
#: tile requests that may fetch or render at once (their own worker threads; FastAPI's pool keeps its 40 for
#: the other routes; services.api.routes.tiles)
TILE_THREADS = 16
#: connections open at once before requests get 503 (`--max-connections`)
MAX_CONNECTIONS = 256
#: file descriptors the API process holds besides its connections (it holds about 30 idle: its Zenoh session, the
#: event streams' pipes, files read at a request), kept free of --max-connections (:func:`fit_connections`)
FD_RESERVE = 64
#: s an idle keep-alive connection stays open (`--keep-alive-timeout`)
KEEP_ALIVE = 5.0
#: s a request may take to arrive whole (`--request-timeout`; services.api.protocol)
REQUEST_TIMEOUT = 10.0
#: maps the API holds at most, proved or pending (`--max-maps`; services.api.registry)
MAX_MAPS = 64
#: shard liveliness tokens that may wait for their shard's stats at once, over all maps
MAX_PENDING = 256
#: s a shard's liveliness token may stay unproved before it is forgotten (`--verify-window`; services.api.mappers)
VERIFY_WINDOW = 30.0
#: robots tracked at most, and robot names vouched for at most (`--max-robots`; services.api.robots)
MAX_ROBOTS = 256
#: s after its last pose that a robot no process token vouched for is forgotten (`--stray-robot-ttl`)
STRAY_TTL = 60.0
#: robot process liveliness tokens ("<robot>/<process>") held at most
MAX_PROCESSES = 1024


@dataclass(frozen=True)
class HttpLimits:
    """The limits the routes enforce."""

    event_clients: int = MAX_EVENT_CLIENTS
    exports: int = MAX_EXPORTS
    export_cells: int = MAX_EXPORT_CELLS


class Tally:
    """Thread-safe counts of refusals by what was at its limit ("maps", "robots", "exports", ...)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()

    def add(self, what: str) -> None:
        with self._lock:
            self._counts[what] += 1

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._counts)


class Slots:
    """At most ``size`` holders at once; :meth:`take` never waits. Thread-safe (exports run on worker threads,
    event streams on the event loop)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._lock = threading.Lock()
        self._taken = 0

    def take(self) -> bool:
        """Take a slot; False when all ``size`` are taken."""
        with self._lock:
            if self._taken >= self.size:
                return False
            self._taken += 1
            return True

    def give_back(self) -> None:
        with self._lock:
            self._taken -= 1

    @property
    def taken(self) -> int:
        return self._taken


def fit_connections(wanted: int, log: logging.Logger) -> int:
    """The connections the API may keep open at once: ``wanted`` (--max-connections) when the process may open that
    many files and FD_RESERVE more, after raising its soft limit (RLIMIT_NOFILE, `ulimit -n`) up to the hard one
    where it is lower; else fewer, said in a warning. Beyond its open-file limit a connection is reset, a request
    fails half sent or with a 500 (a module or file it opens), and uvicorn prints a traceback a request, where
    --max-connections promises a 503."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = wanted + FD_RESERVE
    if soft != resource.RLIM_INFINITY and soft < need:
        raised = need if hard == resource.RLIM_INFINITY else min(need, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (raised, hard))
            soft = raised
        except (ValueError, OSError):
            pass
    if soft == resource.RLIM_INFINITY or soft >= need:
        return wanted
    fitted = max(1, soft - FD_RESERVE, soft // 4)
    log.warning(
        "this process may open %d files (ulimit -n; hard limit %s): serving at most %d connections at once, not "
        "--max-connections %d (%d files are kept for the rest); raise the limit to serve more",
        soft,
        "none" if hard == resource.RLIM_INFINITY else hard,
        fitted,
        wanted,
        FD_RESERVE,
    )
    return fitted
