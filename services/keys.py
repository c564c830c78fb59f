"""The Zenoh key space (docs/keys.md): every key posegrid uses is built or parsed here.

pg/<robot>/scan                      LaserScan
pg/<robot>/odom                      Odometry
pg/<robot>/landmarks                 LandmarkObservations
pg/<robot>/pose                      PoseSamples or PoseGaussian, tagged with the scan's seq
pg/<robot>/end                       StreamEnd
pg/<robot>/prior                     PoseGaussian: where a SLAM filter starts (seq 0, zero covariance)
pg/<robot>/slam/stats                queryable: NodeStats
pg/<robot>/history/<stream>          queryable (source): the messages it has published, for late joiners
pg/<robot>/alive/<process>           liveliness token of the robot's source or SLAM node
pg/map/<map>/tile/<z>/<tx>/<ty>      TileUpdate publications; queryable (the owning shard answers)
pg/map/<map>/stats/<shard>           queryable: ShardStats
pg/map/<map>/alive/<shard>           liveliness token of a mapper shard
"""

from __future__ import annotations

from schemas.messages import (
    MAX_SHARDS,
    POSE_TYPES,
    RESERVED_ROBOT_NAMES,
    LandmarkObservations,
    LaserScan,
    Odometry,
    StreamEnd,
)
from schemas.wire import is_valid_name

ROOT = "pg"

#: per-robot streams a mapper or SLAM node subscribes to, by last key chunk
SCAN, ODOM, LANDMARKS, POSE, END, PRIOR = "scan", "odom", "landmarks", "pose", "end", "prior"


def robot_key(robot: str, stream: str) -> str:
    """pg/<robot>/<stream>; ``robot`` may be "*" for every robot."""
    return f"{ROOT}/{robot}/{stream}"


#: the streams a robot publishes on pg/<robot>/<stream>
ROBOT_STREAMS = frozenset({SCAN, ODOM, LANDMARKS, POSE, END, PRIOR})

#: the stream (last key chunk) each message type a robot publishes goes out on: every pose type on POSE (the
#: prior, a PoseGaussian too, goes out on PRIOR instead)
STREAM_OF: dict[type, str] = {
    LaserScan: SCAN,
    Odometry: ODOM,
    LandmarkObservations: LANDMARKS,
    StreamEnd: END,
    **dict.fromkeys(POSE_TYPES, POSE),
}


def parse_robot_key(key: str, streams: frozenset[str] | set[str] = ROBOT_STREAMS) -> tuple[str, str] | None:
    """(robot, stream) of a concrete key pg/<robot>/<stream> whose stream is one of ``streams``; None for any
    other key: a wildcard (``*``, ``**``, ``$*``) in any chunk, another depth, a robot chunk that is no robot
    name (schemas.wire.NAME_PATTERN, not ``map``), or an unknown stream. A subscriber on pg/*/scan receives a
    publication on pg/r1/* or pg/** too (their key expressions intersect), so every subscriber parses the key
    with this before using any part of it."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != ROOT or parts[2] not in streams:
        return None
    robot = parts[1]
    if not is_valid_name(robot) or robot in RESERVED_ROBOT_NAMES:
        return None
    return robot, parts[2]


def parse_history_reply_key(key: str) -> tuple[str, str] | None:
    """(robot, stream) of a concrete history reply key pg/<robot>/history/<stream> (services.history); None for
    any other key (a wildcard, another depth, an unknown stream, a robot chunk that is no robot name)."""
    parts = key.split("/")
    if len(parts) != 4 or parts[2] != "history":
        return None
    return parse_robot_key(f"{parts[0]}/{parts[1]}/{parts[3]}")


def parse_index(text: str) -> int | None:
    """The shard index a key chunk names, in its one decimal form (ASCII digits, no sign, no leading zero, below
    MAX_SHARDS); None for anything else: "+0", "00", " 0", "0_0" and other scripts' digits (U+0660, "²") are other
    keys, not shard 0, though int() reads some of them as 0 (a peer's token under one, gone again, took the real
    shard 0 down in the API)."""
    if not (text.isascii() and text.isdigit()) or (len(text) > 1 and text[0] == "0") or len(text) > 4:
        return None
    index = int(text)
    return index if index < MAX_SHARDS else None


def parse_shard_alive_key(key: str) -> tuple[str, int] | None:
    """(map, shard) of a concrete shard liveliness key pg/map/<map>/alive/<shard> (:func:`parse_index`); None for any
    other key."""
    parts = key.split("/")
    if len(parts) != 5 or parts[:2] != [ROOT, "map"] or parts[3] != "alive" or not is_valid_name(parts[2]):
        return None
    shard = parse_index(parts[4])
    return None if shard is None else (parts[2], shard)


def parse_process_alive_key(key: str) -> tuple[str, str] | None:
    """(robot, process) of a concrete process liveliness key pg/<robot>/alive/<process>; None for any other key (a
    robot chunk that is no robot name or is reserved, ``map``)."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != ROOT or parts[2] != "alive":
        return None
    robot, process = parts[1], parts[3]
    if not is_valid_name(robot) or robot in RESERVED_ROBOT_NAMES or not is_valid_name(process):
        return None
    return robot, process


#: the label rejections of a key that is no posegrid key are counted under (the key itself may be anything a peer
#: makes up, so it is not used as a counter's name)
INVALID_KEY = f"{ROOT}/<invalid key>"


def history_key(robot: str, stream: str = "**") -> str:
    """pg/<robot>/history/<stream>: the source's queryable of what it has published (``stream`` "**": all)."""
    return f"{ROOT}/{robot}/history/{stream}"


def slam_stats_key(robot: str) -> str:
    return f"{ROOT}/{robot}/slam/stats"


def ros2_stats_key(robot: str) -> str:
    """pg/<robot>/ros2/stats: the ROS 2 bridge's counts (JSON)."""
    return f"{ROOT}/{robot}/ros2/stats"


def robot_alive_key(robot: str, process: str) -> str:
    return f"{ROOT}/{robot}/alive/{process}"


def tile_key(map_name: str, z: int | str, tx: int | str, ty: int | str) -> str:
    """pg/map/<map>/tile/<z>/<tx>/<ty>; pass "*" for any chunk."""
    return f"{ROOT}/map/{map_name}/tile/{z}/{tx}/{ty}"


def tiles_key(map_name: str) -> str:
    """Every tile of every zoom level of a map."""
    return f"{ROOT}/map/{map_name}/tile/**"


def stats_key(map_name: str, shard: int | str) -> str:
    return f"{ROOT}/map/{map_name}/stats/{shard}"


def shard_alive_key(map_name: str, shard: int | str) -> str:
    return f"{ROOT}/map/{map_name}/alive/{shard}"
