"""ROS bag reader on small bags written here with rosbags' writers, and on the real bags."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bags import BagBuilder
from conftest import shared_file
from slam.carmen import read_carmen
from slam.errors import LogFormatError
from slam.rosbag_reader import read_rosbag


def standard_bag(ros2: bool = False, odometry_on_tf: bool = False) -> BagBuilder:
    bag = BagBuilder(ros2)
    bag.tf(0.0, "base_link", "laser", 0.1, 0.0, math.pi / 2, topic="/tf_static")  # message 1
    poses = [(0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, math.pi / 2), (2.0, 1.0, 2.0, -3.0)]
    for stamp, x, y, yaw in poses:  # messages 2, 4, 7 (odometry at t = 0, 1, 2)
        if odometry_on_tf:
            bag.tf(stamp, "odom", "base_link", x, y, yaw)
        else:
            bag.odom(stamp, x, y, yaw)
    bag.scan(0.5, [1.0, 2.0, 3.0])  # message 3
    bag.scan(1.5, [4.0, 12.0, np.nan])  # message 5
    bag.scan(1.6, [4.0, 5.0])  # message 6: two beams instead of three, read with its own geometry
    bag.scan(2.3, [7.0, 8.0, 9.0])  # message 8: 0.3 s after the last odometry, end pose held
    bag.scan(3.0, [7.0, 8.0, 9.0])  # message 9: 1.0 s after: skipped
    return bag


def check_standard(log):
    assert log.where.tolist() == [3, 5, 6, 8]
    assert [s.where for s in log.skipped] == [9]
    assert "outside the odometry" in log.skipped[0].reason
    np.testing.assert_allclose(log.stamps, [0.5, 1.5, 1.6, 2.3])
    assert log.beams.tolist() == [3, 3, 2, 3]
    assert log.angle_min == pytest.approx(-1.0) and log.angle_increment == pytest.approx(0.5)
    assert log.range_min == pytest.approx(0.1) and log.range_max == pytest.approx(10.0)
    np.testing.assert_allclose(log.sensor_offset, [[0.1, 0.0, math.pi / 2]] * 4, atol=1e-12)
    # halfway between (0,0,0) and (1,0,pi/2); then between (1,0,pi/2) and (1,2,-3) the short way over pi
    later = -3.0 + 2 * math.pi  # -3 rad unwrapped after pi/2
    yaw = 0.5 * (math.pi / 2 + later)  # 2.427 rad, below pi
    expected = [[0.5, 0.0, math.pi / 4], [1.0, 1.0, yaw], [1.0, 1.2, math.pi / 2 + 0.6 * (later - math.pi / 2)]]
    np.testing.assert_allclose(log.odometry, [*expected, [1.0, 2.0, -3.0]], atol=1e-9)
    np.testing.assert_array_equal(log.ranges[1, :2], [4.0, np.inf])
    assert log.ranges[1, 2] == 0.0  # NaN, invalid: below range_min, skipped (REP 117)
    assert log.scan_ranges(2).tolist() == [4.0, 5.0] and np.isnan(log.ranges[2, 2])  # the padding stays NaN


def beam_ends(log) -> np.ndarray:
    """Each scan's beam ends (T, B, 2) in the odometry frame, by hand: odometry pose, then the laser's pose on the
    robot, then the beam at angle_min + i angle_increment in the laser's frame (as every consumer reads them)."""
    ends = np.zeros((len(log), log.ranges.shape[1], 2))
    for t in range(len(log)):
        x, y, yaw = log.odometry[t]
        ox, oy, oyaw = log.sensor_offset[t]
        lx, ly, lyaw = (
            x + math.cos(yaw) * ox - math.sin(yaw) * oy,
            y + math.sin(yaw) * ox + math.cos(yaw) * oy,
            yaw + oyaw,
        )
        angles = lyaw + log.angle_min[t] + log.angle_increment[t] * np.arange(log.ranges.shape[1])
        ends[t] = np.column_stack([lx + log.ranges[t] * np.cos(angles), ly + log.ranges[t] * np.sin(angles)])
    return ends


@pytest.mark.parametrize("ros2", [False, True])
def test_a_laser_mounted_upside_down_is_read_with_its_beams_mirrored(tmp_path, ros2):
    """A laser rolled by pi on its mount (under a table-top robot) lists its beams the other way round: read with
    the mount's yaw alone, every scan was mirrored, the map silently wrong (a ROS 2 probe: 9 of 825 occupied cells
    where the upright run had its walls). Its beams end where a level laser's at the same place would, in a chain
    whose upside-down link lies between the laser and the base too; a mount tilted 60 deg is refused."""
    ranges = [1.0, 2.0, 3.0, 4.0, 5.0]

    def bag(name, mounts, scan_min, scan_ranges):
        builder = BagBuilder(ros2)
        for parent, child, pose, roll in mounts:
            builder.tf(0.0, parent, child, *pose, topic="/tf_static", roll=roll)
        builder.odom(0.0, 1.0, 2.0, 0.4)
        builder.odom(1.0, 1.5, 2.5, 0.9)
        builder.scan(0.5, scan_ranges, angle_min=scan_min, increment=0.25)
        return read_rosbag(builder.write(tmp_path / (name if ros2 else f"{name}.bag")))

    level = bag("level", [("base_link", "laser", (0.1, 0.2, 0.7), 0.0)], -0.5, ranges)
    # upside down: the beam at base-frame angle 0.7 + a is the laser's -a; listed from the smallest angle up
    flipped = bag("flipped", [("base_link", "laser", (0.1, 0.2, 0.7), math.pi)], -0.5, ranges[::-1])
    np.testing.assert_allclose(beam_ends(flipped)[0, ::-1], beam_ends(level)[0], atol=1e-9)
    # a plate mounted upside down at (0.2, 0.1) with no turn, the laser on it at (0.05, 0.03) turned 0.3 rad
    # (in the plate's frame) and level on it: in the base frame at (0.25, 0.07), facing -0.3, upside down
    plate = bag(
        "plate",
        [("base_link", "plate", (0.2, 0.1, 0.0), math.pi), ("plate", "laser", (0.05, 0.03, 0.3), 0.0)],
        -0.5,
        ranges,
    )
    np.testing.assert_allclose(plate.sensor_offset[0], [0.25, 0.07, -0.3], atol=1e-12)
    assert (plate.angle_min[0], plate.angle_increment[0]) == pytest.approx((0.5, -0.25))
    with pytest.raises(LogFormatError, match="tilts the laser's scan plane more than 30 deg"):
        builder = BagBuilder(ros2)
        builder.tf(0.0, "base_link", "laser", 0.1, 0.2, 0.7, topic="/tf_static", pitch=math.radians(60))
        builder.odom(0.0, 1.0, 2.0, 0.4)
        builder.odom(1.0, 1.5, 2.5, 0.9)
        builder.scan(0.5, ranges)
        read_rosbag(builder.write(tmp_path / ("tilted" if ros2 else "tilted.bag")))


def test_a_quaternion_not_of_unit_norm_reads_its_yaw():
    """A quaternion scaled by 0.5 read a yaw of pi/2 as 18.4 deg, by 2 as 126.9 deg (a re-probe)."""
    from types import SimpleNamespace

    from slam.rosbag_reader import quaternion_yaw

    for scale in (0.5, 1.0, 2.0, 1e-3):
        q = SimpleNamespace(w=scale * math.cos(math.pi / 4), x=0.0, y=0.0, z=scale * math.sin(math.pi / 4))
        assert quaternion_yaw(q) == pytest.approx(math.pi / 2, abs=1e-12)
    assert quaternion_yaw(SimpleNamespace(w=0.0, x=0.0, y=0.0, z=0.0)) == 0.0
    # components whose squares overflow or underflow: a yaw of pi/2 all the same
    for scale in (1e200, 1e-200):
        q = SimpleNamespace(w=scale, x=0.0, y=0.0, z=scale)
        assert quaternion_yaw(q) == pytest.approx(math.pi / 2, abs=1e-12)


def test_a_quaternion_that_is_not_finite_is_no_yaw_and_no_level_mount():
    """A NaN or infinite component read as a level mount (a zero norm's identity) before: now NaN, TILTED."""
    from types import SimpleNamespace

    from slam.rosbag_reader import LEVEL, TILTED, UPSIDE_DOWN, quaternion_attitude, quaternion_yaw

    for bad in (math.nan, math.inf, -math.inf):
        for field in "wxyz":
            parts = {"w": 1.0, "x": 0.0, "y": 0.0, "z": 0.0, field: bad}
            q = SimpleNamespace(**parts)
            assert math.isnan(quaternion_yaw(q)), parts
            assert quaternion_attitude(q) == TILTED, parts
    assert quaternion_attitude(SimpleNamespace(w=2.0, x=0.0, y=0.0, z=0.0)) == LEVEL
    assert quaternion_attitude(SimpleNamespace(w=0.0, x=3.0, y=0.0, z=0.0)) == UPSIDE_DOWN  # pi about x
    assert quaternion_attitude(SimpleNamespace(w=1e-200, x=1e-200, y=0.0, z=0.0)) == TILTED  # pi/2 about x


def test_ros1_bag_with_odometry(tmp_path):
    check_standard(read_rosbag(standard_bag().write(tmp_path / "a.bag")))


def test_ros1_bag_with_tf_odometry(tmp_path):
    check_standard(read_rosbag(standard_bag(odometry_on_tf=True).write(tmp_path / "a.bag")))


def test_ros2_bag(tmp_path):
    check_standard(read_rosbag(standard_bag(ros2=True).write(tmp_path / "bag2")))


def test_undecodable_message_is_skipped(tmp_path):
    bag = standard_bag()
    bag.raw(1.7, "/scan", "sensor_msgs/msg/LaserScan", b"\x01\x02\x03")
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert log.where.tolist() == [3, 5, 6, 9]
    bad = {s.where: s.reason for s in log.skipped}
    assert set(bad) == {7, 10} and "does not decode" in bad[7]


def test_scans_the_wire_refuses_are_skipped_by_the_reader(tmp_path):
    """A scan with a negative range, range_min >= range_max or a zero angle increment would stop a replay when the
    source publishes it (the wire's LaserScan refuses it): the reader skips and lists it instead, and every scan it
    keeps encodes."""
    from services.streams import laser_log_stream

    bag = BagBuilder()
    bag.tf(0.0, "base_link", "laser", 0.0, 0.0, 0.0, topic="/tf_static")
    for t in range(6):
        bag.odom(float(t), float(t), 0.0, 0.0)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    bag.scan(1.5, [1.0, -0.5, 3.0])
    bag.scan(2.5, [1.0, 2.0, 3.0], range_max=0.05)  # below the builder's range_min, 0.1 m
    bag.scan(3.5, [1.0, 2.0, 3.0], increment=0.0)
    bag.scan(4.5, [1.0, -np.inf, 3.0])  # -inf: too close to tell (REP 117), skipped like an invalid reading
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    np.testing.assert_allclose(log.stamps, [0.5, 4.5])
    reasons = [s.reason for s in log.skipped]
    assert len(reasons) == 3 and "range 1 is -0.5 m, below 0" in reasons[0]
    assert "need 0 <= range_min < range_max" in reasons[1] and "angle_increment is 0" in reasons[2]
    for step in laser_log_stream(log, "r").steps:
        for message in step.messages:
            message.encode()


def test_invalid_and_too_close_readings_clear_no_free_space(tmp_path):
    """REP 117: NaN is an invalid reading and -inf one too close to measure; neither says the beam went far. They
    become 0, below range_min (raised to 1 mm from a bag's 0), so the fusion skips those beams, as grid FastSLAM
    does; +inf and readings at range_max are no return (free space up to the laser's no-return range)."""
    from mapping.beam_model import BEAM_HIT, BEAM_NO_RETURN, BEAM_SKIP, beam_table
    from mapping.sensor_model import SensorModel

    bag = BagBuilder()
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.odom(1.0, 1.0, 0.0, 0.0)
    bag.scan(0.5, [np.nan, -np.inf, np.inf, 10.0, 2.0], range_min=0.0)
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert log.range_min == 1e-3 and log.ranges[0].tolist() == [0.0, 0.0, np.inf, np.inf, 2.0]
    kinds = beam_table(log.ranges[0], SensorModel(), log.range_min[0], log.range_max[0]).kind
    assert kinds.tolist() == [BEAM_SKIP, BEAM_SKIP, BEAM_NO_RETURN, BEAM_NO_RETURN, BEAM_HIT]


def test_a_scan_stating_an_infinite_range_max_is_read_with_a_kilometre(tmp_path):
    """ROS 2's pointcloud_to_laserscan states range_max +inf by default (its parameter defaults to the largest
    double) and no return as +inf: every such scan was skipped as "non-finite geometry", so a bag of a robot that
    makes its scan from a 3D lidar had no scan to map. Its range_max is now read as 1 km (beyond any laser):
    its finite readings are returns, +inf and readings past 1 km no return."""
    bag = BagBuilder(ros2=True)
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.odom(1.0, 1.0, 0.0, 0.0)
    bag.scan(0.4, [np.inf, 25.0, 2.0], range_max=np.inf, range_min=0.0)
    bag.scan(0.6, [1e6, 40.0, 3.0], range_max=3.4e38)  # FLT_MAX: finite, but no laser's
    log = read_rosbag(bag.write(tmp_path / "a"))
    assert log.skipped == () and log.range_max.tolist() == [1000.0, 1000.0]
    assert log.ranges.tolist() == [[np.inf, 25.0, 2.0], [np.inf, 40.0, 3.0]]


def test_a_laser_frame_not_linked_to_the_odometry_is_an_error_naming_the_bag(tmp_path):
    bag = BagBuilder()
    bag.tf(0.0, "mast", "laser", 0.1, 0.0, 0.0, topic="/tf_static")  # mast -> laser; nothing links mast to base_link
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.odom(1.0, 1.0, 0.0, 0.0)
    bag.scan(0.5, [1.0, 2.0, 3.0])
    path = bag.write(tmp_path / "a.bag")
    with pytest.raises(LogFormatError, match=f"^{path}: no chain of transforms .* links the laser frame 'laser'"):
        read_rosbag(path)


REAR = (0.3, 0.0, math.pi)  # a laser 0.3 m ahead of the base, facing backwards


def moving_robot(bag: BagBuilder, odometry_on_tf: bool = False, child: str = "base_link") -> None:
    """Odometry at t = 0 .. 3 s, 1 m/s along x, and scans at 0.5, 1.5, 2.5 s in frame 'laser'."""
    for t in range(4):
        if odometry_on_tf:
            bag.tf(float(t), "odom", child, float(t), 0.0, 0.0)
        else:
            bag.odom(float(t), float(t), 0.0, 0.0, child=child)
    for t in (0.5, 1.5, 2.5):
        bag.scan(t, [1.0, 2.0, 3.0])


def check_rear_mount(log, notes=()):
    np.testing.assert_allclose(log.odometry, [[0.5, 0.0, 0.0], [1.5, 0.0, 0.0], [2.5, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(np.abs(log.sensor_offset), [np.abs(REAR)] * 3, atol=1e-12)
    assert log.notes == notes


@pytest.mark.parametrize("odometry_on_tf", [False, True])
def test_a_mount_published_fixed_on_tf_is_the_lasers_pose(tmp_path, odometry_on_tf):
    """ROS 1 bags (static_transform_publisher of old) carry the mount on /tf, again and again, with no /tf_static:
    that fixed link is the laser's pose on the robot, whether the odometry comes from a topic or from /tf itself
    (the moving odom -> base_link link; the mount's child is not the robot's base)."""
    bag = BagBuilder()
    moving_robot(bag, odometry_on_tf)
    for t in (0.2, 1.2, 2.2):
        bag.tf(t, "base_link", "laser", *REAR)
    check_rear_mount(read_rosbag(bag.write(tmp_path / "a.bag")))


def test_the_odometry_on_tf_is_the_link_nearest_the_root_below_amcls_map(tmp_path):
    """Odometry only on /tf, with amcl's map -> odom above it and the mount fixed on /tf below it: the base frame is
    odom -> base_link's child, whether the robot moves or stands still (then every link is fixed)."""
    for moving in (True, False):
        bag = BagBuilder()
        for t in range(4):
            bag.tf(float(t), "map", "odom", 1.0, 2.0, 0.3)
            bag.tf(float(t), "odom", "base_link", float(t) if moving else 5.0, 0.0, 0.0)
        for t in (0.2, 1.2, 2.2):
            bag.tf(t, "base_link", "laser", *REAR)
        for t in (0.5, 1.5, 2.5):
            bag.scan(t, [1.0, 2.0, 3.0])
        log = read_rosbag(bag.write(tmp_path / f"{moving}.bag"))
        np.testing.assert_allclose(np.abs(log.sensor_offset), [np.abs(REAR)] * 3, atol=1e-12)
        expected = [0.5, 1.5, 2.5] if moving else [5.0] * 3
        np.testing.assert_allclose(log.odometry[:, 0], expected, atol=1e-12)


def test_a_mount_that_wobbles_on_tf_is_refused_even_when_the_robot_stands_still(tmp_path):
    for moving in (True, False):
        bag = BagBuilder()
        for t in range(4):
            bag.tf(float(t), "odom", "base_link", float(t) if moving else 0.0, 0.0, 0.0)
        for i, t in enumerate((0.2, 1.2, 2.2)):
            bag.tf(t, "base_link", "laser", 0.3 + 1e-3 * i, 0.0, 0.0)
        bag.scan(0.5, [1.0, 2.0, 3.0])
        path = bag.write(tmp_path / f"{moving}.bag")
        with pytest.raises(LogFormatError, match=r"from 'base_link' to 'laser' on /tf, .* moves during the bag"):
            read_rosbag(path)


def test_a_laser_frame_no_transform_names_with_odometry_on_tf_is_taken_at_the_base(tmp_path):
    bag = BagBuilder()
    moving_robot(bag, odometry_on_tf=True)
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert log.sensor_offset.tolist() == [[0.0, 0.0, 0.0]] * 3 and len(log.notes) == 1
    np.testing.assert_allclose(log.odometry[:, 0], [0.5, 1.5, 2.5])


def test_transforms_in_a_cycle_are_refused_as_one(tmp_path):
    bag = BagBuilder()
    bag.tf(0.0, "base_link", "laser", 0.1, 0.0, 0.0, topic="/tf_static")
    bag.tf(0.0, "laser", "plate", 0.1, 0.0, 0.0, topic="/tf_static")
    bag.tf(0.0, "plate", "base_link", 0.1, 0.0, 0.0, topic="/tf_static")
    moving_robot(bag)
    with pytest.raises(LogFormatError, match="the transforms form a cycle through the frame"):
        read_rosbag(bag.write(tmp_path / "a.bag"))


def test_frame_names_with_ros1s_leading_slash_are_tf2s_names(tmp_path):
    bag = BagBuilder()
    bag.tf(0.0, "/base_link", "laser", *REAR, topic="/tf_static")
    for t in range(4):
        bag.odom(float(t), float(t), 0.0, 0.0, child="/base_link")
    for t in (0.5, 1.5, 2.5):
        bag.scan(t, [1.0, 2.0, 3.0], frame="/laser")
    check_rear_mount(read_rosbag(bag.write(tmp_path / "a.bag")))


def test_odometry_with_no_child_frame_takes_the_root_of_the_lasers_chain(tmp_path):
    """An Odometry topic with an empty child frame: the base is the laser's chain's frame below its first link that
    moves (odom -> base_link, recorded on /tf as well), else its root; a pan unit elsewhere on /tf, moving, is not
    taken for the odometry."""
    for odometry_on_tf in (False, True):
        bag = BagBuilder()
        bag.tf(0.0, "base_link", "laser", *REAR, topic="/tf_static")
        moving_robot(bag, child="")
        for i, t in enumerate((0.2, 1.2, 2.2)):
            bag.tf(t, "base_link", "camera", 0.1, 0.0, 0.2 * i)
            if odometry_on_tf:
                bag.tf(t, "odom", "base_link", t, 0.0, 0.0)
        check_rear_mount(read_rosbag(bag.write(tmp_path / f"{odometry_on_tf}.bag")))


def test_a_laser_on_a_moving_joint_is_refused(tmp_path):
    bag = BagBuilder()
    moving_robot(bag)
    for i, t in enumerate((0.2, 1.2, 2.2)):
        bag.tf(t, "base_link", "laser", 0.3, 0.0, 0.1 * i)  # a pan unit
    path = bag.write(tmp_path / "a.bag")
    with pytest.raises(LogFormatError, match=r"from 'base_link' to 'laser' on /tf, .* moves during the bag"):
        read_rosbag(path)


def test_a_laser_frame_no_transform_names_is_taken_at_the_base_and_noted(tmp_path):
    bag = BagBuilder()
    moving_robot(bag)
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert log.sensor_offset.tolist() == [[0.0, 0.0, 0.0]] * 3
    (note,) = log.notes
    assert "no transform names the laser frame 'laser'" in note and "'base_link'" in note
    assert log.remarks() == [f"{log.source}: {note}"]


@pytest.mark.parametrize("name", ["a.BAG", "a", "a.bag.active"])
def test_a_bag_file_not_named_dot_bag_is_refused_with_what_to_do(tmp_path, name):
    path = standard_bag().write(tmp_path / "a.bag").rename(tmp_path / name)
    with pytest.raises(LogFormatError, match=r"not named as a bag: .*rename or link it"):
        read_rosbag(path)


def test_a_ros2_storage_file_alone_is_read(tmp_path):
    folder = standard_bag(ros2=True).write(tmp_path / "bag2")
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    check_standard(read_rosbag(storage))


def test_the_commands_read_a_ros2_storage_file_or_metadata_yaml_as_the_bag(tmp_path):
    """`posegrid slam`, `eval-relations` and the replay read a log through read_log: a ROS 2 storage file (.db3,
    .mcap) or the bag's metadata.yaml given alone is the bag, not a CARMEN log without laser lines."""
    from services.commands.logs import read_log

    folder = standard_bag(ros2=True).write(tmp_path / "bag2")
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    check_standard(read_log(storage))
    check_standard(read_log(folder / "metadata.yaml"))


def test_a_bag_whose_scans_are_all_refused_says_why(tmp_path):
    bag = BagBuilder()
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.odom(1.0, 1.0, 0.0, 0.0)
    bag.scan(0.5, [1.0, -2.0, 3.0])
    with pytest.raises(LogFormatError, match="no usable scan on /scan \\(the first: /scan: range 1 is -2 m, below 0"):
        read_rosbag(bag.write(tmp_path / "a.bag"))


def test_every_scan_keeps_its_own_geometry_jittered_or_not(tmp_path):
    """Scans whose increments differ by a float32 ulp, and scans of another beam count, are all read, each with the
    geometry its message gives."""
    bag = BagBuilder()
    for t in range(20):
        bag.odom(float(t), float(t), 0.0, 0.0)
    half = np.float32(0.5)
    increments = [0.5, float(np.nextafter(half, np.float32(1))), float(np.nextafter(half, np.float32(0)))]
    for i in range(12):
        bag.scan(0.5 + i, [1.0, 2.0, 3.0], increment=increments[i % 3])
    for i in range(5):
        bag.scan(13.5 + i, [1.0, 2.0])
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert len(log) == 17 and log.ranges.shape[1] == 3 and log.skipped == ()
    assert log.beams.tolist() == [3] * 12 + [2] * 5
    expected = [float(np.float32(increments[i % 3])) for i in range(12)] + [0.5] * 5
    assert log.angle_increment.tolist() == expected


def test_an_odd_first_scan_is_read_with_its_own_beam_count(tmp_path):
    """A first scan of 2 beams among scans of 3 is read, and so are the others."""
    bag = standard_bag()
    bag.scan(0.2, [1.0, 2.0])
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    assert len(log) == 5 and log.beams.tolist() == [2, 3, 3, 2, 3]
    assert not [s for s in log.skipped if "beams" in s.reason]


def test_odometry_gap_limit(tmp_path):
    bag = BagBuilder()
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.odom(6.0, 6.0, 0.0, 0.0)
    bag.scan(3.0, [1.0, 1.0, 1.0])
    path = bag.write(tmp_path / "a.bag")
    with pytest.raises(LogFormatError, match="6 s apart"):
        read_rosbag(path)
    log = read_rosbag(path, max_odom_gap=7.0)
    np.testing.assert_allclose(log.odometry, [[3.0, 0.0, 0.0]])
    # no /tf_static: the laser frame is the base frame
    assert np.all(log.sensor_offset == 0)


def test_topic_choice_and_unusable_bags(tmp_path):
    bag = BagBuilder()
    bag.odom(0.0, 0.0, 0.0, 0.0)
    bag.scan(0.0, [1.0, 2.0, 3.0], topic="/front")
    bag.scan(0.0, [5.0, 6.0, 7.0], topic="/rear")
    path = bag.write(tmp_path / "two.bag")
    with pytest.raises(LogFormatError, match="several LaserScan topics"):
        read_rosbag(path)
    np.testing.assert_array_equal(read_rosbag(path, scan_topic="/rear").ranges[0], [5.0, 6.0, 7.0])
    with pytest.raises(LogFormatError, match="no sensor_msgs/msg/LaserScan topic '/nope'"):
        read_rosbag(path, scan_topic="/nope")
    only_odom = BagBuilder()
    only_odom.odom(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(LogFormatError, match="no sensor_msgs/LaserScan"):
        read_rosbag(only_odom.write(tmp_path / "odom.bag"))
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(500))
    with pytest.raises(LogFormatError, match="not a readable ROS bag"):
        read_rosbag(tmp_path / "junk.bag")
    with pytest.raises(LogFormatError, match="no such file"):
        read_rosbag(tmp_path / "missing.bag")


def test_real_mit_csail_bag_matches_the_clf():
    bag = read_rosbag(shared_file("mit-csail", "mit-csail.orig.bag"))
    clf = read_carmen(shared_file("mit-csail", "mit-csail.clf"))
    assert len(bag) == len(clf) == 1988 and bag.skipped == ()
    np.testing.assert_allclose(bag.stamps, clf.stamps, atol=1e-5)
    np.testing.assert_allclose(bag.odometry, clf.odometry, atol=1e-9)
    np.testing.assert_array_equal(bag.ranges, clf.ranges)
    assert bag.angle_increment == pytest.approx(clf.angle_increment, rel=1e-6)


@pytest.mark.parametrize(
    "name,scans,beams,offset",
    [
        ("fr079/fr079.orig.bag", 4934, 360, 0.04),
    ],
)
def test_real_bag(name, scans, beams, offset):
    log = read_rosbag(shared_file(name))
    assert log.ranges.shape == (scans, beams) and log.skipped == ()
    assert log.sensor_offset[:, 0] == pytest.approx(offset)
    assert np.all(np.diff(log.stamps) > 0)


def test_bag_that_breaks_off_midway_keeps_what_came_before(tmp_path):
    bag = BagBuilder()
    for k in range(200):
        bag.odom(0.5 * k, 0.01 * k, 0.0, 0.0)
        bag.scan(0.25 + 0.5 * k, [1.0, 2.0, 3.0] if k != 100 else [7.5, 8.5, 9.5])
    path = bag.write(tmp_path / "a.bag")
    blob = bytearray(path.read_bytes())
    at = blob.find(np.array([7.5, 8.5, 9.5], np.float32).tobytes())
    assert at > 0
    # the record of scan 100: garble the lengths before its ranges so the chunk cannot be parsed on
    blob[at - 120 : at - 4] = b"\xff" * 116
    broken = tmp_path / "broken.bag"
    broken.write_bytes(bytes(blob))
    try:
        log = read_rosbag(broken)
    except LogFormatError as exc:  # the garbling may also hit what the reader needs up front: one sentence
        assert str(broken) in str(exc)
        return
    assert 0 < len(log) < 200
    assert "breaks off" in log.skipped[-1].reason or any("decode" in s.reason for s in log.skipped)
    # what was read is whole: stamps on the 0.5 s grid from the first scan, odometry interpolated halfway
    np.testing.assert_allclose(log.stamps[0], 0.25)
    np.testing.assert_allclose((log.stamps - 0.25) / 0.5 % 1.0, 0.0, atol=1e-6)
    np.testing.assert_allclose(log.odometry[:, 0], 0.02 * log.stamps, atol=1e-6)


def test_odometry_and_transforms_beyond_the_pose_limit_are_skipped(tmp_path):
    # a pose of 1e300 m is finite but would overflow the filters' maps and covariances (schemas.messages.POSE_LIMIT)
    bag = standard_bag()
    bag.odom(1.2, 1e300, 0.0, 0.0)  # message 5, between the odometry at 1.0 and the scan at 1.5
    bag.tf(1.8, "base_link", "laser", 2e7, 0.0, 0.0, topic="/tf_static")  # message 8
    log = read_rosbag(bag.write(tmp_path / "a.bag"))
    reasons = {s.where: s.reason for s in log.skipped}
    assert "beyond +-1e+07 m" in reasons[5] and "beyond +-1e+07 m" in reasons[8]
    assert np.abs(log.odometry[:, :2]).max() <= 2.0
    np.testing.assert_allclose(log.sensor_offset, [[0.1, 0.0, math.pi / 2]] * len(log), atol=1e-12)


def test_run_leaves_the_logs_notes_to_its_source_which_says_them_once(tmp_path, capsys):
    """`posegrid run --bag` reads the log to check it before it starts anything, and its source child reads it again:
    only the source says what the reader took for granted (run said each note a second time)."""
    import argparse

    from services.commands.pipeline import _laser_log

    bag = BagBuilder()
    moving_robot(bag)  # a laser frame no transform names: a note
    args = argparse.Namespace(
        carmen=None, bag=bag.write(tmp_path / "a.bag"), scan_topic=None, odom_delay=0.0, no_return_range=None
    )
    _laser_log(args, None)
    assert capsys.readouterr().err == ""
    _laser_log(args, "source")
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and said[0].startswith("posegrid source: note: ") and "no transform names" in said[0]
