"""HTTP API figures (issue 7), on the simulated office mapped by one shard behind a router:

- cached tile requests per second on one uvicorn worker: a Python load loop (raw keep-alive sockets, a few
  connections in threads, a bounded number of requests) asking for one PNG tile again and again, both as
  full 200 answers and as If-None-Match revalidations (304);
- uncached tile requests per second: a second API started with a cache too small to keep anything, so every
  request asks the owning shard over Zenoh, and encodes the PNG, again;
- time from starting `posegrid run` (what `make run` runs) to the first map tile drawn by the viewer in
  headless Chromium (the browser is open and waiting, as a user's would be); on the way it saves the viewer
  screenshots under docs/img/ that the README shows.

Every process, the load loop included, shares this machine's cores: the figures are lower bounds for a
server with cores of its own.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from bench.scenarios import honest_posed_scans, office_run
from schemas.files import save_posed_scans
from services.nodes.launcher import Children, free_port
from services.process import get_logger

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "img"
MAP, STEPS = "bench", 150
CACHED_REQUESTS, UNCACHED_REQUESTS, CONNECTIONS = 20_000, 300, 4
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def _wait(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.1)
    return value


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=5).status_code == 200
    except httpx.TransportError:
        return False


def _load(port: int, paths: list[bytes], requests: int, headers: bytes = b"") -> float:
    """Requests per second of ``requests`` GETs cycling over ``paths``, on CONNECTIONS keep-alive sockets."""
    per_connection = requests // CONNECTIONS
    statuses: list[set] = []

    def worker() -> None:
        seen = set()
        with socket.create_connection(("127.0.0.1", port)) as sock, sock.makefile("rb") as reader:
            for i in range(per_connection):
                sock.sendall(b"GET " + paths[i % len(paths)] + b" HTTP/1.1\r\nHost: bench\r\n" + headers + b"\r\n")
                seen.add(reader.readline().split(b" ")[1])
                length = 0
                while (line := reader.readline()) not in (b"\r\n", b""):
                    if line.lower().startswith(b"content-length:"):
                        length = int(line.split(b":")[1])
                reader.read(length)
        statuses.append(seen)

    threads = [threading.Thread(target=worker) for _ in range(CONNECTIONS)]
    started = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    codes = set().union(*statuses)
    if len(codes) != 1:
        raise RuntimeError(f"the load loop got mixed statuses {codes}")
    return per_connection * CONNECTIONS / elapsed


def _throughput(posed_path: Path) -> dict:
    children = Children(get_logger("bench"))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    connect = ["--connect", endpoint]
    cached_port, uncached_port = free_port(), free_port()
    try:
        children.start("router", ["router", "--listen", endpoint])
        children.start("mapper", ["mapper", "--shard", "0", "--shards", "1", "--map", MAP, *connect])
        children.start("api", ["api", "--port", str(cached_port), *connect])
        children.start("api-nocache", ["api", "--port", str(uncached_port), "--cache-mb", "0.001", *connect])
        children.start(
            "source",
            ["source", "--posed", str(posed_path), "--map", MAP, "--wait-mappers", "1", "--rate", "max", *connect],
            expected_to_finish=True,
        )
        api = f"http://127.0.0.1:{cached_port}"
        _wait(lambda: _answers(f"{api}/maps/{MAP}"), 120, "the API")
        _wait(
            lambda: httpx.get(f"{api}/maps/{MAP}/stats", timeout=30).json()["scans_fused"].get("robot0") == STEPS,
            300,
            "the shard to fuse the run",
        )
        summary = httpx.get(f"{api}/maps/{MAP}", timeout=30).json()
        bounds = summary["tile_bounds"]
        tiles = [
            f"/maps/{MAP}/tiles/0/{x}/{y}.png".encode()
            for x in range(bounds["x_min"], bounds["x_max"] + 1)
            for y in range(bounds["y_min"], bounds["y_max"] + 1)
        ]
        answers = {path: httpx.get(f"{api}{path.decode()}", timeout=30) for path in tiles}
        busiest = max(tiles, key=lambda path: len(answers[path].content))  # the most detailed tile
        etag = answers[busiest].headers["etag"].encode()
        _answers(f"http://127.0.0.1:{uncached_port}/maps/{MAP}")
        return {
            "tiles_level0": len(tiles),
            "tile_png_bytes": len(answers[busiest].content),
            "cached_tile_requests_per_s": _load(cached_port, [busiest], CACHED_REQUESTS),
            "cached_304_requests_per_s": _load(
                cached_port, [busiest], CACHED_REQUESTS, b"If-None-Match: " + etag + b"\r\n"
            ),
            "uncached_tile_requests_per_s": _load(uncached_port, tiles, UNCACHED_REQUESTS),
        }
    finally:
        children.stop_all()


def _first_tile() -> dict:
    """Seconds from starting `posegrid run` to the first tile on the viewer's canvas; saves screenshots."""
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1200, "height": 800})
        started = time.perf_counter()
        run = subprocess.Popen(
            [
                sys.executable,
                "-c",
                "import sys; from services.cli import main; sys.exit(main())",
                "run",
                "--api-port",
                str(port),
            ],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            while True:
                try:
                    page.goto(url, timeout=5_000)
                    break
                except PlaywrightError:
                    if run.poll() is not None or time.perf_counter() - started > 120:
                        raise RuntimeError("`posegrid run` ended or its API never answered") from None
                    time.sleep(0.1)
            page_loaded = time.perf_counter() - started
            page.wait_for_function("window.pgViewer && window.pgViewer.tilesDrawn > 0", timeout=120_000, polling=50)
            first_tile = time.perf_counter() - started
            page.wait_for_timeout(20_000)  # let the run map more of the office for the pictures
            page.click("#fit")
            page.wait_for_timeout(1_000)
            IMAGES.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(IMAGES / "viewer.png"))
            page.click("#layer-variance")
            page.wait_for_function("window.pgViewer.drawnLayer === 'variance'", timeout=30_000)
            page.wait_for_timeout(1_000)
            page.screenshot(path=str(IMAGES / "viewer-variance.png"))
        finally:
            browser.close()
            run.send_signal(2)
            run.wait(60)
    return {"run_to_viewer_page_s": page_loaded, "run_to_first_tile_s": first_tile}


def run() -> dict:
    with tempfile.TemporaryDirectory() as folder:
        posed_path = Path(folder) / "office.npz"
        save_posed_scans(posed_path, honest_posed_scans(office_run(seed=0, steps=STEPS), seed=1))
        figures = _throughput(posed_path)
    figures.update(_first_tile())
    return figures
