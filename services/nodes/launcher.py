"""`posegrid run`: starts the router, the mapper shards, the HTTP API, the SLAM node (when the input has no
poses) and the source as child processes, shows progress, exports the map when asked, and stops every
child cleanly.

Children run in their own process group, so the launcher alone decides when they stop: on Ctrl-C
(SIGINT) or SIGTERM it sends SIGTERM to the source, then to the SLAM node, the API and the shards together,
then to the router, waits for each (SIGKILL after a grace period) and reports every exit code. Each child also
watches the launcher (services.process.PARENT_PID_ENV) and stops if the launcher dies.

A child that ends while the run goes on (any exit or signal; the source: a non-zero exit or a signal, since
one that ends 0 has finished its replay) is started again with the same arguments after a backoff
(:class:`RestartPolicy`), and takes what it missed from the histories (docs/keys.md). A restarted source
replays its input from the start: every input of `posegrid run` is a file or the seeded simulation, so it
publishes the very messages it published before, which the shards drop as `resent` and the SLAM node as
out of order. A child that fails more often than the policy allows stops the run.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import zenoh
from tqdm import tqdm

from mapping.grid import RasterTooLarge
from schemas.files import MapFile, save_map
from schemas.messages import MessageError, NodeStats, decode_message
from services import keys
from services.api.guard import TOKEN_ENV
from services.errors import USAGE_EXIT
from services.map_client import IncompleteMap, MapReader
from services.ports import free_port
from services.process import PARENT_PID_ENV, Stopped, WarnOnce, get_logger, until_stopped
from services.security import Role, remove_material, run_material, zenoh_argv
from services.state.store.run import RunState
from services.zenoh_config import build_config, close_session, open_session, replier

#: seconds a child gets to stop after SIGTERM before it is killed
STOP_GRACE = 15.0
#: exit codes of a child that stopped as asked: 0, 130 (a SIGINT before it had set up its handlers), -15 (the
#: launcher's SIGTERM before that: the default action ends it at once, with nothing of its own begun, or a
#: store's last commit kept as after a crash). The launcher stops its children with SIGTERM, not SIGINT: a
#: child still starting would turn a SIGINT into a KeyboardInterrupt inside an import (numpy's gives an
#: ImportError and a traceback) or inside the interpreter's own start-up (a fatal error, exit 1)
CLEAN_EXITS = (0, 130, -signal.SIGTERM)
#: seconds the launcher waits for the shards to come up (their kernels already compiled: _load_fusion_kernels)
START_TIMEOUT = 60.0
#: seconds into loading the fusion kernels after which the launcher says it is compiling them
COMPILE_NOTE_AFTER = 2.0
#: seconds the launcher waits for the SLAM node's stats when it says why the shards gave up on scans
NODE_STATS_TIMEOUT = 5.0


@dataclass(frozen=True)
class RestartPolicy:
    """When `posegrid run` starts a child again that ended while the run went on.

    The restart of a child that has had n restarts in the last ``window`` s waits ``first_delay`` * 2**n s, at
    most ``max_delay`` s (0.5, 1, 2, 4, 8 s by default); a child that fails once more after ``max_restarts``
    restarts within ``window`` s stops the run (at most 5 restarts within 60 s by default)."""

    max_restarts: int = 5  # restarts of one child within ``window``
    window: float = 60.0  # s
    first_delay: float = 0.5  # s
    max_delay: float = 10.0  # s

    def recent(self, restarts: Sequence[float], now: float) -> int:
        """How many of the restart times ``restarts`` (s) lie within ``window`` s before ``now`` (s, same clock)."""
        return sum(1 for t in restarts if now - t < self.window)

    def delay(self, restarts: Sequence[float], now: float) -> float | None:
        """Seconds to wait before restarting a child that failed at ``now`` (s) and was restarted before at the
        times ``restarts`` (s, the same clock); None when it may not be restarted again."""
        recent = self.recent(restarts, now)
        if recent >= self.max_restarts:
            return None
        return min(self.first_delay * 2.0 ** min(recent, 64), self.max_delay)


def describe_exit(code: int) -> str:
    """ "exited 1", or for a child ended by a signal "exited -9 (SIGKILL)" (Popen's code: minus the signal)."""
    if code < 0:
        try:
            return f"exited {code} ({signal.Signals(-code).name})"
        except ValueError:
            return f"exited {code} (signal {-code})"
    return f"exited {code}"


def _say(line: str) -> None:
    """One line on stderr, above the progress bar if one is showing."""
    tqdm.write(line, file=sys.stderr)
    sys.stderr.flush()


def spawn_service(argv: list[str]) -> subprocess.Popen:
    """``python -m services ARGV`` in a session of its own, told the launcher's pid (PARENT_PID_ENV)."""
    env = {**os.environ, PARENT_PID_ENV: str(os.getpid())}
    return subprocess.Popen([sys.executable, "-m", "services", *argv], env=env, start_new_session=True)


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    expected_to_finish: bool = False  # the source ends on its own when the replay is over
    argv: list[str] = field(default_factory=list)  # its `posegrid` arguments, to start it again with
    restarts: list[float] = field(default_factory=list)  # clock times of the failures it was restarted after, s
    failures: int = 0  # times it ended while it should have kept running
    restart_at: float | None = None  # clock time its pending restart is due, s (None: none pending)

    def ended_badly(self) -> bool:
        """Whether it has ended when it should not have (any non-zero exit, or a server that ended)."""
        code = self.process.poll()
        return code is not None and (code != 0 or not self.expected_to_finish)


class Children:
    """The launcher's child processes, started in order and stopped in reverse; :meth:`tend` restarts the ones
    that end under ``policy``. ``clock`` (s) and ``spawn`` (argv -> Popen) are for tests."""

    def __init__(
        self,
        log,
        policy: RestartPolicy | None = None,
        clock: Callable[[], float] = time.monotonic,
        spawn: Callable[[list[str]], subprocess.Popen] = spawn_service,
    ):
        self.log = log
        self.policy = policy or RestartPolicy()
        self.clock = clock
        self.spawn = spawn
        self.children: list[Child] = []
        self.last_start = clock()  # clock time of the latest start or restart, s
        self.killed: set[str] = set()  # the children killed at the stop, after STOP_GRACE

    def start(self, name: str, argv: list[str], expected_to_finish: bool = False) -> Child:
        child = Child(name, self.spawn(argv), expected_to_finish, argv=list(argv))
        self.children.append(child)
        self.last_start = self.clock()
        return child

    def failed(self) -> Child | None:
        """A child that ended when it should not have (any non-zero exit, or a server that ended)."""
        return next((child for child in self.children if child.ended_badly()), None)

    def running_to_finish(self) -> bool:
        """Whether a child that ends on its own (the source) is still running, or is to be restarted."""
        return any(
            c.expected_to_finish and (c.process.poll() is None or c.restart_at is not None) for c in self.children
        )

    def tend(self) -> Child | None:
        """Restart the children whose backoff is over, and schedule a restart for each that has just ended badly,
        one line each on stderr. Returns a child that failed past the policy's cap (having said so on stderr):
        the run must stop. Call it every fraction of a second."""
        now = self.clock()
        for child in self.children:
            if child.restart_at is not None:
                if now >= child.restart_at:
                    self._restart(child)
            elif child.ended_badly() and not self._schedule(child, now):
                return child
        return None

    def _schedule(self, child: Child, now: float) -> bool:
        """Note a failure of ``child`` at ``now`` and plan its restart; False when the policy allows none."""
        child.failures += 1
        code = child.process.returncode
        if code == USAGE_EXIT:  # its input or options are wrong: it would fail the same way again
            _say(
                f"posegrid run: error: {child.name} (pid {child.process.pid}) {describe_exit(code)}: its input or "
                "options were refused (its own error line above says why); not restarting it: stopping the run"
            )
            return False
        delay = self.policy.delay(child.restarts, now)
        if delay is None:
            times = "time" if child.failures == 1 else "times"
            _say(
                f"posegrid run: error: {child.name} failed {child.failures} {times}; the last time (pid "
                f"{child.process.pid}) it {describe_exit(code)}; it had {self.policy.recent(child.restarts, now)} "
                f"restart(s) in the last {self.policy.window:g} s, the most --max-restarts allows: stopping the run"
            )
            return False
        child.restarts.append(now)
        child.restart_at = now + delay
        _say(
            f"posegrid run: {child.name} (pid {child.process.pid}) {describe_exit(code)}; restarting in {delay:g} s "
            f"(restart {self.policy.recent(child.restarts, now)} of {self.policy.max_restarts} within "
            f"{self.policy.window:g} s)"
        )
        return True

    def _restart(self, child: Child) -> None:
        child.restart_at = None
        child.process = self.spawn(child.argv)
        self.last_start = self.clock()
        _say(f"posegrid run: {child.name} restarted (pid {child.process.pid})")

    def stop_all(self) -> dict[str, int]:
        """SIGTERM every running child and wait; the router last, so the others can still say goodbye.
        Returns every child's exit code, in start order."""
        others = [c for c in self.children if c.name != "router"]
        self._stop([c for c in others if c.expected_to_finish])
        self._stop([c for c in others if not c.expected_to_finish])
        self._stop([c for c in self.children if c.name == "router"])
        return {child.name: child.process.returncode for child in self.children}

    def _stop(self, group: list[Child]) -> None:
        for child in group:
            if child.process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    child.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE
        for child in group:
            try:
                child.process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.log.warning(
                    "%s (pid %d) did not stop within %.0f s; killing it", child.name, child.process.pid, STOP_GRACE
                )
                child.process.kill()
                child.process.wait()
                self.killed.add(child.name)

    def stopped_badly(self) -> list[str]:
        """The children that did not end as asked, after :meth:`stop_all`: an exit code outside CLEAN_EXITS, but not
        the router's kill after the grace (it holds no state: with every other child stopped, its end loses
        nothing; the kill is said on stderr)."""
        return [
            child.name
            for child in self.children
            if child.process.returncode not in CLEAN_EXITS and not (child.name == "router" and "router" in self.killed)
        ]


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
    api_argv: list[str] = field(default_factory=list)  # the API's HTTP options (services.commands.api)
    description: str = ""
    restart: RestartPolicy = field(default_factory=RestartPolicy)  # when a child that ends is started again
    secure: bool = False  # TLS, client certificates, passwords and ACL per role (services.security)
    state: RunState | None = None  # the run's state directory and session (None: the map lives in memory only)
    source_command: str = "source"  # the child feeding the robot's streams: `source` (a replay), or `ros2` (live)
    router_argv: list[str] = field(default_factory=list)  # more router options (`run --ros2 --ros2-connect`)


def _describe_exit(codes: dict[str, int]) -> str:
    return ", ".join(f"{name} exited {code}" for name, code in codes.items())


def run_pipeline(plan: Plan, stop: threading.Event) -> int:
    """Run the pipeline of ``plan`` until the export is written or ``stop`` is set; returns the exit code."""
    log = get_logger("run")
    port = plan.router_port or free_port()
    endpoint = f"{'tls' if plan.secure else 'tcp'}/127.0.0.1:{port}"
    material = run_material(plan.robot, plan.map_name, endpoint) if plan.secure else None
    if material is not None:
        try:
            print(
                f"posegrid run: secure: TLS, passwords and ACL; CA {material.ca}; a read-only client connects with "
                f"--zenoh-config {material.config_for(Role('api'))} (removed when the run ends)",
                flush=True,
            )
        except BaseException:  # (stdout a full disk or a closed pipe: the keys go before the error does)
            remove_material(material)
            raise

    def role_zenoh(kind: str, scope: str | None = None) -> list[str]:
        """A child's --connect, and with --secure the config of its role."""
        return ["--connect", endpoint, *zenoh_argv(material, Role(kind, scope))]

    children = Children(log, plan.restart)
    code = 1
    try:
        children.start("router", ["router", "--listen", endpoint, *plan.router_argv, *zenoh_argv(material, None)])
        if not _load_fusion_kernels(stop):  # (while the router starts)
            return 130
        for shard in range(plan.shards):  # they keep trying to reach the router while it starts
            children.start(
                f"mapper[{shard}]",
                [
                    "mapper",
                    "--shard",
                    str(shard),
                    "--shards",
                    str(plan.shards),
                    "--map",
                    plan.map_name,
                    *plan.mapper_argv,
                    *([] if plan.state is None else plan.state.shard_argv(shard)),
                    *role_zenoh("mapper", plan.map_name),
                ],
            )
        if plan.api_port is not None:  # the API learns the shards from their liveliness: start it alongside
            children.start(
                "api", ["api", "--host", "127.0.0.1", "--port", str(plan.api_port), *plan.api_argv, *role_zenoh("api")]
            )
        launcher_config = material.config_for(Role("launcher")) if material is not None else None
        session = open_session(build_config("client", connect=[endpoint], config_file=launcher_config), "the launcher")
        try:
            if not _wait_for_shards(session, plan, children, stop):
                return 130 if stop.is_set() else 1
            if plan.slam_argv is not None:
                children.start(
                    "slam-node", ["slam-node", "--robot", plan.robot, *plan.slam_argv, *role_zenoh("slam", plan.robot)]
                )
            children.start(
                plan.source_command,
                [
                    plan.source_command,
                    "--robot",
                    plan.robot,
                    "--map",
                    plan.map_name,
                    "--wait-mappers",
                    str(plan.shards),
                    *(["--wait-slam"] if plan.slam_argv is not None else []),
                    *plan.source_argv,
                    *role_zenoh("source", plan.robot),
                ],
                expected_to_finish=plan.source_command == "source",  # (the ROS 2 bridge runs until Ctrl-C)
            )
            _banner(plan, endpoint, children)
            code = _supervise(session, plan, children, stop, log)
        finally:
            close_session(session, "the launcher")
    finally:
        codes = children.stop_all()
        remove_material(material)
        print(f"posegrid run: stopped: {_describe_exit(codes)}", flush=True)
        if code == 0 and children.stopped_badly():
            code = 1
    return code


def _load_fusion_kernels(stop: threading.Event) -> bool:
    """Load the shards' compiled fusion kernels in this process before any shard starts, compiling them where the
    cache lacks them (the first start after an install or an edit: a minute or more on a slow machine, which the
    shards would otherwise spend past START_TIMEOUT); the shards then load them from the cache. Says so when it
    takes longer than COMPILE_NOTE_AFTER s. False when ``stop`` is set first: the compile cannot be interrupted and
    is left to end with the process (services.process.until_stopped; numba writes a cache entry whole or not at
    all), so Ctrl-C during it stops the run at once."""
    from mapping.grid import TILE_SIZE
    from mapping.sensor_model import SensorModel
    from services.state.shard import warm_fusion

    note = threading.Timer(
        COMPILE_NOTE_AFTER,
        lambda: print(
            "posegrid run: compiling the fusion kernels (once after an install or an edit; a minute or two)", flush=True
        ),
    )
    note.daemon = True
    started = time.monotonic()
    note.start()
    try:
        until_stopped(lambda: warm_fusion(SensorModel(), TILE_SIZE), stop, "compiling the fusion kernels")
    except Stopped:
        return False
    finally:
        note.cancel()
    took = time.monotonic() - started
    if took > COMPILE_NOTE_AFTER:
        print(f"posegrid run: fusion kernels ready in {took:.0f} s; later starts load them at once", flush=True)
    return True


def _wait_for_shards(session, plan: Plan, children: Children, stop: threading.Event) -> bool:
    """Wait until every shard's liveliness token is up, restarting children that end (:meth:`Children.tend`).
    False when ``stop`` is set, a child fails past the restart cap, or START_TIMEOUT s pass after the latest
    start or restart of a child without every shard up."""
    shards = MapReader(session, plan.map_name)
    while not stop.is_set():
        alive = shards.shards_up(plan.shards)
        if alive >= plan.shards:
            return True
        if children.tend() is not None:
            print(f"posegrid run: error: the {plan.shards} mapper shard(s) did not start", file=sys.stderr)
            return False
        if children.clock() > children.last_start + START_TIMEOUT:
            print(
                f"posegrid run: error: the {plan.shards} mapper shard(s) did not start (only {alive} came up in "
                f"{START_TIMEOUT:.0f} s)",
                file=sys.stderr,
            )
            return False
        stop.wait(0.1)
    return False


def _banner(plan: Plan, endpoint: str, children: Children) -> None:
    lines = [
        f"posegrid run: {plan.description}",
        f"  zenoh router: {endpoint}  (connect with --connect {endpoint})",
        (
            f"  map {plan.map_name!r}: tiles on {keys.tile_key(plan.map_name, 0, '*', '*')}, "
            f"stats on {keys.stats_key(plan.map_name, '*')}"
        ),
        (
            f"  HTTP API and map viewer: http://127.0.0.1:{plan.api_port}/  (OpenAPI: /openapi.json)"
            + (
                "; it wants the access token: open /?token=TOKEN once, or send 'Authorization: Bearer TOKEN'"
                if os.environ.get(TOKEN_ENV)
                else ""
            )
            if plan.api_port is not None
            else "  HTTP API: not started (--no-api)"
        ),
        "  state: " + ("in memory only (--no-state)" if plan.state is None else plan.state.describe()),
        *_resume_lines(plan),
        "  running: " + ", ".join(f"{c.name} (pid {c.process.pid})" for c in children.children),
        "  Ctrl-C stops everything",
    ]
    print("\n".join(lines), flush=True)


def _resume_lines(plan: Plan) -> list[str]:
    """The banner's commands that go on from the run's state (none without one): a plain --resume adds new input
    as a new session, so a replay that stopped before its end goes on with --continue-session (a plain --resume after
    a crash fused its scans a second time)."""
    if plan.state is None:
        return []
    resume = f"posegrid run --resume {shlex.quote(str(plan.state.directory))}"
    lines = [f"  add new input to this map later with: {resume}"]
    if plan.scans is not None:
        lines.append(f"  if this replay stops before its end, go on with it with: {resume} --continue-session")
    return lines


def _supervise(session, plan: Plan, children: Children, stop: threading.Event, log) -> int:
    """Show progress until every shard has all scans; then export (and return) or serve until stopped. Restarts
    the children that end meanwhile (:meth:`Children.tend`); returns 1 when one fails past the restart cap."""
    reader = MapReader(session, plan.map_name)
    warn_once = WarnOnce(log)  # (the problems with the shards' stats, said once)
    finished = False
    fused = 0  # scans every shard has fused (kept here: a bar that does not show, with no terminal, counts none)
    with tqdm(
        total=plan.scans, desc="fused (slowest shard)", unit="scan", file=sys.stderr, disable=None, mininterval=0.5
    ) as bar:
        while not stop.wait(0.25):
            if children.tend() is not None:  # (it said which child, and why)
                if not finished and plan.scans is not None:
                    _say_unfinished(plan, fused)
                return 1
            if finished:
                continue
            answers = reader.answers(timeout=2.0)
            for problem in answers.problems:
                warn_once(f"not trusting the shards' stats (waiting until they agree): {problem}")
            stats = answers.trusted
            if len(stats) < plan.shards:
                continue
            done = min(s.fused.get(plan.robot, 0) for s in stats.values())
            bar.update(done - fused)
            fused = done
            ended = [s.ended.get(plan.robot) for s in stats.values()]
            if (
                children.running_to_finish()
                or None in ended
                or any(s.fused.get(plan.robot, 0) + s.discarded.get(plan.robot, 0) < ended[0] for s in stats.values())
            ):
                continue
            finished = True
            bar.close()
            discarded = max(s.discarded.get(plan.robot, 0) for s in stats.values())
            print(
                f"posegrid run: replay finished: {ended[0]} scans, each of {plan.shards} shard(s) fused "
                f"{min(s.fused.get(plan.robot, 0) for s in stats.values())}"
                + (f", gave up on up to {discarded}" if discarded else ""),
                flush=True,
            )
            clashes = max(s.refused.get("duplicate", 0) for s in stats.values())
            if clashes:
                print(clash_message(clashes, plan), file=sys.stderr, flush=True)
            refused = max(s.rejected.get(f"fuse/{plan.robot}", 0) for s in stats.values())
            why = _given_up_because(session, plan, discarded, refused) if discarded else ""
            if plan.export is not None:
                rc = _export(reader, plan, discarded, why)
                return 1 if clashes else rc
            if discarded:
                print(f"posegrid run: the map misses up to {discarded} scans the shards gave up on: {why}", flush=True)
            print("posegrid run: serving the finished map until Ctrl-C", flush=True)
    if finished:
        return 0
    if plan.scans is None:  # a live robot (run --ros2): no replay to end, nothing to go on with but a new session
        print(f"posegrid run: stopped after {fused} scans fused by every shard", file=sys.stderr, flush=True)
        return 0
    _say_unfinished(plan, fused)
    # (--export exited 0 without the file: `run --export m.npz && use m.npz` went on with no map)
    return 130 if plan.export is not None else 0


def _say_unfinished(plan: Plan, fused: int) -> None:
    """Say that the run stopped before its replay ended (``fused`` scans by every shard) and, when it keeps its state,
    the command that goes on with it: a plain --resume would start a new session and fuse the same scans again."""
    print(
        f"posegrid run: stopped before the replay ended ({fused} of {plan.scans} scans fused by every shard)"
        + (f": no map written to {plan.export}" if plan.export is not None else ""),
        file=sys.stderr,
        flush=True,
    )
    if plan.state is not None:
        print(
            "posegrid run: to go on with this replay of the same input: posegrid run --resume "
            f"{shlex.quote(str(plan.state.directory))} --continue-session (with the same input options; without "
            "--continue-session it is fused again, as a new session)",
            file=sys.stderr,
            flush=True,
        )


def clash_message(clashes: int, plan: Plan) -> str:
    """The error a run ends with when its shards refused ``clashes`` of its scans or poses (the most of one shard)
    because each differs from the one of the same robot and seq that they had fused: the map holds those others."""
    cause = (
        "the input is not the one this session was fused from (--continue-session goes on with an interrupted replay "
        "of the same input; leave it out to add this input to the map as a new session)"
        if plan.state is not None and plan.state.continued
        else f"another run or process publishes under robot {plan.robot!r} (give this run another --robot)"
    )
    return (
        f"posegrid run: error: the shards refused {clashes} scan(s) or pose(s) of this run that differ from the ones "
        f"of the same seq they had fused: {cause}; the map holds the others there"
    )


def _given_up_because(session: zenoh.Session, plan: Plan, discarded: int = 0, shard_refused: int = 0) -> str:
    """Why the shards gave up on ``discarded`` scans (the most of one shard): the ``shard_refused`` of them that a
    shard refused to fuse (the most of one shard: by its limits, --max-map-cells and the others, or a scan no fusion
    takes), and for the rest, as far as the run's SLAM node says, the steps it could not take (an odometry jump
    refused, a step the filter refused: they have no pose, so their scans are given up); else the poses or scans
    never came."""
    if shard_refused:
        said = f"the shards refused to fuse {shard_refused} of them (a limit, or a scan no fusion takes: the lines "
        said += "above say why)"
        return said if shard_refused >= discarded else f"{said}; for the others, {_given_up_because(session, plan)}"
    lost = "their poses or scans never came (lost in transit, or refused: the lines above say why)"
    if plan.slam_argv is None:
        return lost
    refused: dict[str, int] = {}  # answering process -> the steps it refused
    for reply in session.get(
        keys.slam_stats_key(plan.robot),
        target=zenoh.QueryTarget.ALL,  # (every answerer, as the source asks: one alone could be a peer)
        consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
        timeout=NODE_STATS_TIMEOUT,
    ):
        if reply.ok is not None:
            try:
                stats = decode_message(reply.ok.payload.to_bytes(), NodeStats)
            except MessageError:
                continue
            refused[replier(reply)] = stats.rejected.get(keys.robot_key(plan.robot, "steps"), 0)
    if len(refused) > 1:  # (a peer answering as the node: its counts are no cause to give)
        return f"{lost}; {len(refused)} processes answer as the SLAM node of robot {plan.robot!r} (docs/security.md)"
    if not sum(refused.values()):
        return lost
    (refused_steps,) = refused.values()
    return (
        f"the SLAM node could not take {refused_steps} step(s) and gave no pose for them (its lines above say why: an "
        "odometry jump it refused, or a step its filter refused)"
    )


def _export(reader: MapReader, plan: Plan, discarded: int, why: str) -> int:
    """Write the map assembled from every shard to ``plan.export`` (schemas.files.save_map: a temporary file,
    fsynced, renamed onto the path); 1 with one line on stderr when the map is incomplete or empty or the write
    fails (nothing is written then), else 0 unless the shards gave up on scans (``why``: why they did,
    :func:`_given_up_because`)."""
    assert plan.export is not None  # called only for a plan with an export path
    try:
        grid = reader.assemble(plan.shards, plan.resolution)
    except IncompleteMap as exc:
        print(f"posegrid run: error: cannot export the map: {exc}", file=sys.stderr)
        return 1
    try:
        raster = grid.rasterize()
    except RasterTooLarge as exc:
        print(
            f"posegrid run: error: cannot export the map: {exc}; nothing written to {plan.export}. The shards hold "
            "it: leave out --export and take windows of it from the HTTP API (GET /maps/MAP/export?x_min=...), "
            "or run again with a coarser --resolution",
            file=sys.stderr,
        )
        return 1
    if not raster["observed"].any():
        empty = (
            f"the shards gave up on {discarded} scan(s): {why}"
            if discarded
            else "no scan had a usable beam, so no cell was observed"
        )
        print(f"posegrid run: error: the map is empty ({empty}); nothing written to {plan.export}", file=sys.stderr)
        return 1
    try:
        map_file = MapFile.from_raster(raster)
        save_map(plan.export, map_file)
    except OSError as exc:
        print(f"posegrid run: error: cannot write {plan.export}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    height, width = raster["logodds"].shape
    print(
        f"posegrid run: wrote {plan.export}: {width} x {height} cells at {plan.resolution} m, "
        f"{int(raster['observed'].sum())} observed, from {len(grid.keys())} tiles of {plan.shards} shard(s)",
        flush=True,
    )
    if discarded:
        print(
            f"posegrid run: error: the map misses up to {discarded} scans the shards gave up on: {why}", file=sys.stderr
        )
        return 1
    return 0
