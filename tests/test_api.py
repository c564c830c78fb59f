"""`posegrid api` over HTTP (a real uvicorn process) against real mapper shards on a real Zenoh router.

One stack for the module: a router, two shards mapping the test room moved to straddle the map frame's
origin (so tile indices go negative) at 2 cm with 32-cell tiles (so there are four zoom levels), the API,
and a source replaying 20 scans with weighted pose samples. The last test stops a shard.
"""

from __future__ import annotations

import io
import json
import signal
import socket
import subprocess
import threading
import time
import warnings
import zipfile

import httpx
import numpy as np
import pytest
import zenoh
from PIL import Image

from api_stack import POSEGRID, ROOT, Stack, free_port, wait_until, write_room
from mapping.export import render_pgm
from peers import put
from schemas.files import load_map, load_posed_scans
from schemas.messages import TileUpdate
from services import keys
from services.map_client import MapReader
from services.state.ownership import tile_owner
from services.zenoh_config import build_config, open_session
from test_pipeline import procs  # noqa: F401  (the fixture: processes ended by PID)

STATIC = ROOT / "services" / "api" / "static"  # the viewer's files

pytestmark = pytest.mark.slow

MAP, SHARDS, RESOLUTION, TILE, SCANS = "lab", 2, 0.02, 32, 20
SHIFT = (-1.0, -1.0)

BLOCK = zenoh.CongestionControl.BLOCK  # (tiles: as the shards send them; DROP may lose large messages)


def settled(api: str, robot: str, scans: int):
    """Stats once every shard fused ``scans`` of ``robot`` and the API has every tile update they published."""
    response = httpx.get(f"{api}/maps/{MAP}/stats", timeout=30)
    if response.status_code == 404:  # no shard of the map is up yet (they warm their kernels first)
        return None
    stats = response.json()
    shards = stats["per_shard"]
    done = len(shards) == SHARDS and all(
        s["answered"] and s["scans_fused"].get(robot) == scans and s["tile_updates_received"] == s["tile_updates"]
        for s in shards
    )
    return stats if done else None


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    folder = tmp_path_factory.mktemp("api")
    processes = Stack(folder)
    try:
        processes.router()
        processes.mappers(SHARDS, MAP, "--resolution", str(RESOLUTION), "--tile-size", str(TILE))
        processes.api()
        processes.source(write_room(folder / "room.npz", SHIFT), MAP, SHARDS)
        wait_until(lambda: settled(processes.api_url, "robot0", SCANS), 120, "the shards to fuse the replay")
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


def shards_grid(session):
    """The map as the shards hold it, asked over Zenoh without the API."""
    return MapReader(session, MAP).assemble(SHARDS, RESOLUTION)


def npz(response: httpx.Response) -> dict[str, np.ndarray]:
    assert response.status_code == 200, response.text
    with np.load(io.BytesIO(response.content)) as data:
        return {key: data[key] for key in data.files}


def problem(response: httpx.Response, status: int) -> str:
    assert response.status_code == status, response.text
    assert response.headers["content-type"] == "application/json"
    detail = response.json()["detail"]
    assert isinstance(detail, str) and detail
    return detail


# ------------------------------------------------------------------------------------------ maps


def test_maps_report_extent_resolution_cells_and_shards(api, session):
    grid = shards_grid(session)
    tiles = grid.keys()
    listed = httpx.get(f"{api}/maps", timeout=30).json()
    assert [m["name"] for m in listed] == [MAP]
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
    assert summary == listed[0]
    assert (summary["resolution"], summary["tile_size"], summary["shards"]) == (RESOLUTION, TILE, SHARDS)
    assert summary["shards_alive"] == [0, 1]
    assert summary["tiles"] == len(tiles)
    bounds = summary["tile_bounds"]
    assert (bounds["x_min"], bounds["x_max"]) == (min(t[0] for t in tiles), max(t[0] for t in tiles))
    assert (bounds["y_min"], bounds["y_max"]) == (min(t[1] for t in tiles), max(t[1] for t in tiles))
    assert bounds["x_min"] < 0 and bounds["y_min"] < 0
    assert summary["extent"]["x_min"] == pytest.approx(bounds["x_min"] * TILE * RESOLUTION)
    raster = grid.rasterize()
    assert summary["cells"] == {
        "per_tile": TILE * TILE,
        "total": len(tiles) * TILE * TILE,
        "observed": int(raster["observed"].sum()),
    }
    height, width = raster["observed"].shape
    observed = summary["observed_extent"]
    assert observed["x_min"] == pytest.approx(raster["origin"][0])
    assert observed["y_max"] == pytest.approx(raster["origin"][1] + height * RESOLUTION)
    assert observed["x_max"] - observed["x_min"] == pytest.approx(width * RESOLUTION)
    assert summary["max_zoom"] == 3  # x tiles -2..5 -> -1..2 -> -1..1 -> -1..0 (at most 2 x 2)


def test_unknown_map_is_404_everywhere(api):
    for path in (
        "/maps/nowhere",
        "/maps/nowhere/tiles/0/0/0.png",
        "/maps/nowhere/tiles/0/0/0.npz",
        "/maps/nowhere/stats",
        "/maps/nowhere/export?format=npz",
    ):
        detail = problem(httpx.get(api + path, timeout=30), 404)
        assert "nowhere" in detail and MAP in detail, path


# ------------------------------------------------------------------------------------------ tiles


def test_level0_tiles_equal_the_shards_tiles(api, session):
    grid = shards_grid(session)
    for tile in grid.keys():  # noqa: SIM118  # a TiledGrid, not a dict: keys() lists its tiles, it has no __iter__
        data = npz(httpx.get(f"{api}/maps/{MAP}/tiles/0/{tile[0]}/{tile[1]}.npz", timeout=30))
        logodds, variance, observed = grid.tile_arrays(tile)
        np.testing.assert_array_equal(data["logodds"], logodds)
        np.testing.assert_array_equal(data["variance"], variance)
        np.testing.assert_array_equal(data["observed"], observed)
        np.testing.assert_allclose(data["origin"], grid.tile_origin(tile))
        assert float(data["resolution"]) == RESOLUTION


def reference_parent(children: list[dict | None]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The documented rule, written independently: NaN-mean over the observed cells of each 2 x 2 block."""
    size = 2 * TILE
    logodds, variance = np.full((size, size), np.nan), np.full((size, size), np.nan)
    for (dx, dy), child in zip(((0, 0), (1, 0), (0, 1), (1, 1)), children):
        if child is not None:
            block = (slice(dy * TILE, (dy + 1) * TILE), slice(dx * TILE, (dx + 1) * TILE))
            logodds[block] = np.where(child["observed"], child["logodds"], np.nan)
            variance[block] = np.where(child["observed"], child["variance"], np.nan)
    blocks = [
        layer.reshape(TILE, 2, TILE, 2).transpose(0, 2, 1, 3).reshape(TILE, TILE, 4) for layer in (logodds, variance)
    ]
    seen = ~np.isnan(blocks[0]).all(axis=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "mean of empty slice" for unobserved blocks
        means = [np.nan_to_num(np.nanmean(b, axis=2)) for b in blocks]
    return means[0], means[1], seen


def test_coarse_tiles_are_the_combination_of_their_four_children(api):
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
    bounds = summary["tile_bounds"]
    tiles: dict[tuple[int, int, int], dict | None] = {}
    with httpx.Client(base_url=api, timeout=30) as client:
        for z in range(summary["max_zoom"] + 1):
            for x in range(bounds["x_min"] >> z, (bounds["x_max"] >> z) + 1):
                for y in range(bounds["y_min"] >> z, (bounds["y_max"] >> z) + 1):
                    tiles[(z, x, y)] = npz(client.get(f"/maps/{MAP}/tiles/{z}/{x}/{y}.npz"))
    checked = 0
    for (z, x, y), parent in tiles.items():
        if z == 0:
            continue
        children = [tiles.get((z - 1, 2 * x + dx, 2 * y + dy)) for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1))]
        logodds, variance, observed = reference_parent(children)
        np.testing.assert_array_equal(parent["observed"], observed)
        np.testing.assert_allclose(parent["logodds"], logodds, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(parent["variance"], variance, rtol=1e-6, atol=1e-6)
        cell = RESOLUTION * 2**z
        assert float(parent["resolution"]) == pytest.approx(cell)
        np.testing.assert_allclose(parent["origin"], [x * TILE * cell, y * TILE * cell])
        checked += int(parent["observed"].any())
    assert checked >= 3 + 2 + 1  # observed tiles at levels 1, 2 and 3


def test_png_tiles_and_layers(api):
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
    base = f"{api}/maps/{MAP}/tiles/0/0/0.png"
    images = {}
    for layer in ("probability", "logodds", "variance"):
        response = httpx.get(base, params={"layer": layer}, timeout=30)
        assert response.status_code == 200 and response.headers["content-type"] == "image/png"
        images[layer] = np.asarray(Image.open(io.BytesIO(response.content)).convert("RGB"))
        assert images[layer].shape == (TILE, TILE, 3)
    assert not np.array_equal(images["probability"], images["variance"])
    red = images["variance"][..., 0].astype(int) - images["variance"][..., 2]
    assert (red > 60).any(), "the variance ramp shows no red or yellow cell"
    default = httpx.get(base, params={"layer": "variance"}, timeout=30)
    explicit = httpx.get(base, params={"layer": "variance", "vmax": summary["variance_scale"]}, timeout=30)
    assert default.headers["etag"] == explicit.headers["etag"] and default.content == explicit.content
    other = httpx.get(base, params={"layer": "variance", "vmax": summary["variance_scale"] / 4}, timeout=30)
    assert other.headers["etag"] != explicit.headers["etag"]


def test_npz_tile_is_a_map_file_or_one_layer(api, tmp_path):
    response = httpx.get(f"{api}/maps/{MAP}/tiles/1/0/0.npz", timeout=30)
    path = tmp_path / "tile.npz"
    path.write_bytes(response.content)
    tile = load_map(path)  # the map-file loader validates every key
    assert tile.logodds.shape == (TILE, TILE) and tile.resolution == pytest.approx(2 * RESOLUTION)
    one = npz(httpx.get(f"{api}/maps/{MAP}/tiles/1/0/0.npz", params={"layer": "variance"}, timeout=30))
    assert set(one) == {"variance", "observed", "origin", "resolution"}
    np.testing.assert_array_equal(one["variance"], tile.variance)


def test_cached_answer_matches_the_first_and_etag_round_trip(api):
    url = f"{api}/maps/{MAP}/tiles/2/0/0.png?layer=logodds"
    first, second = httpx.get(url, timeout=30), httpx.get(url, timeout=30)
    assert first.status_code == second.status_code == 200
    drop = {"date"}
    assert {k: v for k, v in first.headers.items() if k not in drop} == {
        k: v for k, v in second.headers.items() if k not in drop
    }
    assert first.content == second.content
    etag = first.headers["etag"]
    assert first.headers["cache-control"] == "no-cache"
    not_modified = httpx.get(url, headers={"If-None-Match": etag}, timeout=30)
    assert not_modified.status_code == 304 and not_modified.content == b""
    assert not_modified.headers["etag"] == etag
    assert httpx.get(url, headers={"If-None-Match": '"something-else"'}, timeout=30).status_code == 200
    assert httpx.get(url, headers={"If-None-Match": f'"x", {etag}'}, timeout=30).status_code == 304


def test_head_answers_as_get_without_the_body(api):
    """HEAD (curl -I, uptime monitors) gets GET's status and headers, Content-Length included, and no body; the
    event stream answers HEAD at once instead of streaming."""
    drop = {"date"}
    for path in (
        f"/maps/{MAP}/tiles/3/0/0.png",
        f"/maps/{MAP}/tiles/3/0/0.png",  # FastAPI, then the tile cache
        f"/maps/{MAP}/tiles/0/0/0.npz?layer=logodds",
        f"/maps/{MAP}/export?format=pgm",
        "/maps",
        "/",
        "/maps/nope",
        f"/maps/{MAP}/tiles/0/0/0.png?layer=nope",
    ):
        get, head = httpx.get(f"{api}{path}", timeout=30), httpx.head(f"{api}{path}", timeout=30)
        assert head.status_code == get.status_code, path
        assert head.content == b"" and get.content, path
        assert {k: v for k, v in head.headers.items() if k not in drop} == {
            k: v for k, v in get.headers.items() if k not in drop
        }, path
        assert int(head.headers["content-length"]) == len(get.content), path
    for _ in range(20):
        events = httpx.head(f"{api}/events", timeout=10)
        assert events.status_code == 200 and events.headers["content-type"].startswith("text/event-stream")
    # the server goes on, and no event-hub client is left behind (an audit found some left to the garbage collector)
    wait_until(lambda: httpx.get(f"{api}/health", timeout=30).json()["event_clients"] == 0, 5, "HEAD's clients to go")


def test_bad_tile_requests_are_4xx_with_a_reason(api):
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
    b, top = summary["tile_bounds"], summary["max_zoom"]
    tiles = f"{api}/maps/{MAP}/tiles"
    assert "coarsest" in problem(httpx.get(f"{tiles}/{top + 1}/0/0.png", timeout=30), 404)
    assert "outside" in problem(httpx.get(f"{tiles}/0/{b['x_max'] + 1}/0.png", timeout=30), 404)
    assert "outside" in problem(httpx.get(f"{tiles}/1/0/{(b['y_min'] >> 1) - 1}.npz", timeout=30), 404)
    assert "'z'" in problem(httpx.get(f"{tiles}/-1/0/0.png", timeout=30), 422)
    assert "'y'" in problem(httpx.get(f"{tiles}/0/0/north.png", timeout=30), 422)
    assert "'layer'" in problem(httpx.get(f"{tiles}/0/0/0.png", params={"layer": "colour"}, timeout=30), 422)
    assert "'vmax'" in problem(
        httpx.get(f"{tiles}/0/0/0.png", params={"layer": "variance", "vmax": 0}, timeout=30), 422
    )
    assert "'vmax'" in problem(
        httpx.get(f"{tiles}/0/0/0.png", params={"layer": "variance", "vmax": "inf"}, timeout=30), 422
    )
    assert ".png" in problem(httpx.get(f"{tiles}/0/0/0.jpg", timeout=30), 404)
    assert "'format'" in problem(httpx.get(f"{api}/maps/{MAP}/export", params={"format": "tiff"}, timeout=30), 422)
    assert "'format'" in problem(httpx.get(f"{api}/maps/{MAP}/export", timeout=30), 422)
    # a fuzz's findings: a parameter given twice was read at its last value (vmax=-1&vmax=2 served,
    # format=npz&format=png as a PNG); a 19-digit integer was said not to be ASCII digits; a 405 said Allow: GET
    # where HEAD is answered too
    repeated = problem(httpx.get(f"{tiles}/0/0/0.png?layer=variance&vmax=-1&vmax=2", timeout=30), 422)
    assert "'vmax'" in repeated and "more than once" in repeated
    assert "'format'" in problem(httpx.get(f"{api}/maps/{MAP}/export?format=npz&format=png", timeout=30), 422)
    assert "at most 18 ASCII digits" in problem(httpx.get(f"{tiles}/0/4611686018427387904/0.png", timeout=30), 422)
    refused = httpx.post(f"{tiles}/0/0/0.png", timeout=30)
    assert refused.status_code == 405 and refused.headers["allow"] == "GET, HEAD", refused.headers


def test_the_tile_cache_takes_only_what_fastapi_would_answer_alike(api):
    """Arabic-Indic and fullwidth digits are no integers or numbers to FastAPI (422), and the cache in front of
    it must not answer them with the ASCII tile it holds (it did: \\d matches them and int() reads them)."""
    b = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()["tile_bounds"]
    x, y = b["x_min"], b["y_min"]
    tile = f"{api}/maps/{MAP}/tiles/0/{x}/{y}.png"
    for params in ({}, {"layer": "variance", "vmax": "4"}):
        assert httpx.get(tile, params=params, timeout=30).status_code == 200  # now cached
    arabic = "".join(chr(0x660 + int(d)) if d.isdigit() else d for d in str(x))  # U+0660.. are 0-9
    assert "'x'" in problem(httpx.get(f"{api}/maps/{MAP}/tiles/0/{arabic}/{y}.png", timeout=30), 422)
    assert "'vmax'" in problem(httpx.get(tile, params={"layer": "variance", "vmax": "\uff14"}, timeout=30), 422)


# ------------------------------------------------------------------------------------------ export


def test_export_equals_the_shards_state(api, session, tmp_path):
    raster = shards_grid(session).rasterize()
    response = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz"}, timeout=60)
    assert response.headers["content-disposition"] == f'attachment; filename="{MAP}.npz"'
    path = tmp_path / "export.npz"
    path.write_bytes(response.content)
    exported = load_map(path)
    for key in ("logodds", "probability", "observed", "variance"):
        np.testing.assert_array_equal(getattr(exported, key), raster[key], err_msg=key)
    np.testing.assert_allclose(exported.origin, raster["origin"])
    assert exported.resolution == RESOLUTION

    archive = zipfile.ZipFile(
        io.BytesIO(httpx.get(f"{api}/maps/{MAP}/export", params={"format": "pgm"}, timeout=60).content)
    )
    assert sorted(archive.namelist()) == [f"{MAP}.pgm", f"{MAP}.yaml"]
    pgm, yaml = render_pgm(raster, image_name=f"{MAP}.pgm")
    assert archive.read(f"{MAP}.pgm") == pgm and archive.read(f"{MAP}.yaml").decode() == yaml

    # a pgm is occupancy only (the layer was ignored, silently); npz+layer: tests/test_api_hardening.py
    refused = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "pgm", "layer": "variance"}, timeout=60)
    assert refused.status_code == 422 and "pgm" in refused.json()["detail"]
    png = httpx.get(f"{api}/maps/{MAP}/export", params={"format": "png", "layer": "variance"}, timeout=60)
    assert png.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(png.content)).size == raster["observed"].shape[::-1]


# ------------------------------------------------------------------------------------------ robots


def test_robot_pose_and_trajectory(api, stack):
    posed = load_posed_scans(stack.logs / "room.npz")
    samples, weights = posed.poses.samples[-1], posed.poses.weights[-1]
    assert [r["robot"] for r in httpx.get(f"{api}/robots", timeout=30).json()] == ["robot0"]
    pose = httpx.get(f"{api}/robots/robot0/pose", timeout=30).json()
    assert (pose["seq"], pose["form"], pose["samples_total"]) == (SCANS - 1, "samples", len(weights))
    np.testing.assert_allclose(pose["samples"], samples)
    np.testing.assert_allclose(pose["weights"], weights)
    np.testing.assert_allclose(pose["mean"][:2], np.average(samples[:, :2], axis=0, weights=weights))
    np.testing.assert_allclose(
        pose["covariance"][0][0], np.average((samples[:, 0] - pose["mean"][0]) ** 2, weights=weights)
    )
    fewer = httpx.get(f"{api}/robots/robot0/pose", params={"max_samples": 3}, timeout=30).json()
    assert len(fewer["samples"]) == 3 and sum(fewer["weights"]) == pytest.approx(1.0)
    track = httpx.get(f"{api}/robots/robot0/trajectory", timeout=30).json()
    assert track["seq"] == list(range(SCANS))
    assert track["x"][-1] == pytest.approx(pose["mean"][0])
    assert "robot9" in problem(httpx.get(f"{api}/robots/robot9/pose", timeout=30), 404)
    assert "robot9" in problem(httpx.get(f"{api}/robots/robot9/trajectory", timeout=30), 404)
    problem(httpx.get(f"{api}/robots/robot0/pose", params={"max_samples": 0}, timeout=30), 422)
    for route in ("pose", "trajectory"):  # (a name no robot may have: 404 before, as if it could)
        assert "reserved" in problem(httpx.get(f"{api}/robots/map/{route}", timeout=30), 422)


# ------------------------------------------------------------------------------------------ stats, health


def test_stats_and_health(api):
    stats = httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).json()
    assert (stats["shards"], stats["shards_alive"]) == (SHARDS, [0, 1])
    assert stats["scans_fused"] == {"robot0": SCANS} and stats["lag_scans"] == {"robot0": 0}
    assert stats["scans_discarded"] == {"robot0": 0}
    for shard in stats["per_shard"]:
        assert shard["alive"] and shard["answered"]
        # every scan arrived; a shard that joined late (kernels compiling on a fresh install) also has some of
        # them again from the source's history, which it counts as received and fuses once
        assert shard["received"]["pg/robot0/scan"] >= SCANS and shard["tiles_owned"] > 0
        assert shard["last_tile_update_age_s"] >= 0
    health = httpx.get(f"{api}/health", timeout=30).json()
    assert health["status"] == "ok"
    assert health["maps"][MAP]["shards_alive"] == [0, 1] and "robot0" in health["robots"]


def test_bad_zenoh_data_is_counted_by_key_never_trusted(api, session):
    """Garbage, and a valid tile on the wrong key, are rejected per key; the API keeps serving."""
    garbage_key = keys.tile_key(MAP, 0, 0, 0)
    put(session, garbage_key, b"\x93not msgpack")
    put(session, keys.robot_key("robot0", keys.POSE), b"\x81\xa4type\xa9PoseNoise")
    tile = TileUpdate.of_window(
        (np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32), np.ones((1, 1), bool)),
        map=MAP,
        shard=0,
        z=0,
        tx=0,
        ty=0,
        tile_size=TILE,
        resolution=RESOLUTION,
        row0=0,
        col0=0,
        robot="robot0",
        seq=0,
        published=0.0,
    )
    wrong_key = keys.tile_key(MAP, 0, 7, 7)
    put(session, wrong_key, tile.encode())

    def counted():
        rejected = httpx.get(f"{api}/health", timeout=30).json()["rejected"]
        return all(rejected.get(k, 0) >= 1 for k in (garbage_key, wrong_key, "pg/robot0/pose")) and rejected

    wait_until(counted, 30, "the API to count the bad messages")
    shards = wait_until(
        lambda: [
            s
            for s in httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).json()["per_shard"]
            if s["rejected"].get("pg/robot0/pose")
        ],
        30,
        "the shards to count the bad pose",
    )
    assert len(shards) == SHARDS
    stats = httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).json()
    assert stats["rejected"]["pg/robot0/pose"] >= SHARDS + 1  # both shards and the API
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
    assert summary["tile_bounds"]["x_max"] < 7  # the misplaced tile was not taken
    assert httpx.get(f"{api}/maps/{MAP}/tiles/0/0/0.png", timeout=30).status_code == 200


# ------------------------------------------------------------------------------------------ live changes


def read_events(url: str, events: list, stop: threading.Event) -> None:
    """Collect (event, data) pairs from a server-sent event stream until ``stop`` is set."""
    with httpx.stream("GET", url, timeout=httpx.Timeout(30, read=None)) as response:
        name = None
        for line in response.iter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                events.append((name, json.loads(line[6:])))
            if stop.is_set():
                return


def test_tiles_change_etags_change_and_events_flow(api, stack, tmp_path):
    """A second robot maps the same room: the tiles it touches get new ETags and the stream says so."""
    events: list = []
    stop = threading.Event()
    reader = threading.Thread(target=read_events, args=(f"{api}/events", events, stop), daemon=True)
    reader.start()
    wait_until(lambda: any(name == "hello" for name, _ in events), 30, "the event stream to open")
    url = f"{api}/maps/{MAP}/tiles/0/1/0.npz"
    before = httpx.get(url, timeout=30)
    etag = before.headers["etag"]

    stack.source(write_room(tmp_path / "second.npz", SHIFT, seed=1), MAP, SHARDS, robot="robot1")
    wait_until(lambda: settled(api, "robot1", SCANS), 120, "the shards to fuse the second robot's scans")
    after = httpx.get(url, headers={"If-None-Match": etag}, timeout=30)
    assert after.status_code == 200 and after.headers["etag"] != etag
    assert not np.array_equal(npz(after)["variance"], npz(before)["variance"])
    assert httpx.get(url, headers={"If-None-Match": after.headers["etag"]}, timeout=30).status_code == 304

    def seen():
        tiles = {
            (tx, ty) for name, data in events if name == "tiles" and data["map"] == MAP for tx, ty, _ in data["tiles"]
        }
        poses = [data for name, data in events if name == "pose" and data["robot"] == "robot1"]
        return (1, 0) in tiles and poses and poses

    poses = wait_until(seen, 30, "tiles and pose events of the second robot")
    stop.set()
    assert poses[-1]["seq"] == SCANS - 1 and len(poses[-1]["samples"]) == 10
    assert sorted(r["robot"] for r in httpx.get(f"{api}/robots", timeout=30).json()) == ["robot0", "robot1"]


# ------------------------------------------------------------------------------------------ docs, viewer, CLI


def test_openapi_describes_every_parameter_and_error(api):
    spec = httpx.get(f"{api}/openapi.json", timeout=30).json()
    assert {
        "/maps",
        "/maps/{map}",
        "/maps/{map}/tiles/{z}/{x}/{y}.png",
        "/maps/{map}/tiles/{z}/{x}/{y}.npz",
        "/maps/{map}/export",
        "/maps/{map}/stats",
        "/health",
        "/robots/{robot}/pose",
        "/robots/{robot}/trajectory",
        "/events",
    } <= set(spec["paths"])
    assert "security" not in spec and "securitySchemes" not in spec.get("components", {})  # no token here
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            # the guard's answers, on every route: a Host it does not answer to, a missing or wrong token
            assert {"400", "401"} <= set(operation["responses"]), f"{method} {path}"
            assert "WWW-Authenticate" in operation["responses"]["401"]["headers"], f"{method} {path}"
            if "503" in operation["responses"]:
                assert "Retry-After" in operation["responses"]["503"]["headers"], f"{method} {path}"
            for parameter in operation.get("parameters", []):
                assert parameter.get("description"), f"{method} {path}: {parameter['name']} has no description"
            if "{" in path:
                assert "404" in operation["responses"], f"{method} {path} documents no 404"
            if operation.get("parameters"):
                schema = operation["responses"]["422"]["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/Problem"}, f"{method} {path}"
    assert "m" in spec["components"]["schemas"]["Extent"]["properties"]["x_min"]["description"]
    # the bounds in JSON Schema's words (a probe: pydantic's ge / le / gt, which no client or validator reads)
    tile = {p["name"]: p["schema"] for p in spec["paths"]["/maps/{map}/tiles/{z}/{x}/{y}.png"]["get"]["parameters"]}
    assert (tile["z"]["minimum"], tile["z"]["maximum"]) == (0, 32) and "ge" not in tile["z"]
    vmax = next(s for s in tile["vmax"]["anyOf"] if s.get("type") == "number")
    assert vmax["exclusiveMinimum"] == 0 and "gt" not in vmax
    pose = spec["paths"]["/robots/{robot}/pose"]["get"]["parameters"]
    samples = next(p["schema"] for p in pose if p["name"] == "max_samples")
    assert next(s for s in samples["anyOf"] if s.get("type") == "integer")["minimum"] == 1


def test_viewer_page_and_assets_are_served(api):
    page = httpx.get(f"{api}/", timeout=30)
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "static/viewer.js" in page.text
    for asset, kind in (("", "text/html"), ("static/viewer.js", "javascript"), ("static/viewer.css", "text/css")):
        response = httpx.get(f"{api}/{asset}", timeout=30)
        assert response.status_code == 200 and kind in response.headers["content-type"]
        assert "https://" not in response.text and "http://" not in response.text, f"{asset} loads an outside asset"
        # a Range is ignored, whatever its unit or form (HTTP lets a server ignore it; a unit it does not know it
        # must): the whole file, 200, where Starlette answered a plain-text 400 to the malformed ones
        whole = (STATIC / (asset.removeprefix("static/") or "index.html")).read_bytes()
        for ranges in ("bytes=0-5", "items=0-5", "bytes=-1,0-0,5-2", "bytes=abc", "bytes=99999999-"):
            ranged = httpx.get(f"{api}/{asset}", headers={"Range": ranges}, timeout=30)
            assert (ranged.status_code, ranged.content) == (200, whole), (asset, ranges, ranged.text[:200])
        # and not offered: Starlette's FileResponse said Accept-Ranges: bytes, which these files are not served in
        assert "accept-ranges" not in response.headers, asset


def test_api_command_rejects_a_taken_port():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = subprocess.run(
            [*POSEGRID, "api", "--port", str(port)], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
        )
    assert result.returncode == 2 and "pick another --port" in result.stderr
    result = subprocess.run(
        [*POSEGRID, "api", "--port", "70000"], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2 and "--port" in result.stderr


def test_a_taken_router_port_is_refused_before_anything_starts_and_a_foreign_host_is_named(tmp_path, capsys):
    """A probe: `posegrid run --router-port P` with P held by another run's router started its children anyway;
    its router failed, its launcher found the other run's shard 0 of 'main' through P and started its SLAM node and
    source on that run's router. And `api --host 256.1.1.1` said "pick another --port"."""
    from services.cli import main
    from services.commands.api import listen_on
    from services.errors import UsageError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        export = tmp_path / "map.npz"
        assert main(["run", "--router-port", str(port), "--no-api", "--export", str(export)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(f"127.0.0.1:{port} (Address already in use); pick another --router-port"), err
        assert not export.exists()
    with pytest.raises(UsageError, match=r"; give --host an address of this machine \(e\.g\. 127\.0\.0\.1\)$"):
        listen_on("192.0.2.1", 0)  # (TEST-NET-1: no address of this machine, and no name to look up)


def test_two_apis_started_on_one_port_at_once_one_serves_and_the_other_says_so_in_one_line(procs):  # noqa: F811
    """Both passed a check that bound the port and let it go again; the loser then said "serving on ..." and failed
    in uvicorn (its raw message, exit 3; `posegrid run` took that for a crash and restarted it). The socket is now
    bound before anything says it serves: one serves, the other exits 2 with one line."""
    router_port, port = free_port(), free_port()
    procs([*POSEGRID, "router", "--listen", f"tcp/127.0.0.1:{router_port}"], cwd=ROOT).wait_for("routing")
    argv = [*POSEGRID, "api", "--port", str(port), "--connect", f"tcp/127.0.0.1:{router_port}"]
    apis = [procs(argv, cwd=ROOT) for _ in range(2)]
    wait_until(lambda: any(api.process.poll() is not None for api in apis), 60, "one of the two APIs to end")
    (loser,) = [api for api in apis if api.process.poll() is not None]
    (winner,) = [api for api in apis if api is not loser]
    loser.wait_for("pick another --port")  # (its output is read on a thread: all of it, once this line is in)
    assert loser.process.returncode == 2 and len(loser.lines) == 1, loser.output()
    assert "serving on" not in loser.output()
    assert httpx.get(f"http://127.0.0.1:{port}/health", timeout=30).status_code in (200, 503)
    assert winner.process.poll() is None


# ------------------------------------------------------------------------------------------ last: a shard stops


def test_tile_updates_no_shard_stands_behind_do_not_break_the_map(api, session):
    """Well-formed updates on the right keys, for a tile no shard holds (7, 7), from each shard in turn, and for
    a map no shard serves: the non-owner's and the unknown map's are refused; the owner's is taken, and the
    first request that asks the owner for that tile finds it does not hold it and drops it. (Late in the module:
    the owner's update counts as received, which `settled` would see.)"""

    def forged(map_name: str, shard: int) -> bytes:
        return TileUpdate.of_window(
            (np.full((TILE, TILE), 3.0, np.float32), np.zeros((TILE, TILE), np.float32), np.ones((TILE, TILE), bool)),
            map=map_name,
            shard=shard,
            z=0,
            tx=7,
            ty=7,
            tile_size=TILE,
            resolution=RESOLUTION,
            row0=0,
            col0=0,
            robot="robot0",
            seq=0,
            published=0.0,
        ).encode()

    httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).raise_for_status()  # the API knows the shard count
    for shard in range(SHARDS):
        session.put(keys.tile_key(MAP, 0, 7, 7), forged(MAP, shard), congestion_control=BLOCK)
    session.put(keys.tile_key("ghost", 0, 7, 7), forged("ghost", 0), congestion_control=BLOCK)
    wait_until(
        lambda: httpx.get(f"{api}/health", timeout=30).json()["rejected"].get(keys.tile_key("ghost", 0, 7, 7)),
        30,
        "the API to refuse the update of a map no shard serves",
    )
    maps = httpx.get(f"{api}/maps", timeout=30)
    assert maps.status_code == 200 and [m["name"] for m in maps.json()] == [MAP]
    summary = httpx.get(f"{api}/maps/{MAP}", timeout=30)
    assert summary.status_code == 200 and summary.json()["tile_bounds"]["x_max"] < 7
    assert problem(httpx.get(f"{api}/maps/{MAP}/tiles/0/7/7.png", timeout=30), 404)
    assert httpx.get(f"{api}/maps/{MAP}/tiles/0/0/0.png", timeout=30).status_code == 200
    assert httpx.get(f"{api}/health", timeout=30).json()["status"] == "ok"


def test_a_stalled_shard_holds_up_only_its_own_tiles(api, stack, session):
    """A stopped shard (SIGSTOP) stays alive to the router until its Zenoh lease (10 s) runs out, and a query it
    should answer waits for it. Its own tiles wait; a tile of the other shard, the robot routes and /health must
    not. They did: every tile query waited for every shard's queryable, 40 tile requests waiting took FastAPI's
    whole thread pool, /robots included, and /health waited out the query timeout. A second API with a 60 s
    query timeout is used, so that nothing ends before the lease does; updates announced while the shard is
    stopped make it ask for the two tiles again."""
    port = free_port()
    stack.start("api-stall", "api", "--port", str(port), "--query-timeout", "60")
    url = f"http://127.0.0.1:{port}"
    owned = {0: [], 1: []}
    for tile in sorted(shards_grid(session).keys()):
        owned[tile_owner(tile, range(SHARDS))].append(tile)
    (x, y), (sx, sy) = owned[0][0], owned[1][0]

    def etag() -> str | None:
        try:
            response = httpx.get(f"{url}/maps/{MAP}/tiles/0/{x}/{y}.png", timeout=8)  # under the lease
        except httpx.ConnectError:  # not listening yet
            return None
        return response.headers["etag"] if response.status_code == 200 else None

    before = wait_until(etag, 60, "the second API to serve a tile")
    stalled, waiting, threads = stack.processes["mapper1"], [], []
    stalled.send_signal(signal.SIGSTOP)
    try:
        for (tx, ty), shard in (((sx, sy), 1), ((x, y), 0)):  # in this order: one subscriber, one session
            session.put(
                keys.tile_key(MAP, 0, tx, ty),
                TileUpdate.of_window(
                    (
                        np.zeros((TILE, TILE), np.float32),
                        np.zeros((TILE, TILE), np.float32),
                        np.zeros((TILE, TILE), bool),
                    ),
                    map=MAP,
                    shard=shard,
                    z=0,
                    tx=tx,
                    ty=ty,
                    tile_size=TILE,
                    resolution=RESOLUTION,
                    row0=0,
                    col0=0,
                    robot="robot0",
                    seq=0,
                    published=0.0,
                ).encode(),
                congestion_control=BLOCK,
            )
        # shard 0's tile is asked for again and comes back while shard 1 is stopped (a request that waited for
        # shard 1 would raise ReadTimeout here)
        wait_until(lambda: etag() not in (None, before), 30, "shard 0's tile under its new version")

        def ask_stalled(vmax: int) -> None:
            try:
                waiting.append(
                    httpx.get(
                        f"{url}/maps/{MAP}/tiles/0/{sx}/{sy}.png",
                        params={"layer": "variance", "vmax": vmax},
                        timeout=90,
                    ).status_code
                )
            except httpx.HTTPError as exc:
                waiting.append(type(exc).__name__)

        threads += [threading.Thread(target=ask_stalled, args=(vmax,), daemon=True) for vmax in range(1, 61)]
        for thread in threads:
            thread.start()
        time.sleep(3.0)  # for the requests to be in (nothing outside the API shows where they are)
        assert not waiting, waiting  # they wait for shard 1
        assert httpx.get(f"{url}/robots", timeout=5).status_code == 200
        assert httpx.get(f"{url}/robots/robot9/pose", timeout=5).status_code == 404
        health = httpx.get(f"{url}/health", timeout=5).json()  # the shards' stats are asked for 2 s at most
        assert health["status"] == "degraded" and health["maps"][MAP]["shards_alive"] == [0, 1]
    finally:
        stalled.send_signal(signal.SIGCONT)
    for thread in threads:
        thread.join(120)
    assert waiting == [200] * 60  # shard 1 answers once it runs again


def test_a_stopped_shard_shows_in_health_and_stops_the_export(api, stack):
    stack.processes["mapper1"].send_signal(signal.SIGINT)
    stack.processes["mapper1"].wait(30)
    health = wait_until(
        lambda: (h := httpx.get(f"{api}/health", timeout=30).json())["status"] == "degraded" and h,
        30,
        "health to report the stopped shard",
    )
    assert health["maps"][MAP]["shards_alive"] == [0]
    stats = httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).json()
    assert [(s["shard"], s["alive"], s["answered"]) for s in stats["per_shard"]] == [(0, True, True), (1, False, False)]
    detail = problem(httpx.get(f"{api}/maps/{MAP}/export", params={"format": "npz"}, timeout=60), 503)
    assert "shard" in detail
    # the map list and the map's summary still answer (they were 503 for every map while one shard was down); what
    # needs every tile is null unless the API holds them all already
    listed = httpx.get(f"{api}/maps", timeout=30)
    assert listed.status_code == 200 and [m["shards_alive"] for m in listed.json() if m["name"] == MAP] == [[0]]
    one = httpx.get(f"{api}/maps/{MAP}", timeout=30)
    assert one.status_code == 200 and one.json()["tiles"] > 0
    # started again after the sources ended: every shard answers, but shard 1's scans cannot come back (no source
    # holds a history any more); the lag says so and the status stays degraded (it said ok)
    stack.start(
        "mapper1",
        "mapper",
        "--shard",
        "1",
        "--shards",
        str(SHARDS),
        "--map",
        MAP,
        "--resolution",
        str(RESOLUTION),
        "--tile-size",
        str(TILE),
    )
    health = wait_until(
        lambda: (
            (h := httpx.get(f"{api}/health", timeout=30).json())["maps"][MAP]["shards_alive"] == [0, 1]
            and h["maps"][MAP]["lag_scans"].get("robot0", 0) > 0
            and h
        ),
        60,
        "the restarted shard to answer with its lag",
    )
    assert "robot0/source" not in health["processes_alive"]
    wait_until(
        lambda: httpx.get(f"{api}/health", timeout=30).json()["status"] == "degraded",
        30,
        "health to call the scans that cannot come stranded",
    )


def test_a_map_whose_only_tiles_may_lie_on_a_down_shard_is_503_not_empty(api, stack):
    """Shard 0 of 2 of a new map runs and holds nothing; shard 1 never started. A tile and an export are 503 (the
    data may be on shard 1), not 404 / 409 "no tiles yet" (they were)."""
    stack.start("half0", "mapper", "--shard", "0", "--shards", "2", "--map", "half")
    wait_until(
        lambda: (
            httpx.get(f"{api}/maps/half", timeout=30).status_code == 200
            and httpx.get(f"{api}/maps/half", timeout=30).json()["shards_alive"] == [0]
        ),
        60,
        "map 'half' to show",
    )
    assert "shard(s) [1]" in problem(httpx.get(f"{api}/maps/half/tiles/0/0/0.png", timeout=30), 503)
    assert "shard(s) [1]" in problem(httpx.get(f"{api}/maps/half/export", params={"format": "npz"}, timeout=60), 503)


def test_zoom_beyond_max_level_is_refused_by_validation(api):
    # z is declared 0 .. MAX_LEVEL (32); 33 must be a 422 naming 'z', not a 404 from the map's own range check
    assert "'z'" in problem(httpx.get(f"{api}/maps/{MAP}/tiles/33/0/0.png", timeout=30), 422)
