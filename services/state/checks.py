"""The checks every message a shard or a SLAM node takes passes, written once for both (services.state.shard,
services.state.slam) and for the intake queue in front of them (services.intake): its key is a robot stream the
process reads, its payload decodes to a type that stream may carry, and it is of the robot its key names. A reply
from a history (services.history) passes one more: it holds a seq of the span asked for.

Each refusal is counted by a :class:`services.process.RejectCounter` (logged once per key and kind); the functions
return None then, so the caller drops the message.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TypeVar

from schemas.messages import (
    LandmarkObservations,
    LaserScan,
    MessageError,
    Odometry,
    PoseGaussian,
    PoseSamples,
    StreamEnd,
    decode_message,
)
from schemas.wire import Message
from services import keys
from services.process import RejectCounter

#: a message of one seq of a robot's stream (each has ``robot`` and ``seq`` fields)
SeqMessage = LaserScan | Odometry | LandmarkObservations | PoseSamples | PoseGaussian
#: a message of a robot's stream (each has a ``robot`` field)
RobotMessage = SeqMessage | StreamEnd

_M = TypeVar("_M", bound=Message)
_R = TypeVar("_R", bound=RobotMessage)
_S = TypeVar("_S", bound=SeqMessage)


def robot_stream(
    key: str, streams: Iterable[str], rejects: RejectCounter, robot: str | None = None
) -> tuple[str, str] | None:
    """(robot, stream) of ``key`` when it is pg/<robot>/<stream> with a stream of ``streams`` (and, given ``robot``,
    that robot's); None after counting it under keys.INVALID_KEY, kind "key" (a wildcard such as pg/*/scan reaches
    every subscriber, and a peer may publish on any key its role allows)."""
    streams = tuple(streams)
    parsed = keys.parse_robot_key(key, frozenset(streams))
    if parsed is None or robot not in (None, parsed[0]):
        rejects.count(
            keys.INVALID_KEY,
            "key",
            f"a message on {key[:200]!r}, which is no pg/{robot or '<robot>'}/"
            f"<stream> key of the streams {', '.join(streams)} (a wildcard, another depth, another robot or "
            "an invalid robot name)",
        )
        return None
    return parsed


def decode_of_robot(
    key: str, robot: str, payload: bytes, types: tuple[type[_R], ...], rejects: RejectCounter
) -> _R | None:
    """The message ``payload`` received on ``key`` holds, when it decodes to one of ``types`` and is ``robot``'s;
    None after counting why not under ``key`` (the decoding's reason, e.g. "malformed" or "type"; or "robot")."""
    message = _decoded(key, payload, types, rejects)
    if message is None:
        return None
    if message.robot != robot:
        rejects.count(key, "robot", f"a {message.TYPE} of robot {message.robot!r} arrived on {key}")
        return None
    return message


def history_reply(
    key: str,
    robot: str,
    payload: bytes,
    types: tuple[type[_S], ...],
    first: int,
    last: int | None,
    rejects: RejectCounter,
) -> _S | None:
    """The message a history replied with (``payload``) to a question about ``robot``'s seqs first..last (last None:
    every seq from ``first``), when it decodes to one of ``types``, is that robot's and holds a seq of the span; None
    after counting why not under ``key`` (the history's key the caller counts it under): the decoding's reason, or
    "key" for a reply about another robot or seq."""
    message = _decoded(key, payload, types, rejects)
    if message is None:
        return None
    if message.robot != robot or message.seq < first or (last is not None and message.seq > last):
        rejects.count(
            key,
            "key",
            f"a {message.TYPE} of robot {message.robot!r}, seq {message.seq}, answered a "
            f"question about seqs {first}-{'' if last is None else last} of robot {robot!r}",
        )
        return None
    return message


def _decoded(key: str, payload: bytes, types: tuple[type[_M], ...], rejects: RejectCounter) -> _M | None:
    """``payload`` decoded as one of ``types``; None after counting the decoding's reason under ``key``."""
    try:
        message = decode_message(payload, *types)
    except MessageError as exc:
        rejects.count(key, exc.reason, str(exc))
        return None
    assert isinstance(message, types)  # decode_message refuses every other type
    return message
