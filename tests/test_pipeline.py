"""The distributed pipeline with real processes and real Zenoh sessions on loopback.

- `posegrid run --posed F --shards N --export M` writes the map `posegrid fuse F` builds, N = 1, 2, 3;
- garbage on every key the processes listen to is dropped, counted per key, logged once, and the
  processes keep working;
- Ctrl-C (SIGINT) on the launcher stops every child, mid-replay, with their exit codes reported.

Every process is started here or by the launcher started here, and ended by PID in a finalizer.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from peers import put
from schemas.files import PosedScans, PoseSet, load_map, load_posed_scans, save_posed_scans
from schemas.messages import (
    LandmarkObservations,
    LaserScan,
    MessageError,
    NodeStats,
    Odometry,
    PoseGaussian,
    PoseSamples,
    ShardStats,
    StreamEnd,
    TileUpdate,
    decode_message,
)
from services import history, keys
from services.cli import main
from services.ports import free_port
from services.state.ownership import tile_owner
from services.zenoh_config import build_config

pytestmark = pytest.mark.slow

ROOM = (-14.0, 14.0, -6.0, 6.0)  # x0, x1, y0, y1 of the walls, m: spans tiles tx -3..2, ty -1..0 at 12.8 m
RANGE_MAX = 8.0
CLI = [sys.executable, "-m", "services"]


# ------------------------------------------------------------------------------------------------ world


def room_ranges(poses: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Exact ranges from laser poses (T, 3) to the walls of ROOM along beam angles (B,); inf beyond RANGE_MAX."""
    x0, x1, y0, y1 = ROOM
    heading = poses[:, 2:3] + angles[None, :]
    c, s = np.cos(heading), np.sin(heading)
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (x1 - poses[:, :1]) / c, np.where(c < 0, (x0 - poses[:, :1]) / c, np.inf))
        ty = np.where(s > 0, (y1 - poses[:, 1:2]) / s, np.where(s < 0, (y0 - poses[:, 1:2]) / s, np.inf))
    ranges = np.minimum(tx, ty)
    return np.where(ranges <= RANGE_MAX, ranges, np.inf).astype(np.float32)


def make_posed(path: Path, form: str, steps: int = 36, beams: int = 120, particles: int = 6, seed: int = 3) -> Path:
    """A robot driving along the room's long axis, with noisy pose samples or a Gaussian per scan."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps)
    true = np.column_stack([-11.0 + 22.0 * t / (steps - 1), 1.5 * np.sin(t / 5.0), 0.3 * np.cos(t / 7.0)])
    angles = -np.pi + 2 * np.pi * np.arange(beams) / beams
    ranges = room_ranges(true, angles) + rng.normal(0, 0.01, (steps, beams)).astype(np.float32)
    if form == "gaussian":
        cov = np.tile(np.diag([0.02, 0.02, 0.005]) ** 2, (steps, 1, 1))
        poses = PoseSet(mean=true + rng.normal(0, 0.01, true.shape), cov=cov)
    else:
        samples = true[:, None, :] + rng.normal(0, [0.03, 0.03, 0.01], (steps, particles, 3))
        weights = rng.random((steps, particles))
        poses = PoseSet(samples=samples, weights=weights / weights.sum(axis=1, keepdims=True))
    save_posed_scans(
        path,
        PosedScans(
            ranges=ranges,
            angle_min=float(angles[0]),
            angle_increment=float(angles[1] - angles[0]),
            range_min=0.05,
            range_max=RANGE_MAX,
            stamps=0.1 * t,
            sensor_offset=np.zeros(3),
            poses=poses,
        ),
    )
    return path


def touched_tiles(resolution: float = 0.05, tile: int = 256) -> set[tuple[int, int]]:
    span = resolution * tile
    x0, x1, y0, y1 = ROOM
    return {
        (tx, ty)
        for tx in range(int(np.floor(x0 / span)), int(np.floor(x1 / span)) + 1)
        for ty in range(int(np.floor(y0 / span)), int(np.floor(y1 / span)) + 1)
    }


# ------------------------------------------------------------------------------------------------ processes


class Proc:
    """A child process whose merged output is read line by line on a thread."""

    def __init__(self, argv: list[str], **kwargs):
        self.process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)
        self.lines: list[str] = []
        self._queue: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self):
        for line in self.process.stdout:
            self.lines.append(line.rstrip("\n"))
            self._queue.put(line)

    def wait_for(self, pattern: str, timeout: float = 60.0) -> re.Match:
        deadline = time.monotonic() + timeout
        for line in list(self.lines):
            if match := re.search(pattern, line):
                return match
        while time.monotonic() < deadline:
            try:
                line = self._queue.get(timeout=0.2)
            except queue.Empty:
                if self.process.poll() is not None and self._queue.empty():
                    break
                continue
            if match := re.search(pattern, line):
                return match
        raise AssertionError(f"no line matching {pattern!r}; output:\n" + "\n".join(self.lines[-40:]))

    def output(self) -> str:
        return "\n".join(self.lines)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _http_status(url: str, timeout: float = 20.0) -> int:
    """The status of GET url, retried while the server is still binding its port."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as response:
                return response.status
        except urllib.error.URLError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


@pytest.fixture
def procs():
    """Starts processes; the finalizer ends every one still running (and the children they reported) by PID."""
    started: list[Proc] = []
    reported: list[int] = []

    def start(argv, **kwargs) -> Proc:
        proc = Proc(argv, **kwargs)
        started.append(proc)
        return proc

    start.reported = reported
    yield start
    for proc in started:
        reported += [int(pid) for pid in re.findall(r"\(pid (\d+)\)", proc.output())]
    for proc in reversed(started):
        if proc.process.poll() is None:
            proc.process.send_signal(signal.SIGINT)
            try:
                proc.process.wait(20)
            except subprocess.TimeoutExpired:
                proc.process.kill()
                proc.process.wait()
    for pid in reported:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


# ------------------------------------------------------------------------------------------------ tests


@pytest.mark.parametrize(
    "shards, form, bundle",
    [(1, "gaussian", []), (2, "samples", []), (3, "gaussian", []), (2, "gaussian", ["--bundle", "0.1"])],
)
def test_run_posed_export_equals_fuse(tmp_path, procs, shards, form, bundle):
    """`posegrid run --posed ... --export` over Zenoh gives `posegrid fuse`'s map, on 1 to 3 shards, and with the
    pose samples bundled (--bundle, passed on to the shards) the bundled map, which differs from the exact one."""
    owners = {tile_owner(tile, range(shards)) for tile in touched_tiles()}
    assert owners == set(range(shards)), "the test world must give every shard tiles"
    posed = make_posed(tmp_path / "posed.npz", form)
    fused = tmp_path / "fused.npz"
    draws = ["--samples", "12"] if form == "gaussian" else []  # fuse refuses a sample count for samples
    assert main(["fuse", str(posed), "-o", str(fused), *draws, *bundle]) == 0
    if bundle:
        exact = tmp_path / "exact.npz"
        assert main(["fuse", str(posed), "-o", str(exact), *draws]) == 0
        assert not np.array_equal(load_map(exact).logodds, load_map(fused).logodds)
    exported = tmp_path / "run.npz"
    run = procs(
        [
            *CLI,
            "run",
            "--posed",
            str(posed),
            "--shards",
            str(shards),
            "--export",
            str(exported),
            "--samples",
            "12",
            "--no-api",
            *(["--threads", "2"] if shards == 2 else []),  # (two fusion threads in each shard: the same map)
            *bundle,
        ]
    )
    assert run.process.wait(120) == 0, run.output()
    output = run.output()
    assert re.search(rf"stopped: router exited 0, (mapper\[\d\] exited 0, ){{{shards}}}source exited 0", output), output
    expected, got = load_map(fused), load_map(exported)
    assert got.logodds.shape == expected.logodds.shape
    np.testing.assert_array_equal(got.observed, expected.observed)
    np.testing.assert_allclose(got.logodds, expected.logodds, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.variance, expected.variance, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(got.origin, expected.origin)
    assert got.resolution == expected.resolution
    assert expected.observed.sum() > 10_000  # the map is not trivially empty


def test_launcher_stops_every_child_on_sigint_mid_replay(tmp_path, procs):
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=300)
    api_port = free_port()
    run = procs(
        [*CLI, "run", "--posed", str(posed), "--shards", "2", "--rate", "realtime", "--api-port", str(api_port)]
    )
    url = run.wait_for(r"HTTP API and map viewer: (http://\S+)").group(1)
    assert url == f"http://127.0.0.1:{api_port}/"
    banner = run.wait_for(r"running: (.*)")
    pids = {name: int(pid) for name, pid in re.findall(r"(\S+) \(pid (\d+)\)", banner.group(1))}
    assert set(pids) == {"router", "mapper[0]", "mapper[1]", "api", "source"}
    run.wait_for(r"publishing 300 steps")
    run.wait_for(r"api: serving on")
    assert _http_status(url) == 200
    assert all(_alive(pid) for pid in pids.values())
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(60) == 0, run.output()
    stopped = run.wait_for(r"stopped: (.*)").group(1)
    assert stopped == "router exited 0, mapper[0] exited 0, mapper[1] exited 0, api exited 0, source exited 0"
    assert not any(_alive(pid) for pid in pids.values())


def test_a_run_stopped_before_its_export_says_so_and_exits_130(tmp_path, procs):
    """A real-log probe: `run --export m.npz` stopped by Ctrl-C mid-replay exited 0 and wrote no file, without a
    word: `posegrid run --export m.npz && use m.npz` went on with no map. It says no map was written, exit 130.
    A determinism probe: the banner's `posegrid run --resume DIR` then starts a new session, which fuses the same
    scans a second time (12 051 cells off the uninterrupted map); the stop now gives the command that goes on."""
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=300)
    exported, state = tmp_path / "m.npz", tmp_path / "run state"
    run = procs([*CLI, "run", "--posed", str(posed), "--rate", "realtime", "--no-api", "--state-dir", str(state),
                 "--export", str(exported)])  # fmt: skip
    run.wait_for(r"publishing 300 steps")
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(60) == 130, run.output()
    hint = run.wait_for(r"to go on with this replay of the same input: (posegrid run --resume .*? --continue-session)")
    assert hint.group(1) == f"posegrid run --resume {shlex.quote(str(state))} --continue-session"
    said = run.wait_for(r"stopped before the replay ended \((\d+) of 300 scans fused by every shard\): (.*)")
    assert int(said.group(1)) < 300 and said.group(2) == f"no map written to {exported}"
    assert not exported.exists()


def test_a_run_whose_map_is_too_large_for_one_file_says_what_to_do(tmp_path, procs):
    """A scale probe: a run whose tiles span 65 x 65 tiles of 12.8 m (more than one raster holds) ended its export
    with the library's "read it tile by tile instead". It now says nothing was written and how to get the map."""
    posed = tmp_path / "edge.npz"
    edge = np.array([[0.0, 0.0, 0.0], [64 * 12.8 + 1.0, 64 * 12.8 + 1.0, 0.0]])
    np.savez(posed, ranges=np.ones((2, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
             range_max=5.0, stamps=np.arange(2.0), samples=edge[:, None, :], weights=np.ones((2, 1)))  # fmt: skip
    exported = tmp_path / "m.npz"
    run = procs([*CLI, "run", "--posed", str(posed), "--no-api", "--no-state", "--export", str(exported)])
    assert run.process.wait(300) == 1, run.output()
    said = run.wait_for(r"posegrid run: error: cannot export the map: (.*)").group(1)
    assert said.startswith("the map's tiles span 16640 x 16640 cells") and "GET /maps/MAP/export" in said
    assert f"nothing written to {exported}" in said and not exported.exists()


def test_a_run_whose_shards_refused_a_scan_by_their_limit_says_so(tmp_path, procs):
    """A probe: a run whose shards refused a scan by --max-map-cells said the map missed it because "their poses or
    scans never came". Now it says the shards refused to fuse it. Scans at (3, 3) m reach the 3 x 3 tiles of 12.8 m
    around the origin's, within the limit of 9 tiles; the one 300 m away would add 9 more."""
    posed = tmp_path / "far.npz"
    spots = np.array([[3.0, 3.0, 0.0], [300.0, 3.0, 0.0], [3.0, 3.0, 0.0]])
    np.savez(posed, ranges=np.ones((3, 3), np.float32), angle_min=0.0, angle_increment=0.1, range_min=0.1,
             range_max=5.0, stamps=np.arange(3.0), samples=spots[:, None, :], weights=np.ones((3, 1)))  # fmt: skip
    exported = tmp_path / "m.npz"
    run = procs(
        [*CLI, "run", "--posed", str(posed), "--no-api", "--no-state", "--export", str(exported)]
        + ["--max-map-cells", str(9 * 256 * 256)]
    )
    assert run.process.wait(300) == 1, run.output()
    said = run.wait_for(r"error: the map misses up to (\d+) scans the shards gave up on: (.*)")
    assert said.group(1) == "1" and said.group(2).startswith("the shards refused to fuse 1 of them"), said.group(0)
    assert "--max-map-cells" in run.output() and load_map(exported).observed.any()


def test_launcher_stops_on_sigint_while_it_compiles_the_fusion_kernels(tmp_path, procs):
    """On a fresh install `posegrid run` compiles the fusion kernels before it starts the shards (40 s here); a
    Ctrl-C then took effect only after the compile. Now it stops at once (an empty kernel cache makes the compile
    happen: numba's NUMBA_CACHE_DIR, a folder of this test's)."""
    run = procs([*CLI, "run", "--no-api", "--no-state"], env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)})
    run.wait_for("compiling the fusion kernels")
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(15) == 130, run.output()  # (the compile alone takes longer than that)
    # (a router still starting as the SIGTERM comes dies of it at once: -15, as clean an exit as 0 here; a suite run
    # on a loaded machine saw it)
    assert run.wait_for(r"stopped: (.*)").group(1) in ("router exited 0", f"router exited {-signal.SIGTERM}")
    assert "fusion kernels ready" not in run.output()


def test_launcher_stopped_as_its_children_start_stops_them_without_a_crash(procs):
    """Ctrl-C right after the banner: the children are still importing. The launcher's SIGINT became a
    KeyboardInterrupt inside numpy's import (an ImportError and its traceback) or inside the interpreter's start-up
    (a fatal error), the child exited 1 and so did the run. It sends SIGTERM now, which a child not yet handling
    it dies of at once (-15, a clean exit for the launcher)."""
    run = procs([*CLI, "run", "--no-api", "--no-state"])
    run.wait_for(r"running: ")
    run.process.send_signal(signal.SIGINT)
    assert run.process.wait(60) in (0, 130), run.output()
    stopped = run.wait_for(r"stopped: (.*)").group(1)
    assert all(int(code) in (0, 130, -signal.SIGTERM) for code in re.findall(r"exited (-?\d+)", stopped)), stopped
    assert "Traceback" not in run.output() and "Fatal Python error" not in run.output(), run.output()


# ------------------------------------------------------------------------------------------------ garbage


def _scan(seq: int, robot: str = "r1") -> LaserScan:
    angles = np.linspace(-np.pi, np.pi, 60, endpoint=False)
    ranges = room_ranges(np.array([[0.5, 0.2, 0.0]]), angles)[0]
    return LaserScan(
        robot=robot,
        seq=seq,
        stamp=0.1 * seq,
        angle_min=float(angles[0]),
        angle_increment=float(angles[1] - angles[0]),
        range_min=0.05,
        range_max=RANGE_MAX,
        sensor_offset=np.zeros(3),
        ranges=ranges,
        no_return_range=RANGE_MAX,
    )


def _pose(seq: int, robot: str = "r1") -> PoseSamples:
    return PoseSamples(
        robot=robot,
        seq=seq,
        stamp=0.1 * seq,
        samples=np.array([[0.5, 0.2, 0.0], [0.52, 0.2, 0.01]]),
        weights=np.array([0.5, 0.5]),
    )


GARBAGE = {
    "malformed": b"\xc1\x00garbage",
    "truncated": _scan(0).encode()[:-7],
    "version": msgpack.packb({**msgpack.unpackb(_scan(0).encode()), "v": 99}),
    "unknown type": msgpack.packb({"type": "Telemetry", "v": 1}),
}


def test_a_shard_cut_off_mid_stream_takes_what_it_missed_from_the_history(tmp_path, procs):
    """A mapper stalled past its Zenoh lease (SIGSTOP; a 1 s lease here) loses what is published meanwhile, and
    maybe the end of the stream. The source repeats the end until the shard knows it, and the shard takes the
    scans and poses it never got from the source's history (a posed-scan file's source holds both), so every
    scan is fused and the run finishes. Before the history, the shard counted them as given up (10 to 100 of
    120 here); before that, it waited for them for ever, the source gave up after 60 s, and `posegrid run`
    stopped everything."""
    lease = tmp_path / "lease.json5"
    lease.write_text("{transport: {link: {tx: {lease: 1000}}}}")
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=120)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zenoh_args = ["--connect", endpoint, "--zenoh-config", str(lease)]
    procs([*CLI, "router", "--listen", endpoint, "--zenoh-config", str(lease)]).wait_for("routing")
    mapper = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "gap", *zenoh_args])
    mapper.wait_for("up; tiles on")
    source = procs(
        [*CLI, "source", "--posed", str(posed), "--map", "gap", "--wait-mappers", "1", "--rate", "2", *zenoh_args]
    )
    source.wait_for("publishing")
    time.sleep(1.5)
    os.kill(mapper.process.pid, signal.SIGSTOP)
    time.sleep(4.0)
    os.kill(mapper.process.pid, signal.SIGCONT)
    assert source.process.wait(90) == 0, source.output()
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        from services.map_client import MapReader

        deadline, stats = time.monotonic() + 60, None
        while time.monotonic() < deadline:  # scans waiting for a lost pose settle 15 s after the robot goes quiet
            stats = MapReader(session, "gap").stats()[0]
            if stats.fused.get("robot0", 0) + stats.discarded.get("robot0", 0) == 120:
                break
            time.sleep(0.5)
    finally:
        session.close()
    assert stats.ended == {"robot0": 120}
    assert stats.fused == {"robot0": 120} and not stats.discarded.get("robot0"), stats
    mapper.wait_for(r"took \d+ scan\(s\) of robot 'robot0' in seqs \d+-\d+ from the history \(lost in transit")


def test_a_second_run_under_a_robot_name_the_shard_holds_says_so(tmp_path, procs):
    """A run under the name of a robot whose run the shard has fused: its first seqs are refused as duplicates and
    its scans past the first run's end were fused into that robot's map; the source said nothing (a probe, 500 + 60
    scans). It now warns. (Not an exit 2: the shards count rejections by key and by kind apart, so another robot's
    clash on the map with any refusal on this robot's key looks the same, a re-probe.) The first run, repeated exactly
    (a restarted source replaying its input), says nothing: its scans come back as resent, not duplicates."""
    first, second = (
        make_posed(tmp_path / "a.npz", "samples", steps=20),
        make_posed(tmp_path / "b.npz", "samples", steps=25, seed=9),
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint]).wait_for(
        "up; tiles on"
    )

    def source(posed: Path):
        argv = ["source", "--posed", str(posed), "--map", "m", "--robot", "beta", "--wait-mappers", "1"]
        return procs([*CLI, *argv, "--rate", "max", "--connect", endpoint])

    # a rerun of the first log with other poses: its scans come back as resent, every pose is refused as a duplicate,
    # and none of it is in the map; the source said nothing (a probe of a fleet in one map)
    repose = tmp_path / "a-reposed.npz"
    moved = load_posed_scans(first)
    shifted = PoseSet(samples=moved.poses.samples + np.array([0.0, 20.0, 0.0]), weights=moved.poses.weights)
    save_posed_scans(repose, replace(moved, poses=shifted))
    for posed, clash in ((first, False), (first, False), (repose, True), (second, True)):
        run = source(posed)
        assert run.process.wait(120) == 0, run.output()
        assert ("may hold some of its seqs" in run.output()) == clash, run.output()


def test_a_rerun_sent_while_the_shard_is_busy_with_another_robot_still_hears_of_its_clash(tmp_path, procs):
    """The rerun of the test above while the shard takes another robot's long run: the shard takes the robots'
    messages in turns, so the rerun's were taken long after the source had left, "accounted for" by the first
    run's counts, and it said nothing of the clash. It now waits for the shard to take its end."""
    first = make_posed(tmp_path / "a.npz", "samples", steps=20)
    busy = make_posed(tmp_path / "busy.npz", "samples", steps=400, beams=720, particles=40, seed=5)
    repose = tmp_path / "a-reposed.npz"
    moved = load_posed_scans(first)
    shifted = PoseSet(samples=moved.poses.samples + np.array([0.0, 20.0, 0.0]), weights=moved.poses.weights)
    save_posed_scans(repose, replace(moved, poses=shifted))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint]).wait_for(
        "up; tiles on"
    )

    def source(posed: Path, robot: str):
        argv = ["source", "--posed", str(posed), "--map", "m", "--robot", robot, "--wait-mappers", "1"]
        return procs([*CLI, *argv, "--rate", "max", "--connect", endpoint])

    run = source(first, "beta")
    assert run.process.wait(120) == 0, run.output()
    other = source(busy, "alpha")
    other.wait_for("published 40 of 400 steps")
    run = source(repose, "beta")
    assert run.process.wait(120) == 0, run.output()
    assert "may hold some of its seqs" in run.output(), run.output()
    assert other.process.wait(120) == 0, other.output()


def test_a_rerun_at_max_rate_is_held_to_its_window_as_a_first_run_is(tmp_path, procs):
    """A run sent again under its robot name, --rate max --window 4, into a shard whose intake holds 12 messages
    (--intake-buffer): each run holds at most 4 scans and their poses in flight, so neither overflows the intake.
    When the source counted the first run's fused scans as the rerun's, the rerun's 200 steps went out at once and
    the intake overflowed."""
    posed = make_posed(tmp_path / "a.npz", "samples", steps=200)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    mapper = ["mapper", "--shard", "0", "--shards", "1", "--map", "m", "--intake-buffer", "12", "--connect", endpoint]
    procs([*CLI, *mapper]).wait_for("up; tiles on")
    argv = ["source", "--posed", str(posed), "--map", "m", "--robot", "r", "--wait-mappers", "1", "--window", "4"]
    for _ in range(2):
        run = procs([*CLI, *argv, "--rate", "max", "--connect", endpoint])
        assert run.process.wait(120) == 0, run.output()
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        from services.map_client import MapReader

        stats = MapReader(session, "m").stats(timeout=5.0)[0]
    finally:
        session.close()
    scan, pose = keys.robot_key("r", keys.SCAN), keys.robot_key("r", keys.POSE)
    assert stats.fused == {"r": 200} and stats.resent == {scan: 200, pose: 200}, stats
    assert not stats.refused.get("overflow") and not any(stats.overflow.values()), stats


def test_a_source_counts_its_run_accounted_for_only_once_every_shard_took_its_end():
    """A rerun under a robot name whose run of as many scans a shard holds: that run's counts (its end, its scans
    fused) accounted for the new run before the shard had taken any of it, so the source left at once and missed
    the duplicates its messages then met (the test above failed once in four runs under load). The shard takes a
    robot's messages in order, so the new run's end taken says it has taken the run."""
    from services.nodes.source import UPTIME_SLACK, baselines, took_end
    from test_api_status import shard

    end_key = keys.robot_key("r", keys.END)
    before = baselines([shard(0, received={end_key: 1}, uptime=50.0), shard(1, uptime=50.0)], "r")
    assert before == {0: (1, 0, 50.0), 1: (0, 0, 50.0)}
    same = [shard(0, received={end_key: 1}, uptime=53.0), shard(1, received={end_key: 1}, uptime=53.0)]
    assert not took_end(same, "r", before, elapsed=3.0)  # shard 0 has not taken this run's end yet
    taken = [shard(0, received={end_key: 2}, uptime=53.0), shard(1, received={end_key: 1}, uptime=53.0)]
    assert took_end(taken, "r", before, elapsed=3.0)
    other_robot = [shard(0, received={end_key: 1, keys.robot_key("q", keys.END): 5}, uptime=53.0), taken[1]]
    assert not took_end(other_robot, "r", before, elapsed=3.0)
    # a shard restarted since the run began counts from 0: one end taken is this run's
    restarted = shard(0, received={end_key: 1}, uptime=1.0)
    assert took_end([restarted, taken[1]], "r", before, elapsed=3.0)
    assert not took_end([shard(0, uptime=1.0), taken[1]], "r", before, elapsed=3.0)
    # within the slack of a snapshot's age a shard has not restarted; a shard that was not there at the start: 0
    assert not took_end([shard(0, received={end_key: 1}, uptime=53.0 - UPTIME_SLACK / 2), taken[1]], "r", before, 3.0)
    assert took_end([*taken, shard(2, received={end_key: 1}, uptime=2.0)], "r", before, elapsed=3.0)
    assert not took_end([*taken, shard(2, uptime=2.0)], "r", before, elapsed=3.0)


def test_a_sources_window_counts_the_scans_each_shard_dealt_with_since_the_run_began():
    """What a source at --rate max counts as taken by the shards (services.nodes.source.scans_taken), against counts
    worked by hand: a scan fused, given up, dropped as a copy (resent) or refused on the robot's scan key, less what
    the shard had dealt with when the run began. Counted whole, a rerun under a robot name whose earlier run of 100
    scans the shard had fused was "taken" before it began, and went out unthrottled."""
    from services.nodes.source import UPTIME_SLACK, baselines, scans_taken
    from services.process import OTHER_KEYS
    from test_api_status import shard

    scan, pose = keys.robot_key("r", keys.SCAN), keys.robot_key("r", keys.POSE)
    earlier = shard(0, fused={"r": 98, "q": 7}, discarded={"r": 2}, uptime=50.0)
    before = baselines([earlier, shard(1, uptime=50.0)], "r")
    assert before[0].scans == 100 and before[1].scans == 0
    # the rerun's first 30 scans: 25 copies of the ones fused and 5 that differ (refused as duplicates), poses apart
    now = shard(
        0, fused={"r": 98, "q": 9}, discarded={"r": 2}, resent={scan: 25, pose: 30}, rejected={scan: 5, pose: 1}
    )
    other = shard(1, fused={"r": 27}, discarded={"r": 1}, uptime=53.0)
    assert scans_taken([replace(now, uptime=53.0), other], "r", before, elapsed=3.0) == 28  # (shard 1: 27 + 1)
    assert scans_taken([replace(now, uptime=53.0)], "r", before, elapsed=3.0) == 30
    # refusals a shard could no longer count by key (a peer filled its table) are counted as this robot's
    assert scans_taken([replace(now, uptime=53.0, rejected={OTHER_KEYS: 4})], "r", before, elapsed=3.0) == 29
    # a shard restarted since the run began (or not there then) counts from 0: its copies and refusals count anew
    assert scans_taken([replace(now, uptime=1.0)], "r", before, elapsed=3.0) == 130
    assert scans_taken([replace(now, uptime=53.0 - UPTIME_SLACK / 2)], "r", before, elapsed=3.0) == 30
    assert scans_taken([shard(2, fused={"r": 3}, uptime=2.0)], "r", before, elapsed=3.0) == 3


def test_a_mapper_restarted_while_the_source_holds_back_takes_the_run_from_the_histories(tmp_path, procs):
    """With --rate max the source holds back until the shards take what it sent, so a restarted mapper sees no
    live message and no gap to recover from: the source gave up after 60 s and the map was empty. Now the
    mapper takes the run so far from the histories at startup (the source's scans, the SLAM node's poses), and
    the source waits for every scan to be accounted for before it goes (while it goes on answering its history).
    The two histories answer one after the other; taken in that order, a run longer than the join buffer (4
    halves here, 512 by default) overflowed it, and most scans were given up (1 640 of 3 000 in a run
    restarted at step 2 000)."""
    sim = tmp_path / "sim"
    assert main(["simulate", str(sim), "--steps", "60", "--beams", "31", "--seed", "3"]) == 0
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    procs([*CLI, "slam-node", "--robot", "r1", "--algo", "ekf", "--connect", endpoint]).wait_for("up for robot")
    mapper_argv = [
        *CLI,
        "mapper",
        "--shard",
        "0",
        "--shards",
        "1",
        "--map",
        "again",
        "--join-buffer",
        "4",
        "--connect",
        endpoint,
    ]
    first = procs(mapper_argv)
    first.wait_for("up; tiles on")
    source = procs(
        [
            *CLI,
            "source",
            "--sim-dir",
            str(sim),
            "--robot",
            "r1",
            "--map",
            "again",
            "--wait-mappers",
            "1",
            "--wait-slam",
            "--rate",
            "max",
            "--window",
            "4",
            "--connect",
            endpoint,
        ]
    )
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        from services.map_client import MapReader

        reader = MapReader(session, "again")
        deadline = time.monotonic() + 60
        while (progress := reader.stats().get(0)) is None or progress.fused.get("r1", 0) < 30:
            assert time.monotonic() < deadline, "the first mapper fused fewer than 30 scans in 60 s"
            time.sleep(0.05)
        first.process.kill()
        first.process.wait(10)
        second = procs(mapper_argv)
        assert source.process.wait(90) == 0, source.output()
        second.wait_for(
            r"took [1-9]\d* scan\(s\) and \d+ pose\(s\) published before this shard was up from the "
            "histories"
        )  # scans among them: the ones the killed shard had not fused
        stats = reader.stats()[0]
    finally:
        session.close()
    assert stats.fused == {"r1": 60} and not stats.discarded.get("r1") and stats.overflow["join"] == 0, stats


def test_garbage_on_every_key_is_counted_and_processes_keep_working(tmp_path, procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = procs([*CLI, "router", "--listen", endpoint])
    router.wait_for("routing")
    mappers = [procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint])]
    node = procs([*CLI, "slam-node", "--robot", "r1", "--algo", "ekf", "--initial", "0,0,0", "--connect", endpoint])
    for mapper in mappers:
        mapper.wait_for("up; tiles on")
    node.wait_for("up for robot")
    session = zenoh.open(build_config("client", connect=[endpoint]))
    node_poses: list = []  # what the SLAM node publishes (the test's own garbage on the key is left out)

    def keep_gaussians(sample):
        with contextlib.suppress(MessageError):  # the test's own garbage on the key is not the node's
            node_poses.append(decode_message(sample.payload.to_bytes(), PoseGaussian))

    listener = session.declare_subscriber("pg/r1/pose", keep_gaussians)
    try:
        keys = ["pg/r1/scan", "pg/r1/pose", "pg/r1/end", "pg/r1/odom", "pg/r1/landmarks", "pg/r1/prior"]
        for key in keys:
            for payload in GARBAGE.values():
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        put(session, "pg/r1/scan", _pose(0).encode())  # a valid message of the wrong type for its key
        put(session, "pg/r2/scan", _scan(0).encode())  # a valid scan claiming another robot than its key
        # valid messages that drive the EKF 1e14 m away: its pose is no PoseGaussian; the step is skipped
        put(
            session,
            "pg/r1/odom",
            Odometry(
                robot="r1", seq=0, stamp=0.0, pose=np.zeros((0, 3)), commands=np.array([[1e7, 0.0, 1e7]])
            ).encode(),
        )
        put(
            session,
            "pg/r1/landmarks",
            LandmarkObservations(
                robot="r1", seq=0, stamp=0.0, ids=np.zeros(0, np.int64), ranges=np.zeros(0), bearings=np.zeros(0)
            ).encode(),
        )
        # ... and the filter is back where it was: the next, ordinary step is published
        put(
            session,
            "pg/r1/odom",
            Odometry(
                robot="r1", seq=1, stamp=0.1, pose=np.zeros((0, 3)), commands=np.array([[0.5, 0.0, 0.1]])
            ).encode(),
        )
        put(
            session,
            "pg/r1/landmarks",
            LandmarkObservations(
                robot="r1", seq=1, stamp=0.1, ids=np.zeros(0, np.int64), ranges=np.zeros(0), bearings=np.zeros(0)
            ).encode(),
        )
        for selector in ("pg/map/m/tile/0/*/*", "pg/map/m/stats/*"):
            list(session.get(selector, payload=b"\xff garbage query", timeout=5))
        # the shards still work: a valid scan and pose are joined and fused, in reverse order (robot r3: r1's
        # poses come from the SLAM node, and a second publisher of them would race it)
        put(session, "pg/r3/pose", _pose(0, "r3").encode())
        put(session, "pg/r3/scan", _scan(0, "r3").encode())
        put(session, "pg/r3/end", StreamEnd(robot="r3", scans=1).encode())
        deadline = time.monotonic() + 30
        while True:
            stats = [
                decode_message(r.ok.payload.to_bytes(), ShardStats)
                for r in session.get("pg/map/m/stats/*", timeout=5)
                if r.ok is not None
            ]
            if (
                len(stats) == 1 and stats[0].fused.get("r3") == 1 and stats[0].ended.get("r3") == 1
            ) or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        tiles = [r.ok for r in session.get("pg/map/m/tile/0/*/*", timeout=10) if r.ok is not None]
        deadline = time.monotonic() + 30
        while not node_poses and time.monotonic() < deadline:
            time.sleep(0.1)
        node_pose = node_poses[0] if node_poses else None
        node_stats = [
            decode_message(r.ok.payload.to_bytes(), NodeStats)
            for r in session.get("pg/r1/slam/stats", timeout=5)
            if r.ok is not None
        ]
    finally:
        listener.undeclare()
        session.close()
    assert len(stats) == 1 and stats[0].fused == {"r3": 1}, (repr(stats), mappers[0].output())
    for s in stats:
        # the mappers subscribe to scan, pose and end; every garbage payload there is counted on its key
        assert s.rejected == {
            "pg/r1/scan": len(GARBAGE) + 1,
            "pg/r1/pose": len(GARBAGE),
            "pg/r1/end": len(GARBAGE),
            "pg/r2/scan": 1,
        }, s.rejected
        assert s.discarded == {} and s.ended == {"r3": 1}, s
        assert s.received["pg/r1/scan"] == len(GARBAGE) + 1
    assert tiles and sum(s.tiles_owned for s in stats) == len(tiles)
    # the SLAM node subscribes to scan, odom, landmarks, end and prior of its robot
    assert len(node_stats) == 1
    assert node_stats[0].rejected == {
        "pg/r1/scan": len(GARBAGE) + 1,
        "pg/r1/steps": 1,
        **{f"pg/r1/{k}": len(GARBAGE) for k in ("odom", "landmarks", "end", "prior")},
    }, node_stats[0].rejected
    assert node_stats[0].steps_done == 2 and node_stats[0].poses_published == 1
    assert node_pose is not None and node_pose.seq == 1
    # 0.5 m/s for 0.1 s from the start (the mean given out is the heading's turn's, slam.turn_moments: 3e-7 m off)
    np.testing.assert_allclose(node_pose.mean, [0.05, 0.0, 0.0], atol=1e-6)
    assert router.process.poll() is None and node.process.poll() is None
    assert all(m.process.poll() is None for m in mappers)
    for mapper in mappers:
        mapper.process.send_signal(signal.SIGINT)
        assert mapper.process.wait(30) == 0
        log = mapper.output()
        # logged once per (key, kind): 3 kinds of MessageError on pg/r1/scan (malformed x2, version, type x2)
        assert len(re.findall(r"dropped a message on pg/r1/scan \(malformed\)", log)) == 1, log
        assert len(re.findall(r"dropped a message on pg/r1/scan \(type\)", log)) == 1, log
        assert len(re.findall(r"dropped a message on pg/r1/scan \(version\)", log)) == 1, log


# ------------------------------------------------------------------------------------------------ SLAM node


def test_run_through_the_slam_node_equals_offline_slam_then_fuse(tmp_path, procs):
    """simulate -> (slam-node over zenoh -> shard) must give what `posegrid slam` then `posegrid fuse` give."""
    sim = tmp_path / "sim"
    assert main(["simulate", str(sim), "--steps", "40", "--beams", "121", "--seed", "5"]) == 0
    offline = tmp_path / "ekf.npz"
    assert main(["slam", str(sim), "--algo", "ekf", "-o", str(offline)]) == 0
    fused = tmp_path / "fused.npz"
    assert main(["fuse", str(offline), "-o", str(fused), "--samples", "8"]) == 0
    exported = tmp_path / "run.npz"
    run = procs(
        [*CLI, "run", "--sim-dir", str(sim), "--algo", "ekf", "--samples", "8", "--no-api", "--export", str(exported)]
    )
    assert run.process.wait(120) == 0, run.output()
    assert "slam-node exited 0" in run.output()
    expected, got = load_map(fused), load_map(exported)
    np.testing.assert_array_equal(got.observed, expected.observed)
    np.testing.assert_allclose(got.logodds, expected.logodds, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.variance, expected.variance, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(got.origin, expected.origin)


def _write_log(sim, path: Path, fmt: str) -> Path:
    """A simulated run as a CARMEN log or a ROS 1 bag: its scans with the true poses as odometry."""
    if fmt == "carmen":
        from slam.carmen import write_carmen_scans

        write_carmen_scans(path, sim, odometry=sim.true_poses)
        return path
    from bags import BagBuilder

    bag = BagBuilder()
    bag.tf(0.0, "base_link", "laser", *sim.sensor_offset, topic="/tf_static")
    for stamp, ranges, (x, y, yaw) in zip(sim.stamps, sim.ranges, sim.true_poses):
        bag.odom(stamp, x, y, yaw)
        bag.scan(stamp, ranges, angle_min=sim.angle_min, increment=sim.angle_increment, range_max=sim.range_max)
    bag.odom(sim.stamps[-1] + 0.1, *sim.true_poses[-1])  # odometry past the last scan, for --odom-delay
    return bag.write(path)


def grid_filter_in_process(stream, particles: int, seed: int) -> PosedScans:
    """The posed scans the SLAM node's grid FastSLAM driver gives, in this process, for a source ``stream``
    (services.streams): every scan with the particles it was integrated at (resample threshold 0.5), its beams with
    no return clearing as far as its message says (a posed-scan file's way: `posegrid slam`'s)."""
    from services.commands.gridslam import posed_no_returns
    from services.keys import ODOM, SCAN
    from services.state.slam import GridDriver
    from slam.gridslam import GridSlamConfig

    config = GridSlamConfig(particles=particles, particle_cap=particles, resample_threshold=0.5)  # a fixed count
    driver = GridDriver(stream.prior.mean, config, seed=seed)
    scans, samples, weights = [], [], []
    for step in stream.steps:
        parts = {
            SCAN if isinstance(m, LaserScan) else ODOM: m for m in step.messages if isinstance(m, (LaserScan, Odometry))
        }
        poses, w = driver.step(parts)
        scans.append(parts[SCAN])
        samples.append(poses)
        weights.append(w)
    first = scans[0]
    range_max = np.full(len(scans), first.range_max)
    (clears,) = {m.no_return_range for m in scans}
    ranges, range_max = posed_no_returns(np.array([m.ranges for m in scans]), range_max, range_max, clears)
    return PosedScans(
        ranges=ranges,
        angle_min=first.angle_min,
        angle_increment=first.angle_increment,
        range_min=first.range_min,
        range_max=range_max,
        stamps=np.array([m.stamp for m in scans]),
        sensor_offset=first.sensor_offset,
        poses=PoseSet(samples=np.array(samples), weights=np.array(weights)),
    )


def test_a_run_whose_slam_node_refused_a_step_says_why_the_map_misses_its_scan(tmp_path, procs):
    """A probe: a live run of a log whose odometry jumps 80 m for one scan ended with exit 1 and "the map misses up
    to 1 scans the shards gave up on", which was right but did not say why. The run now asks the SLAM node and says
    it could not take that step; the rest of the map is written."""
    from slam.carmen import write_carmen_scans
    from slam.gridslam.simlogs import sim_log

    log = sim_log("room", seed=1)
    odometry = log.odometry.copy()
    odometry[15] += np.array([80.0, 0.0, 0.0])
    path = tmp_path / "spike.clf"
    write_carmen_scans(path, log, odometry=odometry)
    exported = tmp_path / "run.npz"
    run = procs(
        [*CLI, "run", "--carmen", str(path), "--particles", "5", "--particle-cap", "5", "--no-api", "--no-state"]
        + ["--export", str(exported)]
    )
    assert run.process.wait(180) == 1, run.output()
    said = run.wait_for(r"error: the map misses up to (\d+) scans the shards gave up on: (.*)")
    assert said.group(1) == "1" and said.group(2).startswith("the SLAM node could not take 1 step(s)"), said.group(0)
    assert "seq 15: the odometry moved 80 m in 0.1 s" in run.output() and load_map(exported).observed.any()


def test_why_scans_were_given_up_is_not_taken_from_two_processes_answering_as_the_slam_node(procs):
    """The run's reason comes from the SLAM node's stats; a peer answering as the node too could make it name a
    cause that is not one (its own count of refused steps): with two answers the run says so instead."""
    from services.nodes.launcher import Plan, _given_up_because

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    plan = Plan(map_name="m", robot="r1", shards=1, resolution=0.05, mapper_argv=[], source_argv=[], slam_argv=[])
    node, peer, asker = (zenoh.open(build_config("client", connect=[endpoint])) for _ in range(3))
    try:
        said = []
        for answerer, refused in ((node, 4), (peer, 0)):
            payload = _stats_payload(refused)
            answerer.declare_queryable(keys.slam_stats_key("r1"), lambda q, p=payload: q.reply(q.key_expr, p))
            answers = 1 if answerer is node else 2
            deadline = time.monotonic() + 10
            while len(_everyones_answers(asker, keys.slam_stats_key("r1"))) < answers:
                assert time.monotonic() < deadline, "the answerers' queryables never reached the asker"
                time.sleep(0.1)
            said.append(_given_up_because(asker, plan))
    finally:
        for session in (node, peer, asker):
            session.close()
    assert said[0].startswith("the SLAM node could not take 4 step(s)"), said
    assert said[1].endswith("2 processes answer as the SLAM node of robot 'r1' (docs/security.md)"), said
    assert "could not take" not in said[1]


def _everyones_answers(session: zenoh.Session, key: str) -> list[zenoh.Sample]:
    """The answers of every queryable on ``key`` (zenoh asks the best match only, by default)."""
    target, every = zenoh.QueryTarget.ALL, zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)
    return [r.ok for r in session.get(key, target=target, consolidation=every, timeout=2.0) if r.ok is not None]


def _stats_payload(refused_steps: int) -> bytes:
    """A SLAM node's stats of robot r1 that count ``refused_steps`` refused steps and nothing else."""
    return NodeStats(
        robot="r1",
        algorithm="gridslam",
        poses_published=0,
        steps_done=0,
        uptime=1.0,
        received={},
        rejected={keys.robot_key("r1", "steps"): refused_steps},
        out_of_order={},
        noise_scale=1.0,
        consistency={},
        health={},
    ).encode()


@pytest.mark.parametrize(("fmt", "clears"), [("carmen", None), ("bag", None), ("carmen", 8.0)])
def test_grid_fastslam_node_over_zenoh_gives_the_map_of_its_filter_in_process(tmp_path, procs, fmt, clears):
    """run --carmen / --bag (source -> grid FastSLAM slam-node -> shard, over Zenoh) must give the map that the
    same filter, fed the same scans in this process, and `posegrid fuse` give. The bag's odometry is read
    0.04 s after each scan (--odom-delay), between its odometry messages. The log's beams with no return say
    nothing by default; with --no-return-range 8 they clear up to 8 m (its range_max), and the map holds more."""
    from services.commands.logs import read_log
    from services.fusion_runner import fuse_posed_scans
    from services.streams import laser_log_stream
    from slam.laserlog import NO_RETURN_RANGE, with_odometry_delay
    from slam.simulator import simulate_office

    sim = simulate_office(seed=4, steps=60, n_beams=91, range_max=8.0)
    log = _write_log(sim, tmp_path / ("office.clf" if fmt == "carmen" else "office.bag"), fmt)
    delay = 0.0 if fmt == "carmen" else 0.04
    stream = laser_log_stream(with_odometry_delay(read_log(log), delay), "robot0", clears or NO_RETURN_RANGE)
    assert len(stream.steps) == 60
    posed = grid_filter_in_process(stream, particles=5, seed=7)
    expected = fuse_posed_scans(posed).rasterize()
    assert len({tuple(np.round(s[:, :2].ravel(), 9)) for s in posed.poses.samples}) > 1  # the particles do spread
    if clears is not None:
        nothing = fuse_posed_scans(replace(posed, ranges=np.where(np.isinf(posed.ranges), 0.0, posed.ranges)))
        assert expected["observed"].sum() > nothing.rasterize()["observed"].sum()

    exported = tmp_path / "run.npz"
    run = procs(
        [
            *CLI,
            "run",
            f"--{fmt}",
            str(log),
            "--odom-delay",
            str(delay),
            "--particles",
            "5",
            "--particle-cap",
            "5",
            "--seed",
            "7",
            "--resample-threshold",
            "0.5",
            "--no-api",
            "--export",
            str(exported),
            *([] if clears is None else ["--no-return-range", str(clears)]),
        ]
    )
    assert run.process.wait(180) == 0, run.output()
    assert "slam-node exited 0" in run.output()
    got = load_map(exported)
    np.testing.assert_array_equal(got.observed, expected["observed"])
    np.testing.assert_allclose(got.logodds, expected["logodds"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got.variance, expected["variance"], rtol=1e-6, atol=1e-6)


def test_slam_node_takes_steps_in_order_and_reports_late_ones(procs):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    node = procs([*CLI, "slam-node", "--robot", "r1", "--algo", "odometry", "--connect", endpoint])
    node.wait_for("up for robot")
    poses = queue.Queue()
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        subscriber = session.declare_subscriber("pg/r1/pose", lambda s: poses.put(s.payload.to_bytes()))

        def step(seq: int, parts=("odom", "landmarks")):
            if "odom" in parts:
                put(
                    session,
                    "pg/r1/odom",
                    Odometry(
                        robot="r1",
                        seq=seq,
                        stamp=0.1 * seq,
                        pose=np.zeros((0, 3)),
                        commands=np.array([[1.0, 0.0, 0.1]] if seq else np.zeros((0, 3))),
                    ).encode(),
                )
            if "landmarks" in parts:
                put(
                    session,
                    "pg/r1/landmarks",
                    LandmarkObservations(
                        robot="r1",
                        seq=seq,
                        stamp=0.1 * seq,
                        ids=np.zeros(0, np.int64),
                        ranges=np.zeros(0),
                        bearings=np.zeros(0),
                    ).encode(),
                )

        step(1, ("landmarks",))  # parts of seq 1 before seq 0 and before the prior: held back
        step(0)
        put(
            session,
            "pg/r1/prior",
            PoseGaussian(robot="r1", seq=0, stamp=0.0, mean=np.array([2.0, 3.0, 0.0]), cov=np.zeros((3, 3))).encode(),
        )
        step(1, ("odom",))
        step(2)
        received = [decode_message(poses.get(timeout=20), PoseGaussian) for _ in range(3)]
        step(1)  # late: seq 1 was processed already
        deadline = time.monotonic() + 20
        while True:
            stats = [
                decode_message(r.ok.payload.to_bytes(), NodeStats)
                for r in session.get("pg/r1/slam/stats", timeout=5)
                if r.ok is not None
            ]
            if (stats and sum(stats[0].out_of_order.values()) == 3) or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        subscriber.undeclare()
    finally:
        session.close()
    assert [p.seq for p in received] == [0, 1, 2]
    # dead reckoning from the prior (2, 3, 0) at 1 m/s along x for 0.1 s per step
    np.testing.assert_allclose(
        [p.mean for p in received], [[2.0, 3.0, 0.0], [2.1, 3.0, 0.0], [2.2, 3.0, 0.0]], atol=1e-9
    )
    # landmarks: seq 0 after seq 1 (reordered and used), then seq 1 again after 2; odom: seq 1 again after 2
    assert stats[0].out_of_order == {"pg/r1/odom": 1, "pg/r1/landmarks": 2} and stats[0].poses_published == 3
    node.wait_for(
        r"out of order on pg/r1/landmarks: seq 0 arrived after seq 1; its step is still to come, so it "
        r"is used"
    )
    node.wait_for(r"out of order on pg/r1/odom: seq 1 arrived after seq 2; it is dropped")


def test_slam_node_moves_over_lost_steps_by_the_odometry_poses(procs):
    """Steps 3-12 never arrive (as in a router restart). Robot r1's odometry carries the dead-reckoned pose: its
    dead reckoning (velocity commands) moves over the gap by the odometry poses around it and stays on the path.
    Robot r2's carries none: the gap's motion is lost, which the node says. The path is an exact arc (1 m/s,
    0.5 rad/s), so both expectations are hand-computed: on the arc, and for r2, one arc step after seq 2."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    nodes = {
        robot: procs(
            [*CLI, "slam-node", "--robot", robot, "--algo", "odometry", "--initial", "0,0,0", "--connect", endpoint]
        )
        for robot in ("r1", "r2")
    }
    for node in nodes.values():
        node.wait_for("up for robot")
    v, w, dt = 1.0, 0.5, 0.1

    def on_arc(seq: int) -> list[float]:
        theta = w * dt * seq
        return [v / w * np.sin(theta), v / w * (1.0 - np.cos(theta)), theta]

    poses = {robot: queue.Queue() for robot in nodes}
    sent = [0, 1, 2, *range(13, 31)]
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        subscribers = [
            session.declare_subscriber(f"pg/{robot}/pose", lambda s, q=poses[robot]: q.put(s.payload.to_bytes()))
            for robot in nodes
        ]
        for seq in sent:
            for robot, pose in (("r1", np.array([on_arc(seq)])), ("r2", np.zeros((0, 3)))):
                commands = np.array([[v, w, dt]]) if seq else np.zeros((0, 3))
                put(
                    session,
                    f"pg/{robot}/odom",
                    Odometry(robot=robot, seq=seq, stamp=dt * seq, pose=pose, commands=commands).encode(),
                )
                put(
                    session,
                    f"pg/{robot}/landmarks",
                    LandmarkObservations(
                        robot=robot,
                        seq=seq,
                        stamp=dt * seq,
                        ids=np.zeros(0, np.int64),
                        ranges=np.zeros(0),
                        bearings=np.zeros(0),
                    ).encode(),
                )
        received = {
            robot: [decode_message(poses[robot].get(timeout=20), PoseGaussian) for _ in sent] for robot in nodes
        }
        for subscriber in subscribers:
            subscriber.undeclare()
    finally:
        session.close()
    assert [p.seq for p in received["r1"]] == [p.seq for p in received["r2"]] == sent
    np.testing.assert_allclose([p.mean for p in received["r1"]], [on_arc(seq) for seq in sent], atol=1e-9)
    # r2 takes seq 13's own command only: one arc step after seq 2, then on an arc turned and moved with it
    np.testing.assert_allclose(received["r2"][3].mean, on_arc(3), atol=1e-9)
    assert np.linalg.norm(received["r2"][3].mean[:2] - on_arc(13)[:2]) > 0.9
    nodes["r1"].wait_for(r"seq 13: moved over seq 3-12, which never arrived, by the odometry poses around them")
    nodes["r2"].wait_for(
        r"seq 13: the velocity commands of seq 3-12, which never arrived, are not used and the odometry messages "
        r"carry no pose to bridge them"
    )


def _simulated_run_and_offline_poses(tmp_path: Path, steps: int) -> tuple[Path, list[str], PoseSet]:
    """A simulated run of ``steps`` steps, the SLAM node's options, and offline `posegrid slam`'s poses for it
    with those options: what a SLAM node over Zenoh must publish, bit for bit."""
    sim = tmp_path / "sim"
    assert main(["simulate", str(sim), "--steps", str(steps), "--beams", "31", "--seed", "3"]) == 0
    offline = tmp_path / "fs2.npz"
    node_args = ["--algo", "fastslam2", "--particles", "20", "--seed", "4"]
    assert main(["slam", str(sim), *node_args, "-o", str(offline)]) == 0
    return sim, node_args, load_posed_scans(offline).poses


class _Poses:
    """Robot r1's poses as a client of the router receives them."""

    def __init__(self, session: zenoh.Session):
        self._queue: queue.Queue = queue.Queue()
        self.received: list[PoseSamples] = []
        self._subscriber = session.declare_subscriber("pg/r1/pose", lambda s: self._queue.put(s.payload.to_bytes()))

    def take(self, n: int, timeout: float) -> None:
        """Wait for ``n`` more poses, each within ``timeout`` s."""
        self.received += [decode_message(self._queue.get(timeout=timeout), PoseSamples) for _ in range(n)]

    def until(self, done: Callable[[set[int]], bool], seconds: float = 30.0) -> None:
        """Take poses until ``done`` holds for the seqs received so far, or ``seconds`` pass."""
        deadline = time.monotonic() + seconds
        while not done(self.seqs()) and time.monotonic() < deadline:
            with contextlib.suppress(queue.Empty):  # none this second: look at the deadline again
                self.received.append(decode_message(self._queue.get(timeout=1), PoseSamples))

    def seqs(self) -> set[int]:
        return {pose.seq for pose in self.received}

    def fill_from_history(self, session: zenoh.Session, seqs: int) -> None:
        """Take the poses of seqs 0 .. ``seqs``-1 this subscriber missed from the SLAM node's history: those the
        node published while the router was down (a loaded machine leaves it a backlog of steps it had received)
        never reached this client, but the node keeps them, as a restarted shard would ask for them."""
        missing = set(range(seqs)) - self.seqs()
        if not missing:
            return
        messages, _ = history.ask(
            session, "r1", {"streams": keys.POSE, "from": str(min(missing)), "to": str(max(missing) + 1)}, 30.0
        )
        for _, _, payload in messages:  # (what still lacks is reported by the caller's check of every seq)
            pose = decode_message(payload, PoseSamples)
            if pose.seq in missing:
                self.received.append(pose)
                missing.discard(pose.seq)

    def close(self) -> None:
        self._subscriber.undeclare()


def _replay(procs, sim: Path, endpoint: str, rate: str, wait_mappers: int = 1):
    """Replay the simulated run ``sim`` as robot r1 into map m at ``rate``, waiting for ``wait_mappers`` shards."""
    argv = ["source", "--sim-dir", str(sim), "--robot", "r1", "--rate", rate, "--map", "m"]
    return procs([*CLI, *argv, "--wait-mappers", str(wait_mappers), "--connect", endpoint])


def test_replay_offsets_keep_gaps_cut_long_pauses_and_send_steps_that_go_back_at_once():
    from services.nodes.source import MAX_STEP_GAP, replay_offsets

    offsets, notes = replay_offsets([5.0, 5.1, 5.3, 5.2, 5.4, 5.4 + 1e300, 0.0], rate=2.0)
    # gaps 0.1, 0.2, back 0.1 (0), 0.2, 1e300 (cut to MAX_STEP_GAP), back (0); each over the rate of 2
    expected = np.cumsum([0.0, 0.05, 0.1, 0.0, 0.1, MAX_STEP_GAP / 2, 0.0])
    np.testing.assert_allclose(offsets, expected, rtol=0, atol=1e-12)
    assert len(notes) == 2  # one of each kind, the first
    assert notes[0].startswith("stamps go back 0.1 s from step 2 to 3")
    assert notes[1].startswith("stamps jump 1e+300 s from step 4 to 5")
    assert replay_offsets([0.0, 1.0, 2.0], rate=1.0) == ([0.0, 1.0, 2.0], [])


def test_a_source_replays_stamps_that_jump_or_go_back_and_says_so(tmp_path, procs):
    """A posed-scan file's stamps are finite floats, nothing more: one of 1e300 s ended the source with a traceback
    (a wait past the platform's time_t, the run's other scans never sent and no end published), one of 1e6 s slept
    for 11 days without a word, and stamps that went back were sent at once, unsaid."""
    posed = make_posed(tmp_path / "posed.npz", "gaussian", steps=8)
    scans = load_posed_scans(posed)
    stamps = np.array([0.0, 0.1, 1e300, 1e300, 1e300, 5.0, 5.1, 5.2])
    save_posed_scans(posed, replace(scans, stamps=stamps))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    source = procs([*CLI, "source", "--posed", str(posed), "--robot", "r1", "--rate", "100", "--connect", endpoint])
    assert source.process.wait(60) == 0, source.output()
    output = source.output()
    assert "stamps jump 1e+300 s from step 1 to 2" in output and "replayed as 10 s" in output
    assert "stamps go back 1e+300 s from step 4 to 5" in output
    assert "Traceback" not in output


def test_a_shard_started_late_takes_another_maps_robot_from_its_live_source(tmp_path, procs):
    """Every map fuses every robot's live scans, but a shard that started late (or restarted) took the histories of
    its own map's sources only: another map's robot, still driving, had its first scans given up as lost ("no history
    holds them"; map A lacked 22 of 60 in the probe). A source that has not ended is taken, whatever its map."""
    from services.map_client import MapReader

    posed = make_posed(tmp_path / "posed.npz", "samples", steps=36)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    source = procs(
        [*CLI, "source", "--posed", str(posed), "--robot", "r10", "--map", "B", "--rate", "0.5", "--connect", endpoint]
    )
    source.wait_for(r"published ([7-9]|[1-3]\d) of 36 steps")  # (its first scans went out before map A had a shard)
    shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "A", "--connect", endpoint])
    shard.wait_for("up; tiles on")
    assert source.process.wait(60) == 0, source.output()
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            stats = MapReader(session, "A").stats(timeout=2.0)
            if (
                stats
                and stats[0].ended.get("r10") == 36
                and stats[0].fused.get("r10", 0) + stats[0].discarded.get("r10", 0) >= 36
            ):
                break
            time.sleep(0.2)
    finally:
        session.close()
    assert stats[0].fused == {"r10": 36} and stats[0].discarded == {}, (stats, shard.output())


def test_a_stale_runs_stalled_source_of_another_map_does_not_leak_into_a_new_map(tmp_path, procs):
    """A re-probe of the rule above: an earlier run's source of robot r1 for map A, stalled mid-stream waiting for a
    frozen shard (so not ended), answered a new map B's shard catching up at its start; B took its 4 scans, and the new
    run's own seqs 0-3 were then refused as duplicates, exit 0, the map partly the other run's. Catching up takes only
    the shard's own map's sources; only a gap in a live stream takes another map's live source."""
    from services.map_client import MapReader

    stale = make_posed(tmp_path / "stale.npz", "samples", steps=20, seed=5)
    fresh = make_posed(tmp_path / "fresh.npz", "samples", steps=20, seed=6)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    old_shards = [
        procs([*CLI, "mapper", "--shard", str(k), "--shards", "2", "--map", "A", "--connect", endpoint]) for k in (0, 1)
    ]
    for shard in old_shards:
        shard.wait_for("up; tiles on")
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:  # (both tokens and answers through the router before one shard freezes: under load the frozen one's token
        # had not reached the router, and the old source waited for a second shard without publishing a step)
        deadline = time.monotonic() + 60
        while len(MapReader(session, "A").stats(timeout=2.0)) < 2:
            assert time.monotonic() < deadline, "map A's two shards did not answer"
    finally:
        session.close()
    frozen = old_shards[1].process
    frozen.send_signal(signal.SIGSTOP)  # (the old run's source waits for it, mid-stream)
    try:
        old = procs(
            [*CLI, "source", "--posed", str(stale), "--robot", "r1", "--map", "A", "--rate", "max"]
            + ["--wait-mappers", "2", "--window", "4", "--connect", endpoint]
        )
        old.wait_for("published 4 of 20 steps")
        shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "B", "--connect", endpoint])
        shard.wait_for("up; tiles on")
        new = procs(
            [*CLI, "source", "--posed", str(fresh), "--robot", "r1", "--map", "B", "--rate", "max"]
            + ["--wait-mappers", "1", "--connect", endpoint]
        )
        assert new.process.wait(60) == 0, new.output()
        session = zenoh.open(build_config("client", connect=[endpoint]))
        try:
            (stats,) = MapReader(session, "B").stats(timeout=5.0).values()
        finally:
            session.close()
    finally:
        frozen.send_signal(signal.SIGCONT)
    assert stats.fused == {"r1": 20} and "duplicate" not in stats.refused, (stats, shard.output())
    assert "from the histories" not in shard.output()


def test_a_history_left_behind_answers_at_once(tmp_path, procs):
    """Once the source has ended, the SLAM node's history of poses answers at once, and once one of two shards has
    stopped, the other's tiles do. zenoh's router (1.10) went on routing wildcard queries to a queryable undeclared
    while another session declared the same key expression (pg/<robot>/history/**: the source and the node;
    pg/map/<map>/tile/**: every shard), and each query waited its whole timeout for that queryable's last answer:
    every question to the node's history after the source had ended took its whole timeout (a shard's 5 s; the
    router-loss test's question 30 s). Processes now leave their queryables to the session's close
    (services.zenoh_config.undeclare_all)."""
    sim = tmp_path / "sim"
    assert main(["simulate", str(sim), "--steps", "40", "--beams", "31", "--seed", "3"]) == 0
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    node = procs(
        [*CLI, "slam-node", "--robot", "r1", "--algo", "fastslam2", "--particles", "20", "--connect", endpoint]
    )
    shards = [
        procs([*CLI, "mapper", "--shard", str(k), "--shards", "2", "--map", "m", "--connect", endpoint]) for k in (0, 1)
    ]
    node.wait_for("up for robot")
    for shard in shards:
        shard.wait_for("up; tiles on")
    source = procs(
        [*CLI, "source", "--sim-dir", str(sim), "--robot", "r1", "--map", "m", "--wait-mappers", "2"]
        + ["--connect", endpoint]
    )
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        source.wait_for("publishing")  # (the router's routes are made by a first question, while all are up)
        history.ask(session, "r1", {"streams": keys.POSE, "from": "0", "to": "1"}, 10.0)
        list(session.get(keys.tiles_key("m"), timeout=10.0))
        assert source.process.wait(120) == 0, source.output()
        shards[1].process.send_signal(signal.SIGINT)
        assert shards[1].process.wait(30) == 0, shards[1].output()
        poses, problems = history.ask(session, "r1", {"streams": keys.POSE, "from": "0", "to": "10"}, 10.0)
        tiles = list(session.get(keys.tiles_key("m"), timeout=10.0))
    finally:
        session.close()
    assert len(poses) == 10 and problems == [], problems  # "Timeout" before
    assert tiles and all(reply.ok is not None for reply in tiles), [r.err.payload.to_bytes() for r in tiles if r.err]


def test_a_slam_node_waiting_on_the_sources_history_answers_for_its_poses_and_stats_at_once(procs):
    """A suite run on a loaded machine: the source ended, the SLAM node asked its history for the stream's tail
    (which may wait 5 + 10 + 20 s for a history that does not finish answering) holding the lock its queryables
    took, and a question for the node's poses got nothing in 30 s. The poses (and the stats) no longer wait for
    the node's thread. A stand-in source here holds the node's question for the tail unanswered."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    held: list[zenoh.Query] = []  # the node's questions for missed steps, kept unanswered and open
    caught_up = threading.Event()

    def source_history(query: zenoh.Query) -> None:  # answers nothing; holds a question for missed steps
        if query.parameters.get("from") is not None and query.parameters.get("streams") != keys.POSE:
            held.append(query)
        elif query.parameters.get("streams") != keys.POSE:
            caught_up.set()  # (the node's question as it starts: answered with nothing)

    source = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        source.declare_queryable(keys.history_key("r1"), source_history)
        node = procs(
            [*CLI, "slam-node", "--robot", "r1", "--algo", "odometry", "--initial", "0,0,0", "--connect", endpoint]
        )
        node.wait_for("up for robot")
        assert caught_up.wait(30), node.output()
        for seq in range(3):
            pose = np.array([[0.1 * seq, 0.0, 0.0]])
            odometry = Odometry(robot="r1", seq=seq, stamp=0.1 * seq, pose=pose, commands=np.zeros((0, 3)))
            nothing = np.zeros(0)
            seen = LandmarkObservations(
                robot="r1", seq=seq, stamp=0.1 * seq, ids=np.zeros(0, np.int64), ranges=nothing, bearings=nothing
            )
            source.put(keys.robot_key("r1", keys.ODOM), odometry.encode())
            source.put(keys.robot_key("r1", keys.LANDMARKS), seen.encode())
        deadline = time.monotonic() + 30
        while _node_stats(source, "r1").steps_done < 3:  # (the three steps taken before the end is put)
            assert time.monotonic() < deadline, node.output()
            time.sleep(0.05)
        source.put(keys.robot_key("r1", keys.END), StreamEnd(robot="r1", scans=3).encode())
        while not held:  # the node now waits for the tail
            assert time.monotonic() < deadline, node.output()
            time.sleep(0.05)
        asked = time.monotonic()
        poses, problems = history.ask(source, "r1", {"streams": keys.POSE}, 10.0)  # (10 s, then 20: in the wait)
        stats = _node_stats(source, "r1", timeout=10.0)
        answered_in = time.monotonic() - asked
    finally:
        source.close()
    assert [decode_message(payload, PoseGaussian).seq for _, _, payload in poses] == [0, 1, 2], problems
    assert problems == [] and answered_in < 20.0, (problems, answered_in)  # (the node's wait: 35 s)
    assert stats.steps_done == 3 and stats.poses_published == 3


def test_a_shard_waiting_on_a_history_answers_tile_queries_at_once(procs):
    """A shard asks the histories from inside its handling of a message, holding the lock its tile queries take; a
    history that does not finish answering held the tile queries (the HTTP API's map) for up to 5 + 10 + 20 s. The
    shard now lets the lock go while it waits. Here a robot's stream ends two scans short, the shard asks for those
    two (its tails, TAIL_AFTER s later), and a stand-in source holds that question unanswered."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    held: list[zenoh.Query] = []  # the shard's question for the tails, kept unanswered and open
    caught_up = threading.Event()

    def source_history(query: zenoh.Query) -> None:  # answers nothing; holds a question for seqs from 2
        if query.parameters.get("from") == "2":
            held.append(query)
        elif query.parameters.get("from") is None:
            caught_up.set()  # (the shard's question as it starts: the router has its subscribers, declared before)

    source = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        source.declare_queryable(keys.history_key("r1"), source_history)
        shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint])
        shard.wait_for("up; tiles on")
        assert caught_up.wait(30), shard.output()
        for seq in range(2):
            put(source, keys.robot_key("r1", keys.SCAN), _scan(seq).encode())
            put(source, keys.robot_key("r1", keys.POSE), _pose(seq).encode())
        put(source, keys.robot_key("r1", keys.END), StreamEnd(robot="r1", scans=4).encode())
        deadline = time.monotonic() + 30
        while not held:  # the shard now waits for the tails
            assert time.monotonic() < deadline, shard.output()
            time.sleep(0.05)
        asked = time.monotonic()
        tiles = [reply.ok for reply in source.get(keys.tiles_key("m"), timeout=15.0) if reply.ok is not None]
        answered_in = time.monotonic() - asked
    finally:
        source.close()
    assert tiles and answered_in < 15.0, (answered_in, shard.output())  # (the shard's wait: 35 s)
    assert {decode_message(tile.payload.to_bytes(), TileUpdate).seq for tile in tiles} == {1}  # (both scans fused)


def _node_stats(session: zenoh.Session, robot: str, timeout: float = 5.0) -> NodeStats:
    """The stats of ``robot``'s SLAM node (one answer)."""
    replies = [reply.ok for reply in session.get(keys.slam_stats_key(robot), timeout=timeout) if reply.ok is not None]
    assert len(replies) == 1, f"{len(replies)} answers to a SLAM node's stats question"
    return decode_message(replies[0].payload.to_bytes(), NodeStats)


def test_a_restarted_slam_node_takes_the_run_from_the_sources_history(tmp_path, procs):
    """A SLAM node killed mid-run and started again takes what the source published before it was up from the
    source's history (pg/<robot>/history/**) and goes on as if it had never stopped: every pose either node
    publishes is offline `posegrid slam`'s for that step, same seed, bit for bit. Before, the new node never got
    the prior (published once, at the start) and published nothing. Meanwhile the scans wait in the mapper's
    join for their poses, more of them than it holds (4 halves here): those it evicts, it asks the source's
    history for again when their poses come, so every scan is fused (they were given up)."""
    sim, node_args, expected = _simulated_run_and_offline_poses(tmp_path, 120)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    mapper = procs(
        [*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--join-buffer", "4", "--connect", endpoint]
    )
    node = [*CLI, "slam-node", "--robot", "r1", *node_args, "--connect", endpoint]
    first = procs(node)
    first.wait_for("up for robot")
    mapper.wait_for("up; tiles on")
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        poses = _Poses(session)
        source = _replay(procs, sim, endpoint, "1")
        poses.take(20, timeout=30)
        first.process.kill()
        first.process.wait(10)
        time.sleep(2.0)  # scans pile up in the mapper's join meanwhile, waiting for their poses
        second = procs(node)
        second.wait_for(r"took \d+ message\(s\) the source published before this node was up")
        bad = [
            reply.err.payload.to_string()
            for reply in session.get("pg/r1/history/**?from=-1;streams=odom,x", timeout=10)
            if reply.err is not None
        ]
        assert bad and all("unknown stream(s) ['x']" in error for error in bad)  # from the source and the node
        assert source.process.wait(60) == 0, source.output()  # (once the shard has accounted for every scan)
        from services.map_client import MapReader

        stats = MapReader(session, "m").stats()[0]
        poses.until(lambda seqs: seqs == set(range(120)))
        poses.close()
    finally:
        session.close()
    assert poses.seqs() == set(range(120)), (sorted(poses.seqs()), second.output())
    assert len(poses.received) > 120  # the second node published again what the first had
    assert stats.fused == {"r1": 120} and not stats.discarded.get("r1") and stats.overflow["join"] == 0, stats
    # the poses published again are the fused ones: resent, not rejected (they were counted as duplicates)
    assert stats.resent.get("pg/r1/pose", 0) > 0 and "pg/r1/pose" not in stats.rejected, stats
    mapper.wait_for(r"took \d+ scan\(s\) of robot 'r1' in seqs \d+-\d+ from the history")
    for pose in poses.received:
        np.testing.assert_array_equal(pose.samples, expected.samples[pose.seq])
        np.testing.assert_array_equal(pose.weights, expected.weights[pose.seq])


def test_a_history_question_asked_while_the_router_restarts_waits_for_it(procs):
    """A question asked while the router was down came back empty at once, and the shard gave up what it asked
    for as lost though the history held it (scans evicted from its join while the SLAM node was down, asked for
    again during a 3 s router restart: 125 of 3 000 given up). Now it waits for the session to reach the router
    again, and asks again while the answerer is not back yet."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = [*CLI, "router", "--listen", endpoint]
    first = procs(router)
    first.wait_for("routing")
    answerer, asker = (zenoh.open(build_config("client", connect=[endpoint])) for _ in range(2))
    try:
        who = history.Answerer(str(answerer.info.zid()), "m", False)
        answerer.declare_queryable(
            keys.history_key("r"), lambda query: history.reply(query, who, "r", keys.SCAN, b"scan 7")
        )
        deadline = time.monotonic() + 10  # until the queryable's declaration has reached the asker through the router
        while history.ask(asker, "r", {}, 5.0) != ([("r", keys.SCAN, b"scan 7")], []):
            assert time.monotonic() < deadline, "the answerer never answered with the router up"
            time.sleep(0.1)
        first.process.kill()
        first.process.wait(10)
        time.sleep(0.5)
        answers: list = []
        asking = threading.Thread(target=lambda: answers.append(history.ask(asker, "r", {}, 5.0)))
        asking.start()
        time.sleep(1.0)
        procs(router).wait_for("routing")
        asking.join(60)
    finally:
        answerer.close()
        asker.close()
    assert answers == [([("r", keys.SCAN, b"scan 7")], [])]


def test_a_history_slower_than_the_questions_timeout_is_asked_again_with_more_time(procs):
    """A suite run on a loaded machine: a restarted shard asked the source's history for 359 scans, the source had
    not finished answering in the question's 5 s (zenoh's "Timeout" reply), and the shard took what had come as all
    there was: it gave up on every scan (and counted "Timeout" as a rejected message). A question a history was still
    answering as its time ran out is asked again, its timeout doubled, TIMEOUT_RETRIES times up to TIMEOUT_CAP s.
    A probe: a peer's queryable that never answers, alone or beside the real history, held a shard 5 + 10 + 20 s a
    question. Such a question is not asked again: its one timeout is all it waits."""
    assert history.question_timeouts(5.0) == [5.0, 10.0, 20.0] and history.question_timeouts(60.0) == [60.0]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    answerer, asker, peer = (zenoh.open(build_config("client", connect=[endpoint])) for _ in range(3))
    asked: list[float] = []
    scans = [f"scan {seq}".encode() for seq in range(60)]
    try:
        who = history.Answerer(str(answerer.info.zid()), "m", False)

        def slow(query) -> None:  # the first question answered a scan every 0.05 s, 3 s in all; the others at once
            asked.append(time.monotonic())
            if len(asked) > 1:
                for scan in scans:
                    history.reply(query, who, "r", keys.SCAN, scan)
                return

            def streaming() -> None:  # (on a thread of its own: zenoh's callback thread stays free for the next)
                for scan in scans:
                    history.reply(query, who, "r", keys.SCAN, scan)
                    time.sleep(0.05)

            threading.Thread(target=streaming, daemon=True).start()

        answerer.declare_queryable(keys.history_key("r"), slow)
        deadline = time.monotonic() + 10  # until the queryable's declaration has reached the asker through the router
        while not answerer.info.routers_zid() or not asker.info.routers_zid():
            assert time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(1.0)
        messages, problems = history.ask(asker, "r", {}, 2.0)
        assert messages == [("r", keys.SCAN, scan) for scan in scans] and problems == [], problems
        assert len(asked) == 2  # (the first question's answer was cut off, the second came whole in time)
        stalled: list = []  # (a history that never answers: the question gives up after its timeout, and says why)
        answerer.declare_queryable(keys.history_key("q"), stalled.append)
        time.sleep(1.0)
        started = time.monotonic()
        messages, problems = history.ask(asker, "q", {}, 0.5)
        waited = time.monotonic() - started
        assert messages == [] and len(problems) == 1, problems
        assert "did not finish answering in 0.5 s (asked 1 time(s)" in problems[0] and 0.4 <= waited < 1.4, waited
        # a peer's silent queryable beside the real history: the real answer is taken after one timeout
        answerer.declare_queryable(
            keys.history_key("p"), lambda query: history.reply(query, who, "p", keys.SCAN, b"scan 3")
        )
        peer.declare_queryable(keys.history_key("p"), stalled.append)
        time.sleep(1.0)
        started = time.monotonic()
        messages, problems = history.ask(asker, "p", {}, 0.5)
        waited = time.monotonic() - started
    finally:
        for session in (answerer, asker, peer):
            session.close()
    assert messages == [("p", keys.SCAN, b"scan 3")] and len(problems) == 1 and 0.4 <= waited < 1.4, (problems, waited)


@pytest.mark.parametrize("node", ["mapper", "slam-node"])
def test_a_process_stopped_while_its_history_question_waits_stops_at_once(procs, node):
    """A shard (or SLAM node) asks the histories when it starts. Stopped while that question waited (an answerer
    that never finishes here; the router stopped first, as a test's teardown does, behaves alike), it went on
    waiting for the question's 60 s before it looked at its stop flag, and was killed. Now it stops within a few
    tenths of a second (15 s allowed for a busy machine), with exit 0."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    held: list[zenoh.Query] = []  # the questions, kept unanswered and open
    answerer = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        answerer.declare_queryable(keys.history_key("*"), held.append)
        args = {
            "mapper": ["mapper", "--shard", "0", "--shards", "1"],
            "slam-node": ["slam-node", "--robot", "r1", "--algo", "odometry"],
        }[node]
        proc = procs([*CLI, *args, "--connect", endpoint])
        proc.wait_for("up")
        deadline = time.monotonic() + 30
        while not held:
            assert time.monotonic() < deadline, "the process never asked the histories"
            time.sleep(0.05)
        proc.process.send_signal(signal.SIGINT)
        assert proc.process.wait(15) == 0
    finally:
        answerer.close()
    assert "stopped while asking the histories" in proc.output()


def test_a_shard_stopped_while_it_compiles_its_kernels_stops_at_once(tmp_path, procs):
    """A shard started on its own after an install compiles its fusion kernels before it is up (20 s and more
    here); a stop waited for the compile. Now it stops at once. An empty kernel cache (NUMBA_CACHE_DIR, a folder
    of this test's) makes the compile happen; the SIGINT comes 4 s in, past the imports and into the compile."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    shard = procs(
        [*CLI, "mapper", "--shard", "0", "--shards", "1", "--connect", endpoint],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)},
    )
    time.sleep(4.0)
    assert shard.process.poll() is None and not any(" up;" in line for line in shard.lines), shard.output()
    shard.process.send_signal(signal.SIGINT)
    signalled = time.monotonic()
    code = shard.process.wait(60)
    assert code in (0, 130) and time.monotonic() - signalled < 8.0, (code, shard.output())
    assert code == 130 or "stopped while loading the fusion kernels" in shard.output()


def test_a_source_stopped_while_it_simulates_its_input_stops_at_once(procs):
    """`posegrid source --sim --steps 100000` simulates for minutes before it publishes; a stop waited for the end
    of it. Now the source stops at once (exit 0) and says where it was."""
    source = procs([*CLI, "source", "--sim", "--steps", "100000", "--connect", f"tcp/127.0.0.1:{free_port()}"])
    source.wait_for("simulating 100000 steps")
    source.process.send_signal(signal.SIGINT)
    assert source.process.wait(15) == 0, source.output()
    assert "stopped while reading its input" in source.output()


def test_a_shard_stopped_while_it_fuses_the_histories_stops_between_chunks(procs):
    """A shard that starts into a long run fuses the histories' scans before it takes live ones (thousands: many
    seconds). Stopped meanwhile, it went on to the end of them (over 8 s in a probe, then killed). Now it stops
    after the chunk it is fusing, and commits what it fused as any stop does."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    pairs = 3000
    samples = np.array([[0.5, 0.2, 0.0]]) + np.random.default_rng(1).normal(0.0, 0.02, (30, 3))
    history_messages = []
    for seq in range(pairs):
        pose = PoseSamples(robot="r1", seq=seq, stamp=0.1 * seq, samples=samples, weights=np.full(30, 1 / 30))
        history_messages += [(keys.SCAN, _scan(seq).encode()), (keys.POSE, pose.encode())]
    with zenoh.open(build_config("client", connect=[endpoint])) as session:
        who = history.Answerer(str(session.info.zid()), "m", False)

        def answer(query: zenoh.Query) -> None:
            for stream, payload in history_messages:
                history.reply(query, who, "r1", stream, payload)

        session.declare_queryable(keys.history_key("r1"), answer)
        shard = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint])
        shard.wait_for("up")
        from services.map_client import MapReader

        reader, deadline = MapReader(session, "m"), time.monotonic() + 60
        while not any(s.fused.get("r1", 0) > 0 for s in reader.stats(timeout=2.0).values()):
            assert time.monotonic() < deadline, "the shard fused none of the histories' scans"
            time.sleep(0.02)
        shard.process.send_signal(signal.SIGINT)
        assert shard.process.wait(15) == 0
    taken, offered = map(int, shard.wait_for(r"stopped taking the histories after (\d+) of (\d+)").groups())
    assert 0 < taken < offered == 2 * pairs


@pytest.mark.parametrize("wait_mappers", [1, 0], ids=["waits", "live"])
def test_what_the_router_loses_is_taken_from_the_histories(tmp_path, procs, wait_mappers):
    """The router dies mid-run and comes back on its port: what the source published meanwhile never reaches the
    SLAM node or the mapper shard. The node takes those steps from the source's history instead of skipping
    them, so every step gets its pose, and each is offline `posegrid slam`'s for that step, same seed, bit for
    bit; the shard takes the scans from it too, and fuses every scan of the run. More steps are lost (the router
    stays down until the source has published 360 of the 400) than the node's step buffer holds (256): a node used
    to keep only the newest 256 of those it took back, and bridged the rest. A source that waits for no shard
    ("live", `--wait-mappers 0`) used to exit at its end with the end mark lost too: the shard fused the 40 steps
    before the outage and nothing said the rest was missing; having published while no router was reachable, it
    now stays and answers its history until the shard has taken every scan."""
    sim, node_args, expected = _simulated_run_and_offline_poses(tmp_path, 400)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = procs([*CLI, "router", "--listen", endpoint])
    router.wait_for("routing")
    node = procs([*CLI, "slam-node", "--robot", "r1", *node_args, "--connect", endpoint])
    mapper = procs([*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--connect", endpoint])
    node.wait_for("up for robot")
    mapper.wait_for("up; tiles on")  # (a live source waits for no shard: one up late takes the run from the histories)
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        poses = _Poses(session)
        # the router dies once the source is a tenth of the way in: at 5x real time (50 steps/s) the test may react
        # a second late on a loaded machine and still see 300 or more steps lost (waiting for the node's poses
        # instead let a lagging node run the source to step 157 first)
        source = _replay(procs, sim, endpoint, "5", wait_mappers)
        source.wait_for("published 40 of 400 steps", timeout=120)
        router.process.kill()
        router.process.wait(10)
        source.wait_for("published 360 of 400 steps", timeout=120)  # 300 steps or more go out meanwhile, to no one
        procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
        assert source.process.wait(60) == 0, source.output()
        spans = node.wait_for(r"took seq (.+?), which (?:did not all arrive|had not all arrived)").group(1)
        recovered = {
            seq for span in spans.split(", ") for seq in range(int(span.split("-")[0]), int(span.split("-")[-1]) + 1)
        }
        poses.until(lambda seqs: recovered <= seqs)
        poses.close()
        poses.fill_from_history(session, 400)
        deadline, shard = time.monotonic() + 60, []
        while time.monotonic() < deadline:  # the shard may still be fusing the last pairs the poses completed
            shard = [
                decode_message(r.ok.payload.to_bytes(), ShardStats)
                for r in session.get("pg/map/m/stats/0", timeout=10)
                if r.ok is not None
            ]
            if shard and shard[0].fused.get("r1", 0) + shard[0].discarded.get("r1", 0) >= 400:
                break
            time.sleep(0.2)
    finally:
        session.close()
    assert "skipped" not in node.output()
    # the lost steps' poses went out after the router was back; poses the node published while it was down (steps
    # it had received before) never reached this subscriber and are read from the node's history instead
    seqs = poses.seqs()
    assert len(recovered) > 256 and recovered <= seqs and seqs == set(range(400)), (sorted(seqs), spans)
    for pose in poses.received:
        np.testing.assert_array_equal(pose.samples, expected.samples[pose.seq])
        np.testing.assert_array_equal(pose.weights, expected.weights[pose.seq])
    mapper.wait_for(r"took \d+ scan\(s\) of robot 'r1' in seqs \d+-\d+ from the history \(lost in transit")
    assert shard[0].fused == {"r1": 400} and not shard[0].discarded.get("r1"), (shard, mapper.output())


def _mrclam_excerpt(source: Path, target: Path, seconds: float) -> Path:
    """Robot 1's first ``seconds`` of an MRCLAM folder, in the dataset's own format (headers kept)."""
    target.mkdir()
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat"):
        (target / name).write_text((source / name).read_text())
    start = None
    for kind in ("Groundtruth", "Odometry", "Measurement"):
        lines = (source / f"Robot1_{kind}.dat").read_text().splitlines()
        header = [line for line in lines if line.startswith("#")]
        rows = [line for line in lines if line.strip() and not line.startswith("#")]
        start = float(rows[0].split()[0]) if start is None else start
        kept = [line for line in rows if float(line.split()[0]) < start + seconds]
        (target / f"Robot1_{kind}.dat").write_text("\n".join(header + kept) + "\n")
    return target


def test_run_hands_the_resampling_choice_to_the_slam_node():
    # `posegrid run --plain-resampling` must reach the slam-node child, which must accept it
    from services.cli import build_parser
    from services.commands.pipeline import slam_argv

    parser = build_parser()
    for flags, expected in (([], False), (["--plain-resampling"], True)):
        argv = slam_argv(parser.parse_args(["run", *flags]), "sim")
        assert ("--plain-resampling" in argv) is expected
        node = parser.parse_args(["slam-node", *argv])
        assert node.plain_resampling is expected


def test_run_hands_the_node_limits_to_the_slam_node():
    """`posegrid run --max-landmarks` and `--max-odometry-step` reach its SLAM node's NodeConfig."""
    from services.cli import build_parser
    from services.commands.pipeline import node_config, slam_argv

    parser = build_parser()
    for flags, field, value in (
        (["--algo", "ekf", "--max-landmarks", "7"], "max_landmarks", 7),
        (["--algo", "gridslam", "--max-odometry-step", "2.5"], "max_odometry_step", 2.5),
    ):
        argv = slam_argv(parser.parse_args(["run", *flags]), "sim")
        config = node_config(parser.parse_args(["slam-node", "--robot", "r", *argv]))
        assert getattr(config, field) == value, argv


@pytest.mark.parametrize("calibrated", [False, True], ids=["generic", "drive-angle"])
def test_slam_node_on_real_mrclam_data_publishes_what_offline_slam_writes(tmp_path, procs, data_dir, calibrated):
    """Real data: source --mrclam -> slam-node (EKF) over zenoh gives `posegrid slam`'s poses: bit for bit with the
    generic noise on both sides (`--models mrclam` for the node); with one calibration file on both sides that
    delays the commands and states a bearing bias, a drive angle and its sd (the node's delay line and corrections,
    its filter's frame and the turn about the start), to 1e-6: the node's delay line cuts the commands into pieces
    by subtracting durations, the reader by shifting stamps of about 1.2e9 s (the poses differ by up to 3e-8)."""
    from slam.calibration import GENERIC, save_calibration

    folder = _mrclam_excerpt(data_dir / "mrclam7", tmp_path / "mrclam", seconds=60.0)
    offline = tmp_path / "ekf.npz"
    if calibrated:
        calibration = tmp_path / "cal.json"
        save_calibration(
            calibration,
            replace(GENERIC, command_delay=0.2, bearing_bias=0.01, drive_angle=-0.02, drive_angle_sd=0.01),
        )
        chosen = ["--calibration", str(calibration)]
    offline_argv = ["slam", str(folder), "--robot", "1", "--algo", "ekf", "-o", str(offline)]
    assert main([*offline_argv, *(chosen if calibrated else ["--calibration", "none"])]) == 0
    expected = np.load(offline)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    models = chosen if calibrated else ["--models", "mrclam"]
    node = procs([*CLI, "slam-node", "--algo", "ekf", *models, "--connect", endpoint])
    node.wait_for("up for robot")
    got: dict[int, PoseGaussian] = {}
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        subscriber = session.declare_subscriber(
            "pg/robot0/pose", lambda s: (lambda m: got.__setitem__(m.seq, m))(decode_message(s.payload.to_bytes()))
        )
        source = procs(
            [
                *CLI,
                "source",
                "--mrclam",
                str(folder),
                "--mrclam-robot",
                "1",
                "--rate",
                "max",
                "--wait-slam",
                "--connect",
                endpoint,
            ]
        )
        assert source.process.wait(120) == 0, source.output()
        deadline = time.monotonic() + 30
        while len(got) < len(expected["stamps"]) and time.monotonic() < deadline:
            time.sleep(0.1)
        subscriber.undeclare()
    finally:
        session.close()
    assert sorted(got) == list(range(len(expected["stamps"])))
    np.testing.assert_array_equal([got[t].stamp for t in sorted(got)], expected["stamps"])
    tolerance = 1e-6 if calibrated else 0.0
    np.testing.assert_allclose([got[t].mean for t in sorted(got)], expected["mean"], rtol=0, atol=tolerance)
    np.testing.assert_allclose([got[t].cov for t in sorted(got)], expected["cov"], rtol=0, atol=tolerance)


def test_a_stalled_sources_message_names_only_what_it_waited_for_and_why_it_counted_nothing():
    """It said "SLAM node: 0 of 32 steps" with no --wait-slam, and "shards: 0 of 32 scans" when every shard had fused
    the 32 but their stats were not trusted (a shard started with another --shards)."""
    from services.nodes.source import stall_message

    said = stall_message((0, 32), None, "shards of map 'C' disagree on their count")
    assert said == (
        "the subscribers took nothing for 60 s (shards: 0 of 32 scans); the shards' stats were not trusted, so their "
        "progress was not counted: shards of map 'C' disagree on their count"
    )
    assert stall_message((3, 32), (5, 40), None) == (
        "the subscribers took nothing for 60 s (shards: 3 of 32 scans, SLAM node: 5 of 40 steps)"
    )
