"""The size of a whole-map export, known before anything is allocated, and the window that crops one.

An export rasterizes the level-0 tiles it covers into one array of the bounding box of those tiles
(mapping.grid.TiledGrid.rasterize) before cropping it to the observed cells; that box, in cells, is what the
API's --max-export-cells limits. A window (x_min, y_min, x_max, y_max, m, map frame) keeps the tiles that
overlap it and, within them, the cells that overlap it, so the export of a window holds the observed cells
inside it, cropped to them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mapping.grid import TiledGrid

TileKey = tuple[int, int]

# A window edge's cell index is held within +-2^62 cells: an edge past that (1e308 m over 0.05 m cells is inf
# cells) holds no tile a map can have, and its index as an int is still what the overlap tests compare.
CELL_INDEX_LIMIT = 2.0**62


# A window edge within this many cells (relative to its index) of a cell boundary lies on it: 5.05 m / 0.05 m is
# 100.99999999999999 in floats, and floored it took in the cell [5.00, 5.05) m, wholly outside the window.
ON_BOUNDARY = 1e-12


def _cell_edge(edge: float, resolution: float, rounding: Callable[[float], int]) -> int:
    """``rounding`` (math.floor or math.ceil) of ``edge`` / ``resolution`` (m over m/cell), an edge within
    :data:`ON_BOUNDARY` of a cell boundary taken as on it, held within :data:`CELL_INDEX_LIMIT` so that a finite
    edge whose quotient overflows to inf gives a cell index too."""
    cells = min(CELL_INDEX_LIMIT, max(-CELL_INDEX_LIMIT, edge / resolution))
    boundary = round(cells)
    if abs(cells - boundary) <= ON_BOUNDARY * max(1.0, abs(cells)):
        return int(boundary)
    return int(rounding(cells))


@dataclass(frozen=True)
class Window:
    """Level-0 cells ix in [ix0, ix1), iy in [iy0, iy1): those that overlap a rectangle of the map frame."""

    ix0: int
    iy0: int
    ix1: int
    iy1: int

    @classmethod
    def of(cls, x_min: float, y_min: float, x_max: float, y_max: float, resolution: float) -> Window:
        """The cells of ``resolution`` m that overlap [x_min, x_max) x [y_min, y_max) m."""
        return cls(
            _cell_edge(x_min, resolution, math.floor),
            _cell_edge(y_min, resolution, math.floor),
            _cell_edge(x_max, resolution, math.ceil),
            _cell_edge(y_max, resolution, math.ceil),
        )

    def overlaps(self, tile: TileKey, tile_size: int) -> bool:
        """Whether level-0 tile ``tile`` holds a cell of the window."""
        x0, y0 = tile[0] * tile_size, tile[1] * tile_size
        return x0 < self.ix1 and x0 + tile_size > self.ix0 and y0 < self.iy1 and y0 + tile_size > self.iy0

    def mask(self, tile: TileKey, tile_size: int) -> np.ndarray:
        """(T, T) bool, row = y: which cells of ``tile`` lie in the window."""
        cells = np.arange(tile_size)
        columns = (cells + tile[0] * tile_size >= self.ix0) & (cells + tile[0] * tile_size < self.ix1)
        rows = (cells + tile[1] * tile_size >= self.iy0) & (cells + tile[1] * tile_size < self.iy1)
        return rows[:, None] & columns[None, :]


def covered(tiles: Iterable[TileKey], tile_size: int, window: Window | None) -> list[TileKey]:
    """The tiles an export of ``window`` (None: the whole map) reads."""
    return [tile for tile in tiles if window is None or window.overlaps(tile, tile_size)]


def raster_shape(tiles: list[TileKey], tile_size: int) -> tuple[int, int]:
    """(columns, rows) of cells of the bounding box of ``tiles``: the raster an export of them allocates."""
    if not tiles:
        return 0, 0
    columns = [tile[0] for tile in tiles]
    rows = [tile[1] for tile in tiles]
    return (max(columns) - min(columns) + 1) * tile_size, (max(rows) - min(rows) + 1) * tile_size


def windowed(grid: TiledGrid, window: Window | None) -> TiledGrid:
    """``grid`` itself without a window; else a grid of its tiles that overlap the window, each with the cells
    outside the window marked unobserved (so rasterizing it crops the export to the window's observed cells)."""
    if window is None:
        return grid
    size = grid.tile_size
    out = TiledGrid(grid.resolution, size)
    for tile in covered(grid.keys(), size, window):
        logodds, variance, observed = grid.tile_arrays(tile)
        out.set_tile(tile, logodds, variance, observed & window.mask(tile, size))
    return out
