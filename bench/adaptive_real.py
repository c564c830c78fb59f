"""The adaptive grid on a real laser log: MIT CSAIL (1988 scans, 361 beams, 30 m range), paper Fig. 4(b) style.

The pose distribution is grid FastSLAM's, run through the command line as a user would (`posegrid slam --algo
gridslam mit-csail.clf --seed 0`, 30 particles, about 4 minutes). Every SCAN_STEP-th scan of the whole log is
then fused into the fine regular grid and into adaptive grids over the sweep below, and each is scored against
the regular grid as `bench/adaptive.py` scores the simulated office (`compare_rules`). The sweep adds
`unknown_range` 1.6 m, because on this log the unknowns behind small objects reach to 30 m (docs/adaptive.md).
Skipped, with the reason, when ../shared/data/mit-csail is absent. About 10 minutes on one core.
"""
from __future__ import annotations

import tempfile
from dataclasses import replace
from pathlib import Path

from bench.adaptive import RESOLUTION, SIGNIFICANCES, compare_rules
from bench.slam import run_cli
from mapping.adaptive import AdaptiveParams
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans, PoseSet, load_posed_scans

LOG = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mit-csail" / "mit-csail.clf"
#: fuse every SCAN_STEP-th scan (the map still covers the whole building)
SCAN_STEP = 4
#: how far behind a return the extra sweep entry counts unknowns, m
SHORT_UNKNOWN_RANGE = 1.6


def every_nth_scan(posed: PosedScans, step: int) -> PosedScans:
    """Every ``step``-th scan of ``posed`` with its pose distribution (samples and weights)."""
    poses = PoseSet(samples=posed.poses.samples[::step], weights=posed.poses.weights[::step])
    return replace(posed, ranges=posed.ranges[::step], stamps=posed.stamps[::step], poses=poses)


def run() -> dict:
    if not LOG.is_file():
        return {"skipped": f"the MIT CSAIL log is not present ({LOG})"}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mit-csail.npz"
        run_cli(["slam", "--algo", "gridslam", str(LOG), "--seed", "0", "-o", str(path)])
        posed = every_nth_scan(load_posed_scans(path), SCAN_STEP)
    sweep = {}
    for name, unknowns in (("unknowns", True), ("no_unknowns", False)):
        for alpha in SIGNIFICANCES:
            prefix = name if alpha == SIGNIFICANCES[0] else f"{name}_alpha_{alpha:g}"
            sweep[prefix] = AdaptiveParams(unknowns=unknowns, significance=alpha)
    sweep[f"unknowns_range_{SHORT_UNKNOWN_RANGE:g}m"] = AdaptiveParams(unknown_range=SHORT_UNKNOWN_RANGE)
    out: dict = {"log": LOG.name, "scans": len(posed.stamps), "scan_step": SCAN_STEP,
                 "beams": int(posed.ranges.shape[1]), "range_max_m": float(posed.range_max),
                 "particles": int(posed.poses.samples.shape[1]), "resolution_m": RESOLUTION}
    out.update(compare_rules(posed, SensorModel(resolution=RESOLUTION), sweep))
    return out
