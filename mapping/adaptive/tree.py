"""The adaptive grid's storage: a region quadtree per tile, kept as a linear quadtree in sorted arrays.

Frames: the same unbounded tiled world frame as :class:`mapping.grid.TiledGrid`. Finest cell (ix, iy) covers
map-frame x in [ix*res, (ix+1)*res) and y in [iy*res, (iy+1)*res); tile (tx, ty) holds the finest cells
ix in [tx*T, (tx+1)*T), iy in [ty*T, (ty+1)*T) (T = tile_size, a power of two). A tile is the root of a
full quadtree of depth log2(T): a cell of level k covers 2^k x 2^k finest cells, so level 0 is the finest
resolution and level log2(T) is the whole tile. Cell (k, ax, ay) covers the finest cells
ix in [ax*2^k, (ax+1)*2^k), iy in [ay*2^k, (ay+1)*2^k).

Only the *active* cells (the leaves) are stored, one row each in parallel arrays sorted by

    key = slot << 2*log2(T)  |  morton(ix0 - tx*T, iy0 - ty*T)

where slot numbers the tiles in creation order and (ix0, iy0) is the cell's lower-left finest cell. In Morton
(Z) order a level-k cell owns the contiguous key range [key, key + 4^k), so the active cell covering any
finest cell is found with one binary search (:meth:`AdaptiveGrid.find`). Active cells never overlap and every
active cell has been observed; a finest cell that no active cell covers was never observed.

Per active cell: ``level`` (int8), ``logodds`` and ``variance`` (float32, as in the regular grid) and the
weighted ``hits`` and ``misses`` counts (float32) that the split test carries from scan to scan.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.errors import InputError
from mapping.grid import MAX_RASTER_CELLS, TILE_SIZE, RasterTooLarge, empty_raster, probability_of

#: per-cell columns besides the key, with their dtypes
CELL_COLUMNS = (
    ("level", np.int8),
    ("logodds", np.float32),
    ("variance", np.float32),
    ("hits", np.float32),
    ("misses", np.float32),
)

#: tiles of up to 2^15 finest cells a side keep the local Morton code within 30 bits
MAX_TILE_SHIFT = 15

#: raster value of ``level`` where no active cell covers a cell
NO_CELL = -1

#: the four children of cell (ax, ay) are (2 ax + dx, 2 ay + dy), in this order
CHILD_DX = np.array([0, 1, 0, 1])
CHILD_DY = np.array([0, 0, 1, 1])


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert a 0 bit above every bit of v < 2^16: the x or y half of a Morton code."""
    v = v.astype(np.int64) & 0xFFFF
    v = (v | (v << 8)) & 0x00FF00FF
    v = (v | (v << 4)) & 0x0F0F0F0F
    v = (v | (v << 2)) & 0x33333333
    return (v | (v << 1)) & 0x55555555


def _compact_bits(m: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_spread_bits`: the even bits of m as one integer."""
    m = m & 0x55555555
    m = (m | (m >> 1)) & 0x33333333
    m = (m | (m >> 2)) & 0x0F0F0F0F
    m = (m | (m >> 4)) & 0x00FF00FF
    return (m | (m >> 8)) & 0xFFFF


def morton(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Morton (Z-order) code of tile-local finest cell coordinates (each < 2^15)."""
    return _spread_bits(x) | (_spread_bits(y) << 1)


def unique_cells(ax: np.ndarray, ay: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct pairs (ax, ay) of two integer arrays, sorted by (ax, ay)."""
    ax = np.asarray(ax, np.int64)
    ay = np.asarray(ay, np.int64)
    if ax.size == 0:
        return ax, ay
    x0, y0 = ax.min(), ay.min()
    span = int(ay.max() - y0) + 1
    code = np.unique((ax - x0) * span + (ay - y0))
    return code // span + x0, code % span + y0


def children(ax: np.ndarray, ay: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (4N,) of the children of cells (ax, ay), four consecutive per cell (CHILD_DX, CHILD_DY order)."""
    return (2 * np.asarray(ax)[:, None] + CHILD_DX).ravel(), (2 * np.asarray(ay)[:, None] + CHILD_DY).ravel()


class AdaptiveGrid:
    """Active cells of a region quadtree over the tiled world frame (see the module docstring).

    resolution: the finest cell size in m (level 0); tile_size: finest cells per tile side, a power of two
    (the tile is the coarsest possible cell, level log2(tile_size)).
    """

    # the CELL_COLUMNS arrays, one entry per active cell in key order (set by name in __init__ and edit)
    level: np.ndarray  # int8, the cell's level
    logodds: np.ndarray  # float32
    variance: np.ndarray  # float32
    hits: np.ndarray  # float32
    misses: np.ndarray  # float32

    def __init__(self, resolution: float = 0.05, tile_size: int = TILE_SIZE) -> None:
        if not 0 < resolution < math.inf:
            raise InputError(f"resolution must be > 0 m and finite, got {resolution}")
        whole = isinstance(tile_size, int | np.integer)  # (64.0 failed later: "unsupported operand &")
        if not whole or tile_size < 1 or tile_size & (tile_size - 1) or tile_size > 1 << MAX_TILE_SHIFT:
            raise InputError(f"tile_size must be a power of two up to {1 << MAX_TILE_SHIFT} cells, got {tile_size}")
        self.resolution = float(resolution)
        self.tile_size = int(tile_size)
        self.tile_shift = self.tile_size.bit_length() - 1
        self._key_shift = 2 * self.tile_shift
        self._tile_xy = np.zeros((0, 2), np.int64)  # (tx, ty) of each slot, in creation order
        self._tile_code = np.zeros(0, np.int64)  # sorted tile codes ...
        self._tile_slot = np.zeros(0, np.int64)  # ... and their slots
        self.key = np.zeros(0, np.int64)
        for name, dtype in CELL_COLUMNS:
            setattr(self, name, np.zeros(0, dtype))
        #: the level of the cells a fusion starts where no active cell is (mapping.adaptive.fusion), once one has
        #: fused into the grid: every fusion into it must start at the same level, so that active cells never overlap
        self.start_level: int | None = None

    # ----------------------------------------------------------------------------------- sizes
    @property
    def max_level(self) -> int:
        """The coarsest level: one cell per tile."""
        return self.tile_shift

    @property
    def active_cells(self) -> int:
        return int(self.key.size)

    @property
    def nbytes(self) -> int:
        """Bytes held by the active cells' arrays (key and columns) and the tile tables."""
        return int(
            self.key.nbytes
            + sum(getattr(self, name).nbytes for name, _ in CELL_COLUMNS)
            + self._tile_xy.nbytes
            + self._tile_code.nbytes
            + self._tile_slot.nbytes
        )

    # ----------------------------------------------------------------------------------- keys
    def _slots(self, tx: np.ndarray, ty: np.ndarray, create: bool) -> np.ndarray:
        """Slot of each tile (tx, ty), -1 where the tile does not exist (created instead if ``create``).

        Tiles are found by binary search in their codes (tx << 32 | ty), kept sorted beside their slots.
        """
        tx = np.asarray(tx, np.int64)
        ty = np.asarray(ty, np.int64)
        code = (tx << 32) | (ty & 0xFFFFFFFF)
        where = np.minimum(np.searchsorted(self._tile_code, code), max(self._tile_code.size - 1, 0))
        found = (self._tile_code[where] == code) if self._tile_code.size else np.zeros(code.shape, bool)
        if create and not found.all():
            new, first = np.unique(code[~found], return_index=True)
            self._tile_xy = np.concatenate([self._tile_xy, np.stack([tx[~found][first], ty[~found][first]], axis=1)])
            codes = np.concatenate([self._tile_code, new])
            order = np.argsort(codes)
            self._tile_code = codes[order]
            self._tile_slot = np.concatenate(
                [self._tile_slot, np.arange(len(self._tile_xy) - new.size, len(self._tile_xy))]
            )[order]
            return self._slots(tx, ty, create=False)
        return np.where(found, self._tile_slot[where] if self._tile_code.size else -1, -1)

    def _finest_keys(self, ix: np.ndarray, iy: np.ndarray, create: bool = False) -> np.ndarray:
        """Key of finest cells (ix, iy); -1 where their tile does not exist."""
        ix = np.asarray(ix, np.int64)
        iy = np.asarray(iy, np.int64)
        if ix.size == 0:
            return np.zeros(ix.shape, np.int64)
        shift = self.tile_shift
        slots = self._slots(ix >> shift, iy >> shift, create)
        mask = self.tile_size - 1
        keys = (slots << self._key_shift) | morton(ix & mask, iy & mask)
        return np.where(slots >= 0, keys, -1)

    def cell_keys(self, level: np.ndarray, ax: np.ndarray, ay: np.ndarray, create: bool = False) -> np.ndarray:
        """Keys of cells (level, ax, ay); -1 where their tile does not exist (created instead if ``create``)."""
        level = np.asarray(level, np.int64)
        return self._finest_keys(np.asarray(ax, np.int64) << level, np.asarray(ay, np.int64) << level, create)

    def cells(self, index: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(level, ax, ay) of the active cells at ``index`` (all if None)."""
        key = self.key if index is None else self.key[index]
        level = (self.level if index is None else self.level[index]).astype(np.int64)
        slot = key >> self._key_shift
        code = key & ((1 << self._key_shift) - 1)
        tile = self._tile_xy[slot]
        ix = (tile[:, 0] << self.tile_shift) + _compact_bits(code)
        iy = (tile[:, 1] << self.tile_shift) + _compact_bits(code >> 1)
        return level, ix >> level, iy >> level

    # ----------------------------------------------------------------------------------- lookups
    def find(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        """Index of the active cell covering each finest cell (ix, iy); -1 where none does."""
        keys = self._finest_keys(ix, iy)
        return self._covering(keys)

    def _covering(self, keys: np.ndarray) -> np.ndarray:
        """Index of the active cell whose key range holds each finest-cell key; -1 where none does."""
        if self.key.size == 0:
            return np.full(np.shape(keys), -1, np.int64)
        i = np.searchsorted(self.key, keys, side="right") - 1
        safe = np.maximum(i, 0)
        span = np.left_shift(1, 2 * self.level[safe].astype(np.int64))
        inside = (i >= 0) & (keys >= 0) & (keys < self.key[safe] + span)
        return np.where(inside, i, -1)

    def find_exact(self, level: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
        """Index of the active cell that is exactly cell (level, ax, ay); -1 where it is not active."""
        keys = self.cell_keys(level, ax, ay)
        if self.key.size == 0:
            return np.full(keys.shape, -1, np.int64)
        safe = np.minimum(np.searchsorted(self.key, keys), self.key.size - 1)
        hit = (keys >= 0) & (self.key[safe] == keys) & (self.level[safe] == np.asarray(level))
        return np.where(hit, safe, -1)

    def cells_in_blocks(self, level: int, bx: np.ndarray, by: np.ndarray) -> np.ndarray:
        """Sorted indices of the active cells inside or covering the cells (level, bx, by) (blocks)."""
        keys = self.cell_keys(np.full(np.shape(bx), level), bx, by)
        keys = keys[keys >= 0]
        lo = np.searchsorted(self.key, keys)
        hi = np.searchsorted(self.key, keys + (1 << 2 * level))
        lengths = hi - lo
        inside = np.repeat(lo - np.cumsum(lengths) + lengths, lengths) + np.arange(int(lengths.sum()))
        covering = self._covering(keys)
        return np.unique(np.concatenate([inside, covering[covering >= 0]]))

    # ----------------------------------------------------------------------------------- edits
    def edit(
        self,
        remove: np.ndarray,
        level: np.ndarray,
        ax: np.ndarray,
        ay: np.ndarray,
        logodds: np.ndarray,
        variance: np.ndarray,
        hits: np.ndarray,
        misses: np.ndarray,
    ) -> None:
        """Remove the active cells at indices ``remove`` and add cells (level, ax, ay) with the given values.

        The caller keeps the partition: the added cells must cover exactly what was removed, plus cells
        that no active cell covered before.
        """
        keep = np.ones(self.key.size, bool)
        keep[np.asarray(remove, np.int64)] = False
        new_keys = self.cell_keys(level, ax, ay, create=True)
        order = np.argsort(new_keys, kind="stable")
        new_keys = new_keys[order]
        where = np.searchsorted(self.key[keep], new_keys)
        values = {"level": level, "logodds": logodds, "variance": variance, "hits": hits, "misses": misses}
        self.key = np.insert(self.key[keep], where, new_keys)
        for name, dtype in CELL_COLUMNS:
            added = np.broadcast_to(np.asarray(values[name], dtype), new_keys.shape)[order]
            setattr(self, name, np.insert(getattr(self, name)[keep], where, added))

    # ----------------------------------------------------------------------------------- export
    def rasterize(self, resolution: float | None = None) -> dict[str, np.ndarray]:
        """The map as one raster with the map file's keys (docs/formats.md), plus ``level``.

        resolution: the raster's cell size in m (default: the finest). Each raster cell takes the values of
        the active cell under its centre. The raster spans the active cells' bounding box, which at the
        finest resolution is exactly the crop to the observed cells. ``level`` (int8) is the level of that
        active cell (0 = finest, k = 2^k times wider, -1 = none); at the finest resolution the number of
        active cells is sum(4.0 ** -level) over the covered cells. Raises mapping.grid.RasterTooLarge, before
        anything is allocated, for a raster of more than MAX_RASTER_CELLS cells.
        """
        out_res = self.resolution if resolution is None else float(resolution)
        if not 0 < out_res < math.inf:
            raise InputError(f"raster resolution must be > 0 m and finite, got {resolution}")
        if self.key.size == 0:
            return empty_raster(out_res, level=np.zeros((0, 0), np.int8))
        level, ax, ay = self.cells()
        x0, y0 = int((ax << level).min()), int((ay << level).min())
        x1, y1 = int(((ax + 1) << level).max()), int(((ay + 1) << level).max())
        origin = np.array([x0 * self.resolution, y0 * self.resolution])
        width = max(1, math.ceil((x1 - x0) * self.resolution / out_res - 1e-9))
        height = max(1, math.ceil((y1 - y0) * self.resolution / out_res - 1e-9))
        if width * height > MAX_RASTER_CELLS:  # (Python ints: no overflow; checked before anything is allocated)
            raise RasterTooLarge(
                f"the map's active cells span {width} x {height} cells of {out_res:g} m ({width * out_res:.6g} m x "
                f"{height * out_res:.6g} m), more than the {MAX_RASTER_CELLS} cells one raster may hold"
            )
        centres = (np.arange(max(width, height)) + 0.5) * out_res
        ix = np.floor((origin[0] + centres[:width]) / self.resolution).astype(np.int64)
        iy = np.floor((origin[1] + centres[:height]) / self.resolution).astype(np.int64)
        index = self.find(np.broadcast_to(ix[None, :], (height, width)), np.broadcast_to(iy[:, None], (height, width)))
        covered = index >= 0
        safe = np.maximum(index, 0)
        logodds = np.where(covered, self.logodds[safe], 0).astype(np.float32)
        return {
            "logodds": logodds,
            "probability": probability_of(logodds),
            "observed": covered,
            "variance": np.where(covered, self.variance[safe], 0).astype(np.float32),
            "level": np.where(covered, self.level[safe], NO_CELL).astype(np.int8),
            "origin": origin,
            "resolution": np.float64(out_res),
        }
