"""The ROS 2 message types the bridge reads and writes: CDR (de)serialisation and RIHS01 type hashes through
``rosbags``' Jazzy type store, with the map_msgs and nav2_msgs types it lacks added from their .msg definitions.

A ROS 2 type ``pkg/msg/Name`` has the DDS name ``pkg::msg::dds_::Name_`` (what rmw_zenoh puts in its key
expressions) and a RIHS01 hash of its type description (REP 2016), e.g. ``RIHS01_df668c74...`` for
``std_msgs/msg/String`` (docs/ros2.md quotes the examples this is checked against).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from services.ros2.names import dds_type_name

#: .msg definitions of the types rosbags' store lacks (ros-planning/navigation_msgs
#: map_msgs/msg/OccupancyGridUpdate.msg, ros-navigation/navigation2 nav2_msgs/msg/Particle.msg and ParticleCloud.msg;
#: comments left out: they do not enter the type hash), registered in this order
EXTRA_TYPES = {
    "map_msgs/msg/OccupancyGridUpdate": "std_msgs/Header header\nint32 x\nint32 y\nuint32 width\nuint32 height\n"
    "int8[] data\n",
    "nav2_msgs/msg/Particle": "geometry_msgs/Pose pose\nfloat64 weight\n",
    "nav2_msgs/msg/ParticleCloud": "std_msgs/Header header\nParticle[] particles\n",
}

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_COVARIANCE = "geometry_msgs/msg/PoseWithCovarianceStamped"
PARTICLE_CLOUD = "nav2_msgs/msg/ParticleCloud"


class CdrError(ValueError):
    """Bytes that do not decode as the message type they were sent as."""


@functools.cache
def typestore():
    """rosbags' ROS 2 Jazzy type store with :data:`EXTRA_TYPES` registered (built once per process)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in EXTRA_TYPES.items():
        store.register(get_types_from_msg(text, name))
    return store


@dataclass(frozen=True)
class MessageType:
    """One ROS 2 message type, by its ROS name ``pkg/msg/Name``."""

    name: str

    @property
    def dds_name(self) -> str:
        """``pkg::msg::dds_::Name_``: the name rmw_zenoh's key expressions and tokens carry."""
        return dds_type_name(self.name)

    @property
    def type_hash(self) -> str:
        """``RIHS01_<64 hex digits>``: the REP 2016 hash of the type description."""
        return _type_hash(self.name)

    def cls(self) -> Any:
        """The rosbags message class, to build a message with keyword arguments."""
        return typestore().types[self.name]

    def encode(self, message: Any) -> bytes:
        """CDR bytes (little endian, with the 4-byte encapsulation header) of ``message``."""
        return bytes(typestore().serialize_cdr(message, self.name))

    def decode(self, data: bytes) -> Any:
        """The message ``data`` holds; raises :class:`CdrError` when it does not decode as this type."""
        try:
            return typestore().deserialize_cdr(data, self.name)
        except Exception as exc:  # noqa: BLE001 - rosbags raises struct, index, value and unicode errors on bad bytes
            raise CdrError(f"does not decode as {self.name} ({type(exc).__name__}: {exc})"[:300]) from None


@functools.cache
def _type_hash(name: str) -> str:
    return str(typestore().hash_rihs01(name))


def field_class(name: str) -> Any:
    """The rosbags class of a nested type such as ``geometry_msgs/msg/Pose`` (to build messages)."""
    return typestore().types[name]
