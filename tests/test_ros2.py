"""The ROS 2 bridge's pieces without a network: the key expressions, liveliness tokens, QoS strings and attachments
of rmw_zenoh and zenoh-bridge-ros2dds against the examples docs/ros2.md quotes from their sources; type hashes;
odometry interpolation against the bag reader's; the join of scans with the robot's own poses; the map mirror."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from mapping.grid import MAX_RASTER_CELLS
from schemas.messages import PoseGaussian, PoseSamples, TileUpdate
from services import keys
from services.process import RejectCounter
from services.ros2 import convert, names
from services.ros2 import types as rt
from services.ros2.ingest import MAX_STATIC_FRAMES, MAX_TF_FRAMES, Ingest, IngestConfig, OdometryTrack
from services.ros2.mapout import MapMirror, MapStamp
from slam.laserlog import interpolate_poses

DOC = (Path(__file__).resolve().parents[1] / "docs" / "ros2.md").read_text()
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING = "std_msgs/msg/String"


def quoted(text: str) -> str:
    """``text``, after checking that docs/ros2.md quotes it."""
    assert text in DOC, f"docs/ros2.md does not quote {text!r}"
    return text


def test_topic_keys_match_rmw_zenohs_examples():
    graph = names.Graph(names.RMW, 0, "/", "talker", "8b20917502ee955ac4476e0266340d5c")
    assert rt.MessageType(STRING).type_hash == STRING_HASH
    assert graph.topic_key("/chatter", STRING, STRING_HASH) == quoted(
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    robot1 = names.Graph(names.RMW, 0, "/robot1", "talker", "x")
    key = robot1.topic_key(names.resolve("chatter", "/robot1"), STRING, STRING_HASH)
    assert key == quoted(f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}")
    grid = rt.MessageType(rt.OCCUPANCY_GRID)
    assert robot1.topic_key("/robot1/map", grid.name, grid.type_hash) == quoted(
        "0/robot1/map/nav_msgs::msg::dds_::OccupancyGrid_/RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
    )
    assert names.parse_topic_key(key, robot1, "/robot1/chatter") == ("std_msgs::msg::dds_::String_", STRING_HASH)
    for other in ("0/robot1/chatter/*/x", "0/robot1/chatter/a/b/c", "1/robot1/chatter/a/b", "0/robot1/chat/a/b"):
        assert names.parse_topic_key(other, robot1, "/robot1/chatter") is None


def test_liveliness_tokens_and_qos_match_rmw_zenohs_examples():
    listener = names.Graph(names.RMW, 2, "/", "listener", "aac3178e146ba6f1fc6e6a4085e77f21")
    assert listener.node_token() == quoted("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")
    subscription = listener.entity_token(names.SUBSCRIPTION, 10, "/chatter", STRING, STRING_HASH, names.QoS(depth=10))
    assert subscription == quoted(
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,"
    )
    talker = names.Graph(names.RMW, 2, "/", "talker", "8b20917502ee955ac4476e0266340d5c")
    publisher = talker.entity_token(names.PUBLISHER, 10, "/chatter", STRING, STRING_HASH, names.QoS(depth=7))
    assert publisher == quoted(
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )
    assert names.rmw_qos(names.MAP_QOS) == quoted(":1:,1:,:,:,,")
    assert names.rmw_qos(names.SENSOR_QOS) == quoted("2::,5:,:,:,,")
    assert names.rmw_qos(names.QoS(depth=names.RMW_DEFAULT_DEPTH)) == "::,:,:,:,,"  # all defaults: all empty


def test_bridge_mode_keys_and_route_tokens_match_zenoh_bridge_ros2dds():
    graph = names.Graph(names.BRIDGE, 0, "/robot1", "posegrid", "aac3178e146ba6f1fc6e6a4085e77f21")
    assert graph.topic_key("/robot1/map", rt.OCCUPANCY_GRID, "ignored") == "robot1/map"
    assert graph.node_token() is None
    token = graph.entity_token(names.PUBLISHER, 1, "/robot1/map", rt.OCCUPANCY_GRID, "ignored", names.MAP_QOS)
    assert token == quoted(
        "@/aac3178e146ba6f1fc6e6a4085e77f21/@ros2_lv/MP/robot1§map/nav_msgs§msg§OccupancyGrid/:1:1:0,1"
    )
    assert names.parse_topic_key("robot1/map", graph, "/robot1/map") == ("", "")
    assert names.parse_topic_key("robot1/map/x", graph, "/robot1/map") is None


def test_attachment_layout_matches_the_docs():
    attachment = names.Attachment(1, 1_700_000_000 * 10**9, bytes(range(16)))
    data = names.encode_attachment(attachment)
    assert data.hex() == quoted("0100000000000000 00002a36fe9c9717 10 000102030405060708090a0b0c0d0e0f").replace(
        " ", ""
    )
    assert names.decode_attachment(data) == attachment
    from zenoh.ext import Int64, z_serialize  # the earlier layout, fields named first

    named = z_serialize(("sequence_number", Int64(3), "source_timestamp", Int64(4), "source_gid", bytes(16)))
    assert names.decode_attachment(named.to_bytes()) == names.Attachment(3, 4, bytes(16))
    for bad in (b"", b"garbage", data + b"x", data[:-1]):
        assert names.decode_attachment(bad) is None
    token = "@ros2_lv/0/x/0/1/MP/%/%/posegrid/%map/t/h/q"
    assert names.gid_of(token) == names.gid_of(token) and len(names.gid_of(token)) == 16


def test_type_hashes_match_what_ros2_reports():
    for name, prefix in (
        (rt.OCCUPANCY_GRID, "RIHS01_8d348150"),
        (rt.LASER_SCAN, "RIHS01_64c19139"),
        (rt.GRID_UPDATE, "RIHS01_c4095b0b"),
        (rt.PARTICLE_CLOUD, "RIHS01_193d8cb8"),
    ):
        assert rt.MessageType(name).type_hash.startswith(quoted(prefix))
    assert rt.MessageType(rt.GRID_UPDATE).dds_name == "map_msgs::msg::dds_::OccupancyGridUpdate_"
    with pytest.raises(rt.CdrError):
        rt.MessageType(rt.LASER_SCAN).decode(b"\x00\x01\x00\x00garbage")


@pytest.mark.parametrize("records", [4096, 8])
def test_odometry_is_interpolated_as_the_bag_reader_does_bit_for_bit(records):
    """Yaw unwrapped one record at a time (and only the newest ``records`` kept) gives np.unwrap's value over the
    whole stream: interpolate_poses over all odometry, as slam.rosbag_reader reads a bag."""
    rng = np.random.default_rng(3)
    stamps = np.cumsum(rng.uniform(0.01, 0.2, 300))
    poses = np.column_stack([rng.normal(0, 5, 300), rng.normal(0, 5, 300), rng.uniform(-np.pi, np.pi, 300)])
    poses[::7, 2] = np.pi  # the boundary cases of np.unwrap
    poses[1::7, 2] = -np.pi
    track = OdometryTrack(records)
    for i, (stamp, pose) in enumerate(zip(stamps, poses)):
        assert track.add(float(stamp), tuple(pose))
        if i >= 3:
            query = float(stamps[i - 2] + 0.3 * (stamps[i - 1] - stamps[i - 2]))
            expected = interpolate_poses(stamps[: i + 1], poses[: i + 1], np.array([query]))[0]
            assert np.array_equal(track.pose_at(query), expected)
    assert not track.add(float(stamps[0]), (0.0, 0.0, 0.0))  # older than the last: refused


def _ros_scan(stamp: float, frame: str = "laser", increment: float = 0.5, range_max: float = 10.0):
    return rt.MessageType(rt.LASER_SCAN).cls()(
        header=convert.header(stamp, frame),
        angle_min=-1.0,
        angle_max=0.0,
        angle_increment=increment,
        time_increment=0.0,
        scan_time=0.0,
        range_min=0.1,
        range_max=range_max,
        ranges=np.array([1.0, 2.0, 3.0], np.float32),
        intensities=np.zeros(0, np.float32),
    )


def _tf(stamp: float, parent: str, child: str, x: float, yaw: float):
    transform = rt.field_class("geometry_msgs/msg/Transform")(
        translation=rt.field_class("geometry_msgs/msg/Vector3")(x=x, y=0.0, z=0.0),
        rotation=convert.ros_pose(0, 0, yaw).orientation,
    )
    stamped = rt.field_class("geometry_msgs/msg/TransformStamped")(
        header=convert.header(stamp, parent), child_frame_id=child, transform=transform
    )
    return rt.MessageType(rt.TF_MESSAGE).cls()(transforms=[stamped])


def _ros_odometry(stamp: float, x: float = 0.0):
    """A decoded ``nav_msgs/Odometry`` of base_link at (x, 0, 0) stamped ``stamp`` s."""
    odom_type = rt.MessageType(rt.ODOMETRY)
    vector = rt.field_class("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
    message = odom_type.cls()(
        header=convert.header(stamp, "odom"),
        child_frame_id="base_link",
        pose=rt.field_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=convert.ros_pose(x, 0, 0), covariance=np.zeros(36)
        ),
        twist=rt.field_class("geometry_msgs/msg/TwistWithCovariance")(
            twist=rt.field_class("geometry_msgs/msg/Twist")(linear=vector, angular=vector), covariance=np.zeros(36)
        ),
    )
    return odom_type.decode(odom_type.encode(message))


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_robots_own_poses_are_joined_with_the_scans_nearest_their_stamps():
    rejects = RejectCounter(logging.getLogger("test"))
    clock = Clock()
    ingest = Ingest(IngestConfig("r1", poses=True, wait=1.0, pose_tolerance=0.02), rejects, clock)
    ingest.on_transforms("/tf_static", _tf(0.0, "base_link", "laser", 0.2, math.pi / 2), static=True)
    for stamp in (0.0, 0.1, 0.2, 0.3):
        ingest.on_scan("/scan", _ros_scan(stamp))
    covariance = np.zeros(36)
    covariance[[0, 7, 35]] = [0.01, 0.02, 0.03]
    pose_msg = rt.MessageType(rt.POSE_COVARIANCE).cls()(
        header=convert.header(0.205, "map"),
        pose=rt.field_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=convert.ros_pose(1.0, 2.0, 0.5), covariance=covariance
        ),
    )
    ingest.on_pose("/amcl_pose", convert.to_gaussian(pose_msg, "r1", 0))
    out = ingest.ready()
    assert [(stream, m.seq) for stream, m in out] == [(keys.SCAN, 0), (keys.POSE, 0)]
    scan, pose = out[0][1], out[1][1]
    assert scan.stamp == pytest.approx(0.2) and np.allclose(scan.sensor_offset, [0.2, 0.0, math.pi / 2])
    assert isinstance(pose, PoseGaussian) and np.allclose(pose.mean, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(pose.cov, np.diag([0.01, 0.02, 0.03]))
    assert ingest.unposed == 2  # the scans at 0.0 and 0.1 came before the one matched
    cloud_type = rt.MessageType(rt.PARTICLE_CLOUD)
    particle = rt.field_class("nav2_msgs/msg/Particle")
    cloud = cloud_type.cls()(
        header=convert.header(0.31, "map"),
        particles=[
            particle(pose=convert.ros_pose(1, 1, 0), weight=1.0),
            particle(pose=convert.ros_pose(2, 1, 0), weight=3.0),
        ],
    )
    decoded = cloud_type.decode(cloud_type.encode(cloud))
    ingest.on_pose("/particle_cloud", convert.to_samples(decoded, "r1", 0, weighted=True))
    out = ingest.ready()
    samples = out[1][1]
    assert [m.seq for _, m in out] == [1, 1] and isinstance(samples, PoseSamples)
    np.testing.assert_allclose(samples.weights, [0.25, 0.75])
    ingest.on_pose("/particle_cloud", convert.to_samples(decoded, "r1", 0, weighted=True))  # no scan near 0.31 now
    clock.now = 5.0
    assert ingest.ready() == [] and rejects.kinds() == {"join": 1}


def test_with_the_robots_own_poses_a_laser_frame_no_transform_names_is_refused_not_put_at_the_base(caplog):
    """An integrator's probe: with --pose-topic and no /tf_static, scans from lidar_link (mounted 0.3 m forward, yaw
    0.5 rad) were fused as if the laser sat at the robot's centre facing ahead: no refusal, no word, AUC 0.60 where
    the mount gives 0.97. Such a scan now waits and is refused as ``transform`` (docs/ros2.md), saying what to do;
    a scan made in a frame the robot names (its /tf base, a /tf_static parent, --base-frame) sits at the base."""

    def joined(config: IngestConfig, transforms=()) -> tuple[list, RejectCounter]:
        rejects, clock = RejectCounter(logging.getLogger("test")), Clock()
        ingest = Ingest(config, rejects, clock)
        for message, static in transforms:
            ingest.on_transforms("/tf_static" if static else "/tf", message, static=static)
        ingest.on_scan("/scan", _ros_scan(1.0, frame="lidar_link"))
        pose_msg = rt.MessageType(rt.POSE_COVARIANCE).cls()(
            header=convert.header(1.0, "map"),
            pose=rt.field_class("geometry_msgs/msg/PoseWithCovariance")(
                pose=convert.ros_pose(1.0, 2.0, 0.5), covariance=np.eye(6).ravel() * 0.01
            ),
        )
        ingest.on_pose("/amcl_pose", convert.to_gaussian(pose_msg, "r1", 0))
        out = ingest.ready()
        clock.now = 5.0
        return out + ingest.ready(), rejects

    out, rejects = joined(IngestConfig("r1", poses=True, wait=1.0))
    assert out == [] and rejects.kinds() == {"transform": 1}
    assert any("give --base-frame lidar_link if it is the robot's base" in r.getMessage() for r in caplog.records)
    # the robot's /tf names lidar_link as a frame it moves (odom -> lidar_link): the scans are made in its base
    out, rejects = joined(IngestConfig("r1", poses=True, wait=1.0), [(_tf(1.0, "odom", "lidar_link", 0.0, 0.0), False)])
    assert [stream for stream, _ in out] == [keys.SCAN, keys.POSE] and rejects.kinds() == {}
    # lidar_link is the parent of a static transform (a camera on it): a root, taken as the base
    out, _ = joined(IngestConfig("r1", poses=True, wait=1.0), [(_tf(0.0, "lidar_link", "camera", 0.1, 0.0), True)])
    assert [stream for stream, _ in out] == [keys.SCAN, keys.POSE]
    out, _ = joined(IngestConfig("r1", poses=True, wait=1.0, base_frame="lidar_link"))
    assert [stream for stream, _ in out] == [keys.SCAN, keys.POSE]
    # and with its mount on /tf_static, the mount is the scan's offset
    mounted = [(_tf(0.0, "base_link", "lidar_link", 0.3, 0.5), True)]
    out, _ = joined(IngestConfig("r1", poses=True, wait=1.0), mounted)
    np.testing.assert_allclose(out[0][1].sensor_offset, [0.3, 0.0, 0.5], atol=1e-12)


def test_a_cloud_of_equal_weights_comes_with_the_pose_nearest_its_mean_first():
    """A mapper's --mode ml fuses the first of equal weights; the first pose of a PoseArray (or of a ParticleCloud
    just resampled) is any particle, here one 3 m off the rest. The bridge puts the pose nearest the cloud's mean
    first, the others in their order; weighted clouds keep their order (ml takes the heaviest)."""
    poses = [(4.0, 1.0, 0.0), (1.1, 1.0, 0.02), (0.9, 1.02, -0.01), (1.0, 1.1, 0.0), (1.0, 0.95, 0.01)]
    array = rt.MessageType(rt.POSE_ARRAY).cls()(
        header=convert.header(0.3, "map"), poses=[convert.ros_pose(*pose) for pose in poses]
    )
    samples = convert.to_samples(array, "r1", 0, weighted=False)
    p = np.array(poses)  # (yaws near 0: the plain mean and covariance are the circular ones)
    offset = p - p.mean(axis=0)
    distance = np.einsum("mi,ij,mj->m", offset, np.linalg.inv(np.cov(p.T, bias=True)), offset)
    first = int(np.argmin(distance))
    assert first != 0  # (the pose 3 m off is not the one nearest the mean)
    np.testing.assert_allclose(samples.samples, p[[first, *(i for i in range(5) if i != first)]], atol=1e-12)
    np.testing.assert_allclose(samples.weights, 0.2)
    cloud = rt.MessageType(rt.PARTICLE_CLOUD).cls()(
        header=convert.header(0.3, "map"),
        particles=[
            rt.field_class("nav2_msgs/msg/Particle")(pose=convert.ros_pose(*pose), weight=w)
            for pose, w in zip(poses, (5.0, 1.0, 1.0, 1.0, 1.0))
        ],
    )
    assert convert.to_samples(cloud, "r1", 0, weighted=True).samples[0, 0] == pytest.approx(4.0)


def test_scans_without_a_transform_or_with_nan_geometry_are_counted_not_taken():
    rejects = RejectCounter(logging.getLogger("test"))
    clock = Clock()
    ingest = Ingest(IngestConfig("r1", wait=1.0), rejects, clock)
    ingest.on_odometry("/odom", _ros_odometry(1.0))
    ingest.on_scan("/scan", _ros_scan(1.0, increment=math.nan))
    ingest.on_scan("/scan", _ros_scan(1.0, frame="nowhere"))
    assert ingest.ready() == []  # waits for a transform that may still come
    clock.now = 2.0
    assert ingest.ready() == []
    assert rejects.kinds() == {"geometry": 1, "transform": 1} and rejects.snapshot() == {"/scan": 2}
    ingest.on_scan("/scan", _ros_scan(1.0, frame="base_link"))  # the laser at the base: no transform needed
    assert [stream for stream, _ in ingest.ready()] == [keys.PRIOR, keys.SCAN, keys.ODOM]


def test_a_scan_stating_an_infinite_range_max_goes_out_with_a_kilometre():
    """pointcloud_to_laserscan's default range_max is +inf: the bridge refused every scan of such a robot as
    "geometry". It now sends them with range_max 1 km, its no-return range as configured."""
    rejects = RejectCounter(logging.getLogger("test"))
    clock = Clock()
    ingest = Ingest(IngestConfig("r1", wait=1.0, no_return_range=8.0), rejects, clock)
    ingest.on_odometry("/odom", _ros_odometry(1.0))
    ingest.on_scan("/scan", _ros_scan(1.0, frame="base_link", range_max=math.inf))
    clock.now = 2.0
    scans = [message for stream, message in ingest.ready() if stream == keys.SCAN]
    assert rejects.kinds() == {} and len(scans) == 1
    assert (scans[0].range_max, scans[0].no_return_range) == (1000.0, 8.0)
    assert scans[0].ranges.tolist() == [1.0, 2.0, 3.0]
    scans[0].encode()  # the wire takes it


def _tf_rolled(parent: str, child: str, x: float, yaw: float, roll: float):
    """``_tf`` of a child turned ``yaw`` and rolled ``roll`` (rad): the quaternion of Rz(yaw) Rx(roll)."""
    message = _tf(0.0, parent, child, x, yaw)
    rotation = message.transforms[0].transform.rotation
    cy, sy, cr, sr = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(roll / 2), math.sin(roll / 2)
    rotation.w, rotation.x, rotation.y, rotation.z = cy * cr, cy * sr, sy * sr, sy * cr
    return message


def test_a_laser_upside_down_goes_out_with_its_beams_mirrored_and_a_tilted_one_is_counted(caplog):
    """The bridge read a mount rolled by pi as level, and every scan went out mirrored (a probe: the map silently
    wrong). Its scans now go out as a level laser's at the same place would give them; a laser tilted 60 deg off
    the floor's plane is refused as ``transform``, saying so."""
    rejects = RejectCounter(logging.getLogger("test"))
    clock = Clock()
    ingest = Ingest(IngestConfig("r1", wait=1.0), rejects, clock)
    ingest.on_transforms("/tf_static", _tf_rolled("base_link", "laser", 0.2, 0.7, math.pi), static=True)
    ingest.on_transforms("/tf_static", _tf_rolled("base_link", "tilted", 0.2, 0.7, math.radians(60)), static=True)
    ingest.on_odometry("/odom", _ros_odometry(1.0))
    ingest.on_scan("/scan", _ros_scan(1.0))
    ingest.on_scan("/scan", _ros_scan(1.0, frame="tilted"))
    clock.now = 2.0
    scans = [message for stream, message in ingest.ready() if stream == keys.SCAN]
    assert len(scans) == 1
    np.testing.assert_allclose(scans[0].sensor_offset, [0.2, 0.0, 0.7], atol=1e-12)
    assert (scans[0].angle_min, scans[0].angle_increment) == pytest.approx((1.0, -0.5))  # beams at 0.7 - a
    assert rejects.kinds() == {"transform": 1}
    assert any("tilts the laser's scan plane" in record.getMessage() for record in caplog.records)


def test_a_stamp_past_what_a_ros_time_holds_is_clamped_in_what_goes_out():
    """A scan stamped 2147483647.999999999 s (2^31 as a float) stamped the map with 2^31 s, which a ROS Time's int32
    cannot hold: every later map message failed to encode. Out-of-range stamps are clamped to the range's ends."""
    grid = rt.MessageType(rt.GRID_UPDATE)
    for stamp, expected in ((2.0**31, (2**31 - 1, 999_999_999)), (-1e12, (-(2**31), 0)), (12.5, (12, 500_000_000))):
        update = convert.grid_update(np.zeros((1, 1), np.int8), 0, 0, stamp, "map")
        decoded = grid.decode(grid.encode(update))
        assert (decoded.header.stamp.sec, decoded.header.stamp.nanosec) == expected


def test_odometry_whose_clock_went_back_starts_the_track_over():
    """One odometry message stamped in 2033 (or a robot's clock set back) made every later one "order" and every
    later scan "odometry", for good. Three records in a row behind the last, each in order, start the track over
    from them (counted as "clock"); one late record among newer ones does not."""
    track = OdometryTrack()
    for stamp in (1.0, 2.0, 3.0):
        assert track.add(stamp, (stamp, 0.0, 0.0))
    assert not track.add(2.5, (0.0, 0.0, 0.0)) and track.add(4.0, (4.0, 0.0, 0.0))  # one late record: refused
    assert track.add(2.0e9, (9.0, 0.0, 0.0))  # stamped far ahead
    assert [track.add(stamp, (stamp, 0.0, 0.0)) for stamp in (5.0, 6.0, 7.0)] == [False, False, True]
    assert track.restarts == 1 and track.arrays()[0].tolist() == [5.0, 6.0, 7.0]
    np.testing.assert_allclose(track.pose_at(6.5), [6.5, 0.0, 0.0])
    rejects = RejectCounter(logging.getLogger("test"))
    clock = Clock()
    ingest = Ingest(IngestConfig("r1", wait=1.0), rejects, clock)
    for stamp in (1.0, 2.0e9, 2.0, 3.0, 4.0):
        ingest.on_odometry("/odom", _ros_odometry(stamp, x=min(stamp, 9.0)))
    ingest.on_scan("/scan", _ros_scan(3.5, frame="base_link"))
    out = ingest.ready()
    assert [stream for stream, _ in out] == [keys.PRIOR, keys.SCAN, keys.ODOM] and out[2][1].pose[0, 0] == 3.5
    assert rejects.kinds() == {"order": 2, "clock": 1}


def test_made_up_frames_neither_grow_the_transforms_nor_push_out_the_base_frame():
    """/tf_static kept every frame a peer made up (40 000 a message: 100 MB and on); it keeps 1 024. On /tf, 70
    made-up frames before the robot's own locked its base frame out for good (64 tracked, the rest refused): a new
    frame now replaces the one updated longest ago that no scan took as its base."""
    rejects = RejectCounter(logging.getLogger("test"))
    ingest = Ingest(IngestConfig("r1", wait=1.0), rejects, Clock())
    made_up = rt.MessageType(rt.TF_MESSAGE).cls()(
        transforms=[_tf(1.0, "base_link", f"x{i}", 0.0, 0.0).transforms[0] for i in range(MAX_STATIC_FRAMES + 5)]
    )
    ingest.on_transforms("/tf_static", made_up, static=True)
    assert len(ingest.static) == MAX_STATIC_FRAMES and rejects.kinds() == {"overflow": 5}
    ingest.static.clear()
    ingest.on_transforms("/tf_static", _tf(0.0, "base5", "laser5", 0.2, 0.0), static=True)
    for i in range(70):
        ingest.on_transforms("/tf", _tf(1.0, "odom", f"bogus{i}", 0.0, 0.0), static=False)
    assert len(ingest.tf_tracks) == MAX_TF_FRAMES
    for stamp in (20.0, 21.0):
        ingest.on_transforms("/tf", _tf(stamp, "odom", "base5", stamp, 0.0), static=False)
    ingest.on_scan("/scan", _ros_scan(20.5, frame="laser5"))
    out = ingest.ready()
    assert [stream for stream, _ in out] == [keys.PRIOR, keys.SCAN, keys.ODOM] and out[2][1].pose[0, 0] == 20.5
    for i in range(70, 200):  # a base a scan took is never the one replaced
        ingest.on_transforms("/tf", _tf(1.0, "odom", f"bogus{i}", 0.0, 0.0), static=False)
    assert "base5" in ingest.tf_tracks and len(ingest.tf_tracks) == MAX_TF_FRAMES


def _tile(
    tx: int, ty: int, row0: int = 0, col0: int = 0, size: int = 4, shape=(4, 4), seed: int = 0, given=None
) -> TileUpdate:
    """A tile update of random values over a window of ``shape`` at (row0, col0), giving the cells ``given``
    marks (default every one)."""
    rng = np.random.default_rng(seed)
    layers = (
        rng.normal(0, 2, shape).astype(np.float32),
        rng.uniform(0, 2, shape).astype(np.float32),
        rng.uniform(size=shape) < 0.8,
    )
    return TileUpdate.of_window(
        layers,
        given,
        map="main",
        shard=0,
        z=0,
        tx=tx,
        ty=ty,
        tile_size=size,
        resolution=0.5,
        row0=row0,
        col0=col0,
        robot="r1",
        seq=0,
        published=0.0,
    )


def test_the_map_is_stamped_with_the_latest_scan_by_seq_not_the_largest_stamp():
    """One scan stamped far ahead (2^31 s) stamped every later map with it, as the map took the largest stamp of the
    scans fused; it takes the latest scan's by seq, so a robot's clock set back stamps the maps that follow."""
    stamp = MapStamp(kept=3)
    for seq, when in enumerate((10.0, 2.0**31, 11.0, 12.0)):
        stamp.published(seq, when)
    stamp.fused(1)
    assert stamp.stamp == 2.0**31
    stamp.fused(3)
    assert stamp.stamp == 12.0
    stamp.fused(2)  # (an older scan's tile, updated late: the map is as new as scan 3)
    assert stamp.stamp == 12.0
    stamp.fused(0)  # (forgotten: the newest 3 are kept)
    assert stamp.stamp == 12.0


def test_the_map_mirror_places_updates_in_the_grid_last_published():
    mirror = MapMirror(variance_scale=2.0)
    assert mirror.apply(_tile(0, 0)) is None and mirror.grown  # nothing published yet
    mirror.apply(_tile(-1, 1, seed=1))
    raster = mirror.raster()
    assert raster is not None and raster.occupancy.shape == (8, 8) and raster.origin == (-2.0, 0.0)
    tile = _tile(0, 0, seed=2)
    logodds, spread, observed = (layer.copy() for layer in tile.whole_layers())
    patch = mirror.apply(_tile(0, 0, row0=1, col0=2, shape=(2, 2), seed=3))
    assert patch is not None and (patch.x, patch.y) == (4 + 2, 0 + 1)  # tile (0, 0): column 4, row 0
    mirror.apply(tile)
    # an update that gives two cells of its 2 x 3 window: the others keep the whole tile's values
    given = np.array([[True, False, False], [False, False, True]])
    part = _tile(0, 0, row0=2, col0=1, shape=(2, 3), seed=4, given=given)
    window = _tile(0, 0, row0=2, col0=1, shape=(2, 3), seed=4)  # (the same values, every cell given)
    patch = mirror.apply(part)
    for layer, values in zip((logodds, spread, observed), (window.logodds, window.variance, window.given_observed())):
        layer[2:4, 1:4][given] = values.reshape(2, 3)[given]
    expected = np.rint(100 / (1 + np.exp(-logodds.astype(np.float64)))).astype(np.int8)
    assert patch is not None and (patch.x, patch.y) == (4 + 1, 0 + 2)
    np.testing.assert_array_equal(patch.values, np.where(observed, expected, -1)[2:4, 1:4])
    raster = mirror.raster()
    values = raster.occupancy[0:4, 4:8]
    np.testing.assert_array_equal(values, np.where(observed, expected, -1))
    variance = np.rint(np.clip(100 * spread.astype(np.float64) / 2.0, 0, 100)).astype(np.int8)
    np.testing.assert_array_equal(raster.variance[0:4, 4:8], np.where(observed, variance, -1))
    assert (raster.occupancy[4:8, 4:8] == -1).all()  # tile (0, 1) was never seen
    assert mirror.apply(_tile(1, 0)) is None and mirror.grown  # beyond the grid: the next whole grid takes it
    assert "resolution" not in mirror.check(tile) and mirror.check(_tile(0, 0, size=8, shape=(8, 8)))
    # a tile so far off that the grid could not be published whole is refused, and the grid goes on
    far = MAX_RASTER_CELLS // 16  # tiles of 4 x 4 cells: the grid would span far + 2 tiles across, 4 down
    assert "more than" in mirror.check(_tile(far, 0)) and mirror.raster() is not None


@pytest.mark.parametrize(
    "argv, message",
    [
        (["ros2", "--namespace", "/9robot", "--connect", "tcp/127.0.0.1:1"], "is not a ROS 2 name"),
        (["ros2", "--domain", "300", "--connect", "tcp/127.0.0.1:1"], "the ROS domain id must be 0 .. 232"),
        (["ros2", "--scan-topic", "a//b", "--connect", "tcp/127.0.0.1:1"], "topic 'a//b' is not a ROS 2 name"),
        (["ros2", "--robot", "map", "--connect", "tcp/127.0.0.1:1"], "--robot 'map' is not a valid name"),
        # the rule said letters, digits, '_', '.', '-' and refused '.' (a probe's): it starts with a letter or digit
        (
            ["ros2", "--robot", ".", "--connect", "tcp/127.0.0.1:1"],
            "'.' is not a valid name (letters, digits, '_', '.' and '-', starting with a letter or digit, at most 64;",
        ),
        (["ros2", "play", "/nonexistent/bag", "--rate", "2x"], "rate must be 'max'"),
        (["run", "--ros2", "--posed", "x.npz", "--no-api"], "--ros2 maps a live robot: it takes no input (--posed)"),
        (["run", "--ros2", "--export", "m.npz", "--no-api"], "leave out --export"),
        (["run", "--ros2", "--secure", "--no-api"], "--ros2 does not run with --secure"),
        # an endpoint the router would refuse, after the run had started its children (a probe's)
        (["run", "--ros2", "--ros2-connect", "foo", "--no-api"], "--ros2-connect: zenoh rejects connect/endpoints"),
        (["run", "--ros2", "--algo", "ekf", "--no-api"], "--algo must be gridslam"),
        # frame ids and pose inputs the bridge started with (a probe's): tf2 refuses a leading '/' or an empty id
        (["ros2", "--frame", "", "--connect", "tcp/127.0.0.1:1"], "--frame '' is no frame id"),
        (["ros2", "--base-frame", "/base", "--connect", "tcp/127.0.0.1:1"], "--base-frame '/base' is no frame id"),
        (["ros2", "--frame", "a b", "--connect", "tcp/127.0.0.1:1"], "--frame 'a b' is no frame id"),
        (["ros2", "--pose-topic", "amcl_pose", "--particles-topic", "p", "--connect", "tcp/127.0.0.1:1"], "give one"),
        (["ros2", "--particles-type", "PoseArray", "--connect", "tcp/127.0.0.1:1"], "give that topic too"),
        # an output on an input's topic (the bridge read its own maps as scans), waits that never end (a probe's)
        (["ros2", "--map-topic", "scan", "--connect", "tcp/127.0.0.1:1"], "--scan-topic and --map-topic name one"),
        (["ros2", "--odom-wait", "1e308", "--connect", "tcp/127.0.0.1:1"], "--odom-wait must be at most 3600 s"),
        # `run --ros2` checks its bridge's options before it starts anything (it started four children first)
        (["run", "--ros2", "--ros2-pose-out-topic", "odom", "--no-api"], "--ros2-odom-topic and --ros2-pose-out-t"),
    ],
)
def test_bad_ros2_options_are_one_line_and_exit_2(argv, message, capsys):
    from services.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0] and "Traceback" not in err[0], err


def test_the_variance_scale_is_refused_in_its_own_unit(capsys):
    """--variance-scale is log-odds squared; a negative one said "must be > 0 s"."""
    from services.cli import main

    with pytest.raises(SystemExit) as exited:
        main(["ros2", "--variance-scale", "-1", "--connect", "tcp/127.0.0.1:1"])
    err = capsys.readouterr().err
    assert exited.value.code == 2 and "--variance-scale: must be > 0, got '-1'" in err, err


def test_play_refuses_a_missing_bag_and_a_ros1_bag(tmp_path, capsys):
    from bags import BagBuilder
    from services.cli import main

    assert main(["ros2", "play", str(tmp_path / "none"), "--connect", "tcp/127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "no such file or bag folder (expected a ROS 2 bag: its folder with metadata.yaml" in err, err
    assert "ROS 1" not in err, err  # (play replays ROS 2 bags only: a missing bag's message says so)
    ros1 = BagBuilder()
    ros1.scan(0.0, [1.0])
    path = ros1.write(tmp_path / "a.bag")
    assert main(["ros2", "play", str(path), "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "a ROS 1 bag; `posegrid ros2 play` replays ROS 2 bags" in capsys.readouterr().err


def test_the_map_mirror_holds_at_most_its_tile_bound(monkeypatch):
    """A probe's finding: with 1-cell tiles the raster bound let a mirror hold 2**28 tiles, and its whole grid is made
    tile by tile (60 000 took 0.7 s a grid). A new tile past MAX_MIRROR_TILES is refused; the tiles held still
    update, and the mirror's extent follows the tiles taken."""
    from services.ros2 import mapout

    monkeypatch.setattr(mapout, "MAX_MIRROR_TILES", 3)
    mirror = MapMirror()
    for tx in range(3):
        assert mirror.check(_tile(tx, -tx)) == ""
        mirror.apply(_tile(tx, -tx))
    assert "past 3 tiles" in mirror.check(_tile(5, 0))
    assert mirror.check(_tile(1, -1, seed=2)) == "" and mirror.extent() == (0, -2, 2, 0)


def test_a_pose_array_or_particle_cloud_past_the_pose_limit_is_refused_before_it_is_decoded():
    """A probe's 100 000-pose PoseArray (5.6 MB, under the bridge's 8 MB input limit) was decoded and converted (0.66
    s) before the 10 000-pose limit refused it, holding the robot's scans back 0.7 s each. Its size alone refuses it
    now, as the payload's length says how many poses it can hold (56 CDR bytes a pose, 64 a particle), before any
    decoding (the check never reaches the bridge's ROS node: none is made here)."""
    from types import SimpleNamespace

    from schemas.messages import MAX_POSE_SAMPLES
    from services.ros2.bridge import CDR_HEADROOM, Bridge
    from services.ros2.endpoint import Received

    for type_name, per_pose in ((rt.POSE_ARRAY, 56), (rt.PARTICLE_CLOUD, 64)):
        size = MAX_POSE_SAMPLES * per_pose + CDR_HEADROOM + 1
        received = Received("/robot1/particles_in", "0/robot1/particles_in", b"", None, size)
        problem = Bridge._sample_problem(SimpleNamespace(), received, rt.MessageType(type_name))  # type: ignore[arg-type]
        assert problem is not None and problem[0] == "pose" and f"more than {MAX_POSE_SAMPLES} poses" in problem[1]
