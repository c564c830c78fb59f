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

from api_stack import Stack, free_port, wait_until, write_room
from bench.api import CHROMIUM, CHROMIUM_ARGS  # the browser and its flags, as the benchmark drives it

pytestmark = pytest.mark.slow

#: the viewer's canvas background and the tiles' unobserved colour (mapping.export.UNOBSERVED_RGB)
BACKGROUND = (180, 190, 205)


#: in the page: the canvas's painted pixels in a frame drawn now, then in one drawn at once after the variance scale
#: changed to one never used (no tile of it loaded yet), and how many tiles of that scale the second frame drew
REPAINT_AT_A_NEW_SCALE = """() => {
  const state = window.pgViewer, canvas = document.getElementById("view");
  const painted = () => {
    const rgba = canvas.getContext("2d").getImageData(0, 0, canvas.width, canvas.height).data;
    let count = 0;
    for (let i = 3; i < rgba.length; i += 4) if (rgba[i] > 0) count += 1;
    return count;
  };
  state.redraw();
  const before = painted();
  state.info.variance_scale *= 1024;
  state.redraw();
  const result = [before, painted(), state.tilesDrawn];
  state.info.variance_scale /= 1024;
  state.redraw();
  return result;
}"""


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
            # the variance scale steps up (by powers of two) as the map grows, and every variance tile's key with it:
            # the map went blank until the tiles of the new scale loaded (a loaded CI run's screenshot caught that).
            # The tiles of the old scale now stand in while the new ones load.
            before, after, drawn = page.evaluate(REPAINT_AT_A_NEW_SCALE)
            assert before > 0 and after >= 0.9 * before and drawn == 0, (before, after, drawn)
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


def test_viewer_recovers_its_events_fits_a_late_canvas_and_lists_late_maps(playwright_start, tmp_path):
    """A probe of the viewer: (1) a page whose /events was refused (503: every event slot taken) never asked again,
    "reconnecting…" for good, its map stale; (2) a canvas of no height when the map came fitted it at a scale of 0
    (an invisible map, "Infinity m" on the scale bar) until "fit"; (3) the list of maps was read once, so a map that
    came up later never showed, and ?map=NAME for it showed another map for good."""
    stack = Stack(tmp_path)
    try:
        stack.router()
        stack.mappers(1, "main")
        port = free_port()
        stack.start("api", "api", "--port", str(port), "--max-event-clients", "1")
        stack.api_url = f"http://127.0.0.1:{port}"
        wait_until(stack._api_up, 60, "the API")
        stack.source(write_room(tmp_path / "room.npz", (-1.0, -1.0), steps=40), "main", 1, rate="realtime")
        with playwright_start() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                first = browser.new_page(viewport={"width": 800, "height": 600})
                first.goto(stack.api_url + "/")
                first.wait_for_function("window.pgViewer && window.pgViewer.eventsOpen === true", timeout=60_000)
                late = browser.new_page(viewport={"width": 800, "height": 60})  # (2): the canvas has no height yet
                errors: list[str] = []
                late.on("pageerror", lambda error: errors.append(str(error)))
                late.goto(stack.api_url + "/?map=later")  # (3): a map not up yet
                late.wait_for_function("document.querySelector('#message').textContent.includes('later')")
                assert late.evaluate("window.pgViewer.eventsOpen") is not True  # (1): the one slot is the first's
                first.close()
                late.wait_for_function("window.pgViewer.eventsOpen === true", timeout=30_000)  # asked again
                stack.start("mapper-later", "mapper", "--shard", "0", "--shards", "1", "--map", "later")
                stack.source(write_room(tmp_path / "later.npz", (3.0, 3.0), steps=10), "later", 1, robot="r2")
                late.wait_for_function("window.pgViewer.map === 'later' && window.pgViewer.info", timeout=60_000)
                assert late.evaluate("document.getElementById('view').clientHeight") == 0  # (what the case needs)
                late.set_viewport_size({"width": 800, "height": 600})
                late.wait_for_function("window.pgViewer.tilesDrawn > 0", timeout=60_000)
                scale = late.evaluate("window.pgViewer.view.scale")
                assert 1 < scale < 2000, scale
                options = late.eval_on_selector_all("#map option", "options => options.map(o => o.value)")
                assert sorted(options) == ["later", "main"]
                assert not errors, errors
            finally:
                browser.close()
    finally:
        stack.stop()
