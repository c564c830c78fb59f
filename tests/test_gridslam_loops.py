"""Loop closure for grid FastSLAM (slam.gridslam.loops): the likelihood field against hand-computed values, the
wide-window scan-to-submap search against known offsets, and a long corridor loop that the filter closes only with
it (docs/gridslam.md, "Loop closure")."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.gridslam import write_sim_log
from services.cli import build_parser, main
from services.commands.gridslam import gridslam_config
from services.commands.options import option_argv
from slam.angles import wrap_angle
from slam.carmen import read_carmen
from slam.gridslam import GridSlamConfig, run_gridslam
from slam.gridslam.loops import end_points, likelihood_field, match_scan
from slam.gridslam.simlogs import LASER_OFFSET, corridor_world, laser_scans, room_world, sim_log
from slam.laserlog import LaserLog

RES, SIGMA = 0.05, 0.05


def test_the_likelihood_field_falls_with_the_distance_to_the_nearest_point():
    field, origin = likelihood_field(np.array([[1.02, 2.03]]), RES, SIGMA, margin=0.5)
    cell = np.floor((np.array([1.02, 2.03]) - origin) / RES).astype(int)
    assert field[cell[1], cell[0]] == pytest.approx(1.0)
    # two cells along x: d = 0.1 m, exp(-0.1^2 / (2 * 0.05^2)) = exp(-2); one cell diagonally: d = 0.05 sqrt(2), exp(-1)
    assert field[cell[1], cell[0] + 2] == pytest.approx(math.exp(-2.0), rel=1e-6)
    assert field[cell[1] + 1, cell[0] - 1] == pytest.approx(math.exp(-1.0), rel=1e-6)
    # the box spans the margin on every side
    assert origin[0] <= 1.02 - 0.5 and origin[1] <= 2.03 - 0.5
    assert origin[0] + field.shape[1] * RES >= 1.02 + 0.5 and origin[1] + field.shape[0] * RES >= 2.03 + 0.5


def scan_of(world, pose: np.ndarray) -> np.ndarray:
    """The end points (K, 2) in the robot frame of the simulated laser's noise-free scan at ``pose``."""
    segments, _ = world()
    ranges, angle_min, step = laser_scans(pose[None], segments, np.random.default_rng(0), sigma=0.0)
    angles = angle_min + step * np.arange(ranges.shape[1])
    r = ranges[0].astype(np.float64)
    hit = np.isfinite(r)
    return end_points(np.where(hit, r, np.nan), hit, np.cos(angles), np.sin(angles), np.array(LASER_OFFSET))


def world_points(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack(
        [pose[0] + c * points[:, 0] - s * points[:, 1], pose[1] + s * points[:, 0] + c * points[:, 1]]
    )


@pytest.mark.parametrize("offset", [(0.8, -0.5, 0.08), (-1.3, 0.9, -0.15), (0.02, 0.01, 0.0)])
def test_the_search_finds_the_true_pose_metres_from_the_guess(offset):
    """A furnished room's scans from three poses make the submap; a scan from a fourth pose, searched from a guess
    offset by up to 1.6 m and 0.15 rad, is put back within half a cell and 0.005 rad (the field marks whole cells,
    so the mean distance to a point's cell centre keeps the matched fraction near exp(-(0.03 / 0.05)^2 / 2) = 0.84)."""
    truth = np.array([4.3, 1.6, 0.4])
    submap = np.vstack(
        [world_points(scan_of(room_world, p), p) for p in (np.array([2.0, 2.0, 0.0]), np.array([5.0, 3.0, 2.5]), truth)]
    )
    field, origin = likelihood_field(submap, RES, SIGMA, margin=3.0)
    scan = scan_of(room_world, truth)
    guess = truth + np.array(offset)
    match = match_scan(field, origin, RES, scan, guess, window_xy=2.0, window_yaw=0.2, temper=1 / 3)
    assert np.hypot(*(match.pose[:2] - truth[:2])) <= RES / 2
    assert abs(wrap_angle(match.pose[2] - truth[2])) <= 0.005
    assert match.matched > 0.8
    # the coarse search's envelope (max-filtered over 4 cells, steps of 0.2 m) keeps the spread at about 0.1 m
    assert np.all(np.sqrt(np.diag(match.covariance)[:2]) < 0.15)


def test_a_bare_corridor_fixes_the_pose_across_it_and_not_along_it():
    """In a 60 m corridor whose ends lie out of range, the search's response is flat along the axis: the match's
    covariance is wide along x and narrow across (y) (to the coarse search's envelope, about 0.1 m)."""
    truth = np.array([30.0, 1.0, 0.0])
    submap = np.vstack([world_points(scan_of(corridor_world, p), p) for p in (truth, truth + [2.0, 0.0, 0.0])])
    field, origin = likelihood_field(submap, RES, SIGMA, margin=3.0)
    match = match_scan(field, origin, RES, scan_of(corridor_world, truth), truth + [0.5, 0.3, 0.05], 2.0, 0.2, 1 / 3)
    sd = np.sqrt(np.diag(match.covariance))
    assert abs(match.pose[1] - truth[1]) <= RES / 2 and abs(wrap_angle(match.pose[2])) <= 0.005
    assert sd[0] > 0.5 and sd[1] < 0.15 and sd[0] > 5 * sd[1]


# ------------------------------------------------------------------------------------- a long corridor loop


def ring_corridor(folder) -> tuple[LaserLog, np.ndarray]:
    """The ring corridor (30 m x 14 m, 2 m wide, driven once round and 8 m on: 86 m of corridor), seed 2, written and
    read back as a CARMEN log; and its true poses."""
    log = sim_log("loop", 2)
    write_sim_log(log, folder / "ring.clf")
    return read_carmen(folder / "ring.clf"), log.true_poses


def best_errors(result, truth: np.ndarray) -> np.ndarray:
    """The best trajectory's position error (T,) (m) against the true poses."""
    best = result.samples[:, result.best]
    return np.hypot(best[:, 0] - truth[:, 0], best[:, 1] - truth[:, 1])


@pytest.mark.slow
def test_a_long_corridor_loop_closes_with_the_loop_search_and_not_without(tmp_path):
    """A heading error picked up at a corner bends the corridor the particles map. Without loop closure and without
    the failed-match recovery the filter comes back metres off and does not close the loop (docs/gridslam.md: the
    shipped 30 particles end 2.95 m off here; 10 keep the test's time down). With loop closure (the
    default) the same 10 particles find the old corridor by the wide search, a second match confirms it,
    the pose graph is solved and the grids rebuilt: over the last 5 % of the drive (back in the old corridor) the
    best particle stays within 0.35 m of the truth where the plain filter is more than 1 m off, and the solved graph
    takes the whole path's RMS error down by a quarter at least."""
    log, truth = ring_corridor(tmp_path)
    plain = run_gridslam(log, GridSlamConfig(particles=10, particle_cap=10, recovery=False, loop_closure=False), seed=0)
    closing = run_gridslam(log, GridSlamConfig(particles=10, particle_cap=10), seed=0)
    plain_errors, closing_errors = best_errors(plain, truth), best_errors(closing, truth)
    plain_rms, closing_rms = np.sqrt(np.mean(plain_errors**2)), np.sqrt(np.mean(closing_errors**2))
    tail = slice(int(0.95 * len(truth)), None)
    assert plain_errors[tail].min() > 1.0 and plain_rms > 0.5
    assert closing.loops["closures"] >= 1 and closing.loops["rebuilds"] >= 1
    assert closing_errors[tail].max() < 0.35, closing_errors[tail].max()
    assert closing_rms < 0.75 * plain_rms, (closing_rms, plain_rms)
    assert plain.loops == {"searches": 0, "closures": 0, "rebuilds": 0, "cpu_seconds": 0.0}


def test_loop_closure_is_switched_by_on_or_off_and_refused_otherwise(tmp_path, capsys):
    """--loop-closure takes 'on' or 'off' (argparse: one line naming the option, exit 2), and only with gridslam."""
    path = tmp_path / "room.clf"
    write_sim_log(sim_log("room", 1), path)
    with pytest.raises(SystemExit) as stopped:
        main(["slam", "--algo", "gridslam", str(path), "-o", str(tmp_path / "o.npz"), "--loop-closure", "maybe"])
    assert stopped.value.code == 2
    assert "--loop-closure: expected 'on' or 'off', got 'maybe'" in capsys.readouterr().err
    argv = ["slam", "--algo", "gridslam", str(path), "-o", str(tmp_path / "o.npz")]
    parse = build_parser().parse_args
    assert gridslam_config(parse([*argv, "--loop-closure", "on", "--resample-threshold", "0.5"])).loop_closure
    assert not gridslam_config(parse([*argv, "--loop-closure", "off", "--resample-threshold", "0.5"])).loop_closure
    assert parse(argv).loop_closure is None
    assert gridslam_config(parse([*argv, "--resample-threshold", "0.5"])).loop_closure  # on by default
    # `run` hands it to its SLAM node as given
    run = parse(["run", "--carmen", str(path), "--loop-closure", "on"])
    assert option_argv(run, ["--loop-closure"]) == ["--loop-closure", "on"]
