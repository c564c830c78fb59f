"""`posegrid api` against what a peer on the Zenoh network or an HTTP client may do wrong or on purpose (docs/api.md):
made-up shard liveliness tokens and stray poses, the Host header, the access token, the limits on event streams,
exports and export size, the export window, and requests that never finish arriving.

One stack for the module: a router, one real mapper shard mapping the test room at 2 cm with 32-cell tiles, the
API (real uvicorn process) with small limits, a source replaying 20 scans; the test plays extra "shards" and
peers over its own Zenoh session.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import select
import socket
import subprocess
import threading
import time

import httpx
import numpy as np
import pytest

from api_stack import POSEGRID, ROOT, Stack, free_port, wait_until, write_room
from peers import put
from schemas.messages import PoseSamples, ShardStats
from services import history, keys
from services.api.guard import allowed_hosts
from services.api.status import STRANDED_AFTER
from services.map_client import MapReader
from services.zenoh_config import build_config, open_session

pytestmark = pytest.mark.slow

MAP, RESOLUTION, TILE, SCANS = "lab", 0.02, 32, 20
TOKEN = "test-token-0123456789abcdef"
#: the module API's limits (small, so that the tests reach them)
EXPORT_CELLS, VERIFY_WINDOW, STRAY_TTL, MAX_MAPS, MAX_ROBOTS, REQUEST_TIMEOUT = 20000, 3, 8, 6, 6, 2
API_OPTIONS = (
    "--max-maps",
    str(MAX_MAPS),
    "--max-robots",
    str(MAX_ROBOTS),
    "--stray-robot-ttl",
    str(STRAY_TTL),
    "--verify-window",
    str(VERIFY_WINDOW),
    "--max-exports",
    "1",
    "--max-event-clients",
    "2",
    "--max-export-cells",
    str(EXPORT_CELLS),
    "--request-timeout",
    str(REQUEST_TIMEOUT),
)


def start_api(stack: Stack, name: str, *options: str, headers: dict | None = None) -> str:
    """Start `posegrid api` with ``options`` as process ``name``; its URL once /health answers 200."""
    url = f"http://127.0.0.1:{free_port()}"
    stack.start(name, "api", "--port", url.rsplit(":", 1)[1], *options)

    def up() -> bool:
        stack.check_alive()
        try:
            return httpx.get(f"{url}/health", headers=headers, timeout=5).status_code == 200
        except httpx.TransportError:
            return False

    wait_until(up, 60, f"{name} to answer /health")
    return url


def settled(api: str) -> bool:
    """Whether the shard fused every scan of the replay and the API has every tile update it published."""
    response = httpx.get(f"{api}/maps/{MAP}/stats", timeout=30)
    if response.status_code != 200:
        return False
    shards = response.json()["per_shard"]
    return (
        len(shards) == 1
        and shards[0]["answered"]
        and shards[0]["scans_fused"].get("robot0") == SCANS
        and shards[0]["tile_updates_received"] == shards[0]["tile_updates"]
    )


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hardening")
    processes = Stack(folder)
    try:
        processes.router()
        processes.mappers(1, MAP, "--resolution", str(RESOLUTION), "--tile-size", str(TILE))
        processes.api_url = start_api(processes, "api", *API_OPTIONS)
        processes.source(write_room(folder / "room.npz", (0.0, 0.0)), MAP, 1)
        wait_until(lambda: settled(processes.api_url), 180, "the shard to fuse the replay")
        yield processes
    finally:
        processes.stop()


@pytest.fixture(scope="module")
def api(stack) -> str:
    return stack.api_url


@pytest.fixture(scope="module")
def session(stack):
    zenoh_session = open_session(build_config("client", connect=[stack.endpoint]), "the test")
    yield zenoh_session
    zenoh_session.close()


class FakeShard:
    """Shard 0 of 1 of map ``name``, played by the test: a liveliness token and a stats queryable that answers
    valid ShardStats (no tiles). With :attr:`hold` set, it keeps the stats queries it gets unanswered (the query
    stays open until :meth:`release`) and sets :attr:`held`."""

    def __init__(self, session, name: str, fused: dict[str, int] | None = None) -> None:
        self.name = name
        self.fused = {} if fused is None else fused  # scans fused by robot, as its stats say (the test may change it)
        self.hold = False
        self.held = threading.Event()
        self._kept: list = []
        self._queryable = session.declare_queryable(keys.stats_key(name, 0), self._on_query)
        self._token = session.liveliness().declare_token(keys.shard_alive_key(name, 0))

    def _on_query(self, query) -> None:
        if self.hold:
            self._kept.append(query)
            self.held.set()
            return
        given = {"map": self.name, "shard": 0, "shards": 1, "uptime": 1.0, "persist": "off", "fused": dict(self.fused)}
        stats = ShardStats(
            **{f.name: given.get(f.name, {} if f.type in ("dict", dict) else 0) for f in dataclasses.fields(ShardStats)}
        )
        query.reply(keys.stats_key(self.name, 0), stats.encode())

    def release(self) -> None:
        """Answer nothing more to the held queries (dropping them ends them) and answer again."""
        self.hold = False
        self._kept.clear()

    def close(self) -> None:
        self._token.undeclare()
        self._queryable.undeclare()


@pytest.fixture(scope="module")
def fake_shards(session):
    """A factory of FakeShards that stay up until the module ends (a proved map whose shard goes away would make
    /health degraded for the tests after)."""
    made: list[FakeShard] = []

    def make(name: str, fused: dict[str, int] | None = None) -> FakeShard:
        made.append(FakeShard(session, name, fused))
        return made[-1]

    yield make
    for fake in made:
        fake.close()


def get_json(url: str, **kwargs) -> dict | list:
    response = httpx.get(url, timeout=30, **kwargs)
    assert response.status_code == 200, response.text
    return response.json()


def problem(response: httpx.Response, status: int) -> str:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json"
    detail = response.json()["detail"]
    assert isinstance(detail, str) and detail
    return detail


def map_names(api: str) -> list[str]:
    return [m["name"] for m in get_json(f"{api}/maps")]


def pose(robot: str, seq: int) -> bytes:
    return PoseSamples(
        robot=robot, seq=seq, stamp=seq * 0.1, samples=np.array([[1.0, 1.0, 0.0]]), weights=np.array([1.0])
    ).encode()


# ------------------------------------------------------------------------------------------ Zenoh peers


def test_a_made_up_shard_token_lists_no_map_and_is_forgotten(api, session):
    key = keys.shard_alive_key("ghost", 0)
    token = session.liveliness().declare_token(key)
    try:

        def forgotten() -> bool:
            assert "ghost" not in map_names(api)
            assert httpx.get(f"{api}/maps/ghost", timeout=30).status_code == 404
            health = get_json(f"{api}/health")
            assert health["status"] == "ok" and "ghost" not in health["maps"], health
            return health["rejected"].get(key, 0) >= 1  # counted as unproved once the window is over

        wait_until(forgotten, VERIFY_WINDOW + 60, "the made-up token to be counted as unproved")
    finally:
        token.undeclare()


def test_a_token_for_a_shard_beyond_the_maps_shard_count_is_no_shard(api, session):
    key = keys.shard_alive_key(MAP, 5)  # the map has 1 shard
    token = session.liveliness().declare_token(key)
    try:

        def forgotten() -> bool:
            assert get_json(f"{api}/maps/{MAP}")["shards_alive"] == [0]
            assert [s["shard"] for s in get_json(f"{api}/maps/{MAP}/stats")["per_shard"]] == [0]
            health = get_json(f"{api}/health")
            assert health["status"] == "ok", health
            return health["rejected"].get(key, 0) >= 1

        wait_until(forgotten, VERIFY_WINDOW + 60, "the token of shard 5 to be counted as unproved")
    finally:
        token.undeclare()


def test_look_alike_shard_tokens_and_long_keys_are_refused_under_the_invalid_key(api, session, stack):
    """Probes: a token pg/map/lab/alive/+0 (or 00, or Arabic-Indic zero), up 3 s and gone, took the live shard 0
    down in the API for good (int() read its chunk as 0); one on alive/² stopped `posegrid source --wait-mappers`
    and `posegrid run` with a traceback (MapReader: '²'.isdigit() but int('²') fails); a robot called map was
    vouched for; and rejections were counted under the key as the peer made it, so 256 keys of 60 000 characters
    made every /health 15 MB, and a key with a newline wrote a forged line into the API's log. Now those keys are
    no shard's and no robot's, and rejections on such keys count under pg/<invalid key>."""
    chunks = ["+0", "00", "\u0660", "\u00b2", "0_0"]
    tokens = [session.liveliness().declare_token(keys.shard_alive_key(MAP, chunk)) for chunk in chunks]
    tokens.append(session.liveliness().declare_token(keys.robot_alive_key("map", "source")))
    long_robot = "a" * 5000
    for i in range(3):
        put(session, f"pg/{long_robot}{i}/pose", b"\xc1")
    put(session, "pg/r1\nposegrid api: FORGED LINE/pose", b"\xc1")
    reader = MapReader(session, MAP)
    assert reader.tokens() == {0}
    log = stack.logs / "api.log"
    wait_until(lambda: get_json(f"{api}/health")["rejected"].get(keys.INVALID_KEY, 0) >= 10, 30, "the rejections")
    assert "map/source" not in get_json(f"{api}/health")["processes_alive"]
    for token in tokens:
        token.undeclare()
    time.sleep(2)  # (the tokens' going reaches the API)
    health = get_json(f"{api}/health")
    assert health["status"] == "ok" and get_json(f"{api}/maps/{MAP}")["shards_alive"] == [0], health
    assert all(len(key) <= 200 for key in health["rejected"]), list(health["rejected"])
    assert len(httpx.get(f"{api}/health", timeout=30).content) < 100_000
    assert not any(line.startswith("posegrid api: FORGED LINE") for line in log.read_text().splitlines())


def test_a_robots_trajectory_begins_with_the_poses_its_histories_hold(api, session):
    """A crash probe: an API restarted mid-run served the trajectory from the first pose it heard (seq 178 of 600),
    though the SLAM node's history holds the poses before it, and nothing said the start was missing. A robot new to
    the API has the poses before its first one asked from its histories and put first."""
    who = history.Answerer(str(session.info.zid()), MAP, False)
    earlier = [
        PoseSamples(robot="rb", seq=seq, stamp=0.1 * seq, samples=np.array([[seq, 2.0 * seq, 0.1]]), weights=np.ones(1))
        for seq in range(5)
    ]

    doubled = PoseSamples(robot="rb", seq=2, stamp=0.2, samples=np.array([[99.0, 99.0, 0.1]]), weights=np.ones(1))

    def answer(query) -> None:  # (the SLAM node's history: every pose it has, whatever the range asked; a re-probe:
        for message in [*earlier, earlier[3], doubled]:  # seq 3 twice alike, seq 2 two ways, which is left out)
            history.reply(query, who, "rb", keys.POSE, message.encode())

    queryable = session.declare_queryable(keys.history_key("rb"), answer)
    try:
        time.sleep(1.0)  # (the router hands the queryable on)
        for seq in range(5, 8):
            pose = PoseSamples(
                robot="rb", seq=seq, stamp=0.1 * seq, samples=np.array([[seq, 2.0 * seq, 0.1]]), weights=np.ones(1)
            )
            put(session, keys.robot_key("rb", keys.POSE), pose.encode())

        def whole():
            response = httpx.get(f"{api}/robots/rb/trajectory", timeout=30)
            return response.status_code == 200 and response.json()["seq"] == [0, 1, 3, 4, 5, 6, 7] and response.json()

        track = wait_until(whole, 30, "the trajectory with its earlier poses")
    finally:
        queryable.undeclare()
    assert track["x"] == pytest.approx([0.0, 1.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    assert get_json(f"{api}/health")["rejected"].get(keys.history_key("rb"), 0) >= 1  # (seq 2 left out: counted)
    assert track["y"] == pytest.approx([0.0, 2.0, 6.0, 8.0, 10.0, 12.0, 14.0])


def test_a_second_process_answering_as_a_shard_degrades_health_until_it_goes(api, session):
    """A shard started twice (a second process with the same --shard and no state directory of its own) went
    unnoticed, and the stats flipped between the two from one ask to the next (fused 20 / 0, uptime too); the
    flips kept /health "ok". Now the shard is listed as duplicated, /health is degraded, and the stats kept are
    those of the process up longer (the real shard, not this one of 1 s)."""
    stats_key = keys.stats_key(MAP, 0)
    given = {"map": MAP, "shard": 0, "shards": 1, "uptime": 1.0, "persist": "off"}
    young = ShardStats(
        **{f.name: given.get(f.name, {} if f.type in ("dict", dict) else 0) for f in dataclasses.fields(ShardStats)}
    )
    twin = session.declare_queryable(stats_key, lambda query: query.reply(stats_key, young.encode()))
    try:

        def noticed() -> bool:
            health = get_json(f"{api}/health")
            return health["status"] == "degraded" and health["maps"][MAP]["duplicated_shards"] == [0]

        wait_until(noticed, 30, "the second shard 0 to be noticed")
        for _ in range(3):  # the same process's stats every time
            stats = get_json(f"{api}/maps/{MAP}/stats")
            assert stats["duplicated_shards"] == [0]
            assert stats["per_shard"][0]["scans_fused"] == {"robot0": SCANS} and stats["per_shard"][0]["uptime_s"] > 1.0
        assert get_json(f"{api}/health")["rejected"].get(stats_key, 0) >= 1
    finally:
        twin.undeclare()
    # a re-probe: a twin up "longer" that says the map has 64 shards had its count taken (every real tile then
    # belonged to a shard that never answers) and would have had its tiles served: an untrusted round changes
    # neither the count nor who answers for a tile
    given = {**given, "uptime": 1e6, "shards": 64}
    old = ShardStats(
        **{f.name: given.get(f.name, {} if f.type in ("dict", dict) else 0) for f in dataclasses.fields(ShardStats)}
    )
    twin = session.declare_queryable(stats_key, lambda query: query.reply(stats_key, old.encode()))
    try:
        wait_until(lambda: get_json(f"{api}/health")["maps"][MAP]["duplicated_shards"] == [0], 30, "the old twin")
        assert get_json(f"{api}/maps/{MAP}")["shards"] == 1
    finally:
        twin.undeclare()

    def alone() -> bool:
        health = get_json(f"{api}/health")
        return health["status"] == "ok" and health["maps"][MAP]["duplicated_shards"] == []

    wait_until(alone, 30, "/health to be ok once the second shard 0 is gone")


def test_stats_of_a_shard_with_no_token_change_nothing(api, session):
    """A hostile-peer probe's finding: a queryable on pg/map/main/stats/1023 answering "shard 1023 of 1024", with no
    liveliness token, made the API take the map for 1024 shards and refuse every real tile update as another
    shard's (the map froze). Stats count only for shards whose token is up; the rest are counted."""
    key = keys.stats_key(MAP, 1023)
    given = {"map": MAP, "shard": 1023, "shards": 1024, "uptime": 1.0, "persist": "off"}
    forged = ShardStats(
        **{f.name: given.get(f.name, {} if f.type in ("dict", dict) else 0) for f in dataclasses.fields(ShardStats)}
    )
    ghost = session.declare_queryable(key, lambda query: query.reply(key, forged.encode()))
    try:
        wait_until(lambda: get_json(f"{api}/health")["rejected"].get(key, 0) >= 1, 30, "the forged stats to be counted")
        assert get_json(f"{api}/maps/{MAP}")["shards"] == 1
        stats = get_json(f"{api}/maps/{MAP}/stats")
        assert stats["shards"] == 1 and [s["shard"] for s in stats["per_shard"]] == [0]
        assert get_json(f"{api}/health")["status"] == "ok"
    finally:
        ghost.undeclare()


def test_a_lag_that_began_before_anyone_asked_is_stranded_at_the_first_health(api, session, fake_shards):
    """/health's clock of no progress started at its first call, so a monitor asking less often than every 5 s saw
    "ok" at its first ask however long a robot's scans had been stranded. The API looks at the maps every second
    itself now. Robot lagbot: vouched for by its SLAM node's token (no source), scan 0 fused by map lagmap's shard,
    pose 9 seen: 9 scans lag and cannot come."""
    fake = fake_shards("lagmap", fused={"lagbot": 1})
    token = session.liveliness().declare_token(keys.robot_alive_key("lagbot", "slam"))
    try:
        wait_until(lambda: "lagmap" in map_names(api), 30, "map lagmap to be listed")

        def seen() -> bool:
            session.put(keys.robot_key("lagbot", keys.POSE), pose("lagbot", 9))
            return "lagbot" in [r["robot"] for r in get_json(f"{api}/robots")]

        wait_until(seen, 30, "lagbot's pose to arrive")
        time.sleep(STRANDED_AFTER + 2.0)  # (no /health asked meanwhile)
        health = get_json(f"{api}/health")
        assert health["status"] == "degraded" and health["maps"]["lagmap"]["lag_scans"]["lagbot"] == 9, health
    finally:
        fake.fused["lagbot"] = 10  # (caught up: the map is healthy again for the tests after)
        token.undeclare()
    wait_until(lambda: get_json(f"{api}/health")["status"] == "ok", 30, "/health to be ok once lagbot caught up")


def test_made_up_maps_are_capped_and_forgotten_when_their_tokens_go(api, session, fake_shards):
    before = get_json(f"{api}/health")["refused"].get("shard_tokens", 0)
    tokens = [session.liveliness().declare_token(keys.shard_alive_key(f"flood{i}", 0)) for i in range(10)]
    try:  # at most MAX_MAPS maps, one of them the real one: at least 10 - (MAX_MAPS - 1) tokens refused
        wait_until(
            lambda: get_json(f"{api}/health")["refused"].get("shard_tokens", 0) - before >= 10 - MAX_MAPS + 1,
            30,
            "the tokens beyond --max-maps to be refused",
        )
        assert not any(name.startswith("flood") for name in map_names(api))
    finally:
        for token in tokens:
            token.undeclare()
    fake_shards("late")  # a real-looking shard of a new map: there is room for it once the tokens are gone
    wait_until(lambda: "late" in map_names(api), 30, "map 'late' to be listed")
    health = get_json(f"{api}/health")
    assert health["limits"]["maps"] == MAX_MAPS and health["maps"]["late"]["shards_alive"] == [0]


def test_stray_poses_neither_lag_nor_degrade_health_and_expire(api, session):
    """Poses of a robot no source or SLAM node token vouched for: listed for --stray-robot-ttl s, never in the lag,
    never stranded (they were: lag = seq + 1, 'stranded' 5 s later, degraded until the API restarted)."""
    key = keys.robot_key("ghostbot", keys.POSE)

    def listed() -> bool:
        session.put(key, pose("ghostbot", 1000))  # again each time: an earlier one may have met a full tracker
        return "ghostbot" in [r["robot"] for r in get_json(f"{api}/robots")]

    wait_until(listed, 60, "the stray robot to be listed")
    assert STRAY_TTL > 5.0  # longer than the API's STRANDED_AFTER: a stranded robot would show before it expires

    def gone() -> bool:
        health = get_json(f"{api}/health")
        assert health["status"] == "ok", health
        assert "ghostbot" not in health["maps"][MAP]["lag_scans"]
        assert "ghostbot" not in get_json(f"{api}/maps/{MAP}/stats")["lag_scans"]
        return "ghostbot" not in health["robots"]

    wait_until(gone, STRAY_TTL + 60, "the stray robot to expire", interval=0.5)
    assert httpx.get(f"{api}/robots/ghostbot/pose", timeout=30).status_code == 404


def test_robots_are_capped_and_refusals_counted(api, session):
    before = get_json(f"{api}/health")["refused"].get("robots", 0)
    for i in range(MAX_ROBOTS + 4):
        session.put(keys.robot_key(f"crowd{i}", keys.POSE), pose(f"crowd{i}", 1))
    wait_until(
        lambda: get_json(f"{api}/health")["refused"].get("robots", 0) - before >= 4,
        30,
        "the poses beyond --max-robots to be refused",
    )
    assert len(get_json(f"{api}/robots")) <= MAX_ROBOTS
    assert get_json(f"{api}/health")["limits"]["robots"] == MAX_ROBOTS


# ------------------------------------------------------------------------------------------ HTTP access


def test_a_name_no_map_or_robot_could_have_is_422_without_echoing_it(api):
    """A new user's probe: a 20 000-character map name came back in its 404 body (20 045 bytes). Names are checked
    as the wire checks them (letters, digits, '_', '.', '-', at most 64): 422, and the body does not repeat it."""
    for path in (f"/maps/{'m' * 20_000}", f"/maps/{'m' * 65}/stats", "/maps/a%20b", f"/robots/{'r' * 20_000}/pose"):
        response = httpx.get(f"{api}{path}", timeout=30)
        assert response.status_code == 422 and len(response.content) < 300, (path, response.text[:300])
    assert httpx.get(f"{api}/maps/{'m' * 64}", timeout=30).status_code == 404  # (a name, of no map)


def test_a_path_with_a_control_character_is_no_route(api):
    """A probe's finding: every route also answered its path with a newline after it (the routes' patterns end in
    $, which matches before a final newline): /health%0A was 200, /events%0A opened a stream."""
    get_json(f"{api}/maps/{MAP}/stats")  # (the tile below is then cached: the fast path's pattern is checked too)
    httpx.get(f"{api}/maps/{MAP}/tiles/0/0/0.png", timeout=30)
    for path in ("/health%0A", f"/maps/{MAP}/stats%0A", f"/maps/{MAP}/tiles/0/0/0.png%0A", "/events%0A", "/maps%7F"):
        with httpx.stream("GET", f"{api}{path}", timeout=30) as response:
            response.read()
            assert "control character" in problem(response, 404), path
    assert httpx.get(f"{api}/health", timeout=30).status_code == 200


def test_numbers_written_as_int_and_float_take_them_but_a_map_reader_would_not_are_422(api):
    """A probe's finding: tile x "1_0" was tile 10, "+1" and " 1" tile 1, vmax=1_0 and x_min=1_0 were 10 (Python's
    int() and float() take them). A parameter is ASCII digits as written in a URL: -1, 2.5, 1e3."""
    for path in ("/tiles/0/1_0/0.png", "/tiles/0/%2B1/0.png", "/tiles/0/%201/0.png", "/tiles/0_0/0/0.png"):
        assert "ASCII digits" in problem(httpx.get(f"{api}/maps/{MAP}{path}", timeout=30), 422), path
    for params in ({"vmax": "1_0"}, {"vmax": " 1"}):
        detail = problem(httpx.get(f"{api}/maps/{MAP}/tiles/0/0/0.png", params={"layer": "variance", **params}), 422)
        assert "ASCII digits" in detail, params
    window = {"x_min": "1_0", "y_min": "0", "x_max": "20", "y_max": "20"}
    assert "ASCII digits" in problem(httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz", **window}), 422)
    assert "ASCII digits" in problem(httpx.get(f"{api}/robots/robot0/pose", params={"max_samples": "1_0"}), 422)
    assert "its row y" in problem(httpx.get(f"{api}/maps/{MAP}/tiles/0/0/.png", timeout=30), 404)  # (said "not .png")
    assert "not 'a.gif'" in problem(httpx.get(f"{api}/maps/{MAP}/tiles/0/0/a.gif", timeout=30), 404)
    for path in ("/tiles/0/-1/0.png", "/tiles/0/0/0.png?layer=variance&vmax=1e-3", "/tiles/0/0/0.png?vmax=.5"):
        assert httpx.get(f"{api}/maps/{MAP}{path}", timeout=30).status_code in (200, 404), path


def test_host_header_must_name_the_api(api):
    detail = problem(httpx.get(f"{api}/health", headers={"Host": "evil.example"}, timeout=30), 400)
    assert "evil.example" in detail and "--allowed-host" in detail
    problem(httpx.get(f"{api}/maps", headers={"Host": "evil.example:80"}, timeout=30), 400)
    problem(
        httpx.get(f"{api}/maps/{MAP}/tiles/0/0/0.png", headers={"Host": "127.0.0.1.evil.example"}, timeout=30), 400
    )  # the cached-tile fast path is behind the check too
    for host in ("localhost:1234", "127.0.0.1", "[::1]:8000", "LOCALHOST"):
        assert httpx.get(f"{api}/health", headers={"Host": host}, timeout=30).status_code == 200, host


def test_hosts_beyond_loopback_are_the_allowed_ones_and_the_bound_address():
    assert allowed_hosts("192.0.2.7", ["maps.example"]) == {
        "localhost",
        "127.0.0.1",
        "::1",
        "192.0.2.7",
        "maps.example",
    }
    assert allowed_hosts("0.0.0.0", []) == {"localhost", "127.0.0.1", "::1"}
    assert allowed_hosts("::", ["[2001:db8::1]"]) == {"localhost", "127.0.0.1", "::1", "2001:db8::1"}


def test_the_access_token_guards_every_route(stack):
    url = start_api(stack, "api-token", "--token", TOKEN, headers={"Authorization": f"Bearer {TOKEN}"})
    try:
        for path in ("/health", "/maps", "/", "/static/viewer.js", "/openapi.json", "/events"):
            response = httpx.get(url + path, timeout=30)
            assert "access token" in problem(response, 401), path
            assert response.headers["www-authenticate"].startswith("Bearer"), path
        assert "wrong" in problem(httpx.get(f"{url}/health", headers={"Authorization": "Bearer nope"}, timeout=30), 401)
        assert httpx.get(f"{url}/health", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30).status_code == 200
        assert httpx.get(f"{url}/health", params={"token": TOKEN}, timeout=30).status_code == 200
        # the OpenAPI document says how to give the token (the one without a token asks for none: test_api)
        spec = httpx.get(f"{url}/openapi.json", params={"token": TOKEN}, timeout=30).json()
        schemes = spec["components"]["securitySchemes"]
        assert schemes["bearer"] == {"type": "http", "scheme": "bearer", "description": "Authorization: Bearer TOKEN"}
        assert (schemes["query"]["in"], schemes["query"]["name"]) == ("query", "token")
        assert (schemes["cookie"]["in"], schemes["cookie"]["name"]) == ("cookie", "posegrid_token")
        assert spec["security"] == [{"bearer": []}, {"query": []}, {"cookie": []}]
        # the viewer: /?token= sets the cookie and drops the token from the address; the viewer's requests
        # (static files, the event stream, the API) then carry the cookie
        opened = httpx.get(f"{url}/", params={"token": TOKEN, "map": MAP}, timeout=30)
        assert opened.status_code == 303 and opened.headers["location"] == f"/?map={MAP}"
        cookie = opened.headers["set-cookie"]
        assert cookie.startswith(f"posegrid_token={TOKEN};") and "HttpOnly" in cookie
        with httpx.Client(base_url=url, cookies={"posegrid_token": TOKEN}, timeout=30) as browser:
            assert browser.get("/").headers["content-type"].startswith("text/html")
            assert browser.get("/static/viewer.js").status_code == 200
            assert browser.get("/maps").status_code == 200
            with browser.stream("GET", "/events") as events:
                assert events.status_code == 200
                assert "event: hello" in next(events.iter_text())
    finally:
        stack.end("api-token")


def test_a_bad_token_is_a_usage_error():
    for argv, env in ((["api", "--token", "short"], {}), (["api"], {"POSEGRID_API_TOKEN": "has spaces in it ok"})):
        result = subprocess.run(
            [*POSEGRID, *argv, "--port", str(free_port())],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, **env},
            check=False,
        )
        assert result.returncode == 2, result.stderr
        assert "16 to 256" in result.stderr and "Traceback" not in result.stderr


def test_run_checks_the_token_in_its_environment_before_it_starts_anything(monkeypatch):
    """`POSEGRID_API_TOKEN='bad token!' posegrid run` started the router and the mapper, then its API refused the
    token and the run stopped with exit 1 (a probe); --api-token was checked up front. The variable is too."""
    from services.cli import build_parser
    from services.commands.api import TOKEN_ENV, api_child_options
    from services.errors import UsageError

    monkeypatch.setenv(TOKEN_ENV, "bad token!!!!!!!!!!!")
    with pytest.raises(UsageError, match="16 to 256"):
        api_child_options(build_parser().parse_args(["run", "--sim"]))


def test_posegrid_run_passes_the_http_options_on(monkeypatch):
    from services.cli import build_parser
    from services.commands.api import TOKEN_ENV, api_child_options

    monkeypatch.setenv(TOKEN_ENV, "placeholder-0123456789")  # restored after the test
    args = build_parser().parse_args(
        [
            "run",
            "--api-token",
            TOKEN,
            "--api-allowed-host",
            "maps.example",
            "--api-max-exports",
            "3",
            "--api-request-timeout",
            "4",
        ]
    )
    assert api_child_options(args) == [
        "--allowed-host",
        "maps.example",
        "--max-exports",
        "3",
        "--request-timeout",
        "4.0",
    ]
    assert os.environ[TOKEN_ENV] == TOKEN  # the child inherits it; it is not on its command line


# ------------------------------------------------------------------------------------------ limits


def test_event_streams_beyond_the_limit_are_503(api):
    with httpx.Client(base_url=api, timeout=30) as client:
        with client.stream("GET", "/events") as first, client.stream("GET", "/events") as second:
            readers = [stream.iter_text() for stream in (first, second)]  # kept: a reader let go closes its stream
            for stream, reader in zip((first, second), readers):
                assert stream.status_code == 200 and "event: hello" in next(reader)
            with httpx.stream("GET", f"{api}/events", timeout=30) as third:  # a stream, were it admitted
                if third.status_code == 503:
                    third.read()
                refused = third
            assert "--max-event-clients" in problem(refused, 503)
            assert int(refused.headers["retry-after"]) > 0
        assert get_json(f"{api}/health")["refused"]["event_clients"] >= 1

        def admitted() -> bool:  # the slots come back once the server sees the streams closed
            with client.stream("GET", "/events") as again:
                return again.status_code == 200

        wait_until(admitted, 30, "an event-stream slot to be free again")


def test_an_event_stream_left_with_a_request_queued_behind_it_is_closed_at_its_next_write(stack):
    """A probe's finding: a client that sent GET /events and another request on the same connection, then left,
    left a traceback in the API's log (the write to the closed connection raised RuntimeError, as the queued
    request keeps the server from reading the close) and, for most such streams, an event-hub client that was
    never let go (/health's event_clients 39 after 140, a queue each that fills while a map changes). The stream
    is closed at its next write (the keep-alive, every 2 s: at 15 s, a later probe's 32 such clients locked every
    viewer of an idle map out for 15 s), its client let go, without a traceback, and without uvicorn's ERROR line
    for a response left unfinished (a line for each such client, none of them the API's error)."""

    api = start_api(stack, "api-events", "--max-event-clients", "16")

    def clients() -> int:
        return int(get_json(f"{api}/health")["event_clients"])

    host = api.split("//")[1]
    for _ in range(6):
        with socket.create_connection((host.split(":")[0], int(host.split(":")[1])), timeout=10) as raw:
            raw.sendall(
                b"GET /events HTTP/1.1\r\nHost: localhost\r\n\r\nGET /health HTTP/1.1\r\nHost: localhost\r\n\r\n"
            )
            got = b""
            while b"event: hello" not in got:
                chunk = raw.recv(4096)
                assert chunk, got
                got += chunk
    assert clients() == 6
    wait_until(lambda: clients() == 0, 60, "the abandoned event streams to be let go")
    said = (stack.logs / "api-events.log").read_text(errors="replace")
    assert "Traceback" not in said and "without completing response" not in said


def test_exports_beyond_the_limit_are_503(api, fake_shards):
    slow = fake_shards("slow")
    wait_until(lambda: "slow" in map_names(api), 30, "map 'slow' to be listed")
    for _ in range(3):  # again only if the first export was over (the API waits 2 s for stats) before the second
        slow.held.clear()
        slow.hold = True  # the export of 'slow' waits for its shard's stats, holding the only export slot
        answers: list[httpx.Response] = []
        first = threading.Thread(
            target=lambda into=answers: into.append(
                httpx.get(f"{api}/maps/slow/export", params={"format": "npz"}, timeout=60)
            )
        )
        first.start()
        try:
            assert slow.held.wait(30), "the export did not ask the shard"
            refused = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "png"}, timeout=30)
            first_over = bool(answers)
        finally:
            slow.release()
            first.join(60)
        if refused.status_code == 503 or not first_over:
            break
    assert "--max-exports" in problem(refused, 503)
    assert int(refused.headers["retry-after"]) > 0
    assert answers and answers[0].status_code == 503  # its shard did not answer in time
    assert get_json(f"{api}/health")["refused"]["exports"] >= 1
    assert httpx.get(f"{api}/maps/{MAP}/export", params={"format": "png"}, timeout=60).status_code != 503


# ------------------------------------------------------------------------------------------ export size, window


def shards_grid(session):
    return MapReader(session, MAP).assemble(1, RESOLUTION)


def windowed_reference(session, window: tuple[float, float, float, float]) -> dict[str, np.ndarray]:
    """The shards' map restricted to the cells that overlap ``window`` (m) and cropped to the observed ones,
    computed here from the whole raster."""
    full = shards_grid(session).rasterize()
    rows, columns = full["observed"].shape
    ix0, iy0 = (round(v / RESOLUTION) for v in full["origin"])
    ix = ix0 + np.arange(columns)
    iy = iy0 + np.arange(rows)
    inside = ((iy >= math.floor(window[1] / RESOLUTION)) & (iy < math.ceil(window[3] / RESOLUTION)))[:, None] & (
        (ix >= math.floor(window[0] / RESOLUTION)) & (ix < math.ceil(window[2] / RESOLUTION))
    )[None, :]
    observed = full["observed"] & inside
    keep_rows, keep_columns = np.flatnonzero(observed.any(axis=1)), np.flatnonzero(observed.any(axis=0))
    crop = (slice(keep_rows[0], keep_rows[-1] + 1), slice(keep_columns[0], keep_columns[-1] + 1))
    out = {key: full[key][crop] for key in ("logodds", "probability", "variance")}
    out["observed"] = observed[crop]
    out["origin"] = np.array([(ix0 + keep_columns[0]) * RESOLUTION, (iy0 + keep_rows[0]) * RESOLUTION])
    return out


WINDOW = (1.5, 1.0, 2.5, 2.0)  # m, inside the room (0..4 m x 0..3 m)


def test_an_export_beyond_the_cell_limit_is_413_before_it_is_built_and_a_window_exports(api, session):
    tiles = shards_grid(session).keys()
    width = (max(t[0] for t in tiles) - min(t[0] for t in tiles) + 1) * TILE
    height = (max(t[1] for t in tiles) - min(t[1] for t in tiles) + 1) * TILE
    assert width * height > EXPORT_CELLS
    detail = problem(httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz"}, timeout=60), 413)
    for part in (f"{width} x {height}", str(width * height), str(width * height * 13), str(EXPORT_CELLS), "x_min"):
        assert part in detail, (part, detail)

    window = dict(zip(("x_min", "y_min", "x_max", "y_max"), WINDOW))
    response = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz", **window}, timeout=60)
    assert response.status_code == 200, response.text
    with np.load(io.BytesIO(response.content)) as data:
        exported = {key: data[key] for key in data.files}
    reference = windowed_reference(session, WINDOW)
    for key in ("logodds", "probability", "observed", "variance"):
        np.testing.assert_array_equal(exported[key], reference[key], err_msg=key)
    np.testing.assert_allclose(exported["origin"], reference["origin"])
    assert exported["origin"][0] >= WINDOW[0] - RESOLUTION and exported["origin"][1] >= WINDOW[1] - RESOLUTION

    assert "all four" in problem(
        httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz", "x_min": 1}, timeout=30), 422
    )
    assert "x_min < x_max" in problem(
        httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz", **window, "x_max": 1.0}, timeout=30), 422
    )
    # edges whose cell index overflows a float (1e308 m over 0.05 m cells) are edges far away, not a 500
    for far in ({"x_min": 1e300, "x_max": 1e308}, {"y_min": -1e308, "y_max": -1e300}):
        response = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "png", **window, **far}, timeout=30)
        assert "observed" in problem(response, 409), far


def test_an_api_started_after_the_tiles_exports_them_at_its_first_request(stack, session):
    """An API started after the shard had published its tiles has seen no tile update, so it knew the map (from the
    shard's token) but not its cells' size: its first export was a 409 'no tiles yet' for a map of several tiles."""
    url = start_api(stack, "api-late", *API_OPTIONS)
    try:
        wait_until(lambda: MAP in httpx.get(f"{url}/health", timeout=30).json()["maps"], 60, "the map to be known")
        window = dict(zip(("x_min", "y_min", "x_max", "y_max"), WINDOW))
        response = httpx.get(f"{url}/maps/{MAP}/export", params={"format": "npz", **window}, timeout=60)
        assert response.status_code == 200, response.text
        with np.load(io.BytesIO(response.content)) as data:
            np.testing.assert_array_equal(data["logodds"], windowed_reference(session, WINDOW)["logodds"])
    finally:
        stack.end("api-late")


def test_export_layers_follow_the_openapi_schema(api, session):
    """Every format and layer the OpenAPI document offers for the export is answered as its description says:
    npz with a layer is that layer with observed, origin and resolution (it was 422 though the schema allows it),
    png draws it, pgm takes only probability."""
    operation = get_json(f"{api}/openapi.json")["paths"]["/maps/{map}/export"]["get"]
    parameters = {p["name"]: p for p in operation["parameters"]}
    formats = parameters["format"]["schema"]["enum"]
    layer_schema = parameters["layer"]["schema"]
    layers = next(option["enum"] for option in layer_schema["anyOf"] if "enum" in option)
    assert {"npz", "pgm", "png"} == set(formats) and "variance" in layers
    assert not parameters["layer"].get("required", False)
    described = parameters["layer"]["description"]
    assert "pgm" in described and "422" in described  # the one refused pair is in the document
    window = dict(zip(("x_min", "y_min", "x_max", "y_max"), WINDOW))
    reference = windowed_reference(session, WINDOW)
    for fmt in formats:
        for layer in layers:
            response = httpx.get(
                f"{api}/maps/{MAP}/export", params={"format": fmt, "layer": layer, **window}, timeout=60
            )
            if fmt == "pgm" and layer != "probability":
                assert "pgm" in problem(response, 422)
                continue
            assert response.status_code == 200, (fmt, layer, response.text)
            if fmt == "npz":
                with np.load(io.BytesIO(response.content)) as data:
                    assert sorted(data.files) == sorted([layer, "observed", "origin", "resolution"])
                    np.testing.assert_array_equal(data["observed"], reference["observed"])
                    np.testing.assert_array_equal(data[layer], reference[layer])


# ------------------------------------------------------------------------------------------ slow requests


def closed_within(sock: socket.socket, seconds: float, drip: bytes = b"") -> bool:
    """Whether the server closes ``sock`` within ``seconds``, while the client sends ``drip`` every 0.5 s."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        readable, _, _ = select.select([sock], [], [], 0.5)
        try:
            if readable and sock.recv(4096) == b"":
                return True
            if drip:
                sock.sendall(drip)
        except (ConnectionResetError, BrokenPipeError):
            return True
    return False


def test_a_request_that_never_finishes_arriving_is_cut_off(api):
    host, port = api.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as partial:
        partial.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # no blank line: the headers never end
        assert closed_within(partial, 30), "the server kept a half-sent request open"
    with socket.create_connection((host, int(port)), timeout=30) as slowloris:
        slowloris.sendall(b"GET /health HTTP/1.1\r\n")
        assert closed_within(slowloris, 30, drip=b"X-Slow: 1\r\n"), "the server kept a dripping request open"
    with socket.create_connection((host, int(port)), timeout=30) as whole:  # a whole request is answered
        whole.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert whole.recv(12).startswith(b"HTTP/1.1 200")
    # an answer that takes longer than the deadline (an event stream) is not cut off
    with httpx.stream("GET", f"{api}/events", timeout=30) as events:
        reader = events.iter_text()  # kept: a reader let go closes its stream
        assert "event: hello" in next(reader)
        time.sleep(2 * REQUEST_TIMEOUT + 1)
        assert get_json(f"{api}/health")["event_clients"] >= 1


def _answer(sock: socket.socket) -> bytes:
    """What the server sends on ``sock`` until it closes it (at most 30 s)."""
    sock.settimeout(30)
    answer = b""
    try:
        while chunk := sock.recv(4096):
            answer += chunk
    except ConnectionResetError:  # (after the answer: the server closed with bytes of ours unread)
        pass
    return answer


def test_a_request_whose_headers_do_not_end_is_refused_at_its_bound_not_held(api, stack):
    """A probe: httptools bounds no header, and uvicorn kept every one a client sent: 400 MB of headers in 1.6 s made
    the API hold 540 MB (the request deadline bounds the time, not the bytes). Past 64 KiB of request line and
    headers the API answers 431 with a reason, closes and counts it in /health; a request just under it is answered; a
    request httptools cannot parse gets its 400 as JSON, as every other error of the API."""
    from services.api.protocol import MAX_HEAD_BYTES

    host, port = api.removeprefix("http://").split(":")
    counted = get_json(f"{api}/health")["refused"].get("request_head", 0)
    pid = stack.processes["api"].pid
    with open(f"/proc/{pid}/status") as status:
        before = next(int(line.split()[1]) for line in status if line.startswith("VmRSS"))
    header = b"X-Filler: " + b"a" * 990 + b"\r\n"  # 1 000 bytes a header, counted 1 000 (4 for ': ' and CRLF)
    with socket.create_connection((host, int(port)), timeout=30) as flood:
        flood.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        sent = 0
        try:
            while sent < 50 * 2**20:  # 50 MB, if the server took them
                flood.sendall(header * 64)
                sent += 64 * len(header)
        except (ConnectionResetError, BrokenPipeError):
            pass
    assert sent < 50 * 2**20, "the server took 50 MB of headers"
    with open(f"/proc/{pid}/status") as status:
        after = next(int(line.split()[1]) for line in status if line.startswith("VmRSS"))
    assert after - before < 20 * 1024, (before, after)  # kB
    # all of it sent, then the answer read (httptools hands a header on when the next one starts: two past the bound)
    with socket.create_connection((host, int(port)), timeout=30) as over:
        over.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n" + header * (MAX_HEAD_BYTES // len(header) + 2))
        over.shutdown(socket.SHUT_WR)
        head, body = _answer(over).split(b"\r\n\r\n", 1)
    assert head.startswith(b"HTTP/1.1 431 ") and b"content-type: application/json" in head.lower(), head
    assert json.loads(body) == {"detail": f"the request line and headers are over {MAX_HEAD_BYTES} bytes"}
    assert get_json(f"{api}/health")["refused"]["request_head"] == counted + 2  # the flood and this one
    fillers = (MAX_HEAD_BYTES - 200) // len(header)  # under the bound with the request line and Host
    with socket.create_connection((host, int(port)), timeout=30) as large:
        large.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n" + header * fillers + b"\r\n")
        assert _answer(large).startswith(b"HTTP/1.1 200 ")
    with socket.create_connection((host, int(port)), timeout=30) as garbage:
        garbage.sendall(b"NOT HTTP AT ALL\r\n\r\n")
        head, body = _answer(garbage).split(b"\r\n\r\n", 1)
    assert head.startswith(b"HTTP/1.1 400 ") and b"content-type: application/json" in head.lower()
    assert "not an HTTP/1.1 request" in json.loads(body)["detail"]


@pytest.mark.parametrize(
    "soft, hard, expected, warned",
    [(100, 100, 36, True), (60, 60, 15, True), (100, 4096, 256, False), (4096, 4096, 256, False)],
)
def test_the_connection_limit_fits_the_files_the_process_may_open(soft, hard, expected, warned):
    """A probe under `ulimit -n 64`: the API kept --max-connections 256, and past its open-file limit answered with
    200s cut off half sent, 500s and connection resets, and printed a traceback a request. It now raises its soft
    limit to what the connections need where the hard limit lets it, else serves fewer connections and says so.
    (A process of its own: the limits are the process's.)"""
    import sys

    script = (
        "import logging, resource, sys\n"
        "from services.api.limits import fit_connections\n"
        "logging.basicConfig(stream=sys.stderr, format='%(message)s')\n"
        "print(fit_connections(256, logging.getLogger('api')), resource.getrlimit(resource.RLIMIT_NOFILE)[0])\n"
    )

    def limit() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))

    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=limit,
        check=True,
    )
    fitted, now_soft = map(int, done.stdout.split())
    assert fitted == expected and now_soft == max(soft, min(hard, 256 + 64)), done
    assert ("serving at most" in done.stderr) == warned, done
    assert not warned or f"at most {expected} connections at once, not --max-connections 256" in done.stderr, done


def test_connections_beyond_the_limit_are_503_counted_in_health_and_said_once(stack):
    """The same probe: uvicorn printed "Exceeded concurrency limit." for every connection answered 503 at
    --max-connections (20 000 lines on the run's console in 12 s). They are counted in /health (refused
    connections) and said in one line."""
    url = start_api(stack, "api-connections", "--max-connections", "2")
    port = int(url.rsplit(":", 1)[1])
    held = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(2)]
    statuses: list[int] = []
    try:
        deadline = time.monotonic() + 30  # (until the server has taken the two held ones: then every other is 503)
        while statuses.count(503) < 3 and time.monotonic() < deadline:
            statuses.append(httpx.get(f"{url}/health", timeout=10).status_code)
    finally:
        for connection in held:
            connection.close()
    assert statuses.count(503) == 3 and set(statuses) <= {200, 503}, statuses
    wait_until(lambda: get_json(f"{url}/health")["refused"].get("connections") == 3, 10, "the refusals counted")
    log = (stack.logs / "api-connections.log").read_text()
    assert "Exceeded concurrency limit" not in log and log.count("more than 2 connections at once") == 1, log


def test_a_new_run_under_the_maps_name_with_another_resolution_is_taken_up(stack):
    """A probe (the viewer's): a map's shard replaced by one of another --resolution was never taken up, though
    docs/api.md says the map takes the new cell size once every shard holds it: the fetch of every tile dropped the
    new run's tiles as of the wrong geometry, so it fell short and the map was never moved (/maps/geo said 1 m for
    60 s, the new run's tiles 404, the old run's 200). The unit test fed the tiles past that check."""
    api = stack.api_url
    mapper = ("mapper", "--shard", "0", "--shards", "1", "--map", "geo", "--tile-size", "32")
    stack.start("geo-coarse", *mapper, "--resolution", "1.0")
    stack.source(write_room(stack.logs / "geo.npz", (0.0, 0.0)), "geo", 1, robot="geo1")

    def geometry() -> tuple | None:
        response = httpx.get(f"{api}/maps/geo", timeout=10)
        if response.status_code != 200:
            return None
        info = response.json()
        return (info["resolution"], info["tiles"]) if info["tiles"] else None

    assert wait_until(geometry, 120, "the 1 m run's tiles")[0] == 1.0
    stack.end("geo-coarse")
    stack.start("geo-fine", *mapper, "--resolution", "0.05")
    stack.source(write_room(stack.logs / "geo2.npz", (0.0, 0.0)), "geo", 1, robot="geo2")

    def fine() -> tuple | None:
        got = geometry()
        return got if got is not None and got[0] == 0.05 else None

    _, tiles = wait_until(fine, 120, "the map to take the 0.05 m run's cells")
    assert tiles >= 4  # (the 4 m x 3 m room in 1.6 m tiles)
    assert httpx.get(f"{api}/maps/geo/tiles/0/0/0.npz", timeout=30).status_code == 200
