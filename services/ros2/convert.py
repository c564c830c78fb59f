"""ROS 2 messages to and from posegrid's (no networking here).

In: a ``sensor_msgs/LaserScan`` becomes posegrid's LaserScan as the bag reader reads one (slam.rosbag_reader: a
reading at or beyond range_max is no return, +inf; a range_max of +inf or beyond 1 km is read as 1 km; NaN and -inf
say nothing about free space and become 0, below range_min, which is raised to 1 mm when the laser gives 0);
transforms and odometry become (x m, y m, yaw rad); ``geometry_msgs/PoseWithCovarianceStamped`` becomes a
PoseGaussian (x, y, yaw of the 6 x 6 covariance) and ``geometry_msgs/PoseArray`` or ``nav2_msgs/ParticleCloud`` a
PoseSamples (the array's poses weigh alike; the cloud's weights are normalised).

Out: map cells become ``nav_msgs/OccupancyGrid`` values, the occupancy probability as 0 .. 100 and -1 where no beam
has been; the variance layer likewise, as 100 * variance / scale clipped to 0 .. 100; pose samples become a
``geometry_msgs/PoseArray`` and their fitted Gaussian a ``PoseWithCovarianceStamped``. Frames: poses are the robot's
in the map frame (REP 105), the grid's origin is the lower-left corner of its cell (0, 0), rows run along +y.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mapping.grid import probability_of
from schemas.messages import LaserScan, PoseGaussian, PoseSamples
from schemas.wire import Message, MessageError
from services.ros2 import types
from slam.laserlog import plausible_pose
from slam.rosbag_reader import MIN_RANGE_FLOOR, Mount, header_stamp, quaternion_yaw, scan_geometry, wire_scan_problem
from slam.scoring import fit_gaussian

#: indices of x, y and yaw in a ROS 6 x 6 pose covariance (x, y, z, roll, pitch, yaw), row major
COVARIANCE_AXES = (0, 1, 5)
#: ns per s
NS = 1_000_000_000


class ConversionError(ValueError):
    """A ROS message posegrid cannot take; ``kind`` names why (the rejection counters' kind)."""

    def __init__(self, kind: str, detail: str):
        super().__init__(detail)
        self.kind = kind


def stamp_of(header: Any) -> float:
    """A header's stamp in s."""
    return header_stamp(header)


def transform_pose(transform: Any) -> tuple[float, float, float]:
    """(x m, y m, yaw rad) of a ``geometry_msgs/Transform`` projected onto the plane."""
    t, q = transform.translation, transform.rotation
    return (float(t.x), float(t.y), quaternion_yaw(q))


def pose_of(pose: Any) -> tuple[float, float, float]:
    """(x m, y m, yaw rad) of a ``geometry_msgs/Pose`` projected onto the plane."""
    p, q = pose.position, pose.orientation
    return (float(p.x), float(p.y), quaternion_yaw(q))


def scan_problem(msg: Any) -> str:
    """Why a ROS LaserScan cannot become posegrid's, or "": a non-finite stamp or geometry, no ranges, or what the
    wire's LaserScan refuses (slam.rosbag_reader.wire_scan_problem)."""
    geometry = scan_geometry(msg)
    ranges = np.asarray(msg.ranges, dtype=np.float32)
    if not (all(math.isfinite(g) for g in geometry) and math.isfinite(stamp_of(msg.header))) or ranges.size == 0:
        return "no ranges, or a non-finite stamp or geometry"
    return wire_scan_problem(ranges, *geometry)


def encoded(message: Message, kind: str) -> bytes:
    """The wire bytes of ``message`` (encoding validates it); raises :class:`ConversionError` of ``kind`` when the
    wire refuses it."""
    try:
        return message.encode()
    except MessageError as exc:
        raise ConversionError(kind, str(exc)) from None


def to_laser_scan(msg: Any, robot: str, seq: int, mount: Mount, no_return_range: float) -> LaserScan:
    """posegrid's LaserScan of a ROS LaserScan ``msg`` that :func:`scan_problem` passes, the laser at ``mount`` on the
    robot (its beams as a level laser's: slam.rosbag_reader.Mount; not validated yet: :func:`encoded`), its beams
    with no return clearing free space up to ``no_return_range`` m (at most its range_max)."""
    range_max = scan_geometry(msg)[3]
    ranges = np.array(msg.ranges, dtype=np.float32)
    ranges[ranges >= range_max] = np.inf
    ranges[np.isnan(ranges) | np.isneginf(ranges)] = 0.0  # invalid, or too close: below range_min, skipped
    angle_min, angle_increment = mount.beam_angles(float(msg.angle_min), float(msg.angle_increment))
    return LaserScan(
        robot=robot,
        seq=seq,
        stamp=stamp_of(msg.header),
        angle_min=angle_min,
        angle_increment=angle_increment,
        range_min=max(float(msg.range_min), MIN_RANGE_FLOOR),
        range_max=range_max,
        sensor_offset=np.array(mount.pose, dtype=np.float64),
        ranges=ranges,
        no_return_range=min(float(no_return_range), range_max),
    )


def to_gaussian(msg: Any, robot: str, seq: int) -> PoseGaussian:
    """A PoseGaussian of a ``PoseWithCovarianceStamped`` (x, y, yaw and their covariance); raises
    :class:`ConversionError` ("pose") for a pose or covariance the wire refuses."""
    mean = pose_of(msg.pose.pose)
    full = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    cov = full[np.ix_(COVARIANCE_AXES, COVARIANCE_AXES)]
    if not plausible_pose(mean) or not np.isfinite(cov).all():
        raise ConversionError("pose", "a pose or covariance that is not finite or lies beyond the pose limit")
    message = PoseGaussian(robot=robot, seq=seq, stamp=stamp_of(msg.header), mean=np.array(mean), cov=cov)
    encoded(message, "pose")
    return message


def to_samples(msg: Any, robot: str, seq: int, weighted: bool) -> PoseSamples:
    """PoseSamples of a ``PoseArray`` (``weighted`` False: equal weights) or a ``nav2_msgs/ParticleCloud``
    (``weighted``: its weights, normalised); raises :class:`ConversionError` ("pose") when the poses or weights are
    unusable (none, not finite, negative, summing to 0, too many). When every pose weighs the same (a PoseArray, a
    cloud just resampled) the one nearest their mean comes first (:func:`central_first`): a mapper's ``--mode ml``
    takes the first of equal weights, and the first of an AMCL cloud is any particle."""
    poses = [particle.pose for particle in msg.particles] if weighted else list(msg.poses)
    if not poses:
        raise ConversionError("pose", "no poses")
    samples = np.array([pose_of(pose) for pose in poses], dtype=np.float64)
    if weighted:
        weights = np.array([float(particle.weight) for particle in msg.particles])
        total = float(weights.sum()) if np.isfinite(weights).all() and (weights >= 0).all() else math.nan
        if not total > 0:
            raise ConversionError("pose", "particle weights that are negative, not finite or sum to 0")
        weights = weights / total
    else:
        weights = np.full(len(poses), 1.0 / len(poses))
    if not np.isfinite(samples).all():
        raise ConversionError("pose", "poses that are not finite")
    if np.all(weights == weights[0]):
        samples = central_first(samples)
    message = PoseSamples(robot=robot, seq=seq, stamp=stamp_of(msg.header), samples=samples, weights=weights)
    encoded(message, "pose")
    return message


def central_first(samples: np.ndarray) -> np.ndarray:
    """Equal-weight pose samples (M, 3) (m, rad) reordered so that the one nearest their mean (Mahalanobis under
    their fitted Gaussian, yaw circular; slam.scoring.fit_gaussian) comes first, the others in their order; a map of
    them all is the same, and the first stands for the most likely pose."""
    if len(samples) < 2:
        return samples
    mean, cov = fit_gaussian(samples[None], np.ones((1, len(samples))))
    offset = samples - mean[0]
    offset[:, 2] = np.angle(np.exp(1j * offset[:, 2]))  # (yaw differences wrapped)
    distance = np.einsum("mi,ij,mj->m", offset, np.linalg.pinv(cov[0], hermitian=True), offset)
    first = int(np.argmin(distance))
    return np.concatenate([samples[first : first + 1], np.delete(samples, first, axis=0)])


# --------------------------------------------------------------------------------------------- out


#: the seconds a builtin_interfaces/Time holds (int32)
TIME_SECONDS = (-(2**31), 2**31 - 1)


def header(stamp: float, frame: str) -> Any:
    """A ``std_msgs/Header`` at ``stamp`` s in ``frame``, clamped to the times a ROS Time holds (int32 seconds): a
    scan stamped 2147483647.999999999 s, which rounds to 2^31 as a float, stamps the map with the last nanosecond
    of that range instead of failing every later message of the map."""
    if not TIME_SECONDS[0] <= stamp < TIME_SECONDS[1] + 1:
        sec, nanosec = (TIME_SECONDS[1], NS - 1) if stamp > 0 else (TIME_SECONDS[0], 0)
        time = types.field_class("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)
        return types.field_class("std_msgs/msg/Header")(stamp=time, frame_id=frame)
    sec = math.floor(stamp)
    nanosec = min(round((stamp - sec) * NS), NS - 1)
    time = types.field_class("builtin_interfaces/msg/Time")(sec=int(sec), nanosec=int(nanosec))
    return types.field_class("std_msgs/msg/Header")(stamp=time, frame_id=frame)


def ros_pose(x: float, y: float, yaw: float) -> Any:
    """A ``geometry_msgs/Pose`` in the plane."""
    point = types.field_class("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0)
    quaternion = types.field_class("geometry_msgs/msg/Quaternion")(
        x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0)
    )
    return types.field_class("geometry_msgs/msg/Pose")(position=point, orientation=quaternion)


def pose_array(message: PoseSamples, frame: str) -> Any:
    """A ``geometry_msgs/PoseArray`` of the samples of ``message``, stamped as it is."""
    poses = [ros_pose(*sample) for sample in message.samples.tolist()]
    return types.MessageType(types.POSE_ARRAY).cls()(header=header(message.stamp, frame), poses=poses)


def fitted_gaussian(message: PoseSamples | PoseGaussian) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and covariance (3, 3) of a pose distribution: a Gaussian's own, or the samples' weighted mean
    (circular for yaw) and covariance (slam.scoring.fit_gaussian)."""
    if isinstance(message, PoseGaussian):
        return message.mean, message.cov
    mean, cov = fit_gaussian(message.samples[None], message.weights[None])
    return mean[0], cov[0]


def pose_with_covariance(message: PoseSamples | PoseGaussian, frame: str) -> Any:
    """A ``PoseWithCovarianceStamped`` of the fitted Gaussian of ``message`` (z, roll and pitch: variance 0)."""
    mean, cov = fitted_gaussian(message)
    full = np.zeros((6, 6))
    full[np.ix_(COVARIANCE_AXES, COVARIANCE_AXES)] = cov
    with_cov = types.field_class("geometry_msgs/msg/PoseWithCovariance")(pose=ros_pose(*mean), covariance=full.ravel())
    return types.MessageType(types.POSE_COVARIANCE).cls()(header=header(message.stamp, frame), pose=with_cov)


def occupancy_values(logodds: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """OccupancyGrid values (int8) of cells: round(100 * occupancy probability), -1 where unobserved."""
    values = np.rint(100.0 * probability_of(logodds).astype(np.float64)).astype(np.int8)
    values[~observed] = -1
    return values


def variance_values(variance: np.ndarray, observed: np.ndarray, scale: float) -> np.ndarray:
    """OccupancyGrid values (int8) of the variance layer: round(100 * variance / scale) clipped to 0 .. 100, -1
    where unobserved; ``scale`` in the variance's unit (log-odds squared)."""
    values = np.rint(np.clip(100.0 * variance.astype(np.float64) / scale, 0.0, 100.0)).astype(np.int8)
    values[~observed] = -1
    return values


def occupancy_grid(values: np.ndarray, origin: tuple[float, float], resolution: float, stamp: float, frame: str) -> Any:
    """A ``nav_msgs/OccupancyGrid`` of ``values`` (H, W) int8, row = y, cell (0, 0)'s lower-left corner at ``origin``
    (m) in ``frame``, cells ``resolution`` m."""
    height, width = values.shape
    time = header(stamp, frame).stamp
    info = types.field_class("nav_msgs/msg/MapMetaData")(
        map_load_time=time,
        resolution=float(resolution),
        width=int(width),
        height=int(height),
        origin=ros_pose(origin[0], origin[1], 0.0),
    )
    grid_type = types.MessageType(types.OCCUPANCY_GRID)
    return grid_type.cls()(header=header(stamp, frame), info=info, data=np.ascontiguousarray(values).ravel())


def grid_update(values: np.ndarray, x: int, y: int, stamp: float, frame: str) -> Any:
    """A ``map_msgs/OccupancyGridUpdate`` of ``values`` (H, W) int8 placed at column ``x``, row ``y`` of the grid
    last published on ``map``."""
    height, width = values.shape
    update_type = types.MessageType(types.GRID_UPDATE)
    return update_type.cls()(
        header=header(stamp, frame),
        x=int(x),
        y=int(y),
        width=int(width),
        height=int(height),
        data=np.ascontiguousarray(values).ravel(),
    )
