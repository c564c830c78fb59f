"""Simulated laser logs with known truth, for grid FastSLAM's tests and benchmarks.

A :class:`SimLaserLog` holds a true path, odometry that drifts away from it and laser scans cast against a world
of wall segments. bench.gridslam.write_sim_log writes it as a CARMEN log (what `posegrid slam --algo gridslam`
reads) and the truth as a pose-distribution file (what `posegrid eval-traj` scores against). The odometry starts
at the true first pose, so the filter's map frame is the truth's and no alignment is needed.

Worlds (:data:`WORLDS`): ``office`` (slam.world's office, the robot driven by slam.simulator), ``loop`` (a ring
corridor 30 m x 14 m with door recesses, driven once round and on past the start), ``corridor`` (a straight
corridor with bare walls whose ends lie out of the laser's range: nothing fixes the position along it) and
``room`` (a 7 m x 5 m room with furniture: every scan fixes the pose).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from slam.angles import wrap_angle
from slam.raycast import cast_rays
from slam.simulator import simulate_office
from slam.world import box_segments

#: the laser's pose (x m, y m, yaw rad) on the robot in every simulated log
LASER_OFFSET = (0.1, 0.0, 0.0)
#: beams over 180 deg and the range (m) of the simulated laser
BEAMS, RANGE_MAX = 181, 10.0


@dataclass(frozen=True)
class SimLaserLog:
    """A simulated run: stamps (T,) s, true_poses (T, 3) and odometry (T, 3) (m, rad; the odometry starts at the
    true first pose), ranges (T, B) m (inf: no return within range_max), the laser geometry (rad) and its pose on
    the robot (3,), and the world's wall segments (S, 4) m."""

    stamps: np.ndarray
    true_poses: np.ndarray
    odometry: np.ndarray
    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_max: float
    sensor_offset: np.ndarray
    segments: np.ndarray


def drifting_odometry(
    true_poses: np.ndarray,
    seed: int,
    scale: float = 0.05,
    slip: float = 0.02,
    drift: float = 0.03,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """Odometry (T, 3) from the true motion with ``scale`` relative noise on each forward step, lateral slip of
    ``slip`` times the step and a heading drift of ``drift`` rad per m driven (a miscalibrated wheel base),
    integrated from ``start`` (3,) (m, rad; default: the true first pose)."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(true_poses[:-1, 2]), np.sin(true_poses[:-1, 2])
    d = np.diff(true_poses[:, :2], axis=0)
    forward, lateral = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    turn = wrap_angle(np.diff(true_poses[:, 2]))
    noise = rng.standard_normal((len(forward), 3))
    forward = forward * (1 + scale * noise[:, 0])
    lateral = lateral + slip * np.abs(forward) * noise[:, 1]
    turn = turn + scale * np.abs(turn) * noise[:, 2] + drift * forward
    x0, y0, yaw0 = true_poses[0] if start is None else start
    heading = yaw0 + np.concatenate([[0.0], np.cumsum(turn)])
    ch, sh = np.cos(heading[:-1]), np.sin(heading[:-1])
    x = x0 + np.concatenate([[0.0], np.cumsum(ch * forward - sh * lateral)])
    y = y0 + np.concatenate([[0.0], np.cumsum(sh * forward + ch * lateral)])
    return np.column_stack([x, y, wrap_angle(heading)])


def polyline_path(waypoints: np.ndarray, speed: float, turn_rate: float, dt: float) -> np.ndarray:
    """True poses (T, 3) of a robot that drives the polyline ``waypoints`` (W, 2) m at ``speed`` m/s, turning on
    the spot at ``turn_rate`` rad/s at each corner, one pose every ``dt`` s."""
    poses = [np.array([*waypoints[0], math.atan2(*(waypoints[1] - waypoints[0])[::-1])])]
    for a, b in itertools.pairwise(waypoints):
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        turn = float(wrap_angle(heading - poses[-1][2]))
        start = poses[-1][2]
        for k in range(1, int(abs(turn) / (turn_rate * dt)) + 1):
            poses.append(np.array([a[0], a[1], wrap_angle(start + math.copysign(k * turn_rate * dt, turn))]))
        length = float(np.hypot(*(b - a)))
        for k in range(1, int(length / (speed * dt)) + 1):
            poses.append(np.array([*(a + (b - a) * (k * speed * dt / length)), heading]))
    return np.array(poses)


def laser_scans(
    true_poses: np.ndarray, segments: np.ndarray, rng: np.random.Generator, sigma: float = 0.01
) -> tuple[np.ndarray, float, float]:
    """Ranges (T, BEAMS) float32 m of a laser at LASER_OFFSET over 180 deg, cast against ``segments`` (S, 4) m
    with Gaussian noise of ``sigma`` m (inf: no wall within RANGE_MAX), with angle_min and angle_increment (rad)."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, BEAMS)
    ox, oy, oth = LASER_OFFSET
    c, s = np.cos(true_poses[:, 2]), np.sin(true_poses[:, 2])
    origin = true_poses[:, :2] + np.column_stack([c * ox - s * oy, s * ox + c * oy])
    world = (true_poses[:, 2:3] + oth + angles[None, :]).ravel()
    exact = cast_rays(np.repeat(origin, BEAMS, axis=0), world, segments, RANGE_MAX)
    noisy = np.where(np.isfinite(exact), np.maximum(exact + sigma * rng.standard_normal(exact.shape), 0.05), np.inf)
    return noisy.reshape(len(true_poses), BEAMS).astype(np.float32), float(angles[0]), float(angles[1] - angles[0])


def _boxes(boxes: list[tuple[float, float, float, float]]) -> list[tuple[float, float, float, float]]:
    return [edge for box in boxes for edge in box_segments(box)]


def loop_world() -> tuple[np.ndarray, np.ndarray]:
    """A ring corridor 2 m wide round a 26 m x 10 m block (outer walls 30 m x 14 m) with a door recess every few
    metres on the outer wall, and its route (W, 2) m: once round and 8 m on past the start."""
    outer, inner = (0.0, 0.0, 30.0, 14.0), (2.0, 2.0, 28.0, 12.0)
    walls = _boxes([inner])
    # the outer wall with recesses 1 m wide and 0.5 m deep along the long sides, at irregular spacing
    for y, side in ((0.0, -1.0), (14.0, 1.0)):
        xs = [0.0] + [
            x for door in ((4.0, 11.5, 19.0, 25.5) if y == 0 else (7.0, 15.0, 22.0)) for x in (door, door + 1)
        ]
        xs.append(30.0)
        for x0, x1 in zip(xs[0::2], xs[1::2]):
            walls.append((x0, y, x1, y))
        for door in xs[1:-1:2]:
            walls += [(door, y, door, y + side * 0.5), (door, y + side * 0.5, door + 1, y + side * 0.5)]
            walls.append((door + 1, y + side * 0.5, door + 1, y))
    walls += [(outer[0], outer[1], outer[0], outer[3]), (outer[2], outer[1], outer[2], outer[3])]
    route = np.array([(6.0, 1.0), (29.0, 1.0), (29.0, 13.0), (1.0, 13.0), (1.0, 1.0), (14.0, 1.0)])
    return np.array(walls, float), route


def corridor_world() -> tuple[np.ndarray, np.ndarray]:
    """A straight corridor 2 m wide and 60 m long with bare walls, and a route of 12 m along its middle, whose
    ends stay out of the laser's range."""
    walls = [(0.0, 0.0, 60.0, 0.0), (0.0, 2.0, 60.0, 2.0), (0.0, 0.0, 0.0, 2.0), (60.0, 0.0, 60.0, 2.0)]
    return np.array(walls, float), np.array([(24.0, 1.0), (36.0, 1.0)])


def room_world() -> tuple[np.ndarray, np.ndarray]:
    """A 7 m x 5 m room with five pieces of furniture, and a route round it."""
    walls = _boxes([(0.0, 0.0, 7.0, 5.0)])
    walls += _boxes([(1.0, 3.8, 2.2, 4.6), (5.6, 0.3, 6.6, 1.1), (3.2, 2.2, 3.7, 2.7), (0.3, 0.4, 0.9, 1.6)])
    walls += _boxes([(5.0, 3.6, 6.0, 4.7)])
    route = np.array([(1.5, 2.0), (5.0, 2.0), (5.0, 3.0), (2.0, 3.0), (2.0, 1.5), (4.5, 1.5)])
    return np.array(walls, float), route


def _log(truth: np.ndarray, segments: np.ndarray, seed: int, drift: float = 0.03) -> SimLaserLog:
    ranges, angle_min, angle_increment = laser_scans(truth, segments, np.random.default_rng([seed, 1]))
    return SimLaserLog(
        stamps=0.1 * np.arange(len(truth)),
        true_poses=truth,
        odometry=drifting_odometry(truth, seed=seed, drift=drift),
        ranges=ranges,
        angle_min=angle_min,
        angle_increment=angle_increment,
        range_max=RANGE_MAX,
        sensor_offset=np.array(LASER_OFFSET),
        segments=segments,
    )


def office_log(seed: int, steps: int = 420) -> SimLaserLog:
    """``steps`` steps of 0.1 s through slam.world's office (slam.simulator drives; its route closes a loop
    after about 400 steps), laser and odometry from ``seed``."""
    truth = simulate_office(seed=seed, steps=steps, n_beams=2, range_max=RANGE_MAX).true_poses
    from slam.world import office_segments

    return _log(truth, office_segments(), seed)


def sim_log(world: str, seed: int, steps: int | None = None) -> SimLaserLog:
    """The simulated log of :data:`WORLDS` ``world`` with noise from ``seed`` (``steps``: office only)."""
    if world == "office":
        return office_log(seed) if steps is None else office_log(seed, steps)
    if world not in WORLDS:
        raise ValueError(f"unknown simulated world {world!r}; one of {', '.join(WORLDS)}")
    walls_and_route, speed, drift = WORLDS[world]
    assert walls_and_route is not None  # (only the office has none)
    segments, route = walls_and_route()
    return _log(polyline_path(route, speed=speed, turn_rate=0.8, dt=0.1), segments, seed, drift)


#: world name: (walls and route, speed m/s, odometry heading drift rad per m); the office is simulated by
#: slam.simulator. The ring corridor's odometry drifts half as much as the others' (0.03 rad/m would turn it by 2.3
#: rad over its 78 m)
WORLDS = {
    "office": (None, 0.0, 0.03),
    "loop": (loop_world, 0.8, 0.015),
    "corridor": (corridor_world, 0.8, 0.03),
    "room": (room_world, 0.5, 0.03),
}
