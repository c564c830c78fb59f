"""Subcommands on the SLAM side: simulate, slam, eval-traj (docs/slam.md).

Units everywhere: metres, radians, seconds; poses are (x, y, yaw) in the map frame.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from services.commands.argtypes import (
    INPUT_FOLDER_FILES,
    check_outputs,
    checked_output,
    finite_float,
    finite_or_inf,
    path_argument,
    pose_sample_count,
    random_seed,
)
from services.commands.options import add_choice, add_command, dest

if TYPE_CHECKING:
    from slam.motion import MotionModel
    from slam.range_bearing import RangeBearingModel
    from slam.sequence import SlamSequence

ALGORITHMS = ("odometry", "ekf", "fastslam1", "fastslam2", "gridslam")
#: FastSLAM particles of `posegrid slam` when --particles is not given: on MRCLAM dataset 7, 29 of 30 runs (robots
#: 1-5, both FastSLAMs, seeds 0-2) keep the truth inside the 95 % region at >= 85 % of the steps with 2 000, far
#: fewer with 500, at 16x real time or faster (docs/slam.md)
DEFAULT_PARTICLES = 2000
#: s within which a simulator folder's scan stamps must equal its controls' step stamps
STAMP_TOLERANCE = 1e-6
#: eval-traj: an estimate's step is scored when its stamp lies within this many s of the ground truth's span
#: (MRCLAM estimates end about 7 ms after their ground truth; farther out, the held end pose is no truth)
TRUTH_MARGIN = 0.05
#: simulate: the most ranges (steps x beams) one run holds, 400 MB of float32
MAX_SIMULATED_RANGES = 10**8
#: simulate's options: the slam.simulator.simulate_office argument each sets and the values it takes, [low, high]
#: (the office is 20 m x 12 m, its robot drives at 0.5 m/s)
SIMULATION_OPTIONS = {
    "--steps": ("steps", 1, 100_000),
    "--beams": ("n_beams", 1, 100_000),
    "--dt": ("dt", 1e-3, 1.0),
    "--resolution": ("truth_resolution", 5e-3, 1.0),
    "--laser-sigma": ("laser_sigma", 0.0, 1.0),
    "--fov": ("fov", 1e-3, 2 * math.pi),
    "--range-max": ("range_max", 0.1, 1000.0),
}
#: MRCLAM: the shortest --period in s; the commands come at about 67 Hz, so a finer grid adds steps (and memory:
#: steps x particles x 3 floats) without information
MIN_PERIOD = 0.01
#: defaults of the options whose default is None in the parser, so that an option given to an algorithm that
#: would ignore it can be told from one left alone (:func:`_refuse_ignored_options`)
DEFAULT_SEED = 0
DEFAULT_RESAMPLE_THRESHOLD = 0.5
SLAM_DEFAULTS = {
    "seed": DEFAULT_SEED,
    "associate": "known",
    "motion": "velocity",
    "resample_threshold": DEFAULT_RESAMPLE_THRESHOLD,
}
#: MRCLAM: the default --period in s (a simulator folder has a pose at every step and refuses --period)
DEFAULT_PERIOD = 0.2

_LANDMARK_FILTERS = ("ekf", "fastslam1", "fastslam2")
_FASTSLAMS = ("fastslam1", "fastslam2")
#: the algorithms each option of `posegrid slam` applies to (grid FastSLAM's own options: gridslam.py)
OPTION_ALGORITHMS = {
    "--particles": _FASTSLAMS + ("gridslam",),
    "--seed": _FASTSLAMS + ("gridslam",),
    "--resample-threshold": _FASTSLAMS + ("gridslam",),
    "--plain-resampling": _FASTSLAMS,
    "--associate": _LANDMARK_FILTERS,
    "--sigma-range": _LANDMARK_FILTERS,
    "--sigma-bearing": _LANDMARK_FILTERS,
    "--range-fraction": _LANDMARK_FILTERS,
    "--outlier-gate": _LANDMARK_FILTERS,
    "--fixed-noise": _LANDMARK_FILTERS,
    "--drive-angle-sd": _LANDMARK_FILTERS,
    **dict.fromkeys(
        ("--alphas", "--robot", "--initial", "--period", "--profile", "--calibration", "--motion"),
        ("odometry",) + _LANDMARK_FILTERS,
    ),
    **dict.fromkeys(  # (a delay of 0, the default, counts as not given)
        ("--stats", "--scan-topic", "--best-output", "--poses-output", "--odom-delay", "--max-odometry-step"),
        ("gridslam",),
    ),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    _add_simulate(subparsers)
    _add_slam(subparsers)
    _add_eval_traj(subparsers)


def _add_simulate(subparsers: argparse._SubParsersAction) -> None:
    simulate = add_command(subparsers, "simulate", run_simulate)
    simulate.add_argument("outdir", help="folder to write (created if missing)")
    simulate.add_argument("--seed", type=random_seed, default=0, help="seed of every noise source (default 0)")
    simulate.add_argument("--steps", type=int, default=400, help="number of steps (default 400)")
    simulate.add_argument("--dt", type=finite_float, default=0.1, help="step length in s (default 0.1)")
    simulate.add_argument("--beams", type=int, default=361, help="laser beams per scan (default 361)")
    simulate.add_argument("--fov", type=finite_float, default=math.pi, help="laser field of view in rad (default pi)")
    simulate.add_argument("--range-max", type=finite_float, default=12.0, help="laser maximum range in m (default 12)")
    simulate.add_argument(
        "--laser-sigma", type=finite_float, default=0.01, help="laser range noise std in m (default 0.01)"
    )
    simulate.add_argument(
        "--resolution", type=finite_float, default=0.05, help="truth raster cell size in m (default 0.05)"
    )


def _add_slam(subparsers: argparse._SubParsersAction) -> None:
    slam = add_command(subparsers, "slam", run_slam)
    slam.add_argument(
        "input", type=path_argument, help="simulator folder or MRCLAM folder (gridslam: a CARMEN log or ROS bag)"
    )
    slam.add_argument("-o", "--output", required=True, metavar="OUTPUT.npz", help=".npz to write")
    slam.add_argument(
        "--algo",
        choices=ALGORITHMS,
        required=True,
        help="odometry: dead reckoning (baseline); ekf: EKF-SLAM; fastslam1 / fastslam2: FastSLAM; "
        "gridslam: grid FastSLAM on a laser log",
    )
    slam.add_argument(
        "--particles", type=pose_sample_count, default=None, help=f"FastSLAM particles (default {DEFAULT_PARTICLES:d})"
    )
    slam.add_argument(
        "--seed",
        type=random_seed,
        default=None,
        help=f"seed of the particle filter (default {DEFAULT_SEED:d})",
    )
    add_choice(
        slam,
        "--associate",
        ("known", "unknown"),
        "landmark correspondences: known ids (default) or estimated (EKF: nearest in "
        "Mahalanobis distance with gating; FastSLAM: per-particle maximum likelihood)",
        default=None,
    )
    add_mrclam_input_options(slam, "output a pose")
    add_calibration_options(slam)
    add_heading_frame_option(slam, "with --calibration auto")
    add_choice(
        slam,
        "--motion",
        ("velocity", "odometry"),
        "simulator: the velocity commands (default) or the odometry readings as controls",
        default=None,
    )
    _add_noise_options(slam)
    from services.commands.gridslam import add_gridslam_arguments  # grid FastSLAM (--algo gridslam)

    add_gridslam_arguments(slam)


def _add_noise_options(slam: argparse.ArgumentParser) -> None:
    """The noise-model options of `posegrid slam`, in their own --help group."""
    from slam.motion import ALPHA_LIMITS
    from slam.range_bearing import RANGE_FRACTION_LIMITS, SIGMA_BEARING_LIMITS, SIGMA_RANGE_LIMITS

    noise = slam.add_argument_group(
        "noise models (defaults: the calibration's, or a simulator folder's own models; these override them)"
    )
    noise.add_argument(
        "--alphas",
        type=str,
        default=None,
        metavar="A1,...",
        help="motion noise: 6 numbers for the velocity model (PR table 5.3, variances per "
        f"0.1 s), 4 for the odometry model (PR table 5.6); each in [{ALPHA_LIMITS[0]:g}, {ALPHA_LIMITS[1]:g}]",
    )
    noise.add_argument(
        "--sigma-range",
        type=finite_float,
        default=None,
        help=f"landmark range noise std in m, in [{SIGMA_RANGE_LIMITS[0]:g}, {SIGMA_RANGE_LIMITS[1]:g}]",
    )
    noise.add_argument(
        "--sigma-bearing",
        type=finite_float,
        default=None,
        help=f"landmark bearing noise std in rad, in [{SIGMA_BEARING_LIMITS[0]:g}, pi]",
    )
    noise.add_argument(
        "--range-fraction",
        type=finite_float,
        default=None,
        help="landmark range noise std grows by this many m per m of range (on top of --sigma-range), "
        f"in [{RANGE_FRACTION_LIMITS[0]:g}, {RANGE_FRACTION_LIMITS[1]:g}]",
    )
    noise.add_argument(
        "--outlier-gate",
        type=finite_or_inf,
        default=None,
        metavar="D2",
        help="known ids: ignore a measurement whose squared Mahalanobis distance exceeds D2 "
        "(FastSLAM: per particle, likelihood capped at D2); 'inf' turns it off",
    )
    add_drive_angle_sd_option(noise, "landmark filters: ", "the calibration's")
    noise.add_argument(
        "--fixed-noise",
        action="store_true",
        help="landmark filters: keep the noise models as given (default: inflate them while the innovations show "
        "the filter overconfident, slam.consistency)",
    )
    noise.add_argument(
        "--resample-threshold",
        type=finite_float,
        default=None,
        help=f"FastSLAM: resample when N_eff < this fraction of the particles (default {DEFAULT_RESAMPLE_THRESHOLD:g})",
    )
    noise.add_argument(
        "--plain-resampling",
        action="store_true",
        help="FastSLAM: resample the particles' map frames with them, as the textbook does "
        "(default: keep every frame, known ids only; docs/slam.md)",
    )


def _add_eval_traj(subparsers: argparse._SubParsersAction) -> None:
    evaluate = add_command(subparsers, "eval-traj", run_eval_traj)
    evaluate.add_argument("poses", type=path_argument, help="pose-distribution or posed-scan .npz")
    evaluate.add_argument(
        "groundtruth", type=path_argument, help="pose .npz, simulator folder or RobotK_Groundtruth.dat"
    )


# ------------------------------------------------------------------------------------------------ simulate


def _simulation_folder(text: str) -> Path:
    """OUTDIR of `posegrid simulate`, created if missing (its parent must exist), after checking that it can hold
    every one of :data:`slam.simlog.SIMULATION_FILES` (UsageError otherwise, naming the path and what to do)."""
    from schemas.files import output_folder_problem
    from services.errors import UsageError
    from slam.simlog import SIMULATION_FILES

    if not text:
        raise UsageError("OUTDIR '': an empty path names no folder; give the folder to write")
    folder = Path(text)
    problem = output_folder_problem(folder)
    if problem is not None:
        raise UsageError(f"OUTDIR {folder}: {problem}")
    held = sorted(p.name for pattern in INPUT_FOLDER_FILES for p in folder.glob(pattern)) if folder.is_dir() else []
    if held:  # (a simulation written beside an MRCLAM folder's tables is what `slam` then reads: theirs are lost)
        shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
        raise UsageError(
            f"OUTDIR {folder}: holds another dataset's files ({shown}); a simulation goes in a folder of its own: "
            "give a new or empty one"
        )
    try:
        folder.mkdir(exist_ok=True)
    except OSError as exc:
        raise UsageError(f"OUTDIR {folder}: cannot be created ({exc.strerror}); give a folder that can") from None
    for name in SIMULATION_FILES:
        checked_output(folder / name, "OUTDIR's")
    return folder


def run_simulate(args: argparse.Namespace) -> int:
    """simulate a robot in an office: odometry, landmarks, laser scans, ground truth

    Simulate a robot driving through a 20 m x 12 m office (corridor, six rooms with doors, furniture, 37 point
    landmarks) and write OUTDIR/scans.npz (posed scans at the TRUE poses), truth.npz (truth raster),
    groundtruth.npz (true poses as a pose-distribution file), controls.npz (velocity commands and odometry
    readings) and landmarks.npz (range-bearing measurements); docs/slam.md describes the last two. The same --seed
    gives the same files."""
    from services.errors import UsageError

    for option, (_, low, high) in SIMULATION_OPTIONS.items():
        _check_limits(option, getattr(args, dest(option)), (low, high))
    if args.steps * args.beams > MAX_SIMULATED_RANGES:
        raise UsageError(
            f"--steps x --beams is {args.steps * args.beams}, more than the {MAX_SIMULATED_RANGES:.0e} "
            "ranges a run may hold (each scan's beams are kept in memory)"
        )
    import numpy as np

    from schemas.files import (
        PoseDistributionFile,
        PosedScans,
        PoseSet,
        TruthRaster,
        save_arrays,
        save_pose_distribution,
        save_posed_scans,
        save_truth,
        written_together,
    )
    from slam.simlog import sim_log_arrays
    from slam.simulator import simulate_office

    args.outdir = _simulation_folder(args.outdir)
    run = simulate_office(
        seed=args.seed, **{name: getattr(args, dest(option)) for option, (name, _, _) in SIMULATION_OPTIONS.items()}
    )
    truth_poses = PoseSet(samples=run.true_poses[:, None, :], weights=np.ones((len(run.stamps), 1)))
    with written_together():  # (the five files are one run: a failed write leaves the folder's old run whole)
        save_posed_scans(args.outdir / "scans.npz", PosedScans.from_scans(run, truth_poses))
        save_truth(
            args.outdir / "truth.npz",
            TruthRaster(run.truth_occupied, run.truth_visible, run.truth_origin, run.truth_resolution),
        )
        save_pose_distribution(
            args.outdir / "groundtruth.npz", PoseDistributionFile(stamps=run.stamps, poses=truth_poses)
        )
        for name, arrays in sim_log_arrays(run.log()).items():
            save_arrays(args.outdir / name, arrays)
    print(
        f"wrote {args.outdir}: {len(run.stamps)} steps of {args.dt} s, {run.ranges.shape[1]} beams, "
        f"{len(run.landmarks)} landmarks, {len(run.landmark_step)} landmark measurements, "
        f"truth raster {run.truth_occupied.shape[1]} x {run.truth_occupied.shape[0]} cells"
    )
    return 0


# ------------------------------------------------------------------------------------------------ slam


def _floats(text: str, count: tuple[int, ...], option: str) -> list[float]:
    from services.errors import UsageError

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise UsageError(f"{option} takes comma-separated numbers, got '{text}'") from None
    if len(values) not in count or not all(math.isfinite(v) for v in values):
        raise UsageError(f"{option} takes {' or '.join(map(str, count))} finite numbers, got '{text}'")
    return values


def add_mrclam_input_options(parser: argparse.ArgumentParser, each: str) -> None:
    """--robot K, --initial X,Y,YAW and --period PERIOD (s) of an MRCLAM input; ``each`` says what happens every
    PERIOD s (e.g. "output a pose")."""
    parser.add_argument("--robot", type=int, default=None, help="MRCLAM: robot number K (RobotK_*.dat)")
    add_initial_option(parser, "MRCLAM: start pose in m, m, rad (default: the first ground-truth pose)")
    parser.add_argument(
        "--period",
        type=finite_float,
        default=None,
        help=f"MRCLAM: {each} at least every PERIOD s besides every landmark-measurement "
        f"stamp (default {DEFAULT_PERIOD:g}, at least {MIN_PERIOD:g})",
    )


def add_initial_option(parser: argparse.ArgumentParser, help: str) -> None:
    """--initial X,Y,YAW: where the filter starts (read by :func:`initial_pose`; None when not given)."""
    parser.add_argument("--initial", default=None, metavar="X,Y,YAW", help=help)


def add_calibration_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup, auto: bool = True) -> None:
    """--profile NAME and --calibration FILE (with ``auto``: also 'auto' and 'none'), read by
    :func:`chosen_calibration`."""
    from slam.calibration import PROFILES

    parser.add_argument(
        "--profile",
        choices=sorted(PROFILES),
        default=None,
        help="a named calibration of the robot's data and noise (mrclam7: MRCLAM dataset 7's, fitted to its ground "
        "truth; docs/slam.md)",
    )
    parser.add_argument(
        "--calibration",
        default=None,
        metavar="FILE" + ("|auto|none" if auto else ""),
        help="a calibration file (from `posegrid calibrate`)"
        + (
            "; 'auto' fits one to INPUT first, without ground truth (the default for an MRCLAM folder); 'none' "
            "takes the data as logged with generic noise (slam.calibration.GENERIC); a simulator folder uses the "
            "noise it was made with unless this or --profile is given"
            if auto
            else " (default: none, the data as logged with generic noise)"
        ),
    )


def add_heading_frame_option(parser: argparse.ArgumentParser, when: str) -> None:
    """--heading-frame: what the robot's heading is, which decides how the self-calibration splits the disagreement
    of drive and camera (slam.heading_frames.HEADING_FRAMES; a module with no imports: the parser is built on every
    start)."""
    from slam.heading_frames import HEADING_FRAMES

    parser.add_argument(
        "--heading-frame",
        choices=sorted(HEADING_FRAMES),
        default=None,
        help=f"{when}: what your robot's heading (its ground truth's, the initial pose's) is: 'drive', the direction "
        "it drives in (ROS's base_link); 'sensor', its camera's axis; 'unknown' (the default). The data show only how "
        "drive and camera disagree in angle: it goes to the camera, to the drive, or half to each with the drive "
        "angle's sd at the half (docs/slam.md, 'Drive angle')",
    )


def chosen_calibration(args: argparse.Namespace):
    """The calibration of --profile or --calibration FILE (None for neither, 'auto' or 'none'); UsageError when
    both are given."""
    from services.errors import UsageError
    from slam.calibration import named_calibration

    if args.profile is not None and args.calibration is not None:
        raise UsageError("give --profile or --calibration, not both")
    path = None if args.calibration in (None, "auto", "none") else args.calibration
    return named_calibration(args.profile, path)


def initial_pose(text: str) -> list[float]:
    """--initial X,Y,YAW (m, m, rad), each within +-POSE_LIMIT (the bound every pose message keeps to)."""
    import math

    from schemas.files import YAW_LIMIT
    from schemas.messages import POSE_LIMIT
    from services.errors import UsageError

    pose = _floats(text, (3,), "--initial")
    if max(abs(v) for v in pose) > POSE_LIMIT:
        raise UsageError(f"--initial takes a pose within +-{POSE_LIMIT:g} m (rad), got '{text}'")
    if abs(pose[2]) > YAW_LIMIT:
        raise UsageError(
            f"--initial's yaw {pose[2]:g} is more than a full turn: give it in rad (90 deg is {math.radians(90):.4f})"
        )
    return pose


def mrclam_input(args: argparse.Namespace):
    """The MRCLAM robot of --robot in ``args.input``: (run, sequence_at(delay) the filter input as logged with its
    commands delayed by ``delay`` s, notes on what was skipped)."""
    import numpy as np

    from services.errors import UsageError
    from slam import mrclam

    robots = mrclam.find_robots(args.input)
    if args.robot is None:
        raise UsageError(f"{args.input} is an MRCLAM folder: pick a robot with --robot K (here: {robots})")
    if getattr(args, "motion", "velocity") != "velocity":
        raise UsageError("MRCLAM logs hold velocity commands only: drop --motion odometry")
    period = DEFAULT_PERIOD if args.period is None else args.period
    if not period >= MIN_PERIOD:
        raise UsageError(
            f"--period must be at least {MIN_PERIOD:g} s (the commands come about every 0.015 s), got {period:g}"
        )
    initial = np.array(initial_pose(args.initial)) if args.initial is not None else None
    run = mrclam.read_mrclam(args.input, args.robot)
    usable = len(run.measurements)
    if getattr(args, "algo", None) != "odometry" and run.skipped_invalid > usable:
        raise UsageError(  # (negated ranges or bearings in degrees ran as dead reckoning, exit 0)
            f"{args.input} robot {args.robot}: {run.skipped_invalid} of its "
            f"{run.skipped_invalid + usable} landmark measurements have a range <= 0 m or a bearing beyond a full "
            f"turn, more than the {usable} usable: is its Measurement file in m and rad? (--algo odometry does "
            "without them)"
        )

    def sequence_at(delay: float):
        return mrclam.mrclam_sequence(run, initial_pose=initial, period=period, command_delay=delay)

    before_start = len(run.measurements) - len(sequence_at(0.0).measurements)  # mrclam_sequence leaves them out
    notes = (
        f"skipped {run.skipped_robots} measurements of robots, {run.skipped_unknown} of barcodes "
        f"in no table, {run.skipped_outside} stamped outside the odometry's time span, "
        f"{before_start} before the filter's start and "
        f"{run.skipped_invalid} with a range <= 0 m or a bearing beyond a full turn"
    )
    return run, sequence_at, notes


def sim_folder_input(args: argparse.Namespace):
    """A simulator folder's log, after refusing the options that are for MRCLAM folders."""
    from services.errors import UsageError
    from slam.simlog import load_sim_log

    if args.robot is not None or args.initial is not None:
        raise UsageError("--robot and --initial are for MRCLAM folders; a simulator folder starts at its true pose")
    if args.period is not None:
        raise UsageError("--period is for MRCLAM folders; a simulator folder has a pose at every step")
    return load_sim_log(args.input)


def landmark_input_kind(path: Path) -> Literal["sim", "mrclam"]:
    """Whether INPUT is a simulator folder (it holds controls.npz) or an MRCLAM folder (Barcodes.dat and a
    RobotK_Odometry.dat); UsageError when it is neither, or both (which files to read would be a guess)."""
    from services.errors import UsageError
    from slam import mrclam
    from slam.simlog import CONTROLS_FILE

    if not path.exists():
        raise UsageError(f"{path}: no such folder")
    sim = (path / CONTROLS_FILE).is_file()
    mrclam_folder = mrclam.is_mrclam_folder(path)
    if sim and mrclam_folder:
        raise UsageError(
            f"{path}: holds both a simulator log ({CONTROLS_FILE}) and an MRCLAM dataset (Barcodes.dat, "
            "RobotK_Odometry.dat); give a folder with one of them"
        )
    if sim:
        return "sim"
    if mrclam_folder:
        return "mrclam"
    raise UsageError(
        f"{path}: neither a simulator folder (no {CONTROLS_FILE}) nor an MRCLAM folder "
        "(no Barcodes.dat and RobotK_Odometry.dat)"
    )


@dataclass
class SlamInput:
    """What `posegrid slam` runs a landmark filter over: the sequence (corrected by the calibration), the models,
    the outlier gate, the map scale's sd, the posed scans to carry along (or None) and notes for the output line."""

    sequence: SlamSequence
    motion: MotionModel
    sensor: RangeBearingModel
    gate: float | None
    scale_sd: float
    drive_angle: float
    drive_angle_sd: float
    scans: Path | None
    notes: list[str]


def _self_calibrated(args: argparse.Namespace, sequence_at, delays):
    """--calibration auto: the calibration fitted to the input (slam.selfcal), and a note on it."""
    from services.errors import UsageError
    from slam.calibration import GENERIC
    from slam.selfcal import NotEnoughData, self_calibrate

    if args.associate != "known":
        raise UsageError("--calibration auto needs the landmark ids: use --associate known, or a calibration file")
    started = time.perf_counter()
    try:
        calibration = self_calibrate(
            sequence_at,
            delays=delays,
            source=f"posegrid slam {args.input}",
            heading_frame=args.heading_frame or "unknown",
        ).calibration
    except NotEnoughData as exc:
        return GENERIC, (
            f"not self-calibrated ({exc}): generic noise, the data as logged. It was chosen on simulated robots of "
            "0.15 to 2 m/s (a1 up to 0.3, a4 up to 0.2): a noisier robot may get overconfident poses; calibrate on a "
            "longer run of it (posegrid calibrate) and give --calibration FILE"
        )
    return calibration, f"self-calibrated in {time.perf_counter() - started:.1f} s: {calibration.summary()}"


def _load_input(args: argparse.Namespace) -> SlamInput:
    """The filter input of ``args.input`` with the calibration the options choose (docs/slam.md, "Calibration")."""
    from services.errors import UsageError
    from slam.calibration import GENERIC

    chosen = chosen_calibration(args)
    if args.heading_frame is not None and (chosen is not None or args.calibration == "none"):
        raise UsageError(
            "--heading-frame applies to the self-calibration (--calibration auto); a calibration file or profile "
            "states its own bearing bias and drive angle"
        )
    if landmark_input_kind(args.input) == "sim":
        log = sim_folder_input(args)
        scans = args.input / "scans.npz"
        scans_path = scans if scans.is_file() else None
        if chosen is None and args.calibration in (None, "none"):  # the noise the folder was made with
            if args.heading_frame is not None:
                raise UsageError("--heading-frame applies to the self-calibration: add --calibration auto")
            motion = log.velocity_model if args.motion == "velocity" else log.odometry_model
            return SlamInput(log.sequence(args.motion), motion, log.sensor, None, 0.0, 0.0, 0.0, scans_path, [])
        if args.motion != "velocity":
            raise UsageError("a calibration is for velocity commands: drop --motion odometry")
        notes = []
        if chosen is None:
            chosen, note = _self_calibrated(args, lambda delay: log.sequence(), (0.0,))
            notes.append(note)
        if chosen.command_delay:
            notes.append(f"a simulator folder's commands take no delay (the calibration's: {chosen.command_delay:g} s)")
        return _calibrated(chosen.apply(log.sequence()), chosen, scans_path, notes)
    _, sequence_at, skipped = mrclam_input(args)
    notes = [skipped]
    if chosen is None and args.calibration == "none":
        chosen = GENERIC
    elif chosen is None:
        from slam.selfcal import DELAY_GRID

        chosen, note = _self_calibrated(args, sequence_at, DELAY_GRID)
        notes.append(note)
    return _calibrated(chosen.apply(sequence_at(chosen.command_delay)), chosen, None, notes)


def _calibrated(sequence, calibration, scans: Path | None, notes: list[str]) -> SlamInput:
    """The :class:`SlamInput` of a corrected ``sequence`` with ``calibration``'s models; UsageError when the
    corrections made a measured range no range (the readers take only ranges > 0 m: a calibration fitted to
    another robot's sensor, whose range correction c0 + c2 bearing^2 passes 0 at its bearings, failed deep in the
    filter with "measured range must be finite and within ...")."""
    import numpy as np

    from services.errors import UsageError

    ranges = sequence.measurements[:, 0]
    bad = ~(np.isfinite(ranges) & (ranges > 0.0))
    if bad.any():
        c0, c2 = calibration.range_calibration
        raise UsageError(
            f"the calibration turns {int(bad.sum())} of the {len(ranges)} measured ranges to <= 0 m or not finite "
            f"(its range correction {c0:g} + {c2:g} bearing^2, at bearings up to "
            f"{float(np.abs(sequence.measurements[:, 1]).max()):.2f} rad): it was fitted to another sensor; give "
            "another --profile or --calibration (auto fits one to this input, none leaves it as logged)"
        )
    return SlamInput(
        sequence,
        calibration.motion,
        calibration.sensor,
        calibration.outlier_gate,
        calibration.scale_sd,
        calibration.drive_angle,
        calibration.drive_angle_sd,
        scans,
        notes,
    )


def _check_limits(option: str, value: float, limits: tuple[float, float]) -> None:
    """Raise UsageError unless low <= value <= high for ``limits`` = (low, high) (the option's units)."""
    from services.errors import UsageError

    low, high = limits
    if not low <= value <= high:
        raise UsageError(f"{option} must be in [{low:g}, {high:g}], got {value:g}")


def noise_overrides(args: argparse.Namespace, motion, sensor, gate):
    from dataclasses import replace

    from services.errors import UsageError
    from slam.motion import ALPHA_LIMITS, VelocityMotionModel
    from slam.range_bearing import RANGE_FRACTION_LIMITS, SIGMA_BEARING_LIMITS, SIGMA_RANGE_LIMITS

    if args.alphas is not None:
        count = 6 if isinstance(motion, VelocityMotionModel) else 4
        alphas = _floats(args.alphas, (count,), "--alphas")
        for alpha in alphas:
            _check_limits("--alphas", alpha, ALPHA_LIMITS)
        motion = replace(motion, alphas=tuple(alphas))
    limits = {
        "sigma_range": SIGMA_RANGE_LIMITS,
        "sigma_bearing": SIGMA_BEARING_LIMITS,
        "range_fraction": RANGE_FRACTION_LIMITS,
    }
    for name, name_limits in limits.items():
        value = getattr(args, name)
        if value is not None:
            _check_limits(f"--{name.replace('_', '-')}", value, name_limits)
            sensor = replace(sensor, **{name: value})
    if args.outlier_gate is not None:
        if not args.outlier_gate > 0:
            raise UsageError(f"--outlier-gate must be > 0 (or inf), got {args.outlier_gate}")
        gate = None if math.isinf(args.outlier_gate) else args.outlier_gate
    return motion, sensor, gate


def add_drive_angle_sd_option(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup, who: str, default: str
) -> None:
    """--drive-angle-sd RAD, read by :func:`stated_drive_angle_sd`; ``who`` leads its help, ``default`` names what
    stands without it."""
    parser.add_argument(
        "--drive-angle-sd",
        type=finite_float,
        default=None,
        metavar="RAD",
        help=f"{who}the sd (rad) of the robot's drive angle, the angle between its drive direction and its heading (a "
        "crab; docs/slam.md, 'Drive angle'): the positions given out are turned about the start by that much; in "
        f"[0, 0.5] (default: {default})",
    )


def stated_drive_angle_sd(args: argparse.Namespace, calibration_sd: float) -> float:
    """The drive angle's sd (rad): --drive-angle-sd where given (checked against its limits), else the
    calibration's, ``calibration_sd``."""
    from slam.calibration import DRIVE_ANGLE_SD_LIMITS

    stated = getattr(args, "drive_angle_sd", None)
    if stated is None:
        return calibration_sd
    _check_limits("--drive-angle-sd", stated, DRIVE_ANGLE_SD_LIMITS)
    return float(stated)


def make_filter(
    args: argparse.Namespace,
    motion,
    sensor,
    gate,
    initial,
    default_particles: int = DEFAULT_PARTICLES,
    scale_sd: float = 0.0,
    drive_angle_sd: float = 0.0,
    drive_angle: float = 0.0,
):
    """The filter of --algo with the given models, outlier gate, map-scale sd, drive-angle sd (rad) and drive angle
    (rad: the filter runs in the drive's frame) (slam.calibration), adaptive noise unless --fixed-noise."""
    from services.errors import UsageError
    from slam.dead_reckoning import DeadReckoning
    from slam.ekf import EKFSLAM
    from slam.fastslam import FastSLAM
    from slam.landmark_filter import LandmarkOptions

    known = args.associate == "known"
    adaptive = not getattr(args, "fixed_noise", False)
    if args.algo == "odometry":
        return DeadReckoning(motion, initial, drive_angle)
    options = LandmarkOptions(
        known_correspondences=known,
        outlier_gate=gate,
        adaptive=adaptive,
        scale_sd=scale_sd,
        drive_angle=drive_angle,
        drive_angle_sd=drive_angle_sd,
    )
    if args.algo == "ekf":
        return EKFSLAM(motion, sensor, initial, **options)
    particles = default_particles if args.particles is None else args.particles
    if not 0 <= args.resample_threshold <= 1:
        raise UsageError(f"--resample-threshold must be in [0, 1], got {args.resample_threshold}")
    return FastSLAM(
        motion,
        sensor,
        initial,
        n_particles=particles,
        version=1 if args.algo == "fastslam1" else 2,
        seed=args.seed,
        resample_threshold=args.resample_threshold,
        preserve_gauge=not args.plain_resampling,
        **options,
    )


def _given(value: object) -> bool:
    """Whether an option's parsed value says it was given: not its default None, nor False for a flag. (By
    identity: ``0 in (None, False)`` is true, and --seed 0 passed for not given.)"""
    return value is not None and value is not False


def _refuse_ignored_options(args: argparse.Namespace) -> None:
    """Raise UsageError when an option is given to an algorithm that would ignore it (:data:`OPTION_ALGORITHMS`;
    grid FastSLAM's own options: :func:`services.commands.gridslam.reject_filter_options`), then put the
    defaults of :data:`SLAM_DEFAULTS` in place of the options left alone."""
    from services.commands.gridslam import reject_filter_options
    from services.errors import UsageError

    reject_filter_options(args, args.algo)
    ignored = [
        option
        for option, algorithms in OPTION_ALGORITHMS.items()
        if args.algo not in algorithms and _given(getattr(args, dest(option)))
    ]
    if ignored:
        users = sorted({algo for option in ignored for algo in OPTION_ALGORITHMS[option]}, key=ALGORITHMS.index)
        raise UsageError(
            f"{', '.join(ignored)} {'does' if len(ignored) == 1 else 'do'} not apply to --algo "
            f"{args.algo} (only to {', '.join(users)}): drop {'it' if len(ignored) == 1 else 'them'} "
            "or pick another --algo"
        )
    for name, value in SLAM_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def run_slam(args: argparse.Namespace) -> int:
    """estimate the pose distribution: dead reckoning, EKF-SLAM, FastSLAM 1.0/2.0 or grid FastSLAM

    Run a SLAM filter over INPUT, a simulator folder (from 'posegrid simulate') or a UTIAS MRCLAM dataset folder
    (with --robot), or grid FastSLAM (--algo gridslam) over a laser log: a CARMEN log or a ROS bag. Output: with a
    simulator folder that holds scans.npz, a posed-scan file (its scans with the filter's pose distribution at
    every scan); otherwise a pose-distribution file. EKF and odometry give mean+cov per step; FastSLAM gives
    particles and their weights before resampling. The filter starts at the true first pose (simulator; MRCLAM
    ground truth) or at --initial. Landmark positions are estimated, never read from the input's truth."""
    _refuse_ignored_options(args)
    check_outputs(args, inputs=(args.input,), kinds={"output": "poses"}, output="-o")
    if args.algo == "gridslam":  # laser logs: services/commands/gridslam.py
        from services.commands.gridslam import run_gridslam_command

        return run_gridslam_command(args)
    from dataclasses import replace

    import numpy as np
    from tqdm import tqdm

    from schemas.errors import FormatError
    from schemas.files import PoseDistributionFile, PoseSet, load_posed_scans, save_pose_distribution, save_posed_scans
    from slam.sequence import run_filter

    loaded = _load_input(args)
    sequence, scans_path = loaded.sequence, loaded.scans
    motion, sensor, gate = noise_overrides(args, loaded.motion, loaded.sensor, loaded.gate)
    sequence.validate(str(args.input))
    scans = load_posed_scans(scans_path) if scans_path is not None else None
    if scans is not None and len(scans.stamps) != len(sequence):
        raise FormatError(f"{scans_path}: holds {len(scans.stamps)} scans but the controls have {len(sequence)} steps")
    if scans is not None and not np.allclose(scans.stamps, sequence.stamps, rtol=0.0, atol=STAMP_TOLERANCE):
        step = int(np.argmax(np.abs(scans.stamps - sequence.stamps) > STAMP_TOLERANCE))
        raise FormatError(
            f"{scans_path}: scan {step} is stamped {scans.stamps[step]:.6f} s but the controls' step "
            f"{step} {sequence.stamps[step]:.6f} s; the scans must be those of the controls' steps"
        )
    slam_filter = make_filter(
        args,
        motion,
        sensor,
        gate,
        sequence.initial_pose,
        scale_sd=loaded.scale_sd,
        drive_angle_sd=stated_drive_angle_sd(args, loaded.drive_angle_sd),
        drive_angle=loaded.drive_angle,
    )

    started = time.perf_counter()
    with tqdm(total=len(sequence), desc=f"slam {args.algo}", unit="step", disable=None, file=sys.stderr) as bar:
        track = run_filter(slam_filter, sequence, progress=bar.update)
    elapsed = time.perf_counter() - started

    if track.is_gaussian:
        poses = PoseSet(mean=track.mean, cov=track.cov)
    else:
        poses = PoseSet(samples=track.samples, weights=track.weights)
    if scans is not None:
        save_posed_scans(args.output, replace(scans, poses=poses))
        kind = "posed-scan file"
    else:
        save_pose_distribution(args.output, PoseDistributionFile(stamps=track.stamps, poses=poses))
        kind = "pose-distribution file"
    duration = float(track.stamps[-1] - track.stamps[0])
    rejected = getattr(slam_filter, "rejected", None)
    extras = list(loaded.notes)
    if rejected is not None:
        extras.append(f"{rejected} measurements dropped by the gates")
    if hasattr(slam_filter, "monitor"):
        extras.append(slam_filter.monitor.stats().summary())
    if hasattr(slam_filter, "resamplings"):
        extras.append(
            f"{slam_filter.stationary_skipped} measurements skipped while standing still, "
            f"{slam_filter.resamplings} resamplings"
        )
    print(
        f"wrote {args.output} ({kind}): {len(sequence)} steps over {duration:.1f} s of data in {elapsed:.2f} s, "
        f"{1e3 * elapsed / len(sequence):.2f} ms per step, {duration / max(elapsed, 1e-9):.0f}x real time"
        + "".join(f"; {e}" for e in extras)
    )
    return 0


# ------------------------------------------------------------------------------------------------ eval-traj


def _truth_at(path: Path, stamps):
    """Ground-truth poses (T, 3) at ``stamps`` (s) from a pose .npz, a simulator folder or a
    RobotK_Groundtruth.dat, and which stamps the ground truth covers: within TRUTH_MARGIN of its time span
    (past it, interpolation would only repeat its end poses). UsageError when the path does not exist or the
    ground truth covers no stamp or holds two poses at one time."""
    import numpy as np

    from schemas.files import load_pose_distribution, require_time_order
    from services.errors import UsageError
    from slam.mrclam import read_groundtruth
    from slam.scoring import fit_gaussian, interpolate_poses

    if not path.exists():
        raise UsageError(
            f"{path}: no such file or folder (GROUNDTRUTH is a pose .npz, a simulator folder or a "
            "RobotK_Groundtruth.dat)"
        )
    if path.is_dir():
        folder, path = path, path / "groundtruth.npz"
        if not path.exists():
            dat = sorted(p.name for p in folder.glob("Robot*_Groundtruth.dat"))
            raise UsageError(
                f"{folder} is a folder without a simulator's groundtruth.npz"
                + (f"; for an MRCLAM folder give one robot's ground truth, e.g. {folder / dat[0]}" if dat else "")
            )
    if path.suffix.lower() == ".npz":
        dist = load_pose_distribution(path)
        poses = dist.poses
        mean = poses.gaussian()[0] if poses.is_gaussian else fit_gaussian(*poses.weighted_samples())[0]
        truth_stamps = dist.stamps
    else:
        table = read_groundtruth(path)
        truth_stamps, mean = table[:, 0], table[:, 1:4]
    first, last = truth_stamps.min(), truth_stamps.max()
    covered = (stamps >= first - TRUTH_MARGIN) & (stamps <= last + TRUTH_MARGIN)
    if not covered.any():
        raise UsageError(
            f"no stamp of the estimate ({stamps.min():.6f} .. {stamps.max():.6f} s) lies within "
            f"{TRUTH_MARGIN:g} s of the time span of {path} ({first:.6f} .. {last:.6f} s); are they in "
            "the same time base?"
        )
    require_time_order(truth_stamps, path, "the ground truth")
    repeated = np.flatnonzero(np.diff(truth_stamps) <= 0.0)
    if len(repeated):
        raise UsageError(
            f"{path}: holds two poses at {truth_stamps[repeated[0]]:.6f} s; ground truth needs one pose per "
            "time to be interpolated"
        )
    return interpolate_poses(stamps, truth_stamps, mean), covered


def run_eval_traj(args: argparse.Namespace) -> int:
    """score a SLAM trajectory against ground truth (ATE, NEES, 95% coverage)

    Score the pose distributions in POSES (a pose-distribution or posed-scan .npz) against GROUNDTRUTH: a
    pose-distribution .npz (its mean or weighted mean), a simulator folder (its groundtruth.npz) or an MRCLAM
    RobotK_Groundtruth.dat; ground truth is interpolated to the estimate's stamps. No alignment: the filters start
    at the true first pose in the map frame. Prints one JSON line: ate_rmse_m (RMS position error, m),
    heading_mae_rad (mean absolute yaw error, rad), nees_mean (mean normalised estimation error squared, 3 DOF;
    about 3 when honest), inside95 (fraction of steps whose true pose is inside the estimate's 95% region,
    particles via a fitted Gaussian; about 0.95 when honest) and steps."""
    import numpy as np

    from schemas.files import load_pose_distribution, require_time_order
    from services.errors import UsageError
    from slam.scoring import fit_gaussian, score_trajectory

    dist = load_pose_distribution(args.poses)
    require_time_order(dist.stamps, args.poses, "the estimate")
    poses = dist.poses
    mean, cov = poses.gaussian() if poses.is_gaussian else fit_gaussian(*poses.weighted_samples())
    truth, covered = _truth_at(args.groundtruth, dist.stamps)
    if not covered.all():
        print(
            f"posegrid eval-traj: note: scored {int(covered.sum())} of {len(covered)} steps; the others lie more "
            f"than {TRUTH_MARGIN:g} s outside the ground truth's time span",
            file=sys.stderr,
        )
    with np.errstate(over="ignore", invalid="ignore"):  # a score that overflows is refused below
        score = score_trajectory(mean[covered], cov[covered], truth[covered])
    if not all(math.isfinite(value) for value in (score.ate_rmse_m, score.heading_mae_rad, score.nees_mean)):
        raise UsageError(
            f"the scores of {args.poses} against {args.groundtruth} are not finite (ATE "
            f"{score.ate_rmse_m}, NEES {score.nees_mean}): a pose or covariance is too large to score"
        )
    print(
        json.dumps(
            {
                "ate_rmse_m": round(score.ate_rmse_m, 6),
                "heading_mae_rad": round(score.heading_mae_rad, 6),
                "nees_mean": round(score.nees_mean, 4),
                "inside95": round(score.inside95, 4),
                "steps": score.steps,
            }
        )
    )
    return 0
