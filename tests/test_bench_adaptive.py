"""The adaptive benchmark's tree oracle (bench/adaptive.py): hand-computed cell means on a tiny raster."""
from __future__ import annotations

import numpy as np

from bench.adaptive import tree_oracle_logodds


def test_tree_oracle_gives_each_active_cell_the_mean_of_the_observed_fine_cells_under_it():
    # regular raster: 4 x 4 cells of 1 m from (2, 2) m, log-odds 0..15 row by row; cell (row 1, col 0) unobserved
    regular = {"logodds": np.arange(16.0).reshape(4, 4), "observed": np.ones((4, 4), bool),
               "origin": np.array([2.0, 2.0]), "resolution": 1.0}
    regular["observed"][1, 0] = False
    # tree raster from (2, 2) m, one column wider than the regular raster: rows 0-1 x cols 0-1 is one level-1
    # cell (world cells 2-3, aligned), rows 2-3 x cols 2-3 another; the rest level 0; the extra column lies off
    # the regular raster and has nothing to average
    level = np.zeros((4, 5), np.int8)
    level[0:2, 0:2] = 1
    level[2:4, 2:4] = 1
    tree = {"level": level, "origin": np.array([2.0, 2.0]), "resolution": 1.0}
    got = tree_oracle_logodds(tree, regular)
    expected = np.zeros((4, 5))
    expected[:, :4] = regular["logodds"]
    expected[0:2, 0:2] = (0 + 1 + 5) / 3  # the unobserved cell (value 4) left out
    expected[2:4, 2:4] = (10 + 11 + 14 + 15) / 4
    expected[1, 0] = expected[0, 0]
    expected[:, 4] = 0.0
    np.testing.assert_allclose(got, expected)


def test_tree_oracle_keeps_cells_of_the_same_size_apart_across_a_level_boundary():
    # two level-1 cells side by side in a 2 x 4 raster: their means must not mix
    regular = {"logodds": np.array([[1.0, 1.0, 5.0, 5.0], [1.0, 1.0, 5.0, 5.0]]), "observed": np.ones((2, 4), bool),
               "origin": np.array([0.0, 0.0]), "resolution": 0.5}
    tree = {"level": np.ones((2, 4), np.int8), "origin": np.array([0.0, 0.0]), "resolution": 0.5}
    np.testing.assert_allclose(tree_oracle_logodds(tree, regular), regular["logodds"])
