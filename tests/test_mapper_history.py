"""A mapper shard's questions to the histories against a peer that declares one and never answers (a probe's): each
question waits on the shard's main thread, so every robot's fusion stood still for the whole timeout per gap of a
stranger robot's stream, one gap every two scans. After one question no one answered, the robot's histories are
left alone for HISTORY_QUIET s, and the gaps they would have filled are counted."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from mapping.sensor_model import SensorModel
from services import history
from services.nodes import mapper as mapper_module
from services.nodes.mapper import Mapper
from services.ports import free_port
from services.state.shard import ShardConfig
from services.zenoh_config import build_config
from test_pipeline import CLI, procs  # noqa: F401 - procs is a fixture


@pytest.fixture
def router(procs):  # noqa: F811
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    return endpoint


def test_a_history_that_never_answers_is_asked_once_per_quiet_period(router, monkeypatch):
    """One question no history answers waits its timeout once (no more time: no history was answering); the robot's
    later gaps are not asked for. A re-probe: a peer whose silent histories stood under robot name after robot name
    (one gap each) held every robot's fusion for good, 35 s a name. While the questions no history answered have held
    the shard HISTORY_TIMEOUT s in the last HISTORY_QUIET s, robots whose histories never answered this shard are not
    asked at all, and the others with HISTORY_SHORT_TIMEOUT; once the window has passed, as before."""
    monkeypatch.setattr(mapper_module, "HISTORY_TIMEOUT", 0.5)  # s: the wait each question takes when unanswered
    monkeypatch.setattr(mapper_module, "HISTORY_SHORT_TIMEOUT", 0.2)
    monkeypatch.setattr(mapper_module, "HISTORY_QUIET", 3.0)
    kept: list[zenoh.Query] = []  # (held, never answered: the query waits for them until its timeout)
    silent = zenoh.open(build_config("client", connect=[router]))
    session = zenoh.open(build_config("client", connect=[router]))
    try:
        queryable = silent.declare_queryable("pg/*/history/**", kept.append)
        time.sleep(0.5)  # (the router hands the queryable to the shard's session)
        shard = Mapper(ShardConfig("m", 0, 1, SensorModel()), session, threading.Event())
        shard._remember_answered(["known"])  # (its histories answered this shard before)
        with shard.lock:  # (as the main thread asks: from inside the shard's handling of a message)
            assert shard._history("q0", "scan", 1, 1) == [] and len(kept) == 1  # asked once, and waited for in vain
            for seq in range(3, 40, 2):  # the stranger's later gaps, and its poses'
                assert shard._history("q0", "scan", seq, seq) == [] and shard._history("q0", "pose", seq, seq) == []
            assert len(kept) == 1  # not asked again: one question's wait, not 39
            counted = shard.rejects.kinds()
            assert counted.get("history", 0) >= 38, counted
            started = time.monotonic()
            assert shard._history("q1", "scan", 5, 5) == [] and len(kept) == 1  # another stranger: not asked
            assert shard._history("known", "scan", 5, 5) == [] and len(kept) == 2  # asked, with the short timeout
            assert time.monotonic() - started < 0.45
            time.sleep(3.0)  # (the window has passed)
            assert shard._history("q1", "scan", 7, 7) == [] and len(kept) == 3  # asked again
        queryable.undeclare()
    finally:
        session.close()
        silent.close()


def test_a_history_that_answers_once_and_stalls_holds_the_shard_once(router, monkeypatch):
    """A re-probe: a peer's history that sent one reply at once (or late, inside the cut-off window, so that it was
    asked again with more time) and never finished, under a new robot name every few seconds, still held every
    robot's fusion for good: a reply made the robot count as answered, so the wait went into no budget. Any question
    that runs its time out now counts, its robot is left alone, and a robot whose histories never answered in time
    gets no more time."""
    monkeypatch.setattr(mapper_module, "HISTORY_TIMEOUT", 0.5)
    monkeypatch.setattr(mapper_module, "HISTORY_QUIET", 30.0)
    kept: list[zenoh.Query] = []
    peer = zenoh.open(build_config("client", connect=[router]))
    session = zenoh.open(build_config("client", connect=[router]))
    who = history.Answerer(str(peer.info.zid()), "m", False)

    def one_reply(query) -> None:  # one reply, then the query held open: its timeout ends it
        history.reply(query, who, str(query.key_expr).split("/")[1], "scan", b"junk")
        kept.append(query)

    try:
        queryable = peer.declare_queryable("pg/*/history/**", one_reply)
        time.sleep(0.5)
        shard = Mapper(ShardConfig("m", 0, 1, SensorModel()), session, threading.Event())
        with shard.lock:
            started = time.monotonic()
            shard._history("e0", "scan", 1, 1)  # (the junk reply is refused later, by the shard's checks)
            assert len(kept) == 1 and time.monotonic() - started < 1.4  # one try: e0 never answered in time
            for robot in ("e0", "e1", "e2", "e3"):  # e0 left alone; the others never answered: not asked
                assert shard._history(robot, "scan", 3, 3) == []
            assert len(kept) == 1 and time.monotonic() - started < 1.4, len(kept)
        queryable.undeclare()
    finally:
        session.close()
        peer.close()


def test_robots_whose_histories_answered_once_cannot_hold_the_shard_either(router, monkeypatch):
    """A re-probe: 40 robot names whose made-up histories answered a gap each at once, in full, then stalled one
    after another held the real robot's fusion for good (2 scans in 75 s): while the budget was spent, robots that
    had answered were still asked, 1 s each. A robot whose question runs out counts as answered no more, and past
    twice HISTORY_TIMEOUT in the window no question is asked at all."""
    monkeypatch.setattr(mapper_module, "HISTORY_TIMEOUT", 0.5)
    monkeypatch.setattr(mapper_module, "HISTORY_SHORT_TIMEOUT", 0.2)
    monkeypatch.setattr(mapper_module, "HISTORY_QUIET", 30.0)
    kept: list[zenoh.Query] = []
    peer = zenoh.open(build_config("client", connect=[router]))
    session = zenoh.open(build_config("client", connect=[router]))
    try:
        queryable = peer.declare_queryable("pg/*/history/**", kept.append)
        time.sleep(0.5)
        shard = Mapper(ShardConfig("m", 0, 1, SensorModel()), session, threading.Event())
        names = [f"e{i}" for i in range(20)]
        shard._remember_answered(names)  # (each answered in time once)
        with shard.lock:
            started = time.monotonic()
            for name in names:
                assert shard._history(name, "scan", 1, 1) == []
            held = time.monotonic() - started
        assert held < 2 * 0.5 + 0.5 + 0.6, held  # (the cap, the question that passed it, a busy machine's slack)
        assert len(kept) <= 5, len(kept)  # 0.5 s, then 0.2 s each up to 1 s in all: 4 questions, 16 not asked
        assert not shard._answered & set(names[: len(kept)])
        queryable.undeclare()
    finally:
        session.close()
        peer.close()
