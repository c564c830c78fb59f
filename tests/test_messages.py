"""Wire messages: every type round-trips bit for bit, and every kind of corruption is rejected with
the reason that names it. The expected values are built here by hand, not by the codec."""

from __future__ import annotations

import dataclasses
import json
import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from conftest import ROOT
from schemas.errors import FormatError
from schemas.jsonschema import render_schemas
from schemas.messages import (
    CELL_SIZE_RANGE,
    MAX_POSE_SAMPLES,
    MAX_SEQ,
    MAX_SHARDS,
    MAX_TILE_INDEX,
    MAX_TILE_SIZE,
    MESSAGE_TYPES,
    POSE_LIMIT,
    LandmarkObservations,
    LaserScan,
    MessageError,
    NodeStats,
    Odometry,
    PoseGaussian,
    PoseSamples,
    ShardStats,
    StreamEnd,
    TileUpdate,
    decode_message,
)
from schemas.wire import MAX_ARRAY_ELEMENTS
from services.nodes.mapper import sent_payload

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])

names = st.from_regex(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,15}\Z").filter(lambda s: s != "map")
seqs = st.integers(0, 2**40)
finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
counts = st.dictionaries(st.text(min_size=1, max_size=12), st.integers(0, 2**31), max_size=4)


def f64(shape):
    return hnp.arrays(np.float64, shape, elements=finite)


@st.composite
def laser_scans(draw):
    beams = draw(st.integers(1, 50))
    ranges = draw(
        hnp.arrays(
            np.float32,
            beams,
            elements=st.one_of(st.floats(0, 50, width=32), st.just(float("nan")), st.just(float("inf"))),
        )
    )
    range_min = draw(st.floats(0, 1))
    range_max = range_min + draw(st.floats(0.5, 80))
    return LaserScan(
        robot=draw(names),
        seq=draw(seqs),
        stamp=draw(finite),
        angle_min=draw(st.floats(-6.28, 6.28)),
        angle_increment=draw(st.floats(0.001, 0.1)),
        range_min=range_min,
        range_max=range_max,
        sensor_offset=draw(f64(3)),
        ranges=ranges,
        no_return_range=draw(st.sampled_from([0.0, range_max, 0.5 * range_max])),
    )


@st.composite
def pose_samples(draw):
    m = draw(st.integers(1, 30))
    raw = draw(hnp.arrays(np.float64, m, elements=st.floats(0.01, 1)))
    return PoseSamples(
        robot=draw(names), seq=draw(seqs), stamp=draw(finite), samples=draw(f64((m, 3))), weights=raw / raw.sum()
    )


@st.composite
def pose_gaussians(draw):
    a = draw(hnp.arrays(np.float64, (3, 3), elements=st.floats(-2, 2)))
    return PoseGaussian(robot=draw(names), seq=draw(seqs), stamp=draw(finite), mean=draw(f64(3)), cov=a @ a.T)


@st.composite
def odometries(draw):
    k = draw(st.integers(0, 5))
    commands = draw(f64((k, 3)))
    commands[:, 2] = np.abs(commands[:, 2])
    return Odometry(
        robot=draw(names),
        seq=draw(seqs),
        stamp=draw(finite),
        pose=draw(f64((draw(st.integers(0, 1)), 3))),
        commands=commands,
    )


@st.composite
def landmarks(draw):
    k = draw(st.integers(0, 10))
    return LandmarkObservations(
        robot=draw(names),
        seq=draw(seqs),
        stamp=draw(finite),
        ids=draw(hnp.arrays(np.int64, k, elements=st.integers(-1, 1000))),
        ranges=draw(hnp.arrays(np.float64, k, elements=st.floats(0, 100))),
        bearings=draw(f64(k)),
    )


@st.composite
def tile_updates(draw):
    size = 2 ** draw(st.integers(0, 5))
    h, w = draw(st.integers(1, size)), draw(st.integers(1, size))
    layers = (
        draw(hnp.arrays(np.float32, (h, w), elements=st.floats(-20, 20, width=32))),
        draw(hnp.arrays(np.float32, (h, w), elements=st.floats(0, 50, width=32))),
        draw(hnp.arrays(np.bool_, (h, w))),
    )
    return TileUpdate.of_window(
        layers,
        draw(hnp.arrays(np.bool_, (h, w))),
        map=draw(names),
        shard=draw(st.integers(0, 9)),
        z=0,
        tx=draw(st.integers(-1000, 1000)),
        ty=draw(st.integers(-1000, 1000)),
        tile_size=size,
        resolution=draw(st.floats(0.001, 1)),
        row0=draw(st.integers(0, size - h)),
        col0=draw(st.integers(0, size - w)),
        robot=draw(names),
        seq=draw(seqs),
        published=draw(finite),
    )


@st.composite
def shard_stats(draw):
    shards = draw(st.integers(1, 8))
    return ShardStats(
        map=draw(names),
        shard=draw(st.integers(0, shards - 1)),
        shards=shards,
        tiles_owned=draw(st.integers(0, 10**6)),
        cells_updated=draw(st.integers(0, 10**12)),
        tile_updates=draw(st.integers(0, 10**6)),
        join_pending=draw(st.integers(0, 100)),
        uptime=draw(st.floats(0, 1e6)),
        fused=draw(counts),
        discarded=draw(counts),
        ended=draw(counts),
        received=draw(counts),
        resent=draw(counts),
        rejected=draw(counts),
        overflow=draw(counts),
        refused=draw(counts),
    )


MESSAGES = {
    "LaserScan": laser_scans(),
    "Odometry": odometries(),
    "LandmarkObservations": landmarks(),
    "PoseSamples": pose_samples(),
    "PoseGaussian": pose_gaussians(),
    "StreamEnd": st.builds(StreamEnd, robot=names, scans=st.integers(0, 10**9)),
    "TileUpdate": tile_updates(),
    "ShardStats": shard_stats(),
    "NodeStats": st.builds(
        NodeStats,
        robot=names,
        algorithm=st.sampled_from(["ekf", "fastslam", "gridslam"]),
        poses_published=st.integers(0, 10**6),
        steps_done=st.integers(0, 10**6),
        uptime=st.floats(0, 1e6),
        received=counts,
        rejected=counts,
        out_of_order=counts,
        noise_scale=st.floats(0, 1e4),
        consistency=counts,
    ),
}
any_message = st.sampled_from(sorted(MESSAGES)).flatmap(lambda name: MESSAGES[name])


def fields(message) -> dict:
    return {name: getattr(message, name) for name in type(message).__dataclass_fields__}


def assert_same(a, b):
    assert type(a) is type(b)
    for name, value in fields(a).items():
        other = getattr(b, name)
        if isinstance(value, np.ndarray):
            assert other.dtype == value.dtype and other.shape == value.shape, name
            assert value.tobytes() == other.tobytes(), name  # bit-exact, NaN payloads included
        else:
            assert other == value, name


def test_every_type_has_a_strategy():
    assert set(MESSAGES) == set(MESSAGE_TYPES)


@SETTINGS
@given(any_message)
def test_round_trip_is_bit_exact(message):
    payload = message.encode()
    assert_same(decode_message(payload), message)
    assert_same(decode_message(payload, type(message)), message)


@SETTINGS
@given(tile_updates(), st.floats(0.0, 4e9))
def test_a_shard_stamps_a_tile_update_as_it_sends_it(update, now):
    sent = decode_message(sent_payload(update, clock=lambda: now), TileUpdate)
    assert sent.published == now
    assert_same(sent, dataclasses.replace(update, published=now))  # everything else as it was made


def test_arrays_travel_as_raw_bytes_not_lists():
    ranges = np.arange(1, 361, dtype=np.float32) / 10
    scan = LaserScan(
        robot="r",
        seq=0,
        stamp=0.0,
        angle_min=0.0,
        angle_increment=0.01,
        range_min=0.0,
        range_max=40.0,
        sensor_offset=np.zeros(3),
        ranges=ranges,
        no_return_range=0.0,
    )
    wire = msgpack.unpackb(scan.encode())
    assert wire["ranges"] == {"dtype": "<f4", "shape": [360], "data": ranges.tobytes()}
    assert len(scan.encode()) < 360 * 4 + 300


# ------------------------------------------------------------------------------------- corruptions


def wire_of(message) -> dict:
    return msgpack.unpackb(message.encode())


def reason_of(wire_or_bytes, *expected) -> str:
    payload = wire_or_bytes if isinstance(wire_or_bytes, bytes) else msgpack.packb(wire_or_bytes, use_bin_type=True)
    with pytest.raises(MessageError) as info:
        decode_message(payload, *expected)
    assert isinstance(info.value, FormatError) and str(info.value)
    return info.value.reason


@SETTINGS
@given(st.binary(max_size=200))
def test_random_bytes_are_malformed_or_rejected(data):
    try:
        wire = msgpack.unpackb(data)
    except Exception:
        assert reason_of(data) == "malformed"
        return
    if not isinstance(wire, dict) or not isinstance(wire.get("type"), str):
        assert reason_of(data) == "malformed"
    else:
        with pytest.raises(MessageError):
            decode_message(data)


@SETTINGS
@given(any_message, st.data())
def test_truncated_payload_is_malformed(message, data):
    payload = message.encode()
    cut = data.draw(st.integers(0, len(payload) - 1))
    assert reason_of(payload[:cut]) == "malformed"


@SETTINGS
@given(any_message, st.integers(-5, 1000))
def test_unknown_version_is_rejected(message, version):
    assume(version != message.VERSION)
    wire = wire_of(message)
    wire["v"] = version
    assert reason_of(wire) == "version"


@SETTINGS
@given(any_message)
def test_unknown_type_and_unexpected_type(message):
    wire = wire_of(message)
    wire["type"] = "NoSuchMessage"
    assert reason_of(wire) == "type"
    other = StreamEnd if not isinstance(message, StreamEnd) else LaserScan
    assert reason_of(message.encode(), other) == "type"


@SETTINGS
@given(any_message, st.data())
def test_missing_and_unknown_fields(message, data):
    wire = wire_of(message)
    name = data.draw(st.sampled_from(sorted(fields(message))))
    del wire[name]
    assert reason_of(wire) == "missing_field"
    wire = wire_of(message)
    wire["colour"] = 1
    assert reason_of(wire) == "unknown_field"


@SETTINGS
@given(any_message, st.data())
def test_field_of_the_wrong_kind(message, data):
    wire = wire_of(message)
    name = data.draw(st.sampled_from(sorted(fields(message))))
    wire[name] = [1.0, 2.0] if isinstance(wire[name], (str, int, float, bytes, dict)) else "text"
    assert reason_of(wire) == "field_type"


def array_fields(message):
    return sorted(name for name, value in fields(message).items() if isinstance(value, np.ndarray))


with_arrays = any_message.filter(array_fields)


@SETTINGS
@given(with_arrays, st.data())
def test_wrong_dtype(message, data):
    wire = wire_of(message)
    name = data.draw(st.sampled_from(array_fields(message)))
    wire[name]["dtype"] = {"<f4": "<f8", "<f8": ">f8", "<i8": "<i4", "|u1": "|i1"}[wire[name]["dtype"]]
    assert reason_of(wire) == "dtype"


@SETTINGS
@given(with_arrays, st.data())
def test_wrong_shape_and_size(message, data):
    name = data.draw(st.sampled_from(array_fields(message)))
    wire = wire_of(message)
    wire[name]["shape"] = wire[name]["shape"] + [1]
    assert reason_of(wire) == "shape"
    wire = wire_of(message)
    wire[name]["data"] = wire[name]["data"] + b"\x00"
    assert reason_of(wire) == "size"


def test_inconsistent_lengths_across_fields():
    wire = wire_of(PoseSamples(robot="r", seq=0, stamp=0.0, samples=np.zeros((4, 3)), weights=np.full(4, 0.25)))
    wire["weights"] = {"dtype": "<f8", "shape": [2], "data": np.full(2, 0.5).tobytes()}
    assert reason_of(wire) == "shape"


@SETTINGS
@given(any_message, st.data())
def test_nonfinite_values(message, data):
    wire = wire_of(message)
    finite_fields = [
        n
        for n, v in fields(message).items()
        if isinstance(v, float) or (isinstance(v, np.ndarray) and v.dtype.kind == "f" and v.size and n != "ranges")
    ]
    if not finite_fields:
        return
    name = data.draw(st.sampled_from(sorted(finite_fields)))
    bad = data.draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    if isinstance(wire[name], float):
        wire[name] = bad
    else:
        array = np.frombuffer(wire[name]["data"], wire[name]["dtype"]).copy()
        array[data.draw(st.integers(0, array.size - 1))] = bad
        wire[name]["data"] = array.tobytes()
    assert reason_of(wire) == "nonfinite"


def scan(**overrides):
    values = dict(
        robot="r",
        seq=0,
        stamp=0.0,
        angle_min=-1.0,
        angle_increment=0.5,
        range_min=0.1,
        range_max=5.0,
        sensor_offset=np.zeros(3),
        ranges=np.array([1.0, 2.0, 3.0], np.float32),
        no_return_range=5.0,
    )
    values.update(overrides)
    return LaserScan(**values)


def test_the_largest_seq_goes_through():
    assert decode_message(scan(seq=MAX_SEQ).encode(), LaserScan).seq == MAX_SEQ


def test_ranges_may_say_no_return_or_too_close():
    """NaN and +inf are no return; -inf a reading too close to measure (REP 117), which the mapper skips."""
    ranges = np.array([1.0, np.nan, np.inf, -np.inf], np.float32)
    decoded = decode_message(scan(ranges=ranges).encode(), LaserScan)
    np.testing.assert_array_equal(decoded.ranges, ranges)


@pytest.mark.parametrize(
    "overrides",
    [
        {"ranges": np.array([1.0, -0.5, 2.0], np.float32)},
        {"range_min": 6.0},
        {"range_min": -0.1},
        {"angle_increment": 0.0},
        {"robot": "a/b"},
        {"robot": "*"},
        {"robot": "map"},
        {"robot": ""},
        {"seq": -1},
        {"seq": MAX_SEQ + 1},  # not exact as a JSON number: /health's lag would lie to JavaScript clients
        {"angle_min": 1e30},  # every beam on one ray, once the angles are rounded
        {"angle_increment": -7.0},
        {"range_min": 2.0, "range_max": 2.0},  # range_min < range_max, strictly
        {"no_return_range": 5.5},  # a beam with no return clears at most up to range_max (5 m)
        {"no_return_range": -0.5},
        {"angle_increment": 0.0, "ranges": np.array([1.0, 2.0], np.float32)},  # two beams on one ray
        {"angle_increment": 0.5, "ranges": np.ones(15, np.float32)},  # 7 rad: the last beams repeat the first's
        {"angle_increment": -0.5, "ranges": np.ones(15, np.float32)},
    ],
)
def test_out_of_range_values(overrides):
    with pytest.raises(MessageError) as info:
        scan(**overrides).encode()
    assert info.value.reason == "range"


def test_a_peer_sending_a_no_return_range_past_range_max_is_refused_on_decode():
    """A peer's scan whose beams with no return would clear past its laser's range is checked as it is decoded; a
    version 1 scan (no no_return_range) is refused as a version this build does not read."""
    wire = wire_of(scan(no_return_range=5.0))
    wire["no_return_range"] = 5.0001
    assert reason_of(wire, LaserScan) == "range"
    wire = wire_of(scan())
    del wire["no_return_range"]
    wire["v"] = 1
    assert reason_of(wire, LaserScan) == "version"
    assert decode_message(msgpack.packb(wire_of(scan(no_return_range=0.0))), LaserScan).no_return_range == 0.0


def test_a_peer_sending_a_fan_past_a_turn_is_refused_on_decode():
    """What a peer sends is checked as it is decoded, not only by this side's encoder: 15 beams 0.5 rad apart."""
    wire = wire_of(scan(angle_increment=0.4, ranges=np.ones(15, np.float32)))  # 5.6 rad: valid as sent
    wire["angle_increment"] = 0.5
    assert reason_of(wire, LaserScan) == "range"


def test_a_fan_of_exactly_one_turn_goes_through():
    """361 beams a degree apart (first and last on one direction), as some 360 deg scanners report."""
    decoded = decode_message(scan(angle_increment=2 * np.pi / 360, ranges=np.ones(361, np.float32)).encode(), LaserScan)
    assert decoded.ranges.shape == (361,)


def test_odometry_with_two_poses_or_negative_dt_is_rejected():
    wire = wire_of(Odometry(robot="r", seq=1, stamp=0.1, pose=np.zeros((1, 3)), commands=np.array([[0.5, 0.1, 0.1]])))
    wire["pose"] = {"dtype": "<f8", "shape": [2, 3], "data": np.zeros((2, 3)).tobytes()}
    assert reason_of(wire) == "shape"
    wire = wire_of(Odometry(robot="r", seq=1, stamp=0.1, pose=np.zeros((1, 3)), commands=np.array([[0.5, 0.1, 0.1]])))
    wire["commands"]["data"] = np.array([0.5, 0.1, -0.1]).tobytes()
    assert reason_of(wire) == "range"


def test_scan_without_beams_is_rejected():
    with pytest.raises(MessageError) as info:
        scan(ranges=np.zeros(0, np.float32)).encode()
    assert info.value.reason == "shape"


@pytest.mark.parametrize(
    "weights, reason",
    [
        (np.array([0.5, 0.6]), "weights"),
        (np.array([1.5, -0.5]), "weights"),
        (np.array([0.0, 0.0]), "weights"),
        (np.array([0.5, 0.501]), "weights"),  # sums to 1.001: past the 1e-4 tolerance
    ],
)
def test_bad_weights(weights, reason):
    wire = wire_of(PoseSamples(robot="r", seq=0, stamp=0.0, samples=np.zeros((2, 3)), weights=np.full(2, 0.5)))
    wire["weights"]["data"] = weights.astype("<f8").tobytes()
    assert reason_of(wire) == reason


def test_weights_within_the_tolerance_of_one_are_taken():
    wire = wire_of(PoseSamples(robot="r", seq=0, stamp=0.0, samples=np.zeros((2, 3)), weights=np.full(2, 0.5)))
    wire["weights"]["data"] = np.array([0.5, 0.50001]).astype("<f8").tobytes()
    assert decode_message(msgpack.packb(wire, use_bin_type=True)).weights[1] == 0.50001


@pytest.mark.parametrize(
    "cov",
    [
        np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # not symmetric
        np.diag([1.0, -0.1, 1.0]),  # not positive semi-definite
        np.array([[1.0, 1e-6, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # asymmetric by 1e-6 (tolerance 2e-9)
        np.diag([1.0, -1e-6, 1.0]),  # eigenvalue -1e-6 (tolerance -2e-12)
    ],
)
def test_bad_covariance(cov):
    wire = wire_of(PoseGaussian(robot="r", seq=0, stamp=0.0, mean=np.zeros(3), cov=np.eye(3)))
    wire["cov"]["data"] = cov.astype("<f8").tobytes()
    assert reason_of(wire) == "covariance"


def test_poses_beyond_the_pose_limit_are_rejected():
    """A sample or mean 1e300 m out, or a covariance of 1e308, is finite but no pose: it would overflow the
    mapper's cell indices and the API's JSON. The limit itself still passes."""
    edge = np.array([[POSE_LIMIT, -POSE_LIMIT, 0.0]])
    assert decode_message(PoseSamples(robot="r", seq=0, stamp=0.0, samples=edge, weights=np.ones(1)).encode())
    for samples in (np.array([[1e300, 0.0, 0.0]]), np.array([[0.0, -2 * POSE_LIMIT, 0.0]])):
        with pytest.raises(MessageError) as info:
            PoseSamples(robot="r", seq=0, stamp=0.0, samples=samples, weights=np.ones(1)).encode()
        assert info.value.reason == "range" and "'samples'" in str(info.value)
    with pytest.raises(MessageError) as info:
        PoseGaussian(robot="r", seq=0, stamp=0.0, mean=np.array([0.0, 1e8, 0.0]), cov=np.eye(3)).encode()
    assert info.value.reason == "range" and "'mean'" in str(info.value)
    with pytest.raises(MessageError) as info:
        PoseGaussian(robot="r", seq=0, stamp=0.0, mean=np.zeros(3), cov=np.full((3, 3), 1e308)).encode()
    assert info.value.reason == "range" and "'cov'" in str(info.value)


def test_more_samples_than_a_message_may_carry_are_rejected():
    def samples(m):
        return PoseSamples(robot="r", seq=0, stamp=0.0, samples=np.zeros((m, 3)), weights=np.full(m, 1.0 / m))

    assert decode_message(samples(MAX_POSE_SAMPLES).encode()).samples.shape == (MAX_POSE_SAMPLES, 3)
    with pytest.raises(MessageError) as info:
        samples(MAX_POSE_SAMPLES + 1).encode()
    assert info.value.reason == "size"


def test_a_window_past_its_tile_is_refused():
    tile = TileUpdate.of_window(
        (np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), np.ones((2, 2), bool)),
        map="m",
        shard=0,
        z=0,
        tx=0,
        ty=0,
        tile_size=2,
        resolution=0.1,
        row0=0,
        col0=0,
        robot="r",
        seq=0,
        published=0.0,
    )
    wire = wire_of(tile)
    wire["row0"] = 1  # a 2x2 window at row 1 leaves a 2x2 tile
    assert reason_of(wire) == "range"


def test_error_message_is_one_sentence_naming_the_field():
    wire = wire_of(scan())
    wire["sensor_offset"]["shape"] = [4]
    with pytest.raises(MessageError) as info:
        decode_message(msgpack.packb(wire))
    text = str(info.value)
    assert "LaserScan" in text and "sensor_offset" in text and "\n" not in text


# ------------------------------------------------------------------------------------- JSON Schema


def test_committed_json_schemas_are_the_generated_ones():
    folder = ROOT / "docs" / "messages"
    rendered = render_schemas()
    assert sorted(p.name for p in folder.glob("*.json")) == sorted(rendered)
    for name, text in rendered.items():
        assert (folder / name).read_text() == text, f"docs/messages/{name} is stale: run python -m schemas.jsonschema"


@SETTINGS
@given(any_message)
def test_schema_describes_the_wire_keys_and_constants(message):
    schema = json.loads(render_schemas()[f"{message.TYPE}.json"])
    wire = wire_of(message)
    assert set(schema["required"]) == set(wire) == set(schema["properties"])
    assert schema["properties"]["type"]["const"] == wire["type"]
    assert schema["properties"]["v"]["const"] == wire["v"]
    for name, value in wire.items():
        if isinstance(value, dict) and set(value) == {"dtype", "shape", "data"}:
            prop = schema["properties"][name]["properties"]
            assert prop["dtype"]["const"] == value["dtype"]
            assert len(prop["shape"]["prefixItems"]) == len(value["shape"])


def tile(given=None, **overrides):
    """A TileUpdate of a 2 x 2 window of a 4-cell tile giving the cells ``given`` marks (default all)."""
    values = dict(
        map="m",
        shard=0,
        z=0,
        tx=0,
        ty=0,
        tile_size=4,
        resolution=0.1,
        row0=0,
        col0=0,
        robot="r",
        seq=0,
        published=0.0,
    )
    values.update(overrides)
    layers = (np.arange(4, dtype=np.float32).reshape(2, 2), np.zeros((2, 2), np.float32), np.ones((2, 2), bool))
    return TileUpdate.of_window(layers, given, **values)


def stats(**overrides):
    values = dict(
        map="m",
        shard=0,
        shards=2,
        tiles_owned=0,
        cells_updated=0,
        tile_updates=0,
        join_pending=0,
        uptime=0.0,
        fused={},
        discarded={},
        ended={},
        received={},
        resent={},
        rejected={},
        overflow={},
        refused={},
    )
    values.update(overrides)
    return ShardStats(**values)


@pytest.mark.parametrize(
    "message",
    [
        tile(resolution=0.0),  # exclusive minimum
        tile(col0=3),  # a 2-wide window from column 3 leaves a 4-wide tile
        tile(tile_size=3),  # tiles are a power of two cells wide
        tile(tile_size=2 * MAX_TILE_SIZE),  # a receiver makes a grid of the size an update names
        tile(tx=MAX_TILE_INDEX + 1),  # tile indices that stay exact as cells in float64
        tile(ty=-MAX_TILE_INDEX - 1),
        tile(resolution=CELL_SIZE_RANGE[1] * 2),  # cells of 1 mm to 1 km
        tile(resolution=CELL_SIZE_RANGE[0] / 2),
        stats(shards=MAX_SHARDS + 1),  # every shard's index is hashed with each tile
        stats(shard=2, shards=2),  # shard indices are 0 .. shards - 1
        stats(fused={"r": -1}),  # counts are >= 0
    ],
)
def test_tile_and_stats_boundary_values_are_out_of_range(message):
    with pytest.raises(MessageError) as info:
        message.encode()
    assert info.value.reason == "range"


def test_a_tile_window_may_end_exactly_at_the_tile_edge():
    assert decode_message(tile(row0=2, col0=2).encode()).col0 == 2


def test_a_tile_update_gives_the_marked_cells_in_row_major_order():
    given = np.array([[False, True], [True, True]])
    decoded = decode_message(tile(given, row0=1, col0=2).encode())
    assert decoded.given.tolist() == [0b1110]  # cells 1, 2, 3 of the window, least significant bit first
    assert decoded.given_mask().tolist() == given.tolist()
    assert decoded.logodds.tolist() == [1.0, 2.0, 3.0]  # the window's arange(4) at cells 1, 2, 3
    assert decoded.observed.tolist() == [0b111] and decoded.given_observed().tolist() == [True] * 3
    layers = (np.full((4, 4), -1, np.float32), np.full((4, 4), 7, np.float32), np.zeros((4, 4), bool))
    decoded.paste(*layers)
    expected = np.full((4, 4), -1, np.float32)
    expected[1, 3], expected[2, 2], expected[2, 3] = 1.0, 2.0, 3.0  # window cell (r, c) is tile cell (1 + r, 2 + c)
    assert layers[0].tolist() == expected.tolist()
    assert layers[1][1, 2] == 7 and layers[1][2, 3] == 0  # a cell not given keeps its value
    assert layers[2].sum() == 3
    assert not decoded.is_whole()
    with pytest.raises(ValueError):
        decoded.whole_layers()


def test_a_whole_tile_gives_its_layers():
    whole = decode_message(tile(tile_size=2).encode())
    assert whole.is_whole()
    assert whole.whole_layers()[0].tolist() == [[0.0, 1.0], [2.0, 3.0]]


@pytest.mark.parametrize(
    ("given", "reason"),
    [
        (b"", "shape"),  # a 2 x 2 window needs one byte of bits
        (b"\x0f\x00", "shape"),  # and no more
        (b"\x1f", "range"),  # bit 4 lies past the window's 4 cells
        (b"\x07", "range"),  # three cells marked: the fourth bit of observed lies past them
    ],
)
def test_a_tile_update_whose_given_bits_do_not_fit_is_refused(given, reason):
    wire = wire_of(tile())
    wire["given"]["data"] = given
    wire["given"]["shape"] = [len(given)]
    assert reason_of(wire) == reason


@pytest.mark.parametrize(
    ("observed", "reason"),
    [
        (b"", "shape"),  # four given cells need one byte of bits
        (b"\x0f\x00", "shape"),  # and no more
        (b"\x1f", "range"),  # bit 4 lies past the four given cells
    ],
)
@pytest.mark.parametrize("field", ["observed", "logodds_cells", "variance_cells"])
def test_a_tile_update_whose_bits_of_given_cells_do_not_fit_is_refused(observed, reason, field):
    wire = wire_of(tile())
    wire[field]["data"] = observed
    wire[field]["shape"] = [len(observed)]
    assert reason_of(wire) == reason


@pytest.mark.parametrize("field", ["logodds", "variance"])
def test_a_tile_update_with_more_values_than_its_cells_bits_is_refused(field):
    wire = wire_of(tile())
    wire[f"{field}_cells"]["data"] = b"\x07"  # three of the four given cells
    assert reason_of(wire) == "shape"


def test_a_tile_update_gives_each_layers_changed_values_only():
    """Cells 1, 2 and 3 of a 2 x 2 window at (1, 2) of a 4 x 4 tile given: the log-odds of cell 2 only, the variances
    of cells 1 and 3; pasted, the other values stay as they were (by hand)."""
    fields = dict(map="m", shard=0, z=0, tx=0, ty=0, tile_size=4, resolution=0.1, row0=1, col0=2, robot="r", seq=0)
    given = np.array([[False, True], [True, True]])
    update = TileUpdate.of_cells(
        given,
        np.array([True, False, True]),
        (np.array([False, True, False]), np.array([2.5], np.float32)),
        (np.array([True, False, True]), np.array([0.25, 0.75], np.float32)),
        published=0.0,
        **fields,
    )
    decoded = decode_message(update.encode())
    assert decoded.logodds_cells.tolist() == [0b010] and decoded.variance_cells.tolist() == [0b101]
    layers = (np.full((4, 4), -1, np.float32), np.full((4, 4), 7, np.float32), np.ones((4, 4), bool))
    decoded.paste(*layers)
    logodds, variance, observed = np.full((4, 4), -1.0), np.full((4, 4), 7.0), np.ones((4, 4), bool)
    logodds[2, 2] = 2.5  # given cell 2 is window cell (1, 0): tile cell (2, 2)
    variance[1, 3], variance[2, 3] = 0.25, 0.75  # given cells 1 and 3: window cells (0, 1) and (1, 1)
    observed[2, 2] = False
    assert layers[0].tolist() == logodds.tolist() and layers[1].tolist() == variance.tolist()
    assert layers[2].tolist() == observed.tolist()
    assert not decoded.is_whole()


@pytest.mark.parametrize(("field", "value"), [("seq", True), ("stamp", False), ("tile_updates", True)])
def test_booleans_are_not_numbers(field, value):
    wire = wire_of(stats() if field == "tile_updates" else scan())
    wire[field] = value
    assert reason_of(wire) == "field_type"


def test_array_data_that_is_text_is_a_field_type_error_not_a_crash():
    wire = wire_of(scan())
    wire["ranges"]["data"] = "abcdefghijkl"  # 12 characters: the byte count a (3,) <f4 array needs
    assert reason_of(wire) == "field_type"


def test_an_array_past_the_element_limit_is_refused_by_its_declared_shape():
    """The limit is checked on the declared shape, before the data is looked at."""
    wire = wire_of(scan())
    wire["ranges"]["shape"] = [MAX_ARRAY_ELEMENTS + 1]
    with pytest.raises(MessageError) as info:
        decode_message(msgpack.packb(wire, use_bin_type=True))
    assert info.value.reason == "size" and "more than the limit" in str(info.value)
