"""`posegrid run` supervises its children (services.nodes.launcher.RestartPolicy, Children.tend):

- the backoff and the cap on restarts, with an injected clock: exact delays;
- a child that ends is started again with the same arguments, one line per restart; the source only when it
  ends non-zero or by a signal (one that ends 0 has finished its replay);
- end to end: a mapper shard or the source SIGKILLed mid-run is restarted and the exported map is the one
  `posegrid fuse` builds, every scan fused; a shard killed while the launcher waits for the shards to come up is
  restarted too; a child killed more often than --max-restarts allows stops the run with one line saying which,
  how often and how it ended, and a non-zero exit.

Every process is started here or by the launcher started here, and ended by PID in a finalizer (the ``procs``
fixture of test_pipeline, which also ends every pid the launcher printed, restarted ones included).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from schemas.files import load_map
from services.cli import main
from services.nodes.launcher import Children, RestartPolicy, describe_exit
from services.process import get_logger
from test_pipeline import CLI, _alive, make_posed, procs  # noqa: F401  (procs: the fixture)

# ------------------------------------------------------------------------------------------------ policy


def test_backoff_doubles_from_the_first_delay_up_to_the_cap_on_restarts():
    policy = RestartPolicy(max_restarts=5, window=60.0, first_delay=0.5, max_delay=10.0)
    restarts: list[float] = []
    delays = []
    for now in (100.0, 101.0, 103.0, 106.0, 111.0):
        delays.append(policy.delay(restarts, now))
        restarts.append(now)
    assert delays == [0.5, 1.0, 2.0, 4.0, 8.0]
    assert policy.delay(restarts, 120.0) is None  # a sixth failure within 60 s: no restart


def test_backoff_is_capped_at_the_longest_delay():
    policy = RestartPolicy(max_restarts=6, window=60.0, first_delay=3.0, max_delay=10.0)
    assert [policy.delay([0.0] * n, 1.0) for n in range(7)] == [3.0, 6.0, 10.0, 10.0, 10.0, 10.0, None]


def test_only_restarts_within_the_window_count():
    policy = RestartPolicy(max_restarts=5, window=60.0, first_delay=0.5, max_delay=10.0)
    restarts = [0.0, 1.0, 2.0, 3.0, 4.0]
    assert policy.delay(restarts, 59.0) is None  # all five within the last 60 s
    assert policy.delay(restarts, 61.5) == 4.0  # 0 and 1 are 60 s or more ago: 3 recent, 0.5 * 2**3
    assert policy.delay(restarts, 64.0) == 0.5  # none recent: the backoff starts over


def test_no_restarts_allowed():
    assert RestartPolicy(max_restarts=0).delay([], 0.0) is None


def test_exit_descriptions_name_the_signal():
    assert describe_exit(1) == "exited 1"
    assert describe_exit(-9) == "exited -9 (SIGKILL)"
    assert describe_exit(-15) == "exited -15 (SIGTERM)"


# ------------------------------------------------------------------------------------------------ Children.tend


class FakeProcess:
    """What Children needs of a Popen: a pid, poll() and returncode, ended by the test with end()."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        return self.returncode

    def end(self, code: int) -> None:
        self.returncode = code


class Clock:
    def __init__(self, now: float = 1000.0):
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def fake_children():
    """(Children with an injected clock and fake processes, the clock, the argvs spawned in order)."""
    clock = Clock()
    spawned: list[list[str]] = []

    def spawn(argv: list[str]) -> FakeProcess:
        spawned.append(argv)
        return FakeProcess(100 + len(spawned))

    children = Children(
        get_logger("test"),
        RestartPolicy(max_restarts=2, window=60.0, first_delay=0.5, max_delay=10.0),
        clock=clock,
        spawn=spawn,
    )
    return children, clock, spawned


def test_only_a_router_killed_at_the_stop_is_forgiven(fake_children):
    """After the stop, a child outside CLEAN_EXITS fails the run, except the router killed after the grace: it holds
    no state. A router that ended -9 on its own (not killed by the stop) still counts."""
    children, _, _ = fake_children
    for name in ("router", "mapper[0]", "source"):
        children.start(name, [name])
    router, mapper, source = (child.process for child in children.children)
    router.end(-signal.SIGKILL)
    mapper.end(0)
    source.end(-signal.SIGTERM)
    assert children.stopped_badly() == ["router"]
    children.killed.add("router")
    assert children.stopped_badly() == []
    mapper.end(-signal.SIGKILL)
    children.killed.add("mapper[0]")
    assert children.stopped_badly() == ["mapper[0]"]


def test_a_child_that_ends_is_started_again_with_its_argv_after_the_backoff(fake_children, capsys):
    children, clock, spawned = fake_children
    mapper = children.start("mapper[1]", ["mapper", "--shard", "1"])
    children.start("router", ["router"])
    mapper.process.end(-signal.SIGKILL)
    assert children.tend() is None
    assert capsys.readouterr().err == (
        "posegrid run: mapper[1] (pid 101) exited -9 (SIGKILL); restarting in 0.5 s (restart 1 of 2 within 60 s)\n"
    )
    clock.now += 0.49
    assert children.tend() is None
    assert len(spawned) == 2 and mapper.process.pid == 101  # not yet
    clock.now += 0.01
    assert children.tend() is None
    assert spawned[-1] == ["mapper", "--shard", "1"] and mapper.process.pid == 103
    assert capsys.readouterr().err == "posegrid run: mapper[1] restarted (pid 103)\n"
    clock.now += 5.0
    mapper.process.end(0)  # a server that ends at all, even with 0, is restarted
    assert children.tend() is None
    assert "mapper[1] (pid 103) exited 0; restarting in 1 s (restart 2 of 2 within 60 s)" in capsys.readouterr().err
    clock.now += 1.0
    children.tend()
    assert mapper.process.pid == 104


def test_a_child_failing_past_the_cap_is_returned_with_one_line(fake_children, capsys):
    children, clock, _ = fake_children
    api = children.start("api", ["api"])
    for delay in (0.5, 1.0):
        api.process.end(1)
        assert children.tend() is None
        clock.now += delay
        assert children.tend() is None
    api.process.end(-signal.SIGKILL)
    assert children.tend() is api
    last = capsys.readouterr().err.splitlines()[-1]
    assert last == (
        "posegrid run: error: api failed 3 times; the last time (pid 103) it exited -9 (SIGKILL); it had "
        "2 restart(s) in the last 60 s, the most --max-restarts allows: stopping the run"
    )


def test_a_child_that_refuses_its_input_is_not_restarted(fake_children, capsys):
    """Exit 2 is a refused input or option (services.errors.UsageError): a restart would fail the same way, so the run
    stops at once with one line."""
    children, _, spawned = fake_children
    source = children.start("source", ["source", "--posed", "bad.npz"], expected_to_finish=True)
    source.process.end(2)
    assert children.tend() is source and len(spawned) == 1
    assert capsys.readouterr().err == (
        "posegrid run: error: source (pid 101) exited 2: its input or options were "
        "refused (its own error line above says why); not restarting it: stopping "
        "the run\n"
    )


def test_the_source_is_restarted_only_when_it_fails(fake_children, capsys):
    children, clock, spawned = fake_children
    source = children.start("source", ["source", "--posed", "x.npz"], expected_to_finish=True)
    source.process.end(-signal.SIGKILL)
    assert children.tend() is None
    assert children.running_to_finish()  # its restart is pending: the replay is not over
    clock.now += 0.5
    children.tend()
    assert spawned == [["source", "--posed", "x.npz"]] * 2
    source.process.end(0)  # the replay is over
    assert children.tend() is None
    assert not children.running_to_finish()
    assert len(spawned) == 2 and source.failures == 1


# ------------------------------------------------------------------------------------------------ end to end


def _pids(banner: str) -> dict[str, int]:
    return {name: int(pid) for name, pid in re.findall(r"(\S+) \(pid (\d+)\)", banner)}


def _fused_map(tmp_path: Path, posed: Path) -> Path:
    fused = tmp_path / "fused.npz"
    assert main(["fuse", str(posed), "-o", str(fused)]) == 0
    return fused


def _assert_same_map(exported: Path, fused: Path) -> None:
    expected, got = load_map(fused), load_map(exported)
    assert got.logodds.shape == expected.logodds.shape
    np.testing.assert_array_equal(got.observed, expected.observed)
    np.testing.assert_allclose(got.logodds, expected.logodds, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(got.origin, expected.origin)
    assert expected.observed.sum() > 10_000  # the map is not trivially empty


@pytest.mark.slow
@pytest.mark.parametrize("victim", ["mapper[1]", "source"])
def test_a_child_killed_mid_run_is_restarted_and_every_scan_is_fused(tmp_path, procs, victim):  # noqa: F811
    steps = 200
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=steps)
    exported = tmp_path / "run.npz"
    run = procs(
        [*CLI, "run", "--posed", str(posed), "--shards", "2", "--export", str(exported), "--rate", "2", "--no-api"]
    )
    pid = _pids(run.wait_for(r"running: (.*)").group(1))[victim]
    run.wait_for(rf"publishing {steps} steps")
    time.sleep(2.0)  # some 40 steps into the 10 s replay
    os.kill(pid, signal.SIGKILL)
    restart = re.escape(
        f"posegrid run: {victim} (pid {pid}) exited -9 (SIGKILL); restarting in 0.5 s (restart 1 of 5 within 60 s)"
    )
    run.wait_for(restart)
    new_pid = int(run.wait_for(rf"{re.escape(victim)} restarted \(pid (\d+)\)").group(1))
    assert new_pid != pid and not _alive(pid)
    assert run.process.wait(180) == 0, run.output()
    output = run.output()
    finished = f"posegrid run: replay finished: {steps} scans, each of 2 shard(s) fused {steps}"
    assert finished in run.lines, output
    assert re.search(restart, output).start() < output.index(finished), "killed after the replay had finished"
    assert re.search(
        r"stopped: router exited 0, mapper\[0\] exited 0, mapper\[1\] exited 0, source exited 0", output
    ), output
    assert not _alive(new_pid)
    _assert_same_map(exported, _fused_map(tmp_path, posed))


def _children_of(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(FileNotFoundError):
            found += [int(child) for child in (task / "children").read_text().split()]
    return found


def _first_mapper(launcher: int, timeout: float = 60.0) -> int:
    """The pid of the launcher's child `posegrid mapper --shard 0`, as soon as it is there."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for child in _children_of(launcher):
            try:
                argv = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            except FileNotFoundError:
                continue
            if b"mapper" in argv and argv[argv.index(b"--shard") + 1] == b"0":
                return child
        time.sleep(0.01)
    raise AssertionError("the launcher started no mapper shard 0")


@pytest.mark.slow
def test_a_shard_killed_while_starting_is_restarted(tmp_path, procs):  # noqa: F811
    steps = 40
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=steps)
    exported = tmp_path / "run.npz"
    run = procs([*CLI, "run", "--posed", str(posed), "--export", str(exported), "--no-api"])
    pid = _first_mapper(run.process.pid)
    os.kill(pid, signal.SIGKILL)
    restart = re.escape(f"posegrid run: mapper[0] (pid {pid}) exited -9 (SIGKILL); restarting in 0.5 s")
    run.wait_for(restart)
    assert run.process.wait(180) == 0, run.output()
    output = run.output()
    assert re.search(restart, output).start() < output.index("  running: "), "killed after the shards were up"
    assert f"posegrid run: replay finished: {steps} scans, each of 1 shard(s) fused {steps}" in run.lines, output
    _assert_same_map(exported, _fused_map(tmp_path, posed))


@pytest.mark.slow
def test_a_child_failing_past_the_cap_stops_the_run(tmp_path, procs):  # noqa: F811
    posed = make_posed(tmp_path / "posed.npz", "samples", steps=600)
    run = procs(
        [
            *CLI,
            "run",
            "--posed",
            str(posed),
            "--shards",
            "2",
            "--rate",
            "realtime",
            "--no-api",
            "--max-restarts",
            "1",
            "--restart-delay",
            "0.2",
            "--restart-window",
            "600",
        ]
    )
    pids = _pids(run.wait_for(r"running: (.*)").group(1))
    first = pids["mapper[0]"]
    os.kill(first, signal.SIGKILL)
    run.wait_for(re.escape(f"mapper[0] (pid {first}) exited -9 (SIGKILL); restarting in 0.2 s (restart 1 of 1"))
    second = int(run.wait_for(r"mapper\[0\] restarted \(pid (\d+)\)").group(1))
    os.kill(second, signal.SIGKILL)
    assert run.process.wait(120) == 1, run.output()
    reason = (
        f"posegrid run: error: mapper[0] failed 2 times; the last time (pid {second}) it exited -9 (SIGKILL); "
        "it had 1 restart(s) in the last 600 s, the most --max-restarts allows: stopping the run"
    )
    assert reason in run.lines, run.output()
    assert not any("replay finished" in line for line in run.lines)
    # (a crash probe: this stop gave no way on; the banner's plain --resume fused the replay's scans twice)
    run.wait_for(r"stopped before the replay ended \(\d+ of 600 scans")
    run.wait_for(r"to go on with this replay of the same input: posegrid run --resume .* --continue-session")
    assert run.wait_for(r"stopped: (.*)").group(1).startswith("router exited 0, mapper[0] exited -9")
    assert not any(_alive(pid) for pid in [*pids.values(), second])


def test_the_banners_resume_command_can_be_pasted_into_a_shell(capsys):
    """A probe: with a state folder whose path holds a space, the banner's "go on later with: posegrid run --resume
    ..." failed when pasted (unrecognized arguments). The path is quoted for the shell. Another: after a crash, that
    plain --resume fused the interrupted replay's scans a second time; the banner gives both commands."""
    import shlex

    from services.nodes.launcher import Children, Plan, _banner
    from services.process import get_logger
    from services.state.store.run import RunState

    folder = Path("/tmp/my maps/état")
    plan = Plan("m", "r", 1, 0.05, [], [], state=RunState(folder, "s1", resumed=False), scans=50)
    _banner(plan, "tcp/127.0.0.1:1", Children(get_logger("test")))
    out = capsys.readouterr().out.splitlines()
    line = next(line for line in out if "add new input to this map later with:" in line)
    assert shlex.split(line.split("later with: ", 1)[1]) == ["posegrid", "run", "--resume", str(folder)]
    line = next(line for line in out if "if this replay stops before its end, go on with it with:" in line)
    assert shlex.split(line.split("with it with: ", 1)[1])[-2:] == [str(folder), "--continue-session"]
