"""The zoom-level combination rule (mapping/pyramid.py) against hand-computed values."""

import numpy as np
import pytest

from mapping.errors import InputError
from mapping.pyramid import children_of, combine_children, downsample, tile_range, top_level


def test_downsample_hand_computed_block():
    # rows are y; the 2 x 2 blocks are [rows 0-1, cols 0-1], [rows 0-1, cols 2-3], [rows 2-3, ...]
    logodds = np.array(
        [[1.0, 3.0, 9.0, -2.0], [-1.0, 5.0, 4.0, 0.0], [2.0, 2.0, 7.0, 7.0], [2.0, 2.0, 7.0, 7.0]], np.float32
    )
    variance = np.array(
        [[0.5, 0.1, 8.0, 1.0], [0.2, 0.3, 2.0, 3.0], [1.0, 1.0, 9.0, 9.0], [1.0, 1.0, 9.0, 9.0]], np.float32
    )
    observed = np.array(
        [
            [True, True, False, True],
            [False, True, False, True],
            [False, False, False, False],
            [False, False, False, True],
        ]
    )
    lo, var, obs = downsample(logodds, variance, observed)
    # block (0, 0): observed 1, 3, 5 -> mean 3; variances 0.5, 0.1, 0.3 -> 0.3
    # block (0, 1): observed -2, 0 -> -1; variances 1, 3 -> 2 (the unobserved 9 and 4 do not count)
    # block (1, 0): nothing observed -> 0, 0, False; block (1, 1): one observed 7 -> 7, variance 9
    np.testing.assert_allclose(lo, [[3.0, -1.0], [0.0, 7.0]], rtol=1e-6)
    np.testing.assert_allclose(var, [[0.3, 2.0], [0.0, 9.0]], rtol=1e-6)
    assert obs.tolist() == [[True, True], [False, True]]
    assert lo.dtype == np.float32 and var.dtype == np.float32 and obs.dtype == bool


def test_combine_children_places_each_child_in_its_quarter():
    size = 2
    ones = np.ones((size, size), np.float32)
    seen = np.ones((size, size), bool)
    # child order (dx, dy): (0,0) lower-left, (1,0) lower-right, (0,1) upper-left, (1,1) upper-right
    children = [(1 * ones, 0.1 * ones, seen), (2 * ones, 0.2 * ones, seen), None, (4 * ones, 0.4 * ones, seen)]
    lo, var, obs = combine_children(children, size)
    assert lo.tolist() == [[1.0, 2.0], [0.0, 4.0]]  # row 0 (south) = children dy = 0
    np.testing.assert_allclose(var, [[0.1, 0.2], [0.0, 0.4]], rtol=1e-6)
    assert obs.tolist() == [[True, True], [False, True]]


def test_tile_addressing_below_zero():
    assert children_of(-1, 0) == [(-2, 0), (-1, 0), (-2, 1), (-1, 1)]
    assert tile_range(-3, 2, 1) == (-2, 1)
    assert top_level((-1, 0), (-1, 0)) == 0  # 2 x 2 tiles around the origin: already the top
    assert top_level((-3, 0), (0, 0)) == 2  # -3..0 -> -2..0 at z = 1 (3 tiles) -> -1..0 at z = 2
    assert top_level((5, 7), (0, 0)) == 1  # 5..7 -> 2..3


def test_bad_shapes_are_input_errors():
    with pytest.raises(InputError):
        downsample(np.zeros((3, 4)), np.zeros((3, 4)), np.zeros((3, 4), bool))
    with pytest.raises(InputError):
        combine_children([None] * 3, 2)


def test_odd_column_count_is_an_input_error():
    with pytest.raises(InputError):
        downsample(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros((4, 3), bool))


def test_observed_of_another_shape_is_an_input_error():
    with pytest.raises(InputError):
        downsample(np.zeros((4, 4)), np.zeros((4, 4)), np.zeros((2, 8), bool))


def test_child_of_the_wrong_shape_is_an_input_error():
    # a (1, 2) row would broadcast silently into the (2, 2) quarter
    good = (np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), np.ones((2, 2), bool))
    bad = (np.ones((1, 2), np.float32), np.ones((1, 2), np.float32), np.ones((1, 2), bool))
    with pytest.raises(InputError):
        combine_children([good, bad, None, None], 2)
