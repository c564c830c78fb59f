"""Free-space runs (mapping.free_runs) mark exactly the cells the exact traversal visits before a range."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mapping.free_runs import fold_columns, mark_free_runs, set_run, set_short_run, transpose64
from mapping.raytrace import corner_tol, traverse
from mapping.window_walk import JUMP_MARGIN, Window

RES = 0.05
# a window that is neither square nor centred, and holds every ray below (origins within 2 m of (0, 0), 1.8 m
# long at most: x and y within 3.8 m); the kernels rely on the caller for that
WIN_IX0, WIN_IY0, WIN_W, WIN_H = -104, -88, 192, 170  # (the width a multiple of 64, as fold_columns needs)
COL_STRIDE = 192  # the column-major plane's column length: WIN_H rounded up to a multiple of 64


def runs_cells(x0, y0, angle, r_end, stop):
    """The cells mark_free_runs marks for the ray (both planes folded), and the last cell it returns."""
    ix, iy, _r_in, _r_out = traverse(x0, y0, angle, stop, RES)
    assert ix.min() > WIN_IX0 and ix.max() < WIN_IX0 + WIN_W - 1
    assert iy.min() > WIN_IY0 and iy.max() < WIN_IY0 + WIN_H - 1
    rows = np.zeros(WIN_W * WIN_H // 64 + 1, np.uint64)
    columns = np.zeros(WIN_W * COL_STRIDE // 64, np.uint64)
    last = mark_free_runs(
        rows,
        columns,
        COL_STRIDE,
        Window(WIN_IX0, WIN_IY0, WIN_W, WIN_H),
        (x0, y0, math.cos(angle), math.sin(angle)),
        (int(ix[0]), int(iy[0])),
        r_end,
        RES,
        corner_tol(stop),
        np.empty((2, WIN_W), np.int64),
    )
    fold_columns(columns, COL_STRIDE, rows, WIN_W, WIN_H, np.empty(64, np.uint64))
    assert not columns.any(), "the fold clears the column-major plane"
    bits = np.unpackbits(rows.view(np.uint8), bitorder="little")[: WIN_W * WIN_H]
    marked = {(int(c % WIN_W) + WIN_IX0, int(c // WIN_W) + WIN_IY0) for c in np.flatnonzero(bits)}
    return marked, last


def traversal(x0, y0, angle, r_end, stop):
    """The traversal's cells in order, and the index of the one holding r_end (entered before it)."""
    ix, iy, r_in, _r_out = traverse(x0, y0, angle, stop, RES)
    cells = list(zip(ix.tolist(), iy.tolist()))
    return cells, int(np.count_nonzero(r_in < r_end)) - 1


def check_prefix(x0, y0, angle, stop, end_fraction):
    """The runs mark a prefix of the traversal's cells that ends at the cell holding r_end, give or take one cell
    where r_end meets a grid line within rounding, and return that prefix's last cell (the walk goes on from
    it). As in the kernel, r_end stops short of the ray's end by JUMP_MARGIN."""
    r_end = min(stop * end_fraction, stop - JUMP_MARGIN * (1.0 + stop))
    marked, last = runs_cells(x0, y0, angle, r_end, stop)
    cells, holding = traversal(x0, y0, angle, r_end, stop)
    end = cells.index(last)
    assert abs(end - holding) <= 1, (x0, y0, angle, stop, r_end)
    assert marked == set(cells[: end + 1]), (x0, y0, angle, stop, r_end)


# origins on cell corners, edges and centres, and anywhere; angles along the axes, the diagonals and anywhere
nice_coordinate = st.integers(-40, 40).map(lambda k: k * RES / 2)
coordinate = st.one_of(nice_coordinate, st.floats(-2.0, 2.0))
angle = st.one_of(
    st.integers(-8, 8).map(lambda k: k * math.pi / 4),
    st.integers(-16, 16).map(lambda k: k * math.pi / 8),
    st.floats(-math.pi, math.pi),
)


@settings(max_examples=300, deadline=None)
@given(x0=coordinate, y0=coordinate, angle=angle, stop=st.floats(0.01, 1.8), end_fraction=st.floats(0.02, 1.0))
# along a grid line within rounding: sin(pi) = 1.2e-16 takes the ray from y = 0.15 (just below the line 3 * 0.05)
# across it only 0.23 m on, and the runs must cross where the traversal does (found by hypothesis, 2026-11-27)
@example(x0=0.0, y0=0.15, angle=math.pi, stop=0.5, end_fraction=0.25)
@example(x0=0.0, y0=0.15, angle=math.pi, stop=1.0, end_fraction=1.0)
@example(x0=0.15, y0=0.1, angle=-math.pi / 2, stop=1.3, end_fraction=0.6)  # the same, steep
def test_runs_mark_the_traversal_cells_before_the_end(x0, y0, angle, stop, end_fraction):
    check_prefix(x0, y0, angle, stop, end_fraction)


def test_runs_on_many_random_rays():
    """A seeded sweep of 4 000 rays: half from grid points at multiples of pi/8 and pi/6, with lengths and ends
    on multiples of the cell size (where ends meet grid lines), half anywhere."""
    rng = np.random.default_rng(0)
    nice_angles = np.concatenate([np.arange(-16, 17) * math.pi / 8, np.arange(-12, 13) * math.pi / 6])
    for trial in range(4000):
        if trial % 2 == 0:
            x0, y0 = rng.integers(-80, 80, 2) * RES / 4
            theta = float(rng.choice(nice_angles))
            stop = rng.integers(1, 72) * RES / 2
            end_fraction = rng.integers(1, 11) / 10
        else:
            x0, y0 = rng.uniform(-2.0, 2.0, 2)
            theta = rng.uniform(-math.pi, math.pi)
            stop = rng.uniform(0.01, 1.8)
            end_fraction = rng.uniform(0.02, 1.0)
        check_prefix(x0, y0, theta, stop, end_fraction)


def test_a_ray_through_cell_corners_marks_no_cell_beside_them():
    """Along the diagonal from a cell corner the ray passes through every corner: only the diagonal cells."""
    marked, last = runs_cells(0.0, 0.0, math.pi / 4, 0.3, 0.4)  # 0.3 m reach 0.212 m in x and y: cells 0..4
    assert marked == {(k, k) for k in range(5)} and last == (4, 4)


@pytest.mark.parametrize("mark", [set_run, set_short_run])
@pytest.mark.parametrize(
    ("c_lo", "c_hi"), [(0, 0), (3, 60), (0, 63), (63, 64), (5, 200), (64, 127), (130, 130), (128, 191)]
)
def test_set_run_sets_exactly_the_bits_of_the_run(mark, c_lo, c_hi):
    """Within a word, across one word's end, over whole words; both ways of marking a run."""
    plane = np.zeros(5, np.uint64)
    mark(plane, c_lo, c_hi)
    bits = np.unpackbits(plane.view(np.uint8), bitorder="little")
    assert np.flatnonzero(bits).tolist() == list(range(c_lo, c_hi + 1))


def test_transpose64_against_numpy():
    rng = np.random.default_rng(3)
    for density in (0.01, 0.5, 1.0):
        bits = rng.random((64, 64)) < density  # bits[i, b]: bit b of word i
        block = np.packbits(bits, axis=1, bitorder="little").view(np.uint64).ravel().copy()
        transpose64(block)
        got = np.unpackbits(block.view(np.uint8), bitorder="little").reshape(64, 64).astype(bool)
        np.testing.assert_array_equal(got, bits.T)


def test_fold_moves_every_column_bit_to_its_row():
    """Bits set cell by cell in the column-major plane reach the row-major plane at the same cells, in every
    64 x 64 block, the partial last row block included; the column plane is left clear."""
    rng = np.random.default_rng(4)
    cells = {(int(gx), int(gy)) for gx, gy in zip(rng.integers(0, WIN_W, 3000), rng.integers(0, WIN_H, 3000))}
    columns = np.zeros(WIN_W * COL_STRIDE // 64, np.uint64)
    for gx, gy in cells:
        c = gx * COL_STRIDE + gy
        columns[c >> 6] |= np.uint64(1) << np.uint64(c & 63)
    rows = np.zeros(WIN_W * WIN_H // 64, np.uint64)
    fold_columns(columns, COL_STRIDE, rows, WIN_W, WIN_H, np.empty(64, np.uint64))
    bits = np.unpackbits(rows.view(np.uint8), bitorder="little")
    assert {(int(c % WIN_W), int(c // WIN_W)) for c in np.flatnonzero(bits)} == cells
    assert not columns.any()
