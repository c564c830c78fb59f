"""A peer answering as a robot's history (services.history): what it can make a mapper shard believe, with real
processes (a router and a shard) and Zenoh sessions played by the test: the real source and the peer."""

from __future__ import annotations

import logging
import threading
import time

import pytest
import zenoh

from peers import put
from services import keys
from services.ports import free_port
from services.process import RejectCounter
from services.zenoh_config import build_config
from test_hostile_peers import _pose, _scan
from test_pipeline import CLI, procs  # noqa: F401 - procs is a fixture


def _history_of(session: zenoh.Session, robot: str, held: dict[tuple[str, int], bytes], map_name: str = "m"):
    """A history queryable of ``robot`` on ``session`` answering from ``held`` ((stream, seq) -> payload), as its
    own process (services.history)."""
    from services import history

    who = history.Answerer(str(session.info.zid()), map_name, False)

    def answer(query: zenoh.Query) -> None:
        request = history.parse_request(query, robot, RejectCounter(logging.getLogger("history")))
        if request is None:
            return
        for (stream, seq), payload in sorted(held.items(), key=lambda item: item[0][1]):
            if stream in request.streams and request.wants(seq):
                history.reply(query, who, robot, stream, payload)

    return session.declare_queryable(keys.history_key(robot), answer)


@pytest.mark.parametrize("shard_map", ["m", "other"])
def test_a_forged_far_run_that_a_peers_own_history_vouches_for_is_not_believed(procs, shard_map):  # noqa: F811
    """A hostile-peer probe's finding: a peer declared a history of robot r's and published 32 scans and poses at
    seqs 100 000 and up; the shard asked the histories for seq 100 000 alone, only the peer's answered, and the jump
    was believed: 99 832 real scans given up, every later real one refused as old. The shard now asks for the far
    seq with the last one its stream has passed: the real history answers too, two answer for the stream, and
    neither is taken. The real stream is fused whole. Also for a shard of another map than the real source's (every
    shard fuses every robot): a re-probe found its vouching question took only its own map's answerers, so the peer,
    answering as that map, was alone."""
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
        shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", shard_map, "--connect", endpoint])
        shard.wait_for("up")
        reader = MapReader(real, shard_map)

        def publish(seqs) -> None:
            for seq in seqs:
                for stream, message in ((keys.SCAN, _scan(seq, "r")), (keys.POSE, _pose(seq, "r"))):
                    published[(stream, seq)] = message.encode()
                    put(real, keys.robot_key("r", stream), published[(stream, seq)])

        def fused(count: int) -> bool:
            return any(s.fused.get("r", 0) >= count for s in reader.stats(timeout=2.0).values())

        deadline = time.monotonic() + 60
        while not any(s.received.get("pg/probe/scan") for s in reader.stats(timeout=2.0).values()):
            # (the shard's subscription reaches the publisher through the router some time after it says "up": a
            # scan lost before then is no history's of its map in the "other" case, and would be given up)
            assert time.monotonic() < deadline, "the shard never received a scan"
            put(real, keys.robot_key("probe", keys.SCAN), _scan(0, "probe").encode())
            time.sleep(0.2)
        publish(range(60))
        deadline = time.monotonic() + 60
        while not fused(60):
            assert time.monotonic() < deadline, "the shard did not fuse the first 60 real scans"
            time.sleep(0.1)
        kept.append(
            _history_of(peer, "r", forged, shard_map)
        )  # (declared once the shard has caught up: see docs/security.md)
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


def _node_stats(steps_done: int) -> bytes:
    from schemas.messages import NodeStats

    return NodeStats(
        robot="r",
        algorithm="ekf",
        poses_published=steps_done,
        steps_done=steps_done,
        uptime=1.0,
        received={},
        rejected={},
        out_of_order={},
        noise_scale=1.0,
        consistency={},
        health={},
    ).encode()


def test_a_peer_answering_as_the_slam_node_neither_stalls_nor_speeds_the_source(procs):  # noqa: F811
    """A re-probe: a peer answering pg/<robot>/slam/stats with steps_done = 0 (its queryable declared complete, so
    the router gave it the source's question) stalled `posegrid run` at 32 of 400 scans for good. The source asks
    every answerer: one (the node) is taken; two make it say so once and wait for the shards alone."""
    from services.nodes.source import Source, SourceOptions
    from services.streams import Stream

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    config = build_config("client", connect=[endpoint])
    key = keys.slam_stats_key("r")
    with zenoh.open(config) as node, zenoh.open(config) as peer, zenoh.open(config) as own:
        source = Source(own, Stream("r", [], None, True), SourceOptions(wait_slam=True))
        source._steps_published = 9
        kept = [node.declare_queryable(key, lambda query: query.reply(key, _node_stats(7)))]
        deadline = time.monotonic() + 20
        while source._slam_done() != 7:
            assert time.monotonic() < deadline, "the node's stats never came"
            time.sleep(0.1)
        kept.append(peer.declare_queryable(key, lambda query: query.reply(key, _node_stats(0)), complete=True))
        deadline = time.monotonic() + 20
        while source._slam_done() != 9:  # (as if done: the steps published)
            assert time.monotonic() < deadline, "the peer's answer was not noticed"
            time.sleep(0.1)
        assert any("2 processes answer as the SLAM node of robot 'r'" in said for said in source._warn_once.said)
        del kept


def test_oversized_replies_are_dropped_as_they_come(procs):  # noqa: F811
    """A re-probe: a peer answering a shard's history question with twenty replies of 100 MB took the shard to 4.3 GB,
    and thirty to the API's tile query took the API to 3.5 GB: every reply was kept until the question ended. A
    history reply past services.history.MAX_REPLY_BYTES, or a tile reply past the API's, is dropped and said."""
    from services import history
    from services.api.mappers import MAX_REPLY_BYTES, MapperLink
    from services.api.registry import MapRegistry

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    config = build_config("client", connect=[endpoint])
    with zenoh.open(config) as peer, zenoh.open(config) as asker:
        who = history.Answerer(str(peer.info.zid()), "m", False)
        big, small = b"x" * (history.MAX_REPLY_BYTES + 1), b"scan 3"

        def answer(query: zenoh.Query) -> None:
            history.reply(query, who, "r", keys.SCAN, big)
            history.reply(query, who, "r", keys.SCAN, small)

        def tiles(query: zenoh.Query) -> None:
            query.reply(keys.tile_key("m", 0, 0, 0), b"y" * (MAX_REPLY_BYTES + 1))

        kept = [  # noqa: F841 - (a queryable no one holds is undeclared)
            peer.declare_queryable(keys.history_key("r"), answer),
            peer.declare_queryable(keys.tile_key("m", 0, "*", "*"), tiles),
        ]
        deadline = time.monotonic() + 20
        while True:
            messages, problems = history.ask(asker, "r", {}, timeout=10)
            if messages:
                break
            assert time.monotonic() < deadline, "the peer's history never answered"
            time.sleep(0.1)
        assert messages == [("r", keys.SCAN, small)]
        too_big = f"a reply of {history.MAX_REPLY_BYTES + 1} bytes on pg/r/history/scan, more than "
        assert problems == [too_big + f"{history.MAX_REPLY_BYTES}; not taken"]
        link = MapperLink(asker, MapRegistry(), None, None)  # type: ignore[arg-type]  # (queries only)
        assert link._query(keys.tile_key("m", 0, "*", "*"), timeout=10) == []
        assert link.rejects.kinds() == {"size": 1}


def test_a_source_stays_until_the_shards_that_keep_a_store_have_committed_its_scans():
    """A re-probe: a state-directory shard killed as the source left lost the ~85 scans fused since its last commit
    (every 2 s or 256 scans): the source had left when they were fused, taking its history with it. A shard with
    `persist` on must also hold them in its store; one without a store, fused is enough."""
    from schemas.messages import StreamEnd
    from services.nodes.source import FAILING_GRACE, _accounted
    from test_api_status import shard

    end = StreamEnd(robot="r", scans=300)
    fused = dict(fused={"r": 290}, discarded={"r": 10}, ended={"r": 300})
    assert _accounted([shard(0, **fused)], end)  # (persist off)
    assert not _accounted([shard(0, persist="ok", committed={"r": 215}, **fused)], end)
    # commits failing for a few seconds may be a passing fault: waited for; for more than FAILING_GRACE: not
    assert not _accounted([shard(0, persist="failing", committed={"r": 215}, commit_age=3.0, **fused)], end)
    stuck = shard(0, persist="failing", committed={"r": 215}, commit_age=FAILING_GRACE + 1, uptime=60.0, **fused)
    assert _accounted([stuck], end)
    resumed = shard(0, persist="failing", commit_age=60.0, uptime=2.0, **fused)  # (its last commit: a process before)
    assert not _accounted([resumed], end)
    for uptime, waited in ((FAILING_GRACE + 1, False), (FAILING_GRACE - 1, True)):  # (no commit yet: since it started)
        stuck = shard(0, persist="failing", commit_age=-1.0, uptime=uptime, **fused)
        assert _accounted([stuck], end) is not waited
    assert _accounted([shard(0, persist="ok", committed={"r": 300}, **fused), shard(1, **fused)], end)
    assert not _accounted([shard(0, persist="ok", committed={"r": 300}, fused={"r": 290}, ended={"r": 300})], end)


def test_the_end_of_a_replay_is_waited_for_while_the_pipeline_makes_progress(procs, monkeypatch):  # noqa: F811
    """An overload probe: a SLAM node working through a backlog with the source's history (178 steps taken from it)
    was still at step 1 794 of 3 000 when the source gave up waiting for the end, 60 s after it; restarted, the source
    answered no history while it simulated, and the node skipped 859 steps. The wait for the end now gives up only
    after WAIT_TIMEOUT without progress (the shards' counts, the node's steps), as the wait for the window did."""
    from services.nodes import source as source_module
    from services.nodes.source import Source, SourceOptions, SourceStalled
    from services.streams import Stream

    monkeypatch.setattr(source_module, "WAIT_TIMEOUT", 0.5)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    with zenoh.open(build_config("client", connect=[endpoint])) as own:
        source = Source(own, Stream("r", [], None, True), SourceOptions(wait_mappers=1))
        began = time.monotonic()
        done = lambda: time.monotonic() - began > 2.0  # noqa: E731 - the pipeline done after 2 s
        progress = lambda: int((time.monotonic() - began) / 0.2)  # noqa: E731 - a step every 0.2 s
        assert source._wait_for("the end", done, threading.Event(), progress)  # (2 s, four WAIT_TIMEOUTs)
        began = time.monotonic()
        with pytest.raises(SourceStalled, match="gave up after 0 s without progress waiting for the end"):
            source._wait_for("the end", done, threading.Event(), lambda: 0)  # (no progress)
        source._end_counts = ((0, 5, 0, 5),)
        assert source._end_progress() == (((0, 5, 0, 5),), 0)  # (no SLAM node waited for: its steps stay 0)


def test_a_question_takes_at_most_its_bytes_of_replies(procs):  # noqa: F811
    """A re-probe: the API's fill of a new robot's trajectory took every pose a peer's history sent, 6 000 of 10 000
    samples each, 3.9 GB. A question given max_bytes keeps the replies up to that many bytes in all, and says so."""
    from services import history

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    config = build_config("client", connect=[endpoint])
    with zenoh.open(config) as answerer, zenoh.open(config) as asker:
        who = history.Answerer(str(answerer.info.zid()), "m", False)
        answerer.declare_queryable(
            keys.history_key("r"),
            lambda query: [history.reply(query, who, "r", keys.POSE, bytes([i]) * 1000) for i in range(10)],
        )
        deadline = time.monotonic() + 20
        while not history.ask(asker, "r", {}, 5.0)[0]:
            assert time.monotonic() < deadline, "the answerer never answered"
            time.sleep(0.1)
        messages, problems = history.ask(asker, "r", {}, 5.0, max_bytes=3500)
    assert [payload for _, _, payload in messages] == [bytes([i]) * 1000 for i in range(3)]
    assert problems == ["replies past 3500 bytes in all; not taken"]


def test_a_source_waiting_for_n_shards_counts_any_n_of_them_by_their_indices(procs, monkeypatch):  # noqa: F811
    """A re-probe of the look-alike tokens' fix: `source --wait-mappers 1` with shard 1 of 2 up waited for ever, as it
    counted shards 0 .. N-1 only, though it knows how many shards to wait for, not their count. It counts any N
    distinct shard indices; a look-alike token (alive/00) still counts for none."""
    from services.nodes import source as source_module
    from services.nodes.source import Source, SourceOptions, SourceStalled
    from services.streams import Stream

    monkeypatch.setattr(source_module, "WAIT_TIMEOUT", 3.0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    config = build_config("client", connect=[endpoint])
    with zenoh.open(config) as peer, zenoh.open(config) as own:
        source = Source(own, Stream("r", [], None, True), SourceOptions(wait_mappers=1, map_name="m"))
        fake = peer.liveliness().declare_token(keys.shard_alive_key("m", "00"))
        with pytest.raises(SourceStalled):
            source._wait_for_subscribers(threading.Event())
        real = peer.liveliness().declare_token(keys.shard_alive_key("m", 1))
        assert source._wait_for_subscribers(threading.Event())
        fake.undeclare()
        real.undeclare()
