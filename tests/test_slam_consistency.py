"""The consistency watch and adaptive noise of the landmark filters (slam.consistency, slam.ekf, slam.fastslam), and
what a SLAM node reports of it (services.state.slam)."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.messages import PoseGaussian, decode_message
from services import keys, streams
from services.process import RejectCounter, get_logger
from services.state.slam import NodeConfig, SlamState
from slam.calibration import Calibration
from slam.consistency import CHI2_2_MEDIAN, ConsistencyMonitor, scaled_motion, scaled_sensor
from slam.ekf import EKFSLAM
from slam.fastslam import FastSLAM
from slam.motion import VelocityMotionModel
from slam.mrclam import read_sequence
from slam.mrclam_sim import simulate_mrclam_robot, write_mrclam_folder
from slam.range_bearing import RangeBearingModel
from slam.scoring import fit_gaussian, score_trajectory
from slam.sequence import run_filter
from slam.simulator import simulate_office

#: the noise the filters assume below: the simulator's defaults
MOTION, SENSOR = VelocityMotionModel(), RangeBearingModel(sigma_range=0.1, sigma_bearing=0.03)


def test_an_honest_filter_keeps_its_noise():
    rng = np.random.default_rng(0)
    monitor = ConsistencyMonitor()
    changes = [monitor.add(float(v)) for v in rng.chisquare(2, 3000)]
    assert sum(c is not None for c in changes) <= 2 and monitor.scale <= 1.7
    assert 0.8 < monitor.nis_ratio < 1.25


def test_an_overconfident_filter_gets_its_noise_scaled_to_the_innovations():
    # innovations 9 times the variance the filter expects: after one window the scale is about 9, and stays there
    rng = np.random.default_rng(1)
    monitor = ConsistencyMonitor()
    factors = []
    for value in 9.0 * rng.chisquare(2, 2000):
        factor = monitor.add(float(value) / monitor.scale)  # the filter's NIS falls as its noise grows
        if factor is not None:
            factors.append(factor)
    assert factors[0] == pytest.approx(9.0, rel=0.35)
    assert monitor.scale == pytest.approx(9.0, rel=0.35) and monitor.inflations >= 1
    # not below the configured noise: innovations smaller than expected bring the scale back to 1, no lower
    for value in 0.1 * rng.chisquare(2, 600):
        monitor.add(float(value))
    assert monitor.scale == 1.0 and monitor.deflations >= 1


def test_a_gate_that_drops_most_measurements_makes_the_noise_grow():
    monitor = ConsistencyMonitor()
    gated = [50.0] * 40 + [1.0] * 20  # two thirds beyond a gate of 18.4
    factors = [monitor.add(value, gated=value > 18.4) for value in gated]
    assert factors[-1] == pytest.approx(50.0 / CHI2_2_MEDIAN) and monitor.gated == 40
    assert ConsistencyMonitor(adaptive=False).add(1.0) is None


@pytest.fixture(scope="module")
def noisy_run():
    """The office with motion and landmark noise 3 times (in sd) what the filters assume."""
    run = simulate_office(
        seed=4, steps=400, n_beams=3, velocity_model=scaled_motion(MOTION, 9.0), sensor=scaled_sensor(SENSOR, 9.0)
    )
    return run, run.log()


def _inside95(track, truth) -> float:
    mean, cov = (track.mean, track.cov) if track.is_gaussian else fit_gaussian(track.samples, track.weights)
    return score_trajectory(mean, cov, truth).inside95


@pytest.mark.parametrize("algo", ["ekf", "fastslam2"])
def test_with_three_times_the_noise_the_adaptive_filter_stays_honest_where_the_fixed_one_does_not(noisy_run, algo):
    run, log = noisy_run

    def make(adaptive: bool):
        if algo == "ekf":
            return EKFSLAM(MOTION, SENSOR, log.initial_pose, adaptive=adaptive)
        return FastSLAM(MOTION, SENSOR, log.initial_pose, n_particles=500, version=2, seed=1, adaptive=adaptive)

    fixed, adaptive = make(False), make(True)
    assert _inside95(run_filter(fixed, log.sequence()), run.true_poses) < 0.5
    assert _inside95(run_filter(adaptive, log.sequence()), run.true_poses) >= 0.85
    assert fixed.monitor.scale == 1.0 and 4.0 < adaptive.monitor.scale < 20.0  # the truth: 9


def _messages(stream):
    for step in stream.steps:
        for message in step.messages:
            yield (
                keys.robot_key(
                    stream.robot, {"Odometry": keys.ODOM, "LandmarkObservations": keys.LANDMARKS}[message.TYPE]
                ),
                message,
            )


def test_a_slam_node_applies_its_calibration_and_reports_its_consistency(tmp_path):
    """A node given the robot's calibration publishes the poses the offline filter gives on the corrected data
    (command delay included), and its stats say how its consistency watch scaled the noise."""
    truth = Calibration(
        command_delay=0.15,
        velocity_scale=(0.9, 1.05),
        velocity_bias=(0.0, -0.01),
        range_calibration=(1.0, -0.2),
        motion=VelocityMotionModel((0.1, 0.01, 0.0, 0.05, 0.0, 0.0), floor=(1e-4, 5e-4)),
        sensor=RangeBearingModel(0.08, 0.03),
        scale_sd=0.0,
    )
    folder = write_mrclam_folder(tmp_path / "robot", simulate_mrclam_robot(truth, seed=2, duration=60.0))
    overconfident = scaled_sensor(truth.sensor, 1 / 16)  # the node's filter expects a quarter of the camera's sd
    stream = streams.mrclam_stream(folder, 1, "r")
    published: list[bytes] = []
    config = NodeConfig(
        robot="r",
        algorithm="ekf",
        make_filter=lambda start: EKFSLAM(truth.motion, overconfident, start, outlier_gate=truth.outlier_gate),
        initial=stream.prior.mean,
        calibration=truth,
    )
    state = SlamState(config, RejectCounter(get_logger("test-consistency")), publish=published.append)
    for key, message in _messages(stream):
        state.handle(key, message.encode())
    stats = state.stats()
    assert stats.noise_scale > 4.0 and stats.consistency["inflations"] >= 1
    assert stats.consistency["measurements"] > 100 and decode_message(stats.encode()).noise_scale == stats.noise_scale

    _, sequence = read_sequence(folder, 1, truth)
    offline = run_filter(
        EKFSLAM(truth.motion, overconfident, sequence.initial_pose, outlier_gate=truth.outlier_gate), sequence
    )
    poses = [decode_message(payload, PoseGaussian) for payload in published]
    assert len(poses) == len(sequence)
    np.testing.assert_allclose(np.array([p.mean for p in poses]), offline.mean, atol=1e-6)
