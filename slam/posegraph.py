"""A 2D pose graph: poses (x m, y m, yaw rad) linked by measured relative motions, solved by Gauss-Newton.

Node k holds a pose X_k in the map frame. An edge (i, j, z, Omega) says that X_j seen from X_i is z = (dx, dy, dyaw)
(in X_i's frame) with information Omega (3 x 3, the inverse of the measurement's covariance). The residual of an
edge is e = [R_z^T (R_i^T (t_j - t_i) - t_z), wrap(yaw_j - yaw_i - yaw_z)], and the graph's poses minimise
sum e^T Omega e with the first pose held where it is (Grisetti, Kuemmerle, Stachniss, Burgard 2010, 'A tutorial on
graph-based SLAM': the Jacobians below are theirs). The normal equations are sparse (a block per edge end) and
are solved with scipy's sparse LU; every edge is handled in one vectorised pass, no Python loop per edge.

Inputs are checked where they enter (InputError, slam.errors): poses and measurements finite, an edge's ends two
different existing nodes (whole numbers), its covariance symmetric and positive definite; :meth:`PoseGraph.optimize`
refuses a graph with nodes that no chain of edges ties to the first (their poses would be undetermined).
"""

from __future__ import annotations

import operator

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

from mapping.covariance import check_covariances
from slam.angles import wrap_angle
from slam.errors import InputError, check_count, check_within, finite_array
from slam.motion import compose
from slam.relations import relative_motion

#: information that holds the first pose in place (a gauge: without it the graph could drift as a whole)
ANCHOR_INFORMATION = 1e9


def transform_between(target: np.ndarray, source: np.ndarray) -> np.ndarray:
    """The rigid transforms T (N, 3) (as poses: x m, y m, yaw rad) with T (+) source = target for pose rows
    (N, 3): what moves a frame in which a pose reads ``source`` to one in which it reads ``target``."""
    c, s = np.cos(target[:, 2] - source[:, 2]), np.sin(target[:, 2] - source[:, 2])
    x = target[:, 0] - (c * source[:, 0] - s * source[:, 1])
    y = target[:, 1] - (s * source[:, 0] + c * source[:, 1])
    return np.column_stack([x, y, wrap_angle(target[:, 2] - source[:, 2])])


def apply_transform(transform: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses moved by rigid transforms, T (+) pose: poses (N, 3) by one transform (3,), or poses (T, M, 3) by one
    transform per leading row (T, 3)."""
    poses = np.asarray(poses, np.float64)
    flat = poses.reshape(-1, 3)
    transforms = np.asarray(transform, np.float64).reshape(-1, 3)
    transforms = np.repeat(transforms, len(flat) // len(transforms), axis=0)
    return compose(transforms, flat.T).reshape(poses.shape)


def _information(covariance: np.ndarray) -> np.ndarray:
    """The inverse (3, 3) of an edge's covariance (3, 3), InputError unless that is symmetric and positive
    definite (mapping.covariance.check_covariances, and no eigenvalue <= 0) with a finite inverse."""
    check_covariances(covariance[None], "covariance")
    lowest = float(np.linalg.eigvalsh(0.5 * (covariance + covariance.T))[0])
    information = np.linalg.inv(covariance) if lowest > 0.0 else np.full((3, 3), np.nan)
    if not np.all(np.isfinite(information)):
        raise InputError(
            f"covariance is singular (smallest eigenvalue {lowest:.3g}): an edge's covariance must be positive "
            "definite, its inverse is the edge's information; give every direction some variance"
        )
    return information


class PoseGraph:
    """Nodes (poses) and edges (relative measurements with their information); :meth:`optimize` solves it."""

    def __init__(self) -> None:
        self.poses = np.zeros((0, 3))
        self._i: list[int] = []
        self._j: list[int] = []
        self._z: list[np.ndarray] = []
        self._info: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self.poses)

    def add_node(self, pose: np.ndarray) -> int:
        """Append a node at ``pose`` (3,) (x m, y m, yaw rad; finite, else InputError); returns its index."""
        pose = finite_array("pose", pose, (3,), " (x m, y m, yaw rad)")
        self.poses = np.vstack([self.poses, pose[None]])
        return len(self.poses) - 1

    def add_edge(self, i: int, j: int, z: np.ndarray, covariance: np.ndarray) -> None:
        """Node j seen from node i is z (3,) (dx m, dy m, dyaw rad in node i's frame) with ``covariance`` (3, 3)
        (m, rad). InputError unless i and j are two different existing nodes (whole numbers), z is finite and the
        covariance finite, symmetric and positive definite (its inverse, the edge's information, must exist)."""
        try:
            i, j = operator.index(i), operator.index(j)
        except TypeError:
            raise InputError(f"an edge's nodes must be whole numbers (node indices), got {i!r} and {j!r}") from None
        if not (0 <= i < len(self) and 0 <= j < len(self) and i != j):
            raise InputError(f"an edge needs two different existing nodes, got {i} and {j} of {len(self)}")
        z = finite_array("z", z, (3,), " (dx m, dy m, dyaw rad in node i's frame)")
        covariance = finite_array("covariance", covariance, (3, 3), " (m, rad)")
        information = _information(covariance)
        self._i.append(int(i))
        self._j.append(int(j))
        self._z.append(z)
        self._info.append(information)

    def remove_last_edges(self, count: int) -> None:
        """Drop the ``count`` edges added last (0 up to the number of edges, else InputError)."""
        check_count("count", count, least=0)
        if count > len(self._i):
            raise InputError(f"count: cannot remove {count} edges, the graph has {len(self._i)}")
        for column in (self._i, self._j, self._z, self._info):
            del column[len(column) - count :]

    def _check_connected(self) -> None:
        """InputError naming the nodes that no chain of edges ties to node 0 (the anchor). O(N + E)."""
        n = len(self)
        links = scipy.sparse.coo_matrix((np.ones(len(self._i)), (self._i, self._j)), shape=(n, n))
        _, label = scipy.sparse.csgraph.connected_components(links, directed=False)
        loose = np.flatnonzero(label != label[0])
        if len(loose):
            shown = ", ".join(str(k) for k in loose[:10]) + (" ..." if len(loose) > 10 else "")
            raise InputError(
                f"{len(loose)} of the pose graph's {n} nodes (nodes {shown}) are tied to node 0 by no chain of edges: "
                "their poses are undetermined; add edges that link them, or leave them out of the graph"
            )

    def residuals(self, poses: np.ndarray | None = None) -> np.ndarray:
        """Every edge's residual (E, 3) at ``poses`` (N, 3) (default: the graph's)."""
        poses = self.poses if poses is None else poses
        i, j = np.array(self._i, np.int64), np.array(self._j, np.int64)
        return relative_motion(np.array(self._z), relative_motion(poses[i], poses[j]))

    def chi2(self, poses: np.ndarray | None = None) -> np.ndarray:
        """Every edge's squared Mahalanobis residual e^T Omega e (E,)."""
        e = self.residuals(poses)
        return np.einsum("ei,eij,ej->e", e, np.array(self._info), e)

    def _step(self) -> np.ndarray:
        """One Gauss-Newton step (N, 3) from the current poses."""
        n, poses = len(self), self.poses
        i, j = np.array(self._i, np.int64), np.array(self._j, np.int64)
        z, info = np.array(self._z), np.array(self._info)
        e = self.residuals()
        ci, si = np.cos(poses[i, 2]), np.sin(poses[i, 2])
        cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
        rz_t = np.stack([np.stack([cz, sz], -1), np.stack([-sz, cz], -1)], -2)  # R_z^T (E, 2, 2)
        ri_t = np.stack([np.stack([ci, si], -1), np.stack([-si, ci], -1)], -2)  # R_i^T
        dri_t = np.stack([np.stack([-si, ci], -1), np.stack([-ci, -si], -1)], -2)  # d R_i^T / d yaw_i
        dt = poses[j, :2] - poses[i, :2]
        a = np.zeros((len(i), 3, 3))
        b = np.zeros((len(i), 3, 3))
        a[:, :2, :2] = -rz_t @ ri_t
        a[:, :2, 2] = np.einsum("eab,eb->ea", rz_t @ dri_t, dt)
        a[:, 2, 2] = -1.0
        b[:, :2, :2] = rz_t @ ri_t
        b[:, 2, 2] = 1.0
        blocks, rows, cols = [], [], []
        grad = np.zeros((n, 3))
        for left, lj, right, rj in ((a, i, a, i), (a, i, b, j), (b, j, a, i), (b, j, b, j)):
            blocks.append(np.swapaxes(left, 1, 2) @ info @ right)
            rows.append(3 * lj[:, None, None] + np.arange(3)[None, :, None])
            cols.append(3 * rj[:, None, None] + np.arange(3)[None, None, :])
        np.add.at(grad, i, np.einsum("eji,ejk,ek->ei", a, info, e))
        np.add.at(grad, j, np.einsum("eji,ejk,ek->ei", b, info, e))
        anchor = np.full(3, ANCHOR_INFORMATION)
        data = np.concatenate([np.broadcast_to(blk, (len(i), 3, 3)).ravel() for blk in blocks] + [anchor])
        row = np.concatenate([np.broadcast_to(r, (len(i), 3, 3)).ravel() for r in rows] + [np.arange(3)])
        col = np.concatenate([np.broadcast_to(c, (len(i), 3, 3)).ravel() for c in cols] + [np.arange(3)])
        hessian = scipy.sparse.coo_matrix((data, (row, col)), shape=(3 * n, 3 * n)).tocsc()
        return scipy.sparse.linalg.spsolve(hessian, -grad.ravel()).reshape(n, 3)

    def optimize(self, iterations: int = 10, tolerance: float = 1e-6) -> int:
        """Gauss-Newton until the largest step is below ``tolerance`` (m or rad, >= 0) or ``iterations`` (>= 1)
        steps; the first node stays where it is. Returns the steps taken. InputError when some node is tied to the
        first by no chain of edges (its pose would be undetermined: the system singular), naming the nodes."""
        check_count("iterations", iterations, least=1)
        check_within("tolerance", tolerance, (0.0, np.inf), "m or rad")
        if not self._i or len(self) < 2:
            return 0
        self._check_connected()
        for step in range(1, iterations + 1):
            delta = self._step()
            if not np.all(np.isfinite(delta)):  # (not with finite, positive definite edges tied to the anchor)
                raise InputError("the pose graph's normal equations have no solution: check its edges' covariances")
            self.poses = self.poses + delta
            self.poses[:, 2] = wrap_angle(self.poses[:, 2])
            if np.max(np.abs(delta)) < tolerance:
                return step
        return iterations
