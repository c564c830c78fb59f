"""The checks a mapper shard and a SLAM node share (services.intake, services.state.checks): the bounded intake
queue in front of both, and the checks of what a history answers, run the same way by the shard's join and by the
SLAM node's step assembler (services.state.slam, driven here without a network)."""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import zenoh

from mapping.sensor_model import SensorModel
from peers import BLOCK
from schemas.messages import (
    LandmarkObservations,
    LaserScan,
    Odometry,
    PoseGaussian,
    PoseSamples,
    StreamEnd,
    decode_message,
)
from services import keys
from services.errors import UsageError
from services.intake import Intake
from services.process import RejectCounter
from services.state.limits import ShardLimits
from services.state.shard import SHARD_STREAMS, MapShard, ShardConfig
from services.state.slam import EXPECTED, PRIOR_RETRY, NodeConfig, SlamState
from slam.dead_reckoning import DeadReckoning
from slam.ekf import EKFSLAM
from slam.gridslam import GridSlamConfig
from slam.gridslam.simlogs import sim_log
from slam.motion import OdometryMotionModel, VelocityMotionModel
from slam.range_bearing import RangeBearingModel

SENSOR = RangeBearingModel(0.1, 0.05)  # a landmark sensor's range (m) and bearing (rad) sd
NO_COMMANDS = np.zeros((0, 3))  # an Odometry message's commands: none (the grid filter reads the pose)


def _rejects(name: str) -> RejectCounter:
    return RejectCounter(logging.getLogger(f"test-intake-{name}"))


# ------------------------------------------------------------------------------------------------ the intake queue


@pytest.mark.parametrize("key", ["pg/*/scan", "pg/r/odom", "pg/r/scan/x", "pg/map/scan", "pg/-x/pose"])
def test_the_intake_refuses_a_key_that_is_no_robot_stream_it_reads(key):
    rejects = _rejects("key")
    intake = Intake(SHARD_STREAMS, rejects)
    assert not intake.offer(key, b"payload")
    assert rejects.snapshot() == {keys.INVALID_KEY: 1} and rejects.kinds() == {"key": 1} and intake.empty()


@pytest.mark.parametrize(("streams", "robot"), [(SHARD_STREAMS, None), (EXPECTED, "r")], ids=["shard", "slam-node"])
def test_the_intake_takes_a_robots_messages_on_all_its_keys_in_the_order_they_were_published(streams, robot):
    """A re-probe (a CI failure): the shard read each stream through a subscriber of its own, and zenoh-python runs
    each subscriber's callbacks on a thread of its own, so a StreamEnd reached the queue before some of the scans
    and poses published before it (in 28 of 50 bursts), and a source that had seen its end taken left before the
    shard had taken its poses, saying nothing of their clash. Real sessions, peer to peer on loopback: 40 bursts of
    a robot's scans, poses and odometry and its end come out of the queue exactly in the order they were put; the
    stream the process does not read (a shard's odometry, a SLAM node's poses: its own) is passed over without a
    count, and a put on the wildcard pg/r/* is counted once (it reached each of a shard's three subscribers before).
    A SLAM node's intake reads its own robot's streams (pg/r/*)."""
    from services.ports import free_port
    from services.zenoh_config import build_config

    endpoint, rejects = f"tcp/127.0.0.1:{free_port()}", _rejects("order")
    intake = Intake(streams, rejects, robot=robot)
    with (
        zenoh.open(build_config("peer", listen=[endpoint])) as shard,
        zenoh.open(build_config("peer", connect=[endpoint])) as source,
    ):
        subscriber = intake.subscribe(shard)
        publishers = {
            s: source.declare_publisher(keys.robot_key("r", s), congestion_control=BLOCK)
            for s in (keys.SCAN, keys.ODOM, keys.POSE, keys.END)
        }
        deadline = time.monotonic() + 30
        while not all(p.matching_status.matching for p in publishers.values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        published = []
        for burst in range(40):
            for seq in range(20):
                for stream in (keys.SCAN, keys.ODOM, keys.POSE):
                    publishers[stream].put(f"{stream}-{burst}-{seq}".encode())
                    published.append((keys.robot_key("r", stream), f"{stream}-{burst}-{seq}".encode()))
            publishers[keys.END].put(f"end-{burst}".encode())
            published.append((keys.robot_key("r", keys.END), f"end-{burst}".encode()))
        source.put("pg/r/*", b"x", congestion_control=BLOCK)
        expected = [item for item in published if item[0].rsplit("/", 1)[-1] in streams]
        taken = [intake.next(30.0) for _ in expected]
        deadline = time.monotonic() + 30
        while not rejects.snapshot() and time.monotonic() < deadline:
            time.sleep(0.05)
        subscriber.undeclare()
    assert taken == expected
    assert intake.empty() and rejects.snapshot() == {keys.INVALID_KEY: 1}


def test_a_node_intake_takes_only_its_own_robots_streams():
    rejects = _rejects("robot")
    intake = Intake(["odom", "scan"], rejects, robot="r1")
    assert not intake.offer("pg/r2/odom", b"x") and intake.offer("pg/r1/odom", zenoh.ZBytes(b"abc"))
    assert rejects.snapshot() == {keys.INVALID_KEY: 1}
    assert intake.next(1.0) == ("pg/r1/odom", b"abc")  # a Zenoh payload is queued as a copy of its bytes


def test_the_intake_refuses_a_message_larger_than_any_scan_the_limits_allow():
    rejects = _rejects("size")
    limits = ShardLimits(max_beams=10)  # messages of up to 16 * 10 + 2^20 bytes
    intake = Intake(SHARD_STREAMS, rejects, limits)
    assert intake.offer("pg/r/scan", b"x" * limits.message_bytes())
    assert not intake.offer("pg/r/scan", b"x" * (limits.message_bytes() + 1))
    assert rejects.snapshot() == {"pg/r/scan": 1} and rejects.kinds() == {"size": 1} and intake.overflow == 0


def test_the_intake_bounds_what_waits_by_bytes_and_by_count_and_counts_each_overflow():
    rejects = _rejects("overflow")
    intake = Intake(SHARD_STREAMS, rejects, ShardLimits(intake_bytes=100), capacity=3)
    assert intake.offer("pg/r/scan", b"a" * 60) and not intake.offer("pg/r/pose", b"b" * 41)  # 101 bytes > 100
    assert intake.offer("pg/r/pose", b"c" * 40) and intake.bytes_waiting == 100
    assert (
        intake.next(1.0) == ("pg/r/scan", b"a" * 60) and intake.bytes_waiting == 40
    )  # taken out: its bytes are free again
    assert intake.offer("pg/r/end", b"d") and intake.offer("pg/r/end", b"e")
    assert not intake.offer("pg/r/end", b"f")  # 3 messages wait already
    assert intake.overflow == 2 and rejects.kinds() == {"overflow": 2}
    assert rejects.snapshot() == {"pg/r/pose": 1, "pg/r/end": 1} and intake.bytes_waiting == 42
    assert [intake.next(1.0)[1] for _ in range(3)] == [b"c" * 40, b"d", b"e"] and intake.bytes_waiting == 0
    with pytest.raises(queue.Empty):
        intake.next(0.01)


def test_robots_take_turns_and_each_keeps_its_order():
    """A flood of one robot's messages (h) delays another robot's (r) by one of the flood's each, not by all of it:
    the robots with messages waiting take turns, each robot's messages in the order they came."""
    intake = Intake(SHARD_STREAMS, _rejects("turns"))
    for seq in range(50):
        assert intake.offer("pg/h/scan", b"h%d" % seq)
    for seq in range(3):
        assert intake.offer("pg/r/scan", b"r%d" % seq)
    taken = [intake.next(1.0)[1] for _ in range(53)]
    assert taken[:7] == [b"h0", b"r0", b"h1", b"r1", b"h2", b"r2", b"h3"]
    assert taken[6:] == [b"h%d" % seq for seq in range(3, 50)] and intake.empty() and intake.bytes_waiting == 0


@pytest.mark.parametrize("bound", ["count", "bytes"])
def test_a_full_intake_takes_a_robot_holding_less_by_evicting_the_floods_newest(bound):
    """A flood that fills the intake (by count or by bytes) no longer shuts another robot out: that robot's message
    evicts the flood's newest (counted as the flood's overflow), and the flood's own next message is refused."""
    rejects = _rejects(f"fair-{bound}")
    limits = ShardLimits(intake_bytes=100) if bound == "bytes" else ShardLimits()
    intake = Intake(SHARD_STREAMS, rejects, limits, capacity=10 if bound == "count" else 1000)
    flood = [intake.offer("pg/h/scan", b"h%02d" % seq + b"." * 7) for seq in range(12)]  # 10 bytes each
    assert flood == [True] * 10 + [False] * 2 and intake.overflow == 2
    assert intake.offer("pg/r/scan", b"r" * (10 if bound == "count" else 25))  # evicts 1 of h's (count), 3 (bytes)
    evicted = 1 if bound == "count" else 3
    assert not intake.offer("pg/h/scan", b"h99" + b"." * 7)  # h holds the most: its own message is refused
    assert intake.overflow == 3 + evicted and rejects.snapshot() == {"pg/h/scan": 3 + evicted}
    taken = [intake.next(1.0)[1][:3] for _ in range(11 - evicted)]
    assert taken[:3] == [b"h00", b"rrr", b"h01"]  # (the turns)
    assert [t for t in taken if t.startswith(b"h")] == [b"h%02d" % seq for seq in range(10 - evicted)]
    assert intake.empty() and intake.bytes_waiting == 0


def test_a_flood_of_small_messages_does_not_displace_a_robot_of_large_ones():
    """Fairness by share, not by bytes alone: a flood of tiny messages that fills the intake's count (its bytes few)
    holds the larger share; the real robot's scan evicts one of them, not one of its own."""
    rejects = _rejects("fair-share")
    intake = Intake(SHARD_STREAMS, rejects, ShardLimits(intake_bytes=10_000), capacity=10)
    assert intake.offer("pg/r/scan", b"r" * 2000) and intake.offer("pg/r/scan", b"s" * 2000)  # 2 of 10, 40 %
    assert all(intake.offer("pg/h/scan", b"h%d" % seq) for seq in range(8))  # 8 of 10 by count: 80 %, 16 bytes
    assert intake.offer("pg/r/scan", b"t" * 2000) and rejects.snapshot() == {"pg/h/scan": 1}
    taken = [intake.next(1.0)[1][:2] for _ in range(10)]
    assert [t for t in taken if t[:1] in b"rst"] == [b"rr", b"ss", b"tt"] and b"h7" not in taken


def test_robots_waiting_in_the_intake_are_bounded_by_max_robots():
    """Making room weighs every robot waiting: 4 096 made-up robot names, a message each, took 0.9 ms an offer once
    the intake was full. At most --max-robots robots have messages waiting; a further one is refused ("robots")
    until one of them has none left."""
    rejects = _rejects("owners")
    intake = Intake(SHARD_STREAMS, rejects, ShardLimits(max_robots=3))
    assert all(intake.offer(f"pg/{robot}/scan", b"x") for robot in ("a", "b", "c"))
    assert not intake.offer("pg/d/scan", b"x") and rejects.kinds() == {"robots": 1}
    assert intake.offer("pg/a/pose", b"y")  # (a robot waiting already)
    assert [intake.next(1.0)[0] for _ in range(2)] == ["pg/a/scan", "pg/b/scan"]  # b has none left now
    assert intake.offer("pg/d/scan", b"x") and intake.overflow == 0


# ------------------------------------------------------------------------------------------------ history replies


def _scan(seq: int, beams: int = 5) -> LaserScan:
    ranges = np.full(beams, 1.5, np.float32)
    return LaserScan(
        robot="r",
        seq=seq,
        stamp=0.1 * seq,
        angle_min=-1.0,
        angle_increment=2.0 / beams,
        range_min=0.05,
        range_max=5.0,
        sensor_offset=np.zeros(3),
        ranges=ranges,
        no_return_range=5.0,
    )


def _pose(seq: int) -> PoseSamples:
    return PoseSamples(
        robot="r", seq=seq, stamp=0.1 * seq, samples=np.array([[3.0, 3.0, 0.01 * seq]]), weights=np.ones(1)
    )


def test_a_shard_refuses_a_scan_from_a_history_with_more_beams_than_the_limit():
    """A history's scans pass the checks a live scan passes: one of more beams than --max-beams is refused and
    counted under the history's key, not fused (the history path took it unchecked)."""

    def history(robot: str, stream: str, first: int, last: int) -> list[bytes]:
        make = (lambda seq: _scan(seq, beams=10 if seq == 5 else 5)) if stream == keys.SCAN else _pose
        return [make(seq).encode() for seq in range(first, last + 1)]

    shard = MapShard(
        ShardConfig("m", 0, 1, SensorModel(), join_capacity=4, limits=ShardLimits(max_beams=5)),
        _rejects("beams"),
        history=history,
    )
    for seq in (20, 21, 22):
        shard.handle("pg/r/scan", _scan(seq).encode())
        shard.handle("pg/r/pose", _pose(seq).encode())
    stats = shard.stats({"intake": 0})
    assert stats.rejected[keys.history_key("r", keys.SCAN)] == 1 and stats.refused["size"] == 1, stats
    assert stats.fused == {"r": 22} and stats.discarded == {"r": 1}  # the join gives seq 5 up: its scan is missing


def _odometry(seq: int, robot: str = "r") -> Odometry:
    return Odometry(
        robot=robot, seq=seq, stamp=0.1 * seq, pose=np.array([[0.1 * seq, 0.0, 0.0]]), commands=np.zeros((0, 3))
    )


def _seen(seq: int) -> LandmarkObservations:
    return LandmarkObservations(
        robot="r", seq=seq, stamp=0.1 * seq, ids=np.zeros(0, np.int64), ranges=np.zeros(0), bearings=np.zeros(0)
    )


def test_a_slam_node_takes_lost_steps_from_the_history_and_counts_replies_about_other_robots_or_seqs():
    """Steps 3-4 never arrive; the source's history gives them back, along with an odometry of another robot for
    seq 3 and landmarks of seq 1, before the span asked for: those two are counted under the history's key,
    the steps are taken, and every step gets its pose, in seq order."""
    asked, published = [], []

    def history(streams: frozenset[str], first: int, last: int | None) -> list[tuple[str, bytes]]:
        asked.append((sorted(streams), first, last))
        replies = [("pg/r/odom", _odometry(3, robot="x").encode()), ("pg/r/landmarks", _seen(1).encode())]
        for seq in range(first, (last if last is not None else 9) + 1):
            replies += [("pg/r/odom", _odometry(seq).encode()), ("pg/r/landmarks", _seen(seq).encode())]
        return replies

    rejects = _rejects("slam-history")
    state = _dead_reckoning_state(rejects, published.append, history)
    for seq in [0, 1, 2, *range(5, 10)]:
        state.handle("pg/r/odom", _odometry(seq).encode())
        state.handle("pg/r/landmarks", _seen(seq).encode())
    state.handle("pg/r/end", StreamEnd(robot="r", scans=10).encode())
    assert asked and all(first <= 3 and (last is None or last >= 4) for _, first, last in asked), asked
    assert rejects.snapshot() == {keys.history_key("r"): 2 * len(asked)} and rejects.kinds() == {"key": 2 * len(asked)}
    poses = [decode_message(payload, PoseGaussian) for payload in published]
    assert [pose.seq for pose in poses] == list(range(10)) and state.stats().poses_published == 10
    np.testing.assert_allclose(poses[9].mean, [0.9, 0.0, 0.0], atol=1e-12)  # moved by every step's odometry


def _dead_reckoning_state(rejects, publish, history) -> SlamState:
    """A SLAM node's state for robot r with an odometry-only filter from the origin, publishing with ``publish``
    (a pose's payload) and asking ``history`` for what its streams skipped."""
    config = NodeConfig(
        robot="r",
        algorithm="odometry",
        motion="odometry",
        initial=np.zeros(3),
        make_filter=lambda start: DeadReckoning(OdometryMotionModel(), start),
    )
    return SlamState(config, rejects, publish=publish, history=history)


def test_an_odometry_pose_that_jumps_is_skipped_and_three_that_agree_are_a_reset():
    """A forged odometry pose 5 km off moved a landmark filter's odometry motion there and back (its covariance then
    km wide): as grid FastSLAM's node does (slam.odometry_jumps), a step that jumps is counted and skipped, and three
    in a row that agree are a reset of the odometry, across which the robot did not move."""
    published: list[bytes] = []
    rejects = _rejects("slam-odometry-jumps")
    state = _dead_reckoning_state(rejects, published.append, lambda *args: [])
    frame = {seq: (0.1 * seq, 0.0) for seq in range(12)}
    frame[4] = (5000.0, 0.0)  # forged: one pose far off
    for seq in range(7, 12):  # the odometry reset: a new frame 300 m away from seq 7 on
        frame[seq] = (300.0 + 0.1 * (seq - 7), 40.0)
    for seq in range(12):
        x, y = frame[seq]
        odometry = Odometry(
            robot="r", seq=seq, stamp=0.1 * seq, pose=np.array([[x, y, 0.0]]), commands=np.zeros((0, 3))
        )
        state.handle("pg/r/odom", odometry.encode())
        state.handle("pg/r/landmarks", _seen(seq).encode())
    poses = {p.seq: p for p in (decode_message(payload, PoseGaussian) for payload in published)}
    assert sorted(poses) == [0, 1, 2, 3, 5, 6, 9, 10, 11] and rejects.kinds() == {"step": 3}
    assert poses[6].mean[0] == pytest.approx(0.6, abs=1e-9)  # (seq 5 moved from seq 3, as over a gap)
    assert poses[9].mean[0] == pytest.approx(0.6, abs=1e-9)  # (the reset: no drive across it)
    assert poses[11].mean[0] == pytest.approx(0.8, abs=1e-9) and abs(poses[11].mean[1]) < 1e-9


def test_a_slam_node_that_missed_the_prior_asks_the_history_for_it():
    """A probe: a node paused (SIGSTOP) as it started missed the prior, which the source publishes once; it never
    asked for it again, took no step and the shards gave up on every scan of the run. Steps waiting with no start
    pose now ask the source's history for its prior, at most once a second (none given: the steps wait)."""
    published: list[bytes] = []
    asked: list[tuple[frozenset, int, int | None]] = []
    prior = PoseGaussian(robot="r", seq=0, stamp=0.0, mean=np.array([2.0, 1.0, 0.0]), cov=np.eye(3) * 1e-4)
    answers: list[tuple[str, bytes]] = []

    def history(streams, first, last):
        asked.append((streams, first, last))
        return [(key, payload) for key, payload in answers if key.rsplit("/", 1)[-1] in streams]

    config = replace(_dead_reckoning_state(_rejects("x"), published.append, history).config, initial=None)
    state = SlamState(config, _rejects("slam-prior"), publish=published.append, history=history)
    said: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: said.append(record.getMessage())
    state.log.addHandler(handler)
    for seq in range(3):  # the history does not answer (a source not up yet, or gone): asked once, steps wait
        state.handle("pg/r/odom", _odometry(seq).encode())
        state.handle("pg/r/landmarks", _seen(seq).encode())
    assert asked == [(frozenset({keys.PRIOR}), 0, 0)] and published == []
    answers.append(("pg/r/prior", prior.encode()))
    state._prior_asked -= PRIOR_RETRY  # (a second later)
    for seq in range(3, 6):
        state.handle("pg/r/odom", _odometry(seq).encode())
        state.handle("pg/r/landmarks", _seen(seq).encode())
    assert len(asked) == 2 and [decode_message(p, PoseGaussian).seq for p in published] == list(range(6))
    np.testing.assert_allclose(decode_message(published[0], PoseGaussian).mean, [2.0, 1.0, 0.0])  # from the prior
    state.handle("pg/r/odom", _odometry(6).encode())
    state.handle("pg/r/landmarks", _seen(6).encode())
    assert len(asked) == 2 and len(published) == 7  # started: no more questions
    state.log.removeHandler(handler)
    assert sum("asking the source's history for its prior" in line for line in said) == 1  # said once, asked twice


def test_a_slam_node_stopping_while_it_takes_the_history_stops_taking_it():
    """A node that starts into a long run takes the source's history first (thousands of steps: seconds); asked to
    stop meanwhile (here as its third pose goes out), it takes no further message."""
    published: list[bytes] = []
    stop = threading.Event()

    def publish(payload: bytes) -> None:
        published.append(payload)
        if len(published) == 3:
            stop.set()

    state = _dead_reckoning_state(_rejects("slam-stop"), publish, history=lambda *_: [])
    replies = [(f"pg/r/{s}", m) for seq in range(50) for s, m in (("odom", _odometry(seq)), ("landmarks", _seen(seq)))]
    state.take_history([(key, message.encode()) for key, message in replies], stop)
    assert [decode_message(p, PoseGaussian).seq for p in published] == [0, 1, 2]


def test_a_far_seq_on_a_stream_the_filter_does_not_use_is_counted_and_leaves_the_order_alone():
    """A scan forged at seq 2^53 - 101 for a landmark node (which takes no scans) became the highest seq of
    pg/r/scan, so every real scan after it was counted out of order. It is counted as ahead, as on the streams
    the filter uses, and the real scans are in order."""
    published: list[bytes] = []
    rejects = _rejects("slam-far-unused")
    state = _dead_reckoning_state(rejects, published.append, history=lambda *_: [])
    state.handle("pg/r/scan", _scan(2**53 - 101).encode())
    for seq in range(10):
        for key, message in (("pg/r/scan", _scan(seq)), ("pg/r/odom", _odometry(seq)), ("pg/r/landmarks", _seen(seq))):
            state.handle(key, message.encode())
    assert [decode_message(p, PoseGaussian).seq for p in published] == list(range(10))
    assert state.stats().out_of_order == {} and rejects.kinds().get("ahead") == 1


def test_landmark_steps_of_values_no_robot_gives_are_counted_and_skipped():
    """Valid on the wire, hostile in intent: a command of 10^6 m/s (the EKF then published poses 10^6 m away),
    ranges of 10^30 (FastSLAM divided by zero, with a traceback), 5 000 new landmark ids (three such messages took
    a node past 5.8 GB), a command of 0.5 m/s held for 2e4 s (the EKF 10^4 m away for good). Each step is counted
    and skipped, and the real steps around them are taken."""
    published: list[bytes] = []
    rejects = _rejects("slam-hostile-values")
    config = NodeConfig(
        robot="r",
        algorithm="ekf",
        make_filter=lambda start: EKFSLAM(VelocityMotionModel((0.1, 0.01, 0.01, 0.1, 0.0, 0.0)), SENSOR, start),
        initial=np.zeros(3),
    )
    state = SlamState(config, rejects, publish=published.append)
    walk = np.array([[0.5, 0.0, 0.1]])  # 0.5 m/s for 0.1 s a step
    hostile = {
        3: (np.array([[1e6, 0.0, 0.1]]), [7], [1.0], [0.1]),
        4: (walk, [7], [1e30], [0.1]),
        5: (walk, list(range(100, 5100)), [1.0] * 5000, [0.1] * 5000),
        6: (walk, [7], [1.0], [7.0]),  # a bearing beyond 2 pi
        7: (np.array([[0.5, 0.0, 2e4]]), [7], [1.0], [0.1]),  # a slow command held 2e4 s (took the EKF 10^4 m away)
        8: (np.tile([0.5, 0.0, 1.0], (120, 1)), [7], [1.0], [0.1]),  # 60 m in one step, in 120 commands
    }
    for seq in range(11):
        commands, ids, ranges, bearings = hostile.get(seq, (walk, [7], [2.0 - 0.05 * seq], [0.1]))
        odometry = Odometry(robot="r", seq=seq, stamp=0.1 * seq, pose=np.zeros((0, 3)), commands=commands)
        seen = LandmarkObservations(
            robot="r", seq=seq, stamp=0.1 * seq, ids=np.array(ids), ranges=np.array(ranges), bearings=np.array(bearings)
        )
        state.handle("pg/r/odom", odometry.encode())
        state.handle("pg/r/landmarks", seen.encode())
    poses = [decode_message(payload, PoseGaussian) for payload in published]
    assert [pose.seq for pose in poses] == [0, 1, 2, 9, 10] and rejects.kinds().get("step") == 6
    assert all(np.hypot(*pose.mean[:2]) < 1.0 for pose in poses)  # 5 steps of 5 cm, not 10^5 m
    assert state.driver is not None and state.driver.filter.n_landmarks == 1


def test_a_gap_over_steps_the_filter_refused_is_said_as_skipped_not_as_lost():
    """The step after refused ones moves over them as over a gap; its line said their commands "never arrived"
    (lost in transit) though they came and were refused, which the node had just said and counted."""
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())
    config = NodeConfig(
        robot="gap-cause",
        algorithm="ekf",
        make_filter=lambda start: EKFSLAM(VelocityMotionModel((0.1, 0.01, 0.01, 0.1, 0.0, 0.0)), SENSOR, start),
        initial=np.zeros(3),
    )
    published: list[bytes] = []
    state = SlamState(config, _rejects("slam-gap-cause"), publish=published.append)
    state.log.addHandler(handler)
    try:
        for seq in range(6):
            speed = 1e6 if seq in (2, 3) else 0.5  # (refused: past what one step may move)
            commands = np.array([[speed, 0.0, 0.1]])
            odometry = Odometry(robot="gap-cause", seq=seq, stamp=0.1 * seq, pose=np.zeros((0, 3)), commands=commands)
            seen = LandmarkObservations(
                robot="gap-cause", seq=seq, stamp=0.1 * seq, ids=np.array([7]), ranges=[2.0], bearings=[0.1]
            )
            state.handle("pg/gap-cause/odom", odometry.encode())
            state.handle("pg/gap-cause/landmarks", seen.encode())
    finally:
        state.log.removeHandler(handler)
    assert [decode_message(p, PoseGaussian).seq for p in published] == [0, 1, 4, 5]
    said = [r for r in records if r.startswith("seq 4:")]
    assert len(said) == 1 and "seq 2-3, which were skipped (the filter could not take them" in said[0], records
    assert not any("never arrived" in r for r in records)


def test_a_step_that_could_start_too_many_unknown_landmarks_is_skipped():
    """With unknown ids each measurement may start a landmark: a step of 5 000 would pass the 1 024 an EKF holds
    (its joint covariance grows with their square)."""
    published: list[bytes] = []
    rejects = _rejects("slam-unknown-flood")
    config = NodeConfig(
        robot="r",
        algorithm="ekf",
        make_filter=lambda start: EKFSLAM(
            VelocityMotionModel((0.1, 0.01, 0.01, 0.1, 0.0, 0.0)), SENSOR, start, known_correspondences=False
        ),
        initial=np.zeros(3),
    )
    state = SlamState(config, rejects, publish=published.append)
    for seq, count in enumerate((1, 5000, 1)):
        rng = np.random.default_rng(seq)
        odometry = Odometry(robot="r", seq=seq, stamp=0.1 * seq, pose=np.zeros((0, 3)), commands=NO_COMMANDS)
        seen = LandmarkObservations(
            robot="r",
            seq=seq,
            stamp=0.1 * seq,
            ids=np.full(count, -1),
            ranges=rng.uniform(1.0, 9.0, count),
            bearings=rng.uniform(-3.0, 3.0, count),
        )
        state.handle("pg/r/odom", odometry.encode())
        state.handle("pg/r/landmarks", seen.encode())
    assert [decode_message(p, PoseGaussian).seq for p in published] == [0, 2] and rejects.kinds().get("step") == 1


def _grid_step(state: SlamState, log, seq: int, odometry: np.ndarray) -> None:
    """Hand ``state`` step ``seq`` of a simulated laser log (slam.gridslam.simlogs): its scan, and ``odometry`` (3,)
    as the step's odometry pose."""
    scan = LaserScan(
        robot="r",
        seq=seq,
        stamp=float(log.stamps[seq]),
        angle_min=log.angle_min,
        angle_increment=log.angle_increment,
        range_min=0.0,
        range_max=log.range_max,
        sensor_offset=np.asarray(log.sensor_offset, np.float64),
        ranges=np.asarray(log.ranges[seq], np.float32),
        no_return_range=log.range_max,
    )
    state.handle("pg/r/scan", scan.encode())
    pose = Odometry(robot="r", seq=seq, stamp=float(log.stamps[seq]), pose=odometry[None], commands=NO_COMMANDS)
    state.handle("pg/r/odom", pose.encode())


def test_a_grid_node_refuses_an_odometry_jump_and_takes_a_reset_after_three_steps():
    """One odometry message moved 3 km took a grid FastSLAM node to 13 GB (every particle's tile table spans the
    particles' box) and its poses 3 km away. The jump is counted and skipped, and the steps after it are taken as
    before; an odometry that stays moved (a reset of the robot's odometry) is its new frame from the third step."""
    log = sim_log("room", seed=1)
    published: list[bytes] = []
    rejects = _rejects("slam-grid-jump")
    config = NodeConfig(
        robot="r", algorithm="gridslam", make_filter=None, initial=log.odometry[0], grid_config=GridSlamConfig()
    )
    state = SlamState(config, rejects, publish=published.append)
    reset = np.array([-500.0, 200.0, 0.0])  # from step 30 on, the odometry reads this much off
    for seq in range(40):
        odometry = log.odometry[seq] + (reset if seq >= 30 else 0.0)
        if seq == 10:
            odometry = odometry + np.array([3000.0, 3000.0, 0.0])
        _grid_step(state, log, seq, odometry)
    poses = {p.seq: p for p in (decode_message(payload, PoseSamples) for payload in published)}
    assert sorted(poses) == [s for s in range(40) if s not in (10, 30, 31)] and rejects.kinds().get("step") == 3
    assert state.driver.filter.maps.table.shape[1] < 200  # tiles of 1.6 m: a few hundred m at most, not 3 km
    for seq, pose in poses.items():  # each step's best particle within 0.5 m of the truth, before and after
        best = pose.samples[int(np.argmax(pose.weights))]
        assert np.hypot(*(best[:2] - log.true_poses[seq][:2])) < 0.5, (seq, best, log.true_poses[seq])


def test_the_landmark_limit_is_the_nodes_option():
    """`slam-node --max-landmarks N` bounds the landmarks a filter holds (the default, 1 024 for EKF-SLAM, would
    refuse a map of more): with 3, a step bringing a fourth id is refused and counted, one of the ids held is taken."""
    from services.cli import build_parser
    from services.commands.pipeline import node_config

    parse = build_parser().parse_args
    config = node_config(parse(["slam-node", "--robot", "r", "--algo", "ekf", "--max-landmarks", "3"]))
    published: list[bytes] = []
    rejects = _rejects("slam-landmark-option")
    state = SlamState(replace(config, initial=np.zeros(3)), rejects, publish=published.append)
    for seq, ids in enumerate(([1, 2], [3], [4], [2])):
        odometry = Odometry(robot="r", seq=seq, stamp=0.1 * seq, pose=np.zeros((0, 3)), commands=NO_COMMANDS)
        n = len(ids)
        seen = LandmarkObservations(
            robot="r", seq=seq, stamp=0.1 * seq, ids=np.array(ids), ranges=np.full(n, 2.0), bearings=np.zeros(n)
        )
        state.handle("pg/r/odom", odometry.encode())
        state.handle("pg/r/landmarks", seen.encode())
    assert [decode_message(p, PoseGaussian).seq for p in published] == [0, 1, 3] and rejects.kinds() == {"step": 1}
    assert node_config(parse(["slam-node", "--robot", "r", "--algo", "ekf"])).max_landmarks is None  # (the default)
    for argv in (["--algo", "gridslam", "--max-landmarks", "3"], ["--algo", "ekf", "--max-odometry-step", "9"]):
        with pytest.raises(UsageError, match="bounds"):
            node_config(parse(["slam-node", "--robot", "r", *argv]))


@pytest.mark.parametrize("limit", [None, 1.0])
def test_the_odometry_step_limit_is_the_nodes_option(limit):
    """`slam-node --max-odometry-step M`: grid FastSLAM refuses a step whose odometry moved more than M (1 m; 2 m
    here, between scans a few cm apart), and takes it under the default of 50 m."""
    from services.cli import build_parser
    from services.commands.pipeline import node_config

    argv = ["slam-node", "--robot", "r", "--algo", "gridslam"] + ([] if limit is None else ["--max-odometry-step", "1"])
    config = node_config(build_parser().parse_args(argv))
    log = sim_log("room", seed=1)
    published: list[bytes] = []
    rejects = _rejects(f"slam-odometry-option-{limit}")
    state = SlamState(replace(config, initial=log.odometry[0]), rejects, publish=published.append)
    for seq in range(5):  # the odometry 2 m off from seq 2 on: a reset, taken as one at its third step
        odometry = log.odometry[seq] + (np.array([2.0, 0.0, 0.0]) if seq >= 2 else 0.0)
        _grid_step(state, log, seq, odometry)
    taken = [decode_message(p, PoseSamples).seq for p in published]
    assert taken == ([0, 1, 2, 3, 4] if limit is None else [0, 1, 4]), (taken, rejects.kinds())


def test_a_history_reply_on_a_stream_no_step_has_is_counted_not_fatal():
    """A hostile answerer replying on pg/r/history/end (a StreamEnd has no seq) stopped the SLAM node with an
    AttributeError while it recovered lost steps; the reply is counted and the steps are taken."""
    published: list[bytes] = []

    def history(streams: frozenset[str], first: int, last: int | None) -> list[tuple[str, bytes]]:
        replies = [("pg/r/end", StreamEnd(robot="r", scans=10).encode())]
        for seq in range(first, (last if last is not None else 4) + 1):
            replies += [("pg/r/odom", _odometry(seq).encode()), ("pg/r/landmarks", _seen(seq).encode())]
        return replies

    rejects = _rejects("slam-history-end")
    state = _dead_reckoning_state(rejects, published.append, history)
    for seq in (0, 1, 3, 4):
        state.handle("pg/r/odom", _odometry(seq).encode())
        state.handle("pg/r/landmarks", _seen(seq).encode())
    state.handle("pg/r/end", StreamEnd(robot="r", scans=5).encode())
    assert [decode_message(p, PoseGaussian).seq for p in published] == [0, 1, 2, 3, 4]
    assert rejects.kinds().get("history", 0) >= 1
