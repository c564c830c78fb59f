"""Importance-weight helpers for particle filters."""

from __future__ import annotations

import numpy as np


def normalize_log_weights(log_weights: np.ndarray) -> np.ndarray:
    """Weights (N,) summing to 1 from unnormalised log weights (N,), without overflow."""
    shifted = np.exp(log_weights - np.max(log_weights))
    return shifted / shifted.sum()


def effective_sample_size(weights: np.ndarray) -> float:
    """N_eff = 1 / sum(w^2) of normalised weights (N,); N for uniform weights, 1 for a single survivor."""
    return float(1.0 / np.sum(weights * weights))


def low_variance_resample(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices (N,) of the particles kept by low-variance (systematic) resampling, PR table 4.4.

    One uniform offset r in [0, 1/N) and the N pointers r + k/N walk the cumulative weights, so a particle
    of weight w is copied floor(N w) or ceil(N w) times.
    """
    n = len(weights)
    pointers = rng.uniform(0.0, 1.0 / n) + np.arange(n) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.minimum(np.searchsorted(cumulative, pointers, side="right"), n - 1)
