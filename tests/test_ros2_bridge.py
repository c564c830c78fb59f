"""`posegrid ros2` and `posegrid ros2 play` as real processes on loopback Zenoh (ports picked free, every process
ended by PID in the procs fixture's finalizer):

- a ROS 2 bag played onto rmw_zenoh keys (or zenoh-bridge-ros2dds keys) reaches posegrid as the very messages the bag
  reader gives (`posegrid source --bag` sends), bit for bit;
- the map and the poses go out as ROS messages that rosbags' CDR deserializer decodes, cell for cell and pose for
  pose what posegrid published, with rmw_zenoh's attachment and liveliness tokens; a subscriber that joins late gets
  the latest map;
- garbage on every subscribed key is counted per topic and kind, and the bridge goes on;
- scans no pose came for are said at the bridge's exit;
- `posegrid run --ros2` fed a replayed bag builds the map `posegrid run --bag` builds from it.
"""

from __future__ import annotations

import json
import math
import queue
import signal
import time
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
import zenoh.ext

from bags import BagBuilder
from peers import put
from schemas.messages import PoseSamples, TileUpdate, decode_message
from services import keys
from services.ports import free_port
from services.ros2 import names
from services.ros2 import types as rt
from services.streams import laser_log_stream
from services.zenoh_config import build_config
from slam.rosbag_reader import read_rosbag
from test_pipeline import CLI, grid_filter_in_process, procs  # noqa: F401 - procs is a fixture

pytestmark = pytest.mark.slow

NAMESPACE = "/robot1"

BLOCK = zenoh.CongestionControl.BLOCK


def small_bag(path: Path, scan_stamps=(0.5, 1.5, 2.3)) -> Path:
    """A ROS 2 bag: the laser's mount on /tf_static, odometry at 0, 1, 2 s (the yaw crosses pi between the last
    two), scans at ``scan_stamps`` (the last one past the odometry, its pose held)."""
    bag = BagBuilder(ros2=True)
    bag.tf(0.0, "base_link", "laser", 0.1, 0.0, math.pi / 2, topic="/tf_static")
    for stamp, x, y, yaw in [(0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, math.pi / 2), (2.0, 1.0, 2.0, -3.0)]:
        bag.odom(stamp, x, y, yaw)
    for stamp in scan_stamps:
        bag.scan(stamp, [1.0, 12.0, np.nan])
    return bag.write(path)


@pytest.fixture
def router(procs):  # noqa: F811
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    return endpoint


@pytest.fixture
def session(router):
    opened = zenoh.open(build_config("client", connect=[router]))
    yield opened
    opened.close()


def start_bridge(procs, router: str, *options: str):  # noqa: F811
    bridge = procs([*CLI, "ros2", "--robot", "r1", "--namespace", NAMESPACE, "--connect", router, *options])
    bridge.wait_for(r"up \(")
    return bridge


def play(procs, router: str, bag: Path, *options: str) -> None:  # noqa: F811
    player = procs(
        [*CLI, "ros2", "play", str(bag), "--namespace", NAMESPACE, "--connect", router, "--wait", "30", *options]
    )
    assert player.process.wait(60) == 0, player.output()


def bridge_stats(session) -> dict:
    for reply in session.get(keys.ros2_stats_key("r1"), timeout=5.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    raise AssertionError("the bridge did not answer its stats query")


def wait_until(check, timeout: float = 30.0, what: str = "the condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def collect(session, key: str) -> queue.Queue:
    received: queue.Queue = queue.Queue()
    session.declare_subscriber(key, lambda s: received.put((str(s.key_expr), s.payload.to_bytes())))
    return received


@pytest.mark.parametrize("mode", ["rmw_zenoh", "bridge"])
def test_a_played_bag_reaches_posegrid_as_the_bag_readers_messages(tmp_path, procs, router, session, mode):  # noqa: F811
    bag = small_bag(tmp_path / "bag")
    received = collect(session, "pg/r1/*")
    start_bridge(procs, router, "--mode", mode)
    play(procs, router, bag, "--mode", mode, "--rate", "max")
    stream = laser_log_stream(read_rosbag(bag), "r1")
    expected = [("pg/r1/prior", stream.prior)] + [
        (f"pg/r1/{'scan' if type(m).__name__ == 'LaserScan' else 'odom'}", m)
        for step in stream.steps
        for m in step.messages
        if type(m).__name__ in ("LaserScan", "Odometry")
    ]
    got = [received.get(timeout=30) for _ in expected]
    assert [key for key, _ in got] == [key for key, _ in expected]
    assert [decode_message(payload).digest() for _, payload in got] == [m.digest() for _, m in expected]
    stats = bridge_stats(session)
    assert stats["rejected"] == {} and stats["scans"] == 3
    tokens = {str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=5.0)}
    if mode == "rmw_zenoh":  # the node and its topics show in the ROS graph
        scan_hash = rt.MessageType(rt.LASER_SCAN).type_hash
        assert any(t.endswith("/NN/%/%robot1/posegrid") for t in tokens)
        assert any(
            f"/MS/%/%robot1/posegrid/%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/{scan_hash}/2::,5:" in t
            for t in tokens
        )
        assert any("/MP/%/%robot1/posegrid/%robot1%map/nav_msgs::msg::dds_::OccupancyGrid_/" in t for t in tokens)
    else:
        routes = {str(r.ok.key_expr) for r in session.liveliness().get("@/*/@ros2_lv/**", timeout=5.0)}
        assert not tokens and any(
            t.endswith("/@ros2_lv/MP/robot1§map/nav_msgs§msg§OccupancyGrid/:1:1:0,1") for t in routes
        )


#: TileUpdate's fields that of_window makes of a window's layers
CELL_FIELDS = ("logodds", "variance", "observed", "logodds_cells", "variance_cells")


def _tiles(stamp_seq: int) -> list[TileUpdate]:
    """Four whole 256-cell tiles around the origin: a 512 x 512 grid, 262 kB, larger than Zenoh's 64 kB batch."""
    rng = np.random.default_rng(9)
    tiles = []
    for tx, ty in ((-1, -1), (0, -1), (-1, 0), (0, 0)):
        tiles.append(
            TileUpdate.of_window(
                (
                    rng.normal(0, 3, (256, 256)).astype(np.float32),
                    rng.uniform(0, 1.5, (256, 256)).astype(np.float32),
                    rng.uniform(size=(256, 256)) < 0.7,
                ),
                map="main",
                shard=0,
                z=0,
                tx=tx,
                ty=ty,
                tile_size=256,
                resolution=0.05,
                row0=0,
                col0=0,
                robot="r1",
                seq=stamp_seq,
                published=time.time(),
            )
        )
    return tiles


def _expected_grid(tiles: list[TileUpdate], layer: str) -> np.ndarray:
    """The OccupancyGrid values of the four tiles, computed here: row = y from tile row -1, column = x from -1."""
    grid = np.full((512, 512), -1, np.int16)
    for tile in tiles:
        rows = slice((tile.ty + 1) * 256, (tile.ty + 2) * 256)
        cols = slice((tile.tx + 1) * 256, (tile.tx + 2) * 256)
        logodds, variance, observed = tile.whole_layers()
        if layer == "occupancy":
            values = np.rint(100.0 / (1.0 + np.exp(-logodds.astype(np.float64))))
        else:
            values = np.rint(np.clip(100.0 * variance.astype(np.float64), 0, 100))
        grid[rows, cols] = np.where(observed, values, -1)
    return grid.astype(np.int8).ravel()


def _ros_subscriber(session, key: str, late: bool = False) -> queue.Queue:
    """Samples on an rmw_zenoh key, as a ROS subscriber takes them (TRANSIENT_LOCAL: an advanced subscriber that
    queries the publishers' caches)."""
    received: queue.Queue = queue.Queue()

    def take(sample):
        received.put((sample.payload.to_bytes(), None if sample.attachment is None else sample.attachment.to_bytes()))

    if late:
        subscriber = zenoh.ext.declare_advanced_subscriber(
            session, key, take, history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1)
        )
    else:
        subscriber = session.declare_subscriber(key, take)
    received.subscriber = subscriber  # (kept as long as the queue is)
    return received


def _key(topic: str, type_name: str) -> str:
    return f"0{NAMESPACE}/{topic}/{rt.MessageType(type_name).dds_name}/{rt.MessageType(type_name).type_hash}"


def test_the_map_and_poses_go_out_as_ros_messages_cell_for_cell(tmp_path, procs, router, session):  # noqa: F811
    start_bridge(procs, router, "--map-period", "0.2", "--variance-scale", "1.0")
    play(procs, router, small_bag(tmp_path / "bag", scan_stamps=(1.25,)))  # seq 0, stamped 1.25 s
    wait_until(lambda: bridge_stats(session)["scans"] == 1, what="the played scan")
    subscribers = {
        name: _ros_subscriber(session, _key(topic, type_name))
        for name, topic, type_name in (
            ("map", "map", rt.OCCUPANCY_GRID),
            ("variance", "map_variance", rt.OCCUPANCY_GRID),
            ("updates", "map_updates", rt.GRID_UPDATE),
            ("cloud", "particle_cloud", rt.POSE_ARRAY),
            ("pose", "pose", rt.POSE_COVARIANCE),
        )
    }
    tiles = _tiles(0)
    for tile in tiles:
        # (a tile is 590 kB: BLOCK, as the shards send them; the default DROP may lose it on a loaded machine)
        session.put(f"pg/map/main/tile/0/{tile.tx}/{tile.ty}", tile.encode(), congestion_control=BLOCK)
    grid_type = rt.MessageType(rt.OCCUPANCY_GRID)
    expected = _expected_grid(tiles, "occupancy")
    while True:  # (the whole grid goes out as the tiles come, at most every 0.2 s: the first may hold fewer)
        payload, attachment = subscribers["map"].get(timeout=30)
        grid = grid_type.decode(payload)
        if (grid.info.width, grid.info.height) == (512, 512) and (grid.data != -1).sum() == (expected != -1).sum():
            break
    assert len(payload) > 262_144
    assert (grid.info.origin.position.x, grid.info.origin.position.y, grid.info.resolution) == pytest.approx(
        (-12.8, -12.8, 0.05)
    )
    assert (grid.header.frame_id, grid.header.stamp.sec, grid.header.stamp.nanosec) == ("map", 1, 250_000_000)
    np.testing.assert_array_equal(grid.data, expected)
    variance = grid_type.decode(subscribers["variance"].get(timeout=30)[0])
    while (variance.data != -1).sum() != (expected != -1).sum():
        variance = grid_type.decode(subscribers["variance"].get(timeout=30)[0])
    np.testing.assert_array_equal(variance.data, _expected_grid(tiles, "variance"))
    tokens = {str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**", timeout=5.0)}
    map_token = next(t for t in tokens if "/MP/%/%robot1/posegrid/%robot1%map/" in t)
    assert map_token.endswith(f"{grid_type.type_hash}/:1:,1:,:,:,,")
    first = names.decode_attachment(attachment)
    assert (
        first is not None
        and first.gid == names.gid_of(map_token)
        and abs(first.source_timestamp / 1e9 - time.time()) < 600
    )

    window = TileUpdate.of_window(
        (np.full((3, 5), 4.0, np.float32), np.zeros((3, 5), np.float32), np.ones((3, 5), bool)),
        **{
            **{k: v for k, v in vars(tiles[3]).items() if k not in ("rows", "cols", "given", *CELL_FIELDS)},
            "row0": 10,
            "col0": 20,
        },
    )
    session.put("pg/map/main/tile/0/0/0", window.encode(), congestion_control=BLOCK)
    update_type = rt.MessageType(rt.GRID_UPDATE)
    update = update_type.decode(subscribers["updates"].get(timeout=30)[0])
    while update.width == 256:  # (the whole tile (0, 0), sent as an update once the grid held it)
        update = update_type.decode(subscribers["updates"].get(timeout=30)[0])
    assert (update.x, update.y, update.width, update.height) == (256 + 20, 256 + 10, 5, 3)
    np.testing.assert_array_equal(update.data, np.full(15, round(100 / (1 + math.exp(-4.0))), np.int8))
    later = names.decode_attachment(subscribers["map"].get(timeout=30)[1])  # the whole grid again, throttled
    assert later is not None and later.sequence_number == first.sequence_number + 1

    samples = PoseSamples(
        robot="r1",
        seq=0,
        stamp=1.25,
        samples=np.array([[1.0, 2.0, 3.1], [1.2, 2.2, -3.1]]),
        weights=np.array([0.25, 0.75]),
    )
    # a pose of a seq the bridge sent no scan of (a probe's flood of such 10 000-sample poses held the map updates
    # 45 s, each made into ROS messages): counted, not sent on
    put(session, "pg/r1/pose", replace(samples, seq=10**9, samples=samples.samples + 50.0).encode())
    wait_until(lambda: bridge_stats(session)["rejected_kinds"].get("ahead") == 1, what="the forged pose counted")
    put(session, "pg/r1/pose", samples.encode())
    cloud = rt.MessageType(rt.POSE_ARRAY).decode(subscribers["cloud"].get(timeout=30)[0])
    got = [
        (p.position.x, p.position.y, math.atan2(2 * p.orientation.w * p.orientation.z, 1 - 2 * p.orientation.z**2))
        for p in cloud.poses
    ]
    np.testing.assert_allclose(got, samples.samples, atol=1e-12)
    pose = rt.MessageType(rt.POSE_COVARIANCE).decode(subscribers["pose"].get(timeout=30)[0])
    assert (pose.pose.pose.position.x, pose.pose.pose.position.y) == pytest.approx((1.15, 2.15))
    yaw = math.atan2(
        2 * pose.pose.pose.orientation.w * pose.pose.pose.orientation.z, 1 - 2 * pose.pose.pose.orientation.z**2
    )
    assert abs((yaw - math.pi + math.pi) % (2 * math.pi) - math.pi) < 0.1  # circular mean of 3.1 and -3.1: near pi
    assert pose.pose.covariance.reshape(6, 6)[0, 0] == pytest.approx(0.25 * 0.75**2 * 0.04 + 0.75 * 0.25**2 * 0.04)

    joiner = zenoh.open(build_config("client", connect=[router]))
    try:
        late = _ros_subscriber(joiner, _key("map", rt.OCCUPANCY_GRID), late=True)
        latest = grid_type.decode(late.get(timeout=10)[0])  # a subscriber that joins late gets the latest map at once
    finally:
        joiner.close()
    assert latest.data.reshape(512, 512)[256 + 10, 256 + 20] == round(100 / (1 + math.exp(-4.0)))


def test_garbage_on_every_subscribed_key_is_counted_and_the_bridge_goes_on(tmp_path, procs, router, session):  # noqa: F811
    bridge = start_bridge(procs, router, "--odom-wait", "0.5")
    attachment = names.encode_attachment(names.Attachment(1, time.time_ns(), bytes(16)))
    scan_key = _key("scan", rt.LASER_SCAN)
    garbage = [
        (scan_key, b"\x00\x01\x00\x00not a scan", attachment),
        (f"0{NAMESPACE}/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_{'0' * 64}", b"\x00\x01\x00\x00", attachment),
        (_key("odom", rt.ODOMETRY), b"\xff" * 7, attachment),
        (_key("tf", rt.TF_MESSAGE), b"", attachment),
        (_key("tf_static", rt.TF_MESSAGE), b"\x00\x01\x00\x00\xff\xff\xff\x7f", attachment),
    ]
    builder = BagBuilder(ros2=True)
    builder.scan(1.0, [1.0, 2.0], increment=math.nan)  # NaN geometry
    builder.scan(1.0, [1.0, 2.0], frame="nowhere")  # no transform places it
    builder.scan(1.0, [1.0, 2.0], frame="base_link")  # a good scan (the laser at the base), but no attachment
    builder.odom(1.0, 0.0, 0.0, 0.0)
    scan_type = rt.MessageType(rt.LASER_SCAN)
    nan_scan, lost_scan, good_scan = (scan_type.encode(item[3]) for item in builder.items[:3])
    garbage += [(scan_key, nan_scan, attachment), (scan_key, lost_scan, attachment), (scan_key, good_scan, None)]
    garbage += [("pg/map/main/tile/0/0/0", b"\xc1", None), ("pg/r1/pose", b"not msgpack", None)]
    forged = msgpack.unpackb(_tiles(0)[0].encode())  # well-formed tiles of sizes and places no grid could hold
    for change in ({"tile_size": 2**20}, {"tile_size": 3}, {"tx": 2**63 + 1}, {"resolution": 1e300}):
        payload = msgpack.packb({**forged, **change}, use_bin_type=True)
        garbage.append(("pg/map/main/tile/0/0/0", payload, None))
    # a put before the router has learnt the bridge's subscriptions is lost (a loaded machine): wait for a match
    keys = {_key("odom", rt.ODOMETRY)} | {key for key, _, _ in garbage if not key.startswith("pg/")}
    for key in keys:
        publisher = session.declare_publisher(key)
        wait_until(lambda p=publisher: p.matching_status.matching, what=f"the bridge to subscribe to {key}")
        publisher.undeclare()
    put(
        session,
        _key("odom", rt.ODOMETRY),
        rt.MessageType(rt.ODOMETRY).encode(builder.items[3][3]),
        attachment=attachment,
    )
    for key, payload, attached in garbage:
        put(session, key, payload, attachment=attached)
    expected_kinds = {"cdr": 4, "type": 1, "attachment": 1, "geometry": 1, "transform": 1, "malformed": 2, "range": 4}
    stats = wait_until(
        lambda: (s := bridge_stats(session))["rejected_kinds"] == expected_kinds and s, what="every garbage counted"
    )
    assert stats["rejected"] == {
        f"{NAMESPACE}/scan": 5,
        f"{NAMESPACE}/odom": 1,
        f"{NAMESPACE}/tf": 1,
        f"{NAMESPACE}/tf_static": 1,
        "pg/map/main/tile/0/0/0": 5,
        "pg/r1/pose": 1,
    }
    assert bridge.process.poll() is None and stats["scans"] == 0
    put(session, scan_key, good_scan, attachment=attachment)  # a good scan still goes through
    wait_until(lambda: bridge_stats(session)["scans"] == 1, what="the good scan")
    logged = [line for line in bridge.lines if "further ones of this kind are only counted" in line]
    assert len(logged) == 11  # once per topic and kind
    for i in range(1, 41):  # tiles on keys of their own: counted under the subscription, not a counter a key
        put(session, f"pg/map/main/tile/0/{i}/{7 * i}", b"\xc1")
    stats = wait_until(
        lambda: (s := bridge_stats(session))["rejected_kinds"]["malformed"] == 42 and s, what="40 more tiles counted"
    )
    assert {key: n for key, n in stats["received"].items() if "/tile/" in key} == {"pg/map/main/tile/0/*/*": 45}


def test_scans_no_pose_came_for_are_said_at_the_bridges_exit(procs, router, session):  # noqa: F811
    """With the robot's own poses, a scan no pose comes for within --odom-wait s is dropped, not refused: the exit
    line says so instead of "none refused" alone."""
    bridge = start_bridge(procs, router, "--pose-topic", "amcl_pose", "--odom-wait", "0.3")
    builder = BagBuilder(ros2=True)
    builder.scan(1.0, [1.0, 2.0], frame="base_link")
    scan = rt.MessageType(rt.LASER_SCAN).encode(builder.items[0][3])
    publisher = session.declare_publisher(_key("scan", rt.LASER_SCAN))
    wait_until(lambda: publisher.matching_status.matching, what="the bridge to subscribe to the scans")
    attachment = names.encode_attachment(names.Attachment(1, time.time_ns(), bytes(16)))
    publisher.put(scan, attachment=attachment)
    stats = wait_until(lambda: (s := bridge_stats(session))["unposed"] == 1 and s, what="the scan dropped")
    assert stats["rejected"] == {} and stats["scans"] == 0
    bridge.process.send_signal(signal.SIGINT)
    assert bridge.process.wait(20) == 0
    bridge.wait_for(r"stopped after 0 scans; none refused; 1 scan\(s\) dropped with no pose within --odom-wait s")


def test_run_ros2_gives_the_map_run_bag_gives(tmp_path, procs):  # noqa: F811
    """The simulated office as a ROS 2 bag, replayed through `posegrid run --ros2` (bridge, grid FastSLAM node,
    shard): the map equals the one the same filter and fusion give in this process from the bag reader's stream,
    which is the map `posegrid run --bag` gives (tests/test_pipeline.py)."""
    from services.fusion_runner import fuse_posed_scans
    from services.map_client import MapReader
    from slam.simulator import simulate_office

    sim = simulate_office(seed=4, steps=40, n_beams=91, range_max=8.0)
    builder = BagBuilder(ros2=True)
    builder.tf(0.0, "base_link", "laser", *sim.sensor_offset, topic="/tf_static")
    for stamp, ranges, (x, y, yaw) in zip(sim.stamps, sim.ranges, sim.true_poses):
        builder.odom(stamp, x, y, yaw)
        builder.scan(stamp, ranges, angle_min=sim.angle_min, increment=sim.angle_increment, range_max=sim.range_max)
    bag = builder.write(tmp_path / "office")
    stream = laser_log_stream(read_rosbag(bag), "robot0")
    posed = grid_filter_in_process(stream, particles=5, seed=7)
    expected = fuse_posed_scans(posed).rasterize()

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    run = procs(
        [
            *CLI,
            "run",
            "--ros2",
            "--namespace",
            NAMESPACE,
            "--router-port",
            str(port),
            "--no-api",
            "--particles",
            "5",
            "--particle-cap",
            "5",
            "--seed",
            "7",
            "--resample-threshold",
            "0.5",
        ]
    )
    run.wait_for(r"running: .*ros2 \(pid", timeout=120)
    play(procs, endpoint, bag, "--rate", "max")
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        reader = MapReader(session, "main")
        try:  # a fresh clone on a busy machine compiles the filter's and the shard's kernels first: minutes
            wait_until(
                lambda: (s := reader.stats(timeout=2.0)) and s[0].fused.get("robot0", 0) == len(posed.stamps),
                timeout=300,
                what=f"{len(posed.stamps)} scans fused",
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}; stats {reader.stats(timeout=2.0)}; output:\n{run.output()[-4000:]}") from None
        got = reader.assemble(1, 0.05).rasterize()
    finally:
        session.close()
    np.testing.assert_array_equal(got["observed"], expected["observed"])
    np.testing.assert_array_equal(got["origin"], expected["origin"])
    np.testing.assert_allclose(got["logodds"], expected["logodds"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got["variance"], expected["variance"], rtol=1e-6, atol=1e-6)
    # a live robot has no replay to end: its stop said "stopped before the replay ended (40 of None scans ...)"
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(60) == 0, run.output()[-4000:]
    stopped = run.wait_for(r"posegrid run: stopped after (\d+) scans fused by every shard")
    assert int(stopped.group(1)) <= len(posed.stamps) and "None" not in run.output()
