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
from services.nodes.launcher import free_port
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
def sessions(procs):  # noqa: F811
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    procs([*CLI, "router", "--listen", endpoint]).wait_for("routing")
    shard, reader = (zenoh.open(build_config("client", connect=[endpoint])) for _ in range(2))
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
    ]


def _until_served(reader: zenoh.Session) -> None:
    """Wait until the queryables _serve declared reach ``reader`` through the router (on a busy machine that took
    longer than the reader's first query: "expected shards 0..0, got []"), at most 20 s."""
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
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
