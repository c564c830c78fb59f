"""services.map_client.MapReader.assemble against a shard the test plays: a real router process and two Zenoh
sessions, the shard's stats and tile queryables answered from here. Every tile must be a whole level-0 tile of the
map's cell size, not only the first."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from schemas.messages import TileUpdate
from services import keys
from services.map_client import IncompleteMap, MapReader
from services.ports import free_port
from services.zenoh_config import build_config
from test_messages import stats
from test_pipeline import CLI, procs  # noqa: F401 - procs is a fixture

pytestmark = pytest.mark.slow


def _tile(tx: int, **changes) -> TileUpdate:
    """A whole 4-cell tile of map "m" at 0.05 m, its log-odds tx + the cell's index; ``changes``: other fields."""
    layers = (np.arange(16, dtype=np.float32).reshape(4, 4) + tx, np.zeros((4, 4), np.float32), np.ones((4, 4), bool))
    fields = dict(map="m", shard=0, z=0, tx=tx, ty=0, tile_size=4, resolution=0.05, row0=0, col0=0, robot="r")
    return TileUpdate.of_window(layers, None, **{**fields, "seq": 0, "published": 0.0, **changes})


@pytest.fixture
def router_endpoint(procs):  # noqa: F811
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    return endpoint


@pytest.fixture
def sessions(router_endpoint):
    shard, reader = (zenoh.open(build_config("client", connect=[router_endpoint])) for _ in range(2))
    yield shard, reader
    reader.close()
    shard.close()


def _serve(session: zenoh.Session, tiles: list[TileUpdate], shards: int = 1, owned: int | None = None) -> list:
    """Answer map "m"'s stats query as its shard 0 (of ``shards``, by its stats) holding ``tiles`` (``owned``: the
    count its stats give instead), and its tile query with them."""
    shard_stats = stats(map="m", shard=0, shards=shards, tiles_owned=len(tiles) if owned is None else owned)

    def on_stats(query: zenoh.Query) -> None:
        query.reply(keys.stats_key("m", 0), shard_stats.encode())

    def on_tiles(query: zenoh.Query) -> None:
        for tile in tiles:
            query.reply(keys.tile_key("m", 0, tile.tx, tile.ty), tile.encode())

    return [
        session.declare_queryable(keys.stats_key("m", 0), on_stats),
        session.declare_queryable(keys.tile_key("m", 0, "*", "*"), on_tiles),
        session.liveliness().declare_token(keys.shard_alive_key("m", 0)),
    ]


def _until_served(reader: zenoh.Session) -> None:
    """Wait until the queryables _serve declared reach ``reader`` through the router (on a busy machine that took
    longer than the reader's first query: "expected shards 0..0, got []"), at most 20 s."""
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        if MapReader(reader, "m").tokens() != {0}:
            time.sleep(0.05)
            continue
        for key in (keys.stats_key("m", 0), keys.tile_key("m", 0, "*", "*")):
            if not any(reply.ok is not None for reply in reader.get(key, timeout=2.0)):
                break
        else:
            return
        time.sleep(0.05)
    raise AssertionError("the played shard's queryables did not reach the reader in 20 s")


@pytest.mark.parametrize(
    ("second", "refused"),
    [
        ({}, None),
        ({"resolution": 0.1}, r"at 0.1 m \(tile 1, 0\), not 0.05 m"),  # a tile of another cell size than the first's
        ({"z": 3}, "at zoom level 3"),
    ],
)
def test_every_tile_of_an_assembled_map_has_the_maps_geometry(sessions, second, refused):
    shard, reader_session = sessions
    served = _serve(shard, [_tile(0), _tile(1, **second)])
    _until_served(reader_session)
    reader = MapReader(reader_session, "m")
    if refused is None:
        grid = reader.assemble(1, 0.05, timeout=10.0)
        assert sorted(grid.keys()) == [(0, 0), (1, 0)]
        assert grid.tile_arrays((1, 0))[0][3, 3] == 15 + 1
    else:
        with pytest.raises(IncompleteMap, match=refused):
            reader.assemble(1, 0.05, timeout=10.0)
    for entity in served:
        entity.undeclare()


def test_a_map_whose_shards_say_there_are_more_of_them_is_incomplete(sessions):
    """A probe's finding: assemble checked that shards 0 .. n-1 answered for the n its caller gave, not that they
    said n: shard 0 of 3 answering a caller who asked for one gave a map without the other shards' tiles."""
    shard, reader_session = sessions
    served = _serve(shard, [_tile(0)], shards=3)
    _until_served(reader_session)
    with pytest.raises(IncompleteMap, match="has 3 shard"):
        MapReader(reader_session, "m").assemble(1, 0.05, timeout=10.0)
    for entity in served:
        entity.undeclare()


@pytest.mark.parametrize("owned", [1, 3])
def test_a_shard_that_grew_between_its_stats_and_its_tiles_gives_a_whole_map(sessions, owned):
    """A probe's finding: an export while a shard caught up was a 503, "shard 0 holds 1 tiles but 2 arrived": the
    stats are asked first and the shard made a tile before the tiles were. Fewer tiles than the stats held is still a
    map with tiles missing."""
    shard, reader_session = sessions
    served = _serve(shard, [_tile(0), _tile(1)], owned=owned)
    _until_served(reader_session)
    reader = MapReader(reader_session, "m")
    if owned == 1:
        assert sorted(reader.assemble(1, 0.05, timeout=10.0).keys()) == [(0, 0), (1, 0)]
    else:
        with pytest.raises(IncompleteMap, match="shard 0 holds 3 tiles but 2 arrived"):
            reader.assemble(1, 0.05, timeout=10.0)
    for entity in served:
        entity.undeclare()


def _until_answers(reader: zenoh.Session, count: int) -> None:
    """Wait until ``count`` stats replies for map "m" reach ``reader`` (queryables of two sessions), at most 20 s."""
    deadline = time.monotonic() + 20.0
    every = dict(target=zenoh.QueryTarget.ALL, consolidation=zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE))
    while sum(reply.ok is not None for reply in reader.get(keys.stats_key("m", "*"), timeout=2.0, **every)) < count:
        assert time.monotonic() < deadline, f"fewer than {count} stats replies in 20 s"
        time.sleep(0.05)


def test_a_second_session_answering_as_the_shard_makes_the_stats_untrusted(sessions, router_endpoint):
    """A hostile-peer probe's finding: a peer answering pg/map/main/stats/0 after the real shard, with fused =
    ended = 600, made `posegrid run --export` stop and export a map missing 97 % of its scans, exit 0 (the last
    reply won). Two sessions answering as one shard make the round untrusted: the launcher and the source wait,
    assemble refuses."""
    shard, reader_session = sessions
    served = _serve(shard, [_tile(0)])
    forger = zenoh.open(build_config("client", connect=[router_endpoint]))
    try:
        forged = stats(map="m", shard=0, shards=1, tiles_owned=1, fused={"r": 600}, ended={"r": 600}, uptime=99.0)
        kept = forger.declare_queryable(  # noqa: F841 - (a queryable no one holds is undeclared)
            keys.stats_key("m", 0), lambda q: q.reply(keys.stats_key("m", 0), forged.encode())
        )
        _until_served(reader_session)
        _until_answers(reader_session, 2)
        reader = MapReader(reader_session, "m")
        answers = reader.answers(timeout=5.0)
        assert answers.trusted == {} and reader.stats(timeout=5.0) == {}
        twice = "2 processes answer as shard 0 of map 'm' (a shard started twice, or a peer forging its stats: "
        assert answers.problems == [twice + "docs/security.md)"]
        with pytest.raises(IncompleteMap, match="2 processes answer as shard 0"):
            reader.assemble(1, 0.05, timeout=10.0)
    finally:
        forger.close()
        for entity in served:
            entity.undeclare()


def test_tiles_from_a_session_that_is_not_their_shard_are_left_out(sessions, router_endpoint):
    """The probe's other finding: a peer answering the tile query with a whole tile of its own (log-odds 5.0 at tile
    (20, 20), claiming shard 0) put it into `posegrid run --export`'s map, exit 0. A tile is taken only from the
    session that answered the stats of the shard owning it; a stats reply for a shard with no liveliness token
    (shard 5 of 6 here: it stalled the source) is left out."""
    shard, reader_session = sessions
    served = _serve(shard, [_tile(0)])
    forger = zenoh.open(build_config("client", connect=[router_endpoint]))
    try:
        fake_tile = _tile(20, ty=20)
        ghost = stats(map="m", shard=5, shards=6)

        def on_tiles(query: zenoh.Query) -> None:
            query.reply(keys.tile_key("m", 0, 20, 20), fake_tile.encode())

        kept = [  # noqa: F841 - (a queryable no one holds is undeclared)
            forger.declare_queryable(keys.tile_key("m", 0, "*", "*"), on_tiles),
            forger.declare_queryable(keys.stats_key("m", 5), lambda q: q.reply(keys.stats_key("m", 5), ghost.encode())),
        ]
        _until_served(reader_session)
        _until_answers(reader_session, 2)
        reader = MapReader(reader_session, "m")
        answers = reader.answers(timeout=5.0)
        assert sorted(answers.trusted) == [0] and answers.untokened == 1 and answers.problems == []
        assert (20, 20) in {(t.tx, t.ty) for t in reader.tiles(timeout=10.0)}  # (it does arrive)
        before = reader.rejected
        grid = reader.assemble(1, 0.05, timeout=10.0)
        assert sorted(grid.keys()) == [(0, 0)] and reader.rejected - before >= 2  # the tile and shard 5's stats
    finally:
        forger.close()
        for entity in served:
            entity.undeclare()


@pytest.mark.parametrize("name", ["", "main/", "/main", "*", "**", "ma*", "a?b", "a#b", "main/extra", None])
def test_a_map_name_no_key_may_hold_is_refused_before_any_query(name):
    """ "*" and "main/extra" quietly queried other keys (and answered {}), "a?b" asked pg/map/a, and "main/" raised
    zenoh's own error quoting its Rust sources. Refused before the session is used (here: none)."""
    from services.errors import UsageError

    with pytest.raises(UsageError, match="is not valid"):
        MapReader(None, name)  # type: ignore[arg-type]


@pytest.mark.parametrize("timeout", [float("nan"), float("inf"), -1.0])
def test_a_timeout_that_is_not_a_finite_number_of_seconds_is_refused(timeout):
    from services.errors import UsageError

    reader = MapReader(None, "main")  # type: ignore[arg-type]  (refused before the session is used)
    for ask in (reader.stats, reader.tiles, reader.tokens):
        with pytest.raises(UsageError, match="a timeout must be a finite number of seconds >= 0"):
            ask(timeout=timeout)


def test_shards_up_counts_each_shard_of_the_map_once_by_its_index(sessions):
    """A re-probe: `posegrid source --wait-mappers 1` began publishing with no shard up, because a peer held a token
    on pg/map/main/alive/00; the source, the ROS 2 bridge and the launcher counted the replies to alive/*. They now
    count the distinct shards 0 .. N-1 whose token is up, each index in its one decimal form."""
    peer, reader = sessions
    held = [peer.liveliness().declare_token(keys.shard_alive_key("m", chunk)) for chunk in ("00", "+1", "5")]
    maps = MapReader(reader, "m")
    time.sleep(0.5)  # (the router hands the tokens on)
    assert maps.shards_up(2) == 0
    held += [peer.liveliness().declare_token(keys.shard_alive_key("m", 1))]
    deadline = time.monotonic() + 10
    while maps.shards_up(2) != 1:
        assert time.monotonic() < deadline, "the token of shard 1 never came"
        time.sleep(0.1)
    assert maps.shards_up(6) == 2  # (shard 5 of a map of 6: its token counts)
    for token in held:
        token.undeclare()
