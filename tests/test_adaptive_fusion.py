"""Adaptive fusion: the paper's Fig. 3, the merge rules, a one-wall world, weighted counts against a slow
reference, and agreement with the regular grid where the two must agree."""

import math

import numpy as np
import pytest

from mapping.adaptive import AdaptiveFusion, AdaptiveGrid, AdaptiveParams, MergeRules, level_for_cell_size
from mapping.adaptive.evidence import EvidenceScanner
from mapping.adaptive.merging import merge_siblings
from mapping.beam_model import BEAM_HIT, BEAM_NO_RETURN, beam_table, logodds_model
from mapping.errors import InputError
from mapping.fusion import MonteCarloFusion, laser_poses
from mapping.grid import TiledGrid
from mapping.sensor_model import TAIL_SIGMAS, SensorModel
from reference import cells_on_ray
from worlds import room_posed_scans

RES = 0.05
NEVER_MERGE = MergeRules(std_max=0.0, margin=0.0, above=1.0, below=0.0)


def logit(p):
    return math.log(p / (1 - p))


def fused(params, scans, angles, range_max, model=None):
    """An adaptive grid after fusing [(ranges, samples, weights)]."""
    model = model or SensorModel(resolution=RES)
    grid = AdaptiveGrid(RES)
    fusion = AdaptiveFusion(grid, model, angles, 0.05, range_max, params=params)
    for ranges, samples, weights in scans:
        fusion.fuse(ranges, samples, weights)
    return grid


# ------------------------------------------------------------------------------------------- Fig. 3
# a laser at the origin looks along +x at the level-3 cell (5, 0): x in [2.0, 2.4], y in [0, 0.4]. Beams
# below 4.5 degrees have no return and cross it; beams above end on an obstacle at 1 m, so the cell's upper
# part is hidden behind it.
FIG3_ANGLES = np.radians(np.arange(0.2, 9.5, 0.2))
FIG3_RANGES = np.where(np.radians(4.5) < FIG3_ANGLES, 1.0, np.inf)
FIG3_POSE = np.array([[0.013, 0.017, 0.0]])
FIG3_CELL = (np.array([3]), np.array([5]), np.array([0]))


def fig3_params(unknowns):
    return AdaptiveParams(start_level=3, unknowns=unknowns, merge=NEVER_MERGE)


def test_half_free_half_hidden_cell_splits_with_unknowns_only():
    scan = (FIG3_RANGES, FIG3_POSE, np.ones(1))
    with_unknowns = fused(fig3_params(True), [scan], FIG3_ANGLES, 3.0)
    without = fused(fig3_params(False), [scan], FIG3_ANGLES, 3.0)
    assert without.find_exact(*FIG3_CELL)[0] >= 0, "Einhorn's rule sees only misses: a free cell"
    assert with_unknowns.find_exact(*FIG3_CELL)[0] == -1, "with unknowns the cell is split"
    level, ax, _ay = with_unknowns.cells(with_unknowns.find(np.arange(40, 48), np.full(8, 2)))
    assert (level < 3).all() and ((ax << level) >= 40).all()


def test_merging_never_paints_the_hidden_part_of_a_fig3_cell_free():
    """With the default merge rules, Fig. 3's view seen six times: the seen part turns certain and merges, but
    the corner hidden behind the obstacle (finest cell (47, 7)) keeps what it had after the first scan, in a
    cell finer than Fig. 3's, not free to a planner: no merge reaches across the shadow's edge."""
    scan = (FIG3_RANGES, FIG3_POSE, np.ones(1))
    params = AdaptiveParams(start_level=3, unknowns=True)
    cells = (np.array([40, 47]), np.array([0, 7]))  # a seen finest cell and the hidden corner
    once, six = fused(params, [scan], FIG3_ANGLES, 3.0), fused(params, [scan] * 6, FIG3_ANGLES, 3.0)
    seen, hidden = six.find(*cells)
    assert six.logodds[seen] < logit(0.2) and six.active_cells < once.active_cells  # certain, and merged
    assert six.logodds[hidden] == once.logodds[once.find(*cells)[1]] and six.level[hidden] < 3
    assert six.logodds[hidden] > logit(0.2)


def test_children_inherit_the_parents_logodds_and_hits_and_misses_carry_over():
    # scan 1 sees the whole cell free (no obstacle); scan 2 is Fig. 3's half-hidden view
    free = (np.full(FIG3_ANGLES.shape, np.inf), FIG3_POSE, np.ones(1))
    half = (FIG3_RANGES, FIG3_POSE, np.ones(1))
    once = fused(fig3_params(True), [free], FIG3_ANGLES, 3.0)
    parent = once.find_exact(*FIG3_CELL)[0]
    parent_logodds = float(once.logodds[parent])
    assert parent_logodds == pytest.approx(logit(0.4), abs=1e-6)  # every fine cell it holds got the miss value
    twice = fused(fig3_params(True), [free, half], FIG3_ANGLES, 3.0)
    assert twice.find_exact(*FIG3_CELL)[0] == -1
    # the upper-right corner (x 2.35, y 0.38) is hidden in scan 2: its cell still holds the inherited value
    hidden = twice.find(np.array([47]), np.array([7]))[0]
    assert twice.logodds[hidden] == pytest.approx(parent_logodds, abs=1e-6)
    # the lower-left corner is seen free again: inherited value plus one more miss increment
    seen = twice.find(np.array([40]), np.array([0]))[0]
    assert twice.logodds[seen] == pytest.approx(2 * logit(0.4), abs=1e-6)
    # without unknowns the cell stays whole and its hits and misses add up over the two scans
    plain = fused(fig3_params(False), [free, half], FIG3_ANGLES, 3.0)
    one = fused(fig3_params(False), [free], FIG3_ANGLES, 3.0)
    cell, first = plain.find_exact(*FIG3_CELL)[0], one.find_exact(*FIG3_CELL)[0]
    assert plain.hits[cell] == 0 and one.misses[first] == pytest.approx(np.sum(np.radians(9.46) > FIG3_ANGLES), abs=2)
    assert one.misses[first] < plain.misses[cell] < 2 * one.misses[first]


# ------------------------------------------------------------------------------------------- merging
def sibling_grid(groups):
    """Groups of four level-0 siblings under parents (g, 0), g = 0, 1, ...: log-odds from probabilities."""
    grid = AdaptiveGrid(RES, tile_size=16)
    ax, ay, lo = [], [], []
    for g, probabilities in enumerate(groups):
        ax += [2 * g, 2 * g + 1, 2 * g, 2 * g + 1]
        ay += [0, 0, 1, 1]
        lo += [logit(p) for p in probabilities]
    zeros = np.zeros(len(lo))
    grid.edit(
        np.zeros(0, np.int64),
        np.zeros(len(lo), np.int64),
        np.array(ax),
        np.array(ay),
        np.array(lo),
        zeros,
        zeros,
        zeros,
    )
    return grid, np.array(lo).reshape(-1, 4)


@pytest.mark.parametrize(
    "rules, merged, kept",
    [
        # rule 1: spread below 0.05 and mean within 0.15 of 0 or 1
        (
            MergeRules(std_max=0.05, margin=0.15, above=1.0, below=0.0),
            [[0.87, 0.87, 0.87, 0.95], [0.05, 0.1, 0.1, 0.12]],
            [[0.8, 0.8, 0.8, 0.8], [0.05, 0.05, 0.05, 0.2]],
        ),
        # rule 2: all above 0.9
        (
            MergeRules(std_max=0.0, margin=0.0, above=0.9, below=0.0),
            [[0.91, 0.93, 0.95, 0.97], [0.95, 0.95, 0.95, 0.95]],
            [[0.91, 0.93, 0.95, 0.89], [0.1, 0.1, 0.1, 0.1]],
        ),
        # rule 3: all below 0.2
        (
            MergeRules(std_max=0.0, margin=0.0, above=1.0, below=0.2),
            [[0.12, 0.15, 0.19, 0.13], [0.01, 0.02, 0.03, 0.04]],
            [[0.12, 0.15, 0.21, 0.13], [0.95, 0.95, 0.95, 0.95]],
        ),
    ],
)
def test_each_merge_rule(rules, merged, kept):
    grid, lo = sibling_grid(merged + kept)
    level, ax, ay = grid.cells()
    assert merge_siblings(grid, level, ax, ay, rules, max_level=1) == len(merged)
    for g in range(len(merged)):
        index = grid.find_exact(np.array([1]), np.array([g]), np.array([0]))[0]
        assert index >= 0
        assert grid.logodds[index] == pytest.approx(lo[g].mean(), rel=1e-6)  # the mean of the log-odds
    for g in range(len(merged), len(merged) + len(kept)):
        assert grid.find_exact(np.array([1]), np.array([g]), np.array([0]))[0] == -1
        assert (
            grid.find_exact(
                np.zeros(4, np.int64), np.array([2 * g, 2 * g + 1, 2 * g, 2 * g + 1]), np.array([0, 0, 1, 1])
            )
            >= 0
        ).all()


def test_merging_recurses_and_needs_four_leaves():
    grid = AdaptiveGrid(RES, tile_size=16)
    # 16 free finest cells under level-2 cell (0, 0); under level-2 cell (1, 0) three free level-1 cells and
    # four finest cells, one of them occupied
    ix, iy = np.meshgrid(np.arange(4), np.arange(4))
    level = [0] * 16 + [1, 1, 1, 0, 0, 0, 0]
    ax = list(ix.ravel()) + [3, 2, 3, 4, 5, 4, 5]
    ay = list(iy.ravel()) + [0, 1, 1, 0, 0, 1, 1]
    lo = np.array([-2.0 + 0.01 * n for n in range(16)] + [-2.0, -2.0, -2.0, -2.0, -2.0, -2.0, 3.0])
    zeros = np.zeros(lo.size)
    grid.edit(np.zeros(0, np.int64), np.array(level), np.array(ax), np.array(ay), lo, zeros, zeros, zeros)
    lv, cx, cy = grid.cells()
    assert merge_siblings(grid, lv, cx, cy, MergeRules(), max_level=4) == 5
    whole = grid.find_exact(np.array([2]), np.array([0]), np.array([0]))[0]
    assert whole >= 0 and grid.logodds[whole] == pytest.approx(lo[:16].mean(), rel=1e-6)
    # the occupied finest cell keeps its siblings apart, so level-2 cell (1, 0) cannot form either
    assert grid.find_exact(np.array([2]), np.array([1]), np.array([0]))[0] == -1
    assert grid.active_cells == 1 + 3 + 4


# ------------------------------------------------------------------------------------------- a wall
def wall_scans(steps=8, seed=0):
    """A laser with 180 degrees of beams driving along the straight wall x = 3.13 m at x = 1.5 m, looking
    along +y, with small pose uncertainty; the wall spans y in [-3, 3] m."""
    rng = np.random.default_rng(seed)
    angles = np.radians(np.linspace(-90, 90, 361))
    scans = []
    for t in range(steps):
        truth = np.array([1.5, -1.5 + 0.4 * t, math.pi / 2 + 0.05 * (t % 3 - 1)])
        theta = truth[2] + angles
        with np.errstate(divide="ignore"):
            ranges = np.where(np.cos(theta) > 1e-9, (3.13 - truth[0]) / np.cos(theta), np.inf)
        hit_y = truth[1] + ranges * np.sin(theta)
        ranges = np.where(np.abs(hit_y) < 3.0, ranges + rng.normal(0, 0.01, angles.size), np.inf)
        samples = truth + rng.normal(0, 1, (8, 3)) * np.array([0.01, 0.01, 0.002])
        scans.append((ranges, samples, np.full(8, 1 / 8)))
    return scans, angles


def test_one_wall_gives_fine_cells_along_it_and_coarse_cells_elsewhere():
    scans, angles = wall_scans()
    grid = fused(AdaptiveParams(start_level=4), scans, angles, 4.0)
    regular = TiledGrid(RES)
    fusion = MonteCarloFusion(regular, SensorModel(resolution=RES), angles, 0.05, 4.0)
    for scan in scans:
        fusion.fuse(*scan)
    level, ax, ay = grid.cells()
    x0, x1 = (ax << level) * RES, ((ax + 1) << level) * RES
    y_mid = ((ay << level) + (1 << level) / 2) * RES
    on_wall = (x0 <= 3.13) & (x1 > 3.13) & (y_mid > -1.0) & (y_mid < 2.0)  # the part seen from near
    length = (1 << level[on_wall]) * RES
    assert length.sum() == pytest.approx(3.0, abs=0.5), "the wall is covered by active cells"
    assert (level[on_wall] <= 2).all() and length[level[on_wall] <= 1].sum() > 0.6 * length.sum()
    far = x1 < 2.13  # open space more than 1 m from the wall
    assert (level[far] >= 3).all() and np.median(level[far]) >= 4
    assert grid.active_cells < 0.1 * regular.observed_cells()


# ------------------------------------------------------------------------------------------- counts
def reference_counts(model, angles, range_min, range_max, ranges, lasers, weights, levels, unknowns):
    """{(level, ax, ay): [hits, misses, unknowns]}: each ray's outcome per cell it crosses, times its sample's
    weight, summed over samples, by brute force over grid-line crossings (no unknowns at level 0)."""
    counts = {}
    for (x, y, yaw), w in zip(lasers, weights):
        for angle, z in zip(angles, ranges):
            no_return = not np.isfinite(z) or z > range_max
            if not no_return and z < range_min:
                continue
            stop = range_max if no_return else z + TAIL_SIGMAS * float(model.sigma_at(z))
            if unknowns and not no_return:
                stop = max(stop, range_max)
            cells = cells_on_ray(x, y, yaw + angle, stop, model.resolution)
            hit_at = len(cells) if no_return else next(n for n, c in enumerate(cells) if c[2] <= z < c[3])
            for k in range(levels):
                runs = {}
                for n, (ix, iy, _, _) in enumerate(cells):
                    runs.setdefault((ix >> k, iy >> k), []).append(n)
                for cell, members in runs.items():
                    outcome = 0 if members[0] <= hit_at <= members[-1] else (2 if members[0] > hit_at else 1)
                    if outcome == 2 and (not unknowns or k == 0):  # no unknowns at the finest level
                        continue
                    counts.setdefault((k, *cell), [0.0, 0.0, 0.0])[outcome] += w
    return counts


@pytest.mark.parametrize("unknowns", [True, False])
def test_weighted_counts_equal_the_sum_of_per_sample_counts(unknowns):
    rng = np.random.default_rng(3)
    model = SensorModel(resolution=0.1, sigma0=0.05)
    angles = rng.uniform(-math.pi, math.pi, 12)
    ranges = rng.uniform(0.3, 2.5, 12)
    ranges[[2, 7]] = np.inf  # no return
    ranges[5] = 0.01  # below range_min: skipped
    lasers = np.column_stack([rng.uniform(-0.3, 0.3, 4), rng.uniform(-0.3, 0.3, 4), rng.uniform(-3, 3, 4)])
    weights = np.array([0.1, 0.2, 0.3, 0.4])
    levels = 4
    beams = beam_table(ranges, model, 0.05, 2.0)
    r_count = beams.r_stop.copy()
    if unknowns:
        r_count[beams.kind == BEAM_HIT] = np.maximum(r_count[beams.kind == BEAM_HIT], 2.0)
    assert (beams.kind == BEAM_NO_RETURN).sum() >= 2
    evidence = EvidenceScanner(levels, unknowns).scan(
        lasers,
        weights,
        angles,
        beams,
        r_count,
        logodds_model(model),
        model.resolution,
    )
    expected = reference_counts(model, angles, 0.05, 2.0, ranges, lasers, weights, levels, unknowns)
    for k in range(levels):
        ax, ay = np.meshgrid(
            np.arange(evidence.x0[k], evidence.x0[k] + evidence.w[k]),
            np.arange(evidence.y0[k], evidence.y0[k] + evidence.h[k]),
        )
        got = evidence.counts(np.full(ax.size, k), ax.ravel(), ay.ravel())
        want = np.array([expected.get((k, x, y), [0.0, 0.0, 0.0]) for x, y in zip(ax.ravel(), ay.ravel())])
        want[want[:, 0] + want[:, 1] == 0, 2] = 0.0  # unknowns are kept only where the test reads them
        np.testing.assert_allclose(got, want, atol=1e-12)
        assert want[:, 2].sum() > 0 if unknowns and k > 0 else want[:, 2].sum() == 0


# ------------------------------------------------------------------------------------------- agreement
def test_finest_start_without_merging_is_the_regular_grid():
    posed = room_posed_scans(steps=4, beams=90, gaussian=False, particles=6)
    model = SensorModel(resolution=RES)
    grid = AdaptiveGrid(RES)
    angles, range_min, range_max, _ = posed.single_geometry()
    adaptive = AdaptiveFusion(
        grid, model, angles, range_min, range_max, params=AdaptiveParams(start_level=0, merge=NEVER_MERGE)
    )
    regular = TiledGrid(RES)
    fusion = MonteCarloFusion(regular, model, angles, range_min, range_max)
    for t in range(4):
        adaptive.fuse(posed.ranges[t], posed.poses.samples[t], posed.poses.weights[t])
        fusion.fuse(posed.ranges[t], posed.poses.samples[t], posed.poses.weights[t])
    mine, theirs = grid.rasterize(), regular.rasterize()
    for key in ("logodds", "variance", "observed", "origin"):
        np.testing.assert_array_equal(mine[key], theirs[key])
    assert (mine["level"][mine["observed"]] == 0).all()


def test_a_coarse_cell_holds_the_mean_of_the_regular_grids_cells():
    posed = room_posed_scans(steps=1, beams=90, gaussian=False, particles=6)
    model = SensorModel(resolution=RES)
    angles, range_min, range_max, _ = posed.single_geometry()
    grid = fused(
        AdaptiveParams(start_level=3, merge=NEVER_MERGE),
        [(posed.ranges[0], posed.poses.samples[0], posed.poses.weights[0])],
        angles,
        range_max,
        model,
    )
    regular = TiledGrid(RES)
    MonteCarloFusion(regular, model, angles, range_min, range_max).fuse(
        posed.ranges[0], posed.poses.samples[0], posed.poses.weights[0]
    )
    raster = regular.rasterize()
    rows, cols = np.nonzero(raster["observed"])
    ix = np.round(raster["origin"][0] / RES).astype(int) + cols
    iy = np.round(raster["origin"][1] / RES).astype(int) + rows
    owner = grid.find(ix, iy)
    assert (owner >= 0).all()
    sums = np.bincount(owner, weights=raster["logodds"][rows, cols].astype(float), minlength=grid.active_cells)
    counts = np.bincount(owner, minlength=grid.active_cells)
    level, _, _ = grid.cells()
    assert (level > 0).sum() > 10
    np.testing.assert_allclose(grid.logodds[counts > 0], (sums / np.maximum(counts, 1))[counts > 0], atol=1e-5)


def test_same_input_gives_the_same_tree():
    scans, angles = wall_scans(steps=3, seed=4)
    a = fused(AdaptiveParams(), scans, angles, 4.0)
    b = fused(AdaptiveParams(), scans, angles, 4.0)
    for name in ("key", "level", "logodds", "variance", "hits", "misses"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_laser_poses_are_used_with_the_sensor_offset():
    # the same scan from a laser mounted 0.2 m ahead equals the scan from a robot 0.2 m further
    scans, angles = wall_scans(steps=2, seed=5)
    shifted = [(r, s + 0.2 * np.stack([np.cos(s[:, 2]), np.sin(s[:, 2]), 0 * s[:, 2]], 1), w) for r, s, w in scans]
    model = SensorModel(resolution=RES)
    a = AdaptiveGrid(RES)
    fa = AdaptiveFusion(a, model, angles, 0.05, 4.0, sensor_offset=(0.2, 0.0, 0.0))
    b = AdaptiveGrid(RES)
    fb = AdaptiveFusion(b, model, angles, 0.05, 4.0)
    for (r, s, w), (_, s2, _) in zip(scans, shifted):
        fa.fuse(r, s, w)
        fb.fuse(r, s2, w)
    np.testing.assert_array_equal(a.key, b.key)
    np.testing.assert_allclose(a.logodds, b.logodds, atol=1e-6)
    assert np.allclose(laser_poses(scans[0][1], np.array([0.2, 0.0, 0.0])), shifted[0][1])


def test_a_diverged_pose_spread_is_refused_not_allocated():
    """Two samples 300 m apart would need a window of 12 000 x 12 000 finest cells: refused with the spread."""
    spread = (np.full(3, 2.0), np.array([[0.0, 0.0, 0.0], [300.0, 300.0, 0.0]]), np.full(2, 0.5))
    with pytest.raises(InputError, match="spread over 300 m x 300 m"):
        fused(AdaptiveParams(), [spread], np.array([-0.1, 0.0, 0.1]), 5.0)


def _siblings(probabilities, variance, hits, misses):
    """Four level-0 siblings under parent (1, 0, 0)."""
    grid = AdaptiveGrid(0.05, tile_size=16)
    lo = np.array([math.log(p / (1 - p)) for p in probabilities])
    grid.edit(
        np.zeros(0, np.int64),
        np.zeros(4, np.int64),
        np.array([0, 1, 0, 1]),
        np.array([0, 0, 1, 1]),
        lo,
        np.array(variance, float),
        np.array(hits, float),
        np.array(misses, float),
    )
    return grid, lo


def test_a_merge_the_split_test_would_undo_is_not_made_and_the_veto_sees_the_parent():
    """undone(parent_level, px, py, carried) is asked about the parent (level 1, cell (0, 0)) with the children's
    summed hits and misses, and a True answer keeps the four children."""
    grid, _ = _siblings([0.1] * 4, [0.0] * 4, [1, 2, 3, 4], [10, 20, 30, 40])
    calls = []

    def undone(level, px, py, carried):
        calls.append((level, px.tolist(), py.tolist(), carried.tolist()))
        return np.ones(px.shape, bool)

    level, ax, ay = grid.cells()
    assert merge_siblings(grid, level, ax, ay, MergeRules(), max_level=1, undone=undone) == 0
    assert calls == [(1, [0], [0], [[10.0, 100.0]])]
    assert grid.find_exact(np.array([1]), np.array([0]), np.array([0]))[0] == -1
    assert grid.active_cells == 4


def test_a_scans_unknowns_do_not_veto_merging_siblings_that_earlier_scans_saw_free():
    """Four free finest cells (p = 0.1, 5 misses each) under level-1 cell (20, 1): x in [2.0, 2.1], y in
    [0.1, 0.2]. Fig. 3's view sees their lower half free and hides the rest behind the obstacle at 1 m (its
    shadow edge, the 4.5 degree beam, crosses them at y = 0.174-0.182), so this scan has misses and unknowns in
    the parent, which its split test with unknowns rejects (a parent with no history splits on them). The
    siblings still merge: the veto asks only whether their carried hits and misses would split the parent again,
    and they were all seen free before."""
    grid = AdaptiveGrid(RES)
    children = (np.zeros(4, np.int64), np.array([40, 41, 40, 41]), np.array([2, 2, 3, 3]))
    grid.edit(np.zeros(0, np.int64), *children, np.full(4, logit(0.1)), np.zeros(4), np.zeros(4), np.full(4, 5.0))
    fusion = AdaptiveFusion(
        grid, SensorModel(resolution=RES), FIG3_ANGLES, 0.05, 3.0, params=AdaptiveParams(start_level=1, unknowns=True)
    )
    parent = (np.array([1]), np.array([20]), np.array([1]))
    for unknowns, splits in ((True, True), (False, False)):  # seen by this scan alone, it splits on the unknowns
        fresh = fused(
            AdaptiveParams(start_level=1, unknowns=unknowns, merge=NEVER_MERGE),
            [(FIG3_RANGES, FIG3_POSE, np.ones(1))],
            FIG3_ANGLES,
            3.0,
        )
        assert (fresh.find_exact(*parent)[0] == -1) == splits
    fusion.fuse(FIG3_RANGES, FIG3_POSE, np.ones(1))
    merged = grid.find_exact(*parent)[0]
    assert merged >= 0 and (grid.find_exact(*children) == -1).all()
    assert grid.logodds[merged] < logit(0.2)  # still free: the mean of the children, updated by this scan


def test_a_merged_cell_takes_the_mean_variance_and_the_summed_hits_and_misses():
    grid, lo = _siblings([0.1, 0.12, 0.08, 0.1], [1.0, 2.0, 3.0, 4.0], [1, 2, 3, 4], [10, 20, 30, 40])
    level, ax, ay = grid.cells()
    assert (
        merge_siblings(
            grid, level, ax, ay, MergeRules(), max_level=1, undone=lambda lv, px, py, carried: np.zeros(px.shape, bool)
        )
        == 1
    )
    parent = grid.find_exact(np.array([1]), np.array([0]), np.array([0]))[0]
    assert parent >= 0
    assert grid.logodds[parent] == pytest.approx(lo.mean(), rel=1e-6)
    assert grid.variance[parent] == pytest.approx(2.5)
    assert grid.hits[parent] == pytest.approx(10.0) and grid.misses[parent] == pytest.approx(100.0)


@pytest.mark.parametrize("kwargs", [dict(std_max=1.5), dict(margin=-0.1), dict(above=2.0), dict(below=float("nan"))])
def test_merge_thresholds_outside_0_1_are_refused(kwargs):
    with pytest.raises(InputError, match="merge threshold"):
        MergeRules(**kwargs)


@pytest.mark.parametrize("cell, level", [(0.05, 0), (0.1, 1), (0.4, 3), (0.05 * 2.0**62, 62)])
def test_a_cell_size_a_power_of_two_times_the_resolution_gives_its_level(cell, level):
    assert level_for_cell_size(cell, 0.05) == level


@pytest.mark.parametrize("cell", [0.03, 0.15, 0.0, -0.1, 0.05 * 2.0**63, 1e308, math.inf, math.nan])
def test_any_other_cell_size_is_refused_with_a_reason(cell):
    """Not a power of two times 0.05 m, none at all, or beyond 2^62 (1e308 overflowed the level's integer)."""
    with pytest.raises(InputError, match="times a power of two"):
        level_for_cell_size(cell, 0.05)


def test_a_grid_takes_fusions_of_one_start_level_only():
    """A probe: three scans fused with start level 2, then three with start level 4 into the same grid, put start
    cells on top of the finer cells already there (a block's start cell was made where its lower-left finest cell was
    not covered): 320 finest cells were covered twice. A fusion of another start level into the grid is refused; one
    of the same start level goes on as before, and no finest cell is covered twice."""
    angles = np.radians(np.arange(-60.0, 61.0, 2.0))
    ranges = np.full(angles.shape, 3.0)
    model = SensorModel(resolution=RES)
    grid = AdaptiveGrid(RES)
    first = AdaptiveFusion(grid, model, angles, 0.05, 4.0, params=AdaptiveParams(start_level=2))
    for x in (0.0, 0.3, 0.6):
        first.fuse(ranges, np.array([[x, 0.1, 0.0]]), np.ones(1))
    with pytest.raises(InputError, match="fused with start level 2"):
        AdaptiveFusion(grid, model, angles, 0.05, 4.0, params=AdaptiveParams(start_level=4))
    again = AdaptiveFusion(grid, model, angles, 0.05, 4.0, params=AdaptiveParams(start_level=2))
    again.fuse(ranges, np.array([[0.9, -0.2, 0.5]]), np.ones(1))
    level, ax, ay = grid.cells()
    span = 1 << level
    covered = np.zeros((400, 400), int)  # finest cells -200 .. 199 both ways: the scans' reach
    for k, x, y in zip(span, ax * span, ay * span, strict=True):
        covered[y + 200 : y + 200 + k, x + 200 : x + 200 + k] += 1
    assert covered.max() == 1 and covered.sum() == int((4 ** level.astype(np.int64)).sum())
