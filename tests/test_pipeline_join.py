"""The in-process parts of the pipeline: joining scans with poses by (robot, seq) in any arrival order with a
bounded, counted buffer; the SLAM node's in-order step release; a shard's counting of bad input."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.sensor_model import SensorModel
from schemas.messages import LaserScan, PoseGaussian, PoseSamples, StreamEnd
from services.join import JoinBuffer, SeqLedger
from services.process import RejectCounter
from services.shard import FUSIONS_KEPT, MapShard, ShardConfig
from services.steps import OutOfOrder, StepAssembler


@settings(max_examples=60, deadline=None)
@given(st.permutations([(kind, seq) for seq in range(8) for kind in ("scan", "pose")]))
def test_join_pairs_every_scan_with_its_pose_in_any_order(arrivals):
    buffer = JoinBuffer(capacity=16)
    pairs = []
    for kind, seq in arrivals:
        add = buffer.add_scan if kind == "scan" else buffer.add_pose
        pair, evicted = add(("r", seq), f"{kind}{seq}")
        assert evicted == []
        if pair is not None:
            pairs.append(pair)
    assert sorted(pairs) == [(f"scan{seq}", f"pose{seq}") for seq in range(8)]
    assert len(buffer) == 0


def test_join_overflow_evicts_the_oldest_and_says_so():
    buffer = JoinBuffer(capacity=3)
    for seq in range(3):
        assert buffer.add_scan(("r", seq), seq) == (None, [])
    pair, evicted = buffer.add_pose(("r", 7), "p7")
    assert pair is None and [(e.key, e.was_scan) for e in evicted] == [(("r", 0), True)]
    assert buffer.add_pose(("r", 0), "p0")[0] is None  # its scan is gone: it waits in turn
    assert buffer.add_pose(("r", 2), "p2")[0] == (2, "p2")


@settings(max_examples=60, deadline=None)
@given(st.permutations([(part, seq) for seq in range(6) for part in ("odom", "landmarks")]))
def test_steps_come_out_in_seq_order_whatever_the_arrival_order(arrivals):
    steps = StepAssembler({"odom", "landmarks"}, reorder=100)
    released = []
    for part, seq in arrivals:
        out = steps.add(part, seq, f"{part}{seq}")
        assert out.skipped == [] and out.evicted == 0
        released += [seq for seq, _ in out.steps]
    assert released == list(range(6))


def test_late_parts_are_out_of_order_and_gaps_are_skipped():
    steps = StepAssembler({"odom"}, reorder=2)
    assert [s for s, _ in steps.add("odom", 0, "a").steps] == [0]
    with pytest.raises(OutOfOrder, match="seq 0 arrived after seq 0"):
        steps.add("odom", 0, "again")
    assert steps.add("odom", 2, "c").steps == []  # seq 1 missing: wait
    out = steps.add("odom", 3, "d")  # two complete steps wait: give up on seq 1
    assert out.skipped == [1] and [s for s, _ in out.steps] == [2, 3]
    with pytest.raises(OutOfOrder):
        steps.add("odom", 1, "too late")


def _scan(seq: int, robot: str = "r") -> LaserScan:
    return LaserScan(robot=robot, seq=seq, stamp=0.1 * seq, angle_min=-1.0, angle_increment=0.5, range_min=0.05,
                     range_max=5.0, sensor_offset=np.zeros(3), ranges=np.array([1.0, 2.0, np.inf, 1.5, 3.0], np.float32))


def _pose(seq: int, robot: str = "r") -> PoseSamples:
    """At (3 m, 3 m): every beam of _scan stays inside tile (0, 0), which spans 0 .. 12.8 m."""
    return PoseSamples(robot=robot, seq=seq, stamp=0.1 * seq, samples=np.array([[3.0, 3.0, 0.1 * seq]]),
                       weights=np.ones(1))


def test_shard_counts_join_overflow_and_bad_input_per_key():
    log = logging.getLogger("test-shard")
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel(), join_capacity=4), RejectCounter(log))
    for seq in range(6):  # six scans, no poses: two are given up on
        shard.handle("pg/r/scan", _scan(seq).encode())
    shard.handle("pg/r/pose", _pose(5).encode())  # completes seq 5
    shard.handle("pg/r/pose", b"\x00 not msgpack")
    shard.handle("pg/r/end", StreamEnd(robot="r", scans=6).encode())
    stats = shard.stats({"intake": 0})
    assert stats.fused == {"r": 1} and stats.discarded == {"r": 2}
    assert stats.overflow == {"intake": 0, "join": 2} and stats.join_pending == 3
    assert stats.rejected == {"join/r": 2, "pg/r/pose": 1}
    assert stats.received == {"pg/r/scan": 6, "pg/r/pose": 2, "pg/r/end": 1}
    assert stats.ended == {"r": 6} and not shard.caught_up()
    assert stats.tiles_owned == 1 and stats.cells_updated > 0


def test_seq_ledger_remembers_done_seqs_within_its_horizon():
    ledger = SeqLedger(horizon=10)
    assert not ledger.done("r", 0)
    for seq in (0, 1, 2, 5):
        ledger.mark("r", seq)
    assert ledger.done("r", 1) and ledger.done("r", 5) and not ledger.done("r", 3) and not ledger.done("r", 6)
    assert not ledger.done("other", 1)  # per robot
    for seq in range(6, 100):
        ledger.mark("r", seq)
    assert ledger.done("r", 3) and ledger.done("r", 89) and not ledger.done("r", 100)  # 3 lies below the horizon


def test_shard_refuses_a_pair_it_has_fused_already():
    """A re-sent scan and pose (a source restarted, a replay run twice) would be fused twice: counted, refused."""
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel()), RejectCounter(logging.getLogger("test-shard")))
    shard.handle("pg/r/scan", _scan(0).encode())
    shard.handle("pg/r/pose", _pose(0).encode())
    before = [a.copy() for a in shard.grid.tile_arrays((0, 0))]
    shard.handle("pg/r/pose", _pose(0).encode())
    shard.handle("pg/r/scan", _scan(0).encode())
    for now, then in zip(shard.grid.tile_arrays((0, 0)), before):
        np.testing.assert_array_equal(now, then)
    shard.handle("pg/r/pose", _pose(1).encode())
    shard.handle("pg/r/scan", _scan(1).encode())
    stats = shard.stats({"intake": 0})
    assert stats.fused == {"r": 2} and stats.join_pending == 0
    assert stats.rejected == {"pg/r/scan": 1, "pg/r/pose": 1}


def test_shard_counts_poses_no_fusion_can_take_and_goes_on():
    """A Gaussian of 100 m sd (a diverged EKF) or samples 1 km apart would need a window of gigabytes: each is
    counted and dropped, and the next scan is fused."""
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel()), RejectCounter(logging.getLogger("test-shard")))
    diverged = PoseGaussian(robot="r", seq=0, stamp=0.0, mean=np.array([3.0, 3.0, 0.0]), cov=np.diag([1e4, 1e4, 0.01]))
    apart = PoseSamples(robot="r", seq=1, stamp=0.1, samples=np.array([[3.0, 3.0, 0.0], [1003.0, 1003.0, 0.0]]),
                        weights=np.full(2, 0.5))
    for seq, pose in enumerate((diverged, apart, _pose(2))):
        shard.handle("pg/r/scan", _scan(seq).encode())
        shard.handle("pg/r/pose", pose.encode())
    stats = shard.stats({"intake": 0})
    assert stats.fused == {"r": 1} and stats.discarded == {"r": 2} and stats.rejected == {"fuse/r": 2}
    assert stats.tiles_owned == 1


def test_shard_keeps_a_bounded_number_of_laser_geometries():
    """A laser whose beam angles change scan by scan must not grow the shard's memory (each geometry's fusion
    holds a scratch window)."""
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel()), RejectCounter(logging.getLogger("test-shard")))
    for seq in range(FUSIONS_KEPT + 3):
        scan = _scan(seq)
        shard.handle("pg/r/scan", LaserScan(**{**scan.__dict__, "angle_min": -1.0 + 1e-6 * seq}).encode())
        shard.handle("pg/r/pose", _pose(seq).encode())
    assert shard.stats({"intake": 0}).fused == {"r": FUSIONS_KEPT + 3}
    assert len(shard._fusions) == FUSIONS_KEPT


def test_tile_updates_carry_only_the_changed_window():
    log = logging.getLogger("test-shard")
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel(), publish_interval=0.0), RejectCounter(log))
    shard.handle("pg/r/scan", _scan(0).encode())
    shard.handle("pg/r/pose", _pose(0).encode())
    first, _ = shard.due_updates(now=0.0)
    assert [(u.tx, u.ty, u.robot, u.seq) for u in first] == [(0, 0, "r", 0)]
    again, _ = shard.due_updates(now=1.0)
    assert again == []  # nothing changed since
    for update in first:
        logodds, variance, observed = shard.grid.tile_arrays((update.tx, update.ty))
        window = (slice(update.row0, update.row0 + update.logodds.shape[0]),
                  slice(update.col0, update.col0 + update.logodds.shape[1]))
        np.testing.assert_array_equal(update.logodds, logodds[window])
        outside = observed.copy()
        outside[window] = False
        assert not outside.any()  # every observed cell of the tile is inside the window
        assert update.logodds.shape[0] < shard.grid.tile_size  # a window, not the whole tile


def test_warm_up_leaves_the_shard_empty():
    shard = MapShard(ShardConfig("m", 0, 1, SensorModel(), publish_interval=0.0), RejectCounter(logging.getLogger("t")))
    shard.warm_up()
    assert shard.tiles() == [] and shard.cells_updated == 0 and sum(shard.fused.values()) == 0
    assert shard.due_updates(now=0.0, flush=True) == ([], None)
