"""`posegrid source`: publishes one robot's run (services.streams) over Zenoh at a chosen rate.

Rate: a factor of real time (1 = as recorded, 2 = twice as fast) or "max": as fast as the subscribers
take it. In "max" mode the source never runs more than ``window`` scans ahead of the slowest mapper shard
it waits for, nor ``window`` steps ahead of the SLAM node it waits for (it reads their progress from their
stats queryables), so no buffer downstream overflows; every message goes out reliably with congestion
control BLOCK.

Before the first message the source waits for the liveliness tokens of ``wait_mappers`` mapper shards (and
of the robot's SLAM node with ``wait_slam``), so nothing is published before its subscribers are up. After
the last step it publishes a StreamEnd with the number of scans, and, when it waited for mappers, waits
until every shard has acknowledged that end in its stats, publishing it again every END_REPEAT s meanwhile.

While it runs, the source answers queries on pg/<robot>/history/<stream> with what it has published so far
(:meth:`Source.history`), so a SLAM node that starts late or restarts can take the run from its start.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Collection
from dataclasses import dataclass
from typing import NamedTuple

import zenoh

from schemas.messages import LaserScan, MessageError, NodeStats, ShardStats, StreamEnd, decode_message
from services import history, keys
from services.map_client import MapReader
from services.process import OTHER_KEYS, RejectCounter, WarnOnce, get_logger
from services.streams import Stream
from services.zenoh_config import replier, undeclare_all

#: the replay logs its progress this many times (at every tenth of its steps)
PROGRESS_PARTS = 10
#: how long the source waits for subscribers to appear, or for a stalled mapper to make progress, s
WAIT_TIMEOUT = 60.0
#: s between two publications of the end of the stream while a shard has not acknowledged it
END_REPEAT = 1.0
#: s a source that published while no router was reachable (those messages went nowhere) waits, at its end, for the
#: shards that answer to make progress on the scans before it exits anyway (:meth:`Source._linger`)
LINGER = 30.0
#: s between two looks at whether the session reaches a router, while publishing
REACH_CHECK = 0.1


#: s a shard's uptime in its stats may lag (its snapshot is at most 0.2 s old, the query takes its time): a shard
#: whose uptime is shorter than its uptime at the run's start plus the time since, by more than this, restarted
UPTIME_SLACK = 2.0

#: s a shard's commits must have been failing (since its last commit, else since it started) before a source stops
#: waiting for them: five retries at the default --commit-interval of 2 s
FAILING_GRACE = 10.0

#: the longest pause between two steps a replay at a factor of real time keeps, s of the stamps: a longer gap (a log
#: that paused, or stamps that jump: 1e6 s slept 11 days without a word, 1e300 s ended the source with a traceback, a
#: wait past the platform's time_t) is cut to it, and said
MAX_STEP_GAP = 10.0


def replay_offsets(stamps: list[float], rate: float) -> tuple[list[float], list[str]]:
    """When each step of a replay at ``rate`` x real time goes out, s after the first, from the steps' ``stamps``
    (s): each gap from the step before over the rate, a gap past MAX_STEP_GAP cut to it, and one that goes back
    (stamps out of order) taken as 0, so that step goes out at once. Also the notes to say (the first gap of each
    kind, with its steps)."""
    offsets: list[float] = []
    back = jump = ""  # (the first of each kind)
    due = 0.0
    for index, stamp in enumerate(stamps):
        gap = stamp - stamps[index - 1] if index else 0.0
        if gap < 0 and not back:
            back = (
                f"stamps go back {-gap:.6g} s from step {index - 1} to {index}: steps whose stamps go back are "
                "published at once, without pacing"
            )
        if gap > MAX_STEP_GAP and not jump:
            jump = (
                f"stamps jump {gap:.6g} s from step {index - 1} to {index}: pauses longer than {MAX_STEP_GAP:g} s "
                f"are replayed as {MAX_STEP_GAP:g} s"
            )
        due += min(max(gap, 0.0), MAX_STEP_GAP) / rate
        offsets.append(due)
    return offsets, [note for note in (back, jump) if note]


def stall_message(shards: tuple[int, int] | None, slam: tuple[int, int] | None, distrust: str | None) -> str:
    """Why a source gave up: what the subscribers it waits for took ((done, sent) of the shards' scans and of the SLAM
    node's steps; None: not waited for), and why the shards' stats were not believed, if they were not (a count of
    0 then says nothing of what the shards fused)."""
    parts = [f"shards: {shards[0]} of {shards[1]} scans"] if shards is not None else []
    parts += [f"SLAM node: {slam[0]} of {slam[1]} steps"] if slam is not None else []
    why = f"; the shards' stats were not trusted, so their progress was not counted: {distrust}" if distrust else ""
    return f"the subscribers took nothing for {WAIT_TIMEOUT:.0f} s ({', '.join(parts)}){why}"


class SourceStalled(RuntimeError):
    """The subscribers the source waits for did not appear, or stopped making progress."""


@dataclass(frozen=True)
class SourceOptions:
    """rate: factor of real time, or None for "as fast as the subscribers take"; window: scans the source
    may run ahead of the slowest mapper in that mode; map_name: the map whose shards it waits for."""

    rate: float | None = 1.0
    wait_mappers: int = 0
    map_name: str = "main"
    wait_slam: bool = False
    window: int = 32


#: the factors of real time a source may replay at: 1e-3 (a step of 0.1 s every 100 s) to 1e6 (beyond it, 'max');
#: a factor of 1e-308 made a wait past the platform's time_t, a traceback
RATE_RANGE = (1e-3, 1e6)


def parse_rate(text: str) -> float | None:
    """ "max" -> None (as fast as subscribers take), "realtime" -> 1.0, a number in RATE_RANGE -> that factor."""
    if text == "max":
        return None
    if text == "realtime":
        return 1.0
    try:
        factor = float(text)
    except ValueError:
        factor = math.nan
    low, high = RATE_RANGE
    if not low <= factor <= high:
        raise ValueError(
            f"rate must be 'max', 'realtime' or a factor of real time in [{low:g}, {high:g}], got {text!r}"
        )
    return factor


class Source:
    """Publishes a :class:`Stream` on an open session. Use :meth:`run`."""

    def __init__(self, session: zenoh.Session, stream: Stream, options: SourceOptions):
        self.session = session
        self.stream = stream
        self.options = options
        self.log = get_logger(f"source[{stream.robot}]")
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._scans_done = 0  # scans of this run every waited-for shard has dealt with (:func:`scans_taken`)
        self._steps_done = 0  # steps the SLAM node has taken or given up on
        self._reader = MapReader(session, options.map_name)
        self._warn_once = WarnOnce(self.log)  # (the shards' and the SLAM node's stats' problems, said once)
        self.rejects = RejectCounter(self.log)  # the history queries refused (logged once a kind)
        self._distrust: str | None = None  # why the shards' last stats were not trusted (None: they were)
        self._end_sent = 0.0  # time.monotonic() of the last StreamEnd published
        self._warned_beyond = False  # whether a shard holding more scans than this run published was reported
        # (the end's progress, :meth:`_end_progress`: the shards' counts as last read, the SLAM node's steps done)
        self._end_counts: tuple = ()
        self._slam_asked, self._slam_seen = -math.inf, 0
        self._clashes_before: dict[int, tuple[int, int]] = {}  # shard -> its clash counts (_clash_counts) at the start
        self._before: dict[int, ShardBaseline] = {}  # shard -> what it had taken of this robot at the start
        self._started = 0.0  # time.monotonic() when those were read
        self._unreached = 0  # steps published while the session reached no router (they went nowhere)
        self._reach_seen = (-1.0, True)  # (time.monotonic() of the last look, whether it reached a router then)
        self._prior_out = False  # whether the prior is out (what the history may answer with, with ...)
        self._steps_published = 0  # ... the steps whose messages are all out
        self._end_out = False  # whether the end of the stream is out
        self._history_lock = threading.Lock()

    def _publisher(self, stream: str) -> zenoh.Publisher:
        if stream not in self._publishers:
            self._publishers[stream] = self.session.declare_publisher(
                keys.robot_key(self.stream.robot, stream), congestion_control=zenoh.CongestionControl.BLOCK
            )
        return self._publishers[stream]

    def _report_progress(self, published: int, total: int) -> None:
        """Log how far the replay is, at every tenth of its steps (a long replay shows it is moving)."""
        if published < total and published * PROGRESS_PARTS // total > (published - 1) * PROGRESS_PARTS // total:
            self.log.info("published %d of %d steps", published, total)

    def _publish(self, message, stream: str | None = None) -> None:
        self._publisher(stream or keys.STREAM_OF[type(message)]).put(message.encode())

    # ------------------------------------------------------------------------------- history
    def history(
        self, streams: set[str], first: int, stop: int | None = None, seqs: Collection[int] | None = None
    ) -> list[tuple[str, bytes]]:
        """(stream, encoded message) of what was published on ``streams`` (key chunks; PRIOR for the prior), in
        the order it went out: the prior, then the messages of steps ``first`` .. ``stop`` - 1 (default: up to
        the last step published), of them only ``seqs`` when given."""
        with self._history_lock:
            prior_out, published = self._prior_out, self._steps_published
        out = []
        if keys.PRIOR in streams and prior_out:
            assert self.stream.prior is not None  # it is out only when there is one
            out.append((keys.PRIOR, self.stream.prior.encode()))
        end = published if stop is None else min(stop, published)
        for seq in range(first, end) if seqs is None else sorted(q for q in seqs if first <= q < end):
            messages = self.stream.steps[seq].messages
            out += [(keys.STREAM_OF[type(m)], m.encode()) for m in messages if keys.STREAM_OF[type(m)] in streams]
        return out

    def _on_history_query(self, query: zenoh.Query) -> None:
        """pg/<robot>/history/** (services.history): the prior and the messages of the steps asked for."""
        request = history.parse_request(query, self.stream.robot, self.rejects)
        if request is None:
            return
        with self._history_lock:
            ended = self._end_out
        answerer = history.Answerer(str(self.session.info.zid()), self.options.map_name, ended)
        for stream, payload in self.history(set(request.streams), request.first, request.stop, request.seqs):
            history.reply(query, answerer, self.stream.robot, stream, payload)

    # ------------------------------------------------------------------------------- waiting
    def _shard_stats(self) -> list[ShardStats]:
        """The stats of the map's shards, none while they cannot be trusted (services.map_client.sort_answers:
        the source then waits, as for shards that do not answer, and says why once)."""
        answers = self._reader.answers()
        for problem in answers.problems:
            self._warn_once(f"not trusting the shards' stats: {problem}")
        self._distrust = answers.problems[0] if answers.problems else None
        return list(answers.trusted.values())

    def _wait_for(self, what: str, ready, stop: threading.Event, progress=None) -> bool:
        """Poll ``ready()`` until it is true (returns True) or ``stop`` is set (False); raise after WAIT_TIMEOUT, or,
        given ``progress`` (a callable whose value changes while the subscribers make progress), after WAIT_TIMEOUT
        without progress: a shard or SLAM node working through a backlog past the end of a replay is waited for (the
        source gave up 60 s after its end while the SLAM node was still taking steps from its history, exit 1; its
        restart answered no history while it simulated, and the node skipped 859 steps)."""
        deadline = time.monotonic() + WAIT_TIMEOUT
        seen = None if progress is None else progress()
        while not ready():
            if stop.wait(0.05):
                return False
            now = progress() if progress is not None else None
            if now != seen:
                seen, deadline = now, time.monotonic() + WAIT_TIMEOUT
            if time.monotonic() > deadline:
                raise SourceStalled(
                    f"gave up after {WAIT_TIMEOUT:.0f} s "
                    + ("without progress " if progress is not None else "")
                    + f"waiting for {what}"
                )
        return True

    def _end_progress(self) -> tuple:
        """What changes while the pipeline works through the end of a replay: each waited-for shard's scans of the
        robot fused, given up and committed (as the last stats read said: :meth:`_ended_everywhere`), and the SLAM
        node's steps done (asked at most every END_REPEAT s)."""
        if self.options.wait_slam and time.monotonic() - self._slam_asked >= END_REPEAT:
            self._slam_asked = time.monotonic()
            self._slam_seen = self._slam_done()
        return self._end_counts, self._slam_seen

    def _tokens(self, key: str) -> int:
        return sum(reply.ok is not None for reply in self.session.liveliness().get(key, timeout=2.0))

    def _wait_for_subscribers(self, stop: threading.Event) -> bool:
        opts = self.options
        if opts.wait_mappers and not self._wait_for(
            f"{opts.wait_mappers} mapper shard(s) of map {opts.map_name!r}",
            lambda: len(self._reader.tokens(timeout=2.0)) >= opts.wait_mappers,
            stop,
        ):
            return False
        if opts.wait_slam and not self._wait_for(
            f"the SLAM node of robot {self.stream.robot!r}",
            lambda: self._tokens(keys.robot_alive_key(self.stream.robot, "slam")) >= 1,
            stop,
        ):
            return False
        if opts.wait_mappers and self.stream.scans:
            scans = self._publisher(keys.SCAN)
            return self._wait_for("a subscriber of the scans", lambda: scans.matching_status, stop)
        return True

    def _shards_done(self) -> int:
        """Scans of this run the slowest of the waited-for shards has dealt with (:func:`scans_taken`)."""
        stats = self._shard_stats()
        if len(stats) < self.options.wait_mappers:
            return self._scans_done
        return scans_taken(stats, self.stream.robot, self._before, time.monotonic() - self._started)

    def _slam_done(self) -> int:
        """Steps the robot's SLAM node has taken or given up on. Every answer is asked for and known by its sender
        (services.map_client.replier): when two processes answer as the node, the source says so once and goes on
        as if the node were done, waiting for the shards alone (they cannot fuse a scan before the node's pose
        for it), rather than take a peer's "0 steps" (it stalled a run at 32 of 400 scans) or its "all"."""
        done: dict[str, int] = {}
        for reply in self.session.get(
            keys.slam_stats_key(self.stream.robot),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE),
            timeout=5.0,
        ):
            if reply.ok is not None:
                try:
                    done[replier(reply)] = decode_message(reply.ok.payload.to_bytes(), NodeStats).steps_done
                except MessageError as exc:
                    self.log.warning("ignored a bad SLAM node stats reply: %s", exc)
        if len(done) > 1:
            robot = self.stream.robot
            self._warn_once(
                f"not waiting for the SLAM node: {len(done)} processes answer as the SLAM node of robot {robot!r} "
                "(docs/security.md)"
            )
            return self._steps_published  # (as if done: the shards hold the source back)
        return next(iter(done.values()), self._steps_done)

    def _backlog(self, scans_sent: int, steps_sent: int) -> int:
        """The larger of the scans the shards and the steps the SLAM node still have to take."""
        backlog = 0
        if self.options.wait_mappers:
            backlog = scans_sent - self._scans_done
        if self.options.wait_slam:
            backlog = max(backlog, steps_sent - self._steps_done)
        return backlog

    def _wait_for_window(self, scans_sent: int, steps_sent: int, stop: threading.Event) -> bool:
        """With ``window`` scans (or steps) in flight, wait until the slowest subscriber has taken half of them.

        Returns False when ``stop`` is set; raises :class:`SourceStalled` after WAIT_TIMEOUT without progress.
        """
        if self._backlog(scans_sent, steps_sent) < self.options.window:
            return True
        deadline = time.monotonic() + WAIT_TIMEOUT
        while True:
            progress = (
                self._shards_done() if self.options.wait_mappers else 0,
                self._slam_done() if self.options.wait_slam else 0,
            )
            if progress[0] > self._scans_done or progress[1] > self._steps_done:
                self._scans_done = max(self._scans_done, progress[0])
                self._steps_done = max(self._steps_done, progress[1])
                deadline = time.monotonic() + WAIT_TIMEOUT
            if self._backlog(scans_sent, steps_sent) <= self.options.window // 2:
                return True
            if stop.wait(0.01):
                return False
            if time.monotonic() > deadline:
                raise SourceStalled(
                    stall_message(
                        (self._scans_done, scans_sent) if self.options.wait_mappers else None,
                        (self._steps_done, steps_sent) if self.options.wait_slam else None,
                        self._distrust,
                    )
                )

    def _ended_everywhere(self, end: StreamEnd) -> bool:
        """Whether every shard waited for knows the end of the stream and has fused or given up on every scan;
        if not, the end is published again (at most every END_REPEAT s): a shard that missed it, say while its
        Zenoh session was closed, would wait for it for ever. Until then the source answers its history."""
        stats = self._shard_stats()
        robot, scans = end.robot, end.scans
        self._end_counts = tuple(
            sorted(
                (s.shard, s.fused.get(robot, 0), s.discarded.get(robot, 0), s.committed.get(robot, 0)) for s in stats
            )
        )
        beyond = [s.shard for s in stats if s.fused.get(robot, 0) + s.discarded.get(robot, 0) > scans]
        if beyond and not self._warned_beyond:  # (the shards refuse such an end: services.state.shard)
            self._warned_beyond = True
            self.log.warning(
                "shard(s) %s of map %r hold more scans of robot %r than the %d this run published: "
                "another run under this robot name reached them, and they refuse this end; use another "
                "--robot",
                ", ".join(map(str, beyond)),
                self.options.map_name,
                robot,
                scans,
            )
        stuck = [s.shard for s in stats if commits_stuck(s)]
        if stuck:
            self._warn_once(
                f"shard(s) {', '.join(map(str, sorted(stuck)))} of map {self.options.map_name!r} cannot commit to "
                f"their state directory (persist: failing for more than {FAILING_GRACE:g} s): they serve the map "
                "from memory, and the source does not wait for those commits"
            )
        if (
            len(stats) >= self.options.wait_mappers
            and _accounted(stats, end)
            and took_end(stats, robot, self._before, time.monotonic() - self._started)
        ):
            return True  # (every scan accounted for: a shard that restarted may still ask the history)
        self._repeat_end(end)
        return False

    def _clash_counts(self, stats: list[ShardStats] | None = None) -> dict[int, tuple[int, int]]:
        """Per shard of ``stats`` (default: those answering now): (its rejections on the keys this robot's source
        publishes to the shards: its scans, and its poses when the input gives them; its duplicate rejections of any
        key). A rerun of a log with other poses under the robot's name had its scans come back as resent and every pose
        refused as a duplicate: no warning, and none of the run in the map (a probe)."""
        published = (keys.SCAN, keys.POSE) if self.stream.has_poses else (keys.SCAN,)
        ours = [keys.robot_key(self.stream.robot, stream) for stream in published]
        return {
            s.shard: (sum(s.rejected.get(key, 0) for key in ours), s.refused.get("duplicate", 0))
            for s in (self._shard_stats() if stats is None else stats)
        }

    def _clashed(self) -> list[int]:
        """The shards that refused scans on this robot's key as duplicates since the run started: scans of its seqs
        that differ from the ones they fused, another run's under this robot name (or another publisher's)."""
        now = self._clash_counts()
        return sorted(
            shard
            for shard, (rejected, duplicates) in now.items()
            if shard in self._clashes_before
            and rejected > self._clashes_before[shard][0]
            and duplicates > self._clashes_before[shard][1]
        )

    def _repeat_end(self, end: StreamEnd) -> None:
        """Publish the end of the stream again when END_REPEAT s have passed since it last went out."""
        if time.monotonic() - self._end_sent >= END_REPEAT:
            self._publish(end)
            self._end_sent = time.monotonic()

    def _note_reach(self) -> None:
        """Count a step just published while the session reached no router (looked at every REACH_CHECK s)."""
        now = time.monotonic()
        if now - self._reach_seen[0] >= REACH_CHECK:
            self._reach_seen = (now, history.reachable(self.session))
        self._unreached += not self._reach_seen[1]

    def _linger(self, end: StreamEnd, stop: threading.Event) -> None:
        """After a run of which some steps went out while no router was reachable (lost on the way: a router
        restart), stay for the shards that answer the map's stats, as --wait-mappers does: answer the history and
        publish the end again until they have taken or given up every scan, or made no progress for LINGER s
        (none answering among them), so that what went nowhere is taken from the history or counted, not lost
        silently with the end of the stream. Returns at once when ``stop`` is set."""
        self.log.warning(
            "%d step(s) went out while no router was reachable; answering the history until the shards of map %r "
            "have taken every scan (at most %g s without progress)",
            self._unreached,
            self.options.map_name,
            LINGER,
        )
        robot, best, since = end.robot, -1, time.monotonic()
        while not stop.wait(0.2):
            reached = history.reachable(self.session)
            stats = self._shard_stats() if reached else []
            if stats and _accounted(stats, end):
                return
            done = min((s.fused.get(robot, 0) + s.discarded.get(robot, 0) for s in stats), default=-1)
            if done > best:
                best, since = done, time.monotonic()
            elif time.monotonic() - since > LINGER:
                self.log.warning("the shards made no progress for %g s; ending with %d scans accounted", LINGER, best)
                return
            if reached:
                self._repeat_end(end)

    # ------------------------------------------------------------------------------- run
    def _stopped(self) -> int:
        self.log.info("stopped on request before the end of the stream")
        return 0

    def run(self, stop: threading.Event) -> int:
        """Publish every step, then the StreamEnd, unless ``stop`` is set first; returns the exit code (0). When the
        shards waited for refused messages on its scan key and counted duplicates meanwhile, it says so."""
        opts, stream = self.options, self.stream
        token = self.session.liveliness().declare_token(keys.robot_alive_key(stream.robot, "source"))
        answers = self.session.declare_queryable(keys.history_key(stream.robot), self._on_history_query)
        try:
            if not self._wait_for_subscribers(stop):
                return self._stopped()
            if opts.wait_mappers:
                before = self._shard_stats()
                self._clashes_before = self._clash_counts(before)
                self._before = baselines(before, stream.robot)
                self._started = time.monotonic()
            if stream.prior is not None:
                self._publish(stream.prior, keys.PRIOR)
                with self._history_lock:
                    self._prior_out = True
            self.log.info(
                "publishing %d steps (%d scans) of robot %r %s",
                len(stream.steps),
                stream.scans,
                stream.robot,
                "as fast as the subscribers take" if opts.rate is None else f"at {opts.rate:g}x real time",
            )
            started = time.monotonic()
            offsets, notes = replay_offsets([step.stamp for step in stream.steps], opts.rate or 1.0)
            for note in notes if opts.rate is not None else ():
                self.log.warning("%s", note)
            scans_sent = 0
            flow_control = opts.rate is None and (opts.wait_mappers > 0 or opts.wait_slam)
            for steps_sent, step in enumerate(stream.steps):
                if opts.rate is not None:
                    delay = started + offsets[steps_sent] - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        return self._stopped()
                elif flow_control and not self._wait_for_window(scans_sent, steps_sent, stop):
                    return self._stopped()
                if stop.is_set():
                    return self._stopped()
                for message in step.messages:
                    self._publish(message)
                    scans_sent += isinstance(message, LaserScan)
                with self._history_lock:
                    self._steps_published = steps_sent + 1
                self._note_reach()
                self._report_progress(steps_sent + 1, len(stream.steps))
            end = StreamEnd(robot=stream.robot, scans=scans_sent)
            self._publish(end)
            with self._history_lock:
                self._end_out = True
            self._end_sent = time.monotonic()
            elapsed = time.monotonic() - started
            self.log.info(
                "published %d scans in %.2f s (%.1f scans/s)", scans_sent, elapsed, scans_sent / max(elapsed, 1e-9)
            )
            if opts.wait_mappers and not self._wait_for(
                "every shard to acknowledge the end of the stream",
                lambda: self._ended_everywhere(end),
                stop,
                self._end_progress,
            ):
                return self._stopped()
            clashed = self._clashed() if opts.wait_mappers else []
            if clashed:  # (a warning: the counts are by key and by kind apart, so this may be another robot's clash)
                self.log.warning(
                    "shard(s) %s of map %r refused messages on robot %r's keys during this run while they counted "
                    "duplicates: another run under this robot name (or another process on its keys) may hold some "
                    "of its seqs, and the map is then not this run's there; see the shards' stats and logs, and use "
                    "another --robot (or a new session: docs/persistence.md) if so",
                    ", ".join(map(str, clashed)),
                    opts.map_name,
                    stream.robot,
                )
            if not opts.wait_mappers and self._unreached:
                self._linger(end, stop)
            return 0
        finally:
            undeclare_all([token, answers, *reversed(self._publishers.values())])


def _accounted(stats: list[ShardStats], end: StreamEnd) -> bool:
    """Whether every shard of ``stats`` has the end of the stream and has fused or given up on each of its scans,
    and, a shard that keeps a state directory, committed them: until then its history is what a shard killed now
    would take them from (a re-probe: a shard killed as the source left lost the ~85 scans since its last commit).
    A shard whose commits have failed for more than FAILING_GRACE s (:func:`commits_stuck`) is not waited for: its
    commits may never succeed again, and the source waiting on them gave up after WAIT_TIMEOUT, exit 1, was
    restarted and replayed the run, for ever. One that failed for less may be retrying past a passing fault."""
    robot, scans = end.robot, end.scans
    return all(
        s.ended.get(robot) == scans
        and s.fused.get(robot, 0) + s.discarded.get(robot, 0) >= scans
        and (s.persist == "off" or commits_stuck(s) or s.committed.get(robot, 0) >= scans)
        for s in stats
    )


class ShardBaseline(NamedTuple):
    """What a shard had taken of a robot's messages when a run began (:func:`baselines`), and its uptime then."""

    ends: int  # StreamEnd messages of the robot it had taken
    scans: int  # scans of the robot it had dealt with (:func:`dealt_with`)
    uptime: float  # s


def baselines(stats: list[ShardStats], robot: str) -> dict[int, ShardBaseline]:
    """Per shard of ``stats``: what it has taken of ``robot`` now (:func:`took_end`, :func:`scans_taken`)."""
    end_key = keys.robot_key(robot, keys.END)
    return {s.shard: ShardBaseline(s.received.get(end_key, 0), dealt_with(s, robot), s.uptime) for s in stats}


def dealt_with(stats: ShardStats, robot: str) -> int:
    """The scans of ``robot`` the shard has dealt with since it started (or, for those it fused or gave up on, since
    its store began): fused, given up on, dropped as copies of a scan it has (resent), or refused (as a duplicate of
    another run's, malformed, past a limit...). Refusals it counts under no key (:data:`OTHER_KEYS`, when a peer has
    filled its table of keys) count as this robot's, so that the count cannot stall while the shard takes scans."""
    key = keys.robot_key(robot, keys.SCAN)
    done = stats.fused.get(robot, 0) + stats.discarded.get(robot, 0)
    return done + stats.resent.get(key, 0) + stats.rejected.get(key, 0) + stats.rejected.get(OTHER_KEYS, 0)


#: the baseline of a shard that was not there when a run began, or restarted since: its counts begin at 0
FROM_ZERO = ShardBaseline(0, 0, 0.0)


def baseline_of(stats: ShardStats, before: dict[int, ShardBaseline], elapsed: float) -> ShardBaseline:
    """What the shard of ``stats`` had taken when :func:`baselines` gave ``before``, ``elapsed`` s ago; FROM_ZERO when
    it was not there or is another process now: its uptime short of the one then plus ``elapsed`` by more than
    UPTIME_SLACK (it restarted)."""
    base = before.get(stats.shard)
    if base is None or stats.uptime < base.uptime + elapsed - UPTIME_SLACK:
        return FROM_ZERO
    return base


def took_end(stats: list[ShardStats], robot: str, before: dict[int, ShardBaseline], elapsed: float) -> bool:
    """Whether every shard of ``stats`` has taken a StreamEnd of ``robot`` since :func:`baselines` gave ``before``,
    ``elapsed`` s ago: its count of them risen, or at least one taken where it restarted since or was not there
    (:func:`baseline_of`). A shard takes a robot's messages in the order they came (services.intake), so one that took
    this run's end has taken every message of the run that reached it. Without this, a run under a robot name whose
    earlier run of as many scans the shards hold was "accounted for" by that run's counts before the shards had
    taken any of it: the source left, and said nothing of the clash its messages met (a rerun with other poses; seen
    once in four runs under load)."""
    key = keys.robot_key(robot, keys.END)
    return all(s.received.get(key, 0) > baseline_of(s, before, elapsed).ends for s in stats)


def scans_taken(stats: list[ShardStats], robot: str, before: dict[int, ShardBaseline], elapsed: float) -> int:
    """The scans of a run of ``robot`` that the slowest shard of ``stats`` has dealt with (:func:`dealt_with`) since
    :func:`baselines` gave ``before``, ``elapsed`` s ago: what a source running ahead of the shards by a window
    counts. Counted from the run's start, so that a rerun under a robot name is held back as a first run is: counted
    whole, an earlier run's scans that the shards fused would make the rerun's look taken, and it would go out
    unthrottled. A shard that restarted since (:func:`baseline_of`) counts whole: its counts of copies and refusals
    began again, and counted from the run's start it would hold the source back until it had taken as many scans
    again, which it may never be sent (a rerun that a shard with a store restarted during goes on unthrottled)."""
    return min((dealt_with(s, robot) - baseline_of(s, before, elapsed).scans for s in stats), default=0)


def commits_stuck(stats: ShardStats) -> bool:
    """Whether the shard's commits fail (persist: failing) and have for more than FAILING_GRACE s: since its last
    commit (commit_age), or since it started when it has made none or made the last one before it started (a resumed
    store's commit_age counts from the commit of the process before it: the grace was not kept)."""
    since = min(stats.commit_age, stats.uptime) if stats.commit_age >= 0 else stats.uptime
    return stats.persist == "failing" and since > FAILING_GRACE
