"""`posegrid slam --algo gridslam LOG -o POSED.npz`: grid FastSLAM over a CARMEN log or a ROS bag.

The slam command (services/commands/slam.py) adds these options to its parser and hands over to
:func:`run_gridslam_command` when --algo is gridslam.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from services.commands.argtypes import (
    check_outputs,
    checked_output,
    finite_float,
    odom_delay_seconds,
    positive_number,
    refuse_another_kind,
)
from services.commands.options import add_scan_topic, dest, no_return_range, no_return_range_keywords
from slam.gridslam.config import SPARSE_LOG_DRIVE, SPARSE_MOTION_STEP
from slam.motion import HOLONOMIC_SHARE, sideways_watch
from slam.odometry_jumps import JUMP_FLOOR, MAX_ODOMETRY_SPEED, MAX_ODOMETRY_STEP, REBASE_STEPS, joined_odometry

if TYPE_CHECKING:
    import numpy as np

#: grid FastSLAM particles when --particles is not given: the least KLD-sampling keeps (GridSlamConfig.particle_cap
#: the most)
DEFAULT_GRID_PARTICLES = 30

#: --odom-delay auto runs the filter over this much of the log's start (s) to estimate the delay
AUTO_DELAY_SECONDS = 120.0
#: ... with this many particles: one is a scan matcher, whose headings are all the estimate reads (on the Freiburg 079
#: and MIT CSAIL bags it finds what 30 particles find, -0.10 and -0.13 to -0.14 s over seeds 0-2, in a twentieth of
#: the CPU time: 2 s against 40 s)
AUTO_DELAY_PARTICLES = 1
#: accepted --grid-resolution (m): finer than 1 cm is below a laser scanner's accuracy and, as each halving
#: quadruples the cells, soon needs more memory than a machine has; coarser than 1 m cannot hold a room's walls
GRID_RESOLUTION_LIMITS = (0.01, 1.0)
#: the most grid FastSLAM particles: each keeps a map (shared tiles, copied on write); 10 000 asked for 32 GiB
MAX_GRID_PARTICLES = 1000


def _odom_delay(text: str) -> str | float:
    """--odom-delay: "auto" or seconds."""
    if text == "auto":
        return text
    try:
        float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds or 'auto', got {text!r}") from None
    return odom_delay_seconds(text)


def _motion_step(text: str) -> str | float:
    """--motion-step: "auto", "off" or a positive length in m."""
    if text in ("auto", "off"):
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto', 'off' or metres, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a length > 0 in m, got {text!r}")
    return value


#: grid FastSLAM's filter options, shared by `posegrid slam`, `slam-node` and `run`: (option, GridSlamConfig field)
FILTER_OPTIONS = (
    ("--max-range", "max_range"),
    ("--linear-update", "linear_update"),
    ("--angular-update", "angular_update"),
    ("--grid-resolution", "resolution"),
    ("--min-range", "min_range"),
    ("--prior-cap", "prior_cap"),
    ("--particle-cap", "particle_cap"),
    ("--widen", "widen"),
    ("--loop-closure", "loop_closure"),
)


def _on_off(text: str) -> str:
    """--loop-closure: "on" or "off" (kept as text, so that `run` passes it on to its SLAM node as given)."""
    if text not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"expected 'on' or 'off', got {text!r}")
    return text


def filter_option_values(args: argparse.Namespace) -> list[tuple[str, str, float | str | None]]:
    """(option, GridSlamConfig field, the value given or None) for each of :data:`FILTER_OPTIONS`."""
    return [(option, field, getattr(args, option[2:].replace("-", "_"))) for option, field in FILTER_OPTIONS]


def reject_filter_options(args: argparse.Namespace, algo: str) -> None:
    """Raise UsageError when a grid FastSLAM filter option is given to another algorithm (it would be ignored)."""
    from services.errors import UsageError

    given = [option for option, _, value in filter_option_values(args) if value is not None]
    given += [option for option in ("--scans", "--no-return-range") if getattr(args, dest(option), None) is not None]
    if given and algo != "gridslam":
        raise UsageError(
            f"{', '.join(given)} only apply to grid FastSLAM, but the SLAM algorithm is {algo}; add "
            "--algo gridslam or drop them"
        )


def add_filter_options(group: argparse._ArgumentGroup, label: str = "") -> None:
    """Add :data:`FILTER_OPTIONS` to ``group`` (default None: GridSlamConfig's, shown in the help), each
    help text starting with ``label``."""
    from slam.gridslam.config import GridSlamConfig

    defaults = GridSlamConfig()
    helps = {
        "--max-range": f"m: beams are used up to here, longer ones only clear space (default {defaults.max_range:g}, "
        "at most the laser's)",
        "--linear-update": f"m of odometry between scans integrated into the maps (default {defaults.linear_update:g})",
        "--angular-update": f"rad of odometry turn between integrated scans (default {defaults.angular_update:g})",
        "--grid-resolution": f"m, cell size of the particles' grids, in [{GRID_RESOLUTION_LIMITS[0]:g}, "
        f"{GRID_RESOLUTION_LIMITS[1]:g}] (default {defaults.resolution:g})",
        "--min-range": f"m: shorter readings are ignored, e.g. people right beside the robot (default "
        f"{defaults.min_range:g}, or the sensor's if larger)",
        "--prior-cap": "squared Mahalanobis distance from the odometry beyond which the scan matcher stops weighing "
        f"the odometry (default {defaults.prior_cap:g}; larger trusts the odometry more)",
        "--particle-cap": "the most particles KLD-sampling grows the set to while the scans leave the pose open "
        f"(--particles is the least; default {defaults.particle_cap}; at most --particles: a fixed count, the "
        "default, chosen by leave-one-out on the shared logs, docs/gridslam.md)",
        "--widen": "after a failed match, the next proposal's motion variances (and its yaw search's square) are "
        f"this many times larger, >= 1 (default {defaults.widen:g}: not widened, chosen by leave-one-out; a failed "
        "match never weighs the particles)",
        "--loop-closure": "'on' (default): search old submaps over a wide window for a loop the particles lost, and "
        "correct the path and the grids through a pose graph; 'off': the particles alone (less CPU, and about 7 kB "
        "less memory per integrated scan; docs/gridslam.md, 'Loop closure')",
    }
    types: dict[str, Callable[[str], object]] = {"--particle-cap": int, "--loop-closure": _on_off}
    for option, _ in FILTER_OPTIONS:
        group.add_argument(
            option,
            type=types.get(option, finite_float),
            default=None,
            metavar={"--prior-cap": "D2", "--particle-cap": "N", "--widen": "FACTOR", "--loop-closure": "on|off"}.get(
                option
            ),
            help=label + helps[option],
        )


def add_max_odometry_step(group: argparse._ArgumentGroup) -> None:
    """--max-odometry-step (slam.odometry_jumps), for `posegrid slam --algo gridslam`, `slam-node` and `run`."""
    group.add_argument(
        "--max-odometry-step",
        type=positive_number,
        default=None,
        metavar="M",
        help="m: the farthest grid FastSLAM's odometry may move from one scan to the next (and at most "
        f"{MAX_ODOMETRY_SPEED:g} m/s past {JUMP_FLOOR:g} m); a farther step is left out, unless {REBASE_STEPS} in a "
        "row agree with each other: an odometry reset, joined to the odometry before as if the robot had not moved "
        f"across it (default {MAX_ODOMETRY_STEP:g})",
    )


def add_gridslam_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of --algo gridslam (INPUT is then a CARMEN log .clf/.log/.gz or a ROS 1/2 bag)."""
    group = parser.add_argument_group(
        "grid FastSLAM (--algo gridslam: INPUT is a CARMEN log .clf/.log/.gz or a ROS bag; --particles "
        f"defaults to {DEFAULT_GRID_PARTICLES}; docs/gridslam.md)"
    )
    group.add_argument(
        "--poses-output",
        default=None,
        metavar="POSES.npz",
        help="pose-distribution file: every scan, the final particles' trajectories with the final "
        "weights (default: OUTPUT with the suffix .poses.npz)",
    )
    group.add_argument(
        "--best-output",
        default=None,
        metavar="BEST.npz",
        help="posed-scan file: the integrated scans at the final best particle's poses, one sample "
        "each, for its map (default: OUTPUT with the suffix .best.npz)",
    )
    add_filter_options(group)
    group.add_argument(
        "--odom-delay",
        type=_odom_delay,
        default=None,
        metavar="SECONDS|auto",
        help="read each scan's odometry this many seconds after its stamp (negative: before), for a "
        "laser whose stamps run late against the odometry's; 'auto' estimates it by running the "
        f"filter (one particle: a scan matcher) over the first {AUTO_DELAY_SECONDS:.0f} s and comparing its "
        "scan-matched turns with the odometry's (needs a separate odometry stream). Default: auto where the "
        "log has a separate odometry stream (a bag's odometry topic, a CARMEN log's ODOM lines) long enough to "
        "compare, else 0 (docs/gridslam.md, 'Laser and odometry clocks')",
    )
    group.add_argument(
        "--scans",
        type=int,
        default=None,
        metavar="N",
        help="use only the log's first N scans, e.g. to try options quickly on a long log (default: all)",
    )
    group.add_argument(
        "--odometry-model",
        choices=("auto", "diff", "omni"),
        default="auto",
        help="the odometry's noise: 'diff' turns, drives and turns (a differential drive's), 'omni' travels in any "
        "direction with the noise of the turn made (a holonomic base's, or a robot frame whose x axis is not the "
        "driving direction); 'auto' (default): omni where the odometry travels sideways (more than 45 deg off its "
        f"heading) for more than {100 * HOLONOMIC_SHARE:.0f} %% of its distance, else diff (docs/gridslam.md)",
    )
    group.add_argument(
        "--motion-step",
        type=_motion_step,
        default="auto",
        metavar="auto|off|METRES",
        help="the drive the odometry noise describes: with METRES, a longer drive between two integrated scans is as "
        "many such drives, whose variances add; 'off': each integrated drive gets the model's variances; 'auto' "
        f"(default): {SPARSE_MOTION_STEP:g} m for a sparse log (a median drive between scans of "
        f"{SPARSE_LOG_DRIVE:g} m or more), else off (docs/gridslam.md, 'Sparse logs')",
    )
    add_max_odometry_step(group)
    add_scan_topic(group)
    group.add_argument(
        "--no-return-range",
        **no_return_range_keywords(
            "the posed scans written (OUTPUT, BEST.npz; the filter's own map clears up to --max-range): "
        ),
    )
    group.add_argument(
        "--stats", default=None, metavar="OUT.json", help="write timing and effective-sample-size figures as JSON"
    )


def gridslam_config(args: argparse.Namespace):
    from dataclasses import replace

    from services.errors import UsageError
    from slam.gridslam import GridSlamConfig

    overrides = {
        "particles": DEFAULT_GRID_PARTICLES if args.particles is None else args.particles,
        "resample_threshold": args.resample_threshold,
    }
    for _, field, value in filter_option_values(args):
        if value is not None:
            overrides[field] = value == "on" if isinstance(value, str) else value
    config = replace(GridSlamConfig(), **overrides)
    for option, count in (("--particles", config.particles), ("--particle-cap", config.particle_cap)):
        if count > MAX_GRID_PARTICLES:
            raise UsageError(
                f"{option} for grid FastSLAM must be at most {MAX_GRID_PARTICLES} (each particle keeps a map), "
                f"got {count}"
            )
    low, high = GRID_RESOLUTION_LIMITS
    if not low <= config.resolution <= high:
        raise UsageError(f"--grid-resolution must be in [{low:g}, {high:g}] m, got {config.resolution:g}")
    try:
        config.validate()
    except ValueError as exc:
        raise UsageError(f"grid FastSLAM option out of range: {exc}") from None
    if config.linear_update < 0 or config.angular_update < 0:
        raise UsageError("--linear-update and --angular-update must be >= 0")
    if config.angular_update > 2.0 * math.pi:  # (30 was taken: almost five turns, never reached)
        raise UsageError(
            f"--angular-update {config.angular_update:g} is more than a full turn: give it in rad (30 deg is "
            f"{math.radians(30):.4f})"
        )
    return config


def _output_paths(args: argparse.Namespace) -> tuple[Path, Path]:
    """The best-particle and pose-distribution paths (--best-output, --poses-output or their defaults beside
    OUTPUT), each output checked by :func:`checked_output`; raise UsageError when one cannot be written or two of
    OUTPUT, those two and --stats name one file (one would overwrite the other)."""
    from services.errors import UsageError

    check_outputs(
        args,
        inputs=(args.input,),
        kinds={"output": "poses", "best_output": "poses", "poses_output": "poses"},
        output="-o",
        best_output="--best-output",
        poses_output="--poses-output",
        stats="--stats",
    )
    best = args.best_output or checked_output(args.output.with_suffix(".best.npz"), "--best-output's default")
    poses = args.poses_output or checked_output(args.output.with_suffix(".poses.npz"), "--poses-output's default")
    refuse_another_kind(best, "poses", "--best-output")
    refuse_another_kind(poses, "poses", "--poses-output")
    named = [
        ("-o", args.output),
        ("--best-output" if args.best_output else "--best-output's default", best),
        ("--poses-output" if args.poses_output else "--poses-output's default", poses),
    ]
    named += [("--stats", args.stats)] if args.stats is not None else []
    seen: dict[Path, str] = {}
    for option, path in named:
        if path.resolve() in seen:
            raise UsageError(f"{seen[path.resolve()]} and {option} both name {path}: give each output its own file")
        seen[path.resolve()] = option
    return best, poses


def _check_log(log, config) -> None:
    """Raise LogFormatError unless the log holds at least 2 scans, in increasing time order, of which at least 2
    have a beam at or beyond the minimum range (the first scan starts the maps, the next is matched to them)."""
    import numpy as np

    from slam.errors import LogFormatError
    from slam.laserlog import check_scan_order

    if len(log) < 2:
        raise LogFormatError(
            f"{log.source}: holds {len(log)} usable scan; grid FastSLAM needs at least 2 (a scan to "
            "start from and one to integrate)"
        )
    check_scan_order(log)
    range_min = np.maximum(log.range_min, config.min_range)
    usable = int(np.count_nonzero((log.ranges >= range_min[:, None]).any(axis=1)))  # (NaN padding: never)
    if usable < 2:
        raise LogFormatError(
            f"{log.source}: only {usable} of its {len(log)} scans have a reading of at least "
            f"{range_min.min():g} m (--min-range); grid FastSLAM needs at least 2"
        )


def _apply_odometry_delay(args: argparse.Namespace, log, config):
    """The log with its odometry read at --odom-delay, and the delay in s. Without it, the delay is estimated
    where the log can time one and is 0 elsewhere (said on stderr when the log has an odometry stream whose stamps
    cannot time it); 'auto' on a log that cannot time one is refused."""
    from services.errors import UsageError
    from slam.errors import LogFormatError
    from slam.laserlog import with_odometry_delay

    wanted = args.odom_delay
    if wanted is None or wanted == "auto":
        problem, has_stream = _untimeable(log)
        if problem and wanted == "auto":
            raise UsageError(f"--odom-delay auto: {problem}; give the delay in seconds, or 0")
        if problem and has_stream:
            print(f"posegrid slam: odometry delay 0 s (not estimated: {problem})", file=sys.stderr)
        delay = 0.0 if problem else _estimated_delay(args, log, config, asked=wanted == "auto")
    else:
        delay = float(wanted)
    try:
        return with_odometry_delay(log, delay), delay
    except LogFormatError as exc:
        raise UsageError(f"--odom-delay: {exc}") from None


def _untimeable(log) -> tuple[str, bool]:
    """Why an odometry delay cannot be estimated on the log ("" when it can: a separate odometry stream in time
    order, and stamps not in bursts, slam.timealign.bursty_stamps), and whether it has an odometry stream."""
    from slam.errors import LogFormatError
    from slam.laserlog import check_odometry_stream
    from slam.timealign import bursty_stamps

    try:
        check_odometry_stream(log)
    except LogFormatError as exc:  # (a stream that goes back in time is said; none at all needs no saying)
        return str(exc), len(log.odom_stamps) > 0
    problem = bursty_stamps(log.stamps, log.odom_stamps)
    return (f"{log.source}: {problem}" if problem else ""), True


def _estimated_delay(args: argparse.Namespace, log, config, asked: bool) -> float:
    """The odometry delay (s) estimated by running the filter with AUTO_DELAY_PARTICLES over the log's first
    AUTO_DELAY_SECONDS (a log that can time one, :func:`_untimeable`); a trajectory too short to compare is refused
    (UsageError) where --odom-delay auto was ``asked`` for, else read with 0."""
    from dataclasses import replace

    import numpy as np
    from tqdm import tqdm

    from services.errors import UsageError
    from slam.gridslam import run_gridslam
    from slam.timealign import odometry_delay

    count = int(np.searchsorted(log.stamps, log.stamps[0] + AUTO_DELAY_SECONDS))
    head = log.first(max(count, 2))
    with tqdm(
        total=len(head), desc="odometry delay", unit="scan", file=sys.stderr, mininterval=0.5, disable=None
    ) as bar:
        matcher = replace(config, particles=AUTO_DELAY_PARTICLES, particle_cap=AUTO_DELAY_PARTICLES)
        trial = run_gridslam(head, matcher, seed=args.seed, progress=lambda done, ess: bar.update(done))
    try:
        delay, mismatch = odometry_delay(
            trial.stamps, trial.samples[:, trial.best, 2], log.odom_stamps, log.odom_poses[:, 2]
        )
    except ValueError as exc:
        if asked:
            raise UsageError(f"--odom-delay auto: {exc}") from None
        print(f"posegrid slam: odometry delay 0 s (not estimated: {exc})", file=sys.stderr)
        return 0.0
    print(
        f"posegrid slam: odometry delay {delay:+.2f} s, estimated over the first {len(head)} scans "
        f"(mean heading mismatch {np.degrees(mismatch):.2f} deg per 0.5 s)",
        file=sys.stderr,
    )
    return delay


def run_gridslam_command(args: argparse.Namespace) -> int:
    """Run grid FastSLAM over args.input and write three files (docs/gridslam.md, "Output"):
    OUTPUT, a posed-scan file of the integrated scans with every final particle's trajectory and the final
    weights (`posegrid fuse` makes the Monte Carlo map);
    the .best.npz posed-scan file with the final best particle's poses (its map); and the .poses.npz
    pose-distribution file with every scan's pose on each final particle's trajectory (for the relation
    error)."""
    from schemas.files import write_atomically

    config = gridslam_config(args)
    best_path, poses_path = _output_paths(args)
    before = time.process_time()
    log, config, delay, sideways = _prepared_log(args, config)
    reading_cpu = time.process_time() - before  # (reading the log, and estimating the delay where it is)
    started = time.perf_counter()
    cpu_started = time.process_time()
    result = _run_filter(log, config, args.seed)
    elapsed = time.perf_counter() - started
    cpu = time.process_time() - cpu_started
    _save_outputs(args.output, best_path, poses_path, log, config, result, no_return_range(args))
    stats = _run_stats(log, config, result, delay, elapsed, cpu)
    stats["odometry_sideways_share"] = sideways
    stats["cpu_seconds_reading"] = reading_cpu
    _report_health(stats)
    if args.stats is not None:
        text = json.dumps(stats, indent=1) + "\n"
        write_atomically(args.stats, lambda handle: handle.write(text.encode()))
    print(
        f"wrote {args.output} (posed-scan file, {stats['integrated']} integrated scans), {best_path} (the best "
        f"particle's poses) and {poses_path} (pose-distribution file, {len(log)} scans): "
        f"{1e3 * stats['seconds_per_integrated_scan']:.1f} ms per "
        f"integrated scan, {stats['log_duration_s']:.0f} s of log in {elapsed:.1f} s ({stats['real_time_factor']:.1f}x "
        f"real time), final N_eff {stats['final_ess']:.1f} of {stats['final_particles']}, {stats['resamplings']} "
        "resamplings"
    )
    return 0


def _report_health(stats: dict) -> None:
    """Print the run's health summary (slam.gridslam.health) on stderr: one line, and a warning line for each
    thing that went wrong (scans that stayed unmatched, a trajectory farther from the log's own poses than its
    odometry)."""
    summary = stats["health_summary"]
    reference = stats.get("reference")
    if summary["median_matched"] is None:  # (NaN in the stats' JSON: no scan but the first was integrated)
        line = (
            f"posegrid slam: health: {summary['scans']} integrated scan(s), none matched against a map (the first "
            "starts it; the next is integrated once the odometry moves --linear-update m or turns --angular-update "
            "rad)"
        )
    else:
        line = (
            f"posegrid slam: health: matched-beam fraction median {summary['median_matched']:.2f} (5th percentile "
            f"{summary['low_matched']:.2f}), {summary['failed']} of {summary['scans']} integrated scans failed to "
            f"match, {summary['mean_particles']:.1f} particles on average (at most {summary['max_particles']})"
        )
    if reference is not None:
        line += (
            f"; against the poses the log states: best trajectory {reference['best_rmse_m']:.3f} m, odometry "
            f"{reference['odometry_rmse_m']:.3f} m (RMS)"
        )
    print(line, file=sys.stderr)
    for warning in summary["warnings"]:
        print(f"posegrid slam: warning: {warning}", file=sys.stderr)


def _prepared_log(args: argparse.Namespace, config):
    """The laser log of args.input (its first --scans scans) with its odometry read at --odom-delay, checked by
    :func:`_check_log` before and after the delay, ``config`` with its odometry model (--odometry-model), the
    delay in s and the share of the odometry's distance travelled sideways."""
    from services.commands.logs import read_log
    from services.errors import UsageError
    from slam.laserlog import no_return_note

    if args.scans is not None and args.scans < 2:
        raise UsageError(f"--scans must be >= 2 (a scan to start from and one to integrate), got {args.scans}")
    log = read_log(args.input, scan_topic=args.scan_topic)
    if args.scans is not None:
        log = log.first(args.scans)
    _check_log(log, config)
    config, sideways = _odometry_model(args.odometry_model, log, config)
    config = _sparse_log(args.motion_step, log, config)
    log, delay = _apply_odometry_delay(args, log, config)
    log = joined_odometry(log, args.max_odometry_step or MAX_ODOMETRY_STEP)
    clearing = no_return_note(log, no_return_range(args), config.max_range)
    for remark in [*log.remarks(), *([clearing] if clearing else [])]:  # (after the delay, which skips scans)
        print(f"posegrid slam: note: {remark}", file=sys.stderr)
    _check_log(log, config)
    return log, config, delay, sideways


def _odometry_model(choice: str, log, config):
    """``config`` with the odometry model ``choice`` (auto: :class:`slam.motion.SidewaysWatch`'s verdict on the log's
    odometry; said on stderr when it is omni), and the share of the odometry's distance travelled sideways."""
    from dataclasses import replace

    watch = sideways_watch(log.odometry)
    share = watch.share()
    holonomic = choice == "omni" or (choice == "auto" and watch.verdict() is True)
    if choice == "auto" and holonomic:
        print(
            f"posegrid slam: note: the odometry travels sideways for {share:.0%} of its distance: a holonomic base, "
            "or a robot frame whose x axis is not the driving direction; using the omni odometry model "
            "(--odometry-model diff to refuse it)",
            file=sys.stderr,
        )
    return replace(config, holonomic=holonomic), share


def _sparse_log(choice: str | float, log, config):
    """``config`` with the motion step ``choice`` (--motion-step; auto: the log's, slam.gridslam.filter.
    sparse_motion_step, said on stderr when the log is sparse)."""
    from dataclasses import replace

    from slam.gridslam.config import median_scan_drive, sparse_motion_step

    if choice == "off":
        return replace(config, motion_step=None)
    if choice != "auto":
        return replace(config, motion_step=float(choice))
    step = sparse_motion_step(log.odometry)
    if step is not None:
        print(
            f"posegrid slam: note: a sparse log (its scans lie {median_scan_drive(log.odometry):.2f} m apart, median): "
            f"a drive between two scans is taken as drives of {step:g} m whose noise adds up (--motion-step off to "
            "refuse it)",
            file=sys.stderr,
        )
    return replace(config, motion_step=step)


def _run_filter(log, config, seed: int):
    """slam.gridslam.run_gridslam over ``log``, with a progress bar on stderr that shows the effective sample
    size."""
    from tqdm import tqdm

    from slam.gridslam import run_gridslam

    total, taken, said = len(log), [0], [0]
    lines = not sys.stderr.isatty()  # (the bar is off: a line at every tenth instead, for a log file or CI)
    with tqdm(total=total, desc="slam gridslam", unit="scan", file=sys.stderr, mininterval=0.5, disable=None) as bar:

        def progress(done: int, ess: float) -> None:
            bar.update(done)
            bar.set_postfix(ess=f"{ess:.1f}", refresh=False)
            taken[0] += done
            if lines and taken[0] < total and taken[0] * 10 // total > said[0]:
                said[0] = taken[0] * 10 // total
                print(f"posegrid slam: {taken[0]} of {total} scans (effective sample size {ess:.1f})", file=sys.stderr)

        return run_gridslam(log, config, seed=seed, progress=progress)


def posed_no_returns(
    ranges: np.ndarray, range_max: np.ndarray, limit: np.ndarray, no_return_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """(ranges (T, B) m, range_max (T,) m) for a posed-scan file of scans whose laser states ``range_max`` (T,) m,
    mapped up to ``limit`` (T,) m, whose beams with no return clear up to ``no_return_range`` m. The format clears a
    beam with no return up to the file's range_max, so with a no-return range of 0 those beams become 0 (no reading,
    which says nothing) and with one below ``limit`` the file's range_max becomes it (a return beyond then clears up
    to it too, as GMapping's maxUrange)."""
    import numpy as np

    ranges = np.array(ranges, dtype=np.float32)
    no_return = np.isposinf(ranges) | (ranges > range_max[:, None])  # (NaN, the beams past a row's count, stays)
    if no_return_range == 0.0:
        ranges[no_return] = 0.0
        return ranges, np.asarray(limit, np.float64)
    return ranges, np.minimum(limit, no_return_range)


def _save_outputs(output: Path, best_path: Path, poses_path: Path, log, config, result, no_return_range: float) -> None:
    """Write the three files of :func:`run_gridslam_command` from the filter's ``result``, the posed scans' beams
    with no return clearing up to ``no_return_range`` m (:func:`posed_no_returns`)."""
    import numpy as np

    from schemas.files import PoseDistributionFile, PosedScans, PoseSet, save_pose_distribution, save_posed_scans

    chosen = result.integrated
    scans = log.select(chosen)  # each with its own geometry, the range limits the filter used
    ranges, range_max = posed_no_returns(
        scans.ranges, scans.range_max, np.minimum(scans.range_max, config.max_range), no_return_range
    )

    def posed(samples, weights) -> PosedScans:
        return PosedScans(
            ranges=ranges,
            angle_min=scans.angle_min,
            angle_increment=scans.angle_increment,
            range_min=np.maximum(scans.range_min, config.min_range),
            range_max=range_max,
            stamps=scans.stamps,
            sensor_offset=scans.sensor_offset,
            poses=PoseSet(samples=samples, weights=weights),
            beams=scans.beams,
        )

    weights = np.tile(result.weights, (len(log), 1))
    save_posed_scans(output, posed(result.samples[chosen], weights[chosen]))
    best = result.samples[chosen][:, [result.best]]
    save_posed_scans(best_path, posed(best, np.ones((int(chosen.sum()), 1))))
    save_pose_distribution(
        poses_path, PoseDistributionFile(stamps=result.stamps, poses=PoseSet(samples=result.samples, weights=weights))
    )


def _run_stats(log, config, result, delay: float, elapsed: float, cpu: float) -> dict:
    """The figures --stats writes: times (s) of ``elapsed`` wall and ``cpu`` time (the filter's run; the caller adds
    ``cpu_seconds_reading``, reading the log and estimating its odometry delay), effective sample sizes,
    resamplings, tiles, the odometry ``delay`` (s), the odometry model (the caller adds the share of the odometry's
    distance travelled sideways), the loop closer's counts, the health of every integrated scan
    (columns, one value per integrated scan) and its summary, and the errors against the poses the log states where
    it states others than its odometry."""
    duration = float(log.stamps[-1] - log.stamps[0])
    health, summary, reference = _health_figures(log, result)
    return {
        "scans": len(log),
        "integrated": int(result.integrated.sum()),
        "particles": config.particles,
        "seconds_total": elapsed,
        "cpu_seconds_total": cpu,
        "seconds_per_scan": elapsed / len(log),
        "seconds_per_integrated_scan": float(result.seconds.mean()) if len(result.seconds) else 0.0,
        "log_duration_s": duration,
        "real_time_factor": duration / max(elapsed, 1e-9),
        "final_ess": float(result.ess[-1]) if len(result.ess) else float(config.particles),
        "mean_ess": float(result.ess.mean()) if len(result.ess) else float(config.particles),
        "resamplings": int(result.resampled.sum()),
        "motion_fallbacks": result.fallbacks,
        "tiles_in_use": result.maps.tiles_in_use,
        "tiles_copied": result.maps.copies,
        "odometry_delay_s": delay,
        "odometry_model": "omni" if config.holonomic else "diff",
        "motion_step_m": config.motion_step,
        "final_particles": len(result.weights),
        "loop_closure": result.loops,
        "health_summary": summary,
        "reference": reference,
        "health": health,
    }


def _health_figures(log, result) -> tuple[dict, dict, dict | None]:
    """(per-scan health columns, summary, reference errors or None) of a run; the summary gains a warning when the
    best trajectory ends farther from the log's stated poses than its odometry."""
    import math

    from slam.gridslam.health import ScanHealth, reference_errors, summarize

    columns: dict[str, list] = {name: [] for name in ScanHealth.__dataclass_fields__}
    for record in result.health:
        for name, value in record.as_dict().items():
            columns[name].append(round(value, 5) if isinstance(value, float) else value)
    columns["stamp"] = [round(float(t), 6) for t in result.stamps[result.integrated]]
    summary = summarize(list(result.health)).as_dict()
    summary = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in summary.items()}
    errors = reference_errors(result.samples[:, result.best], log.odometry, log.poses)
    if errors is None:
        return columns, summary, None
    if errors[0] >= errors[1]:
        summary["warnings"].append(
            f"the best trajectory is farther from the poses the log states ({errors[0]:.3f} m RMS) than its own "
            f"odometry is ({errors[1]:.3f} m): this run ended worse than its odometry"
        )
    return columns, summary, {"best_rmse_m": errors[0], "odometry_rmse_m": errors[1]}
