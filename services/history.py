"""Queries on pg/<robot>/history/**: what a process has published of a robot's streams, for whoever missed it
(docs/keys.md, "The histories"). The source answers with its steps, the SLAM node with the poses it published.

A query names ``streams`` (comma-separated key chunks, default every one the answering process knows), ``from``
(the first seq, default 0) and ``to`` (the seq after the last, default everything published); each message
comes back as one reply on pg/<robot>/history/<its stream>, in the order it was published, so a query must ask
for no consolidation.
"""
from __future__ import annotations

from dataclasses import dataclass

import zenoh

from services import keys


@dataclass(frozen=True)
class HistoryRequest:
    """What a history query asks for: streams (key chunks), seqs first .. stop - 1 (stop None: no end)."""

    streams: frozenset[str]
    first: int
    stop: int | None

    def wants(self, seq: int) -> bool:
        return self.first <= seq and (self.stop is None or seq < self.stop)


def parse_request(query: zenoh.Query, known: set[str]) -> HistoryRequest | None:
    """The request of ``query``; None after answering it with an error reply that says what was wrong."""
    asked = query.parameters.get("streams")
    streams = set(known) if asked is None else set(asked.split(","))
    first, stop = query.parameters.get("from", "0"), query.parameters.get("to")
    problem = (f"unknown stream(s) {sorted(streams - known)}; known: {sorted(known)}" if streams - known else
               None if first.isdigit() and (stop is None or stop.isdigit()) else
               f"'from' and 'to' must be seqs >= 0, got {first!r} and {stop!r}")
    if problem:
        query.reply_err(f"history query {query.selector}: {problem}".encode())
        return None
    return HistoryRequest(frozenset(streams), int(first), None if stop is None else int(stop))


def reply(query: zenoh.Query, robot: str, stream: str, payload: bytes) -> None:
    """One message of the history, on pg/<robot>/history/<stream>."""
    query.reply(keys.history_key(robot, stream), payload, congestion_control=zenoh.CongestionControl.BLOCK)


def ask(session: zenoh.Session, robot: str, parameters: dict[str, str], timeout: float) \
        -> tuple[list[tuple[str, bytes]], list[str]]:
    """Ask every history of ``robot``: ((stream, payload) of each message in the order sent, error replies)."""
    messages, errors = [], []
    for answer in session.get(zenoh.Selector(keys.history_key(robot), parameters), timeout=timeout,
                              consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)):
        if answer.ok is None:
            errors.append(answer.err.payload.to_string())
        else:
            messages.append((str(answer.ok.key_expr).rsplit("/", 1)[-1], answer.ok.payload.to_bytes()))
    return messages, errors
