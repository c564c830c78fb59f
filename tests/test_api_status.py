"""services.api.status: what /maps/{map}/stats and /health say, from plain data, against hand-computed values."""

from __future__ import annotations

import dataclasses

from schemas.messages import ShardStats
from services.api.models import MapStats
from services.api.registry import MapInfo, MapRegistry
from services.api.status import STRANDED_AFTER, Progress, distrust, health_report, map_stats, shards_healthy, stranded

#: the Health fields about the API itself, passed through health_report unchanged
SYSTEM = dict(
    uptime_s=12.5,
    robots=["r1"],
    rejected={"pose": 1},
    event_clients=2,
    exports_running=1,
    refused={"exports": 3},
    limits={"maps": 64},
)


def _unset(field: dataclasses.Field):
    """What a ShardStats field not given holds: its default, else an empty dict (counts by key) or 0."""
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return {} if field.type in ("dict", dict) else 0


def shard(index: int, shards: int = 2, **given) -> ShardStats:
    """Stats of shard ``index`` of map m: ``given`` fields, every other one its default, 0 or an empty dict."""
    values = {"map": "m", "shard": index, "shards": shards, "uptime": 1.0, **given}
    return ShardStats(
        **{f.name: values[f.name] if f.name in values else _unset(f) for f in dataclasses.fields(ShardStats)}
    )


def info(shards: int | None = 2, alive: set[int] | None = None, **given) -> MapInfo:
    return MapInfo(name="m", shards=shards, alive=set(range(shards or 0)) if alive is None else alive, **given)


def two_shards() -> dict[int, ShardStats]:
    return {
        0: shard(
            0,
            fused={"r1": 10, "r2": 3},
            discarded={"r1": 1},
            rejected={"scan": 2},
            refused={"ahead": 4, "malformed": 1},
        ),
        1: shard(
            1, fused={"r1": 7}, discarded={"r1": 2, "r2": 1}, rejected={"pose": 1}, refused={"ahead": 1, "key": 2}
        ),
    }


def test_map_stats_fuse_min_discard_max_and_lag_max_over_the_shards():
    s = map_stats(info(), two_shards(), latest={"r1": 12}, api_rejected={"scan": 5}, now=0.0)
    assert s.scans_fused == {"r1": 7, "r2": 0}  # min(10, 7); min(3, none = 0)
    assert s.scans_discarded == {"r1": 2, "r2": 1}  # max(1, 2); max(none = 0, 1)
    # lag = latest seq + 1 - fused - discarded: shard 0 13 - 10 - 1 = 2, shard 1 13 - 7 - 2 = 4; r2 has no
    # vouched pose, so no lag
    assert [p.lag_scans for p in s.per_shard] == [{"r1": 2}, {"r1": 4}]
    assert s.lag_scans == {"r1": 4}
    assert s.rejected == {"scan": 7, "pose": 1}  # the API's 5 + shard 0's 2; shard 1's 1
    assert s.refused == {"ahead": 5, "malformed": 1, "key": 2}
    assert s.shards == 2 and s.shards_alive == [0, 1] and shards_healthy(s)


def test_lag_counts_the_scans_the_shards_know_of_when_the_api_saw_no_pose():
    """An API restarted after the source ended has seen no pose of robot r1 (its SLAM node vouches for it): shard 1
    fused 300 and was announced the end at 300, shard 0 (restarted) fused 256, so shard 0 lags 44. The API said
    lag {} and ok. A robot no token vouched for gets no lag from the shards' counts (stray poses make none either)."""
    stats = {
        0: shard(0, fused={"r1": 256, "r9": 3}),
        1: shard(1, fused={"r1": 290, "r9": 5}, discarded={"r1": 10}, ended={"r1": 300}),
    }
    s = map_stats(info(), stats, latest={}, api_rejected={}, now=0.0, vouched={"r1", "r2"})
    assert [p.lag_scans for p in s.per_shard] == [{"r1": 44}, {"r1": 0}]  # r2: counted by no shard
    assert s.lag_scans == {"r1": 44}
    announced = map_stats(info(), {0: shard(0, ended={"r1": 50})}, latest={"r1": 9}, api_rejected={}, now=0.0)
    assert announced.lag_scans == {"r1": 50}  # max(latest 9 + 1, the end 50): the source said 50 scans
    # a posed-scan replay (no SLAM node) ended, then the API restarted: no token vouches for r1, but shard 1 was
    # announced its end (a re-probe found the new API "ok" with no lag); a stray robot with no end stays out
    replay = {0: shard(0, fused={"r9": 2}), 1: shard(1, fused={"r1": 300, "r9": 2}, ended={"r1": 300})}
    restarted = map_stats(info(), replay, latest={}, api_rejected={}, now=0.0)
    assert restarted.lag_scans == {"r1": 300} and [p.lag_scans for p in restarted.per_shard] == [{"r1": 300}, {"r1": 0}]
    ahead = map_stats(info(), {0: shard(0, fused={"r1": 5})}, latest={"r1": 20}, api_rejected={}, now=0.0)
    assert ahead.lag_scans == {"r1": 16}  # max(latest 20 + 1, 5) - 5


def test_a_shard_two_processes_answer_for_is_unhealthy():
    s = map_stats(info(duplicated={1}), two_shards(), latest={}, api_rejected={}, now=0.0)
    assert s.duplicated_shards == [1] and not shards_healthy(s)
    report = health_report({"m": s}, ["r1/source"], Progress(), 0.0, **SYSTEM)
    assert report.status == "degraded" and report.maps["m"].duplicated_shards == [1]


def test_lag_is_never_negative_and_counts_robots_no_shard_has_fused():
    s = map_stats(
        info(shards=1), {0: shard(0, shards=1, fused={"r1": 5})}, latest={"r1": 2, "r3": 0}, api_rejected={}, now=0.0
    )
    assert s.lag_scans == {"r1": 0, "r3": 1}  # r1: 3 - 5 < 0; r3: seq 0 + 1 - nothing
    assert s.scans_fused == {"r1": 5, "r3": 0}


def test_a_shard_that_is_down_is_listed_silent_and_the_map_is_unhealthy():
    s = map_stats(
        info(shards=3, alive={0, 2}, last_update={0: 100.0}, updates_received={0: 7}),
        {0: shard(0, shards=3), 2: shard(2, shards=3)},
        latest={},
        api_rejected={},
        now=103.5,
    )
    assert [(p.shard, p.alive, p.answered) for p in s.per_shard] == [
        (0, True, True),
        (1, False, False),
        (2, True, True),
    ]
    assert s.per_shard[1].scans_fused is None and s.per_shard[1].tiles_owned is None
    assert (s.per_shard[0].tile_updates_received, s.per_shard[0].last_tile_update_age_s) == (7, 3.5)
    assert (s.per_shard[2].tile_updates_received, s.per_shard[2].last_tile_update_age_s) == (0, None)
    assert not shards_healthy(s)
    report = health_report({"m": s}, [], Progress(), 0.0, **SYSTEM)
    assert report.status == "degraded"


def test_an_alive_shard_that_does_not_answer_or_an_unknown_count_is_unhealthy():
    silent = map_stats(info(), {0: shard(0)}, latest={}, api_rejected={}, now=0.0)
    assert [(p.alive, p.answered) for p in silent.per_shard] == [(True, True), (True, False)]
    assert not shards_healthy(silent)
    assert silent.scans_fused == {} and silent.per_shard[1].lag_scans is None
    nobody = map_stats(info(shards=None, alive=set()), {}, latest={"r1": 3}, api_rejected={}, now=0.0)
    assert nobody.shards is None and nobody.per_shard == [] and nobody.lag_scans == {}
    assert not shards_healthy(nobody)


def test_health_is_ok_with_every_shard_up_and_degraded_without_maps():
    s = map_stats(info(), two_shards(), latest={"r1": 12}, api_rejected={}, now=0.0)
    report = health_report({"m": s}, ["r1/slam", "r1/source"], Progress(), 0.0, **SYSTEM)
    assert report.status == "ok"
    assert report.processes_alive == ["r1/slam", "r1/source"]
    assert (report.uptime_s, report.event_clients, report.exports_running, report.refused) == (
        12.5,
        2,
        1,
        {"exports": 3},
    )
    m = report.maps["m"]
    assert (m.scans_fused, m.scans_discarded, m.lag_scans) == ({"r1": 7, "r2": 0}, {"r1": 2, "r2": 1}, {"r1": 4})
    assert m.distrust == [  # ahead 4 + 1, key 2; malformed is no sign of distrust
        "5 messages with seqs or ends beyond the seq window (forged or stray seqs; held, never fused)",
        "2 messages on keys that are no posegrid key (wildcards, made-up streams)",
    ]
    assert report.reasons == []
    empty = health_report({}, [], Progress(), 0.0, **SYSTEM)
    assert empty.status == "degraded" and empty.reasons == [
        "no map is known yet: no mapper shard has announced itself to the API"
    ]


def test_a_degraded_health_says_why_map_by_map():
    """/health said "degraded" with no reason: an operator had to read every map's shards to find which was down."""
    down = map_stats(info(shards=3, alive={0, 2}), {0: shard(0, shards=3)}, latest={}, api_rejected={}, now=0.0)
    twice = map_stats(info(duplicated={1}), two_shards(), latest={}, api_rejected={}, now=0.0)
    report = health_report({"a": down, "b": twice}, [], Progress(), 0.0, **SYSTEM)
    assert report.status == "degraded" and report.reasons == [
        "map 'a': shard(s) 1, 2 not alive or not answering",
        "map 'b': shard(s) 1 answered by two processes each",
    ]


def test_shards_of_two_geometries_or_past_the_count_are_a_conflict_and_degrade_health():
    """A map whose shards were started with two --resolution showed whichever shard's tiles the API met first (a
    partial map) while /health said ok; a shard 2 of a 2-shard map was listed alive. Both are the map's conflict."""
    registry = MapRegistry()
    registry.tile_changed("m", (0, 0), 0.05, 256)
    assert registry.check_geometry("m", 0.05, 256) is None
    why = registry.check_geometry("m", 0.1, 256)
    assert why == "map 'm' has 256-cell tiles of 0.05 m cells, not 256 of 0.1 m"
    registry.note_conflict("m", why)  # (as the API does for a tile its shard sent: services.api.mappers)
    mixed = registry.get("m")
    assert mixed is not None and mixed.conflict is not None
    mixed.shards, mixed.alive = 2, {0, 1}
    s = map_stats(mixed, two_shards(), latest={}, api_rejected={}, now=0.0)
    assert s.conflict == "its shards publish tiles of two geometries: " + (
        "map 'm' has 256-cell tiles of 0.05 m cells, not 256 of 0.1 m"
    )
    assert not shards_healthy(s)
    report = health_report({"m": s}, [], Progress(), 0.0, **SYSTEM)
    assert report.status == "degraded" and report.maps["m"].conflict == s.conflict
    assert report.reasons == [f"map 'm': {s.conflict}"]
    extra = map_stats(info(alive={0, 1, 2}), {**two_shards(), 2: shard(2, shards=3)}, {}, {}, 0.0)
    assert extra.conflict == "shard(s) 2 answer though the map has 2 shards: a shard started with another --shards"
    assert health_report({"m": extra}, [], Progress(), 0.0, **SYSTEM).status == "degraded"


def test_distrust_follows_the_table_order_and_skips_zero_and_unnamed_kinds():
    assert distrust({"extent": 1, "duplicate": 2, "size": 0, "missing": 9}) == [
        "2 scans or poses that differ from the ones fused for the same seq (two publishers for one robot?)",
        "1 scans reaching more cells than --max-scan-cells",
    ]


def lagging(fused: int = 10, **given) -> MapStats:
    """Stats of a one-shard map on which r1 (latest seq 19) lags 20 - fused scans."""
    return map_stats(
        info(shards=1),
        {0: shard(0, shards=1, fused={"r1": fused} if fused else {}, **given)},
        latest={"r1": 19},
        api_rejected={},
        now=0.0,
    )


def test_a_lagging_robot_whose_source_is_gone_is_stranded_after_no_progress_for_the_limit():
    progress = Progress()
    s = lagging()
    assert STRANDED_AFTER == 5.0
    assert stranded("m", s, set(), progress, now=100.0) == []  # first seen: progress now
    assert stranded("m", s, set(), progress, now=104.9) == []
    assert stranded("m", s, set(), progress, now=105.0) == ["r1"]
    report = health_report({"m": s}, ["r1/slam"], progress, 105.0, **SYSTEM)  # a slam process is no source
    assert report.status == "degraded"
    moved = lagging(fused=11)  # progress at 106: the clock starts again
    assert stranded("m", moved, set(), progress, now=106.0) == []
    assert stranded("m", moved, set(), progress, now=110.9) == []
    assert stranded("m", moved, set(), progress, now=111.0) == ["r1"]


def test_no_robot_is_stranded_while_its_source_lives_or_no_shard_counted_its_scans():
    progress = Progress()
    s = lagging()
    stranded("m", s, set(), progress, now=0.0)
    assert stranded("m", s, {"r1"}, progress, now=100.0) == []
    assert health_report({"m": s}, ["r1/source"], progress, 100.0, **SYSTEM).status == "ok"
    fresh = Progress()
    uncounted = lagging(fused=0)  # lag 20, but no shard fused, gave up on or was announced a scan of r1
    stranded("m", uncounted, set(), fresh, now=0.0)
    assert stranded("m", uncounted, set(), fresh, now=100.0) == []
    announced = lagging(fused=0, ended={"r1": 20})  # the source's end counted on the shard
    stranded("m", announced, set(), fresh, now=0.0)
    assert stranded("m", announced, set(), fresh, now=100.0) == ["r1"]


def test_a_robot_counted_once_stays_counted_when_a_shard_restarted_in_memory_counts_nothing():
    """A lone in-memory shard killed after the source ended came back with nothing fused and no history to take
    the scans from: lag 300, fused 0, and /health said ok for good (no shard had counted the robot)."""
    progress = Progress()
    stranded("m", lagging(fused=10), {"r1"}, progress, now=0.0)  # counted while its source ran
    restarted = lagging(fused=0)
    assert stranded("m", restarted, set(), progress, now=1.0) == []
    assert stranded("m", restarted, set(), progress, now=6.0) == ["r1"]
    assert stranded("n", restarted, set(), progress, now=6.0) == []  # (counted on map m, not n)
    assert stranded("n", restarted, set(), progress, now=60.0) == []


def test_progress_is_kept_per_map():
    progress = Progress()
    s = lagging()
    stranded("a", s, set(), progress, now=0.0)
    assert stranded("a", s, set(), progress, now=10.0) == ["r1"]
    assert stranded("b", s, set(), progress, now=10.0) == []  # first seen on b
