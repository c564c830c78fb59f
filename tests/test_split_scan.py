"""One scan's samples walked in parts (MonteCarloFusion.walk's part and parts, apply_parts; FusionThreads for a lone
scan; a live shard): the map is the one a single walk of all the samples gives, bit for bit, because the samples
pass sums whole numbers of fixed steps (mapping.fixed_point), which add up the same in any order."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mapping.fusion as fusion_module
from bench.scenarios import honest_posed_scans, office_run
from mapping.fixed_point import MAX_FRACTION_BITS, SUM_BITS, moment_scale
from mapping.fusion import FusionScratch, FusionThreads, MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.samples_pass import add_sample_excess
from mapping.sensor_model import SensorModel
from services.process import RejectCounter
from services.state.ownership import owns_tile
from services.state.shard import MapShard, ShardConfig
from test_threads import _messages, assert_same_map, particle_scans

RES = 0.05
MODEL = SensorModel(resolution=RES)


@pytest.fixture(scope="module")
def particles():
    """Office scans under 40 particles: up to 5 parts of 8 samples."""
    return honest_posed_scans(office_run(steps=16), particles=40)


def unequal(scans: list[tuple]) -> list[tuple]:
    """The same scans with seeded random weights (summing to 1): the weight sums W are summed, not counted."""
    out = []
    for t, (ranges, samples, _) in enumerate(scans):
        weights = np.random.default_rng(t).random(len(samples)) + 0.1
        out.append((ranges, samples, weights / weights.sum()))
    return out


def fused_in_parts(posed, scans, parts: int, grid: TiledGrid, owner=None) -> None:
    """Each scan prepared once and walked in ``parts`` parts, one after the other, each into a scratch of its own
    (a part's scratch is reused by the next scan's same part, as the threads' scratches are)."""
    fusion = MonteCarloFusion(grid, MODEL, *posed.single_geometry(), owner)
    scratches = [FusionScratch() for _ in range(parts)]
    for scan in scans:
        ready = fusion.prepare(scan)
        assert ready is not None and fusion.parts_for(ready, parts) == parts
        fusion.apply_parts([fusion.walk(ready, scratches[part], part, parts) for part in reversed(range(parts))])
        for scratch in scratches:  # (the first applied, the others merged into it: all cleared)
            assert not (scratch.listed.any() or scratch.raised.any() or scratch.counts.any())
            assert not scratch.weight_sum.any()
            assert not scratch.moments[:, 2:].any()


@pytest.mark.parametrize("parts", (2, 3, 5))
@pytest.mark.parametrize("weights", ("equal", "unequal"))
@pytest.mark.parametrize("shard", (None, 0, 1))
def test_a_scan_walked_in_parts_gives_the_map_of_one_walk(particles, parts, weights, shard):
    """Whole windows and each of two shards of 32-cell tiles (the ownership walk), equal weights (counted) and
    unequal ones (summed), the parts walked last first: the map of fuse(), which walks all samples at once."""
    scans = particle_scans(particles)
    scans = scans if weights == "equal" else unequal(scans)
    owner = None if shard is None else owns_tile(shard, 2)
    expected, got = TiledGrid(RES, tile_size=32), TiledGrid(RES, tile_size=32)
    fusion = MonteCarloFusion(expected, MODEL, *particles.single_geometry(), owner)
    for scan in scans:
        fusion.fuse(*scan)
    fused_in_parts(particles, scans, parts, got, owner)
    assert_same_map(got, expected)
    assert np.count_nonzero(expected.variance) > 1_000


def test_parts_are_bounded_by_the_samples_and_checked(particles):
    fusion = MonteCarloFusion(TiledGrid(RES), MODEL, *particles.single_geometry())
    ranges, samples, weights = particle_scans(particles)[0]
    ready = fusion.prepare((ranges, samples, weights))
    assert ready is not None
    assert [fusion.parts_for(ready, threads) for threads in (1, 2, 5, 6, 64)] == [1, 2, 5, 5, 5]  # 40 // 8
    one = fusion.prepare((ranges, samples[:1], np.ones(1)))
    assert one is not None and fusion.parts_for(one, 8) == 1  # one sample: the one-sample pass
    for part, parts in ((0, 6), (2, 2), (-1, 2), (0, 0)):
        with pytest.raises(ValueError, match="need 0 <= part < parts"):
            fusion.walk(ready, FusionScratch(), part, parts)


@pytest.mark.parametrize("threads", (2, 3, 4))
def test_a_lone_scan_on_threads_is_walked_in_parts_into_the_serial_map(particles, threads):
    scans = particle_scans(particles)
    expected, got = TiledGrid(RES), TiledGrid(RES)
    serial = MonteCarloFusion(expected, MODEL, *particles.single_geometry())
    pool = FusionThreads(threads)
    fusion = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=pool)
    for scan in scans:
        assert fusion.fuse_many([scan]) == [serial.fuse(*scan)]
    assert_same_map(got, expected)
    sizes = [scratch.size for scratch in pool._scratches]
    assert sizes[:threads] == [sizes[0]] * threads and sizes[0] > 0  # every thread walked a part
    assert sizes[threads] == 0  # the spare scratch of side-by-side scans: not used for parts


@pytest.mark.parametrize("failing", (0, 1))  # (part 0 is walked on the calling thread, part 1 on the pool)
def test_a_part_that_fails_raises_and_leaves_no_trace_in_the_next_scans(particles, monkeypatch, failing):
    """A part's walk that raises (a fault injected: walks do not fail on any input) is raised for its scan; the other
    part, walked and never added up, must not leak into the next scan: the map is that of the other scans alone."""
    scans = particle_scans(particles)
    expected, got = TiledGrid(RES), TiledGrid(RES)
    fusion = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=FusionThreads(2))
    walk = MonteCarloFusion.walk

    def walk_or_fail(self, ready, scratch, part=0, parts=1):
        if part == failing:
            raise RuntimeError(f"part {part} failed")
        return walk(self, ready, scratch, part, parts)

    monkeypatch.setattr(MonteCarloFusion, "walk", walk_or_fail)
    with pytest.raises(RuntimeError, match=f"part {failing} failed"):
        fusion.fuse_many([scans[0]])
    monkeypatch.undo()
    serial = MonteCarloFusion(expected, MODEL, *particles.single_geometry())
    for scan in scans[1:]:
        serial.fuse(*scan)
        fusion.fuse_many([scan])
    assert_same_map(got, expected)


def test_parts_whose_adding_up_fails_leave_no_trace_in_the_next_scans(particles, monkeypatch):
    """The parts walked, then their adding up fails (a fault injected into merge_scan, in every band): the error is
    raised for the scan, and the parts' marks, never added up nor applied, must not leak into the next scans. The
    failed scan's tiles were created (empty) before the bands; the expected grid gets them in the same slots."""
    scans = particle_scans(particles)
    expected, got = TiledGrid(RES), TiledGrid(RES)
    fusion = MonteCarloFusion(got, MODEL, *particles.single_geometry(), threads=FusionThreads(2))

    def fail(*args):
        raise RuntimeError("merge failed")

    monkeypatch.setattr(fusion_module, "merge_scan", fail)
    with pytest.raises(RuntimeError, match="merge failed"):
        fusion.fuse_many([scans[0]])
    monkeypatch.undo()
    for key in got.keys():  # noqa: SIM118 - a TiledGrid, not a dict
        expected.slot(key)
    serial = MonteCarloFusion(expected, MODEL, *particles.single_geometry())
    for scan in scans[1:]:
        serial.fuse(*scan)
        fusion.fuse_many([scan])
    assert_same_map(got, expected)


def test_a_live_shard_fusing_each_pair_as_it_comes_on_two_threads_makes_the_one_thread_map(particles):
    """Messages handed one at a time: each completed pair is fused alone, in parts on the shard's threads."""
    shards = []
    for threads in (1, 2):
        config = ShardConfig("m", 0, 1, MODEL, tile_size=64, threads=threads)
        shard = MapShard(config, RejectCounter(logging.getLogger("test-split-scan")))
        for key, payload in _messages(particles):
            shard.handle(key, payload)
        shards.append(shard)
    one, two = shards
    assert_same_map(two.grid, one.grid)
    assert two.fused == one.fused == {"r": 16} and two.cells_updated == one.cells_updated
    assert two._threads._scratches[1].size > 0  # the second thread walked parts


def test_moment_scale_is_the_finest_power_of_two_that_keeps_the_sums_in_range():
    # the default model: logit(0.7) - logit(0.4) = 1.2528; 2 * 1.2528**2 = 3.14 < 2**2: 2**(62 - 2), capped at 2**60
    default = math.log(0.7 / 0.3) - math.log(0.4 / 0.6)
    assert moment_scale(default) == 2.0**60
    assert moment_scale(0.0) == 2.0**MAX_FRACTION_BITS
    assert moment_scale(100.0) == 2.0 ** (62 - 15)  # 2 * 1e4 = 20000 < 2**15
    # the widest span a SensorModel allows: p_miss just above the smallest positive float, p_hit just below 1
    widest = math.log1p(-1e-16) - math.log(1e-16) - (math.log(1e-323) - math.log1p(-1e-323))
    assert moment_scale(widest) == 2.0**41
    for excess in (1e-3, default, 7.0, 100.0, widest):
        assert 2.0 * max(excess, excess**2) * moment_scale(excess) < 2.0**SUM_BITS
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="finite excess_max"):
            moment_scale(bad)


@settings(max_examples=60, deadline=None)
@given(
    visits=st.lists(
        st.tuples(st.integers(0, 5), st.floats(0.0, 1.25, allow_nan=False), st.integers(0, 2)), min_size=1, max_size=40
    ),
    weights=st.lists(st.floats(0.0, 1.0, allow_nan=False), min_size=6, max_size=6),
)
def test_a_cells_excess_moments_are_each_samples_largest_term_in_any_sample_order(visits, weights):
    """Visits (sample, excess d, cell) of three cells: a cell's moments are the sum over the samples that visited it
    of trunc(w_j s d_j) and trunc(w_j s d_j^2), d_j the sample's largest excess there (by hand, in Python integers),
    whatever order the samples come in (here: as given, and with the samples reversed)."""
    scale = moment_scale(1.25)
    for order in (visits, sorted(visits, key=lambda v: -v[0])):
        rec = np.zeros((3, 4))
        moments = rec.view(np.int64)
        stamp_of = {}  # a sample's stamp: its rank in this order (each sample's visits are consecutive)
        for sample, d, cell in _by_sample(order):
            stamp = stamp_of.setdefault(sample, float(len(stamp_of) + 1))
            add_sample_excess(rec, moments, np.uint64(cell), stamp, weights[sample] * scale, d)
        for cell in range(3):
            largest = {}
            for sample, d, at in visits:
                if at == cell:
                    largest[sample] = max(largest.get(sample, 0.0), d)
            ws = {sample: weights[sample] * scale for sample in largest}
            assert moments[cell, 2] == sum(int(ws[j] * largest[j]) for j in largest)
            assert moments[cell, 3] == sum(int(ws[j] * largest[j] * largest[j]) for j in largest)


def _by_sample(visits: list[tuple]) -> list[tuple]:
    """The visits with each sample's together (a sample walks all its beams before the next sample), samples in the
    order of their first visit, each sample's visits in their order."""
    first = {}
    for index, (sample, _, _) in enumerate(visits):
        first.setdefault(sample, index)
    return sorted(visits, key=lambda v: first[v[0]])
