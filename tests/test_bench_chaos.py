"""The hostile mix of bench/chaos.py: what it may and may not carry, and what a shard makes of it (in process, the
shard's own decoding and join, no network)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import chaos
from bench.scenarios import honest_posed_scans, office_run
from mapping.sensor_model import SensorModel
from schemas.messages import POSE_TYPES, LaserScan, MessageError, StreamEnd, decode_message
from services import keys
from services.process import RejectCounter, get_logger
from services.state.join import CONFIRM_RUN, DEFAULT_SEQ_WINDOW
from services.state.shard import MapShard, ShardConfig
from services.streams import posed_stream

SCANS = 12


@pytest.fixture(scope="module")
def stream():
    posed = honest_posed_scans(office_run(seed=0, steps=SCANS), seed=1, particles=10)
    return posed_stream(posed, chaos.ROBOT)


@pytest.fixture(scope="module")
def mix(stream):
    return chaos.hostile_mix(stream, chaos.MAP)


def _decoded(payload: bytes):
    try:
        return decode_message(payload, LaserScan, *POSE_TYPES, StreamEnd)
    except MessageError:
        return None


def _decoding_refusals(mix, reason: str) -> int:
    """How many payloads of ``mix`` on a robot's scan, pose or end key fail to decode as that key's messages for
    ``reason``."""
    expected = {keys.SCAN: (LaserScan,), keys.POSE: POSE_TYPES, keys.END: (StreamEnd,)}
    count = 0
    for key, payload in mix:
        parts = key.split("/")
        if len(parts) != 3 or parts[0] != "pg" or parts[2] not in expected or "*" in key or "$" in key:
            continue
        try:
            decode_message(payload, *expected[parts[2]])
        except MessageError as exc:
            count += exc.reason == reason
    return count


def _longest_run(seqs: set[int]) -> int:
    return max(
        (len([s for s in range(seq, seq + CONFIRM_RUN) if s in seqs]) for seq in seqs if seq - 1 not in seqs), default=0
    )


def test_the_mix_is_deterministic_and_forges_the_real_robot_only_beyond_its_seq_window(mix, stream):
    assert mix == chaos.hostile_mix(stream, chaos.MAP)
    assert 4_500 <= len(mix) <= 5_000
    seqs: dict[type, set[int]] = {LaserScan: set(), POSE_TYPES[0]: set(), POSE_TYPES[1]: set()}
    for _, payload in mix:
        message = _decoded(payload)
        if message is None or message.robot != chaos.ROBOT:
            continue
        if isinstance(message, StreamEnd):
            assert message.scans - 1 > SCANS + DEFAULT_SEQ_WINDOW
        else:
            assert message.seq > SCANS + DEFAULT_SEQ_WINDOW
            seqs[type(message)].add(message.seq)
    assert len(seqs[LaserScan]) == chaos.FORGED  # the forged far scans are there, in runs the join checks against
    for found in (f for f in seqs.values() if f):  # the histories (which lack them) before it believes a jump
        assert _longest_run(found) >= CONFIRM_RUN


def test_expected_arrivals_counts_one_delivery_per_shard_subscriber_a_key_intersects():
    mix = [
        ("pg/**", b""),
        ("**", b""),
        ("pg/*/scan", b""),
        ("pg/bench/sc$*", b""),
        ("pg/bench/odom", b""),
        ("pg/bench/history/scan", b""),
        ("pg/map/chaos/tile/0/0/0", b""),
        ("pg/r1/end", b""),
    ]
    assert chaos.expected_arrivals(mix) == 3 + 3 + 1 + 1 + 0 + 0 + 0 + 1


def _replay(stream, mix) -> MapShard:
    """A one-shard map of ``stream`` with ``mix`` handed to the shard after the first scan (keys a shard does not
    subscribe to left out, as the network would)."""
    published = {
        (keys.STREAM_OF[type(message)], message.seq): message.encode()
        for step in stream.steps
        for message in step.messages
        if hasattr(message, "seq")
    }

    def history(robot: str, what: str, first: int, last: int, seqs=None) -> list[bytes]:
        """What the source's history answers: the real stream's messages (a forged run is not among them)."""
        if robot != chaos.ROBOT or (seqs is None and last - first > 10_000):
            return []
        return [published[(what, seq)] for seq in seqs or range(first, last + 1) if (what, seq) in published]

    shard = MapShard(
        ShardConfig(chaos.MAP, 0, 1, SensorModel()), RejectCounter(get_logger("test-chaos")), history=history
    )
    arrivals = [(key, payload) for key, payload in mix if chaos.expected_arrivals([(key, payload)])]
    for seq, step in enumerate(stream.steps):
        for message in step.messages:
            shard.handle(keys.robot_key(chaos.ROBOT, keys.STREAM_OF[type(message)]), message.encode())
        if seq == 0:
            for key, payload in arrivals:
                shard.handle(key, payload)
    return shard


def test_a_shard_fed_the_mix_refuses_each_part_by_its_kind_and_maps_exactly_what_it_maps_without(stream, mix):
    clean, hostile = _replay(stream, []), _replay(stream, mix)
    assert hostile.fused[chaos.ROBOT] == clean.fused[chaos.ROBOT] == SCANS
    assert hostile.discarded[chaos.ROBOT] == 0
    a, b = clean.grid.rasterize(), hostile.grid.rasterize()
    assert chaos.identical(a, b)
    refused = hostile.rejects.kinds()
    assert refused["ahead"] == 2 * chaos.FORGED + chaos.FORGED // 2  # far scans and poses, forged ends
    assert refused["bound"] == refused["extent"] == refused["work"] == 1
    # the oversize scans, and the overwritten templates whose arrays no longer fit their shapes (the larger payloads
    # fail to decode here: no intake check)
    assert refused["size"] == 10 + _decoding_refusals(mix, "size")
    assert refused["robots"] == chaos.STRAY_ROBOTS - (chaos.LIMITS.max_robots - 4)  # 4: bench and the 3 probes
    assert refused["key"] > 0 and refused["malformed"] > 0 and refused["robot"] > 0 and refused["type"] > 0
    assert not np.array_equal(a["logodds"], np.zeros_like(a["logodds"]))
