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
    monkeypatch.setattr(mapper_module, "HISTORY_TIMEOUT", 0.5)  # s: the wait each question takes when unanswered
    kept: list[zenoh.Query] = []  # (held, never answered: the query waits for them until its timeout)
    silent = zenoh.open(build_config("client", connect=[router]))
    session = zenoh.open(build_config("client", connect=[router]))
    try:
        queryable = silent.declare_queryable("pg/*/history/**", kept.append)
        time.sleep(0.5)  # (the router hands the queryable to the shard's session)
        shard = Mapper(ShardConfig("m", 0, 1, SensorModel()), session, threading.Event())
        tries = len(history.question_timeouts(0.5))  # (0.5, 1 and 2 s: a slow history is given more time)
        with shard.lock:  # (as the main thread asks: from inside the shard's handling of a message)
            assert shard._history("q0", "scan", 1, 1) == [] and len(kept) == tries  # asked, and waited for in vain
            for seq in range(3, 40, 2):  # the stranger's later gaps, and its poses'
                assert shard._history("q0", "scan", seq, seq) == [] and shard._history("q0", "pose", seq, seq) == []
            assert len(kept) == tries  # not asked again: one question's waits, not 39
            counted = shard.rejects.kinds()
            assert counted.get("history", 0) >= 38, counted
            assert shard._history("r1", "scan", 5, 5) == [] and len(kept) == 2 * tries  # another robot's are asked
        queryable.undeclare()
    finally:
        session.close()
        silent.close()
