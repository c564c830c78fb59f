"""End-to-end figures of the distributed pipeline over Zenoh (issue 8), on the simulated office with 60 pose
samples per scan, and (issue 34, figures prefixed "warehouse_") on the simulated warehouse's modern lidar (1081
beams to 30 m) with 100 particles a scan, 1 and 2 shards, exact and with the samples bundled (`mapper --bundle 0.1`,
names ending "_bundle0.1"), fewer scans (WAREHOUSE_STEPS; WAREHOUSE_LATENCY_SCANS at 10 Hz, which one exact shard
does not keep up with: the backlog, and so the latency, grows over the run).

- throughput: scans per second from the first publication until every shard has fused every scan, with
  1 and 2 mapper shards (processes; 2 also with 32-cell tiles, see CONFIGURATIONS) behind a router (a
  process), the source publishing "as fast as the shards take" from this process; as a ratio to the
  in-process `posegrid fuse` rate on the same scans, measured right before and right after each pipeline
  run (their mean, bundled where the shards bundle; the figure without a prefix is the median over the exact runs);
- latency at a 10 Hz laser: per scan, from its publication to the arrival (here) of the last tile update
  that the shards sent right after fusing it (updates carry the seq of the last scan fused into the tile);
  median and p99 over the scans after the first WARMUP ones, which a mapper takes while it loads its
  compiled kernels and creates its first tiles (a laser streams for hours; start-up is reported apart,
  as the worst latency among the warm-up scans);
- tile query while a shard drains a backlog (the warehouse, one shard): a client asks one tile again and again,
  QUERY_GAP s after each reply, while the shard fuses the scans the source sends as fast as it takes them: the
  replies' time, median, p90 and max (a query waits for the scan under way: services.handoff_lock);
- bytes per scan: msgpack payloads of the scan and pose messages (in) and of the tile updates (out);
  Zenoh framing and TCP headers are not counted;
- each mapper shard's peak resident memory (VmHWM, read before it stops) in the throughput runs;
- for each configuration of more than one shard, the total CPU of its shards' fusions over one shard's, in process
  (`bench.warehouse.shards_cpu`, the same scans in turns, every SHARD_CPU_EVERY-th): what the shards' work costs in
  all, which the shared cores pay.

All processes share this machine's cores, so the figures bound what separate machines would give.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from bench.scenarios import honest_posed_scans, office_run, select_scans, warehouse_run
from bench.warehouse import shards_cpu
from mapping.grid import TILE_SIZE
from schemas.messages import ShardStats, TileUpdate, decode_message
from services import keys
from services.fusion_runner import fuse_posed_scans
from services.map_client import MapReader
from services.nodes.launcher import Children, free_port
from services.nodes.source import Source, SourceOptions
from services.process import get_logger
from services.streams import posed_stream
from services.zenoh_config import build_config

SAMPLES = 60
STEPS = 200  # scans in the throughput runs
LATENCY_SCANS = 100  # scans measured in the 10 Hz latency runs
WARMUP = 10  # scans published before them, at the same rate
LASER_HZ = 10.0
ROBOT = "bench"
#: (mapper shards, tile side in cells, bundle tolerance m). The office spans about 2 x 2 default tiles, most of its
#: cells in one of them, so with the default tiles one of two shards does nearly all the work; with 32-cell tiles
#: both shards' tiles lie under every ray, and each walks most of every scan (docs/architecture.md, "Sharding": the
#: work does not divide; the configuration shows what that costs). A tolerance > 0: the shards bundle the samples
#: (`mapper --bundle`, mapping.bundling), and the in-process rate they are compared with does too.
CONFIGURATIONS = ((1, TILE_SIZE, 0.0), (2, TILE_SIZE, 0.0), (2, 32, 0.0))
#: the warehouse: particles a scan, scans in the throughput runs and in the 10 Hz latency runs, configurations
WAREHOUSE_PARTICLES = 100
WAREHOUSE_STEPS = 120
WAREHOUSE_LATENCY_SCANS = 40
#: the in-process shard CPU figures take every this-many-th scan
SHARD_CPU_EVERY = 2
#: the tile query figures: s between a reply and the next query, and the scans fused before the first query
QUERY_GAP = 0.02
QUERY_AFTER = 20
WAREHOUSE_CONFIGURATIONS = ((1, TILE_SIZE, 0.0), (2, TILE_SIZE, 0.0), (1, TILE_SIZE, 0.1), (2, TILE_SIZE, 0.1))


class Cluster:
    """A router and ``shards`` mapper processes on loopback, and a client session of this process."""

    def __init__(self, shards: int, map_name: str, tile_size: int = TILE_SIZE, bundle: float = 0.0):
        self.shards = shards
        self.tile_size = tile_size
        self.bundle = bundle
        self.map_name = map_name
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.children = Children(get_logger("bench"))
        self._session: zenoh.Session | None = None
        self.tile_bytes = 0
        self.tile_updates: list[tuple[float, int]] = []  # (arrival s, seq tag)
        self._lock = threading.Lock()

    def __enter__(self) -> Cluster:
        connect = ["--connect", self.endpoint]
        self.children.start("router", ["router", "--listen", self.endpoint])
        for shard in range(self.shards):
            self.children.start(
                f"mapper[{shard}]",
                [
                    "mapper",
                    "--shard",
                    str(shard),
                    "--shards",
                    str(self.shards),
                    "--map",
                    self.map_name,
                    "--tile-size",
                    str(self.tile_size),
                    "--bundle",
                    repr(self.bundle),
                    *connect,
                ],
            )
        self._session = zenoh.open(build_config("client", connect=[self.endpoint]))
        self.session.declare_subscriber(keys.tiles_key(self.map_name), self._on_tile)
        deadline = time.monotonic() + 120
        while (
            sum(
                r.ok is not None
                for r in self.session.liveliness().get(keys.shard_alive_key(self.map_name, "*"), timeout=2.0)
            )
            < self.shards
        ):
            if time.monotonic() > deadline or self.children.failed():
                raise RuntimeError("the bench's mapper shards did not come up")
            time.sleep(0.1)
        return self

    @property
    def session(self) -> zenoh.Session:
        """This process's client session, open inside the ``with`` block."""
        if self._session is None:
            raise RuntimeError("the cluster is not running: use it in a with block")
        return self._session

    def __exit__(self, *exc: object) -> None:
        self.session.close()
        self.children.stop_all()

    def _on_tile(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        arrival = time.perf_counter()
        update = decode_message(payload, TileUpdate)
        with self._lock:
            self.tile_bytes += len(payload)
            self.tile_updates.append((arrival, update.seq))

    def peak_rss_bytes(self) -> list[int]:
        """Each mapper shard's peak resident memory so far (VmHWM of /proc/PID/status, bytes), in shard order."""
        peaks = []
        for child in self.children.children:
            if child.name.startswith("mapper"):
                status = Path(f"/proc/{child.process.pid}/status").read_text()
                found = re.search(r"^VmHWM:\s+(\d+) kB", status, re.MULTILINE)
                if found is None:
                    raise RuntimeError(f"no VmHWM in /proc/{child.process.pid}/status")
                peaks.append(int(found.group(1)) * 1024)
        return peaks

    def fused(self) -> int:
        stats: dict[int, ShardStats] = MapReader(self.session, self.map_name).stats()
        if len(stats) < self.shards:
            return 0
        return min(s.fused.get(ROBOT, 0) for s in stats.values())

    def wait_fused(self, scans: int, timeout: float = 600.0) -> None:
        deadline = time.monotonic() + timeout
        while self.fused() < scans:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the shards did not fuse {scans} scans in {timeout:.0f} s")
            time.sleep(0.01)


def _in_process_rate(posed, bundle: float = 0.0) -> float:
    """Scans per second of `posegrid fuse`'s loop (after one warm-up scan that compiles the kernels), the samples
    bundled with tolerance ``bundle`` m."""
    fuse_posed_scans(select_scans(posed, slice(0, 1)), bundle=bundle)
    started = time.perf_counter()
    fuse_posed_scans(posed, bundle=bundle)
    return len(posed.stamps) / (time.perf_counter() - started)


def _throughput(posed, shards: int, tile_size: int, bundle: float) -> dict:
    stream = posed_stream(posed, ROBOT)
    in_bytes = sum(len(m.encode()) for step in stream.steps for m in step.messages)
    with Cluster(shards, f"tp{shards}", tile_size, bundle) as cluster:
        source = Source(
            cluster.session, stream, SourceOptions(rate=None, wait_mappers=shards, map_name=cluster.map_name)
        )
        started = time.perf_counter()
        source.run(threading.Event())
        cluster.wait_fused(len(stream.steps))
        elapsed = time.perf_counter() - started
        time.sleep(0.5)  # the last tile updates
        out_bytes = cluster.tile_bytes
        peaks = cluster.peak_rss_bytes()
    scans = len(stream.steps)
    return {
        "scans_per_s": scans / elapsed,
        "bytes_in_per_scan": in_bytes / scans,
        "bytes_out_per_scan": out_bytes / scans,
        **{f"shard{shard}_peak_rss_mb": peak / 2**20 for shard, peak in enumerate(peaks)},
    }


def _latency(posed, shards: int, tile_size: int, bundle: float, scans: int = LATENCY_SCANS) -> dict:
    stream = posed_stream(select_scans(posed, slice(0, WARMUP + scans)), ROBOT)
    published: dict[int, float] = {}
    with Cluster(shards, f"lat{shards}", tile_size, bundle) as cluster:
        publishers = {
            name: cluster.session.declare_publisher(
                keys.robot_key(ROBOT, name), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for name in (keys.SCAN, keys.POSE)
        }
        t0 = time.perf_counter()
        for seq, step in enumerate(stream.steps):
            delay = t0 + seq / LASER_HZ - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            scan, pose = step.messages
            payloads = scan.encode(), pose.encode()
            published[seq] = time.perf_counter()
            publishers[keys.SCAN].put(payloads[0])
            publishers[keys.POSE].put(payloads[1])
        cluster.wait_fused(len(stream.steps))
        time.sleep(0.5)
        updates = list(cluster.tile_updates)
    last: dict[int, float] = {}
    for arrival, seq in updates:
        last[seq] = max(last.get(seq, 0.0), arrival)
    latency_ms = {seq: 1e3 * (arrival - published[seq]) for seq, arrival in last.items()}
    measured = np.array([ms for seq, ms in latency_ms.items() if seq >= WARMUP])
    warmup = [ms for seq, ms in latency_ms.items() if seq < WARMUP]
    return {
        "latency_ms_median": float(np.median(measured)),
        "latency_ms_p99": float(np.percentile(measured, 99)),
        "latency_ms_max": float(measured.max()),
        "latency_ms_warmup_max": max(warmup, default=float("nan")),
        "latency_scans_without_own_update": len(stream.steps) - len(last),
    }


def _tile_queries(posed) -> dict:
    """How long a query of one tile takes while one shard fuses ``posed`` from a source at --rate max (ms: median,
    p90, max), from its QUERY_AFTER-th scan fused to the source's end."""
    stream = posed_stream(posed, ROBOT)
    with Cluster(1, "query") as cluster:
        source = Source(cluster.session, stream, SourceOptions(rate=None, wait_mappers=1, map_name=cluster.map_name))
        done = threading.Event()

        def send() -> None:
            try:
                source.run(threading.Event())
            finally:
                done.set()

        sending = threading.Thread(target=send)
        sending.start()
        try:
            while cluster.fused() < QUERY_AFTER and not done.is_set():
                time.sleep(0.05)
            every_tile = cluster.session.get(keys.tile_key(cluster.map_name, 0, "*", "*"), timeout=10.0)
            tiles = [reply.ok.key_expr for reply in every_tile if reply.ok is not None]
            if not tiles:
                raise RuntimeError("the bench's shard had no tile to ask for")
            key = str(tiles[0])  # (one of its tiles)
            took = []
            while not done.is_set():
                began = time.perf_counter()
                if not any(reply.ok is not None for reply in cluster.session.get(key, timeout=10.0)):
                    raise RuntimeError(f"the bench's shard did not answer the query of {key}")
                took.append(1e3 * (time.perf_counter() - began))
                time.sleep(QUERY_GAP)
        finally:
            sending.join()
    if not took:
        raise RuntimeError("the source ended before the bench asked for a tile")
    return {
        "tile_query_ms_median": float(np.median(took)),
        "tile_query_ms_p90": float(np.percentile(took, 90)),
        "tile_query_ms_max": float(max(took)),
        "tile_queries": len(took),
    }


def _scenario(posed, configurations, latency_scans: int) -> dict:
    """The throughput and latency figures of ``posed`` in each (shards, tile size, bundle tolerance) configuration."""
    out: dict = {}
    in_process = []
    for shards, tile_size, bundle in configurations:
        name = f"shards{shards}" + ("" if tile_size == TILE_SIZE else f"_tile{tile_size}")
        name += f"_bundle{bundle:g}" if bundle > 0 else ""
        # the baseline right before and right after each pipeline run (their mean): this shared machine's
        # speed drifts by tens of percent within a minute
        before = _in_process_rate(posed, bundle)
        for key, value in _throughput(posed, shards, tile_size, bundle).items():
            out[f"{name}_{key}"] = value
        rate = (before + _in_process_rate(posed, bundle)) / 2
        if bundle == 0:
            in_process.append(rate)  # (the exact fusion's rate, below)
        out[f"{name}_in_process_scans_per_s"] = rate
        out[f"{name}_ratio_to_in_process"] = out[f"{name}_scans_per_s"] / rate
        for key, value in _latency(posed, shards, tile_size, bundle, latency_scans).items():
            out[f"{name}_{key}_at_{LASER_HZ:g}hz"] = value
        if shards > 1 and bundle == 0:
            cpu = shards_cpu(posed, (shards,), SHARD_CPU_EVERY, tile_size)
            out[f"{name}_in_process_cpu_ratio_to_one"] = cpu[f"shards{shards}_cpu_ratio_to_one"]
            out[f"{name}_in_process_busiest_ratio_to_one"] = cpu[f"shards{shards}_busiest_ratio_to_one"]
    out["in_process_scans_per_s"] = float(np.median(in_process))  # (exact)
    return out


def run() -> dict:
    posed = honest_posed_scans(office_run(seed=0, steps=STEPS), seed=1, particles=SAMPLES)
    out: dict = {"samples": SAMPLES, "scans": STEPS}
    out.update(_scenario(posed, CONFIGURATIONS, LATENCY_SCANS))
    warehouse = honest_posed_scans(warehouse_run(seed=0, steps=WAREHOUSE_STEPS), seed=1, particles=WAREHOUSE_PARTICLES)
    out.update({"warehouse_particles": WAREHOUSE_PARTICLES, "warehouse_scans": WAREHOUSE_STEPS})
    figures = _scenario(warehouse, WAREHOUSE_CONFIGURATIONS, WAREHOUSE_LATENCY_SCANS)
    figures.update(_tile_queries(warehouse))
    out.update({f"warehouse_{key}": value for key, value in figures.items()})
    return out
