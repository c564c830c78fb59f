"""Grid FastSLAM on the shared laser logs, and the leave-one-out choice of the options fitted to real logs.

`python -m bench.run gridslam_logs` (about 80 minutes on one core): every candidate of :data:`CANDIDATES` runs on every
bag of :data:`LOGS` (`posegrid slam --algo gridslam BAG --seed 0` plus the candidate's options, as a user would run
it) and is scored by the log's relations (`posegrid eval-relations`, Kuemmerle et al. 2009: translational mean, m).
The corrected logs (GMapping) are scored the same way, for issue 31's target (within 1.5x of the corrected log).

Leave one out: for each log held out, the candidate with the smallest mean over the other logs of its error divided
by the best candidate's error on that log (so that no log weighs more for being harder) is chosen; its error on the
held-out log is the held-out figure, and `loo_choice_<log>` names it. The candidates are the choices made while
fitting the filter to these logs (docs/gridslam.md): whether the laser-to-odometry delay is estimated (it was
added for Freiburg 079) and the particle count (KLD-sampling's 25 to 50, chosen on MIT CSAIL's speed, a fixed 30,
the count the filter was first fitted with) and how far the proposal widens after a failed match (4, chosen on
simulated logs and MIT CSAIL, or not at all). A log absent from ../shared/data is
skipped with the reason, and so is the choice that needs it.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.run import run_cli
from bench.scenarios import SHARED_DATA

#: log -> (bag, relations, corrected log or None), paths under ../shared/data
LOGS = {
    "mit-csail": ("mit-csail/mit-csail.orig.bag", "mit-csail/mit-csail.relations", None),
    "intel-lab": ("intel-lab/intel.orig.bag", "intel-lab/intel.relations", "intel-lab/intel-corrected.log.gz"),
    "fr079": ("fr079/fr079.orig.bag", "fr079/fr079.relations", "fr079/freiburg-079-corrected.log.gz"),
}
#: candidate -> its `posegrid slam` options. "delay0": the odometry read at the scans' stamps; "timed": the default,
#: the delay estimated where the log has an odometry stream and stamps that can time it (docs/gridslam.md);
#: "kldA_B": KLD-sampling between A and B particles; "fixedN": N particles throughout; "widenW": after a failed match
#: the next proposal's motion variances (and the yaw search's square) W times larger
CANDIDATES = {
    "delay0_kld25_50_widen4": ["--odom-delay", "0", "--particles", "25", "--particle-cap", "50", "--widen", "4"],
    "timed_kld25_50_widen4": ["--particles", "25", "--particle-cap", "50", "--widen", "4"],
    "delay0_fixed30_widen4": ["--odom-delay", "0", "--particles", "30", "--particle-cap", "30", "--widen", "4"],
    "timed_fixed30_widen4": ["--particles", "30", "--particle-cap", "30", "--widen", "4"],
    "timed_fixed30_widen1": ["--particles", "30", "--particle-cap", "30", "--widen", "1"],
}
#: issue 31: a shared log's relation error with the default options at most this times its corrected log's
CORRECTED_TARGET = 1.5


def relation_error(poses: Path, relations: Path, align_to: Path | None = None) -> dict:
    """`posegrid eval-relations POSES RELATIONS [--align-to LOG]`: its summary (translational mean m, ...)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "relations.json"
        argv = ["eval-relations", str(poses), str(relations), "--json", str(out)]
        run_cli(argv + (["--align-to", str(align_to)] if align_to is not None else []))
        return json.loads(out.read_text())


def slam_run(bag: Path, relations: Path, options: list[str], folder: Path) -> dict:
    """One `posegrid slam --algo gridslam` run with ``options``: its relation error, timing and particles."""
    output, stats_path = folder / "run.npz", folder / "stats.json"
    run_cli(
        ["slam", "--algo", "gridslam", str(bag), "-o", str(output), "--seed", "0", "--stats", str(stats_path)] + options
    )
    stats = json.loads(stats_path.read_text())
    score = relation_error(folder / "run.poses.npz", relations)
    return {
        "trans_m": score["trans_mean_m"],
        "rot_deg": score["rot_mean_deg"],
        "cpu_real_time": stats["log_duration_s"] / stats["cpu_seconds_total"],
        "mean_particles": stats["health_summary"]["mean_particles"],
    }


def leave_one_out(errors: dict[str, dict[str, float]]) -> dict[str, tuple[str, float]]:
    """For each log (``errors``: candidate -> log -> error), the candidate chosen on the other logs (the smallest mean
    error relative to the best candidate on each) and its error on the held-out log."""
    logs = sorted({log for by_log in errors.values() for log in by_log})
    best = {log: min(by_log[log] for by_log in errors.values()) for log in logs}
    chosen: dict[str, tuple[str, float]] = {}
    for held_out in logs:
        others = [log for log in logs if log != held_out]
        if not others:
            continue
        relative = {
            name: float(np.mean([by_log[log] / best[log] for log in others])) for name, by_log in errors.items()
        }
        name = min(relative, key=lambda candidate: (relative[candidate], candidate))
        chosen[held_out] = (name, errors[name][held_out])
    return chosen


def run() -> dict:
    """Every candidate on every log present, the corrected logs' errors, and the leave-one-out choices."""
    figures: dict = {}
    present = {name: paths for name, paths in LOGS.items() if (SHARED_DATA / paths[0]).exists()}
    for name in LOGS.keys() - present.keys():
        figures[f"{name}_skipped"] = f"the log is not present ({SHARED_DATA / LOGS[name][0]})"
    errors: dict[str, dict[str, float]] = {candidate: {} for candidate in CANDIDATES}
    for log, (bag, relations, corrected) in present.items():
        if corrected is not None:
            score = relation_error(SHARED_DATA / corrected, SHARED_DATA / relations, align_to=SHARED_DATA / bag)
            figures[f"{log}_corrected_trans_m"] = score["trans_mean_m"]
        for candidate, options in CANDIDATES.items():
            with tempfile.TemporaryDirectory() as tmp:
                result = slam_run(SHARED_DATA / bag, SHARED_DATA / relations, options, Path(tmp))
            for key, value in result.items():
                figures[f"{log}_{candidate}_{key}"] = value
            errors[candidate][log] = result["trans_m"]
            print(f"  {log} {candidate}: {result['trans_m']:.4f} m", file=sys.stderr, flush=True)
    for log, (candidate, error) in leave_one_out(errors).items():
        figures[f"loo_choice_{log}"] = candidate
        figures[f"loo_held_out_{log}_trans_m"] = error
        if f"{log}_corrected_trans_m" in figures:
            figures[f"loo_held_out_{log}_over_corrected"] = error / figures[f"{log}_corrected_trans_m"]
    return figures


if __name__ == "__main__":
    for key, value in run().items():
        print(f"{key}: {value}")
