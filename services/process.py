"""What every long-running posegrid process shares: a stop flag set by SIGINT/SIGTERM (or by the death of
the launcher that started it), stderr logging, and counting of rejected messages with one log line per kind.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import sys
import threading
from collections import Counter
from collections.abc import Callable
from typing import TypeVar

from services.keys import INVALID_KEY

#: set by the launcher in its children: the child stops when this process is no longer its parent
PARENT_PID_ENV = "POSEGRID_PARENT_PID"


def install_stop_event(name: str | None = None) -> threading.Event:
    """An event set on SIGINT, SIGTERM or SIGHUP, or when the launcher named in $POSEGRID_PARENT_PID goes away (said on
    the log of ``name``, the process's own, e.g. "mapper[0]": a launcher killed leaves each child saying so).

    Installs handlers explicitly, so a child started with SIGINT ignored (a background job) still stops.
    Call from the main thread.
    """
    stop = threading.Event()
    # A signal handler runs in the main thread between two of its bytecodes, maybe while that thread holds the
    # event's lock (inside stop.wait, or inside an earlier handler's stop.set when signals come in quick succession:
    # repeated Ctrl-C hung `posegrid run` for good, its children running on). Event.set takes that lock, so the
    # handler only puts on a SimpleQueue (whose put is reentrant, made for signal handlers) and a thread sets it.
    signals: queue.SimpleQueue[int] = queue.SimpleQueue()

    def set_on_signal() -> None:
        signals.get()
        stop.set()

    threading.Thread(target=set_on_signal, daemon=True, name="stop-on-signal").start()

    def handler(signum, frame):
        signals.put(signum)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGHUP, handler)  # (the terminal closed: `posegrid run --secure` left its keys behind)
    parent = os.environ.get(PARENT_PID_ENV)
    if parent and parent.isdigit():
        watch = (int(parent), stop, name)
        threading.Thread(target=_watch_parent, args=watch, daemon=True, name="parent-watch").start()
    return stop


class Stopped(Exception):
    """The process was asked to stop while it waited for something (a question to the histories, its input, a
    compile); nothing of what it waited for is taken."""


T = TypeVar("T")


def until_stopped(work: Callable[[], T], stop: threading.Event, what: str) -> T:
    """``work()``'s result, computed in a daemon thread named ``what``; its exception is raised here. Raises
    :class:`Stopped` as soon as ``stop`` is set first: work that cannot be interrupted (a simulation, a file read,
    a kernel compile) is left to end with the process, so a stop takes effect at once."""
    results: list[T] = []
    failures: list[Exception] = []

    def run() -> None:
        try:
            results.append(work())
        except Exception as exc:  # noqa: BLE001 - raised again in the caller's thread
            failures.append(exc)

    worker = threading.Thread(target=run, daemon=True, name=what)
    worker.start()
    while True:
        worker.join(0.1)
        if not worker.is_alive():
            break
        if stop.is_set():
            raise Stopped(f"stopped while {what}")
    if failures:
        raise failures[0]
    if not results:  # (the work ended by SystemExit or the like, which no thread should raise)
        raise RuntimeError(f"{what}: the work ended without a result")
    return results[0]


def _watch_parent(parent_pid: int, stop: threading.Event, name: str | None) -> None:
    while not stop.wait(0.5):
        if os.getppid() != parent_pid:
            log = logging.getLogger("posegrid") if name is None else get_logger(name)
            log.warning("the launcher (pid %d) is gone; stopping", parent_pid)
            stop.set()


def get_logger(name: str) -> logging.Logger:
    """A logger writing one line per record to stderr, prefixed with ``name`` (e.g. "mapper[0]")."""
    logger = logging.getLogger(f"posegrid.{name}")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(f"posegrid {name}: %(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        logger.propagate = False
    return logger


#: distinct keys a :class:`RejectCounter` counts under their own name; rejections on further keys (a peer making up
#: key after key) are counted under OTHER_KEYS, so the counter's memory stays bounded
MAX_REJECT_KEYS = 256
OTHER_KEYS = "<other keys>"
#: the longest key a :class:`RejectCounter` counts under its own name (posegrid's keys take well under 100
#: characters); a longer one, or one with a character that is not printable ASCII, is a peer's making and is counted
#: under services.keys.INVALID_KEY (256 keys of 60 000 characters made every /health answer 15 MB)
MAX_KEY_LABEL = 200
#: the most characters of a rejection's detail that are logged (non-printable ones escaped: a key with a newline
#: wrote a forged line into the log)
MAX_DETAIL_LOGGED = 500


class WarnOnce:
    """Logs each distinct warning once (a process that looks at the same problem every loop says it once)."""

    def __init__(self, logger: logging.Logger):
        self._logger = logger
        self.said: set[str] = set()

    def __call__(self, text: str) -> None:
        if text not in self.said:
            self.said.add(text)
            self._logger.warning("%s", text)


def _loggable(text: str) -> str:
    """``text`` cut to MAX_DETAIL_LOGGED characters, with every character that is not printable ASCII escaped (a
    newline, a NUL, a right-to-left mark), so that one log line stays one line of what posegrid wrote."""
    cut = text[:MAX_DETAIL_LOGGED] + ("..." if len(text) > MAX_DETAIL_LOGGED else "")
    return cut if cut.isascii() and cut.isprintable() else cut.encode("unicode_escape").decode("ascii")


class RejectCounter:
    """Counts dropped messages by key and kind, and logs the first one of each (key, kind).

    Thread-safe: zenoh callbacks and the main loop may both count. At most :data:`MAX_REJECT_KEYS` keys are
    counted by name; the rest go under :data:`OTHER_KEYS`.
    """

    def __init__(self, logger: logging.Logger):
        self._logger = logger
        self._lock = threading.Lock()
        self._logged: set[tuple[str, str]] = set()
        self.by_key: Counter[str] = Counter()
        self.by_kind: Counter[str] = Counter()

    def count(self, key: str, kind: str, detail: str, times: int = 1) -> None:
        """Count ``times`` messages on ``key`` dropped for ``kind``; log ``detail`` the first time per (key, kind).
        A key past MAX_KEY_LABEL characters or with characters that are not printable ASCII is counted under
        services.keys.INVALID_KEY; the detail is logged escaped and cut to MAX_DETAIL_LOGGED characters."""
        if len(key) > MAX_KEY_LABEL or not (key.isascii() and key.isprintable()):
            detail = f"on {key[:MAX_KEY_LABEL]!r}: {detail}"
            key = INVALID_KEY
        with self._lock:
            if key not in self.by_key and len(self.by_key) >= MAX_REJECT_KEYS:
                key = OTHER_KEYS
            self.by_key[key] += times
            self.by_kind[kind] += times
            first = (key, kind) not in self._logged
            self._logged.add((key, kind))
        if first:
            self._logger.warning(
                "dropped a message on %s (%s): %s; further ones of this kind are only counted",
                key,
                kind,
                _loggable(detail),
            )

    def snapshot(self) -> dict[str, int]:
        """Rejections by key."""
        with self._lock:
            return dict(self.by_key)

    def kinds(self) -> dict[str, int]:
        """Rejections by kind (e.g. "ahead", "size", "key")."""
        with self._lock:
            return dict(self.by_kind)
