"""Small Gaussian helpers vectorised over a leading batch axis (particles or landmarks)."""
from __future__ import annotations

import numpy as np


def sqrtm_psd(cov: np.ndarray) -> np.ndarray:
    """A square root A with A A^T = cov for a stack (..., d, d) of symmetric positive semi-definite matrices.

    Uses the eigendecomposition so that a zero (or singular) covariance gives an exact zero (singular) root,
    where a Cholesky factorisation would fail.
    """
    eigval, eigvec = np.linalg.eigh(cov)
    return eigvec * np.sqrt(np.clip(eigval, 0.0, None))[..., None, :]


def sample_gaussian(mean: np.ndarray, cov: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw from N(mean[k], cov[k]) for every k; mean (N, d), cov (N, d, d) -> (N, d)."""
    noise = rng.standard_normal(mean.shape)
    return mean + np.einsum("nij,nj->ni", sqrtm_psd(cov), noise)


def inv2(mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse and determinant of a stack (..., 2, 2) of 2x2 matrices, in closed form."""
    a, b, c, d = mat[..., 0, 0], mat[..., 0, 1], mat[..., 1, 0], mat[..., 1, 1]
    det = a * d - b * c
    inv = np.stack([np.stack([d, -b], -1), np.stack([-c, a], -1)], -2) / det[..., None, None]
    return inv, det


def gaussian_logpdf2(innovation: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """log N(innovation; 0, cov) for stacks of 2-vectors (..., 2) and 2x2 covariances (..., 2, 2)."""
    inv, det = inv2(cov)
    maha = np.einsum("...i,...ij,...j->...", innovation, inv, innovation)
    return -0.5 * maha - 0.5 * np.log(det) - np.log(2.0 * np.pi)


def mahalanobis2(innovation: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance innovation^T cov^-1 innovation for stacks of 2-vectors."""
    inv, _ = inv2(cov)
    return np.einsum("...i,...ij,...j->...", innovation, inv, innovation)
