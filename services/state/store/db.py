"""One mapper shard's database: SQLite in WAL mode, one file per shard in its state directory (docs/persistence.md).

Tables:
- ``meta`` (key, value): the store's format and schema version and what it belongs to (map, shard index and count,
  tile size, resolution), the cell updates fused so far and the Unix time of the last commit;
- ``sessions`` (ordinal, id, started): the sessions that have written to it, oldest first;
- ``tiles`` (tx, ty, robot, seq, layers): every tile's layers (log-odds float32, variance float32, observed as bits,
  over the window of its cells a scan touched, zlib-compressed together: :func:`encode_layers`; sealed with a CRC-32
  of the whole row: :func:`seal_tile`) and the last scan fused into it;
- ``robots`` (session, robot, fused, discarded, ended, next_seq, checksum): per session and robot, the scans fused and
  given up, the scans the stream's end announced, the seq below which every scan is fused or given up, and a CRC-32
  of those values (:func:`robot_check`; NULL in a row a schema-1 store holds);
- ``ledger`` (session, robot, seq, scan, pose): the digests of the scan and pose fused for each seq, kept for the
  seqs a shard still compares a re-sent message with (services.state.join.SeqLedger's horizon).

A commit writes one batch (:class:`Batch`: the tiles changed since the last one, every robot's counts and the new
ledger entries) in one transaction, so the file always holds a prefix of the run.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import secrets
import sqlite3
import struct
import time
import zlib
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from schemas.messages import MAX_SEQ, MAX_TILE_INDEX
from schemas.wire import NAME_RULE, is_valid_name
from services.errors import UsageError
from services.state.ownership import owns_tile

#: what the ``meta`` table's ``format`` says: the file is a posegrid shard's store
FORMAT = "posegrid-shard-store"
#: the layout of the tables; a store of another version is refused, not guessed at. 2: a tile's layers are sealed
#: with a CRC-32 of its whole row, and a robots row carries one of its values (a bit flipped in a tile's window, which
#: zlib's own check does not cover, moved the tile by a cell, unsaid); a store of version 1 is brought to 2 when a
#: shard opens it (its rows are read as they were written, unchecked, until they are written again)
SCHEMA_VERSION = 2
#: the versions a shard opens
READ_VERSIONS = (1, 2)
#: the first bytes of a tile's sealed layers (:func:`seal_tile`); as a schema-1 window's row0 (uint32) it is far past
#: any tile, so a tile of either version is told apart, and a flipped bit in it is refused
SEALED = b"PGT2"
#: the database file and the lock file in a shard's state directory
DB_NAME = "shard.sqlite"
LOCK_NAME = "shard.lock"
#: zlib level of the tile layers: the fastest; on the simulated office with 30 pose samples a scan (noisy floats) it
#: halves a tile in about 12 ms, and higher levels gain a few per cent for two to three times the time
COMPRESSION_LEVEL = 1
#: SQLite's magic string, the first 16 bytes of every database file
SQLITE_HEADER = b"SQLite format 3\x00"

TileKey = tuple[int, int]

_TABLES = (
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value) WITHOUT ROWID",
    "CREATE TABLE sessions (ordinal INTEGER PRIMARY KEY, id TEXT NOT NULL UNIQUE, started REAL NOT NULL)",
    (
        "CREATE TABLE tiles (tx INTEGER NOT NULL, ty INTEGER NOT NULL, robot TEXT NOT NULL, seq INTEGER NOT NULL, "
        "layers BLOB NOT NULL, PRIMARY KEY (tx, ty))"
    ),
    (
        "CREATE TABLE robots (session TEXT NOT NULL, robot TEXT NOT NULL, fused INTEGER NOT NULL, discarded INTEGER "
        "NOT NULL, ended INTEGER, next_seq INTEGER NOT NULL, checksum INTEGER, PRIMARY KEY (session, robot)) WITHOUT "
        "ROWID"
    ),
    (
        "CREATE TABLE ledger (session TEXT NOT NULL, robot TEXT NOT NULL, seq INTEGER NOT NULL, scan BLOB NOT NULL, "
        "pose BLOB NOT NULL, PRIMARY KEY (session, robot, seq)) WITHOUT ROWID"
    ),
)


class StoreError(UsageError):
    """A state directory or store that a shard cannot use: one sentence saying why (the shard exits 2)."""


class StoreWriteError(Exception):
    """A commit that failed (disk full, I/O error, the store's size limit); the store holds the previous one."""


@dataclass(frozen=True)
class StoreIdentity:
    """What a store belongs to; a shard refuses a store of any other (map, shard, shards, tile size, resolution)."""

    map_name: str
    shard: int
    shards: int
    tile_size: int  # cells per tile side
    resolution: float  # m per cell

    def describe(self) -> str:
        return (
            f"shard {self.shard} of {self.shards} of map {self.map_name!r} (tiles of {self.tile_size} cells, "
            f"{self.resolution:g} m cells)"
        )


@dataclass(frozen=True)
class TileState:
    """One tile's layers, (T, T) each, row = y (mapping.grid), and the last scan fused into it."""

    key: TileKey
    logodds: np.ndarray  # float32
    variance: np.ndarray  # float32
    observed: np.ndarray  # bool
    robot: str
    seq: int


@dataclass(frozen=True)
class RobotState:
    """One robot's counts in a session: scans fused, given up, announced by its end (None: no end yet), and the seq
    below which every scan is fused or given up."""

    robot: str
    fused: int
    discarded: int
    ended: int | None
    next_seq: int


@dataclass(frozen=True)
class LedgerEntry:
    """A fused seq and the digests (schemas.wire.Message.digest) of the scan and the pose fused."""

    robot: str
    seq: int
    scan: bytes
    pose: bytes


@dataclass
class Batch:
    """What one commit writes: the tiles changed since the last commit, every robot's counts, the new ledger entries,
    the lowest seq whose ledger entry is still needed by robot (older ones are deleted), the cell updates so far and
    the scans fused or given up since the last commit (``scans``)."""

    tiles: list[TileState] = field(default_factory=list)
    robots: list[RobotState] = field(default_factory=list)
    ledger: list[LedgerEntry] = field(default_factory=list)
    keep_from: dict[str, int] = field(default_factory=dict)
    cells_updated: int = 0
    scans: int = 0


@dataclass
class StoredState:
    """What a store holds for a shard that starts on it: every tile, and its session's robots and ledger."""

    session: str
    tiles: list[TileState]
    robots: dict[str, RobotState]
    ledger: list[LedgerEntry]  # in seq order
    cells_updated: int
    committed_at: float | None  # Unix time of the last commit, s (None: none yet)


def new_session_id() -> str:
    """A new session id: the UTC time and 6 random hex digits, e.g. 20250101T120000Z-3fa9c1."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + secrets.token_hex(3)


#: the header of a tile's blob: the window (row0, col0, rows, cols) outside which every layer is zero, uint32 each
_WINDOW = np.dtype("<u4")


def encode_layers(logodds: np.ndarray, variance: np.ndarray, observed: np.ndarray) -> bytes:
    """A tile's three layers as one blob: the window of its cells that are not all zero (row0, col0, rows, cols as
    little-endian uint32), then, zlib-compressed, the window's log-odds and variance as little-endian float32 and its
    observed cells as bits (numpy.packbits, row-major). Cells a scan never touched are zero in every layer, so a tile
    the robot saw a corner of costs what the corner does."""
    touched = observed | (logodds != 0) | (variance != 0)
    rows, cols = np.flatnonzero(touched.any(axis=1)), np.flatnonzero(touched.any(axis=0))
    if rows.size == 0:
        window = (0, 0, 0, 0)
    else:
        window = (int(rows[0]), int(cols[0]), int(rows[-1] + 1 - rows[0]), int(cols[-1] + 1 - cols[0]))
    inside = (slice(window[0], window[0] + window[2]), slice(window[1], window[1] + window[3]))
    raw = (
        np.ascontiguousarray(logodds[inside], "<f4").tobytes()
        + np.ascontiguousarray(variance[inside], "<f4").tobytes()
        + np.packbits(observed[inside]).tobytes()
    )
    return np.array(window, _WINDOW).tobytes() + zlib.compress(raw, COMPRESSION_LEVEL)


def decode_layers(blob: bytes, tile_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (logodds, variance, observed) of a blob :func:`encode_layers` wrote; ValueError when it is not one."""
    head = 4 * _WINDOW.itemsize
    if len(blob) < head:
        raise ValueError(f"its layers are {len(blob)} bytes, shorter than their header")
    row0, col0, rows, cols = (int(v) for v in np.frombuffer(blob, _WINDOW, 4))
    if row0 + rows > tile_size or col0 + cols > tile_size:
        raise ValueError(f"its window ({row0}, {col0}, {rows}, {cols}) exceeds a {tile_size}x{tile_size} tile")
    cells = rows * cols
    size = 8 * cells + (cells + 7) // 8  # the window's log-odds and variance (float32) and observed bits
    try:  # inflated to one byte past the window's size at most: a 2 MB blob of zeros inflated to 2 GB before
        inflater = zlib.decompressobj()
        raw = inflater.decompress(blob[head:], size + 1)
    except zlib.error as exc:
        raise ValueError(f"its layers do not decompress ({exc})") from None
    if len(raw) != size or not inflater.eof:
        held = f"more than {size}" if len(raw) > size else str(len(raw))
        raise ValueError(f"its layers hold {held} bytes, not the {size} of a {rows}x{cols} window")
    shape, inside = (tile_size, tile_size), (slice(row0, row0 + rows), slice(col0, col0 + cols))
    logodds, variance, observed = np.zeros(shape, np.float32), np.zeros(shape, np.float32), np.zeros(shape, bool)
    logodds[inside] = np.frombuffer(raw, "<f4", cells).reshape(rows, cols)
    variance[inside] = np.frombuffer(raw, "<f4", cells, 4 * cells).reshape(rows, cols)
    observed[inside] = np.unpackbits(np.frombuffer(raw, np.uint8, offset=8 * cells), count=cells).reshape(rows, cols)
    if not (np.isfinite(logodds).all() and np.isfinite(variance).all() and (variance >= 0).all()):
        raise ValueError("its layers hold values no fusion writes (not finite, or a negative variance)")
    return logodds, variance, observed


def _tile_check(key: TileKey, robot: str, seq: int, layers: bytes) -> int:
    """CRC-32 of a tile's row: its index, the last scan fused into it and its layers as :func:`encode_layers` wrote
    them."""
    return zlib.crc32(struct.pack("<qq", *key) + robot.encode() + struct.pack("<Bq", 0, seq) + layers)


def seal_tile(key: TileKey, robot: str, seq: int, layers: bytes) -> bytes:
    """A tile's layers as a schema-2 store holds them: SEALED, the CRC-32 of its row (little-endian uint32), the
    layers."""
    return SEALED + struct.pack("<I", _tile_check(key, robot, seq, layers)) + layers


def unseal_tile(key: TileKey, robot: str, seq: int, blob: bytes) -> bytes:
    """The layers of a tile's stored ``blob`` (:func:`seal_tile`; a schema-1 blob is the layers themselves);
    ValueError when its row does not match its check."""
    if not blob.startswith(SEALED):
        return blob
    if len(blob) < len(SEALED) + 4:
        raise ValueError(f"its layers are {len(blob)} bytes, shorter than their seal")
    layers = blob[len(SEALED) + 4 :]
    (stored,) = struct.unpack_from("<I", blob, len(SEALED))
    if stored != _tile_check(key, robot, seq, layers):
        raise ValueError("its row does not match its checksum (a changed byte in its index, scan, window or cells)")
    return layers


def _layers_of(tile: TileState) -> bytes:
    """:func:`encode_layers` of ``tile``'s layers."""
    return encode_layers(tile.logodds, tile.variance, tile.observed)


def robot_check(session: str, state: RobotState) -> int:
    """CRC-32 of a robots row of ``session``."""
    ended = -1 if state.ended is None else state.ended
    counts = struct.pack("<qqqq", state.fused, state.discarded, ended, state.next_seq)
    return zlib.crc32(session.encode() + b"\0" + state.robot.encode() + b"\0" + counts)


class ShardStore:
    """An open store (:meth:`open`): loads the state (:meth:`load`) and commits batches (:meth:`commit`). The
    state directory is locked (flock on shard.lock) while it is open, so two shard processes never write one store.
    Not thread-safe: one thread at a time (services.state.store.writer hands it to its thread)."""

    def __init__(
        self, directory: Path, connection: sqlite3.Connection, lock: int, session: str, identity: StoreIdentity
    ):
        self.directory = directory
        self.path = directory / DB_NAME
        self._db = connection
        self._lock = lock
        self.session = session
        self._tile_size = identity.tile_size
        self._owns = owns_tile(identity.shard, identity.shards)
        self._file = _file_identity(self.path)  # (what commit checks the path still names)

    # ------------------------------------------------------------------------------------------ opening
    @classmethod
    def open(
        cls,
        directory: Path,
        identity: StoreIdentity,
        session: str | None = None,
        max_bytes: int | None = None,
        run_id: str | None = None,
    ) -> ShardStore:
        """Open (or create) the store in ``directory`` for ``identity``; ``session``: the session this shard writes
        (None: the store's latest, or a new one); ``max_bytes``: the most the database file may grow to (None: no
        limit); ``run_id``: the `posegrid run` the store belongs to (recorded in a store that has none; None: not
        checked). Raises :class:`StoreError` when the directory cannot be written or the store is damaged,
        truncated, foreign, another shard's or another run's."""
        for option, name in (("--session", session), ("--run-id", run_id)):
            if name is not None and not is_valid_name(name):
                raise StoreError(f"{option} {name!r} is not a valid name ({NAME_RULE})")
        lock = _lock_directory(directory)
        path, created = directory / DB_NAME, False
        try:
            created = not _check_file(path, tidy=True)
            if not created:
                _refuse_a_foreign_log(path)
            connection = _connect(path, max_bytes)
            try:
                if created:
                    _create(connection, path, identity)
                else:
                    _check_integrity(connection, path)
                    _check_meta(connection, path, identity)
                if run_id is not None:
                    _check_run(connection, path, run_id)
                if not created:  # (after the checks that refuse it as another's: a refused store is left as it was)
                    _bring_to_current(connection, path)
                chosen = _register_session(connection, path, session)
            except BaseException:
                connection.close()
                raise
        except BaseException:
            if created:  # (a store this call began and could not finish, say on a full disk, is no store at all)
                for leftover in (path, Path(f"{path}-wal"), Path(f"{path}-shm")):
                    leftover.unlink(missing_ok=True)
            os.close(lock)
            raise
        return cls(directory, connection, lock, chosen, identity)

    # ------------------------------------------------------------------------------------------ reading
    def load(self) -> StoredState:
        """Every tile, and this session's robots and ledger. Raises :class:`StoreError` for a damaged tile."""
        db = self._db
        try:
            tiles = [self._tile(row) for row in db.execute("SELECT tx, ty, robot, seq, layers FROM tiles")]
            rows = db.execute(
                "SELECT session, robot, fused, discarded, ended, next_seq, checksum FROM robots"
            ).fetchall()
            known = {row[0] for row in db.execute("SELECT id FROM sessions")}
            ledger = [
                LedgerEntry(*row)
                for row in db.execute(
                    "SELECT robot, seq, scan, pose FROM ledger WHERE session = ? ORDER BY robot, seq", (self.session,)
                )
            ]
            meta = dict(db.execute("SELECT key, value FROM meta WHERE key IN ('cells_updated', 'committed_at')"))
        except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
            raise StoreError(f"the store {self.path} cannot be read ({exc}): it is damaged") from None
        states = [(row[0], self._robot(row, known)) for row in rows]  # (every session's: each row checked)
        robots = {state.robot: state for session, state in states if session == self.session}
        for entry in ledger:
            name: object = entry.robot
            if not (isinstance(name, str) and is_valid_name(name) and _whole(entry.seq, 0, MAX_SEQ)):
                raise StoreError(
                    f"the store {self.path} holds a ledger entry of robot {name!r}, seq {entry.seq!r}, which no shard "
                    "writes: it is damaged"
                )
        cells_updated, committed_at = meta.get("cells_updated") or 0, meta.get("committed_at")
        if not _whole(cells_updated, 0) or not (committed_at is None or isinstance(committed_at, (int, float))):
            raise StoreError(
                f"the store {self.path} holds a meta value no shard writes (cells_updated {cells_updated!r}, "
                f"committed_at {committed_at!r}): it is damaged"
            )
        return StoredState(self.session, tiles, robots, ledger, cells_updated, committed_at)

    def _tile(self, row: tuple) -> TileState:
        tx, ty, robot, seq, blob = row
        where = f"tile ({tx!r}, {ty!r}) of the store {self.path}"
        if not (_whole(tx, -MAX_TILE_INDEX, MAX_TILE_INDEX) and _whole(ty, -MAX_TILE_INDEX, MAX_TILE_INDEX)):
            raise StoreError(f"{where} has an index no map holds: it is damaged")
        if not (
            isinstance(robot, str) and is_valid_name(robot) and _whole(seq, 0, MAX_SEQ) and isinstance(blob, bytes)
        ):
            raise StoreError(f"{where} has a robot {robot!r} or seq {seq!r} no shard writes: it is damaged")
        if not self._owns(tx, ty):
            raise StoreError(
                f"{where} is another shard's (tiles go to shards by services.state.ownership): it was copied in; "
                "remove the tile or restore the store"
            )
        try:
            logodds, variance, observed = decode_layers(unseal_tile((tx, ty), robot, seq, blob), self._tile_size)
        except ValueError as exc:
            raise StoreError(f"{where} is damaged: {exc}") from None
        return TileState((tx, ty), logodds, variance, observed, robot, seq)

    def _robot(self, row: tuple, sessions: Collection[object]) -> RobotState:
        """The robots row ``row`` (session, robot, fused, discarded, ended, next_seq, checksum); StoreError for one of
        values no shard writes, of a session not in ``sessions`` (the store's), or whose checksum does not match (None:
        a row of a schema-1 store). Every session's rows are checked: a changed session name moved a row out of
        sight, and the shard then wrote its robot's counts anew."""
        session, state, checksum = row[0], RobotState(*row[1:6]), row[6]
        counts = (state.fused, state.discarded, state.next_seq) + (() if state.ended is None else (state.ended,))
        robot: object = state.robot  # (as the row held it: the dataclass does not check its types)
        if not (isinstance(robot, str) and is_valid_name(robot)) or not all(_whole(c, 0, MAX_SEQ + 1) for c in counts):
            raise StoreError(
                f"the store {self.path} holds robot {state.robot!r} with counts {counts!r}, which no shard writes: "
                "it is damaged"
            )
        if session not in sessions:
            raise StoreError(
                f"the store {self.path} holds robot {state.robot!r} of session {session!r}, which it does not record: "
                "it is damaged"
            )
        if checksum is not None and checksum != robot_check(str(session), state):
            raise StoreError(
                f"the store {self.path} holds robot {state.robot!r} with counts {counts!r}, which do not match their "
                "checksum: it is damaged"
            )
        return state

    def sessions(self) -> list[str]:
        """The ids of the sessions that have written to this store, oldest first."""
        return [row[0] for row in self._db.execute("SELECT id FROM sessions ORDER BY ordinal")]

    # ------------------------------------------------------------------------------------------ writing
    def commit(self, batch: Batch) -> float:
        """Write ``batch`` in one transaction; returns the commit's Unix time (s). Raises :class:`StoreWriteError`
        (after rolling back) when SQLite or the disk refuses it."""
        session, db = self.session, self._db
        now = time.time()
        gone = self._gone()
        if gone:
            raise StoreWriteError(f"a commit to {self.path} failed: {gone}")
        try:
            db.execute("BEGIN IMMEDIATE")
            try:
                db.executemany(
                    "INSERT OR REPLACE INTO tiles VALUES (?, ?, ?, ?, ?)",
                    ((*t.key, t.robot, t.seq, seal_tile(t.key, t.robot, t.seq, _layers_of(t))) for t in batch.tiles),
                )
                db.executemany(
                    "INSERT OR REPLACE INTO robots VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        (session, r.robot, r.fused, r.discarded, r.ended, r.next_seq, robot_check(session, r))
                        for r in batch.robots
                    ),
                )
                db.executemany(
                    "INSERT OR REPLACE INTO ledger VALUES (?, ?, ?, ?, ?)",
                    ((session, e.robot, e.seq, e.scan, e.pose) for e in batch.ledger),
                )
                db.executemany(
                    "DELETE FROM ledger WHERE session = ? AND robot = ? AND seq < ?",
                    ((session, robot, seq) for robot, seq in batch.keep_from.items()),
                )
                db.executemany(
                    "INSERT OR REPLACE INTO meta VALUES (?, ?)",
                    (("cells_updated", batch.cells_updated), ("committed_at", now)),
                )
                # (counted up at every commit: a log older than the file holds fewer; _refuse_a_foreign_log)
                db.execute("INSERT INTO meta VALUES ('commits', 1) ON CONFLICT (key) DO UPDATE SET value = value + 1")
                db.execute("COMMIT")
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    db.execute("ROLLBACK")
                raise
        except (sqlite3.Error, OSError) as exc:
            raise StoreWriteError(f"a commit to {self.path} failed: {exc}") from None
        return now

    def _gone(self) -> str:
        """Why the database file this store wrote is no longer at its path ("" when it is): SQLite goes on writing to
        a file removed while it is open, and what it writes there is lost with the last handle."""
        now = _file_identity(self.path)
        if now == self._file:
            return ""
        if now is None:
            return "the file was removed while the shard ran (its state directory deleted?); what it held is lost"
        return "another file took its place while the shard ran; this shard's commits would not be in it"

    def close(self) -> None:
        """Close the database (SQLite checkpoints the write-ahead log into it) and release the directory's lock."""
        try:
            self._db.close()
        finally:
            os.close(self._lock)


def _file_identity(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path``, None when there is none."""
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    return st.st_dev, st.st_ino


def _whole(value: object, low: int, high: int | None = None) -> bool:
    """Whether ``value`` (a row's) is an integer (no bool) in [low, high] (high None: no bound)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)


# ---------------------------------------------------------------------------------------------- opening steps


def store_exists(directory: Path) -> bool:
    """Whether the shard folder ``directory`` holds a store (its database file, or its write-ahead log alone)."""
    path = directory / DB_NAME
    return path.exists() or Path(f"{path}-wal").exists()


def check_store(
    directory: Path, identity: StoreIdentity, run_id: str | None, unfinished: dict[str, set[str]] | None = None
) -> dict[str, set[str]]:
    """Check the store in ``directory`` as a shard of ``identity`` in run ``run_id`` would before it fuses (its
    file, SQLite's check of every page, that it is that shard's and that run's store, every tile readable and its
    own, no other process holding the directory), writing nothing; the sessions it holds fused or given-up scans of,
    each with the robots whose scans they are (none when there is no store yet). StoreError says what is wrong:
    `posegrid run --resume` checks every shard's store before it starts any process (a damaged store, another
    shard's folder or another run's stopped the run after the router and the other shards had started, exit 1 with
    their lines and a new session in run.json). ``unfinished`` gets, per session, the robots whose stream this store
    has not seen end and fused or given up whole (a replay stopped before its end)."""
    path = directory / DB_NAME
    if not store_exists(directory):
        return {}
    if (path.exists() and not os.access(path, os.W_OK)) or not os.access(directory, os.W_OK):
        raise StoreError(  # (found only once the network was up: the shard's sentence, exit 1, a stray session)
            f"the store {path} cannot be written (its file or folder is read-only, or immutable): make both "
            "writable, or resume a copy of the run's folder"
        )
    lock = _lock_directory(directory)
    if not _check_file(path):
        os.close(lock)
        return {}
    try:
        _refuse_a_foreign_log(path)
        connection = _connect(path, None)
    except BaseException:
        os.close(lock)
        raise
    store = ShardStore(directory, connection, lock, "", identity)  # (only read: no session registered)
    try:
        _check_integrity(connection, path)
        _check_meta(connection, path, identity)
        if run_id is not None:
            _refuse_another_run(path, _run_of(connection), run_id)
        for tile in connection.execute("SELECT tx, ty, robot, seq, layers FROM tiles"):
            store._tile(tile)
        known = {row[0] for row in connection.execute("SELECT id FROM sessions")}
        checksums = "checksum" if _has_checksums(connection) else "NULL"
        for row in connection.execute(
            f"SELECT session, robot, fused, discarded, ended, next_seq, {checksums} FROM robots"
        ):
            store._robot(row, known)
        rows = connection.execute("SELECT session, robot FROM robots WHERE fused + discarded > 0").fetchall()
        open_streams = connection.execute(
            "SELECT session, robot FROM robots WHERE fused + discarded > 0 AND (ended IS NULL OR next_seq < ended)"
        ).fetchall()
    except sqlite3.DatabaseError as exc:
        raise StoreError(f"the store {path} cannot be read ({exc}): it is damaged") from None
    finally:
        store.close()
    sessions: dict[str, set[str]] = {}
    for found, pairs in ((sessions, rows), (unfinished if unfinished is not None else {}, open_streams)):
        for session, robot in pairs:
            if isinstance(session, str) and isinstance(robot, str):
                found.setdefault(session, set()).add(robot)
    return sessions


def _lock_directory(directory: Path) -> int:
    """Create ``directory`` if needed and lock it for this process (the lock's fd); StoreError when it cannot be
    created or written, or another process holds it."""
    if directory.exists() and not directory.is_dir():
        raise StoreError(f"the state directory {directory} is not a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        lock = os.open(directory / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise StoreError(f"cannot write to the state directory {directory}: {exc.strerror or exc}") from None
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.read(lock, 32).decode("ascii", "replace").strip() or "unknown"
        os.close(lock)
        raise StoreError(
            f"the state directory {directory} is in use by another shard process (pid {holder}); give each "
            "shard its own --state-dir"
        ) from None
    os.ftruncate(lock, 0)
    os.pwrite(lock, str(os.getpid()).encode(), 0)
    return lock


def _check_file(path: Path, tidy: bool = False) -> bool:
    """Whether the store's file exists; StoreError when it exists but is no SQLite database (empty, truncated before
    its header, another kind of file), or when only its write-ahead log is left. An empty file beside the rollback
    journal of its first write (a shard stopped within a millisecond of making it: nothing was ever committed) is no
    store: with ``tidy``, both are removed (a probe's shard then refused to start, saying the store was truncated)."""
    if not path.exists():
        if Path(f"{path}-wal").exists():
            raise StoreError(
                f"the store {path} is missing but its write-ahead log {path}-wal is there: the database was "
                "removed or moved; restore it, or remove the log to start an empty map"
            )
        return False
    if not path.is_file():
        raise StoreError(f"the store {path} is not a regular file")
    with path.open("rb") as file:
        header = file.read(100)
    journal, log = Path(f"{path}-journal"), Path(f"{path}-wal")
    if not header and journal.exists() and not log.exists():
        if tidy:
            for leftover in (path, journal, Path(f"{path}-shm")):
                leftover.unlink(missing_ok=True)
        return False
    if len(header) < 100:
        raise StoreError(
            f"the store {path} is truncated ({len(header)} bytes, less than a SQLite header)"
            + (
                ": if its shard never committed a scan (stopped as it made the store), remove it and the shard makes "
                "it anew; else restore it from a copy"
                if not header
                else ""
            )
        )
    if not header.startswith(SQLITE_HEADER):
        raise StoreError(f"the store {path} is not a SQLite database")
    return True


#: the meta rows that say whose store a file is (a write-ahead log that changes any of them is another database's),
#: and how many commits it holds (a log that holds fewer than the file is an earlier copy of the store's own)
_WHOSE = ("format", "map", "shard", "shards", "tile_size", "resolution", "run", "commits")


def _meta_seen(path: Path, options: str) -> dict[str, Any] | None:
    """The store's identity rows (:data:`_WHOSE`) read through a connection opened with the URI ``options``, which
    writes nothing to the database or its log; {} when the database read that way has no such rows (another
    database); None when it cannot be read at all (a folder that cannot be written: a read-only connection could not
    make the log's index there), which says nothing of whose the log is."""
    try:
        db = sqlite3.connect(f"{path.resolve().as_uri()}?{options}", uri=True, timeout=10.0)
    except sqlite3.Error:
        return None
    try:
        marks = ", ".join("?" * len(_WHOSE))
        return dict(db.execute(f"SELECT key, value FROM meta WHERE key IN ({marks})", _WHOSE))
    except sqlite3.OperationalError as exc:
        return {} if "no such table" in str(exc) else None
    except (sqlite3.DatabaseError, UnicodeDecodeError):
        return {}
    finally:
        db.close()


def _refuse_a_foreign_log(path: Path) -> None:
    """StoreError, with nothing written, when the store's write-ahead log is another database's: the store read from
    its file alone (SQLite's ``immutable``) is a posegrid store, and read through the log (``mode=ro``: the log is
    applied in memory only) it is another store, another run's or no store. SQLite cannot tell a log put beside a
    database from its own, and a connection that may write merges the log into the file when it closes: the check
    of a foreign log used to replace the store it refused. A store whose file holds no identity yet (its first commits
    still in its log) cannot be told apart, and passes."""
    log = Path(f"{path}-wal")
    if not log.exists() or log.stat().st_size == 0:
        return
    alone = _meta_seen(path, "immutable=1")
    if alone is None or alone.get("format") != FORMAT:
        return
    through = _meta_seen(path, "mode=ro")
    if through is None:  # (unreadable through its log: the open that follows says why, say a read-only folder)
        return
    behind = isinstance(alone.get("commits"), int) and not through.get("commits", -1) >= alone["commits"]
    if behind and not [key for key in _WHOSE if key != "commits" and through.get(key) != alone.get(key)]:
        raise StoreError(
            f"the write-ahead log {log} is older than the store {path}: read through it, the store goes back from "
            f"commit {alone['commits']} to {through.get('commits')} (a copy of an earlier log put back beside it). "
            f"Nothing was changed: move {log} (and {path}-shm) away to keep the store as it is, or restore the folder "
            "from a copy"
        )
    changed = [key for key in _WHOSE if key in alone and key != "commits" and through.get(key) != alone[key]]
    if changed:
        raise StoreError(
            f"the write-ahead log {log} is not the log of the store {path}: read through it, the store's "
            f"{', '.join(changed)} change ({', '.join(f'{alone[k]!r} -> {through.get(k)!r}' for k in changed)}), so "
            f"another database's log was put beside it. Nothing was changed: move {log} (and {path}-shm) away to "
            "keep the store as it was last written to its file, or restore the folder from a copy"
        )


def _connect(path: Path, max_bytes: int | None) -> sqlite3.Connection:
    """A connection in WAL mode with full synchronous commits (a commit survives a power cut), autocommit off (the
    commits begin their own transactions), usable from the writer thread."""
    try:
        db = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=10.0)
    except sqlite3.Error as exc:
        raise StoreError(f"cannot open the store {path}: {exc}") from None
    try:
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        db.execute("PRAGMA synchronous = FULL")
        if max_bytes is not None:
            page = db.execute("PRAGMA page_size").fetchone()[0]
            db.execute(f"PRAGMA max_page_count = {max(1, max_bytes // page)}")
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:  # (SQLite's message about a damaged page may
        db.close()  # itself be no UTF-8)
        if isinstance(exc, sqlite3.OperationalError) and "unable to open" in str(exc):  # (its log cannot be made)
            raise StoreError(
                f"the store {path} cannot be opened for writing ({exc}): its folder or file cannot be written "
                "(permissions, a read-only or immutable folder, a read-only file system)"
            ) from None
        raise StoreError(f"the store {path} cannot be opened ({exc}): it is damaged or not a database") from None
    if mode != "wal":
        db.close()
        raise StoreError(f"the store {path} cannot use a write-ahead log (journal mode {mode!r})")
    return db


def _check_integrity(db: sqlite3.Connection, path: Path) -> None:
    """SQLite's own check of every page, and of every index against its table (PRAGMA integrity_check: a bit
    flipped in a tile's key moved or dropped the tile past quick_check); StoreError when it finds a problem."""
    try:
        rows = db.execute("PRAGMA integrity_check").fetchall()
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
        raise StoreError(f"the store {path} fails SQLite's integrity check ({exc}): it is damaged") from None
    if rows != [("ok",)]:
        first = " ".join(str(rows[0][0]).replace("*** in database main ***", "").split()) if rows else "no answer"
        raise StoreError(f"the store {path} fails SQLite's integrity check ({first[:200]}): it is damaged")


def _check_meta(db: sqlite3.Connection, path: Path, identity: StoreIdentity) -> None:
    """StoreError unless the file is a posegrid shard store of this schema version and of ``identity``."""
    meta: dict[str, Any]
    try:
        meta = dict(db.execute("SELECT key, value FROM meta"))
    except (sqlite3.DatabaseError, UnicodeDecodeError):
        meta = {}
    if meta.get("format") != FORMAT:
        try:
            tables = db.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
        except sqlite3.DatabaseError:
            tables = None
        raise StoreError(
            f"the store {path} is a SQLite database but no posegrid shard store"
            + (
                # (a store's first commit makes its tables: a crash before it, or its write-ahead log, which held
                # them, removed, leaves none; a probe found no way out said)
                f": it holds no tables, so no scans (a shard stopped as it made it, or its write-ahead log removed): "
                f"remove {path} and its -wal and -shm files, and the shard makes it anew"
                if tables == 0
                else ""
            )
        )
    if meta.get("schema_version") not in READ_VERSIONS:
        raise StoreError(
            f"the store {path} has schema version {meta.get('schema_version')!r}; this build reads versions "
            f"{', '.join(map(str, READ_VERSIONS))}"
        )
    try:
        stored = StoreIdentity(meta["map"], meta["shard"], meta["shards"], meta["tile_size"], meta["resolution"])
    except KeyError as missing:
        raise StoreError(
            f"the store {path} lacks its {missing} entry: it is no complete posegrid shard store"
        ) from None
    if stored != identity:
        raise StoreError(
            f"the store {path} holds {stored.describe()}, not {identity.describe()}: another map's or another "
            "shard's state; give this shard its own --state-dir"
        )


def _has_checksums(db: sqlite3.Connection) -> bool:
    """Whether the store's robots table has its checksum column (schema 2; a schema-1 store gets it when a shard
    opens it, not when it is only checked)."""
    return any(column[1] == "checksum" for column in db.execute("PRAGMA table_info(robots)"))


def _bring_to_current(db: sqlite3.Connection, path: Path) -> None:
    """Bring a store of schema 1 to SCHEMA_VERSION in one transaction: the robots' checksum column (NULL in the rows
    written before: read unchecked until they are written again)."""
    if db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0] == SCHEMA_VERSION:
        return
    try:
        db.execute("BEGIN IMMEDIATE")
        db.execute("ALTER TABLE robots ADD COLUMN checksum INTEGER")
        db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (SCHEMA_VERSION,))
        db.execute("COMMIT")
    except sqlite3.Error as exc:
        with contextlib.suppress(sqlite3.Error):
            db.execute("ROLLBACK")
        raise StoreError(f"cannot write the store {path}: {exc}") from None


def _run_of(db: sqlite3.Connection) -> str | None:
    """The `posegrid run` the store records (None: none yet)."""
    row = db.execute("SELECT value FROM meta WHERE key = 'run'").fetchone()
    return None if row is None else row[0]


def _refuse_another_run(path: Path, stored: str | None, run_id: str) -> None:
    """StoreError when the store records a run (``stored``) other than ``run_id``."""
    if stored is not None and stored != run_id:
        raise StoreError(
            f"the store {path} belongs to run {stored!r}, not to this run ({run_id!r}): another run's state was "
            "put in its folder; restore this run's, or start the run anew"
        )


def _check_run(db: sqlite3.Connection, path: Path, run_id: str) -> None:
    """StoreError when the store belongs to another `posegrid run` than ``run_id``; a store of none (made by a shard
    on its own, or before runs had ids) is given this one."""
    try:
        stored = _run_of(db)
        if stored is None:
            db.execute("INSERT INTO meta VALUES ('run', ?)", (run_id,))
    except sqlite3.Error as exc:
        raise StoreError(f"cannot write the store {path}: {exc}") from None
    _refuse_another_run(path, stored, run_id)


def _create(db: sqlite3.Connection, path: Path, identity: StoreIdentity) -> None:
    """The tables and the meta rows of a new store, in one transaction."""
    meta = {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "map": identity.map_name,
        "shard": identity.shard,
        "shards": identity.shards,
        "tile_size": identity.tile_size,
        "resolution": identity.resolution,
        "created": time.time(),
        "cells_updated": 0,
    }
    try:
        db.execute("BEGIN IMMEDIATE")
        for statement in _TABLES:
            db.execute(statement)
        db.executemany("INSERT INTO meta VALUES (?, ?)", meta.items())
        db.execute("COMMIT")
    except sqlite3.Error as exc:
        db.close()
        raise StoreError(f"cannot write the store {path}: {exc}") from None


def _register_session(db: sqlite3.Connection, path: Path, session: str | None) -> str:
    """The session this shard writes: ``session`` (recorded when it is new), else the store's latest, else a new one."""
    try:
        if session is None:
            latest = db.execute("SELECT id FROM sessions ORDER BY ordinal DESC LIMIT 1").fetchone()
            session = latest[0] if latest else new_session_id()
        db.execute("BEGIN IMMEDIATE")
        db.execute("INSERT OR IGNORE INTO sessions (id, started) VALUES (?, ?)", (session, time.time()))
        db.execute("COMMIT")
    except sqlite3.Error as exc:
        raise StoreError(f"cannot write the store {path}: {exc}") from None
    assert session is not None  # (chosen above)
    return session
