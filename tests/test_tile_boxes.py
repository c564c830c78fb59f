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
        before = {key: [layer.copy() for layer in grid.tile_arrays(key)] for key in grid.keys()}  # noqa: SIM118 - a TiledGrid, not a dict
        ready = fusion.prepare(scan)
        result = fusion.apply_parts([fusion.walk(ready, scratches[p], p, parts) for p in range(parts)])
        windows = dict(zip(result.tiles_changed, result.windows))
        for key in grid.keys():  # noqa: SIM118 - a TiledGrid, not a dict
            now = grid.tile_arrays(key)
            old = before.get(key, [np.zeros_like(layer) for layer in now])
            changed = np.zeros(now[0].shape, bool)
            for a, b in zip(now, old):
                changed |= a != b
            if not changed.any():
                continue
            row0, col0, rows, cols = windows[key]
            inside = np.zeros_like(changed)
            inside[row0 : row0 + rows, col0 : col0 + cols] = True
            assert not (changed & ~inside).any(), key
