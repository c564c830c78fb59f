"""Importance-weight helpers for particle filters."""

from __future__ import annotations

import numpy as np

from slam.errors import InputError

#: weights whose sum lies this close to 1 are taken as normalised and used as they are (as before unnormalised
#: weights were accepted: results for normalised weights stay bit for bit the same); others are divided by their sum
NORMALISED_TOLERANCE = 1e-9


def normalize_log_weights(log_weights: np.ndarray) -> np.ndarray:
    """Weights (N,) summing to 1 from unnormalised log weights (N,), without overflow. InputError when the largest
    log weight is not finite (every particle at -inf, one at +inf, or NaN): there is no distribution to give, where
    the weights came out NaN."""
    top = np.max(log_weights)
    if not np.isfinite(top) or np.isnan(log_weights).any():
        raise InputError(
            f"the log weights give no distribution (largest {top}, {int(np.isnan(log_weights).sum())} NaN): every "
            "particle ruled out, or a likelihood that is not finite"
        )
    shifted = np.exp(log_weights - top)
    return shifted / shifted.sum()


def checked_weights(weights: np.ndarray) -> tuple[np.ndarray, float]:
    """Importance weights (N,) as float64 and their sum; InputError unless they are a non-empty 1-D array of finite,
    non-negative numbers with a positive sum (any scale: they need not sum to 1). O(N), vectorised."""
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 1 or len(w) == 0:
        raise InputError(f"weights must be a non-empty 1-D array (one per particle), got shape {w.shape}")
    bad = np.flatnonzero(~(np.isfinite(w) & (w >= 0.0)))
    if len(bad):
        raise InputError(
            f"weights must be finite and non-negative, got {w[bad[0]]} at particle {bad[0]}; from log weights use "
            "normalize_log_weights"
        )
    total = float(w.sum())
    if not total > 0.0 or not np.isfinite(total):
        raise InputError(f"weights must have a positive, finite sum, got {total} (every particle has weight 0?)")
    return w, total


def effective_sample_size(weights: np.ndarray) -> float:
    """N_eff = (sum w)^2 / sum(w^2) of importance weights (N,) of any positive scale (1 / sum(w^2) when they sum to
    1): N for equal weights, 1 for a single survivor. InputError for empty, negative, non-finite or all-zero weights."""
    w, total = checked_weights(weights)
    if abs(total - 1.0) > NORMALISED_TOLERANCE:
        w = w / total
    return float(1.0 / np.sum(w * w))


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator, count: int | None = None) -> np.ndarray:
    """Indices (count,) of the particles kept by low-variance (systematic) resampling of weights (N,), PR table 4.4
    (``count`` None: N).

    One uniform offset r in [0, 1/count) and the pointers r + k/count walk the cumulative weights (divided by their
    sum when it is not 1), so a particle of weight w is copied floor(count w) or ceil(count w) times. InputError for
    empty, negative, non-finite or all-zero weights, or a count below 1.
    """
    w, total = checked_weights(weights)
    n = len(w)
    count = n if count is None else int(count)
    if count < 1:
        raise InputError(f"resampling needs a count of at least 1 particle, got {count}")
    pointers = rng.uniform(0.0, 1.0 / count) + np.arange(count) / count
    cumulative = np.cumsum(w)
    if abs(total - 1.0) > NORMALISED_TOLERANCE:
        cumulative /= cumulative[-1]
    cumulative[-1] = 1.0
    return np.minimum(np.searchsorted(cumulative, pointers, side="right"), n - 1)
