"""slam.posegraph: the pose graph's least-squares solution against hand-solved graphs, and its Jacobians by
recovering exactly the poses behind consistent edges."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slam.angles import wrap_angle
from slam.posegraph import PoseGraph, apply_transform, transform_between
from slam.relations import relative_motion


def test_a_line_of_three_poses_takes_the_least_squares_compromise():
    """0 -> 1 and 1 -> 2 measure 1 m each, 0 -> 2 measures 2.3 m, all with the same information. With x0 = 0 held,
    (x1 - 1)^2 + (x2 - x1 - 1)^2 + (x2 - 2.3)^2 is least at x1 = 1.1, x2 = 2.2 (by hand: its gradient is 0 where
    2 x1 = x2 and 2 x2 - x1 = 3.3)."""
    graph = PoseGraph()
    for x in (0.0, 1.0, 2.0):
        graph.add_node(np.array([x, 0.0, 0.0]))
    cov = np.diag([0.01, 0.01, 0.001])
    graph.add_edge(0, 1, np.array([1.0, 0.0, 0.0]), cov)
    graph.add_edge(1, 2, np.array([1.0, 0.0, 0.0]), cov)
    graph.add_edge(0, 2, np.array([2.3, 0.0, 0.0]), cov)
    graph.optimize()
    assert graph.poses[:, 0] == pytest.approx([0.0, 1.1, 2.2], abs=1e-9)
    assert graph.poses[:, 1:] == pytest.approx(np.zeros((3, 2)), abs=1e-9)
    # each residual is 0.1 m; chi2 = 0.1^2 / 0.01 = 1 per edge
    assert graph.chi2() == pytest.approx([1.0, 1.0, 1.0], abs=1e-9)


def test_a_weaker_edge_gives_way():
    """The same line with the long edge 100 times less certain: x2 stays near the chained 2 m
    (by hand, weights 1, 1 and 1/100: the gradient is 0 where x2 = 2 x1 and 101 x2 - 100 x1 = 102.3, so
    x1 = 1 + 0.15 / 51, x2 = 2 + 0.3 / 51)."""
    graph = PoseGraph()
    for x in (0.0, 1.0, 2.0):
        graph.add_node(np.array([x, 0.0, 0.0]))
    graph.add_edge(0, 1, np.array([1.0, 0.0, 0.0]), np.diag([0.01, 0.01, 0.001]))
    graph.add_edge(1, 2, np.array([1.0, 0.0, 0.0]), np.diag([0.01, 0.01, 0.001]))
    graph.add_edge(0, 2, np.array([2.3, 0.0, 0.0]), np.diag([1.0, 1.0, 0.1]))
    graph.optimize()
    assert graph.poses[:, 0] == pytest.approx([0.0, 1.0 + 0.15 / 51, 2.0 + 0.3 / 51], abs=1e-9)


pose = st.tuples(
    st.floats(-20, 20, allow_nan=False), st.floats(-20, 20, allow_nan=False), st.floats(-3.1, 3.1, allow_nan=False)
)


@settings(max_examples=30, deadline=None)
@given(st.lists(pose, min_size=3, max_size=12), st.integers(0, 2**31 - 1))
def test_consistent_edges_give_back_the_poses_they_were_measured_between(truth, seed):
    """Edges measured exactly between true poses (a chain and random extra pairs), started from poses up to 0.3 m
    and 0.2 rad off: the solution is the truth (the first pose is held). Wrong Jacobians would stop short."""
    truth = np.array(truth)
    rng = np.random.default_rng(seed)
    graph = PoseGraph()
    graph.add_node(truth[0])
    for k in range(1, len(truth)):
        start = truth[k] + rng.uniform(-1, 1, 3) * np.array([0.3, 0.3, 0.2])
        graph.add_node(np.array([start[0], start[1], wrap_angle(start[2])]))
    cov = np.diag([0.01, 0.01, 0.001])
    pairs = [(k, k + 1) for k in range(len(truth) - 1)]
    pairs += [tuple(rng.choice(len(truth), 2, replace=False)) for _ in range(len(truth))]
    for i, j in pairs:
        graph.add_edge(int(i), int(j), relative_motion(truth[[i]], truth[[j]])[0], cov)
    graph.optimize(iterations=20, tolerance=1e-10)
    assert graph.poses[:, :2] == pytest.approx(truth[:, :2], abs=1e-6)
    assert np.abs(wrap_angle(graph.poses[:, 2] - truth[:, 2])).max() < 1e-6
    assert graph.chi2().max() < 1e-6


def test_an_edge_needs_two_existing_nodes():
    graph = PoseGraph()
    graph.add_node(np.zeros(3))
    with pytest.raises(ValueError, match="two different existing nodes"):
        graph.add_edge(0, 1, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="two different existing nodes"):
        graph.add_edge(0, 0, np.zeros(3), np.eye(3))


@settings(max_examples=30, deadline=None)
@given(pose, pose, pose)
def test_the_transform_between_two_frames_maps_one_onto_the_other(a, b, c):
    """T = transform_between(a, b) takes b to a, and moves any other pose rigidly: distances and relative
    motions stay."""
    a, b, c = np.array([a]), np.array([b]), np.array([c])
    transform = transform_between(a, b)
    assert apply_transform(transform[0], b)[0, :2] == pytest.approx(a[0, :2], abs=1e-9)
    assert abs(wrap_angle(apply_transform(transform[0], b)[0, 2] - a[0, 2])) < 1e-9
    moved = apply_transform(transform[0], np.vstack([b, c]))
    assert relative_motion(moved[[0]], moved[[1]])[0] == pytest.approx(relative_motion(b, c)[0], abs=1e-9)
    # one transform per leading row of (T, M, 3)
    rows = apply_transform(np.vstack([transform, transform]), np.stack([np.vstack([b, c])] * 2))
    assert rows[1] == pytest.approx(moved, abs=1e-12)
