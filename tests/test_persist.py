"""Durable maps end to end (docs/persistence.md): real processes, real Zenoh on loopback, real SQLite files.

- the mapper shard of `posegrid run --state-dir` SIGKILLed at 10 seeded random points of its progress, each time
  restarted by the launcher while the source goes on, starts from its store and takes from the histories only
  what came after its ledger: the exported map is bit for bit the one `posegrid fuse` builds, every scan fused once;
- the whole pipeline SIGKILLed mid-run and started again with `--resume DIR --continue-session`: the map is the
  one of a run never stopped; a second robot's run added with `--resume DIR` (a new session) gives the map of both
  runs fused one after the other; and shards started on the saved state with no source serve that map.

Every process is started here or by the launcher started here, and ended by PID in a finalizer (the ``procs``
fixture of test_pipeline, which also ends every pid the launcher printed, restarted ones included).
"""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from schemas.files import load_map, load_posed_scans
from services.cli import main
from services.fusion_runner import fuse_posed_scans
from services.map_client import MapReader
from services.ports import free_port
from services.zenoh_config import build_config
from test_pipeline import CLI, Proc, _alive, make_posed, procs  # noqa: F401  (procs: the fixture)

pytestmark = pytest.mark.slow


def _pids(banner: str) -> dict[str, int]:
    return {name: int(pid) for name, pid in re.findall(r"(\S+) \(pid (\d+)\)", banner)}


def _raster_equal(got: dict | Path, expected: dict | Path) -> None:
    """Bit for bit: every layer, the origin and the resolution."""
    got = vars(load_map(got)) if isinstance(got, Path) else got
    expected = vars(load_map(expected)) if isinstance(expected, Path) else expected
    for key in ("logodds", "variance", "observed", "origin", "resolution"):
        np.testing.assert_array_equal(got[key], expected[key], err_msg=key)
    assert np.asarray(expected["observed"]).sum() > 10_000  # not trivially empty


def _wait_stats(reader: MapReader, done, what: str, timeout: float = 120.0) -> dict:
    """The shards' stats once ``done(stats)`` holds; fails naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        stats = reader.stats(timeout=2.0)
        if done(stats):
            return stats
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


def _new_pid(run: Proc, name: str, seen: set[int], timeout: float = 60.0) -> int:
    """The pid of ``name``'s latest restart, once the launcher has printed one not in ``seen``."""
    pattern = re.compile(rf"{re.escape(name)} restarted \(pid (\d+)\)")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pids = [int(m.group(1)) for line in list(run.lines) if (m := pattern.search(line))]
        fresh = [pid for pid in pids if pid not in seen]
        if fresh:
            return fresh[-1]
        time.sleep(0.02)
    raise AssertionError(f"{name} was not restarted; output:\n{run.output()[-3000:]}")


def test_a_shard_killed_at_ten_random_points_ends_with_the_map_of_a_run_without_kills(tmp_path, procs):  # noqa: F811
    # long enough that ten kills end before the replay does even when the shard, catching up after each restart,
    # runs many scans past the kill point before the test reads its stats (a loaded machine: tens of scans)
    steps = 500
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=steps)
    exported = tmp_path / "run.npz"
    port = free_port()
    run = procs(
        [
            *CLI,
            "run",
            "--posed",
            str(posed),
            "--robot",
            "r1",
            "--shards",
            "1",
            "--state-dir",
            str(tmp_path / "state"),
            "--export",
            str(exported),
            "--rate",
            "max",
            "--no-api",
            "--router-port",
            str(port),
            "--commit-scans",
            "5",
            "--max-restarts",
            "30",
            "--restart-delay",
            "0.05",
            "--max-restart-delay",
            "0.05",
        ]
    )
    pid = _pids(run.wait_for(r"running: (.*)").group(1))["mapper[0]"]
    rng = np.random.default_rng(32)
    seen, target = {pid}, 0
    with zenoh.open(build_config("client", connect=[f"tcp/127.0.0.1:{port}"])) as session:
        reader = MapReader(session, "main")
        for _ in range(10):  # each kill 1 to 15 scans past the last one (the shard resumes from its last commit)
            target += int(rng.integers(1, 16))
            assert target < steps, "the run would end before this kill: the test needs a longer run"
            stats = _wait_stats(
                reader, lambda s, t=target: 0 in s and s[0].fused.get("r1", 0) >= t, f"the shard to fuse {target} scans"
            )
            target = stats[0].fused["r1"]
            assert target < steps, "the run ended before the kill: the test needs a longer run"
            time.sleep(float(rng.uniform(0.0, 0.02)))  # (anywhere: between scans, mid-fusion, mid-commit)
            os.kill(pid, signal.SIGKILL)
            pid = _new_pid(run, "mapper[0]", seen)
            seen.add(pid)
    assert run.process.wait(180) == 0, run.output()
    output = run.output()
    assert len(seen) == 11 and len(re.findall(r"mapper\[0\] \(pid \d+\) exited -9 \(SIGKILL\)", output)) == 10
    assert f"posegrid run: replay finished: {steps} scans, each of 1 shard(s) fused {steps}" in run.lines, output
    assert "gave up" not in output
    assert re.search(r"mapper\[0\]: state in .*: resumed \d+ tile\(s\) and [1-9]\d* scan\(s\)", output), output
    fused = tmp_path / "fused.npz"
    assert main(["fuse", str(posed), "-o", str(fused)]) == 0
    _raster_equal(exported, fused)


def _run(tmp_path: Path, procs, posed: Path, robot: str, *extra: str) -> Proc:  # noqa: F811
    port = free_port()
    argv = [*CLI, "run", "--posed", str(posed), "--robot", robot, "--shards", "2", "--no-api", "--router-port"]
    return procs([*argv, str(port), "--commit-scans", "8", *extra])


def test_a_killed_pipeline_resumes_and_a_second_robots_session_adds_to_the_map(tmp_path, procs):  # noqa: F811
    first = make_posed(tmp_path / "a.npz", "samples", steps=120)
    second = make_posed(tmp_path / "b.npz", "samples", steps=50, seed=11)
    state = tmp_path / "state"
    port = free_port()
    run = procs(
        [
            *CLI,
            "run",
            "--posed",
            str(first),
            "--robot",
            "r1",
            "--shards",
            "2",
            "--state-dir",
            str(state),
            "--rate",
            "2",
            "--no-api",
            "--router-port",
            str(port),
            "--commit-scans",
            "8",
        ]
    )
    pids = _pids(run.wait_for(r"running: (.*)").group(1))
    with zenoh.open(build_config("client", connect=[f"tcp/127.0.0.1:{port}"])) as session:
        stats = _wait_stats(
            MapReader(session, "main"),
            lambda s: len(s) == 2 and all(x.committed.get("r1", 0) >= 24 for x in s.values()),
            "both shards to commit 24 scans",
        )
    assert all(s.fused["r1"] < 120 and s.persist == "ok" for s in stats.values()), stats
    for pid in [run.process.pid, *pids.values()]:  # everything at once, the launcher first: nothing stops cleanly
        os.kill(pid, signal.SIGKILL)
    run.process.wait(10)
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in pids.values()):  # (a shard still dying holds its state directory's lock)
        assert time.monotonic() < deadline, "the killed processes did not go"
        time.sleep(0.05)

    exported = tmp_path / "first.npz"
    again = _run(tmp_path, procs, first, "r1", "--resume", str(state), "--continue-session", "--export", str(exported))
    assert again.process.wait(120) == 0, again.output()
    resumed = [int(n) for n in re.findall(r"resumed \d+ tile\(s\) and (\d+) scan\(s\) of 1 robot", again.output())]
    assert len(resumed) == 2 and min(resumed) >= 24, again.output()
    assert "replay finished: 120 scans, each of 2 shard(s) fused 120" in again.output()
    expected = fuse_posed_scans(load_posed_scans(first))
    _raster_equal(exported, expected.rasterize())  # the map of a run never stopped

    both = tmp_path / "both.npz"
    added = _run(tmp_path, procs, second, "r2", "--resume", str(state), "--export", str(both))
    assert added.process.wait(120) == 0, added.output()
    assert "replay finished: 50 scans, each of 2 shard(s) fused 50" in added.output()
    fuse_posed_scans(load_posed_scans(second), grid=expected)  # the first run's map, then the second's scans
    _raster_equal(both, expected.rasterize())

    # shards started on the saved state, with no source: they serve the map (the API reads it the same way)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    for shard in range(2):
        procs(
            [
                *CLI,
                "mapper",
                "--shard",
                str(shard),
                "--shards",
                "2",
                "--state-dir",
                str(state / f"shard-{shard}"),
                "--connect",
                endpoint,
            ]
        ).wait_for("up; tiles on")
    with zenoh.open(build_config("client", connect=[endpoint])) as session:
        reader = MapReader(session, "main")
        served = _wait_stats(reader, lambda s: len(s) == 2, "both shards' stats", timeout=30)
        assert all(s.fused == {"r2": 50} and s.committed == {"r2": 50} and s.persist == "ok" for s in served.values())
        _raster_equal(reader.assemble(2, 0.05).rasterize(), expected.rasterize())


def test_continuing_a_session_with_another_input_fails_and_keeps_the_map(tmp_path, procs):  # noqa: F811
    """--continue-session with an input other than the session's: every scan and pose differs from the one fused
    for its seq, the shards refuse them all, and the run says so and exits 1 (it used to say "fused 30", exit 0)."""
    first = make_posed(tmp_path / "a.npz", "samples", steps=30)
    other = make_posed(tmp_path / "b.npz", "samples", steps=30, seed=11)
    state = tmp_path / "state"
    made = _run(tmp_path, procs, first, "r1", "--state-dir", str(state), "--export", str(tmp_path / "first.npz"))
    assert made.process.wait(120) == 0, made.output()

    exported = tmp_path / "again.npz"
    again = _run(tmp_path, procs, other, "r1", "--resume", str(state), "--continue-session", "--export", str(exported))
    assert again.process.wait(120) == 1, again.output()
    errors = [line for line in again.lines if "posegrid run: error:" in line]
    assert len(errors) == 1 and "the input is not the one this session was fused from" in errors[0], again.output()
    # (every scan and pose of the 30 differs: 60 refusals by the shard that owns tiles of all of them, or fewer)
    assert re.search(r"refused ([1-9]\d*) scan\(s\) or pose\(s\)", errors[0]), errors[0]
    _raster_equal(exported, tmp_path / "first.npz")  # the map is the session's own input's, untouched
    # (the same input continued exits 0: test_a_killed_pipeline_resumes_and_a_second_robots_session_adds_to_the_map)


def test_a_source_does_not_wait_for_a_shard_whose_commits_fail(tmp_path, procs):  # noqa: F811
    """A shard whose store cannot be written (here past --state-limit-mb; a full or immutable disk in the probe) goes
    on fusing from memory, persist: failing. The source waited for its commits, gave up after 60 s with exit 1, and
    `posegrid run` restarted it, which replayed the run, for ever (11 minutes in the probe). It now ends once every
    scan is fused, and says why it did not wait; the shard's clean stop, whose last commit fails, exits 1."""
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=36)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    shard = procs(
        [*CLI, "mapper", "--shard", "0", "--shards", "1", "--map", "m", "--state-dir", str(tmp_path / "state")]
        + ["--state-limit-mb", "0.06", "--commit-scans", "4", "--connect", endpoint]
    )
    shard.wait_for("up; tiles on")
    source = procs(
        [*CLI, "source", "--posed", str(posed), "--robot", "r1", "--map", "m", "--wait-mappers", "1"]
        + ["--rate", "max", "--connect", endpoint]
    )
    assert source.process.wait(50) == 0, source.output()  # (it gave up after 60 s, exit 1)
    assert "shard(s) 0 of map 'm' cannot commit to their state directory (persist: failing for more than 10 s)" in (
        source.output()
    )
    assert "persist: failing" in shard.output()
    shard.process.send_signal(signal.SIGINT)
    assert shard.process.wait(30) == 1, shard.output()
    assert "the last changes could not be committed" in shard.output()
