"""Fusion on several threads (mapping.fusion.FusionThreads, mapping.parallel_fusion): whatever the thread count, the
map is the one the serial path (MonteCarloFusion.fuse, scan after scan) gives, bit for bit; refused scans, failures
and several laser geometries behave as they do scan by scan; `posegrid fuse`, the shard and the CLI options."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from bench.scenarios import honest_posed_scans, office_run
from mapping.errors import InputError
from mapping.fusion import FuseResult, FusionThreads, MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans, PoseSet, save_posed_scans
from schemas.messages import LaserScan, PoseSamples
from services.fusion_runner import PoseSampling, fuse_posed_scans
from services.process import RejectCounter
from services.state.ownership import owns_tile
from services.state.shard import MapShard, ShardConfig
from test_cli_mapping import posegrid

RES = 0.05
THREADS = (1, 2, 3, 4)
MODEL = SensorModel(resolution=RES)


@pytest.fixture(scope="module")
def office():
    return office_run(steps=40)


@pytest.fixture(scope="module")
def particles(office) -> PosedScans:
    return honest_posed_scans(office, particles=30)


@pytest.fixture(scope="module")
def gaussian(office) -> PosedScans:
    return honest_posed_scans(office)


def particle_scans(posed: PosedScans) -> list[tuple]:
    """(ranges, samples, weights) of every scan of a posed-scan file with pose samples."""
    samples, weights = posed.poses.weighted_samples()
    return [(posed.scan_ranges(t), samples[t], weights[t]) for t in range(len(posed.stamps))]


def gaussian_scans(posed: PosedScans) -> list[tuple]:
    """(ranges, samples, weights) of every scan of a Gaussian posed-scan file, its samples drawn as `posegrid fuse`
    draws them (the count derived from the covariance)."""
    sampling = PoseSampling(accuracy=RES)
    poses = posed.poses
    drawn = [sampling.draw(t, float(posed.range_max[t]), mean=poses.mean[t], cov=poses.cov[t]) for t in range(40)]
    return [(posed.scan_ranges(t), *drawn[t]) for t in range(len(posed.stamps))]


def serial(posed: PosedScans, scans: list[tuple], grid: TiledGrid, **fusion_options) -> list[FuseResult | InputError]:
    """The serial path: one MonteCarloFusion, :meth:`fuse` scan after scan (a refused scan's InputError kept)."""
    fusion = MonteCarloFusion(grid, MODEL, *posed.single_geometry(), **fusion_options)
    outcomes: list[FuseResult | InputError] = []
    for scan in scans:
        try:
            outcomes.append(fusion.fuse(*scan))
        except InputError as exc:
            outcomes.append(exc)
    return outcomes


def assert_same_map(got: TiledGrid, expected: TiledGrid) -> None:
    """Bit for bit: the same tiles in the same slots, and every layer equal."""
    assert got.keys() == expected.keys() and len(expected.keys()) > 0
    n = len(expected.keys())
    for layer in ("logodds", "variance", "observed"):
        assert np.array_equal(getattr(got, layer)[:n], getattr(expected, layer)[:n]), layer


def outcomes_text(outcomes: list) -> list:
    """Outcomes comparable with ==: results as they are, errors by type and message."""
    return [(type(o).__name__, str(o)) if isinstance(o, Exception) else o for o in outcomes]


@pytest.mark.parametrize("threads", THREADS)
@pytest.mark.parametrize("form", ["particles", "gaussian"])
def test_any_thread_count_gives_the_serial_map_bit_for_bit(request, form, threads):
    posed = request.getfixturevalue(form)
    scans = particle_scans(posed) if form == "particles" else gaussian_scans(posed)
    expected = TiledGrid(RES)
    serial_outcomes = serial(posed, scans, expected)
    got = TiledGrid(RES)
    outcomes = MonteCarloFusion(got, MODEL, *posed.single_geometry(), threads=threads).fuse_many(scans)
    assert outcomes == serial_outcomes
    assert_same_map(got, expected)
    assert np.count_nonzero(expected.variance) > 10_000  # several samples a scan: the spread layer is filled


@pytest.mark.parametrize("threads", THREADS)
def test_a_shards_tiles_are_the_serial_shards_bit_for_bit(particles, threads):
    """Small tiles, so that both shards own many tiles of each scan's window (the ownership-mask walk)."""
    scans = particle_scans(particles)
    for shard in range(2):
        expected, got = TiledGrid(RES, tile_size=32), TiledGrid(RES, tile_size=32)
        owner = owns_tile(shard, 2)
        serial(particles, scans, expected, owns_tile=owner)
        fusion = MonteCarloFusion(got, MODEL, *particles.single_geometry(), owner, threads=threads)
        fusion.fuse_many(scans)
        assert_same_map(got, expected)
        assert all(owner(*key) for key in got.keys())  # noqa: SIM118 - a TiledGrid, not a dict


@pytest.mark.parametrize("threads", THREADS)
def test_a_batch_mixing_one_pose_and_many_pose_scans(particles, threads):
    """One pose (the one-sample pass), 30 copies of one pose (merged: the one-sample pass), and 30 distinct samples
    (the samples pass), scan after scan: the passes' scratches are reused across kinds."""
    scans = []
    for t, (ranges, samples, weights) in enumerate(particle_scans(particles)):
        if t % 3 == 0:
            scans.append((ranges, samples[:1], np.ones(1)))
        elif t % 3 == 1:
            scans.append((ranges, np.repeat(samples[:1], 30, axis=0), np.full(30, 1 / 30)))
        else:
            scans.append((ranges, samples, weights))
    expected, got = TiledGrid(RES), TiledGrid(RES)
    serial_outcomes = serial(particles, scans, expected)
    outcomes = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=threads).fuse_many(scans)
    assert outcomes == serial_outcomes
    assert_same_map(got, expected)


@pytest.mark.parametrize("threads", THREADS)
def test_a_refused_scan_is_its_own_outcome_and_the_others_are_fused(particles, threads):
    """Weights that do not sum to 1, a scan with no usable beam and a wrong beam count: each outcome is what
    fuse gives that scan (an InputError, or an empty result), the map is the one of the other scans."""
    scans = particle_scans(particles)
    ranges, samples, weights = scans[5]
    scans[5] = (ranges, samples, 2 * weights)
    scans[6] = (np.full_like(scans[6][0], -1.0), *scans[6][1:])
    scans[11] = (scans[11][0][:-1], *scans[11][1:])
    expected, got = TiledGrid(RES), TiledGrid(RES)
    serial_outcomes = serial(particles, scans, expected)
    outcomes = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=threads).fuse_many(scans)
    assert isinstance(outcomes[5], InputError) and "sum to 1" in str(outcomes[5])
    assert outcomes[6] == FuseResult(0, []) and isinstance(outcomes[11], InputError)
    assert outcomes_text(outcomes) == outcomes_text(serial_outcomes)
    assert_same_map(got, expected)


class _Broken(Exception):
    """The error a scan source raises half way."""


@pytest.mark.parametrize("threads", THREADS)
def test_an_error_stops_at_its_scan_with_the_earlier_ones_fused_and_no_later_one(particles, threads):
    """A failure that is no refused input (here the scans' own iterator fails at scan 7) is raised at its turn: the
    map holds scans 0-6 exactly, although later scans were being walked, and the threads are idle afterwards."""
    scans = particle_scans(particles)

    def failing():
        for t, scan in enumerate(scans):
            if t == 7:
                raise _Broken("scan 7")
            yield scan

    expected, got = TiledGrid(RES), TiledGrid(RES)
    serial(particles, scans[:7], expected)
    fusion = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=threads)
    taken = []
    with pytest.raises(_Broken):
        for outcome in fusion.fuse_iter(failing()):
            taken.append(outcome)
    assert len(taken) == 7
    assert_same_map(got, expected)
    fusion.fuse_many(scans[7:])  # the scratches are free again: the rest gives the whole map
    whole = TiledGrid(RES)
    serial(particles, scans, whole)
    assert_same_map(got, whole)


@pytest.mark.parametrize("threads", (2, 3))
@pytest.mark.parametrize("stop", ("walk fails", "caller stops"))
def test_walks_never_applied_leave_nothing_in_the_next_scans(particles, monkeypatch, threads, stop):
    """Scans walked side by side whose turn never comes (a walk that fails at scan 5, a fault injected: walks do not
    fail on any input; or a caller that stops after 5 outcomes) hold marks nothing would clear: the threads' next
    scans must not carry them. The map is that of scans 0-4 and of the scans fused afterwards, as one thread gives."""
    scans = particle_scans(particles)
    fusion = MonteCarloFusion(TiledGrid(RES), MODEL, *particles.single_geometry(), threads=threads)
    if stop == "walk fails":
        walk = MonteCarloFusion.walk

        def walk_or_fail(self, ready, scratch, part=0, parts=1):
            if np.array_equal(ready.lasers[:, :2], fusion.prepare(scans[5]).lasers[:, :2]):
                raise RuntimeError("walk of scan 5 failed")
            return walk(self, ready, scratch, part, parts)

        monkeypatch.setattr(MonteCarloFusion, "walk", walk_or_fail)
        with pytest.raises(RuntimeError, match="scan 5"):
            fusion.fuse_many(scans)
        monkeypatch.undo()
    else:
        outcomes = fusion.fuse_iter(scans)
        assert [next(outcomes) for _ in range(5)] and len(fusion.grid.keys()) > 0
        outcomes.close()  # (scans 5, 6, ... were being walked)
    fusion.fuse_many(scans[20:])
    expected = TiledGrid(RES)
    serial(particles, scans[:5] + scans[20:], expected)
    assert_same_map(fusion.grid, expected)


@pytest.mark.parametrize("threads", THREADS)
def test_two_laser_geometries_interleaved_share_the_threads(particles, threads):
    """An interlaced laser: every other scan has every other beam and a shorter range, each geometry its own
    fusion, all writing one grid in scan order."""
    angles, range_min, range_max, offset = particles.single_geometry()
    scans = particle_scans(particles)
    half = [(ranges[::2], samples, weights) for ranges, samples, weights in scans]
    order = [(t % 2, half[t] if t % 2 else scans[t]) for t in range(len(scans))]

    def fusions(grid, shared):
        return (
            MonteCarloFusion(grid, MODEL, angles, range_min, range_max, offset, threads=shared),
            MonteCarloFusion(grid, MODEL, angles[::2], range_min, 0.75 * range_max, offset, threads=shared),
        )

    expected = TiledGrid(RES)
    one_by_one = fusions(expected, 1)
    for which, scan in order:
        one_by_one[which].fuse(*scan)
    got, shared = TiledGrid(RES), FusionThreads(threads)
    pair = fusions(got, shared)
    outcomes = list(shared.fuse_iter((pair[which], scan) for which, scan in order))
    assert all(isinstance(o, FuseResult) and o.cells_updated > 0 for o in outcomes)
    assert_same_map(got, expected)


def test_fuse_posed_scans_on_threads_equals_one_thread(gaussian):
    expected = fuse_posed_scans(gaussian, threads=1).rasterize()
    for threads in (2, 3):
        got = fuse_posed_scans(gaussian, threads=threads).rasterize()
        assert all(np.array_equal(got[key], expected[key]) for key in expected)


def test_fuse_posed_scans_raises_the_first_refused_scan(particles):
    """As on one thread: the scan's InputError, with the scans before it fused and none after it."""
    samples, weights = particles.poses.weighted_samples()
    weights = weights.copy()
    weights[9] *= 3.0
    bad = PosedScans.from_scans(particles, PoseSet(samples=samples, weights=weights))
    expected = TiledGrid(RES)
    serial(particles, particle_scans(particles)[:9], expected)
    for threads in (1, 3):
        grid = TiledGrid(RES)
        with pytest.raises(InputError, match="sum to 1"):
            fuse_posed_scans(bad, grid=grid, threads=threads)
        assert_same_map(grid, expected)


def _messages(posed: PosedScans) -> list[tuple[str, bytes]]:
    """The scans and poses of ``posed`` as a shard receives them (scan, then pose), every other scan with every other
    beam (a second laser geometry)."""
    samples, weights = posed.poses.weighted_samples()
    angles = posed.single_geometry()
    messages = []
    for t in range(len(posed.stamps)):
        step = 2 if t % 2 else 1
        scan = LaserScan(
            robot="r",
            seq=t,
            stamp=float(posed.stamps[t]),
            angle_min=float(angles.beam_angles[0]),
            angle_increment=float(angles.beam_angles[1] - angles.beam_angles[0]) * step,
            range_min=angles.range_min,
            range_max=angles.range_max,
            sensor_offset=angles.sensor_offset,
            ranges=posed.scan_ranges(t)[::step].astype(np.float32),
            no_return_range=angles.range_max,
        )
        pose = PoseSamples(robot="r", seq=t, stamp=float(posed.stamps[t]), samples=samples[t], weights=weights[t])
        messages += [("pg/r/scan", scan.encode()), ("pg/r/pose", pose.encode())]
    return messages


def _shard(threads: int) -> MapShard:
    config = ShardConfig("m", 0, 1, MODEL, tile_size=64, threads=threads)
    return MapShard(config, RejectCounter(logging.getLogger("test-threads")))


@pytest.mark.parametrize("threads", (2, 3))
def test_a_shard_fuses_what_several_messages_complete_together_into_the_same_map(particles, threads):
    """The mapper's main thread hands a shard several messages (defer) and then fuses the pairs they complete
    (fuse_ready), two laser geometries mixed: the map and the counts are those of one message at a time."""
    messages = _messages(particles)
    one = _shard(1)
    for key, payload in messages:
        one.handle(key, payload)
    many = _shard(threads)
    for first in range(0, len(messages), 9):
        for key, payload in messages[first : first + 9]:
            many.handle(key, payload, defer=True)
        many.fuse_ready()
    assert_same_map(many.grid, one.grid)
    assert many.fused == one.fused == {"r": 40} and many.cells_updated == one.cells_updated
    assert sorted(many.tiles()) == sorted(one.tiles())


def test_posegrid_fuse_writes_the_same_file_on_two_threads_as_on_one(particles, tmp_path):
    posed = tmp_path / "office.npz"
    save_posed_scans(posed, particles)
    outputs = []
    for threads in ("1", "2", "1000"):
        output = tmp_path / f"map{threads}.npz"
        result = posegrid("fuse", str(posed), "-o", str(output), "--threads", threads)
        assert result.returncode == 0, result.stderr
        outputs.append(output.read_bytes())
    assert outputs[0] == outputs[1] == outputs[2]
    # more threads than cores fuse on the cores (each thread's scratch window took memory for nothing: 64 threads
    # were accepted on 2 cores), and say so
    cores = len(os.sched_getaffinity(0))
    assert f"--threads 1000 is more than the {cores} core(s) this process may use; fusing on {cores}" in result.stderr


@pytest.mark.parametrize(
    "command, value",
    [
        (["fuse", "posed.npz", "-o", "map.npz"], "0"),
        (["fuse", "posed.npz", "-o", "map.npz"], "-1"),
        (["fuse", "posed.npz", "-o", "map.npz"], "x"),
        (["mapper", "--shard", "0", "--shards", "1"], "0"),
        (["run", "--no-api", "--export", "map.npz"], "x"),
    ],
)
def test_a_bad_thread_count_is_refused_in_one_line(tmp_path, command, value):
    """Before anything is read or started (the posed-scan file does not even exist)."""
    result = posegrid(
        *(str(tmp_path / part) if part.endswith(".npz") else part for part in command), "--threads", value
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert "--threads" in lines[0] and repr(value) in lines[0]


def test_threads_below_one_are_refused_by_the_library():
    with pytest.raises(InputError, match="threads >= 1"):
        FusionThreads(0)


def test_the_fusions_of_one_thread_walk_into_one_shared_scratch(particles):
    """A probe's finding: with one thread each laser geometry's fusion kept a scratch of its own, grown to its widest
    window (a peer's six geometries of spread samples held 3.3 GiB). The fusions of one FusionThreads now walk into
    its one lone scratch, and two geometries fused in turns (scans of 30 samples and of one, both passes) give the
    maps that fusions with scratches of their own give, bit for bit."""
    geometry = particles.single_geometry()
    shorter = geometry._replace(range_max=geometry.range_max * 0.8)  # another geometry: another fusion
    scans = particle_scans(particles)[:12]
    scans = [scan if t % 3 else (scan[0], scan[1][:1], np.ones(1)) for t, scan in enumerate(scans)]
    shared_grid, own_grid = TiledGrid(RES), TiledGrid(RES)
    threads = FusionThreads(1)
    shared = [MonteCarloFusion(shared_grid, MODEL, *g, threads=threads) for g in (geometry, shorter)]
    own = [MonteCarloFusion(own_grid, MODEL, *g) for g in (geometry, shorter)]
    for t, scan in enumerate(scans):
        shared[t % 2].fuse(*scan)
        own[t % 2].fuse(*scan)
    assert shared[0].threads.lone is shared[1].threads.lone and own[0].threads.lone is not own[1].threads.lone
    assert threads.lone.size > 0 and not hasattr(shared[0], "_scratch")
    for key in own_grid.keys():  # noqa: SIM118 - a TiledGrid, not a dict
        for a, b in zip(shared_grid.tile_arrays(key), own_grid.tile_arrays(key)):
            np.testing.assert_array_equal(a, b)
    assert shared_grid.keys() == own_grid.keys()
