"""`posegrid run`: starts the router, the mapper shards, the HTTP API, the SLAM node (when the input has no
poses) and the source as child processes, shows progress, exports the map when asked, and stops every
child cleanly.

Children run in their own process group, so the launcher alone decides when they stop: on Ctrl-C
(SIGINT) or SIGTERM it sends SIGINT to the source, then to the SLAM node, the API and the shards together,
then to the router, waits for each (SIGKILL after a grace period) and reports every exit code. Each child also
watches the launcher (services.process.PARENT_PID_ENV) and stops if the launcher dies.
"""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from schemas.files import MapFile, save_map
from services import keys
from services.map_client import IncompleteMap, MapReader
from services.process import PARENT_PID_ENV, get_logger
from services.zenoh_config import build_config, open_session

#: seconds a child gets to stop after SIGINT before it is killed
STOP_GRACE = 15.0
#: exit codes of a child that stopped as asked (130: SIGINT arrived before it had set up its handlers)
CLEAN_EXITS = (0, 130)
#: seconds the launcher waits for the shards to come up
START_TIMEOUT = 60.0


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    expected_to_finish: bool = False  # the source ends on its own when the replay is over


class Children:
    """The launcher's child processes, started in order and stopped in reverse."""

    def __init__(self, log):
        self.log = log
        self.children: list[Child] = []

    def start(self, name: str, argv: list[str], expected_to_finish: bool = False) -> Child:
        env = {**os.environ, PARENT_PID_ENV: str(os.getpid())}
        process = subprocess.Popen([sys.executable, "-m", "services", *argv], env=env, start_new_session=True)
        child = Child(name, process, expected_to_finish)
        self.children.append(child)
        return child

    def failed(self) -> Child | None:
        """A child that ended when it should not have (any non-zero exit, or a server that ended)."""
        for child in self.children:
            code = child.process.poll()
            if code is not None and (code != 0 or not child.expected_to_finish):
                return child
        return None

    def running_to_finish(self) -> bool:
        """Whether a child that ends on its own (the source) is still running."""
        return any(c.expected_to_finish and c.process.poll() is None for c in self.children)

    def stop_all(self) -> dict[str, int]:
        """SIGINT every running child and wait; the router last, so the others can still say goodbye.
        Returns every child's exit code, in start order."""
        others = [c for c in self.children if c.name != "router"]
        self._stop([c for c in others if c.expected_to_finish])
        self._stop([c for c in others if not c.expected_to_finish])
        self._stop([c for c in self.children if c.name == "router"])
        return {child.name: child.process.returncode for child in self.children}

    def _stop(self, group: list[Child]) -> None:
        for child in group:
            if child.process.poll() is None:
                try:
                    child.process.send_signal(signal.SIGINT)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + STOP_GRACE
        for child in group:
            try:
                child.process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.log.warning("%s (pid %d) did not stop within %.0f s; killing it", child.name, child.process.pid,
                                 STOP_GRACE)
                child.process.kill()
                child.process.wait()


@dataclass
class Plan:
    """What `posegrid run` starts. *_argv are the children's subcommand arguments (without zenoh ones)."""

    map_name: str
    robot: str
    shards: int
    resolution: float
    mapper_argv: list[str]
    source_argv: list[str]
    slam_argv: list[str] | None = None
    export: Path | None = None
    scans: int | None = None  # scans the input holds, for the progress bar (None: unknown)
    router_port: int | None = None
    api_port: int | None = None  # None: no HTTP API
    description: str = ""


def _describe_exit(codes: dict[str, int]) -> str:
    return ", ".join(f"{name} exited {code}" for name, code in codes.items())


def run_pipeline(plan: Plan, stop: threading.Event) -> int:
    """Run the pipeline of ``plan`` until the export is written or ``stop`` is set; returns the exit code."""
    log = get_logger("run")
    port = plan.router_port or free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    children = Children(log)
    connect = ["--connect", endpoint]
    code = 1
    try:
        children.start("router", ["router", "--listen", endpoint])
        for shard in range(plan.shards):  # they keep trying to reach the router while it starts
            children.start(f"mapper[{shard}]", ["mapper", "--shard", str(shard), "--shards", str(plan.shards),
                                                "--map", plan.map_name, *plan.mapper_argv, *connect])
        if plan.api_port is not None:  # the API learns the shards from their liveliness: start it alongside
            children.start("api", ["api", "--host", "127.0.0.1", "--port", str(plan.api_port), *connect])
        session = open_session(build_config("client", connect=[endpoint]), "the launcher")
        try:
            if not _wait_for_shards(session, plan, children, stop):
                return 130 if stop.is_set() else 1
            if plan.slam_argv is not None:
                children.start("slam-node", ["slam-node", "--robot", plan.robot, *plan.slam_argv, *connect])
            children.start("source", ["source", "--robot", plan.robot, "--map", plan.map_name, "--wait-mappers",
                                      str(plan.shards), *(["--wait-slam"] if plan.slam_argv is not None else []),
                                      *plan.source_argv, *connect], expected_to_finish=True)
            _banner(plan, endpoint, children)
            code = _supervise(session, plan, children, stop, log)
        finally:
            session.close()
    finally:
        codes = children.stop_all()
        print(f"posegrid run: stopped: {_describe_exit(codes)}", flush=True)
        if code == 0 and any(c not in CLEAN_EXITS for c in codes.values()):
            code = 1
    return code


def _wait_for_shards(session, plan: Plan, children: Children, stop: threading.Event) -> bool:
    deadline = time.monotonic() + START_TIMEOUT
    key = keys.shard_alive_key(plan.map_name, "*")
    while not stop.is_set():
        alive = sum(r.ok is not None for r in session.liveliness().get(key, timeout=2.0))
        if alive >= plan.shards:
            return True
        failed = children.failed()
        if failed is not None or time.monotonic() > deadline:
            what = f"{failed.name} exited {failed.process.returncode}" if failed else f"only {alive} came up"
            print(f"posegrid run: error: the {plan.shards} mapper shard(s) did not start ({what})", file=sys.stderr)
            return False
        stop.wait(0.1)
    return False


def _banner(plan: Plan, endpoint: str, children: Children) -> None:
    lines = [f"posegrid run: {plan.description}",
             f"  zenoh router: {endpoint}  (connect with --connect {endpoint})",
             f"  map {plan.map_name!r}: tiles on {keys.tile_key(plan.map_name, 0, '*', '*')}, "
             f"stats on {keys.stats_key(plan.map_name, '*')}",
             (f"  HTTP API and map viewer: http://127.0.0.1:{plan.api_port}/  (OpenAPI: /openapi.json)"
              if plan.api_port is not None else "  HTTP API: not started (--no-api)"),
             "  running: " + ", ".join(f"{c.name} (pid {c.process.pid})" for c in children.children),
             "  Ctrl-C stops everything"]
    print("\n".join(lines), flush=True)


def _supervise(session, plan: Plan, children: Children, stop: threading.Event, log) -> int:
    """Show progress until every shard has all scans; then export (and return) or serve until stopped."""
    reader = MapReader(session, plan.map_name)
    finished = False
    with tqdm(total=plan.scans, desc="fused (slowest shard)", unit="scan", file=sys.stderr, disable=None,
              mininterval=0.5) as bar:
        while not stop.wait(0.25):
            failed = children.failed()
            if failed is not None:
                print(f"posegrid run: error: {failed.name} exited {failed.process.returncode}", file=sys.stderr)
                return 1
            if finished:
                continue
            stats = reader.stats(timeout=2.0)
            if len(stats) < plan.shards:
                continue
            done = min(s.fused.get(plan.robot, 0) for s in stats.values())
            bar.update(done - bar.n)
            ended = [s.ended.get(plan.robot) for s in stats.values()]
            if children.running_to_finish() or None in ended or any(s.fused.get(plan.robot, 0) + s.discarded.get(plan.robot, 0) < ended[0]
                                    for s in stats.values()):
                continue
            finished = True
            bar.close()
            discarded = max(s.discarded.get(plan.robot, 0) for s in stats.values())
            print(f"posegrid run: replay finished: {ended[0]} scans, each of {plan.shards} shard(s) fused "
                  f"{min(s.fused.get(plan.robot, 0) for s in stats.values())}"
                  + (f", gave up on up to {discarded}" if discarded else ""), flush=True)
            if plan.export is not None:
                return _export(reader, plan, discarded)
            print("posegrid run: serving the finished map until Ctrl-C", flush=True)
    return 0


def _export(reader: MapReader, plan: Plan, discarded: int) -> int:
    try:
        grid = reader.assemble(plan.shards, plan.resolution)
    except IncompleteMap as exc:
        print(f"posegrid run: error: cannot export the map: {exc}", file=sys.stderr)
        return 1
    raster = grid.rasterize()
    save_map(plan.export, MapFile(**raster))
    height, width = raster["logodds"].shape
    print(f"posegrid run: wrote {plan.export}: {width} x {height} cells at {plan.resolution} m, "
          f"{int(raster['observed'].sum())} observed, from {len(grid.keys())} tiles of {plan.shards} shard(s)",
          flush=True)
    if discarded:
        print(f"posegrid run: error: the map misses up to {discarded} scans the shards gave up on", file=sys.stderr)
        return 1
    return 0
