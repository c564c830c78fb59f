"""What GET /maps/{map}/stats and GET /health say, computed from plain data: the shards' stats, the registry's
view of a map, the robots' latest pose seqs, the robot processes alive and the clock. No Zenoh, no HTTP: the
routes (services.api.routes.status) gather the data and these functions combine it.

Over a map's shards: scans fused = the minimum over the answering shards (every shard has fused at least
that many), scans discarded and lag = the maximum (the scans some part of the map lacks). Lag of a shard for a
robot = the scans known to exist (:func:`expected_scans`: the latest pose seq + 1, the most scans one shard has
done, the end the source announced; the largest) minus the scans the shard fused or gave up on. So a lag shows
from the shards' own counts too: after the API restarts (it has seen no pose yet) and when a restarted shard has
counted nothing yet.

A map is healthy when its shard count is known and every shard is alive, answers from one process only and, when
it keeps a state directory, commits to it (its ``persist`` is not "failing"). A robot is *stranded* on
a map when its scans lag, its source process is gone, a shard has counted scans of it (while this API ran) and the
shards' scans done for it (fused + discarded) have not changed for :data:`STRANDED_AFTER` s: those scans cannot
come any more (a shard restarted after the source ended finds no history to take them from), and nothing else
would say so. /health is "ok" when there is a map, every map is healthy and no robot is stranded. The API looks
at the maps every :data:`WATCH_INTERVAL` s whether or not anyone asks (services.api.routes.status), so the
progress clock runs from when a lag began, not from the first /health call.
"""

from __future__ import annotations

import threading
from collections.abc import Collection, Iterable, Mapping
from typing import Any

from schemas.messages import ShardStats
from services.api import models
from services.api.registry import MapInfo

#: s without progress on a robot's lagging scans, its source gone, before /health calls them stranded
STRANDED_AFTER = 5.0
#: s between the API's own looks at the maps' progress (services.api.routes.status.watch)
WATCH_INTERVAL = 1.0

#: the kinds of refusal (ShardStats.refused) that say a peer sends what it should not, and what each means
DISTRUSTED = {
    "ahead": "messages with seqs or ends beyond the seq window (forged or stray seqs; held, never fused)",
    "key": "messages on keys that are no posegrid key (wildcards, made-up streams)",
    "duplicate": "scans or poses that differ from the ones fused for the same seq (two publishers for one robot?)",
    "robots": "messages of robots past the shards' --max-robots",
    "size": "messages larger than the limits allow",
    "work": "scans whose fusion would cost more than --max-work",
    "bound": "scans posed beyond --map-bound",
    "extent": "scans reaching more cells than --max-scan-cells",
    "map": "scans that could grow a shard's map past --max-map-cells (raise it, or run more shards)",
}


def distrust(refused: Mapping[str, int]) -> list[str]:
    """One sentence per kind of refusal in ``refused`` (by kind, summed over a map's shards) that :data:`DISTRUSTED`
    names, e.g. "4 messages with seqs or ends beyond the seq window (...)"."""
    return [f"{refused[kind]} {text}" for kind, text in DISTRUSTED.items() if refused.get(kind)]


def summed(counts: Iterable[Mapping[str, int]]) -> dict[str, int]:
    """The counts of every mapping added up by key, keys in the order first seen."""
    total: dict[str, int] = {}
    for mapping in counts:
        for key, count in mapping.items():
            total[key] = total.get(key, 0) + count
    return total


def done(s: ShardStats, robot: str) -> int:
    """The robot's scans the shard has fused or given up on."""
    return s.fused.get(robot, 0) + s.discarded.get(robot, 0)


def expected_scans(
    answered: Collection[ShardStats], latest: Mapping[str, int], vouched: Collection[str]
) -> dict[str, int]:
    """By robot whose lag counts (those of ``latest``: robot -> latest pose seq, the ``vouched`` robots an answering
    shard has counted, and those whose end of stream a shard was announced: a source sent it, and it outlives the
    source's token, as after a posed-scan replay an API restarted), the scans known to exist: the latest pose seq +
    1, the most scans one shard has fused or given up on, the stream's end a shard was announced (ShardStats.ended),
    whichever is largest."""
    counted = {r for s in answered for counts in (s.fused, s.discarded, s.ended) for r, n in counts.items() if n}
    announced = {r for s in answered for r, n in s.ended.items() if n}
    return {
        r: max([latest.get(r, -1) + 1, *(max(done(s, r), s.ended.get(r, 0)) for s in answered)])
        for r in set(latest) | (counted & set(vouched)) | announced
    }


def shard_lag(s: ShardStats, expected: Mapping[str, int]) -> dict[str, int]:
    """By robot of ``expected`` (robot -> scans known to exist, :func:`expected_scans`): scans the shard is behind,
    never negative."""
    return {r: max(0, n - done(s, r)) for r, n in expected.items()}


def shard_status(
    shard: int, info: MapInfo, s: ShardStats | None, expected: Mapping[str, int], now: float
) -> models.ShardStatus:
    """One shard of map ``info``: its liveliness and tile updates as the API saw them, and its stats ``s`` (None:
    it did not answer); ``expected``: robot -> scans known to exist (:func:`expected_scans`); ``now``:
    time.monotonic(), s."""
    age = info.last_update.get(shard)
    fields: dict[str, Any] = (
        {}
        if s is None
        else dict(
            scans_fused=s.fused,
            scans_discarded=s.discarded,
            scans_announced=s.ended,
            tiles_owned=s.tiles_owned,
            cells_updated=s.cells_updated,
            tile_updates=s.tile_updates,
            join_pending=s.join_pending,
            uptime_s=s.uptime,
            received=s.received,
            resent=s.resent,
            rejected=s.rejected,
            overflow=s.overflow,
            lag_scans=shard_lag(s, expected),
            persist=s.persist if s.persist in ("off", "ok", "failing") else None,
            committed_scans=s.committed,
            last_commit_age_s=None if s.commit_age < 0 else s.commit_age,
        )
    )
    return models.ShardStatus(
        shard=shard,
        alive=shard in info.alive,
        answered=s is not None,
        tile_updates_received=info.updates_received.get(shard, 0),
        last_tile_update_age_s=None if age is None else now - age,
        **fields,
    )


def map_stats(
    info: MapInfo,
    stats: Mapping[int, ShardStats],
    latest: Mapping[str, int],
    api_rejected: Mapping[str, int],
    now: float,
    vouched: Collection[str] = (),
) -> models.MapStats:
    """Map ``info``'s shards and what they did: ``stats`` by shard (those that answered), ``latest`` the latest
    pose seq by robot (those whose lag counts), ``api_rejected`` the API's own rejected messages by key, ``now``
    time.monotonic() in s, ``vouched`` the robots a process token vouched for (their lag counts from the shards'
    counts too: :func:`expected_scans`). The shards listed: 0..shards-1, those alive and those that answered."""
    shard_ids = sorted(set(range(info.shards or 0)) | info.alive | set(stats))
    answered = list(stats.values())
    expected = expected_scans(answered, latest, vouched)
    lags = [shard_lag(s, expected) for s in answered]
    robots_seen = sorted({r for s in answered for r in s.fused} | set(expected)) if answered else []
    return models.MapStats(
        map=info.name,
        shards=info.shards,
        shards_alive=sorted(info.alive),
        scans_fused={r: min(s.fused.get(r, 0) for s in answered) for r in robots_seen},
        scans_discarded={r: max(s.discarded.get(r, 0) for s in answered) for r in robots_seen},
        lag_scans={r: max(lag.get(r, 0) for lag in lags) for r in robots_seen if r in expected},
        rejected=summed([api_rejected, *(s.rejected for s in answered)]),
        refused=summed(s.refused for s in answered),
        duplicated_shards=sorted(info.duplicated),
        per_shard=[shard_status(shard, info, stats.get(shard), expected, now) for shard in shard_ids],
        conflict=info.conflict or beyond_count(info, stats),
        tiles_incomplete=info.incomplete,
    )


def beyond_count(info: MapInfo, stats: Mapping[int, ShardStats]) -> str | None:
    """Why shards of indices at or past the map's shard count answer (a shard started with another --shards), or
    None."""
    if info.shards is None:
        return None
    beyond = sorted(shard for shard in info.alive | set(stats) if shard >= info.shards)
    if not beyond:
        return None
    return (
        f"shard(s) {', '.join(map(str, beyond))} answer though the map has {info.shards} shards: a shard started "
        "with another --shards"
    )


def map_health(s: models.MapStats) -> models.MapHealth:
    """The part of a map's stats /health shows, with the distrust sentences of its refusals."""
    return models.MapHealth(
        shards=s.shards,
        shards_alive=s.shards_alive,
        scans_fused=s.scans_fused,
        scans_discarded=s.scans_discarded,
        lag_scans=s.lag_scans,
        duplicated_shards=s.duplicated_shards,
        conflict=s.conflict,
        tiles_incomplete=s.tiles_incomplete,
        distrust=distrust(s.refused),
        commits=[
            models.ShardCommit(
                shard=p.shard,
                persist=p.persist,
                scans=sum((p.committed_scans or {}).values()),
                age_s=p.last_commit_age_s,
            )
            for p in s.per_shard
            if p.persist is not None
        ],
    )


def shards_healthy(s: models.MapStats) -> bool:
    """Whether the map's shard count is known and each of its shards is alive, answered from one process and, with a
    state directory, commits."""
    return not map_problems(s)


def map_problems(s: models.MapStats) -> list[str]:
    """Why the map's shards are not healthy (:func:`shards_healthy`), one sentence each."""
    if s.shards is None:
        return ["no shard has answered with the map's shard count (or its shards disagree on it)"]
    problems = [] if s.conflict is None else [s.conflict]
    if s.tiles_incomplete is not None:
        problems.append(s.tiles_incomplete)
    if s.duplicated_shards:
        problems.append(f"shard(s) {', '.join(map(str, s.duplicated_shards))} answered by two processes each")
    known = {p.shard for p in s.per_shard}
    down = sorted({p.shard for p in s.per_shard if not (p.alive and p.answered)} | (set(range(s.shards)) - known))
    if down:
        problems.append(f"shard(s) {', '.join(map(str, down))} not alive or not answering")
    failing = [p.shard for p in s.per_shard if p.persist == "failing"]
    if failing:
        problems.append(f"shard(s) {', '.join(map(str, failing))} cannot commit to their state directory")
    return problems


def sources_alive(processes: Iterable[str]) -> set[str]:
    """The robots whose source process ("<robot>/source") holds a liveliness token."""
    return {process.split("/", 1)[0] for process in processes if process.endswith("/source")}


def counted_robots(s: models.MapStats) -> set[str]:
    """The robots some shard of the map has fused, given up on or been announced a scan of."""
    return {
        robot
        for p in s.per_shard
        for counts in (p.scans_fused, p.scans_discarded, p.scans_announced)
        for robot, n in (counts or {}).items()
        if n
    }


class Progress:
    """When the scans done (fused + discarded) for each robot on each map last changed, as the API saw them, and the
    robots some shard of each map has counted scans of while the API ran (a shard restarted in memory counts
    nothing: its robots stay counted)."""

    def __init__(self) -> None:
        self._seen: dict[tuple[str, str], tuple[int, float]] = {}  # (map, robot) -> (scans done, since when, s)
        self._counted: set[tuple[str, str]] = set()  # (map, robot)
        self._lock = threading.Lock()  # (/health's threads and the API's watch record at once)

    def counted(self, map_name: str, robots: Iterable[str]) -> set[str]:
        """Record ``robots`` as counted on the map; every robot counted on it so far."""
        with self._lock:
            self._counted.update((map_name, robot) for robot in robots)
            return {robot for name, robot in self._counted if name == map_name}

    def stalled(self, map_name: str, robot: str, scans_done: int, now: float) -> float:
        """Record ``scans_done`` scans at time ``now`` (s); the s since the count last changed (0 when it just did)."""
        with self._lock:
            seen = self._seen.get((map_name, robot))
            if seen is None or seen[0] != scans_done:
                self._seen[(map_name, robot)] = seen = (scans_done, now)
            return now - seen[1]


def stranded(map_name: str, s: models.MapStats, sources: set[str], progress: Progress, now: float) -> list[str]:
    """The robots stranded on the map (module docstring), sorted; records the progress of every robot that has a
    lag, so call it at every /health. ``sources``: robots whose source is alive; ``now``: time.monotonic(), s."""
    counted = progress.counted(map_name, counted_robots(s))
    out = []
    for robot, lag in sorted(s.lag_scans.items()):
        scans_done = s.scans_fused.get(robot, 0) + s.scans_discarded.get(robot, 0)
        still = progress.stalled(map_name, robot, scans_done, now)  # a source that did not wait for the shards exits
        if lag > 0 and robot in counted and robot not in sources and still >= STRANDED_AFTER:  # while they catch up
            out.append(robot)
    return out


def health_report(
    maps: Mapping[str, models.MapStats], processes: Iterable[str], progress: Progress, now: float, **system: Any
) -> models.Health:
    """/health from every map's stats, the robot processes alive ("<robot>/<process>") and ``now``
    (time.monotonic(), s); ``system``: the remaining Health fields, about the API itself (uptime_s, robots,
    rejected, event_clients, exports_running, refused, limits)."""
    processes = sorted(processes)
    sources = sources_alive(processes)
    stuck = {name: stranded(name, s, sources, progress, now) for name, s in maps.items()}
    reasons = [] if maps else ["no map is known yet: no mapper shard has announced itself to the API"]
    for name, s in maps.items():
        reasons += [f"map {name!r}: {problem}" for problem in map_problems(s)]
        if stuck[name]:
            reasons.append(
                f"map {name!r}: robot(s) {', '.join(stuck[name])} stranded: their source is gone and the shards make "
                "no progress on the scans they lag"
            )
    return models.Health(
        status="degraded" if reasons else "ok",
        reasons=reasons,
        maps={name: map_health(s) for name, s in maps.items()},
        processes_alive=processes,
        **system,
    )
