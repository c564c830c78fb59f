"""Monte Carlo fusion: hand-computed cells, a slow reference, ml equivalence, reproducibility, sharding."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.beam_model import BEAM_HIT, BEAM_NO_RETURN, BEAM_SKIP, beam_table, farthest_walk
from mapping.errors import InputError
from mapping.fan_runs import FAN_FLOATS, FAN_INTS
from mapping.fusion import (
    SAMPLES_SCRATCH_BYTES_PER_CELL,
    FusionScratch,
    MonteCarloFusion,
    _with_room,
    merge_duplicates,
)
from mapping.grid import TiledGrid
from mapping.poses import scan_samples
from mapping.scan_input import MAX_WINDOW_CELLS
from mapping.sensor_model import SensorModel
from reference import reference_fuse
from services.state.ownership import owns_tile

RES = 0.05


def fused_cells(grid: TiledGrid) -> dict:
    """{(ix, iy): (logodds, variance)} of every observed cell."""
    out = {}
    for key in grid.keys():  # noqa: SIM118  # a TiledGrid, not a dict: it has no __iter__
        lo, var, obs = grid.tile_arrays(key)
        rows, cols = np.nonzero(obs)
        for r, c in zip(rows, cols):
            out[(key[0] * grid.tile_size + c, key[1] * grid.tile_size + r)] = (float(lo[r, c]), float(var[r, c]))
    return out


def whole_and_joined(tile_size, fusion_args, scans, shards, shard_of):
    """The grid of ``scans`` ((ranges, samples, weights) each) fused by one MonteCarloFusion(grid, *fusion_args)
    owning every tile, and the grid joined from ``shards`` fusions that each own the tiles (tx, ty) with
    shard_of(tx, ty) == its index (each shard's tiles checked to be its own, and its scratch planes and sums clear
    after each scan: a shard folds and sweeps only the blocks of its own tiles, so a bit its walk set elsewhere would
    stay there into the next sample)."""
    res = fusion_args[0].resolution
    whole = TiledGrid(res, tile_size=tile_size)
    fusion = MonteCarloFusion(whole, *fusion_args)
    for scan in scans:
        fusion.fuse(*scan)
    joined = TiledGrid(res, tile_size=tile_size)
    for shard in range(shards):
        part = TiledGrid(res, tile_size=tile_size)
        fusion = MonteCarloFusion(part, *fusion_args, owns_tile=lambda tx, ty, shard=shard: shard_of(tx, ty) == shard)
        for scan in scans:
            fusion.fuse(*scan)
            scratch = fusion.threads.lone
            assert not (
                scratch.plane.any()
                or scratch.group_planes.any()
                or scratch.columns.any()
                or scratch.listed.any()
                or scratch.raised.any()
                or scratch.weight_sum.any()
                or scratch.counts.any()
            )
        for key in part.keys():  # noqa: SIM118  # a TiledGrid, not a dict: it has no __iter__
            assert shard_of(*key) == shard
            joined.set_tile(key, *part.tile_arrays(key))
    return whole, joined


def erf_model(r, z, sigma, l):
    """The closed form written out by hand, independent of mapping.sensor_model."""
    s = math.sqrt(2) * sigma
    return 0.25 + 0.25 * math.erf((z + l / 2 - r) / s) - 0.5 * math.erf((z - l / 2 - r) / s)


def test_single_beam_hand_computed():
    """One beam along +x from the centre of cell (0, 0); return at 0.5 m, sigma 0.03 m, 0.05 m cells.

    Cell k >= 1 spans r in [0.05k - 0.025, 0.05k + 0.025]. The return lies in cell 10; the model's peak
    gives that cell logit(0.7). Cells ending more than 5 sigma before the peak's start (r < 0.3146) get
    logit(0.4). Cells starting beyond z + 3 sigma = 0.59 m are untouched: cells 0..12 are updated.
    """
    model = SensorModel(resolution=RES, sigma0=0.03)
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, model, np.array([0.0]), 0.05, 10.0)
    fusion.fuse(np.array([0.5]), np.array([[0.025, 0.025, 0.0]]), np.array([1.0]))
    cells = fused_cells(grid)
    assert sorted(cells) == [(k, 0) for k in range(13)]
    l_free, l_hit = math.log(0.4 / 0.6), math.log(0.7 / 0.3)
    for k in range(6):
        assert cells[(k, 0)][0] == pytest.approx(l_free, abs=1e-6)
    assert cells[(10, 0)][0] == pytest.approx(l_hit, abs=1e-6)
    g_peak = max(erf_model(r, 0.5, 0.03, model.l) for r in np.linspace(0.49, 0.52, 30001))
    for k in (6, 7, 8, 9):  # rising side: the maximum is at the cell's far edge
        g = erf_model(0.05 * k + 0.025, 0.5, 0.03, model.l)
        p = 0.5 - 0.1 * (1 - 2 * g) if g < 0.5 else 0.5 + 0.2 * (g - 0.5) / (g_peak - 0.5)
        assert cells[(k, 0)][0] == pytest.approx(math.log(p / (1 - p)), abs=2e-4)
    for k in (11, 12):  # falling side: the maximum is at the cell's near edge
        g = erf_model(0.05 * k - 0.025, 0.5, 0.03, model.l)
        p = 0.5 + 0.2 * (g - 0.5) / (g_peak - 0.5)
        assert cells[(k, 0)][0] == pytest.approx(math.log(p / (1 - p)), abs=2e-4)
    assert all(v == 0.0 for _, v in cells.values()), "one sample has no spread"


def test_no_return_marks_free_space_to_range_max_and_no_hit():
    model = SensorModel(resolution=RES)
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, model, np.array([0.0, 0.0, 0.0]), 0.05, 0.5)
    fusion.fuse(np.array([np.nan, np.inf, 0.7]), np.array([[0.025, 0.025, 0.0]]), np.array([1.0]))
    cells = fused_cells(grid)
    assert sorted(cells) == [(k, 0) for k in range(11)]  # r < 0.5 m: cells 0..10 (cell 10 starts at 0.475)
    assert all(v[0] == pytest.approx(model.l_free) for v in cells.values())


@pytest.mark.parametrize("too_close", [0.1, -np.inf])
@pytest.mark.parametrize("samples", [1, 3])
def test_too_short_ranges_are_skipped(too_close, samples):
    """A range below range_min, or -inf (a reading too close to measure, REP 117), touches no cell: before,
    -inf cleared free space to range_max, through whatever stood in front of the laser."""
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, SensorModel(resolution=RES), np.array([0.0]), 0.2, 5.0)
    poses = np.zeros((samples, 3)) + np.arange(samples)[:, None] * 0.01
    result = fusion.fuse(np.array([too_close]), poses, np.full(samples, 1 / samples))
    assert result.cells_updated == 0 and grid.keys() == []


@pytest.mark.parametrize("sigma", ["constant", "linear"])
def test_a_range_of_zero_is_no_reading_even_with_a_range_min_of_zero(sigma):
    """A probe: `posegrid run --carmen` (CARMEN logs carry no range_min: 0) fused a reading of 0, what a laser writes
    for no reading, as a hit in the laser's own cell along the robot's path. 0 is skipped like -inf; the beam beside
    it, a hit at 1 m, is fused as on its own."""
    model = SensorModel(resolution=RES, sigma=sigma)
    table = beam_table(np.array([0.0, 1.0, -0.0]), model, 0.0, 5.0)
    assert table.kind.tolist() == [BEAM_SKIP, BEAM_HIT, BEAM_SKIP]
    maps = []
    for ranges in (np.array([0.0, 1.0]), np.array([-np.inf, 1.0])):
        grid = TiledGrid(RES)
        fusion = MonteCarloFusion(grid, model, np.array([0.0, 0.5]), 0.0, 5.0)
        fusion.fuse(ranges, np.array([[0.025, 0.025, 0.0]]), np.array([1.0]))
        maps.append(fused_cells(grid))
    assert maps[0] == maps[1] and (0, 0) in maps[0]  # (the 1 m beam starts in the laser's cell: free there)
    assert maps[0][(0, 0)][0] < 0


def test_occupied_wins_within_one_sample():
    """A beam ending in a cell beats another beam passing through it in the same scan and sample."""
    model = SensorModel(resolution=RES)
    grid = TiledGrid(RES)
    angles = np.array([0.0, 0.0])
    fusion = MonteCarloFusion(grid, model, angles, 0.05, 10.0)
    fusion.fuse(np.array([0.5, 2.0]), np.array([[0.025, 0.025, 0.0]]), np.array([1.0]))
    assert fused_cells(grid)[(10, 0)][0] == pytest.approx(model.l_hit, abs=1e-6)


def random_scan(rng, n_beams, n_samples, spread):
    angles = np.sort(rng.uniform(-math.pi, math.pi, n_beams))
    ranges = rng.uniform(0.1, 1.2, n_beams)
    ranges[rng.random(n_beams) < 0.15] = np.nan
    samples = np.column_stack(
        [
            rng.normal(0.3, spread, n_samples),
            rng.normal(-0.2, spread, n_samples),
            rng.normal(0.4, 3 * spread, n_samples),
        ]
    )
    weights = rng.random(n_samples)
    return angles, ranges, samples, weights / weights.sum()


@settings(max_examples=16, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_beams=st.integers(1, 12),
    n_samples=st.integers(1, 5),
    sigma_kind=st.sampled_from(["constant", "linear"]),
    clears=st.sampled_from([None, 0.0, 0.37, 1.0]),
)
def test_compiled_fusion_matches_slow_reference(seed, n_beams, n_samples, sigma_kind, clears):
    """Both passes (one pose, and several) against the slow reference's cells and values, with beams that have no
    return cleared up to the no-return range ``clears`` (None: range_max, 1 m; 0: left out; between)."""
    rng = np.random.default_rng(seed)
    model = SensorModel(
        resolution=0.1, sigma=sigma_kind, sigma0=0.04, sigma_slope=0.02 if sigma_kind == "linear" else 0.0
    )
    angles, ranges, samples, weights = random_scan(rng, n_beams, n_samples, 0.08)
    ranges[rng.integers(n_beams)] = np.inf  # at least one beam with no return
    offset = (0.1, -0.05, 0.2)
    grid = TiledGrid(0.1, tile_size=8)  # small tiles: scans cross tile borders
    MonteCarloFusion(grid, model, angles, 0.15, 1.0, offset, no_return_range=clears).fuse(ranges, samples, weights)
    mean, spread = reference_fuse(model, angles, 0.15, 1.0, ranges, samples, weights, offset, no_return_range=clears)
    got = fused_cells(grid)
    assert set(got) == set(mean)
    for cell, (lo, var) in got.items():
        expected = min(max(mean[cell], model.l_min), model.l_max)
        assert lo == pytest.approx(expected, abs=3e-4), cell
        assert var == pytest.approx(max(spread[cell], 0.0), abs=3e-4), cell


@settings(max_examples=16, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    n_beams=st.integers(1, 12),
    copies=st.integers(1, 3),
    sigma_kind=st.sampled_from(["constant", "linear"]),
    shard=st.sampled_from([None, 0, 1]),
    tile_size=st.sampled_from([4, 8]),
)
def test_one_sample_pass_matches_slow_reference(seed, n_beams, copies, sigma_kind, shard, tile_size):
    """One distinct pose (also a particle set whose particles are all that pose) takes the one-sample pass:
    it must agree with the slow reference, with beams that have no return, for a shard that fuses only its
    own tiles, and with tiles smaller than the pass's 8 x 8 blocks."""
    rng = np.random.default_rng(seed)
    slope = 0.02 if sigma_kind == "linear" else 0.0
    model = SensorModel(resolution=0.1, sigma=sigma_kind, sigma0=0.04, sigma_slope=slope)
    angles, ranges, sample, _ = random_scan(rng, n_beams, 1, 0.08)
    ranges[rng.integers(n_beams)] = np.inf  # at least one beam with no return
    offset = (0.1, -0.05, 0.2)
    shift = tile_size.bit_length() - 1
    owner = None if shard is None else (lambda tx, ty: (tx * 7 + ty * 13) % 2 == shard)
    grid = TiledGrid(0.1, tile_size=tile_size)
    fusion = MonteCarloFusion(grid, model, angles, 0.15, 1.0, offset, owns_tile=owner)
    result = fusion.fuse(ranges, np.repeat(sample, copies, axis=0), np.full(copies, 1.0 / copies))
    mean, _ = reference_fuse(model, angles, 0.15, 1.0, ranges, sample, np.ones(1), offset)
    if owner is not None:
        mean = {cell: value for cell, value in mean.items() if owner(cell[0] >> shift, cell[1] >> shift)}
    got = fused_cells(grid)
    assert set(got) == set(mean)
    assert result.cells_updated == len(mean)
    assert sorted(result.tiles_changed) == sorted(grid.keys())
    for cell, (lo, var) in got.items():
        assert lo == pytest.approx(min(max(mean[cell], model.l_min), model.l_max), abs=3e-4), cell
        assert var == 0.0, "one sample has no spread"


def test_constant_sigma_beam_table_matches_the_general_one():
    """The compiled beam table of constant-sigma models against the array expressions every other model
    takes (a linear model with slope 0 is the same model): kinds exactly, every field to rounding."""
    ranges = np.array([0.05, 0.2, 1.0, 3.7, 12.0, 12.5, np.inf, -np.inf, np.nan, 0.1])
    constant = beam_table(ranges, SensorModel(resolution=0.05, sigma0=0.04), 0.1, 12.0)
    linear = beam_table(ranges, SensorModel(resolution=0.05, sigma="linear", sigma0=0.04), 0.1, 12.0)
    # 12.5, +inf and NaN: no return; -inf (too close to measure, REP 117) is skipped like a range below range_min
    expected_kinds = [BEAM_SKIP] + [BEAM_HIT] * 4 + [BEAM_NO_RETURN] * 2 + [BEAM_SKIP, BEAM_NO_RETURN, BEAM_HIT]
    assert constant.kind.tolist() == linear.kind.tolist() == expected_kinds
    for field in ("z", "r_stop", "r_peak", "a", "b", "s", "g_peak", "free_until"):
        np.testing.assert_allclose(
            getattr(constant, field), getattr(linear, field), rtol=1e-12, atol=1e-12, err_msg=field
        )
    assert constant.r_stop[[5, 6, 8]].tolist() == [12.0] * 3  # no return: free up to range_max
    assert constant.r_stop[7] == 0.0


@settings(max_examples=200, deadline=None)
@given(
    ranges=st.lists(
        st.one_of(st.floats(0.0, 60.0), st.sampled_from([0.0, np.inf, -np.inf, np.nan, 1e300]), st.floats(-1.0, -1e-9)),
        min_size=1,
        max_size=12,
    ),
    range_max=st.sampled_from([5.0, 30.0, 1000.0, 1e300]),
    no_return=st.sampled_from([None, 0.0, 2.5]),
    sigma=st.sampled_from(["constant", "linear"]),
)
def test_the_farthest_walk_bounds_the_beam_tables_reach_from_both_sides(ranges, range_max, no_return, sigma):
    """farthest_walk (a shard's bound on a scan's reach, whatever its range_max states) against the beam table that
    the fusion walks: its longest stop lies between the farthest walk and the model's reach for it."""
    model = SensorModel(resolution=0.05, sigma=sigma, sigma0=0.03, sigma_slope=0.01)
    ranges = np.array(ranges)
    clear = None if no_return is None else min(no_return, range_max)
    with np.errstate(over="ignore"):  # (a linear sigma's peak offset at a return of 1e300 m: inf)
        table = beam_table(ranges, model, 0.1, range_max, clear)
    farthest = farthest_walk(ranges, 0.1, range_max, clear)
    used = table.kind != BEAM_SKIP
    stop = float(table.r_stop[used].max(initial=0.0))
    assert farthest <= stop <= model.beam_reach(farthest)
    assert (farthest == 0.0) == (not used.any())


@pytest.mark.parametrize("reach", [2.0, 5.0, 12.0, 32.0, 50.0])
@pytest.mark.parametrize("yaw", [0.0, math.pi / 2, math.pi, -math.pi / 2])
@pytest.mark.parametrize("samples", [1, 2])
def test_a_beam_with_no_return_along_an_axis_from_a_grid_line_clears_its_whole_reach(reach, yaw, samples):
    """A probe's finding: a robot at the origin (on grid lines) whose beam with no return pointed along an axis, and
    cleared to 5 m (or to 32 to 100 m, with 0.05 m cells), marked no cell at all: the scan's window, floor((x + reach)
    / res), lost a cell to rounding (6.05 / 0.05 = 120.99999999999999), and the ray, its end cell without a cell to
    spare, was skipped without a word. Each sample's ray now clears reach / res cells (it ends on a grid line, so no
    sliver of the next cell), as counted by hand; the second sample lies a cell to the side."""
    res = 0.05
    heading = np.array([math.cos(yaw), math.sin(yaw)]).round()
    poses = np.array([[0.0, 0.0, yaw], [1.0 - 3.0 * abs(heading[1]), 3.0 - 3.0 * abs(heading[0]), yaw]])
    poses[1, :2] += res * heading[::-1]  # a cell aside from the first: its ray crosses other cells
    grid = TiledGrid(res)
    fusion = MonteCarloFusion(grid, SensorModel(res), np.array([0.0]), 0.1, reach)
    result = fusion.fuse(np.array([np.inf]), poses[:samples], np.full(samples, 1.0 / samples))
    assert result.cells_updated == samples * round(reach / res)


def test_many_samples_match_slow_reference():
    """130 samples, more than the 64 bits of a word (the kernel once kept one bit per sample in a cell's mask)."""
    rng = np.random.default_rng(5)
    model = SensorModel(resolution=0.1, sigma0=0.04)
    n_samples = 130
    angles, ranges, samples, weights = random_scan(rng, 6, n_samples, 0.08)
    grid = TiledGrid(0.1, tile_size=8)
    MonteCarloFusion(grid, model, angles, 0.15, 1.0, merge_identical=False).fuse(ranges, samples, weights)
    mean, spread = reference_fuse(model, angles, 0.15, 1.0, ranges, samples, weights, (0.0, 0.0, 0.0))
    got = fused_cells(grid)
    assert set(got) == set(mean)
    for cell, (lo, var) in got.items():
        assert lo == pytest.approx(min(max(mean[cell], model.l_min), model.l_max), abs=3e-4), cell
        assert var == pytest.approx(max(spread[cell], 0.0), abs=3e-4), cell


def test_variance_layer_sums_per_scan_spread_over_scans():
    rng = np.random.default_rng(3)
    model = SensorModel(resolution=0.1)
    angles, ranges, samples, weights = random_scan(rng, 8, 4, 0.1)
    grid = TiledGrid(0.1)
    fusion = MonteCarloFusion(grid, model, angles, 0.15, 1.0)
    fusion.fuse(ranges, samples, weights)
    fusion.fuse(ranges, samples, weights)
    _, spread = reference_fuse(model, angles, 0.15, 1.0, ranges, samples, weights)
    for cell, (_, var) in fused_cells(grid).items():
        assert var == pytest.approx(2 * max(spread[cell], 0.0), abs=5e-4)


def test_all_weight_on_one_sample_equals_ml():
    rng = np.random.default_rng(7)
    model = SensorModel(resolution=RES)
    angles, ranges, samples, _ = random_scan(rng, 50, 6, 0.1)
    one_hot = np.zeros(6)
    one_hot[2] = 1.0
    a, b = TiledGrid(RES), TiledGrid(RES)
    MonteCarloFusion(a, model, angles, 0.15, 1.0).fuse(ranges, samples, one_hot)
    MonteCarloFusion(b, model, angles, 0.15, 1.0).fuse(ranges, samples[2:3], np.ones(1))
    ra, rb = a.rasterize(), b.rasterize()
    for key in ra:
        np.testing.assert_array_equal(ra[key], rb[key])


def test_ml_fuses_the_pose_whose_copies_weigh_most():
    """A paper probe's finding: ml took the particle of the largest weight before identical ones were merged, so a
    pose held by three copies of weight 0.25 (0.75 in all) lost to one of 0.25 that came first, and two files of
    the same distribution gave two ml maps. Merged first, as mc merges them (docs/sensor_model.md, section 4)."""
    a, b = [0.0, 0.0, 0.1], [0.05, 0.03, 0.0]
    for poses, weights in (
        ([b, a, a, a], [0.25] * 4),
        ([b, a], [0.25, 0.75]),
        ([b, a, b, a, a], [0.1, 0.3, 0.15, 0.2, 0.25]),  # a 0.75 in three copies, b 0.25 in two; b's 0.15 is no max
    ):
        chosen, weight = scan_samples("ml", samples=np.array(poses), weights=np.array(weights))
        assert chosen.tolist() == [a] and weight.tolist() == [1.0]
    tie = scan_samples("ml", samples=np.array([b, a, a]), weights=np.array([0.5, 0.25, 0.25]))[0]
    assert tie.tolist() == [b]  # equal weights once merged: the first


def test_clamping():
    model = SensorModel(resolution=RES)
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, model, np.array([0.0]), 0.05, 10.0)
    for _ in range(20):
        fusion.fuse(np.array([0.5]), np.array([[0.025, 0.025, 0.0]]), np.ones(1))
    cells = fused_cells(grid)
    assert cells[(10, 0)][0] == pytest.approx(model.l_max, abs=1e-6)
    assert cells[(2, 0)][0] == pytest.approx(model.l_min, abs=1e-6)


def test_shards_partition_the_map():
    """Fusing only owned tiles in three shards and joining them gives the single-process map (rays that
    cross other shards' tiles in their free part, at their return, and with no return at all)."""
    rng = np.random.default_rng(11)
    model = SensorModel(resolution=RES)
    angles = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    scans = [
        (
            np.where(np.arange(90) % 7 == 0, np.inf, rng.uniform(1, 6, 90)),
            np.column_stack([rng.normal(0, 0.1, 5), rng.normal(0, 0.1, 5), rng.normal(0, 0.05, 5)]),
            np.full(5, 0.2),
        )
        for _ in range(3)
    ]
    whole, joined = whole_and_joined(32, (model, angles, 0.1, 8.0), scans, 3, lambda tx, ty: (tx * 7 + ty * 13) % 3)
    a, b = whole.rasterize(), joined.rasterize()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_a_shard_keeps_only_its_own_tiles_when_rays_pass_tile_corners():
    """A ray from a laser on a tile's corner (1 km out: its coordinates are not exact in binary), heading along its
    tile's edge or diagonal within the corner tolerance, steps through the corner diagonally, while its runs, which
    follow its line, take a sliver of a cell beside the corner. A stretch of a shard's own tiles ends at such a
    corner: no shard holds a tile it does not own. (Found by a fuzz: shard 1 of 2 wrote a cell of shard 0's tile.)"""
    model = SensorModel(resolution=0.05, sigma="constant", sigma0=0.01)
    corner = np.array([996.8, -2001.6])  # (a corner of tiles of 32 cells: 1.6 m)
    rng = np.random.default_rng(3)
    angles = np.concatenate([[0.08735365380480542], rng.uniform(-math.pi, math.pi, 40)])
    found = (  # the fuzz's case, shrunk: one beam, two samples, the first on the corner
        np.concatenate([[0.2], np.full(40, np.inf)]),
        np.array([[996.8, -2001.6, -math.pi / 2], [995.1999999999999, -2001.6, -math.pi]]),
        np.array([0.5, 0.5]),
    )
    scans = [found]
    for offset in ((0.0, 0.0), (-1.6, 0.0), (0.0, 1.6), (1.6, -1.6)):
        yaws = np.arange(-4, 4) * math.pi / 4 + rng.choice([0.0, 1e-12, -1e-11], 8)
        samples = np.column_stack([np.full(8, corner[0] + offset[0]), np.full(8, corner[1] + offset[1]), yaws])
        scans.append((rng.uniform(0.2, 3.0, len(angles)), samples, np.full(8, 1 / 8)))
    for shard in range(2):
        owns = owns_tile(shard, 2)
        grid = TiledGrid(0.05, tile_size=32)
        fusion = MonteCarloFusion(grid, model, angles, 0.0, 0.5, owns_tile=owns)
        fusion.fuse(*found)
        fusion = MonteCarloFusion(grid, model, angles, 0.0, 3.5, owns_tile=owns)
        for scan in scans[1:]:
            fusion.fuse(*scan)
        assert list(grid.keys()) and all(owns(*key) for key in grid.keys()), shard  # noqa: SIM118 (no __iter__)


def test_a_shards_cells_past_another_shards_tile_are_the_whole_windows_bit_for_bit():
    """A diagonal ray along cell corners (from (-0.1, 0.06) m: not exact in binary), its cells near the return walked
    one by one for 7 m (a stereo model: its spread grows with the range squared, so the near phase starts 1.09 m
    out). The whole window's walk sums its crossing ranges step by step; a shard that jumped over another shard's tile
    took them as products, the two parted by more than the corner tolerance a cell apart, and that shard's staircase
    started a cell later. A shard steps through the other shards' tiles after its runs: four shards joined give the
    whole window's tiles bit for bit. (Found by a fuzz: 0.02 in log-odds in two cells.)"""
    model = SensorModel(resolution=0.02, sigma="stereo", sigma0=0.002, baseline_focal=50.0)
    angles = np.array([3 * math.pi / 4])
    ranges = np.array([8.739039], np.float32).astype(np.float64)
    samples = np.array([[-0.1, 0.06, math.pi], [-0.1, 0.06, math.pi]])  # (two: the samples pass)

    def fused(owns):
        grid = TiledGrid(0.02, tile_size=64)
        fusion = MonteCarloFusion(grid, model, angles, 0.05, 12.0, owns_tile=owns, merge_identical=False)
        fusion.fuse(ranges, samples, np.array([0.5, 0.5]))
        return {key: grid.tile_arrays(key) for key in grid.keys() if owns is None or owns(*key)}  # noqa: SIM118

    whole = fused(None)
    joined = {key: arrays for shard in range(4) for key, arrays in fused(owns_tile(shard, 4)).items()}
    assert sorted(joined) == sorted(whole)
    for key, arrays in whole.items():
        for layer, joined_layer in zip(arrays, joined[key], strict=True):
            assert np.array_equal(layer, joined_layer), key


def test_a_shard_owning_no_tile_of_a_scans_window_walks_nothing():
    """A scan whose window (every sample's rays, to range_max) holds none of the shard's tiles is not walked: nothing
    changes and no sample is counted as walked. Owning one tile of the window, the same shard walks all 5 samples."""
    model, angles = SensorModel(resolution=RES), np.linspace(-math.pi, math.pi, 90, endpoint=False)
    rng = np.random.default_rng(5)
    scan = (
        rng.uniform(1, 6, 90),
        np.column_stack([rng.normal(0, 0.1, (5, 2)), rng.normal(0, 0.05, 5)]),
        np.full(5, 0.2),
    )
    asked: list[tuple[int, int]] = []

    def far(tx: int, ty: int) -> bool:
        asked.append((tx, ty))
        return tx >= 100  # tiles of 32 cells of 0.05 m: 160 m away and more

    fusion = MonteCarloFusion(TiledGrid(RES, tile_size=32), model, angles, 0.1, 8.0, owns_tile=far)
    result = fusion.fuse(*scan)
    assert asked and (result.cells_updated, result.tiles_changed, result.samples_walked) == (0, [], 0)
    assert not list(fusion.grid.keys())
    fusion = MonteCarloFusion(
        TiledGrid(RES, tile_size=32), model, angles, 0.1, 8.0, owns_tile=lambda tx, ty: tx == ty == 0
    )
    result = fusion.fuse(*scan)
    assert result.tiles_changed == [(0, 0)] and result.samples_walked == 5 and result.cells_updated > 0


def test_merge_duplicates():
    samples = np.array([[1.0, 2.0, 0.1], [0.0, 0.0, 0.0], [1.0, 2.0, 0.1], [5.0, 5.0, 5.0]])
    merged, weights = merge_duplicates(samples, np.array([0.25, 0.25, 0.5, 0.0]))
    np.testing.assert_array_equal(merged, samples[:2])
    np.testing.assert_allclose(weights, [0.75, 0.25])


def test_unbounded_map_grows_tiles_on_demand():
    grid = TiledGrid(RES, tile_size=16)
    fusion = MonteCarloFusion(grid, SensorModel(resolution=RES), np.array([0.0]), 0.05, 5.0)
    fusion.fuse(np.array([1.0]), np.array([[-100.0, 250.0, math.pi]]), np.ones(1))
    assert all(key[0] < 0 and key[1] > 0 for key in grid.keys())  # noqa: SIM118  # TiledGrid: no __iter__
    raster = grid.rasterize()
    assert raster["origin"][0] < -100.9 and raster["origin"][1] == pytest.approx(250.0)


@pytest.mark.parametrize(
    "samples, weights, message",
    [
        (np.zeros((2, 3)), np.array([0.5, 0.6]), "sum to 1"),
        (np.full((1, 3), np.nan), np.ones(1), "finite"),
        (np.zeros((0, 3)), np.zeros(0), "M >= 1"),
        (np.zeros((2, 2)), np.full(2, 0.5), "M >= 1"),  # not (M, 3): one sentence, not numpy's reshape error
        (np.zeros((1, 6)), np.full(2, 0.5), "M >= 1"),  # two poses in one row: refused, not read as (2, 3)
        (np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.inf]]), np.full(2, 0.5), "finite"),
        (np.zeros((2, 3)), np.array([1.5, -0.5]), "non-negative"),
        (np.array([[1e300, 0.0, 0.0]]), np.ones(1), "beyond"),  # finite, but no cell index reaches it
        (np.array([[0.0, -1e16, 0.0]]), np.ones(1), "beyond"),
        (np.array([[0.0, 0.0, 0.0], [300.0, 300.0, 0.0]]), np.full(2, 0.5), "spread over 300 m x 300 m"),  # diverged
    ],
)
def test_bad_poses_are_rejected(samples, weights, message):
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, SensorModel(resolution=RES), np.array([0.0]), 0.05, 5.0)
    with pytest.raises(InputError, match=message):
        fusion.fuse(np.array([1.0]), samples, weights)
    assert grid.keys() == []  # refused before anything was written


@pytest.mark.parametrize(
    "range_max, message",
    [
        (1e308, "reaches beyond"),  # finite, but its reach over a cell overflows to inf
        (1000.0, "spread over 0 m x 0 m and its rays reach 1000"),  # 40 000 x 40 000 cells of 0.05 m
    ],
)
def test_a_range_limit_no_window_can_hold_is_refused(range_max, message):
    grid = TiledGrid(RES)
    fusion = MonteCarloFusion(grid, SensorModel(resolution=RES), np.array([0.0]), 0.05, range_max)
    with pytest.raises(InputError, match=message):
        fusion.fuse(np.array([np.inf]), np.zeros((1, 3)), np.ones(1))  # no return: free up to range_max
    assert grid.keys() == []


@settings(max_examples=200, deadline=None)
@given(
    reach_cells=st.integers(1_990, 2_060),  # rays about half the side of the largest window (4 096 cells square)
    origin=st.tuples(st.floats(-50.0, 50.0), st.floats(-50.0, 50.0)),
    spread=st.tuples(st.floats(0.0, 3.0), st.floats(0.0, 3.0)),
    sharded=st.booleans(),
)
def test_a_window_a_scan_is_given_fits_the_largest_a_scan_may_take(reach_cells, origin, spread, sharded):
    """check_window lets a scan through before its window is laid out; the window then laid out (its origin on 8
    cells, a shard's on 64, its rows padded to whole 64-cell words) holds at most MAX_WINDOW_CELLS cells."""
    owner = (lambda tx, ty: True) if sharded else None
    fusion = MonteCarloFusion(
        TiledGrid(RES), SensorModel(resolution=RES), np.array([0.0]), 0.05, reach_cells * RES, owns_tile=owner
    )
    samples = np.array([[origin[0], origin[1], 0.0], [origin[0] + spread[0], origin[1] + spread[1], 0.0]])
    try:
        ready = fusion.prepare((np.array([np.inf]), samples, np.full(2, 0.5)))
    except InputError:
        return  # (refused: too large)
    assert ready is not None
    assert -(-ready.window.w // 64) * 64 * ready.window.h <= MAX_WINDOW_CELLS


def test_a_map_too_wide_for_one_raster_is_refused_not_allocated():
    """Two scans 2 000 km apart: each fuses, but one raster of both would hold 4e15 cells."""
    grid = TiledGrid(RES, tile_size=16)
    fusion = MonteCarloFusion(grid, SensorModel(resolution=RES), np.array([0.0]), 0.05, 5.0)
    for x in (0.0, 2e6):
        fusion.fuse(np.array([1.0]), np.array([[x, 0.0, 0.0]]), np.ones(1))
    # 16 cells of 0.05 m a tile
    assert {tx for tx, _ in grid.keys()} == {0, 1, 2_500_000, 2_500_001}  # noqa: SIM118  # TiledGrid: no __iter__
    with pytest.raises(InputError, match=r"more than the .* cells one raster may hold"):
        grid.rasterize()


def _model_g(r, z, sigma, l):
    """The convolved ideal model g(r) for a return at z (docs/sensor_model.md, section 2), written out again."""
    s = math.sqrt(2) * sigma
    return 0.25 + 0.25 * math.erf((z + l / 2 - r) / s) - 0.5 * math.erf((z - l / 2 - r) / s)


@pytest.mark.parametrize("sigma", ["constant", "linear"])  # linear with slope 0: the same model, in closed form
@pytest.mark.parametrize(("resolution", "sigma0"), [(0.2, 0.01), (0.05, 0.002)])
def test_a_narrow_noise_model_keeps_the_cell_before_the_peak_free(resolution, sigma0, sigma):
    """A peak much wider than sigma (l/2 = 14 and 18 sigma): the cell before the return's is on the model's rising
    side, at the value of its far edge. (The constant-sigma table covers l/2 up to 8 sigma; past that, cells
    before the peak had read the table's first entry, a value from inside the peak: +0.09 instead of -0.405 at
    0.2 m cells, a wall drawn one cell early.) One beam along +x from x0 = resolution - 0.01 in cell 0, return at
    2.0 m: cell k >= 1 spans r in [k res - x0, (k + 1) res - x0]."""
    model = SensorModel(resolution=resolution, sigma=sigma, sigma0=sigma0)
    x0 = resolution - 0.01
    grid = TiledGrid(resolution)
    MonteCarloFusion(grid, model, np.array([0.0]), 0.05, 10.0).fuse(
        np.array([2.0]), np.array([[x0, resolution / 2, 0.0]]), np.ones(1)
    )
    k = int(math.floor(2.0 / resolution + 1e-9)) - 1  # the cell just before the one holding x = 2.0
    g = _model_g((k + 1) * resolution - x0, 2.0, sigma0, model.l)
    assert g < 0.5  # before the peak: the free branch of the squashing
    p = 0.5 - (0.5 - model.p_miss) * (1 - 2 * g)
    logodds, _, observed = grid.tile_arrays((0, 0))
    assert observed[0, k]
    assert float(logodds[0, k]) == pytest.approx(math.log(p / (1 - p)), abs=2e-4)


def test_rays_ending_on_a_grid_line_give_the_same_cells_whole_and_sharded():
    """Three samples' rays along +x from x = 0, free to range_max = 0.2 m with 0.02 m cells: each ends on a grid
    line and covers cells 0..9 of its row. The summed crossings of the walk (the shards' path) land 3e-17 m short
    of the end; the walk used to visit a sliver of cell 10 there while the runs (one shard owning every tile) did
    not, so the sharded map differed from the whole one."""
    samples = np.array([[0.0, 0.006, 0.0], [0.0, 0.026, 0.0], [0.0, 0.046, 0.0]])
    scan = (np.array([np.nan]), samples, np.full(3, 1 / 3))
    whole, joined = whole_and_joined(
        4, (SensorModel(resolution=0.02), np.array([0.0]), 0.05, 0.2), [scan], 2, lambda tx, ty: (tx + ty) % 2
    )
    assert sorted(fused_cells(whole)) == sorted((k, row) for k in range(10) for row in range(3))
    a, b = whole.rasterize(), joined.rasterize()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


@pytest.mark.parametrize("seed", range(4))
def test_whole_and_sharded_maps_agree_on_random_setups(seed):
    """One shard owning every tile against two shards joined (their runs by stretches of their own tiles, their walks
    near the returns stepping through the other's tiles), over random cell sizes, tile sizes, sigma models, beams,
    samples and sensor offsets, a third of the poses on grid points with headings at multiples of pi/4: the same maps
    bit for bit (with jumps over the other shard's tiles, which take the crossings' ranges as products where the
    single shard's walk sums them, two of the four seeds differed in the last bits)."""
    rng = np.random.default_rng(seed)
    for _ in range(6):
        res = float(rng.choice([0.02, 0.05, 0.1, 0.2]))
        tile = int(rng.choice([4, 8, 32]))
        sigma = str(rng.choice(["constant", "linear", "stereo"]))
        model = SensorModel(resolution=res, sigma=sigma, sigma_slope=0.01, baseline_focal=50.0)
        n_beams = int(rng.integers(1, 120))
        angles = np.linspace(-math.pi, math.pi, n_beams, endpoint=False)
        range_max = float(rng.choice([1.0, 4.0]))
        offset = tuple(rng.normal(0, 0.1, 3)) if rng.random() < 0.5 else (0.0, 0.0, 0.0)
        ranges = rng.uniform(0.0, range_max * 1.1, n_beams)
        ranges[rng.random(n_beams) < 0.1] = np.nan
        m = int(rng.integers(2, 40))
        if rng.random() < 0.3:
            poses = np.column_stack(
                [
                    rng.integers(-20, 20, m) * res / 2,
                    rng.integers(-20, 20, m) * res / 2,
                    rng.integers(-8, 8, m) * math.pi / 4,
                ]
            )
        else:
            poses = np.column_stack([rng.normal(0, 0.3, m), rng.normal(0, 0.3, m), rng.normal(0, 0.5, m)])
        weights = rng.random(m)
        weights /= weights.sum()
        whole, joined = whole_and_joined(
            tile,
            (model, angles, 0.05, range_max, offset),
            [(ranges, poses, weights)],
            2,
            lambda tx, ty: (tx * 7 + ty * 13) % 2,
        )
        a, b = whole.rasterize(), joined.rasterize()
        for layer in ("observed", "logodds", "variance"):
            np.testing.assert_array_equal(a[layer], b[layer])


def test_the_samples_scratch_holds_the_bytes_a_cell_its_docs_give():
    """Hand-computed: six bit planes (a group's four, the listed and the raised cells) and a bit of the column-major
    plane (0.875 byte), the weight sum (8), the excess record (32) and 16 levels of counts (2): 42.875 bytes a cell; a
    512 x 512 window (words whole) adds only the per-line and per-beam scratch (2 x 512 int64, 28 int64 and float64
    fan records for each of 361 beams) and the 64 words of a 64 x 64 bit block."""
    assert SAMPLES_SCRATCH_BYTES_PER_CELL == 42.875
    scratch = FusionScratch()
    cells = 512 * 512
    scratch.for_samples(cells, cells, 512, 361)
    assert FAN_INTS + FAN_FLOATS == 28
    room = cells + cells // 8  # (a scratch grows by an eighth more than the window asks: the per-cell arrays)
    per_cell = SAMPLES_SCRATCH_BYTES_PER_CELL - 1 / 8  # (the column-major plane's bit: for the window's columns only)
    assert scratch.nbytes == per_cell * room + cells / 8 + 2 * 512 * 8 + 28 * 361 * 8 + 64 * 8


def test_a_scratch_keeps_an_eighth_more_cells_so_that_a_growing_window_seldom_reallocates():
    scratch = FusionScratch()
    scratch.for_samples(8000, 8000, 100, 10)
    assert scratch.size == 9000 and scratch.excess.shape == (9000, 4) and scratch.weight_sum.shape == (9000,)
    excess = scratch.excess
    scratch.for_samples(9000, 8000, 100, 10)  # grown by an eighth: no new arrays
    assert scratch.excess is excess
    scratch.for_samples(9001, 8000, 100, 10)
    assert scratch.size == 9001 + 1125 and scratch.excess is not excess
    # near the largest window a scan may take, no room beyond it (checked on the rule: those arrays take 0.7 GB)
    assert (
        _with_room(MAX_WINDOW_CELLS - 10) == MAX_WINDOW_CELLS
        and _with_room(MAX_WINDOW_CELLS + 5) == MAX_WINDOW_CELLS + 5
    )
    scratch.for_single(800)
    assert scratch.single_blocks == 900 and scratch.largest.shape == (900 * 64,)


def test_the_weight_sums_are_kept_only_once_a_scans_weights_differ():
    """Equal weights are counted, so their scans need no weight sums: 8 bytes a cell fewer (34.5), until a scan whose
    weights differ comes."""
    counted, summed = FusionScratch(), FusionScratch()
    counted.for_samples(512 * 512, 512 * 512, 512, 361, summed=False)
    summed.for_samples(512 * 512, 512 * 512, 512, 361, summed=True)
    room = 512 * 512 + 512 * 512 // 8
    assert counted.weight_sum.size == 0 and summed.nbytes - counted.nbytes == 8 * room
    counted.for_samples(512 * 512, 512 * 512, 512, 361, summed=True)
    assert counted.weight_sum.shape == (room,) and counted.nbytes == summed.nbytes
