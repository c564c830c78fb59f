"""The viewer in a real browser: headless Chromium (the system's, driven by Playwright) on a running pipeline.

Skips with a reason where Chromium or Playwright is absent, except in CI (CI=true), where it must run.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from api_stack import Stack, wait_until, write_room
from bench.api import CHROMIUM, CHROMIUM_ARGS  # the browser and its flags, as the benchmark drives it

pytestmark = pytest.mark.slow

#: the viewer's canvas background and the tiles' unobserved colour (mapping.export.UNOBSERVED_RGB)
BACKGROUND = (180, 190, 205)


def sync_playwright():
    """Playwright's entry point; skips (fails in CI) when it or the system's Chromium is missing."""
    missing = None
    try:
        from playwright.sync_api import sync_playwright as start
    except ImportError:
        missing, start = "the playwright Python package is not installed (pip install -e '.[test]')", None
    if missing is None and not Path(CHROMIUM).is_file():
        missing = f"{CHROMIUM} is absent (apt-get install chromium; .ci/run does)"
    if missing is not None:
        if os.environ.get("CI") == "true":
            pytest.fail(f"the browser test must run in CI but {missing}")
        pytest.skip(missing)
    return start


@pytest.fixture
def playwright_start():
    """Playwright's entry point, looked for before the pipeline starts (a test that skips starts nothing)."""
    return sync_playwright()


@pytest.fixture
def pipeline(tmp_path):
    """A router, one shard (256-cell tiles of 5 cm), the API and a source replaying 80 scans in real time
    (8 s), so the map is still being built while the browser looks at it."""
    processes = Stack(tmp_path)
    try:
        processes.router()
        processes.mappers(1, "main")
        processes.api()
        processes.source(write_room(tmp_path / "room.npz", (-1.0, -1.0), steps=80), "main", 1, rate="realtime")
        yield processes
    finally:
        processes.stop()


def test_viewer_draws_tiles_live_and_switches_to_variance(playwright_start, pipeline, tmp_path):
    with playwright_start() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            errors = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.goto(pipeline.api_url + "/")
            page.wait_for_function("window.pgViewer && window.pgViewer.tilesDrawn > 0", timeout=60_000)
            page.wait_for_function("window.pgViewer.eventsSeen > 0", timeout=60_000)  # live updates arrive
            page.wait_for_function("window.pgViewer.robots.size > 0", timeout=60_000)
            page.click("#layer-variance")
            page.wait_for_function(
                "window.pgViewer.drawnLayer === 'variance' && window.pgViewer.tilesDrawn > 0", timeout=60_000
            )
            status = wait_until(
                lambda: (text := page.inner_text("#status")).startswith("scans fused") and text, 60, "the status line"
            )
            assert "shards alive: 1/1" in status
            shot = tmp_path / "viewer.png"
            page.locator("#view").screenshot(path=str(shot))
            assert page.get_attribute("#layer-variance", "aria-pressed") == "true"
            assert not errors, errors
        finally:
            browser.close()
    pixels = np.asarray(Image.open(io.BytesIO(shot.read_bytes())).convert("RGB")).astype(int)
    flat = pixels.reshape(-1, 3)
    not_background = np.abs(flat - BACKGROUND).sum(axis=1) > 30
    assert not_background.mean() > 0.02, "the map area is blank"
    assert len(np.unique(flat[not_background], axis=0)) > 20, "the map shows almost no detail"
    heat = (flat[:, 0] > 120) & (flat[:, 0] - flat[:, 2] > 80)  # red to yellow: the variance ramp
    assert heat.sum() > 50, "no variance colours on screen"
    assert flat.std(axis=0).mean() > 10
