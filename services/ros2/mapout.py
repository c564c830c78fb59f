"""The map the bridge sends to ROS 2 (no networking here): a mirror of the shards' tiles, kept from their
TileUpdates, and the ``nav_msgs/OccupancyGrid`` and ``map_msgs/OccupancyGridUpdate`` values made of it.

The whole grid spans the bounding box of the tiles known when it is published, whole tiles, so its origin is the
lower-left corner of the lowest tile (tx0 * T * resolution, ty0 * T * resolution) and stays put until a tile beyond
it appears. A tile update inside the box last published becomes an OccupancyGridUpdate of its window, at column
(tx - tx0) * T + col0 and row (ty - ty0) * T + row0 of that grid; one beyond it waits for the next whole grid
(:attr:`MapMirror.grown`), which the bridge publishes at its throttled rate.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from mapping.grid import MAX_RASTER_CELLS, TiledGrid
from schemas.messages import TileUpdate
from services.ros2.convert import occupancy_values, variance_values

#: (tx0, ty0, tx1, ty1): the tiles a published grid spans, inclusive
Extent = tuple[int, int, int, int]

#: the most tiles a mirror holds: the whole grid is made tile by tile, and a map of 1-cell tiles within
#: MAX_RASTER_CELLS would be 2**28 of them (a map of 256-cell tiles reaches MAX_RASTER_CELLS with 4 096)
MAX_MIRROR_TILES = 1 << 16


@dataclass(frozen=True)
class Raster:
    """A whole published grid: values (H, W) int8 of occupancy and of variance, origin (m), resolution (m)."""

    occupancy: np.ndarray
    variance: np.ndarray
    origin: tuple[float, float]
    resolution: float
    extent: Extent


@dataclass(frozen=True)
class Patch:
    """One OccupancyGridUpdate: values (H, W) int8 at column ``x``, row ``y`` of the last published grid."""

    x: int
    y: int
    values: np.ndarray


class MapMirror:
    """Tiles of one map as its shards publish them. ``variance_scale``: the variance shown as 100 on map_variance."""

    def __init__(self, variance_scale: float = 1.0):
        self.variance_scale = variance_scale
        self.grid: TiledGrid | None = None
        self.published: Extent | None = None  # the tiles of the grid last published
        self.dirty = False  # changed since the whole grid was last published
        self.grown = False  # holds a tile beyond the grid last published
        self._extent: Extent | None = None  # the bounding box of the tiles held

    def check(self, tile: TileUpdate) -> str:
        """Why ``tile`` cannot be taken, or "": a zoom level other than 0, a resolution or tile size other than
        the first tile's (two maps under one name), or a new tile that would take the grid past MAX_RASTER_CELLS
        cells (the whole grid could no longer be published, and the tiles held are bounded) or the mirror past
        MAX_MIRROR_TILES tiles."""
        if tile.z != 0:
            return f"zoom level {tile.z}; only level 0 is mirrored"
        grid = self.grid
        if grid is None:
            return ""
        if (tile.resolution, tile.tile_size) != (grid.resolution, grid.tile_size):
            return (
                f"a tile of {tile.tile_size} cells at {tile.resolution} m, but the map's are "
                f"{grid.tile_size} cells at {grid.resolution} m"
            )
        extent = self._extent
        if extent is not None and (tile.tx, tile.ty) not in grid:
            if grid.tile_count >= MAX_MIRROR_TILES:
                return f"tile ({tile.tx}, {tile.ty}) would take the mirror past {MAX_MIRROR_TILES} tiles"
            grown = _grown(extent, (tile.tx, tile.ty))
            cells = self.cells(grown)
            if cells > MAX_RASTER_CELLS:
                return (
                    f"tile ({tile.tx}, {tile.ty}) would take the grid to {cells} cells, more than the "
                    f"{MAX_RASTER_CELLS} one grid may hold"
                )
        return ""

    def apply(self, tile: TileUpdate) -> Patch | None:
        """Take a TileUpdate that :meth:`check` passes; the OccupancyGridUpdate of its window when it lies inside the
        grid last published, else None."""
        if self.grid is None:
            self.grid = TiledGrid(tile.resolution, tile.tile_size)
        key = (tile.tx, tile.ty)
        if key not in self.grid:
            self._extent = (*key, *key) if self._extent is None else _grown(self._extent, key)
        self.grid.slot(key)  # (created, all unknown, when new)
        layers = self.grid.tile_arrays(key)
        tile.paste(*layers)
        self.dirty = True
        extent = self.published
        if extent is None or not (extent[0] <= tile.tx <= extent[2] and extent[1] <= tile.ty <= extent[3]):
            self.grown = True
            return None
        size = self.grid.tile_size
        x = (tile.tx - extent[0]) * size + tile.col0
        y = (tile.ty - extent[1]) * size + tile.row0
        region = (slice(tile.row0, tile.row0 + tile.rows), slice(tile.col0, tile.col0 + tile.cols))
        return Patch(x, y, occupancy_values(layers[0][region], layers[2][region]))

    def extent(self) -> Extent | None:
        """The bounding box of the tiles held, None when none is."""
        return self._extent

    def cells(self, extent: Extent) -> int:
        """Cells of a grid spanning ``extent``."""
        assert self.grid is not None
        size = self.grid.tile_size
        return (extent[2] - extent[0] + 1) * (extent[3] - extent[1] + 1) * size * size

    def raster(self) -> Raster | None:
        """The whole grid over every tile held, marked published (:attr:`dirty` and :attr:`grown` cleared); None
        when no tile is held or the grid would pass mapping.grid.MAX_RASTER_CELLS cells."""
        extent = self.extent()
        if extent is None or self.cells(extent) > MAX_RASTER_CELLS:
            return None
        grid = self.grid
        assert grid is not None
        size = grid.tile_size
        shape = ((extent[3] - extent[1] + 1) * size, (extent[2] - extent[0] + 1) * size)
        occupancy = np.full(shape, -1, np.int8)
        variance = np.full(shape, -1, np.int8)
        tiles = grid.keys()  # (a TiledGrid's, in creation order: it is no dict)
        for key in tiles:
            logodds, spread, observed = grid.tile_arrays(key)
            rows = slice((key[1] - extent[1]) * size, (key[1] - extent[1] + 1) * size)
            cols = slice((key[0] - extent[0]) * size, (key[0] - extent[0] + 1) * size)
            occupancy[rows, cols] = occupancy_values(logodds, observed)
            variance[rows, cols] = variance_values(spread, observed, self.variance_scale)
        self.published, self.dirty, self.grown = extent, False, False
        span = size * grid.resolution
        return Raster(occupancy, variance, (extent[0] * span, extent[1] * span), grid.resolution, extent)


def _grown(extent: Extent, tile: tuple[int, int]) -> Extent:
    """``extent`` widened to hold ``tile`` (tx, ty)."""
    return (min(extent[0], tile[0]), min(extent[1], tile[1]), max(extent[2], tile[0]), max(extent[3], tile[1]))


class MapStamp:
    """The stamp (s) the map goes out with: that of the latest scan, by seq, fused into it. The stamps of the newest
    ``kept`` scans the bridge published are remembered by seq (:meth:`published`), and a tile update naming a seq
    past the latest makes it the latest (:meth:`fused`). By seq, not the largest stamp seen: a robot's clock set
    back, or one scan stamped far ahead, would have stamped every later map with that stamp."""

    def __init__(self, kept: int):
        self.kept = kept
        self._stamps: OrderedDict[int, float] = OrderedDict()  # seq -> stamp of the scans published, oldest first
        self._latest_seq = -1
        self.stamp = 0.0

    def published(self, seq: int, stamp: float) -> None:
        """Scan ``seq`` went out stamped ``stamp`` s."""
        self._stamps[seq] = stamp
        while len(self._stamps) > self.kept:
            self._stamps.popitem(last=False)

    def fused(self, seq: int) -> None:
        """A tile update says scan ``seq`` (of this bridge's robot) is fused into the map."""
        if seq > self._latest_seq and seq in self._stamps:
            self.stamp, self._latest_seq = self._stamps[seq], seq
