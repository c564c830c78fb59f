"""Trajectory scoring against ground truth: accuracy (ATE) and consistency (NEES, 95% coverage).

No alignment is applied: the filters start at the true first pose in the map frame, so their estimates
and the ground truth share a frame and the raw differences are the errors.

For particles, the point estimate is the weighted mean (circular mean for yaw) and the covariance is the
weighted covariance of the particles about it (yaw residuals wrapped): the Gaussian fitted to them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.covariance import check_covariances
from slam.angles import wrap_angle
from slam.errors import InputError, finite_array

#: chi-square(3) 95% quantile: the true pose is inside the 95% region when its NEES is below this
CHI2_3_95 = 7.8147
#: added to every covariance's diagonal (m^2, m^2, rad^2) before inversion, so a zero covariance (the known
#: start, or a single particle) gives a finite NEES: 0 for a zero error, enormous otherwise
COVARIANCE_JITTER = 1e-6


@dataclass(frozen=True)
class TrajectoryScore:
    """ate_rmse_m: RMS position error (m); heading_mae_rad: mean |yaw error| (rad); nees_mean: mean
    normalised estimation error squared (3 DOF, ideally 3); inside95: fraction of steps whose true pose lies in
    the estimate's 95% region (ideally 0.95); steps: how many steps were scored."""

    ate_rmse_m: float
    heading_mae_rad: float
    nees_mean: float
    inside95: float
    steps: int


def fit_gaussian(samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean (T, 3) and covariance (T, 3, 3) of particles samples (T, N, 3), weights (T, N)."""
    weights = weights / weights.sum(axis=1, keepdims=True)
    mean_xy = np.einsum("tn,tnk->tk", weights, samples[..., :2])
    yaw = np.arctan2(
        np.einsum("tn,tn->t", weights, np.sin(samples[..., 2])), np.einsum("tn,tn->t", weights, np.cos(samples[..., 2]))
    )
    mean = np.column_stack([mean_xy, yaw])
    residual = samples - mean[:, None, :]
    residual[..., 2] = wrap_angle(residual[..., 2])
    cov = np.einsum("tn,tni,tnj->tij", weights, residual, residual)
    return mean, cov


def score_trajectory(mean: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> TrajectoryScore:
    """Score estimates mean (T, 3), cov (T, 3, 3) against true poses truth (T, 3), all in the map frame (x m, y m,
    yaw rad; cov in m^2, m rad, rad^2). InputError unless T >= 1 is the same for all three, every value is finite and
    every covariance symmetric positive semi-definite (:func:`check_covariances`)."""
    mean = finite_array("mean", mean, (None, 3), " (estimated poses x m, y m, yaw rad)")
    steps = len(mean)
    if steps == 0:
        raise InputError("mean, cov and truth hold no step: give at least one pose to score")
    cov = finite_array("cov", cov, (steps, 3, 3), f" (one (3, 3) covariance per pose of mean: {steps})")
    truth = finite_array("truth", truth, (steps, 3), f" (one true pose per pose of mean: {steps})")
    check_covariances(cov)
    error = truth - mean
    error[:, 2] = wrap_angle(error[:, 2])
    regularised = cov + COVARIANCE_JITTER * np.eye(3)
    nees = np.einsum("ti,ti->t", error, np.linalg.solve(regularised, error[..., None])[..., 0])
    return TrajectoryScore(
        ate_rmse_m=float(np.sqrt(np.mean(np.sum(error[:, :2] ** 2, axis=1)))),
        heading_mae_rad=float(np.mean(np.abs(error[:, 2]))),
        nees_mean=float(np.mean(nees)),
        inside95=float(np.mean(nees <= CHI2_3_95)),
        steps=len(mean),
    )


def interpolate_poses(stamps: np.ndarray, truth_stamps: np.ndarray, truth_poses: np.ndarray) -> np.ndarray:
    """Ground truth (G, 3) at truth_stamps (G,) interpolated linearly to ``stamps`` (T,) (yaw unwrapped first,
    so it turns the short way); stamps outside the ground truth's span take its first or last pose. Stamps in s,
    poses (x m, y m, yaw rad). InputError unless truth_stamps are strictly increasing (they are not sorted here: an
    unsorted ground truth is more likely a mistake than an order to fix) and everything is finite."""
    truth_stamps = finite_array("truth_stamps", truth_stamps, (None,))
    if len(truth_stamps) == 0:
        raise InputError("truth_stamps is empty: give at least one ground-truth pose")
    truth_poses = finite_array("truth_poses", truth_poses, (len(truth_stamps), 3), " (one pose per truth stamp)")
    stamps = finite_array("stamps", stamps, (None,))
    bad = np.flatnonzero(np.diff(truth_stamps) <= 0.0)
    if len(bad):
        k = int(bad[0])
        raise InputError(
            f"truth_stamps must be strictly increasing, but [{k}] = {float(truth_stamps[k])!r} s and [{k + 1}] = "
            f"{float(truth_stamps[k + 1])!r} s: sort the ground truth by time and keep one pose per stamp"
        )
    yaw = np.unwrap(truth_poses[:, 2])
    return np.column_stack(
        [
            np.interp(stamps, truth_stamps, truth_poses[:, 0]),
            np.interp(stamps, truth_stamps, truth_poses[:, 1]),
            wrap_angle(np.interp(stamps, truth_stamps, yaw)),
        ]
    )
