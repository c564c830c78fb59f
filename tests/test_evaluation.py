"""Map scoring against hand-computed AUC, Brier and NLL values."""
import math

import numpy as np
import pytest

from mapping.evaluation import roc_auc, score_map, score_probabilities


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


def test_score_map_samples_the_map_at_truth_cell_centres():
    # truth 0.1 m cells from (0, 0); map 0.05 m cells from (-0.05, 0): truth cell (row 0, col 1) has its
    # centre at x = 0.15, y = 0.05, which is map cell row 1, col 4
    truth = {"occupied": np.array([[False, True]]), "visible": np.array([[True, True]]),
             "origin": np.zeros(2), "resolution": 0.1}
    probability = np.full((4, 6), 0.5, np.float32)
    probability[1, 4] = 0.9
    probability[1, 2] = 0.2  # truth cell (0, 0): centre x = 0.05 -> map col 2
    scores = score_map({"probability": probability, "origin": np.array([-0.05, 0.0]), "resolution": 0.05}, truth)
    assert scores["auc"] == 1.0
    assert scores["brier"] == pytest.approx((0.2 ** 2 + 0.1 ** 2) / 2, rel=1e-6)


def test_cells_outside_the_map_count_as_unknown():
    truth = {"occupied": np.array([[True]]), "visible": np.array([[True]]), "origin": np.array([10.0, 10.0]),
             "resolution": 0.1}
    scores = score_map({"probability": np.ones((2, 2), np.float32), "origin": np.zeros(2), "resolution": 0.1}, truth)
    assert scores["brier"] == pytest.approx(0.25)
