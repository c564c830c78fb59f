"""Benchmark helpers the figures rest on: the adaptive benchmark's tree oracle (hand-computed cell means on a tiny
raster), its label-pure quadtree (cells counted by hand), the scan selection every suite cuts its inputs with, the
landmark benchmark's figures pooled over robots, and the record `make bench` writes of each suite."""

from __future__ import annotations

import json
import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import bench.run
from bench.adaptive import label_pure_cells, tree_oracle_logodds
from bench.scenarios import select_scans
from bench.slam import pooled
from schemas.files import PosedScans, PoseSet


def test_tree_oracle_gives_each_active_cell_the_mean_of_the_observed_fine_cells_under_it():
    # regular raster: 4 x 4 cells of 1 m from (2, 2) m, log-odds 0..15 row by row; cell (row 1, col 0) unobserved
    regular = {
        "logodds": np.arange(16.0).reshape(4, 4),
        "observed": np.ones((4, 4), bool),
        "origin": np.array([2.0, 2.0]),
        "resolution": 1.0,
    }
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
    regular = {
        "logodds": np.array([[1.0, 1.0, 5.0, 5.0], [1.0, 1.0, 5.0, 5.0]]),
        "observed": np.ones((2, 4), bool),
        "origin": np.array([0.0, 0.0]),
        "resolution": 0.5,
    }
    tree = {"level": np.ones((2, 4), np.int8), "origin": np.array([0.0, 0.0]), "resolution": 0.5}
    np.testing.assert_allclose(tree_oracle_logodds(tree, regular), regular["logodds"])


def _labels(occupied: np.ndarray, observed: np.ndarray, origin: tuple[float, float]) -> dict:
    return {
        "probability": np.where(occupied, 0.9, 0.1),
        "observed": observed,
        "origin": np.array(origin),
        "resolution": 1.0,
    }


def test_label_pure_quadtree_keeps_fine_cells_only_where_the_labels_mix():
    occupied = np.zeros((4, 4), bool)
    occupied[0, 0] = True
    observed = np.ones((4, 4), bool)
    # start cells of 4 x 4: the 2 x 2 block holding the occupied cell mixes labels and stays 4 fine cells, its
    # three siblings are pure (one cell each), and the start cell cannot merge: 4 + 3
    assert label_pure_cells(_labels(occupied, observed, (0.0, 0.0)), 2) == 7
    # the same cell unobserved instead: every observed cell is free, so the start cell is one cell
    observed[0, 0] = False
    assert label_pure_cells(_labels(np.zeros((4, 4), bool), observed, (0.0, 0.0)), 2) == 1
    # nothing observed under a block: it is not counted
    assert label_pure_cells(_labels(np.zeros((4, 4), bool), np.zeros((4, 4), bool), (0.0, 0.0)), 2) == 0


def test_label_pure_quadtree_blocks_follow_the_world_frame_not_the_raster():
    # 2 rows x 4 columns, column 0 occupied, the rest free; start cells 2 fine cells wide
    occupied = np.zeros((2, 4), bool)
    occupied[:, 0] = True
    observed = np.ones((2, 4), bool)
    # raster column 0 is world column 1 (origin x = 1 m): world blocks [0, 1], [2, 3], [4, 5] are pure: 3 cells
    assert label_pure_cells(_labels(occupied, observed, (1.0, 0.0)), 1) == 3
    # world column -1 (origin x = -1 m) lies in block [-2, -1]: the same split
    assert label_pure_cells(_labels(occupied, observed, (-1.0, 0.0)), 1) == 3
    # aligned at 0: block [0, 1] mixes labels (4 fine cells), block [2, 3] is pure (1)
    assert label_pure_cells(_labels(occupied, observed, (0.0, 0.0)), 1) == 5


def _posed(poses: PoseSet, scans: int) -> PosedScans:
    return PosedScans(
        ranges=np.arange(scans * 2, dtype=np.float32).reshape(scans, 2),
        angle_min=0.0,
        angle_increment=0.1,
        range_min=0.1,
        range_max=5.0,
        stamps=np.arange(scans) * 0.5,
        sensor_offset=np.zeros(3),
        poses=poses,
    )


def test_select_scans_keeps_each_scan_with_its_own_pose_distribution_in_either_form():
    scans = 9
    particles = PoseSet(samples=np.arange(scans * 2 * 3.0).reshape(scans, 2, 3), weights=np.full((scans, 2), 0.5))
    gaussian = PoseSet(mean=np.arange(scans * 3.0).reshape(scans, 3), cov=np.tile(np.eye(3), (scans, 1, 1)))
    for poses in (particles, gaussian):
        picked = select_scans(_posed(poses, scans), slice(None, None, 4))  # scans 0, 4 and 8
        np.testing.assert_array_equal(picked.stamps, [0.0, 2.0, 4.0])
        np.testing.assert_array_equal(picked.ranges[:, 0], [0.0, 8.0, 16.0])
        for key, value in picked.poses.arrays().items():
            np.testing.assert_array_equal(value, poses.arrays()[key][[0, 4, 8]])
        assert picked.poses.is_gaussian == poses.is_gaussian and (picked.range_max == 5.0).all()


def test_leave_one_out_chooses_on_the_other_logs_relative_to_their_best():
    """Hand-worked: on log a, candidate x is best (1.0) and y 2x worse; on b, y is best and x 1.5x worse; on c both
    are equal. Holding out a: b and c prefer y (means 1.25 against 1.0 for y); holding out b: a and c prefer x;
    holding out c: x (relative 1.0 and 1.5 -> 1.25) against y (2.0 and 1.0 -> 1.5)."""
    from bench.gridslam_logs import leave_one_out

    errors = {"x": {"a": 0.10, "b": 0.06, "c": 0.05}, "y": {"a": 0.20, "b": 0.04, "c": 0.05}}
    chosen = leave_one_out(errors)
    assert chosen == {"a": ("y", 0.20), "b": ("x", 0.06), "c": ("x", 0.05)}
    assert leave_one_out({"x": {"a": 1.0}}) == {}  # one log: nothing to choose on


def test_pooled_figures_are_the_mean_inside95_and_the_geometric_mean_ate_ratio_per_group():
    figures = {}
    runs = {  # robot -> (inside95, ATE ratio) of every (filter, label); ref has no ratio
        "sim_a1": (0.80, 2.0),
        "sim_b1": (1.00, 0.5),
        "mrclam_r1": (0.90, 4.0),
        "tune_c3": (0.50, 1.0),
    }
    for robot, (inside, ratio) in runs.items():
        for algo in ("ekf", "fastslam2"):
            figures[f"{robot}_{algo}_ref_ate_m"] = 0.1
            for label in ("ref", "default", "half"):
                figures[f"{robot}_{algo}_{label}_inside95"] = inside
                if label != "ref":
                    figures[f"{robot}_{algo}_{label}_ate_ratio"] = ratio
    got = pooled(figures)
    assert got["pooled_sim_ekf_default_inside95"] == pytest.approx(0.90)
    assert got["pooled_sim_ekf_default_ate_ratio"] == pytest.approx(1.0)  # sqrt(2 * 0.5)
    assert got["pooled_mrclam_fastslam2_half_ate_ratio"] == pytest.approx(4.0)
    assert got["pooled_tune_ekf_half_inside95"] == pytest.approx(0.50)
    assert got["pooled_all_ekf_ref_inside95"] == pytest.approx(0.80)  # (0.8 + 1 + 0.9 + 0.5) / 4
    assert got["pooled_all_fastslam2_default_ate_ratio"] == pytest.approx(4.0 ** (1 / 4))  # (2 * 0.5 * 4 * 1)^(1/4)
    assert "pooled_all_ekf_ref_ate_ratio" not in got and len(got) == 4 * 2 * 5


def test_a_suites_record_names_the_processor_and_the_cores_its_figures_come_from(tmp_path, monkeypatch, capsys):
    suite = types.ModuleType("bench.tiny_suite")
    suite.run = lambda: {"scans_per_s": 2.5}  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "bench.tiny_suite", suite)
    monkeypatch.setattr(bench.run, "RESULTS", tmp_path)
    assert bench.run.main(["tiny_suite"]) == 0
    record = json.loads((tmp_path / "tiny_suite.json").read_text())
    assert record["figures"]["scans_per_s"] == 2.5
    assert record["cores"] == len(os.sched_getaffinity(0))
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [
            line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines() if line.startswith("model name")
        ]
        assert record["cpu"] in names  # (the first processor's model name)
    assert record["cpu"]
    assert "tiny_suite.json" in capsys.readouterr().out
