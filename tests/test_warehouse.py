"""The simulated warehouse (slam.warehouse): seeded layout, lidar geometry, a route in free space, a truth raster
that agrees with the simulated ranges; and shards fusing its scans join to the whole map bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from slam.raycast import cast_rays
from slam.warehouse import ROUTE, simulate_warehouse, warehouse_world

STEPS = 6


@pytest.fixture(scope="module")
def run():
    return simulate_warehouse(seed=5, steps=STEPS)


def _point_segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance (P, S) in m from each point (P, 2) to each segment (S, 4)."""
    a, b = segments[None, :, :2], segments[None, :, 2:]
    e = b - a
    u = np.clip(((points[:, None, :] - a) * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
    return np.hypot(*(points[:, None, :] - a - u[..., None] * e).transpose(2, 0, 1))


def _point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance (P,) in m from each point (P, 2) to the nearest segment (S, 4)."""
    return _point_segment_distances(points, segments).min(axis=1)


def _nearest_segment(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Index (P,) of the segment (S, 4) nearest to each point (P, 2)."""
    return _point_segment_distances(points, segments).argmin(axis=1)


def test_the_layout_is_seeded():
    a, b, c = warehouse_world(3), warehouse_world(3), warehouse_world(4)
    np.testing.assert_array_equal(a.segments, b.segments)
    assert a.segments.shape != c.segments.shape or not np.array_equal(a.segments, c.segments)


def test_the_run_is_seeded(run):
    again = simulate_warehouse(seed=5, steps=STEPS)
    np.testing.assert_array_equal(run.ranges, again.ranges)
    np.testing.assert_array_equal(run.true_poses, again.true_poses)
    assert not np.array_equal(simulate_warehouse(seed=6, steps=STEPS).ranges, run.ranges)


def test_hall_size_and_lidar_geometry(run):
    """A 100 m x 100 m hall; 1081 beams over 270 deg from -3 pi / 4, 0.25 deg apart, to 30 m, at 40 Hz."""
    xs, ys = run.segments[:, [0, 2]], run.segments[:, [1, 3]]
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (0.0, 100.0, 0.0, 100.0)
    assert run.ranges.shape == (STEPS, 1081)
    assert run.angle_min == pytest.approx(-3 * math.pi / 4)
    assert run.angle_increment == pytest.approx(math.radians(0.25))
    assert run.angle_min + 1080 * run.angle_increment == pytest.approx(3 * math.pi / 4)
    assert run.range_max == 30.0
    np.testing.assert_allclose(np.diff(run.stamps), 0.025)
    assert run.truth_resolution == 0.05


def test_racks_make_aisles_and_the_route_runs_through_free_space():
    """The route keeps more than 1 m from every obstacle edge all along, and racks stand within 3 m of it on both
    sides somewhere (an aisle)."""
    world = warehouse_world(0)
    route = np.array(ROUTE)
    legs = zip(route, np.roll(route, -1, axis=0))
    points = np.concatenate([a + np.linspace(0, 1, 200)[:, None] * (b - a) for a, b in legs])
    assert _point_segment_distance(points, world.segments).min() > 1.0
    aisle = np.array([[25.75 + 10.0, 39.5]])  # between two racks of the west block
    above, below = aisle + [0.0, 3.0], aisle - [0.0, 3.0]
    for side in (above, below):
        assert _point_segment_distance(np.vstack([aisle, side]), world.segments).min() < 1.6


def _first_occupied(run, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Along each ray (origins (R, 2) m, unit directions (R, 2)), sampled every fifth of a cell: the range (m) of the
    first sample in an occupied cell of the run's truth raster, and that sample (R, 2) m."""
    res = run.truth_resolution
    steps = np.arange(0.0, run.range_max + 2 * res, res / 5)
    points = origins[:, None, :] + steps[None, :, None] * directions[:, None, :]
    cells = np.floor((points - run.truth_origin) / res).astype(int)
    height, width = run.truth_occupied.shape
    occupied = run.truth_occupied[cells[..., 1].clip(0, height - 1), cells[..., 0].clip(0, width - 1)]
    assert occupied.any(axis=1).all()
    first = occupied.argmax(axis=1)
    return steps[first], points[np.arange(len(first)), first]


def test_truth_raster_agrees_with_the_ranges(run):
    """For every beam with a return, cast into the truth raster: its first occupied cell lies no farther than a cell
    (diagonal) past the noise-free range, and no nearer than a cell across the wall it hits (a cell diagonal over the
    sine of the angle of incidence) but where the ray grazes another obstacle within a cell (a few per cent), and
    wherever it lies an obstacle edge passes within a cell diagonal of the point the ray enters it at. The return's
    cell is visible; the simulated ranges are the noise-free ones with the laser's noise (sigma 0.01 m)."""
    res, diagonal = run.truth_resolution, run.truth_resolution * math.sqrt(2)
    angles = run.angle_min + run.angle_increment * np.arange(run.ranges.shape[1])
    scans = [0, STEPS - 1]
    pose = run.true_poses[scans]
    sensor = pose[:, :2] + run.sensor_offset[0] * np.column_stack([np.cos(pose[:, 2]), np.sin(pose[:, 2])])
    origins = np.repeat(sensor, len(angles), axis=0)
    headings = (pose[:, 2:3] + angles[None, :]).ravel()
    exact = cast_rays(origins, headings, run.segments, run.range_max)
    hit = np.isfinite(exact)
    origins, headings, exact = origins[hit], headings[hit], exact[hit]
    np.testing.assert_allclose(run.ranges[scans].ravel()[hit], exact, atol=6 * 0.01)
    directions = np.column_stack([np.cos(headings), np.sin(headings)])
    ends = origins + exact[:, None] * directions
    first, entry = _first_occupied(run, origins, directions)
    assert (first <= exact + diagonal).all()
    assert _point_segment_distance(entry, run.segments).max() <= diagonal + res / 5
    walls = run.segments[_nearest_segment(ends, run.segments)]
    along = walls[:, 2:] - walls[:, :2]
    incidence = np.abs(directions[:, 0] * along[:, 1] - directions[:, 1] * along[:, 0]) / np.hypot(*along.T)
    assert (first < exact - diagonal / incidence).mean() < 0.03
    end_cells = np.floor((ends - run.truth_origin) / res).astype(int)
    assert run.truth_visible[end_cells[:, 1], end_cells[:, 0]].all()


def _whole_and_shards(
    scans, tile_size: int, shards: int, geometry, model: SensorModel | None = None
) -> tuple[TiledGrid, list[TiledGrid]]:
    """The grid of ``scans`` ((ranges, samples, weights) each) fused whole, and the grids of ``shards`` fusions that
    each own the tiles (tx, ty) with (7 tx + 13 ty) mod shards == their index (``model``: 0.05 m cells, else the
    default)."""
    model = model or SensorModel(resolution=0.05)
    whole = TiledGrid(0.05, tile_size=tile_size)
    grids = [whole] + [TiledGrid(0.05, tile_size=tile_size) for _ in range(shards)]
    owners = [None] + [lambda tx, ty, s=s: (7 * tx + 13 * ty) % shards == s for s in range(shards)]
    for grid, owner in zip(grids, owners):
        fusion = MonteCarloFusion(grid, model, *geometry, owns_tile=owner)
        for scan in scans:
            fusion.fuse(*scan)
    return whole, grids[1:]


def _assert_shards_join_to(whole: TiledGrid, parts: list[TiledGrid]) -> None:
    """Every tile of the whole grid is in exactly one shard's grid, the same bit for bit, and no shard has more."""
    keys = [key for part in parts for key in part.keys()]  # noqa: SIM118  # a TiledGrid, not a dict: it has no __iter__
    assert sorted(keys) == sorted(whole.keys())
    for part in parts:
        for key in part.keys():  # noqa: SIM118
            for mine, theirs in zip(part.tile_arrays(key), whole.tile_arrays(key)):
                np.testing.assert_array_equal(mine, theirs)


@pytest.mark.parametrize(("tile_size", "shards"), [(64, 2), (32, 3)])
def test_shards_fusing_warehouse_scans_join_to_the_whole_map(run, tile_size, shards):
    """30 m rays over many tiles, 20 particles: a shard marks the free space as runs in its own tiles only and
    skips the rays that reach none; joined, the shards' maps are the whole map, every layer bit for bit."""
    rng = np.random.default_rng(2)
    scans = [
        (run.ranges[t], run.true_poses[t] + rng.normal(0, [0.1, 0.1, 0.02], (20, 3)), np.full(20, 1 / 20))
        for t in (0, STEPS - 1)
    ]
    angles = run.angle_min + run.angle_increment * np.arange(run.ranges.shape[1])
    geometry = (angles, run.range_min, run.range_max, run.sensor_offset)
    _assert_shards_join_to(*_whole_and_shards(scans, tile_size, shards, geometry))


def test_a_ray_starting_on_a_tile_corner_reaches_the_shard_beyond():
    """A laser at (-0.5, -0.2), on a corner of 4-cell tiles, heading -3 pi / 2: its beam at pi / 2 runs along -x with
    dy = -1.2e-16, so the ray leaves the row above the corner at once and all its cells lie in the tile below; the
    shard of that tile must walk it, though the ray's start and end points both lie in the row above (its end, at
    0.079 m, lies less than half a unit in the last place of y below the corner; a bound taken from the two points'
    cells alone skipped the ray there). A second pose elsewhere."""
    samples = np.array([[-0.5, -0.2, -6 * math.pi / 4], [0.3, 0.4, 0.1]])
    scan = (np.array([0.079]), samples, np.array([0.5, 0.5]))
    model = SensorModel(resolution=0.05, sigma="stereo", baseline_focal=50.0)  # sigma 0.1 mm at 0.079 m
    geometry = (np.array([math.pi / 2]), 0.05, 10.0, (0.0, 0.0, 0.0))
    whole, shards = _whole_and_shards([scan], 4, 2, geometry, model)
    assert (-3, -2) in whole  # the tile below the corner, left of it
    _assert_shards_join_to(whole, shards)
