"""The window of each changed tile a fusion reports (FuseResult.windows, mapping.tile_boxes): on a fresh grid, where
every cell a scan touches becomes observed, it is exactly the bounding box of the tile's observed cells (by numpy);
on a grid with earlier scans, every cell whose values changed lies inside it. Samples pass and one-sample pass, whole
windows and shards, tiles of 4 cells (smaller than the one-sample pass's 8 x 8 blocks), 32 and 256, a scan in parts."""

from __future__ import annotations

import numpy as np
import pytest

from bench.scenarios import honest_posed_scans, office_run
from mapping.fusion import FusionScratch, MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from mapping.tile_changes import ALL_CHANGED, LOGODDS_CHANGED, OBSERVED_CHANGED, VARIANCE_CHANGED, take_changed_cells
from services.state.ownership import owns_tile
from test_threads import particle_scans

RES = 0.05
MODEL = SensorModel(resolution=RES)


@pytest.fixture(scope="module")
def particles():
    return honest_posed_scans(office_run(steps=6), particles=24)


def observed_box(observed: np.ndarray) -> tuple[int, int, int, int]:
    """(row0, col0, rows, cols) of a tile's observed cells, by numpy."""
    rows, cols = np.flatnonzero(observed.any(axis=1)), np.flatnonzero(observed.any(axis=0))
    return int(rows[0]), int(cols[0]), int(rows[-1] - rows[0] + 1), int(cols[-1] - cols[0] + 1)


def layers_now(grid: TiledGrid) -> dict:
    """A copy of every tile's layers, by tile."""
    return {key: [layer.copy() for layer in grid.tile_arrays(key)] for key in grid.keys()}  # noqa: SIM118 - a TiledGrid


def changed_since(grid: TiledGrid, before: dict, key) -> list[np.ndarray]:
    """Of each layer (log-odds, variance, observed) of tile ``key``, the cells that differ from ``before``
    (:func:`layers_now`; a tile new since then against zeros), bool (T, T) each."""
    now = grid.tile_arrays(key)
    old = before.get(key, [np.zeros_like(layer) for layer in now])
    return [a != b for a, b in zip(now, old)]


def scans_of(posed, kind):
    scans = particle_scans(posed)
    if kind == "one pose":
        return [(ranges, samples[:1], np.ones(1)) for ranges, samples, _ in scans]
    return scans


@pytest.mark.parametrize("tile_size", (4, 32, 256))
@pytest.mark.parametrize("kind", ("samples", "one pose"))
@pytest.mark.parametrize("shard", (None, 0))
def test_a_fresh_grids_windows_are_the_observed_cells_bounding_boxes(particles, tile_size, kind, shard):
    owner = None if shard is None else owns_tile(shard, 2)
    for t, scan in enumerate(scans_of(particles, kind)[:3]):
        grid = TiledGrid(RES, tile_size=tile_size)
        result = MonteCarloFusion(grid, MODEL, *particles.single_geometry(), owner).fuse(*scan)
        assert len(result.windows) == len(result.tiles_changed) > 0, t
        for key, window in zip(result.tiles_changed, result.windows):
            assert window == observed_box(grid.tile_arrays(key)[2]), (t, key)


@pytest.mark.parametrize("parts", (1, 3))
def test_every_changed_cell_lies_in_its_tiles_window(particles, parts):
    """Scan after scan into one grid of 32-cell tiles (a scan in parts too): the cells whose log-odds, variance or
    observed changed lie inside the windows reported for their tiles, and no tile changed unreported."""
    grid = TiledGrid(RES, tile_size=32)
    fusion = MonteCarloFusion(grid, MODEL, *particles.single_geometry())
    scratches = [FusionScratch() for _ in range(parts)]
    for scan in particle_scans(particles):
        before = layers_now(grid)
        ready = fusion.prepare(scan)
        result = fusion.apply_parts([fusion.walk(ready, scratches[p], p, parts) for p in range(parts)])
        windows = dict(zip(result.tiles_changed, result.windows))
        for key in grid.keys():  # noqa: SIM118 - a TiledGrid, not a dict
            changed = np.logical_or.reduce(changed_since(grid, before, key))
            if not changed.any():
                continue
            row0, col0, rows, cols = windows[key]
            inside = np.zeros_like(changed)
            inside[row0 : row0 + rows, col0 : col0 + cols] = True
            assert not (changed & ~inside).any(), key


@pytest.mark.parametrize(
    ("tile_size", "kind", "parts", "shard"),
    [
        (256, "samples", 1, None),
        (256, "samples", 3, None),
        (256, "one pose", 1, None),
        (256, "samples", 3, 0),
        (4, "samples", 1, 0),
        (4, "one pose", 1, 0),
    ],
)
def test_a_grid_that_tracks_changes_marks_exactly_the_changed_cells(particles, tile_size, kind, parts, shard):
    """Scan after scan (mapping.grid's track_changes, as a shard's grid): the cells take_changes gives are exactly
    those whose log-odds, variance or observed changed since it was last called (by numpy, against copies), with
    their values, in the smallest window that holds them, and the map is bit for bit that of a grid that does not
    track them. Tiles of 4 cells take the one-sample pass's
    cell-by-cell apply, larger ones its block apply."""
    owner = None if shard is None else owns_tile(shard, 2)
    tracked, plain = TiledGrid(RES, tile_size, track_changes=True), TiledGrid(RES, tile_size)
    fusions = [MonteCarloFusion(grid, MODEL, *particles.single_geometry(), owner) for grid in (tracked, plain)]
    scratches = [FusionScratch() for _ in range(parts)]
    unchanged_but_updated = 0  # cells a scan updated that kept their values: marking every updated cell fails
    layer_only = 0  # given cells of which a layer kept its value: giving every layer of a given cell fails
    for t, scan in enumerate(scans_of(particles, kind)):
        before = layers_now(tracked)
        ready = fusions[0].prepare(scan)
        result = fusions[0].apply_parts([fusions[0].walk(ready, scratches[p], p, parts) for p in range(parts)])
        fusions[1].fuse(*scan)
        changed_cells = 0
        assert tracked.keys() == plain.keys()
        for key in tracked.keys():  # noqa: SIM118 - a TiledGrid, not a dict
            now = tracked.tile_arrays(key)
            differs = changed_since(tracked, before, key)
            changed = differs[0] | differs[1] | differs[2]
            cells = tracked.take_changes(key, (0, 0, tile_size, tile_size))
            taken = np.zeros_like(changed)
            if cells is not None:
                row0, col0, rows, cols = cells.window
                taken[row0 : row0 + rows, col0 : col0 + cols] = cells.given
                assert cells.given[[0, -1], :].any(axis=1).all() and cells.given[:, [0, -1]].any(axis=0).all()
                for layer, layer_cells, values, differ in zip(
                    now, (cells.logodds_cells, cells.variance_cells), (cells.logodds, cells.variance), differs
                ):
                    np.testing.assert_array_equal(layer_cells, differ[taken])
                    np.testing.assert_array_equal(values, layer[taken][layer_cells])
                np.testing.assert_array_equal(cells.observed, now[2][taken])
                layer_only += int((~cells.logodds_cells).sum() + (~cells.variance_cells).sum())
            assert (taken == changed).all(), (t, key)
            changed_cells += int(changed.sum())
            for a, b in zip(now, plain.tile_arrays(key)):
                np.testing.assert_array_equal(a, b)
        unchanged_but_updated += result.cells_updated - changed_cells
    assert unchanged_but_updated > 0 and layer_only > 0
    assert not tracked.changed.any()  # (taken, so cleared)


def test_taking_a_tiles_changed_cells_by_hand():
    """Three marks in a 4 x 4 tile, looked for in its lower 3 x 4 window: the 2 x 2 window that holds two of them,
    which of its cells they are, which changed their log-odds (cell (1, 2)) and which their variance (cell (2, 1)),
    those values and both cells' observed, in row-major order; the marks cleared, the mark outside the window left."""
    logodds = np.arange(16, dtype=np.float32).reshape(4, 4)
    variance, observed, changed = logodds / 2, logodds > 4, np.zeros((4, 4), np.uint8)
    changed[1, 2] = LOGODDS_CHANGED | OBSERVED_CHANGED
    changed[2, 1] = VARIANCE_CHANGED
    changed[0, 0] = ALL_CHANGED
    cells = take_changed_cells((logodds, variance, observed, changed), (1, 0, 3, 4))
    assert cells is not None and cells.window == (1, 1, 2, 2)
    assert cells.given.tolist() == [[False, True], [True, False]]
    assert cells.logodds_cells.tolist() == [True, False] and cells.logodds.tolist() == [6.0]
    assert cells.variance_cells.tolist() == [False, True] and cells.variance.tolist() == [4.5]
    assert cells.observed.tolist() == [True, True]
    assert np.flatnonzero(changed).tolist() == [0]
    assert take_changed_cells((logodds, variance, observed, changed), (1, 0, 3, 4)) is None
