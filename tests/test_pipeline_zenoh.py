"""Zenoh configuration (one builder, loopback-only defaults, user overrides), the router process, and the
pipeline commands' command-line behaviour."""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import time

import pytest
import zenoh

from services.cli import build_parser, main
from services.commands.mapping import available_memory
from services.commands.pipeline import check_shards_fit
from services.errors import UsageError
from services.ports import free_port
from services.process import RejectCounter
from services.zenoh_config import build_config, close_session, read_key

CLI = [sys.executable, "-m", "services"]


def test_defaults_are_loopback_only_without_multicast():
    router, peer, client = (build_config(mode) for mode in ("router", "peer", "client"))
    for config, mode in ((router, "router"), (peer, "peer"), (client, "client")):
        assert read_key(config, "mode") == mode
        assert read_key(config, "scouting/multicast/enabled") is False
    assert read_key(router, "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert read_key(router, "connect/endpoints") == []
    assert read_key(peer, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert read_key(peer, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert read_key(client, "listen/endpoints") == []
    assert read_key(client, "connect/endpoints") == ["tcp/127.0.0.1:7447"]


def test_user_file_overrides_what_it_sets_and_defaults_fill_the_rest(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ // a user config\n mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:17999"] },\n'
        " scouting: { multicast: { enabled: true } } }\n"
    )
    config = build_config("client", config_file=path)
    assert read_key(config, "mode") == "peer"
    assert read_key(config, "listen/endpoints") == ["tcp/127.0.0.1:17999"]
    assert read_key(config, "scouting/multicast/enabled") is True  # the user's explicit choice stands
    assert read_key(config, "connect/endpoints") == ["tcp/127.0.0.1:7447"]  # unset in the file: default


def test_command_line_endpoints_override_the_file(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text(json.dumps({"connect": {"endpoints": ["tcp/127.0.0.1:1111"]}}))
    config = build_config("client", config_file=path, connect=["tcp/127.0.0.1:2222"], listen=["tcp/127.0.0.1:0"])
    assert read_key(config, "connect/endpoints") == ["tcp/127.0.0.1:2222"]
    assert read_key(config, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert read_key(config, "scouting/multicast/enabled") is False


def test_a_session_that_fails_to_close_is_one_line_not_a_traceback(capsys):
    """zenoh gives up closing a session when the router or the machine stalls ("close operation timed out"): the
    process says so in one line and ends as it would (a stand-in session: a real close cannot be made to time out
    on demand). A session that closes is closed."""

    class StalledSession:
        def close(self) -> None:
            raise zenoh.ZError("close operation timed out! at zenoh/src/api/builders/close.rs:135.")

    close_session(StalledSession(), "the router")  # type: ignore[arg-type]
    assert capsys.readouterr().err == (
        "posegrid: the router's zenoh session did not close cleanly (close operation timed out!)\n"
    )
    session = zenoh.open(build_config("peer", listen=[]))
    close_session(session, "a peer")
    assert session.is_closed() and capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"connect": ["not-an-endpoint"]}, "connect/endpoints"),
        ({"config_file": "/nonexistent/zenoh.json5"}, "/nonexistent/zenoh.json5: no such file"),
    ],
)
def test_bad_configuration_is_one_sentence(kwargs, message):
    with pytest.raises(UsageError) as info:
        build_config("client", **kwargs)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_invalid_config_file_is_one_sentence(tmp_path):
    path = tmp_path / "bad.json5"
    path.write_text("{ mode: ")
    with pytest.raises(UsageError, match="not valid"):
        build_config("client", config_file=path)


@pytest.fixture
def started():
    processes: list[subprocess.Popen] = []
    yield processes
    for process in processes:
        if process.poll() is None:
            process.kill()
            process.wait()


@pytest.mark.parametrize("port", ["free", "0"])
def test_router_process_routes_between_two_clients_and_stops_on_sigint(started, port):
    """With port 0 the router says the port it listens on (it said :0, which no client can connect to)."""
    given = f"tcp/127.0.0.1:{free_port() if port == 'free' else 0}"
    router = subprocess.Popen([*CLI, "router", "--listen", given], stderr=subprocess.PIPE, text=True)
    started.append(router)
    said = router.stderr.readline()
    endpoint = said.split("routing; listening on ", 1)[1].strip()
    assert endpoint == given if port == "free" else endpoint != given and endpoint.startswith("tcp/127.0.0.1:")
    config = build_config("client", connect=[endpoint])
    received = []
    with zenoh.open(config) as a, zenoh.open(config) as b:
        subscriber = b.declare_subscriber("pg/test/ping", lambda sample: received.append(sample.payload.to_bytes()))
        deadline = time.monotonic() + 10
        while not received and time.monotonic() < deadline:
            a.put("pg/test/ping", b"hello", congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.05)
        subscriber.undeclare()
    assert received and received[0] == b"hello"
    router.send_signal(signal.SIGINT)
    assert router.wait(20) == 0


def test_mapper_without_a_router_says_so_in_one_sentence(tmp_path, capsys):
    port = free_port()
    base = ["mapper", "--shard", "0", "--shards", "1", "--connect", f"tcp/127.0.0.1:{port}"]
    assert main([*base, "--zenoh-config", str(tmp_path / "none.json5")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none.json5: no such file" in err
    # a config cut short (a secure-mode probe's): it said "is not valid: --> 3:25", where but not what
    cut = tmp_path / "cut.json5"
    cut.write_text('{\n  mode: "client",\n  connect: { endpoints: ["tcp/127.0.0.1:1"] ')
    assert main([*base, "--zenoh-config", str(cut)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cut.json5 is not valid: line 3, column " in err and ": expected " in err, err
    assert ".rs:" not in err
    base = [*CLI, *base]
    quick = tmp_path / "quick.json5"
    quick.write_text(json.dumps({"connect": {"timeout_ms": 500}}))  # do not wait 10 s for a router
    result = subprocess.run(
        [*base, "--zenoh-config", str(quick)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    assert "could not open its zenoh session" in result.stderr and f"tcp/127.0.0.1:{port}" in result.stderr


def test_a_router_port_in_use_names_the_option_to_change():
    """A busy listening port said "is `posegrid router` running at ...?", which sends the user to the router that
    could not start; it now names the port's option."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [*CLI, "router", "--listen", f"tcp/127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "is another process listening on" in result.stderr and "pick another --listen" in result.stderr


@pytest.mark.parametrize(
    "argv, message",
    [
        (["mapper", "--shard", "2", "--shards", "2"], "--shard"),
        (["mapper", "--shard", "0", "--shards", "1", "--tile-size", "100"], "power of 2"),
        (["mapper", "--shard", "0", "--shards", "1", "--tile-size", "2048"], "up to 1024"),
        (["mapper", "--shard", "0", "--shards", "5000"], "--shards <= 1024"),
        (["mapper", "--shard", "0", "--shards", "1", "--resolution", "0.0001"], "0.001 .. 1000 m"),
        (["run", "--posed", "x.npz", "--shards", "5000"], "--shards must be 1 .. 1024"),
        (["mapper", "--shard", "0", "--shards", "1", "--map", "a/b"], "--map"),
        (["source", "--posed", "x.npz", "--rate", "fast"], "rate"),
        # past the platform's time_t: a traceback, and under run a crash loop of the source
        (["source", "--posed", "x.npz", "--rate", "1e-308"], "a factor of real time in [0.001, 1e+06]"),
        (["run", "--posed", "x.npz", "--rate", "5e-324"], "a factor of real time in [0.001, 1e+06]"),
        (["api", "--cache-mb", "1e308"], "--cache-mb must be > 0 and at most 1048576"),  # tracebacks, as these three
        (["api", "--query-timeout", "1e308"], "--query-timeout must be > 0 and at most 86400 s"),
        (["mapper", "--shard", "0", "--shards", "1", "--state-dir", "st", "--state-limit-mb", "1e308"], "1 PiB"),
        (["api", "--host", ""], "--host '' would listen on every interface"),
        (["source", "--sim", "--steps", "1000000000"], "--steps must be 1 .. 277008"),  # memory for minutes
        (["run", "--sim", "--steps", "1000000000"], "--steps must be 1 .. 277008"),
        (["router", "--zenoh-config", "/dev/null"], "zenoh config file /dev/null: is a character device"),
        (["router", "--zenoh-config", "/tmp"], "zenoh config file /tmp: is a folder"),  # both said "does not exist"
        # a port past 65535: a connect timed out after 10 s, a listen blamed another process
        (["router", "--connect", "tcp/127.0.0.1:99999"], "--connect tcp/127.0.0.1:99999: port 99999 is no TCP/UDP"),
        (["router", "--listen", "tcp/127.0.0.1:65536"], "port 65536 is no TCP/UDP port (0..65535)"),
        (["source", "--posed", "x.npz", "--robot", "map"], "--robot"),
        (["run", "--posed", "/nonexistent.npz"], "no such file"),
        (["run", "--posed", "x.npz", "--shards", "0"], "--shards"),
        (["run", "--posed", "x.npz", "--max-map-cells", "0"], "--max-map-cells: max_map_cells must be >= 1, got 0"),
        (["run", "--mrclam", "/tmp"], "no laser"),
        (["run", "--carmen", "x.clf", "--algo", "ekf"], "gridslam"),
        (["run", "--bag", "x.bag", "--algo", "fastslam2"], "a ROS bag has no landmarks"),
        (["run", "--carmen", "x.clf", "--scan-topic", "/scan"], "give it with --bag"),
        (["source", "--carmen", "x.clf", "--scan-topic", "/scan"], "give it with --bag"),
        (["source", "--bag", "/nonexistent.bag"], "/nonexistent.bag"),
        (["run", "--bag", "/nonexistent.bag", "--no-api"], "/nonexistent.bag"),  # before anything is started
        (["run", "--posed", "x.npz", "--odom-delay", "0.1"], "give it with --carmen or --bag"),
        (["run", "--posed", "x.npz", "--steps", "10"], "--posed replays its input whole"),  # (it did, silently)
        (["source", "--carmen", "x.clf", "--steps", "10"], "--carmen replays its input whole"),
        (["slam-node", "--initial", "1,2"], "--initial"),
        (["slam-node", "--initial", "1,2,90"], "--initial's yaw 90 is more than a full turn: give it in rad"),
        (["simulate", "out", "--resolution", "1e-5"], "--resolution must be in [0.005, 1]"),  # a 2.8 TiB raster
        (["simulate", "out", "--dt", "1e6"], "--dt must be in [0.001, 1]"),
        (["simulate", "out", "--steps", "100000", "--beams", "100000"], "--steps x --beams is 10000000000"),
    ],
)
def test_bad_arguments_exit_2_with_one_sentence(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and err.count("\n") == 1, err


def test_an_option_a_command_does_not_know_is_said_with_that_commands_usage(capsys):
    """A new user's probe: `posegrid mapper ... --no-state` (an option of `run`) printed posegrid's own usage,
    "posegrid [-h] COMMAND ...", which names no option of the mapper."""
    with pytest.raises(SystemExit) as exit_info:
        main(["mapper", "--shard", "0", "--shards", "1", "--no-state"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: posegrid mapper ") and "--state-dir DIR" in err
    assert err.endswith("posegrid mapper: error: unrecognized arguments: --no-state\n")


def test_run_refuses_more_shards_than_the_machines_memory_holds(tmp_path, monkeypatch, capsys):
    """`run --shards 1000` on a 2-core machine with 23 GB started mapper after mapper until the kernel killed
    processes. Each process is reckoned at 200 MiB: 6 GiB holds 25 shards beside the 5 other processes, not 26."""
    gib = 2**30
    check_shards_fit(25, 6 * gib)
    with pytest.raises(
        UsageError, match=r"--shards 26 would start 26 mapper processes .* about 6\.1 GiB .* 6\.0 GiB is"
    ):
        check_shards_fit(26, 6 * gib)
    check_shards_fit(1024, None)  # (memory not known: not checked)
    available = available_memory()
    assert available is not None and available > 0  # (Linux)
    if available >= (1024 + 5) * 200 * 2**20:
        pytest.skip("this machine holds 1 024 shards")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert main(["run", "--sim", "--no-api", "--shards", "1024"]) == 2
    err = capsys.readouterr().err
    assert "--shards 1024 would start 1024 mapper processes" in err and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "options, message",
    [
        (["--sigma0", "-1"], "sigma0 must be > 0 m"),
        (["--peak-width", "0"], "peak_width must be > 0 m"),
        (["--outlier-gate", "0"], "--outlier-gate must be > 0 (or inf)"),
        (["--resample-threshold", "2"], "--resample-threshold must be in [0, 1]"),
        (["--algo", "gridslam", "--widen", "0"], "grid FastSLAM option out of range"),
        (["--drive-angle-sd", "1"], "--drive-angle-sd must be in [0, 0.5]"),
    ],
)
def test_run_refuses_its_childrens_options_before_it_starts_anything(tmp_path, monkeypatch, capsys, options, message):
    """`run --sigma0 -1` started a router and a shard, which refused the option, then exited 1 with the launcher's
    lines and left a run directory behind; the shards' and the SLAM node's options are checked first."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert main(["run", "--sim", "--no-api", *options]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []  # no run directory


@pytest.mark.parametrize(
    "argv, message",
    [
        (["slam-node", "--particles", "0"], "argument --particles: must be in 1 .. 10000, got 0"),
        (["slam-node", "--particles", "10001"], "argument --particles: must be in 1 .. 10000"),  # past a PoseSamples
        (["run", "--particles", "20000"], "argument --particles: must be in 1 .. 10000"),
        (["mapper", "--shard", "0", "--shards", "1", "--map", "m", "--samples", "10001"], "argument --samples"),
        (["fuse", "x.npz", "-o", "y.npz", "--samples", "100000000"], "argument --samples: must be in 1 .. 10000"),
        (["fuse", "x.npz", "-o", "y.npz", "--resolution", "inf"], "argument --resolution: must be a finite number"),
        (["fuse", "x.npz", "-o", "y.npz", "--sigma-slope", "nan"], "argument --sigma-slope: must be a finite number"),
        (["fuse", "x.npz", "-o", "y.npz", "--seed", "-1"], "argument --seed: a seed is an integer >= 0, got -1"),
        (["simulate", "out", "--dt", "nan"], "argument --dt: must be a finite number"),
        (["slam", "sim", "-o", "p.npz", "--algo", "ekf", "--seed", "-2"], "argument --seed"),
        (["export", "m.npz", "--format", "png", "-o", "m.png", "--crop", "inf"], "argument --crop"),
    ],
)
def test_bad_values_stop_at_parsing_with_the_option_named(argv, message, capsys):
    """argparse's own error: the usage, then one line naming the option and what it must be; exit 2."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and message in err.splitlines()[-1] and "Traceback" not in err, err


def _every_command(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every command and subcommand of ``parser`` (as argv prefixes), found in the parser itself."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found += [(*prefix, name), *_every_command(sub, (*prefix, name))]
    return found


@pytest.mark.parametrize("command", _every_command(build_parser()), ids=" ".join)
def test_every_command_has_help(command, capsys):
    """Every command's --help prints its usage and exits 0 (a help text with a bare '%' made argparse raise a
    TypeError: `posegrid slam --help` gave a traceback)."""
    with pytest.raises(SystemExit) as info:
        main([*command, "--help"])
    assert info.value.code == 0 and "usage: posegrid " + " ".join(command) in capsys.readouterr().out


def test_the_parser_loads_no_fit_compiler_or_web_library():
    """Every ``posegrid`` start builds the whole parser. A helper that imported the landmark self-calibration for
    its choices loaded scipy.optimize and numba there: 0.9 of a 1.2 CPU s start, in every command and every test's
    subprocess. Checked in a fresh interpreter, since this one has them loaded already."""
    heavy = ("scipy", "numba", "fastapi", "uvicorn")
    probe = (
        "import sys; from services.cli import build_parser; build_parser(); "
        f"print(sorted({{m.split('.')[0] for m in sys.modules if m.startswith({heavy!r})}}))"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    assert result.stdout.strip() == "[]", f"building the parser imported {result.stdout.strip()}"


def test_the_slam_node_loads_grid_fastslam_only_to_run_it():
    """A landmark SLAM node has no use for grid FastSLAM's filter, its loop closure and their scipy parts (0.6 CPU s
    of every node's start): services.state.slam imports them at the first scan of a grid FastSLAM node."""
    probe = (
        "import sys; import services.nodes.slam_node; "
        "print(sorted(m for m in sys.modules if m in ('slam.gridslam.filter', 'slam.gridslam.loops', 'scipy')))"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=True)
    assert result.stdout.strip() == "[]", f"the SLAM node's import loaded {result.stdout.strip()}"


def test_an_interrupt_while_the_commands_load_is_one_line_and_exit_130(monkeypatch, capsys):
    """A SIGINT that arrives while ``posegrid`` imports its command modules (a test's teardown, a user's Ctrl-C
    right after the start) gave a KeyboardInterrupt traceback. The interrupt stands in here for the signal."""
    from services import cli

    def interrupted(name: str):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.importlib, "import_module", interrupted)
    try:
        code = cli.main(["mapper", "--help"])
    except KeyboardInterrupt:
        pytest.fail("the interrupt escaped main() (a traceback for the user)")
    assert code == 130
    captured = capsys.readouterr()
    assert captured.err == "posegrid: interrupted\n" and captured.out == ""


def test_a_child_whose_launcher_is_gone_says_so_under_its_own_name():
    """A probe: after the launcher was SIGKILLed every child said "the launcher (pid N) is gone; stopping" with no
    name before it, so the lines did not say which process stopped. A process that is not its launcher's child any
    more (here: the pid it is told is not its parent's) sets its stop flag and says so as itself."""
    code = (
        "from services.process import install_stop_event\n"
        "stop = install_stop_event('mapper[3]')\n"
        "assert stop.wait(20), 'the parent watch did not fire'\n"
    )
    gone = 2**22 + 7  # (no parent of this child: its parent is the test)
    env = {**os.environ, "POSEGRID_PARENT_PID": str(gone)}
    argv = [sys.executable, "-c", code]
    result = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 0, result.stderr
    assert result.stderr.strip() == f"posegrid mapper[3]: the launcher (pid {gone}) is gone; stopping"


def test_a_burst_of_signals_sets_the_stop_flag_and_never_hangs_the_process():
    """A probe pressed Ctrl-C many times at a `posegrid run`: it hung for good, ignoring every later signal, its
    children running on. The handler called Event.set, which takes the event's lock, from the main thread, which may
    hold that lock at that moment (in stop.wait, or in an earlier handler's set). Here a process waiting on its stop
    flag gets 200 SIGINTs 20 us apart from another process, 30 times over: each time the flag is set and the wait
    returns (with the old handler it hung within a few rounds)."""
    code = (
        "import os, subprocess, sys\n"
        "from services.process import install_stop_event\n"
        "burst = 'import os, signal, sys, time\\ntime.sleep(0.05)\\n"
        "for _ in range(200):\\n    os.kill(int(sys.argv[1]), signal.SIGINT)\\n    time.sleep(0.00002)\\n'\n"
        "for trial in range(30):\n"
        "    stop = install_stop_event('burst')\n"
        "    sender = subprocess.Popen([sys.executable, '-c', burst, str(os.getpid())])\n"
        "    while not stop.wait(0.25):\n"
        "        pass\n"
        "    sender.wait()\n"
        "print('stopped 30 times')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0 and result.stdout.strip() == "stopped 30 times", result.stderr


def test_work_until_stopped_gives_its_result_its_error_or_stopped():
    """services.process.until_stopped: the work's result, or its exception raised in the caller's thread, or
    Stopped at once when the stop flag is set while the work still runs (the work is left to its thread)."""
    import threading

    from services.process import Stopped, until_stopped

    stop = threading.Event()
    assert until_stopped(lambda: 41 + 1, stop, "adding") == 42

    def refuse() -> int:
        raise UsageError("no such log")

    with pytest.raises(UsageError, match="no such log"):
        until_stopped(refuse, stop, "reading")
    release = threading.Event()
    threading.Timer(0.2, stop.set).start()
    started = time.monotonic()
    with pytest.raises(Stopped, match="stopped while waiting for ever"):
        until_stopped(lambda: release.wait(60), stop, "waiting for ever")
    assert time.monotonic() - started < 10.0  # (the work itself would take 60 s)
    release.set()


#: a `posegrid router` started with SIGINT ignored (as a script's background job is), which sends itself a SIGINT
#: while main() loads its commands: before the router installs its stop handlers
_IGNORED_SIGINT_CHILD = """
import os, signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
from services import cli
load = cli.build_parser
def interrupted_load():
    os.kill(os.getpid(), signal.SIGINT)
    return load()
cli.build_parser = interrupted_load
sys.exit(cli.main(["router", "--listen", sys.argv[1]]))
"""


def test_a_sigint_before_the_stop_handlers_stops_a_process_started_with_it_ignored(started):
    """A background job of a script starts with SIGINT ignored. A SIGINT that reached a service before it installed
    its stop handlers was lost, and the process ran on (a router 0.1 s after its start, a mapper up to 0.5 s)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    child = subprocess.Popen([sys.executable, "-c", _IGNORED_SIGINT_CHILD, endpoint], stderr=subprocess.PIPE, text=True)
    started.append(child)
    try:
        code = child.wait(30)
    except subprocess.TimeoutExpired:
        pytest.fail("the SIGINT was lost: the router runs on")
    assert code == 130 and child.stderr.read() == "posegrid: interrupted\n"


#: a `posegrid router` whose zenoh session close never ends (as one did once on a loaded machine, past the launcher's
#: grace): the real router and session, only the close replaced by a wait
_HANGING_CLOSE_ROUTER = """
import sys, threading
from services import cli
from services.nodes import router
router.close_session = lambda session, what: threading.Event().wait()
sys.exit(cli.main(["router", "--listen", sys.argv[1]]))
"""


def test_a_router_whose_session_close_hangs_still_stops_with_exit_0(started):
    """The router holds no state: a close that does not end within CLOSE_TIMEOUT is said in one line and the process
    ends 0, not killed by the launcher after its grace (which failed a run whose map was already exported)."""
    from services.nodes.router import CLOSE_TIMEOUT

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    child = subprocess.Popen([sys.executable, "-c", _HANGING_CLOSE_ROUTER, endpoint], stderr=subprocess.PIPE, text=True)
    started.append(child)
    assert "routing; listening on" in child.stderr.readline()
    child.send_signal(signal.SIGTERM)
    try:
        code = child.wait(CLOSE_TIMEOUT + 30)
    except subprocess.TimeoutExpired:
        pytest.fail("the router waits on its hanging close")
    said = child.stderr.read()
    assert code == 0, said
    assert said.count("\n") == 1 and "did not end within 5 s; stopping without it" in said, said
    assert "Traceback" not in said


@pytest.mark.parametrize(
    "argv",
    [
        ["mapper", "--shard", "0", "--shards", "1"],
        ["slam-node", "--robot", "r1", "--algo", "odometry"],
        ["source", "--sim", "--steps", "20"],
        ["api", "--port", str(free_port())],
    ],
    ids=lambda argv: argv[0],
)
def test_a_process_waiting_for_a_router_that_is_not_there_stops_at_once(started, argv):
    """With no router at the endpoint, opening the Zenoh session waits out the connect timeout (10 s) and then
    fails in one sentence; a stop meanwhile waited for it too. Now the process says, a second into the wait, that it
    is waiting for the router, and a stop then ends it at once, exit 0. (A fixed 3 s before the SIGINT was not always
    into the wait: a busy machine's source was still simulating its input.)"""
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # (nothing listens there)
    child = subprocess.Popen([*CLI, *argv, "--connect", endpoint], stderr=subprocess.PIPE, text=True)
    started.append(child)
    assert child.stderr is not None
    before = ""
    while "is waiting for the router" not in before:  # (the wait lasts 10 s; EOF means the process ended)
        line = child.stderr.readline()
        assert line, f"no word of the wait for the router: {before!r}"
        before += line
    assert f'is waiting for the router at ["{endpoint}"]' in before, before
    child.send_signal(signal.SIGINT)
    signalled = time.monotonic()
    code = child.wait(30)
    waited = time.monotonic() - signalled
    err = child.stderr.read()
    assert code == 0 and waited < 5.0 and "Traceback" not in err, (code, waited, err)
    assert "stopped while waiting for the router" in err, err


def test_two_processes_answering_one_robots_history_are_both_refused(started):
    """A source of an earlier run still up under the same robot name answers the history too: whose messages a
    reader would take is chance, and taking them made a map silently wrong (an audit). Both are left out, with
    a problem that says why; a stream only one process answers is taken, in its order, with its bad parameters
    refused in one sentence (ASCII seqs only: '²' passes str.isdigit but not int())."""
    from services import history

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen([*CLI, "router", "--listen", endpoint], stderr=subprocess.PIPE, text=True)
    started.append(router)
    assert "routing" in router.stderr.readline()
    config = build_config("client", connect=[endpoint])
    with zenoh.open(config) as old, zenoh.open(config) as new, zenoh.open(config) as reader:

        def answering(session, run: bytes, streams: set[str]):
            def answer(query):
                request = history.parse_request(query, "r1", RejectCounter(logging.getLogger("history")))
                for stream in sorted(streams & (request.streams if request else set())):
                    for seq in filter(request.wants, range(3)):
                        history.reply(
                            query,
                            history.Answerer(str(session.info.zid()), "m", False),
                            "r1",
                            stream,
                            run + b"%d" % seq,
                        )

            return session.declare_queryable("pg/r1/history/**", answer)

        queryables = [answering(old, b"old", {"scan"}), answering(new, b"new", {"scan", "pose"})]
        time.sleep(0.5)
        messages, problems = history.ask(reader, "r1", {}, timeout=10)
        assert messages == [("r1", "pose", b"new0"), ("r1", "pose", b"new1"), ("r1", "pose", b"new2")]
        assert len(problems) == 1 and "2 processes answer the scan history of robot 'r1'" in problems[0]
        messages, problems = history.ask(reader, "r1", {"streams": "pose", "from": "\u00b2"}, timeout=10)
        assert messages == [] and len(problems) == 2  # each answerer refuses it
        assert all("'from' and 'to' must be seqs 0 .. 10^18 in ASCII digits" in problem for problem in problems)
        messages, _ = history.ask(reader, "r1", {"streams": "pose", "from": "1", "to": "2"}, timeout=10)
        assert messages == [("r1", "pose", b"new1")]
        messages, _ = history.ask(reader, "r1", {"streams": "pose", "from": "0", "to": "3", "seqs": "2,0"}, timeout=10)
        assert messages == [("r1", "pose", b"new0"), ("r1", "pose", b"new2")]  # (only those seqs, in order)
        messages, problems = history.ask(reader, "r1", {"streams": "pose", "seqs": ",".join(["1"] * 65)}, timeout=10)
        assert messages == [] and problems and all("'seqs' must be at most 64" in problem for problem in problems)
        for queryable in queryables:
            queryable.undeclare()
        # a peer posing as the real history (its replies name the real session): not taken, said, and the real
        # history's stream is left out as for two answerers (a hostile-peer probe: a forged far run was believed)
        real = answering(new, b"new", {"scan"})
        poser = old.declare_queryable(
            "pg/r1/history/**",
            lambda query: history.reply(query, history.Answerer(str(new.info.zid()), "m", False), "r1", "scan", b"x"),
        )
        time.sleep(0.5)
        messages, problems = history.ask(reader, "r1", {"streams": "scan"}, timeout=10)
        assert messages == [("r1", "scan", b"new0"), ("r1", "scan", b"new1"), ("r1", "scan", b"new2")]
        posing = f"a reply on pg/r1/history/scan says it comes from process {str(new.info.zid())!r} but came from "
        assert problems == [posing + f"{old.info.zid()} (a peer posing as a history); not taken"]
        poser.undeclare()
        real.undeclare()
