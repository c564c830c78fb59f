"""Small ROS bags written with rosbags' writers, for the tests of the bag reader and of the pipeline's --bag."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

NS = 1_000_000_000


class BagBuilder:
    """Messages for one bag, written as ROS 1 or ROS 2; times in s."""

    def __init__(self, ros2: bool = False) -> None:
        self.ros2 = ros2
        self.store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # the ROS 1 store lacks tf2_msgs
            self.store.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
            )
        self.items: list[tuple[str, str, float, object]] = []  # topic, msgtype, time, msg or raw bytes

    def _t(self, name):
        return self.store.types[name]

    def header(self, stamp: float, frame: str):
        sec = int(math.floor(stamp))
        time = self._t("builtin_interfaces/msg/Time")(sec=sec, nanosec=int(round((stamp - sec) * NS)))
        if self.ros2:
            return self._t("std_msgs/msg/Header")(stamp=time, frame_id=frame)
        return self._t("std_msgs/msg/Header")(seq=0, stamp=time, frame_id=frame)

    def quat(self, yaw: float, pitch: float = 0.0, roll: float = 0.0):
        """The quaternion of Rz(yaw) Ry(pitch) Rx(roll) (ROS's fixed-axis roll, pitch, yaw)."""
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
        cr, sr = math.cos(roll / 2), math.sin(roll / 2)
        return self._t("geometry_msgs/msg/Quaternion")(
            w=cy * cp * cr + sy * sp * sr,
            x=cy * cp * sr - sy * sp * cr,
            y=cy * sp * cr + sy * cp * sr,
            z=sy * cp * cr - cy * sp * sr,
        )

    def scan(
        self, stamp, ranges, topic="/scan", angle_min=-1.0, increment=0.5, range_max=10.0, frame="laser", range_min=0.1
    ):
        ranges = np.asarray(ranges, np.float32)
        msg = self._t("sensor_msgs/msg/LaserScan")(
            header=self.header(stamp, frame),
            angle_min=angle_min,
            angle_max=angle_min + increment * (len(ranges) - 1),
            angle_increment=increment,
            time_increment=0.0,
            scan_time=0.0,
            range_min=range_min,
            range_max=range_max,
            ranges=ranges,
            intensities=np.zeros(0, np.float32),
        )
        self.items.append((topic, "sensor_msgs/msg/LaserScan", stamp, msg))

    def odom(self, stamp, x, y, yaw, topic="/odom", child="base_link"):
        t = self._t
        pose = t("geometry_msgs/msg/Pose")(
            position=t("geometry_msgs/msg/Point")(x=x, y=y, z=0.0), orientation=self.quat(yaw)
        )
        zero3 = t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        msg = t("nav_msgs/msg/Odometry")(
            header=self.header(stamp, "odom"),
            child_frame_id=child,
            pose=t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
            twist=t("geometry_msgs/msg/TwistWithCovariance")(
                twist=t("geometry_msgs/msg/Twist")(linear=zero3, angular=zero3), covariance=np.zeros(36)
            ),
        )
        self.items.append((topic, "nav_msgs/msg/Odometry", stamp, msg))

    def tf(self, stamp, parent, child, x, y, yaw, topic="/tf", pitch=0.0, roll=0.0):
        t = self._t
        transform = t("geometry_msgs/msg/Transform")(
            translation=t("geometry_msgs/msg/Vector3")(x=x, y=y, z=0.0), rotation=self.quat(yaw, pitch, roll)
        )
        stamped = t("geometry_msgs/msg/TransformStamped")(
            header=self.header(stamp, parent), child_frame_id=child, transform=transform
        )
        self.items.append((topic, "tf2_msgs/msg/TFMessage", stamp, t("tf2_msgs/msg/TFMessage")(transforms=[stamped])))

    def raw(self, stamp, topic, msgtype, data: bytes):
        self.items.append((topic, msgtype, stamp, data))

    def write(self, path: Path) -> Path:
        from rosbags.rosbag1 import Writer as Writer1
        from rosbags.rosbag2 import Writer as Writer2

        writer = Writer2(path, version=9) if self.ros2 else Writer1(path)
        serialize = self.store.serialize_cdr if self.ros2 else self.store.serialize_ros1
        with writer:
            conns = {}
            for topic, msgtype, stamp, msg in sorted(self.items, key=lambda i: i[2]):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=self.store)
                data = msg if isinstance(msg, bytes) else serialize(msg, msgtype)
                writer.write(conns[topic], int(round(stamp * NS)), data)
        return path
