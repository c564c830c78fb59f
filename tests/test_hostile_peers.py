"""What a hostile peer on the Zenoh network can send to a mapper shard and a SLAM node (issue 29, findings 1-3):
wildcard and made-up keys, forged seqs and ends, and valid messages built to exhaust a machine. Each is refused
and counted, and the real stream is fused as if nothing had happened.

The unit tests drive :class:`services.state.shard.MapShard` directly; the last test publishes generated keys to real
processes (router, mapper shard, SLAM node, HTTP API) and checks that every one of them lives and still works.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import replace

import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapping.sensor_model import SensorModel
from peers import put
from schemas.messages import MAX_SEQ, MAX_SHARDS, LaserScan, PoseSamples, ShardStats, StreamEnd, decode_message
from services import keys
from services.ports import free_port
from services.process import MAX_REJECT_KEYS, OTHER_KEYS, RejectCounter
from services.state.limits import ShardLimits, reach_cells, reach_tiles
from services.state.shard import MapShard, ShardConfig
from services.zenoh_config import build_config

CLI = [sys.executable, "-m", "services"]


def _scan(seq: int, robot: str = "r", beams: int = 5, range_max: float = 5.0) -> LaserScan:
    ranges = np.array([1.0, 2.0, np.inf, 1.5, 3.0] * (beams // 5 + 1), np.float32)[:beams]
    return LaserScan(
        robot=robot,
        seq=seq,
        stamp=0.1 * seq,
        angle_min=-1.0,
        angle_increment=2.0 / beams,
        range_min=0.05,
        range_max=range_max,
        sensor_offset=np.zeros(3),
        ranges=ranges,
        no_return_range=range_max,
    )


def _pose(seq: int, robot: str = "r", xy=(3.0, 3.0), samples: int = 1) -> PoseSamples:
    """``samples`` distinct poses (1 mm apart in x, so that none are merged as duplicates) at ``xy`` (m)."""
    cloud = np.tile([xy[0], xy[1], 0.01 * seq], (samples, 1)).astype(np.float64)
    cloud[:, 0] += 1e-3 * np.arange(samples)
    return PoseSamples(robot=robot, seq=seq, stamp=0.1 * seq, samples=cloud, weights=np.full(samples, 1.0 / samples))


def _shard(limits: ShardLimits = ShardLimits()) -> MapShard:
    return MapShard(ShardConfig("m", 0, 1, SensorModel(), limits=limits), RejectCounter(logging.getLogger("hostile")))


def _feed(shard: MapShard, seqs, robot: str = "r") -> None:
    for seq in seqs:
        shard.handle(keys.robot_key(robot, keys.SCAN), _scan(seq, robot).encode())
        shard.handle(keys.robot_key(robot, keys.POSE), _pose(seq, robot).encode())


def _grid_bytes(shard: MapShard) -> dict:
    return {tile: tuple(layer.tobytes() for layer in shard.grid.tile_arrays(tile)) for tile in shard.tiles()}


# ------------------------------------------------------------------------------------------------ keys


@pytest.mark.parametrize(
    "key",
    [
        "pg/r/*",
        "pg/**",
        "pg/*/scan",
        "pg/r/$*",
        "pg/r/scan/extra",
        "pg/r",
        "pg/map/scan",
        "pg/-bad/scan",
        "pg/r/odom",
        "xx/r/scan",
        "pg/" + "a" * 65 + "/scan",
    ],
)
def test_a_publication_on_a_key_that_is_no_robot_stream_is_counted_not_fatal(key):
    """Finding 1: a put on pg/robot0/* raised KeyError('*') in the shard and the SLAM node, which exited."""
    shard = _shard()
    shard.handle(key, _scan(0).encode())
    _feed(shard, range(3))
    stats = shard.stats({})
    assert stats.rejected == {keys.INVALID_KEY: 1} and stats.fused == {"r": 3}


def test_parse_robot_key_takes_exactly_the_concrete_keys_of_known_streams():
    assert keys.parse_robot_key("pg/robot0/scan") == ("robot0", "scan")
    assert keys.parse_robot_key("pg/robot0/pose", {keys.SCAN}) is None
    assert keys.parse_robot_key("pg/map/scan") is None  # "map" is no robot name
    assert keys.parse_history_reply_key("pg/r1/history/odom") == ("r1", "odom")
    assert keys.parse_history_reply_key("pg/r1/history/**") is None
    assert keys.parse_history_reply_key("pg/*/history/scan") is None


@given(st.text(max_size=6))
def test_a_shard_index_is_read_only_in_its_one_decimal_form(text):
    """A peer's token pg/map/<map>/alive/+0 is not shard 0's: int() reads "+0", "00", " 0" and other scripts' digits
    as numbers, and a look-alike token that came and went took the real shard 0 down in the API."""
    canonical = text.isascii() and text.isdigit() and str(int(text)) == text and int(text) < MAX_SHARDS
    assert keys.parse_index(text) == (int(text) if canonical else None)
    assert keys.parse_shard_alive_key(f"pg/map/m/alive/{text}") == (("m", int(text)) if canonical else None)


def test_liveliness_keys_parse_to_their_parts_only():
    assert keys.parse_shard_alive_key("pg/map/main/alive/12") == ("main", 12)
    for key in ("pg/map/main/alive/+0", "pg/map/main/alive/00", "pg/map/*/alive/0", "pg/map/main/alive/0/x"):
        assert keys.parse_shard_alive_key(key) is None, key
    assert keys.parse_shard_alive_key("pg/map/main/alive/1024") is None  # MAX_SHARDS shards: 0 to 1023
    assert keys.parse_process_alive_key("pg/r1/alive/source") == ("r1", "source")
    for key in ("pg/map/alive/source", "pg/*/alive/slam", "pg/r1/alive", "pg/r 1/alive/slam", "xx/r1/alive/slam"):
        assert keys.parse_process_alive_key(key) is None, key


def test_the_reject_counter_counts_a_made_up_key_under_the_invalid_key_and_logs_it_escaped(caplog):
    """256 keys of 60 000 characters made every /health answer 15 MB, and a key with a newline wrote a forged line
    into the log. Such keys are counted under pg/<invalid key>; what is logged is escaped and cut."""
    counter = RejectCounter(logging.getLogger("hostile"))
    with caplog.at_level(logging.WARNING, logger="hostile"):
        counter.count("pg/" + "a" * 60_000 + "/pose", "malformed", "x")
        counter.count("pg/r1\nposegrid api: FORGED/pose", "robot", "a pose of robot 'r1\nFORGED'")
        counter.count("pg/r1/pose", "malformed", "y" * 10_000)
    assert counter.snapshot() == {keys.INVALID_KEY: 2, "pg/r1/pose": 1}
    lines = [record.getMessage() for record in caplog.records]
    assert len(lines) == 3 and all("\n" not in line and len(line) < 1000 for line in lines), lines
    assert "\\nposegrid api: FORGED" in lines[1] and lines[2].endswith(
        "...; further ones of this kind are only counted"
    )


def test_the_reject_counter_keeps_at_most_its_bound_of_keys():
    counter = RejectCounter(logging.getLogger("hostile"))
    for index in range(MAX_REJECT_KEYS + 500):
        counter.count(f"pg/robot{index}/scan", "malformed", "x")
    counted = counter.snapshot()
    assert len(counted) == MAX_REJECT_KEYS + 1 and counted[OTHER_KEYS] == 500
    assert sum(counted.values()) == MAX_REJECT_KEYS + 500 and counter.kinds() == {"malformed": MAX_REJECT_KEYS + 500}


def test_robots_past_the_limit_are_refused_and_counted():
    shard = _shard(ShardLimits(max_robots=2))
    for robot in ("a", "b", "c", "d"):
        _feed(shard, range(2), robot)
    stats = shard.stats({})
    assert stats.fused == {"a": 2, "b": 2} and stats.rejected == {keys.INVALID_KEY: 8}


# ------------------------------------------------------------------------------------------------ forged seqs


def test_forged_seqs_far_ahead_leave_the_real_stream_whole():
    """Finding 2: two valid scans and two valid poses at seq 100000/100001 made each shard give up 99 890 scans as
    missing and refuse every later real scan as late. The map must be the one without them."""
    clean, attacked = _shard(), _shard()
    _feed(clean, range(300))
    _feed(attacked, range(112))
    _feed(attacked, (100_000, 100_001))
    _feed(attacked, range(112, 300))
    for shard in (clean, attacked):
        shard.handle("pg/r/end", StreamEnd(robot="r", scans=300).encode())
    stats = attacked.stats({})
    assert stats.fused == {"r": 300} and stats.discarded == {} and attacked.caught_up()
    assert stats.rejected == {"join/r": 4}  # held beyond the window, counted as ahead
    assert _grid_bytes(attacked) == _grid_bytes(clean)


def test_a_forged_end_far_ahead_cannot_make_the_counters_absurd():
    """Finding 2: an end announcing 2^53 scans after the run made scans_discarded 9 007 199 254 740 592."""
    now = [0.0]
    shard = MapShard(
        ShardConfig("m", 0, 1, SensorModel()), RejectCounter(logging.getLogger("hostile")), clock=lambda: now[0]
    )
    _feed(shard, range(50))
    shard.handle("pg/r/end", StreamEnd(robot="r", scans=50).encode())
    shard.handle("pg/r/end", StreamEnd(robot="r", scans=MAX_SEQ + 1).encode())
    now[0] = 1000.0
    shard.settle()
    stats = shard.stats({})
    assert stats.ended == {"r": 50} and stats.fused == {"r": 50} and stats.discarded == {}
    assert stats.rejected == {"pg/r/end": 1} and shard.rejects.kinds() == {"ahead": 1}


def test_scans_past_an_end_taken_on_its_word_are_fused_and_said_once():
    """A probe's finding: an end forged inside the seq window (announcing 12 scans while the run went on) was taken
    without a word, and the shard then reported more scans fused than its stream's end announced. The scans that
    follow are fused as before, and the contradiction is logged once (not once a scan)."""
    shard = _shard()
    _feed(shard, range(10))
    shard.handle("pg/r/end", StreamEnd(robot="r", scans=12).encode())
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())
    shard.log.addHandler(handler)
    try:
        _feed(shard, range(10, 20))
    finally:
        shard.log.removeHandler(handler)
    stats = shard.stats({})
    assert stats.fused == {"r": 20} and stats.ended == {"r": 12} and stats.discarded == {}
    said = [r for r in records if "past the end" in r]
    assert len(said) == 1 and "seq 12 came past the end of robot 'r'" in said[0] and "(12 scans" in said[0], said


# ------------------------------------------------------------------------------------------------ resources


def test_a_scan_of_more_beams_than_the_limit_is_refused_before_it_is_held():
    """Finding 3: 25 scans of 10^7 beams with no pose grew each shard by about 1 GB."""
    shard = _shard(ShardLimits(max_beams=100))
    for seq in range(25):
        shard.handle("pg/r/scan", _scan(seq, beams=101).encode())
    assert shard._join.held_bytes("r") == 0
    assert shard.stats({}).rejected == {"pg/r/scan": 25} and shard.rejects.kinds() == {"size": 25}


def test_the_join_holds_at_most_its_byte_bound_of_scans_waiting_for_a_pose():
    shard = _shard(ShardLimits(join_bytes=100_000))
    for seq in range(200):
        shard.handle("pg/r/scan", _scan(seq, beams=1000).encode())  # 4 000 bytes each, no pose ever
    assert shard._join.held_bytes("r") <= 100_000


def test_the_join_bound_holds_for_all_robots_together_and_the_flooding_robot_pays():
    """A probe's finding: the join's byte bound was per robot, so 64 robots of scans with no pose held 1.87 GB (the
    limits allowed 4 GiB). The bound is now for every robot together, and the robot holding the most loses its oldest
    halves: a robot whose scan waits for its pose still gets it fused."""
    shard = _shard(ShardLimits(join_bytes=100_000))
    shard.handle("pg/a/scan", _scan(0, robot="a", beams=1000).encode())
    for robot in ("b", "c", "d"):
        for seq in range(100):
            shard.handle(f"pg/{robot}/scan", _scan(seq, robot=robot, beams=1000).encode())  # no pose ever
        assert shard._join.held_bytes() <= 100_000
    shard.handle("pg/a/pose", _pose(0, robot="a").encode())
    shard.fuse_ready()
    assert shard.stats({}).fused == {"a": 1}


def test_a_scan_that_could_grow_the_map_past_its_limit_is_refused():
    """A probe's finding: 1 025 one-beam scans in distinct tiles, each within --map-bound, took 1.6 GB, and the whole
    bound would take 19 GB. A shard holds at most --max-map-cells cells of tiles: here 9 tiles of 256 x 256 cells. A
    scan at (3, 3) m with a 5 m range reaches the 3 x 3 tiles around tile (0, 0) and makes only that one; a scan
    300 m away could add 9 more (refused), and one back near the first could add only the 8 still missing."""
    shard = _shard(ShardLimits(max_map_cells=9 * 256 * 256))
    for seq, xy in enumerate([(3.0, 3.0), (300.0, 3.0), (3.0, 3.0)]):
        shard.handle("pg/r/scan", _scan(seq).encode())
        shard.handle("pg/r/pose", _pose(seq, xy=xy).encode())
    shard.fuse_ready()
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"map": 1}
    assert shard.tiles() == [(0, 0)]


def test_a_batch_of_scans_counts_the_tiles_its_earlier_scans_may_add():
    """A probe's finding: a batch's scans (several messages' pairs fused together on the shard's threads, or a run of
    seqs confirmed at once) were each checked against the tiles held before the batch, so 40 scans 40 m apart made
    95 tiles under a limit of 9. Now the first scan's 3 x 3 tiles count for the rest: the nine far scans are refused,
    and a last scan back at the first spot, which can add no tile the first does not, is fused."""
    shard = _shard(ShardLimits(max_map_cells=9 * 256 * 256))
    spots = [(3.0 + 40.0 * i, 3.0) for i in range(10)] + [(3.0, 3.0)]
    for seq, xy in enumerate(spots):
        shard.handle("pg/r/scan", _scan(seq).encode(), defer=True)
        shard.handle("pg/r/pose", _pose(seq, xy=xy).encode(), defer=True)
    shard.fuse_ready()
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 9} and shard.rejects.kinds() == {"map": 9}
    assert shard.grid.tile_count <= 9


def test_the_tiles_a_scan_makes_lie_within_its_counted_reach():
    """A probe's finding: the limits counted the tiles within range_max of the laser, but a return just short of
    range_max is walked TAIL_SIGMAS sigma and half the peak width past it, so 2 159 of 7 598 random scans made tiles
    outside the count. Random scans whose returns lie just short of range_max, near tile corners, with tiles of 1 to
    256 cells and sensor offsets: every tile made lies within reach_tiles of the model's beam_reach."""
    rng = np.random.default_rng(7)
    model = SensorModel()
    limits = ShardLimits(max_map_cells=10**9, max_work=10**12, max_scan_cells=10**9)
    for _ in range(60):
        tile_size = int(2 ** rng.integers(0, 9))
        side = tile_size * model.resolution
        range_max = max(0.06, min(5.0, side * int(rng.integers(1, 4)) * float(rng.choice([1.0, 0.999, 1.5]))))
        offset = rng.choice([0.0, 1.0]) * rng.uniform(-1, 1, 3) * np.array([side, side, np.pi])
        count = int(rng.choice([1, 5, 50]))
        corner = rng.integers(-5, 5, 2) * side - 1e-4
        samples = np.column_stack(
            [corner[0] + rng.uniform(-1e-3, 1e-3, count), corner[1] + rng.uniform(-1e-3, 1e-3, count)]
            + [rng.uniform(-np.pi, np.pi, count)]
        )
        ranges = np.full(360, range_max * float(rng.choice([0.999, 1.0 - 1e-6])), np.float32)
        ranges[::7] = np.inf
        shard = MapShard(
            ShardConfig("m", 0, 1, model, tile_size=tile_size, limits=limits),
            RejectCounter(logging.getLogger("hostile")),
        )
        scan = replace(_scan(0, beams=360, range_max=range_max), ranges=ranges, sensor_offset=offset)
        scan = replace(scan, angle_min=-np.pi, angle_increment=2 * np.pi / 360)
        pose = PoseSamples(robot="r", seq=0, stamp=0.0, samples=samples, weights=np.full(count, 1.0 / count))
        shard.handle("pg/r/scan", scan.encode())
        shard.handle("pg/r/pose", pose.encode())
        assert shard.stats({}).fused == {"r": 1}
        drawn, _ = shard.pose_samples(scan, pose)
        reach = model.beam_reach(range_max) + float(np.hypot(offset[0], offset[1]))
        counted = {tuple(tile) for tile in reach_tiles(drawn, reach, model.resolution, tile_size).tolist()}
        assert set(shard.tiles()) <= counted, (tile_size, range_max, offset)


def test_a_scan_past_the_work_limit_is_refused_and_counted_as_discarded():
    """Finding 3: one 10^6-beam scan with a 1 000-sample pose kept a shard busy for 5 minutes."""
    model = SensorModel()
    work = 1000 * 50 * int(np.ceil(5.0 / model.resolution))
    shard = _shard(ShardLimits(max_work=work - 1))
    shard.handle("pg/r/scan", _scan(0, beams=50).encode())
    shard.handle("pg/r/pose", _pose(0, samples=1000).encode())
    _feed(shard, range(1, 3))
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"work": 1}


def test_a_wide_cloud_of_samples_costs_its_window_and_is_refused():
    """A probe's finding: 10 000 samples spread over 190 m with one beam made 10^6 ray cells, a thousandth of the
    work limit, yet took 3.6 s and 1 GB: the fusion folds and sweeps the samples' whole window once a sample. The
    work counts the window's words: 10^4 x (100 + 4000^2 / 64) = 2.5 x 10^9, past the default 10^9."""
    shard = _shard(ShardLimits())
    spread = np.random.default_rng(3).uniform(-95.0, 95.0, (10_000, 3))
    cloud = PoseSamples(robot="r", seq=0, stamp=0.0, samples=spread, weights=np.full(10_000, 1e-4))
    shard.handle("pg/r/scan", _scan(0, beams=1).encode())
    shard.handle("pg/r/pose", cloud.encode())
    assert shard.stats({}).discarded == {"r": 1} and shard.rejects.kinds() == {"work": 1} and not shard.tiles()


def test_a_pose_beyond_the_map_bound_is_refused():
    """Finding 3: a pose at (750 m, 750 m) made each npz export 2.96 GB."""
    shard = _shard(ShardLimits(map_bound=500.0))
    shard.handle("pg/r/scan", _scan(0).encode())
    shard.handle("pg/r/pose", _pose(0, xy=(750.0, 750.0)).encode())
    _feed(shard, range(1, 3))
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"bound": 1}
    assert all(abs(tx) < 5 and abs(ty) < 5 for tx, ty in shard.tiles())


def test_a_laser_offset_beyond_the_map_bound_is_refused():
    """A probe's finding: a scan whose sensor offset put its laser 1e6 to 5e10 m from a pose at (3, 3) was fused
    into tiles that far away, past the map bound that the pose met. The bound and the extent hold for where the
    laser may be."""
    shard = _shard(ShardLimits(map_bound=500.0))
    far = replace(_scan(0), sensor_offset=np.array([1e6, 0.0, 0.0]))
    shard.handle("pg/r/scan", far.encode())
    shard.handle("pg/r/pose", _pose(0).encode())
    _feed(shard, range(1, 3))
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"bound": 1}
    assert all(abs(tx) < 5 and abs(ty) < 5 for tx, ty in shard.tiles())
    near, _ = ShardLimits(map_bound=500.0).check_scan(np.array([[3.0, 3.0, 0.0]]), 5, 5.0, 0.05, 256, 0.3)
    assert near is None  # a laser mounted 0.3 m off the base is no problem


def test_reach_cells_counts_the_union_of_the_widened_sample_tiles():
    """Hand-computed: 12.8 m tiles (256 cells of 0.05 m); range 5 m widens each sample's tile by one tile."""
    one = np.array([[3.0, 3.0, 0.0]])
    assert reach_cells(one, 5.0, 0.05, 256) == 9 * 256 * 256
    two_apart = np.array([[3.0, 3.0, 0.0], [3.0 + 12.8, 3.0, 0.0]])  # neighbouring tiles: 4 x 3 tiles
    assert reach_cells(two_apart, 5.0, 0.05, 256) == 12 * 256 * 256
    far = np.array([[3.0, 3.0, 0.0], [300.0, 3.0, 0.0]])  # disjoint: 9 + 9
    assert reach_cells(far, 5.0, 0.05, 256) == 18 * 256 * 256
    cloud = np.array([[3.0, 3.0, 0.0], [12.7, 0.1, 1.0], [0.1, 12.7, -1.0]])  # one tile, three samples: 3 x 3 tiles
    assert reach_cells(cloud, 5.0, 0.05, 256) == 9 * 256 * 256
    assert reach_cells(cloud, 30.0, 0.05, 256) == 49 * 256 * 256  # 30 m: three tiles a side, 7 x 7
    assert reach_cells(np.zeros((0, 3)), 5.0, 0.05, 256) == 0


def test_reach_tiles_are_the_slow_references_union_of_squares():
    """Random clouds (1 to 40 samples spread 1 cm to 300 m, tiles of 1 to 256 cells, reach up to 12 tiles): the tiles
    listed are exactly the union of each sample's tile widened by ceil(reach / tile side) tiles, built here one tile
    at a time, and reach_cells counts them; where the box is too large to list, the count is at least the union."""
    rng = np.random.default_rng(3)
    for _ in range(150):
        count, tile_size = int(rng.integers(1, 40)), int(2 ** rng.integers(0, 9))
        side = tile_size * 0.05
        reach, spread = float(rng.uniform(0.01, 12 * side)), float(rng.choice([0.01, 1.0, 30.0, 300.0]))
        samples = np.column_stack(
            [rng.normal(0, spread, count) + rng.uniform(-500, 500), rng.normal(0, spread, count), np.zeros(count)]
        )
        widen = math.ceil(reach / side)
        union = {
            (math.floor(x / side) + dx, math.floor(y / side) + dy)
            for x, y, _ in samples
            for dx in range(-widen, widen + 1)
            for dy in range(-widen, widen + 1)
        }
        listed = reach_tiles(samples, reach, 0.05, tile_size)
        cells = reach_cells(samples, reach, 0.05, tile_size)
        if listed is None:
            assert cells >= len(union) * tile_size**2
        else:
            assert {(tx, ty) for tx, ty in listed.tolist()} == union and cells == len(union) * tile_size**2


def test_a_pose_cloud_spread_over_a_large_area_is_refused_by_the_extent_limit():
    shard = _shard(ShardLimits(max_scan_cells=50 * 256 * 256))
    spread = PoseSamples(
        robot="r",
        seq=0,
        stamp=0.0,
        weights=np.full(40, 1 / 40),
        samples=np.column_stack([np.arange(40) * 20.0, np.zeros(40), np.zeros(40)]),
    )
    shard.handle("pg/r/scan", _scan(0).encode())
    shard.handle("pg/r/pose", spread.encode())
    assert shard.stats({}).discarded == {"r": 1} and shard.rejects.kinds() == {"extent": 1} and not shard.tiles()


@pytest.mark.parametrize(
    ("model", "range_max"),
    [(SensorModel(), 1e300), (SensorModel(), 1e7), (SensorModel(sigma="stereo", baseline_focal=100.0), 1e200)],
    ids=["1e300 m", "1e7 m", "a reach of inf m"],
)
def test_a_scan_whose_range_reaches_absurdly_far_is_refused_and_the_shard_goes_on(model, range_max):
    """A probe's finding: one scan with range_max 1e300 m (valid on the wire: finite and positive) crashed every
    shard with an OverflowError, as the count of the tiles within its reach (about 1e604 cells) was written into the
    refusal with :.3g; six such scans in a minute used up `posegrid run`'s restarts and stopped the run. With the
    stereo model's sigma (z**2 / b f) the reach itself is inf. Refused as "extent", counted, and the next scans fuse."""
    shard = MapShard(ShardConfig("m", 0, 1, model), RejectCounter(logging.getLogger("hostile")))
    shard.handle("pg/r/scan", _scan(0, range_max=range_max).encode())
    shard.handle("pg/r/pose", _pose(0).encode())
    _feed(shard, range(1, 3))
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"extent": 1}
    assert all(abs(tx) < 5 and abs(ty) < 5 for tx, ty in shard.tiles())


def test_a_scan_whose_range_max_is_a_kilometre_but_whose_beams_stop_near_is_fused_as_a_near_one():
    """A ROS robot whose scans state range_max +inf reaches the shards with range_max 1 km (slam.laserlog's ceiling):
    the shard bounded its reach by range_max and refused every such scan as "extent". The bound now comes from the
    farthest its beams are walked (returns, and the no-return range), so the scans fuse, into the same map as the
    same readings stated with a range_max of 10 m."""
    maps = []
    for range_max in (1000.0, 10.0):
        shard = _shard()
        for seq in range(3):
            scan = _scan(seq)
            shard.handle("pg/r/scan", replace(scan, range_max=range_max, no_return_range=5.0).encode())
            shard.handle("pg/r/pose", _pose(seq).encode())
        assert shard.stats({}).fused == {"r": 3} and shard.rejects.kinds() == {}
        maps.append(_grid_bytes(shard))
    assert maps[0] == maps[1]


@settings(max_examples=300, deadline=None)
@given(
    reach=st.floats(0.01, 2000.0),
    tile_size=st.sampled_from([1, 4, 64, 256]),
    max_scan_cells=st.integers(1, 10**9),
    spread=st.sampled_from([0.0, 1.0, 40.0]),
)
def test_the_extent_limit_refuses_exactly_the_scans_whose_reach_holds_too_many_cells(
    reach, tile_size, max_scan_cells, spread
):
    """The refusal of a reach too far to count (before reach_cells) never refuses a scan that the count of its
    tiles would let through: "extent" exactly when reach_cells, the reference, passes the limit."""
    samples = np.array([[3.0, 3.0, 0.0], [3.0 + spread, 3.0 - spread, 0.5]])
    limits = ShardLimits(max_scan_cells=max_scan_cells, max_work=10**18, map_bound=1e4)
    refused, _ = limits.check_scan(samples, 5, reach, 0.05, tile_size)
    too_many = reach_cells(samples, reach, 0.05, tile_size) > max_scan_cells
    assert (refused is not None and refused[0] == "extent") == too_many


def test_a_check_that_fails_on_a_scan_is_counted_as_its_error_and_the_shard_goes_on():
    """Whatever goes wrong while a scan is checked (a value the checks were not written for) is the scan's failure,
    counted and logged with its traceback, not the shard's: nothing of that scan reaches the map."""

    class Brittle(ShardLimits):
        def check_scan(self, samples, beams, range_max, resolution, tile_size, sensor_reach=0.0):
            if samples[0, 2] == 0.0:  # the pose of seq 0 (_pose's yaw is 0.01 seq)
                raise OverflowError("a value the checks were not written for")
            return super().check_scan(samples, beams, range_max, resolution, tile_size, sensor_reach)

    shard = _shard(Brittle())
    _feed(shard, range(3))
    stats = shard.stats({})
    assert stats.fused == {"r": 2} and stats.discarded == {"r": 1} and shard.rejects.kinds() == {"error": 1}


def test_limits_refuse_nonsense_values():
    for bad in ({"max_beams": 0}, {"map_bound": float("nan")}, {"map_bound": -1.0}, {"seq_window": 0}):
        with pytest.raises(ValueError):
            ShardLimits(**bad)


# ------------------------------------------------------------------------------------------------ real processes

KEY_CHUNKS = st.one_of(
    st.sampled_from(
        [
            "*",
            "**",
            "$*",
            "pg",
            "map",
            "robot0",
            "scan",
            "pose",
            "end",
            "odom",
            "prior",
            "landmarks",
            "history",
            "alive",
            "tile",
            "stats",
            "slam",
            "0",
        ]
    ),
    st.from_regex(r"[A-Za-z0-9_.\-]{1,12}", fullmatch=True),
    st.text(alphabet=st.characters(blacklist_characters="/*$?#", blacklist_categories=("Cs",)), min_size=1, max_size=8),
)
HOSTILE_KEYS = st.lists(KEY_CHUNKS, min_size=1, max_size=6).map(lambda chunks: "/".join(["pg", *chunks]))


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    """A router, one mapper shard, a grid FastSLAM node for robot0 and the HTTP API, ended by PID at the end."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    api_port = free_port()
    log_dir = tmp_path_factory.mktemp("hostile-logs")
    argvs = {
        "router": ["router", "--listen", endpoint],
        "mapper": ["mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint],
        "slam": ["slam-node", "--robot", "robot0", "--algo", "ekf", "--initial", "0,0,0", "--connect", endpoint],
        "api": ["api", "--host", "127.0.0.1", "--port", str(api_port), "--connect", endpoint],
    }
    procs = {}
    try:
        for name, argv in argvs.items():
            log = open(log_dir / f"{name}.log", "w")  # noqa: SIM115 - closed with the process below
            procs[name] = (subprocess.Popen([*CLI, *argv], stdout=log, stderr=subprocess.STDOUT), log)
            if name == "router":
                time.sleep(0.5)
        session = zenoh.open(build_config("client", connect=[endpoint]))
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            if list(session.get("pg/map/m/stats/0", timeout=2)) and list(
                session.get("pg/robot0/slam/stats", timeout=2)
            ):
                break
            time.sleep(0.2)
        yield session, procs, api_port
        session.close()
    finally:
        for process, log in reversed(list(procs.values())):
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
                try:
                    process.wait(20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
            log.close()


@pytest.mark.slow
@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    key=HOSTILE_KEYS,
    payload=st.one_of(
        st.binary(max_size=64), st.sampled_from([_scan(0, "robot0").encode(), _pose(0, "robot0").encode()])
    ),
)
def test_generated_keys_reach_every_process_and_none_of_them_dies(pipeline, key, payload):
    """Finding 1, as a property: a put on any key under pg/ (wildcards, unknown streams, wrong depth, odd
    characters) leaves the router, the shard, the SLAM node and the API running."""
    session, procs, _ = pipeline
    with contextlib.suppress(zenoh.ZError):  # a key expression zenoh itself refuses never leaves the session
        put(session, key, payload)
    dead = {name: process.returncode for name, (process, _) in procs.items() if process.poll() is not None}
    assert not dead, f"after a put on {key!r}: {dead} exited"


@pytest.mark.slow
def test_after_the_hostile_keys_every_process_still_answers_and_fuses(pipeline):
    session, procs, api_port = pipeline
    put(session, "pg/robot0/*", b"")  # the finding's own put
    put(session, "pg/**", b"\x00")
    put(session, "pg/r8/scan", _scan(0, "r8", range_max=1e300).encode())  # (crashed the shard: an OverflowError)
    put(session, "pg/r8/pose", _pose(0, "r8").encode())
    put(session, "pg/r9/pose", _pose(0, "r9").encode())
    put(session, "pg/r9/scan", _scan(0, "r9").encode())
    deadline, stats = time.monotonic() + 60, None
    while time.monotonic() < deadline:
        replies = [r.ok for r in session.get("pg/map/m/stats/0", timeout=5) if r.ok is not None]
        stats = decode_message(replies[0].payload.to_bytes(), ShardStats) if replies else None
        if stats is not None and stats.fused.get("r9") == 1 and stats.discarded.get("r8") == 1:
            break
        time.sleep(0.2)
    assert stats is not None and stats.fused.get("r9") == 1 and stats.discarded.get("r8") == 1, stats
    assert stats.rejected.get(keys.INVALID_KEY, 0) >= 2
    assert [r.ok for r in session.get("pg/robot0/slam/stats", timeout=5) if r.ok is not None]
    put(session, "pg/r9/scan", _scan(100_000, "r9").encode())
    health, deadline = None, time.monotonic() + 60
    while time.monotonic() < deadline:  # /health says what the shards could not trust (finding 2)
        with urllib.request.urlopen(f"http://127.0.0.1:{api_port}/health", timeout=20) as response:
            health = json.load(response)
        distrust = " ".join(health["maps"].get("m", {}).get("distrust", []))
        if "seq window" in distrust and "no posegrid key" in distrust:
            break
        time.sleep(0.5)
    assert "seq window" in distrust and "no posegrid key" in distrust, health
    dead = {name: process.returncode for name, (process, _) in procs.items() if process.poll() is not None}
    assert not dead, dead


def test_health_names_each_kind_of_distrusted_refusal_once():
    from services.api.status import distrust

    assert distrust({"ahead": 4, "malformed": 7, "key": 1}) == [
        "4 messages with seqs or ends beyond the seq window (forged or stray seqs; held, never fused)",
        "1 messages on keys that are no posegrid key (wildcards, made-up streams)",
    ]
    assert distrust({"malformed": 3, "missing": 2}) == []


# ------------------------------------------------------------------------------------------------ files


def _npz_with_member(path, name: str, header: dict, body: bytes) -> None:
    """A .npz whose member ``name`` has the .npy ``header`` as given and ``body`` after it (deflated)."""
    import io
    import zipfile

    member = io.BytesIO()
    np.lib.format.write_array_header_1_0(member, header)
    member.write(body)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(name, member.getvalue())


def test_an_array_declaring_a_trillion_elements_is_refused_as_damaged_not_out_of_memory(tmp_path):
    """Finding 8: a declared 10^12-element array was refused with a misleading "out of memory" message."""
    from schemas.files import read_npz
    from schemas.wire import FormatError

    path = tmp_path / "huge.npz"
    _npz_with_member(path, "ranges.npy", {"descr": "<f8", "fortran_order": False, "shape": (10**12,)}, bytes(16))
    with pytest.raises(FormatError, match=r"declares shape \(1000000000000,\).*holds 16 bytes"):
        read_npz(path, "posed-scan file")
    out = subprocess.run(
        [*CLI, "fuse", str(path), "-o", str(tmp_path / "map.npz")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 2 and "declares shape" in out.stderr and "Traceback" not in out.stderr
    assert "memory" not in out.stderr and not (tmp_path / "map.npz").exists()


def test_a_zip_bomb_is_refused_before_it_is_inflated(tmp_path, monkeypatch):
    """Finding 8: a 2 MB zip bomb reached 4.25 GB of memory before it was refused. The sizes in the zip directory
    are read first (the limit is lowered here so that the test inflates nothing large)."""
    import schemas.files
    from schemas.wire import FormatError

    monkeypatch.setattr(schemas.files, "MAX_NPZ_BYTES", 2**20)
    path = tmp_path / "bomb.npz"
    _npz_with_member(
        path, "ranges.npy", {"descr": "|u1", "fortran_order": False, "shape": (8 * 2**20,)}, bytes(8 * 2**20)
    )
    assert path.stat().st_size < 64 * 2**10
    with pytest.raises(FormatError, match="GiB once inflated"):
        schemas.files.read_npz(path, "posed-scan file")
