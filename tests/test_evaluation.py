"""Map scoring against hand-computed AUC, Brier and NLL values."""
import math

import numpy as np
import pytest

from mapping.evaluation import probability_on_raster, roc_auc, score_map, score_probabilities


def test_auc_by_hand():
    # positives 0.9, 0.4; negatives 0.5, 0.1: pairs (0.9>0.5, 0.9>0.1, 0.4<0.5, 0.4>0.1) -> 3/4
    assert roc_auc(np.array([0.9, 0.4, 0.5, 0.1]), np.array([1, 1, 0, 0])) == pytest.approx(0.75)
    # a tie counts one half
    assert roc_auc(np.array([0.5, 0.5]), np.array([1, 0])) == pytest.approx(0.5)


def test_brier_and_nll_by_hand():
    scores = score_probabilities(np.array([0.8, 0.5]), np.array([True, False]))
    assert scores["brier"] == pytest.approx((0.2 ** 2 + 0.5 ** 2) / 2)
    assert scores["nll"] == pytest.approx(-(math.log(0.8) + math.log(0.5)) / 2)
    assert scores["n"] == 2


def test_a_truth_cell_takes_the_map_averaged_over_its_area():
    # truth 0.1 m cells from (0, 0); map 0.05 m cells from (-0.05, 0): truth cell (row 0, col 1) covers x 0.1 .. 0.2,
    # y 0 .. 0.1, that is map columns 3 and 4 of rows 0 and 1; truth cell (0, 0) covers map columns 1 and 2
    truth = {"occupied": np.array([[False, True]]), "visible": np.array([[True, True]]),
             "origin": np.zeros(2), "resolution": 0.1}
    probability = np.full((4, 6), 0.5, np.float32)
    probability[0:2, 3:5] = [[0.9, 0.7], [0.8, 1.0]]  # mean 0.85
    probability[0:2, 1:3] = [[0.2, 0.1], [0.3, 0.2]]  # mean 0.2
    scores = score_map({"probability": probability, "origin": np.array([-0.05, 0.0]), "resolution": 0.05}, truth)
    assert scores["auc"] == 1.0
    assert scores["brier"] == pytest.approx((0.2 ** 2 + 0.15 ** 2) / 2, rel=1e-6)


def test_a_truth_grid_half_a_cell_off_the_map_takes_four_quarters():
    """The simulator's truth cells are centred on the map's grid lines: each one covers a quarter of four map
    cells, whichever way the map's origin rounds."""
    probability = np.array([[0.1, 0.3], [0.5, 0.9]], np.float32)
    truth_origin = np.array([0.025, 0.025])
    averaged = probability_on_raster({"probability": probability, "origin": np.zeros(2), "resolution": 0.05},
                                     truth_origin, 0.05, (2, 2))
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
    truth = {"occupied": occupied, "visible": np.ones_like(occupied), "origin": np.array([-1.025, 2.025]),
             "resolution": 0.05}
    exact = score_map({"probability": probability, "origin": np.array([-1.05, 2.0]), "resolution": 0.05}, truth)
    for origin in (np.array([-1.05 + shift, 2.0 - shift]), np.array([-1.05, 2.0], np.float32)):
        moved = score_map({"probability": probability, "origin": origin, "resolution": 0.05}, truth)
        for key in ("auc", "brier", "nll"):
            assert moved[key] == pytest.approx(exact[key], abs=1e-6), key


def test_aligned_rasters_match_cell_for_cell():
    rng = np.random.default_rng(4)
    probability = rng.uniform(0, 1, (6, 7)).astype(np.float32)
    averaged = probability_on_raster({"probability": probability, "origin": np.array([0.3, -0.2]),
                                      "resolution": 0.1}, np.array([0.5, 0.0]), 0.1, (3, 4))
    np.testing.assert_array_equal(averaged, probability[2:5, 2:6].astype(np.float64))


def test_unobserved_map_cells_count_as_unknown():
    """A map file (from another tool) may say a cell is unobserved and still carry a probability: 0.5 counts."""
    truth = {"occupied": np.array([[True, False]]), "visible": np.array([[True, True]]), "origin": np.zeros(2),
             "resolution": 0.1}
    probability = np.array([[0.9, 0.88]], np.float32)
    observed = np.array([[True, False]])
    scores = score_map({"probability": probability, "observed": observed, "origin": np.zeros(2),
                        "resolution": 0.1}, truth)
    assert scores["brier"] == pytest.approx((0.1 ** 2 + 0.5 ** 2) / 2, rel=1e-6) and scores["auc"] == 1.0


def test_cells_outside_the_map_count_as_unknown():
    truth = {"occupied": np.array([[True]]), "visible": np.array([[True]]), "origin": np.array([10.0, 10.0]),
             "resolution": 0.1}
    scores = score_map({"probability": np.ones((2, 2), np.float32), "origin": np.zeros(2), "resolution": 0.1}, truth)
    assert scores["brier"] == pytest.approx(0.25)
