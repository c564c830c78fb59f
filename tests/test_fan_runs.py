"""Fans of neighbouring rays (mapping.fan_runs): the rows they share near the laser are marked once a fan, and the map
is the one the rays' own runs give, cell for cell: against the slow reference, and against two shards joined (a
shard's fans join only the rays that cross its own tiles alone; the others it walks tile by tile)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.fan_runs import SKIP
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from reference import reference_fuse
from test_fusion import fused_cells, whole_and_joined


def _poses(rng: np.random.Generator, count: int, res: float, on_grid: bool) -> np.ndarray:
    """Pose samples anywhere, or (on_grid) half of them on grid points and cell edges with headings at multiples of
    pi / 4: rays along the grid lines and through cell corners."""
    poses = np.column_stack([rng.normal(0, 0.2, count), rng.normal(0, 0.2, count), rng.normal(0, 1.0, count)])
    if on_grid:
        poses[::2, 0] = rng.integers(-6, 6, len(poses[::2])) * res / 2
        poses[::2, 1] = rng.integers(-6, 6, len(poses[::2])) * res / 2
        poses[::2, 2] = rng.integers(-8, 8, len(poses[::2])) * math.pi / 4
    return poses


def _assert_the_references_cells(grid: TiledGrid, args: tuple, scan: tuple) -> None:
    """The grid holds the cells of the slow reference's map of ``scan`` (ranges, samples, weights) under ``args``
    (model, angles, range_min, range_max), each value within 3e-4 of the reference's (its erf from scipy)."""
    model = args[0]
    mean, spread = reference_fuse(*args, *scan)
    got = fused_cells(grid)
    assert set(got) == set(mean)
    for cell, (lo, var) in got.items():
        assert lo == pytest.approx(min(max(mean[cell], model.l_min), model.l_max), abs=3e-4), cell
        assert var == pytest.approx(max(spread[cell], 0.0), abs=3e-4), cell


def _skipped_rows(fusion: MonteCarloFusion) -> int:
    """Rows the fans marked for the rays of the last sample walked (their SKIP)."""
    return int(fusion.threads.lone.fan_ints[SKIP].sum())


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), n_beams=st.integers(90, 360), n_samples=st.integers(2, 4))
def test_fans_give_the_slow_references_cells(seed, n_beams, n_samples):
    """Beams dense enough that neighbours pass within a cell of each other for the first metres: the cells and
    values of the slow reference, which walks every ray cell by cell. (Poses anywhere: from a pose on a grid line, a
    beam along that line runs in the row above it or below by the sign of a direction of 1e-16, which the kernels
    and the reference round apart; the next test has such poses.)"""
    rng = np.random.default_rng(seed)
    model = SensorModel(resolution=0.1, sigma0=0.04)
    angles = np.linspace(-math.pi, math.pi, n_beams, endpoint=False)
    ranges = rng.uniform(0.3, 3.2, n_beams)
    ranges[rng.random(n_beams) < 0.1] = np.inf
    samples = _poses(rng, n_samples, 0.1, on_grid=False)
    weights = np.full(n_samples, 1.0 / n_samples)
    grid = TiledGrid(0.1, tile_size=16)
    fusion = MonteCarloFusion(grid, model, angles, 0.15, 3.0)
    fusion.fuse(ranges, samples, weights)
    assert _skipped_rows(fusion) > 0  # (the fans were used)
    _assert_the_references_cells(grid, (model, angles, 0.15, 3.0), (ranges, samples, weights))


@pytest.mark.parametrize("seed", range(3))
def test_fans_mark_the_cells_two_shards_walk_for_a_modern_lidar(seed):
    """1081 beams over 270 deg to 12 m in 0.05 m cells (fans out to about 10 m): one fusion owning every tile
    against two shards joined (fans of the rays in a shard's own tiles only, the rest walked tile by tile): the same
    maps bit for bit."""
    rng = np.random.default_rng(seed)
    model = SensorModel(resolution=0.05)
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 1081)
    scans = []
    for _ in range(2):
        ranges = rng.uniform(0.3, 12.5, 1081)
        ranges[rng.random(1081) < 0.05] = np.nan
        samples = _poses(rng, 6, 0.05, on_grid=True)
        scans.append((ranges, samples, np.full(6, 1.0 / 6)))
    args = (model, angles, 0.05, 12.0, (0.1, 0.0, 0.0))
    whole, joined = whole_and_joined(64, args, scans, 2, lambda tx, ty: (tx * 7 + ty * 13) % 2)
    probe = MonteCarloFusion(TiledGrid(0.05, tile_size=64), *args)
    probe.fuse(*scans[0])
    assert _skipped_rows(probe) > 1081 * 20  # (most rays left rows to their fans)
    a, b = whole.rasterize(), joined.rasterize()
    for layer in ("observed", "logodds", "variance"):
        np.testing.assert_array_equal(a[layer], b[layer])


def _turning_back(rng: np.random.Generator, n_beams: int) -> np.ndarray:
    """Beam angles that turn back: random directions, each beam after the first either a new one or one of the two
    before it again (so that a beam between two of the same direction points elsewhere)."""
    angles = [rng.uniform(-math.pi, math.pi)]
    for _ in range(n_beams - 1):
        angles.append(angles[-2] if len(angles) > 1 and rng.random() < 0.5 else rng.uniform(-math.pi, math.pi))
    return np.array(angles)


@pytest.mark.parametrize("seed", range(40))
def test_fans_of_beams_whose_angles_turn_back_give_the_slow_references_cells(seed):
    """The library takes beam angles in any order (a scan message's are angle_min + i * angle_increment, in order; a
    caller of MonteCarloFusion may pass two lasers' beams merged, or repeated directions). A fan is spanned by its end
    rays only while its beams turn one way: beams that point away and come back give the slow reference's cells and
    values, and no fewer. (Found by a fuzz: three beams, the first and last the same direction, the middle one 0.5 rad
    off and joined to both near the laser; its cells in those rows were left out.)"""
    rng = np.random.default_rng(seed)
    model = SensorModel(resolution=0.1, sigma="linear", sigma0=0.1, sigma_slope=0.01)
    n_beams = int(rng.integers(3, 9))
    angles = _turning_back(rng, n_beams)
    ranges = rng.uniform(0.5, 4.5, n_beams)
    ranges[rng.random(n_beams) < 0.3] = np.nan  # (no return: free to range_max beside shorter beams)
    samples = np.column_stack([rng.normal(0, 0.2, 2), rng.normal(0, 0.2, 2), rng.normal(0, 1.0, 2)])
    weights = np.array([0.4, 0.6])
    grid = TiledGrid(0.1, tile_size=4)
    MonteCarloFusion(grid, model, angles, 0.1, 4.0).fuse(ranges, samples, weights)
    _assert_the_references_cells(grid, (model, angles, 0.1, 4.0), (ranges, samples, weights))
