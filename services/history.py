"""Queries on pg/<robot>/history/**: what a process has published of a robot's streams, for whoever missed it
(docs/keys.md, "The histories"). The source answers with its steps, the SLAM node with the poses it published.

A query names ``streams`` (comma-separated key chunks, default every one the answering process knows), ``from``
(the first seq, default 0), ``to`` (the seq after the last, default everything published) and ``seqs`` (at most
MAX_SEQS comma-separated seqs: only those of the range, default all of it); each message
comes back as one reply on pg/<robot>/history/<its stream>, in the order it was published, so a query must ask
for no consolidation.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import msgpack
import zenoh

from services import keys
from services.process import RejectCounter, Stopped
from services.zenoh_config import is_timeout_reply, replier

#: a seq in a query's parameters
_SEQ = re.compile(r"[0-9]{1,18}")
#: seqs one query's ``seqs`` may name
MAX_SEQS = 64
#: bytes of one reply a question takes (a scan of 32 768 beams with intensities is 0.5 MB; larger replies are
#: dropped as they come, and said: a peer's twenty 100 MB replies took a shard to 4.3 GB)
MAX_REPLY_BYTES = 8 << 20

#: the streams a history holds (docs/keys.md): the source answers for all but the poses of a SLAM node
STREAMS = frozenset({keys.PRIOR, keys.ODOM, keys.LANDMARKS, keys.SCAN, keys.POSE})

#: s a question waits for its session to reach a router or peer again (a router restart takes about 5 s here)
RECONNECT_WAIT = 30.0
#: s after such a wait during which a question that nobody answered is asked again, every RETRY_PERIOD s: the
#: processes that answer reconnect on their own schedule
RECONNECT_GRACE = 5.0
RETRY_PERIOD = 0.5
#: s between looks at the stop flag while a question waits (for its replies or for the router)
STOP_POLL = 0.1
#: times a question some history did not finish answering in its timeout is asked again, the timeout doubled each
#: time up to TIMEOUT_CAP s (5 s, then 10 and 20 for a shard's gaps; a 60 s catch-up is asked once): a source
#: answering 359 scans on a loaded machine took more than 5 s, and the shard took what had come as all there was and
#: gave up on the rest. Asked again only when a history was still answering as the time ran out (:func:`cut_off`):
#: a peer's queryable that never answers, alone or beside the real history, held a shard 5 + 10 + 20 s a question
TIMEOUT_RETRIES, TIMEOUT_CAP = 2, 20.0
#: a try's last reply came at most this share of its timeout before the timeout: a history was still answering
CUT_OFF_SHARE = 0.25


def question_timeouts(timeout: float) -> list[float]:
    """The timeouts (s) a question asked with ``timeout`` is asked with, one a try, while a history does not finish
    answering (:data:`TIMEOUT_RETRIES`, :data:`TIMEOUT_CAP`)."""
    tries = [timeout]
    while len(tries) <= TIMEOUT_RETRIES and tries[-1] * 2 <= TIMEOUT_CAP:
        tries.append(tries[-1] * 2)
    return tries


@dataclass(frozen=True)
class HistoryRequest:
    """What a history query asks for: streams (key chunks), seqs first .. stop - 1 (stop None: no end), of them only
    ``seqs`` when given."""

    streams: frozenset[str]
    first: int
    stop: int | None
    seqs: frozenset[int] | None = None

    def wants(self, seq: int) -> bool:
        return self.first <= seq and (self.stop is None or seq < self.stop) and (self.seqs is None or seq in self.seqs)


def parse_request(query: zenoh.Query, robot: str, rejects: RejectCounter) -> HistoryRequest | None:
    """The request of ``query`` to ``robot``'s history: the streams asked for, narrowed to those whose
    pg/<robot>/history/<stream> key its key expression takes in; None after answering it with an error reply that
    says what was wrong, counted by ``rejects`` under pg/<robot>/history/** (kind "query", logged once)."""
    asked = query.parameters.get("streams")
    streams = set(STREAMS) if asked is None else set(asked.split(","))
    asked_first, stop = query.parameters.get("from"), query.parameters.get("to")
    first = "0" if asked_first is None else asked_first
    listed = query.parameters.get("seqs")
    seqs = None if listed is None else listed.split(",")
    problem = (
        f"unknown stream(s) {sorted(streams - STREAMS)}; known: {sorted(STREAMS)}"
        if streams - STREAMS
        else None
        if _SEQ.fullmatch(first) and (stop is None or _SEQ.fullmatch(stop))
        else f"'from' and 'to' must be seqs 0 .. 10^18 in ASCII digits, got {first!r} and {stop!r}"
    )
    if problem is None and seqs is not None and (len(seqs) > MAX_SEQS or not all(_SEQ.fullmatch(q) for q in seqs)):
        shown = str(listed)[:100]
        problem = f"'seqs' must be at most {MAX_SEQS} comma-separated seqs 0 .. 10^18 in ASCII digits, got {shown!r}"
    if problem:
        said = f"history query {query.selector}: {problem}"
        rejects.count(keys.history_key(robot), "query", said)
        query.reply_err(said.encode())
        return None
    streams = {stream for stream in streams if query.key_expr.intersects(keys.history_key(robot, stream))}
    return HistoryRequest(
        frozenset(streams),
        int(first),
        None if stop is None else int(stop),
        None if seqs is None else frozenset(map(int, seqs)),
    )


@dataclass(frozen=True)
class Answerer:
    """Who answers a history, attached to each reply: its Zenoh session's id; the map it publishes for (a source's
    ``--map``; None for a SLAM node, which serves any map); whether it has published the end of its stream."""

    id: str
    map: str | None
    ended: bool

    def encode(self) -> bytes:
        return msgpack.packb([self.id, self.map, self.ended])

    @staticmethod
    def decode(data: bytes) -> Answerer | None:
        """The answerer ``data`` describes; None when it does not describe one."""
        try:
            ident, map_name, ended = msgpack.unpackb(data)
        except (ValueError, TypeError, msgpack.UnpackException):
            return None
        ok = isinstance(ident, str) and (map_name is None or isinstance(map_name, str)) and isinstance(ended, bool)
        return Answerer(ident, map_name, ended) if ok else None


def reply(query: zenoh.Query, answerer: Answerer, robot: str, stream: str, payload: bytes) -> None:
    """One message of the history, on pg/<robot>/history/<stream>, with ``answerer`` attached."""
    query.reply(keys.history_key(robot, stream), payload, attachment=answerer.encode())


def cut_off(reply_times: list[float], started: float, timeout: float) -> bool:
    """Whether a try of a question asked at ``started`` (time.monotonic(), s) that ran out of its ``timeout`` s cut a
    history off as it answered: its last reply (their arrival times ``reply_times``) came within CUT_OFF_SHARE of the
    timeout of the end. A history that sent nothing, or sent all it had long before the end (the wait then was for
    another answerer that never answers), is not asked again."""
    return bool(reply_times) and started + timeout - reply_times[-1] <= CUT_OFF_SHARE * timeout


def reachable(session: zenoh.Session) -> bool:
    """Whether the session is connected to a router or a peer: a question can reach a history."""
    return bool(list(session.info.routers_zid())) or bool(list(session.info.peers_zid()))


def _asked(
    session: zenoh.Session,
    robot: str,
    parameters: dict[str, str],
    timeout: float,
    stop: threading.Event,
    dropped: list[str],
    reply_times: list[float] | None = None,
    max_bytes: int | None = None,
) -> list[zenoh.Reply]:
    """The replies to one question in the order they came, once it is answered or ``timeout`` s have passed
    (Stopped when ``stop`` is set first); a reply of more than MAX_REPLY_BYTES is dropped as it comes, and said in
    ``dropped``. ``reply_times`` gets the arrival time (time.monotonic()) of each reply with a sample. With
    ``max_bytes``, the replies past that many bytes in all are dropped as they come, and said once."""
    replies: list[zenoh.Reply] = []
    done = threading.Event()
    times = reply_times if reply_times is not None else []
    held = [0]  # bytes of the replies kept

    def keep(reply: zenoh.Reply) -> None:
        sample = reply.ok  # (None: an error reply, kept: ask says it)
        if sample is not None:
            times.append(time.monotonic())
            if max_bytes is not None and held[0] + len(sample.payload) > max_bytes:
                if held[0] <= max_bytes:
                    dropped.append(f"replies past {max_bytes} bytes in all; not taken")
                    held[0] = max_bytes + 1
                return
            held[0] += len(sample.payload)
        if sample is None or len(sample.payload) <= MAX_REPLY_BYTES:
            replies.append(reply)
        else:
            size = len(sample.payload)
            dropped.append(f"a reply of {size} bytes on {sample.key_expr}, more than {MAX_REPLY_BYTES}; not taken")

    session.get(
        zenoh.Selector(keys.history_key(robot), parameters),
        handler=zenoh.handlers.Callback(keep, done.set),  # done: after the last reply's callback
        timeout=timeout,
        consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )  # (replies go out under it)
    while not done.wait(STOP_POLL):
        if stop.is_set():
            raise Stopped(f"stopped while asking the histories of {robot!r}")
    return replies


def _answers(
    session: zenoh.Session,
    robot: str,
    parameters: dict[str, str],
    timeout: float,
    stop: threading.Event,
    dropped: list[str],
    tries: list[float],
    retry: bool = True,
    max_bytes: int | None = None,
) -> list[zenoh.Reply]:
    """The replies to one question (the timeout of each try it took appended to ``tries``, s: more time is given
    while a history was cut off as it answered, :func:`cut_off`), asked once the session reaches a router or peer.
    While it reaches none (the router restarting), a question would come back empty at once, and what it asked for
    would be given up as lost though a history holds it: it waits for the connection instead, up to RECONNECT_WAIT
    s. A question nobody answers is asked again while the connection is down, and for RECONNECT_GRACE s after it
    came back. Every wait ends with Stopped when ``stop`` is set: a process asked to stop does not wait for the
    router."""
    deadline = time.monotonic() + RECONNECT_WAIT
    grace_until = None  # set once the session had to wait for its connection
    more_time = question_timeouts(timeout)[1:] if retry else []
    while True:
        while not reachable(session) and time.monotonic() < deadline:
            if stop.wait(STOP_POLL):
                raise Stopped(f"stopped while waiting for the router to ask the histories of {robot!r}")
            grace_until = time.monotonic() + RECONNECT_GRACE
        started = time.monotonic()
        reply_times: list[float] = []
        tries.append(timeout)
        replies = _asked(session, robot, parameters, timeout, stop, dropped, reply_times, max_bytes)
        timed_out = any(is_timeout_reply(reply) for reply in replies)
        if more_time and timed_out and cut_off(reply_times, started, timeout):  # (a slow history: all of it, in time)
            timeout = more_time.pop(0)
            continue
        now = time.monotonic()
        if replies or now >= deadline:
            return replies
        if reachable(session):
            if grace_until is None or now >= grace_until:
                return replies
            if stop.wait(RETRY_PERIOD):
                raise Stopped(f"stopped while asking the histories of {robot!r} again")


def ask(
    session: zenoh.Session,
    robot: str,
    parameters: dict[str, str],
    timeout: float,
    accept: Callable[[Answerer], bool] = lambda answerer: True,
    stop: threading.Event | None = None,
    retry: bool = True,
    max_bytes: int | None = None,
) -> tuple[list[tuple[str, str, bytes]], list[str]]:
    """Ask the histories of ``robot`` ("*": every robot): ((robot, stream, payload) of each message in the order
    sent, problems). Only answerers that ``accept`` takes count (a shard takes its own map's sources; a SLAM node
    catching up, sources still publishing). When two of them answer for one robot's stream (a robot name that
    two runs use at once, or a peer answering as a history), neither is taken: that stream's messages are left out
    and a problem says so, since the live stream cannot say which run it belongs to. An answerer is known by the
    Zenoh session that sent the reply (its ``replier_id``, which zenoh sets): a reply whose attachment names
    another session is not taken, so a peer cannot pose as the real history to slip past that rule. A session cut
    off from the router waits for it to come back (:func:`_answers`); Stopped when ``stop`` is set while it
    waits. ``retry`` False: a history cut off as it answered is not asked again with more time; ``max_bytes``: the
    replies past that many bytes in all are not taken (a problem says so)."""
    messages: list[tuple[str, str, bytes]] = []
    problems: list[str] = []
    answerers: dict[tuple[str, str], set[str]] = {}  # (robot, stream) -> ids of the processes answering for it
    tries: list[float] = []
    for answer in _answers(
        session, robot, parameters, timeout, stop or threading.Event(), problems, tries, retry, max_bytes
    ):
        if answer.ok is None:
            error = answer.err
            assert error is not None  # a reply holds either a sample or an error
            problems.append(
                f"a history did not finish answering in {tries[-1]:g} s (asked {len(tries)} time(s): a slow or "
                "stalled process); what it did not send is taken as lost"
                if is_timeout_reply(answer)
                else error.payload.to_bytes()[:500].decode("utf-8", "replace")
            )
            continue
        parsed = keys.parse_history_reply_key(str(answer.ok.key_expr))  # (robot, stream) of pg/<robot>/history/<s>
        attachment = answer.ok.attachment
        answerer = None if attachment is None else Answerer.decode(attachment.to_bytes())
        if parsed is None or robot not in ("*", parsed[0]):
            problems.append(
                f"a reply on {str(answer.ok.key_expr)[:200]!r} is no pg/{robot}/history/<stream> key "
                "(a wildcard, an unknown stream or another robot); not taken"
            )
        elif answerer is None:
            problems.append(f"a reply on {answer.ok.key_expr} does not say who answers it; not taken")
        elif answer.replier_id is not None and answerer.id != replier(answer):
            problems.append(
                f"a reply on {answer.ok.key_expr} says it comes from process {answerer.id[:40]!r} but came from "
                f"{replier(answer)} (a peer posing as a history); not taken"
            )
        elif accept(answerer):
            answerers.setdefault(parsed, set()).add(answerer.id)
            messages.append((*parsed, answer.ok.payload.to_bytes()))
    clashes = {key for key, ids in answerers.items() if len(ids) > 1}
    problems += [
        f"{len(answerers[key])} processes answer the {key[1]} history of robot {key[0]!r} (is a robot name "
        "used by two runs at once?); none of them is taken"
        for key in sorted(clashes)
    ]
    return [m for m in messages if (m[0], m[1]) not in clashes], problems


def ask_counted(
    session: zenoh.Session,
    robot: str,
    parameters: dict[str, str],
    timeout: float,
    rejects: RejectCounter,
    accept: Callable[[Answerer], bool] = lambda answerer: True,
    stop: threading.Event | None = None,
    retry: bool = True,
    max_bytes: int | None = None,
) -> list[tuple[str, str, bytes]]:
    """:func:`ask`, each problem counted by ``rejects`` under pg/<robot>/history/** (kind "history", logged once):
    (robot, stream, payload) of each message taken, in the order sent."""
    messages, problems = ask(session, robot, parameters, timeout, accept, stop, retry, max_bytes)
    for problem in problems:
        rejects.count(keys.history_key(robot), "history", problem)
    return messages
