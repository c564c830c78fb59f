"""Real processes for the API and viewer tests: a Zenoh router, mapper shards, the API and a source, each
started as `python -m services.cli ...` on free loopback ports and ended by PID."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from schemas.files import PosedScans, PoseSet, save_posed_scans
from services.ports import free_port
from worlds import room_posed_scans

ROOT = Path(__file__).resolve().parents[1]
#: the `posegrid` console script, independent of where pip put it (``-m services.cli`` would run cli.py as
#: __main__, whose UsageError is not the class the commands raise)
POSEGRID = [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())"]


def wait_until(predicate, timeout: float, what: str, interval: float = 0.1):
    """Poll ``predicate`` until it returns something truthy (returned); fail naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def write_room(path: Path, shift: tuple[float, float], steps: int = 20, particles: int = 10, seed: int = 0) -> Path:
    """The 4 m x 3 m test room (tests/worlds.py) moved by ``shift`` m, with weighted pose samples."""
    scans = room_posed_scans(steps=steps, seed=seed, gaussian=False, particles=particles)
    samples = scans.poses.samples + np.array([shift[0], shift[1], 0.0])
    moved = PosedScans(
        ranges=scans.ranges,
        angle_min=scans.angle_min,
        angle_increment=scans.angle_increment,
        range_min=scans.range_min,
        range_max=scans.range_max,
        stamps=scans.stamps,
        sensor_offset=scans.sensor_offset,
        poses=PoseSet(samples=samples, weights=scans.poses.weights),
    )
    save_posed_scans(path, moved)
    return path


class Stack:
    """Processes started for a test, all ended (SIGINT, then SIGKILL) by :meth:`stop`."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.router_port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.router_port}"
        self.processes: dict[str, subprocess.Popen] = {}
        self.api_url: str | None = None

    def start(self, name: str, *argv: str, connect: bool = True) -> subprocess.Popen:
        command = [*POSEGRID, *argv, *(["--connect", self.endpoint] if connect else [])]
        with open(self.logs / f"{name}.log", "wb") as log:  # the child keeps its own copy of the descriptor
            process = subprocess.Popen(
                command, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"}
            )
        self.processes[name] = process
        return process

    def router(self) -> None:
        self.start("router", "router", "--listen", self.endpoint, connect=False)

    def mappers(self, shards: int, map_name: str, *options: str) -> None:
        for shard in range(shards):
            self.start(
                f"mapper{shard}", "mapper", "--shard", str(shard), "--shards", str(shards), "--map", map_name, *options
            )

    def api(self) -> str:
        port = free_port()
        self.start("api", "api", "--port", str(port))
        self.api_url = f"http://127.0.0.1:{port}"
        wait_until(self._api_up, 60, "the API to answer /health")
        return self.api_url

    def _api_up(self) -> bool:
        self.check_alive()
        try:
            return httpx.get(f"{self.api_url}/health", timeout=5).status_code == 200
        except httpx.TransportError:
            return False

    def source(self, posed: Path, map_name: str, shards: int, robot: str = "robot0", rate: str = "max") -> None:
        self.start(
            f"source-{robot}",
            "source",
            "--posed",
            str(posed),
            "--robot",
            robot,
            "--map",
            map_name,
            "--wait-mappers",
            str(shards),
            "--rate",
            rate,
        )

    def check_alive(self) -> None:
        """Fail (with the process's log) if a server process has ended."""
        for name, process in self.processes.items():
            if not name.startswith("source") and process.poll() is not None:
                log = (self.logs / f"{name}.log").read_text(errors="replace")[-3000:]
                raise AssertionError(f"{name} exited {process.returncode}:\n{log}")

    def end(self, name: str) -> None:
        """End process ``name`` (SIGTERM, then SIGKILL after 30 s) and forget it."""
        process = self.processes.pop(name)
        process.terminate()
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def stop(self) -> None:
        for process in reversed(list(self.processes.values())):
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        for process in self.processes.values():
            try:
                process.wait(15)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
