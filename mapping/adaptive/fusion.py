"""Monte Carlo fusion into the adaptive grid, one scan at a time (paper, sections V and VI).

Per scan, with pose samples x_j and weights w_j (sum 1):

1. one compiled pass gathers the scan's evidence at every level (:mod:`mapping.adaptive.evidence`): the
   weighted log-odds moments of the regular grid's Monte Carlo rule and the weighted hits, misses and
   unknowns of every ray;
2. the start-level cells the scan touches for the first time become active (log-odds 0);
3. split, from the coarsest level down: an active cell the scan sees (it has hits or misses this scan) is
   tested with its carried hits and misses plus this scan's, and this scan's unknowns
   (:class:`~mapping.adaptive.splitting.SplitTest`). A rejected cell is replaced by its four children, which
   inherit its log-odds and variance, share its carried hits and misses in proportion to the scan's hits and
   misses in each child, add their own counts of this scan, and are tested in turn;
4. update: every finest cell the scan touches gets its Monte Carlo increment sum_j w_j y_ij and spread
   sum_j w_j y_ij^2 - (sum_j w_j y_ij)^2 exactly as a regular-grid cell (docs/sensor_model.md, sections 3
   and 4); an active cell adds the mean of the increments of its finest cells that the scan touched to its
   log-odds (clamped) and the mean of their spreads to its variance. A finest active cell is therefore
   updated exactly as the regular grid's cell, and a coarser one tracks the mean log-odds of the regular
   grid over its area, the same quantity that merging (mean of the children) and splitting (inheritance)
   assume;
5. merge, from the finest level up: four active siblings of which the scan touched at least one merge into
   their parent when a rule of :class:`~mapping.adaptive.merging.MergeRules` holds, unless the split test
   rejects the parent with the children's carried hits and misses (the merge would be undone; this scan's
   unknowns do not count, see ``_merge``); the parent takes the mean of their log-odds (and of their
   variances) and the sum of their hits and misses.

Unknowns are never stored: they count in the test of the scan that saw them only.
All loops over samples, beams and cells are compiled or vectorised; Python loops run per level and per tile.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mapping.adaptive.evidence import EvidenceScanner, ScanEvidence
from mapping.adaptive.merging import MergeRules, merge_siblings
from mapping.adaptive.splitting import SplitTest
from mapping.adaptive.tree import AdaptiveGrid, children, unique_cells
from mapping.beam_model import BEAM_HIT, BEAM_SKIP, BeamTable, beam_table, logodds_model
from mapping.errors import InputError
from mapping.scan_input import check_laser, check_no_return_range, check_scan, laser_poses, merge_duplicates
from mapping.sensor_model import SensorModel


@dataclass(frozen=True)
class AdaptiveParams:
    """How the adaptive grid refines and coarsens.

    start_level: level of the cells a scan creates where nothing was observed (4: 0.8 m cells over 0.05 m);
    max_level: coarsest level merges may reach (None: a whole tile); unknowns: count unknowns in the split
    test (the paper's rule) or only hits and misses (Einhorn et al.'s); significance: alpha of the split
    test; unknown_range: how far beyond a return its ray counts unknowns, m, at least to where its values end
    (3 sigma past the return: the walk for the values counts them) (None: up to range_max, the field of view);
    sigma: range noise in m for the test's expected distributions (None: the sensor model's sigma at half of
    range_max); floor: share of any outcome a homogeneous cell may show beyond the noise;
    merge: the merge rules.
    """

    start_level: int = 4
    max_level: int | None = None
    unknowns: bool = True
    significance: float = 0.01
    unknown_range: float | None = None
    sigma: float | None = None
    floor: float = 0.01
    merge: MergeRules = field(default_factory=MergeRules)

    def __post_init__(self) -> None:
        """InputError for levels that are not whole numbers, a sigma (m) that is not finite and > 0 (inf: no cell
        ever split), or merge rules that are not MergeRules; the rest SplitTest and AdaptiveFusion check."""
        for name, level in (("start_level", self.start_level), ("max_level", self.max_level)):
            if level is not None and (isinstance(level, bool) or not isinstance(level, int | np.integer)):
                raise InputError(f"{name} must be a whole number, got {level!r}")
        if self.sigma is not None and not 0 < self.sigma < np.inf:
            raise InputError(f"sigma must be a finite number of metres > 0 (or None), got {self.sigma}")
        if not isinstance(self.merge, MergeRules):
            raise InputError(f"merge must be MergeRules, got {type(self.merge).__name__}")


@dataclass(frozen=True)
class AdaptiveFuseResult:
    """What one scan did to the tree."""

    cells_updated: int  # active cells whose log-odds the scan updated
    cells_created: int  # start-level cells activated for the first time
    splits: int  # cells replaced by their children
    merges: int  # groups of four siblings replaced by their parent


def level_for_cell_size(cell_size: float, resolution: float) -> int:
    """The level k with resolution * 2^k == cell_size (m), k at most 62; InputError if there is none, or if the
    resolution is not finite and > 0 (0 divided by zero; -0.4 over -0.05 gave level 3)."""
    if not 0 < resolution < np.inf:
        raise InputError(f"the finest resolution must be finite and > 0 m, got {resolution}")
    ratio = cell_size / resolution
    level = int(round(np.log2(ratio))) if 0 < ratio < np.inf else -1
    if not 0 <= level <= 62 or not np.isclose(resolution * (1 << level), cell_size, rtol=1e-9):
        raise InputError(
            f"cell size {cell_size} m is not the finest resolution {resolution} m times a power of two (2^0 to 2^62)"
        )
    return level


class AdaptiveFusion:
    """Fuses scans of one laser into an :class:`AdaptiveGrid`, one compiled pass per scan.

    beam_angles: (B,) rad in the laser frame; range_min, range_max: m; sensor_offset: the laser's
    (x m, y m, yaw rad) in the robot frame; params: see :class:`AdaptiveParams`; no_return_range: how far (m) a
    beam with no return clears free space, as :class:`mapping.fusion.MonteCarloFusion` takes it.
    """

    def __init__(
        self,
        grid: AdaptiveGrid,
        model: SensorModel,
        beam_angles: np.ndarray,
        range_min: float,
        range_max: float,
        sensor_offset: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        params: AdaptiveParams | None = None,
        no_return_range: float | None = None,
    ) -> None:
        params = AdaptiveParams() if params is None else params
        if not isinstance(params, AdaptiveParams):
            raise InputError(f"params must be AdaptiveParams, got {type(params).__name__}")
        if not np.isclose(grid.resolution, model.resolution):
            raise InputError(
                f"grid resolution {grid.resolution} m differs from the sensor model's {model.resolution} m"
            )
        angles, offset = check_laser(beam_angles, range_min, range_max, sensor_offset)
        max_level = grid.max_level if params.max_level is None else params.max_level
        if not 0 <= params.start_level <= max_level <= grid.max_level:
            raise InputError(
                f"need 0 <= start_level <= max_level <= {grid.max_level} (a tile), got "
                f"{params.start_level} and {max_level}"
            )
        if params.unknown_range is not None and not params.unknown_range >= 0:
            raise InputError(f"unknown_range must be >= 0 m, got {params.unknown_range}")
        if grid.start_level is not None and grid.start_level != params.start_level:
            # (a start cell is made where a block's lower-left finest cell is not covered: with another start level's
            # cells there, it went on top of them, and active cells overlapped)
            cell = grid.resolution * 2**grid.start_level
            raise InputError(
                f"the grid was fused with start level {grid.start_level} (cells of {cell:g} m), this fusion asks for "
                f"{params.start_level}: fuse into a grid with one start level (a new grid, or the same --coarse-cell)"
            )
        grid.start_level = params.start_level
        self.grid = grid
        self.model = model
        self.params = params
        self.max_level = max_level
        self.angles = angles
        self.range_min = float(range_min)
        self.range_max = float(range_max)
        self.no_return_range = check_no_return_range(no_return_range, self.range_max)
        self.sensor_offset = offset
        sigma = params.sigma if params.sigma is not None else float(model.sigma_at(range_max / 2))
        self.test = SplitTest(model.resolution, sigma, params.significance, params.unknowns, params.floor)
        self.scanner = EvidenceScanner(max_level + 1, params.unknowns)
        self._model_terms = logodds_model(model)

    # ----------------------------------------------------------------------------------- one scan
    def fuse(self, ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray) -> AdaptiveFuseResult:
        """Fuse one scan: ranges (B,) m, robot pose samples (M, 3) map frame, weights (M,) summing to 1."""
        ranges, samples, weights = check_scan(ranges, samples, weights, self.angles.shape[0])
        samples, weights = merge_duplicates(samples, weights)
        beams = beam_table(ranges, self.model, self.range_min, self.range_max, self.no_return_range)
        if not (beams.kind != BEAM_SKIP).any():
            return AdaptiveFuseResult(0, 0, 0, 0)
        evidence = self.scanner.scan(
            laser_poses(samples, self.sensor_offset),
            weights,
            self.angles,
            beams,
            self._count_ranges(beams),
            self._model_terms,
            self.model.resolution,
        )
        ix, iy, first, spread = evidence.fine()
        created = self._activate(ix, iy)
        splits = self._split(evidence, np.unique(self.grid.find(ix, iy)))
        updated = self._update(self.grid.find(ix, iy), first, spread)
        merges = self._merge(updated)
        return AdaptiveFuseResult(len(updated[0]), created, splits, merges)

    def _count_ranges(self, beams: BeamTable) -> np.ndarray:
        """How far each ray is followed (m): the value range, and with unknowns beyond the return."""
        r_count = beams.r_stop.copy()
        if self.params.unknowns:
            hit = beams.kind == BEAM_HIT
            reach = (
                self.range_max
                if self.params.unknown_range is None
                else np.minimum(self.range_max, beams.z[hit] + self.params.unknown_range)
            )
            r_count[hit] = np.maximum(beams.r_stop[hit], reach)
        return r_count

    def _activate(self, ix: np.ndarray, iy: np.ndarray) -> int:
        """Activate the start-level cells over the touched finest cells (ix, iy) that no active cell covers."""
        start = self.params.start_level
        bx, by = unique_cells(ix >> start, iy >> start)
        new = self.grid.find(bx << start, by << start) < 0
        if new.any():
            zeros = np.zeros(int(new.sum()))
            self.grid.edit(
                np.zeros(0, np.int64), np.full(zeros.shape, start), bx[new], by[new], zeros, zeros, zeros, zeros
            )
        return int(new.sum())

    def _split(self, evidence: ScanEvidence, index: np.ndarray) -> int:
        """Test the active cells at ``index`` (those the scan touched) and split recursively (step 3 of the
        module docstring); returns the number of splits."""
        grid = self.grid
        level, ax, ay = grid.cells(index)
        removed = []
        added = []  # (level, ax, ay, logodds, variance, hits, misses) of new active cells
        empty_i, empty_f = np.zeros(0, np.int64), np.zeros(0)
        # children of split cells, waiting for their own test: ax, ay, inherited logodds and variance, and
        # their share of the parent's carried hits and misses
        pending = (empty_i, empty_i, empty_f, empty_f, empty_f, empty_f)
        splits = 0
        for k in range(self.max_level, -1, -1):
            here = index[level == k]
            cx = np.concatenate([ax[level == k], pending[0]])
            cy = np.concatenate([ay[level == k], pending[1]])
            lo = np.concatenate([grid.logodds[here], pending[2]])
            var = np.concatenate([grid.variance[here], pending[3]])
            carried = np.stack(
                [np.concatenate([grid.hits[here], pending[4]]), np.concatenate([grid.misses[here], pending[5]])], axis=1
            )
            counts = evidence.counts(np.full(cx.shape, k), cx, cy)
            totals = np.concatenate([carried + counts[:, :2], counts[:, 2:]], axis=1)
            # a cell is tested when the scan sees it; the finest cells are never split
            split = (counts[:, 0] + counts[:, 1] > 0) & (k > 0)
            split[split] = self.test.reject(np.full(int(split.sum()), k), totals[split])
            old = np.arange(cx.size) < here.size
            grid.hits[here] = totals[old, 0]
            grid.misses[here] = totals[old, 1]
            removed.append(here[split[old]])
            keep = ~old & ~split
            added.append(
                (np.full(int(keep.sum()), k), cx[keep], cy[keep], lo[keep], var[keep], totals[keep, 0], totals[keep, 1])
            )
            splits += int(split.sum())
            kx, ky = children(cx[split], cy[split])
            shares = self._shares(evidence.counts(np.full(kx.shape, k - 1), kx, ky)[:, :2])
            pending = (
                kx,
                ky,
                np.repeat(lo[split], 4),
                np.repeat(var[split], 4),
                np.repeat(carried[split, 0], 4) * shares[:, 0],
                np.repeat(carried[split, 1], 4) * shares[:, 1],
            )
        columns = [np.concatenate(parts) for parts in zip(*added)]
        grid.edit(np.concatenate(removed), *columns)
        return splits

    @staticmethod
    def _shares(child_counts: np.ndarray) -> np.ndarray:
        """(4N, 2): each child's share of its parent's carried hits and misses, in proportion to the scan's
        hits and misses in the four children (equal shares where the scan has none)."""
        groups = child_counts.reshape(-1, 4, child_counts.shape[1])
        total = groups.sum(axis=1, keepdims=True)
        shares = np.where(total > 0, groups / np.where(total > 0, total, 1.0), 0.25)
        return shares.reshape(child_counts.shape)

    def _update(
        self, owner: np.ndarray, first: np.ndarray, spread: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Monte Carlo update (step 4): each touched active cell gets the mean, over the finest cells it holds
        that the scan touched (``owner`` their active cells), of their first moments and spreads. Returns the
        updated cells' (level, ax, ay)."""
        grid, model = self.grid, self.model
        cells, inverse = np.unique(owner, return_inverse=True)
        count = np.bincount(inverse)
        mean_first = np.bincount(inverse, weights=first) / count
        grid.logodds[cells] = np.clip(grid.logodds[cells] + mean_first, model.l_min, model.l_max)
        grid.variance[cells] = grid.variance[cells] + np.bincount(inverse, weights=spread) / count
        return grid.cells(cells)

    def _merge(self, updated: tuple[np.ndarray, np.ndarray, np.ndarray]) -> int:
        """Merge siblings recursively from the finest level up (step 5); returns the number of merges.

        The veto tests the parent on its children's carried hits and misses only. This scan's unknowns do not
        count: they say that this scan left part of the parent unseen, not that earlier scans did. Siblings
        that a merge rule finds nearly certain or in agreement got those values from scans (a child never seen
        keeps its parent's value, the prior p = 1/2 where the parent split when first seen partly hidden, and
        fails every rule), so the merge paints no unseen space. Counting them kept the free cells along shadow
        edges split for good (docs/adaptive.md, section 5).
        """

        def undone(level: int, px: np.ndarray, py: np.ndarray, carried: np.ndarray) -> np.ndarray:
            totals = np.concatenate([carried, np.zeros((px.size, 1))], axis=1)  # no unknowns
            return (carried.sum(axis=1) > 0) & self.test.reject(np.full(px.shape, level), totals)

        return merge_siblings(self.grid, *updated, self.params.merge, self.max_level, undone)
