"""Exact traversal against an independent grid-line-crossing reference."""

import math

from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from mapping.raytrace import traverse
from reference import cells_on_ray


def test_hand_computed_ray():
    # from the centre of cell (0, 0) along +x for 0.2 m with 0.1 m cells: cells 0, 1 and 2 (half of it)
    ix, iy, r_in, r_out = traverse(0.05, 0.05, 0.0, 0.2, 0.1)
    assert list(ix) == [0, 1, 2] and list(iy) == [0, 0, 0]
    assert [round(v, 12) for v in r_in] == [0.0, 0.05, 0.15]
    assert [round(v, 12) for v in r_out] == [0.05, 0.15, 0.2]


def test_diagonal_through_corners_visits_no_point_contact_cells():
    # exactly through cell corners: only the diagonal cells have positive length
    ix, iy, _, _ = traverse(0.05, 0.05, math.pi / 4, 0.05 * math.sqrt(2) * 5, 0.1)
    assert list(zip(ix, iy)) == [(k, k) for k in range(len(ix))]


@settings(max_examples=300, deadline=None)
@given(
    x0=st.floats(-5, 5),
    y0=st.floats(-5, 5),
    angle=st.floats(-math.pi, math.pi),
    length=st.floats(0.01, 6),
    res=st.sampled_from([0.05, 0.1, 0.25]),
)
@example(x0=1e-09, y0=0.0, angle=0.0, length=1.0, res=0.1)
def test_traversal_matches_reference(x0, y0, angle, length, res):
    # a ray within 1e-9 rad of a grid line's direction but not on it is numerically ambiguous: skip those
    for component in (math.cos(angle), math.sin(angle)):
        assume(component == 0.0 or abs(component) > 1e-9)
    ix, iy, r_in, r_out = traverse(x0, y0, angle, length, res)
    got = list(zip(ix.tolist(), iy.tolist()))
    assert len(got) == len(set(got)), "a cell was visited twice"
    # consecutive, covering [0, length] without gaps
    assert r_in[0] == 0.0 and abs(r_out[-1] - length) < 1e-9
    assert all(abs(a - b) < 1e-9 for a, b in zip(r_out[:-1], r_in[1:]))
    # a cell crossed for less than 1e-8 m (in either walk) is a rounding of its edge: left out of both; a cutoff
    # applied to each alone fell between 1.0000001e-9 and 0.9999999e-9 m for the ray's last cell (the example)
    ref = [((c[0], c[1]), c[3] - c[2]) for c in cells_on_ray(x0, y0, angle, length, res)]
    mine = [(cell, b - a) for cell, a, b in zip(got, r_in, r_out)]
    short = {cell for cell, crossed in ref + mine if crossed < 1e-8}
    assert [cell for cell, _ in mine if cell not in short] == [cell for cell, _ in ref if cell not in short]


def test_an_origin_within_rounding_of_a_grid_line_starts_at_r_0():
    # 0.85 / 0.05 rounds below 17: the first crossing lies 2.7e-16 m behind the origin, and must not become r_in
    _, _, r_in, r_out = traverse(0.85, 0.0, 2.0, 1.0, 0.05)
    assert r_in[0] == 0.0 and all(a == b for a, b in zip(r_out[:-1], r_in[1:]))


def test_origin_on_a_grid_line_going_back_skips_the_point_contact_cell():
    # the origin lies on x = 0.1 and the ray goes along -x: cell 1 is touched only at r = 0 and is not visited
    ix, iy, r_in, r_out = traverse(0.1, 0.05, math.pi, 0.25, 0.1)
    assert list(zip(ix, iy)) == [(0, 0), (-1, 0), (-2, 0)]
    assert [round(v, 12) for v in r_in] == [0.0, 0.1, 0.2]
    assert [round(v, 12) for v in r_out] == [0.1, 0.2, 0.25]


def test_a_near_corner_miss_still_visits_the_cell_it_clips():
    # 1e-8 m above the corner (0.1, 0.1): the ray crosses y = 0.1 about 1e-8 m before x = 0.1, so it clips
    # cell (0, 1) over ~1.4e-8 m; that is far above the corner tolerance of 1e-12 (1 + r)
    ix, iy, r_in, r_out = traverse(0.05, 0.05 + 1e-8, math.pi / 4, 0.1, 0.1)
    assert list(zip(ix, iy)) == [(0, 0), (0, 1), (1, 1)]
    assert 0 < r_out[1] - r_in[1] < 2e-8


def test_a_long_ray_through_corners_keeps_the_corner_tolerance_relative():
    # y = 2 (x - 0.05) from (0.05, 0) with 0.1 m cells: every vertical grid line is crossed at a corner, so the
    # ray visits 1 + (horizontal lines crossed) cells: y ends at 300 * 2/sqrt(5) = 268.33 m -> 2683 lines.
    # Over 300 m the two crossing families drift apart by more than 1e-12 m absolute, so a fixed tolerance
    # would add point-contact cells (~1e-12 m long).
    ix, _iy, r_in, r_out = traverse(0.05, 0.0, math.atan2(2.0, 1.0), 300.0, 0.1)
    assert len(ix) == 2684
    assert (r_out - r_in).min() > 1e-6
