"""History-query parsing (services.history) at its boundaries; the pipeline tests query history through real
Zenoh sessions. parse_request only reads a query's parameters, selector and key expression and answers errors
with reply_err, so a stand-in query object drives it here."""

from __future__ import annotations

import logging

import zenoh

from services.history import HistoryRequest, parse_request
from services.process import RejectCounter


class FakeQuery:
    def __init__(self, key: str, parameters: dict[str, str]):
        self.key_expr = zenoh.KeyExpr(key)
        self.parameters = parameters
        self.selector = f"{key}?{parameters}"
        self.errors: list[bytes] = []

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(payload)


def _rejects() -> RejectCounter:
    return RejectCounter(logging.getLogger("history-test"))


def test_wants_is_first_inclusive_stop_exclusive():
    request = HistoryRequest(frozenset({"scan"}), 2, 5)
    assert [seq for seq in range(8) if request.wants(seq)] == [2, 3, 4]
    assert [seq for seq in range(4) if HistoryRequest(frozenset(), 1, None).wants(seq)] == [1, 2, 3]


def test_defaults_are_every_stream_from_seq_0_without_end():
    request = parse_request(FakeQuery("pg/r1/history/**", {}), "r1", _rejects())
    assert request == HistoryRequest(frozenset({"prior", "odom", "landmarks", "scan", "pose"}), 0, None)


def test_streams_are_narrowed_to_the_key_expression():
    query = FakeQuery("pg/r1/history/scan", {"streams": "scan,pose", "from": "3", "to": "9"})
    assert parse_request(query, "r1", _rejects()) == HistoryRequest(frozenset({"scan"}), 3, 9)
    assert query.errors == []


def test_seqs_beyond_18_digits_are_refused_with_a_reason():
    query = FakeQuery("pg/r1/history/**", {"from": "1" + "0" * 18})  # 10^18: 19 digits
    assert parse_request(query, "r1", _rejects()) is None
    assert len(query.errors) == 1 and b"'from' and 'to' must be seqs" in query.errors[0]
    query = FakeQuery("pg/r1/history/**", {"to": "-1"})
    assert parse_request(query, "r1", _rejects()) is None and len(query.errors) == 1


def test_unknown_streams_are_refused_with_their_names():
    query = FakeQuery("pg/r1/history/**", {"streams": "scan,x"})
    assert parse_request(query, "r1", _rejects()) is None
    assert len(query.errors) == 1 and b"unknown stream(s) ['x']" in query.errors[0]


def test_each_refused_query_is_counted_under_the_robots_history_key_and_logged_once():
    """A probe's finding: a history query with bad parameters got its error reply, but nothing was counted or logged
    by the process it asked."""
    rejects, records = _rejects(), []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())
    logging.getLogger("history-test").addHandler(handler)
    try:
        for parameters in ({"from": "abc"}, {"streams": "foo"}, {"seqs": ",".join(["1"] * 65)}):
            assert parse_request(FakeQuery("pg/r1/history/**", parameters), "r1", rejects) is None
        assert parse_request(FakeQuery("pg/r1/history/**", {"from": "2"}), "r1", rejects) is not None
    finally:
        logging.getLogger("history-test").removeHandler(handler)
    assert rejects.snapshot() == {"pg/r1/history/**": 3} and rejects.kinds() == {"query": 3}
    assert len(records) == 1 and "'from' and 'to' must be seqs" in records[0], records
