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

ROOT = "pg"

#: per-robot streams a mapper or SLAM node subscribes to, by last key chunk
SCAN, ODOM, LANDMARKS, POSE, END, PRIOR = "scan", "odom", "landmarks", "pose", "end", "prior"


def robot_key(robot: str, stream: str) -> str:
    """pg/<robot>/<stream>; ``robot`` may be "*" for every robot."""
    return f"{ROOT}/{robot}/{stream}"


def robot_of(key: str) -> str:
    """The robot chunk of a pg/<robot>/... key."""
    return key.split("/")[1]


def history_key(robot: str, stream: str = "**") -> str:
    """pg/<robot>/history/<stream>: the source's queryable of what it has published (``stream`` "**": all)."""
    return f"{ROOT}/{robot}/history/{stream}"


def slam_stats_key(robot: str) -> str:
    return f"{ROOT}/{robot}/slam/stats"


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
