"""The adaptive grid's storage: lookups against a brute-force cover, edits, and the raster with `level`."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.adaptive.tree import NO_CELL, AdaptiveGrid, children, morton
from mapping.errors import InputError
from mapping.grid import RasterTooLarge


def build(cells, tile_size=16, resolution=0.5):
    """A grid holding cells [(level, ax, ay, logodds)], all added in one edit."""
    grid = AdaptiveGrid(resolution, tile_size)
    level, ax, ay, lo = (np.array(c) for c in zip(*cells))
    zeros = np.zeros(len(cells))
    grid.edit(np.zeros(0, np.int64), level, ax, ay, lo, zeros, zeros, zeros)
    return grid


def brute_cover(cells, ix, iy):
    """Index in ``cells`` of the cell covering finest cell (ix, iy), -1 if none."""
    for n, (k, ax, ay, _) in enumerate(cells):
        if ax << k <= ix < (ax + 1) << k and ay << k <= iy < (ay + 1) << k:
            return n
    return -1


# a 16 x 16 tile at (0, 0) split unevenly, plus one coarse cell in the tile at (-1, -1)
CELLS = [
    (3, 0, 0, 1.0),  # finest cells x 0..7, y 0..7
    (2, 2, 0, 2.0),
    (2, 3, 0, 3.0),
    (2, 3, 1, 4.0),  # three quarters of the tile's lower-right level-3 cell
    (0, 8, 4, 5.0),
    (0, 9, 4, 6.0),
    (0, 8, 5, 7.0),
    (1, 5, 3, 8.0),  # its last quarter, split further
    (4, -1, -1, 9.0),  # the whole tile (-1, -1): finest cells -16..-1
]


def test_morton_interleaves_bits():
    assert morton(np.array([0b101]), np.array([0b011])).tolist() == [0b011011]
    assert morton(np.array([1, 0, 1]), np.array([0, 1, 1])).tolist() == [1, 2, 3]


def test_find_matches_brute_force_cover():
    grid = build(CELLS)
    ix, iy = np.meshgrid(np.arange(-17, 17), np.arange(-17, 17))
    found = grid.find(ix.ravel(), iy.ravel())
    level, ax, ay = grid.cells(np.maximum(found, 0))
    for f, x, y, k, cx, cy in zip(found, ix.ravel(), iy.ravel(), level, ax, ay):
        expected = brute_cover(CELLS, x, y)
        if expected < 0:
            assert f == -1, (x, y)
        else:
            assert (k, cx, cy) == CELLS[expected][:3], (x, y)
    assert grid.logodds[grid.find(np.array([9]), np.array([4]))].tolist() == [6.0]
    assert grid.find(np.array([9, 10, 8]), np.array([5, 4, 6])).tolist() == [-1, -1, -1]  # holes in the tree


def test_find_exact_and_blocks():
    grid = build(CELLS)
    assert grid.find_exact(np.array([2, 2, 1, 4]), np.array([3, 2, 5, -1]), np.array([1, 1, 3, -1])).tolist()[1] == -1
    exact = grid.find_exact(np.array([2, 1, 4, 3]), np.array([3, 5, -1, 1]), np.array([1, 3, -1, 0]))
    assert grid.logodds[exact[:3]].tolist() == [4.0, 8.0, 9.0] and exact[3] == -1
    # the active cells inside the level-3 block (1, 0) and the one covering block (-2, -2) at level 3
    inside = grid.cells_in_blocks(3, np.array([1, -2]), np.array([0, -2]))
    assert sorted(grid.logodds[inside].tolist()) == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]


def test_edit_replaces_a_cell_by_its_children():
    grid = build(CELLS)
    parent = grid.find_exact(np.array([3]), np.array([0]), np.array([0]))
    kx, ky = children(np.array([0]), np.array([0]))
    grid.edit(parent, np.full(4, 2), kx, ky, np.array([1.0, 1.5, 2.5, 3.5]), np.zeros(4), np.zeros(4), np.zeros(4))
    assert grid.active_cells == len(CELLS) + 3
    assert np.all(np.diff(grid.key) > 0), "keys stay sorted and distinct"
    assert grid.logodds[grid.find(np.array([0, 7, 0, 7]), np.array([0, 0, 7, 7]))].tolist() == [1.0, 1.5, 2.5, 3.5]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(-40, 40), st.integers(-40, 40)), min_size=1, max_size=25))
def test_cells_round_trip_and_cover(raw):
    # disjoint random cells: keep a cell only if it overlaps none kept before
    kept = []
    taken = set()
    for k, x, y in raw:
        ax, ay = x >> k, y >> k
        finest = {(fx, fy) for fx in range(ax << k, (ax + 1) << k) for fy in range(ay << k, (ay + 1) << k)}
        if finest & taken:
            continue
        taken |= finest
        kept.append((k, ax, ay, float(len(kept))))
    grid = build(kept, tile_size=8)
    level, ax, ay = grid.cells()
    assert sorted(zip(level.tolist(), ax.tolist(), ay.tolist())) == sorted(c[:3] for c in kept)
    probe = np.array(sorted(taken) + [(100, 100)])
    found = grid.find(probe[:, 0], probe[:, 1])
    assert found[-1] == -1
    for f, (x, y) in zip(found[:-1], probe[:-1]):
        assert grid.logodds[f] == kept[brute_cover(kept, x, y)][3]


def test_rasterize_holds_levels_and_counts_cells():
    grid = build(CELLS)
    raster = grid.rasterize()
    # bounding box: finest cells x -16..15, y -16..7 at 0.5 m
    assert raster["logodds"].shape == (24, 32)
    np.testing.assert_allclose(raster["origin"], [-8.0, -8.0])
    level = raster["level"]
    assert level.dtype == np.int8
    assert level[16 + 0, 16 + 0] == 3 and level[16 + 4, 16 + 9] == 0 and level[0, 0] == 4
    assert level[16 + 5, 16 + 9] == NO_CELL and not raster["observed"][16 + 5, 16 + 9]
    assert level[16 + 7, 16 + 9] == NO_CELL
    covered = raster["observed"]
    assert np.isclose((4.0 ** -level[covered].astype(float)).sum(), grid.active_cells)
    assert raster["logodds"][16 + 6, 16 + 10] == np.float32(8.0)
    np.testing.assert_allclose(raster["probability"][16, 16], 1 / (1 + np.exp(-1.0)), rtol=1e-6)


def test_rasterize_at_a_coarser_resolution_samples_cell_centres():
    grid = build(CELLS)
    raster = grid.rasterize(resolution=2.0)  # 4 finest cells per raster cell side
    assert raster["logodds"].shape == (6, 8) and float(raster["resolution"]) == 2.0
    # raster cell (row 4, col 4) is centred on finest (2, 2) -> the level-3 cell with log-odds 1
    assert raster["logodds"][4, 4] == 1.0 and raster["level"][4, 4] == 3
    # raster cell (row 5, col 6) is centred on finest (10, 6) -> the level-1 cell (5, 3)
    assert raster["logodds"][5, 6] == 8.0


def test_a_raster_larger_than_one_map_file_is_refused_before_it_is_allocated():
    """A probe: two scans 800 m apart fused on the adaptive grid took `posegrid fuse` to 6.3 GB before numpy ran out
    of memory, where the regular grid refuses a raster past MAX_RASTER_CELLS at once; an infinite resolution gave a
    1 x 1 raster. The same bound and a finite resolution now hold here."""
    far = build([(0, 0, 0, 1.0), (0, 20_000, 20_000, 2.0)], resolution=0.05)  # 20 001 x 20 001 finest cells
    with pytest.raises(RasterTooLarge, match=r"span 20001 x 20001 cells of 0\.05 m"):
        far.rasterize()
    assert far.rasterize(resolution=5.0)["logodds"].shape == (201, 201)  # coarser: 40 401 cells
    near = build(CELLS)
    for resolution in (float("inf"), float("nan"), 0.0):
        with pytest.raises(InputError, match="finite"):
            near.rasterize(resolution)


def test_empty_grid_and_bad_arguments():
    grid = AdaptiveGrid(0.05)
    raster = grid.rasterize()
    assert raster["logodds"].shape == (0, 0) and raster["level"].shape == (0, 0)
    assert grid.find(np.array([0]), np.array([0])).tolist() == [-1]
    with pytest.raises(InputError):
        AdaptiveGrid(0.05, tile_size=100)
    with pytest.raises(InputError):
        grid.rasterize(resolution=0.0)
