"""`posegrid ros2`: the bridge between one robot's ROS 2 topics on Zenoh and posegrid's keys; `posegrid ros2 play
BAG`: a ROS 2 bag replayed onto those topics (docs/ros2.md). Also the options `posegrid run --ros2` takes
(:func:`add_ros2_run_arguments`, :func:`plan_ros2`).
"""

from __future__ import annotations

import argparse
import os
import re
from typing import TYPE_CHECKING

from services.commands.argtypes import finite_float, path_argument, positive_number, positive_seconds
from services.commands.options import OptionRow, add_group, no_return_range_keywords
from slam.laserlog import NO_RETURN_RANGE

if TYPE_CHECKING:
    from services.nodes.launcher import Plan

DEFAULT_ROBOT = "robot0"
DEFAULT_MAP = "main"
#: the particle cloud types the bridge reads, by the name --particles-type takes
PARTICLE_TYPES = {"ParticleCloud": "nav2_msgs/msg/ParticleCloud", "PoseArray": "geometry_msgs/msg/PoseArray"}
#: where the robot sits in the ROS 2 graph, as the bridge (`posegrid ros2`) and `posegrid run --ros2` both take it
ROBOT_GRAPH: tuple[OptionRow, ...] = (
    ("domain", dict(type=int, default=None, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID, else 0)")),
    ("namespace", dict(default="/", help="the robot's ROS namespace, e.g. /robot1 (default /)")),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    bridge = subparsers.add_parser(
        "ros2",
        allow_abbrev=False,  # (else `ros2 play --wait` would read as an abbreviation of the bridge's --wait-*)
        help="bridge one robot's ROS 2 topics (rmw_zenoh or zenoh-bridge-ros2dds) and posegrid, both ways",
        description="Read the robot's LaserScan, Odometry and /tf, /tf_static (or its own pose: --pose-topic, "
        "--particles-topic) from ROS 2 over Zenoh and publish them as pg/ROBOT/scan, odom, prior (or pose); publish "
        "the map of --map as nav_msgs/OccupancyGrid on map (TRANSIENT_LOCAL, at most every --map-period s) and "
        "map_variance, the changed tiles as map_msgs/OccupancyGridUpdate on map_updates, and the poses as PoseArray "
        "on particle_cloud and PoseWithCovarianceStamped on pose. No ROS installation needed. `posegrid ros2 play "
        "BAG` replays a ROS 2 bag onto the same topics. Counts on pg/ROBOT/ros2/stats (JSON).",
    )
    bridge.add_argument(
        "--robot", default=DEFAULT_ROBOT, help=f"posegrid's name of the robot (default {DEFAULT_ROBOT})"
    )
    bridge.add_argument("--map", default=DEFAULT_MAP, help=f"the map sent to ROS 2 (default {DEFAULT_MAP})")
    bridge.add_argument(
        "--wait-mappers", type=int, default=0, metavar="N", help="wait for N mapper shards of --map first (default 0)"
    )
    bridge.add_argument("--wait-slam", action="store_true", help="wait for the robot's SLAM node first")
    add_graph_arguments(bridge)
    add_bridge_arguments(bridge)
    add_zenoh_arguments(bridge)
    bridge.set_defaults(func=run_bridge)
    commands = bridge.add_subparsers(dest="ros2_command", metavar="{play}")
    play = commands.add_parser(
        "play",
        help="replay a ROS 2 bag onto ROS 2 topics over Zenoh (a stand-in for a robot)",
        description="Publish a ROS 2 bag's messages as recorded (CDR) on their topics placed under --namespace, "
        "as a robot on rmw_zenoh (or behind zenoh-bridge-ros2dds with --mode bridge) would, paced by the bag's "
        "timestamps. /tf_static is TRANSIENT_LOCAL. Exits 0 after the last message.",
    )
    play.add_argument("bag", type=path_argument, metavar="BAG", help="a ROS 2 bag folder, or its .mcap or .db3 file")
    add_graph_arguments(play, node="posegrid_play")
    play.add_argument(
        "--rate", default="realtime", help="'realtime', a factor of real time (e.g. 2) or 'max' (default realtime)"
    )
    play.add_argument("--topic", action="append", default=None, help="a bag topic to play (repeatable; default all)")
    play.add_argument(
        "--wait",
        type=finite_float,
        default=0.0,
        metavar="SECONDS",
        help="wait up to this long for a subscription of every played topic before the first message (default 0)",
    )
    add_zenoh_arguments(play)
    play.set_defaults(func=run_play)


def add_graph_arguments(parser: argparse.ArgumentParser, node: str = "posegrid") -> None:
    """Where the process sits in the ROS 2 graph: --mode, --domain, --namespace, --node."""
    mode = dict(
        choices=("rmw_zenoh", "bridge"),
        default="rmw_zenoh",
        help="rmw_zenoh: keys <domain>/<topic>/<type>/<hash>, attachments and liveliness tokens; bridge: plain "
        "topic keys as zenoh-bridge-ros2dds routes them (default rmw_zenoh)",
    )
    node_row = ("node", dict(default=node, help=f"the node name in the ROS graph (default {node})"))
    add_group(parser, "ROS 2 graph", None, [("mode", mode), *ROBOT_GRAPH, node_row])


#: a tf2 frame id as posegrid takes one: no leading '/', no spaces, no empty part (tf2 refuses a leading '/')
_FRAME = re.compile(r"(?=.{1,256}$)[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*")


def _bridge_table() -> list[tuple[str, str, dict]]:
    """(group, option name without --, argparse keywords) of every option of the bridge's topics and behaviour:
    `posegrid ros2` takes them as they are, `posegrid run --ros2` with the prefix ``ros2-`` and passes them on."""
    topics = "ROS 2 topics (relative names resolve in --namespace)"
    table: list[tuple[str, str, dict]] = [
        (topics, name, {"default": default, "help": f"{what} (default {default})"})
        for name, default, what in (
            ("scan-topic", "scan", "sensor_msgs/LaserScan in"),
            ("odom-topic", "odom", "nav_msgs/Odometry in"),
            ("tf-topic", "tf", "tf2_msgs/TFMessage in (odometry when no Odometry comes)"),
            ("tf-static-topic", "tf_static", "tf2_msgs/TFMessage in: the laser's mount (TRANSIENT_LOCAL)"),
            ("map-topic", "map", "nav_msgs/OccupancyGrid out (TRANSIENT_LOCAL)"),
            ("map-updates-topic", "map_updates", "map_msgs/OccupancyGridUpdate out"),
            ("map-variance-topic", "map_variance", "nav_msgs/OccupancyGrid of the variance layer out"),
            ("particle-cloud-topic", "particle_cloud", "geometry_msgs/PoseArray of the pose samples out"),
            ("pose-out-topic", "pose", "geometry_msgs/PoseWithCovarianceStamped of the fitted Gaussian out"),
        )
    ]
    table += [
        (
            topics,
            "pose-topic",
            {
                "default": None,
                "help": "take the robot's own pose, geometry_msgs/PoseWithCovarianceStamped (amcl_pose), instead of "
                "odometry and posegrid's SLAM node; joined with the scans by stamp",
            },
        ),
        (
            topics,
            "particles-topic",
            {
                "default": None,
                "help": "take the robot's own particles (of the message type the particles-type option names) instead "
                "of odometry",
            },
        ),
        (
            topics,
            "particles-type",
            {
                "choices": sorted(PARTICLE_TYPES),
                "default": "ParticleCloud",
                "help": "the particles topic's message type: nav2_msgs/ParticleCloud or geometry_msgs/PoseArray "
                "(default ParticleCloud)",
            },
        ),
        ("bridge", "frame", {"default": "map", "help": "frame_id of the map and poses (default map)"}),
        ("bridge", "no-return-range", no_return_range_keywords("the laser's scans: ", NO_RETURN_RANGE)),
        (
            "bridge",
            "base-frame",
            {
                "default": None,
                "help": "the robot's base frame (default: the Odometry's child frame, else the root of the laser's "
                "/tf_static chain)",
            },
        ),
    ]
    for name, default, unit, what in (
        ("map-period", 1.0, "SECONDS", "shortest time between two whole maps on the map topic, s"),
        ("variance-scale", 1.0, "LOGODDS2", "the variance (log-odds squared) shown as 100 on the variance topic"),
        ("odom-wait", 2.0, "SECONDS", "how long a scan waits for its odometry, transform or pose, s"),
        ("pose-tolerance", 0.05, "SECONDS", "how far a pose's stamp may lie from its scan's, s"),
    ):
        keywords = {
            "type": positive_seconds if unit == "SECONDS" else positive_number,
            "default": default,
            "metavar": unit,
            "help": f"{what} (default {default})",
        }
        table.append(("bridge", name, keywords))
    return table


def add_bridge_arguments(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """The bridge's topics and behaviour (``prefix``: none for `posegrid ros2`, "ros2-" for `posegrid run`)."""
    table = _bridge_table()
    for title in dict.fromkeys(group for group, _name, _keywords in table):
        add_group(parser, title, None, [(name, keywords) for group, name, keywords in table if group == title], prefix)


def bridge_argv(args: argparse.Namespace, prefix: str) -> list[str]:
    """The options of :func:`add_bridge_arguments` parsed with ``prefix``, as `posegrid ros2` takes them."""
    argv = []
    for _group, name, _keywords in _bridge_table():
        value = getattr(args, (prefix + name).replace("-", "_"))
        if value is not None:
            argv.append(f"--{name}={value}")
    return argv


def _domain(value: int | None) -> int:
    from services.errors import UsageError
    from services.ros2.names import RosNameError, check_domain

    if value is None:
        text = os.environ.get("ROS_DOMAIN_ID", "0") or "0"
        if not text.isdigit():
            raise UsageError(f"$ROS_DOMAIN_ID must be an integer, got {text!r}")
        value = int(text)
    try:
        check_domain(value)
    except RosNameError as exc:
        raise UsageError(str(exc)) from None
    return value


def _graph(args: argparse.Namespace) -> tuple[str, int, str]:
    """(mode, domain, namespace) of the graph options; UsageError for a bad name or domain."""
    from services.errors import UsageError
    from services.ros2 import names

    try:
        namespace = names.normalize_namespace(args.namespace)
        names.check_name(args.node, "node name")
        if "/" in args.node:
            raise names.RosNameError(f"node name {args.node!r} may not hold '/'")
    except names.RosNameError as exc:
        raise UsageError(str(exc)) from None
    return (names.RMW if args.mode == "rmw_zenoh" else names.BRIDGE), _domain(args.domain), namespace


#: the longest a bridge's waits and periods may be, s (1e308 s: scans that never time out)
MAX_SECONDS = 3600.0
#: the option that names each of services.ros2.bridge.Topics' topics
_TOPIC_OPTIONS = {
    "scan": "scan-topic",
    "odom": "odom-topic",
    "tf": "tf-topic",
    "tf_static": "tf-static-topic",
    "pose_in": "pose-topic",
    "particles_in": "particles-topic",
    "map": "map-topic",
    "map_updates": "map-updates-topic",
    "map_variance": "map-variance-topic",
    "particle_cloud": "particle-cloud-topic",
    "pose": "pose-out-topic",
}


def bridge_options(args: argparse.Namespace, prefix: str = ""):
    """The services.ros2.bridge.BridgeOptions of the parsed options; UsageError for a bad name."""
    from services.commands.pipeline import _check_name
    from services.errors import UsageError
    from services.ros2 import names
    from services.ros2.bridge import BridgeOptions, Topics
    from services.ros2.ingest import IngestConfig

    def value(name: str):
        return getattr(args, prefix.replace("-", "_") + name)

    _check_name(args.robot, "--robot")
    _check_name(args.map, "--map")
    mode, domain, namespace = _graph(args)
    topics = Topics(
        scan=value("scan_topic"),
        odom=value("odom_topic"),
        tf=value("tf_topic"),
        tf_static=value("tf_static_topic"),
        pose_in=value("pose_topic"),
        particles_in=value("particles_topic"),
        particles_type=PARTICLE_TYPES[value("particles_type")],
        map=value("map_topic"),
        map_updates=value("map_updates_topic"),
        map_variance=value("map_variance_topic"),
        particle_cloud=value("particle_cloud_topic"),
        pose=value("pose_out_topic"),
    )
    resolved: dict[str, list[str]] = {}  # fully qualified topic -> the options naming it
    for field, topic in vars(topics).items():
        if topic is not None and field != "particles_type":
            try:
                full = names.resolve(topic, namespace)
            except names.RosNameError as exc:
                raise UsageError(str(exc)) from None
            resolved.setdefault(full, []).append(f"--{prefix}{_TOPIC_OPTIONS[field]}")
    shared = next(((topic, options) for topic, options in resolved.items() if len(options) > 1), None)
    if shared is not None:
        raise UsageError(
            f"{' and '.join(shared[1])} name one topic, {shared[0]}: the bridge would read what it publishes "
            "there, or publish two things on it; give each its own topic"
        )
    for name in ("odom_wait", "pose_tolerance", "map_period"):
        if value(name) > MAX_SECONDS:
            option = f"--{prefix}{name.replace('_', '-')}"
            raise UsageError(f"{option} must be at most {MAX_SECONDS:g} s, got {value(name):g}")
    if topics.pose_in is not None and topics.particles_in is not None:
        raise UsageError(
            f"--{prefix}pose-topic and --{prefix}particles-topic are two sources of the robot's pose: give one"
        )
    if topics.particles_in is None and value("particles_type") != "ParticleCloud":
        raise UsageError(f"--{prefix}particles-type says what --{prefix}particles-topic carries: give that topic too")
    for option, frame in (("frame", value("frame")), ("base-frame", value("base_frame"))):
        if frame is not None and not _FRAME.fullmatch(frame):
            raise UsageError(
                f"--{prefix}{option} {frame!r} is no frame id: 1 to 256 letters, digits, '_', '-', '.' and inner "
                "'/' (tf2 frame ids have no leading '/')"
            )
    takes_poses = topics.pose_in is not None or topics.particles_in is not None
    ingest = IngestConfig(
        args.robot,
        no_return_range=value("no_return_range"),
        base_frame=value("base_frame"),
        wait=value("odom_wait"),
        poses=takes_poses,
        pose_tolerance=value("pose_tolerance"),
    )
    return BridgeOptions(
        robot=args.robot,
        map_name=args.map,
        mode=mode,
        domain=domain,
        namespace=namespace,
        node=args.node,
        frame=value("frame"),
        topics=topics,
        map_period=value("map_period"),
        variance_scale=value("variance_scale"),
        wait_mappers=getattr(args, "wait_mappers", 0),
        wait_slam=getattr(args, "wait_slam", False),
        ingest=ingest,
    )


def run_bridge(args: argparse.Namespace) -> int:
    from services.commands.zenoh_options import config_from_args
    from services.errors import UsageError
    from services.process import install_stop_event
    from services.ros2.bridge import Bridge
    from services.zenoh_config import close_session, open_session

    if args.wait_mappers < 0:
        raise UsageError(f"--wait-mappers must be >= 0, got {args.wait_mappers}")
    options = bridge_options(args)
    stop = install_stop_event("ros2")
    session = open_session(config_from_args(args, "client"), "the ROS 2 bridge")
    try:
        return Bridge(session, options).run(stop)
    finally:
        close_session(session, "the ROS 2 bridge")


def run_play(args: argparse.Namespace) -> int:
    from services.commands.pipeline import _rate
    from services.commands.zenoh_options import config_from_args
    from services.process import install_stop_event
    from services.ros2.play import Player, PlayOptions
    from services.zenoh_config import close_session, open_session

    mode, domain, namespace = _graph(args)
    options = PlayOptions(
        mode=mode,
        domain=domain,
        namespace=namespace,
        node=args.node,
        rate=_rate(args.rate),
        topics=None if args.topic is None else tuple(args.topic),
        wait=max(args.wait, 0.0),
    )
    player = Player(None, args.bag, options)
    player.check()  # a bag that cannot be played is said before the session is opened
    stop = install_stop_event("ros2 play")
    session = player.session = open_session(config_from_args(args, "client"), "the bag player")
    try:
        return player.run(stop)
    finally:
        close_session(session, "the bag player")


# ------------------------------------------------------------------------------------------ posegrid run --ros2


def add_ros2_run_arguments(run: argparse.ArgumentParser) -> None:
    """`posegrid run --ros2`'s options: the robot is a live ROS 2 robot, its bridge a child of the run."""
    rows = [
        ("ros2", dict(action="store_true", help="map a live ROS 2 robot (rmw_zenoh or zenoh-bridge-ros2dds)")),
        *ROBOT_GRAPH,
        ("ros2-mode", dict(choices=("rmw_zenoh", "bridge"), default="rmw_zenoh", help="(default rmw_zenoh)")),
        ("ros2-node", dict(default="posegrid", help="the bridge's node name (default posegrid)")),
        (
            "ros2-connect",
            dict(
                action="append",
                default=[],
                metavar="ENDPOINT",
                help="the run's router also connects to this Zenoh router of the ROS 2 side (rmw_zenohd, "
                "zenoh-bridge-ros2dds), e.g. tcp/192.168.1.5:7447 (repeatable); or give --router-port 7447 and let "
                "the robot's sessions connect to the run's router",
            ),
        ),
    ]
    add_group(
        run,
        "ROS 2 robot (--ros2)",
        "With --ros2 the run maps a live ROS 2 robot instead of replaying an input: `posegrid ros2` (the bridge) "
        "takes its scans, odometry and transforms, grid FastSLAM its poses (unless --ros2-pose-topic or "
        "--ros2-particles-topic take the robot's own), and the map goes back on its map topics. The bridge's "
        "options (`posegrid ros2 --help`) are taken here with the prefix --ros2-.",
        rows,
    )
    add_bridge_arguments(run, prefix="ros2-")


def plan_ros2(args: argparse.Namespace, plan: Plan) -> None:
    """Fill in ``plan`` for a live ROS 2 robot: the bridge as the robot's feeding child, grid FastSLAM unless the
    robot's own poses are taken; UsageError for options that do not go with --ros2."""
    from services.commands.pipeline import slam_argv
    from services.errors import UsageError
    from services.zenoh_config import build_config

    given = [f"--{n.replace('_', '-')}" for n in ("posed", "sim_dir", "mrclam", "carmen", "bag") if getattr(args, n)]
    if given or args.sim:
        raise UsageError(f"--ros2 maps a live robot: it takes no input ({', '.join(given) or '--sim'})")
    if args.export is not None:
        raise UsageError("--ros2 maps a live robot, whose stream has no end to export at: leave out --export")
    if args.secure:
        raise UsageError("--ros2 does not run with --secure: the roles' access rules know no ROS 2 keys")
    graph = argparse.Namespace(mode=args.ros2_mode, domain=args.domain, namespace=args.namespace, node=args.ros2_node)
    mode, domain, namespace = _graph(graph)
    bridge_options(argparse.Namespace(**{**vars(args), **vars(graph)}), "ros2-")  # (checked before anything starts)
    bridge = bridge_argv(args, "ros2-")
    plan.source_command = "ros2"
    plan.source_argv = [f"--mode={args.ros2_mode}", f"--domain={domain}", f"--namespace={namespace}"]
    plan.source_argv += [f"--node={args.ros2_node}", *bridge]
    try:  # (the router would refuse them after the run had started its children)
        build_config("router", connect=list(args.ros2_connect))
    except UsageError as exc:
        raise UsageError(f"--ros2-connect: {exc}") from None
    plan.router_argv = [f"--connect={endpoint}" for endpoint in args.ros2_connect]
    plan.scans = None
    robot_poses = args.ros2_pose_topic is not None or args.ros2_particles_topic is not None
    if robot_poses:
        plan.slam_argv = None
        how = "with the robot's own poses"
    else:
        if args.algo not in (None, "gridslam"):
            raise UsageError("a ROS 2 robot's laser and odometry go through grid FastSLAM: --algo must be gridslam")
        args.algo = "gridslam"
        plan.slam_argv = slam_argv(args, "sim")
        how = "through grid FastSLAM"
    plan.description = (
        f"mapping the ROS 2 robot in namespace {namespace} (domain {domain}, {mode}) live {how} into "
        f"{args.shards} shard(s); the map goes out on its {args.ros2_map_topic} topic"
    )
