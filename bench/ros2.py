"""Figures of the ROS 2 bridge (issue 33, docs/ros2.md) on the simulated office as a ROS 2 bag: 361 beams over
180 degrees, 12 m range, the robot's noisy odometry on /odom and the laser's mount on /tf_static.

- bridge_ms_per_scan: in this process, what the bridge does per scan: decode the LaserScan and Odometry CDR
  (rosbags), interpolate the odometry at the scan, and encode posegrid's LaserScan and Odometry (median, p99);
- scan rate, with and without the bridge: scans per second from the first publication until the shard has fused
  every scan, through grid FastSLAM's SLAM node (PARTICLES particles) and one mapper shard (processes behind a
  router): `posegrid source --rate max`'s replay of the bag from this process, which holds back to 32 scans ahead of
  the SLAM node and the shard (without), or the bag played onto rmw_zenoh keys as fast as it goes from this process
  through a `posegrid ros2` process, which cannot hold a live robot back (with); REPEATS runs of each, alternating;
- latency at a 10 Hz laser, with the bridge: per scan, from its arrival here on the ROS scan topic to the arrival of
  the first map_updates sample stamped with it (an update carries the stamp of the last scan fused into its tile);
  median and p99 over LATENCY_SCANS scans played once WARMUP scans before them have been fused (the SLAM node has
  loaded its compiled kernels); through grid FastSLAM's node, and with the robot's own poses (/amcl_pose) instead;
- bytes: the mean map_updates sample (CDR) against the mean whole OccupancyGrid on map.

All processes share this machine's cores, so the figures bound what separate machines would give.
"""

from __future__ import annotations

import json
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from bench.pipeline import Cluster
from bench.scenarios import office_run
from services.keys import ros2_stats_key
from services.nodes.source import Source, SourceOptions
from services.process import RejectCounter, get_logger
from services.ros2 import convert, names
from services.ros2 import types as rt
from services.ros2.ingest import Ingest, IngestConfig
from services.ros2.play import Player, PlayOptions
from services.streams import laser_log_stream
from slam.laserlog import NO_RETURN_RANGE
from slam.rosbag_reader import read_rosbag
from slam.simulator import SimRun

ROBOT = "bench"
STEPS = 120  # scans in the rate runs
REPEATS = 2  # rate runs with and without the bridge, alternating (this shared machine's speed drifts)
PARTICLES = 10  # grid FastSLAM's
LATENCY_SCANS = 60  # scans measured at 10 Hz
WARMUP = 10  # scans before them
NS = 1_000_000_000


def _write_bag(run: SimRun, path: Path, steps: range, poses: bool = False) -> Path:
    """The run's ``steps`` as a ROS 2 bag: /tf_static, then per step /odom and /scan, and with ``poses`` the true
    pose with a small covariance on /amcl_pose (as a robot's own localisation)."""
    from rosbags.rosbag2 import Writer

    store = rt.typestore()
    tf_type, odom_type, scan_type = (rt.MessageType(n) for n in (rt.TF_MESSAGE, rt.ODOMETRY, rt.LASER_SCAN))
    vector = rt.field_class("geometry_msgs/msg/Vector3")
    x, y, yaw = run.sensor_offset
    mount = rt.field_class("geometry_msgs/msg/TransformStamped")(
        header=convert.header(0.0, "base_link"),
        child_frame_id="laser",
        transform=rt.field_class("geometry_msgs/msg/Transform")(
            translation=vector(x=float(x), y=float(y), z=0.0), rotation=convert.ros_pose(0, 0, yaw).orientation
        ),
    )
    zero = vector(x=0.0, y=0.0, z=0.0)
    with Writer(path, version=9) as writer:
        static = writer.add_connection("/tf_static", rt.TF_MESSAGE, typestore=store)
        odom = writer.add_connection("/odom", rt.ODOMETRY, typestore=store)
        scan = writer.add_connection("/scan", rt.LASER_SCAN, typestore=store)
        amcl = writer.add_connection("/amcl_pose", rt.POSE_COVARIANCE, typestore=store) if poses else None
        writer.write(static, 0, tf_type.encode(tf_type.cls()(transforms=[mount])))
        for t in steps:
            stamp = float(run.stamps[t])
            pose = rt.field_class("geometry_msgs/msg/PoseWithCovariance")(
                pose=convert.ros_pose(*run.odometry[t]), covariance=np.zeros(36)
            )
            twist = rt.field_class("geometry_msgs/msg/TwistWithCovariance")(
                twist=rt.field_class("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=np.zeros(36)
            )
            message = odom_type.cls()(
                header=convert.header(stamp, "odom"), child_frame_id="base_link", pose=pose, twist=twist
            )
            writer.write(odom, round(stamp * NS) + 1, odom_type.encode(message))
            ranges = np.asarray(run.ranges[t], np.float32)
            laser = scan_type.cls()(
                header=convert.header(stamp, "laser"),
                angle_min=float(run.angle_min),
                angle_max=float(run.angle_min + run.angle_increment * (len(ranges) - 1)),
                angle_increment=float(run.angle_increment),
                time_increment=0.0,
                scan_time=0.0,
                range_min=float(run.range_min),
                range_max=float(run.range_max),
                ranges=ranges,
                intensities=np.zeros(0, np.float32),
            )
            writer.write(scan, round(stamp * NS) + 2, scan_type.encode(laser))
            if amcl is not None:
                writer.write(amcl, round(stamp * NS) + 3, _amcl_pose(stamp, run.true_poses[t]))
    return path


def _amcl_pose(stamp: float, pose: np.ndarray) -> bytes:
    """CDR of a PoseWithCovarianceStamped at ``pose`` with 5 cm and 0.01 rad standard deviations."""
    covariance = np.zeros(36)
    covariance[[0, 7, 35]] = [0.05**2, 0.05**2, 0.01**2]
    with_cov = rt.field_class("geometry_msgs/msg/PoseWithCovariance")(
        pose=convert.ros_pose(*pose), covariance=covariance
    )
    message_type = rt.MessageType(rt.POSE_COVARIANCE)
    return message_type.encode(message_type.cls()(header=convert.header(stamp, "map"), pose=with_cov))


def _bridge_cost(bag: Path) -> dict:
    """ms per scan of the bridge's work on one scan and the odometry before it, in this process."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        raws = [(c.topic, bytes(raw)) for c, _, raw in reader.messages()]
    ingest = Ingest(IngestConfig(ROBOT, wait=60.0), RejectCounter(get_logger("bench")))
    static, odom, scan = (rt.MessageType(n) for n in (rt.TF_MESSAGE, rt.ODOMETRY, rt.LASER_SCAN))
    per_scan, pending = [], 0.0
    for topic, raw in raws:
        started = time.perf_counter()
        if topic == "/tf_static":
            ingest.on_transforms(topic, static.decode(raw), static=True)
        elif topic == "/odom":
            ingest.on_odometry(topic, odom.decode(raw))
        else:
            ingest.on_scan(topic, scan.decode(raw))
        for _, message in ingest.ready():
            message.encode()
        pending += time.perf_counter() - started
        if topic == "/scan":
            per_scan.append(pending)
            pending = 0.0
    costs = 1e3 * np.array(per_scan[WARMUP:])
    return {
        "bridge_ms_per_scan_median": float(np.median(costs)),
        "bridge_ms_per_scan_p99": float(np.percentile(costs, 99)),
    }


def _slam_node(cluster: Cluster) -> None:
    cluster.children.start(
        "slam-node",
        [
            "slam-node",
            "--robot",
            ROBOT,
            "--algo",
            "gridslam",
            "--particles",
            str(PARTICLES),
            "--connect",
            cluster.endpoint,
        ],
    )


def _bridge(cluster: Cluster, *options: str) -> None:
    cluster.children.start(
        "ros2",
        [
            "ros2",
            "--robot",
            ROBOT,
            "--map",
            cluster.map_name,
            "--wait-mappers",
            "1",
            "--connect",
            cluster.endpoint,
            *options,
        ],
    )


def _rate_without_bridge(bag: Path) -> float:
    stream = laser_log_stream(read_rosbag(bag), ROBOT, NO_RETURN_RANGE)
    with Cluster(1, "rosbag") as cluster:
        _slam_node(cluster)
        options = SourceOptions(rate=None, wait_mappers=1, map_name=cluster.map_name, wait_slam=True)
        started = time.perf_counter()
        Source(cluster.session, stream, options).run(threading.Event())
        cluster.wait_fused(stream.scans)
        return stream.scans / (time.perf_counter() - started)


def _rate_with_bridge(bag: Path) -> float:
    scans = len(laser_log_stream(read_rosbag(bag), ROBOT, NO_RETURN_RANGE).steps)
    with Cluster(1, "ros2") as cluster:
        _slam_node(cluster)
        _bridge(cluster)
        player = Player(cluster.session, bag, PlayOptions(rate=None, wait=120.0))
        started = time.perf_counter()
        player.run(threading.Event())
        cluster.wait_fused(scans)
        return scans / (time.perf_counter() - started)


def _latency_and_bytes(warmup: Path, bag: Path, own_poses: bool) -> dict:
    """Scan-to-map_updates latency at 10 Hz through grid FastSLAM's node, or (``own_poses``) with the robot's own
    poses (/amcl_pose) and no SLAM node; and the bytes of an update and of a whole map. The ``warmup`` bag's scans
    go first, and the measured ones once the pipeline has fused them (its SLAM node has loaded its kernels)."""
    arrivals: dict[int, float] = {}  # scan stamp (ns) -> arrival of the scan, s
    updates: dict[int, float] = {}  # stamp (ns) -> arrival of its first map_updates sample, s
    lock = threading.Lock()

    def stamp_ns(header) -> int:
        return int(header.stamp.sec) * NS + int(header.stamp.nanosec)

    def on_scan(sample: zenoh.Sample) -> None:
        arrival = time.perf_counter()
        with lock:
            arrivals[stamp_ns(rt.MessageType(rt.LASER_SCAN).decode(sample.payload.to_bytes()).header)] = arrival

    def on_update(sample: zenoh.Sample) -> None:
        arrival = time.perf_counter()
        with lock:
            updates.setdefault(
                stamp_ns(rt.MessageType(rt.GRID_UPDATE).decode(sample.payload.to_bytes()).header), arrival
            )

    with Cluster(1, "ros2lat") as cluster:
        if own_poses:
            _bridge(cluster, "--pose-topic", "amcl_pose")
        else:
            _slam_node(cluster)
            _bridge(cluster)
        graph = names.Graph(names.RMW, 0, "/", "bench", "0")
        for topic, type_name, callback in (
            ("/scan", rt.LASER_SCAN, on_scan),
            ("/map_updates", rt.GRID_UPDATE, on_update),
        ):
            kind = rt.MessageType(type_name)
            cluster.session.declare_subscriber(graph.topic_key(topic, type_name, kind.type_hash), callback)
        Player(cluster.session, warmup, PlayOptions(rate=1.0, wait=120.0)).run(threading.Event())
        cluster.wait_fused(WARMUP)
        Player(cluster.session, bag, PlayOptions(rate=1.0)).run(threading.Event())
        cluster.wait_fused(WARMUP + LATENCY_SCANS)
        time.sleep(1.5)  # the last updates, and a whole map after them
        stats = json.loads(next(iter(cluster.session.get(ros2_stats_key(ROBOT), timeout=5.0))).ok.payload.to_bytes())
    ordered = sorted(arrivals)
    latency = [1e3 * (updates[s] - arrivals[s]) for s in ordered[WARMUP:] if s in updates]  # (the measured bag's)
    published, sizes = stats["published"], stats["bytes_published"]
    how = "own_poses" if own_poses else "gridslam"
    return {
        f"scan_to_map_update_ms_median_at_10hz_{how}": float(np.median(latency)),
        f"scan_to_map_update_ms_p99_at_10hz_{how}": float(np.percentile(latency, 99)),
        f"scans_without_own_update_{how}": len(ordered) - WARMUP - len(latency),
        f"bytes_per_map_update_{how}": sizes["/map_updates"] / published["/map_updates"],
        f"bytes_per_whole_map_{how}": sizes["/map"] / published["/map"],
    }


def run() -> dict:
    office = office_run(seed=0, steps=STEPS)
    with tempfile.TemporaryDirectory() as folder:
        bag = _write_bag(office, Path(folder) / "office", range(STEPS))
        warmup = _write_bag(office, Path(folder) / "warmup", range(WARMUP), poses=True)
        measured = _write_bag(office, Path(folder) / "measured", range(WARMUP, WARMUP + LATENCY_SCANS), poses=True)
        out: dict = {"scans": STEPS, "beams": int(office.ranges.shape[1]), "particles": PARTICLES}
        out.update(_bridge_cost(bag))
        rates: dict[str, list[float]] = {"without": [], "with": []}
        for _ in range(REPEATS):
            rates["without"].append(_rate_without_bridge(bag))
            rates["with"].append(_rate_with_bridge(bag))
        out["scans_per_s_without_bridge"] = float(np.median(rates["without"]))
        out["scans_per_s_with_bridge"] = float(np.median(rates["with"]))
        out["scans_per_s_without_bridge_runs"] = [round(rate, 2) for rate in rates["without"]]
        out["scans_per_s_with_bridge_runs"] = [round(rate, 2) for rate in rates["with"]]
        out["rate_ratio_with_to_without"] = out["scans_per_s_with_bridge"] / out["scans_per_s_without_bridge"]
        out.update(_latency_and_bytes(warmup, measured, own_poses=False))
        out.update(_latency_and_bytes(warmup, measured, own_poses=True))
    return out
