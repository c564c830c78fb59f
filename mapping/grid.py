"""Unbounded occupancy map stored as fixed-size square tiles created on demand.

Global cell (ix, iy) covers map-frame x in [ix*res, (ix+1)*res) and y in [iy*res, (iy+1)*res); the
grid's origin is the map frame's origin. Tile (tx, ty) holds cells ix in [tx*T, (tx+1)*T) and iy in
[ty*T, (ty+1)*T); its arrays are indexed [iy - ty*T, ix - tx*T] (row = y), the row order of the map file.

Per cell the grid keeps
- ``logodds`` (float32): the occupancy log-odds, clamped to the sensor model's range; 0 = unknown,
- ``variance`` (float32): the sum over scans of the per-scan spread of the sample log-odds
  (E_w[y^2] - E_w[y]^2): how much pose uncertainty blurred the cell,
- ``observed`` (bool): whether any scan touched it,
- and in a grid made with ``track_changes`` (a mapper shard's), ``changed`` (uint8): which of the cell's layers the
  fusion has changed since :meth:`TiledGrid.take_changes` last took it (a bit each, mapping.tile_changes), so that a
  tile update gives only those cells, and of them only the values that changed (schemas.messages.TileUpdate).

Tiles live in stacked arrays (slot, T, T) that grow by doubling, so compiled kernels can write
into any tile through a slot index; memory follows the observed area.
"""

from __future__ import annotations

import math
import operator

import numpy as np

from mapping.errors import InputError
from mapping.tile_changes import ALL_CHANGED, ChangedCells, take_changed_cells

TILE_SIZE = 256
#: the largest tile side, cells: a tile's three layers take 9 bytes a cell (150 MB at 4096)
MAX_TILE_SIZE = 4096
#: the most cells a raster of the whole map may span before it is cropped (9 bytes a cell while it is built, so
#: about 2.4 GB): 16 384 x 16 384 cells, 819 m square at 0.05 m. A map whose tiles lie farther apart than that
#: is refused, not allocated.
MAX_RASTER_CELLS = 1 << 28

TileKey = tuple[int, int]


class RasterTooLarge(InputError):
    """The map's tiles span more cells than one raster (and so one map file) may hold (MAX_RASTER_CELLS): read it
    tile by tile, or in windows, instead."""


class TiledGrid:
    """A tiled log-odds map with a variance layer; see the module docstring for frames and layout."""

    def __init__(self, resolution: float = 0.05, tile_size: int = TILE_SIZE, track_changes: bool = False) -> None:
        if not 0 < resolution < math.inf:
            raise InputError(f"resolution must be > 0 m and finite, got {resolution}")
        whole = isinstance(tile_size, int | np.integer)
        if not whole or not 1 <= tile_size <= MAX_TILE_SIZE or tile_size & (tile_size - 1):
            raise InputError(f"tile_size must be a power of two up to {MAX_TILE_SIZE} (cells), got {tile_size!r}")
        self.resolution = float(resolution)
        self.tile_size = int(tile_size)
        self.tile_shift = self.tile_size.bit_length() - 1  # tile_size == 1 << tile_shift
        self._slot_of: dict[TileKey, int] = {}
        self.logodds = np.zeros((0, tile_size, tile_size), np.float32)
        self.variance = np.zeros((0, tile_size, tile_size), np.float32)
        self.observed = np.zeros((0, tile_size, tile_size), np.bool_)
        self.track_changes = bool(track_changes)
        # (untracked: no slots, and the fusion's kernels skip it)
        self.changed = np.zeros((0, tile_size, tile_size) if track_changes else (0, 1, 1), np.uint8)

    # ----------------------------------------------------------------------------------- tiles
    def keys(self) -> list[TileKey]:
        """Keys (tx, ty) of the tiles that exist, in creation order."""
        return list(self._slot_of)

    @property
    def tile_count(self) -> int:
        """How many tiles exist."""
        return len(self._slot_of)

    def __contains__(self, key: TileKey) -> bool:
        return key in self._slot_of

    def slot(self, key: TileKey) -> int:
        """The slot of tile ``key``, creating the tile (all unknown) if it does not exist."""
        slot = self._slot_of.get(key)
        if slot is None:
            slot = len(self._slot_of)
            if slot == self.logodds.shape[0]:
                self._grow(max(4, 2 * slot))
            self._slot_of[key] = slot
        return slot

    def _grow(self, capacity: int) -> None:
        extra = capacity - self.logodds.shape[0]
        shape = (extra, self.tile_size, self.tile_size)
        self.logodds = np.concatenate([self.logodds, np.zeros(shape, np.float32)])
        self.variance = np.concatenate([self.variance, np.zeros(shape, np.float32)])
        self.observed = np.concatenate([self.observed, np.zeros(shape, np.bool_)])
        if self.track_changes:
            self.changed = np.concatenate([self.changed, np.zeros(shape, np.uint8)])

    def tile_arrays(self, key: TileKey) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(logodds, variance, observed) views of tile ``key``, each (T, T), row = y."""
        if key not in self._slot_of:
            raise KeyError(f"tile {key} does not exist")
        slot = self._slot_of[key]
        return self.logodds[slot], self.variance[slot], self.observed[slot]

    def set_tile(self, key: TileKey, logodds: np.ndarray, variance: np.ndarray, observed: np.ndarray) -> None:
        """Replace tile ``key``'s layers (used when assembling a map from shards, and by a shard seeding or restoring
        a tile); with ``track_changes`` every layer of every cell of it is marked changed."""
        try:
            key = (operator.index(key[0]), operator.index(key[1]))
        except (TypeError, IndexError):
            raise InputError(f"a tile key must be two whole numbers (tx, ty), got {key!r}") from None
        shape = (self.tile_size, self.tile_size)
        for name, layer in (("logodds", logodds), ("variance", variance), ("observed", observed)):
            if np.shape(layer) != shape:
                raise InputError(f"tile {key}: '{name}' must have shape {shape}, got {np.shape(layer)}")
        observed = np.asarray(observed)
        if not (np.isfinite(logodds).all() and np.isfinite(variance).all() and (np.asarray(variance) >= 0).all()):
            raise InputError(f"tile {key}: 'logodds' must be finite and 'variance' finite and >= 0")
        if observed.dtype != np.bool_ and not np.isin(observed, (0, 1)).all():
            raise InputError(f"tile {key}: 'observed' must be booleans (or 0 and 1), got dtype {observed.dtype}")
        slot = self.slot(key)
        self.logodds[slot] = logodds
        self.variance[slot] = variance
        self.observed[slot] = observed
        if self.track_changes:
            self.changed[slot] = ALL_CHANGED

    def take_changes(self, key: TileKey, window: tuple[int, int, int, int]) -> ChangedCells | None:
        """The cells of tile ``key`` whose values changed since the last call that took them, looked for in
        ``window`` (row0, col0, rows, cols; tile-local cells), and their marks there cleared
        (:func:`mapping.tile_changes.take_changed_cells`); None when none changed. Only in a grid made with
        ``track_changes``."""
        if not self.track_changes:
            raise ValueError("this grid does not track changes: make it with track_changes=True")
        slot = self._slot_of[key]
        layers = (self.logodds[slot], self.variance[slot], self.observed[slot], self.changed[slot])
        return take_changed_cells(layers, window)

    def tile_origin(self, key: TileKey) -> tuple[float, float]:
        """Map-frame (x, y) in m of the lower-left corner of tile ``key``."""
        span = self.tile_size * self.resolution
        return key[0] * span, key[1] * span

    # ----------------------------------------------------------------------------------- summaries
    @property
    def nbytes(self) -> int:
        """Bytes held by the tiles that exist (the slot arrays' unused capacity excluded)."""
        per_tile = self.tile_size * self.tile_size * (4 + 4 + 1 + (1 if self.track_changes else 0))
        return per_tile * len(self._slot_of)

    def observed_cells(self) -> int:
        n = len(self._slot_of)
        return int(self.observed[:n].sum())

    def rasterize(self) -> dict[str, np.ndarray]:
        """The map as one raster with the map file's keys, cropped to the observed cells.

        Returns logodds, probability, observed, variance, origin (m, lower-left of cell [0, 0]) and
        resolution (m). An empty grid gives a 0 x 0 raster at the origin. Raises InputError when the tiles span
        more than MAX_RASTER_CELLS cells.
        """
        keys = self.keys()
        size = self.tile_size
        if not keys:
            return empty_raster(self.resolution)
        tx = np.array([k[0] for k in keys])
        ty = np.array([k[1] for k in keys])
        tx0, ty0 = tx.min(), ty.min()
        shape = (int(ty.max() - ty0 + 1) * size, int(tx.max() - tx0 + 1) * size)  # Python ints: no overflow
        if shape[0] * shape[1] > MAX_RASTER_CELLS:
            width_m, height_m = shape[1] * self.resolution, shape[0] * self.resolution
            raise RasterTooLarge(
                f"the map's tiles span {shape[1]} x {shape[0]} cells ({width_m:.6g} m x "
                f"{height_m:.6g} m), more than the {MAX_RASTER_CELLS} cells one raster may hold"
            )
        logodds = np.zeros(shape, np.float32)
        variance = np.zeros(shape, np.float32)
        observed = np.zeros(shape, bool)
        for key, slot in self._slot_of.items():
            tile_rows = slice((key[1] - ty0) * size, (key[1] - ty0 + 1) * size)
            tile_cols = slice((key[0] - tx0) * size, (key[0] - tx0 + 1) * size)
            logodds[tile_rows, tile_cols] = self.logodds[slot]
            variance[tile_rows, tile_cols] = self.variance[slot]
            observed[tile_rows, tile_cols] = self.observed[slot]
        rows = np.flatnonzero(observed.any(axis=1))
        cols = np.flatnonzero(observed.any(axis=0))
        if rows.size == 0:
            rows = cols = np.array([0])
            crop = (slice(0, 0), slice(0, 0))
        else:
            crop = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        logodds = logodds[crop]
        origin = np.array([(tx0 * size + cols[0]) * self.resolution, (ty0 * size + rows[0]) * self.resolution])
        return {
            "logodds": logodds,
            "probability": probability_of(logodds),
            "observed": observed[crop],
            "variance": variance[crop],
            "origin": origin,
            "resolution": np.float64(self.resolution),
        }


def empty_raster(resolution: float, **layers: np.ndarray) -> dict[str, np.ndarray]:
    """The raster of a map with no observed cell: 0 x 0 layers at the origin, cells of ``resolution`` m, with the map
    file's keys and any further (0 x 0) ``layers`` before origin."""
    empty = np.zeros((0, 0), np.float32)
    return {
        "logodds": empty,
        "probability": empty.copy(),
        "observed": np.zeros((0, 0), bool),
        "variance": empty.copy(),
        **layers,
        "origin": np.zeros(2),
        "resolution": np.float64(resolution),
    }


def probability_of(logodds: np.ndarray) -> np.ndarray:
    """Occupancy probability from log-odds (float32), 0.5 where the log-odds is 0."""
    return (1.0 / (1.0 + np.exp(-logodds.astype(np.float64)))).astype(np.float32)
