"""`posegrid slam-node`: runs a SLAM filter on what a source publishes and publishes a pose distribution per
scan (pg/<robot>/pose, tagged with the scan's seq).

Landmark filters (odometry dead reckoning, EKF-SLAM, FastSLAM 1.0/2.0, slam/) take step ``seq`` when its
Odometry and LandmarkObservations are in; grid FastSLAM (slam/gridslam) when its LaserScan and Odometry
(with the odometry pose) are in. Steps are taken strictly in seq order (services.state.steps). A message whose
seq is not above every seq seen on its key arrived out of order: the node says so (logged once per key,
counted per key) and uses it if its step is still to come, else drops it. The filter starts at ``--initial`` or at
the prior the source publishes on pg/<robot>/prior. Per step, the node publishes what the offline
`posegrid slam` writes for that step: mean and covariance (Gaussian filters) or particles and their
weights before resampling; grid FastSLAM publishes the filtered particles (the offline run smooths them
by ancestry, which a live node cannot do).

Threads and bad input as in services.nodes.mapper: callbacks feed a bounded intake queue, one thread decodes
and filters; malformed messages are counted per key in the NodeStats (pg/<robot>/slam/stats) and logged
once per kind.
"""
from __future__ import annotations

import copy
import queue
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import zenoh

from schemas.messages import (
    LandmarkObservations,
    LaserScan,
    MessageError,
    NodeStats,
    Odometry,
    PoseGaussian,
    PoseSamples,
    StreamEnd,
    decode_message,
)
from services import history, keys
from services.state.limits import ShardLimits
from services.process import RejectCounter, get_logger
from services.state.steps import OutOfOrder, Released, StepAssembler
from services.zenoh_config import open_session
from slam.gridslam import GridFastSLAM, GridSlamConfig
from slam.motion import OdometryMotionModel, odometry_controls, split_odometry_motion

EXPECTED = {keys.SCAN: (LaserScan,), keys.ODOM: (Odometry,), keys.LANDMARKS: (LandmarkObservations,),
            keys.END: (StreamEnd,), keys.PRIOR: (PoseGaussian,)}
#: s to wait for the source's history of the run (what it published before this node was up)
HISTORY_TIMEOUT = 60.0
#: s to wait for the source's history of steps that did not all arrive (the node waits meanwhile)
RECOVER_TIMEOUT = 5.0
#: bytes of published poses the node keeps for its history (the oldest go first): 1 KB a pose of 30 particles
POSE_HISTORY_BYTES = 64 * 2**20
#: the largest message the node takes off the network: a scan of services.state.limits.DEFAULT_MAX_BEAMS beams
MAX_MESSAGE_BYTES = ShardLimits().message_bytes()


class StepError(ValueError):
    """A step the filter cannot take (e.g. odometry motion without an odometry pose)."""


@dataclass(frozen=True)
class NodeConfig:
    """robot: whose streams to follow; algorithm: odometry, ekf, fastslam1, fastslam2 or gridslam;
    make_filter(initial_pose) builds a landmark filter (None for gridslam); motion: "velocity" or
    "odometry" (which Odometry field the landmark filters read); initial: start pose or None to wait
    for the source's prior; grid_config, seed: grid FastSLAM's (max_range is capped at the laser's);
    intake_capacity: bounded queue size; bridge: the odometry motion model that moves a velocity-motion filter
    over steps that never arrived, by the odometry poses around them (:class:`LandmarkDriver`)."""

    robot: str
    algorithm: str
    make_filter: Callable[[np.ndarray], object] | None
    motion: str = "velocity"
    initial: np.ndarray | None = None
    grid_config: GridSlamConfig | None = None
    seed: int = 0
    intake_capacity: int = 4096
    bridge: OdometryMotionModel | None = OdometryMotionModel()


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
    it."""

    needs = {keys.ODOM, keys.LANDMARKS}

    def __init__(self, slam_filter, motion: str, bridge: OdometryMotionModel | None = None):
        self.filter = slam_filter
        self.motion = motion
        self.bridge = bridge
        self._last_pose: np.ndarray | None = None  # odometry pose of the last step taken (None: it had none)
        self._last_seq: int | None = None
        self.last_gap: Gap | None = None

    def step(self, parts: dict) -> tuple[np.ndarray, np.ndarray]:
        odom: Odometry = parts[keys.ODOM]
        seen: LandmarkObservations = parts[keys.LANDMARKS]
        pose = odom.pose[0] if odom.pose.shape[0] else None
        gap = None if self._last_seq is None or odom.seq == self._last_seq + 1 else (self._last_seq + 1, odom.seq - 1)
        model = None
        if self.motion == "odometry":
            if pose is None:
                raise StepError(f"seq {odom.seq}: odometry motion needs the odometry pose, the message has none")
            controls = np.zeros((0, 3)) if self._last_pose is None else odometry_controls(
                np.stack([self._last_pose, pose]))
        elif gap is not None and pose is not None and self._last_pose is not None and self.bridge is not None:
            motion = odometry_controls(np.stack([self._last_pose, pose]))[0]
            controls, model = split_odometry_motion(motion, odom.seq - self._last_seq), self.bridge
        else:
            controls = odom.commands
        measurements = np.column_stack([seen.ranges, seen.bearings])
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
        return copy.deepcopy((self.filter, self._last_pose, self._last_seq))

    def restore(self, saved: object) -> None:
        """Go back to the state :meth:`save` returned, undoing a step whose pose could not be published."""
        self.filter, self._last_pose, self._last_seq = saved
        self.last_gap = None


class GridDriver:
    """Feeds grid FastSLAM one scan at a time: integrate when due, else follow the odometry. A failed step is
    not undone (:meth:`save` keeps nothing): a copy of every particle's map per scan would cost more than the
    step. Odometry beyond the wire's pose limit never reaches it."""

    needs = {keys.SCAN, keys.ODOM}

    def save(self) -> object:
        return None

    def restore(self, saved: object) -> None:
        pass

    def __init__(self, initial: np.ndarray, config: GridSlamConfig, seed: int):
        self.initial = initial
        self.config = config
        self.seed = seed
        self.filter = None

    def step(self, parts: dict) -> tuple[np.ndarray, np.ndarray]:
        scan: LaserScan = parts[keys.SCAN]
        odom: Odometry = parts[keys.ODOM]
        if odom.pose.shape[0] == 0:
            raise StepError(f"seq {odom.seq}: grid FastSLAM needs the odometry pose, the message has none")
        if self.filter is None:  # as slam.gridslam.run_gridslam sets it up
            config = replace(self.config, max_range=min(self.config.max_range, scan.range_max))
            angles = scan.angle_min + scan.angle_increment * np.arange(scan.ranges.shape[0])
            self.filter = GridFastSLAM(config, angles, scan.sensor_offset, scan.range_min, self.initial, self.seed)
        if self.filter.due(odom.pose[0]):
            poses, weights, _, _ = self.filter.integrate(odom.pose[0], scan.ranges)
            return poses, weights
        return self.filter.follow(odom.pose[0]), self.filter.weights


class SlamNode:
    """A running node. Use :meth:`run`."""

    def __init__(self, config: NodeConfig, session: zenoh.Session):
        self.config = config
        self.session = session
        self.log = get_logger(f"slam-node[{config.robot}]")
        self.rejects = RejectCounter(self.log)
        self.intake: queue.Queue[tuple[str, bytes]] = queue.Queue(config.intake_capacity)
        self.lock = threading.Lock()
        self.received: Counter[str] = Counter()
        self.out_of_order: Counter[str] = Counter()
        self.published = 0
        self.steps_done = 0  # seqs taken, failed or skipped
        self.started = time.monotonic()
        self.initial = config.initial
        self.driver = None
        needs = GridDriver.needs if config.algorithm == "gridslam" else LandmarkDriver.needs
        self.steps = StepAssembler(needs, recover=self._recover, same=lambda a, b: a.digest() == b.digest())
        self._ready: list[tuple[int, dict]] = []
        self._highest_seq: dict[str, int] = {}
        self._history_high: dict[str, int] = {}  # per stream, the highest seq the source's history gave
        self._poses_sent: OrderedDict[int, bytes] = OrderedDict()  # seq -> published pose, for the history
        self._poses_bytes = 0
        self._declared = []
        self._pose_publisher = None

    # ---------------------------------------------------------------------------- zenoh callbacks
    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Queue a publication for the filter thread, unless its key is no stream of this robot (a wildcard such as
        pg/<robot>/* reaches every subscriber): counted under keys.INVALID_KEY."""
        key = str(sample.key_expr)
        parsed = keys.parse_robot_key(key, EXPECTED.keys())
        if parsed is None or parsed[0] != self.config.robot:
            self.rejects.count(keys.INVALID_KEY, "key", f"a message on {key[:200]!r}, which is no "
                               f"pg/{self.config.robot}/<stream> key of a stream this node reads")
            return
        if len(sample.payload) > MAX_MESSAGE_BYTES:
            self.rejects.count(key, "size", f"a message of {len(sample.payload)} bytes, more than the "
                               f"{MAX_MESSAGE_BYTES} this node takes")
            return
        try:
            self.intake.put_nowait((key, sample.payload.to_bytes()))
        except queue.Full:
            self.rejects.count(key, "overflow", f"the intake queue ({self.intake.maxsize}) was full")

    def _on_stats_query(self, query: zenoh.Query) -> None:
        with self.lock:
            stats = NodeStats(robot=self.config.robot, algorithm=self.config.algorithm,
                              poses_published=self.published, steps_done=self.steps_done,
                              uptime=time.monotonic() - self.started,
                              received=dict(self.received), rejected=self.rejects.snapshot(),
                              out_of_order=dict(self.out_of_order))
        query.reply(keys.slam_stats_key(self.config.robot), stats.encode())

    # ---------------------------------------------------------------------------- messages
    def handle(self, key: str, payload: bytes, from_history: bool = False) -> None:
        """Decode one message, file it with its step, and take every step that is now complete. A live message
        that the source's history gave already (:meth:`catch_up`) is dropped without a word."""
        parsed = keys.parse_robot_key(key, EXPECTED.keys())
        if parsed is None or parsed[0] != self.config.robot:
            self.rejects.count(keys.INVALID_KEY, "key", f"a message on {key[:200]!r}, which is no "
                               f"pg/{self.config.robot}/<stream> key of a stream this node reads")
            return
        self.received[key] += 1
        stream = parsed[1]
        try:
            message = decode_message(payload, *EXPECTED[stream])
        except MessageError as exc:
            self.rejects.count(key, exc.reason, str(exc))
            return
        if message.robot != self.config.robot:
            self.rejects.count(key, "robot", f"a {message.TYPE} of robot {message.robot!r} arrived on {key}")
            return
        if stream in self.steps.needs and from_history:
            self._history_high[stream] = max(self._history_high.get(stream, -1), message.seq)
        elif stream in self.steps.needs and message.seq <= self._history_high.get(stream, -1):
            return
        if stream == keys.PRIOR:
            if self.initial is None:
                self.initial = message.mean
                self.log.info("starting at the source's prior (%.3f m, %.3f m, %.3f rad)", *message.mean)
            self._take_ready()
        elif stream == keys.END:
            # the steps lost at the end are taken back only for a run this node has followed (it has taken steps
            # of it): a node that starts after the end would take an ended source's history, which catch_up refuses
            # (it may be a stale run's)
            self._file(self.steps.flush(tail=self.steps.next_seq > 0))
        elif stream in self.steps.needs and not from_history and self.steps.beyond_window(message.seq):
            self.rejects.count(key, "ahead", f"a {message.TYPE} for seq {message.seq}, more than the seq window "
                               f"({self.steps.window}) beyond the next step {self.steps.next_seq} (a forged or "
                               "stray seq?): held, and used only if the stream gets near it or goes on from it")
            self._file(self.steps.add(stream, message.seq, message))
        else:
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

    def _file(self, released: Released) -> None:
        if released.skipped:
            self.log.warning("skipped seq %s of robot %s: parts of them never arrived",
                             _spans(released.skipped), self.config.robot)
            self.steps_done += sum(count for _, count in released.skipped)
        lost = released.evicted
        self._ready.extend(released.steps)
        while self.initial is None and len(self._ready) > self.steps.capacity:  # no start pose yet: the newest
            self._ready.pop(0)
            self.steps_done += 1
            lost += 1
        if lost:
            self.rejects.count(keys.robot_key(self.config.robot, "steps"), "overflow",
                               f"dropped {lost} step(s) to bound the buffers")
        self._take_ready()

    def _take_ready(self) -> None:
        if self.initial is None:
            return
        for seq, parts in self._ready:
            self._take(seq, parts)
        self._ready.clear()

    def _take(self, seq: int, parts: dict) -> None:
        cfg = self.config
        if self.driver is None:
            initial = np.asarray(self.initial, np.float64)
            self.driver = (GridDriver(initial, cfg.grid_config, cfg.seed) if cfg.algorithm == "gridslam"
                           else LandmarkDriver(cfg.make_filter(initial), cfg.motion, cfg.bridge))
        stamp = next(iter(parts.values())).stamp
        self.steps_done += 1
        saved = self.driver.save()
        try:
            first, second = self.driver.step(parts)
            if cfg.algorithm == "gridslam" or not self.driver.filter.gaussian:
                message = PoseSamples(robot=cfg.robot, seq=seq, stamp=stamp, samples=first, weights=second)
            else:
                message = PoseGaussian(robot=cfg.robot, seq=seq, stamp=stamp, mean=first, cov=second)
            payload = message.encode()  # validates: a filter driven out of range by its input gives no pose
        except (StepError, ValueError, IndexError, KeyError, np.linalg.LinAlgError) as exc:
            # valid messages the filter still cannot use (e.g. an unknown landmark id), or a pose outside what a
            # PoseSamples/PoseGaussian may carry: skip the step, as if it had not come, and go on
            self.driver.restore(saved)
            self.rejects.count(keys.robot_key(cfg.robot, "steps"), "step", f"seq {seq} skipped: {exc}")
            return
        except Exception as exc:  # noqa: BLE001 - a defect met by one step must not stop the node: counted, logged
            self.driver.restore(saved)
            self.log.exception("seq %d failed; the node goes on", seq)
            self.rejects.count(keys.robot_key(cfg.robot, "steps"), "error", f"seq {seq} failed: {type(exc).__name__}")
            return
        self._pose_publisher.put(payload)
        self.published += 1
        self._keep_pose(seq, payload)
        gap = getattr(self.driver, "last_gap", None)
        if gap is not None and gap.bridged:
            self.log.info("seq %d: moved over seq %d-%d, which never arrived, by the odometry poses around them", seq,
                          gap.first, gap.last)
        elif gap is not None:
            self.log.warning("seq %d: the velocity commands of seq %d-%d never arrived and the odometry messages "
                             "carry no pose to bridge them; the poses from here on miss that motion", seq, gap.first,
                             gap.last)

    def _history(self, parameters: dict[str, str], timeout: float,
                 accept: Callable[[history.Answerer], bool] = lambda answerer: True) -> list[tuple[str, bytes]]:
        """(pg/<robot>/<stream>, payload) of the messages the histories ``accept`` answers with (services.history),
        in the order they were sent; none when nobody answers."""
        robot = self.config.robot
        messages, problems = history.ask(self.session, robot, parameters, timeout, accept)
        for problem in problems:
            self.rejects.count(keys.history_key(robot), "history", problem)
        return [(keys.robot_key(robot, stream), payload) for _, stream, payload in messages if stream in EXPECTED]

    def _keep_pose(self, seq: int, payload: bytes) -> None:
        """Keep a published pose for the history, within POSE_HISTORY_BYTES (called holding ``lock``)."""
        old = self._poses_sent.pop(seq, None)
        self._poses_bytes += len(payload) - (0 if old is None else len(old))
        self._poses_sent[seq] = payload
        while self._poses_bytes > POSE_HISTORY_BYTES:
            self._poses_bytes -= len(self._poses_sent.popitem(last=False)[1])

    def _on_history_query(self, query: zenoh.Query) -> None:
        """pg/<robot>/history/** (services.history): the poses this node has published, of the seqs asked for
        (the other streams are the source's to answer)."""
        request = history.parse_request(query, self.config.robot)
        if request is None or keys.POSE not in request.streams:  # before the lock: the node's own history
            return  # queries, which it makes holding the lock, never ask for poses
        with self.lock:
            poses = [payload for seq, payload in self._poses_sent.items() if request.wants(seq)]
        answerer = history.Answerer(str(self.session.info.zid()), None, False)
        for payload in poses:
            history.reply(query, answerer, self.config.robot, keys.POSE, payload)

    def catch_up(self) -> None:
        """Take what the source published before this node subscribed: the prior and every step so far, in the
        order they went out, as if they had arrived live. A node that starts late or restarts so resumes where
        the run is, in the state of a node that saw all of it (its poses so far are published again; shards
        refuse the ones they have fused). Nothing happens when no source answers."""
        replies = self._history({"streams": ",".join(sorted(self.steps.needs | {keys.PRIOR}))}, HISTORY_TIMEOUT,
                                accept=lambda answerer: not answerer.ended)  # a run that has ended is not this one
        if not replies:
            return
        with self.lock:
            for key, payload in replies:
                self.handle(key, payload, from_history=True)
        self.log.info("took %d message(s) the source published before this node was up (steps up to seq %d)",
                      len(replies), max(self._history_high.values(), default=-1))

    def _recover(self, first: int, last: int | None) -> dict[int, dict]:
        """The parts of steps first..last (None: every step the source has published from ``first``), which did
        not all arrive (lost in transit), from the source's history ({seq: {stream: message}}; what it lacks is
        skipped as before). Called by the step assembler. A live copy of a part taken here that comes later is
        dropped without a word, as after :meth:`catch_up`."""
        parts: dict[int, dict] = {}
        span = {"from": str(first)} if last is None else {"from": str(first), "to": str(last + 1)}
        for key, payload in self._history({"streams": ",".join(sorted(self.steps.needs)), **span}, RECOVER_TIMEOUT):
            stream = key.rsplit("/", 1)[-1]
            try:
                message = decode_message(payload, *EXPECTED[stream])
            except MessageError as exc:
                self.rejects.count(keys.history_key(self.config.robot), exc.reason, str(exc))
                continue
            if message.robot != self.config.robot or message.seq < first or (last is not None and message.seq > last):
                self.rejects.count(keys.history_key(self.config.robot), "key", f"a {message.TYPE} of robot "
                                   f"{message.robot!r}, seq {message.seq}, answered a question about seqs "
                                   f"{first}-{'' if last is None else last} of robot {self.config.robot!r}")
            else:
                parts.setdefault(message.seq, {})[stream] = message
                self._history_high[stream] = max(self._history_high.get(stream, -1), message.seq)
        if parts and last is None:  # the end mark can overtake the last steps: they may still be on their way
            self.log.info("at the end of the stream, took seq %s, which had not all arrived (lost, or still on their "
                          "way), from the source's history", _spans(_runs(sorted(parts))))
        elif parts:
            self.log.info("took seq %s, which did not all arrive, from the source's history",
                          _spans(_runs(sorted(parts))))
        return parts

    # ---------------------------------------------------------------------------- lifecycle
    def run(self, stop: threading.Event) -> int:
        """Filter and publish until ``stop`` is set; returns the exit code (0)."""
        robot, session = self.config.robot, self.session
        self._pose_publisher = session.declare_publisher(keys.robot_key(robot, keys.POSE),
                                                         congestion_control=zenoh.CongestionControl.BLOCK)
        for stream in EXPECTED:
            self._declared.append(session.declare_subscriber(keys.robot_key(robot, stream), self._on_sample))
        self._declared.append(session.declare_queryable(keys.slam_stats_key(robot), self._on_stats_query))
        self._declared.append(session.declare_queryable(keys.history_key(robot), self._on_history_query))
        self._declared.append(session.liveliness().declare_token(keys.robot_alive_key(robot, "slam")))
        self.log.info("%s up for robot %r; poses on %s", self.config.algorithm, robot, keys.robot_key(robot, keys.POSE))
        self.catch_up()
        while not stop.is_set():
            try:
                key, payload = self.intake.get(timeout=0.2)
            except queue.Empty:
                continue
            with self.lock:
                self.handle(key, payload)
        for entity in reversed(self._declared):
            entity.undeclare()
        self._pose_publisher.undeclare()
        self.log.info("stopped after publishing %d poses", self.published)
        return 0


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


def run_slam_node(config: NodeConfig, zenoh_config: zenoh.Config, stop: threading.Event) -> int:
    """Open a session and run the node until ``stop`` is set."""
    session = open_session(zenoh_config, f"the SLAM node of robot {config.robot}")
    try:
        return SlamNode(config, session).run(stop)
    finally:
        session.close()
