"""Bad inputs to slam's library calls are refused with slam.errors.InputError (a ValueError) naming what was wrong,
never turned into a silently wrong result or a NaN state: resampling weights, trajectory scoring, the landmark
filters' models, options and steps, and the simulator's options."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.files import MAX_TRUTH_CELLS as SCHEMAS_MAX_TRUTH_CELLS
from slam.ekf import EKFSLAM
from slam.errors import InputError
from slam.fastslam import FastSLAM
from slam.motion import OdometryMotionModel, OmniOdometryMotionModel, VelocityMotionModel
from slam.range_bearing import RangeBearingModel
from slam.raster import MAX_TRUTH_CELLS
from slam.resampling import effective_sample_size, low_variance_resample, normalize_log_weights
from slam.scoring import interpolate_poses, score_trajectory
from slam.simulator import simulate_office

# ----------------------------------------------------------------------------------------------- resampling


def _old_low_variance_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The implementation before unnormalised weights were handled: the reference for normalised weights."""
    n = len(weights)
    pointers = rng.uniform(0.0, 1.0 / n) + np.arange(n) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.minimum(np.searchsorted(cumulative, pointers, side="right"), n - 1)


def test_low_variance_resample_normalises_weights_by_their_sum():
    assert low_variance_resample(np.array([2.0, 2, 2, 2]), np.random.default_rng(0)).tolist() == [0, 1, 2, 3]
    half = np.array([0.25, 0.125, 0.125, 0.0])  # sums to 0.5: the same draw as the weights doubled
    for seed in range(20):
        got = low_variance_resample(half, np.random.default_rng(seed))
        assert got.tolist() == low_variance_resample(2 * half, np.random.default_rng(seed)).tolist()
        assert np.bincount(got, minlength=4).tolist() == [2, 1, 1, 0]


@settings(max_examples=60, deadline=None)
@given(
    raw=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=30).filter(lambda w: sum(w) > 1e-3),
    count=st.integers(1, 90),
    seed=st.integers(0, 2**30),
)
def test_resampling_to_another_count_copies_each_particle_floor_or_ceil_of_its_share(raw, count, seed):
    """To ``count`` particles (grid FastSLAM's KLD-sampling grows or shrinks its cloud), a particle of weight w is
    copied floor(count w) or ceil(count w) times, and the draw is the count-N one's for count = N."""
    weights = np.array(raw) / sum(raw)
    got = low_variance_resample(weights, np.random.default_rng(seed), count)
    copies = np.bincount(got, minlength=len(weights))
    assert len(got) == count and (np.diff(got) >= 0).all()
    assert (copies >= np.floor(count * weights - 1e-9)).all() and (copies <= np.ceil(count * weights + 1e-9)).all()
    same = low_variance_resample(weights, np.random.default_rng(seed), len(weights))
    np.testing.assert_array_equal(same, low_variance_resample(weights, np.random.default_rng(seed)))


def test_resampling_to_no_particle_is_refused():
    with pytest.raises(InputError, match="count of at least 1"):
        low_variance_resample(np.ones(3), np.random.default_rng(0), 0)


def test_normalised_weights_resample_and_count_bit_for_bit_as_before():
    rng = np.random.default_rng(42)
    for trial in range(500):
        n = int(rng.integers(1, 200))
        if trial % 2:
            weights = normalize_log_weights(rng.normal(0.0, 5.0, n))
        else:
            raw = rng.random(n) ** 3
            weights = raw / raw.sum()
        seed = int(rng.integers(1 << 30))
        new = low_variance_resample(weights, np.random.default_rng(seed))
        old = _old_low_variance_resample(weights, np.random.default_rng(seed))
        np.testing.assert_array_equal(new, old)
        assert effective_sample_size(weights) == float(1.0 / np.sum(weights * weights))


def test_effective_sample_size_is_that_of_the_normalised_weights():
    assert effective_sample_size(np.array([2.0, 2.0])) == pytest.approx(2.0)
    assert effective_sample_size(np.array([3.0, 0.0, 0.0])) == pytest.approx(1.0)
    assert effective_sample_size(np.array([0.1, 0.1, 0.1, 0.1])) == pytest.approx(4.0)


@pytest.mark.parametrize(
    ("weights", "words"),
    [
        ([], "non-empty"),
        ([0.5, -0.1, 0.6], "non-negative"),
        ([0.5, np.nan, 0.5], "finite"),
        ([0.5, np.inf, 0.5], "finite"),
        ([0.0, 0.0], "positive"),
        ([[0.5, 0.5]], "1-D"),
    ],
)
def test_bad_weights_are_refused(weights, words):
    for call in (lambda w: low_variance_resample(w, np.random.default_rng(0)), effective_sample_size):
        with pytest.raises(InputError, match=words):
            call(np.array(weights, dtype=np.float64))


# ----------------------------------------------------------------------------------------------- scoring


def _trajectory(steps: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    truth = np.zeros((steps, 3))
    return truth + 0.01, np.tile(np.eye(3) * 1e-2, (steps, 1, 1)), truth


def test_score_trajectory_refuses_mismatched_lengths_and_shapes():
    mean, cov, truth = _trajectory()
    with pytest.raises(InputError, match=r"truth must have shape \(1, 3\)"):
        score_trajectory(mean[:1], cov[:1], truth)
    with pytest.raises(InputError, match=r"cov must have shape \(5, 3, 3\)"):
        score_trajectory(mean, cov[:4], truth)
    with pytest.raises(InputError, match=r"mean must have shape"):
        score_trajectory(mean[:, :2], cov, truth)
    with pytest.raises(InputError, match="no step"):
        score_trajectory(mean[:0], cov[:0], truth[:0])


def test_score_trajectory_refuses_non_finite_values():
    mean, cov, truth = _trajectory()
    mean[3, 1] = np.nan
    with pytest.raises(InputError, match=r"mean must be finite.*\(3, 1\)"):
        score_trajectory(mean, cov, truth)


def test_score_trajectory_refuses_covariances_that_are_not_covariances():
    mean, cov, truth = _trajectory()
    with pytest.raises(InputError, match=r"cov\[0\] is not positive semi-definite"):
        score_trajectory(mean, -np.tile(np.eye(3), (5, 1, 1)) * 1e-4, truth)
    lopsided = cov.copy()
    lopsided[2, 0, 1] = 1.0
    with pytest.raises(InputError, match=r"cov\[2\] is not symmetric"):
        score_trajectory(mean, lopsided, truth)
    # a singular (zero) covariance is the known start: still scored, as before
    assert score_trajectory(truth, np.zeros((5, 3, 3)), truth).nees_mean == 0.0
    # rounding-level asymmetry is no error
    nearly = cov.copy()
    nearly[:, 0, 1] = 1e-15
    assert score_trajectory(mean, nearly, truth).steps == 5


def test_interpolate_poses_refuses_truth_stamps_that_do_not_increase():
    poses = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    with pytest.raises(InputError, match=r"strictly increasing.*\[0\] = 1.0 s and \[1\] = 0.0 s"):
        interpolate_poses(np.array([0.5]), np.array([1.0, 0.0]), poses)
    with pytest.raises(InputError, match="strictly increasing"):
        interpolate_poses(np.array([0.5]), np.array([1.0, 1.0]), poses)
    with pytest.raises(InputError, match=r"truth_poses must have shape \(2, 3\)"):
        interpolate_poses(np.array([0.5]), np.array([0.0, 1.0]), poses[:1])


# ----------------------------------------------------------------------------------------------- landmark filters

MOTION, SENSOR = VelocityMotionModel(), RangeBearingModel()
CONTROLS, Z, IDS = np.array([[1.0, 0.0, 0.1]]), np.array([[2.0, 0.1]]), np.array([0])
FILTERS = (EKFSLAM, FastSLAM)


def _make(kind, motion=MOTION, sensor=SENSOR, pose=None, **options):
    extra = {"n_particles": 4} if kind is FastSLAM else {}
    return kind(motion, sensor, np.zeros(3) if pose is None else pose, **extra, **options)


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: VelocityMotionModel(alphas=(-1.0,) * 6), "alphas must be 6 finite numbers >= 0"),
        (lambda: VelocityMotionModel(alphas=(0.01,) * 5), "alphas must be 6"),
        (lambda: VelocityMotionModel(floor=(np.nan, 0.0)), "floor"),
        (lambda: VelocityMotionModel(dt_ref=0.0), "dt_ref"),
        (lambda: OdometryMotionModel(alphas=(0.01, 0.01, -0.01, 0.01)), "alphas"),
        (lambda: OmniOdometryMotionModel(alphas=(0.01, np.inf, 0.01, 0.01)), "alphas"),
        (lambda: RangeBearingModel(0.1, np.nan), "sigma_bearing"),
        (lambda: RangeBearingModel(-0.1, 0.03), "sigma_range"),
    ],
)
def test_models_refuse_negative_or_non_finite_noise(make, words):
    with pytest.raises(InputError, match=words):
        make()


@pytest.mark.parametrize("kind", FILTERS)
@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"pose": np.array([np.nan, 0.0, 0.0])}, "initial_pose must be finite"),
        ({"pose": np.zeros(2)}, r"initial_pose must have shape \(3,\)"),
        ({"drive_angle": np.nan}, "drive_angle"),
        ({"scale_sd": np.nan}, "scale_sd"),
        ({"drive_angle_sd": -0.1}, "drive_angle_sd"),
        ({"outlier_gate": np.nan}, "outlier_gate"),
        ({"sensor": RangeBearingModel(sigma_range=0.0)}, "sigma_range must be finite and within"),
        ({"sensor": RangeBearingModel(0.1, 4.0)}, "sigma_bearing"),
        ({"motion": VelocityMotionModel(alphas=(2e3,) * 6)}, "alphas must be finite and within"),
    ],
)
def test_filters_refuse_unusable_models_and_options(kind, options, words):
    with pytest.raises(InputError, match=words):
        _make(kind, **options)


@pytest.mark.parametrize("kind", FILTERS)
@pytest.mark.parametrize(
    ("controls", "z", "ids", "words"),
    [
        ([[np.nan, 0.0, 0.1]], Z, IDS, "controls must be finite"),
        ([[1.0, 0.0, -0.1]], Z, IDS, "control dt"),
        ([[1e6, 0.0, 0.1]], Z, IDS, "control velocity"),
        (CONTROLS, [[np.nan, 0.1]], IDS, "measurements must be finite"),
        (CONTROLS, [[2.0, 0.1, 0.0]], IDS, r"measurements must have shape \(N, 2\)"),
        (CONTROLS, [[-2.0, 0.1]], IDS, "measured range"),
        (CONTROLS, [[2.0, 7.0]], IDS, "measured bearing"),
        (CONTROLS, [[2.0, 0.1], [3.0, 0.2]], [0], r"one id per measurement, \(2,\)"),
        (CONTROLS, Z, [0, 1], r"one id per measurement, \(1,\)"),
        (CONTROLS, Z, [0.7], "whole numbers"),
    ],
)
def test_filter_steps_refuse_bad_inputs_and_keep_their_state(kind, controls, z, ids, words):
    slam = _make(kind)
    slam.step(CONTROLS, Z, IDS)
    before = (slam.mu.copy(), slam.sigma.copy(), len(slam.slot_of))
    with pytest.raises(InputError, match=words):
        slam.step(np.array(controls, dtype=np.float64), np.array(z, dtype=np.float64), np.array(ids))
    np.testing.assert_array_equal(slam.mu, before[0])
    np.testing.assert_array_equal(slam.sigma, before[1])
    assert len(slam.slot_of) == before[2]
    mean, _ = slam.step(CONTROLS, Z, IDS)  # and it goes on
    assert np.all(np.isfinite(mean))


@pytest.mark.parametrize("kind", FILTERS)
def test_filter_steps_take_whole_float_ids_one_control_and_no_ids_for_unknown_correspondences(kind):
    slam = _make(kind)
    slam.step(np.array([1.0, 0.0, 0.1]), Z, np.array([3.0]))
    assert list(slam.slot_of) == [3]
    blind = _make(kind, known_correspondences=False)
    mean, _ = blind.step(CONTROLS, np.array([[2.0, 0.1], [3.0, -1.0]]), np.zeros(0))
    assert np.all(np.isfinite(mean))


def test_fastslam_refuses_bad_particle_options():
    with pytest.raises(InputError, match="n_particles"):
        FastSLAM(MOTION, SENSOR, np.zeros(3), n_particles=2.5)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="resample_threshold"):
        FastSLAM(MOTION, SENSOR, np.zeros(3), resample_threshold=np.nan)


# ----------------------------------------------------------------------------------------------- simulator


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ({"fov": np.nan}, "fov"),
        ({"fov": 10.0}, "more than a full turn"),
        ({"laser_sigma": np.nan}, "laser_sigma"),
        ({"range_max": np.nan}, "not finite"),
        ({"range_max": np.inf}, "not finite"),
        ({"dt": np.nan}, "dt"),
        ({"dt": np.inf}, "dt"),
        ({"max_speed": np.nan}, "max_speed"),
        ({"max_speed": np.inf}, "max_speed"),
        ({"truth_resolution": np.nan}, "truth_resolution"),
        ({"truth_resolution": np.inf}, "truth_resolution"),
        ({"truth_resolution": 1e-3}, "more than the 33554432"),
        ({"truth_resolution": 1e-300}, "more than the 33554432"),
        ({"landmark_fov": np.nan}, "landmark_fov"),
        ({"steps": 0}, "steps"),
        ({"n_beams": 2.0}, "n_beams"),
    ],
)
def test_simulator_refuses_unusable_options_up_front(options, words):
    options = {"steps": 3, **options}
    with pytest.raises(InputError, match=words):
        simulate_office(**options)


def test_simulator_takes_a_fan_of_exactly_a_full_turn():
    run = simulate_office(steps=2, n_beams=9, fov=2 * math.pi)
    assert run.angle_increment == pytest.approx(math.pi / 4)


def test_the_truth_cell_cap_is_the_one_load_truth_applies():
    assert MAX_TRUTH_CELLS == SCHEMAS_MAX_TRUTH_CELLS


@pytest.mark.parametrize(
    "log_weights", [[-np.inf, -np.inf], [0.0, np.inf], [0.0, np.nan]], ids=["all-minf", "inf", "nan"]
)
def test_log_weights_that_give_no_distribution_are_refused(log_weights):
    """All -inf gave NaN weights (0 / 0) that went on into the filter without a word."""
    from slam.resampling import normalize_log_weights

    with pytest.raises(InputError, match="the log weights give no distribution"):
        normalize_log_weights(np.array(log_weights))
    np.testing.assert_allclose(normalize_log_weights(np.array([0.0, -np.inf, np.log(3.0)])), [0.25, 0.0, 0.75])


def test_dead_reckoning_refuses_what_the_landmark_filters_refuse():
    """The baseline filter took NaN controls, a negative dt (no motion) and a NaN start without a word."""
    from slam.dead_reckoning import DeadReckoning
    from slam.motion import VelocityMotionModel

    model = VelocityMotionModel((0.1, 0.01, 0.01, 0.1, 0.0, 0.0))
    with pytest.raises(InputError, match="initial_pose must be finite"):
        DeadReckoning(model, np.array([0.0, np.nan, 0.0]))
    with pytest.raises(InputError, match="drive_angle"):
        DeadReckoning(model, np.zeros(3), drive_angle=np.nan)
    robot = DeadReckoning(model, np.zeros(3))
    for controls, message in (([[np.nan, 0.0, 0.1]], "controls must be finite"), ([[0.5, 0.0, -0.1]], "control dt")):
        with pytest.raises(InputError, match=message):
            robot.step(np.array(controls), np.zeros((0, 2)), np.zeros(0))
    mean, cov = robot.step(np.array([[0.5, 0.0, 0.1]]), np.zeros((0, 2)), np.zeros(0))  # (the pose was not moved)
    np.testing.assert_allclose(mean, [0.05, 0.0, 0.0], atol=1e-12)
    assert np.all(np.isfinite(cov)) and cov[0, 0] > 0


def _grid_filter(**given):
    from slam.gridslam import GridSlamConfig
    from slam.gridslam.filter import GridFastSLAM

    args = {
        "beam_angles": np.linspace(-1.5, 1.5, 90),
        "sensor_offset": np.zeros(3),
        "range_min": 0.05,
        "initial_pose": np.zeros(3),
    }
    args.update(given)
    config = GridSlamConfig(particles=5, particle_cap=5, loop_closure=False)
    return GridFastSLAM(config, args["beam_angles"], args["sensor_offset"], args["range_min"], args["initial_pose"], 0)


@pytest.mark.parametrize(
    "given, message",
    [
        ({"initial_pose": np.array([np.nan, 0.0, 0.0])}, "initial_pose must be finite"),
        ({"initial_pose": np.array([1e300, 0.0, 0.0])}, "initial_pose x and y must be"),
        ({"beam_angles": np.zeros((3, 3))}, r"beam_angles must have shape \(N,\)"),
        ({"beam_angles": np.array([0.0, np.nan, 0.1])}, "beam_angles must be finite"),
        ({"sensor_offset": np.zeros(2)}, r"sensor_offset must have shape \(3,\)"),
    ],
    ids=["nan-start", "far-start", "2d-angles", "nan-angle", "short-offset"],
)
def test_grid_fastslam_refuses_a_start_or_laser_it_cannot_use(given, message):
    """A NaN start pose made the grid's insertion loop for ever (compiled, past Ctrl-C); 2-D angles gave a numba
    typing error; a NaN angle was taken."""
    with pytest.raises(InputError, match=message):
        _grid_filter(**given)


def test_grid_fastslam_refuses_odometry_or_ranges_it_cannot_use():
    """NaN odometry was said as a jump of -1.5e19 m; string ranges were read as numbers."""
    grid = _grid_filter()
    for odometry, ranges, message in (
        (np.array([np.nan, 0.0, 0.0]), np.full(90, 3.0), "odometry must be finite"),
        (np.zeros(3), np.array(["3"] * 90), "ranges must be one real number"),
        (np.zeros(3), np.full(89, 3.0), "ranges must be one real number"),
    ):
        with pytest.raises(InputError, match=message):
            grid.integrate(odometry, ranges)
    poses, weights, _, _ = grid.integrate(np.zeros(3), np.full(90, 3.0))
    assert poses.shape == (5, 3) and np.isclose(weights.sum(), 1.0)
