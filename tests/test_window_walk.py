"""The one ray walk (mapping.window_walk.walk_ray) against the slow reference traversal: the cells it visits, the
phase it hands each to, and the tiles of another shard it leaves out."""

import math

import numba
import numpy as np
import pytest

from mapping.beam_model import BeamTable, beam_table
from mapping.sensor_model import SensorModel
from mapping.window_walk import Tiles, Window, ray_start, walk_ray
from reference import cells_on_ray
from worlds import ownership_pattern

RES = 0.1
WINDOW = Window(-64, -64, 128, 128)  # cells -64..63 a side: every ray below (origins within 1 m, 4 m long at most)
SHIFT = 3  # tiles of 8 cells: the window's tiles are tx, ty in -8..7
TX0 = TY0 = -8
#: any beam table: the test's visitors do not read the beam
BEAMS = tuple(beam_table(np.array([1.0]), SensorModel(resolution=RES), 0.05, 10.0))
FREE, NEAR = 0, 1


@numba.njit(inline="always")
def _visit_free(out, carry, ix, iy):  # pragma: no cover - compiled
    out[carry, 0], out[carry, 1], out[carry, 2] = ix, iy, FREE
    return carry + 1


@numba.njit(inline="always")
def _visit_near(out, beam, carry, ix, iy, r_in, r_out):  # pragma: no cover - compiled
    out[carry, 0], out[carry, 1], out[carry, 2] = ix, iy, NEAR
    return carry + 1


@numba.njit
def _walk(x0, y0, angle, stop, free_until, window, tiles, beams, out, jumps):  # pragma: no cover - compiled
    """(inside, visits): out[:visits] holds (ix, iy, FREE or NEAR) of each cell the walk hands to a visitor, the walk
    jumping over the other shards' tiles (jumps) or stepping through them."""
    inside, ray = ray_start(x0, y0, math.cos(angle), math.sin(angle), stop, RES, Window(*window))
    if not inside:
        return False, 0
    visits = walk_ray(
        ray, 0.0, free_until, stop, Tiles(*tiles), _visit_free, _visit_near, out, (BeamTable(*beams), 0), 0, jumps
    )
    return True, visits


def walked(x0, y0, angle, stop, free_until, owned, jumps=True):
    """The walk's visits [(ix, iy, phase)], the shard owning the tiles where ``owned`` (16 x 16 bool) is True."""
    out = np.zeros((4096, 3), np.int64)
    tiles = (owned, bool(owned.all()), SHIFT, TX0, TY0)
    inside, visits = _walk(x0, y0, angle, stop, free_until, tuple(WINDOW), tiles, BEAMS, out, jumps)
    assert inside
    return [tuple(row) for row in out[:visits].tolist()]


def expected(x0, y0, angle, stop, free_until, owned):
    """The reference's cells of the ray, in the shard's tiles, each FREE if it ends before free_until."""
    return [
        (ix, iy, FREE if r_out < free_until else NEAR)
        for ix, iy, _r_in, r_out in cells_on_ray(x0, y0, angle, stop, RES)
        if owned[(iy >> SHIFT) - TY0, (ix >> SHIFT) - TX0]
    ]


def random_rays(seed, count):
    """(x0, y0, angle, stop, free_until): origins within 1 m, lengths up to 4 m, free limits anywhere along them."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        stop = float(rng.uniform(0.05, 4.0))
        yield (*rng.uniform(-1.0, 1.0, 2).tolist(), float(rng.uniform(-math.pi, math.pi)), stop, stop * rng.random())


def test_every_tile_owned_visits_the_reference_cells_in_order_free_ones_first():
    owned = np.ones((16, 16), bool)
    for ray in random_rays(0, 300):
        visits = walked(*ray, owned)
        assert visits == expected(*ray, owned), ray
        phases = [phase for _, _, phase in visits]
        assert phases == sorted(phases), "the free phase comes first"


@pytest.mark.parametrize("jumps", [True, False])
@pytest.mark.parametrize("pattern", ["checkerboard", "stripes", "random"])
def test_a_shard_visits_the_cells_of_its_own_tiles_only(pattern, jumps):
    owned = ownership_pattern(pattern)
    for ray in random_rays(2, 300):
        assert walked(*ray, owned, jumps) == expected(*ray, owned), ray


def test_no_tile_owned_visits_nothing():
    owned = np.zeros((16, 16), bool)
    for ray in random_rays(3, 50):
        assert walked(*ray, owned) == [] and walked(*ray, owned, False) == []


def test_a_ray_leaving_the_window_is_not_walked():
    out = np.zeros((4096, 3), np.int64)
    tiles = (np.ones((16, 16), bool), True, SHIFT, TX0, TY0)
    # from (6.3 m, 0): its start cell 63 is the window's last column, with no cell to spare
    assert _walk(6.3, 0.0, 0.3, 1.0, 0.5, tuple(WINDOW), tiles, BEAMS, out, True) == (False, 0)
