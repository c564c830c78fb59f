"""Pose samples for one scan: from weighted particles or from a Gaussian (paper, section V.A).

Poses are (x m, y m, yaw rad) of the robot in the map frame.

Number of samples from a Gaussian (docs/sensor_model.md, "How many samples"): a beam of length R moves its
end point by about sqrt(lambda_max(Sigma_xy) + (R sigma_yaw)^2) when the pose varies, so with M samples the
Monte Carlo mean of that end point has standard error sqrt(v / M), v = lambda_max(Sigma_xy) + (R sigma_yaw)^2.
Asking for that error to stay below ``accuracy`` with 95 % confidence gives

    M = ceil(1.96^2 v / accuracy^2),   clipped to [1, max_samples].
"""

from __future__ import annotations

import math

import numpy as np

from mapping.covariance import check_covariances
from mapping.errors import InputError
from mapping.scan_input import check_samples, merge_duplicates

MODES = ("mc", "ml")
Z95 = 1.959963984540054  # two-sided 95 % standard-normal quantile
DEFAULT_MAX_SAMPLES = 200


def samples_for_accuracy(
    cov: np.ndarray, range_max: float, accuracy: float, max_samples: int = DEFAULT_MAX_SAMPLES
) -> int:
    """The number of Gaussian pose samples the rule in the module docstring asks for."""
    if not accuracy > 0:
        raise InputError(f"accuracy must be > 0 m, got {accuracy}")
    cov = np.asarray(cov, dtype=float)
    # products, not ** 2: a float product past the float range is inf, a power raises OverflowError
    spread = float(np.linalg.eigvalsh(cov[:2, :2]).max()) + range_max * range_max * float(cov[2, 2])
    needed = (Z95 / accuracy) * (Z95 / accuracy) * max(spread, 0.0)
    if not needed < max_samples:  # also inf and NaN, from a spread past what floats hold
        return max_samples
    return max(math.ceil(needed), 1)


def check_gaussian(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a Gaussian pose: mean (3,) (x m, y m, yaw rad) and cov (3, 3), finite, symmetric and positive
    semi-definite. Returns them as float64 arrays."""
    mean = np.asarray(mean, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if mean.shape != (3,) or cov.shape != (3, 3):
        raise InputError(f"a Gaussian pose needs mean (3,) and cov (3, 3), got {mean.shape} and {cov.shape}")
    if not (np.isfinite(mean).all() and np.isfinite(cov).all()):
        raise InputError("the Gaussian pose's mean and cov must be finite")
    check_covariances(cov[None], "the pose covariance")
    return mean, cov


def gaussian_samples(mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n samples (n, 3) of N(mean, cov) through a Cholesky factor (eigen-factor when cov is only semi-definite).
    Refuses a mean or cov that :func:`check_gaussian` does."""
    mean, cov = check_gaussian(mean, cov)
    return _draw(mean, cov, n, rng)


def _draw(mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """:func:`gaussian_samples` of a mean and cov already checked."""
    try:
        factor = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(cov)
        factor = vectors * np.sqrt(np.clip(values, 0.0, None))
    return mean + rng.standard_normal((n, 3)) @ factor.T


def scan_samples(
    mode: str,
    *,
    samples: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    mean: np.ndarray | None = None,
    cov: np.ndarray | None = None,
    n_samples: int | None = None,
    seed: int = 0,
    seq: int = 0,
    accuracy: float = 0.05,
    range_max: float = 10.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Samples (M, 3) and weights (M,) to fuse one scan with.

    mode "mc": all particles (identical ones merged) or, for a Gaussian, n_samples draws (or as many as the
    accuracy rule asks for when n_samples is None), from an rng seeded by (seed, seq) so that every process
    draws the same samples for scan ``seq``. mode "ml": the most likely particle (identical ones merged,
    their weights summed, as mc merges them; the first of equal weights) or the Gaussian's mean, with weight 1: the
    paper's baseline.
    """
    if mode not in MODES:
        raise InputError(f"mode must be 'mc' or 'ml', got {mode!r}")
    if mean is not None:
        if cov is None:
            raise InputError("a Gaussian pose needs both mean and cov")
        mean, cov = check_gaussian(mean, cov)
        if mode == "ml":
            return mean.reshape(1, 3), np.ones(1)
        n = n_samples if n_samples is not None else samples_for_accuracy(cov, range_max, accuracy)
        if n < 1:
            raise InputError(f"n_samples must be >= 1, got {n}")
        rng = np.random.default_rng([int(seed), int(seq)])
        return _draw(mean, cov, n, rng), np.full(n, 1.0 / n)
    if samples is None or weights is None:
        raise InputError("a pose distribution needs samples and weights, or mean and cov")
    samples, weights = merge_duplicates(*check_samples(samples, weights))
    if mode == "ml":  # (merged first: a pose's weight is its copies' sum, as mc fuses it)
        best = int(np.argmax(weights))
        return samples[best : best + 1], np.ones(1)
    return samples, weights
