"""The state directory of a `posegrid run` (:func:`prepare_run`): run.json (the map, shard count, resolution, the
run's id and the sessions that wrote to it) and one state directory per shard, shard-<I>/ (services.state.store.db),
whose store records the run's id and refuses another run's."""

from __future__ import annotations

import fcntl
import json
import os
import shlex
import sys
import time
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from schemas.files import RASTER_RESOLUTION_LIMITS
from schemas.messages import MAX_SHARDS
from schemas.wire import NAME_RULE, is_valid_name
from services.state.store.db import StoreError, new_session_id

RUN_FILE = "run.json"
RUN_FORMAT = "posegrid-run"
RUN_VERSION = 1


@dataclass(frozen=True)
class RunState:
    """Where a run's shards keep their state, and the session they write (shared by every shard of the run, and kept
    when the launcher restarts a shard)."""

    directory: Path
    session: str
    resumed: bool  # the directory held a run before this one
    run_id: str = ""  # the run's own id, given to its shards' stores ("": none, a run.json written before it)
    continued: bool = False  # the session is the resumed run's latest (--continue-session), not a new one

    def shard_dir(self, shard: int) -> Path:
        return shard_dir(self.directory, shard)

    def shard_argv(self, shard: int) -> list[str]:
        """The `posegrid mapper` options of shard ``shard``."""
        return ["--state-dir", str(self.shard_dir(shard)), "--session", self.session] + (
            ["--run-id", self.run_id] if self.run_id else []
        )

    def describe(self) -> str:
        return f"{self.directory} (session {self.session}{', resumed' if self.resumed else ''})"


def default_run_dir(map_name: str) -> Path:
    """Where `posegrid run` keeps a run's state when no --state-dir, --resume or --no-state is given: a new folder
    ``posegrid/runs/<map>-<UTC date>-<time>-<pid>`` under ``$XDG_STATE_HOME`` (default ``~/.local/state``, also for
    a relative $XDG_STATE_HOME, which the XDG base directory specification says to ignore)."""
    given = os.environ.get("XDG_STATE_HOME") or ""
    base = Path(given) if os.path.isabs(given) else Path.home() / ".local" / "state"
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    return base / "posegrid" / "runs" / f"{map_name}-{stamp}-{os.getpid()}"


#: the run directories this process holds locked (resolved path -> the directory's open fd), until it exits
_HELD: dict[Path, int] = {}


def hold_run_directory(directory: Path, create: bool) -> None:
    """Lock ``directory`` (made first when ``create``) for the rest of this process, the launcher's life: another
    `posegrid run` on it is refused at once. Two new runs on one directory raced to write run.json (one then wrote
    the id and session, the other's shards the stores, which then refused every resume); two resumes both added a
    session. Held again by this process, it is a no-op. StoreError when it cannot be made or another holds it."""
    key = directory.resolve()
    if key in _HELD:
        return
    if directory.exists() and not directory.is_dir():
        raise StoreError(f"the state directory {directory} is not a directory")
    if not create and not directory.exists():
        return  # (prepare_run says what is wrong)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        held = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        raise StoreError(
            f"cannot use the state directory {directory}: {exc.strerror or exc}; give --state-dir DIR (a folder "
            "this user may write) or --no-state"
        ) from None
    try:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(held)
        raise StoreError(
            f"the state directory {directory} is in use by another posegrid run; give each run its own --state-dir"
        ) from None
    _HELD[key] = held


def shard_dir(directory: Path, shard: int) -> Path:
    """The state directory of shard ``shard`` in the run directory ``directory``."""
    return directory / f"shard-{shard}"


def prepare_run(
    directory: Path,
    resume: bool,
    continue_session: bool,
    map_name: str,
    shards: int,
    resolution: float,
    with_scans: Mapping[str, Collection[str]] | None = None,
    robot: str | None = None,
    unfinished: Mapping[str, Collection[str]] | None = None,
) -> RunState:
    """The state of a run in ``directory``: a new one (``resume`` False: the directory must be new or empty), or the
    run it holds (``resume``), with a new session or, with ``continue_session``, its latest one that holds scans
    (``with_scans``: the sessions the shards' stores hold scans of, each with the robots of those scans; None: the
    latest one). Raises StoreError (exit 2) for a directory that cannot be used, a run of another map, shard count or
    resolution, or a session to continue whose scans are of robots other than ``robot`` (the run's). A new session on
    a run whose latest session with scans holds a replay stopped before its end (``unfinished``: sessions -> those
    robots) is noted on stderr with the command that goes on with it instead: the same input would be fused twice."""
    path = directory / RUN_FILE
    record: dict[str, Any]
    if not resume:
        if path.exists():
            raise StoreError(f"{directory} holds a run already: continue it with --resume {directory}")
        if directory.is_dir() and any(directory.iterdir()):
            raise StoreError(f"the state directory {directory} is not empty and holds no run")
        record = {"format": RUN_FORMAT, "version": RUN_VERSION, "map": map_name, "shards": shards}
        record |= {"resolution": resolution, "sessions": [], "id": new_session_id()}
    else:
        record = check_run_options(directory, map_name, shards, resolution)
    record.setdefault("id", new_session_id())  # (a run.json written before runs had ids gets one)
    sessions = record["sessions"]
    if continue_session and not sessions:
        raise StoreError(f"{directory} holds no session to continue")
    session = _session_to_continue(sessions, with_scans) if continue_session else new_session_id()
    robots = sorted((with_scans or {}).get(session, ()))
    if continue_session and robot is not None and robots and robot not in robots:
        raise StoreError(
            f"--continue-session: session {session} of {directory} holds scans of robot {', '.join(robots)}, not of "
            f"{robot!r}: its replay under another name would be fused a second time. Give --robot {robots[0]}, or "
            "leave out --continue-session to fuse this robot in a new session on top of the map"
        )
    if not continue_session:
        if resume and unfinished:
            _note_unfinished(directory, sessions, with_scans, unfinished)
        sessions.append({"id": session, "started": time.time()})
    _write_run(path, directory, record)
    run_id = record.get("id")
    run_id = run_id if isinstance(run_id, str) and is_valid_name(run_id) else ""
    return RunState(directory, session, resume, run_id, continue_session)


def check_run_options(directory: Path, map_name: str, shards: int, resolution: float) -> dict[str, Any]:
    """The run record of ``directory`` (a run to resume), if its map, shard count and resolution (m) are the ones
    given; else StoreError naming the option to give. Checked before the shards' stores, whose own refusal of
    another map's state names no option of `posegrid run`."""
    record = _read_run(directory / RUN_FILE, directory)
    for option, key, value in (("--map", "map", map_name), ("--shards", "shards", shards)):
        if record[key] != value:
            raise StoreError(
                f"{directory} holds a run with {option} {record[key]}, not {value}: give {option} {record[key]}"
            )
    if record["resolution"] != resolution:
        raise StoreError(
            f"{directory} holds a map of {record['resolution']!r} m cells, not {resolution!r}: give "
            f"--resolution {record['resolution']!r}"
        )
    return record


def _session_to_continue(sessions: list[dict[str, Any]], with_scans: Collection[str] | None) -> str:
    """The latest of ``sessions`` that holds scans (of ``with_scans``; None: the latest). A resumed run stopped before
    its shards fused anything leaves a session that holds none: continuing it would lay the interrupted replay's
    scans once more over the map (a probe: 7 650 cells from the uninterrupted map, by up to 1.74 in log-odds)."""
    if with_scans is not None:
        for record in reversed(sessions):
            if record["id"] in with_scans:
                if record is not sessions[-1]:
                    print(
                        f"posegrid run: note: --continue-session goes on with session {record['id']}, the latest "
                        f"whose shards fused scans (the {len(sessions) - 1 - sessions.index(record)} after it fused "
                        "none)",
                        file=sys.stderr,
                    )
                return str(record["id"])
    return str(sessions[-1]["id"])


def _note_unfinished(
    directory: Path,
    sessions: list[dict[str, Any]],
    with_scans: Collection[str] | None,
    unfinished: Mapping[str, Collection[str]],
) -> None:
    """Say on stderr that the latest session with scans (of ``with_scans``) holds a replay stopped before its end
    (``unfinished``), which a new session would fuse again on top if it is the same input."""
    latest = next((str(r["id"]) for r in reversed(sessions) if with_scans is None or r["id"] in with_scans), None)
    if latest is None or latest not in unfinished:
        return
    robots = ", ".join(sorted(unfinished[latest]))
    print(
        f"posegrid run: note: session {latest} of {directory} stopped before its replay of robot {robots} ended; this "
        "run adds its input to the map as a new session. If it is the same input, stop now (Ctrl-C) and go on with "
        f"posegrid run --resume {shlex.quote(str(directory))} --continue-session (and the same input options): "
        "else its scans are fused twice",
        file=sys.stderr,
        flush=True,
    )


def run_id_of(directory: Path) -> str | None:
    """The id of the run ``directory`` holds (None: it holds none readable, or a run of before ids: prepare_run
    says what is wrong with it)."""
    try:
        run_id = _read_run(directory / RUN_FILE, directory).get("id")
    except StoreError:
        return None
    return run_id if isinstance(run_id, str) else None


def _read_run(path: Path, directory: Path) -> dict[str, Any]:
    """run.json of ``directory``, checked; StoreError when it is missing or no run's."""
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        if not directory.is_dir():
            raise StoreError(f"--resume {directory}: no such folder (the state directory of an earlier run)") from None
        raise StoreError(f"--resume {directory}: it holds no {RUN_FILE}, so no posegrid run") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise StoreError(f"{path} cannot be read: {exc}") from None
    ok = (
        isinstance(record, dict)
        and record.get("format") == RUN_FORMAT
        and isinstance(record.get("map"), str)
        and isinstance(record.get("shards"), int)
        and isinstance(record.get("resolution"), float)
        and isinstance(record.get("sessions"), list)
        and all(isinstance(s, dict) and isinstance(s.get("id"), str) for s in record["sessions"])
    )
    if not ok:
        raise StoreError(f"{path} is no posegrid run record")
    low, high = RASTER_RESOLUTION_LIMITS
    problem = (
        f"its map name {record['map']!r} is not valid ({NAME_RULE})"
        if not is_valid_name(record["map"])
        else f"its shard count {record['shards']} is not in [1, {MAX_SHARDS}]"
        if not 1 <= record["shards"] <= MAX_SHARDS
        else f"its resolution {record['resolution']!r} m is not in [{low:g}, {high:g}]"
        if not low <= record["resolution"] <= high  # (also NaN)
        else f"its id {record['id']!r} is not a valid name ({NAME_RULE})"
        if "id" in record and not (isinstance(record["id"], str) and is_valid_name(record["id"]))
        else None
    )
    if problem:
        raise StoreError(f"{path} is damaged: {problem}; restore it from a copy (it was not changed)")
    if record.get("version") != RUN_VERSION:
        raise StoreError(f"{path} has version {record.get('version')!r}; this build reads version {RUN_VERSION}")
    return record


def _write_run(path: Path, directory: Path, record: dict[str, Any]) -> None:
    """Write run.json through a temporary file, flushed to disk and renamed onto it; StoreError when it cannot be."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{RUN_FILE}.{os.getpid()}")
        with temporary.open("w") as file:
            json.dump(record, file, indent=2)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except OSError as exc:
        raise StoreError(f"cannot write to the state directory {directory}: {exc.strerror or exc}") from None
