"""A SLAM node's state, without any networking: it decodes what arrives for its robot, files each message with
its step, takes the steps strictly in seq order (services.state.steps) through the filter and hands each pose it
gives to be published, keeping the poses for the node's history. services.nodes.slam_node puts the Zenoh
declarations around it, as services.nodes.mapper does around services.state.shard.

Landmark filters (odometry dead reckoning, EKF-SLAM, FastSLAM 1.0/2.0, slam/) take step ``seq`` when its
Odometry and LandmarkObservations are in; grid FastSLAM (slam/gridslam) when its LaserScan and Odometry
(with the odometry pose) are in. A message whose seq is not above every seq seen on its key arrived out of order:
it is reported (logged once per key, counted per key) and used if its step is still to come, else dropped. The
filter starts at ``--initial`` or at the prior the source publishes on pg/<robot>/prior. Per step, the pose is what
the offline `posegrid slam` writes for that step: mean and covariance (Gaussian filters) or particles and their
weights before resampling; grid FastSLAM gives the filtered particles (the offline run smooths them by ancestry,
which a live node cannot do).
"""

from __future__ import annotations

import copy
import logging
import math
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from schemas.messages import (
    LandmarkObservations,
    LaserScan,
    NodeStats,
    Odometry,
    PoseGaussian,
    PoseSamples,
    StreamEnd,
)
from services import keys
from services.process import RejectCounter, get_logger
from services.state.checks import SeqMessage, decode_of_robot, history_reply, robot_stream
from services.state.pose_history import PoseHistory
from services.state.steps import OutOfOrder, Released, StepAssembler
from slam.calibration import Calibration
from slam.ekf import EKFSLAM
from slam.gridslam import GridSlamConfig
from slam.gridslam.config import SPARSE_LOG_DRIVE, DriveTally, scan_drives
from slam.gridslam.health import ScanHealth
from slam.landmark_filter import LandmarkFilter
from slam.laserlog import POSE_LIMIT
from slam.motion import (
    SIDEWAYS_DECIDE_DISTANCE,
    VELOCITY_LIMIT,
    OdometryMotionModel,
    OmniOdometryMotionModel,
    SidewaysWatch,
    odometry_controls,
    split_odometry_motion,
)
from slam.odometry_jumps import MAX_ODOMETRY_STEP, OdometryJumps, Verdict
from slam.range_bearing import BEARING_LIMIT

if TYPE_CHECKING:
    from slam.gridslam.filter import GridFastSLAM

#: the parts of a step: the message of one seq on pg/<robot>/scan, odom or landmarks
StepPart = LaserScan | Odometry | LandmarkObservations
#: the streams a SLAM node reads, and the message types each may carry
EXPECTED: dict[str, tuple[type[StepPart | StreamEnd | PoseGaussian], ...]] = {
    keys.SCAN: (LaserScan,),
    keys.ODOM: (Odometry,),
    keys.LANDMARKS: (LandmarkObservations,),
    keys.END: (StreamEnd,),
    keys.PRIOR: (PoseGaussian,),
}
#: the parts a step may have, by stream: what a history reply about steps may carry
STEP_PARTS: dict[str, tuple[type[StepPart], ...]] = {
    keys.SCAN: (LaserScan,),
    keys.ODOM: (Odometry,),
    keys.LANDMARKS: (LandmarkObservations,),
}
#: the odometry motion model that moves a velocity-motion filter over steps that never arrived (NodeConfig.bridge)
DEFAULT_BRIDGE = OdometryMotionModel()
#: bytes of published poses kept for the node's history (the oldest go first): 1 KB a pose of 30 particles
POSE_HISTORY_BYTES = 64 * 2**20


class StepError(ValueError):
    """A step the filter cannot take (e.g. odometry motion without an odometry pose)."""


#: the distinct landmark ids a landmark filter may hold: each costs every particle its mean and covariance (about
#: 25 KB a landmark for FastSLAM 2.0's default particles), and three messages of 20 000 new ids took a node past
#: 5.8 GB and slowed every later step to seconds
MAX_LANDMARKS = 4096
#: the same for EKF-SLAM, whose joint covariance grows with the square of its landmarks (1 024: 34 MB, and each step
#: updates all of it)
MAX_EKF_LANDMARKS = 1024


def check_landmark_step(
    odom: Odometry,
    seen: LandmarkObservations,
    ids_held: set[int],
    known: bool,
    held: int = 0,
    limit: int = MAX_LANDMARKS,
) -> None:
    """StepError for a step of values no robot gives (valid on the wire, but they drove the filters to overflow,
    a division by zero or poses 10^6 m away): a velocity command beyond slam.motion.VELOCITY_LIMIT, commands that
    drive farther than slam.odometry_jumps.MAX_ODOMETRY_STEP in one step (0.5 m/s held for 2e4 s took a filter 10^4
    m away for good), a landmark
    range not in (0, POSE_LIMIT] m or a bearing beyond BEARING_LIMIT rad (the offline readers keep these out of a
    filter: an MRCLAM log's are skipped, a simulator folder's refused),
    or landmarks that could take the filter past ``limit`` (:data:`MAX_LANDMARKS`, or :data:`MAX_EKF_LANDMARKS`):
    with known ids, its new ids (``ids_held``: those it holds), else its measurements, each of which may start a
    landmark (``held``: the most a particle holds)."""
    if odom.commands.size and np.abs(odom.commands[:, :2]).max() > VELOCITY_LIMIT:
        raise StepError(
            f"seq {odom.seq}: a velocity command beyond +-{VELOCITY_LIMIT:g} m/s or rad/s (no robot's); its "
            f"largest is {np.abs(odom.commands[:, :2]).max():g}"
        )
    travel = float(np.abs(odom.commands[:, 0]) @ odom.commands[:, 2]) if odom.commands.size else 0.0
    if not travel <= MAX_ODOMETRY_STEP:
        raise StepError(
            f"seq {odom.seq}: its velocity commands drive {travel:.3g} m in one step (speed times dt, summed), more "
            f"than the {MAX_ODOMETRY_STEP:g} m a step may move (slam.odometry_jumps.MAX_ODOMETRY_STEP)"
        )
    ranges, bearings = seen.ranges, seen.bearings
    if ranges.size and not ((ranges > 0).all() and (ranges <= POSE_LIMIT).all()):
        raise StepError(f"seq {seen.seq}: a landmark range not in (0, {POSE_LIMIT:g}] m")
    if bearings.size and not (np.abs(bearings) <= BEARING_LIMIT).all():
        raise StepError(f"seq {seen.seq}: a landmark bearing beyond +-{BEARING_LIMIT:g} rad")
    if known:
        new = set(seen.ids.tolist()) - ids_held
        if len(ids_held) + len(new) > limit:
            raise StepError(
                f"seq {seen.seq}: {len(new)} new landmark ids would make {len(ids_held) + len(new)}, more than the "
                f"{limit} the filter holds"
            )
    elif held + ranges.size > limit:
        raise StepError(
            f"seq {seen.seq}: {ranges.size} measurements of unknown landmarks could take the filter from {held} "
            f"landmarks past the {limit} it holds"
        )


def landmarks_held(slam_filter: object) -> int:
    """The most landmarks a particle of ``slam_filter`` holds (FastSLAM's ``count``), or the EKF's; 0 for none."""
    count = getattr(slam_filter, "count", None)
    if isinstance(count, np.ndarray):
        return int(count.max()) if count.size else 0
    return int(getattr(slam_filter, "n_landmarks", 0))


@dataclass(frozen=True)
class NodeConfig:
    """robot: whose streams to follow; algorithm: odometry, ekf, fastslam1, fastslam2 or gridslam;
    make_filter(initial_pose) builds a landmark filter (None for gridslam); motion: "velocity" or
    "odometry" (which Odometry field the landmark filters read); initial: start pose or None to wait
    for the source's prior; grid_config, seed: grid FastSLAM's (max_range is capped at each scan's range_max);
    intake_capacity: bounded queue size; bridge: the odometry motion model that moves a velocity-motion filter
    over steps that never arrived, by the odometry poses around them (:class:`LandmarkDriver`); calibration: the
    corrections the landmark filters apply to the commands and measurements as they arrive (slam.calibration; None:
    as they come); max_landmarks: the landmarks a landmark filter may hold (None: :data:`MAX_LANDMARKS`,
    :data:`MAX_EKF_LANDMARKS` for EKF-SLAM); max_odometry_step: the farthest grid FastSLAM's odometry may move from
    one step to the next (m, :class:`GridDriver`)."""

    robot: str
    algorithm: str
    make_filter: Callable[[np.ndarray], object] | None
    motion: str = "velocity"
    initial: np.ndarray | None = None
    grid_config: GridSlamConfig | None = None
    seed: int = 0
    intake_capacity: int = 4096
    bridge: OdometryMotionModel | None = DEFAULT_BRIDGE
    calibration: Calibration | None = None
    max_landmarks: int | None = None
    max_odometry_step: float = MAX_ODOMETRY_STEP


@dataclass(frozen=True)
class Gap:
    """Seqs first..last never arrived before the step just taken; bridged: whether its motion covers theirs."""

    first: int
    last: int
    bridged: bool


class LandmarkDriver:
    """Feeds an EKF / FastSLAM / dead-reckoning filter one step at a time, as slam.sequence.run_filter does.

    Steps that never arrived (lost in transit: a router restart, a network gap) take their motion with them. With
    odometry motion the next step's controls come from the last odometry pose taken, so they cover the gap. With
    velocity motion the gap's commands are gone; when the odometry messages carry the dead-reckoned pose, the
    step after the gap is moved by the odometry poses around it instead, split into one piece per step it spans
    (slam.motion.split_odometry_motion), under ``bridge`` (an odometry motion model), and its own commands, which
    that motion includes, are not used. :attr:`last_gap` says what the step just taken did about a gap before
    it. With a ``calibration``, its corrections (command delay, speed scale and bias, range and bearing bias) apply
    to the commands and measurements as they arrive (slam.calibration.StepCorrector)."""

    needs = frozenset({keys.ODOM, keys.LANDMARKS})

    def __init__(
        self,
        slam_filter,
        motion: str,
        bridge: OdometryMotionModel | None = None,
        calibration: Calibration | None = None,
        max_landmarks: int | None = None,
    ):
        self.filter = slam_filter
        self.max_landmarks = max_landmarks  # (None: the filter's kind's default)
        self.motion = motion
        self.bridge = bridge
        self.corrector = None if calibration is None or calibration.is_identity() else calibration.step_corrector()
        self._last_pose: np.ndarray | None = None  # odometry pose of the last step taken (None: it had none)
        self._last_seq: int | None = None
        self._ids: set[int] = set()  # the landmark ids the filter has been given (known ids)
        self.last_gap: Gap | None = None
        # the odometry poses' jump rule (as grid FastSLAM's): not saved and restored with a step, so that the steps
        # it refused count towards a reset of the odometry
        self._jumps = OdometryJumps()

    def step(self, parts: dict) -> tuple[np.ndarray, np.ndarray]:
        odom: Odometry = parts[keys.ODOM]
        seen: LandmarkObservations = parts[keys.LANDMARKS]
        known = isinstance(self.filter, LandmarkFilter) and self.filter.known  # (dead reckoning has no landmarks)
        limit = self.max_landmarks or (MAX_EKF_LANDMARKS if isinstance(self.filter, EKFSLAM) else MAX_LANDMARKS)
        check_landmark_step(odom, seen, self._ids, known, 0 if known else landmarks_held(self.filter), limit)
        if known:
            self._ids.update(seen.ids.tolist())
        pose = odom.pose[0] if odom.pose.shape[0] else None
        if pose is not None:  # (a forged pose 10 km off moved the filter out and back, its covariance km wide)
            verdict = self._jumps.check(pose, odom.stamp)
            if verdict is Verdict.REFUSED:
                raise StepError(f"seq {odom.seq}: {self._jumps.reason}")
            if verdict is Verdict.REBASE:
                self._last_pose = None  # (the jump is no drive)
        gap = None if self._last_seq is None or odom.seq == self._last_seq + 1 else (self._last_seq + 1, odom.seq - 1)
        model = None
        if self.motion == "odometry":
            if pose is None:
                raise StepError(f"seq {odom.seq}: odometry motion needs the odometry pose, the message has none")
            controls = (
                np.zeros((0, 3)) if self._last_pose is None else odometry_controls(np.stack([self._last_pose, pose]))
            )
        elif gap is not None and pose is not None and self._last_pose is not None and self.bridge is not None:
            motion = odometry_controls(np.stack([self._last_pose, pose]))[0]
            spanned = odom.seq - gap[0] + 1  # the steps the motion covers: the gap's and this one
            controls, model = split_odometry_motion(motion, spanned), self.bridge
        else:
            controls = odom.commands
        measurements = np.column_stack([seen.ranges, seen.bearings])
        if self.corrector is not None:  # the delay line takes every step's commands, used or not
            commands, measurements = self.corrector(odom.commands, measurements)
            controls = commands if self.motion == "velocity" and model is None else controls
        if model is None:
            result = self.filter.step(controls, measurements, seen.ids)
        else:
            velocity, self.filter.motion = self.filter.motion, model
            try:
                result = self.filter.step(controls, measurements, seen.ids)
            finally:
                self.filter.motion = velocity
        self.last_gap = None if gap is None else Gap(*gap, bridged=self.motion == "odometry" or model is not None)
        self._last_pose = pose
        self._last_seq = odom.seq
        return result

    def save(self) -> object:
        """The filter's state before a step (a copy: a landmark filter's arrays are small)."""
        return copy.deepcopy((self.filter, self._last_pose, self._last_seq, self.corrector, self._ids))

    def restore(self, saved: object) -> None:
        """Go back to the state :meth:`save` returned, undoing a step whose pose could not be published."""
        assert isinstance(saved, tuple)  # (filter, odometry pose, seq, corrector, ids), as :meth:`save` made it
        self.filter, self._last_pose, self._last_seq, self.corrector, self._ids = saved
        self.last_gap = None


#: s between two questions to the source's history for a prior that never arrived (steps waiting for it)
PRIOR_RETRY = 1.0

#: seqs of steps the filter refused that a SLAM node remembers until it publishes again (for what it says of a gap)
REFUSED_KEPT = 1024


class GridDriver:
    """Feeds grid FastSLAM one scan at a time: integrate when due, else follow the odometry. A failed step is
    not undone (:meth:`save` keeps nothing): a copy of every particle's map per scan would cost more than the
    step. Odometry beyond the wire's pose limit never reaches it; a step whose odometry moved more than
    ``max_odometry_step`` (m, :data:`MAX_ODOMETRY_STEP` unless given) is refused before the filter sees it, unless
    REBASE_STEPS such steps in a row agree with each other (slam.odometry_jumps): then the odometry was reset, and
    the filter takes the new frame without moving."""

    needs = frozenset({keys.SCAN, keys.ODOM})

    def save(self) -> object:
        return None

    def restore(self, saved: object) -> None:
        pass

    def __init__(
        self,
        initial: np.ndarray,
        config: GridSlamConfig,
        seed: int,
        max_odometry_step: float = MAX_ODOMETRY_STEP,
        log: logging.Logger | None = None,
    ):
        self.initial = initial
        self.config = config
        self.seed = seed
        self.filter: GridFastSLAM | None = None  # made at the first scan, which gives the laser's geometry
        self.last_health: ScanHealth | None = None  # of the last integrated scan
        self.scans = 0  # integrated scans
        self.failed = 0  # of them, whose best match failed
        self._jumps = OdometryJumps(max_odometry_step)
        self._sideways: SidewaysWatch | None = SidewaysWatch()  # None once the odometry model is chosen
        self._drives = DriveTally()  # the drives between scans so far, for the motion step
        self._last_pose: np.ndarray | None = None  # the odometry of the last scan, for the next drive
        self._spread_rng = np.random.default_rng([seed, 1])  # the published samples' spread (as slam.gridslam.run's)
        self.log = get_logger("slam-node") if log is None else log

    def health(self) -> dict:
        """NodeStats' health: the last integrated scan's (slam.gridslam.health.ScanHealth; flags as 0 or 1, values
        not yet known left out), the counts of integrated and failed scans and the loop closures taken so far."""
        if self.last_health is None or self.filter is None:
            return {}
        figures = {k: float(v) for k, v in self.last_health.as_dict().items() if v is not None}
        closures = 0 if self.filter.loops is None else len(self.filter.loops.closures)
        return {
            **figures,
            "scans": float(self.scans),
            "failed_scans": float(self.failed),
            "loop_closures": float(closures),
        }

    def step(self, parts: dict) -> tuple[np.ndarray, np.ndarray]:
        scan: LaserScan = parts[keys.SCAN]
        odom: Odometry = parts[keys.ODOM]
        if odom.pose.shape[0] == 0:
            raise StepError(f"seq {odom.seq}: grid FastSLAM needs the odometry pose, the message has none")
        # (the filter's module, its loop closure and their scipy parts: imported by a grid FastSLAM node only, 0.6 s
        # that a landmark node's start would pay for nothing)
        from slam.gridslam.filter import GridFastSLAM, Laser

        angles = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.shape[0])
        if self.filter is None:  # as slam.gridslam.run_gridslam sets it up
            self.filter = GridFastSLAM(self.config, angles, scan.sensor_offset, scan.range_min, self.initial, self.seed)
        self._check_jump(odom.seq, odom.pose[0], float(odom.stamp))
        self._choose_odometry_model(odom.pose[0])
        self._choose_motion_step(odom.pose[0])
        if self.filter.due(odom.pose[0]):  # each scan with its own laser geometry
            laser = Laser.of(self.config, angles, scan.sensor_offset, scan.range_min, scan.range_max)
            poses, weights, _, report = self.filter.integrate(odom.pose[0], scan.ranges, laser)
            self.last_health = report.health
            self.scans += 1
            self.failed += int(report.health.failed)
            return self._published(poses, weights, self.filter.last_covariance)
        poses = self.filter.follow(odom.pose[0])
        return self._published(poses, self.filter.weights, self.filter.covariance(poses))

    def _published(
        self, poses: np.ndarray, weights: np.ndarray, covariance: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The pose samples (M, 3) and weights (M,) the node publishes for particles ``poses`` (M, 3) of ``weights``
        whose spread should be the filter's ``covariance`` (3, 3) (m, rad), the spread that resampling lost kept
        (slam.gridslam.honesty): equal-weight draws of that cloud (slam.gridslam.honesty.cloud_samples), from the
        node's seed. The particles alone agree to a centimetre where the filter is unsure by decimetres: published
        bare, the simulated office's true pose lay in their 95 % region at 56 and 83 % of the scans (seeds 1 and 2)."""
        if not self.config.keep_spread:
            return poses, weights
        from slam.gridslam.honesty import cloud_samples

        samples = cloud_samples(poses, weights, covariance, self._spread_rng)
        return samples, np.full(len(samples), 1.0 / len(samples))

    def _choose_odometry_model(self, pose: np.ndarray) -> None:
        """Once the odometry has travelled slam.motion.SIDEWAYS_DECIDE_DISTANCE, give the filter the omni odometry
        model if it travelled sideways for most of it (as `posegrid slam` decides on a whole log; a filter given
        the omni model keeps it)."""
        if self._sideways is None:
            return
        verdict = self._sideways.add(pose)
        if verdict is None:
            return
        self._sideways = None
        if verdict:
            assert self.filter is not None  # (made before the first step is watched)
            self.filter.motion = OmniOdometryMotionModel(self.config.motion_alphas)
            self.log.info(
                "the odometry travels sideways for most of its first %g m: a holonomic base, or a robot frame "
                "whose x axis is not the driving direction; using the omni odometry model",
                SIDEWAYS_DECIDE_DISTANCE,
            )

    def _choose_motion_step(self, pose: np.ndarray) -> None:
        """Count the drive from the last scan to ``pose`` (if it is one: slam.gridslam.config.scan_drives) and give the
        filter the motion step the drives so far call for (slam.gridslam.config.DriveTally: a sparse log's once at
        least half of them are long, as `posegrid slam --motion-step auto` decides on a whole log), logging each
        change."""
        if self._last_pose is not None:
            self._drives.add(scan_drives(np.stack([self._last_pose, pose])))
        self._last_pose = np.array(pose, np.float64)
        assert self.filter is not None  # (made before the first step is watched)
        step = self._drives.motion_step
        if step == self.filter.config.motion_step:
            return
        self.filter.config = replace(self.filter.config, motion_step=step)
        tally = self._drives
        if step is not None:
            self.log.info(
                "a sparse log so far (%d of its %d drives between scans are %g m or longer): a drive between two "
                "scans is taken as drives of %g m whose noise adds up",
                tally.long,
                tally.drives,
                SPARSE_LOG_DRIVE,
                step,
            )
        else:
            self.log.info(
                "no longer a sparse log (%d of its %d drives between scans are %g m or longer): the model's "
                "variances for each drive, as they are",
                tally.long,
                tally.drives,
                SPARSE_LOG_DRIVE,
            )

    def _check_jump(self, seq: int, pose: np.ndarray, stamp: float) -> None:
        """StepError for odometry ``pose`` (3,) at ``stamp`` (s) that jumped (slam.odometry_jumps); at a reset of the
        odometry the filter's odometry reference becomes ``pose``."""
        verdict = self._jumps.check(pose, stamp)
        if verdict is Verdict.REFUSED:
            raise StepError(f"seq {seq}: {self._jumps.reason}")
        if verdict is Verdict.REBASE:
            assert self.filter is not None  # (made before the first step is checked)
            self.filter.odometry_ref = None if self.filter.odometry_ref is None else np.array(pose, np.float64)
            if self._sideways is not None:
                self._sideways.restart()
            self._last_pose = None  # (the jump is no drive)


class SlamState:
    """One robot's SLAM node without its network: feed it with :meth:`handle` (and :meth:`take_history` at
    startup); it calls ``publish(payload)`` with each encoded pose, in seq order. Not thread-safe: callers serialise
    access (services.nodes.slam_node), all but :meth:`poses`, which any thread may call at any time.

    ``history(streams, first, last)``: (pg/<robot>/<stream>, payload) of the robot's messages of ``streams`` with
    seqs first..last (last None: every one from ``first``) that the source's history holds, in the order it sent
    them; the step assembler takes them for steps that did not all arrive. None: nothing is recovered."""

    def __init__(
        self,
        config: NodeConfig,
        rejects: RejectCounter,
        publish: Callable[[bytes], None],
        history: Callable[[frozenset[str], int, int | None], list[tuple[str, bytes]]] | None = None,
    ):
        self.config = config
        self.log = get_logger(f"slam-node[{config.robot}]")  # the logger services.nodes.slam_node writes to
        self.rejects = rejects
        self._publish = publish
        self._history = history
        self.received: Counter[str] = Counter()
        self.out_of_order: Counter[str] = Counter()
        self.published = 0
        self.steps_done = 0  # seqs taken, failed or skipped
        # seqs of steps the filter could not take since the last one published (REFUSED_KEPT at most, newest kept),
        # so that a gap over them is said as skipped, not as lost in transit
        self._refused: OrderedDict[int, None] = OrderedDict()
        self.started = time.monotonic()
        self.initial = config.initial
        self.driver: LandmarkDriver | GridDriver | None = None
        needs = GridDriver.needs if config.algorithm == "gridslam" else LandmarkDriver.needs
        self.steps: StepAssembler[SeqMessage] = StepAssembler(
            needs, recover=None if history is None else self._recover, same=lambda a, b: a.digest() == b.digest()
        )
        self._ready: list[tuple[int, dict]] = []
        self._highest_seq: dict[str, int] = {}
        self._history_high: dict[str, int] = {}  # per stream, the highest seq the source's history gave
        self._pose_history = PoseHistory(POSE_HISTORY_BYTES)  # (thread-safe: the node's queryable reads it)
        self._prior_asked = -math.inf  # time.monotonic() the source's history was last asked for a missed prior

    # ---------------------------------------------------------------------------- messages
    def handle(self, key: str, payload: bytes, from_history: bool = False) -> None:
        """Decode one message, file it with its step, and take every step that is now complete. A live message
        that the source's history gave already (:meth:`take_history`) is dropped without a word."""
        parsed = robot_stream(key, EXPECTED, self.rejects, self.config.robot)
        if parsed is None:
            return
        self.received[key] += 1
        stream = parsed[1]
        message = decode_of_robot(key, self.config.robot, payload, EXPECTED[stream], self.rejects)
        if message is None:
            return
        if isinstance(message, PoseGaussian):  # keys.PRIOR's type, and no other stream's
            if self.initial is None:
                self.initial = message.mean
                self.log.info("starting at the source's prior (%.3f m, %.3f m, %.3f rad)", *message.mean)
            self._take_ready()
        elif isinstance(message, StreamEnd):  # keys.END's
            # the steps lost at the end are taken back only for a run this node has followed (it has taken steps
            # of it): a node that starts after the end would take an ended source's history, which catch_up refuses
            # (it may be a stale run's)
            self._file(self.steps.flush(tail=self.steps.next_seq > 0))
        else:
            self._take_part(key, stream, message, from_history)

    def _take_part(self, key: str, stream: str, message: StepPart, from_history: bool) -> None:
        """File a scan, odometry or landmarks message that :meth:`handle` decoded on ``key`` with its step, unless the
        source's history gave it already; one beyond the seq window is counted, and held when the filter uses its
        stream (so that it sets no stream's order)."""
        if stream in self.steps.needs and from_history:
            self._history_high[stream] = max(self._history_high.get(stream, -1), message.seq)
        elif stream in self.steps.needs and message.seq <= self._history_high.get(stream, -1):
            return
        if not from_history and self.steps.beyond_window(message.seq):
            used = stream in self.steps.needs  # a far seq of a stream the filter does not use is only counted
            self.rejects.count(
                key,
                "ahead",
                f"a {message.TYPE} for seq {message.seq}, more than the seq window "
                f"({self.steps.window}) beyond the next step {self.steps.next_seq} (a forged or stray seq?): "
                + ("held, and used only if the stream gets near it or goes on from it" if used else "dropped"),
            )
            if used:
                self._file(self.steps.add(stream, message.seq, message))
        else:
            self._add_part(key, stream, message, from_history)

    def _add_part(self, key: str, stream: str, message: StepPart, from_history: bool) -> None:
        """Check the order of a message within the seq window and file it with its step when it is a part of one."""
        late = self._check_order(key, message.seq)
        if stream not in self.steps.needs:
            return
        try:
            released = self.steps.add(stream, message.seq, message, trusted=from_history)
        except OutOfOrder as exc:
            if not late:
                self._report_order(key, str(exc))
            return
        self._file(released)

    def take_history(self, replies: list[tuple[str, bytes]], stop: threading.Event | None = None) -> None:
        """Take what the source's history gave at startup ((pg/<robot>/<stream>, payload), in the order it was
        sent), as if it had arrived live; a live copy that comes later is dropped without a word. Stops taking
        them when ``stop`` is set (the process is stopping: thousands of steps take seconds)."""
        taken = 0
        for key, payload in replies:
            if stop is not None and stop.is_set():
                break
            self.handle(key, payload, from_history=True)
            taken += 1
        self.log.info(
            "took %d%s message(s) the source published before this node was up (steps up to seq %d)",
            taken,
            "" if taken == len(replies) else f" of the {len(replies)}",
            max(self._history_high.values(), default=-1),
        )

    def _check_order(self, key: str, seq: int) -> bool:
        """Report (log once per key, count always) a message whose seq is not above every seq seen on its key."""
        highest = self._highest_seq.get(key, -1)
        if seq > highest:
            self._highest_seq[key] = seq
            return False
        used = "; it is dropped" if seq < self.steps.next_seq else "; its step is still to come, so it is used"
        self._report_order(key, f"seq {seq} arrived after seq {highest}{used}")
        return True

    def _report_order(self, key: str, detail: str) -> None:
        self.out_of_order[key] += 1
        if self.out_of_order[key] == 1:
            self.log.warning("out of order on %s: %s; further ones on this key are only counted", key, detail)

    # ---------------------------------------------------------------------------- steps
    def _file(self, released: Released) -> None:
        if released.skipped:
            self.log.warning(
                "skipped seq %s of robot %s: parts of them never arrived", _spans(released.skipped), self.config.robot
            )
            self.steps_done += sum(count for _, count in released.skipped)
        lost = released.evicted
        self._ready.extend(released.steps)
        if self.initial is None and self._ready:
            self._ask_prior()
        while self.initial is None and len(self._ready) > self.steps.capacity:  # no start pose yet: the newest
            self._ready.pop(0)
            self.steps_done += 1
            lost += 1
        if lost:
            self.rejects.count(
                keys.robot_key(self.config.robot, "steps"), "overflow", f"dropped {lost} step(s) to bound the buffers"
            )
        self._take_ready()

    def _ask_prior(self) -> None:
        """Steps wait and no start pose came: the source publishes its prior once, before its first step, so a node
        that missed it (paused or cut off then) would wait for ever, every step given up. Ask the source's history
        for it, at most once every PRIOR_RETRY s (its answer, when it has one, starts the filter)."""
        now = time.monotonic()
        if self._history is None or now - self._prior_asked < PRIOR_RETRY:
            return
        if self._prior_asked == -math.inf:  # (said once: a source that has no prior would have it said every second)
            self.log.warning("steps are waiting and no start pose came: asking the source's history for its prior")
        self._prior_asked = now
        for key, payload in self._history(frozenset({keys.PRIOR}), 0, 0):
            if key.rsplit("/", 1)[-1] == keys.PRIOR:
                self.handle(key, payload, from_history=True)

    def _take_ready(self) -> None:
        if self.initial is None:
            return
        for seq, parts in self._ready:
            self._take(seq, parts)
        self._ready.clear()

    def _new_driver(self) -> LandmarkDriver | GridDriver:
        cfg = self.config
        initial = np.asarray(self.initial, np.float64)
        if cfg.algorithm == "gridslam":
            assert cfg.grid_config is not None  # NodeConfig: grid FastSLAM's settings come with it
            return GridDriver(initial, cfg.grid_config, cfg.seed, cfg.max_odometry_step, self.log)
        assert cfg.make_filter is not None  # NodeConfig: None for gridslam only
        return LandmarkDriver(cfg.make_filter(initial), cfg.motion, cfg.bridge, cfg.calibration, cfg.max_landmarks)

    def _take(self, seq: int, parts: dict) -> None:
        """Take step ``seq`` through the filter and publish its pose; a step the filter cannot take is undone,
        counted and skipped."""
        cfg = self.config
        if self.driver is None:
            self.driver = self._new_driver()
        stamp = next(iter(parts.values())).stamp
        self.steps_done += 1
        saved = self.driver.save()
        try:
            first, second = self.driver.step(parts)
            message: PoseSamples | PoseGaussian
            if isinstance(self.driver, GridDriver) or not self.driver.filter.gaussian:  # (gridslam's driver)
                message = PoseSamples(robot=cfg.robot, seq=seq, stamp=stamp, samples=first, weights=second)
            else:
                message = PoseGaussian(robot=cfg.robot, seq=seq, stamp=stamp, mean=first, cov=second)
            payload = message.encode()  # validates: a filter driven out of range by its input gives no pose
        except (StepError, ValueError, IndexError, KeyError, np.linalg.LinAlgError) as exc:
            # valid messages the filter still cannot use (e.g. an unknown landmark id), or a pose outside what a
            # PoseSamples/PoseGaussian may carry: skip the step, as if it had not come, and go on
            self.driver.restore(saved)
            self._note_refused(seq)
            self.rejects.count(keys.robot_key(cfg.robot, "steps"), "step", f"seq {seq} skipped: {exc}")
            return
        except Exception as exc:
            self.driver.restore(saved)
            self._note_refused(seq)
            self.log.exception("seq %d failed; the node goes on", seq)
            self.rejects.count(keys.robot_key(cfg.robot, "steps"), "error", f"seq {seq} failed: {type(exc).__name__}")
            return
        self._publish(payload)
        self.published += 1
        self._pose_history.keep(seq, payload)
        self._report_gap(seq, getattr(self.driver, "last_gap", None))
        self._refused.clear()

    def _note_refused(self, seq: int) -> None:
        self._refused[seq] = None
        while len(self._refused) > REFUSED_KEPT:
            self._refused.popitem(last=False)

    def _gap_cause(self, gap: Gap) -> str:
        """Why the steps of ``gap`` were not taken: they never arrived, the filter refused them (counted under
        pg/<robot>/steps when they came), or some of each."""
        refused = sum(1 for seq in self._refused if gap.first <= seq <= gap.last)
        if refused == 0:
            return "never arrived"
        if refused == gap.last - gap.first + 1:
            return "were skipped (the filter could not take them: counted and said above)"
        return "never arrived or were skipped (the filter could not take some: counted and said above)"

    def _report_gap(self, seq: int, gap: Gap | None) -> None:
        """Log how step ``seq`` moved over the steps before it that never arrived, if any."""
        if gap is not None and gap.bridged:
            self.log.info(
                "seq %d: moved over seq %d-%d, which %s, by the odometry poses around them",
                seq,
                gap.first,
                gap.last,
                self._gap_cause(gap),
            )
        elif gap is not None:
            self.log.warning(
                "seq %d: the velocity commands of seq %d-%d, which %s, are not used and the odometry messages "
                "carry no pose to bridge them; the poses from here on miss that motion",
                seq,
                gap.first,
                gap.last,
                self._gap_cause(gap),
            )

    def _recover(self, first: int, last: int | None) -> dict[int, dict[str, SeqMessage]]:
        """The parts of steps first..last (None: every step the source has published from ``first``), which did
        not all arrive (lost in transit), from the source's history ({seq: {stream: message}}; what it lacks is
        skipped as before). Called by the step assembler. A live copy of a part taken here that comes later is
        dropped without a word, as after :meth:`take_history`."""
        assert self._history is not None  # the step assembler is given this method only with a history
        parts: dict[int, dict[str, SeqMessage]] = {}
        robot = self.config.robot
        for key, payload in self._history(self.steps.needs, first, last):
            stream = key.rsplit("/", 1)[-1]
            if stream not in self.steps.needs:  # e.g. a reply on pg/<robot>/history/end: no source sends one
                self.rejects.count(
                    keys.history_key(robot), "history", f"a history reply on {key}, which is no part of a step"
                )
                continue
            message = history_reply(
                keys.history_key(robot), robot, payload, STEP_PARTS[stream], first, last, self.rejects
            )
            if message is not None:
                parts.setdefault(message.seq, {})[stream] = message
                self._history_high[stream] = max(self._history_high.get(stream, -1), message.seq)
        if parts and last is None:  # the end mark can overtake the last steps: they may still be on their way
            self.log.info(
                "at the end of the stream, took seq %s, which had not all arrived (lost, or still on their "
                "way), from the source's history",
                _spans(_runs(sorted(parts))),
            )
        elif parts:
            self.log.info(
                "took seq %s, which did not all arrive, from the source's history", _spans(_runs(sorted(parts)))
            )
        return parts

    # ---------------------------------------------------------------------------- what the node serves
    def poses(self, wants: Callable[[int], bool]) -> list[bytes]:
        """The encoded poses kept for the history whose seq ``wants`` takes, in the order they were published
        (:class:`services.state.pose_history.PoseHistory`: safe to call while another thread handles a message)."""
        return self._pose_history.poses(wants)

    def stats(self) -> NodeStats:
        """The node's statistics (pg/<robot>/slam/stats)."""
        return NodeStats(
            robot=self.config.robot,
            algorithm=self.config.algorithm,
            poses_published=self.published,
            steps_done=self.steps_done,
            uptime=time.monotonic() - self.started,
            received=dict(self.received),
            rejected=self.rejects.snapshot(),
            out_of_order=dict(self.out_of_order),
            health=self.driver.health() if isinstance(self.driver, GridDriver) else {},
            **self._consistency(),
        )

    def _consistency(self) -> dict:
        """The landmark filter's consistency watch (slam.consistency) as NodeStats' noise_scale and consistency."""
        monitor = getattr(getattr(self.driver, "filter", None), "monitor", None)
        if monitor is None:
            return {"noise_scale": 1.0, "consistency": {}}
        watched = monitor.stats()
        counts = {
            "measurements": watched.measurements,
            "gated": watched.gated,
            "inflations": watched.inflations,
            "deflations": watched.deflations,
        }
        return {"noise_scale": watched.noise_scale, "consistency": counts}


def _runs(seqs: list[int]) -> list[tuple[int, int]]:
    """Ascending seqs as runs (first seq, count) of consecutive ones."""
    runs: list[tuple[int, int]] = []
    for seq in seqs:
        if runs and seq == runs[-1][0] + runs[-1][1]:
            runs[-1] = (runs[-1][0], runs[-1][1] + 1)
        else:
            runs.append((seq, 1))
    return runs


def _spans(runs: list[tuple[int, int]]) -> str:
    """Runs (first seq, count) as "3, 7-12, 15"."""
    return ", ".join(str(first) if count == 1 else f"{first}-{first + count - 1}" for first, count in runs)
