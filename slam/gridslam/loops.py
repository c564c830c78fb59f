"""Loop closure for grid FastSLAM (``GridSlamConfig.loop_closure``, on by default): scan-to-submap matching over a
wide window and a pose graph of the path (docs/gridslam.md, "Loop closure", with what it does on the simulated and
real logs).

A particle filter closes a loop only if one of its particles still holds the right pose when the robot comes back;
after a long drive the heading error picked up at one corner bends the rest of the loop and no particle is near
the truth. Graph-based laser SLAM searches for the match instead (Hess et al. 2016, Cartographer; Olson 2009,
correlative scan matching). Here:

- every integrated scan is kept with every particle's pose, the covariance each was drawn with and the resampling
  that followed, so that any particle's path (its lineage: its ancestors' poses) can be read back;
- every ``loop_every`` integrated scans, when the best particle's path holds a node at least ``revisit_gap`` nodes
  old within the search window of its current pose, the scan is matched against a *submap*: the end points of the
  scans of the ``loop_submap`` nodes either side of the nearest such node, placed by that path. The search is
  exhaustive over a window three standard deviations of the filter's covariance wide (at least ``loop_window_xy``
  m and ``loop_window_yaw`` rad, at most ``loop_window_max`` m and MAX_WINDOW_YAW): coarse (COARSE_CELLS cells, on
  a max-filtered likelihood field), then every cell round the best coarse poses, then halved steps
  (:func:`match_scan`, :func:`correlative_search`). Its covariance is the spread of the coarse response (Olson
  2009): along a corridor's axis it is wide;
- a match counts when the submap explains the scan at least as well as the best particle's own map does (and at
  least ``loop_min_match``) and when its offset lies within the chi-square gate of the filter's covariance plus the
  match's. The next search confirms it: centred where the match predicts the robot now is, with the match's
  covariance as window and gate (:func:`_predict`; the filter's own covariance is no guide once its particles agree
  on the wrong corridor), its match must agree (:func:`_agree`);
- it is acted on only when the filter missed the loop: when the match moves the best particle beyond what the
  filter's own matcher pulls in and beyond the match's own uncertainty (:meth:`LoopCloser._significant`). Where
  the filter closed the loop itself nothing changes. Otherwise both matches become loop edges of a pose graph
  (slam.posegraph) along the best particle's path: its own moves from scan to scan, with the covariances the
  proposal drew them with, and every loop edge taken so far. The graph is solved; edges it cannot hold (residual
  beyond the gate) are dropped;
- when the solved graph moves the current pose that far, the filter rebuilds the particles' grids from every
  node's scan at the graph's poses (one shared map) and moves the particles with the best one
  (slam.gridslam.filter).

The written trajectories follow the graph too (:meth:`LoopCloser.corrections`, used by slam.gridslam.run): the graph
is made along the final best particle's lineage with every loop edge and solved, and every scan's particle poses
move by the transform that takes that lineage's pose onto the solved graph's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from mapping.jit import kernel
from slam.angles import wrap_angle
from slam.gridslam.config import GridSlamConfig
from slam.motion import rotate_covariance
from slam.posegraph import PoseGraph, apply_transform, transform_between
from slam.relations import relative_motion

#: chi-square, 3 degrees of freedom, at 0.999: the gate of a loop closure's offset and of its solved residual
GATE_CHI2 = 16.27
#: coarse search step in cells; the coarse likelihood field is max-filtered over this many cells
COARSE_CELLS = 4
#: the fine search refines this many of the best coarse poses
FINE_CANDIDATES = 8
#: rad: the yaw search window's largest half-width (a heading error beyond it is not searched for)
MAX_WINDOW_YAW = 0.4
#: a pending match waits at most this many searches' spacing for one that agrees
PENDING_NODES = 3
#: halvings of the steps refining the best fine pose
REFINEMENTS = 4
#: fewest end points in a scan for a loop search
LEAST_POINTS = 20


@kernel(nogil=True)
def correlative_search(
    field, origin_x, origin_y, res, points, center, steps_xy, step_xy, yaws, smooth, scores
):  # pragma: no cover - compiled
    """scores[a, u, v] = the mean likelihood-field value at the end points (K, 2) (robot frame, m) of the pose
    center (+) (step_xy * (u - steps_xy), step_xy * (v - steps_xy)) (map-frame offsets, m) with yaw
    center[2] + yaws[a] (rad). field (H, W) holds values at cell centres (cells res m, cell [0, 0]'s lower-left
    corner at (origin_x, origin_y), rows along y), interpolated bilinearly if ``smooth`` (else the value of the cell
    a point falls in); a point outside the field scores 0."""
    h, w = field.shape
    n = points.shape[0]
    span = 2 * steps_xy + 1
    for a in range(len(yaws)):
        c, s = math.cos(center[2] + yaws[a]), math.sin(center[2] + yaws[a])
        for u in range(span):
            dx = center[0] + step_xy * (u - steps_xy) - origin_x
            for v in range(span):
                dy = center[1] + step_xy * (v - steps_xy) - origin_y
                total = 0.0
                for k in range(n):
                    px, py = points[k, 0], points[k, 1]
                    if not smooth:
                        ix, iy = (
                            int(math.floor((c * px - s * py + dx) / res)),
                            int(math.floor((s * px + c * py + dy) / res)),
                        )
                        if 0 <= ix < w and 0 <= iy < h:
                            total += field[iy, ix]
                        continue
                    fx = (c * px - s * py + dx) / res - 0.5
                    fy = (s * px + c * py + dy) / res - 0.5
                    ix, iy = int(math.floor(fx)), int(math.floor(fy))
                    ax, ay = fx - ix, fy - iy
                    for jy in range(2):
                        yy = iy + jy
                        if 0 <= yy < h:
                            wy = ay if jy else 1.0 - ay
                            for jx in range(2):
                                xx = ix + jx
                                if 0 <= xx < w:
                                    total += wy * (ax if jx else 1.0 - ax) * field[yy, xx]
                scores[a, u, v] = total / n


def in_frame(covariance: np.ndarray, yaw: float) -> np.ndarray:
    """A pose covariance (3, 3) given in the map frame, expressed in the frame of a pose of heading ``yaw`` rad."""
    return rotate_covariance(covariance, np.array([-yaw]))[0]


def end_points(
    r_stop: np.ndarray, hit: np.ndarray, cos_b: np.ndarray, sin_b: np.ndarray, offset: np.ndarray
) -> np.ndarray:
    """The end points (K, 2) (robot frame, m) of a scan's beams that hit (ranges r_stop (B,) m, hit flags (B,),
    beam directions in the laser frame, the laser's pose offset (3,) on the robot)."""
    r = r_stop[hit]
    lx, ly = r * cos_b[hit], r * sin_b[hit]
    c, s = math.cos(offset[2]), math.sin(offset[2])
    return np.column_stack([offset[0] + c * lx - s * ly, offset[1] + s * lx + c * ly])


def likelihood_field(points: np.ndarray, res: float, sigma: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """A likelihood field (H, W) float32, exp(-d^2 / 2 sigma^2) with d (m) the distance from a cell to the nearest
    cell holding one of ``points`` (P, 2) (map frame, m), over their bounding box grown by ``margin`` m, and the
    lower-left corner (2,) of cell [0, 0] (rows along y)."""
    lo = np.floor((points.min(axis=0) - margin) / res) * res
    shape = (np.ceil((points.max(axis=0) + margin - lo) / res).astype(np.int64) + 1)[::-1]
    cells = np.floor((points - lo) / res).astype(np.int64)
    empty = np.ones(shape, bool)
    empty[cells[:, 1], cells[:, 0]] = False
    distance = scipy.ndimage.distance_transform_edt(empty) * res
    return np.exp(-(distance**2) / (2 * sigma**2)).astype(np.float32), lo


@dataclass(frozen=True)
class Match:
    """The best pose (3,) (map frame) of a scan against a submap, its matched-beam fraction (mean field value) and
    the covariance (3, 3) of the search's response (m, rad)."""

    pose: np.ndarray
    matched: float
    covariance: np.ndarray


def match_scan(
    field: np.ndarray,
    origin: np.ndarray,
    res: float,
    points: np.ndarray,
    center: np.ndarray,
    window_xy: float,
    window_yaw: float,
    temper: float,
) -> Match:
    """Search poses within +-window_xy (m) and +-window_yaw (rad) of ``center`` (3,) for the one that puts a scan's
    end points (K, 2) (robot frame) best on ``field`` (:func:`likelihood_field`, cell ``res`` m): coarse steps of
    COARSE_CELLS cells on the max-filtered field, then every cell and yaw step around the FINE_CANDIDATES best coarse
    poses, then :func:`_refine`. The yaw steps move a point at the 90th percentile of the points' ranges by two cells
    (coarse) and one (fine). The covariance is that of the coarse poses weighted by
    exp(temper * K * (score - best score)) (a log-likelihood per point, tempered), plus the coarse step's own
    uniform spread, so an ambiguous direction (a corridor's axis) comes out wide."""
    reach = max(float(np.percentile(np.hypot(points[:, 0], points[:, 1]), 90)), res)
    yaw_step = res / reach
    coarse_yaw = 2 * yaw_step
    yaws = np.arange(-math.floor(window_yaw / coarse_yaw), math.floor(window_yaw / coarse_yaw) + 1) * coarse_yaw
    coarse_step = COARSE_CELLS * res
    steps = max(1, int(math.ceil(window_xy / coarse_step)))
    coarse_field = scipy.ndimage.maximum_filter(field, size=2 * (COARSE_CELLS // 2) + 1)
    scores = np.empty((len(yaws), 2 * steps + 1, 2 * steps + 1))
    pts = np.ascontiguousarray(points, np.float64)
    correlative_search(coarse_field, origin[0], origin[1], res, pts, center, steps, coarse_step, yaws, False, scores)
    flat = np.argsort(scores.ravel())[::-1][:FINE_CANDIDATES]
    fine_steps = COARSE_CELLS // 2
    fine_yaws = np.arange(-1, 2) * yaw_step
    best_score, best_pose = -1.0, center
    fine = np.empty((len(fine_yaws), 2 * fine_steps + 1, 2 * fine_steps + 1))
    for index in flat:  # a few candidates, each one compiled search
        a, u, v = np.unravel_index(index, scores.shape)
        start = np.array(
            [center[0] + coarse_step * (u - steps), center[1] + coarse_step * (v - steps), center[2] + yaws[a]]
        )
        correlative_search(field, origin[0], origin[1], res, pts, start, fine_steps, res, fine_yaws, True, fine)
        fa, fu, fv = np.unravel_index(int(np.argmax(fine)), fine.shape)
        if fine[fa, fu, fv] > best_score:
            best_score = float(fine[fa, fu, fv])
            best_pose = start + np.array([res * (fu - fine_steps), res * (fv - fine_steps), fine_yaws[fa]])
    best_pose, best_score = _refine(field, origin, res, pts, best_pose, yaw_step)
    weights = np.exp(temper * len(points) * (scores - scores.max()))
    weights /= weights.sum()
    grid = np.stack(
        np.meshgrid(
            yaws,
            coarse_step * (np.arange(2 * steps + 1) - steps),
            coarse_step * (np.arange(2 * steps + 1) - steps),
            indexing="ij",
        ),
        axis=-1,
    ).reshape(-1, 3)[:, [1, 2, 0]]
    w = weights.ravel()
    mean = w @ grid
    spread = grid - mean
    covariance = np.einsum("n,ni,nj->ij", w, spread, spread)
    covariance += np.diag([coarse_step**2 / 12, coarse_step**2 / 12, coarse_yaw**2 / 12])
    best_pose = best_pose.copy()
    best_pose[2] = wrap_angle(best_pose[2])
    return Match(best_pose, best_score, covariance)


def _refine(
    field: np.ndarray, origin: np.ndarray, res: float, points: np.ndarray, pose: np.ndarray, yaw_step: float
) -> tuple[np.ndarray, float]:
    """The best of the 27 poses a half step round ``pose`` (3,) in x, y and yaw, REFINEMENTS times with the steps
    halved each time, starting from half a cell and half ``yaw_step``: the pose (3,) and its score."""
    scores = np.empty((3, 3, 3))
    step_xy, step_yaw = res / 2, yaw_step / 2
    score = -1.0
    for _ in range(REFINEMENTS):  # a few compiled searches of 27 poses
        correlative_search(
            field,
            origin[0],
            origin[1],
            res,
            points,
            pose,
            1,
            step_xy,
            np.array([-1.0, 0.0, 1.0]) * step_yaw,
            True,
            scores,
        )
        a, u, v = np.unravel_index(int(np.argmax(scores)), scores.shape)
        pose = pose + np.array([step_xy * (u - 1), step_xy * (v - 1), step_yaw * (a - 1)])
        score = float(scores[a, u, v])
        step_xy, step_yaw = step_xy / 2, step_yaw / 2
    return pose, score


@dataclass(frozen=True)
class Closure:
    """A loop closure the graph took: the old node the scan matched, the current node, the offset (3,) it moved the
    current node by (in that node's frame, m and rad), and whether the grids must be rebuilt (the transform (3,)
    that moves the filter's frame onto the graph's)."""

    old: int
    node: int
    offset: np.ndarray
    rebuild: bool
    transform: np.ndarray


@dataclass
class _Scan:
    """What a node keeps of its scan: ranges r_stop (B,) m (NaN: unused), hit flags (B,), the laser's beam directions
    and pose on the robot, and the end points (K, 2) in the robot frame."""

    r_stop: np.ndarray
    hit: np.ndarray
    cos_b: np.ndarray
    sin_b: np.ndarray
    offset: np.ndarray
    points: np.ndarray


#: a loop edge of the graph: the old node, the current node, the current node's pose z (3,) in the old node's frame
#: and its covariance (3, 3) in that frame
Edge = tuple[int, int, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class _Candidate:
    """A search's accepted match: the node searched from, the old node whose submap it matched, the match, the best
    particle's pose (3,) when it searched (the estimate) and the loop edge it makes."""

    node: int
    old: int
    match: Match
    estimate: np.ndarray
    edge: Edge


def _predict(first: _Candidate, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a match ``first`` says a later pose of the best particle ``estimate`` (3,) (map frame) truly is: the
    transform that takes the first's estimate to its match, applied to ``estimate``, and the covariance (3, 3) of that
    prediction: the first match's, its yaw uncertainty swung over the distance between the two poses."""
    correction = transform_between(first.match.pose[None], first.estimate[None])
    predicted = apply_transform(correction[0], estimate[None])[0]
    lever = float(np.hypot(*(estimate[:2] - first.estimate[:2]))) ** 2 * first.match.covariance[2, 2]
    return predicted, first.match.covariance + np.diag([lever, lever, 0.0])


def _agree(first: _Candidate, second: _Candidate) -> bool:
    """Whether two matches correct the path alike: :func:`_predict` from the first lands on the second's match within
    the chi-square gate of the prediction's and the second match's covariances."""
    predicted, covariance = _predict(first, second.estimate)
    diff = second.match.pose - predicted
    diff[2] = wrap_angle(diff[2])
    return float(diff @ np.linalg.solve(covariance + second.match.covariance, diff)) <= GATE_CHI2


class LoopCloser:
    """Every integrated scan with the particles' poses, and the loop search along the best particle's path."""

    def __init__(self, config: GridSlamConfig) -> None:
        self.config = config
        self.scans: list[_Scan] = []
        self.poses: list[np.ndarray] = []  # per node: every particle's pose (M, 3) as the filter wrote it
        self.drawn: list[np.ndarray] = []  # ... the covariances (M, 3, 3) it drew them with
        self.parents: list[np.ndarray | None] = []  # ... the resampling after it (None: none)
        self.frames: list[np.ndarray] = []  # ... the transform (3,) a rebuild moved the particles by after it
        self.best: list[int] = []  # ... the best particle
        self.covariances: list[np.ndarray] = []  # per node: the filter's covariance there
        self.solved = np.zeros((0, 3))  # the graph's poses of the nodes up to the last rebuild (the grids' frame)
        self.last_search = -(10**9)
        self.searches = 0
        self.closures: list[Closure] = []
        self.rebuilds = 0
        self.seconds = 0.0  # CPU time (s) in loop searches, graph solves and rebuilds
        self.loop_edges: list[Edge] = []  # taken
        self.pending: _Candidate | None = None  # the last search's match, waiting for the next to agree

    def add(
        self,
        poses: np.ndarray,
        best: int,
        drawn: np.ndarray,
        covariance: np.ndarray,
        r_stop: np.ndarray,
        hit: np.ndarray,
        laser: tuple[np.ndarray, np.ndarray, np.ndarray],
    ) -> int:
        """Add a node for an integrated scan: every particle's pose (M, 3) there (before resampling), the index of
        the best, the covariances (M, 3, 3) (map frame) the poses were drawn with round their moves (with a cell's
        precision), the filter's covariance there, the scan's ranges r_stop (B,) m and hit flags (B,) and its laser
        (cos_b, sin_b, offset). Returns the node's index."""
        cos_b, sin_b, offset = laser
        points = end_points(r_stop, hit, cos_b, sin_b, offset)
        self.scans.append(_Scan(r_stop.copy(), hit.copy(), cos_b, sin_b, offset, points))
        self.covariances.append(np.asarray(covariance, np.float64))
        self.poses.append(np.array(poses, np.float64))
        self.drawn.append(np.array(drawn, np.float64))
        self.parents.append(None)
        self.frames.append(np.zeros(3))
        self.best.append(int(best))
        return len(self.poses) - 1

    def _move(self, n: int, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Particle ``particle``'s move (3,) to node n from its parent at node n - 1, in the parent's frame, and its
        covariance (3, 3) in that frame."""
        parents = self.parents[n - 1]
        parent = self.poses[n - 1][particle if parents is None else parents[particle]]
        parent = apply_transform(self.frames[n - 1], parent[None])[0]  # (moved by a rebuild after node n - 1)
        move = relative_motion(parent[None], self.poses[n][particle][None])[0]
        return move, in_frame(self.drawn[n][particle], float(parent[2]))

    def link(self, parents: np.ndarray | None) -> None:
        """The last node's particle set was resampled or split: particle j of the next node continues particle
        parents[j] of this one (None: particle j continues j)."""
        self.parents[-1] = None if parents is None else np.asarray(parents, np.int64).copy()

    def lineage(self, particle: int) -> np.ndarray:
        """The index (N,) at each node of particle ``particle``'s ancestor (``particle`` indexes the set after the
        last node; before the last node's :meth:`link`, its set)."""
        index = np.empty(len(self.poses), np.int64)
        current = particle
        for n in range(len(self.poses) - 1, -1, -1):  # one step per node
            parents = self.parents[n]
            current = current if parents is None else int(parents[current])
            index[n] = current
        return index

    def _own_path(self, lineage: np.ndarray) -> np.ndarray:
        """The poses (N, 3) of a lineage (:meth:`lineage`) as the filter wrote them."""
        return np.array([poses[j] for poses, j in zip(self.poses, lineage)])

    def path(self, lineage: np.ndarray) -> np.ndarray:
        """The poses (N, 3) of a lineage (:meth:`lineage`) where the grids hold its scans now: the graph's poses up
        to the last rebuild, the particle's own after it."""
        path = self._own_path(lineage)
        path[: len(self.solved)] = self.solved
        return path

    def graph(self, lineage: np.ndarray, edges: list[Edge]) -> PoseGraph:
        """The pose graph along a lineage: its own moves from node to node (with the covariances they were drawn
        with), every loop edge taken and ``edges``; started at :meth:`path`."""
        graph = PoseGraph()
        for pose in self.path(lineage):  # one node each
            graph.add_node(pose)
        for n in range(1, len(lineage)):  # one edge per node
            graph.add_edge(n - 1, n, *self._move(n, int(lineage[n])))
        for edge in [*self.loop_edges, *edges]:
            graph.add_edge(*edge)
        return graph

    def _old_node(self, node: int, center: np.ndarray, path: np.ndarray, window_xy: float) -> int | None:
        """The node at least revisit_gap nodes before ``node`` nearest on ``path`` (N, 3) to ``center`` (3,), if
        within window_xy + 1 m."""
        old = node - self.config.revisit_gap
        if old < 0:
            return None
        distance = np.hypot(path[: old + 1, 0] - center[0], path[: old + 1, 1] - center[1])
        nearest = int(np.argmin(distance))
        return nearest if distance[nearest] <= window_xy + 1.0 else None

    def _submap(self, old: int, node: int, path: np.ndarray) -> np.ndarray:
        """End points (P, 2) (map frame, placed by ``path`` (N, 3)) of the nodes within loop_submap of ``old`` that
        are at least revisit_gap nodes before ``node``."""
        cfg = self.config
        last = min(old + cfg.loop_submap, node - cfg.revisit_gap)
        chunks = []
        for k in range(max(0, old - cfg.loop_submap), last + 1):  # one vectorised transform per node's scan
            points = self.scans[k].points
            chunks.append(apply_transform(path[k], np.column_stack([points, np.zeros(len(points))]))[:, :2])
        return np.concatenate(chunks) if chunks else np.zeros((0, 2))

    def _search(self, node: int, path: np.ndarray, matched: float, pending: _Candidate | None) -> _Candidate | None:
        """Match the scan of ``node`` against the submap round the nearest old node on ``path`` within the window;
        the match if it counts (explains the scan at least as well as ``matched``, the best particle's own map, and
        lies within the chi-square gate), else None. The search is centred on the best particle's pose, its window
        and gate are the filter's covariance (and the old node's); while a match is ``pending`` they are where that
        match predicts the pose and its covariance (:func:`_predict`): the filter's covariance shrinks as its
        particles agree on the wrong corridor, the pending match's does not."""
        cfg = self.config
        estimate = path[node]
        if pending is None:
            center, covariance = estimate, self.covariances[node]
        else:
            center, covariance = _predict(pending, estimate)
        sigma_xy = math.sqrt(max(float(np.linalg.eigvalsh(covariance[:2, :2]).max()), 0.0))
        window_xy = min(max(cfg.loop_window_xy, 3.0 * sigma_xy), cfg.loop_window_max)
        window_yaw = min(max(cfg.loop_window_yaw, 3.0 * math.sqrt(max(covariance[2, 2], 0.0))), MAX_WINDOW_YAW)
        old = self._old_node(node, center, path, window_xy)
        if old is None:
            return None
        self.last_search = node
        self.searches += 1
        submap = self._submap(old, node, path)
        points = self.scans[node].points
        if len(points) > cfg.match_beams:  # evenly spread, as the matcher's beams
            points = points[np.round(np.linspace(0, len(points) - 1, cfg.match_beams)).astype(np.int64)]
        # the field only where the scan's points can land within the window (the field is ~0 beyond 3 sigma)
        reach = float(np.max(np.hypot(points[:, 0], points[:, 1]))) + window_xy + 0.5
        near = (np.abs(submap[:, 0] - center[0]) <= reach) & (np.abs(submap[:, 1] - center[1]) <= reach)
        if near.sum() < LEAST_POINTS:
            return None
        field, origin = likelihood_field(submap[near], cfg.resolution, cfg.sigma_match, 0.5)
        match = match_scan(field, origin, cfg.resolution, points, center, window_xy, window_yaw, 1.0 / cfg.gain)
        if not match.matched >= max(cfg.loop_min_match, matched if math.isfinite(matched) else 1.0):
            return None
        world = np.array([*(match.pose[:2] - center[:2]), wrap_angle(match.pose[2] - center[2])])  # (map frame)
        gate = covariance + match.covariance + (self.covariances[old] if pending is None else 0.0)
        if float(world @ np.linalg.solve(gate, world)) > GATE_CHI2:
            return None
        z = relative_motion(path[old][None], match.pose[None])[0]
        edge = (old, node, z, in_frame(match.covariance, float(path[old, 2])))
        return _Candidate(node, old, match, estimate.copy(), edge)

    def close(self, node: int, matched: float) -> Closure | None:
        """Search for a loop closure at ``node`` (the last added; at most every loop_every nodes) along the best
        particle's path: match its scan against the submap round the nearest old node within the window
        (:meth:`_search`); a match that counts waits for the next search's to agree, and then both become loop
        edges. When they move the best particle beyond what its own matcher pulls in, the graph along its path is
        solved and the grids must be rebuilt from it. ``matched``: the best particle's matched-beam fraction on its
        own map at this scan. Returns the closure taken, or None."""
        cfg = self.config
        if node - self.last_search < cfg.loop_every or len(self.scans[node].points) < LEAST_POINTS:
            return None
        lineage = self.lineage(self.best[node])
        path = self.path(lineage)
        pending = self.pending
        if pending is not None and node - pending.node > PENDING_NODES * cfg.loop_every:
            pending = self.pending = None  # no later match agreed in time
        candidate = self._search(node, path, matched, pending)
        if candidate is None:
            return None
        # a match is taken only when the next search's agrees with it (the same correction of the path)
        self.pending = candidate
        if pending is None or not _agree(pending, candidate):
            return None
        self.pending = None
        if not self._significant(candidate.match.pose - candidate.estimate, candidate.match.covariance):
            return None  # the best particle's path already agrees with the old submap: nothing to correct
        edges = [pending.edge, candidate.edge]
        graph = self.graph(lineage, edges)
        graph.optimize()
        if graph.chi2()[-2:].max() > GATE_CHI2:
            return None
        rebuild = self._significant(graph.poses[node] - path[node], candidate.match.covariance)
        if rebuild:
            self.solved = graph.poses.copy()
        self.loop_edges += edges
        offset = relative_motion(candidate.estimate[None], candidate.match.pose[None])[0]
        transform = transform_between(graph.poses[node][None], path[node][None])[0]
        closure = Closure(pending.old, node, offset, rebuild, transform)
        self.closures.append(closure)
        return closure

    def _significant(self, change: np.ndarray, covariance: np.ndarray) -> bool:
        """Whether a change (3,) of a pose (m, rad; map frame) is a correction the filter needs: beyond what the
        filter's scan matcher pulls in by itself (two hill-climbing steps, 2 lin_step m, or half of ang_step rad) and
        beyond the match's own uncertainty (``covariance`` (3, 3), map frame; the chi-square gate)."""
        cfg = self.config
        change = np.array([change[0], change[1], wrap_angle(float(change[2]))])
        if not (math.hypot(change[0], change[1]) >= 2 * cfg.lin_step or abs(change[2]) >= cfg.ang_step / 2):
            return False
        return float(change @ np.linalg.solve(covariance, change)) > GATE_CHI2

    def rebuilt(self, transform: np.ndarray) -> None:
        """Record that the filter moved its particles by ``transform`` (3,) after the last node (a rebuild)."""
        self.frames[-1] = np.asarray(transform, np.float64).copy()
        self.rebuilds += 1

    def corrections(self, particle: int) -> tuple[np.ndarray, np.ndarray]:
        """Per node the transforms (N, 3) that move the filter's poses onto the solved graph, for the poses written at
        the node's scan and for those of the scans after it (they differ where the grids were rebuilt). The graph is
        made along particle ``particle``'s lineage (its own moves: the path written as the best) with every loop
        edge, and solved; without a loop closure the lineage's path stays as it is."""
        lineage = self.lineage(particle)
        path = self._own_path(lineage)
        solved = path
        if self.closures:
            graph = self.graph(lineage, [])
            graph.optimize(iterations=20)
            solved = graph.poses
        frames = np.array(self.frames)
        written = transform_between(solved, path)
        after = transform_between(solved, apply_transform(frames, path[:, None, :])[:, 0, :])
        return written, after
