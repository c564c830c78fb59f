"""Turn a dataset into the per-scan messages a source publishes (no networking here).

A :class:`Stream` is one robot's run as a list of steps; step ``seq`` holds the messages stamped with that
seq, in publication order: the LaserScan (when the dataset has a laser), Odometry and LandmarkObservations
(when it has them, for a SLAM node) and the pose distribution (when the dataset has poses, e.g. a posed-scan
file: then no SLAM node is needed). ``prior`` is where a SLAM filter starts (published on pg/<robot>/prior).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.files import PosedScans
from schemas.messages import LandmarkObservations, LaserScan, Odometry, PoseGaussian, PoseSamples
from schemas.wire import Message


@dataclass(frozen=True)
class Step:
    """The messages of one seq and the sensor time they share (s)."""

    stamp: float
    messages: tuple[Message, ...]


@dataclass(frozen=True)
class Stream:
    """One robot's run: its steps, how many carry a scan, and the SLAM prior (None: the poses are given)."""

    robot: str
    steps: list[Step]
    prior: PoseGaussian | None
    has_poses: bool

    @property
    def scans(self) -> int:
        return sum(isinstance(m, LaserScan) for step in self.steps for m in step.messages)


def _scan(robot: str, seq: int, stamp: float, ranges: np.ndarray, geometry: dict) -> LaserScan:
    return LaserScan(robot=robot, seq=seq, stamp=stamp, ranges=ranges, **geometry)


def _geometry(source) -> dict:
    return {
        "angle_min": float(source.angle_min),
        "angle_increment": float(source.angle_increment),
        "range_min": float(source.range_min),
        "range_max": float(source.range_max),
        "sensor_offset": np.asarray(source.sensor_offset, np.float64),
    }


def _prior(robot: str, stamp: float, pose) -> PoseGaussian:
    return PoseGaussian(robot=robot, seq=0, stamp=float(stamp), mean=np.asarray(pose, np.float64), cov=np.zeros((3, 3)))


def _landmarks(robot, seq, stamp, ids, z) -> LandmarkObservations:
    z = np.asarray(z, np.float64).reshape(-1, 2)
    return LandmarkObservations(
        robot=robot, seq=seq, stamp=stamp, ids=np.asarray(ids, np.int64), ranges=z[:, 0], bearings=z[:, 1]
    )


def posed_stream(posed: PosedScans, robot: str) -> Stream:
    """A posed-scan file: per row a LaserScan and its pose distribution."""
    geometry = _geometry(posed)
    poses = posed.poses
    steps = []
    for t, stamp in enumerate(posed.stamps.tolist()):
        pose: PoseGaussian | PoseSamples
        if poses.is_gaussian:
            mean, cov = poses.gaussian()
            pose = PoseGaussian(robot=robot, seq=t, stamp=stamp, mean=mean[t], cov=cov[t])
        else:
            samples, weights = poses.weighted_samples()
            pose = PoseSamples(robot=robot, seq=t, stamp=stamp, samples=samples[t], weights=weights[t])
        steps.append(Step(stamp, (_scan(robot, t, stamp, posed.ranges[t], geometry), pose)))
    return Stream(robot, steps, prior=None, has_poses=True)


def slam_input_stream(
    robot: str,
    stamps: np.ndarray,
    *,
    ranges: np.ndarray | None,
    geometry: dict | None,
    odometry: np.ndarray | None,
    commands: np.ndarray | None,
    control_ptr: np.ndarray | None,
    landmark_ids: np.ndarray,
    landmark_z: np.ndarray,
    measurement_ptr: np.ndarray,
    initial_pose: np.ndarray,
) -> Stream:
    """Scans (optional, with their ``geometry``) with what a SLAM node needs per step: odometry pose readings
    (T, 3) and/or velocity commands (K, 3) split by ``control_ptr`` (T + 1,), and landmarks split by
    ``measurement_ptr`` (T + 1,)."""
    steps = []
    for t, stamp in enumerate(np.asarray(stamps, np.float64).tolist()):
        pose = odometry[t : t + 1] if odometry is not None else np.zeros((0, 3))
        cmds = np.zeros((0, 3))
        if commands is not None:
            assert control_ptr is not None  # commands come with the pointer that splits them
            cmds = commands[control_ptr[t] : control_ptr[t + 1]]
        messages = [
            Odometry(robot=robot, seq=t, stamp=stamp, pose=pose, commands=cmds),
            _landmarks(
                robot,
                t,
                stamp,
                landmark_ids[measurement_ptr[t] : measurement_ptr[t + 1]],
                landmark_z[measurement_ptr[t] : measurement_ptr[t + 1]],
            ),
        ]
        if ranges is not None:
            assert geometry is not None  # scans come with their geometry
            messages.insert(0, _scan(robot, t, stamp, ranges[t], geometry))
        steps.append(Step(stamp, tuple(messages)))
    return Stream(robot, steps, prior=_prior(robot, stamps[0], initial_pose), has_poses=False)


def sim_stream(run, robot: str) -> Stream:
    """A simulated run (slam.simulator.SimRun or a simulator folder's pieces): scans, odometry readings,
    velocity commands and landmark measurements; the SLAM prior is the true first pose."""
    sequence = run.log().sequence("velocity")
    return slam_input_stream(
        robot,
        run.stamps,
        ranges=run.ranges,
        geometry=_geometry(run),
        odometry=run.odometry,
        commands=sequence.controls,
        control_ptr=sequence.control_ptr,
        landmark_ids=sequence.landmark_ids,
        landmark_z=sequence.measurements,
        measurement_ptr=sequence.measurement_ptr,
        initial_pose=run.true_poses[0],
    )


def sim_folder_stream(folder: Path, robot: str) -> Stream:
    """A folder written by `posegrid simulate`: scans.npz (its poses, the true ones, are not sent),
    controls.npz and landmarks.npz."""
    from schemas.files import load_posed_scans
    from slam.simlog import load_sim_log

    log = load_sim_log(folder)
    scans = load_posed_scans(folder / "scans.npz") if (folder / "scans.npz").is_file() else None
    sequence = log.sequence("velocity")
    return slam_input_stream(
        robot,
        log.stamps,
        ranges=scans.ranges if scans is not None else None,
        geometry=_geometry(scans) if scans is not None else None,
        odometry=log.odometry,
        commands=sequence.controls,
        control_ptr=sequence.control_ptr,
        landmark_ids=sequence.landmark_ids,
        landmark_z=sequence.measurements,
        measurement_ptr=sequence.measurement_ptr,
        initial_pose=log.initial_pose,
    )


def mrclam_stream(
    folder: Path,
    robot_number: int,
    robot: str,
    period: float = 0.2,
    raw_ranges: bool = False,
    raw_commands: bool = False,
) -> Stream:
    """One robot of an MRCLAM folder: velocity commands and landmark measurements (no laser), stepped every
    ``period`` s and at every measurement, as `posegrid slam` reads them (ranges calibrated unless
    ``raw_ranges``, commands scaled to the executed speeds unless ``raw_commands``); the prior is the first
    ground-truth pose."""
    from slam.mrclam import MRCLAM_RANGE_CALIBRATION, MRCLAM_VELOCITY_SCALE, mrclam_sequence, read_mrclam

    sequence = mrclam_sequence(
        read_mrclam(folder, robot_number),
        period=period,
        range_calibration=None if raw_ranges else MRCLAM_RANGE_CALIBRATION,
        velocity_scale=None if raw_commands else MRCLAM_VELOCITY_SCALE,
    )
    return slam_input_stream(
        robot,
        sequence.stamps,
        ranges=None,
        geometry=None,
        odometry=None,
        commands=sequence.controls,
        control_ptr=sequence.control_ptr,
        landmark_ids=sequence.landmark_ids,
        landmark_z=sequence.measurements,
        measurement_ptr=sequence.measurement_ptr,
        initial_pose=sequence.initial_pose,
    )


def laser_log_stream(log, robot: str) -> Stream:
    """A laser log (slam.laserlog.LaserLog, read from a CARMEN log or a ROS bag): scans with the odometry pose at
    each scan (for grid FastSLAM); no landmarks. The prior is the first odometry pose (the map frame is the
    odometry frame)."""
    steps = len(log.stamps)
    return slam_input_stream(
        robot,
        log.stamps,
        ranges=log.ranges,
        geometry=_geometry(log),
        odometry=log.odometry,
        commands=None,
        control_ptr=None,
        landmark_ids=np.zeros(0, np.int64),
        landmark_z=np.zeros((0, 2)),
        measurement_ptr=np.zeros(steps + 1, np.int64),
        initial_pose=log.odometry[0],
    )
