"""Motion models of Probabilistic Robotics (Thrun, Burgard, Fox), chapter 5, vectorised over poses.

Poses are rows (x, y, theta) in the map frame (m, m, rad). A control is one row of three numbers whose
meaning depends on the model:

- :class:`VelocityMotionModel`: ``(v, w, dt)``, translational velocity (m/s), rotational velocity (rad/s)
  and the time (s) the command is held (section 5.3);
- :class:`OdometryMotionModel`: ``(delta_rot1, delta_trans, delta_rot2)`` (rad, m, rad), the relative motion
  between two odometry readings (section 5.4), as :func:`odometry_controls` computes it.

Every model offers the same three operations, each taking poses (N, 3) and one control (3,) (and ``moves``,
whether a control moves the robot at all):
``predict`` (noise-free motion), ``sample`` (one draw of the noisy motion per pose, for particle filters)
and ``linearize`` (noise-free motion with the Jacobian G = dg/dx and the process-noise covariance
Q = V M V^T in pose space, for EKFs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slam.angles import wrap_angle
from slam.errors import InputError, check_within, finite_array

#: below this odometry translation (m) a motion counts as a turn on the spot and delta_rot1 is taken as 0
MIN_TRANSLATION = 1e-6
#: accepted (low, high) of every motion-noise alpha: a variance of 1000 times the squared motion (per 0.1 s)
#: already makes the motion uninformative, and far larger ones overflow into NaN poses
ALPHA_LIMITS = (0.0, 1e3)
#: the largest |forward velocity| (m/s) and |angular velocity| (rad/s) a velocity command may hold: no ground robot
#: comes near 1000 m/s or 1000 rad/s, and commands near 1e6 made the EKF's covariance lose its positive
#: semi-definiteness (commands of 1e300 overflowed)
VELOCITY_LIMIT = 1e3
#: accepted dt_ref (s) of :class:`VelocityMotionModel`: the time its noise is stated for (the simulator's: 0.1 s)
DT_REF_LIMITS = (1e-3, 1e3)


def _check_noise(model: str, name: str, values: tuple[float, ...], count: int) -> None:
    """InputError unless ``values`` are ``count`` finite, non-negative numbers (noise variances or their factors).
    Plain Python on a handful of numbers: models are built per step by the consistency watch (scaled_motion)."""
    try:
        ok = len(values) == count and all(math.isfinite(v) and v >= 0.0 for v in values)
    except TypeError:
        ok = False
    if not ok:
        raise InputError(
            f"{model}: {name} must be {count} finite numbers >= 0 (noise variance factors), got {values!r}"
        )


def _sinc(a: np.ndarray) -> np.ndarray:
    """sin(a)/a, exact at a = 0."""
    return np.sinc(a / np.pi)


def _dsinc(a: np.ndarray) -> np.ndarray:
    """d/da of sin(a)/a, with its Taylor series near 0 where the closed form cancels."""
    small = np.abs(a) < 1e-3
    safe = np.where(small, 1.0, a)
    closed = (safe * np.cos(safe) - np.sin(safe)) / safe**2
    return np.where(small, -a / 3.0 + a**3 / 30.0, closed)


@dataclass(frozen=True)
class VelocityMotionModel:
    """The velocity motion model (PR table 5.3) with rate-independent noise.

    The executed velocities are v^ = v + e1, w^ = w + e2 and a final rotation rate g^ = e3, with zero-mean
    Gaussian e_i of variances (a1 v^2 + a2 w^2, a3 v^2 + a4 w^2, a5 v^2 + a6 w^2) * (dt_ref / dt).
    At dt = dt_ref this is exactly PR's model; the factor dt_ref/dt keeps the pose-error variance growing
    linearly in time whatever the control rate (PR's per-step noise would shrink as the rate rises).
    ``floor`` adds constant variances ((m/s)^2, (rad/s)^2, also times dt_ref/dt) to the v and w errors of
    every command that moves the robot, so that a slow creep is not taken as exact.

    alphas: (a1..a6) dimensionless (a2 in (m/rad)^2, a3 in (rad/m)^2 as PR uses them); dt_ref: s.
    """

    alphas: tuple[float, float, float, float, float, float] = (0.01, 0.0025, 0.01, 0.01, 0.001, 0.001)
    dt_ref: float = 0.1
    floor: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        """InputError for a negative or non-finite alpha or floor, or a dt_ref that is not a positive finite number
        (the limits a filter needs on top: :func:`check_motion_limits`)."""
        _check_noise("VelocityMotionModel", "alphas", self.alphas, 6)
        _check_noise("VelocityMotionModel", "floor", self.floor, 2)
        try:
            ok = math.isfinite(self.dt_ref) and self.dt_ref > 0.0
        except TypeError:
            ok = False
        if not ok:
            raise InputError(f"VelocityMotionModel: dt_ref must be a finite number of seconds > 0, got {self.dt_ref!r}")

    @staticmethod
    def moves(control: np.ndarray) -> bool:
        """Whether the control (v, w, dt) commands any motion."""
        return bool(control[0] != 0.0 or control[1] != 0.0)

    def velocity_variances(self, v: float, w: float, dt: float) -> np.ndarray:
        """Variances (3,) of the (v, w, gamma) errors, (m/s)^2 and (rad/s)^2, for a command held dt s."""
        a = self.alphas
        scale = self.dt_ref / dt if dt > 0 else 0.0
        floor_v, floor_w = self.floor if (v != 0.0 or w != 0.0) else (0.0, 0.0)
        return (
            np.array(
                [
                    a[0] * v * v + a[1] * w * w + floor_v,
                    a[2] * v * v + a[3] * w * w + floor_w,
                    a[4] * v * v + a[5] * w * w,
                ]
            )
            * scale
        )

    @staticmethod
    def _move(poses: np.ndarray, v: np.ndarray, w: np.ndarray, gamma: np.ndarray, dt: float) -> np.ndarray:
        half = w * dt / 2.0
        dist = v * dt * _sinc(half)
        heading = poses[:, 2] + half
        out = np.empty_like(poses, dtype=np.float64)
        out[:, 0] = poses[:, 0] + dist * np.cos(heading)
        out[:, 1] = poses[:, 1] + dist * np.sin(heading)
        out[:, 2] = wrap_angle(poses[:, 2] + (w + gamma) * dt)
        return out

    def predict(self, poses: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Noise-free motion of poses (N, 3) under control (v, w, dt); exact circular arcs."""
        return self.linearize(poses, control)[0]

    def sample(self, poses: np.ndarray, control: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One noisy motion per pose (PR table 5.3, sample_motion_model_velocity)."""
        v, w, dt = control
        std = np.sqrt(self.velocity_variances(v, w, dt))
        noise = rng.standard_normal((len(poses), 3)) * std
        return self._move(poses, v + noise[:, 0], w + noise[:, 1], noise[:, 2], dt)

    def linearize(self, poses: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free motion (N, 3), G = dg/dpose (N, 3, 3) and Q = V M V^T (N, 3, 3) in pose space.

        With a = w dt / 2 the motion is a chord of length v dt sin(a)/a at heading theta + a, exact for every w
        (no special case at w = 0). V = dg/d(v, w, gamma) is taken at the commanded control; M is the diagonal
        of :meth:`velocity_variances`.
        """
        v, w, dt = (float(c) for c in control)
        half = w * dt / 2.0
        s = math.sin(half) / half if half != 0.0 else 1.0
        ds = float(_dsinc(np.float64(half)))
        dist = v * dt * s
        heading = poses[:, 2] + half
        cos_h, sin_h = np.cos(heading), np.sin(heading)
        mean = np.empty_like(poses, dtype=np.float64)
        mean[:, 0] = poses[:, 0] + dist * cos_h
        mean[:, 1] = poses[:, 1] + dist * sin_h
        mean[:, 2] = wrap_angle(poses[:, 2] + w * dt)
        n = len(poses)
        jac_g = np.zeros((n, 3, 3))
        jac_g[:, 0, 0] = jac_g[:, 1, 1] = jac_g[:, 2, 2] = 1.0
        jac_g[:, 0, 2] = -dist * sin_h
        jac_g[:, 1, 2] = dist * cos_h
        jac_v = np.zeros((n, 3, 3))
        jac_v[:, 0, 0] = dt * s * cos_h
        jac_v[:, 1, 0] = dt * s * sin_h
        jac_v[:, 0, 1] = (v * dt * ds * cos_h - dist * sin_h) * (dt / 2.0)
        jac_v[:, 1, 1] = (v * dt * ds * sin_h + dist * cos_h) * (dt / 2.0)
        jac_v[:, 2, 1] = dt
        jac_v[:, 2, 2] = dt
        q = (jac_v * self.velocity_variances(v, w, dt)) @ np.swapaxes(jac_v, 1, 2)
        return mean, jac_g, q


def odometry_controls(odometry: np.ndarray) -> np.ndarray:
    """Relative motions (T-1, 3) (delta_rot1 rad, delta_trans m, delta_rot2 rad) between consecutive
    odometry readings (T, 3) (x, y, theta in the robot's odometry frame), PR table 5.6 lines 2-4.

    A translation under :data:`MIN_TRANSLATION` is a turn on the spot: delta_rot1 = 0 and delta_rot2 holds
    the whole rotation. A motion backwards (the direction of travel more than pi/2 off the heading) is a negative
    delta_trans along the heading turned by |delta_rot1| <= pi/2, not a turn of about pi, a drive forwards and a
    turn back: the model's rotation noise (alpha1 delta_rot^2) would otherwise give a robot that backs up 2 mm
    0.2 rad of heading noise (alphas 0.005).
    """
    odometry = np.asarray(odometry, dtype=np.float64)
    dxy = np.diff(odometry[:, :2], axis=0)
    trans = np.hypot(dxy[:, 0], dxy[:, 1])
    rot1 = np.where(trans < MIN_TRANSLATION, 0.0, wrap_angle(np.arctan2(dxy[:, 1], dxy[:, 0]) - odometry[:-1, 2]))
    backwards = np.abs(rot1) > np.pi / 2
    rot1 = np.where(backwards, wrap_angle(rot1 - np.pi), rot1)
    trans = np.where(backwards, -trans, trans)
    rot2 = wrap_angle(np.diff(odometry[:, 2]) - rot1)
    return np.stack([rot1, trans, rot2], axis=1)


#: a travel more than this far off the heading's axis (rad; forwards or backwards) is sideways
SIDEWAYS_BEARING = math.pi / 4
#: odometry that travels sideways for more than this share of its distance is a holonomic base's (or its robot
#: frame's x axis is not the driving direction): a differential drive's travels along its heading but for slips
#: and turns on the spot (0.03 to 9.8 % on the shared laser logs, their corrected poses included)
HOLONOMIC_SHARE = 0.5


#: a filter decides on the odometry model once its odometry has travelled this far (m)
SIDEWAYS_DECIDE_DISTANCE = 2.0
#: the odometry's travel is classified stretch by stretch, each from where the last ended to where the odometry is
#: this far (m) from there: a robot standing still, whose odometry jitters by millimetres in any direction, adds
#: no travel for minutes
SIDEWAYS_STRETCH = 0.1
#: a step between two readings longer than this (m) is an odometry reset, not travel
SIDEWAYS_RESET = 5.0


class SidewaysWatch:
    """How much of the distance odometry readings (x m, y m, theta rad in the odometry frame), taken one by one,
    travel sideways: stretch by stretch (SIDEWAYS_STRETCH), a stretch whose direction lies more than
    SIDEWAYS_BEARING off the heading's axis at its start (forwards or backwards) is sideways; decided once they
    have travelled SIDEWAYS_DECIDE_DISTANCE."""

    def __init__(self) -> None:
        self.travelled = 0.0  # m
        self.sideways = 0.0  # m
        self._start: np.ndarray | None = None  # the pose the current stretch started at
        self._last: np.ndarray | None = None

    def add(self, pose: np.ndarray) -> bool | None:
        """Take the next reading (3,); :meth:`verdict` after it."""
        pose = np.asarray(pose, dtype=np.float64)
        if self._last is not None and math.hypot(*(pose[:2] - self._last[:2])) > SIDEWAYS_RESET:
            self._start = None  # (a reset: the jump is no travel)
        self._last = pose
        if self._start is None:
            self._start = pose
            return self.verdict()
        dx, dy = pose[:2] - self._start[:2]
        trans = math.hypot(dx, dy)
        if trans >= SIDEWAYS_STRETCH:
            bearing = math.atan2(dy, dx) - self._start[2]
            self.travelled += trans
            self.sideways += trans if abs(math.sin(bearing)) > math.sin(SIDEWAYS_BEARING) else 0.0
            self._start = pose
        return self.verdict()

    def restart(self) -> None:
        """Forget the current stretch (an odometry reset: the jump to the next reading is no travel)."""
        self._start = self._last = None

    def share(self) -> float:
        """The share of the distance travelled so far that was travelled sideways; 0 for none."""
        return self.sideways / self.travelled if self.travelled > 0.0 else 0.0

    def verdict(self) -> bool | None:
        """Whether the odometry travels sideways for more than HOLONOMIC_SHARE of its distance; None until it has
        travelled SIDEWAYS_DECIDE_DISTANCE."""
        if self.travelled < SIDEWAYS_DECIDE_DISTANCE:
            return None
        return self.sideways > HOLONOMIC_SHARE * self.travelled


def sideways_watch(odometry: np.ndarray) -> SidewaysWatch:
    """A :class:`SidewaysWatch` that has taken every reading of ``odometry`` (T, 3), in order."""
    watch = SidewaysWatch()
    for pose in np.asarray(odometry, dtype=np.float64):
        watch.add(pose)
    return watch


def split_odometry_motion(control: np.ndarray, pieces: int) -> np.ndarray:
    """The relative motion ``control`` (rot1 rad, trans m, rot2 rad) as ``pieces`` motions along the same straight
    line (pieces, 3): (rot1, trans / pieces, 0), (0, trans / pieces, 0), ..., (0, trans / pieces, rot2); one piece
    is the motion itself. They compose to the motion. Under the odometry model (variances quadratic in each
    reading's motion) their translation noise adds up to 1 / pieces of the whole motion's as one reading: what
    ``pieces`` readings evenly spaced along it would have. For odometry readings lost between two that arrived."""
    if pieces < 1:
        raise ValueError(f"pieces must be >= 1, got {pieces}")
    rot1, trans, rot2 = np.asarray(control, dtype=np.float64)
    out = np.zeros((pieces, 3))
    out[:, 1] = trans / pieces
    out[0, 0] = rot1
    out[-1, 2] += rot2
    return out


@dataclass(frozen=True)
class OdometryMotionModel:
    """The odometry motion model (PR table 5.6): noise on (delta_rot1, delta_trans, delta_rot2).

    Variances: rot1: a1 rot1^2 + a2 trans^2; trans: a3 trans^2 + a4 (rot1^2 + rot2^2); rot2: a1 rot2^2 + a2 trans^2.
    """

    alphas: tuple[float, float, float, float] = (0.005, 0.005, 0.005, 0.005)

    def __post_init__(self) -> None:
        """InputError for a negative or non-finite alpha (limits a filter needs: :func:`check_motion_limits`)."""
        _check_noise("OdometryMotionModel", "alphas", self.alphas, 4)

    @staticmethod
    def moves(control: np.ndarray) -> bool:
        """Whether the relative motion (rot1, trans, rot2) is not zero."""
        return bool(np.any(np.asarray(control) != 0.0))

    def motion_variances(self, control: np.ndarray) -> np.ndarray:
        """Variances (..., 3) of the errors of (delta_rot1 rad, delta_trans m, delta_rot2 rad) for controls (..., 3)."""
        control = np.asarray(control, dtype=np.float64)
        rot1, trans, rot2 = control[..., 0], control[..., 1], control[..., 2]
        a = self.alphas
        return np.stack(
            [
                a[0] * rot1**2 + a[1] * trans**2,
                a[2] * trans**2 + a[3] * (rot1**2 + rot2**2),
                a[0] * rot2**2 + a[1] * trans**2,
            ],
            axis=-1,
        )

    @staticmethod
    def _move(poses: np.ndarray, rot1: np.ndarray, trans: np.ndarray, rot2: np.ndarray) -> np.ndarray:
        heading = poses[:, 2] + rot1
        return np.stack(
            [poses[:, 0] + trans * np.cos(heading), poses[:, 1] + trans * np.sin(heading), wrap_angle(heading + rot2)],
            axis=1,
        )

    def predict(self, poses: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Noise-free motion of poses (N, 3) by the relative motion control (rot1, trans, rot2)."""
        zeros = np.zeros(len(poses))
        return self._move(poses, zeros + control[0], zeros + control[1], zeros + control[2])

    def sample(self, poses: np.ndarray, control: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One noisy motion per pose (PR table 5.6, sample_motion_model_odometry)."""
        std = np.sqrt(self.motion_variances(control))
        noisy = np.asarray(control) - rng.standard_normal((len(poses), 3)) * std
        return self._move(poses, noisy[:, 0], noisy[:, 1], noisy[:, 2])

    def linearize(self, poses: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free motion (N, 3), G = dg/dpose (N, 3, 3) and Q = V M V^T (N, 3, 3)."""
        rot1, trans, _ = control
        n = len(poses)
        heading = poses[:, 2] + rot1
        cos_h, sin_h = np.cos(heading), np.sin(heading)
        jac_g = np.zeros((n, 3, 3))
        jac_g[:, 0, 0] = jac_g[:, 1, 1] = jac_g[:, 2, 2] = 1.0
        jac_g[:, 0, 2] = -trans * sin_h
        jac_g[:, 1, 2] = trans * cos_h
        jac_v = np.zeros((n, 3, 3))
        jac_v[:, 0, 0] = -trans * sin_h
        jac_v[:, 1, 0] = trans * cos_h
        jac_v[:, 0, 1] = cos_h
        jac_v[:, 1, 1] = sin_h
        jac_v[:, 2, 0] = jac_v[:, 2, 2] = 1.0
        q = np.einsum("nij,j,nkj->nik", jac_v, self.motion_variances(control), jac_v)
        return self.predict(poses, control), jac_g, q


@dataclass(frozen=True)
class OmniOdometryMotionModel:
    """The odometry model for a base that may move in any direction (holonomic, or a robot frame whose x axis is
    not the direction the robot drives): the same relative motion (rot1, trans, rot2), whose rot1 is then only the
    bearing of the travel, not a turn the robot made, with the noise of the turn it made, rot = rot1 + rot2.

    Errors along the travel (e_t), across it (e_s) and of the heading (e_r), with variances
    t: a3 trans^2 + a4 rot^2; s: the same (no direction is preferred); r: a1 rot^2 + a2 trans^2,
    so a move sideways is as certain as a move forwards. :class:`OdometryMotionModel` gives rot1 and rot2 the
    noise of turns: a1 (pi/2)^2 each for a move sideways, 0.35 rad standard deviation apiece at alphas 0.05.
    """

    alphas: tuple[float, float, float, float] = (0.005, 0.005, 0.005, 0.005)

    moves = staticmethod(OdometryMotionModel.moves)

    def __post_init__(self) -> None:
        """InputError for a negative or non-finite alpha (limits a filter needs: :func:`check_motion_limits`)."""
        _check_noise("OmniOdometryMotionModel", "alphas", self.alphas, 4)

    def predict(self, poses: np.ndarray, control: np.ndarray) -> np.ndarray:
        """Noise-free motion of poses (N, 3) by the relative motion control (rot1, trans, rot2)."""
        return OdometryMotionModel(self.alphas).predict(poses, control)

    def travel_variances(self, control: np.ndarray) -> np.ndarray:
        """Variances (3,) of the errors along the travel (m^2), across it (m^2) and of the heading (rad^2)."""
        rot1, trans, rot2 = (float(c) for c in control)
        a, rot = self.alphas, float(wrap_angle(rot1 + rot2))  # (the turn made, within a half turn either way)
        along = a[2] * trans**2 + a[3] * rot**2
        return np.array([along, along, a[0] * rot**2 + a[1] * trans**2])

    @staticmethod
    def _travel_jacobian(poses: np.ndarray, rot1: float) -> np.ndarray:
        """d pose / d (e_t, e_s, e_r) (N, 3, 3) at the travel's bearing theta + rot1."""
        heading = poses[:, 2] + rot1
        cos_h, sin_h = np.cos(heading), np.sin(heading)
        jac = np.zeros((len(poses), 3, 3))
        jac[:, 0, 0], jac[:, 1, 0] = cos_h, sin_h
        jac[:, 0, 1], jac[:, 1, 1] = -sin_h, cos_h
        jac[:, 2, 2] = 1.0
        return jac

    def sample(self, poses: np.ndarray, control: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One noisy motion per pose: the noise-free motion plus (e_t, e_s) along and across the travel and e_r."""
        errors = rng.standard_normal((len(poses), 3)) * np.sqrt(self.travel_variances(control))
        moved = self.predict(poses, control) + np.einsum("nij,nj->ni", self._travel_jacobian(poses, control[0]), errors)
        moved[:, 2] = wrap_angle(moved[:, 2])
        return moved

    def linearize(self, poses: np.ndarray, control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise-free motion (N, 3), G = dg/dpose (N, 3, 3) (as :class:`OdometryMotionModel`'s) and Q = V M V^T
        (N, 3, 3) with V = d pose / d (e_t, e_s, e_r), M their variances."""
        mean, jac_g, _ = OdometryMotionModel(self.alphas).linearize(poses, control)
        jac_v = self._travel_jacobian(poses, control[0])
        q = np.einsum("nij,j,nkj->nik", jac_v, self.travel_variances(control), jac_v)
        return mean, jac_g, q


#: any motion model; each offers predict, sample and linearize over poses (N, 3) and one control (3,)
MotionModel = VelocityMotionModel | OdometryMotionModel | OmniOdometryMotionModel


def check_motion_limits(motion: MotionModel) -> None:
    """InputError unless ``motion`` is a motion model whose alphas (and floor) lie in :data:`ALPHA_LIMITS` and
    dt_ref (s) in :data:`DT_REF_LIMITS`: the noise a filter can use (the file readers refuse the same). The models'
    constructors refuse only negative or non-finite values, as the consistency watch scales them past these."""
    if not isinstance(motion, (VelocityMotionModel, OdometryMotionModel, OmniOdometryMotionModel)):
        raise InputError(f"motion must be a slam.motion model (velocity or odometry), got {type(motion).__name__}")
    name = type(motion).__name__
    check_within(f"{name}.alphas", motion.alphas, ALPHA_LIMITS)
    if isinstance(motion, VelocityMotionModel):
        check_within(f"{name}.floor", motion.floor, ALPHA_LIMITS)
        check_within(f"{name}.dt_ref", motion.dt_ref, DT_REF_LIMITS, "s")


def check_controls(controls: np.ndarray, motion: MotionModel) -> np.ndarray:
    """A step's controls as float64 (K, 3) (one control (3,) is a step of one; none: (0, 3)), or InputError saying
    what is wrong: a value that is not finite, or for a velocity model (v m/s, w rad/s, dt s) |v|, |w| beyond
    VELOCITY_LIMIT or dt < 0 (a step cannot go back in time). O(K), vectorised."""
    controls = np.asarray(controls, dtype=np.float64)
    controls = controls.reshape(-1, 3) if controls.size == 0 or controls.shape == (3,) else controls
    controls = finite_array("controls", controls, (None, 3), " (one row per control)")
    if isinstance(motion, VelocityMotionModel) and len(controls):
        check_within("control velocity (v m/s, w rad/s)", controls[:, :2], (-VELOCITY_LIMIT, VELOCITY_LIMIT))
        check_within(
            "control dt (the time a command is held; a step cannot go back in time)", controls[:, 2], (0.0, np.inf), "s"
        )
    return controls


def compose(poses: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """poses (N, 3) moved by the relative motion delta (3,) given in each pose's own frame (x (+) delta)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    return np.stack(
        [
            poses[:, 0] + c * delta[0] - s * delta[1],
            poses[:, 1] + s * delta[0] + c * delta[1],
            wrap_angle(poses[:, 2] + delta[2]),
        ],
        axis=1,
    )


def local_motion(motion: MotionModel, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The noise-free relative motion delta (3,) over controls (K, 3) and its linearised covariance (3, 3),
    both in the frame of the start pose.

    Every pose moves by the same delta in its own frame, and its linearised motion noise is this covariance
    rotated by its heading (:func:`rotate_covariance`): one linearisation serves all particles. The velocity
    model's runs compiled (slam.kernels.velocity_local_motion), the odometry model's through :meth:`linearize`.
    """
    if isinstance(motion, VelocityMotionModel):
        from slam.kernels import velocity_local_motion

        delta, cov = np.zeros(3), np.zeros((3, 3))
        velocity_local_motion(
            np.ascontiguousarray(controls, dtype=np.float64).reshape(-1, 3),
            np.asarray(motion.alphas, dtype=np.float64),
            np.asarray(motion.floor, dtype=np.float64),
            float(motion.dt_ref),
            delta,
            cov,
        )
        return delta, cov
    pose = np.zeros((1, 3))
    cov = np.zeros((3, 3))
    for control in controls:
        pose, jac_g, q = motion.linearize(pose, control)
        cov = jac_g[0] @ cov @ jac_g[0].T + q[0]
    return pose[0], cov


def rotate_covariance(cov: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """A pose covariance (3, 3) given in a frame of heading 0, expressed in frames of heading theta (N,) rad:
    R cov R^T with R the rotation by theta in the (x, y) block, (N, 3, 3)."""
    c, s = np.cos(theta), np.sin(theta)
    rot = np.zeros((len(theta), 3, 3))
    rot[:, 0, 0] = rot[:, 1, 1] = c
    rot[:, 0, 1] = -s
    rot[:, 1, 0] = s
    rot[:, 2, 2] = 1.0
    return rot @ cov @ np.swapaxes(rot, 1, 2)
