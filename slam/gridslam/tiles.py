"""One occupancy grid per particle, stored as square tiles that particles share copy-on-write.

All grids use the global cell lattice of mapping.raytrace: cell (ix, iy) covers x in [ix*res, (ix+1)*res)
and y in [iy*res, (iy+1)*res) of the map frame (m); a cell holds a log-odds value (0 = unknown). Tile
(tx, ty) holds cells ix in [tx*S, (tx+1)*S), iy likewise, S = ``tile_cells`` (a power of two, so the
compiled kernels split cell indices into tile and offset with shifts).

Storage: a pool of tiles ``pool`` (C, S, S, 4) float32 with a reference count each, and a table
``table`` (M, NY, NX) int32 per particle naming the pool tile at each tile coordinate
(tx0 + u, ty0 + v), or -1 where the particle has never written. Resampling copies table rows only (a few
kB per particle) and recounts references; a particle that writes into a tile it shares gets its own copy
first (slam.gridslam.kernels.own_tile, called by the writing kernel), so a particle's map never changes through
another's writes.

A cell holds four numbers (the last axis): its log-odds (:data:`LOGODDS`), the sums of the x and y offsets
(m) of the beam ends that fell into it from the cell's lower-left corner (:data:`SUM_X`, :data:`SUM_Y`) and
their count (:data:`HITS`), so the scan matcher measures distances to the mean end point, not to the cell
centre (sub-cell precision).
"""

from __future__ import annotations

import numpy as np

from slam.errors import LogFormatError
from slam.gridslam.kernels import insert_scan

#: channels of a cell (the pool's last axis)
LOGODDS, SUM_X, SUM_Y, HITS = 0, 1, 2, 3
CHANNELS = 4
#: entries of the particles' tile tables together (2^27: 512 MiB of int32, 30 particles over 3.4 km x 3.4 km of
#: 1.6 m tiles): a box past it is refused (an odometry jump of 3 km took a run to 13 GB)
MAX_TABLE_ENTRIES = 2**27


class TileMaps:
    """M particle grids of ``resolution`` m cells in shared tiles of ``tile_cells`` x ``tile_cells`` cells."""

    def __init__(self, particles: int, resolution: float, tile_cells: int = 32, capacity: int = 256) -> None:
        if particles < 1 or resolution <= 0 or tile_cells < 1 or tile_cells & (tile_cells - 1):
            raise ValueError("need particles >= 1, resolution > 0 m and tile_cells a power of two")
        self.resolution = float(resolution)
        self.tile_cells = int(tile_cells)
        self.shift = self.tile_cells.bit_length() - 1  # tile_cells == 1 << shift
        self.pool = np.zeros((capacity, tile_cells, tile_cells, CHANNELS), np.float32)
        self.refcount = np.zeros(capacity, np.int32)
        self.free_stack = np.arange(capacity - 1, -1, -1, dtype=np.int32)
        self.n_free = np.array([capacity], np.int64)
        self.table = np.full((particles, 0, 0), -1, np.int32)
        self.tx0 = 0
        self.ty0 = 0
        self.copies = 0  # tiles copied on write so far

    @property
    def particles(self) -> int:
        return self.table.shape[0]

    @property
    def tiles_in_use(self) -> int:
        return int(np.count_nonzero(self.refcount))

    def tile_of(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tile coordinates (tx, ty) of map-frame points (m)."""
        side = self.resolution * self.tile_cells
        return np.floor(np.asarray(x) / side).astype(np.int64), np.floor(np.asarray(y) / side).astype(np.int64)

    def cover(self, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Grow every particle's table so it spans the box [xmin, xmax] x [ymin, ymax] (m), with a margin."""
        (tx_lo, tx_hi), (ty_lo, ty_hi) = self.tile_of(np.array([xmin, xmax]), np.array([ymin, ymax]))
        _, ny, nx = self.table.shape
        if nx and self.tx0 <= tx_lo and tx_hi < self.tx0 + nx and self.ty0 <= ty_lo and ty_hi < self.ty0 + ny:
            return
        margin = 4
        if nx:
            tx_lo, ty_lo = min(tx_lo, self.tx0), min(ty_lo, self.ty0)
            tx_hi, ty_hi = max(tx_hi, self.tx0 + nx - 1), max(ty_hi, self.ty0 + ny - 1)
        tx_lo, ty_lo, tx_hi, ty_hi = tx_lo - margin, ty_lo - margin, tx_hi + margin, ty_hi + margin
        entries = self.particles * int(ty_hi - ty_lo + 1) * int(tx_hi - tx_lo + 1)
        if entries > MAX_TABLE_ENTRIES:
            width, height = (
                self.resolution * self.tile_cells * (hi - lo + 1) for lo, hi in ((tx_lo, tx_hi), (ty_lo, ty_hi))
            )
            raise LogFormatError(
                f"the particles' maps would span {width:.4g} m x {height:.4g} m "
                f"({entries} tile entries for {self.particles} particles), more than the {MAX_TABLE_ENTRIES} grid "
                "FastSLAM holds: does the odometry jump?"
            )
        table = np.full((self.particles, ty_hi - ty_lo + 1, tx_hi - tx_lo + 1), -1, np.int32)
        if nx:
            u0, v0 = self.tx0 - tx_lo, self.ty0 - ty_lo
            table[:, v0 : v0 + ny, u0 : u0 + nx] = self.table
        self.table, self.tx0, self.ty0 = table, int(tx_lo), int(ty_lo)

    def reserve(self, count: int) -> None:
        """Make sure at least ``count`` free tiles are in the pool (doubling it when needed)."""
        if self.n_free[0] >= count:
            return
        old = len(self.pool)
        new = max(2 * old, old + count - int(self.n_free[0]))
        pool = np.zeros((new, self.tile_cells, self.tile_cells, CHANNELS), np.float32)
        pool[:old] = self.pool
        refcount = np.zeros(new, np.int32)
        refcount[:old] = self.refcount
        stack = np.empty(new, np.int32)
        n = int(self.n_free[0])
        stack[:n] = self.free_stack[:n]
        stack[n : n + new - old] = np.arange(new - 1, old - 1, -1, dtype=np.int32)
        self.pool, self.refcount, self.free_stack = pool, refcount, stack
        self.n_free[0] = n + new - old

    def insert(
        self,
        poses: np.ndarray,
        offset: np.ndarray,
        cos_b: np.ndarray,
        sin_b: np.ndarray,
        r_stop: np.ndarray,
        hit: np.ndarray,
        l_occ: float,
        l_free: float,
        l_clamp: float,
    ) -> int:
        """Insert one scan into every particle's grid (slam.gridslam.kernels.insert_scan), growing the pool
        as the kernel asks. poses (M, 3) robot poses (m, rad, map frame); offset (3,) laser pose in the
        robot frame; beams by direction (cos_b, sin_b) in the laser frame, length r_stop (m, NaN: unused)
        and hit flags. The table must already span the beams (:meth:`cover`). Returns the cell updates."""
        resume = np.zeros(3, np.int64)
        counters = np.zeros(2, np.int64)
        frame = (self.tx0, self.ty0, self.shift, self.resolution)
        scan = (np.ascontiguousarray(poses, np.float64), offset, cos_b, sin_b, r_stop, hit)
        update = (l_occ, l_free, -l_clamp, l_clamp)
        while not insert_scan(
            self.pool, self.refcount, self.free_stack, self.n_free, self.table, frame, scan, update, resume, counters
        ):
            self.reserve(len(self.pool))
        self.copies += int(counters[1])
        return int(counters[0])

    def resample(self, parents: np.ndarray) -> None:
        """Particle j takes particle parents[j]'s map (shared, no tile is copied); unreferenced tiles are freed."""
        self.table = np.ascontiguousarray(self.table[np.asarray(parents)])
        used = self.table[self.table >= 0]
        self.refcount = np.bincount(used, minlength=len(self.pool)).astype(np.int32)
        free = np.flatnonzero(self.refcount == 0).astype(np.int32)
        self.free_stack[: len(free)] = free[::-1]
        self.n_free[0] = len(free)

    def raster(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """One particle's grid as a log-odds raster (H, W) float32 over its written tiles, and the map-frame
        (x, y) (m) of the lower-left corner of cell [0, 0]; row i covers y in [y0 + i*res, y0 + (i+1)*res)."""
        rows = self.table[particle]
        vs, us = np.nonzero(rows >= 0)
        side = self.tile_cells
        if not len(vs):
            return np.zeros((0, 0), np.float32), np.zeros(2)
        v0, u0 = vs.min(), us.min()
        out = np.zeros(((vs.max() - v0 + 1) * side, (us.max() - u0 + 1) * side), np.float32)
        for v, u in zip(vs, us):  # one block copy per tile (not per cell): a few hundred per map
            out[(v - v0) * side : (v - v0 + 1) * side, (u - u0) * side : (u - u0 + 1) * side] = self.pool[
                rows[v, u], :, :, LOGODDS
            ]
        origin = np.array([(self.tx0 + u0) * side, (self.ty0 + v0) * side], np.float64) * self.resolution
        return out, origin
