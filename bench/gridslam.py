"""Grid FastSLAM on simulated laser logs with known truth (docs/gridslam.md, "Honesty and health"): is the cloud
honest (inside95: the fraction of scans whose true pose lies in the cloud's 95 % region, about 0.95 when honest;
NEES, about 3), how accurate is it (ATE of the cloud's mean, against the odometry's), how fast (CPU real-time
factor), and what does its health watch say.

Every run goes through the command line as a user's would: the simulated log is written as a CARMEN log with its
truth beside it (`write_sim_log`), `posegrid slam --algo gridslam` runs with its defaults and `posegrid eval-traj`
scores the pose-distribution file against the truth. Logs: the office (slam.world) and the ring corridor
(slam.gridslam.simlogs), seeds 1 to 3 each; none was used to choose the filter's constants (docs/gridslam.md,
"Honesty and health", says where they come from); the ring corridor again with loop closure off. About 8
minutes on one core. `python -m bench.gridslam` prints
the table docs/gridslam.md shows.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.run import run_cli
from slam.carmen import write_carmen_scans
from slam.gridslam.simlogs import SimLaserLog, sim_log

#: (world, seed) of every run
RUNS = tuple((world, seed) for world in ("office", "loop") for seed in (1, 2, 3))
#: runs made again with loop closure off (`--loop-closure off`; docs/gridslam.md, "Loop closure")
NO_LOOP_CLOSURE_RUNS = tuple(("loop", seed) for seed in (1, 2, 3))
#: how the table names the worlds
WORLD_NAMES = {"loop": "ring corridor"}
#: the target of issue 31: the true pose inside the 95 % region at this fraction of the scans or more
INSIDE95_TARGET = 0.85


def write_sim_log(log: SimLaserLog, path: Path) -> Path:
    """Write ``log`` as the CARMEN log ``path`` (FLASER lines, which state the true pose beside the odometry, as a
    corrected log states its corrected poses) and its truth beside it (``path`` with the suffix .truth.npz, a
    pose-distribution file with one sample per scan, for `posegrid eval-traj`); returns the truth's path."""
    from schemas.files import PoseDistributionFile, PoseSet, save_pose_distribution

    write_carmen_scans(path, log, poses=log.true_poses, record="FLASER")
    truth = Path(path).with_suffix(".truth.npz")
    poses = PoseSet(samples=log.true_poses[:, None, :].copy(), weights=np.ones((len(log.stamps), 1)))
    save_pose_distribution(truth, PoseDistributionFile(stamps=log.stamps, poses=poses))
    return truth


def run_one(world: str, seed: int, folder: Path, *options: str) -> dict:
    """One simulated log through `posegrid slam` (with ``options``) and `posegrid eval-traj`: its figures."""
    log = sim_log(world, seed)
    path = folder / f"{world}{seed}.clf"
    truth = write_sim_log(log, path)
    out, stats_path = folder / f"{world}{seed}.npz", folder / f"{world}{seed}.json"
    argv = ["slam", "--algo", "gridslam", str(path), "-o", str(out), "--seed", "0", "--stats", str(stats_path)]
    run_cli([*argv, *options])
    stats = json.loads(stats_path.read_text())
    score = json.loads(run_cli(["eval-traj", str(out.with_suffix(".poses.npz")), str(truth)]))
    summary = stats["health_summary"]
    return {
        "inside95": score["inside95"],
        "nees": score["nees_mean"],
        "ate_m": score["ate_rmse_m"],
        "odometry_ate_m": stats["reference"]["odometry_rmse_m"],
        "cpu_real_time": stats["log_duration_s"] / stats["cpu_seconds_total"],
        "mean_particles": summary["mean_particles"],
        "failed_scans": summary["failed"],
        "warnings": len(summary["warnings"]),
        "loop_closures": stats["loop_closure"]["closures"],
    }


def run() -> dict:
    """Every run of :data:`RUNS`: per run its figures, and the means and the worst inside95."""
    figures: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for world, seed in RUNS:
            for key, value in run_one(world, seed, Path(tmp)).items():
                figures[f"{world}{seed}_{key}"] = value
        for world, seed in NO_LOOP_CLOSURE_RUNS:
            for key, value in run_one(world, seed, Path(tmp), "--loop-closure", "off").items():
                figures[f"no_loop_closure_{world}{seed}_{key}"] = value
    for key in ("inside95", "nees", "ate_m", "cpu_real_time"):
        figures[f"mean_{key}"] = float(np.mean([figures[f"{w}{s}_{key}"] for w, s in RUNS]))
    figures["worst_inside95"] = float(min(figures[f"{w}{s}_inside95"] for w, s in RUNS))
    figures["runs_meeting_inside95"] = sum(figures[f"{w}{s}_inside95"] >= INSIDE95_TARGET for w, s in RUNS)
    return figures


def main() -> int:
    """Print the table of docs/gridslam.md."""
    figures = run()
    print("| log | inside95 | NEES | ATE (m) | odometry ATE (m) | CPU real-time factor | mean particles |")
    print("|---|---|---|---|---|---|---|")
    for world, seed in RUNS:
        f = {k: figures[f"{world}{seed}_{k}"] for k in ("inside95", "nees", "ate_m", "odometry_ate_m")}
        rt, n = figures[f"{world}{seed}_cpu_real_time"], figures[f"{world}{seed}_mean_particles"]
        print(
            f"| {WORLD_NAMES.get(world, world)} seed {seed} | {f['inside95']:.3f} | {f['nees']:.2f} | "
            f"{f['ate_m']:.3f} | {f['odometry_ate_m']:.2f} | {rt:.1f}x | {n:.1f} |"
        )
    for world, seed in NO_LOOP_CLOSURE_RUNS:
        f = {k: figures[f"no_loop_closure_{world}{seed}_{k}"] for k in ("inside95", "nees", "ate_m", "odometry_ate_m")}
        print(
            f"| {WORLD_NAMES.get(world, world)} seed {seed}, --loop-closure off | {f['inside95']:.3f} | "
            f"{f['nees']:.2f} | {f['ate_m']:.3f} | {f['odometry_ate_m']:.2f} | | |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
