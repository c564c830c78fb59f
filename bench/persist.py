"""Durable maps (issue 32, docs/persistence.md): what a shard's state directory costs and what it saves.

- overhead: fusion throughput of one shard (services.state.shard.MapShard driven as services.nodes.mapper drives it,
  in this process) with a store (services.state.store: commits on the writer thread, at the default interval and at
  others) against without; the simulated office, 400 scans of 361 beams with 30 pose samples each (`posegrid run`'s
  SLAM node publishes 30 particles); the median of 3 alternating runs each. ``slowdown`` = time with / time without
  - 1 (0.10: 10 % slower);
- database bytes per observed cell, after that run (the file after a clean stop: the write-ahead log checkpointed);
- restart time to serving: a `posegrid mapper` process started on a store of about 10^6 observed cells (the office's
  tiles repeated), from its start until it answers a stats query holding every tile, against one on an empty state
  directory (the median of REPEATS alternating starts each); and the store's own part in process (open with its
  integrity check, load, resume);
- scans lost across 10 SIGKILLs of the shard of `posegrid run --state-dir` at seeded random points of its progress
  (each restarted by the launcher): the shard's scans fused and given up, and whether the export is bit for bit the
  in-process map.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from bench.scenarios import honest_posed_scans, office_run
from mapping.sensor_model import SensorModel
from schemas.files import load_map, save_posed_scans
from services import keys
from services.fusion_runner import fuse_posed_scans
from services.map_client import MapReader
from services.nodes.launcher import Children, free_port
from services.process import RejectCounter, get_logger
from services.state.shard import MapShard, ShardConfig
from services.state.store import writer
from services.state.store.db import DB_NAME, Batch, ShardStore, StoreIdentity, TileState
from services.state.store.journal import Journal
from services.streams import posed_stream
from services.zenoh_config import build_config

PARTICLES = 30
STEPS = 400
ROBOT = "bench"
REPEATS = 3
#: commit intervals (scans) measured besides the default; the seconds' bound stays the default's
COMMIT_SCANS = (8, 32, 128)
#: observed cells of the store a shard restarts on
RESTART_CELLS = 10**6
KILLS = 10
KILL_STEPS = 300
LOG = logging.getLogger("bench.persist")


def _config() -> ShardConfig:
    return ShardConfig(map_name="bench", shard=0, shards=1, model=SensorModel(resolution=0.05))


def _drive(pairs, directory: Path | None, every_scans: int) -> tuple[tuple[float, float], MapShard, float]:
    """Fuse ``pairs`` into a new shard as the mapper's loop does (take the scan, the pose, then a commit step); with
    ``directory``, on a new store there, finished with a clean stop. ((wall s, CPU s of every thread), the shard,
    mean commit ms)."""
    shard = MapShard(_config(), RejectCounter(LOG))
    shard.warm_up()
    persister = None
    commits: list[float] = []
    if directory is not None:
        store = ShardStore.open(directory, StoreIdentity("bench", 0, 1, shard.grid.tile_size, 0.05))
        timed = store.commit

        def commit(batch: Batch) -> float:
            started = time.perf_counter()
            try:
                return timed(batch)
            finally:
                commits.append(time.perf_counter() - started)

        store.commit = commit  # type: ignore[method-assign]
        shard.journal = Journal()
        persister = writer.Persister(store, every_scans, writer.DEFAULT_COMMIT_INTERVAL, LOG)
    started, cpu = time.perf_counter(), time.process_time()
    for scan, pose in pairs:
        shard.take(keys.robot_key(ROBOT, keys.SCAN), scan)
        shard.take(keys.robot_key(ROBOT, keys.POSE), pose)
        if persister is not None:
            persister.step(shard)
    if persister is not None and not persister.finish(shard):
        raise RuntimeError(f"the bench's store failed: {persister.failing}")
    elapsed = time.perf_counter() - started, time.process_time() - cpu
    mean_ms = 1e3 * float(np.mean(commits)) if commits else 0.0
    return elapsed, shard, mean_ms


def _overhead(pairs, folder: Path) -> dict:
    """Slowdown at the default commit interval and at COMMIT_SCANS, in wall time (the median of REPEATS paired runs'
    ratios) and in CPU time of every thread (the writer's included: what a machine with no idle core pays); bytes
    per observed cell at the default."""
    figures: dict = {}
    for every in (writer.DEFAULT_COMMIT_SCANS, *COMMIT_SCANS):
        wall, cpu, rates, commit_ms, per_cell = [], [], [], [], []
        for repeat in range(REPEATS):
            without = _drive(pairs, None, every)[0]
            directory = folder / f"k{every}-{repeat}"
            with_store, shard, mean_ms = _drive(pairs, directory, every)
            wall.append(with_store[0] / without[0] - 1.0)
            cpu.append(with_store[1] / without[1] - 1.0)
            rates.append((len(pairs) / without[0], len(pairs) / with_store[0]))
            commit_ms.append(mean_ms)
            per_cell.append(((directory / DB_NAME).stat().st_size, shard.grid.observed_cells()))
        figures[f"slowdown_commit_{every}_scans"] = float(np.median(wall))
        figures[f"cpu_overhead_commit_{every}_scans"] = float(np.median(cpu))
        figures[f"commit_ms_mean_{every}_scans"] = float(np.median(commit_ms))
        if every == writer.DEFAULT_COMMIT_SCANS:
            figures["slowdown_default"] = float(np.median(wall))
            figures["cpu_overhead_default"] = float(np.median(cpu))
            figures["scans_per_s_without_store"] = float(np.median([r[0] for r in rates]))
            figures["scans_per_s_with_store"] = float(np.median([r[1] for r in rates]))
            figures["observed_cells"] = per_cell[0][1]
            figures["db_bytes_per_observed_cell"] = per_cell[0][0] / per_cell[0][1]
    return figures


def _big_store(directory: Path, shard: MapShard) -> int:
    """A store of about RESTART_CELLS observed cells: the office's tiles repeated side by side; its observed cells."""
    tiles = [key for key in sorted(shard.grid.keys()) if shard.grid.tile_arrays(key)[2].any()]
    per_copy = sum(int(shard.grid.tile_arrays(key)[2].sum()) for key in tiles)
    copies = -(-RESTART_CELLS // per_copy)
    store = ShardStore.open(directory, StoreIdentity("bench", 0, 1, shard.grid.tile_size, 0.05))
    batch = Batch(cells_updated=shard.cells_updated)
    for copy in range(copies):
        for tx, ty in tiles:
            logodds, variance, observed = shard.grid.tile_arrays((tx, ty))
            batch.tiles.append(TileState((tx + 8 * copy, ty), logodds, variance, observed, ROBOT, 0))
    store.commit(batch)
    store.close()
    return copies * per_copy


def _serving_seconds(state_dir: Path, tiles: int) -> float:
    """Seconds from starting `posegrid mapper --state-dir state_dir` until it answers with ``tiles`` tiles."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    children = Children(get_logger("bench"))
    children.start("router", ["router", "--listen", endpoint])
    try:
        with zenoh.open(build_config("client", connect=[endpoint])) as session:
            reader = MapReader(session, "bench")
            started = time.perf_counter()
            argv = ["mapper", "--shard", "0", "--shards", "1", "--map", "bench", "--state-dir", str(state_dir)]
            children.start("mapper", [*argv, "--connect", endpoint])
            deadline = started + 300
            while (stats := reader.stats(timeout=1.0).get(0)) is None or stats.tiles_owned < tiles:
                if time.perf_counter() > deadline or children.failed():
                    raise RuntimeError("the bench's mapper did not come up")
                time.sleep(0.005)
            return time.perf_counter() - started
    finally:
        children.stop_all()


def _restart(shard: MapShard, folder: Path) -> dict:
    big = folder / "big"
    cells = _big_store(big, shard)
    started = time.perf_counter()
    store = ShardStore.open(big, StoreIdentity("bench", 0, 1, shard.grid.tile_size, 0.05))
    stored = store.load()
    MapShard(_config(), RejectCounter(LOG)).resume(stored)
    in_process = time.perf_counter() - started
    store.close()
    tiles = len(stored.tiles)
    serving, empty = [], []
    for repeat in range(REPEATS):  # (alternating: the machine's load moves both alike)
        empty.append(_serving_seconds(folder / f"empty-{repeat}", 0))
        serving.append(_serving_seconds(big, tiles))
    return {
        "restart_cells": cells,
        "restart_tiles": tiles,
        "restart_db_bytes": (big / DB_NAME).stat().st_size,
        "restart_store_s": in_process,
        "restart_to_serving_s": float(np.median(serving)),
        "restart_to_serving_empty_s": float(np.median(empty)),
    }


class _Lines:
    """A process's merged output, read line by line on a thread."""

    def __init__(self, argv: list[str]):
        self.process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.rstrip("\n"))

    def find(self, pattern: str, exclude: frozenset[int] | set[int] = frozenset(), timeout: float = 120.0) -> int:
        """The last int a line matching ``pattern`` captures that is not in ``exclude``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = [int(m.group(1)) for line in list(self.lines) if (m := re.search(pattern, line))]
            fresh = [value for value in found if value not in exclude]
            if fresh:
                return fresh[-1]
            time.sleep(0.02)
        raise RuntimeError(f"no line matching {pattern!r}: {self.lines[-10:]}")


def _kills(posed_path: Path, folder: Path, expected: dict) -> dict:
    """Kill the shard of a `posegrid run --state-dir` KILLS times; scans lost and whether the export is exact."""
    port, exported = free_port(), folder / "killed.npz"
    argv = [sys.executable, "-m", "services", "run", "--posed", str(posed_path), "--robot", ROBOT, "--rate", "max"]
    argv += ["--state-dir", str(folder / "killed"), "--export", str(exported), "--no-api", "--router-port", str(port)]
    argv += ["--max-restarts", "30", "--restart-delay", "0.05", "--max-restart-delay", "0.05"]
    run = _Lines(argv)
    rng = np.random.default_rng(32)
    try:
        pid = run.find(r"mapper\[0\] \(pid (\d+)\)")
        seen, target = {pid}, 0
        with zenoh.open(build_config("client", connect=[f"tcp/127.0.0.1:{port}"])) as session:
            reader = MapReader(session, "main")
            for _ in range(KILLS):
                target += int(rng.integers(1, KILL_STEPS // (KILLS + 2)))
                while (s := reader.stats(timeout=1.0).get(0)) is None or s.fused.get(ROBOT, 0) < target:
                    time.sleep(0.01)
                target = s.fused[ROBOT]
                time.sleep(float(rng.uniform(0.0, 0.02)))
                os.kill(pid, signal.SIGKILL)
                pid = run.find(r"mapper\[0\] restarted \(pid (\d+)\)", seen)
                seen.add(pid)
        code = run.process.wait(600)
    finally:
        if run.process.poll() is None:
            run.process.send_signal(signal.SIGINT)
            run.process.wait(60)
    finished = re.search(r"replay finished: (\d+) scans, each of 1 shard\(s\) fused (\d+)", "\n".join(run.lines))
    fused = int(finished.group(2)) if finished else 0
    got = vars(load_map(exported)) if code == 0 else {}
    same = bool(got) and all(np.array_equal(got[k], expected[k]) for k in ("logodds", "variance", "observed", "origin"))
    return {"kills": KILLS, "kill_scans": KILL_STEPS, "kill_scans_lost": KILL_STEPS - fused, "kill_map_identical": same}


def run() -> dict:
    posed = honest_posed_scans(office_run(steps=STEPS), particles=PARTICLES)
    pairs = [step.messages for step in posed_stream(posed, ROBOT).steps]
    with tempfile.TemporaryDirectory(prefix="posegrid-bench-persist-") as scratch:
        folder = Path(scratch)
        figures = _overhead(pairs, folder)
        _, shard, _ = _drive(pairs, None, 1)
        figures |= _restart(shard, folder)
        kill_posed = honest_posed_scans(office_run(seed=1, steps=KILL_STEPS), particles=PARTICLES)
        save_posed_scans(folder / "kill.npz", kill_posed)
        figures |= _kills(folder / "kill.npz", folder, fuse_posed_scans(kill_posed).rasterize())
    return figures
