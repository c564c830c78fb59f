"""Gaussian inverse sensor model (paper, section IV), derived in docs/sensor_model.md.

A beam that returned range z says: free before z, occupied over a peak of width l around z, unknown
beyond. Convolving that ideal model with a zero-mean Gaussian of standard deviation sigma(z) gives, for a
point at range r along the beam (a = z - l/2, b = z + l/2),

    g(r) = 1/4 + 1/4 erf((b - r) / (sqrt(2) sigma)) - 1/2 erf((a - r) / (sqrt(2) sigma))

which tends to 0 (free) before the hit, peaks near z and tends to 1/2 (unknown) beyond it.

The probability is then squeezed into a finite log-odds range so that, with the defaults, a cell in free
space gets OctoMap's miss increment logit(0.4) and the cell holding the return gets OctoMap's hit increment
logit(0.7):
    g < 1/2:   p = 1/2 - (1/2 - p_miss) (1 - 2 g)
    g >= 1/2:  p = 1/2 + (p_hit - 1/2) (g - 1/2) / (g_peak - 1/2)
with g_peak = max_r g(r) = g(r*), r* = z + sigma^2 ln2 / l, the model's maximum for this beam. p = 1/2 gives exactly 0.

Ranges in metres along the beam from the laser origin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import overload

import numpy as np

from mapping.errors import InputError
from mapping.jit import kernel

SIGMA_KINDS = ("constant", "linear", "stereo")

#: below this margin over 1/2 the model has no occupied peak
PEAK_EPS = 1e-9

#: the traversal stops this many sigma beyond the return; the model is close to 1/2 there
TAIL_SIGMAS = 3.0


@kernel()
def _erf_into(x, out):  # pragma: no cover - compiled
    """out[i] = erf(x[i]) over flat float64 arrays."""
    for i in range(x.shape[0]):
        out[i] = math.erf(x[i])


def erf(x: np.ndarray) -> np.ndarray:
    """The error function of an array, element by element (compiled: scipy.special would cost every process that
    builds a sensor model 0.3 CPU s to import)."""
    values = np.asarray(x, dtype=np.float64)
    flat = np.ascontiguousarray(values.reshape(-1))
    out = np.empty_like(flat)
    _erf_into(flat, out)
    return out.reshape(values.shape)


@overload
def logit(p: float) -> float: ...


@overload
def logit(p: np.ndarray) -> np.ndarray: ...


def logit(p: float | np.ndarray) -> float | np.ndarray:
    """log(p / (1 - p)): a float for a float, an array (same shape) for an array."""
    return np.log(p) - np.log1p(-p)


class _LogOdds:
    """A read-only attribute of the model: the log-odds (:func:`logit`) of its probability field ``field``."""

    def __init__(self, field: str) -> None:
        self.field = field

    @overload
    def __get__(self, model: None, owner: type) -> _LogOdds: ...

    @overload
    def __get__(self, model: object, owner: type | None = None) -> float: ...

    def __get__(self, model: object, owner: type | None = None) -> float | _LogOdds:
        """logit of ``model``'s field; the descriptor itself when read on the class."""
        return self if model is None else float(logit(getattr(model, self.field)))


#: the largest range noise sigma0 and peak width l, m: beyond 10 km they describe no range sensor, and their squares
#: and the erf arguments of the model leave float64's range
MAX_MODEL_LENGTH = 1e4
#: the steepest linear noise growth, m of sigma per m of range
MAX_SIGMA_SLOPE = 10.0
#: the smallest stereo b*f (m px): 1 mm baseline and 1 px focal length; below it sigma(z) = z^2/(b*f) overflows
MIN_BASELINE_FOCAL = 1e-3


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the inverse sensor model and of the log-odds scale of the map.

    resolution: grid cell size in m (the default peak width l is its diagonal).
    sigma: how the range noise grows with range z: "constant" (sigma0), "linear" (sigma0 + sigma_slope*z)
        or "stereo" (z**2 / baseline_focal, baseline b in m times focal length f in px, with ranges in m).
    peak_width: l in m, None for the cell diagonal.
    p_hit, p_miss: the probabilities a cell holding a return / a cell in free space contributes
        (OctoMap's defaults 0.7 / 0.4); p_min, p_max: the clamping range of the map (0.12 / 0.97).
    """

    resolution: float = 0.05
    sigma: str = "constant"
    sigma0: float = 0.03
    sigma_slope: float = 0.0
    baseline_focal: float = 0.0
    peak_width: float | None = None
    p_hit: float = 0.7
    p_miss: float = 0.4
    p_min: float = 0.12
    p_max: float = 0.97

    def __post_init__(self) -> None:
        if not 0 < self.resolution < math.inf:
            raise InputError(f"resolution must be > 0 m and finite, got {self.resolution}")
        if self.sigma not in SIGMA_KINDS:
            raise InputError(f"sigma must be one of {', '.join(SIGMA_KINDS)}, got {self.sigma!r}")
        if self.sigma == "stereo" and not self.baseline_focal >= MIN_BASELINE_FOCAL:
            raise InputError(
                f"the stereo sigma model needs baseline_focal (b*f) >= {MIN_BASELINE_FOCAL} m px, got "
                f"{self.baseline_focal}"
            )
        if self.sigma != "stereo" and not 0 < self.sigma0 <= MAX_MODEL_LENGTH:
            raise InputError(f"sigma0 must be > 0 m and at most {MAX_MODEL_LENGTH:g} m, got {self.sigma0}")
        if not 0 <= self.sigma_slope <= MAX_SIGMA_SLOPE:
            raise InputError(
                f"sigma_slope must be 0 to {MAX_SIGMA_SLOPE:g} (m of noise per m of range), got {self.sigma_slope}"
            )
        if self.peak_width is not None and not 0 < self.peak_width <= MAX_MODEL_LENGTH:
            raise InputError(f"peak_width must be > 0 m and at most {MAX_MODEL_LENGTH:g} m, got {self.peak_width}")
        if not (0 < self.p_min < self.p_miss < 0.5 < self.p_hit < self.p_max < 1):
            raise InputError(
                "need 0 < p_min < p_miss < 0.5 < p_hit < p_max < 1, got "
                f"p_min={self.p_min}, p_miss={self.p_miss}, p_hit={self.p_hit}, p_max={self.p_max}"
            )

    # ----------------------------------------------------------------------------------- parameters
    @property
    def l(self) -> float:  # noqa: E743 - the paper's symbol
        """Peak width l in m."""
        return self.peak_width if self.peak_width is not None else self.resolution * math.sqrt(2.0)

    #: the log-odds of p_miss, p_hit, p_min and p_max
    l_free = _LogOdds("p_miss")
    l_hit = _LogOdds("p_hit")
    l_min = _LogOdds("p_min")
    l_max = _LogOdds("p_max")

    def beam_reach(self, range_max: float) -> float:
        """How far from the laser a scan's fusion may walk a beam, m: a return just within ``range_max`` and its tail,
        TAIL_SIGMAS sigma past it, with half the peak width besides (sigma grows with the range in every model, so
        it is largest there); inf where the sigma overflows (a range no laser gives)."""
        with np.errstate(over="ignore"):
            return float(range_max + TAIL_SIGMAS * float(self.sigma_at(range_max)) + self.l / 2)

    def sigma_at(self, z: float | np.ndarray) -> float | np.ndarray:
        """Range noise sigma(z) in m."""
        z = np.asarray(z, dtype=float)
        if self.sigma == "constant":
            return np.full_like(z, self.sigma0)
        if self.sigma == "linear":
            return self.sigma0 + self.sigma_slope * z
        return np.maximum(z * z / self.baseline_focal, 1e-6)

    # ----------------------------------------------------------------------------------- the model
    def probability(self, r: float | np.ndarray, z: float | np.ndarray) -> np.ndarray:
        """g(r): the convolved ideal model at range r (m) for a return at z (m); in [0, 1]."""
        r = np.asarray(r, dtype=float)
        z = np.asarray(z, dtype=float)
        s = np.sqrt(2.0) * self.sigma_at(z)
        a = z - self.l / 2
        b = z + self.l / 2
        return 0.25 + 0.25 * erf((b - r) / s) - 0.5 * erf((a - r) / s)

    def peak_range(self, z: float | np.ndarray) -> np.ndarray:
        """r*, where g is largest: z + sigma^2 ln 2 / l (g rises before r* and falls after it).

        Setting g'(r) = 0 gives exp(-((r - a)/s)^2) = exp(-((r - b)/s)^2) / 2 with s = sqrt(2) sigma,
        whose one root is r* = z + s^2 ln 2 / (2 l).
        """
        z = np.asarray(z, dtype=float)
        return z + self.sigma_at(z) ** 2 * np.log(2.0) / self.l

    def peak(self, z: float | np.ndarray) -> np.ndarray:
        """g(r*), the model's maximum for a return at z."""
        return self.probability(self.peak_range(z), z)

    def squashed(self, g: np.ndarray, g_peak: np.ndarray) -> np.ndarray:
        """Map a model probability g into [p_miss, p_hit] (see the module docstring)."""
        g = np.asarray(g, dtype=float)
        free = 0.5 - (0.5 - self.p_miss) * (1.0 - 2.0 * g)
        span = np.asarray(g_peak, dtype=float) - 0.5
        # a beam whose noise swamps the peak (g_peak <= 1/2) carries no occupied evidence
        fraction = np.where(span > PEAK_EPS, (g - 0.5) / np.maximum(span, PEAK_EPS), 0.0)
        occupied = 0.5 + (self.p_hit - 0.5) * np.minimum(fraction, 1.0)
        return np.where(g < 0.5, free, occupied)

    def logodds(self, r: float | np.ndarray, z: float | np.ndarray) -> np.ndarray:
        """The log-odds a point at range r contributes for a return at z (before per-cell max and fusion)."""
        return logit(self.squashed(self.probability(r, z), self.peak(z)))
