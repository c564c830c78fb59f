"""Hostile peers during a run (issue 29): what a bounded mix of bad messages costs the mapper shards.

Two runs of the same pipeline, each a router and two mapper shards (processes) on loopback, with the source
publishing the simulated office's first SCANS scans with SAMPLES pose samples each (posed scans, no SLAM node,
"as fast as the shards take") for robot "bench" from this process:

- clean: nothing else on the network;
- hostile: the same, while a thread of this process, with a Zenoh session of its own, sends a deterministic mix
  (seed MIX_SEED, about MIX_MESSAGES messages, congestion control BLOCK, as fast as the network takes them) once
  both shards have fused the robot's first scan: random bytes, truncated and bit-flipped messages, messages of the
  wrong type or of another robot on every key a peer may publish on (pg/bench/<stream> for every robot stream,
  tile, stats, history and SLAM-stats keys, the reserved name pg/map/scan); the same on wildcard keys (pg/**,
  pg/bench/*, pg/*/scan, pg/bench/sc$* ...); valid scans and poses of "bench" at forged seqs far ahead (100 000
  on); forged ends of its stream (2**53 - 1 and 10**6 scans); scans of max_beams + 1 beams and payloads larger than
  any message a shard takes; a scan posed 5 000 m away (robot "faraway"), one whose samples spread over 1 800 m
  (robot "sprawl"), a 30 000-beam scan with a pose of 10 000 samples (robot "intruder"); and scans of 200 stray
  robot names, more than a shard keeps state for (max_robots).

Figures: whether every process is alive at the end, the scans of "bench" each shard fused (all of them?), whether
the assembled map is bit-identical to the clean run's (logodds, observed, variance and origin of the raster),
each shard's peak resident memory (VmHWM) against the clean run's, what the shards refused, by kind, summed
over the shards, and how many of the mix's messages reached no counter of a shard at all (unaccounted, the most
of any shard; :func:`unaccounted`).

Zenoh's shared-memory transport lost large blocking puts here while a shard's network thread waited for the GIL;
posegrid turns it off in every config it builds (services.zenoh_config), and every message is accounted for.

What the mix leaves out, because no limit can tell it from the real robot (only access control keeps such a
peer out, docs/security.md):

- valid messages of "bench" at seqs within the seq window of its stream (services.state.join.DEFAULT_SEQ_WINDOW): a
  forged pose for a seq the real stream has not reached yet is taken first (the first one stands), so the map
  would differ;
- stray robot names before the real robot's first message: the max_robots slots go first come, first served,
  so the mix starts once the shards know "bench".

All processes share this machine's cores; the hostile run is slower, and its wall time is reported, not judged.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from dataclasses import dataclass, replace

import numpy as np
import zenoh

from bench.pipeline import ROBOT, Cluster
from bench.scenarios import honest_posed_scans, office_run
from mapping.grid import TILE_SIZE
from mapping.sensor_model import SensorModel
from schemas.messages import MAX_SEQ, LaserScan, MessageError, PoseSamples, ShardStats, StreamEnd
from services import keys
from services.map_client import IncompleteMap, MapReader
from services.nodes.source import Source, SourceOptions, SourceStalled
from services.process import get_logger
from services.state.limits import ShardLimits
from services.state.shard import SHARD_STREAMS
from services.streams import Step, Stream, posed_stream
from services.zenoh_config import build_config

SCANS = 200
SAMPLES = 30
SHARDS = 2
MAP = "chaos"
MIX_SEED = 29
MIX_MESSAGES = 5_000  # about: the garbage fills up what the other parts leave
#: first seq of the forged far scans and poses of the real robot, and the step between them (1: runs of consecutive
#: seqs, which the join checks against the histories and does not believe)
FORGED_SEQ = 100_000
FORGED_SEQ_STEP = 1
FORGED = 200  # forged far scans, as many poses, and half as many forged ends
STRAY_ROBOTS = 200
#: scans of the real robot both shards fuse before the mix starts (so they know the robot)
MIX_AFTER_FUSED = 1
#: s the shards' counts must stay unchanged after the mix and the run before they count as drained
QUIET = 1.0
#: the mapper's default cell size, m (what the shards map at: `posegrid mapper --resolution`)
RESOLUTION = SensorModel().resolution
LIMITS = ShardLimits()  # the limits the shards run with (their defaults)
BLOCK = zenoh.CongestionControl.BLOCK
LOG = get_logger("bench.chaos")

Mix = list[tuple[str, bytes]]  # (key, payload), in sending order


class QuietCluster(Cluster):
    """A :class:`bench.pipeline.Cluster` whose tile subscriber counts payloads that are no TileUpdate (the mix
    sends garbage on the tile keys too) instead of raising in the Zenoh callback."""

    bad_tiles = 0

    def _on_tile(self, sample: zenoh.Sample) -> None:
        try:
            super()._on_tile(sample)
        except MessageError:
            self.bad_tiles += 1


# ------------------------------------------------------------------------------------------ the mix
def _garbage_payloads(rng: np.random.Generator, templates: list[bytes], count: int) -> list[bytes]:
    """``count`` bad payloads: random bytes (0 to 4 KiB, log-uniform), ``templates`` (valid encodings) cut short,
    and ``templates`` with a few bytes overwritten, a third each. An overwritten byte may leave a valid message
    (another seq, another value), so the templates must be ones that may arrive whatever their seq:
    :func:`_ghost`'s."""
    out = []
    for i in range(count):
        kind = i % 3
        if kind == 0:
            out.append(rng.bytes(int(np.exp(rng.uniform(0, np.log(4096))))))
            continue
        payload = bytearray(templates[rng.integers(len(templates))])
        if kind == 1:
            out.append(bytes(payload[: rng.integers(len(payload))]))
        else:
            where = rng.integers(0, len(payload), size=int(rng.integers(1, 8)))
            payload_array = np.frombuffer(payload, np.uint8).copy()
            payload_array[where] = rng.integers(0, 256, size=where.size, dtype=np.uint8)
            out.append(payload_array.tobytes())
    return out


def _peer_keys(map_name: str) -> list[str]:
    """Every concrete key a peer may publish on around robot ROBOT and map ``map_name``, and some it may not."""
    streams = sorted(keys.ROBOT_STREAMS)
    return (
        [keys.robot_key(ROBOT, s) for s in streams]
        + [keys.history_key(ROBOT, s) for s in (keys.SCAN, keys.POSE)]
        + [
            keys.tile_key(map_name, 0, 0, 0),
            keys.stats_key(map_name, 0),
            keys.slam_stats_key(ROBOT),
            keys.robot_alive_key(ROBOT, "source"),
            keys.robot_key("map", keys.SCAN),
            keys.robot_key("intruder", keys.SCAN),
        ]
    )


#: wildcard keys (Zenoh takes a put on any of them; "$*" only inside a chunk: "pg/bench/$*" is not canonical)
WILDCARDS = (
    "pg/**",
    "**",
    "pg/bench/*",
    "pg/bench/**",
    "pg/*/scan",
    "pg/*/pose",
    "pg/*/end",
    "pg/*/*",
    "pg/bench/sc$*",
    "pg/*/po$*",
)


def _scan_and_pose(step: Step) -> tuple[LaserScan, PoseSamples]:
    """The scan and the pose samples of one step of a posed-scan stream (:func:`services.streams.posed_stream`)."""
    scan, pose = step.messages
    if not isinstance(scan, LaserScan) or not isinstance(pose, PoseSamples):
        raise TypeError(
            f"a step of scan and pose samples expected, got {type(scan).__name__} and {type(pose).__name__}"
        )
    return scan, pose


def _forged(stream: Stream, count: int) -> tuple[list[LaserScan], list[PoseSamples], list[StreamEnd]]:
    """``count`` scans and poses of the real robot at seqs FORGED_SEQ, + FORGED_SEQ_STEP, ... (copies of its real
    ones, valid and in the office), and ``count // 2`` forged ends of its stream (2**53 - 1 and 10**6 scans)."""
    scans, poses = [], []
    for i in range(count):
        scan, pose = _scan_and_pose(stream.steps[i % len(stream.steps)])
        scans.append(replace(scan, seq=FORGED_SEQ + FORGED_SEQ_STEP * i))
        poses.append(replace(pose, seq=FORGED_SEQ + FORGED_SEQ_STEP * i))
    ends = [StreamEnd(robot=ROBOT, scans=MAX_SEQ if i % 2 else 10**6) for i in range(count // 2)]
    return scans, poses, ends


def _ghost(scan: LaserScan, pose: PoseSamples) -> list[bytes]:
    """Templates for :func:`_garbage_payloads`: a scan and a pose of robot "ghost" (no other message is of it) at
    seq FORGED_SEQ, the pose 5 000 m out (beyond the map bound), and an end of its stream. Overwritten bytes
    may change its seqs (the msgpack integer type byte among them), but not the robot name into "bench"."""
    far = pose.samples + [5_000.0, 0.0, 0.0]
    return [
        replace(scan, robot="ghost", seq=FORGED_SEQ).encode(),
        replace(pose, robot="ghost", seq=FORGED_SEQ, samples=far).encode(),
        StreamEnd(robot="ghost", scans=MAX_SEQ).encode(),
    ]


def _samples(robot: str, seq: int, points: np.ndarray) -> PoseSamples:
    """A pose of ``robot`` at ``seq``: equally weighted samples ``points`` (M, 3: x m, y m, yaw rad)."""
    return PoseSamples(robot=robot, seq=seq, stamp=0.0, samples=points, weights=np.full(len(points), 1 / len(points)))


def _limit_probes(rng: np.random.Generator, scan: LaserScan) -> Mix:
    """Scans and poses past each resource limit, each robot at seqs 0, 1 ... of its own: bound ("faraway",
    5 000 m out), extent ("sprawl", 100 samples over +-900 m), work ("intruder": 30 000 beams, 10 000 samples),
    size (scans of max_beams + 1 beams of "intruder", with poses in the office, and payloads larger than any
    message a shard takes, on the real robot's scan key)."""
    mix: Mix = []

    def pair(robot: str, seq: int, ranges: np.ndarray, points: np.ndarray) -> None:
        fan = scan.angle_increment * (len(scan.ranges) - 1)  # the probe's beams over the laser's fan: a valid scan
        increment = fan / max(len(ranges) - 1, 1)
        probe = replace(scan, robot=robot, seq=seq, ranges=ranges.astype(np.float32), angle_increment=increment)
        pose = _samples(robot, seq, points)
        mix.extend(
            [(keys.robot_key(robot, keys.SCAN), probe.encode()), (keys.robot_key(robot, keys.POSE), pose.encode())]
        )

    office = np.array([[2.0, 2.0, 0.0]])
    pair("faraway", 0, scan.ranges, office + [5_000.0, 0.0, 0.0])
    pair("sprawl", 0, scan.ranges, np.column_stack([rng.uniform(-900, 900, (100, 2)), np.zeros(100)]))
    wide = rng.uniform(0.5, scan.range_max, 30_000)
    pair("intruder", 0, wide, office + rng.normal(0, 0.05, (10_000, 3)))
    oversize = rng.uniform(0.5, scan.range_max, LIMITS.max_beams + 1)
    for seq in range(1, 11):
        pair("intruder", seq, oversize, office)
    mix += [(keys.robot_key(ROBOT, keys.SCAN), rng.bytes(LIMITS.message_bytes() + 1)) for _ in range(5)]
    return mix


def hostile_mix(stream: Stream, map_name: str, seed: int = MIX_SEED, total: int = MIX_MESSAGES) -> Mix:
    """The deterministic mix of the module docstring, about ``total`` messages: the limit probes first (before
    the stray robots take the free robot slots), then garbage, wildcards, forged seqs and ends shuffled, then
    the stray robots' scans (no poses: nothing of theirs is fused)."""
    rng = np.random.default_rng(seed)
    scan, pose = _scan_and_pose(stream.steps[0])
    probes = _limit_probes(rng, scan)
    scans, poses, ends = _forged(stream, FORGED)
    forged = [(keys.robot_key(ROBOT, keys.STREAM_OF[type(m)]), m.encode()) for m in scans + poses + ends]
    valid = [m.encode() for m in (scans[0], poses[0], ends[0], ends[1])]
    on = {stream: keys.robot_key(ROBOT, stream) for stream in SHARD_STREAMS}
    wrong = [
        (on[keys.SCAN], poses[1].encode()),
        (on[keys.POSE], scans[1].encode()),
        (on[keys.END], scans[2].encode()),
        (on[keys.SCAN], replace(scans[3], robot="intruder").encode()),
    ] * 10  # wrong type; another robot's
    wild = [(WILDCARDS[i % len(WILDCARDS)], valid[i % len(valid)] if i % 2 else rng.bytes(64)) for i in range(500)]
    strays = [
        (keys.robot_key(f"stray{i:03d}", keys.SCAN), replace(scan, robot=f"stray{i:03d}").encode())
        for i in range(STRAY_ROBOTS)
    ]
    room = max(0, total - len(probes) - len(forged) - len(wrong) - len(wild) - len(strays))
    targets = _peer_keys(map_name)
    garbage = [
        (targets[i % len(targets)], payload)
        for i, payload in enumerate(_garbage_payloads(rng, _ghost(scan, pose), room))
    ]
    body = forged + wrong + wild + garbage
    order = rng.permutation(len(body))
    return probes + [body[i] for i in order] + strays


# ------------------------------------------------------------------------------------------ the hostile peer
@dataclass
class Peer:
    """The hostile thread's outcome: messages sent, how many of them before the real run was over (the source had
    every scan of it fused and its end acknowledged), when it started and ended (time.perf_counter s), and the
    exception that stopped it, if one did."""

    sent: int = 0
    during_run: int = 0
    started: float = float("nan")
    ended: float = float("nan")
    error: BaseException | None = None


def _wait_for_robot(session: zenoh.Session, map_name: str, timeout: float = 120.0) -> None:
    """Until every shard has fused MIX_AFTER_FUSED scans of the real robot."""
    reader = MapReader(session, map_name)
    deadline = time.monotonic() + timeout
    while True:
        stats = reader.stats()
        if len(stats) == SHARDS and min(s.fused.get(ROBOT, 0) for s in stats.values()) >= MIX_AFTER_FUSED:
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f"the shards did not fuse {MIX_AFTER_FUSED} scans of {ROBOT!r} in {timeout:.0f} s")
        time.sleep(0.02)


def send_mix(endpoint: str, map_name: str, mix: Mix, peer: Peer) -> None:
    """Open a session of its own on ``endpoint``, wait for the shards to know the real robot, and put ``mix`` as
    fast as the network takes it (congestion control BLOCK). Records into ``peer``."""
    session = zenoh.open(build_config("client", connect=[endpoint]))
    try:
        _wait_for_robot(session, map_name)
        peer.started = time.perf_counter()
        for key, payload in mix:
            session.put(key, payload, congestion_control=BLOCK)
            peer.sent += 1
        peer.ended = time.perf_counter()
    except BaseException as exc:  # noqa: BLE001 - handed to the main thread, which raises it
        peer.error = exc
    finally:
        session.close()


# ------------------------------------------------------------------------------------------ one run
@dataclass
class RunResult:
    """What one run left: the raster of the assembled map (None when it could not be assembled), each reachable
    shard's stats and each live shard's peak RSS (bytes), by shard index, whether every process was alive at the
    end, whether the source saw every scan accounted for by every shard, and the run's wall time (s)."""

    raster: dict[str, np.ndarray] | None
    stats: dict[int, ShardStats]
    peak_rss: dict[int, int]
    alive: bool
    completed: bool
    wall_s: float
    peer: Peer | None = None


def peak_rss(pid: int) -> int | None:
    """Peak resident set size of process ``pid`` so far (VmHWM), bytes; None once it has ended."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except FileNotFoundError:
        pass
    return None


def _settled_stats(reader: MapReader, timeout: float = 60.0) -> dict[int, ShardStats]:
    """The stats of the shards that answer, once their received and refused counts have not moved for QUIET s
    (the intake queues drained), or as they are after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    last = None
    while True:
        stats = reader.stats()
        now = tuple(sorted((i, sum(s.received.values()), sum(s.refused.values())) for i, s in stats.items()))
        if now == last or time.monotonic() > deadline:
            return stats
        last = now
        time.sleep(QUIET)


def _publish(cluster: Cluster, stream: Stream) -> bool:
    """Publish ``stream`` as fast as the shards take it; whether every shard acknowledged its end with every scan
    fused or given up (False when the source stalled, e.g. because the shards refuse the end)."""
    try:
        Source(cluster.session, stream, SourceOptions(rate=None, wait_mappers=SHARDS, map_name=MAP)).run(
            threading.Event()
        )
    except SourceStalled as exc:
        LOG.warning("the source stalled: %s", exc)
        return False
    return True


def _one_run(stream: Stream, mix: Mix | None) -> RunResult:
    """Run the pipeline on ``stream`` (with a hostile peer sending ``mix`` unless it is None) and read what it
    left, before stopping it."""
    started = time.perf_counter()
    with QuietCluster(SHARDS, MAP, TILE_SIZE) as cluster:
        peer, thread = None, None
        if mix is not None:
            peer = Peer()
            thread = threading.Thread(
                target=send_mix, name="hostile peer", daemon=True, args=(cluster.endpoint, MAP, mix, peer)
            )
            thread.start()
        completed = _publish(cluster, stream)
        if peer is not None and thread is not None:
            peer.during_run = peer.sent
            thread.join(300)
            if peer.error is not None:
                raise RuntimeError("the hostile peer failed") from peer.error
        reader = MapReader(cluster.session, MAP)
        stats = _settled_stats(reader)
        try:
            raster = reader.assemble(SHARDS, RESOLUTION).rasterize()
        except IncompleteMap as exc:
            LOG.warning("the map could not be assembled: %s", exc)
            raster = None
        rss = {
            int(c.name[len("mapper[") : -1]): peak_rss(c.process.pid)
            for c in cluster.children.children
            if c.name.startswith("mapper[")
        }
        alive = cluster.children.failed() is None and all(c.process.poll() is None for c in cluster.children.children)
    return RunResult(
        raster,
        stats,
        {i: v for i, v in rss.items() if v is not None},
        alive,
        completed,
        time.perf_counter() - started,
        peer,
    )


# ------------------------------------------------------------------------------------------ figures
def identical(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray] | None) -> bool:
    """Whether two rasters have bit-identical logodds, observed, variance and origin (False if one is None)."""
    if a is None or b is None:
        return False
    return all(
        a[k].shape == b[k].shape and a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes()
        for k in ("logodds", "observed", "variance", "origin")
    )


def cells_differing(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray] | None) -> int:
    """Cells whose log-odds differ between two rasters of one shape; -1 when their shapes differ or one is None."""
    if a is None or b is None or a["logodds"].shape != b["logodds"].shape:
        return -1
    return int(np.count_nonzero(a["logodds"] != b["logodds"]))


def expected_arrivals(mix: Mix) -> int:
    """Deliveries of ``mix`` one shard should count: each message once per subscriber of the shard whose key
    expression (pg/*/scan, pg/*/pose, pg/*/end) its key intersects (a put on pg/** reaches all three)."""
    subscribed = [zenoh.KeyExpr(keys.robot_key("*", stream)) for stream in SHARD_STREAMS]
    return sum(sum(zenoh.KeyExpr(key).intersects(sub) for sub in subscribed) for key, _ in mix)


def unaccounted(stats: ShardStats, mix: Mix, real_scans: int) -> int:
    """Deliveries of ``mix`` (:func:`expected_arrivals`) that reached no counter of shard ``stats``: neither received
    (decoded, or refused as malformed, ahead ...) nor refused before that (by key, robot count or a full intake
    queue); 0 when nothing was lost on the way. Left out on both sides: the robot's end key (the source repeats
    its end a varying number of times) and payloads larger than any message a shard takes (refused as ``size``
    on arrival, a kind also counted after decoding). ``real_scans``: the real robot's scans (and as many poses)."""
    end = keys.robot_key(ROBOT, keys.END)
    expected = expected_arrivals([(key, payload) for key, payload in mix if key != end])
    intake_size = sum(len(payload) > LIMITS.message_bytes() for key, payload in mix if key != end)
    received = sum(count for key, count in stats.received.items() if key != end) - 2 * real_scans
    refused_early = sum(stats.refused.get(kind, 0) for kind in ("key", "robots", "overflow"))
    return expected - intake_size - received - refused_early


def _fused(run: RunResult) -> int:
    """Scans of the real robot the shard that fused fewest fused (0 when a shard did not answer)."""
    if len(run.stats) < SHARDS:
        return 0
    return min(s.fused.get(ROBOT, 0) for s in run.stats.values())


def _refused(run: RunResult) -> Counter:
    return sum((Counter(s.refused) for s in run.stats.values()), Counter())


def _rss_ratio_max(clean: RunResult, chaos: RunResult) -> float:
    """The largest ratio of a shard's peak RSS in the hostile run to its peak in the clean run (NaN without one)."""
    ratios = [chaos.peak_rss[i] / clean.peak_rss[i] for i in clean.peak_rss if i in chaos.peak_rss]
    return max(ratios, default=float("nan"))


def run() -> dict:
    posed = honest_posed_scans(office_run(seed=0, steps=SCANS), seed=1, particles=SAMPLES)
    stream = posed_stream(posed, ROBOT)
    mix = hostile_mix(stream, MAP)
    clean = _one_run(stream, None)
    chaos = _one_run(stream, mix)
    peer = chaos.peer
    if peer is None:
        raise RuntimeError("the chaos run has no hostile peer")
    out: dict = {
        "scans": SCANS,
        "samples": SAMPLES,
        "shards": SHARDS,
        "chaos_alive_all": chaos.alive,
        "clean_alive_all": clean.alive,
        "chaos_source_completed": chaos.completed,
        "clean_source_completed": clean.completed,
        "chaos_scans_total": len(stream.steps),
        "chaos_scans_fused": _fused(chaos),
        "clean_scans_fused": _fused(clean),
        "chaos_scans_discarded": max((s.discarded.get(ROBOT, 0) for s in chaos.stats.values()), default=0),
        "chaos_map_identical": identical(clean.raster, chaos.raster),
        "chaos_map_cells_differing": cells_differing(clean.raster, chaos.raster),
        "chaos_rss_ratio_max": _rss_ratio_max(clean, chaos),
        "chaos_rss_mb_max": max(chaos.peak_rss.values(), default=0) / 2**20,
        "clean_rss_mb_max": max(clean.peak_rss.values(), default=0) / 2**20,
        "chaos_messages_sent": peer.sent,
        "chaos_messages_during_run": peer.during_run,
        "chaos_messages_unaccounted": max(
            (unaccounted(s, mix, len(stream.steps)) for s in chaos.stats.values()), default=-1
        ),
        "chaos_mix_s": peer.ended - peer.started,
        "clean_run_s": clean.wall_s,
        "chaos_run_s": chaos.wall_s,
        "clean_refused_total": sum(_refused(clean).values()),
    }
    for kind, count in sorted(_refused(chaos).items()):
        out[f"chaos_refused_{kind}"] = count
    return out
