"""mapping.grid's tiled map: the raster crop, parameter and layer checks and summaries, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.errors import InputError
from mapping.grid import TiledGrid


def _tile(size, cells):
    """Layers of one tile with the given {(row, col): logodds} observed."""
    logodds = np.zeros((size, size), np.float32)
    observed = np.zeros((size, size), bool)
    for (r, c), value in cells.items():
        logodds[r, c] = value
        observed[r, c] = True
    return logodds, np.zeros((size, size), np.float32), observed


def test_rasterize_crops_to_the_observed_cells_by_hand():
    """Tile (1, -1) of 4 x 4 cells of 0.5 m holds global cells ix 4..7, iy -4..-1. Observed: tile row 1, col 2
    (ix 6, iy -3) and tile row 3, col 3 (ix 7, iy -1): the raster is 3 rows x 2 columns from (3.0 m, -1.5 m)."""
    grid = TiledGrid(0.5, tile_size=4)
    grid.set_tile((1, -1), *_tile(4, {(1, 2): 1.5, (3, 3): -2.0}))
    raster = grid.rasterize()
    assert raster["logodds"].shape == raster["observed"].shape == raster["variance"].shape == (3, 2)
    np.testing.assert_array_equal(raster["observed"], [[True, False], [False, False], [False, True]])
    np.testing.assert_array_equal(raster["logodds"], np.array([[1.5, 0.0], [0.0, 0.0], [0.0, -2.0]], np.float32))
    np.testing.assert_allclose(raster["origin"], [3.0, -1.5])
    np.testing.assert_allclose(raster["probability"], 1 / (1 + np.exp(-raster["logodds"].astype(float))), rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(resolution=0.0), "resolution must be > 0"),
        (dict(resolution=float("nan")), "resolution must be > 0"),
        (dict(tile_size=3), "power of two"),
        (dict(tile_size=0), "power of two"),
    ],
)
def test_bad_grid_parameters_are_refused(kwargs, message):
    with pytest.raises(InputError, match=message):
        TiledGrid(**kwargs)


@pytest.mark.parametrize("shape", [(4, 5), (1, 4), ()])
def test_set_tile_refuses_layers_of_another_shape(shape):
    """A scalar or a (1, 4) row would broadcast over the tile silently."""
    grid = TiledGrid(0.5, tile_size=4)
    layers = list(_tile(4, {}))
    layers[2] = np.ones(shape, bool)
    with pytest.raises(InputError, match="'observed' must have shape"):
        grid.set_tile((0, 0), *layers)
    assert grid.keys() == []


def test_summaries_count_bytes_and_observed_cells():
    """Two 4 x 4 tiles: 16 cells x 9 bytes each; three observed cells."""
    grid = TiledGrid(0.5, tile_size=4)
    grid.set_tile((0, 0), *_tile(4, {(0, 0): 1.0, (2, 3): 1.0}))
    grid.set_tile((5, 0), *_tile(4, {(1, 1): -1.0}))
    assert grid.nbytes == 2 * 16 * 9
    assert grid.observed_cells() == 3
    assert grid.tile_origin((5, -2)) == (10.0, -4.0)
