"""Equal weights counted, not summed (mapping.samples_pass, "Equal weights are counted"): the bit-sliced counters
against plain per-bit counts, the table of sums against Python's integers, and maps fused through the counters against
the same scans through the per-cell sums, bit for bit (the whole window and a shard, samples and Gaussian draws)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import mapping.fusion as fusion
from bench.scenarios import honest_posed_scans, office_run
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.samples_pass import APPLY_HELD, COUNT_LEVELS, _byte_count, _count_group, _count_of, _counts_in_bytes
from mapping.sensor_model import SensorModel
from services.fusion_runner import PoseSampling
from services.state.ownership import owns_tile

RES = 0.05
MODEL = SensorModel(resolution=RES)


ZERO = np.uint64(0)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.lists(st.integers(0, 2**64 - 1), min_size=3, max_size=3), min_size=0, max_size=300))
def test_the_bit_sliced_counts_are_the_number_of_times_each_bit_was_set(planes):
    """Words added one plane at a time (three words a plane), each as a last group of one sample is swept (the
    group's other words clear): every cell's count is the number of planes with its bit set, as a plain loop over the
    bits counts it."""
    counts = np.zeros((COUNT_LEVELS, 3), np.uint64)
    for plane in planes:
        for i, word in enumerate(plane):
            _count_group(counts, i, np.uint64(word), ZERO, ZERO, ZERO)
    expected = [[sum((plane[i] >> k) & 1 for plane in planes) for k in range(64)] for i in range(3)]
    levels = max(len(planes).bit_length(), 1)
    got = [[int(_count_of(counts[:, i], k, levels)) for k in range(64)] for i in range(3)]
    assert got == expected


words = st.integers(0, 2**64 - 1)
#: words of samples that mostly agree, as a real filter's do: each a common word with a few bits flipped
agreeing = st.tuples(words, st.lists(st.integers(0, 63), max_size=3)).map(
    lambda drawn: drawn[0] ^ sum(1 << bit for bit in set(drawn[1]))
)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(*(st.one_of(words, agreeing, st.just(0)),) * 4), min_size=0, max_size=300))
def test_a_group_of_four_words_adds_the_number_of_them_with_each_bit_set(groups):
    """Groups of four words added at once (a group's samples' planes swept together; words that agree, which leave
    the adders' low digits clear, and clear words, as past a last group's samples): every cell's count is the number
    of words of all the groups with its bit set, as a plain loop over the bits counts it (and as adding the words one
    by one does)."""
    counts = np.zeros((COUNT_LEVELS, 1), np.uint64)
    one_by_one = np.zeros((COUNT_LEVELS, 1), np.uint64)
    for group in groups:
        _count_group(counts, 0, *(np.uint64(word) for word in group))
        for word in group:
            _count_group(one_by_one, 0, np.uint64(word), ZERO, ZERO, ZERO)
    expected = [sum((word >> k) & 1 for group in groups for word in group) for k in range(64)]
    levels = max((4 * len(groups)).bit_length(), 1)
    assert [int(_count_of(counts[:, 0], k, levels)) for k in range(64)] == expected
    assert np.array_equal(counts, one_by_one)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 8),
    st.lists(st.integers(0, 2**64 - 1), min_size=COUNT_LEVELS, max_size=COUNT_LEVELS),
    st.integers(0, 2**64 - 1),
)
def test_the_counts_read_as_bytes_are_the_counts_read_a_cell_at_a_time(levels, words, bits):
    """The apply reads the counts of up to 8 levels eight cells at a time, as bytes: for every cell of ``bits``,
    the count a cell at a time gives, whatever the levels above ``levels`` hold."""
    held = np.zeros(APPLY_HELD, np.uint64)
    held[:COUNT_LEVELS] = words
    _counts_in_bytes(held, levels, np.uint64(bits))
    cells = [k for k in range(64) if (bits >> k) & 1]
    assert [int(_byte_count(held, k)) for k in cells] == [int(_count_of(held, k, levels)) for k in cells]
    assert [int(_count_of(held, k, levels)) for k in cells] == [
        sum(((words[level] >> k) & 1) << level for level in range(levels)) for k in cells
    ]


def test_the_sums_table_is_the_per_cell_sum_of_fixed_steps():
    """n weights of 1/37, each truncated to steps of 2**-60 and summed as integers (by hand, Python's integers),
    then rounded once to float64: what the per-cell sums of mapping.fixed_point give, in any order."""
    weights = np.full(37, 1.0 / 37)
    step = int(weights[0] * 2**60)  # (1/37 in steps of 2**-60, truncated)
    assert abs(step - 2**60 // 37) < 2**8  # (1/37 as a float64 is within 2**-53 of it, relative)
    expected = [float(n * step) / 2**60 for n in range(38)]
    table = fusion._equal_weight_sums(weights)
    assert table.tolist() == expected
    assert table[-1] == 1.0  # (37 float additions of 1/37 round below 1; the integer sum rounds to 1)
    assert fusion._equal_weight_sums(np.array([0.5, 0.25, 0.25])).size == 0
    assert fusion._equal_weight_sums(np.full(2**COUNT_LEVELS, 2.0**-COUNT_LEVELS)).size == 0


@pytest.fixture(scope="module")
def office():
    return office_run(steps=30)


def _scans(posed, kind):
    """(ranges, samples, weights) of every scan: the particles as they are, or Gaussian draws as `posegrid fuse`
    draws them."""
    if kind == "particles":
        samples, weights = posed.poses.weighted_samples()
        return [(posed.scan_ranges(t), samples[t], weights[t]) for t in range(len(posed.stamps))]
    sampling, poses = PoseSampling(accuracy=RES), posed.poses
    return [
        (posed.scan_ranges(t), *sampling.draw(t, float(posed.range_max[t]), mean=poses.mean[t], cov=poses.cov[t]))
        for t in range(len(posed.stamps))
    ]


def _fuse(posed, scans, owner):
    grid = TiledGrid(RES, 32)
    fuse = MonteCarloFusion(grid, MODEL, *posed.single_geometry(), owner)
    for scan in scans:
        fuse.fuse(*scan)
    return grid


@pytest.mark.parametrize("kind", ["particles", "gaussian"])
@pytest.mark.parametrize("shard", [None, 0])
def test_counted_weights_give_the_map_of_the_per_cell_sums_bit_for_bit(office, monkeypatch, kind, shard):
    posed = honest_posed_scans(office, particles=40) if kind == "particles" else honest_posed_scans(office)
    scans = _scans(posed, kind)
    assert all(len(w) > 1 and np.all(w == w[0]) for _, _, w in scans)  # every scan is counted
    owner = None if shard is None else owns_tile(shard, 2)
    counted = _fuse(posed, scans, owner)
    monkeypatch.setattr(fusion, "_equal_weight_sums", lambda weights: np.zeros(0))  # every cell's weights summed
    summed = _fuse(posed, scans, owner)
    assert counted.observed.any()
    for layer in ("logodds", "variance", "observed"):
        np.testing.assert_array_equal(getattr(counted, layer), getattr(summed, layer))


@pytest.mark.parametrize("particles", [255, 300])
def test_counts_of_more_than_eight_levels_and_of_exactly_eight_give_the_per_cell_sums_map(monkeypatch, particles):
    """255 particles: counts up to 255, the most the apply reads as bytes; 300: nine levels, read a cell at a time."""
    posed = honest_posed_scans(office_run(steps=4), particles=particles)
    scans = _scans(posed, "particles")
    counted = _fuse(posed, scans, None)
    monkeypatch.setattr(fusion, "_equal_weight_sums", lambda weights: np.zeros(0))
    summed = _fuse(posed, scans, None)
    assert counted.observed.any()
    for layer in ("logodds", "variance", "observed"):
        np.testing.assert_array_equal(getattr(counted, layer), getattr(summed, layer))
