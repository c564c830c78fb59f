"""The API's parts that need no process: versions, caches, ETags, pose summaries, event batching."""

from __future__ import annotations

import asyncio
import json
from collections import deque
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapping.pyramid import TileLayers
from mapping.sensor_model import SensorModel, logit
from schemas.messages import PoseGaussian, PoseSamples, TileUpdate
from services.api import tiles as tiles_module
from services.api.cache import ByteLRU
from services.api.events import EventHub
from services.api.export import Window
from services.api.fastpath import etag_matches
from services.api.registry import MapRegistry
from services.api.render import LOGODDS_RANGE
from services.api.robots import PoseRefused, RobotTracker, Track, reduce_samples, summarize, weighted_mean_cov
from services.api.tiles import TileService, render_key, tile_facts, variance_scale
from services.map_client import ShardAnswers
from services.state.ownership import tile_owner
from test_messages import stats


def test_versions_propagate_to_every_level_and_only_grow():
    registry = MapRegistry()
    first = registry.tile_changed("m", (-1, 2), 0.05, 256)
    assert registry.version("m", 0, -1, 2) == first
    assert registry.version("m", 1, -1, 1) == first and registry.version("m", 2, -1, 0) == first
    assert registry.version("m", 1, 0, 1) == 0  # nothing below
    second = registry.tile_changed("m", (-2, 3), 0.05, 256)  # the same level-1 parent (-1, 1)
    assert second > first
    assert registry.version("m", 1, -1, 1) == second and registry.version("m", 0, -1, 2) == first
    info = registry.get("m")
    assert (info.x_range, info.y_range, info.top_level) == ((-2, -1), (2, 3), 0)
    assert registry.check_geometry("m", 0.05, 256) is None
    assert "0.1" in registry.check_geometry("m", 0.1, 256)
    assert registry.version("unknown", 0, 0, 0) == 0


def test_shard_appearing_asks_for_a_sync():
    registry = MapRegistry()
    registry.shard_alive("m", 1, True)
    registry.mark_synced("m")
    registry.shard_alive("m", 0, True)
    assert not registry.get("m").synced and registry.get("m").alive == {0, 1}
    registry.shard_alive("m", 1, False)
    assert registry.get("m").alive == {0}


def test_tile_updates_are_trusted_only_from_the_live_shard_that_owns_the_tile():
    registry = MapRegistry()
    assert "no live shard" in registry.check_sender("m", 0, (0, 0))  # a map no shard has announced
    registry.shard_alive("m", 0, True)
    registry.shard_alive("m", 1, True)
    assert registry.check_sender("m", 1, (5, 5)) is None  # shard count unknown yet: any live shard
    assert "not alive" in registry.check_sender("m", 2, (5, 5))
    registry.set_shards("m", 2)
    owner = tile_owner((5, 5), [0, 1])
    assert registry.check_sender("m", owner, (5, 5)) is None and registry.owner_alive("m", (5, 5))
    assert f"belongs to shard {owner}" in registry.check_sender("m", 1 - owner, (5, 5))
    registry.shard_alive("m", owner, False)
    assert not registry.owner_alive("m", (5, 5))


def test_forgotten_tiles_leave_every_level_and_give_their_parents_new_versions():
    registry = MapRegistry()
    kept = registry.tile_changed("m", (0, 0), 0.05, 256)
    gone = registry.tile_changed("m", (1, 0), 0.05, 256)  # same level-1 parent (0, 0) as the kept tile
    far = registry.tile_changed("m", (7, 7), 0.05, 256)  # alone up to level 3
    assert registry.version("m", 1, 0, 0) == gone and registry.version("m", 2, 1, 1) == far
    registry.forget_tiles("m", {(1, 0), (7, 7)})
    assert registry.version("m", 0, 1, 0) == 0 and registry.version("m", 0, 7, 7) == 0
    assert registry.version("m", 0, 0, 0) == kept
    assert registry.version("m", 1, 0, 0) > far  # changed: a new, larger version
    assert registry.version("m", 1, 3, 3) == 0 and registry.version("m", 2, 1, 1) == 0
    assert registry.version("m", 3, 0, 0) == registry.version("m", 1, 0, 0)  # (7, 7) was under it too
    info = registry.get("m")
    assert (info.x_range, info.y_range, sorted(info.tiles)) == ((0, 0), (0, 0), [(0, 0)])
    registry.forget_tiles("m", {(0, 0)})
    assert info.x_range is None and info.top_level is None and registry.version("m", 5, 0, 0) == 0


def test_byte_lru_serves_only_the_stored_version_and_evicts_by_bytes():
    cache: ByteLRU[str] = ByteLRU(max_bytes=10)
    cache.put("a", 1, "A", 4)
    cache.put("b", 1, "B", 4)
    assert cache.get("a", 1) == "A" and cache.get("a", 2) is None
    cache.put("c", 1, "C", 4)  # over 10 bytes: "b" is the least recently used
    assert cache.get("b", 1) is None and cache.get("a", 1) == "A" and cache.nbytes == 8


def test_etag_matching_and_render_keys():
    assert etag_matches('"x"', '"x"') and etag_matches('"y", "x"', '"x"') and etag_matches("*", '"x"')
    assert etag_matches('W/"x"', '"x"') and not etag_matches('"xy"', '"x"') and not etag_matches(None, '"x"')
    assert render_key("m", 0, 1, 2, "png", None, 3.0) == ("m", 0, 1, 2, "png", "probability", None)
    assert render_key("m", 0, 1, 2, "png", "variance", 2) == ("m", 0, 1, 2, "png", "variance", 2.0)
    assert render_key("m", 0, 1, 2, "npz", None, 2.0) == ("m", 0, 1, 2, "npz", None, None)
    assert (variance_scale(0.0), variance_scale(0.3), variance_scale(4.0), variance_scale(4.1)) == (1.0, 0.5, 4.0, 8.0)


def test_weighted_mean_averages_yaw_on_the_circle():
    samples = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 0.0, -np.pi + 0.1], [1.0, 3.0, np.pi]])
    weights = np.array([0.25, 0.25, 0.5])
    mean, cov = weighted_mean_cov(samples, weights)
    assert mean[0] == pytest.approx(1.0) and mean[1] == pytest.approx(1.5)
    assert abs(abs(mean[2]) - np.pi) < 1e-9  # not 0, the arithmetic mean of the angles
    assert cov[2, 2] == pytest.approx(0.5 * 0.1**2, rel=1e-6)
    assert cov[0, 0] == pytest.approx(0.5) and np.allclose(cov, cov.T)


def test_reduce_samples_follows_the_weights():
    samples = np.arange(30, dtype=float).reshape(10, 3)
    weights = np.array([0.5, 0.5] + [0.0] * 8)
    fewer, equal = reduce_samples(samples, weights, 4)
    assert sorted(fewer[:, 0].tolist()) == [0.0, 0.0, 3.0, 3.0] and equal.tolist() == [0.25] * 4
    same, _ = reduce_samples(samples, weights, 10)
    assert same is samples


def test_gaussian_pose_is_summarised_with_drawn_samples():
    message = PoseGaussian(robot="r", seq=7, stamp=0.7, mean=np.array([1.0, 2.0, 0.5]), cov=np.diag([0.04, 0.01, 0.0]))
    one, two = summarize(message, 0.0), summarize(message, 1.0)
    assert one.form == "gaussian" and one.samples.shape == (100, 3)
    np.testing.assert_array_equal(one.samples, two.samples)  # seeded by seq
    assert np.all(one.samples[:, 2] == 0.5) and abs(one.samples[:, 0].std() - 0.2) < 0.06
    np.testing.assert_array_equal(one.cov, message.cov)


def test_tracker_keeps_latest_and_trajectory():
    tracker = RobotTracker()
    for seq in range(3):
        tracker.update(
            PoseSamples(
                robot="r", seq=seq, stamp=seq * 0.1, samples=np.array([[seq, 0.0, 0.0]]), weights=np.array([1.0])
            )
        )
    assert tracker.robots() == ["r"] and tracker.latest("r").seq == 2 and tracker.latest_seqs() == {"r": 2}
    np.testing.assert_allclose(tracker.trajectory("r")[:, [0, 2]], [[0, 0], [1, 1], [2, 2]])
    assert tracker.trajectory("nobody").shape == (0, 5)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 40), st.lists(st.integers(-3, 30), max_size=120))
def test_a_track_keeps_what_a_bounded_deque_keeps(length, ops):
    """Track (a ring of float64 rows that grows as it fills) against the slow reference it replaced: a deque with
    maxlen. A positive op appends a row, a negative one lets that many of the oldest go."""
    track, reference = Track(length), deque(maxlen=length)
    for i, op in enumerate(ops):
        if op >= 0:
            row = (i, 0.1 * i, float(op), -float(op), 0.5)
            track.append(row)
            reference.append(row)
        else:
            assert track.drop_oldest(-op) == min(-op, len(reference))
            for _ in range(min(-op, len(reference))):
                reference.popleft()
        assert track.count == len(reference)
        np.testing.assert_array_equal(track.rows(), np.array(list(reference), float).reshape(-1, 5))


def test_a_tracks_earlier_poses_go_first_as_many_as_its_length_leaves_room_for():
    track = Track(5)
    for seq in (10, 11):
        track.append((seq, 0.0, 0.0, 0.0, 0.0))
    older = np.array([[seq, 0.0, 0.0, 0.0, 0.0] for seq in range(4, 10)], float)
    assert track.prepend(older) == 3  # room for 3 of the 6: the newest, 7, 8 and 9
    assert track.rows()[:, 0].tolist() == [7, 8, 9, 10, 11]
    track.append((12, 0.0, 0.0, 0.0, 0.0))  # full: the oldest goes
    assert track.rows()[:, 0].tolist() == [8, 9, 10, 11, 12]
    tracker = RobotTracker(trajectory_length=10)
    tracker.update(PoseSamples(robot="r", seq=6, stamp=0.0, samples=np.zeros((1, 3)), weights=np.ones(1)))
    assert tracker.backfill("r", np.array([[seq, 0.0, 0.0, 0.0, 0.0] for seq in range(8)], float)) == 6
    assert tracker.trajectory("r")[:, 0].tolist() == [0, 1, 2, 3, 4, 5, 6]  # (7: not before its first pose)
    assert tracker.backfill("nobody", older) == 0


def test_the_trajectories_of_all_robots_together_stay_within_their_bound():
    """A probe: a peer's poses under 50 robot names took the API 140 MB in 80 s (a tuple of 280 bytes a pose, 100 000
    kept per robot: 7 GB for the API's 256 robots), nothing counted. Past the bound on all robots' poses, the robot
    holding the most lets its oldest go (and a sixteenth of the bound more); the others keep theirs."""
    tracker = RobotTracker(trajectory_length=1000, trajectory_poses=160)
    for seq in range(150):
        tracker.update(PoseSamples(robot="big", seq=seq, stamp=0.0, samples=np.zeros((1, 3)), weights=np.ones(1)))
    for seq in range(20):
        tracker.update(PoseSamples(robot="small", seq=seq, stamp=0.0, samples=np.zeros((1, 3)), weights=np.ones(1)))
    big, small = tracker.trajectory("big"), tracker.trajectory("small")
    # at the 11th of small's poses, 161 in all: big lets 1 + 10 go (150 -> 139), then small's 9 more: 159 in all
    assert len(small) == 20 and len(big) == 139 and big[0, 0] == 11 and big[-1, 0] == 149


def test_tracker_keeps_each_seq_once_in_order_and_refuses_stale_poses():
    """A restarted SLAM node publishes the run's poses again from seq 0, and a second node under the robot's name
    publishes its own: the trajectory went back to seq 0 and held seqs twice (1 071 entries for 900 steps), and the
    latest pose fell back. A pose not after the robot's latest is refused (stale); a new robot beyond the cap too."""

    def pose(seq: int, x: float) -> PoseSamples:
        return PoseSamples(robot="r", seq=seq, stamp=seq * 0.1, samples=np.array([[x, 0.0, 0.0]]), weights=np.ones(1))

    tracker = RobotTracker(max_robots=1)
    for seq in (0, 1, 2, 3):
        tracker.update(pose(seq, float(seq)))
    for seq, x in ((0, 0.0), (2, 99.0), (3, 99.0)):  # again, another node's
        with pytest.raises(PoseRefused) as refused:
            tracker.update(pose(seq, x))
        assert refused.value.kind == "stale" and f"seq {seq}, not after its latest, seq 3" in str(refused.value)
    tracker.update(pose(4, 4.0))
    np.testing.assert_allclose(tracker.trajectory("r")[:, [0, 2]], [[0, 0], [1, 1], [2, 2], [3, 3], [4, 4]])
    assert tracker.latest("r").seq == 4
    # a forged seq ahead would make every later pose stale: refused, far or near, unless the next pose follows it
    for ahead in (10**9, 1024, 5):
        with pytest.raises(PoseRefused) as refused:
            tracker.update(pose(tracker.latest("r").seq + ahead, 99.0))
        assert refused.value.kind == "ahead"
        tracker.update(pose(tracker.latest("r").seq + 1, 0.0))  # the real next pose is taken
    assert tracker.latest("r").seq == 7 and 99.0 not in tracker.trajectory("r")[:, 2]
    with pytest.raises(PoseRefused):
        tracker.update(pose(5000, 50.0))  # (the API cut off for 5 000 poses: the first after it is held back)
    tracker.update(pose(5003, 50.3))  # (two lost between)
    tracker.update(pose(5007, 50.7))  # (three lost: a gap of up to four is taken at once)
    assert tracker.latest("r").seq == 5007
    with pytest.raises(PoseRefused) as refused:
        tracker.update(replace(pose(0, 0.0), robot="s"))
    assert refused.value.kind == "capacity"


def test_event_hub_batches_changes_per_flush():
    async def scenario():
        hub = EventHub("e", interval=0.01, backlog=2)
        stream = hub.stream()
        assert "hello" in await stream.__anext__()
        for version in (1, 2, 3):
            hub.tile_changed("m", (0, -1), version)
        hub.tile_changed("m", (4, 4), 4)
        hub.flush()
        batch = await stream.__anext__()
        events = [block for block in batch.split("\n\n") if block]
        assert len(events) == 1 and events[0].startswith("event: tiles")
        assert json.loads(events[0].split("data: ")[1]) == {"map": "m", "tiles": [[0, -1, 3], [4, 4, 4]]}
        for version in range(4):  # a client that does not read falls behind the backlog: it is told to resync
            hub.tile_changed("m", (0, 0), version)
            hub.flush()
        assert "resync" in await stream.__anext__()
        await stream.aclose()
        assert hub.clients == 0

    asyncio.run(scenario())


def test_a_client_gone_while_its_stream_waits_leaves_no_task_behind():
    """uvicorn cancels a disconnected client's stream inside asyncio.wait: the queue getter must go with it
    (it used to stay pending: "Task was destroyed but it is pending!" in the log, once per client)."""

    async def scenario():
        hub = EventHub("e", interval=0.01, backlog=2)
        stream = hub.stream()
        assert "hello" in await stream.__anext__()
        waiting = asyncio.ensure_future(stream.__anext__())
        await asyncio.sleep(0.05)  # inside asyncio.wait now (the keep-alive is seconds away)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        await asyncio.sleep(0)  # let the cancelled getter finish
        assert [task for task in asyncio.all_tasks() if task is not asyncio.current_task()] == []
        assert hub.clients == 0

    asyncio.run(scenario())


def test_logodds_png_spans_the_sensor_models_clamping_range():
    model = SensorModel()
    assert pytest.approx((logit(model.p_min), logit(model.p_max)), rel=1e-12) == LOGODDS_RANGE


@pytest.mark.parametrize("spec_version", ["2.3", "2.4"])
def test_head_stops_a_streaming_response_under_either_asgi_spec(spec_version):
    """HEAD of an endless event stream sends the headers and an empty end, then stops the stream. Under ASGI 2.4
    Starlette waits for a send to raise OSError rather than for a disconnect, so a middleware that only dropped
    the body would stream forever (found by an audit); a plain response's one body message is dropped."""
    from starlette.responses import Response, StreamingResponse

    from services.api.head import HeadAsGet

    yielded = []

    async def endless():
        while True:
            yielded.append(1)
            yield b"event: hello\n\n"
            await asyncio.sleep(0.01)

    async def serve(app) -> list[dict]:
        sent, complete = [], asyncio.Event()

        async def receive():  # as uvicorn: a disconnect once the response is complete
            await complete.wait()
            return {"type": "http.disconnect"}

        async def send(message):
            sent.append(message)
            if message["type"] == "http.response.body" and not message.get("more_body", False):
                complete.set()

        scope = {
            "type": "http",
            "method": "HEAD",
            "path": "/",
            "headers": [],
            "query_string": b"",
            "asgi": {"version": "3.0", "spec_version": spec_version},
        }
        await asyncio.wait_for(HeadAsGet(app)(scope, receive, send), 5)
        return sent

    sent = asyncio.run(serve(StreamingResponse(endless(), media_type="text/event-stream")))
    assert [m["type"] for m in sent] == ["http.response.start", "http.response.body"] and sent[1]["body"] == b""
    assert dict(sent[0]["headers"])[b"content-type"].startswith(b"text/event-stream") and len(yielded) <= 2
    sent = asyncio.run(serve(Response(b"twelve bytes", media_type="text/plain")))
    assert [m["type"] for m in sent] == ["http.response.start", "http.response.body"] and sent[1]["body"] == b""
    assert dict(sent[0]["headers"])[b"content-length"] == b"12"


def update(tx: int, ty: int, fill: float) -> TileUpdate:
    """A whole 2 x 2 level-0 tile as a shard sends it."""
    return TileUpdate.of_window(
        (np.full((2, 2), fill, np.float32), np.ones((2, 2), np.float32), np.ones((2, 2), bool)),
        map="m",
        shard=0,
        z=0,
        tx=tx,
        ty=ty,
        tile_size=2,
        resolution=0.05,
        row0=0,
        col0=0,
        robot="r",
        seq=0,
        published=0.0,
    )


class Source:
    """The shards as TileService asks them (services.map_client over Zenoh in the API): tiles held in memory."""

    def __init__(self, tiles):
        self.tiles = tiles

    def fetch_tiles(self, map_name, tiles):
        return {key: self.tiles[key] for key in tiles if key in self.tiles}

    def fetch_all(self, map_name):
        return list(self.tiles.values()), None


def test_tile_facts_hand_computed():
    size = 10
    observed = np.zeros((size, size), bool)
    observed[3, 2:10] = True  # 8 cells
    observed[5, 4:6] = True  # 2 cells
    variance = np.zeros((size, size), np.float32)
    variance[observed] = np.arange(1, 11)  # 1 .. 10
    layers: TileLayers = (np.zeros((size, size), np.float32), variance, observed)
    facts = tile_facts((1, -2), layers)
    assert facts.observed == 10
    # numpy's linear percentile of 1..10 at 99 %: index 0.99 * 9 = 8.91 -> 9 + 0.91 * (10 - 9)
    assert facts.variance_p99 == pytest.approx(9.91)
    # global cells: x = 1*10 + col, y = -2*10 + row
    assert facts.bounds == (12, -17, 19, -15)


def test_a_sync_that_finds_the_cached_tile_unchanged_keeps_its_version():
    registry = MapRegistry()
    registry.shard_alive("m", 0, True)
    version = registry.tile_changed("m", (0, 0), 0.05, 2)
    source = Source({(0, 0): update(0, 0, 1.0)})
    changes = []
    service = TileService(
        registry, source, "e", 1 << 20, on_change=lambda name, tile, v: changes.append((name, tile, v))
    )
    assert service.layers("m", 0, 0, 0)[0][0, 0] == 1.0  # fetched and cached at `version`
    service.sync("m")  # the shard holds exactly what is cached: nothing changed
    assert registry.version("m", 0, 0, 0) == version and changes == []
    source.tiles[(0, 0)] = update(0, 0, 2.0)
    registry.request_sync("m")
    service.sync("m")  # now it differs: a new version and one event
    assert registry.version("m", 0, 0, 0) > version
    assert changes == [("m", (0, 0), registry.version("m", 0, 0, 0))]


def test_a_maps_summary_and_a_coarse_tile_fetch_their_level_0_tiles_part_after_part(monkeypatch):
    """A probe: one GET /maps after a shard filled its --max-map-cells (2 045 tiles) asked every tile at once and took
    the API to 2.3 GB, against --cache-mb 256. The tiles are asked FETCH_CELLS cells at a time; the summary and the
    coarse tile are what they were (every tile counted once, hand-summed)."""
    monkeypatch.setattr(tiles_module, "FETCH_CELLS", 8)  # two 2 x 2 tiles a part
    registry = MapRegistry()
    registry.shard_alive("m", 0, True)
    tiles = {(tx, ty): update(tx, ty, float(tx + 8 * ty)) for tx in range(8) for ty in range(8)}
    for tile in tiles:
        registry.tile_changed("m", tile, 0.05, 2)
    asked: list[int] = []

    class Counting(Source):
        def fetch_tiles(self, map_name, wanted):
            asked.append(len(wanted))
            return super().fetch_tiles(map_name, wanted)

    service = TileService(registry, Counting(tiles), "e", 1 << 20, on_change=lambda name, tile, v: None)
    content = service.content("m")
    assert content.observed == 64 * 4 and content.bounds == (0, 0, 15, 15)  # every cell of the 8 x 8 tiles
    assert len(asked) == 32 and max(asked) == 2
    asked.clear()
    coarse = TileService(registry, Counting(tiles), "e", 1 << 20, on_change=lambda name, tile, v: None)
    layers = coarse.layers("m", 3, 0, 0)  # level 3: the 8 x 8 level-0 tiles below it, in one 2 x 2 tile
    assert layers is not None and max(asked) == 2 and sum(asked) == 64
    # each coarse cell is the mean of the 4 x 4 level-0 tiles' cells it covers (all equal within a tile): hand-computed
    expected = [[np.mean([tx + 8 * ty for tx in range(4 * i, 4 * i + 4) for ty in range(4 * j, 4 * j + 4)])
                 for i in range(2)] for j in range(2)]  # fmt: skip
    assert np.allclose(layers[0], expected)


def test_a_maps_conflict_clears_once_every_shard_answers_with_its_geometry():
    """A re-probe: the shard of another --resolution was replaced by one of the map's, and /health still said the
    shards publish two geometries 30 s later: the conflict was kept for as long as the API ran."""
    registry = MapRegistry()
    registry.shard_alive("m", 0, True)
    registry.tile_changed("m", (0, 0), 0.05, 2)
    source = Source({(0, 0): update(0, 0, 1.0), (1, 0): replace(update(1, 0, 1.0), resolution=0.1)})
    service = TileService(registry, source, "e", 1 << 20, on_change=lambda name, tile, v: None)
    service.sync("m")
    info = registry.get("m")
    assert info is not None and info.conflict is not None and "0.1 m" in info.conflict
    del source.tiles[(1, 0)]  # (that shard replaced by one of the map's geometry)
    registry.request_sync("m")
    service.sync("m")
    assert info.conflict is None


def test_a_map_whose_shards_all_hold_another_geometry_takes_it_and_drops_the_old_tiles():
    """A new run under a map's name with another --resolution, and an API that ran on: the API kept the first run's
    geometry for as long as it ran and refused every tile of the new run as a conflict. A complete fetch that finds
    one geometry only, another, gives the map that geometry; the old tiles, which no shard holds, go."""
    registry = MapRegistry()
    registry.shard_alive("m", 0, True)
    registry.tile_changed("m", (0, 0), 0.05, 2)
    registry.tile_changed("m", (5, 5), 0.05, 2)
    source = Source({(1, 0): replace(update(1, 0, 3.0), resolution=0.1)})
    service = TileService(registry, source, "e", 1 << 20, on_change=lambda name, tile, v: None)
    service.sync("m")
    info = registry.get("m")
    assert info is not None and (info.resolution, info.tile_size) == (0.1, 2) and info.conflict is None
    assert set(info.tiles) == {(1, 0)} and info.x_range == (1, 1) and info.y_range == (0, 0)
    assert service.layers("m", 0, 1, 0)[0][0, 0] == 3.0
    # two geometries among the shards: a conflict, the map's geometry kept
    source.tiles[(2, 0)] = update(2, 0, 1.0)
    registry.request_sync("m")
    service.sync("m")
    assert (info.resolution, info.tile_size) == (0.1, 2) and info.conflict is not None
    # an incomplete fetch (a shard did not answer) never moves the geometry
    source.tiles = {(2, 0): update(2, 0, 1.0)}
    source.fetch_all = lambda map_name: (list(source.tiles.values()), False)  # type: ignore[method-assign]
    registry.request_sync("m")
    service.sync("m")
    assert (info.resolution, info.tile_size) == (0.1, 2)


def _whole_tile(tx: int, ty: int, tile_size: int, resolution: float) -> TileUpdate:
    layers = (
        np.full((tile_size, tile_size), 1.0, np.float32),
        np.zeros((tile_size, tile_size), np.float32),
        np.ones((tile_size, tile_size), bool),
    )
    fields = dict(map="m", shard=0, z=0, tx=tx, ty=ty, row0=0, col0=0, robot="r", seq=0, published=0.0)
    return TileUpdate.of_window(layers, None, tile_size=tile_size, resolution=resolution, **fields)


def test_a_tile_querys_reply_of_another_geometry_than_the_maps_is_refused():
    """A probe's finding: the whole tiles that answer the API's tile queries were checked for their key and map only,
    so a reply with 4-cell tiles to a map of 2-cell tiles was served at level 0 as it came, and the level-1 tile made
    of it failed (HTTP 500). The reply is refused as published updates are, and counted; the right one is taken."""
    from services.api.mappers import CONFLICT_RESYNC_INTERVAL, MapperLink
    from services.keys import tile_key

    registry = MapRegistry()
    registry.token_up("m", 0)
    registry.record_stats("m", ShardAnswers({0: stats(map="m", shard=0, shards=1)}, {0: "zid-a"}))
    registry.tile_changed("m", (0, 0), 0.05, 2)  # (a published update: the map's tiles are 2 cells of 0.05 m)
    link = MapperLink(None, registry, None, None)  # type: ignore[arg-type]  # (no session: no query is sent)
    replies = [
        (tile_key("m", 0, 1, 0), _whole_tile(1, 0, *geometry).encode(), "zid-a") for geometry in ((4, 0.1), (2, 0.05))
    ]
    registry.mark_synced("m")
    taken = link._whole_tiles("m", replies)
    assert [(tile.tile_size, tile.resolution) for tile in taken] == [(2, 0.05)]
    # the shard's tile of another geometry asks for a fetch of every shard's tiles (which may find a new run's), at
    # most once in CONFLICT_RESYNC_INTERVAL s (a shard left on another geometry would have every request fetch all)
    assert registry.get("m").synced is False  # type: ignore[union-attr]
    registry.mark_synced("m")
    assert link._whole_tiles("m", replies[:1]) == [] and registry.get("m").synced is True  # type: ignore[union-attr]
    link._conflict_synced["m"] -= CONFLICT_RESYNC_INTERVAL
    assert link._whole_tiles("m", replies[:1]) == [] and registry.get("m").synced is False  # type: ignore[union-attr]
    registry.mark_synced("m")
    assert link.rejects.kinds() == {"key": 3}
    # the same tile from a process that did not answer as shard 0 (a peer's queryable on the tile keys) is refused
    assert link._whole_tiles("m", [(tile_key("m", 0, 1, 0), _whole_tile(1, 0, 2, 0.05).encode(), "zid-b")]) == []
    assert link.rejects.kinds() == {"key": 4}
    # the shard's own reply of another geometry is the map's conflict; a peer's forged one must not be (a review: one
    # forged tile of 0.1 m cells put /health at degraded until the next complete fetch)
    info = registry.get("m")
    assert info is not None and info.conflict is not None and "not 4 of 0.1 m" in info.conflict
    registry.clear_conflict("m")
    forged = [(tile_key("m", 0, 1, 0), _whole_tile(1, 0, 4, 0.1).encode(), "zid-b")]
    assert link._whole_tiles("m", forged) == [] and info.conflict is None


def test_a_shard_that_does_not_answer_in_time_is_no_rejected_message():
    """A probe: a stalled shard's stats query ended in zenoh's own error reply ("Timeout"), which the API counted
    as a message refused (3 a stall, in /health's `rejected`, for as long as it ran). A queryable's own error reply
    is still counted. Real zenoh sessions, peer to peer on loopback."""
    import threading
    import time

    import zenoh

    from services.api.mappers import MapperLink
    from services.ports import free_port
    from services.zenoh_config import build_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    release = threading.Event()
    with (
        zenoh.open(build_config("peer", listen=[endpoint])) as shards,
        zenoh.open(build_config("peer", connect=[endpoint])) as api,
    ):
        stalled = shards.declare_queryable("pg/map/m/stats/0", lambda query: release.wait(10))
        broken = shards.declare_queryable("pg/map/m/stats/1", lambda query: query.reply_err(b"no stats"))
        link = MapperLink(api, MapRegistry(), None, None)  # type: ignore[arg-type]
        deadline = time.monotonic() + 10
        while not link.rejects.kinds() and time.monotonic() < deadline:  # (until the peers see each other)
            assert link._query("pg/map/m/stats/*", timeout=1.0) == []
        release.set()
        assert link.rejects.kinds() == {"error_reply": 1}  # the broken one's; none for the one that timed out
        stalled.undeclare()
        broken.undeclare()


def test_the_variance_scale_of_a_png_does_not_wait_on_a_shard_that_cannot_answer():
    """A probe: a variance PNG without vmax takes its scale from every level-0 tile of the map, so with one shard
    stalled every such PNG, of any shard's tile, failed (503 after the query's timeout). The scale is now made of the
    tiles that can be had, a stalled shard's at their last version fetched; the map's content (GET /maps/{map})
    still says when a tile cannot be had."""
    from services.api.tiles import TileUnavailable

    registry = MapRegistry()
    registry.token_up("m", 0)
    registry.record_stats("m", ShardAnswers({0: stats(map="m", shard=0, shards=2)}, {0: "zid-a"}))
    mine = next((x, 0) for x in range(50) if tile_owner((x, 0), range(2)) == 0)
    theirs = next((x, 0) for x in range(50) if tile_owner((x, 0), range(2)) == 1)  # (shard 1: not alive)
    layers = (np.full((2, 2), 1.0, np.float32), np.full((2, 2), 4.0, np.float32), np.ones((2, 2), bool))
    fields = dict(map="m", shard=1, z=0, tx=theirs[0], ty=theirs[1], tile_size=2, resolution=0.05, row0=0, col0=0)
    wide = TileUpdate.of_window(layers, robot="r", seq=0, published=0.0, **fields)
    source = Source({mine: update(*mine, 1.0), theirs: wide})
    service = TileService(registry, source, "e", 1 << 20, on_change=lambda name, tile, v: None)
    for tile in (mine, theirs):
        registry.tile_changed("m", tile, 0.05, 2)
    both = service.content("m")  # (every tile fetched: shard 1's too, before it stalled)
    assert both.variance_scale == variance_scale(4.0)
    del source.tiles[theirs]  # shard 1 stalls, and its tile changes
    registry.tile_changed("m", theirs, 0.05, 2)
    with pytest.raises(TileUnavailable, match=str(theirs)):
        service.content("m")
    assert service.content("m", best_effort=True).variance_scale == variance_scale(4.0)  # its last version's
    never = next((x, 1) for x in range(50) if tile_owner((x, 1), range(2)) == 1)
    registry.tile_changed("m", never, 0.05, 2)  # a tile of shard 1's never fetched: not in the scale, no failure
    assert service.content("m", best_effort=True).observed == both.observed


def test_a_fetch_of_every_tile_that_falls_short_is_asked_again_and_said_in_health(monkeypatch):
    """A probe: with --query-timeout 0.01 (or a shard holding 45 000 one-cell tiles) the API's first fetch of every
    tile came back short, the map was marked synced all the same and never asked again: /maps showed 0 of 4 tiles,
    every tile 404 and /health "ok" for as long as the API ran. Now a short fetch is said in the map's stats (so
    /health is degraded) and asked again, at most every RESYNC_SHORT s, until it is whole."""
    import services.api.tiles as tiles_module
    from services.api.status import map_problems, map_stats

    class ShortFirst(Source):
        calls = 0

        def fetch_all(self, map_name):
            self.calls += 1
            if self.calls == 1:
                return [self.tiles[(0, 0)]], "shard 0 sent 1 of its 2 tiles"
            return list(self.tiles.values()), None

    clock = [100.0]
    monkeypatch.setattr(tiles_module.time, "monotonic", lambda: clock[0])
    registry = MapRegistry()
    registry.shard_alive("m", 0, True)
    registry.set_shards("m", 1)
    source = ShortFirst({(0, 0): update(0, 0, 1.0), (1, 0): update(1, 0, 2.0)})
    service = TileService(registry, source, "e", 1 << 20, on_change=lambda name, tile, v: None)
    service.sync("m")
    info = registry.get("m")
    assert info is not None and sorted(registry.tiles("m")) == [(0, 0)] and not info.synced
    assert info.incomplete == "shard 0 sent 1 of its 2 tiles"
    assert "shard 0 sent 1 of its 2 tiles" in map_problems(map_stats(info, {0: stats(shards=1)}, {}, {}, 0.0))
    clock[0] += tiles_module.RESYNC_SHORT / 2
    service.sync("m")  # (soon after: what it has is served, the shards not asked again)
    assert source.calls == 1
    clock[0] += tiles_module.RESYNC_SHORT / 2
    service.sync("m")
    assert source.calls == 2 and sorted(registry.tiles("m")) == [(0, 0), (1, 0)]
    assert info.synced and info.incomplete is None
    assert map_problems(map_stats(info, {0: stats(shards=1)}, {}, {}, 0.0)) == []
    service.sync("m")
    assert source.calls == 2  # (whole: not asked again until a shard comes up)


def test_a_fetch_of_every_tile_says_which_shard_fell_short(monkeypatch):
    from services.api.mappers import MapperLink

    link = MapperLink(None, MapRegistry(), None, None, query_timeout=0.01)  # type: ignore[arg-type]
    answered = {0: stats(shards=3, tiles_owned=2), 2: stats(shard=2, shards=3, tiles_owned=1)}
    monkeypatch.setattr(link, "stats", lambda name: answered)
    monkeypatch.setattr(link, "_query", lambda selector: [])
    sent = [update(0, 0, 1.0), update(2, 0, 1.0), replace(update(1, 0, 1.0), shard=2)]
    monkeypatch.setattr(link, "_whole_tiles", lambda name, replies, any_geometry=False: sent)
    tiles, shortfall = link.fetch_all("m")
    assert tiles == sent and shortfall is not None
    assert "shard(s) 1 did not answer" in shortfall and "shard 0 sent 2 of its 2" not in shortfall, shortfall
    assert "--query-timeout 0.01 s" in shortfall, shortfall
    answered[1] = stats(shard=1, shards=3, tiles_owned=0)
    assert link.fetch_all("m")[1] is None
    answered[0] = stats(shards=3, tiles_owned=1)  # (a tile made after its stats: a batch's scan fused between them)
    assert link.fetch_all("m")[1] is None
    answered[1] = stats(shard=1, shards=3, tiles_owned=5)
    assert "shard 1 sent 0 of its 5 tiles" in (link.fetch_all("m")[1] or "")
    monkeypatch.setattr(link, "stats", lambda name: {})
    assert "no shard's stats" in (link.fetch_all("m")[1] or "")


@settings(max_examples=300, deadline=None)
@given(
    first=st.integers(-(10**6), 10**6),
    width=st.integers(1, 1000),
    resolution=st.sampled_from([0.01, 0.025, 0.03, 0.05, 0.1, 0.2, 0.3, 1.0]),
    inside=st.floats(0.001, 0.999),
)
def test_an_export_window_on_cell_edges_holds_exactly_the_cells_between_them(first, width, resolution, inside):
    """A probe's finding: x_min = 5.05 m over 0.05 m cells (100.99999999999999 cells in floats) took in the cell
    [5.00, 5.05) m, outside the window: one cell asked for gave 2 x 2. Edges written as cell edges (i * resolution)
    give exactly the cells between them; edges inside cells take in the cells they cut."""
    low, high = first * resolution, (first + width) * resolution
    assert Window.of(low, low, high, high, resolution) == Window(first, first, first + width, first + width)
    cut = Window.of(low + inside * resolution, low, high - inside * resolution, high, resolution)
    assert (cut.ix0, cut.ix1) == (first, first + width)  # (the cells cut are in)
    assert Window.of(5.05, 5.05, 5.1, 5.1, 0.05) == Window(101, 101, 102, 102)
