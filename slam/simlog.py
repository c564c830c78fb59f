"""The SLAM inputs of a simulated run and their two files in a simulator folder.

``controls.npz``: ``stamps`` (T,) s; ``commands`` (T, 2) the commanded (v m/s, w rad/s) held from step t-1 to
step t (row 0 is zeros); ``odometry`` (T, 3) the robot's odometry readings (x m, y m, yaw rad) in its own
odometry frame, which starts at (0, 0, 0); ``initial_pose`` (3,) the true pose at step 0 in the map frame
(where the filters start); ``velocity_alphas`` (6,) and ``velocity_dt_ref`` (s) of the velocity motion model
and ``odometry_alphas`` (4,) of the odometry motion model the simulator drew its noise from.

``landmarks.npz``: ``step`` (O,) int, the step of each measurement; ``id`` (O,) int landmark id (any
integer: the filters use ids as names only); ``range`` (O,) m and ``bearing`` (O,) rad (robot frame,
counter-clockwise); ``sigma_range`` (m) and ``sigma_bearing`` (rad) of the noise added; ``truth`` (L, 2) true
landmark positions in m (for scoring only).

Frames and ordering follow slam.sequence: measurements are sorted by step. The loader refuses values the
filters cannot use: alphas outside slam.motion.ALPHA_LIMITS, noise outside slam.range_bearing's limits,
``velocity_dt_ref`` outside :data:`DT_REF_LIMITS`, negative ranges, commands beyond slam.motion.VELOCITY_LIMIT,
and poses or positions beyond +-POSE_LIMIT (1e7 m; slam.laserlog).
"""

from __future__ import annotations

import math
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.errors import LogFormatError
from slam.laserlog import POSE_LIMIT
from slam.motion import (
    ALPHA_LIMITS,
    DT_REF_LIMITS,
    VELOCITY_LIMIT,
    OdometryMotionModel,
    VelocityMotionModel,
    odometry_controls,
)
from slam.range_bearing import BEARING_LIMIT, SIGMA_BEARING_LIMITS, SIGMA_RANGE_LIMITS, RangeBearingModel
from slam.sequence import SlamSequence

CONTROLS_FILE = "controls.npz"
LANDMARKS_FILE = "landmarks.npz"
#: the files `posegrid simulate` writes into its folder
SIMULATION_FILES = ("scans.npz", "truth.npz", "groundtruth.npz", CONTROLS_FILE, LANDMARKS_FILE)


@dataclass(frozen=True)
class SimLog:
    """Controls, odometry and landmark measurements of a simulated run, with the noise it was made with."""

    stamps: np.ndarray
    commands: np.ndarray
    odometry: np.ndarray
    initial_pose: np.ndarray
    landmark_step: np.ndarray
    landmark_id: np.ndarray
    landmark_z: np.ndarray  # (O, 2): range m, bearing rad
    landmark_truth: np.ndarray
    velocity_model: VelocityMotionModel
    odometry_model: OdometryMotionModel
    sensor: RangeBearingModel

    def sequence(self, motion: str = "velocity") -> SlamSequence:
        """The filters' input: one step per stamp; ``motion`` picks the controls ("velocity" or "odometry")."""
        steps = len(self.stamps)
        if motion == "velocity":
            dt = np.diff(self.stamps)
            controls = np.column_stack([self.commands[1:], dt])
        else:
            controls = odometry_controls(self.odometry)
        control_ptr = np.concatenate([[0], np.arange(steps)])
        measurement_ptr = np.searchsorted(self.landmark_step, np.arange(steps + 1), side="left")
        return SlamSequence(
            stamps=self.stamps,
            controls=controls,
            control_ptr=control_ptr,
            measurements=self.landmark_z,
            landmark_ids=self.landmark_id,
            measurement_ptr=measurement_ptr,
            initial_pose=self.initial_pose,
            motion=motion,
        )


def sim_log_arrays(log: SimLog) -> dict[str, dict[str, np.ndarray]]:
    """The arrays of ``controls.npz`` and ``landmarks.npz`` (by file name) that :func:`load_sim_log` reads back;
    `posegrid simulate` writes them (schemas.files.save_arrays) with the folder's other files."""
    controls = dict(
        stamps=log.stamps,
        commands=log.commands,
        odometry=log.odometry,
        initial_pose=log.initial_pose,
        velocity_alphas=np.array(log.velocity_model.alphas),
        velocity_dt_ref=np.float64(log.velocity_model.dt_ref),
        odometry_alphas=np.array(log.odometry_model.alphas),
    )
    landmarks = dict(
        step=log.landmark_step,
        id=log.landmark_id,
        range=log.landmark_z[:, 0],
        bearing=log.landmark_z[:, 1],
        sigma_range=np.float64(log.sensor.sigma_range),
        sigma_bearing=np.float64(log.sensor.sigma_bearing),
        truth=log.landmark_truth,
    )
    return {CONTROLS_FILE: controls, LANDMARKS_FILE: landmarks}


def _load(path: Path, shapes: dict[str, tuple]) -> dict[str, np.ndarray]:
    """Arrays of ``path`` checked against ``shapes``: an int is a fixed length, a letter a length shared by
    every array that names it, () a scalar."""
    if not path.is_file():
        raise LogFormatError(f"{path}: no such file (a simulator folder holds {CONTROLS_FILE} and {LANDMARKS_FILE})")
    arrays: dict[str, np.ndarray] | None = None  # stays None when the file holds one bare array
    try:  # as schemas.files.read_npz does, for LogFormatError: slam/ does not import schemas/ (tests/test_layers.py)
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.lib.npyio.NpzFile):
            with loaded as data:  # members are read (and inflated) here
                arrays = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, zlib.error) as exc:
        raise LogFormatError(f"{path}: not a readable .npz file ({exc})") from None
    if arrays is None:
        raise LogFormatError(f"{path}: holds one bare array (a .npy file), not the named arrays of a .npz file")
    sizes: dict[str, int] = {}
    for key, shape in shapes.items():
        if key not in arrays:
            raise LogFormatError(f"{path}: missing array '{key}'")
        value = arrays[key]
        if value.dtype.kind not in "iuf" or not np.all(np.isfinite(value)):
            raise LogFormatError(f"{path}: '{key}' must hold finite real numbers")
        if value.ndim != len(shape) or any(
            actual != (sizes.setdefault(dim, actual) if isinstance(dim, str) else dim)
            for dim, actual in zip(shape, value.shape)
        ):
            raise LogFormatError(
                f"{path}: '{key}' has shape {value.shape}, expected {shape} (letters: lengths shared by arrays)"
            )
    return arrays


def _check_within(path: Path, arrays: dict[str, np.ndarray], limits: dict[str, tuple[float, float]]) -> None:
    """Raise LogFormatError naming the file and key unless every value of arrays[key] lies in limits[key]
    (low, high), in the key's units."""
    for key, (low, high) in limits.items():
        value = arrays[key]
        if value.size and not np.all((value >= low) & (value <= high)):
            raise LogFormatError(
                f"{path}: '{key}' must lie in [{low:g}, {high:g}], but holds values from "
                f"{value.min():g} to {value.max():g}"
            )


def load_sim_log(folder: str | Path) -> SimLog:
    """Read a simulator folder's ``controls.npz`` and ``landmarks.npz``; LogFormatError if malformed."""
    folder = Path(folder)
    c = _load(
        folder / CONTROLS_FILE,
        {
            "stamps": ("T",),
            "commands": ("T", 2),
            "odometry": ("T", 3),
            "initial_pose": (3,),
            "velocity_alphas": (6,),
            "velocity_dt_ref": (),
            "odometry_alphas": (4,),
        },
    )
    m = _load(
        folder / LANDMARKS_FILE,
        {
            "step": ("O",),
            "id": ("O",),
            "range": ("O",),
            "bearing": ("O",),
            "sigma_range": (),
            "sigma_bearing": (),
            "truth": ("L", 2),
        },
    )
    steps = len(c["stamps"])
    step = m["step"].astype(np.int64)
    if steps == 0 or np.any(np.diff(c["stamps"]) <= 0):
        raise LogFormatError(f"{folder / CONTROLS_FILE}: 'stamps' must be non-empty and strictly increasing")
    if len(step) and (np.any(np.diff(step) < 0) or step[0] < 0 or step[-1] >= steps):
        raise LogFormatError(f"{folder / LANDMARKS_FILE}: 'step' must be sorted and index the {steps} steps")
    for key in ("step", "id"):
        if np.any(m[key] != np.round(m[key])):
            raise LogFormatError(f"{folder / LANDMARKS_FILE}: '{key}' must hold whole numbers")
    pose_range = (-POSE_LIMIT, POSE_LIMIT)
    _check_within(
        folder / CONTROLS_FILE,
        c,
        {
            "commands": (-VELOCITY_LIMIT, VELOCITY_LIMIT),  # (v m/s, w rad/s)
            "odometry": pose_range,
            "initial_pose": pose_range,
            "velocity_alphas": ALPHA_LIMITS,
            "velocity_dt_ref": DT_REF_LIMITS,
            "odometry_alphas": ALPHA_LIMITS,
        },
    )
    _check_within(
        folder / LANDMARKS_FILE,
        m,
        {
            "range": (0.0, POSE_LIMIT),
            "bearing": (-BEARING_LIMIT, BEARING_LIMIT),
            "sigma_range": SIGMA_RANGE_LIMITS,
            "sigma_bearing": SIGMA_BEARING_LIMITS,
            "truth": pose_range,
        },
    )
    if not abs(float(c["initial_pose"][2])) <= 2.0 * math.pi:  # (a heading of 90 deg drove every filter off)
        raise LogFormatError(
            f"{folder / CONTROLS_FILE}: 'initial_pose' yaw {float(c['initial_pose'][2]):g} is more than a full turn: "
            f"give it in rad (90 deg is {math.radians(90):.4f})"
        )
    a1, a2, a3, a4, a5, a6 = (float(a) for a in c["velocity_alphas"])  # (6,), as _load checked
    o1, o2, o3, o4 = (float(a) for a in c["odometry_alphas"])  # (4,), as _load checked
    return SimLog(
        stamps=c["stamps"].astype(np.float64),
        commands=c["commands"].astype(np.float64),
        odometry=c["odometry"].astype(np.float64),
        initial_pose=c["initial_pose"].astype(np.float64),
        landmark_step=step,
        landmark_id=m["id"].astype(np.int64),
        landmark_z=np.column_stack([m["range"], m["bearing"]]).astype(np.float64),
        landmark_truth=m["truth"].astype(np.float64),
        velocity_model=VelocityMotionModel((a1, a2, a3, a4, a5, a6), float(c["velocity_dt_ref"])),
        odometry_model=OdometryMotionModel((o1, o2, o3, o4)),
        sensor=RangeBearingModel(float(m["sigma_range"]), float(m["sigma_bearing"])),
    )
