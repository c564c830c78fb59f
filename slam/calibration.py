"""What a landmark filter needs to know about one robot, as one value: corrections of its data and its noise.

A :class:`Calibration` holds

* **corrections** of the logged data: the delay from a velocity command's stamp to the robot's response
  (``command_delay``, s; applied where the commands are read, slam.mrclam, or by :class:`StepCorrector`), the
  executed velocities ``v^ = k_v v + b_v``, ``w^ = k_w w + b_w`` of a command (v m/s, w rad/s) that moves the
  robot (``velocity_scale`` (k_v, k_w) dimensionless, ``velocity_bias`` (b_v m/s, b_w rad/s)), and the landmark
  sensor's range and bearing bias: a measured (r, phi) stands for the true bearing ``phi - bearing_bias`` and
  the true range ``r / (c0 + c2 (phi - bearing_bias)^2)`` with ``range_calibration`` (c0, c2) dimensionless
  (rad^-2 for c2); and the **drive angle** (``drive_angle``, rad): the robot drives at this angle to its heading (a
  crab). The filters run in the drive's frame: they take the measured bearings less ``bearing_bias + drive_angle``,
  start at the given heading plus ``drive_angle`` and give out their heading less it;
* **noise**: the velocity motion model (slam.motion.VelocityMotionModel: alphas, floor, dt_ref) and the
  range-bearing noise (slam.range_bearing.RangeBearingModel) of the corrected data, and the known-ids outlier gate
  (a squared Mahalanobis distance, or None);
* **what no data show**, as priors the filters add to the poses they give out: the relative sd of the map's scale
  (``scale_sd``) and the sd of the drive angle (``drive_angle_sd``, rad). The data show the sum ``bearing_bias +
  drive_angle`` (how the drive and the camera disagree), never how it divides between a turned camera and a crab;
  an error e in the drive angle turns the path about its start by e (the heading given out stays right), so the
  filters add that turn's uncertainty to the positions they give out.

Named profiles (:data:`PROFILES`) hold calibrations fitted elsewhere; ``mrclam7`` is MRCLAM dataset 7's, fitted
to its ground truth (docs/slam.md). No profile is a default: data are read as logged, and without a calibration
the filters use :data:`GENERIC_MOTION` and :data:`GENERIC_SENSOR`. ``posegrid calibrate`` fits one from the data
alone (slam.selfcal) and writes it as a JSON calibration file (:func:`save_calibration`, :func:`load_calibration`;
``schema`` :data:`SCHEMA`, ``version`` :data:`VERSION`, units in the field names and in ``units``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from slam.angles import wrap_angle
from slam.errors import InputError, LogFormatError, check_within, finite_array, refuse_special_file
from slam.motion import ALPHA_LIMITS, DT_REF_LIMITS, VelocityMotionModel, check_motion_limits
from slam.range_bearing import (
    RANGE_FRACTION_LIMITS,
    SIGMA_BEARING_LIMITS,
    SIGMA_RANGE_LIMITS,
    RangeBearingModel,
    check_sensor_limits,
)
from slam.sequence import SlamSequence

SCHEMA = "posegrid.calibration"
VERSION = 1
#: chi-square(2) 0.9999: the default known-ids outlier gate (squared Mahalanobis distance)
DEFAULT_OUTLIER_GATE = 18.4207
#: motion noise the filters assume for a robot without a calibration: a1, a2, a4 and the floors chosen on simulated
#: MRCLAM-format robots of varied noise (docs/slam.md, "Calibration"); the adaptive noise (slam.consistency) scales
#: it to the data. a3, the heading noise that grows with speed ((rad/m)^2), was 0, which left a robot of 0.4-2 m/s
#: confidently wrong (the simulated office under the generic noise: EKF-SLAM's inside95 0.61 pooled over four kinds
#: of its robot at seeds 1-3, NEES 9.6); 0.003 was chosen there among 0, 0.003, 0.01 and 0.03 (0.965, NEES 3.02) and
#: gives 0.941 (NEES 3.55) at the held-out seeds 4-6, against 0.44 with 0; MRCLAM-format robots of 0.15 m/s barely
#: feel it (0.901 -> 0.905 over 51 runs)
GENERIC_MOTION = VelocityMotionModel(alphas=(0.1, 0.01, 0.003, 0.1, 0.0, 0.0), floor=(1e-4, 1e-3))
#: landmark noise the filters assume for a robot without a calibration (docs/slam.md, "Calibration")
GENERIC_SENSOR = RangeBearingModel(sigma_range=0.1, sigma_bearing=0.03, range_fraction=0.0)
#: relative sd of the map's scale when no ground truth fixed it: the data give only the ratio of the speeds to
#: the ranges, so the ranges are taken as exact in scale (c0 = 1), and an uncalibrated ranging sensor (a camera
#: judging a barcode's size, a sonar) is good to a few percent (MRCLAM dataset 7's cameras: 3.3 % long;
#: docs/slam.md). The filters spread their poses by it about the start (slam.ekf, slam.fastslam)
DEFAULT_SCALE_SD = 0.03
SCALE_SD_LIMITS = (0.0, 0.5)
#: the drive angle's sd (rad) when a calibration does not state one: none (a prior on the robot's build, which no
#: data show; docs/slam.md, "Drive angle")
DEFAULT_DRIVE_ANGLE_SD = 0.0
DRIVE_ANGLE_SD_LIMITS = (0.0, 0.5)
DRIVE_ANGLE_LIMITS = (-0.5, 0.5)
#: accepted ranges of the corrections: the delay in s, the scales, the biases (m/s, rad/s, rad) and c0, c2
DELAY_LIMITS = (0.0, 5.0)
SCALE_LIMITS = (0.1, 10.0)
VELOCITY_BIAS_LIMITS = (-1.0, 1.0)
BEARING_BIAS_LIMITS = (-0.5, 0.5)
RANGE_C0_LIMITS = (0.1, 10.0)
RANGE_C2_LIMITS = (-2.0, 2.0)
#: accepted known-ids outlier gate (squared Mahalanobis distance); None is no gate
OUTLIER_GATE_LIMITS = (1e-3, 1e6)
#: the units of every field of a calibration file, written into it
UNITS = {
    "command_delay_s": "s",
    "velocity_scale": "executed / commanded (v, w), dimensionless",
    "velocity_bias": "added to a moving command: (m/s, rad/s)",
    "range_calibration": "measured / true range = c0 + c2 bearing^2: (1, rad^-2)",
    "bearing_bias_rad": "measured - true bearing, rad",
    "motion.alphas": "velocity model a1..a6 (PR table 5.3), variances per dt_ref",
    "motion.floor": "((m/s)^2, (rad/s)^2) per dt_ref, on commands that move",
    "motion.dt_ref_s": "s",
    "sensor.sigma_range_m": "m",
    "sensor.range_fraction": "m of range std per m of range",
    "sensor.sigma_bearing_rad": "rad",
    "outlier_gate": "squared Mahalanobis distance (null: no gate)",
    "scale_sd": "relative sd of the map's scale about the start, dimensionless",
    "drive_angle_rad": "angle from the heading to the direction the robot drives in, rad",
    "drive_angle_sd_rad": "sd of the drive angle: the path's turn about its start, rad",
}


@dataclass(frozen=True)
class Calibration:
    """Corrections of a robot's logged data and the noise of the corrected data (see the module docstring)."""

    command_delay: float = 0.0
    velocity_scale: tuple[float, float] = (1.0, 1.0)
    velocity_bias: tuple[float, float] = (0.0, 0.0)
    range_calibration: tuple[float, float] = (1.0, 0.0)
    bearing_bias: float = 0.0
    drive_angle: float = 0.0
    motion: VelocityMotionModel = GENERIC_MOTION
    sensor: RangeBearingModel = GENERIC_SENSOR
    outlier_gate: float | None = DEFAULT_OUTLIER_GATE
    scale_sd: float = DEFAULT_SCALE_SD
    drive_angle_sd: float = DEFAULT_DRIVE_ANGLE_SD
    source: str = "generic defaults"
    diagnostics: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        """InputError unless every field is within the limits :func:`load_calibration` applies
        (:func:`check_calibration`): a calibration that could not be written and read back is refused here."""
        check_calibration(self)

    def correct_commands(self, controls: np.ndarray) -> np.ndarray:
        """Velocity controls (K, 3) (v m/s, w rad/s, dt s) as executed: scaled, and biased where they move."""
        out = np.array(controls, dtype=np.float64).reshape(-1, 3)
        if self.velocity_scale == (1.0, 1.0) and self.velocity_bias == (0.0, 0.0):
            return out
        moving = (out[:, 0] != 0.0) | (out[:, 1] != 0.0)
        for column in (0, 1):
            corrected = self.velocity_scale[column] * out[:, column] + self.velocity_bias[column]
            out[:, column] = np.where(moving, corrected, 0.0)
        return out

    def correct_measurements(self, measurements: np.ndarray) -> np.ndarray:
        """Landmark measurements (O, 2) (range m, bearing rad) with the bearing bias and the range calibration
        removed, the bearings in the drive's frame (less ``drive_angle`` too)."""
        out = np.array(measurements, dtype=np.float64).reshape(-1, 2)
        if self.bearing_bias != 0.0:
            out[:, 1] = wrap_angle(out[:, 1] - self.bearing_bias)
        c0, c2 = self.range_calibration
        if (c0, c2) != (1.0, 0.0):
            out[:, 0] /= c0 + c2 * out[:, 1] ** 2
        if self.drive_angle != 0.0:
            out[:, 1] = wrap_angle(out[:, 1] - self.drive_angle)
        return out

    def apply(self, sequence: SlamSequence) -> SlamSequence:
        """``sequence`` with its velocity commands and measurements corrected (the command delay is the reader's:
        slam.mrclam.mrclam_sequence). An odometry-motion sequence keeps its controls."""
        controls = self.correct_commands(sequence.controls) if sequence.motion == "velocity" else sequence.controls
        return replace(sequence, controls=controls, measurements=self.correct_measurements(sequence.measurements))

    def is_identity(self) -> bool:
        """Whether the corrections leave every command and measurement as logged."""
        return (
            self.command_delay == 0.0
            and self.velocity_scale == (1.0, 1.0)
            and self.velocity_bias == (0.0, 0.0)
            and self.range_calibration == (1.0, 0.0)
            and self.bearing_bias == 0.0
            and self.drive_angle == 0.0
        )

    def summary(self) -> str:
        """The calibration in one line (units as in :data:`UNITS`)."""
        motion, sensor = self.motion, self.sensor
        return (
            f"command delay {self.command_delay:g} s, speed scale v {self.velocity_scale[0]:.3f} w "
            f"{self.velocity_scale[1]:.3f}, yaw-rate bias {self.velocity_bias[1]:.4f} rad/s, range c0 "
            f"{self.range_calibration[0]:.3f} c2 {self.range_calibration[1]:.3f}, bearing bias {self.bearing_bias:.4f} "
            f"rad, alphas ({', '.join(f'{a:.3g}' for a in motion.alphas)}), floor ({motion.floor[0]:.3g}, "
            f"{motion.floor[1]:.3g}), range sd {sensor.sigma_range:.3g} m + {sensor.range_fraction:.3g} r, bearing sd "
            f"{sensor.sigma_bearing:.3g} rad, map scale sd {self.scale_sd:g}"
            + (f", drive angle {self.drive_angle:.4f} rad" if self.drive_angle != 0.0 else "")
            + (f", drive angle sd {self.drive_angle_sd:.4f} rad" if self.drive_angle_sd > 0.0 else "")
        )

    def step_corrector(self) -> StepCorrector:
        """A :class:`StepCorrector` applying these corrections, the command delay included, to a live stream."""
        return StepCorrector(self)


def _check_pair(name: str, value: object, limits: tuple[tuple[float, float], tuple[float, float]], unit: str) -> None:
    """InputError unless ``value`` is two finite numbers, the k-th within ``limits[k]`` (in ``unit``)."""
    pair = finite_array(name, value, (2,))
    for k in (0, 1):
        check_within(f"{name}[{k}]", pair[k], limits[k], unit)


def check_calibration(calibration: Calibration) -> None:
    """InputError naming the field unless ``calibration`` holds what a calibration file may: the corrections, the
    noise models and the priors within the limits :func:`calibration_from_json` applies (this module's
    ``*_LIMITS``, slam.motion's and slam.range_bearing's). O(1); run by :class:`Calibration` itself."""
    c = calibration
    try:
        check_within("Calibration.command_delay", c.command_delay, DELAY_LIMITS, "s")
        _check_pair("Calibration.velocity_scale", c.velocity_scale, (SCALE_LIMITS, SCALE_LIMITS), "")
        _check_pair(
            "Calibration.velocity_bias", c.velocity_bias, (VELOCITY_BIAS_LIMITS, VELOCITY_BIAS_LIMITS), "(m/s, rad/s)"
        )
        _check_pair("Calibration.range_calibration", c.range_calibration, (RANGE_C0_LIMITS, RANGE_C2_LIMITS), "")
        check_within("Calibration.bearing_bias", c.bearing_bias, BEARING_BIAS_LIMITS, "rad")
        check_within("Calibration.drive_angle", c.drive_angle, DRIVE_ANGLE_LIMITS, "rad")
        if not isinstance(c.motion, VelocityMotionModel):
            raise InputError(f"Calibration.motion must be a VelocityMotionModel, got {type(c.motion).__name__}")
        check_motion_limits(c.motion)
        check_sensor_limits(c.sensor)
        if c.outlier_gate is not None:
            check_within("Calibration.outlier_gate", c.outlier_gate, OUTLIER_GATE_LIMITS)
        check_within("Calibration.scale_sd", c.scale_sd, SCALE_SD_LIMITS)
        check_within("Calibration.drive_angle_sd", c.drive_angle_sd, DRIVE_ANGLE_SD_LIMITS, "rad")
    except InputError as exc:
        raise InputError(
            f"{exc}: a Calibration holds only what a calibration file may (the limits load_calibration applies); "
            "give a value within them"
        ) from None
    except (TypeError, ValueError) as exc:  # a field that is no number at all
        raise InputError(f"Calibration: every correction and sd must be a number ({exc})") from None


class StepCorrector:
    """Corrects a live stream step by step, as :meth:`Calibration.apply` and the reader's command delay do offline.

    Each call takes one step's velocity controls (K, 3) (v, w, dt: pieces covering the step's time) and
    measurements (O, 2). The delay is a delay line: the commands come out ``command_delay`` s late, zero before
    the first (as slam.mrclam.mrclam_sequence holds them), cut to the same step lengths."""

    def __init__(self, calibration: Calibration):
        self.calibration = calibration
        self._queue: list[list[float]] = [[0.0, 0.0, calibration.command_delay]] if calibration.command_delay else []

    def __call__(self, controls: np.ndarray, measurements: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        controls = np.asarray(controls, dtype=np.float64).reshape(-1, 3)
        if self.calibration.command_delay > 0.0:
            controls = self._delay(controls)
        return self.calibration.correct_commands(controls), self.calibration.correct_measurements(measurements)

    def _delay(self, controls: np.ndarray) -> np.ndarray:
        """The pieces of the delayed command signal over this step's time (the sum of ``controls``' dt)."""
        self._queue.extend([float(v), float(w), float(dt)] for v, w, dt in controls)
        remaining = float(controls[:, 2].sum())
        out: list[list[float]] = []
        while remaining > 1e-12 and self._queue:
            v, w, dt = self._queue[0]
            take = min(dt, remaining)
            out.append([v, w, take])
            remaining -= take
            if dt - take > 1e-12:
                self._queue[0][2] = dt - take
            else:
                self._queue.pop(0)
        return np.array(out, dtype=np.float64).reshape(-1, 3)


#: MRCLAM dataset 7's calibration, fitted to its ground truth (all five robots; docs/slam.md, "Profile mrclam7")
MRCLAM7 = Calibration(
    command_delay=0.2,
    velocity_scale=(0.918, 0.958),
    range_calibration=(1.033, -0.46),
    motion=VelocityMotionModel((0.32, 0.086, 0.0, 0.5, 0.0, 0.0), floor=(0.0, 0.0035)),
    sensor=RangeBearingModel(sigma_range=0.05, sigma_bearing=0.02, range_fraction=0.07),
    outlier_gate=DEFAULT_OUTLIER_GATE,
    scale_sd=0.0,
    source="profile mrclam7: MRCLAM dataset 7, fitted to the ground truth of robots 1-5 (docs/slam.md)",
)
#: named calibrations (``--profile NAME``)
PROFILES = {"mrclam7": MRCLAM7}
#: the calibration the filters use when none is given
GENERIC = Calibration()


# ------------------------------------------------------------------------------------------------- files


def calibration_to_json(calibration: Calibration) -> dict[str, Any]:
    """The JSON document of a calibration file (see :data:`UNITS` for every field's units)."""
    motion, sensor = calibration.motion, calibration.sensor
    return {
        "schema": SCHEMA,
        "version": VERSION,
        "source": calibration.source,
        "units": UNITS,
        "command_delay_s": calibration.command_delay,
        "velocity_scale": list(calibration.velocity_scale),
        "velocity_bias": list(calibration.velocity_bias),
        "range_calibration": list(calibration.range_calibration),
        "bearing_bias_rad": calibration.bearing_bias,
        "drive_angle_rad": calibration.drive_angle,
        "motion": {
            "model": "velocity",
            "alphas": list(motion.alphas),
            "floor": list(motion.floor),
            "dt_ref_s": motion.dt_ref,
        },
        "sensor": {
            "sigma_range_m": sensor.sigma_range,
            "range_fraction": sensor.range_fraction,
            "sigma_bearing_rad": sensor.sigma_bearing,
        },
        "outlier_gate": calibration.outlier_gate,
        "scale_sd": calibration.scale_sd,
        "drive_angle_sd_rad": calibration.drive_angle_sd,
        "diagnostics": calibration.diagnostics,
    }


def calibration_text(calibration: Calibration, path: str | Path) -> str:
    """``calibration`` as the text of a JSON calibration file to be written at ``path`` (named in errors);
    InputError when the file would not read back (:func:`load_calibration`): a field out of its limits, diagnostics
    that are no JSON."""
    check_calibration(calibration)
    try:
        text = json.dumps(calibration_to_json(calibration), indent=2) + "\n"
        calibration_from_json(json.loads(text), str(path))
    except (TypeError, ValueError) as exc:  # json's TypeError for an object it cannot write; LogFormatError
        raise InputError(f"{path}: not written, the calibration would not read back: {exc}") from None
    return text


def save_calibration(path: str | Path, calibration: Calibration) -> None:
    """Write ``calibration`` as a JSON calibration file (:func:`calibration_text`; nothing written when it would
    not read back). A plain write: `posegrid calibrate` writes the same text through a temporary file
    (schemas.files.write_atomically), so that a failed write leaves the old file."""
    Path(path).write_text(calibration_text(calibration, path), encoding="utf-8")


#: :meth:`_Reader.number`: read the value from the document
_FROM_FILE = object()


class _Reader:
    """Reads the fields of one calibration document, raising LogFormatError naming the file and the field."""

    def __init__(self, name: str, document: dict[str, Any]):
        self.name = name
        self.document = document

    def fail(self, key: str, what: str) -> LogFormatError:
        return LogFormatError(f"{self.name}: '{key}' {what}")

    def get(self, key: str) -> Any:
        node: Any = self.document
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                raise self.fail(key, "is missing")
            node = node[part]
        return node

    def number(self, key: str, limits: tuple[float, float], value: Any = _FROM_FILE) -> float:
        """The number at ``key`` (or ``value``, an element of the list there), within ``limits``."""
        value = self.get(key) if value is _FROM_FILE else value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"must be a finite number, got {value!r}")
        if not limits[0] <= value <= limits[1]:
            raise self.fail(key, f"must be in [{limits[0]:g}, {limits[1]:g}], got {value:g}")
        return float(value)

    def optional(self, key: str, limits: tuple[float, float], default: float) -> float:
        """The number at top-level ``key`` within ``limits``, or ``default`` when the document has none (files
        written before the field was added)."""
        return self.number(key, limits) if key in self.document else default

    def numbers(self, key: str, limits: list[tuple[float, float]]) -> tuple[float, ...]:
        """A list of numbers, the k-th within ``limits[k]``."""
        values = self.get(key)
        if not isinstance(values, list) or len(values) != len(limits):
            raise self.fail(key, f"must be a list of {len(limits)} numbers, got {values!r}")
        return tuple(self.number(key, low_high, v) for v, low_high in zip(values, limits))


def calibration_from_json(document: Any, name: str = "calibration") -> Calibration:
    """The calibration a JSON document holds; LogFormatError (naming ``name`` and the field) when it is none."""
    if not isinstance(document, dict) or document.get("schema") != SCHEMA:
        raise LogFormatError(f'{name}: not a posegrid calibration file (no "schema": "{SCHEMA}")')
    if document.get("version") != VERSION:
        raise LogFormatError(
            f"{name}: calibration version {document.get('version')!r} is not supported (reads {VERSION})"
        )
    read = _Reader(name, document)
    if read.get("motion.model") != "velocity":
        raise read.fail("motion.model", f'must be "velocity", got {read.get("motion.model")!r}')
    gate = read.get("outlier_gate")
    kv, kw = read.numbers("velocity_scale", [SCALE_LIMITS] * 2)
    bv, bw = read.numbers("velocity_bias", [VELOCITY_BIAS_LIMITS] * 2)
    c0, c2 = read.numbers("range_calibration", [RANGE_C0_LIMITS, RANGE_C2_LIMITS])
    alphas = read.numbers("motion.alphas", [ALPHA_LIMITS] * 6)
    floor = read.numbers("motion.floor", [ALPHA_LIMITS] * 2)
    source = read.get("source")
    diagnostics = document.get("diagnostics", {})
    return Calibration(
        command_delay=read.number("command_delay_s", DELAY_LIMITS),
        velocity_scale=(kv, kw),
        velocity_bias=(bv, bw),
        range_calibration=(c0, c2),
        bearing_bias=read.number("bearing_bias_rad", BEARING_BIAS_LIMITS),
        drive_angle=read.optional("drive_angle_rad", DRIVE_ANGLE_LIMITS, 0.0),
        motion=VelocityMotionModel(
            alphas=(alphas[0], alphas[1], alphas[2], alphas[3], alphas[4], alphas[5]),
            dt_ref=read.number("motion.dt_ref_s", DT_REF_LIMITS),
            floor=(floor[0], floor[1]),
        ),
        sensor=RangeBearingModel(
            sigma_range=read.number("sensor.sigma_range_m", SIGMA_RANGE_LIMITS),
            sigma_bearing=read.number("sensor.sigma_bearing_rad", SIGMA_BEARING_LIMITS),
            range_fraction=read.number("sensor.range_fraction", RANGE_FRACTION_LIMITS),
        ),
        outlier_gate=None if gate is None else read.number("outlier_gate", OUTLIER_GATE_LIMITS),
        scale_sd=read.number("scale_sd", SCALE_SD_LIMITS),
        drive_angle_sd=read.optional("drive_angle_sd_rad", DRIVE_ANGLE_SD_LIMITS, DEFAULT_DRIVE_ANGLE_SD),
        source=source if isinstance(source, str) else str(source),
        diagnostics=diagnostics if isinstance(diagnostics, dict) else {},
    )


def load_calibration(path: str | Path) -> Calibration:
    """Read a JSON calibration file; LogFormatError naming the file (and field) when it cannot be used."""
    path = Path(path)
    refuse_special_file(path, "calibration file")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise LogFormatError(f"{path}: no such calibration file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LogFormatError(f"{path}: cannot be read as a calibration file ({exc})") from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise LogFormatError(f"{path}: not JSON (line {exc.lineno}: {exc.msg})") from None
    except RecursionError:
        raise LogFormatError(f"{path}: not a calibration file (its JSON is nested too deeply to read)") from None
    return calibration_from_json(document, str(path))


def named_calibration(profile: str | None, path: str | Path | None) -> Calibration | None:
    """The calibration of ``--profile NAME`` or ``--calibration FILE`` (at most one given), None for neither."""
    if profile is not None and path is not None:
        raise LogFormatError("give --profile or --calibration, not both")
    if profile is not None:
        if profile not in PROFILES:
            raise LogFormatError(f"no calibration profile '{profile}' (profiles: {', '.join(sorted(PROFILES))})")
        return PROFILES[profile]
    return None if path is None else load_calibration(path)
