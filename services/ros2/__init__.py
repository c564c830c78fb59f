"""ROS 2 over Zenoh, with no ROS installation (docs/ros2.md).

- :mod:`services.ros2.types`: the ROS 2 message types posegrid reads and writes, CDR through ``rosbags`` and their
  RIHS01 type hashes (map_msgs and nav2_msgs added from their .msg definitions);
- :mod:`services.ros2.names`: the key expressions, liveliness tokens, QoS strings, GIDs and sample attachments of
  rmw_zenoh and of zenoh-bridge-ros2dds (pure functions);
- :mod:`services.ros2.convert`: ROS messages to and from posegrid's (laser mounts, odometry, poses, occupancy grids);
- :mod:`services.ros2.ingest` and :mod:`services.ros2.mapout`: what the bridge decides, without a network;
- :mod:`services.ros2.endpoint`: ROS 2 publishers and subscriptions on a Zenoh session;
- :mod:`services.ros2.bridge`: the `posegrid ros2` process; :mod:`services.ros2.play`: `posegrid ros2 play BAG`.
"""
