"""`make bench`: run every benchmark, write JSON under bench/results/, print a table."""

from __future__ import annotations

import importlib
import json
import platform
import sys
import time
from pathlib import Path

from services.commands.mapping import available_cores

RESULTS = Path(__file__).resolve().parent / "results"
#: benchmark modules, each with run() -> dict of figures
SUITES = (
    "bench.fusion",
    "bench.threads",
    "bench.samples_scaling",
    "bench.warehouse",
    "bench.quality",
    "bench.adaptive",
    "bench.adaptive_real",
    "bench.pipeline",
    "bench.api",
    "bench.slam",
    "bench.gridslam",
    "bench.gridslam_logs",
    "bench.chaos",
    "bench.persist",
    "bench.ros2",
)


def run_cli(argv: list[str]) -> str:
    """Run `posegrid ARGV` in this process, as a suite's user would; its stdout (a non-zero exit raises)."""
    from services.cli import run_in_process

    return run_in_process(argv)


def cpu_model() -> str:
    """The processor's model name (/proc/cpuinfo on Linux; else what platform says): figures of two runs compare only
    on the same processor, and a session's machine may change."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv: list[str]) -> int:
    names = [f"bench.{name}" for name in argv] or list(SUITES)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for name in names:
        module = importlib.import_module(name)
        print(f"== {name}: running ...", flush=True)
        started = time.perf_counter()
        figures = module.run()
        figures["wall_s"] = time.perf_counter() - started
        record = {
            "suite": name,
            "machine": platform.machine(),
            "cpu": cpu_model(),
            "cores": available_cores(),
            "python": platform.python_version(),
            "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "figures": figures,
        }
        path = RESULTS / f"{name.split('.')[-1]}.json"
        path.write_text(json.dumps(record, indent=2))
        width = max(len(k) for k in figures)
        for key, value in figures.items():
            shown = f"{value:.4g}" if isinstance(value, float) else str(value)
            print(f"  {key:<{width}}  {shown}")
        print(f"  -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
