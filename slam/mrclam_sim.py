"""Simulated robots in the MRCLAM file format: a chosen command delay, speed scale and bias, range and bearing bias
and noise, so that calibration and consistency can be checked against a known truth.

A robot drives among ``landmarks`` point landmarks in an ``arena`` (m) to random waypoints, turning on the spot
towards each (at ``turn_rate`` rad/s) and driving at ``speed`` m/s, with pauses. It logs its velocity commands every
``command_period`` s. The robot executes each command ``truth.command_delay`` s late, as ``truth.correct_commands``
makes it (scale, and bias while it moves), with the noise of ``truth.motion`` (a velocity motion model sampled every
``SIM_DT`` s), moving at ``drive_angle`` rad to its heading (a crab: an axle not square to the body; the heading is
the body's, which the camera and the ground truth share). A camera every ``frame_period`` s (+-30 %) sees each
landmark within ``max_range`` m and ``fov`` / 2 rad of the heading with probability ``detection``, and logs range
``r (c0 + c2 b^2) + e_r`` and bearing ``b + bearing_bias + e_b`` (``truth.range_calibration``,
``truth.bearing_bias``), with e_r, e_b of ``truth.sensor``'s noise, white or, with ``error_time`` > 0 s, correlated
in time per landmark (AR(1), correlation exp(-dt / error_time)). Ground truth is logged at every command stamp.
:func:`write_mrclam_folder` writes Barcodes.dat, Landmark_Groundtruth.dat and Robot1_*.dat.

The same arguments give the same run (one seeded generator per noise source).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.angles import wrap_angle
from slam.calibration import Calibration

#: s between the simulated motion's noise draws (the commands are held over several)
SIM_DT = 0.005
#: barcodes of subjects 1-5 (robots) and of the landmarks that follow them, as in MRCLAM's Barcodes.dat
ROBOT_BARCODES = (5, 14, 41, 32, 23)
FIRST_LANDMARK_BARCODE = 50
#: m: landmarks keep this far from each other, waypoints this far from the arena's edge
LANDMARK_SPACING = 1.0
WAYPOINT_MARGIN = 1.0


@dataclass(frozen=True)
class SimRobotRun:
    """A simulated MRCLAM-format run (times in s from ``start``, poses x m, y m, yaw rad)."""

    odometry: np.ndarray  # (K, 3): stamp, commanded v m/s, commanded w rad/s
    groundtruth: np.ndarray  # (K, 4): stamp, x, y, yaw
    measurements: np.ndarray  # (M, 4): stamp, landmark subject, range m, bearing rad (as measured)
    landmarks: np.ndarray  # (L, 3): subject, x, y
    truth: Calibration


def _landmark_positions(count: int, arena: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """``count`` points (L, 2) m in the arena, at least LANDMARK_SPACING apart (rejection sampling)."""
    points: list[np.ndarray] = []
    while len(points) < count:
        candidate = rng.uniform((0.3, 0.3), (arena[0] - 0.3, arena[1] - 0.3))
        if all(np.hypot(*(candidate - p)) >= LANDMARK_SPACING for p in points):
            points.append(candidate)
    return np.array(points)


class _Driver:
    """The waypoint follower: a command (v m/s, w rad/s) from the true pose at each command stamp."""

    def __init__(self, arena, speed, turn_rate, rng):
        self.arena, self.speed, self.turn_rate, self.rng = arena, speed, turn_rate, rng
        self.target = self._waypoint()
        self.pause_until = -1.0

    def _waypoint(self) -> np.ndarray:
        return self.rng.uniform(
            (WAYPOINT_MARGIN,) * 2, (self.arena[0] - WAYPOINT_MARGIN, self.arena[1] - WAYPOINT_MARGIN)
        )

    def command(self, t: float, pose: np.ndarray) -> tuple[float, float]:
        if t < self.pause_until:
            return 0.0, 0.0
        dx, dy = self.target - pose[:2]
        if math.hypot(dx, dy) < 0.3:
            self.target = self._waypoint()
            if self.rng.uniform() < 0.3:
                self.pause_until = t + self.rng.uniform(2.0, 5.0)
            return 0.0, 0.0
        error = float(wrap_angle(math.atan2(dy, dx) - pose[2]))
        if abs(error) > 0.3:  # turn on the spot first
            return 0.0, math.copysign(self.turn_rate, error)
        return self.speed, float(np.clip(1.5 * error, -0.5 * self.turn_rate, 0.5 * self.turn_rate))


def _drive(duration, command_period, start_pose, truth: Calibration, driver: _Driver, rng, drive_angle: float = 0.0):
    """Command stamps (K,), commands (K, 2) and true poses (K, 3) at the stamps; the robot moves at ``drive_angle``
    rad to its heading."""
    count = int(duration / command_period) + 1
    stamps = np.arange(count) * command_period
    commands = np.zeros((count, 2))
    poses = np.zeros((count, 3))
    pose = np.array(start_pose, dtype=np.float64)
    t, k = 0.0, 0
    per_command = max(1, int(round(command_period / SIM_DT)))
    fine = command_period / per_command
    delay_steps = int(round(truth.command_delay / fine))
    executed: list[tuple[float, float]] = [(0.0, 0.0)] * delay_steps  # the command line, delay_steps fine steps long
    normals = rng.standard_normal((count, per_command, 3))
    for k in range(count):
        poses[k] = pose
        commands[k] = driver.command(t, pose)
        for i in range(per_command):
            executed.append((commands[k, 0], commands[k, 1]))
            v, w = executed.pop(0)
            if v != 0.0 or w != 0.0:
                pose = _move(pose, truth, v, w, fine, normals[k, i], drive_angle)
            t += fine
    return stamps, commands, poses


def _move(
    pose: np.ndarray, truth: Calibration, v: float, w: float, dt: float, normal: np.ndarray, drive_angle: float = 0.0
) -> np.ndarray:
    """``pose`` moved for ``dt`` s by the command (v, w) as the robot executes it (truth.correct_commands) with the
    velocity model's noise (truth.motion), given standard normal draws (3,): slam.motion.VelocityMotionModel.sample
    for one pose, in scalars, its chord turned by ``drive_angle`` rad from the heading."""
    v_true = truth.velocity_scale[0] * v + truth.velocity_bias[0]
    w_true = truth.velocity_scale[1] * w + truth.velocity_bias[1]
    sd = np.sqrt(truth.motion.velocity_variances(v_true, w_true, dt))
    v_true, w_true, gamma = v_true + normal[0] * sd[0], w_true + normal[1] * sd[1], normal[2] * sd[2]
    half = w_true * dt / 2.0
    dist = v_true * dt * (math.sin(half) / half if half != 0.0 else 1.0)
    heading = pose[2] + half
    if drive_angle != 0.0:
        heading += drive_angle
    return np.array(
        [
            pose[0] + dist * math.cos(heading),
            pose[1] + dist * math.sin(heading),
            wrap_angle(pose[2] + (w_true + gamma) * dt),
        ]
    )


def _camera(stamps, poses, landmarks, truth: Calibration, options: dict, rng) -> np.ndarray:
    """Measurements (M, 4): frame stamp, landmark index, measured range m, measured bearing rad."""
    frames, t = [], 0.5
    while t < stamps[-1]:
        frames.append(t)
        t += options["frame_period"] * rng.uniform(0.7, 1.3)
    frame_t = np.array(frames)
    index = np.minimum(np.searchsorted(stamps, frame_t), len(stamps) - 1)
    pose = poses[index]
    dx = landmarks[None, :, 0] - pose[:, None, 0]
    dy = landmarks[None, :, 1] - pose[:, None, 1]
    r, b = np.hypot(dx, dy), wrap_angle(np.arctan2(dy, dx) - pose[:, None, 2])
    visible = (r >= 0.3) & (r <= options["max_range"]) & (np.abs(b) <= options["fov"] / 2)
    visible &= rng.uniform(size=visible.shape) < options["detection"]
    frame, which = np.nonzero(visible)
    r, b = r[frame, which], b[frame, which]
    noise = _measurement_noise(frame_t[frame], which, rng, options["error_time"])
    sensor = truth.sensor
    c0, c2 = truth.range_calibration
    ranges = r * (c0 + c2 * b**2) + noise[:, 0] * (sensor.sigma_range + sensor.range_fraction * r)
    bearings = wrap_angle(b + truth.bearing_bias + noise[:, 1] * sensor.sigma_bearing)
    return np.column_stack([stamps[index[frame]], which, np.abs(ranges), bearings])


def _measurement_noise(times: np.ndarray, which: np.ndarray, rng, error_time: float) -> np.ndarray:
    """Standard normal errors (M, 2) per measurement: white, or AR(1) in time per landmark (``error_time`` s)."""
    white = rng.standard_normal((len(times), 2))
    if error_time <= 0.0:
        return white
    out = np.empty_like(white)
    last: dict[int, tuple[float, np.ndarray]] = {}
    for m in range(len(times)):
        previous = last.get(int(which[m]))
        if previous is None:
            out[m] = white[m]
        else:
            rho = math.exp(-(times[m] - previous[0]) / error_time)
            out[m] = rho * previous[1] + math.sqrt(1.0 - rho * rho) * white[m]
        last[int(which[m])] = (times[m], out[m])
    return out


def simulate_mrclam_robot(
    truth: Calibration,
    seed: int = 0,
    duration: float = 300.0,
    landmarks: int = 15,
    arena: tuple[float, float] = (15.0, 8.0),
    speed: float = 0.15,
    turn_rate: float = 0.8,
    command_period: float = 0.015,
    frame_period: float = 0.3,
    max_range: float = 7.0,
    fov: float = 1.1,
    detection: float = 0.7,
    error_time: float = 0.0,
    start: float = 1000.0,
    drive_angle: float = 0.0,
) -> SimRobotRun:
    """Simulate one robot for ``duration`` s (see the module docstring for every argument's meaning)."""
    drive_rng, motion_rng, camera_rng, map_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    points = _landmark_positions(landmarks, arena, map_rng)
    start_pose = np.array(
        [*map_rng.uniform((2.0, 2.0), (arena[0] - 2.0, arena[1] - 2.0)), map_rng.uniform(-np.pi, np.pi)]
    )
    driver = _Driver(arena, speed, turn_rate, drive_rng)
    stamps, commands, poses = _drive(duration, command_period, start_pose, truth, driver, motion_rng, drive_angle)
    options = {
        "frame_period": frame_period,
        "max_range": max_range,
        "fov": fov,
        "detection": detection,
        "error_time": error_time,
    }
    seen = _camera(stamps, poses, points, truth, options, camera_rng)
    subjects = np.arange(6, 6 + landmarks)
    measurements = np.column_stack([seen[:, 0] + start, subjects[seen[:, 1].astype(int)], seen[:, 2:4]])
    return SimRobotRun(
        odometry=np.column_stack([stamps + start, commands]),
        groundtruth=np.column_stack([stamps + start, poses]),
        measurements=measurements,
        landmarks=np.column_stack([subjects, points]),
        truth=truth,
    )


def _write_table(path: Path, what: str, columns: str, rows: np.ndarray, formats: tuple[str, ...]) -> None:
    header = (
        "# Simulated robot in the UTIAS MRCLAM format (posegrid slam.mrclam_sim)\r\n"
        f"# {what}\r\n# Data format:\r\n# {columns}\r\n"
    )
    lines = [" \t ".join(f % v for f, v in zip(formats, row)) + " \r\n" for row in rows]
    path.write_text(header + "".join(lines), encoding="ascii", newline="")


def write_mrclam_folder(folder: str | Path, run: SimRobotRun) -> Path:
    """Write ``run`` into ``folder`` (created if missing) as an MRCLAM dataset with one robot (robot 1)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    subjects = run.landmarks[:, 0].astype(int)
    barcode_of = {s: FIRST_LANDMARK_BARCODE + i for i, s in enumerate(subjects)}
    barcodes = [(i + 1, b) for i, b in enumerate(ROBOT_BARCODES)] + [(s, barcode_of[s]) for s in subjects]
    _write_table(folder / "Barcodes.dat", "Barcodes", "Subject #    Barcode #", np.array(barcodes), ("%d", "%d"))
    truth_rows = np.column_stack([run.landmarks, np.full((len(subjects), 2), 1e-4)])
    _write_table(
        folder / "Landmark_Groundtruth.dat",
        "Landmark Groundtruth",
        "Subject #    x [m]    y [m]    x std-dev [m]    y std-dev [m]",
        truth_rows,
        ("%d", "%.8f", "%.8f", "%.8f", "%.8f"),
    )
    time_format = "%.3f"
    _write_table(
        folder / "Robot1_Odometry.dat",
        "Odometry",
        "Time [s]    forward velocity [m/s]    angular velocity[rad/s]",
        run.odometry,
        (time_format, "%.5f", "%.5f"),
    )
    coded = run.measurements.copy()
    coded[:, 1] = [barcode_of[int(s)] for s in run.measurements[:, 1]]
    _write_table(
        folder / "Robot1_Measurement.dat",
        "Measurement",
        "Time [s]    Subject #    range [m]    bearing [rad]",
        coded,
        (time_format, "%d", "%.4f", "%.5f"),
    )
    _write_table(
        folder / "Robot1_Groundtruth.dat",
        "Robot Groundtruth",
        "Time [s]    x [m]    y [m]    orientation [rad]",
        run.groundtruth,
        (time_format, "%.6f", "%.6f", "%.6f"),
    )
    return folder
