"""Compile the numba kernels of mapping/ and slam/ into numba's on-disk cache (mapping.jit) before they are first
needed: ``python -m services.commands.warm_kernels``, which `make install` runs.

On a fresh install every kernel compiles on its first call: the fusion's take about 30 CPU s (a `posegrid run`'s
shards do that before they say they are up), the SLAM filters', the self-calibration's and grid FastSLAM's about as
much again, and the first test of each paid it inside the test suite. Here the commands run on tiny inputs in a
temporary folder, in two processes side by side (the fusion's kernels; the SLAM filters'): the kernels they call are
the ones a user's run calls, and mapping.jit's lock per kernel keeps the two from compiling one kernel twice. Kernels
already cached load in well under a second, so running it again costs little. A kernel edited later compiles again on
its next call, as it would without this.
"""

from __future__ import annotations

import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def _cli(*argv: str) -> None:
    """Run one posegrid command in this process with its output hidden; raise with its output if it fails."""
    from services.cli import run_in_process

    run_in_process(list(argv), quiet=True)


def warm_mapping(folder: Path) -> None:
    """The fusion's kernels: `posegrid fuse` of 30 simulated scans with Gaussian poses (EKF-SLAM) and with particles
    (FastSLAM 2.0), Monte Carlo on one thread and two and bundled, the most likely pose, the adaptive grid, the
    particles once more as a shard of two fuses them, and a lone scan in parts on two threads."""
    sim = folder / "office"
    _cli("simulate", str(sim), "--steps", "30")
    runs = {"ekf": [], "fastslam2": ["--particles", "20"]}  # Gaussian poses; particles
    posed = {algo: folder / f"{algo}.npz" for algo in runs}
    for algo, options in runs.items():
        _cli("slam", str(sim), "--algo", algo, "--calibration", "none", *options, "-o", str(posed[algo]))
    for path in posed.values():
        for options in ([], ["--threads", "2"], ["--bundle", "0.1"], ["--mode", "ml"], ["--grid", "adaptive"]):
            _cli("fuse", str(path), "-o", str(folder / "map.npz"), *options)
    from mapping.fusion import FusionThreads
    from mapping.sensor_model import SensorModel
    from schemas.files import load_posed_scans
    from services.fusion_runner import fuse_posed_scans
    from services.state.ownership import owns_tile
    from services.state.shard import warm_fusion

    fuse_posed_scans(load_posed_scans(posed["fastslam2"]), owns_tile=owns_tile(0, 2))  # a shard of two
    warm_fusion(SensorModel(resolution=0.05), 256, FusionThreads(2))  # a lone scan in parts, as a live shard fuses it


def warm_slam(folder: Path) -> None:
    """The SLAM filters' kernels: the self-calibration (`posegrid calibrate`), EKF-SLAM and FastSLAM 1.0 and 2.0 on
    60 s of the simulated office, and grid FastSLAM on 40 scans of a simulated room."""
    from slam.carmen import write_carmen_scans
    from slam.gridslam.simlogs import sim_log

    sim = folder / "office"
    _cli("simulate", str(sim), "--steps", "600")
    _cli("calibrate", str(sim), "-o", str(folder / "calibration.json"))
    for algo, options in (("ekf", []), ("fastslam1", ["--particles", "20"]), ("fastslam2", ["--particles", "20"])):
        _cli("slam", str(sim), "--algo", algo, *options, "-o", str(folder / f"{algo}.npz"))
    log = folder / "room.clf"
    write_carmen_scans(log, sim_log("room", seed=1), record="FLASER")
    _cli("slam", str(log), "--algo", "gridslam", "--particles", "5", "--scans", "40", "-o", str(folder / "grid.npz"))


def _timed(warm: Callable[[Path], None]) -> float:
    """Run ``warm`` in a temporary folder of its own; its CPU time in s."""
    started = time.process_time()
    with tempfile.TemporaryDirectory(prefix="posegrid-warm-") as tmp:
        warm(Path(tmp))
    return time.process_time() - started


def main() -> int:
    """Warm both sets side by side; print the CPU time each took."""
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=2) as pool:
        jobs = {name: pool.submit(_timed, warm) for name, warm in (("fusion", warm_mapping), ("slam", warm_slam))}
        cpu = {name: job.result() for name, job in jobs.items()}
    print(
        f"posegrid: numba kernels compiled or loaded in {time.perf_counter() - started:.0f} s "
        f"(fusion {cpu['fusion']:.0f} CPU s, SLAM {cpu['slam']:.0f} CPU s)"
    )
    return 0


if __name__ == "__main__":
    if sys.argv[1:] in (["-h"], ["--help"]):
        print(f"usage: python -m services.commands.warm_kernels\n\n{__doc__}")
        sys.exit(0)
    if sys.argv[1:]:
        print(f"warm_kernels takes no arguments, got {' '.join(sys.argv[1:])!r} (see --help)", file=sys.stderr)
        sys.exit(2)
    sys.exit(main())
