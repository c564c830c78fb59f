"""The adaptive grid on real laser logs: MIT CSAIL and Freiburg 079 (30 m lasers), paper Fig. 4(b) style.

Each log's pose distribution is grid FastSLAM's, run through the command line as a user would (`posegrid slam
--algo gridslam LOG --seed 0`, 30 particles; about 4 and 7 minutes). Every SCAN_STEP-th scan of the posed-scan
file is then fused into the fine regular grid and into adaptive grids over the sweep below, and each is scored
against the regular grid as `bench/adaptive.py` scores the simulated office (`compare_rules`); figures carry the
log's name as a prefix. The sweep adds `unknown_range` 1.6 m, because on these logs the unknowns behind small
objects reach to 30 m (docs/adaptive.md). A log that is absent from ../shared/data is skipped, with the reason.
About 16 minutes on one core.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench.adaptive import RESOLUTION, compare_rules, significance_sweep
from bench.run import run_cli
from bench.scenarios import FR079, MIT_CSAIL, select_scans
from mapping.adaptive import AdaptiveParams
from mapping.sensor_model import SensorModel
from schemas.files import load_posed_scans

#: figure prefix -> laser log
LOGS = {"mit_csail": MIT_CSAIL, "fr079": FR079}
#: fuse every SCAN_STEP-th scan (the map still covers the whole building)
SCAN_STEP = 4
#: how far behind a return the extra sweep entry counts unknowns, m
SHORT_UNKNOWN_RANGE = 1.6


def sweep() -> dict[str, AdaptiveParams]:
    """Figure prefix -> parameters: the office's significance sweep, and unknowns up to SHORT_UNKNOWN_RANGE."""
    return {
        **significance_sweep(),
        f"unknowns_range_{SHORT_UNKNOWN_RANGE:g}m": AdaptiveParams(unknown_range=SHORT_UNKNOWN_RANGE),
    }


def measure_log(log: Path) -> dict:
    """Grid FastSLAM on ``log``, then `compare_rules` on every SCAN_STEP-th scan of its posed-scan file."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "posed.npz"
        run_cli(["slam", "--algo", "gridslam", str(log), "--seed", "0", "-o", str(path)])
        posed = select_scans(load_posed_scans(path), slice(None, None, SCAN_STEP))
    out: dict = {
        "scans": len(posed.stamps),
        "beams": int(posed.ranges.shape[1]),
        "range_max_m": float(posed.range_max.max()),
        "particles": int(posed.poses.weighted_samples()[0].shape[1]),
    }
    out.update(compare_rules(posed, SensorModel(resolution=RESOLUTION), sweep()))
    return out


def run() -> dict:
    figures: dict = {"scan_step": SCAN_STEP, "resolution_m": RESOLUTION}
    for name, log in LOGS.items():
        if not log.is_file():
            figures[f"{name}_skipped"] = f"the log is not present ({log})"
            continue
        figures.update({f"{name}_{key}": value for key, value in measure_log(log).items()})
    return figures
