"""Monte Carlo fusion of one scan under M weighted pose samples (paper, section V, eq. 9).

For a scan with pose samples x_j and weights w_j (sum 1), every cell i touched under any sample gets

    l_i <- clamp(l_i + sum_j w_j y_ij)            variance_i <- variance_i + sum_j w_j y_ij^2 - (sum_j w_j y_ij)^2

where y_ij is the cell's log-odds under sample j (0 where sample j does not touch the cell; the prior
log-odds is 0, so nothing is subtracted).

Rule for one cell, one scan, one sample (docs/sensor_model.md): every beam that crosses the cell proposes
the model's largest value over the beam's segment inside the cell, and the cell takes the largest of those
proposals. A beam ending in the cell therefore always beats a beam passing through it: occupied wins over
free, as in OctoMap's per-scan update.

The whole scan is one compiled pass over all (sample, beam, cell) triples, written into a scratch window
that covers the scan (its origin a multiple of 8 cells), followed by one compiled pass that adds the
window's touched cells into the tiles. No Python loop runs per sample, beam or cell.

A scan with M > 1 distinct samples takes the samples pass (:mod:`mapping.samples_pass`: a bit plane per
sample, most of each ray's free space marked in it as runs of cells per grid line (:mod:`mapping.free_runs`),
per-sample records near the returns); one distinct sample takes the one-sample pass (:mod:`mapping.single_pass`),
which gives the same map for about half the time. Both walk the rays with :mod:`mapping.window_walk` and value
the cells with :mod:`mapping.beam_model`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapping.beam_model import BEAM_SKIP, BeamTable, beam_table, logodds_model
from mapping.errors import InputError
from mapping.grid import TiledGrid
from mapping.samples_pass import STAMP_LIMIT, accumulate_scan, apply_scan
from mapping.scan_input import check_scan, check_window, laser_poses, merge_duplicates
from mapping.sensor_model import SensorModel
from mapping.single_pass import accumulate_single, apply_single
from mapping.window_walk import Tiles, Window


@dataclass(frozen=True)
class FuseResult:
    """What one scan changed: the number of distinct cells updated and the tiles they lie in."""

    cells_updated: int
    tiles_changed: list[tuple[int, int]]


class MonteCarloFusion:
    """Fuses scans of one laser into a :class:`TiledGrid`, one compiled pass per scan.

    beam_angles: (B,) rad in the laser frame; range_min, range_max: m; sensor_offset: the laser's
    (x m, y m, yaw rad) in the robot frame; owns_tile: optional (tx, ty) -> bool, for a shard that fuses
    only its own tiles (the cells of other tiles are skipped); merge_identical: merge identical pose
    samples before ray casting (on by default; off only to measure what merging saves).
    """

    def __init__(
        self,
        grid: TiledGrid,
        model: SensorModel,
        beam_angles: np.ndarray,
        range_min: float,
        range_max: float,
        sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        owns_tile: Callable[[int, int], bool] | None = None,
        merge_identical: bool = True,
    ) -> None:
        if not np.isclose(grid.resolution, model.resolution):
            raise InputError(
                f"grid resolution {grid.resolution} m differs from the sensor model's {model.resolution} m"
            )
        if not 0 <= range_min < range_max or not np.isfinite(range_max):
            raise InputError(f"need 0 <= range_min < range_max < inf, got {range_min} and {range_max}")
        self.grid = grid
        self.model = model
        self.angles = np.ascontiguousarray(beam_angles, dtype=np.float64)
        self._cos_angles, self._sin_angles = np.cos(self.angles), np.sin(self.angles)  # (the kernels' beam directions)
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.sensor_offset = np.asarray(sensor_offset, dtype=np.float64)
        self.owns_tile = owns_tile
        self.merge_identical = merge_identical
        self._owned_cache: dict[tuple[int, int], bool] = {}
        self._owned_windows: dict[tuple[int, int, int, int], tuple[np.ndarray, bool]] = {}
        self._stamp_next = 1
        self._scratch_size = 0
        self._columns = np.zeros(0, np.uint64)
        self._lines = np.zeros((2, 0), np.int64)  # a ray's exit and entry cells per grid line (mapping.free_runs)
        self._block = np.zeros(64, np.uint64)  # 64 x 64 bits being folded from the column-major plane
        self._single_blocks = 0
        # what the kernels read of the model, built once: plain tuples (mapping.beam_model.BeamTable says why)
        self._model_terms = tuple(logodds_model(model))
        self._levels = (model.l_free, model.l_min, model.l_max)  # (properties: computed)
        self._directions = (self._cos_angles, self._sin_angles)

    def _scratch(self, cells: int, column_bits: int, lines: int) -> None:
        """The samples pass's scratch for a window of ``cells`` cells, ``column_bits`` bits of the column-major plane
        (mapping.free_runs) and ``lines`` grid lines a side at most."""
        if column_bits > self._columns.shape[0] * 64:
            self._columns = np.zeros(column_bits // 64, np.uint64)
        if lines > self._lines.shape[1]:
            self._lines = np.zeros((2, lines), np.int64)
        if cells <= self._scratch_size:
            return
        self._scratch_size = cells
        # per cell (see accumulate_scan): a bit in the sample's plane and in the listed plane, the weight sum,
        # the excess record
        self._plane = np.zeros((cells + 63) // 64, np.uint64)
        self._listed = np.zeros((cells + 63) // 64, np.uint64)
        self._weight_sum = np.zeros(cells, np.float64)
        self._excess = np.zeros((cells, 4), np.float64)
        self._scan_cells = np.zeros(cells, np.int64)

    def _single_scratch(self, blocks: int) -> None:
        if blocks <= self._single_blocks:
            return
        self._single_blocks = blocks
        # per 8 x 8 block and per cell (see accumulate_single): touched and raised bits, the largest excess
        self._touched_bits = np.zeros(blocks, np.int64)
        self._raised_bits = np.zeros(blocks, np.int64)
        self._largest = np.zeros(blocks * 64, np.float64)

    def _owned_mask(self, tx0: int, ty0: int, ntx: int, nty: int) -> tuple[np.ndarray, bool]:
        """Which tiles of the window's ntx x nty tiles from (tx0, ty0) the shard owns, and whether all; kept
        per window (the kernels only read it)."""
        key = (tx0, ty0, ntx, nty)
        window = self._owned_windows.get(key)
        if window is None:
            owned = np.ones((nty, ntx), np.bool_)
            if self.owns_tile is not None:
                for j in range(nty):
                    for i in range(ntx):
                        tile = (tx0 + i, ty0 + j)
                        if tile not in self._owned_cache:
                            self._owned_cache[tile] = bool(self.owns_tile(*tile))
                        owned[j, i] = self._owned_cache[tile]
            window = self._owned_windows[key] = (owned, bool(owned.all()))
        return window

    def _tile_slots(self, touched: np.ndarray, tx0: int, ty0: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
        """The grid slot of each touched tile of the window (tiles created as needed; -1 elsewhere), and the
        touched tiles' keys in row order."""
        slot_map = np.full(touched.shape, -1, np.int64)
        changed = []
        for j, i in zip(*(index.tolist() for index in np.nonzero(touched))):
            key = (tx0 + i, ty0 + j)
            slot_map[j, i] = self.grid.slot(key)
            changed.append(key)
        return slot_map, changed

    def fuse(self, ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray) -> FuseResult:
        """Fuse one scan: ranges (B,) m, robot pose samples (M, 3) map frame, weights (M,) summing to 1.

        One distinct sample (after merging) takes the one-sample pass
        (:func:`mapping.single_pass.accumulate_single`), which gives the same map as the samples pass for less work."""
        ranges, samples, weights = check_scan(ranges, samples, weights, self.angles.shape[0])
        if self.merge_identical:
            samples, weights = merge_duplicates(samples, weights)
        beams = beam_table(ranges, self.model, self.range_min, self.range_max)
        if not (beams.kind != BEAM_SKIP).any():
            return FuseResult(0, [])
        lasers = laser_poses(samples, self.sensor_offset)
        window, tiles = self._window(lasers, float(beams.r_stop.max()) + self.grid.resolution)
        if len(samples) == 1:
            return self._fuse_single(lasers[0], float(weights[0]), beams, window, tiles)
        return self._fuse_samples(lasers, weights, beams, window, tiles)

    def _window(self, lasers: np.ndarray, reach: float) -> tuple[Window, Tiles]:
        """The scratch window over the rays of laser poses (M, 3) that reach ``reach`` m (its origin a multiple of 8
        cells: the one-sample pass's 8 x 8 blocks are the grid's), and the tiles over it."""
        res = self.grid.resolution
        if len(lasers) == 1:  # (reductions cost a few microseconds each)
            ((x_lo, y_lo, _),) = lasers.tolist()
            x_hi, y_hi = x_lo, y_lo
        else:
            (x_lo, y_lo), (x_hi, y_hi) = lasers[:, :2].min(axis=0).tolist(), lasers[:, :2].max(axis=0).tolist()
        check_window(x_lo, y_lo, x_hi, y_hi, reach, res)
        ix0 = math.floor((x_lo - reach) / res) & ~7
        iy0 = math.floor((y_lo - reach) / res) & ~7
        w = math.floor((x_hi + reach) / res) - ix0 + 1
        h = math.floor((y_hi + reach) / res) - iy0 + 1
        shift = self.grid.tile_shift
        tx0, ty0 = ix0 >> shift, iy0 >> shift
        ntx = ((ix0 + w - 1) >> shift) - tx0 + 1
        nty = ((iy0 + h - 1) >> shift) - ty0 + 1
        owned, all_owned = self._owned_mask(tx0, ty0, ntx, nty)
        return Window(ix0, iy0, w, h), Tiles(owned, all_owned, shift, tx0, ty0)

    def _ray_args(
        self, beams: BeamTable
    ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, ...], tuple[object, ...], float]:
        """What both passes' kernels take about the rays, in their order: the beams' directions (cosines, sines),
        the beam table, the model's terms and the cell size (m), as plain tuples (mapping.beam_model.BeamTable)."""
        return self._directions, tuple(beams), self._model_terms, self.grid.resolution

    def _fuse_single(
        self, laser: np.ndarray, weight: float, beams: BeamTable, window: Window, tiles: Tiles
    ) -> FuseResult:
        """The one-sample pass (laser pose (3,): x m, y m, yaw rad; its sample's weight)."""
        blocks_w, blocks_h = -(-window.w // 8), -(-window.h // 8)
        self._single_scratch(blocks_w * blocks_h)
        touched = np.zeros(tiles.owned.shape, np.bool_)
        scratch = (self._touched_bits, self._raised_bits, self._largest, blocks_w, blocks_h, touched)
        window_args, tile_args = tuple(window), tuple(tiles)
        n_scan = accumulate_single(laser, *self._ray_args(beams), window_args, tile_args, scratch)
        slot_map, changed = self._tile_slots(touched, tiles.tx0, tiles.ty0)
        grid = self.grid  # (its layers after _tile_slots: new tiles may have moved them)
        layers = (grid.logodds, grid.variance, grid.observed)
        apply_single(scratch, weight, window_args, tile_args, slot_map, layers, self._levels)
        return FuseResult(int(n_scan), changed)

    def _fuse_samples(
        self, lasers: np.ndarray, weights: np.ndarray, beams: BeamTable, window: Window, tiles: Tiles
    ) -> FuseResult:
        """The samples pass (laser poses (M, 3), weights (M,))."""
        # the samples pass's scratch rows and columns are whole 64-bit words of its bit planes (mapping.free_runs)
        win_w = -(-window.w // 64) * 64
        col_stride = -(-window.h // 64) * 64
        self._scratch(win_w * window.h, win_w * col_stride, max(win_w, window.h))
        if self._stamp_next + len(lasers) >= STAMP_LIMIT:
            self._excess[:] = 0
            self._stamp_next = 1
        stamp_base = self._stamp_next
        self._stamp_next += len(lasers)
        touched = np.zeros(tiles.owned.shape, np.bool_)
        scratch = (
            self._plane,
            self._columns,
            col_stride,
            self._listed,
            self._weight_sum,
            self._excess,
            self._scan_cells,
            touched,
            self._lines,
            self._block,
        )
        window_args, tile_args = (window.ix0, window.iy0, win_w, window.h), tuple(tiles)
        n_scan = accumulate_scan(lasers, weights, *self._ray_args(beams), window_args, tile_args, scratch, stamp_base)
        slot_map, changed = self._tile_slots(touched, tiles.tx0, tiles.ty0)
        grid = self.grid
        layers = (grid.logodds, grid.variance, grid.observed)
        apply_scan(scratch, n_scan, stamp_base, window_args, tile_args, slot_map, layers, self._levels)
        return FuseResult(int(n_scan), changed)
