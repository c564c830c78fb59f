"""The simulate, slam and eval-traj subcommands end to end, and their one-line errors with exit 2."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from schemas.files import load_pose_distribution, load_posed_scans, load_truth
from services.cli import main


@pytest.fixture(scope="module")
def simdir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("sim")
    assert main(["simulate", str(folder), "--seed", "4", "--steps", "60", "--beams", "31"]) == 0
    return folder


def test_simulate_writes_the_contract_files(simdir):
    scans = load_posed_scans(simdir / "scans.npz")
    truth = load_pose_distribution(simdir / "groundtruth.npz")
    raster = load_truth(simdir / "truth.npz")
    assert scans.ranges.shape == (60, 31)
    np.testing.assert_array_equal(scans.poses.samples, truth.poses.samples)
    np.testing.assert_array_equal(scans.poses.weights, 1.0)
    np.testing.assert_allclose(scans.stamps, 0.1 * np.arange(60))
    assert raster.occupied.any() and raster.visible.sum() > raster.occupied.sum()
    assert (simdir / "controls.npz").is_file() and (simdir / "landmarks.npz").is_file()


def test_simulate_is_reproducible(simdir, tmp_path):
    assert main(["simulate", str(tmp_path), "--seed", "4", "--steps", "60", "--beams", "31"]) == 0
    for name in ("scans.npz", "controls.npz", "landmarks.npz", "truth.npz"):
        with np.load(simdir / name) as a, np.load(tmp_path / name) as b:
            assert a.files == b.files
            for key in a.files:
                np.testing.assert_array_equal(a[key], b[key])


def test_slam_on_a_simulator_folder_writes_posed_scans(simdir, tmp_path, capsys):
    out = tmp_path / "ekf.npz"
    assert main(["slam", "--algo", "ekf", str(simdir), "-o", str(out)]) == 0
    assert "ms per step" in capsys.readouterr().out
    posed = load_posed_scans(out)
    scans = load_posed_scans(simdir / "scans.npz")
    np.testing.assert_array_equal(posed.ranges, scans.ranges)
    assert posed.poses.is_gaussian and posed.poses.mean.shape == (60, 3)

    particles = tmp_path / "fs.npz"
    assert main(["slam", "--algo", "fastslam2", str(simdir), "-o", str(particles), "--particles", "30", "--seed", "2"]) == 0
    assert load_posed_scans(particles).poses.samples.shape == (60, 30, 3)

    capsys.readouterr()
    assert main(["eval-traj", str(out), str(simdir)]) == 0
    from_folder = json.loads(capsys.readouterr().out)
    assert set(from_folder) == {"ate_rmse_m", "heading_mae_rad", "nees_mean", "inside95", "steps"}
    assert from_folder["steps"] == 60 and from_folder["ate_rmse_m"] < 0.3
    assert main(["eval-traj", str(out), str(simdir / "groundtruth.npz")]) == 0
    assert json.loads(capsys.readouterr().out) == from_folder


def test_slam_without_scans_writes_a_pose_distribution(simdir, tmp_path):
    folder = tmp_path / "noscans"
    folder.mkdir()
    for name in ("controls.npz", "landmarks.npz"):
        (folder / name).write_bytes((simdir / name).read_bytes())
    out = tmp_path / "odo.npz"
    assert main(["slam", "--algo", "odometry", str(folder), "-o", str(out), "--motion", "odometry"]) == 0
    dist = load_pose_distribution(out)
    assert len(dist.stamps) == 60 and dist.poses.is_gaussian


def _mrclam_sample(folder: Path) -> None:
    def write(name, rows):
        body = "".join(" \t ".join(str(v) for v in row) + " \r\n" for row in rows)
        (folder / name).write_text("# header\r\n" * 4 + body, newline="")

    write("Barcodes.dat", [(1, 5), (6, 63), (7, 81)])
    write("Robot1_Odometry.dat", [(10.0 + 0.1 * k, 0.2, 0.1) for k in range(30)])
    write("Robot1_Measurement.dat", [(10.5, 63, 2.0, 0.1), (11.0, 81, 1.5, -0.2), (11.5, 5, 1.0, 0.0),
                                     (12.0, 63, 1.9, 0.15)])
    write("Robot1_Groundtruth.dat", [(10.0 + 0.05 * k, 0.01 * k, 0.0, 0.005 * k) for k in range(70)])


def test_slam_and_eval_on_an_mrclam_folder(tmp_path, capsys):
    _mrclam_sample(tmp_path)
    out = tmp_path / "ekf.npz"
    assert main(["slam", "--algo", "ekf", str(tmp_path), "--robot", "1", "-o", str(out)]) == 0
    assert "skipped 1 measurements of robots" in capsys.readouterr().out
    dist = load_pose_distribution(out)
    assert dist.stamps[0] == pytest.approx(10.0)
    assert main(["eval-traj", str(out), str(tmp_path / "Robot1_Groundtruth.dat")]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == len(dist.stamps)


def test_mrclam_commands_are_scaled_to_the_executed_speeds_unless_raw(tmp_path):
    # dead reckoning's heading change is the sum of w dt: 0.1 rad/s held until the last step, times 0.958
    _mrclam_sample(tmp_path)
    yaw_change = {}
    for flags in ([], ["--raw-commands"]):
        out = tmp_path / f"odometry{len(flags)}.npz"
        assert main(["slam", "--algo", "odometry", str(tmp_path), "--robot", "1", "-o", str(out), *flags]) == 0
        mean = load_pose_distribution(out).poses.mean
        yaw_change[bool(flags)] = mean[-1, 2] - mean[0, 2]
    assert yaw_change[True] > 0.2
    assert yaw_change[False] == pytest.approx(0.958 * yaw_change[True], rel=1e-9)


@pytest.mark.parametrize("algo", ["ekf", "fastslam2"])
def test_dataset7_robot3_is_accurate_and_honest_with_the_defaults(tmp_path, capsys, data_dir, algo):
    # issue 4's target on real data, 900 s of robot 3: ATE well under dead reckoning's 2.13 m and the true pose
    # inside the 95 % region at >= 85 % of the steps (docs/slam.md: EKF 0.12 m / 0.99; FastSLAM 2.0 with
    # gauge-preserving resampling 0.20 m / 0.97, with plain resampling 0.20 m / 0.20)
    folder, out = data_dir / "mrclam7", tmp_path / f"{algo}.npz"
    assert main(["slam", "--algo", algo, str(folder), "--robot", "3", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["eval-traj", str(out), str(folder / "Robot3_Groundtruth.dat")]) == 0
    score = json.loads(capsys.readouterr().out)
    assert score["ate_rmse_m"] < 0.3 * 2.13
    assert score["inside95"] >= 0.85


def _one_line_exit_2(argv, capsys, *fragments):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    for fragment in fragments:
        assert fragment in err
    return err


def test_bad_inputs_give_one_line_and_exit_2(simdir, tmp_path, capsys):
    out = str(tmp_path / "x.npz")
    _one_line_exit_2(["slam", "--algo", "ekf", str(tmp_path / "nothing"), "-o", out], capsys, "no such folder")
    _one_line_exit_2(["slam", "--algo", "ekf", str(tmp_path), "-o", out], capsys, "neither a simulator folder")
    _one_line_exit_2(["slam", "--algo", "fastslam1", str(simdir), "-o", out, "--particles", "0"], capsys, "--particles")
    _one_line_exit_2(["slam", "--algo", "ekf", str(simdir), "-o", out, "--alphas", "1,2"], capsys, "--alphas")
    # grid FastSLAM's options given to another filter would be ignored: refused, here and for the pipeline
    _one_line_exit_2(["slam", "--algo", "ekf", str(simdir), "-o", out, "--prior-cap", "36"], capsys, "--prior-cap",
                     "--algo gridslam")
    _one_line_exit_2(["slam", "--algo", "fastslam2", str(simdir), "-o", out, "--scans", "50"], capsys, "--scans",
                     "--algo gridslam")
    _one_line_exit_2(["run", "--sim-dir", str(simdir), "--min-range", "1"], capsys, "--min-range", "fastslam2")

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "controls.npz").write_bytes(b"not a zip file")
    (broken / "landmarks.npz").write_bytes((simdir / "landmarks.npz").read_bytes())
    _one_line_exit_2(["slam", "--algo", "ekf", str(broken), "-o", out], capsys, "controls.npz", "not a readable")

    mrclam = tmp_path / "mrclam"
    mrclam.mkdir()
    _mrclam_sample(mrclam)
    _one_line_exit_2(["slam", "--algo", "ekf", str(mrclam), "-o", out], capsys, "--robot")
    with open(mrclam / "Robot1_Odometry.dat", "a", newline="") as handle:
        handle.write("13.5 \t fast \t 0.1 \r\n")
    _one_line_exit_2(["slam", "--algo", "ekf", str(mrclam), "--robot", "1", "-o", out], capsys,
                     "Robot1_Odometry.dat line 35")
    _one_line_exit_2(["eval-traj", str(simdir / "scans.npz"), str(tmp_path / "missing.dat")], capsys, "missing.dat")
    _one_line_exit_2(["eval-traj", str(tmp_path / "nope.npz"), str(simdir)], capsys, "nope.npz")
