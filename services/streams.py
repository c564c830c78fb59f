"""Turn a dataset into the per-scan messages a source publishes (no networking here).

A :class:`Stream` is one robot's run as a list of steps; step ``seq`` holds the messages stamped with that
seq, in publication order: the LaserScan (when the dataset has a laser), Odometry and LandmarkObservations
(when it has them, for a SLAM node) and the pose distribution (when the dataset has poses, e.g. a posed-scan
file: then no SLAM node is needed). ``prior`` is where a SLAM filter starts (published on pg/<robot>/prior).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from schemas.files import PosedScans
from schemas.messages import LandmarkObservations, LaserScan, Odometry, PoseGaussian, PoseSamples
from schemas.wire import Message
from slam.laserlog import NO_RETURN_RANGE

if TYPE_CHECKING:
    from slam.sequence import SlamSequence


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


def _scan(robot: str, seq: int, stamp: float, scans: Scans, t: int, no_return_range: float | None) -> LaserScan:
    """Row t of ``scans`` as the LaserScan of ``seq``, with the scan's own beam count and geometry; its beams with no
    return clear free space up to ``no_return_range`` m (at most the scan's range_max; None: range_max)."""
    beams = getattr(scans, "beams", None)
    offset = np.asarray(scans.sensor_offset, np.float64)
    range_max = _of_scan(scans.range_max, t)
    return LaserScan(
        robot=robot,
        seq=seq,
        stamp=stamp,
        ranges=scans.ranges[t] if beams is None else scans.ranges[t, : int(beams[t])],
        angle_min=_of_scan(scans.angle_min, t),
        angle_increment=_of_scan(scans.angle_increment, t),
        range_min=_of_scan(scans.range_min, t),
        range_max=range_max,
        sensor_offset=offset if offset.ndim == 1 else offset[t],
        no_return_range=range_max if no_return_range is None else min(float(no_return_range), range_max),
    )


def _of_scan(value: float | np.ndarray, t: int) -> float:
    """Scan t's value of a geometry field that holds one value for every scan or one per scan."""
    array = np.asarray(value, np.float64)
    return float(array if array.ndim == 0 else array[t])


def _prior(robot: str, stamp: float, pose) -> PoseGaussian:
    return PoseGaussian(robot=robot, seq=0, stamp=float(stamp), mean=np.asarray(pose, np.float64), cov=np.zeros((3, 3)))


class Scans(Protocol):
    """Laser scans (T, B) with their geometry: angle_min, angle_increment, range_min and range_max one value for
    every scan or one per scan (T,), sensor_offset (3,) or (T, 3), and optionally ``beams`` (T,), each scan's
    beam count (its readings are the first of its row): schemas.files.PosedScans, slam.simulator.SimRun or
    slam.laserlog.LaserLog."""

    @property
    def ranges(self) -> np.ndarray: ...

    @property
    def angle_min(self) -> float | np.ndarray: ...

    @property
    def angle_increment(self) -> float | np.ndarray: ...

    @property
    def range_min(self) -> float | np.ndarray: ...

    @property
    def range_max(self) -> float | np.ndarray: ...

    @property
    def sensor_offset(self) -> np.ndarray: ...


def _commands(sequence: SlamSequence | None, seq: int) -> np.ndarray:
    """The velocity commands (K, 3) of step ``seq`` of ``sequence`` (none without one)."""
    if sequence is None:
        return np.zeros((0, 3))
    return sequence.controls[sequence.control_ptr[seq] : sequence.control_ptr[seq + 1]]


def _landmarks(robot: str, seq: int, stamp: float, sequence: SlamSequence | None) -> LandmarkObservations:
    """The landmark measurements of step ``seq`` of ``sequence`` (none without one)."""
    ids, z = np.zeros(0, np.int64), np.zeros((0, 2))
    if sequence is not None:
        rows = slice(sequence.measurement_ptr[seq], sequence.measurement_ptr[seq + 1])
        ids, z = sequence.landmark_ids[rows], sequence.measurements[rows]
    z = np.asarray(z, np.float64).reshape(-1, 2)
    return LandmarkObservations(
        robot=robot, seq=seq, stamp=stamp, ids=np.asarray(ids, np.int64), ranges=z[:, 0], bearings=z[:, 1]
    )


def posed_stream(posed: PosedScans, robot: str) -> Stream:
    """A posed-scan file: per row a LaserScan (with the scan's own geometry) and its pose distribution. A beam with
    no return clears free space up to range_max, as the file format says (docs/formats.md; a writer that means it to
    say nothing writes 0, no reading)."""
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
        steps.append(Step(stamp, (_scan(robot, t, stamp, posed, t, None), pose)))
    return Stream(robot, steps, prior=None, has_poses=True)


def slam_input_stream(
    robot: str,
    stamps: np.ndarray,
    *,
    scans: Scans | None,
    odometry: np.ndarray | None,
    sequence: SlamSequence | None,
    initial_pose: np.ndarray,
    no_return_range: float | None = None,
) -> Stream:
    """What a SLAM node needs at each of the T ``stamps`` (s): the scan (when there are ``scans``; its beams with no
    return clearing free space up to ``no_return_range`` m, None: range_max), the odometry pose reading (when there
    is ``odometry``, (T, 3)), and the velocity commands and landmark measurements of the step in ``sequence`` (none
    without one). The SLAM prior is ``initial_pose``."""
    steps = []
    for t, stamp in enumerate(np.asarray(stamps, np.float64).tolist()):
        pose = odometry[t : t + 1] if odometry is not None else np.zeros((0, 3))
        messages = [
            Odometry(robot=robot, seq=t, stamp=stamp, pose=pose, commands=_commands(sequence, t)),
            _landmarks(robot, t, stamp, sequence),
        ]
        if scans is not None:
            messages.insert(0, _scan(robot, t, stamp, scans, t, no_return_range))
        steps.append(Step(stamp, tuple(messages)))
    return Stream(robot, steps, prior=_prior(robot, stamps[0], initial_pose), has_poses=False)


def sim_stream(run, robot: str) -> Stream:
    """A simulated run (slam.simulator.SimRun or a simulator folder's pieces): scans, odometry readings,
    velocity commands and landmark measurements; the SLAM prior is the true first pose. The simulated laser misses
    nothing within range_max, so its beams with no return clear free space up to it."""
    return slam_input_stream(
        robot,
        run.stamps,
        scans=run,
        odometry=run.odometry,
        sequence=run.log().sequence("velocity"),
        initial_pose=run.true_poses[0],
    )


def sim_folder_stream(folder: Path, robot: str) -> Stream:
    """A folder written by `posegrid simulate`: scans.npz (its poses, the true ones, are not sent),
    controls.npz and landmarks.npz; the beams with no return clear free space up to range_max, as
    :func:`sim_stream`'s."""
    from schemas.files import load_posed_scans
    from slam.simlog import load_sim_log

    log = load_sim_log(folder)
    scans = load_posed_scans(folder / "scans.npz") if (folder / "scans.npz").is_file() else None
    return slam_input_stream(
        robot,
        log.stamps,
        scans=scans,
        odometry=log.odometry,
        sequence=log.sequence("velocity"),
        initial_pose=log.initial_pose,
    )


def mrclam_stream(folder: Path, robot_number: int, robot: str, period: float = 0.2) -> Stream:
    """One robot of an MRCLAM folder: velocity commands and landmark measurements (no laser) as logged, stepped
    every ``period`` s and at every measurement, as `posegrid slam` reads them; the prior is the first ground-truth
    pose. A robot's calibration is the SLAM node's (--calibration, --profile)."""
    from slam.mrclam import mrclam_sequence, read_mrclam

    sequence = mrclam_sequence(read_mrclam(folder, robot_number), period=period)
    return slam_input_stream(
        robot, sequence.stamps, scans=None, odometry=None, sequence=sequence, initial_pose=sequence.initial_pose
    )


def laser_log_stream(log, robot: str, no_return_range: float = NO_RETURN_RANGE) -> Stream:
    """A laser log (slam.laserlog.LaserLog, read from a CARMEN log or a ROS bag): scans with the odometry pose at
    each scan (for grid FastSLAM); no landmarks. The prior is the first odometry pose (the map frame is the
    odometry frame). A real laser's beams with no return clear free space up to ``no_return_range`` m (at most a
    scan's range_max; by default 0, :data:`slam.laserlog.NO_RETURN_RANGE`: they say nothing)."""
    return slam_input_stream(
        robot,
        log.stamps,
        scans=log,
        odometry=log.odometry,
        sequence=None,
        initial_pose=log.odometry[0],
        no_return_range=no_return_range,
    )
