"""Small Gaussian helpers vectorised over a leading batch axis (particles or landmarks)."""

from __future__ import annotations

import numpy as np


def psd_cholesky(cov: np.ndarray) -> np.ndarray:
    """Lower-triangular L with L L^T = cov for a stack (..., d, d) of symmetric positive semi-definite matrices.

    The Cholesky recursion, vectorised over the stack (the loop runs over the d columns only), with a zero
    pivot giving a zero column instead of a failure, so that a zero or singular covariance gives an exact
    zero or singular root; negative pivots from rounding are clipped to 0.
    """
    d = cov.shape[-1]
    root = np.zeros_like(cov, dtype=np.float64)
    for j in range(d):
        pivot = cov[..., j, j] - np.sum(root[..., j, :j] ** 2, axis=-1)
        diag = np.sqrt(np.clip(pivot, 0.0, None))
        root[..., j, j] = diag
        safe = np.where(diag > 1e-150, diag, 1.0)
        for i in range(j + 1, d):
            below = cov[..., i, j] - np.sum(root[..., i, :j] * root[..., j, :j], axis=-1)
            root[..., i, j] = np.where(diag > 1e-150, below / safe, 0.0)
    return root


def sample_gaussian(mean: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw from N(mean[k], cov[k]) for every k; mean (N, d), cov (N, d, d) positive semi-definite -> (N, d)."""
    noise = rng.standard_normal(mean.shape)
    return mean + np.einsum("nij,nj->ni", psd_cholesky(cov), noise)


def inv2(mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse and determinant of a stack (..., 2, 2) of 2x2 matrices, in closed form."""
    a, b, c, d = mat[..., 0, 0], mat[..., 0, 1], mat[..., 1, 0], mat[..., 1, 1]
    det = a * d - b * c
    inv = np.stack([np.stack([d, -b], -1), np.stack([-c, a], -1)], -2) / det[..., None, None]
    return inv, det
