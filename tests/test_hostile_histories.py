"""A peer answering as a robot's history (services.history): what it can make a mapper shard believe, with real
processes (a router and a shard) and Zenoh sessions played by the test: the real source and the peer."""

from __future__ import annotations

import time

import zenoh

from peers import put
from services import keys
from services.nodes.launcher import free_port
from services.zenoh_config import build_config
from test_hostile_peers import _pose, _scan
from test_pipeline import CLI, procs  # noqa: F401 - procs is a fixture


def _history_of(session: zenoh.Session, robot: str, held: dict[tuple[str, int], bytes]):
    """A history queryable of ``robot`` on ``session`` answering from ``held`` ((stream, seq) -> payload), as its
    own process (services.history)."""
    from services import history

    who = history.Answerer(str(session.info.zid()), "m", False)

    def answer(query: zenoh.Query) -> None:
        request = history.parse_request(query, robot)
        if request is None:
            return
        for (stream, seq), payload in sorted(held.items(), key=lambda item: item[0][1]):
            if stream in request.streams and request.wants(seq):
                history.reply(query, who, robot, stream, payload)

    return session.declare_queryable(keys.history_key(robot), answer)


def test_a_forged_far_run_that_a_peers_own_history_vouches_for_is_not_believed(procs):  # noqa: F811
    """A hostile-peer probe's finding: a peer declared a history of robot r's and published 32 scans and poses at
    seqs 100 000 and up; the shard asked the histories for seq 100 000 alone, only the peer's answered, and the jump
    was believed: 99 832 real scans given up, every later real one refused as old. The shard now asks for the far
    seq with the last one its stream has passed: the real history answers too, two answer for the stream, and
    neither is taken. The real stream is fused whole."""
    from services.map_client import MapReader

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    config = build_config("client", connect=[endpoint])
    with zenoh.open(config) as real, zenoh.open(config) as peer:
        published: dict[tuple[str, int], bytes] = {}
        forged = {
            (stream, seq): make(seq).encode()
            for seq in range(100_000, 100_032)
            for stream, make in (
                (keys.SCAN, lambda q: _scan(q, "r")),
                (keys.POSE, lambda q: _pose(q, "r", xy=(40.0, 40.0))),
            )
        }
        kept = [_history_of(real, "r", published)]  # (a queryable no one holds is undeclared)
        shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint])
        shard.wait_for("up")
        reader = MapReader(real, "m")

        def publish(seqs) -> None:
            for seq in seqs:
                for stream, message in ((keys.SCAN, _scan(seq, "r")), (keys.POSE, _pose(seq, "r"))):
                    published[(stream, seq)] = message.encode()
                    put(real, keys.robot_key("r", stream), published[(stream, seq)])

        def fused(count: int) -> bool:
            return any(s.fused.get("r", 0) >= count for s in reader.stats(timeout=2.0).values())

        publish(range(60))
        deadline = time.monotonic() + 60
        while not fused(60):
            assert time.monotonic() < deadline, "the shard did not fuse the first 60 real scans"
            time.sleep(0.1)
        kept.append(_history_of(peer, "r", forged))  # (declared once the shard has caught up: see docs/security.md)
        time.sleep(0.5)
        for (stream, _seq), payload in sorted(forged.items(), key=lambda item: item[0][1]):
            put(peer, keys.robot_key("r", stream), payload)
        time.sleep(1.0)
        publish(range(60, 120))
        deadline = time.monotonic() + 60
        while not fused(120):
            assert time.monotonic() < deadline, f"the real scans stopped at {reader.stats(timeout=2.0)}"
            time.sleep(0.1)
        (stats,) = reader.stats(timeout=2.0).values()
        assert stats.fused == {"r": 120} and stats.discarded.get("r", 0) == 0
        assert stats.refused.get("ahead", 0) >= 2 * 32
