"""`posegrid slam-node`: runs a SLAM filter on what a source publishes and publishes a pose distribution per
scan (pg/<robot>/pose, tagged with the scan's seq).

What the node decides (steps in seq order, the filter, out-of-order and lost messages) is
:class:`services.state.slam.SlamState`; this module puts the Zenoh declarations around it, as
services.nodes.mapper does around services.state.shard: subscribers on the robot's streams, the pose publisher,
queryables for its stats (pg/<robot>/slam/stats) and for the poses it has published (pg/<robot>/history/pose),
the liveliness token pg/<robot>/alive/slam, and the questions to the source's history.

Threads and bad input as in services.nodes.mapper: callbacks feed a bounded intake queue (services.intake), one
thread decodes and filters; malformed messages are counted per key in the NodeStats and logged once per kind. The
queryables never wait for that thread, which may wait itself (a step asks the source's history for what did not
arrive: up to 35 s): the history of poses is thread-safe (services.state.pose_history), and stats queries are
answered from a snapshot the thread refreshes when its queue runs empty, and at least every 0.2 s.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable

import zenoh

from services import history, keys
from services.intake import Intake
from services.process import RejectCounter, Stopped, get_logger
from services.state.slam import EXPECTED, NodeConfig, SlamState
from services.zenoh_config import close_session, open_session, undeclare_all

#: s to wait for the source's history of the run (what it published before this node was up)
HISTORY_TIMEOUT = 60.0
#: s to wait for the source's history of steps that did not all arrive (the node waits meanwhile)
RECOVER_TIMEOUT = 5.0
#: s between two refreshes of the stats snapshot while messages wait in the intake (33 us a snapshot against 0.4 ms
#: for a dead-reckoning step: not one a message); the snapshot is also refreshed whenever the intake runs empty
STATS_PERIOD = 0.1


class SlamNode:
    """A running node: Zenoh declarations around a :class:`SlamState`. Use :meth:`run`."""

    def __init__(self, config: NodeConfig, session: zenoh.Session, stop: threading.Event):
        self.config = config
        self.session = session
        self.stop = stop  # set when the process is asked to stop (services.process.install_stop_event)
        self.log = get_logger(f"slam-node[{config.robot}]")
        self.rejects = RejectCounter(self.log)
        self.state = SlamState(config, self.rejects, publish=self._publish_pose, history=self._recover)
        self.intake = Intake(EXPECTED, self.rejects, robot=config.robot, capacity=config.intake_capacity)
        self._stats_lock = threading.Lock()  # guards _stats_payload only
        self._stats_payload = self.state.stats().encode()
        self._stats_at = time.monotonic()  # when _stats_payload was made
        self._declared: list = []
        self._pose_publisher: zenoh.Publisher | None = None

    # ---------------------------------------------------------------------------- zenoh callbacks
    def _on_stats_query(self, query: zenoh.Query) -> None:
        with self._stats_lock:
            payload = self._stats_payload
        query.reply(keys.slam_stats_key(self.config.robot), payload)

    def _refresh_stats(self, busy: bool = False) -> None:
        """Snapshot the node's stats for the stats queries (the node's thread); while ``busy`` (messages wait), at
        most every STATS_PERIOD s."""
        now = time.monotonic()
        if busy and now - self._stats_at < STATS_PERIOD:
            return
        payload = self.state.stats().encode()
        with self._stats_lock:
            self._stats_payload = payload
        self._stats_at = now

    def _on_history_query(self, query: zenoh.Query) -> None:
        """pg/<robot>/history/** (services.history): the poses this node has published, of the seqs asked for
        (the other streams are the source's to answer)."""
        request = history.parse_request(query, self.config.robot, self.rejects)
        if request is None or keys.POSE not in request.streams:  # (the node's own questions never ask for poses)
            return
        poses = self.state.poses(request.wants)  # (at once: the node's thread may be waiting on the source's history)
        answerer = history.Answerer(str(self.session.info.zid()), None, False)
        for payload in poses:
            history.reply(query, answerer, self.config.robot, keys.POSE, payload)

    def _publish_pose(self, payload: bytes) -> None:
        if self._pose_publisher is None:
            raise RuntimeError("the pose publisher is declared by declare(), before the first step")
        self._pose_publisher.put(payload)

    # ---------------------------------------------------------------------------- the source's history
    def _history(
        self,
        parameters: dict[str, str],
        timeout: float,
        accept: Callable[[history.Answerer], bool] = lambda answerer: True,
    ) -> list[tuple[str, bytes]]:
        """(pg/<robot>/<stream>, payload) of the messages the histories ``accept`` answers with (services.history),
        in the order they were sent; none when nobody answers."""
        robot = self.config.robot
        messages = history.ask_counted(self.session, robot, parameters, timeout, self.rejects, accept, self.stop)
        return [(keys.robot_key(robot, stream), payload) for _, stream, payload in messages if stream in EXPECTED]

    def _recover(self, streams: frozenset[str], first: int, last: int | None) -> list[tuple[str, bytes]]:
        """The source's history of ``streams``, seqs first..last (None: to the end), for the state's step
        assembler (on the node's thread)."""
        span = {"from": str(first)} if last is None else {"from": str(first), "to": str(last + 1)}
        return self._history({"streams": ",".join(sorted(streams)), **span}, RECOVER_TIMEOUT)

    def catch_up(self) -> None:
        """Take what the source published before this node subscribed: the prior and every step so far, in the
        order they went out, as if they had arrived live. A node that starts late or restarts so resumes where
        the run is, in the state of a node that saw all of it (its poses so far are published again; shards
        refuse the ones they have fused). Nothing happens when no source answers."""
        streams = ",".join(sorted(self.state.steps.needs | {keys.PRIOR}))
        replies = self._history(
            {"streams": streams}, HISTORY_TIMEOUT, accept=lambda answerer: not answerer.ended
        )  # a run that has ended is not this one
        if replies:
            self.state.take_history(replies, self.stop)
            self._refresh_stats()

    # ---------------------------------------------------------------------------- lifecycle
    def declare(self) -> None:
        """The pose publisher, subscribers and queryables first, the liveliness token last."""
        robot, session = self.config.robot, self.session
        self._pose_publisher = session.declare_publisher(
            keys.robot_key(robot, keys.POSE), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._declared.append(self._pose_publisher)
        self._declared.append(self.intake.subscribe(session))  # (one for every stream: services.intake)
        self._declared.append(session.declare_queryable(keys.slam_stats_key(robot), self._on_stats_query))
        self._declared.append(session.declare_queryable(keys.history_key(robot), self._on_history_query))
        self._declared.append(session.liveliness().declare_token(keys.robot_alive_key(robot, "slam")))

    def run(self) -> int:
        """Filter and publish until the stop flag is set; returns the exit code (0). Stopped while a question to the
        source's history waits (the router gone first), it stops there: a node started again takes the run from
        the histories."""
        robot = self.config.robot
        self.declare()
        self.log.info("%s up for robot %r; poses on %s", self.config.algorithm, robot, keys.robot_key(robot, keys.POSE))
        try:
            self.catch_up()
            while not self.stop.is_set():
                try:
                    key, payload = self.intake.next(0.2)
                except queue.Empty:
                    pass
                else:
                    self.state.handle(key, payload)
                self._refresh_stats(busy=not self.intake.empty())
        except Stopped as exc:
            self.log.info("%s", exc)
        undeclare_all(self._declared)
        self.log.info("stopped after publishing %d poses", self.state.published)
        return 0


def run_slam_node(config: NodeConfig, zenoh_config: zenoh.Config, stop: threading.Event) -> int:
    """Open a session and run the node until ``stop`` is set."""
    session = open_session(zenoh_config, f"the SLAM node of robot {config.robot}", stop)
    try:
        return SlamNode(config, session, stop).run()
    finally:
        close_session(session, f"the SLAM node of robot {config.robot}")
