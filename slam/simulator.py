"""A seeded, reproducible simulation of a robot in a world of straight-edge obstacles: the office of slam.world
(the paper's section VII.A), or any :class:`World` (slam.warehouse builds one).

The robot follows the route's waypoints with commanded velocities; its true motion is the velocity motion
model's sample (so the commands are noisy controls), its odometry readings add the odometry model's noise
to the true relative motion, a landmark sensor measures range and bearing to the landmarks in range, in its
field of view and not hidden by an obstacle, and a 2-D laser measures ranges by exact ray casting against
the obstacle edges. Step t is at time t dt; the measurements of step t are taken at the true pose of step t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam.angles import wrap_angle
from slam.errors import InputError, check_count, check_within
from slam.laserlog import geometry_problem
from slam.motion import VELOCITY_LIMIT, OdometryMotionModel, VelocityMotionModel, odometry_controls
from slam.range_bearing import RangeBearingModel
from slam.raster import check_raster_resolution, truth_raster
from slam.raycast import CHUNK_RAYS, cast_rays, segments_block
from slam.simlog import SimLog
from slam.world import WAYPOINTS, office_landmarks, office_segments

#: the laser's pose (x m, y m, yaw rad) in the robot frame
LASER_OFFSET = (0.1, 0.0, 0.0)
#: waypoint follower: top speed (m/s), top turn rate (rad/s), heading gain (1/s), switch radius (m)
MAX_SPEED, MAX_TURN_RATE, HEADING_GAIN, WAYPOINT_RADIUS = 1.0, 1.5, 2.5, 0.4
#: shortest laser range (m)
LASER_RANGE_MIN = 0.05


@dataclass(frozen=True)
class World:
    """What a simulation drives through: obstacle edges (S, 4) as rows (x0, y0, x1, y1), point landmarks (L, 2)
    and the route's waypoints (K, 2), driven in order and then again from the first; all m, map frame."""

    segments: np.ndarray
    landmarks: np.ndarray
    waypoints: np.ndarray


@dataclass(frozen=True)
class SimRun:
    """Everything a simulated run produces. Poses are (x m, y m, yaw rad) in the map frame."""

    stamps: np.ndarray  # (T,) s
    true_poses: np.ndarray  # (T, 3)
    commands: np.ndarray  # (T, 2): commanded (v m/s, w rad/s) held from step t-1 to t; row 0 zeros
    odometry: np.ndarray  # (T, 3): odometry readings in the odometry frame (starts at 0, 0, 0)
    landmark_step: np.ndarray  # (O,) int: step of each landmark measurement
    landmark_id: np.ndarray  # (O,) int: index into `landmarks`
    landmark_z: np.ndarray  # (O, 2): range m, bearing rad (robot frame)
    ranges: np.ndarray  # float32 (T, B) m; inf: no return within range_max
    angle_min: float  # rad, laser frame
    angle_increment: float  # rad
    range_min: float  # m
    range_max: float  # m
    sensor_offset: np.ndarray  # (3,) laser pose in the robot frame
    landmarks: np.ndarray  # (L, 2) m
    segments: np.ndarray  # (S, 4) obstacle edges x0, y0, x1, y1 in m
    truth_occupied: np.ndarray  # bool (H, W)
    truth_visible: np.ndarray  # bool (H, W)
    truth_origin: np.ndarray  # (2,) m, lower-left corner of cell [0, 0]
    truth_resolution: float  # m
    velocity_model: VelocityMotionModel
    odometry_model: OdometryMotionModel
    sensor: RangeBearingModel

    def log(self) -> SimLog:
        """The SLAM inputs of this run (what ``posegrid simulate`` writes to controls.npz and landmarks.npz)."""
        return SimLog(
            stamps=self.stamps,
            commands=self.commands,
            odometry=self.odometry,
            initial_pose=self.true_poses[0].copy(),
            landmark_step=self.landmark_step,
            landmark_id=self.landmark_id,
            landmark_z=self.landmark_z,
            landmark_truth=self.landmarks,
            velocity_model=self.velocity_model,
            odometry_model=self.odometry_model,
            sensor=self.sensor,
        )


def _drive(
    steps: int,
    dt: float,
    model: VelocityMotionModel,
    rng: np.random.Generator,
    waypoints: np.ndarray,
    max_speed: float = MAX_SPEED,
) -> tuple[np.ndarray, np.ndarray]:
    """True poses (T, 3) and commands (T, 2) of the waypoint follower (it steers from the true pose), from the
    first of the ``waypoints`` (K, 2) (m) facing the second, at up to ``max_speed`` m/s."""
    poses = np.zeros((steps, 3))
    first_leg = waypoints[1 % len(waypoints)] - waypoints[0]
    poses[0] = (waypoints[0, 0], waypoints[0, 1], math.atan2(first_leg[1], first_leg[0]))
    commands = np.zeros((steps, 2))
    target = 1
    for t in range(1, steps):
        pose = poses[t - 1]
        if np.hypot(*(waypoints[target] - pose[:2])) < WAYPOINT_RADIUS:
            target = (target + 1) % len(waypoints)
        dx, dy = waypoints[target] - pose[:2]
        error = float(wrap_angle(math.atan2(dy, dx) - pose[2]))
        w = float(np.clip(HEADING_GAIN * error, -MAX_TURN_RATE, MAX_TURN_RATE))
        v = max_speed * max(0.0, math.cos(error)) ** 2
        commands[t] = (v, w)
        poses[t] = model.sample(pose[None, :], np.array([v, w, dt]), rng)[0]
    return poses, commands


def _odometry(true_poses: np.ndarray, model: OdometryMotionModel, rng: np.random.Generator) -> np.ndarray:
    """Odometry readings (T, 3): the true relative motions plus the odometry model's noise, integrated from 0."""
    motion = odometry_controls(true_poses)
    noisy = motion + rng.standard_normal(motion.shape) * np.sqrt(model.motion_variances(motion))
    theta_before = np.concatenate([[0.0], np.cumsum(noisy[:, 0] + noisy[:, 2])])
    heading = theta_before[:-1] + noisy[:, 0]
    x = np.concatenate([[0.0], np.cumsum(noisy[:, 1] * np.cos(heading))])
    y = np.concatenate([[0.0], np.cumsum(noisy[:, 1] * np.sin(heading))])
    return np.column_stack([x, y, wrap_angle(theta_before)])


def _landmark_measurements(poses, landmarks, segments, sensor, max_range, fov, rng):
    """Noisy (range, bearing) of every landmark within max_range (m), |bearing| <= fov/2 and in sight."""
    dx = landmarks[None, :, 0] - poses[:, None, 0]
    dy = landmarks[None, :, 1] - poses[:, None, 1]
    r = np.hypot(dx, dy)
    bearing = wrap_angle(np.arctan2(dy, dx) - poses[:, None, 2])
    step, ident = np.nonzero((r <= max_range) & (np.abs(bearing) <= fov / 2.0))
    sight = ~segments_block(poses[step, :2], landmarks[ident], segments)
    step, ident = step[sight], ident[sight]
    z = np.column_stack([r[step, ident], bearing[step, ident]])
    z += rng.standard_normal(z.shape) * np.array([sensor.sigma_range, sensor.sigma_bearing])
    z[:, 0] = np.abs(z[:, 0])
    z[:, 1] = wrap_angle(z[:, 1])
    return step.astype(np.int64), ident.astype(np.int64), z


def _laser_rays(
    true_poses: np.ndarray, offset: np.ndarray, beam_angles: np.ndarray, segments: np.ndarray, range_max: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The noise-free beams of a laser at ``offset`` (3,) on the robot at each true pose (T, 3), beam angles
    (B,) rad in the laser frame, over the walls ``segments`` (S, 4): per beam (T*B, pose-major) its origin (2,)
    m, its exact range m (inf: no wall within ``range_max``) and its end point (2,) m (at range_max for no
    return)."""
    cos_t, sin_t = np.cos(true_poses[:, 2]), np.sin(true_poses[:, 2])
    sensor_xy = true_poses[:, :2] + np.column_stack(
        [cos_t * offset[0] - sin_t * offset[1], sin_t * offset[0] + cos_t * offset[1]]
    )
    world_angles = (true_poses[:, 2:3] + offset[2] + beam_angles[None, :]).ravel()
    origins = np.repeat(sensor_xy, len(beam_angles), axis=0)
    exact = np.empty(len(origins))
    group = max(1, CHUNK_RAYS // len(beam_angles))  # poses whose rays are cast together
    for first in range(0, len(true_poses), group):
        rays = slice(first * len(beam_angles), (first + group) * len(beam_angles))
        near = _segments_within(segments, sensor_xy[first : first + group], range_max)
        exact[rays] = cast_rays(origins[rays], world_angles[rays], near, range_max)
    reach = np.minimum(exact, range_max)
    endpoints = origins + reach[:, None] * np.column_stack([np.cos(world_angles), np.sin(world_angles)])
    return origins, exact, endpoints


def _segments_within(segments: np.ndarray, points: np.ndarray, reach: float) -> np.ndarray:
    """The segments (S, 4) whose bounding box lies within ``reach`` m of the bounding box of ``points`` (P, 2): a
    superset of those a ray of length ``reach`` from any of the points can hit, so casting against them gives
    the same ranges as casting against all (the nearest hit is computed alike; the others are farther than
    ``reach``)."""
    low, high = points.min(axis=0), points.max(axis=0)
    seg_low = np.minimum(segments[:, :2], segments[:, 2:])
    seg_high = np.maximum(segments[:, :2], segments[:, 2:])
    gap = np.maximum(np.maximum(seg_low - high, low - seg_high), 0.0)
    return segments[np.hypot(gap[:, 0], gap[:, 1]) <= reach]


def _check_options(
    world: World,
    steps: int,
    n_beams: int,
    range_max: float,
    fov: float,
    laser_sigma: float,
    dt: float,
    truth_resolution: float,
    max_speed: float,
    landmark_range_max: float,
    landmark_fov: float,
    velocity_model: VelocityMotionModel,
    odometry_model: OdometryMotionModel,
    sensor: RangeBearingModel,
) -> tuple[float, float]:
    """InputError (a ValueError) naming the first option of :func:`simulate_world` it cannot use, before any work;
    else the laser's angle_increment and angle_min (rad). The laser's geometry is held to the rules the scan files
    are (slam.laserlog.geometry_problem: a fan of at most a full turn), the truth raster to load_truth's cell cap."""
    check_count("steps", steps)
    check_count("n_beams", n_beams)
    for name, value in (("dt (s between steps)", dt), ("fov (the laser's field of view, rad)", fov)):
        if not (math.isfinite(value) and value > 0.0):
            raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    check_within("laser_sigma (the laser's range noise)", laser_sigma, (0.0, np.inf), "m")
    check_within("max_speed", max_speed, (0.0, VELOCITY_LIMIT), "m/s")
    check_within("landmark_range_max", landmark_range_max, (0.0, np.inf), "m")
    check_within("landmark_fov", landmark_fov, (0.0, 2.0 * math.pi), "rad")
    angle_increment = fov / (n_beams - 1) if n_beams > 1 else 0.0
    angle_min = -fov / 2.0 if n_beams > 1 else 0.0
    problem = geometry_problem(int(n_beams), angle_min, angle_increment, LASER_RANGE_MIN, range_max)
    if problem:
        raise InputError(
            f"the laser (n_beams {n_beams}, fov {fov!r} rad, range_max {range_max!r} m; range_min is "
            f"{LASER_RANGE_MIN} m) is unusable: {problem}"
        )
    for name, model, kind in (
        ("velocity_model", velocity_model, VelocityMotionModel),
        ("odometry_model", odometry_model, OdometryMotionModel),
        ("sensor", sensor, RangeBearingModel),
    ):
        if not isinstance(model, kind):
            raise InputError(f"{name} must be a {kind.__name__}, got {type(model).__name__}")
    check_raster_resolution(np.asarray(world.segments, dtype=np.float64), truth_resolution)
    return angle_increment, angle_min


def simulate_office(seed: int = 0, steps: int = 400, **options: Any) -> SimRun:
    """Simulate ``steps`` steps in the office; ``options`` as for :func:`simulate_world` (its defaults: 361 beams
    over 180 degrees, 12 m range, 0.1 s steps). The same arguments give the same run."""
    office = World(office_segments(), office_landmarks(), np.array(WAYPOINTS))
    return simulate_world(office, seed=seed, steps=steps, **options)


def simulate_world(
    world: World,
    *,
    seed: int = 0,
    steps: int = 400,
    n_beams: int = 361,
    range_max: float = 12.0,
    fov: float = math.pi,
    laser_sigma: float = 0.01,
    dt: float = 0.1,
    truth_resolution: float = 0.05,
    max_speed: float = MAX_SPEED,
    velocity_model: VelocityMotionModel = VelocityMotionModel(),
    odometry_model: OdometryMotionModel = OdometryMotionModel(),
    sensor: RangeBearingModel = RangeBearingModel(sigma_range=0.1, sigma_bearing=0.03),
    landmark_range_max: float = 6.0,
    landmark_fov: float = math.pi,
) -> SimRun:
    """Simulate ``steps`` steps of ``dt`` s in ``world``, the robot driving its route at up to ``max_speed`` m/s;
    the same arguments give the same run.

    Laser: ``n_beams`` beams spread evenly over ``fov`` rad centred on the laser's heading, ranges to
    ``range_max`` m with Gaussian noise of ``laser_sigma`` m. Landmark sensor: ``sensor`` noise, range
    ``landmark_range_max`` m, field of view ``landmark_fov`` rad. The truth raster has cells of
    ``truth_resolution`` m. Noise models: ``velocity_model`` (true motion around the commands) and
    ``odometry_model`` (odometry readings around the true motion).

    InputError (a ValueError) for an option it cannot use, before any work (:func:`_check_options`).
    """
    angle_increment, angle_min = _check_options(
        world,
        steps,
        n_beams,
        range_max,
        fov,
        laser_sigma,
        dt,
        truth_resolution,
        max_speed,
        landmark_range_max,
        landmark_fov,
        velocity_model,
        odometry_model,
        sensor,
    )
    motion_rng, odometry_rng, landmark_rng, laser_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    segments, landmarks = world.segments, world.landmarks
    true_poses, commands = _drive(steps, dt, velocity_model, motion_rng, world.waypoints, max_speed)
    odometry = _odometry(true_poses, odometry_model, odometry_rng)
    landmark_step, landmark_id, landmark_z = _landmark_measurements(
        true_poses, landmarks, segments, sensor, landmark_range_max, landmark_fov, landmark_rng
    )

    offset = np.array(LASER_OFFSET)
    beam_angles = angle_min + angle_increment * np.arange(n_beams)
    origins, exact, endpoints = _laser_rays(true_poses, offset, beam_angles, segments, range_max)
    noisy = np.where(
        np.isfinite(exact),
        np.maximum(exact + laser_rng.standard_normal(exact.shape) * laser_sigma, LASER_RANGE_MIN),
        np.inf,
    )
    occupied, visible, origin = truth_raster(segments, origins, endpoints, truth_resolution)
    return SimRun(
        stamps=np.arange(steps) * dt,
        true_poses=true_poses,
        commands=commands,
        odometry=odometry,
        landmark_step=landmark_step,
        landmark_id=landmark_id,
        landmark_z=landmark_z,
        ranges=noisy.reshape(steps, n_beams).astype(np.float32),
        angle_min=float(angle_min),
        angle_increment=float(angle_increment),
        range_min=LASER_RANGE_MIN,
        range_max=float(range_max),
        sensor_offset=offset,
        landmarks=landmarks,
        segments=segments,
        truth_occupied=occupied,
        truth_visible=visible,
        truth_origin=origin,
        truth_resolution=float(truth_resolution),
        velocity_model=velocity_model,
        odometry_model=odometry_model,
        sensor=sensor,
    )
