"""The simulator: ray casting, grid traversal, truth raster, landmark sensing and reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.angles import wrap_angle
from slam.motion import OdometryMotionModel, VelocityMotionModel, odometry_controls
from slam.range_bearing import RangeBearingModel
from slam.raster import mark_segments, raster_frame
from slam.raycast import cast_rays, segments_block
from slam.simulator import simulate_office
from slam.world import office_landmarks, office_segments


@pytest.fixture(scope="module")
def run():
    return simulate_office(seed=3, steps=120, n_beams=91)


# ------------------------------------------------------------------------------------------- ray casting


def test_cast_rays_by_hand():
    walls = np.array([[5.0, -1.0, 5.0, 1.0], [2.0, 3.0, 2.0, 4.0]])
    origins = np.zeros((4, 2))
    angles = np.array([0.0, math.pi, math.pi / 2, math.atan2(3.5, 2.0)])
    ranges = cast_rays(origins, angles, walls, max_range=20.0)
    assert ranges[0] == pytest.approx(5.0)
    assert ranges[1] == np.inf  # nothing behind
    assert ranges[2] == np.inf  # parallel to both walls' extension, misses
    assert ranges[3] == pytest.approx(math.hypot(2.0, 3.5))
    assert cast_rays(origins[:1], angles[:1], walls, max_range=4.0)[0] == np.inf  # beyond range


def test_segments_block_ignores_touching_at_the_end():
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    starts = np.zeros((3, 2))
    ends = np.array([[2.0, 0.0], [1.0, 0.0], [0.5, 0.0]])
    np.testing.assert_array_equal(segments_block(starts, ends, wall), [True, False, False])


# ------------------------------------------------------------------------------------------- grid traversal


def _cells_crossed_reference(start, end, origin, resolution, shape):
    """Slow reference: every cell whose open interior the segment meets (Liang-Barsky clipping per cell)."""
    out = np.zeros(shape, dtype=bool)
    d = end - start
    for i in range(shape[0]):
        for j in range(shape[1]):
            low = origin + resolution * np.array([j, i])
            high = low + resolution
            t0, t1 = 0.0, 1.0
            for k in range(2):
                if d[k] == 0:
                    if not low[k] < start[k] < high[k]:
                        t0, t1 = 1.0, 0.0
                    continue
                with np.errstate(over="ignore"):  # a subnormal d gives +-inf, which the clipping handles
                    a, b = (low[k] - start[k]) / d[k], (high[k] - start[k]) / d[k]
                t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
            out[i, j] = t1 > t0
    return out


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-0.45, 1.45), min_size=4, max_size=4))
def test_traversal_matches_reference(coords):
    # an origin off round numbers, so that the simple values hypothesis tries do not sit on cell borders
    start, end = np.array(coords[:2]), np.array(coords[2:])
    origin, resolution, shape = np.array([-0.5123, -0.4871]), 0.1, (20, 20)
    grid = np.zeros(shape, dtype=bool)
    mark_segments(grid, start[None], end[None], origin, resolution)
    expected = _cells_crossed_reference(start, end, origin, resolution, shape)
    if np.array_equal(start, end):
        j, i = np.floor((start - origin) / resolution).astype(int)
        expected[i, j] = True
    np.testing.assert_array_equal(grid, expected)


def test_traversal_by_hand():
    grid = np.zeros((3, 4), dtype=bool)
    # from the centre of cell (row 0, col 0) to the centre of cell (row 2, col 3) of a 1 m grid
    mark_segments(grid, np.array([[0.5, 0.5]]), np.array([[3.5, 2.5]]), np.zeros(2), 1.0)
    expected = np.array([[1, 1, 0, 0], [0, 1, 1, 0], [0, 0, 1, 1]], dtype=bool)
    np.testing.assert_array_equal(grid, expected)


def test_raster_frame_puts_round_walls_mid_cell():
    origin, (height, width) = raster_frame(np.array([[0.0, 0.0, 20.0, 12.0]]), 0.05)
    assert ((0.0 - origin[0]) / 0.05) % 1 == pytest.approx(0.5)
    assert origin[0] + width * 0.05 >= 21.0 and origin[1] + height * 0.05 >= 13.0


# ------------------------------------------------------------------------------------------- simulated run


def test_same_seed_same_run_other_seed_other_run():
    a = simulate_office(seed=7, steps=30, n_beams=11)
    b = simulate_office(seed=7, steps=30, n_beams=11)
    c = simulate_office(seed=8, steps=30, n_beams=11)
    for name in ("true_poses", "commands", "odometry", "landmark_z", "ranges", "truth_visible"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.true_poses, c.true_poses)
    assert not np.array_equal(a.ranges, c.ranges)


def test_run_shapes_and_contract(run):
    steps = 120
    assert run.ranges.dtype == np.float32 and run.ranges.shape == (steps, 91)
    np.testing.assert_allclose(run.stamps, 0.1 * np.arange(steps))
    assert run.angle_min == pytest.approx(-math.pi / 2)
    assert run.angle_increment == pytest.approx(math.pi / 90)
    assert run.truth_occupied.shape == run.truth_visible.shape
    assert run.segments.shape[1] == 4 and run.landmarks.shape[1] == 2
    np.testing.assert_allclose(run.true_poses[0], (1.5, 6.0, 0.0))
    assert np.all(np.diff(run.landmark_step) >= 0)


def test_noise_free_laser_ends_on_obstacles_and_inside_the_visible_raster():
    clean = simulate_office(seed=1, steps=40, n_beams=37, laser_sigma=0.0)
    pose = clean.true_poses[25]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    sensor = pose[:2] + np.array([c * clean.sensor_offset[0], s * clean.sensor_offset[0]])
    angles = pose[2] + clean.angle_min + clean.angle_increment * np.arange(37)
    ranges = clean.ranges[25].astype(np.float64)
    hit = np.isfinite(ranges)
    assert hit.sum() > 30  # an office: nearly every beam hits something within 12 m
    ends = sensor + ranges[hit, None] * np.column_stack([np.cos(angles[hit]), np.sin(angles[hit])])
    # every end point lies on some obstacle edge (distance to the nearest segment below float32 rounding)
    a, b = clean.segments[:, :2], clean.segments[:, 2:]
    t = np.clip(np.einsum("rsk,sk->rs", ends[:, None] - a, b - a) / np.sum((b - a) ** 2, axis=1), 0, 1)
    nearest = np.min(np.linalg.norm(ends[:, None] - (a + t[..., None] * (b - a)), axis=2), axis=1)
    assert nearest.max() < 1e-4
    # the hit cells are visible and occupied
    cells = np.floor((ends - clean.truth_origin) / clean.truth_resolution).astype(int)
    assert clean.truth_visible[cells[:, 1], cells[:, 0]].all()
    assert clean.truth_occupied[cells[:, 1], cells[:, 0]].mean() > 0.95


def test_occupied_raster_covers_every_wall_point():
    run = simulate_office(seed=0, steps=2, n_beams=3)
    rng = np.random.default_rng(0)
    seg = run.segments[rng.integers(0, len(run.segments), 500)]
    u = rng.uniform(0, 1, 500)[:, None]
    points = seg[:, :2] + u * (seg[:, 2:] - seg[:, :2])
    cells = np.floor((points - run.truth_origin) / run.truth_resolution).astype(int)
    assert run.truth_occupied[cells[:, 1], cells[:, 0]].all()
    # and the free middle of the corridor is not occupied
    free = np.floor((np.array([[5.0, 6.0], [12.0, 6.2]]) - run.truth_origin) / run.truth_resolution).astype(int)
    assert not run.truth_occupied[free[:, 1], free[:, 0]].any()


def test_landmark_measurements_respect_range_fov_and_noise():
    sensor = RangeBearingModel(sigma_range=0.1, sigma_bearing=0.03)
    run = simulate_office(seed=2, steps=150, n_beams=3, sensor=sensor)
    pose = run.true_poses[run.landmark_step]
    landmark = run.landmarks[run.landmark_id]
    true_r = np.hypot(*(landmark - pose[:, :2]).T)
    true_b = wrap_angle(np.arctan2(landmark[:, 1] - pose[:, 1], landmark[:, 0] - pose[:, 0]) - pose[:, 2])
    assert true_r.max() <= 6.0 and np.abs(true_b).max() <= math.pi / 2
    assert not segments_block(pose[:, :2], landmark, run.segments).any()
    err_r = run.landmark_z[:, 0] - true_r
    err_b = wrap_angle(run.landmark_z[:, 1] - true_b)
    n = len(err_r)
    assert n > 300
    # sample standard deviations within 15% of the configured noise, means within 4 standard errors
    assert err_r.std() == pytest.approx(0.1, rel=0.15) and err_b.std() == pytest.approx(0.03, rel=0.15)
    assert abs(err_r.mean()) < 4 * 0.1 / math.sqrt(n) and abs(err_b.mean()) < 4 * 0.03 / math.sqrt(n)


def test_no_noise_run_follows_its_commands_and_odometry():
    run = simulate_office(
        seed=4,
        steps=80,
        n_beams=3,
        velocity_model=VelocityMotionModel(alphas=(0.0,) * 6),
        odometry_model=OdometryMotionModel(alphas=(0.0,) * 4),
    )
    model = VelocityMotionModel()
    for t in range(1, 80):
        moved = model.predict(run.true_poses[t - 1 : t], np.array([*run.commands[t], 0.1]))
        np.testing.assert_allclose(moved[0], run.true_poses[t], atol=1e-9)
    np.testing.assert_allclose(odometry_controls(run.odometry), odometry_controls(run.true_poses), atol=1e-9)


def test_office_layout():
    segments = office_segments()
    landmarks = office_landmarks()
    assert segments[:, [0, 2]].min() == 0 and segments[:, [0, 2]].max() == 20
    assert segments[:, [1, 3]].min() == 0 and segments[:, [1, 3]].max() == 12
    gaps = np.linalg.norm(landmarks[:, None] - landmarks[None], axis=2) + 100 * np.eye(len(landmarks))
    assert gaps.min() > 1.0


def test_a_ray_through_a_segments_end_point_hits_it():
    # the ray along +x from (0, 0) meets the segment (1, -1)-(1, 0) exactly at its end b: u = 1, t = 1
    segments = np.array([[1.0, -1.0, 1.0, 0.0]])
    assert cast_rays(np.zeros((1, 2)), np.array([0.0]), segments, 5.0).tolist() == [1.0]
    # and at its start a: u = 0
    segments = np.array([[1.0, 0.0, 1.0, 1.0]])
    assert cast_rays(np.zeros((1, 2)), np.array([0.0]), segments, 5.0).tolist() == [1.0]


def test_a_hit_exactly_at_max_range_counts_and_one_beyond_does_not():
    segments = np.array([[2.0, -1.0, 2.0, 1.0]])
    origins = np.zeros((2, 2))
    assert cast_rays(origins, np.array([0.0, 0.0]), segments, 2.0).tolist() == [2.0, 2.0]
    assert cast_rays(origins, np.array([0.0, math.pi]), segments, 1.5).tolist() == [math.inf, math.inf]


def test_sight_lines_touching_a_wall_at_an_end_are_not_blocked():
    wall = np.array([[1.0, -1.0, 1.0, 1.0]])
    starts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    ends = np.array([[1.0, 0.0], [2.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    # ends on the wall; starts on the wall; crosses it mid-wall; crosses the wall's end point (1, 1)
    assert segments_block(starts, ends, wall).tolist() == [False, False, True, True]
