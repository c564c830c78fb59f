"""Subcommands on robot logs: eval-relations (the SLAM benchmark's relation error)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from services.commands.argtypes import check_outputs, finite_float, path_argument
from services.commands.options import add_choice, add_command, add_scan_topic

#: file suffixes (in any case) read as pose .npz files; a bag file (.bag, .mcap, .db3), a folder or a
#: metadata.yaml is a ROS bag; anything else a CARMEN log
NPZ_SUFFIXES = (".npz",)


def register(subparsers: argparse._SubParsersAction) -> None:
    evaluate = add_command(subparsers, "eval-relations", run_eval_relations)
    evaluate.add_argument("poses", type=path_argument, help="pose .npz, CARMEN log (.clf/.log/.gz) or ROS bag")
    evaluate.add_argument(
        "relations", type=path_argument, help="relation file (t1 t2 dx dy dz roll pitch yaw per line)"
    )
    evaluate.add_argument(
        "--align-to",
        type=path_argument,
        default=None,
        metavar="RAWLOG",
        help="put a log's stamps on RAWLOG's clock first, by the scans both hold (for "
        "re-stamped corrected logs such as freiburg-079-corrected.log.gz)",
    )
    evaluate.add_argument(
        "--stamped-by",
        type=path_argument,
        default=None,
        metavar="LOG",
        help="a pose .npz as POSES: the log whose clock its stamps are on (the one `posegrid slam` ran on), whose "
        "scans --align-to matches with RAWLOG's (for a run of a corrected log, scored against the raw log's "
        "relations)",
    )
    add_choice(
        evaluate,
        "--estimate",
        ("best", "mean"),
        "pose files with samples: the highest-weight sample (default) or the weighted mean",
    )
    evaluate.add_argument(
        "--tolerance",
        type=finite_float,
        default=None,
        help="s within which a stamp matches a pose exactly (default 0.001)",
    )
    evaluate.add_argument(
        "--max-gap",
        type=finite_float,
        default=None,
        help="s: interpolate only between poses at most this far apart (default 5)",
    )
    add_scan_topic(evaluate, "a ROS bag as POSES or --align-to")
    evaluate.add_argument("--json", default=None, metavar="OUT", help="also write the scores as JSON")


def read_log(path: Path, scan_topic: str | None = None):
    """A laser log from a ROS bag (a .bag file, a bag folder, its metadata.yaml or a ROS 2 storage file, .mcap or
    .db3; ``scan_topic``: its LaserScan topic, default the only one or /scan) or a CARMEN log (anything else but a
    .npz file); suffixes in any case."""
    from slam.carmen import read_carmen
    from slam.errors import LogFormatError
    from slam.rosbag_reader import BAG_METADATA, BAG_SUFFIXES, read_rosbag

    suffix = path.suffix.lower()
    if suffix in NPZ_SUFFIXES:
        raise LogFormatError(f"{path}: a .npz file, not a laser log (expected a CARMEN log .clf/.log/.gz or a ROS bag)")
    if path.is_dir() or suffix in BAG_SUFFIXES or path.name == BAG_METADATA:
        return read_rosbag(path, scan_topic=scan_topic)
    if scan_topic is not None:
        raise LogFormatError(f"--scan-topic names a topic of a ROS bag, but {path} is read as a CARMEN log")
    return read_carmen(path)


def _pose_file_trajectory(path: Path, estimate: str):
    from schemas.files import load_pose_distribution, require_time_order
    from slam.angles import wrap_angle
    from slam.relations import Trajectory

    dist = load_pose_distribution(path)
    require_time_order(dist.stamps, path, "POSES")
    poses = dist.poses
    if poses.is_gaussian:
        return Trajectory.sorted(dist.stamps, poses.gaussian()[0])
    samples, weights = poses.weighted_samples()
    if estimate == "best":
        chosen = samples[np.arange(len(samples)), np.argmax(weights, axis=1)]
    else:
        xy = np.einsum("tm,tmk->tk", weights, samples[:, :, :2])
        yaw = np.arctan2(
            np.einsum("tm,tm->t", weights, np.sin(samples[:, :, 2])),
            np.einsum("tm,tm->t", weights, np.cos(samples[:, :, 2])),
        )
        chosen = np.column_stack([xy, wrap_angle(yaw)])
    return Trajectory.sorted(dist.stamps, chosen)


def _note(message: str) -> None:
    print(f"posegrid eval-relations: note: {message}", file=sys.stderr)


def run_eval_relations(args: argparse.Namespace) -> int:
    """score a trajectory by the SLAM benchmark's relations (Kuemmerle et al. 2009)

    Relation error of a trajectory: for every relation 't1 t2 dx dy dz roll pitch yaw' (true motion from t1 to t2
    in t1's frame) the estimated motion between the poses at t1 and t2 is compared with it; prints the mean and
    std of the translational (m) and rotational (deg) errors and of their squares. POSES is a posed-scan or
    pose-distribution .npz (per stamp the highest-weight sample, or the weighted mean with --estimate mean, or the
    Gaussian mean), a CARMEN log (its laser lines' poses plus its timed ODOM lines: odometry for raw logs, the
    corrected poses for corrected logs) or a ROS bag (its odometry). Stamps match within --tolerance; between poses
    at most --max-gap apart the pose is interpolated; unmatched relations are skipped and counted. A log re-stamped
    on another clock (a corrected log) is put on RAWLOG's by --align-to; a pose .npz of a run of such a log names the
    log with --stamped-by."""
    from schemas.files import write_atomically
    from services.errors import UsageError
    from slam.relations import (
        DEFAULT_MAX_GAP,
        DEFAULT_TOLERANCE,
        Trajectory,
        read_relations,
        score_relations,
        trajectory_from_log,
    )
    from slam.timealign import time_map, to_reference_time

    check_outputs(args, inputs=(args.poses, args.relations), json="--json")
    tolerance = DEFAULT_TOLERANCE if args.tolerance is None else args.tolerance
    max_gap = DEFAULT_MAX_GAP if args.max_gap is None else args.max_gap
    if tolerance < 0 or max_gap <= 0:
        raise UsageError("--tolerance must be >= 0 and --max-gap > 0 seconds")
    relations = read_relations(args.relations)
    if relations.skipped:
        shown = ", ".join(str(s.where) for s in relations.skipped[:10])
        _note(
            f"{args.relations}: skipped {len(relations.skipped)} malformed lines (lines {shown}"
            f"{' ...' if len(relations.skipped) > 10 else ''})"
        )
    pose_file = args.poses.suffix.lower() in NPZ_SUFFIXES
    if pose_file and args.align_to is not None and args.stamped_by is None:
        raise UsageError(
            "--align-to matches the scans of two logs: with a pose .npz as POSES, name the log its stamps come from "
            "with --stamped-by LOG"
        )
    if args.stamped_by is not None and not pose_file:
        raise UsageError(
            f"--stamped-by names the log a pose .npz given as POSES was stamped by, but POSES {args.poses} is a log: "
            "drop --stamped-by (--align-to aligns a log by its own scans)"
        )
    if args.stamped_by is not None and args.align_to is None:
        raise UsageError("--stamped-by names the log of a pose .npz given as POSES, for --align-to: give both")
    if pose_file and args.stamped_by is None and args.scan_topic is not None:
        raise UsageError(
            f"--scan-topic names the scans' topic of a ROS bag read as a log, but no log is read here (POSES "
            f"{args.poses} is a pose .npz, and no --stamped-by or --align-to): drop it"
        )
    if pose_file:
        trajectory = _pose_file_trajectory(args.poses, args.estimate)
        log = read_log(args.stamped_by, scan_topic=args.scan_topic) if args.stamped_by is not None else None
    else:
        log = read_log(args.poses, scan_topic=args.scan_topic)
        for remark in log.remarks():
            _note(remark)
        trajectory = trajectory_from_log(log)
    if args.align_to is not None and log is not None:  # (a pose .npz is aligned by its --stamped-by log)
        reference = read_log(args.align_to, scan_topic=args.scan_topic)
        stamps, offsets = time_map(log, reference)
        stamped = f" (stamped by {args.stamped_by})" if pose_file else ""
        _note(
            f"aligned {args.poses}{stamped} to {args.align_to} by {len(stamps)} shared scans "
            f"(offset {offsets.min():.6f} .. {offsets.max():.6f} s)"
        )
        trajectory = Trajectory.sorted(to_reference_time(trajectory.stamps, stamps, offsets), trajectory.poses)
    score = score_relations(trajectory, relations, tolerance, max_gap)
    summary = score.summary()
    if args.json is not None:  # first: a file that cannot be written stops the command before it reports
        text = json.dumps(summary, indent=1) + "\n"
        write_atomically(args.json, lambda handle: handle.write(text.encode()))
    print(
        f"{args.poses}: {summary['relations_used']} of {summary['relations_total']} relations matched "
        f"(tolerance {tolerance} s, max gap {max_gap} s)"
    )
    print(
        f"  translational error: mean {summary['trans_mean_m']:.4f} m, std {summary['trans_std_m']:.4f} m; "
        f"squared: mean {summary['trans_sq_mean_m2']:.5f} m^2, std {summary['trans_sq_std_m2']:.5f} m^2"
    )
    print(
        f"  rotational error:    mean {summary['rot_mean_deg']:.3f} deg, std {summary['rot_std_deg']:.3f} deg; "
        f"squared: mean {summary['rot_sq_mean_deg2']:.3f} deg^2, std {summary['rot_sq_std_deg2']:.3f} deg^2"
    )
    return 0
