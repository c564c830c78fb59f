"""Map scoring against hand-computed AUC, Brier and NLL values."""

import math

import numpy as np
import pytest

from mapping.errors import InputError
from mapping.evaluation import probability_on_raster, roc_auc, sample_map, score_map, score_probabilities


def test_auc_by_hand():
    # positives 0.9, 0.4; negatives 0.5, 0.1: pairs (0.9>0.5, 0.9>0.1, 0.4<0.5, 0.4>0.1) -> 3/4
    assert roc_auc(np.array([0.9, 0.4, 0.5, 0.1]), np.array([1, 1, 0, 0])) == pytest.approx(0.75)
    # a tie counts one half
    assert roc_auc(np.array([0.5, 0.5]), np.array([1, 0])) == pytest.approx(0.5)


def test_scores_a_rounding_apart_are_ties():
    # 0.3 and 0.1 + 0.2 (0.30000000000000004) are the same evidence: a tie, one half
    assert roc_auc(np.array([0.3, 0.1 + 0.2]), np.array([1, 0])) == 0.5
    assert roc_auc(np.array([0.3, 0.3 + 2e-9]), np.array([1, 0])) == 0.0  # (beyond the tie decimals: ranked)


def test_the_same_map_and_truth_moved_far_away_score_the_same():
    """A probe: the same map and truth moved by (4.5e5, 5.4e6) m (and a part of a cell) scored AUC 0.8081 against
    0.8021 at the origin, Brier within 1e-10: cells that held the same value at the origin came out of the area
    averaging a rounding apart, and ranked in the order rounding gave them."""
    rng = np.random.default_rng(3)
    probability = np.where(rng.random((60, 80)) < 0.7, 0.12, rng.random((60, 80))).astype(np.float32)  # clamped
    occupied = rng.random((29, 39)) < 0.2
    scores = []
    for shift in (np.zeros(2), np.array([4.5e5, 5.4e6]), np.array([-3e6, -2e6])):
        origin = shift + np.array([0.01234567, 0.03712345])
        truth = {"occupied": occupied, "visible": np.ones_like(occupied), "origin": origin + 0.0137, "resolution": 0.1}
        scores.append(score_map({"probability": probability, "origin": origin, "resolution": 0.05}, truth))
    for moved in scores[1:]:
        assert moved["auc"] == pytest.approx(scores[0]["auc"], abs=1e-9)
        assert moved["brier"] == pytest.approx(scores[0]["brier"], rel=1e-9)


def test_brier_and_nll_by_hand():
    scores = score_probabilities(np.array([0.8, 0.5]), np.array([True, False]))
    assert scores["brier"] == pytest.approx((0.2**2 + 0.5**2) / 2)
    assert scores["nll"] == pytest.approx(-(math.log(0.8) + math.log(0.5)) / 2)
    assert scores["n"] == 2


def test_a_truth_cell_takes_the_map_averaged_over_its_area():
    # truth 0.1 m cells from (0, 0); map 0.05 m cells from (-0.05, 0): truth cell (row 0, col 1) covers x 0.1 .. 0.2,
    # y 0 .. 0.1, that is map columns 3 and 4 of rows 0 and 1; truth cell (0, 0) covers map columns 1 and 2
    truth = {
        "occupied": np.array([[False, True]]),
        "visible": np.array([[True, True]]),
        "origin": np.zeros(2),
        "resolution": 0.1,
    }
    probability = np.full((4, 6), 0.5, np.float32)
    probability[0:2, 3:5] = [[0.9, 0.7], [0.8, 1.0]]  # mean 0.85
    probability[0:2, 1:3] = [[0.2, 0.1], [0.3, 0.2]]  # mean 0.2
    scores = score_map({"probability": probability, "origin": np.array([-0.05, 0.0]), "resolution": 0.05}, truth)
    assert scores["auc"] == 1.0
    assert scores["brier"] == pytest.approx((0.2**2 + 0.15**2) / 2, rel=1e-6)


def test_a_truth_grid_half_a_cell_off_the_map_takes_four_quarters():
    """The simulator's truth cells are centred on the map's grid lines: each one covers a quarter of four map
    cells, whichever way the map's origin rounds."""
    probability = np.array([[0.1, 0.3], [0.5, 0.9]], np.float32)
    truth_origin = np.array([0.025, 0.025])
    averaged = probability_on_raster(
        {"probability": probability, "origin": np.zeros(2), "resolution": 0.05}, truth_origin, 0.05, (2, 2)
    )
    # truth cell (0, 0) covers the four map cells a quarter each; the others reach beyond the map (0.5 there)
    assert averaged[0, 0] == pytest.approx((0.1 + 0.3 + 0.5 + 0.9) / 4)
    assert averaged[0, 1] == pytest.approx((0.3 + 0.9) / 4 + 0.5 / 2)
    assert averaged[1, 1] == pytest.approx(0.9 / 4 + 0.5 * 3 / 4)


@pytest.mark.parametrize("shift", [0.0, 1e-9, -1e-9, 3e-8])
def test_scores_do_not_move_with_a_map_origin_off_by_rounding(shift):
    """A map origin off by a nanometre, or stored as float32, scores as the exact one (AUC moved 0.841 -> 0.798
    when the map was sampled at truth cell centres lying on its cell borders)."""
    rng = np.random.default_rng(3)
    probability = rng.uniform(0, 1, (40, 50)).astype(np.float32)
    occupied = rng.uniform(0, 1, (39, 49)) < 0.3
    truth = {
        "occupied": occupied,
        "visible": np.ones_like(occupied),
        "origin": np.array([-1.025, 2.025]),
        "resolution": 0.05,
    }
    exact = score_map({"probability": probability, "origin": np.array([-1.05, 2.0]), "resolution": 0.05}, truth)
    for origin in (np.array([-1.05 + shift, 2.0 - shift]), np.array([-1.05, 2.0], np.float32)):
        moved = score_map({"probability": probability, "origin": origin, "resolution": 0.05}, truth)
        for key in ("auc", "brier", "nll"):
            assert moved[key] == pytest.approx(exact[key], abs=1e-6), key


def test_aligned_rasters_match_cell_for_cell():
    rng = np.random.default_rng(4)
    probability = rng.uniform(0, 1, (6, 7)).astype(np.float32)
    averaged = probability_on_raster(
        {"probability": probability, "origin": np.array([0.3, -0.2]), "resolution": 0.1},
        np.array([0.5, 0.0]),
        0.1,
        (3, 4),
    )
    np.testing.assert_array_equal(averaged, probability[2:5, 2:6].astype(np.float64))


def test_unobserved_map_cells_count_as_unknown():
    """A map file (from another tool) may say a cell is unobserved and still carry a probability: 0.5 counts."""
    truth = {
        "occupied": np.array([[True, False]]),
        "visible": np.array([[True, True]]),
        "origin": np.zeros(2),
        "resolution": 0.1,
    }
    probability = np.array([[0.9, 0.88]], np.float32)
    observed = np.array([[True, False]])
    scores = score_map(
        {"probability": probability, "observed": observed, "origin": np.zeros(2), "resolution": 0.1}, truth
    )
    assert scores["brier"] == pytest.approx((0.1**2 + 0.5**2) / 2, rel=1e-6) and scores["auc"] == 1.0


def test_informed_counts_the_truth_cells_observed_map_cells_cover_whatever_their_probability():
    """A probe's finding: a map that observed every truth cell at probability 0.5 (log-odds 0) scored "informed": 0
    and eval warned that it observed none of them (informed counted the cells whose probability is not 0.5). By hand:
    a 6 x 6 truth at 0.1 m; a map on the same grid, all observed at 0.5: 36. A map of 0.05 m cells over it, observed
    in its left 5 columns of 12 and in 2 x 2 blocks averaging 0.5: the truth's first 3 columns (the third half
    covered), 18 cells; and a map without an observed layer: every cell it covers, 36."""
    truth = {
        "occupied": np.eye(6, dtype=bool),
        "visible": np.ones((6, 6), bool),
        "origin": np.zeros(2),
        "resolution": 0.1,
    }
    flat = {"probability": np.full((6, 6), 0.5, np.float32), "observed": np.ones((6, 6), bool)}
    assert score_map({**flat, "origin": np.zeros(2), "resolution": 0.1}, truth)["informed"] == 36
    fine = np.tile(np.array([[0.3, 0.7], [0.7, 0.3]], np.float32), (6, 6))
    observed = np.zeros((12, 12), bool)
    observed[:, :5] = True
    half = {"probability": fine, "observed": observed, "origin": np.zeros(2), "resolution": 0.05}
    assert score_map(half, truth)["informed"] == 18
    assert score_map({"probability": fine, "origin": np.zeros(2), "resolution": 0.05}, truth)["informed"] == 36


def test_cells_outside_the_map_count_as_unknown():
    truth = {
        "occupied": np.array([[True]]),
        "visible": np.array([[True]]),
        "origin": np.array([10.0, 10.0]),
        "resolution": 0.1,
    }
    scores = score_map({"probability": np.ones((2, 2), np.float32), "origin": np.zeros(2), "resolution": 0.1}, truth)
    assert scores["brier"] == pytest.approx(0.25)


def test_a_confident_mistake_costs_a_finite_nll_of_minus_log_1e6():
    """p is clipped to [1e-6, 1 - 1e-6] for the NLL: p = 0 on an occupied cell and p = 1 on a free one each cost
    -ln(1e-6) = 13.8155... (kills: clip dropped -> inf; NLL_EPS changed -> another value)."""
    scores = score_probabilities(np.array([0.0, 1.0]), np.array([True, False]))
    assert scores["nll"] == pytest.approx(-math.log(1e-6), rel=1e-9)
    assert scores["brier"] == pytest.approx(1.0)


def test_visible_cells_away_from_the_raster_corner_score_their_own_map_cells():
    """The visible box starts at column 2, row 0 of the truth raster: its corner is origin + (2, 0) cells, not
    (0, 2) (kills: rows and columns swapped in the corner)."""
    visible = np.array([[False, False, True, True], [False, False, True, True]])
    occupied = np.array([[False, False, False, True], [False, False, False, True]])
    probability = np.array([[0.5, 0.5, 0.2, 0.9], [0.5, 0.5, 0.1, 0.8]], np.float32)  # same grid as the truth
    scores = score_map(
        {"probability": probability, "origin": np.zeros(2), "resolution": 0.1},
        {"occupied": occupied, "visible": visible, "origin": np.zeros(2), "resolution": 0.1},
    )
    assert scores["auc"] == 1.0
    assert scores["brier"] == pytest.approx((0.2**2 + 0.1**2 + 0.1**2 + 0.2**2) / 4, rel=1e-6)
    assert scores["n"] == 4


def test_a_truth_raster_a_fifth_of_a_cell_off_takes_area_weighted_fractions():
    """Truth cell k starts 0.2 map cells into map cell k: 0.8 of it lies there and 0.2 in cell k + 1 (kills: an
    edge snap that treats 0.2 cells as aligned)."""
    probability = np.array([[0.1, 0.6, 0.9]], np.float32)
    averaged = probability_on_raster(
        {"probability": probability, "origin": np.zeros(2), "resolution": 0.1}, np.array([0.02, 0.0]), 0.1, (1, 2)
    )
    np.testing.assert_allclose(averaged, [[0.8 * 0.1 + 0.2 * 0.6, 0.8 * 0.6 + 0.2 * 0.9]], atol=1e-6)


def test_a_raster_beside_the_map_on_one_axis_only_is_all_unknown():
    """The truth overlaps the map's x range but lies 5 m north of it: no overlap, 0.5 everywhere (kills: the
    no-overlap shortcut taken only when both axes miss, which then indexes an empty overlap)."""
    probability = np.full((2, 2), 0.9, np.float32)
    averaged = probability_on_raster(
        {"probability": probability, "origin": np.zeros(2), "resolution": 0.1}, np.array([0.0, 5.0]), 0.1, (2, 2)
    )
    np.testing.assert_array_equal(averaged, np.full((2, 2), 0.5))


def test_a_truth_with_no_visible_cell_is_refused():
    truth = {
        "occupied": np.zeros((2, 2), bool),
        "visible": np.zeros((2, 2), bool),
        "origin": np.zeros(2),
        "resolution": 0.1,
    }
    with pytest.raises(InputError, match="no visible cells"):
        score_map({"probability": np.full((2, 2), 0.5, np.float32), "origin": np.zeros(2), "resolution": 0.1}, truth)


def test_truth_cells_too_small_for_the_map_cells_are_refused():
    """1e-5 m truth cells against 0.1 m map cells: every edge snaps onto one map edge (zero length)."""
    with pytest.raises(InputError, match="too small to score"):
        probability_on_raster(
            {"probability": np.full((2, 2), 0.5, np.float32), "origin": np.zeros(2), "resolution": 0.1},
            np.zeros(2),
            1e-5,
            (3, 3),
        )


def test_sample_map_reads_the_last_column_of_a_wide_raster_and_half_outside():
    """sample_map (used by bench/adaptive.py) on a 1 x 3 raster: column 2 is inside, x = 0.35 is not."""
    probability = np.array([[0.1, 0.2, 0.3]])
    got = sample_map(
        probability, np.zeros(2), 0.1, np.array([0.05, 0.25, 0.35, 0.25]), np.array([0.05, 0.05, 0.05, -0.05])
    )
    np.testing.assert_array_equal(got, [0.1, 0.3, 0.5, 0.5])
