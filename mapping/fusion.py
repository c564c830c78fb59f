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

Identical samples are merged first; with a bundle tolerance (:mod:`mapping.bundling`, opt-in) the samples are bundled
and only the bundles' leaders walk. A scan with M > 1 distinct samples takes the samples pass
(:mod:`mapping.samples_pass`: a bit plane per sample, most of each ray's free space marked in it as runs of cells per
grid line (:mod:`mapping.free_runs`), per-sample records near the returns); one distinct sample takes the one-sample
pass (:mod:`mapping.single_pass`), which gives the same map for about half the time. Both walk the rays with
:mod:`mapping.window_walk` and value the cells with :mod:`mapping.beam_model`.

A scan is fused in three stages: :meth:`MonteCarloFusion.prepare` (checks, beam table, window),
:meth:`~MonteCarloFusion.walk` (the compiled pass into a :class:`FusionScratch`; it reads nothing of the map) and
:meth:`~MonteCarloFusion.apply` (the only stage that writes the map). :class:`FusionThreads` walks several scans at
once, each into a scratch of its own, and applies them in scan order (:mod:`mapping.parallel_fusion`), or one scan's
samples in parts at once (their per-cell sums are whole numbers of fixed steps, :mod:`mapping.fixed_point`, the same in
any order), so the map is the same bit for bit on any number of threads.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from mapping.beam_model import BEAM_SKIP, BeamTable, beam_table, logodds_model
from mapping.bundling import bundle_samples, check_tolerance
from mapping.errors import InputError
from mapping.fan_runs import fan_scratch
from mapping.fixed_point import WEIGHT_SCALE, moment_scale
from mapping.grid import TiledGrid
from mapping.parallel_fusion import in_scan_order
from mapping.samples_pass import (
    APPLY_HELD,
    COUNT_LEVELS,
    GROUP,
    STAMP_LIMIT,
    accumulate_scan,
    apply_scan,
    merge_scan,
    owned_table,
)
from mapping.scan_input import (
    MAX_WINDOW_CELLS,
    check_laser,
    check_no_return_range,
    check_scan,
    check_window,
    laser_poses,
    merge_duplicates,
)
from mapping.sensor_model import SensorModel
from mapping.single_pass import accumulate_single, apply_single
from mapping.tile_boxes import empty_boxes, tile_windows
from mapping.window_walk import Tiles, Window


@dataclass(frozen=True)
class FuseResult:
    """What one scan changed: the number of distinct cells updated and the tiles they lie in; the pose samples whose
    rays it walked (after merging identical ones and bundling, mapping.bundling; 0 for a scan not walked); and per
    tile of tiles_changed, the window of it that holds the cells updated: (row0, col0, rows, cols), tile-local
    cells (mapping.tile_boxes)."""

    cells_updated: int
    tiles_changed: list[tuple[int, int]]
    samples_walked: int = 0
    windows: list[tuple[int, int, int, int]] = field(default_factory=list)


#: what :meth:`MonteCarloFusion.fuse_iter` takes per scan: ranges (B,) m, robot pose samples (M, 3), weights (M,)
ScanInput = tuple[np.ndarray, np.ndarray, np.ndarray]


class FusionScratch:
    """The working memory of one scan's walk (:func:`mapping.samples_pass.accumulate_scan` or
    :func:`mapping.single_pass.accumulate_single`), grown to the largest window walked in it and reused.

    Per cell of the scratch window the samples pass keeps six bits (plane and the group's other three planes, listed,
    raised), a four-float excess record (32 bytes) and 16 bits of counts, plus a bit of the column-major plane, and
    once it has walked a scan whose weights differ a weight sum (8 bytes): SAMPLES_SCRATCH_BYTES_PER_CELL, about 43
    bytes a window cell in all (35 while every scan's weights were equal, as resampled particles' and Gaussian draws'
    are; the one-sample pass keeps 8 bytes and two bits). 11 MB for the office's 12 m laser at 0.05 m (a window of
    about 490 x 490 cells), 63 MB for a 30 m laser, 0.71 GB at the largest window a scan may take
    (mapping.scan_input.MAX_WINDOW_CELLS). A :class:`FusionThreads` of T > 1 threads keeps T + 1 of them, and any one
    keeps one more (``lone``) for its fusions' lone scans. When it grows, it takes SCRATCH_ROOM more cells than the
    window asks (up to MAX_WINDOW_CELLS): a window that grows with the samples' spread, scan after scan, then seldom
    reallocates (each growth faults in the new arrays' pages: about 15 ms a scan for a 30 m laser).

    Nothing in it carries from one scan to the next: each pass clears what it set, and the samples pass tells the
    excess records of earlier scans by their stamps (unique per scratch: :meth:`stamps`)."""

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Drop everything it holds, as a new scratch: after a walk that was never applied (it failed, or its scan's
        turn never came), whose marks nothing else would clear."""
        self.stamp_next = 1
        self.size = 0  # cells the samples pass's per-cell arrays hold
        self.columns = np.zeros(0, np.uint64)
        self.lines = np.zeros((2, 0), np.int64)  # a ray's exit and entry cells per grid line (mapping.free_runs)
        self.block = np.zeros(64, np.uint64)  # 64 x 64 bits being folded from the column-major plane
        self.plane = self.listed = self.raised = np.zeros(0, np.uint64)
        self.group_planes = np.zeros((GROUP - 1, 0), np.uint64)
        self.weight_sum = np.zeros(0, np.int64)
        self.excess = np.zeros((0, 4), np.float64)
        self.moments = self.excess.view(np.int64)  # (the records' moments are int64 steps: mapping.fixed_point)
        self.counts = np.zeros((COUNT_LEVELS, 0), np.uint64)
        self.fan_ints, self.fan_floats = fan_scratch(0)
        self.single_blocks = 0
        self.touched_bits = self.raised_bits = np.zeros(0, np.int64)
        self.largest = np.zeros(0, np.float64)

    def for_samples(self, cells: int, column_bits: int, lines: int, beams: int, summed: bool = True) -> None:
        """Room for the samples pass over a window of ``cells`` cells, ``column_bits`` bits of the column-major plane
        (mapping.free_runs), ``lines`` grid lines a side at most and scans of ``beams`` beams (mapping.fan_runs); the
        weight sums only for a scan whose weights are ``summed`` (they differ: equal weights are counted)."""
        if beams > self.fan_ints.shape[1]:
            self.fan_ints, self.fan_floats = fan_scratch(beams)
        if column_bits > self.columns.shape[0] * 64:
            self.columns = np.zeros(column_bits // 64, np.uint64)
        if lines > self.lines.shape[1]:
            self.lines = np.zeros((2, lines), np.int64)
        if cells > self.size:
            self.size = cells = _with_room(cells)
            # per cell (see accumulate_scan): a bit in the sample's plane, the listed plane and the raised plane, the
            # excess record, the counts
            self.plane = np.zeros((cells + 63) // 64, np.uint64)
            self.group_planes = np.zeros((GROUP - 1, (cells + 63) // 64), np.uint64)
            self.listed = np.zeros((cells + 63) // 64, np.uint64)
            self.raised = np.zeros((cells + 63) // 64, np.uint64)
            self.excess = np.zeros((cells, 4), np.float64)
            self.moments = self.excess.view(np.int64)
            self.counts = np.zeros((COUNT_LEVELS, (cells + 63) // 64), np.uint64)
        if summed and self.weight_sum.shape[0] < self.size:  # (read only when the weights differ)
            self.weight_sum = np.zeros(self.size, np.int64)

    def for_single(self, blocks: int) -> None:
        """Room for the one-sample pass over a window of ``blocks`` 8 x 8 blocks."""
        if blocks <= self.single_blocks:
            return
        self.single_blocks = blocks = _with_room(blocks)
        # per 8 x 8 block and per cell (see accumulate_single): touched and raised bits, the largest excess
        self.touched_bits = np.zeros(blocks, np.int64)
        self.raised_bits = np.zeros(blocks, np.int64)
        self.largest = np.zeros(blocks * 64, np.float64)

    @property
    def nbytes(self) -> int:
        """Bytes its arrays hold now (views of another of them aside)."""
        return sum(
            value.nbytes for value in vars(self).values() if isinstance(value, np.ndarray) and value.base is None
        )

    def stamps(self, count: int) -> int:
        """The first of ``count`` fresh sample stamps of this scratch (the records are cleared when stamps would pass
        STAMP_LIMIT, and the stamps start again)."""
        if self.stamp_next + count >= STAMP_LIMIT:
            self.excess[:] = 0
            self.stamp_next = 1
        first = self.stamp_next
        self.stamp_next += count
        return first


class Ready(NamedTuple):
    """A checked scan, to walk: laser poses (M, 3) after merging, their weights (M,), the beam table, the window, its
    tiles and their owned tiles' summed-area table (:func:`mapping.samples_pass.owned_table`)."""

    lasers: np.ndarray
    weights: np.ndarray
    beams: BeamTable
    window: Window
    tiles: Tiles
    owned_sum: np.ndarray


class Walked(NamedTuple):
    """A walked scan, to apply: the pass's scratch (the kernels' tuple), the cells it touched (one-sample pass; the
    samples pass's apply counts them), the tiles it touched, the window and tiles (tuples), the one sample's weight
    (one-sample pass), the number of laser poses walked, and the boxes of the cells touched per tile of the window."""

    single: bool
    scratch: tuple
    n_scan: int
    touched: np.ndarray
    window_args: tuple
    tile_args: tuple
    weight: float
    samples: int  # the laser poses walked
    boxes: np.ndarray  # per tile of the window, the box of the cells touched (mapping.tile_boxes)


class MonteCarloFusion:
    """Fuses scans of one laser into a :class:`TiledGrid`, one compiled pass per scan.

    beam_angles: (B,) rad in the laser frame; range_min, range_max: m; sensor_offset: the laser's
    (x m, y m, yaw rad) in the robot frame; no_return_range: how far (m) a beam with no return clears free space, at
    most range_max (None, the default: range_max, as REP 117 reads +inf; 0: such beams are skipped, as for a real
    laser whose missing echoes come from dark or glancing surfaces too); owns_tile: optional (tx, ty) -> bool, for a
    shard that fuses only its own tiles (the cells of other tiles are skipped); merge_identical: merge identical pose
    samples before ray casting (on by default; off only to measure what merging saves); bundle: the tolerance (m) of
    :mod:`mapping.bundling` (0, the default: every distinct sample walks its rays; > 0: the samples of a scan are
    bundled and only the bundles' leaders walk, an approximation within that bound); threads: how many scans
    :meth:`fuse_iter` walks at once, or a :class:`FusionThreads` shared with the other fusions of the same grid (one
    per laser geometry). Not thread-safe: one caller at a time.
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
        threads: int | FusionThreads = 1,
        bundle: float = 0.0,
        no_return_range: float | None = None,
    ) -> None:
        if not np.isclose(grid.resolution, model.resolution):
            raise InputError(
                f"grid resolution {grid.resolution} m differs from the sensor model's {model.resolution} m"
            )
        angles, offset = check_laser(beam_angles, range_min, range_max, sensor_offset)
        try:
            self.bundle = check_tolerance(bundle)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        self.grid = grid
        self.model = model
        self.angles = angles
        self._cos_angles, self._sin_angles = np.cos(self.angles), np.sin(self.angles)  # (the kernels' beam directions)
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.no_return_range = check_no_return_range(no_return_range, self.range_max)
        self.sensor_offset = offset
        self.owns_tile = owns_tile
        self.merge_identical = merge_identical
        self.threads = threads if isinstance(threads, FusionThreads) else FusionThreads(threads)
        self._owned_cache: dict[tuple[int, int], bool] = {}
        self._owned_windows: dict[tuple[int, int, int, int], tuple[np.ndarray, bool, np.ndarray]] = {}
        # what the kernels read of the model, built once: plain tuples (mapping.beam_model.BeamTable says why)
        terms = logodds_model(model)
        self._model_terms = tuple(terms)
        self._levels = (model.l_free, model.l_min, model.l_max)  # (properties: computed)
        # the steps of the samples pass's excess moments: the model's values exceed l_free by y_peak - l_free at most
        self._moment_scale = moment_scale(terms.y_peak - model.l_free)
        self._directions = (self._cos_angles, self._sin_angles)

    def _owned_mask(self, tx0: int, ty0: int, ntx: int, nty: int) -> tuple[np.ndarray, bool, np.ndarray]:
        """Which tiles of the window's ntx x nty tiles from (tx0, ty0) the shard owns, whether all, and the owned
        tiles' summed-area table (:func:`mapping.samples_pass.owned_table`); kept per window (the kernels only read
        them)."""
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
            window = self._owned_windows[key] = (owned, bool(owned.all()), owned_table(owned))
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
        (:func:`mapping.single_pass.accumulate_single`), which gives the same map as the samples pass for less work.
        Raises InputError for a scan it refuses (the map unchanged)."""
        ready = self.prepare((ranges, samples, weights))
        if ready is None:
            return FuseResult(0, [])
        scratch = self.threads.lone
        try:
            return self.apply(self.walk(ready, scratch))
        except BaseException:
            scratch.clear()  # (shared by the threads' fusions: none may walk into what this one left)
            raise

    def fuse_iter(self, scans: Iterable[ScanInput]) -> Iterator[FuseResult | InputError]:
        """Fuse ``scans`` ((ranges, samples, weights) each, as :meth:`fuse` takes them) in order on this fusion's
        threads (:meth:`FusionThreads.fuse_iter`), yielding each scan's FuseResult or the InputError that refused it;
        the map is the same bit for bit for any thread count."""
        if isinstance(scans, Sequence):  # (a sequence of one is walked in parts: FusionThreads.fuse_iter)
            return self.threads.fuse_iter([(self, scan) for scan in scans])
        return self.threads.fuse_iter((self, scan) for scan in scans)

    def fuse_many(self, scans: Iterable[ScanInput]) -> list[FuseResult | InputError]:
        """:meth:`fuse_iter` as a list."""
        return list(self.fuse_iter(scans))

    def prepare(self, scan: ScanInput) -> Ready | None:
        """The first stage of :meth:`fuse`: the scan (ranges, samples, weights) checked and ready to walk (None when
        no beam of it is used, or when the shard owns no tile of its window); InputError when it is refused. Runs on
        the caller's thread, in scan order (it keeps the shard's ownership caches)."""
        ranges, samples, weights = check_scan(*scan, self.angles.shape[0])
        if self.merge_identical:
            samples, weights = merge_duplicates(samples, weights)
        beams = beam_table(ranges, self.model, self.range_min, self.range_max, self.no_return_range)
        used = beams.kind != BEAM_SKIP
        if not used.any():
            return None
        lasers = laser_poses(samples, self.sensor_offset)
        if self.bundle > 0.0:
            lasers, weights = bundle_samples(lasers, weights, self.bundle, float(beams.r_stop[used].mean()))
        window, tiles, owned_sum = self._window(lasers, float(beams.r_stop.max()) + self.grid.resolution)
        if owned_sum[-1, -1] == 0:  # a shard that owns no tile the scan's rays may reach
            return None
        return Ready(lasers, weights, beams, window, tiles, owned_sum)

    def walk(self, ready: Ready, scratch: FusionScratch, part: int = 0, parts: int = 1) -> Walked:
        """The second stage of :meth:`fuse`: the scan's compiled pass into ``scratch``, the one-sample pass for one
        distinct sample, else the samples pass. Reads nothing of the grid: safe on a pool thread, one walk per
        scratch.

        With parts > 1 (at most :meth:`parts_for`), the samples pass walks only the part-th of ``parts`` runs of the
        scan's samples (near-equal, in sample order); :meth:`apply_parts` adds up the parts' scratches, and the map is
        the same bit for bit as from one walk of all the samples (the sums are whole numbers of fixed steps:
        mapping.fixed_point), so the parts of one scan may run on different threads at once."""
        if not 0 <= part < parts <= self.parts_for(ready, parts):
            raise ValueError(f"need 0 <= part < parts <= {self.parts_for(ready, parts)}, got part {part} of {parts}")
        if len(ready.lasers) == 1:
            return self._walk_single(ready, scratch)
        return self._walk_samples(ready, scratch, part, parts)

    @staticmethod
    def parts_for(ready: Ready, threads: int) -> int:
        """How many parts :meth:`walk` takes a prepared scan in on ``threads`` threads: one for one distinct sample,
        else up to one per MIN_PART_SAMPLES samples (a part's walk must outweigh the adding up of its scratch)."""
        return max(1, min(threads, len(ready.lasers) // MIN_PART_SAMPLES))

    def apply(self, walked: Walked) -> FuseResult:
        """The last stage of :meth:`fuse`: add a walked scan into the grid (its tiles created as needed, in row
        order) and clear its scratch. Runs on the caller's thread, in scan order."""
        return self.apply_parts([walked])

    def apply_parts(self, walked: Sequence[Walked], pool: Executor | None = None) -> FuseResult:
        """:meth:`apply` for a scan walked in parts (every part of :meth:`walk`'s ``parts``, each into a scratch of
        its own): the other parts' scratches added into the first's (:func:`mapping.samples_pass.merge_scan`, which
        clears them) and the first applied, band by band of the window's rows, the bands on ``pool`` at once when
        given (each cell's sums and update are its own, so any bands give the same map). Runs on the caller's thread,
        in scan order; the tiles are created here, in row order, before the bands."""
        first = walked[0]
        for other in walked[1:]:
            first.touched[...] |= other.touched
        tx0, ty0 = first.tile_args[3], first.tile_args[4]  # (Tiles: owned, all_owned, shift, tx0, ty0)
        slot_map, changed = self._tile_slots(first.touched, tx0, ty0)
        windows = tile_windows([part.boxes for part in walked], first.touched)
        grid = self.grid  # (its layers after _tile_slots: new tiles may have moved them)
        layers = (grid.logodds, grid.variance, grid.observed, grid.changed)
        if first.single:
            apply_single(
                first.scratch, first.weight, first.window_args, first.tile_args, slot_map, layers, self._levels
            )
            return FuseResult(first.n_scan, changed, first.samples, windows)

        def band(words: tuple[int, int]) -> int:
            """Merge and apply the scratch words words[0] .. words[1] - 1; the cells updated."""
            for other in walked[1:]:
                merge_scan(first.scratch, other.scratch, words)
            args = (first.window_args, first.tile_args, slot_map, layers, self._levels, self._moment_scale, words)
            return int(apply_scan(first.scratch, *args, np.zeros(APPLY_HELD, np.uint64)))

        _, _, win_w, win_h = first.window_args
        words = (win_w * win_h + 63) >> 6
        if pool is None or len(walked) == 1:
            n_scan = band((0, words))
        else:  # bands 1.. on the pool, band 0 on this thread
            mine, *theirs = _bands(words, len(walked))
            jobs = [pool.submit(band, words) for words in theirs]
            try:
                n_scan = band(mine)
            finally:
                wait(jobs)
            n_scan += sum(job.result() for job in jobs)
        return FuseResult(n_scan, changed, sum(part.samples for part in walked), windows)

    def _window(self, lasers: np.ndarray, reach: float) -> tuple[Window, Tiles, np.ndarray]:
        """The scratch window over the rays of laser poses (M, 3) that reach ``reach`` m (its origin a multiple of 8
        cells: the one-sample pass's 8 x 8 blocks are the grid's; a shard's a multiple of 64 cells, so that the
        samples pass's 64 x 64 blocks, which a shard folds and sweeps where they meet its tiles, each lie in one tile
        of 64 cells or more, not in two shards' tiles), the tiles over it and their owned tiles' summed-area table."""
        res = self.grid.resolution
        if len(lasers) == 1:  # (reductions cost a few microseconds each)
            ((x_lo, y_lo, _),) = lasers.tolist()
            x_hi, y_hi = x_lo, y_lo
        else:
            (x_lo, y_lo), (x_hi, y_hi) = lasers[:, :2].min(axis=0).tolist(), lasers[:, :2].max(axis=0).tolist()
        check_window(x_lo, y_lo, x_hi, y_hi, reach, res)
        align = ~7 if self.owns_tile is None else ~63
        # a cell more on every side than the reach asks: floor((x + reach) / res) may lose one to rounding (from x = 1
        # m, a reach of 5.05 m gives 6.05 / 0.05 = 120.99999999999999), and ray_start would then find a ray's end cell
        # without its cell to spare and skip the ray (a beam with no return along an axis, from a laser on a grid line)
        ix0 = (math.floor((x_lo - reach) / res) - 1) & align
        iy0 = (math.floor((y_lo - reach) / res) - 1) & align
        w = math.floor((x_hi + reach) / res) + 1 - ix0 + 1
        h = math.floor((y_hi + reach) / res) + 1 - iy0 + 1
        shift = self.grid.tile_shift
        tx0, ty0 = ix0 >> shift, iy0 >> shift
        ntx = ((ix0 + w - 1) >> shift) - tx0 + 1
        nty = ((iy0 + h - 1) >> shift) - ty0 + 1
        owned, all_owned, owned_sum = self._owned_mask(tx0, ty0, ntx, nty)
        return Window(ix0, iy0, w, h), Tiles(owned, all_owned, shift, tx0, ty0), owned_sum

    def _ray_args(
        self, beams: BeamTable
    ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, ...], tuple[object, ...], float]:
        """What both passes' kernels take about the rays, in their order: the beams' directions (cosines, sines),
        the beam table, the model's terms and the cell size (m), as plain tuples (mapping.beam_model.BeamTable)."""
        return self._directions, tuple(beams), self._model_terms, self.grid.resolution

    def _walk_single(self, ready: Ready, scratch: FusionScratch) -> Walked:
        """The one-sample pass (one laser pose (3,): x m, y m, yaw rad; its sample's weight)."""
        window, tiles = ready.window, ready.tiles
        blocks_w, blocks_h = -(-window.w // 8), -(-window.h // 8)
        scratch.for_single(blocks_w * blocks_h)
        touched, boxes = np.zeros(tiles.owned.shape, np.bool_), empty_boxes(tiles.owned.shape)
        args = (scratch.touched_bits, scratch.raised_bits, scratch.largest, blocks_w, blocks_h, touched, boxes)
        window_args, tile_args = tuple(window), tuple(tiles)
        n_scan = accumulate_single(ready.lasers[0], *self._ray_args(ready.beams), window_args, tile_args, args)
        weight = float(ready.weights[0])
        return Walked(True, args, int(n_scan), touched, window_args, tile_args, weight, 1, boxes)

    def _walk_samples(self, ready: Ready, scratch: FusionScratch, part: int, parts: int) -> Walked:
        """The samples pass (laser poses (M, 3), weights (M,)) over the part-th of ``parts`` runs of the samples."""
        window, tiles = ready.window, ready.tiles
        lasers, weights = (ready.lasers, ready.weights) if parts == 1 else _part(ready, part, parts)
        # the samples pass's scratch rows and columns are whole 64-bit words of its bit planes (mapping.free_runs)
        win_w = -(-window.w // 64) * 64
        col_stride = -(-window.h // 64) * 64
        sums = _equal_weight_sums(ready.weights)  # (all the scan's weights: the parts' counts are added up)
        room = (win_w * window.h, win_w * col_stride, max(win_w, window.h), len(ready.beams.kind))
        scratch.for_samples(*room, summed=sums.size == 0)
        stamp_base = scratch.stamps(len(lasers))
        touched, boxes = np.zeros(tiles.owned.shape, np.bool_), empty_boxes(tiles.owned.shape)
        args = (
            scratch.plane,
            scratch.columns,
            col_stride,
            scratch.listed,
            scratch.weight_sum,
            scratch.excess,
            touched,
            scratch.lines,
            scratch.block,
            scratch.counts,
            sums,
            scratch.fan_ints,
            scratch.fan_floats,
            scratch.group_planes,
            scratch.moments,
            boxes,
            scratch.raised,
        )
        window_args, tile_args = (window.ix0, window.iy0, win_w, window.h), tuple(tiles)
        accumulate_scan(
            lasers,
            weights,
            *self._ray_args(ready.beams),
            window_args,
            tile_args,
            ready.owned_sum,
            args,
            stamp_base,
            self._moment_scale,
        )
        return Walked(False, args, 0, touched, window_args, tile_args, 0.0, len(lasers), boxes)


#: the share of cells a scratch takes beyond the window that makes it grow (FusionScratch)
SCRATCH_ROOM = 1 / 8


def _with_room(cells: int) -> int:
    """The cells a scratch takes when a window of ``cells`` makes it grow: SCRATCH_ROOM more, up to MAX_WINDOW_CELLS
    (never fewer than ``cells``)."""
    return max(cells, min(cells + int(cells * SCRATCH_ROOM), MAX_WINDOW_CELLS))


#: the fewest samples a part of a scan's walk takes (MonteCarloFusion.parts_for)
MIN_PART_SAMPLES = 8


def _share(total: int, index: int, count: int) -> tuple[int, int]:
    """The index-th of ``count`` near-equal runs (first, end) of ``total`` items, in order."""
    return index * total // count, (index + 1) * total // count


def _bands(words: int, count: int) -> list[tuple[int, int]]:
    """``count`` near-equal runs (first, end) of the scratch's ``words`` words."""
    return [_share(words, band, count) for band in range(count)]


def _part(ready: Ready, part: int, parts: int) -> tuple[np.ndarray, np.ndarray]:
    """The laser poses and weights of the part-th of ``parts`` near-equal runs of a scan's samples, in order."""
    lo, hi = _share(len(ready.lasers), part, parts)
    return ready.lasers[lo:hi], ready.weights[lo:hi]


#: bytes a window cell of the samples pass's scratch (:class:`FusionScratch`): a group's GROUP bit planes, the listed
#: and raised planes and a bit of the column-major plane, the weight sum (int64; only once a scan's weights differ),
#: the excess record (4 float64) and COUNT_LEVELS bits of counts
SAMPLES_SCRATCH_BYTES_PER_CELL = (GROUP + 3) / 8 + 8 + 32 + COUNT_LEVELS / 8


def _equal_weight_sums(weights: np.ndarray) -> np.ndarray:
    """When all M weights are equal (and M < 2**COUNT_LEVELS), the weight sum of n of them for n = 0..M as the
    per-cell sums give it: n whole steps of mapping.fixed_point.WEIGHT_SCALE (the weight truncated to steps, as the
    samples pass takes it), rounded once to float64. The samples pass counts the samples that touch a cell and reads
    its weight sum here (mapping.samples_pass). Else an empty array."""
    if len(weights) >= 2**COUNT_LEVELS or not np.all(weights == weights[0]):
        return np.zeros(0, np.float64)
    step = int(weights[0] * WEIGHT_SCALE)  # (truncated, as to_fixed truncates)
    return (np.arange(len(weights) + 1, dtype=np.int64) * step).astype(np.float64) / WEIGHT_SCALE


class FusionThreads:
    """Fuses scans on ``count`` threads (mapping.parallel_fusion): the walks of up to ``count`` scans at once, each on a
    :class:`FusionScratch` of its own, the scans applied in order, so the map is the same bit for bit as fused one by
    one; a scan handed in alone is walked in parts of its samples on the threads at once (:meth:`fuse_iter`), to the
    same map. One serves any fusions of one grid (a laser whose geometry changes has a fusion per geometry), their
    scans in one stream. With count 1 each scan is fused by its fusion's :meth:`MonteCarloFusion.fuse`, with no pool.

    There is one scratch more than threads: while the calling thread applies a walked scan (its scratch still in
    use), the next scan's walk already waits on the pool, so no core idles during an apply.

    Memory: ``count + 1`` scratches of about 43 bytes a window cell each (:class:`FusionScratch`; a lone scan's parts
    use ``count`` of them), and one more, :attr:`lone`, that :meth:`MonteCarloFusion.fuse` walks a scan into, shared
    by every fusion of these threads (a fusion of each of 8 laser geometries, each with a scratch of its own grown
    to its widest window, held 3.3 GiB after a peer's six geometries of spread samples); the pool's threads start on
    the first scans fused with count > 1. Not thread-safe: one caller at a time."""

    def __init__(self, count: int = 1) -> None:
        try:
            count = operator.index(count)  # (a whole number: 1.5 threads is a mistake, not 1)
        except TypeError:
            raise InputError(f"need a whole number of threads >= 1, got {count!r}") from None
        if count < 1:
            raise InputError(f"need a whole number of threads >= 1, got {count!r}")
        self.count = count
        self._scratches = [FusionScratch() for _ in range(count + 1)] if count > 1 else []
        self.lone = FusionScratch()  # (MonteCarloFusion.fuse's, of whichever fusion; empty until a scan is walked)
        self._pool: ThreadPoolExecutor | None = None

    @property
    def scratches(self) -> int:
        """How many scratches the threads walk into (count + 1; none with one thread)."""
        return len(self._scratches)

    @property
    def nbytes(self) -> int:
        """Bytes the threads' scratches hold now (:attr:`lone` aside)."""
        return sum(scratch.nbytes for scratch in self._scratches)

    def fuse_iter(self, scans: Iterable[tuple[MonteCarloFusion, ScanInput]]) -> Iterator[FuseResult | InputError]:
        """Fuse each scan ((ranges, samples, weights), as :meth:`MonteCarloFusion.fuse` takes them) with its fusion, in
        order, yielding its FuseResult, or the InputError that refused it (the map unchanged by that scan; the next
        scans go on). Any other error is raised at its scan's turn, the earlier scans fused and none of the later
        ones, as fusing them one by one would; closing the iterator early waits for the walks in flight.

        Scans handed in as a sequence of one (a live shard's scan as it comes) are walked in parts on all the threads
        at once; any other scans are walked side by side, a scan a thread. The map is the same either way."""
        if self.count == 1:
            return _one_by_one(scans)
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.count, thread_name_prefix="fusion")
        if isinstance(scans, Sequence) and len(scans) == 1:
            return self._in_parts(*scans[0])
        side_by_side = in_scan_order(scans, _prepare, _walk, _apply, self._scratches, self._pool, FuseResult(0, []))
        return self._cleared_unless_done(side_by_side)

    def _cleared_unless_done(self, outcomes: Iterator[FuseResult | InputError]) -> Iterator[FuseResult | InputError]:
        """``outcomes`` as they come; when an error ends them or the caller stops early, the walks still in flight
        were waited for but never applied, so every scratch is cleared before the threads fuse again."""
        done = False
        try:
            yield from outcomes
            done = True
        finally:
            if not done:
                if isinstance(outcomes, Generator):
                    outcomes.close()  # (waits for the walks in flight)
                for scratch in self._scratches:
                    scratch.clear()

    def _in_parts(self, fusion: MonteCarloFusion, scan: ScanInput) -> Iterator[FuseResult | InputError]:
        """:meth:`fuse_iter` of a single scan: its samples walked in parts on the threads at once
        (:meth:`MonteCarloFusion.walk`), each part into a scratch of its own, then added up and applied. The map is
        the one a single walk gives; a live shard fusing each scan as it comes waits for one scan on all its threads
        instead of on one."""
        try:
            ready = fusion.prepare(scan)
        except InputError as exc:
            yield exc
            return
        if ready is None:
            yield FuseResult(0, [])
            return
        assert self._pool is not None  # (fuse_iter started it)
        parts = fusion.parts_for(ready, self.count)
        jobs = [  # parts 1.. on the pool, part 0 on this thread (one hand-over less, and no wait to wake from)
            self._pool.submit(fusion.walk, ready, self._scratches[part], part, parts) for part in range(1, parts)
        ]
        try:
            first = fusion.walk(ready, self._scratches[0], 0, parts)
        except BaseException:
            self._failed_parts(jobs, parts)
            raise
        if any(job.exception() is not None for job in jobs):  # (waits for each)
            self._failed_parts(jobs, parts)
        try:
            result = fusion.apply_parts([first, *(job.result() for job in jobs)], self._pool)
        except BaseException:
            self._failed_parts([], parts)  # (the adding up or the apply failed: the parts' marks stay)
            raise
        yield result

    def _failed_parts(self, jobs: list[Future[Walked]], parts: int) -> None:
        """After a part's walk, or the adding up and apply of the parts, failed: wait for the walks still in flight
        (their scratches idle before anyone uses them again) and clear the parts' scratches, which hold marks that
        were never added up nor cleared."""
        wait(jobs)
        for scratch in self._scratches[:parts]:
            scratch.clear()


def _one_by_one(scans: Iterable[tuple[MonteCarloFusion, ScanInput]]) -> Iterator[FuseResult | InputError]:
    """:meth:`FusionThreads.fuse_iter` on one thread: each scan's :meth:`MonteCarloFusion.fuse`."""
    for fusion, (ranges, samples, weights) in scans:
        try:
            result = fusion.fuse(ranges, samples, weights)
        except InputError as exc:
            yield exc
        else:
            yield result


def _prepare(item: tuple[MonteCarloFusion, ScanInput]) -> tuple[MonteCarloFusion, Ready] | None:
    """:meth:`MonteCarloFusion.prepare` of a (fusion, scan) pair, the fusion kept with the prepared scan."""
    fusion, scan = item
    ready = fusion.prepare(scan)
    return None if ready is None else (fusion, ready)


def _walk(item: tuple[MonteCarloFusion, Ready], scratch: FusionScratch) -> tuple[MonteCarloFusion, Walked]:
    """:meth:`MonteCarloFusion.walk` of a prepared (fusion, scan) pair into ``scratch`` (on a pool thread)."""
    fusion, ready = item
    return fusion, fusion.walk(ready, scratch)


def _apply(item: tuple[MonteCarloFusion, Walked]) -> FuseResult:
    """:meth:`MonteCarloFusion.apply` of a walked (fusion, scan) pair."""
    fusion, walked = item
    return fusion.apply(walked)
