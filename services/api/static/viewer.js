// posegrid viewer: the map drawn from the API's tiles, pan and zoom, the robots' pose samples and
// trajectories, a probability / variance switch, live updates from GET /events and a status line.
// No build step and no outside assets. Map frame: x east, y north, metres; the canvas puts north up.
"use strict";

(() => {
  const canvas = document.getElementById("view");
  const ctx = canvas.getContext("2d");
  const statusLine = document.getElementById("status");
  const mapSelect = document.getElementById("map");
  const legend = document.getElementById("legend");
  const message = document.getElementById("message");
  const follow = document.getElementById("follow");

  const MAX_LOADS = 6;          // tile requests in flight at once
  const RELOAD_GAP_MS = 300;    // shortest time between two loads of one tile
  const CACHE_LIMIT = 600;      // tile images kept
  const TRAIL_LIMIT = 20000;    // trajectory points kept per robot
  const ROBOT_COLOURS = ["#e8590c", "#1c7ed6", "#2f9e44", "#ae3ec9", "#f08c00"];
  const MIN_SCALE = 1e-6, MAX_SCALE = 2000;  // pixels per metre, for the wheel and "fit" alike
  const EVENTS_RETRY_MS = [1000, 2000, 5000, 10000];  // waits before asking /events again after it was refused
  const MAPS_REFRESH_MS = 5000;  // how often the list of maps is asked again

  // Everything the page knows; exposed for the browser test and for debugging in the console.
  const state = {
    map: null, info: null, layer: "probability",
    view: { cx: 0, cy: 0, scale: 40 },      // centre (m) and pixels per metre
    tiles: new Map(),                          // key -> {z, x, y, layer, image, dirty, loading, lastLoad, missing}
    // layer/z/x/y -> the tile's last image at any variance scale: drawn while the image of the current scale loads
    // (the default scale steps up by powers of two as a map grows, and every variance tile's key changes with it)
    placeholders: new Map(),
    loads: 0, robots: new Map(), stats: null,
    tilesDrawn: 0, drawnLayer: null, framesDrawn: 0, eventsSeen: 0, fitted: false,
  };
  window.pgViewer = state;
  state.redraw = () => draw();   // (a frame drawn now, for the browser test)

  // ---------------------------------------------------------------------------- HTTP
  async function getJSON(path) {
    const response = await fetch(path, { cache: "no-store" });
    if (!response.ok) {
      let detail = response.statusText;
      try { detail = (await response.json()).detail; } catch (_) { /* not JSON */ }
      throw new Error(`${path}: ${response.status} ${detail}`);
    }
    return response.json();
  }

  function showMessage(text) {
    message.hidden = !text;
    message.textContent = text || "";
  }

  // ---------------------------------------------------------------------------- geometry
  function toScreen(x, y) {
    const { cx, cy, scale } = state.view;
    return [canvas.width / 2 + (x - cx) * scale, canvas.height / 2 - (y - cy) * scale];
  }

  function toWorld(sx, sy) {
    const { cx, cy, scale } = state.view;
    return [cx + (sx - canvas.width / 2) / scale, cy - (sy - canvas.height / 2) / scale];
  }

  function zoomLevel() {
    const info = state.info;
    const z = Math.round(Math.log2(1 / (info.resolution * state.view.scale)));
    return Math.max(0, Math.min(info.max_zoom, z));
  }

  function tileSpan(z) {
    return state.info.tile_size * state.info.resolution * 2 ** z;
  }

  function vmaxParam() {
    return state.layer === "variance" && state.info.variance_scale != null ? `&vmax=${state.info.variance_scale}` : "";
  }

  function tileKey(z, x, y) {
    return `${state.layer}${vmaxParam()}/${z}/${x}/${y}`;
  }

  // ---------------------------------------------------------------------------- tiles
  function tileEntry(z, x, y) {
    const key = tileKey(z, x, y);
    let entry = state.tiles.get(key);
    if (!entry) {
      entry = { z, x, y, layer: state.layer, image: null, dirty: true, loading: false, lastLoad: 0, missing: false };
      keepBounded(state.tiles, key, entry);
    }
    return entry;
  }

  function placeholderKey(entry) {
    return `${entry.layer}/${entry.z}/${entry.x}/${entry.y}`;
  }

  // set key -> value in a Map that keeps at most CACHE_LIMIT entries, the oldest going first
  function keepBounded(map, key, value) {
    map.delete(key);
    map.set(key, value);
    if (map.size > CACHE_LIMIT) map.delete(map.keys().next().value);
  }

  function forgetTiles() {
    state.tiles.clear();
    state.placeholders.clear();
  }

  function load(entry) {
    const now = performance.now();
    if (entry.loading || state.loads >= MAX_LOADS || now - entry.lastLoad < RELOAD_GAP_MS) return;
    entry.loading = true;
    entry.dirty = false;
    entry.lastLoad = now;
    state.loads += 1;
    const url = `maps/${encodeURIComponent(state.map)}/tiles/${entry.z}/${entry.x}/${entry.y}.png` +
      `?layer=${state.layer}${vmaxParam()}`;
    // "no-cache": the browser revalidates with If-None-Match and the API answers 304 when unchanged
    fetch(url, { cache: "no-cache" })
      .then((response) => {
        if (response.status === 404) { entry.missing = true; return null; }
        if (!response.ok) throw new Error(`${url}: ${response.status}`);
        return response.blob().then((blob) => createImageBitmap(blob));
      })
      .then((image) => {
        if (!image) return;
        entry.image = image;
        entry.missing = false;
        keepBounded(state.placeholders, placeholderKey(entry), image);
      })
      .catch(() => { entry.dirty = true; })
      .finally(() => { entry.loading = false; state.loads -= 1; requestDraw(); });
  }

  function visibleRange(z) {
    const span = tileSpan(z);
    const [x0, y1] = toWorld(0, 0);
    const [x1, y0] = toWorld(canvas.width, canvas.height);
    const b = state.info.tile_bounds;
    return {
      xMin: Math.max(Math.floor(x0 / span), b.x_min >> z), xMax: Math.min(Math.floor(x1 / span), b.x_max >> z),
      yMin: Math.max(Math.floor(y0 / span), b.y_min >> z), yMax: Math.min(Math.floor(y1 / span), b.y_max >> z),
    };
  }

  function drawTile(entry, image = entry.image) {
    const span = tileSpan(entry.z);
    const [sx, sy] = toScreen(entry.x * span, (entry.y + 1) * span);
    const size = span * state.view.scale;
    // (edges rounded to whole pixels, each tile's right edge the next one's left: no seam, no pixel drawn twice)
    const x0 = Math.round(sx), y0 = Math.round(sy);
    ctx.drawImage(image, x0, y0, Math.round(sx + size) - x0, Math.round(sy + size) - y0);
  }

  function drawTiles() {
    const z = zoomLevel();
    ctx.imageSmoothingEnabled = state.info.resolution * 2 ** z * state.view.scale < 1;
    // coarser tiles first, as placeholders while the ones of this level load
    for (let coarse = Math.min(state.info.max_zoom, z + 2); coarse > z; coarse--) {
      const r = visibleRange(coarse);
      for (let x = r.xMin; x <= r.xMax; x++) {
        for (let y = r.yMin; y <= r.yMax; y++) {
          const entry = state.tiles.get(tileKey(coarse, x, y));
          if (entry && entry.image) drawTile(entry);
        }
      }
    }
    let drawn = 0;
    const r = visibleRange(z);
    for (let x = r.xMin; x <= r.xMax; x++) {
      for (let y = r.yMin; y <= r.yMax; y++) {
        const entry = tileEntry(z, x, y);
        if (entry.dirty && !entry.missing) load(entry);
        if (entry.image) { drawTile(entry); drawn += 1; continue; }
        const earlier = state.placeholders.get(placeholderKey(entry));   // (the same tile at another scale)
        if (earlier && !entry.missing) drawTile(entry, earlier);
      }
    }
    state.tilesDrawn = drawn;
    if (drawn > 0) state.drawnLayer = state.layer;
  }

  // ---------------------------------------------------------------------------- robots
  function robotColour(name) {
    const names = [...state.robots.keys()].sort();
    return ROBOT_COLOURS[names.indexOf(name) % ROBOT_COLOURS.length];
  }

  // the robots the map's shards count (all of them until its stats are known): a robot of another map, or one
  // whose scans this map refused, is neither drawn nor followed here
  function mapRobots() {
    const stats = state.stats && state.stats.map === state.map ? state.stats : null;
    const counted = stats ? new Set([...Object.keys(stats.scans_fused), ...Object.keys(stats.lag_scans)]) : null;
    return [...state.robots].filter(([name]) => counted === null || counted.has(name));
  }

  function drawRobots() {
    for (const [name, robot] of mapRobots()) {
      const colour = robotColour(name);
      if (robot.trail.length > 1) {
        ctx.strokeStyle = colour;
        ctx.globalAlpha = 0.8;
        ctx.lineWidth = 2;
        ctx.beginPath();
        robot.trail.forEach(([x, y], i) => {
          const [sx, sy] = toScreen(x, y);
          if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.stroke();
      }
      const pose = robot.pose;
      if (!pose) continue;
      const [mx, my, yaw] = pose.mean;
      const [sx, sy] = toScreen(mx, my);
      ctx.save();
      ctx.translate(sx, sy);
      ctx.rotate(-yaw);
      ctx.beginPath();
      ctx.moveTo(12, 0); ctx.lineTo(-7, 6); ctx.lineTo(-4, 0); ctx.lineTo(-7, -6); ctx.closePath();
      ctx.fillStyle = colour; ctx.strokeStyle = "#fff"; ctx.lineWidth = 1.5;
      ctx.fill(); ctx.stroke();
      ctx.restore();
      drawEllipse(sx, sy, pose.covariance, colour);
      const maxWeight = Math.max(...pose.weights);
      ctx.fillStyle = colour;
      ctx.strokeStyle = "rgba(255, 255, 255, 0.7)";
      ctx.lineWidth = 0.75;
      pose.samples.forEach(([x, y], i) => {
        const [px, py] = toScreen(x, y);
        ctx.globalAlpha = 0.35 + 0.65 * pose.weights[i] / maxWeight;
        ctx.beginPath();
        ctx.arc(px, py, 2.2, 0, 2 * Math.PI);
        ctx.fill(); ctx.stroke();
      });
      ctx.globalAlpha = 1;
      ctx.font = "12px system-ui, sans-serif";
      ctx.lineWidth = 3;
      ctx.strokeStyle = "rgba(255, 255, 255, 0.85)";
      ctx.strokeText(name, sx + 12, sy - 10);
      ctx.fillStyle = "#20242b";
      ctx.fillText(name, sx + 12, sy - 10);
    }
    ctx.globalAlpha = 1;
  }

  // the 95 % region of the pose's (x, y) covariance: the ellipse of Mahalanobis radius sqrt(5.991)
  function drawEllipse(sx, sy, cov, colour) {
    const [a, b, c] = [cov[0][0], cov[0][1], cov[1][1]];
    const mid = (a + c) / 2, half = Math.sqrt(((a - c) / 2) ** 2 + b * b);
    const k = Math.sqrt(5.991) * state.view.scale;
    const major = k * Math.sqrt(Math.max(mid + half, 0)), minor = k * Math.sqrt(Math.max(mid - half, 0));
    if (major < 1) return;
    ctx.beginPath();
    ctx.ellipse(sx, sy, major, minor, -0.5 * Math.atan2(2 * b, a - c), 0, 2 * Math.PI);
    ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.setLineDash([4, 3]);
    ctx.stroke();
    ctx.setLineDash([]);
  }

  function drawScaleBar() {
    const target = 120 / state.view.scale;   // metres in about 120 px
    const step = 10 ** Math.floor(Math.log10(target));
    const metres = [1, 2, 5, 10].map((k) => k * step).filter((m) => m <= target).pop();
    const length = metres * state.view.scale;
    const x = 16, y = canvas.height - 18;
    ctx.fillStyle = "rgba(32, 36, 43, 0.8)";
    ctx.fillRect(x - 6, y - 18, length + 12, 26);
    ctx.strokeStyle = "#fff"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + length, y); ctx.stroke();
    ctx.fillStyle = "#fff"; ctx.font = "11px system-ui, sans-serif";
    ctx.fillText(metres >= 1 ? `${metres} m` : `${Math.round(metres * 100)} cm`, x, y - 5);
  }

  // ---------------------------------------------------------------------------- frame
  let drawPending = false;
  function requestDraw() {
    if (!drawPending) { drawPending = true; requestAnimationFrame(draw); }
  }

  function draw() {
    drawPending = false;
    const { clientWidth, clientHeight } = canvas;
    if (canvas.width !== clientWidth || canvas.height !== clientHeight) {
      canvas.width = clientWidth; canvas.height = clientHeight;
    }
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (state.info && state.info.max_zoom !== null) {
      if (follow.checked) followRobot();
      drawTiles();
      drawRobots();
      drawScaleBar();
    }
    state.framesDrawn += 1;
  }

  function followRobot() {
    const first = mapRobots().map(([, r]) => r).find((r) => r.pose);
    if (first) { state.view.cx = first.pose.mean[0]; state.view.cy = first.pose.mean[1]; }
  }

  function fit() {
    const info = state.info;
    const e = info && (info.observed_extent || info.extent);
    // (a canvas of no size yet, a window shown later: fitted at the next resize, not to a scale of 0)
    if (!e || canvas.clientWidth <= 0 || canvas.clientHeight <= 0) return;
    state.view.cx = (e.x_min + e.x_max) / 2;
    state.view.cy = (e.y_min + e.y_max) / 2;
    const scale = 0.9 * Math.min(canvas.clientWidth / Math.max(e.x_max - e.x_min, info.resolution),
      canvas.clientHeight / Math.max(e.y_max - e.y_min, info.resolution));
    state.view.scale = Math.min(MAX_SCALE, Math.max(MIN_SCALE, scale));
    state.fitted = true;
    requestDraw();
  }

  // ---------------------------------------------------------------------------- data
  let infoRefresh = null;
  async function refreshInfo() {
    const map = state.map;
    try {
      const info = await getJSON(`maps/${encodeURIComponent(map)}`);
      if (map !== state.map) return;   // (the answer about a map the page has left since it asked)
      if (info.variance_scale === null && state.info && state.info.name === info.name) {
        info.variance_scale = state.info.variance_scale;  // null while a shard is down: keep the scale known
      }
      state.info = info;
      showMessage(info.max_zoom === null ? `map ${info.name}: waiting for the first tile…` : "");
      if (!state.fitted) fit();
      updateLegend();
      requestDraw();
    } catch (error) {
      if (map === state.map) showMessage(String(error.message || error));
    }
  }

  function scheduleInfoRefresh() {
    if (infoRefresh === null) {   // soon for the first tiles, then at most once a second
      const delay = state.info && state.info.max_zoom !== null ? 1000 : 100;
      infoRefresh = setTimeout(() => { infoRefresh = null; refreshInfo(); }, delay);
    }
  }

  function onTiles(event) {
    const data = JSON.parse(event.data);
    state.eventsSeen += 1;
    if (data.map !== state.map) return;
    const b = state.info && state.info.tile_bounds;
    let outside = !b;
    for (const entry of state.tiles.values()) {
      for (const [tx, ty] of data.tiles) {
        if (tx >> entry.z === entry.x && ty >> entry.z === entry.y) { entry.dirty = true; entry.missing = false; }
      }
    }
    for (const [tx, ty] of data.tiles) {
      if (b && (tx < b.x_min || tx > b.x_max || ty < b.y_min || ty > b.y_max)) outside = true;
    }
    if (outside) scheduleInfoRefresh();
    requestDraw();
  }

  function robot(name) {
    if (!state.robots.has(name)) state.robots.set(name, { pose: null, trail: [], lastSeq: -1 });
    return state.robots.get(name);
  }

  function onPose(event) {
    const pose = JSON.parse(event.data);
    state.eventsSeen += 1;
    const r = robot(pose.robot);
    r.pose = pose;
    if (pose.seq > r.lastSeq) {
      r.trail.push([pose.mean[0], pose.mean[1]]);
      r.lastSeq = pose.seq;
      if (r.trail.length > TRAIL_LIMIT) r.trail.splice(0, r.trail.length - TRAIL_LIMIT);
    }
    requestDraw();
  }

  async function loadRobots() {
    for (const summary of await getJSON("robots")) {
      const [pose, track] = await Promise.all([
        getJSON(`robots/${encodeURIComponent(summary.robot)}/pose?max_samples=200`),
        getJSON(`robots/${encodeURIComponent(summary.robot)}/trajectory`),
      ]);
      const r = robot(summary.robot);
      r.pose = pose;
      r.trail = track.x.map((x, i) => [x, track.y[i]]);
      r.lastSeq = track.seq.length ? track.seq[track.seq.length - 1] : -1;
    }
    requestDraw();
  }

  function resync() { for (const e of state.tiles.values()) e.dirty = true; if (state.map) refreshInfo(); }

  // The browser's EventSource reconnects by itself after a dropped connection, but gives up for good on an answer
  // that is not 200 (a 503 when every event slot is taken, a proxy's 502 while the API restarts): the page then
  // asks again itself, waiting longer each time. A stream opened again missed events: every tile is loaded again.
  let eventsTries = 0, eventsOpened = false;
  function connectEvents() {
    const source = new EventSource("events");
    source.addEventListener("tiles", onTiles);
    source.addEventListener("pose", onPose);
    source.addEventListener("resync", resync);
    source.addEventListener("hello", () => {
      if (eventsOpened) resync();
      state.eventsOpen = true; eventsOpened = true; eventsTries = 0;
    });
    source.onerror = () => {
      state.eventsOpen = false;
      if (source.readyState !== EventSource.CLOSED) return;   // (the browser tries again itself)
      const wait = EVENTS_RETRY_MS[Math.min(eventsTries, EVENTS_RETRY_MS.length - 1)];
      eventsTries += 1;
      setTimeout(connectEvents, wait);
    };
  }

  async function refreshStatus() {
    if (!state.map) return;
    try {
      const stats = await getJSON(`maps/${encodeURIComponent(state.map)}/stats`);
      state.stats = stats;
      const fused = Object.entries(stats.scans_fused).map(([r, n]) => `${r} ${n}`).join(", ") || "0";
      const lag = Math.max(0, ...Object.values(stats.lag_scans));
      const alive = stats.shards_alive.length;
      const total = stats.shards ?? alive;
      const rejected = Object.values(stats.rejected).reduce((a, b) => a + b, 0);
      const tiles = state.info ? state.info.tiles : 0;
      statusLine.textContent = `scans fused: ${fused} · shards alive: ${alive}/${total} · lag: ${lag} scans` +
        ` · tiles: ${tiles}` + (rejected ? ` · rejected: ${rejected}` : "") +
        (state.eventsOpen ? " · live" : " · reconnecting…");
      statusLine.classList.toggle("warn", alive < total || !state.eventsOpen);
    } catch (error) {
      statusLine.textContent = `status unavailable: ${error.message || error}`;
      statusLine.classList.add("warn");
    }
  }

  function updateLegend() {
    const unobserved = '<span class="swatch" style="background:#b4becd"></span> unobserved';
    legend.innerHTML = state.layer === "probability"
      ? '<span class="swatch" style="background:#fff"></span> free · ' +
        `<span class="swatch" style="background:#000"></span> occupied · ${unobserved}`
      : '<span class="swatch" style="background:linear-gradient(90deg,#000,#aa141e,#faaa14,#ffffe6)"></span>' +
        ` variance of the log-odds from pose uncertainty, 0 → ${state.info && state.info.variance_scale !== null ? state.info.variance_scale : "?"} · ` +
        unobserved;
    legend.innerHTML += " · dots: pose samples · dashed: 95 % of the pose · line: trajectory" +
      " · drag to pan, wheel to zoom";
  }

  function setLayer(layer) {
    state.layer = layer;
    document.body.dataset.layer = layer;
    for (const button of document.querySelectorAll("[data-layer]")) {
      button.setAttribute("aria-pressed", String(button.dataset.layer === layer));
    }
    updateLegend();
    if (layer === "variance" && state.map) refreshInfo(); else requestDraw();
  }

  // ---------------------------------------------------------------------------- input
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY };
    canvas.setPointerCapture(e.pointerId);
    canvas.classList.add("dragging");
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    state.view.cx -= (e.clientX - drag.x) / state.view.scale;
    state.view.cy += (e.clientY - drag.y) / state.view.scale;
    drag = { x: e.clientX, y: e.clientY };
    follow.checked = false;
    requestDraw();
  });
  const endDrag = () => { drag = null; canvas.classList.remove("dragging"); };
  canvas.addEventListener("pointerup", endDrag);
  canvas.addEventListener("pointercancel", endDrag);
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const rect = canvas.getBoundingClientRect();
    const [wx, wy] = toWorld(e.clientX - rect.left, e.clientY - rect.top);
    const factor = Math.exp(-e.deltaY * 0.0015);
    state.view.scale = Math.min(MAX_SCALE, Math.max(MIN_SCALE, state.view.scale * factor));
    const [nx, ny] = toWorld(e.clientX - rect.left, e.clientY - rect.top);
    state.view.cx += wx - nx;
    state.view.cy += wy - ny;
    requestDraw();
  }, { passive: false });
  for (const button of document.querySelectorAll("[data-layer]")) {
    button.addEventListener("click", () => setLayer(button.dataset.layer));
  }
  document.getElementById("fit").addEventListener("click", () => { state.fitted = false; refreshInfo(); });
  follow.addEventListener("change", requestDraw);
  let mapChosen = false;   // whether the user picked a map (then a map asked for in the URL no longer takes over)
  mapSelect.addEventListener("change", () => {
    mapChosen = true;
    state.map = mapSelect.value; state.info = null; state.stats = null; state.fitted = false; forgetTiles();
    refreshInfo(); refreshStatus();
  });
  window.addEventListener("resize", () => { if (!state.fitted) fit(); requestDraw(); });

  // ---------------------------------------------------------------------------- start
  // Until a map is there (and whenever asking fails) say why on the canvas and try again shortly.
  // The list of maps is asked again every MAPS_REFRESH_MS: a map that comes up later is listed, and a map the URL
  // names (?map=NAME) is waited for and shown once it is there, unless the user picks another meanwhile.
  async function chooseMap() {
    let again = MAPS_REFRESH_MS;
    try {
      const maps = await getJSON("maps");
      if (!maps.length) throw new Error("no map yet: waiting for a mapper shard…");
      const wanted = new URLSearchParams(location.search).get("map");
      const names = maps.map((m) => m.name);
      if ([...mapSelect.options].map((o) => o.value).join("\n") !== names.join("\n")) {
        mapSelect.innerHTML = "";
        for (const name of names) mapSelect.add(new Option(name, name));
      }
      let next = state.map;
      if (wanted && !mapChosen) {
        next = names.includes(wanted) ? wanted : null;
      } else if (next === null || !names.includes(next)) {
        next = names[0];
      }
      if (next === null) {
        showMessage(`waiting for map ${wanted} (named in the URL), or pick one above…`);
        mapSelect.selectedIndex = -1;
        again = 1000;
      } else {
        mapSelect.value = next;
        if (next !== state.map) {
          state.map = next; state.info = null; state.stats = null; state.fitted = false; forgetTiles();
          await refreshInfo();
          refreshStatus();
        }
      }
    } catch (error) {
      showMessage(String(error.message || error));
      again = 500;
    }
    setTimeout(chooseMap, again);
  }

  setLayer(new URLSearchParams(location.search).get("layer") === "variance" ? "variance" : "probability");
  connectEvents();
  chooseMap();
  loadRobots().catch(() => { /* robots appear with their first pose event */ });
  setInterval(refreshStatus, 1000);
  setInterval(() => { if (state.map) refreshInfo(); }, 2000);   // extent, cell counts, variance scale
  requestDraw();
})();
