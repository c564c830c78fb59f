"""Subcommands of the distributed pipeline over Zenoh: router, mapper, source, run (docs/keys.md).

Every process connects to the router as a Zenoh client on tcp/127.0.0.1:7447 unless --connect,
--listen or --zenoh-config say otherwise (services/zenoh_config.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from schemas.messages import CELL_SIZE_RANGE, MAX_SHARDS, MAX_TILE_SIZE
from services.commands.api import add_http_arguments, api_child_options, check_port_free
from services.commands.argtypes import (
    check_outputs,
    finite_float,
    finite_or_inf,
    odom_delay_seconds,
    path_argument,
    pose_sample_count,
    positive_int,
    random_seed,
)
from services.commands.gridslam import (
    DEFAULT_GRID_PARTICLES,
    FILTER_OPTIONS,
    add_filter_options,
    add_max_odometry_step,
    reject_filter_options,
)
from services.commands.limits import add_limit_arguments, limit_argv, limits_from_args
from services.commands.mapping import (
    add_sampling_arguments,
    add_sensor_model_arguments,
    add_threads_argument,
    available_cores,
    available_memory,
    refuse_bundle_with_ml,
    sensor_model_argv,
    threads_from_args,
)
from services.commands.options import (
    add_choice,
    add_command,
    add_group,
    add_scan_topic,
    no_return_range,
    no_return_range_keywords,
    option_argv,
)
from services.commands.persist_options import (
    add_persist_options,
    add_run_persist_options,
    persist_from_args,
    plan_state,
)
from services.commands.slam import add_calibration_options, add_drive_angle_sd_option, add_initial_option

if TYPE_CHECKING:
    from services.nodes.launcher import Plan

DEFAULT_MAP = "main"
DEFAULT_ROBOT = "robot0"
SLAM_ALGORITHMS = ("odometry", "ekf", "fastslam1", "fastslam2", "gridslam")
#: the SLAM node's filter when --algo is not given (a CARMEN log sets gridslam)
DEFAULT_ALGORITHM = "fastslam2"
#: particles of `run`'s SLAM node unless --particles says otherwise: each becomes a pose sample per scan
RUN_PARTICLES = 30
#: landmark FastSLAM particles of a `slam-node` unless --particles says otherwise: fewer than `posegrid slam`'s
#: offline default, since every mapper shard ray-casts each of them in every scan
NODE_PARTICLES = 500
#: the options of :func:`add_slam_arguments` that `run` passes on to its SLAM node as given (--algo and --models
#: are filled in first)
SLAM_NODE_OPTIONS = (
    "--associate",
    "--motion",
    "--seed",
    "--resample-threshold",
    "--plain-resampling",
    "--particles",
    "--alphas",
    "--sigma-range",
    "--sigma-bearing",
    "--range-fraction",
    "--outlier-gate",
    "--drive-angle-sd",
    "--profile",
    "--calibration",
    "--max-landmarks",
    "--max-odometry-step",
    *(option for option, _ in FILTER_OPTIONS),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    _add_router(subparsers)
    _add_mapper(subparsers)
    _add_source(subparsers)
    _add_slam_node(subparsers)
    _add_run(subparsers)


def _add_router(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    router = add_command(subparsers, "router", run_router)
    add_zenoh_arguments(router)


def _add_mapper(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    mapper = add_command(subparsers, "mapper", run_mapper)
    mapper.add_argument("--shard", type=int, required=True, help="this shard's index I, 0 <= I < N")
    mapper.add_argument("--shards", type=int, required=True, help="number of shards N")
    _add_map_option(mapper)
    add_fusion_arguments(mapper)
    shard = mapper.add_argument_group("shard")
    shard.add_argument(
        "--tile-size",
        type=int,
        default=256,
        help=f"cells per tile side, a power of 2 up to {MAX_TILE_SIZE} (default 256); smaller tiles mean more, "
        "smaller tile updates and do not divide a scan's work among shards (docs/architecture.md, Sharding)",
    )
    shard.add_argument(
        "--publish-interval",
        type=finite_float,
        default=0.05,
        help="shortest time between two updates of one tile, s (default 0.05)",
    )
    shard.add_argument(
        "--join-buffer",
        type=int,
        default=512,
        help="scans and poses that may wait for their partner (default 512; overflow is counted)",
    )
    shard.add_argument(
        "--intake-buffer",
        type=int,
        default=4096,
        help="messages that may wait for the fusion thread (default 4096; overflow is counted)",
    )
    add_threads_argument(shard, "every core this process may use")
    add_limit_arguments(mapper)
    add_persist_options(mapper)
    add_zenoh_arguments(mapper)


def _add_source(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    source = add_command(subparsers, "source", run_source)
    add_input_arguments(source, default_sim=False)
    _add_robot_option(source)
    add_rate_argument(source, "realtime")
    source.add_argument(
        "--wait-mappers",
        type=int,
        default=0,
        metavar="N",
        help="wait for N mapper shards of --map before publishing (default 0: do not wait)",
    )
    _add_map_option(source, "map whose shards to wait for")
    source.add_argument("--wait-slam", action="store_true", help="wait for the robot's SLAM node before publishing")
    source.add_argument(
        "--window",
        type=int,
        default=32,
        help="--rate max: scans the source may run ahead of the slowest shard, and steps ahead "
        "of the SLAM node with --wait-slam (default 32)",
    )
    add_zenoh_arguments(source)


def _add_slam_node(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    node = add_command(subparsers, "slam-node", run_slam_node)
    _add_robot_option(node)
    add_slam_arguments(node)
    node.add_argument("--seed", type=random_seed, default=0, help="seed of the particle filter (default 0)")
    add_initial_option(node, "start pose in m, m, rad (default: the prior the source publishes)")
    _add_node_limits(node)
    add_zenoh_arguments(node)


def _add_node_limits(parser: argparse.ArgumentParser) -> None:
    """The SLAM node's bounds on what a peer's steps may ask of its filter (services.state.slam); each step refused
    is counted in its stats and logged."""
    group = parser.add_argument_group("SLAM node limits on what peers may send (docs/security.md)")
    group.add_argument(
        "--max-landmarks",
        type=positive_int,
        default=None,
        help="landmarks a landmark filter may hold; a step whose new ids (or, with unknown ids, its measurements) "
        "could take it past is refused (default 4096; EKF-SLAM 1024, its covariance growing with their square)",
    )
    add_max_odometry_step(group)


def _add_run(subparsers: argparse._SubParsersAction) -> None:
    run = add_command(subparsers, "run", run_pipeline)
    add_input_arguments(run, default_sim=True)
    run.add_argument(
        "--shards",
        type=int,
        default=1,
        help="mapper shards, all started on this machine, about 200 MiB each (default 1; more than its free memory "
        "holds is refused: shards on other machines are started with `posegrid mapper`)",
    )
    run.add_argument(
        "--export",
        default=None,
        metavar="MAP.npz",
        help="write the map when the replay ends, then stop everything and exit (stopped before: no map, exit 130)",
    )
    _add_map_option(run)
    _add_robot_option(run)
    add_rate_argument(run, None)
    run.add_argument(
        "--router-port", type=int, default=None, help="port of the router on 127.0.0.1 (default: a free one)"
    )
    run.add_argument("--api-port", type=int, default=8000, help="port of the HTTP API on 127.0.0.1 (default 8000)")
    run.add_argument("--no-api", action="store_true", help="do not start the HTTP API")
    add_http_arguments(run, prefix="api-")  # passed on to the API (services.commands.api)
    run.add_argument(
        "--secure",
        action="store_true",
        help="Zenoh over TLS with client certificates, a password per process and access control per "
        "role (docs/security.md): a CA, certificates, passwords and configs are written to a new 0700 "
        "folder, printed at the start and removed at the end",
    )
    add_restart_arguments(run)
    add_run_persist_options(run)
    add_fusion_arguments(run)
    add_threads_argument(run, "each of the N shards gets the cores this process may use divided by N, at least 1")
    add_limit_arguments(run)
    _add_node_limits(run)
    add_slam_arguments(run, particles=RUN_PARTICLES)
    from services.commands.ros2 import add_ros2_run_arguments

    add_ros2_run_arguments(run)  # `run --ros2`: a live ROS 2 robot (docs/ros2.md)


# ------------------------------------------------------------------------------------------ shared options


def _add_robot_option(parser: argparse.ArgumentParser) -> None:
    """--robot: whose streams a process publishes or follows."""
    parser.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot name (default {DEFAULT_ROBOT})")


def _add_map_option(parser: argparse.ArgumentParser, text: str = "map name") -> None:
    """--map, with ``text`` as its help (the default is added)."""
    parser.add_argument("--map", default=DEFAULT_MAP, help=f"{text} (default {DEFAULT_MAP})")


def add_restart_arguments(parser: argparse.ArgumentParser) -> None:
    """When `run` starts a child again that ended (services.nodes.launcher.RestartPolicy, whose defaults these show)."""
    rows = [
        (name, dict(type=kind, default=default, metavar=metavar, help=f"{what} (default {default:g})"))
        for name, kind, default, metavar, what in (
            (
                "max-restarts",
                int,
                5,
                "N",
                "restarts of one child within --restart-window; 0: a child that ends stops the run",
            ),
            ("restart-window", finite_float, 60.0, "SECONDS", "the span --max-restarts counts restarts in, s"),
            (
                "restart-delay",
                finite_float,
                0.5,
                "SECONDS",
                "wait before a child's first restart within --restart-window, s; doubles with each further one",
            ),
            ("max-restart-delay", finite_float, 10.0, "SECONDS", "the longest wait before a restart, s"),
        )
    ]
    add_group(
        parser,
        "restarts",
        "A child that ends while the run goes on (the source: with a non-zero exit or a signal) is "
        "started again with the same arguments and takes what it missed from the histories; a restarted source "
        "replays its input from the start, and the shards drop what they have fused. Restart n (n = 0, 1, ...) "
        "within --restart-window waits --restart-delay * 2^n s, at most --max-restart-delay; a child that fails "
        "once more after --max-restarts restarts within --restart-window stops the run.",
        rows,
    )


def restart_policy(args: argparse.Namespace):
    """The services.nodes.launcher.RestartPolicy of the restart options; UsageError (exit 2) for a bad value."""
    from services.errors import UsageError

    if args.max_restarts < 0:
        raise UsageError(f"--max-restarts must be >= 0, got {args.max_restarts}")
    if not args.restart_window > 0:
        raise UsageError(f"--restart-window must be > 0 s, got {args.restart_window}")
    if not 0 <= args.restart_delay <= args.max_restart_delay:
        raise UsageError(
            f"need 0 <= --restart-delay <= --max-restart-delay, got {args.restart_delay} and {args.max_restart_delay}"
        )
    from services.nodes.launcher import RestartPolicy

    return RestartPolicy(
        max_restarts=args.max_restarts,
        window=args.restart_window,
        first_delay=args.restart_delay,
        max_delay=args.max_restart_delay,
    )


def add_fusion_arguments(parser: argparse.ArgumentParser) -> None:
    """`posegrid fuse`'s fusion options, for the shards (and `run`, which passes them on)."""
    add_sampling_arguments(
        parser.add_argument_group("fusion (as for posegrid fuse)"),
        samples="pose samples per scan for Gaussian poses (default: derived from the covariance)",
        accuracy="accuracy in m for the derived sample count (default: one cell)",
        seed="seed of the Gaussian pose sampling (`posegrid run`: also of the simulated world and the SLAM filter) "
        "(default 0)",
    )
    add_sensor_model_arguments(parser)


def fusion_argv(args: argparse.Namespace) -> list[str]:
    """The fusion and sensor-model options of ``args`` as command-line arguments for a shard."""
    return option_argv(args, ("--mode", "--seed", "--samples", "--accuracy", "--bundle")) + sensor_model_argv(args)


def add_input_arguments(parser: argparse.ArgumentParser, default_sim: bool) -> None:
    """The inputs of `source` and (``default_sim``: the simulation unless another is given) of `run`. `run` builds
    a map, so its help offers no MRCLAM folder (no laser); it takes the options only to say where to go."""
    group = parser.add_argument_group("input (one of)")
    mrclam_help = (lambda text: argparse.SUPPRESS) if default_sim else (lambda text: text)
    inputs = group.add_mutually_exclusive_group(required=not default_sim)
    inputs.add_argument(
        "--sim",
        action="store_true",
        help="simulate the office world live (slam.simulator)" + (" (default)" if default_sim else ""),
    )
    inputs.add_argument(
        "--posed", type=path_argument, metavar="FILE.npz", help="posed-scan file: scans with their poses"
    )
    inputs.add_argument("--sim-dir", type=path_argument, metavar="DIR", help="folder written by `posegrid simulate`")
    inputs.add_argument(
        "--mrclam", type=path_argument, metavar="DIR", help=mrclam_help("UTIAS MRCLAM dataset folder (no laser)")
    )
    inputs.add_argument("--carmen", type=path_argument, metavar="FILE", help="CARMEN log (.clf/.log, plain or gzip)")
    inputs.add_argument(
        "--bag",
        type=path_argument,
        metavar="BAG",
        help="ROS bag with LaserScan and odometry (Odometry messages or /tf): a ROS 1 .bag file or a ROS 2 bag folder",
    )
    group.add_argument(
        "--mrclam-robot", type=int, default=1, metavar="K", help=mrclam_help("MRCLAM robot number (default 1)")
    )
    add_scan_topic(group, "--bag")
    group.add_argument(
        "--odom-delay",
        type=odom_delay_seconds,
        default=0.0,
        metavar="SECONDS",
        help="--carmen, --bag: read each scan's odometry this many seconds after its stamp (negative: "
        "before), from the log's separate odometry stream, for a laser whose stamps run late against "
        "the odometry's (Freiburg 079's bag: -0.10; `posegrid slam --algo gridslam LOG --odom-delay "
        "auto` estimates it; default 0)",
    )
    group.add_argument("--no-return-range", **no_return_range_keywords("--carmen, --bag: "))
    group.add_argument(
        "--steps", type=int, default=None, help=f"--sim: steps of 0.1 s to simulate (default {DEFAULT_SIM_STEPS})"
    )
    if not default_sim:  # `run` has --seed among its fusion options and passes it on
        group.add_argument("--seed", type=random_seed, default=0, help="--sim: seed of the simulated world (default 0)")


def add_rate_argument(parser: argparse.ArgumentParser, default: str | None) -> None:
    parser.add_argument(
        "--rate",
        default=default,
        help="'realtime', a factor of real time (e.g. 2) or 'max' (as fast as the shards take); "
        "default " + (default or "max with --export, else realtime") + ". Paced by the stamps: a pause in them "
        "past 10 s is replayed as 10 s, and steps whose stamps go back go out at once (both said)",
    )


def add_slam_arguments(parser: argparse.ArgumentParser, particles: int | None = None) -> None:
    """The SLAM node's filter options (the same names and meanings as `posegrid slam`)."""
    group = parser.add_argument_group("SLAM node (as for posegrid slam)")
    add_choice(
        group,
        "--algo",
        SLAM_ALGORITHMS,
        "odometry, ekf, fastslam1, fastslam2 (landmarks) or gridslam (laser and odometry); "
        f"default {DEFAULT_ALGORITHM}, and for `posegrid run` gridslam with --carmen or --bag",
        default=None,
    )
    group.add_argument(
        "--particles",
        type=pose_sample_count,
        default=particles,
        help="FastSLAM / grid FastSLAM particles (default %s)"
        % (particles or f"{NODE_PARTICLES} for FastSLAM, {DEFAULT_GRID_PARTICLES} for grid FastSLAM"),
    )
    add_choice(group, "--associate", ("known", "unknown"), "landmark correspondences: known ids (default) or estimated")
    add_choice(
        group,
        "--motion",
        ("velocity", "odometry"),
        "landmark filters: velocity commands (default) or odometry readings as controls",
    )
    add_choice(
        group,
        "--models",
        ("sim", "mrclam"),
        "noise-model defaults: the simulator's, or for a robot in the MRCLAM format the generic ones "
        "(slam.calibration.GENERIC; a robot's own: --calibration or --profile) (default: what the input is)",
        default=None,
    )
    add_calibration_options(group, auto=False)
    group.add_argument(
        "--alphas",
        default=None,
        metavar="A1,...",
        help="motion noise: 6 numbers (velocity model) or 4 (odometry model)",
    )
    group.add_argument("--sigma-range", type=finite_float, default=None, help="landmark range noise std in m")
    group.add_argument("--sigma-bearing", type=finite_float, default=None, help="landmark bearing noise std in rad")
    group.add_argument(
        "--range-fraction",
        type=finite_float,
        default=None,
        help="landmark range noise std grows by this many m per m of range",
    )
    group.add_argument(
        "--outlier-gate",
        type=finite_or_inf,
        default=None,
        metavar="D2",
        help="known ids: ignore a measurement beyond this squared Mahalanobis distance",
    )
    add_drive_angle_sd_option(group, "landmark filters: ", "the calibration's")
    group.add_argument(
        "--resample-threshold",
        type=finite_float,
        default=0.5,
        help="FastSLAM: resample when N_eff < this fraction of the particles (default 0.5)",
    )
    group.add_argument(
        "--plain-resampling",
        action="store_true",
        help="FastSLAM: resample the particles' map frames with them, as the textbook does "
        "(default: keep every frame, known ids only; docs/slam.md)",
    )
    add_filter_options(group, label="grid FastSLAM: ")


def slam_argv(args: argparse.Namespace, models: str) -> list[str]:
    """The SLAM options of ``args`` as arguments for a slam-node child (``models``: its noise-model defaults unless
    --models names them)."""
    algo = args.algo or DEFAULT_ALGORITHM
    reject_filter_options(args, algo)
    return ["--algo", algo, "--models", args.models or models, *option_argv(args, SLAM_NODE_OPTIONS)]


def _rate(text: str) -> float | None:
    from services.errors import UsageError
    from services.nodes.source import parse_rate

    try:
        return parse_rate(text)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


#: the most steps --sim simulates (each scan's 361 beams are kept: 1e8 ranges, as `posegrid simulate` allows; 10^9
#: steps grew a source's memory for minutes before it published anything)
MAX_SIM_STEPS = 10**8 // 361


#: steps of 0.1 s the built-in simulation runs when --steps is not given
DEFAULT_SIM_STEPS = 400


def sim_steps(args: argparse.Namespace) -> int:
    """The simulation's steps: --steps, else DEFAULT_SIM_STEPS."""
    return DEFAULT_SIM_STEPS if args.steps is None else args.steps


def _check_sim_steps(steps: int) -> None:
    """UsageError unless --steps is 1 .. MAX_SIM_STEPS."""
    from services.errors import UsageError

    if not 1 <= steps <= MAX_SIM_STEPS:
        raise UsageError(f"--steps must be 1 .. {MAX_SIM_STEPS} (7.7 hours of 0.1 s steps), got {steps}")


def _check_cell_size(resolution: float) -> None:
    """A map's cells must be CELL_SIZE_RANGE m, as its tile updates carry them (schemas.messages.TileUpdate)."""
    from services.errors import UsageError

    low, high = CELL_SIZE_RANGE
    if not low <= resolution <= high:
        raise UsageError(f"--resolution must be {low:g} .. {high:g} m for a map served over Zenoh, got {resolution}")


def _check_name(value: str, option: str) -> None:
    from schemas.messages import RESERVED_ROBOT_NAMES
    from schemas.wire import NAME_RULE, is_valid_name
    from services.errors import UsageError

    if not is_valid_name(value) or (option == "--robot" and value in RESERVED_ROBOT_NAMES):
        raise UsageError(
            f"{option} {value!r} is not a valid name ({NAME_RULE}{'; not map' if option == '--robot' else ''})"
        )


def _check_positive(args: argparse.Namespace, *names: str) -> None:
    from services.errors import UsageError

    for name in names:
        value = getattr(args, name)
        if value is not None and not value > 0:
            raise UsageError(f"--{name.replace('_', '-')} must be > 0, got {value}")


#: the options of a recorded input (the built-in simulation when none is given)
RECORDED_INPUTS = ("--posed", "--sim-dir", "--mrclam", "--carmen", "--bag")


def recorded_inputs(args: argparse.Namespace) -> dict[str, Path]:
    """The recorded inputs given (:data:`RECORDED_INPUTS`: option -> file or folder); empty for the simulation."""
    given = {option: getattr(args, option[2:].replace("-", "_"), None) for option in RECORDED_INPUTS}
    return {option: Path(path) for option, path in given.items() if path is not None}


def _check_log_options(args: argparse.Namespace) -> None:
    """--scan-topic is for a bag, --odom-delay for a laser log, --steps for the simulation."""
    from services.errors import UsageError

    if args.scan_topic is not None and args.bag is None:
        raise UsageError("--scan-topic names a topic of a ROS bag: give it with --bag")
    given = recorded_inputs(args)
    if args.steps is not None and given:  # (it replayed the whole input, saying nothing)
        option = next(iter(given))
        raise UsageError(f"--steps sets how long the built-in simulation runs; {option} replays its input whole")
    if args.odom_delay != 0.0 and args.carmen is None and args.bag is None:
        raise UsageError("--odom-delay shifts a laser log's odometry: give it with --carmen or --bag")
    if args.no_return_range is not None and args.carmen is None and args.bag is None:
        raise UsageError(
            "--no-return-range says how far a real laser's beams with no return clear: give it with --carmen or "
            "--bag (a simulated laser's clear up to its range_max; a posed-scan file's, as its format says)"
        )


def _laser_log(args: argparse.Namespace, command: str | None):
    """The laser log of --carmen or --bag (read by that format's reader, whatever the file's suffix), with its
    odometry read at --odom-delay; what the reader took for granted or skipped is noted on stderr as ``posegrid
    COMMAND`` (None: not noted, as `run`, whose source child reads the log again and notes it). Raises LogFormatError
    (exit 2) for a log that cannot be replayed."""
    from services.errors import UsageError
    from slam.carmen import read_carmen
    from slam.errors import LogFormatError
    from slam.laserlog import check_scan_order, no_return_note, with_odometry_delay
    from slam.rosbag_reader import read_rosbag

    log = read_carmen(args.carmen) if args.carmen is not None else read_rosbag(args.bag, scan_topic=args.scan_topic)
    try:
        log = with_odometry_delay(log, args.odom_delay)
    except LogFormatError as exc:
        raise UsageError(f"--odom-delay: {exc}") from None
    clearing = no_return_note(log, no_return_range(args))
    for remark in [*log.remarks(), *([clearing] if clearing else [])] if command is not None else ():
        print(f"posegrid {command}: note: {remark}", file=sys.stderr, flush=True)
    check_scan_order(log)
    return log


def _stream(args: argparse.Namespace):
    """The services.streams.Stream the input options describe."""
    from services import streams

    _check_log_options(args)

    if args.posed is not None:
        from schemas.files import load_posed_scans

        return streams.posed_stream(load_posed_scans(args.posed), args.robot)
    if args.sim_dir is not None:
        return streams.sim_folder_stream(args.sim_dir, args.robot)
    if args.mrclam is not None:
        return streams.mrclam_stream(args.mrclam, args.mrclam_robot, args.robot)
    if args.carmen is not None or args.bag is not None:
        return streams.laser_log_stream(_laser_log(args, "source"), args.robot, no_return_range(args))
    from slam.simulator import simulate_office

    steps = sim_steps(args)
    print(f"posegrid source[{args.robot}]: simulating {steps} steps of the office", file=sys.stderr, flush=True)
    return streams.sim_stream(simulate_office(seed=args.seed, steps=steps), args.robot)


# ------------------------------------------------------------------------------------------ handlers


def run_router(args: argparse.Namespace) -> int:
    """a Zenoh router in a Python process (for machines without zenohd)

    Route Zenoh traffic between posegrid processes. Listens on tcp/127.0.0.1:7447 unless --listen or
    --zenoh-config say otherwise; multicast scouting is off. Stops on Ctrl-C or SIGTERM."""
    from services.commands.zenoh_options import config_from_args
    from services.nodes.router import run_router as route
    from services.process import install_stop_event

    args.listen = [_port_chosen(endpoint) for endpoint in args.listen or []]
    config = config_from_args(args, "router")
    return route(config, install_stop_event("router"))


def _port_chosen(endpoint: str) -> str:
    """``endpoint`` with a port of 0 on loopback (tcp/127.0.0.1:0) replaced by a free port, so that the router says
    the port clients connect to (zenoh does not tell which it took); other endpoints as given."""
    from services.ports import free_port

    return f"tcp/127.0.0.1:{free_port()}" if endpoint == "tcp/127.0.0.1:0" else endpoint


def run_mapper(args: argparse.Namespace) -> int:
    """one map shard: fuses the scans into the tiles it owns, serves them over Zenoh

    A mapper shard. Owns the tiles that rendezvous hashing of (tile, shards 0..N-1) gives shard I, fuses every
    robot's scans (pg/*/scan) with their poses (pg/*/pose, joined by seq) into those tiles only, publishes tile
    updates on pg/map/MAP/tile/0/TX/TY at most every --publish-interval s per tile, answers tile and stats
    queries, and declares the liveliness token pg/map/MAP/alive/I. Fusion options mean what they mean for
    `posegrid fuse`."""
    from services.commands.zenoh_options import config_from_args
    from services.nodes.mapper import run_mapper as serve
    from services.process import install_stop_event

    config = shard_config(args)
    zenoh_config = config_from_args(args, "client")
    stop = install_stop_event(f"mapper[{config.shard}]")
    return serve(config, zenoh_config, stop, args.intake_buffer, persist_from_args(args))


def shard_config(args: argparse.Namespace):
    """The services.state.shard.ShardConfig of `posegrid mapper`'s options; UsageError (one sentence) for a bad one.
    `posegrid run` calls it on the argv it gives its shards before it starts any process."""
    from services.errors import UsageError

    if not 1 <= args.shards <= MAX_SHARDS or not 0 <= args.shard < args.shards:
        raise UsageError(
            f"need 1 <= --shards <= {MAX_SHARDS} and 0 <= --shard < --shards, got shard {args.shard} of {args.shards}"
        )
    _check_cell_size(args.resolution)
    if args.tile_size < 1 or args.tile_size & (args.tile_size - 1) or args.tile_size > MAX_TILE_SIZE:
        raise UsageError(f"--tile-size must be a power of 2 up to {MAX_TILE_SIZE}, got {args.tile_size}")
    if args.publish_interval < 0:
        raise UsageError(f"--publish-interval must be >= 0 s, got {args.publish_interval}")
    if args.join_buffer < 1 or args.intake_buffer < 1:
        raise UsageError("--join-buffer and --intake-buffer must be >= 1")
    _check_positive(args, "accuracy")
    refuse_bundle_with_ml(args)
    _check_name(args.map, "--map")
    threads = threads_from_args(args)
    from services.commands.mapping import sensor_model_from_args
    from services.state.shard import ShardConfig

    return ShardConfig(
        map_name=args.map,
        shard=args.shard,
        shards=args.shards,
        model=sensor_model_from_args(args),
        mode=args.mode,
        n_samples=args.samples,
        seed=args.seed,
        accuracy=args.accuracy,
        tile_size=args.tile_size,
        publish_interval=args.publish_interval,
        join_capacity=args.join_buffer,
        limits=limits_from_args(args),
        threads=threads,
        bundle=args.bundle,
    )


def run_source(args: argparse.Namespace) -> int:
    """publish a simulated world live, or replay a dataset, over Zenoh

    Publish one robot's scans (pg/ROBOT/scan), odometry, landmarks and, for a posed-scan file, poses
    (pg/ROBOT/pose), each tagged with the scan's seq, then an end-of-stream mark (pg/ROBOT/end). --rate max
    publishes as fast as the mapper shards and the SLAM node take (never more than --window scans or steps ahead
    of the slowest of those it waits for)."""
    from services.errors import UsageError

    _check_name(args.robot, "--robot")
    _check_name(args.map, "--map")
    if args.wait_mappers < 0 or args.window < 1:
        raise UsageError("--wait-mappers must be >= 0 and --window >= 1")
    _check_sim_steps(sim_steps(args))
    rate = _rate(args.rate)
    from services.commands.zenoh_options import config_from_args
    from services.nodes.source import Source, SourceOptions, SourceStalled
    from services.process import install_stop_event, until_stopped
    from services.zenoh_config import close_session, open_session

    stop = install_stop_event(f"source[{args.robot}]")
    zenoh_config = config_from_args(args, "client")
    stream = until_stopped(lambda: _stream(args), stop, "reading its input")  # (a long simulation or log: Stopped)
    options = SourceOptions(
        rate=rate, wait_mappers=args.wait_mappers, map_name=args.map, wait_slam=args.wait_slam, window=args.window
    )
    session = open_session(zenoh_config, "the source", stop)
    try:
        return Source(session, stream, options).run(stop)
    except SourceStalled as exc:
        print(f"posegrid source: error: {exc}", file=sys.stderr, flush=True)
        return 1
    finally:
        close_session(session, "the source")


#: resident memory a process of `posegrid run` takes from its start, bytes (a mapper shard measured 188 to 195 MB on
#: the simulated office; a warehouse scan's fusion scratch adds about 84 MB more)
PROCESS_BYTES = 200 * 2**20
#: the processes `posegrid run` starts beside its shards: itself, the router, a source, a SLAM node and the API
OTHER_PROCESSES = 5


def check_shards_fit(shards: int, available: int | None) -> None:
    """Refuse ``shards`` mapper shards that `posegrid run` could not start on this machine: with the other processes,
    PROCESS_BYTES each, more than ``available`` bytes (None: not known, not checked). 1 000 shards on a 2-core
    machine with 23 GB started until the kernel killed processes, this one among them."""
    from services.errors import UsageError

    if available is None:
        return
    need = (shards + OTHER_PROCESSES) * PROCESS_BYTES
    if need > available:
        raise UsageError(
            f"--shards {shards} would start {shards} mapper processes on this machine: about {need / 2**30:.1f} GiB "
            f"with the router, source, SLAM node and API ({PROCESS_BYTES >> 20} MiB each), and "
            f"{available / 2**30:.1f} GiB is available; run fewer shards, or start them on other machines with "
            "`posegrid mapper --shard K --shards N` (docs/architecture.md)"
        )


def run_pipeline(args: argparse.Namespace) -> int:
    """run the whole pipeline: router, source, SLAM node, mapper shards, HTTP API

    Start a Zenoh router, N mapper shards, the HTTP API and map viewer, a SLAM node (unless the input has
    poses) and a source, print where to look and show progress. Input: the built-in simulated office (default), a
    posed-scan file (--posed: scans and poses, no SLAM node), a simulator folder, a CARMEN log or a ROS bag (both
    with grid FastSLAM). An MRCLAM folder has no laser, so no map: replay it with `posegrid source --mrclam` and
    `posegrid slam-node`. When the replay ends the shards keep serving the map until Ctrl-C; with --export the map
    assembled from all shards is written and run exits 0. Ctrl-C stops every child cleanly."""
    from services.errors import UsageError

    _check_name(args.robot, "--robot")
    _check_name(args.map, "--map")
    if not 1 <= args.shards <= MAX_SHARDS:
        raise UsageError(f"--shards must be 1 .. {MAX_SHARDS}, got {args.shards}")
    check_shards_fit(args.shards, available_memory())
    _check_cell_size(args.resolution)
    if args.router_port is not None and not 0 < args.router_port < 65536:
        raise UsageError(f"--router-port must be a TCP port, got {args.router_port}")
    _check_positive(args, "accuracy", "resolution")
    refuse_bundle_with_ml(args)
    limits_from_args(args)  # (a limit out of range refused here, before any process starts)
    _check_log_options(args)
    threads = threads_from_args(args, default=max(1, available_cores() // args.shards))
    restarts = restart_policy(args)
    rate_text = args.rate or ("max" if args.export is not None else "realtime")
    _rate(rate_text)
    read = [*recorded_inputs(args).values(), *([Path(args.calibration)] if args.calibration else [])]
    check_outputs(args, tuple(read), {"export": "map"}, export="--export")
    if not args.no_api:
        if not 0 < args.api_port < 65536:
            raise UsageError(f"--api-port must be a TCP port (1..65535), got {args.api_port}")
        check_port_free("127.0.0.1", args.api_port, "--api-port")
    if args.router_port is not None:  # (taken by another run's router, this run's children joined that run)
        check_port_free("127.0.0.1", args.router_port, "--router-port")
    from services.nodes.launcher import Plan
    from services.nodes.launcher import run_pipeline as launch
    from services.process import install_stop_event

    plan = Plan(
        map_name=args.map,
        robot=args.robot,
        shards=args.shards,
        resolution=args.resolution,
        mapper_argv=fusion_argv(args) + limit_argv(args) + ["--threads", str(threads)],
        source_argv=["--rate", rate_text],
        export=args.export,
        router_port=args.router_port,
        api_port=None if args.no_api else args.api_port,
        api_argv=[] if args.no_api else api_child_options(args),
    )
    _plan_input(args, plan)
    _check_children(plan)
    plan.restart = restarts
    plan.secure = args.secure
    plan_state(args, plan)
    return launch(plan, install_stop_event())


def _check_children(plan) -> None:
    """Parse and check the options `run` gives its shards and its SLAM node as those commands will (UsageError, one
    sentence, before any process starts or any state is written): `run --sigma0 -1` started a router and a shard,
    which refused it, and exited 1 with the launcher's lines."""
    from services.cli import build_parser

    parser = build_parser()
    mapper = ["mapper", "--shard", "0", "--shards", str(plan.shards), "--map", plan.map_name, *plan.mapper_argv]
    shard_config(parser.parse_args(mapper))
    if plan.slam_argv is not None:
        node_config(parser.parse_args(["slam-node", "--robot", plan.robot, *plan.slam_argv]))


def _plan_input(args: argparse.Namespace, plan: Plan) -> None:
    """Fill in what ``plan`` replays: the input's scan count, the source's and the SLAM node's options and the
    description, after checking the input (UsageError when it cannot be run)."""
    from services.errors import UsageError

    if args.ros2:
        from services.commands.ros2 import plan_ros2

        plan_ros2(args, plan)
    elif args.posed is not None:
        from schemas.files import load_posed_scans

        plan.scans = len(load_posed_scans(args.posed).stamps)  # validates the file before anything starts
        plan.source_argv += ["--posed", str(args.posed)]
        plan.description = f"replaying {args.posed} (scans and poses) into {args.shards} shard(s)"
    elif args.mrclam is not None:
        raise UsageError(
            "an MRCLAM folder holds no laser scans, so there is no map to build; publish its poses "
            "with `posegrid source --mrclam` and `posegrid slam-node` instead"
        )
    elif args.carmen is not None or args.bag is not None:
        option, log = ("--carmen", args.carmen) if args.carmen is not None else ("--bag", args.bag)
        if args.algo not in (None, "gridslam"):
            raise UsageError(
                f"{'a CARMEN log' if option == '--carmen' else 'a ROS bag'} has no landmarks: its SLAM "
                "node must be --algo gridslam"
            )
        args.algo = "gridslam"
        plan.scans = len(_laser_log(args, None))  # read here too: a log that cannot be replayed stops run at once
        plan.source_argv += [f"{option}={log}"]  # (with "=": a file named "-x.bag" is no option)
        if args.scan_topic is not None:
            plan.source_argv += [f"--scan-topic={args.scan_topic}"]
        if args.odom_delay != 0.0:
            plan.source_argv += ["--odom-delay", repr(args.odom_delay)]
        if args.no_return_range is not None:  # (at most grid FastSLAM's --max-range, as `posegrid slam` writes it:
            from services.commands.gridslam import gridslam_config  # past it the live map cleared 50 m for 30)

            reach = min(args.no_return_range, gridslam_config(args).max_range)
            plan.source_argv += ["--no-return-range", repr(reach)]
        plan.slam_argv = slam_argv(args, "sim")
        plan.description = f"replaying {log} through grid FastSLAM into {args.shards} shard(s)"
    elif args.sim_dir is not None:
        from schemas.files import load_posed_scans
        from slam.simlog import load_sim_log

        scans_path = args.sim_dir / "scans.npz"
        if not scans_path.is_file():
            raise UsageError(f"{args.sim_dir} has no scans.npz: there is no laser to map with")
        log = load_sim_log(args.sim_dir)
        plan.scans = len(load_posed_scans(scans_path).stamps)
        _use_sim_models(args, log.velocity_model if args.motion == "velocity" else log.odometry_model, log.sensor)
        plan.source_argv += ["--sim-dir", str(args.sim_dir)]
        plan.slam_argv = slam_argv(args, "sim")
        plan.description = (
            f"replaying {args.sim_dir} through {args.algo or DEFAULT_ALGORITHM} into {args.shards} shard(s)"
        )
    else:
        steps = sim_steps(args)
        _check_sim_steps(steps)
        plan.scans = steps
        plan.source_argv += ["--sim", "--seed", str(args.seed), "--steps", str(steps)]
        plan.slam_argv = slam_argv(args, "sim")
        plan.description = (
            f"simulating the office world (seed {args.seed}, {steps} steps of 0.1 s) through "
            f"{args.algo or DEFAULT_ALGORITHM} into {args.shards} shard(s)"
        )


def _use_sim_models(args: argparse.Namespace, motion, sensor) -> None:
    """Fill the noise options the user left unset with the simulator folder's own models (unless a calibration
    gives them)."""
    if args.profile is not None or args.calibration is not None:
        return
    if args.alphas is None:
        args.alphas = ",".join(repr(float(a)) for a in motion.alphas)
    if args.sigma_range is None:
        args.sigma_range = float(sensor.sigma_range)
    if args.sigma_bearing is None:
        args.sigma_bearing = float(sensor.sigma_bearing)
    if args.range_fraction is None:
        args.range_fraction = float(sensor.range_fraction)


def _slam_models(args: argparse.Namespace):
    """(motion model, landmark sensor model, outlier gate, calibration or None, map-scale sd, drive-angle sd rad) of
    --profile or --calibration, else of --models; then the noise overrides."""
    import inspect

    from services.commands.slam import chosen_calibration, noise_overrides, stated_drive_angle_sd
    from services.errors import UsageError
    from slam.calibration import GENERIC
    from slam.motion import MotionModel, OdometryMotionModel
    from slam.simulator import simulate_world

    motion: MotionModel
    if args.calibration == "auto":
        raise UsageError(
            "--calibration auto fits a calibration to a whole log, which a live node does not have: fit one with "
            "`posegrid calibrate` and give the file"
        )
    calibration = GENERIC if args.calibration == "none" else chosen_calibration(args)
    if calibration is not None and args.motion != "velocity":
        raise UsageError("a calibration is for velocity commands: drop --motion odometry")
    if calibration is None and (args.models or "sim") == "mrclam":
        calibration = GENERIC
    if calibration is not None:
        motion, sensor, gate = calibration.motion, calibration.sensor, calibration.outlier_gate
        scale_sd, drive_angle_sd = calibration.scale_sd, calibration.drive_angle_sd
    else:
        defaults = inspect.signature(simulate_world).parameters  # the simulator's own noise
        motion = defaults["velocity_model" if args.motion == "velocity" else "odometry_model"].default
        sensor, gate, scale_sd, drive_angle_sd = defaults["sensor"].default, None, 0.0, 0.0
    if args.motion == "odometry" and not isinstance(motion, OdometryMotionModel):
        motion = OdometryMotionModel()
    return (
        *noise_overrides(args, motion, sensor, gate),
        calibration,
        scale_sd,
        stated_drive_angle_sd(args, drive_angle_sd),
    )


def run_slam_node(args: argparse.Namespace) -> int:
    """run a SLAM filter on a robot's streams and publish its pose distribution per scan

    Follow robot ROBOT's odometry and landmarks (EKF-SLAM, FastSLAM, dead reckoning) or scans and odometry
    (grid FastSLAM), take the steps in seq order (a message for a seq already processed is reported as out of
    order), and publish per scan the pose distribution on pg/ROBOT/pose: mean and covariance, or particles and
    weights. The filter starts at --initial or at the prior the source publishes. Stats on pg/ROBOT/slam/stats."""
    from services.commands.zenoh_options import config_from_args
    from services.nodes.slam_node import run_slam_node as serve
    from services.process import install_stop_event

    config = node_config(args)
    return serve(config, config_from_args(args, "client"), install_stop_event(f"slam-node[{config.robot}]"))


def node_config(args: argparse.Namespace):
    """The services.state.slam.NodeConfig of `posegrid slam-node`'s options, its landmark filter built once at the
    origin to check them; UsageError (one sentence) for a bad one. `posegrid run` calls it on the argv it gives its
    SLAM node before it starts any process."""
    from services.errors import UsageError

    _check_name(args.robot, "--robot")
    if not 0 <= args.resample_threshold <= 1:
        raise UsageError(f"--resample-threshold must be in [0, 1], got {args.resample_threshold}")
    from services.commands.gridslam import gridslam_config
    from services.commands.slam import initial_pose, make_filter

    algo = args.algo or DEFAULT_ALGORITHM
    args.algo = algo
    reject_filter_options(args, algo)
    if args.max_landmarks is not None and algo in ("gridslam", "odometry"):
        raise UsageError(f"--max-landmarks bounds the landmark filters (ekf, fastslam1, fastslam2), not {algo}")
    if args.max_odometry_step is not None and algo != "gridslam":
        raise UsageError(f"--max-odometry-step bounds grid FastSLAM (--algo gridslam), not {algo}")
    motion, sensor, gate, calibration, scale_sd, drive_angle_sd = _slam_models(args)
    drive_angle = calibration.drive_angle if calibration is not None else 0.0
    initial = initial_pose(args.initial) if args.initial is not None else None
    grid_config = gridslam_config(args) if algo == "gridslam" else None
    import numpy as np

    from services.state.slam import NodeConfig
    from slam.odometry_jumps import MAX_ODOMETRY_STEP

    config = NodeConfig(
        robot=args.robot,
        algorithm=algo,
        make_filter=lambda start: make_filter(
            args,
            motion,
            sensor,
            gate,
            start,
            NODE_PARTICLES,
            scale_sd=scale_sd,
            drive_angle_sd=drive_angle_sd,
            drive_angle=drive_angle,
        ),
        motion=args.motion,
        initial=None if initial is None else np.array(initial),
        grid_config=grid_config,
        seed=args.seed,
        calibration=calibration,
        max_landmarks=args.max_landmarks,
        max_odometry_step=args.max_odometry_step or MAX_ODOMETRY_STEP,
    )
    if config.make_filter is not None and algo != "gridslam":
        try:
            config.make_filter(np.zeros(3) if initial is None else np.array(initial))
        except ValueError as exc:
            raise UsageError(f"a SLAM filter option is out of range: {exc}") from None
    return config
