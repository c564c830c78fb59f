"""Rendezvous ownership: one owner per tile, a stable function across processes, minimal movement."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.state.ownership import owns_tile, tile_owner, tile_score

TILES = [(tx, ty) for tx in range(-30, 30) for ty in range(-30, 30)]  # 3600 tiles


@settings(max_examples=30, deadline=None)
@given(
    st.integers(1, 12),
    st.lists(st.tuples(st.integers(-(10**6), 10**6), st.integers(-(10**6), 10**6)), min_size=1, max_size=50),
)
def test_every_tile_has_exactly_one_owner(shards, tiles):
    predicates = [owns_tile(i, shards) for i in range(shards)]
    for tile in tiles:
        owners = [i for i, owns in enumerate(predicates) if owns(*tile)]
        assert owners == [tile_owner(tile, range(shards))]


@pytest.mark.parametrize("shards", [1, 2, 3, 5, 8])
def test_adding_a_shard_moves_about_one_in_n_plus_one_tiles_all_to_the_new_shard(shards):
    before = {tile: tile_owner(tile, range(shards)) for tile in TILES}
    after = {tile: tile_owner(tile, range(shards + 1)) for tile in TILES}
    moved = [tile for tile in TILES if before[tile] != after[tile]]
    assert all(after[tile] == shards for tile in moved)
    expected = len(TILES) / (shards + 1)
    # binomial(3600, 1/(N+1)): 5 standard deviations
    sd = np.sqrt(len(TILES) * (1 / (shards + 1)) * (1 - 1 / (shards + 1)))
    assert abs(len(moved) - expected) < 5 * sd


@pytest.mark.parametrize("shards", [2, 3, 4])
def test_load_is_balanced(shards):
    counts = np.bincount([tile_owner(tile, range(shards)) for tile in TILES], minlength=shards)
    expected = len(TILES) / shards
    assert (np.abs(counts - expected) < 5 * np.sqrt(expected)).all(), counts


def test_removing_a_shard_moves_only_its_tiles():
    before = {tile: tile_owner(tile, [0, 1, 2, 3]) for tile in TILES}
    after = {tile: tile_owner(tile, [0, 1, 3]) for tile in TILES}
    for tile in TILES:
        if before[tile] != 2:
            assert after[tile] == before[tile]


def test_scores_are_the_same_in_another_process():
    """Python's hash() is salted per process; the score must not be."""
    code = (
        "from services.state.ownership import tile_score; "
        "print([tile_score((tx, -tx), s) for tx in range(5) for s in range(3)])"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        env={"PYTHONHASHSEED": "12345", "PATH": ""},
        cwd=str(__import__("conftest").ROOT),
    )
    assert out.stdout.strip() == str([tile_score((tx, -tx), s) for tx in range(5) for s in range(3)])


def test_bad_shard_index_is_refused():
    with pytest.raises(ValueError):
        owns_tile(2, 2)
    with pytest.raises(ValueError):
        tile_owner((0, 0), [])
