"""Self-calibration: a robot's :class:`slam.calibration.Calibration` estimated from its own data, without ground truth.

The parameters are those of the calibration: the command delay, the executed-speed scale (k_v, k_w) and yaw-rate
bias b_w, the range calibration's bearing term c2 and the bearing bias, the velocity motion noise (a1, a2, a4 and
the floors) and the range-bearing noise (sigma_r, range fraction, sigma_bearing). The filters' own estimate stands
in for the ground truth (:func:`self_calibrate`, several rounds): the command delay is the one on a grid whose
right-invariant EKF-SLAM pass (slam.kernels.ekf_likelihood_pass) has the highest innovation likelihood (the
prediction-error decomposition: each measurement's innovation nu with covariance S contributes (d^2 + log det S) / 2
to the negative log likelihood, d^2 = nu^T S^-1 nu, with a Huber bound on d^2); the trajectory is then smoothed
against that pass's map, and the speed scales, the motion noise (over windows of several lengths, so that the noise,
which grows with a window's length, is told from the estimate's own error, which does not) and the sensor's
corrections and noise are fitted against it, as one would fit them against ground truth. Two parameters that this
fit cannot tell apart from others are taken from the innovation likelihood instead: the yaw-rate floor (the yaw
noise of a straight drive, which the windows confuse with the noise of the turns) and the camera's bearing bias
(which the smoothed heading takes up).

The bearing bias so found is how the camera and the drive disagree: a camera turned by b on a robot that drives
straight and a straight camera on a robot that crabs by b give the same data. Which it is decides where the path
lies (a drive angle e left out turns the path about its start by e) but no data can tell, so the fit gives each half
(``bearing_bias`` and ``drive_angle`` b / 2) and states the drive angle's sd as b / 2, which puts either pure case
one sd away (:func:`split_drive_and_camera`; docs/slam.md, "Drive angle").

Two quantities cannot be had from the data alone. The overall scale: scaling every range and the speed together
changes no bearing and no turn, so the range calibration's c0 stays 1 and k_v is the speed scale relative to the
ranges. And the measurement errors' correlation in time, which makes fusing them as independent overconfident
however well the innovations fit: the fitted range and bearing variances are multiplied by the number of
measurements that carry one measurement's worth of independent information (:func:`error_correlation`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from scipy.optimize import nnls

from slam.angles import wrap_angle
from slam.calibration import (
    BEARING_BIAS_LIMITS,
    GENERIC,
    RANGE_C2_LIMITS,
    SCALE_LIMITS,
    VELOCITY_BIAS_LIMITS,
    Calibration,
)
from slam.consistency import scaled_motion
from slam.errors import InputError, LogFormatError, check_within, finite_array
from slam.heading_frames import HEADING_FRAMES
from slam.kernels import ekf_likelihood_pass, smooth_localisation, window_commands
from slam.motion import ALPHA_LIMITS, VelocityMotionModel, check_controls
from slam.range_bearing import RangeBearingModel
from slam.sequence import SlamSequence

#: squared Mahalanobis distance beyond which a measurement's contribution grows linearly in d (Huber)
HUBER_D2 = 9.21
#: command delays (s) tried by default
DELAY_GRID = tuple(round(0.05 * k, 2) for k in range(9))
#: the smoothed trajectory that the motion is fitted against takes the motion noise this many times larger than
#: the current estimate, so that it follows the landmarks rather than the motion model: with the estimate itself,
#: the fitted noise shrinks from one iteration to the next (residuals against a trajectory that follows the
#: model are smaller than the motion's true errors)
SMOOTHING_MOTION_SCALE = 4.0
#: the least data a fit takes: measurements of landmarks seen more than once, short windows of motion
MIN_MEASUREMENTS, MIN_WINDOWS = 50, 10
#: (rad/s)^2 per dt_ref: the yaw-rate floors tried for the likeliest (half-decade steps, 1e-6 to 0.03). The floor is
#: the yaw noise of a robot driving straight; the windows' fit cannot tell it from a4 w^2 when a robot's turns are
#: spread evenly over its run, and gave 0 on most robots (docs/slam.md, "Self-calibration")
YAW_FLOOR_GRID = tuple(10.0 ** (k / 2.0) for k in range(-12, -2))
#: the yaw noise per turn rate, a4 ((rad/s)^2 per (rad/s)^2 per dt_ref), tried after the rounds (half-decade steps,
#: 1e-4 to 1) where above the windows' a4: the likeliest replaces it. The long windows see less yaw error than a
#: robot's turns accumulate when its controller steers against its heading errors (a waypoint follower turns back
#: what the noise turned), and gave a4 half the truth or less on the simulated robot 'noisy'; the filters add the
#: noise step by step and need all of it. Below the windows' value the likelihood is not followed: on short runs it
#: fell to the grid's least and the filters grew sure of every turn (docs/slam.md, "Self-calibration")
YAW_NOISE_GRID = tuple(10.0 ** (k / 2.0) for k in range(-8, 1))
#: rad: the camera's bearing biases tried for the likeliest (steps of 0.0025 rad, up to 0.05 rad either way)
BEARING_BIAS_GRID = tuple(round(0.0025 * k, 4) for k in range(-20, 21))
#: the likeliest bias on the grid replaces the rounds' only if its negative log likelihood is lower by more than
#: this: a likelihood-ratio test at 95 % (half of chi2(1)'s 95 % point). On a short run the likelihood is flat and
#: its best bias is noise (60 s of the simulated 'noisy' robot, which has none: -0.04 rad, 1 below the rounds')
BIAS_EVIDENCE = 1.92
#: s: windows of the speed scale and the along-track noise, and of the yaw noise; a window starts every
#: length / WINDOW_OVERLAP s. Several lengths, so that the fits can tell the motion noise (whose variance grows with
#: a window's length) from the estimate's own error (the same at every length)
SHORT_WINDOWS, LONG_WINDOWS = (2.0, 4.0, 8.0), (8.0, 16.0, 32.0)
#: s: the window length of the least-data check (:func:`check_enough`)
SHORT_WINDOW = 4.0
WINDOW_OVERLAP = 8
#: a landmark's consecutive measurements farther apart than this (s) start a new track for the autocorrelation
TRACK_GAP = 3.0
#: s: the longest time between two measurements of a track whose correlation counts
MAX_LAG_S = 30
#: the measurement variances are multiplied by the errors' correlation factor (:func:`error_correlation`) to this
#: power. The factor is what a track's mean loses to the correlation; a filter also uses each measurement for the
#: pose of its moment, and with the whole factor EKF-SLAM followed the landmarks less closely than it could.
#: Chosen among 0.25, 0.5 and 1 on the simulated robots of bench/slam.py at seeds 3-6, which the benchmark does
#: not score (docs/slam.md, "Self-calibration")
CORRELATION_POWER = 0.5
#: what :meth:`FitData.of` calls the sequence in its errors
FIT_SOURCE = "self-calibration input"


@dataclass(frozen=True)
class FitData:
    """A velocity-motion sequence with known ids, as the compiled pass takes it (commands and measurements as
    logged; the calibration's corrections are applied per evaluation)."""

    stamps: np.ndarray
    controls: np.ndarray
    control_ptr: np.ndarray
    measurements: np.ndarray
    slot: np.ndarray  # (O,) landmark slot 0..n_slots-1
    measurement_ptr: np.ndarray
    initial_pose: np.ndarray
    n_slots: int
    measurement_time: np.ndarray  # (O,) s

    @classmethod
    def of(cls, sequence: SlamSequence) -> FitData:
        """The fit's view of ``sequence``, checked before any compiled pass reads it: ValueError for odometry
        motion, LogFormatError when its arrays do not fit together (shapes, pointers: :meth:`SlamSequence.validate`),
        hold NaN or inf, or hold a command no filter takes (slam.motion.check_controls: |v| m/s, |w| rad/s beyond
        slam.motion.VELOCITY_LIMIT, dt < 0 s). O(T + K + O), vectorised."""
        if sequence.motion != "velocity":
            raise ValueError("self-calibration needs velocity commands (the odometry motion model has no speed scale)")
        _check_layout(sequence)
        sequence.validate(FIT_SOURCE)
        try:
            check_controls(sequence.controls, GENERIC.motion)
        except InputError as exc:
            raise LogFormatError(f"{FIT_SOURCE}: {exc}") from None
        ids, slot = np.unique(sequence.landmark_ids, return_inverse=True)
        step = np.repeat(np.arange(len(sequence)), np.diff(sequence.measurement_ptr))
        return cls(
            stamps=sequence.stamps,
            controls=np.ascontiguousarray(sequence.controls, dtype=np.float64),
            control_ptr=np.ascontiguousarray(sequence.control_ptr, dtype=np.int64),
            measurements=np.ascontiguousarray(sequence.measurements, dtype=np.float64),
            slot=slot.astype(np.int64),
            measurement_ptr=np.ascontiguousarray(sequence.measurement_ptr, dtype=np.int64),
            initial_pose=np.asarray(sequence.initial_pose, dtype=np.float64),
            n_slots=len(ids),
            measurement_time=sequence.stamps[step],
        )


def _check_layout(sequence: SlamSequence) -> None:
    """LogFormatError unless ``sequence``'s arrays have the shapes of slam.sequence's module docstring, finite values
    (the first bad one named) and integer pointers: what :meth:`SlamSequence.validate` takes for granted."""
    for name, array, shape in (
        ("stamps", sequence.stamps, (None,)),
        ("controls", sequence.controls, (None, 3)),
        ("control_ptr", sequence.control_ptr, (None,)),
        ("measurements", sequence.measurements, (None, 2)),
        ("landmark_ids", sequence.landmark_ids, (None,)),
        ("measurement_ptr", sequence.measurement_ptr, (None,)),
        ("initial_pose", sequence.initial_pose, (3,)),
    ):
        try:
            finite_array(name, array, shape)
        except InputError as exc:
            raise LogFormatError(f"{FIT_SOURCE}: {exc}") from None
    for name, ptr in (("control_ptr", sequence.control_ptr), ("measurement_ptr", sequence.measurement_ptr)):
        kind = np.asarray(ptr).dtype
        if not np.issubdtype(kind, np.integer):
            raise LogFormatError(f"{FIT_SOURCE}: {name} must hold whole numbers (row indices), got {kind}")


@dataclass(frozen=True)
class PassResult:
    """Per measurement: d^2, log det S and the innovation (O, 2), NaN where a measurement started a landmark;
    the pose after each step (T, 3) and the final map (n_slots, 2)."""

    d2: np.ndarray
    logdet: np.ndarray
    nu: np.ndarray
    poses: np.ndarray
    landmarks: np.ndarray

    def negative_log_likelihood(self, huber: float = HUBER_D2) -> float:
        """Sum over measurements of (rho(d^2) + log det S) / 2, rho Huber's bound on d^2; +inf if not finite."""
        used = np.isfinite(self.d2)
        d2 = self.d2[used]
        rho = np.where(d2 <= huber, d2, 2.0 * np.sqrt(huber * d2) - huber)
        value = 0.5 * float(np.sum(rho + self.logdet[used]))
        return value if math.isfinite(value) else math.inf


def _corrected_inputs(
    data: FitData, calibration: Calibration
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled passes' first six arguments: ``data``'s commands and measurements with ``calibration``'s
    corrections, their index arrays and the initial pose (m, m, rad)."""
    return (
        calibration.correct_commands(data.controls),
        data.control_ptr,
        calibration.correct_measurements(data.measurements),
        data.slot,
        data.measurement_ptr,
        data.initial_pose,
    )


def _motion_arguments(motion: VelocityMotionModel) -> tuple[np.ndarray, np.ndarray, float]:
    """The velocity model as the compiled passes take it: alphas (6,), floor (2,), dt_ref (s)."""
    return np.asarray(motion.alphas, dtype=np.float64), np.asarray(motion.floor, dtype=np.float64), float(motion.dt_ref)


def likelihood_pass(data: FitData, calibration: Calibration, huber: float = HUBER_D2) -> PassResult:
    """One EKF pass over ``data`` with ``calibration``'s corrections and noise (its command delay is the data's)."""
    count = len(data.measurements)
    out = PassResult(
        np.empty(count),
        np.empty(count),
        np.empty((count, 2)),
        np.empty((len(data.stamps), 3)),
        np.empty((data.n_slots, 2)),
    )
    sensor = calibration.sensor
    ekf_likelihood_pass(
        *_corrected_inputs(data, calibration),
        data.n_slots,
        *_motion_arguments(calibration.motion),
        np.array([sensor.sigma_range, sensor.range_fraction, sensor.sigma_bearing]),
        huber,
        out.d2,
        out.logdet,
        out.nu,
        out.poses,
        out.landmarks,
    )
    return out


@dataclass(frozen=True)
class Trajectory:
    """Smoothed poses (T, 3) and their covariances (T, 3, 3) against a fixed map (n_slots, 2)."""

    poses: np.ndarray
    cov: np.ndarray
    landmarks: np.ndarray


def smoothed_poses(
    data: FitData, calibration: Calibration, landmarks: np.ndarray, huber: float = HUBER_D2
) -> Trajectory:
    """The poses of ``data`` against the fixed map ``landmarks`` (n_slots, 2), forward filtered and smoothed
    backward (slam.kernels.smooth_localisation), with ``calibration``'s corrections and noise."""
    sensor = calibration.sensor
    out = np.empty((len(data.stamps), 3))
    cov = np.empty((len(data.stamps), 3, 3))
    smooth_localisation(
        *_corrected_inputs(data, calibration),
        np.ascontiguousarray(landmarks, dtype=np.float64),
        *_motion_arguments(calibration.motion),
        np.array([sensor.sigma_range, sensor.range_fraction, sensor.sigma_bearing]),
        huber,
        out,
        cov,
    )
    return Trajectory(out, cov, landmarks)


def refit_map(data: FitData, poses: np.ndarray, calibration: Calibration, iterations: int = 5) -> np.ndarray:
    """Each landmark's position (n_slots, 2) that best explains its measurements from the given poses (T, 3):
    Gauss-Newton on the range and bearing residuals weighted by the calibration's noise, from the first
    sighting's position (NaN for a landmark never seen). The map errors then leave the residuals, which keep the
    measurements' own errors."""
    from slam.range_bearing import inverse_measurement, predict_measurement

    step = np.repeat(np.arange(len(data.stamps)), np.diff(data.measurement_ptr))
    z = calibration.correct_measurements(data.measurements)
    sensor = calibration.sensor
    weight = np.column_stack(
        [
            1.0 / (sensor.sigma_range + sensor.range_fraction * z[:, 0]) ** 2,
            np.full(len(z), 1.0 / sensor.sigma_bearing**2),
        ]
    )
    out = np.full((data.n_slots, 2), np.nan)
    for j in range(data.n_slots):
        rows = np.flatnonzero(data.slot == j)
        if len(rows) == 0:
            continue
        m = inverse_measurement(poses[step[rows[0]]], z[rows[0]])[0]
        for _ in range(iterations):
            z_hat, _, h_m = predict_measurement(poses[step[rows]], np.broadcast_to(m, (len(rows), 2)))
            nu = z[rows] - z_hat
            nu[:, 1] = wrap_angle(nu[:, 1])
            w = np.minimum(
                weight[rows], weight[rows] * HUBER_D2 / np.maximum((nu**2 * weight[rows]).sum(1, keepdims=True), 1e-12)
            )
            normal = np.einsum("nki,nk,nkj->ij", h_m, w, h_m)
            if np.linalg.cond(normal) > 1e12:
                break
            m = m + np.linalg.solve(normal, np.einsum("nki,nk,nk->i", h_m, w, nu))
        out[j] = m
    return out


# ------------------------------------------------------------------------------------------- windows


@dataclass(frozen=True)
class Windows:
    """The commanded and the estimated motion over consecutive windows of a sequence (one row per window).

    ``chord`` m: the length of the motion the commands give (speeds as logged, turns at the calibration's
    yaw-rate scale); ``along`` m: the estimated displacement projected on the commanded one; ``turn_cmd`` rad:
    the commanded yaw change (as logged); ``moving`` s: time spent moving; ``turn`` rad: the estimated yaw change;
    ``v2``, ``w2``: sum of the corrected v^2 dt ((m/s)^2 s) and w^2 dt ((rad/s)^2 s) over the window."""

    chord: np.ndarray
    along: np.ndarray
    turn_cmd: np.ndarray
    moving: np.ndarray
    turn: np.ndarray
    v2: np.ndarray
    w2: np.ndarray


def window_bounds(stamps: np.ndarray, length: float, stride: float) -> np.ndarray:
    """(first, last) step index pairs (W, 2) of windows of about ``length`` s starting every ``stride`` s."""
    starts = np.arange(stamps[0], stamps[-1] - length, stride)
    first = np.searchsorted(stamps, starts, side="left")
    last = np.searchsorted(stamps, starts + length, side="left")
    keep = last < len(stamps)
    return np.unique(np.column_stack([first[keep], last[keep]]), axis=0).reshape(-1, 2)


def measure_windows(data: FitData, poses: np.ndarray, calibration: Calibration, length: float) -> Windows:
    """The windows of ``length`` s of ``data`` (overlapping, :data:`WINDOW_OVERLAP`) against the estimated poses
    (T, 3) (see :class:`Windows`); the commands' sums and noise-free motion compiled (slam.kernels.window_commands)."""
    bounds = window_bounds(data.stamps, length, length / WINDOW_OVERLAP)
    first, last = data.control_ptr[bounds[:, 0]], data.control_ptr[bounds[:, 1]]
    keep = last > first
    bounds, first, last = bounds[keep], first[keep], last[keep]
    sums = np.empty((len(bounds), 6))
    window_commands(
        data.controls, calibration.correct_commands(data.controls), first, last, calibration.velocity_scale[1], sums
    )
    a, b = bounds[:, 0], bounds[:, 1]
    heading = np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(poses[:, 2])))])
    c, s = np.cos(poses[a, 2]), np.sin(poses[a, 2])
    dx, dy = poses[b, 0] - poses[a, 0], poses[b, 1] - poses[a, 1]
    chord = np.hypot(sums[:, 0], sums[:, 1])
    projected = (c * dx + s * dy) * sums[:, 0] + (-s * dx + c * dy) * sums[:, 1]
    along = np.where(chord > 1e-9, projected / np.maximum(chord, 1e-9), 0.0)
    return Windows(chord, along, sums[:, 2], sums[:, 3], heading[b] - heading[a], sums[:, 4], sums[:, 5])


def windows_of(data: FitData, poses: np.ndarray, calibration: Calibration, lengths: tuple[float, ...]) -> Windows:
    """The windows of every length in ``lengths`` (s) of ``data`` against the estimated poses (T, 3), one table
    (:func:`measure_windows`)."""
    parts = [measure_windows(data, poses, calibration, length) for length in lengths]
    return Windows(*(np.concatenate([getattr(part, name) for part in parts]) for name in Windows.__dataclass_fields__))


def _nonnegative_fit(columns: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Non-negative least squares of ``target`` on ``columns``, refitted once without the rows whose target
    exceeds ten times the first fit's value (windows spoiled by an estimate's jump)."""
    coefficients = nnls(columns, target)[0]
    keep = target <= 10.0 * np.maximum(columns @ coefficients, 1e-12)
    if keep.sum() >= columns.shape[1] + 2 and not keep.all():
        coefficients = nnls(columns[keep], target[keep])[0]
    return coefficients


def fit_motion(short: Windows, long: Windows, dt_ref: float) -> dict[str, float]:
    """Speed scale k_v (along-track displacement against the commanded chord), yaw-rate scale k_w and bias b_w
    (yaw change against the commanded one and the time moving), from the short windows; the motion noise by
    non-negative least squares of the squared residuals on the model's variance terms: along-track (a1, a2,
    floor_v and an intercept for the estimate's own noise) from the short windows, yaw (a3, a4, floor_w,
    intercept) from the long ones, where rotation errors that persist over a manoeuvre show. The windows come in
    several lengths (:data:`SHORT_WINDOWS`, :data:`LONG_WINDOWS`): the model's variances grow with a window's
    length and the intercept does not, which is what separates them (with one length a robot that drives at one
    speed makes them collinear, and the fit gave the noise to the intercept)."""
    moving = short.chord > 1e-3
    k_v = float(np.sum(short.along[moving] * short.chord[moving]) / max(np.sum(short.chord[moving] ** 2), 1e-12))
    design = np.column_stack([short.turn_cmd, short.moving])
    k_w, b_w = np.linalg.lstsq(design, short.turn, rcond=None)[0]
    along_error = short.along - k_v * short.chord
    columns = np.column_stack([short.v2 * dt_ref, short.w2 * dt_ref, short.moving * dt_ref, np.ones(len(short.chord))])
    a1, a2, floor_v, _ = _nonnegative_fit(columns, along_error**2)
    turn_error = long.turn - (k_w * long.turn_cmd + b_w * long.moving)
    columns = np.column_stack([long.w2 * dt_ref, long.moving * dt_ref, np.ones(len(long.turn))])
    a4, floor_w, _ = _nonnegative_fit(columns, turn_error**2)
    return {
        "k_v": k_v, "k_w": float(k_w), "b_w": float(b_w), "a1": a1, "a2": a2, "a3": 0.0, "a4": a4,
        "floor_v": floor_v, "floor_w": floor_w,
    }  # fmt: skip


# --------------------------------------------------------------------------------------------- sensor


@dataclass(frozen=True)
class Residuals:
    """Per measurement against a :class:`Trajectory`: the range as logged and as predicted (m), the corrected
    bearing (rad), the bearing residual (as logged less predicted, rad) and the range residual (corrected less
    predicted, m), the variances the trajectory's own uncertainty adds to the two residuals (H P H^T's diagonal;
    m^2, rad^2) and ``used``, whether the landmark is on the map."""

    raw_range: np.ndarray
    predicted_range: np.ndarray
    bearing: np.ndarray
    bearing_error: np.ndarray
    range_error: np.ndarray
    range_var: np.ndarray
    bearing_var: np.ndarray
    used: np.ndarray


def measurement_residuals(data: FitData, trajectory: Trajectory, calibration: Calibration) -> Residuals:
    """The :class:`Residuals` of ``data``'s measurements against ``trajectory``."""
    from slam.range_bearing import predict_measurement

    step = np.repeat(np.arange(len(data.stamps)), np.diff(data.measurement_ptr))
    corrected = calibration.correct_measurements(data.measurements)
    predicted, h_x, _ = predict_measurement(trajectory.poses[step], trajectory.landmarks[data.slot])
    added = np.einsum("nij,njk,nik->ni", h_x, trajectory.cov[step], h_x)
    used = np.isfinite(predicted).all(axis=1) & np.isfinite(added).all(axis=1)
    bearing_error = wrap_angle(data.measurements[:, 1] - predicted[:, 1])
    return Residuals(
        data.measurements[:, 0],
        predicted[:, 0],
        corrected[:, 1],
        bearing_error,
        corrected[:, 0] - predicted[:, 0],
        added[:, 0],
        added[:, 1],
        used,
    )


def fit_sensor(data: FitData, trajectory: Trajectory, calibration: Calibration) -> dict[str, float]:
    """Range calibration c2 (least squares of measured / predicted range on 1 and bearing^2; c0 is the unobservable
    scale, kept 1), bearing bias (median bearing residual), and the noise, with the trajectory's own uncertainty
    added to the squared residuals as the EM step does (E[e^2] = e^2 + H P H^T): sigma_bearing from the bearing's,
    sigma_range and the range fraction from non-negative least squares of the range's on 1 and r^2 (variance
    sigma_range^2 + (fraction r)^2, which the filters' (sigma_range + fraction r)^2 bounds); residuals beyond 5
    robust sd are left out."""
    res = measurement_residuals(data, trajectory, calibration)
    used = res.used
    ratio = res.raw_range[used] / np.maximum(res.predicted_range[used], 1e-6)
    keep = _inliers(ratio)
    design = np.column_stack([np.ones(keep.sum()), res.bearing[used][keep] ** 2])
    c0, c2 = np.linalg.lstsq(design, ratio[keep], rcond=None)[0]
    bias = float(np.median(res.bearing_error[used]))
    centred = res.bearing_error[used] - bias
    keep = _inliers(centred)
    sigma_bearing = math.sqrt(float(np.mean(centred[keep] ** 2 + res.bearing_var[used][keep])))
    errors = res.range_error[used]
    keep = _inliers(errors)
    target = errors[keep] ** 2 + res.range_var[used][keep]
    columns = np.column_stack([np.ones(keep.sum()), res.predicted_range[used][keep] ** 2])
    constant, slope = nnls(columns, target)[0]
    return {
        "c2": float(c2 / c0), "bearing_bias": bias, "sigma_bearing": sigma_bearing,
        "sigma_range": math.sqrt(constant), "range_fraction": math.sqrt(slope),
    }  # fmt: skip


def _inliers(values: np.ndarray) -> np.ndarray:
    """Whether each value lies within 5 robust sd (1.4826 MAD) of the median."""
    centre = np.median(values)
    return np.abs(values - centre) <= 5.0 * 1.4826 * np.median(np.abs(values - centre)) + 1e-12


def _track_pairs(used: np.ndarray, slots: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of measurements of the same landmark in one track (broken at gaps over
    :data:`TRACK_GAP` s), at most :data:`MAX_LAG_S` s apart."""
    pairs_i, pairs_j = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for j in np.unique(slots[used]):
        index = np.flatnonzero(used & (slots == j))
        cuts = np.flatnonzero(np.diff(times[index]) > TRACK_GAP) + 1
        for track in np.split(index, cuts):
            a, b = np.triu_indices(len(track), k=1)
            pairs_i.append(track[a])
            pairs_j.append(track[b])
    first, second = np.concatenate(pairs_i), np.concatenate(pairs_j)
    near = times[second] - times[first] <= MAX_LAG_S
    return first[near], second[near]


def _cross_pairs(used: np.ndarray, slots: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j) of measurements of different landmarks at most :data:`MAX_LAG_S` s apart (the
    measurements are in time order)."""
    pairs_i, pairs_j = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for offset in range(1, len(times)):
        i = np.arange(len(times) - offset)
        keep = (
            (times[i + offset] - times[i] <= MAX_LAG_S) & (slots[i] != slots[i + offset]) & used[i] & used[i + offset]
        )
        if not (times[i + offset] - times[i] <= MAX_LAG_S).any():
            break
        pairs_i.append(i[keep])
        pairs_j.append(i[keep] + offset)
    return np.concatenate(pairs_i), np.concatenate(pairs_j)


def _lag_correlation(u: np.ndarray, first: np.ndarray, second: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The pooled correlation of ``u`` over pairs, per 1 s bin of the time between them (0 where under 30 pairs)."""
    lag = (times[second] - times[first]).astype(np.int64)
    product = np.bincount(lag, u[first] * u[second], minlength=MAX_LAG_S + 1)[: MAX_LAG_S + 1]
    count = np.bincount(lag, minlength=MAX_LAG_S + 1)[: MAX_LAG_S + 1]
    return np.where(count >= 30, product / np.maximum(count, 1) / float(np.mean(u**2)), 0.0)


def error_correlation(data: FitData, trajectory: Trajectory, calibration: Calibration) -> tuple[float, float]:
    """How many measurements carry one measurement's worth of independent information, for range and bearing:
    1 + the mean over measurements of the summed correlation with the other measurements of the same landmark's
    track (tracks broken at gaps over :data:`TRACK_GAP` s). The correlation is a function of the time between two
    measurements, pooled over all pairs in 1 s bins up to :data:`MAX_LAG_S` and counted while positive, less the
    correlation of measurements of different landmarks at that time apart: that part is the estimated
    trajectory's own error, which every landmark sees, not the measurements'. 1 for white errors."""
    res = measurement_residuals(data, trajectory, calibration)
    used, sensor = res.used, calibration.sensor
    scaled = np.column_stack(
        [
            res.range_error / (sensor.sigma_range + sensor.range_fraction * res.predicted_range),
            wrap_angle(res.bearing_error - calibration.bearing_bias) / sensor.sigma_bearing,
        ]
    )
    times, slots = data.measurement_time, data.slot
    first, second = _track_pairs(used, slots, times)
    if len(first) == 0:
        return 1.0, 1.0
    across = _cross_pairs(used, slots, times)
    lag = (times[second] - times[first]).astype(np.int64)
    out = []
    for component in (0, 1):
        u = np.where(used, np.clip(scaled[:, component] - np.median(scaled[used, component]), -4.0, 4.0), 0.0)
        rho = _lag_correlation(u, first, second, times) - np.maximum(_lag_correlation(u, *across, times), 0.0)
        positive = np.cumprod(rho > 0.0).astype(bool)  # lags up to the first that is not positive
        weight = np.where(positive[lag], rho[lag], 0.0)
        extra = np.bincount(first, weight, minlength=len(u)) + np.bincount(second, weight, minlength=len(u))
        out.append(1.0 + float(np.mean(extra[used])))
    return out[0], out[1]


# ------------------------------------------------------------------------------------------------ fit


def _estimate(data: FitData, calibration: Calibration) -> Trajectory:
    """The E-step: the map of an EKF-SLAM pass, the poses smoothed against it (with the motion noise
    :data:`SMOOTHING_MOTION_SCALE` times larger), and the map refitted to those poses."""
    smoothing = replace(calibration, motion=scaled_motion(calibration.motion, SMOOTHING_MOTION_SCALE))
    trajectory = smoothed_poses(data, smoothing, likelihood_pass(data, calibration).landmarks)
    return replace(trajectory, landmarks=refit_map(data, trajectory.poses, calibration))


def _inflated(sensor: RangeBearingModel, correlation: tuple[float, float]) -> RangeBearingModel:
    """``sensor``'s variances multiplied by the correlation factors (range, bearing) to :data:`CORRELATION_POWER`."""
    root_r, root_b = (math.sqrt(factor**CORRELATION_POWER) for factor in correlation)
    return RangeBearingModel(
        sigma_range=max(sensor.sigma_range * root_r, 1e-3),
        sigma_bearing=max(sensor.sigma_bearing * root_b, 1e-3),
        range_fraction=sensor.range_fraction * root_r,
    )


def _em_step(data: FitData, calibration: Calibration, delay: float) -> tuple[Calibration, RangeBearingModel, dict]:
    """One iteration of the fit against the E-step's estimate: the calibration (measurement noise inflated for
    its correlation), the measurement noise before the inflation, and the fitted values."""
    trajectory = _estimate(data, calibration)
    values = fit_motion(
        windows_of(data, trajectory.poses, calibration, SHORT_WINDOWS),
        windows_of(data, trajectory.poses, calibration, LONG_WINDOWS),
        calibration.motion.dt_ref,
    )
    values.update(fit_sensor(data, trajectory, calibration))
    check_fitted(values)
    floor = 1e-8  # keeps every motion variance positive (a zero would make the linearised filters certain)
    if values["a2"] == 0.0 and values["floor_v"] == 0.0:
        # (no position noise at all on a turn on the spot is what the fit cannot tell from a little: the generic a2)
        values["a2"] = GENERIC.motion.alphas[1]
    white = RangeBearingModel(
        max(values["sigma_range"], 1e-3), max(values["sigma_bearing"], 1e-3), values["range_fraction"]
    )
    fitted = replace(
        calibration,
        command_delay=delay,
        velocity_scale=(values["k_v"], values["k_w"]),
        velocity_bias=(0.0, values["b_w"]),
        range_calibration=(1.0, values["c2"]),
        bearing_bias=values["bearing_bias"],
        motion=VelocityMotionModel(
            alphas=(values["a1"] + floor, values["a2"], 0.0, values["a4"] + floor, 0.0, 0.0),
            dt_ref=calibration.motion.dt_ref,
            floor=(values["floor_v"] + floor, values["floor_w"] + floor),
        ),
        sensor=white,
    )
    correlation = error_correlation(data, trajectory, fitted)
    fitted = replace(fitted, sensor=_inflated(white, correlation))
    floored = _likeliest_floor(data, fitted)
    floor_w = floored.motion.floor[1]
    values.update(
        delay=delay,
        range_correlation=correlation[0],
        bearing_correlation=correlation[1],
        floor_w_windows=values["floor_w"],
        floor_w=floor_w,
    )
    return floored, white, values


def likeliest(candidates: tuple[float, ...], passes: Callable[[float], PassResult]) -> float:
    """The candidate whose EKF pass (``passes(candidate)``, :func:`likelihood_pass`) has the least negative log
    likelihood; the first of equals."""
    return min(candidates, key=lambda candidate: passes(candidate).negative_log_likelihood())


def with_yaw_floor(calibration: Calibration, floor_w: float) -> Calibration:
    """``calibration`` with the motion model's yaw-rate floor set to ``floor_w`` ((rad/s)^2 per dt_ref)."""
    motion = calibration.motion
    return replace(calibration, motion=replace(motion, floor=(motion.floor[0], floor_w)))


def with_yaw_noise(calibration: Calibration, a4: float) -> Calibration:
    """``calibration`` with the motion model's yaw noise per turn rate a4 set to ``a4`` (per dt_ref)."""
    a = calibration.motion.alphas
    return replace(calibration, motion=replace(calibration.motion, alphas=(a[0], a[1], a[2], a4, a[4], a[5])))


def _likeliest_floor(
    data: FitData, calibration: Calibration, floors: tuple[float, ...] = YAW_FLOOR_GRID
) -> Calibration:
    """``calibration`` with the yaw-rate floor of the likeliest EKF pass among ``floors``."""
    return with_yaw_floor(
        calibration, likeliest(floors, lambda f: likelihood_pass(data, with_yaw_floor(calibration, f)))
    )


def _raised(current: float, grid: tuple[float, ...]) -> tuple[float, ...]:
    """``current`` and the values of ``grid`` above it: the candidates of a noise the likelihood may only raise."""
    return (current, *(value for value in grid if value > current))


def _likeliest_bias_and_yaw_noise(data: FitData, calibration: Calibration) -> Calibration:
    """``calibration`` with the bearing bias of the likeliest EKF pass on :data:`BEARING_BIAS_GRID` where the data
    prefer it to the calibration's own (:data:`BIAS_EVIDENCE`), then the yaw-rate floor likeliest with it, then a4
    likeliest among the windows' and those of :data:`YAW_NOISE_GRID` above it, and if a4 rose the floor likeliest
    among its value and those of :data:`YAW_FLOOR_GRID` above it. The rounds' median residual cannot find the bias,
    which the smoothed estimate takes up; the innovations of a pass whose heading noise is right do. The likelihood
    may ask for less noise than the pose's error needs (innovations do not see the errors along the directions no
    measurement fixes), so it only raises a4 and the floor after it; the floor chosen with a new bias may go either
    way, as in the rounds (docs/slam.md, "Self-calibration")."""
    nll = {
        b: likelihood_pass(data, replace(calibration, bearing_bias=b)).negative_log_likelihood()
        for b in BEARING_BIAS_GRID
    }
    best = min(nll, key=nll.__getitem__)
    kept = likelihood_pass(data, calibration).negative_log_likelihood()
    if kept - nll[best] > BIAS_EVIDENCE:
        floored = _likeliest_floor(data, replace(calibration, bearing_bias=best))
    else:  # the rounds' bias: the last round chose the floor with it, on these data
        floored = calibration
    windows = floored.motion.alphas[3]
    a4 = likeliest(
        _raised(windows, YAW_NOISE_GRID), lambda value: likelihood_pass(data, with_yaw_noise(floored, value))
    )
    if a4 == windows:
        return floored
    noisier = with_yaw_noise(floored, a4)
    return _likeliest_floor(data, noisier, _raised(noisier.motion.floor[1], YAW_FLOOR_GRID))


def split_drive_and_camera(calibration: Calibration, drive_share: float = 0.5) -> Calibration:
    """``calibration`` (drive angle 0) with its bearing bias b, the camera's and the drive's disagreement, given to
    the drive (``drive_angle``) by ``drive_share`` (0, 0.5 or 1: :data:`HEADING_FRAMES`) and to the camera
    (``bearing_bias``) by the rest, and the drive angle's sd raised to b min(share, 1 - share), b / 2 for half each
    (combined with the calibration's own as independent errors): the data show only the sum."""
    b = calibration.bearing_bias
    return replace(
        calibration,
        bearing_bias=(1.0 - drive_share) * b,
        drive_angle=calibration.drive_angle + drive_share * b,
        drive_angle_sd=math.hypot(calibration.drive_angle_sd, abs(b) * min(drive_share, 1.0 - drive_share)),
    )


class NotEnoughData(ValueError):
    """The data are too short or hold too few measurements or too little motion for a fit."""


class UndeterminedParameter(NotEnoughData):
    """A fitted parameter lands outside what a calibration may hold (slam.calibration's limits, those
    load_calibration applies): the data cannot determine it. A :class:`NotEnoughData`, so that callers which fall
    back on too little data do so here too."""


#: the fitted values :func:`_em_step` checks, by its key: the calibration field named in the error, its limits, units
FITTED_LIMITS: dict[str, tuple[str, tuple[float, float], str]] = {
    "k_v": ("velocity_scale k_v (the speed scale)", SCALE_LIMITS, ""),
    "k_w": ("velocity_scale k_w (the yaw-rate scale)", SCALE_LIMITS, ""),
    "b_w": ("velocity_bias b_w (the yaw-rate bias)", VELOCITY_BIAS_LIMITS, "rad/s"),
    "c2": ("range_calibration c2 (the range's bearing term)", RANGE_C2_LIMITS, "rad^-2"),
    "bearing_bias": ("bearing_bias", BEARING_BIAS_LIMITS, "rad"),
    **{key: (f"motion noise {key}", ALPHA_LIMITS, "") for key in ("a1", "a2", "a4", "floor_v", "floor_w")},
}
#: a motion noise that grew in every round, by more than this factor in the last, ran away (:func:`check_settled`)
SETTLED_FACTOR = 2.0
#: how :class:`UndeterminedParameter` ends: why, and what to do
UNDETERMINED_ADVICE = (
    "the data cannot determine it (commands that never vary, landmarks seen from too few places): calibrate on a "
    "run that drives and turns at varied speeds past several landmarks, or give a calibration file"
)


def check_fitted(values: dict[str, float]) -> None:
    """:class:`UndeterminedParameter` naming the first of ``values`` (the rounds' fitted values, by the keys of
    :data:`FITTED_LIMITS`) that is not finite or lies outside its calibration limits."""
    for key, (field_name, limits, unit) in FITTED_LIMITS.items():
        try:
            check_within(key, values[key], limits, unit)
        except InputError:
            raise UndeterminedParameter(
                f"self-calibration: the fit gives {field_name} = {values[key]:g}{' ' + unit if unit else ''}, "
                f"outside [{limits[0]:g}, {limits[1]:g}]: {UNDETERMINED_ADVICE}"
            ) from None


def check_settled(history: list[dict[str, float]]) -> None:
    """:class:`UndeterminedParameter` when a motion noise (a1, a4) ran away: it grew in every round and by more
    than :data:`SETTLED_FACTOR` in the last (a1 2.5, 7.1, 18, 51 on a 450 s piece of an MRCLAM robot, its speed scale
    falling to 0.67: the fit found nothing the data determine, only its own estimate drifting with the noise it was
    given). Settled fits move by 0.67 to 1.08 in their last round; a noise near 0 may jump by more (a simulated
    robot's a1 0.059, 0, 0.0046, 0.038), which is no runaway."""
    if len(history) < 2:
        return
    for key in ("a1", "a4"):
        rounds = [row[key] for row in history]
        rising = all(later > earlier for earlier, later in itertools.pairwise(rounds))
        if rising and rounds[-1] > SETTLED_FACTOR * rounds[-2]:
            went = ", ".join(f"{value:.3g}" for value in rounds)
            raise UndeterminedParameter(
                f"self-calibration: the fit does not settle: motion noise {key} went {went} over its rounds: "
                f"{UNDETERMINED_ADVICE}"
            )


def check_enough(data: FitData) -> None:
    """Raise :class:`NotEnoughData`, naming what falls short, unless ``data`` holds :data:`MIN_MEASUREMENTS`
    measurements of landmarks seen more than once and :data:`MIN_WINDOWS` short windows of motion (s with a
    non-zero command)."""
    repeated = int(np.sum(np.bincount(data.slot, minlength=data.n_slots)[data.slot] > 1))
    moving = float(data.controls[(data.controls[:, 0] != 0.0) | (data.controls[:, 1] != 0.0), 2].sum())
    short = []
    if moving < MIN_WINDOWS * SHORT_WINDOW:
        short.append(f"{moving:.1f} s of motion (a non-zero command), a fit needs {MIN_WINDOWS * SHORT_WINDOW:g} s")
    if repeated < MIN_MEASUREMENTS:
        short.append(f"{repeated} measurements of landmarks seen more than once, a fit needs {MIN_MEASUREMENTS}")
    if short:
        raise NotEnoughData("; ".join(short))


@dataclass(frozen=True)
class SelfCalibration:
    """What :func:`self_calibrate` found: the calibration, and per iteration the fitted values."""

    calibration: Calibration
    iterations: list[dict[str, float]]


def _pass_at(data_at: Callable[[float], FitData], calibration: Calibration, delay: float) -> PassResult:
    """The EKF pass (:func:`likelihood_pass`) of ``calibration`` over the data with its commands ``delay`` s late."""
    return likelihood_pass(data_at(delay), calibration)


def self_calibrate(
    sequence_at: Callable[[float], SlamSequence],
    delays: tuple[float, ...] = DELAY_GRID,
    start: Calibration = GENERIC,
    iterations: int = 4,
    source: str = "",
    heading_frame: str = "unknown",
) -> SelfCalibration:
    """Fit a calibration to the sequence ``sequence_at(delay)`` (the data with its commands delayed by ``delay`` s,
    as logged otherwise; velocity commands, known ids), without ground truth.

    ``iterations`` rounds, from ``start`` at delay 0, of: the command delay of the best EKF likelihood on the grid
    ``delays``; an estimate of the trajectory and the map with the current calibration (:func:`_estimate`); and
    against it, as one would fit against ground truth, the speed scales, yaw-rate bias and motion noise over
    windows (:func:`fit_motion`), the range calibration, bearing bias and measurement noise from the residuals
    (:func:`fit_sensor`), the measurement noise inflated by the errors' correlation (:func:`error_correlation`),
    and the yaw-rate floor of the best EKF likelihood on :data:`YAW_FLOOR_GRID`. Last, the bearing bias and then
    the floor, then a4 and the floor again (both raised only), of the best likelihood
    (:func:`_likeliest_bias_and_yaw_noise`). That bias, the camera's and the drive's disagreement, is then split
    between them as ``heading_frame`` says (a key of :data:`HEADING_FRAMES`: half each when unknown).

    Raises LogFormatError when a sequence's arrays do not fit together or hold NaN or inf (:meth:`FitData.of`,
    before any compiled pass), :class:`NotEnoughData` for too little data, and :class:`UndeterminedParameter` (a
    NotEnoughData) when a fitted parameter lands outside what a calibration may hold, rather than a calibration
    that could not be used or saved."""
    if iterations < 1:
        raise ValueError(f"iterations must be at least 1, not {iterations}")
    if heading_frame not in HEADING_FRAMES:
        raise ValueError(f"heading_frame must be one of {sorted(HEADING_FRAMES)}, not {heading_frame!r}")
    cache: dict[float, FitData] = {}

    def data_at(delay: float) -> FitData:
        if delay not in cache:
            cache[delay] = FitData.of(sequence_at(delay))
        return cache[delay]

    check_enough(data_at(0.0))
    calibration = replace(
        start, command_delay=0.0, bearing_bias=start.bearing_bias + start.drive_angle, drive_angle=0.0
    )
    history: list[dict[str, float]] = []
    try:  # a Calibration refuses what its limits do not hold (the fitted noise inflated, say): the data's fault
        for _ in range(iterations):
            delay = likeliest(delays, partial(_pass_at, data_at, calibration))
            calibration, _, values = _em_step(data_at(delay), calibration, delay)
            history.append(values)
        check_settled(history)
        calibration = _likeliest_bias_and_yaw_noise(data_at(calibration.command_delay), calibration)
    except InputError as exc:
        raise UndeterminedParameter(f"self-calibration: the fit gives {exc}; {UNDETERMINED_ADVICE}") from None
    disagreement = calibration.bearing_bias
    calibration = split_drive_and_camera(calibration, HEADING_FRAMES[heading_frame])
    diagnostics = {
        "iterations": [{k: round(float(v), 6) for k, v in row.items()} for row in history],
        "final": {
            "bearing_bias": disagreement,
            "a4": calibration.motion.alphas[3],
            "floor_w": calibration.motion.floor[1],
        },
    }
    return SelfCalibration(replace(calibration, source=source, diagnostics=diagnostics), history)
