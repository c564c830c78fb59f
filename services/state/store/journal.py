"""What a shard has changed since its last commit (:class:`Journal`), and the tiles an exported map seeds a shard with
(:func:`tiles_of_map`, `posegrid mapper --load`)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from schemas.files import MapFile
from services.state.store.db import Batch, LedgerEntry, StoredState, StoreError, TileKey

#: the robot name a tile seeded from an exported map carries until a scan is fused into it (TileUpdate.robot)
SEED_ROBOT = "loaded"


class Journal:
    """A shard's changes since its last commit: the tiles fusion changed, the ledger entries of the scans fused, and
    how many scans were fused or given up (``changes``, ends noted included) since when (``since``, the shard's clock
    in s). It also keeps, for the whole session, each robot's highest scan seq fused or given up (``high``) and
    highest seq fused (``fused_high``): a commit stores the seq the robot's streams resume after."""

    def __init__(self) -> None:
        self.tiles: set[TileKey] = set()
        self.ledger: list[LedgerEntry] = []
        self.high: dict[str, int] = {}
        self.fused_high: dict[str, int] = {}
        self.changes = 0
        self.since: float | None = None

    def _changed(self, count: int, now: float) -> None:
        self.changes += count
        if self.since is None:
            self.since = now

    def fused(self, entry: LedgerEntry, tiles: Iterable[TileKey], now: float) -> None:
        """A scan was fused (or refused at fusion: counted as given up, with no tile changed) at ``now``."""
        self.ledger.append(entry)
        self.tiles.update(tiles)
        self.high[entry.robot] = max(self.high.get(entry.robot, -1), entry.seq)
        self.fused_high[entry.robot] = max(self.fused_high.get(entry.robot, -1), entry.seq)
        self._changed(1, now)

    def gave_up(self, robot: str, last: int, count: int, now: float) -> None:
        """``count`` scans of ``robot`` up to seq ``last`` were given up on at ``now``."""
        self.high[robot] = max(self.high.get(robot, -1), last)
        self._changed(count, now)

    def noted(self, now: float, tiles: Iterable[TileKey] = ()) -> None:
        """Something else to commit changed at ``now``: an end of a stream, or ``tiles`` seeded from a map."""
        self.tiles.update(tiles)
        self._changed(1, now)

    def due(self, scans: int, interval: float, now: float) -> bool:
        """Whether a commit is due: ``scans`` changes or more, or a change ``interval`` s old or older."""
        return self.changes >= scans or (self.since is not None and now - self.since >= interval)

    def take(self) -> tuple[set[TileKey], list[LedgerEntry], int]:
        """(tiles changed, ledger entries, changes) since the last batch; the journal starts afresh."""
        taken = self.tiles, self.ledger, self.changes
        self.tiles, self.ledger, self.changes, self.since = set(), [], 0, None
        return taken

    def put_back(self, batch: Batch, now: float) -> None:
        """A batch whose commit failed: its tiles and entries are to be committed with the next one."""
        self.tiles.update(tile.key for tile in batch.tiles)
        self.ledger[:0] = batch.ledger
        self._changed(batch.scans, now)

    def resumed(self, state: StoredState) -> None:
        """Start from what a store holds (the session's highest seqs)."""
        for robot in state.robots.values():
            if robot.next_seq > 0:
                self.high[robot.robot] = robot.next_seq - 1
        for entry in state.ledger:
            self.fused_high[entry.robot] = max(self.fused_high.get(entry.robot, -1), entry.seq)


def tiles_of_map(
    map_file: MapFile, resolution: float, tile_size: int, what: str
) -> dict[TileKey, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The tiles (tx, ty) -> (logodds, variance, observed) of an exported map with at least one observed cell, on
    the grid of ``resolution`` m cells and ``tile_size``-cell tiles (mapping.grid: cell (ix, iy) covers x in
    [ix*res, (ix+1)*res)). ``what`` names the map in errors. Raises StoreError when the map's cells are of another
    size or do not lie on that grid (its origin is no multiple of the resolution)."""
    if abs(map_file.resolution - resolution) > 1e-9 * resolution:
        raise StoreError(f"{what} has cells of {map_file.resolution:g} m; this shard's are {resolution:g} m")
    corner = np.asarray(map_file.origin, np.float64) / resolution
    cells = np.round(corner)
    if not (np.abs(corner - cells) <= 1e-6 * np.maximum(1.0, np.abs(cells))).all():
        raise StoreError(
            f"{what} has its origin at {tuple(map_file.origin.tolist())} m, not on the shard's grid of "
            f"{resolution:g} m cells"
        )
    ix0, iy0 = int(cells[0]), int(cells[1])
    height, width = map_file.logodds.shape
    variance = map_file.variance if map_file.variance is not None else np.zeros_like(map_file.logodds)
    tiles = {}
    for ty in range(iy0 // tile_size, (iy0 + height - 1) // tile_size + 1):
        for tx in range(ix0 // tile_size, (ix0 + width - 1) // tile_size + 1):
            rows = slice(max(0, ty * tile_size - iy0), min(height, (ty + 1) * tile_size - iy0))
            cols = slice(max(0, tx * tile_size - ix0), min(width, (tx + 1) * tile_size - ix0))
            if rows.start >= rows.stop or cols.start >= cols.stop or not map_file.observed[rows, cols].any():
                continue
            inside = (
                slice(iy0 + rows.start - ty * tile_size, iy0 + rows.stop - ty * tile_size),
                slice(ix0 + cols.start - tx * tile_size, ix0 + cols.stop - tx * tile_size),
            )
            layers = (
                np.zeros((tile_size, tile_size), np.float32),
                np.zeros((tile_size, tile_size), np.float32),
                np.zeros((tile_size, tile_size), bool),
            )
            for layer, source in zip(layers, (map_file.logodds, variance, map_file.observed)):
                layer[inside] = source[rows, cols]
            tiles[(tx, ty)] = layers
    return tiles
