"""FastSLAM's gauge-preserving resampling (slam.gauge, slam.fastslam): rigid alignment against brute force, the
weights' blindness to the gauge, and resampling that keeps the set of gauges while copying shapes."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from slam.fastslam import FastSLAM
from slam.gauge import map_gauges, regauge_points
from slam.motion import VelocityMotionModel
from slam.range_bearing import RangeBearingModel

MOTION = VelocityMotionModel(alphas=(0.05, 0.01, 0.05, 0.05, 0.0, 0.0))
SENSOR = RangeBearingModel(0.05, 0.02)
BASE_MAP = np.array([[2.0, 1.0], [3.0, -1.5], [-1.0, 2.5]])
BASE_POSE = np.array([0.3, -0.2, 0.4])


def rotations(theta: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 2, 2) by the angles theta (N,) rad: the tests' reference for the turns slam.gauge
    writes out."""
    c, s = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -s], axis=-1), np.stack([s, c], axis=-1)], axis=-2)


def test_map_gauges_recover_exact_motions():
    # map 0 is the reference (all the weight); map n is it turned by theta[n] about its centroid, moved to centre[n]
    rng = np.random.default_rng(0)
    reference = rng.uniform(-5, 5, (6, 2))
    theta = np.concatenate([[0.0], rng.uniform(-np.pi, np.pi, 49)])
    centre = np.concatenate([reference.mean(axis=0, keepdims=True), rng.uniform(-3, 3, (49, 2))])
    maps = np.einsum("nij,lj->nli", rotations(theta), reference - reference.mean(axis=0)) + centre[:, None, :]
    weights = np.zeros(50)
    weights[0] = 1.0
    turn, centroid = map_gauges(maps, weights)
    np.testing.assert_allclose(np.angle(np.exp(1j * (turn - theta))), 0.0, atol=1e-12)
    np.testing.assert_allclose(centroid, centre, atol=1e-12)


def test_map_gauges_turn_is_the_least_squares_rotation_on_noisy_maps():
    # brute force on a 0.0001 rad grid: turn the weighted mean map about its centroid, put the centroid on the
    # map's, and find the angle of least squared residual; the closed form must sit at that minimum
    rng = np.random.default_rng(1)
    reference = rng.uniform(-5, 5, (5, 2))
    maps = np.einsum("nij,lj->nli", rotations(np.array([0.3, -2.0, 1.0])), reference) + rng.normal(0, 0.4, (3, 5, 2))
    weights = np.array([0.2, 0.5, 0.3])
    turn, centroid = map_gauges(maps, weights)
    mean_map = np.einsum("n,nli->li", weights, maps)
    grid = np.arange(-np.pi, np.pi, 1e-4)
    turned = np.einsum("gij,lj->gli", rotations(grid), mean_map - mean_map.mean(axis=0))
    for n in range(3):
        np.testing.assert_allclose(centroid[n], maps[n].mean(axis=0), atol=1e-12)
        cost = np.sum((maps[n] - centroid[n] - turned) ** 2, axis=(1, 2))
        assert abs(np.angle(np.exp(1j * (turn[n] - grid[np.argmin(cost)])))) <= 1e-4


def test_regauge_points_by_hand():
    # turn by 90 degrees about shift_from = (1, 0), then put that point at (5, 5): (2, 0) -> (5, 6)
    moved = regauge_points(
        np.array([[[2.0, 0.0], [1.0, 0.0]]]), np.array([np.pi / 2]), np.array([[1.0, 0.0]]), np.array([[5.0, 5.0]])
    )
    np.testing.assert_allclose(moved, [[[5.0, 6.0], [5.0, 5.0]]], atol=1e-12)


def _filter(n_particles: int, preserve_gauge: bool = True) -> FastSLAM:
    """A FastSLAM 1.0 whose particles hold three mapped landmarks (ids 0-2), from one measurement each."""
    slam = FastSLAM(
        MOTION, SENSOR, np.zeros(3), n_particles=n_particles, version=1, seed=5, preserve_gauge=preserve_gauge
    )
    slam.update(np.array([[2.2, 0.5], [3.3, -0.4], [2.7, 2.0]]), np.array([0, 1, 2]))
    return slam


def _set_gauges(slam: FastSLAM, theta: np.ndarray, shift: np.ndarray) -> None:
    """Particle n holds BASE_MAP and BASE_POSE moved by R(theta[n]) x + shift[n]."""
    slam.mu[:, :3] = np.einsum("nij,lj->nli", rotations(theta), BASE_MAP) + shift[:, None, :]
    slam.poses[:, :2] = np.einsum("nij,j->ni", rotations(theta), BASE_POSE[:2]) + shift
    slam.poses[:, 2] = BASE_POSE[2] + theta


def test_weights_and_landmark_updates_do_not_see_the_gauge():
    # the premise of gauge-preserving resampling: moving a particle's pose and map together by a rigid motion
    # changes neither its measurement likelihood nor, up to that motion, its landmark update
    slam = _filter(4)
    slam.poses[:] = [[0.1, 0.0, 0.05], [-0.1, 0.1, -0.03], [0.0, -0.1, 0.02], [0.05, 0.05, 0.0]]
    moved = copy.deepcopy(slam)
    turn = np.array([0.3, -1.0, 2.0, 0.0])
    shift_from, shift_to = np.zeros((4, 2)), np.array([[1.0, 2.0], [-3.0, 0.0], [0.0, 5.0], [0.0, 0.0]])
    moved._regauge(turn, shift_from, shift_to)
    z, ids = np.array([[2.0, 0.45], [3.4, -0.35]]), np.array([0, 1])
    before_w, moved_w = slam.log_w.copy(), moved.log_w.copy()
    slam.update(z, ids)
    moved.update(z, ids)
    np.testing.assert_allclose(moved.log_w - moved_w, slam.log_w - before_w, atol=1e-9)
    np.testing.assert_allclose(moved.mu[:, :3], regauge_points(slam.mu[:, :3], turn, shift_from, shift_to), atol=1e-9)
    np.testing.assert_allclose(
        moved.sigma[:, :3],
        rotations(turn)[:, None] @ slam.sigma[:, :3] @ np.swapaxes(rotations(turn), 1, 2)[:, None],
        atol=1e-12,
    )


@pytest.mark.parametrize("preserve_gauge", [True, False])
def test_resampling_copies_the_shape_and_keeps_every_gauge(preserve_gauge):
    # six particles share one shape (BASE_MAP with BASE_POSE) in six gauges; all weight on particle 2 forces a
    # resampling. Plain resampling: six copies of particle 2. Gauge-preserving: particle 2's shape in each of
    # the six gauges once, so the cloud keeps its spread in the world frame.
    n = 6
    slam = _filter(n, preserve_gauge)
    theta = np.array([-0.3, -0.1, 0.0, 0.05, 0.2, 0.4])
    shift = np.array([[0.0, 0.0], [0.5, -0.2], [-0.4, 0.1], [0.2, 0.3], [-0.1, -0.5], [0.3, 0.6]])
    _set_gauges(slam, theta, shift)
    before_mu, before_poses = slam.mu[:, :3].copy(), slam.poses.copy()
    weights = np.zeros(n)
    weights[2] = 1.0
    slam.resample_if_degenerate(weights)
    assert slam.resamplings == 1
    if not preserve_gauge:
        np.testing.assert_array_equal(slam.mu[:, :3], np.repeat(before_mu[2:3], n, axis=0))
        np.testing.assert_array_equal(slam.poses, np.repeat(before_poses[2:3], n, axis=0))
        return
    # each offspring holds exactly one of the original maps, each map once, and the pose that goes with it
    distance = np.abs(slam.mu[:, None, :3] - before_mu[None]).max(axis=(2, 3))
    match = np.argmin(distance, axis=1)
    np.testing.assert_array_equal(np.sort(match), np.arange(n))
    assert distance[np.arange(n), match].max() < 1e-12
    np.testing.assert_allclose(slam.poses[:, :2], before_poses[match, :2], atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (slam.poses[:, 2] - before_poses[match, 2]))), 0.0, atol=1e-12)


def test_unknown_correspondences_resample_plainly():
    # per-particle landmark slots hold different landmarks, so maps cannot be aligned slot by slot
    slam = FastSLAM(MOTION, SENSOR, np.zeros(3), n_particles=3, version=1, seed=0, known_correspondences=False)
    assert not slam.preserve_gauge
