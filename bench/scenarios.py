"""Benchmark inputs: the simulated office and warehouse with honest pose distributions around the true path.

"Honest" means the estimate's error is drawn from the very covariance it reports, so the true pose lies
inside the estimate's 95 % region about 95 % of the time: mean_t = truth_t + L_t eps_t, eps_t ~ N(0, I),
with covariance Sigma_t whose position sigma varies smoothly between 0.03 and 0.15 m and yaw sigma between
0.005 and 0.03 rad along the run (uncertainty grows while exploring and shrinks at loop closures).
`select_scans` cuts any posed scans, real logs included, down to the scans a suite needs. The real laser logs
live in ../shared/data, beside the repository, not in it; a suite skips a log that is absent, with the reason.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from schemas.files import PosedScans, PoseSet
from slam.simulator import SimRun, simulate_office
from slam.warehouse import simulate_warehouse

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MIT_CSAIL = SHARED_DATA / "mit-csail" / "mit-csail.clf"
FR079 = SHARED_DATA / "fr079" / "fr079.orig.bag"


def honest_covariances(steps: int) -> np.ndarray:
    """(T, 3, 3) diagonal covariances whose sigmas rise and fall twice over the run."""
    phase = np.linspace(0, 2 * np.pi, steps)
    level = 0.5 - 0.5 * np.cos(2 * phase)
    sigma_xy = 0.03 + 0.12 * level
    sigma_yaw = 0.005 + 0.025 * level
    cov = np.zeros((steps, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = sigma_xy**2
    cov[:, 2, 2] = sigma_yaw**2
    return cov


def office_run(seed: int = 0, steps: int = 400) -> SimRun:
    """The simulated office: 361 beams over 180 degrees, 12 m range."""
    return simulate_office(seed=seed, steps=steps, n_beams=361, range_max=12.0)


def warehouse_run(seed: int = 0, steps: int = 400) -> SimRun:
    """The simulated warehouse (slam.warehouse): 1081 beams over 270 degrees, 30 m range, 40 Hz."""
    return simulate_warehouse(seed=seed, steps=steps)


def honest_posed_scans(run: SimRun, seed: int = 0, particles: int | None = None) -> PosedScans:
    """The run's scans with honest Gaussian poses, or with ``particles`` equal-weight draws from them."""
    rng = np.random.default_rng(seed)
    cov = honest_covariances(len(run.stamps))
    factors = np.linalg.cholesky(cov)
    mean = run.true_poses + np.einsum("tij,tj->ti", factors, rng.standard_normal((len(cov), 3)))
    if particles is None:
        poses = PoseSet(mean=mean, cov=cov)
    else:
        draws = mean[:, None, :] + np.einsum("tij,tmj->tmi", factors, rng.standard_normal((len(cov), particles, 3)))
        poses = PoseSet(samples=draws, weights=np.full((len(cov), particles), 1.0 / particles))
    return PosedScans.from_scans(run, poses)


def truth_arrays(run: SimRun) -> dict:
    """The run's truth raster as the scorer's dict."""
    return {
        "occupied": run.truth_occupied,
        "visible": run.truth_visible,
        "origin": run.truth_origin,
        "resolution": run.truth_resolution,
    }


def resampled_particles(posed: PosedScans, seed: int = 0) -> PosedScans:
    """The particle set after a multinomial resampling step, as a particle filter outputs it: many
    particles repeat. Weights stay equal (1/M each, duplicates included)."""
    rng = np.random.default_rng(seed)
    samples, weights = posed.poses.weighted_samples()
    steps, count, _ = samples.shape
    picks = rng.integers(0, count, size=(steps, count))
    picks = np.sort(picks // 4 * 4, axis=1)  # draw from every 4th particle: about M/4 distinct poses
    resampled = np.take_along_axis(samples, picks[..., None], axis=1)
    return replace(posed, poses=PoseSet(samples=resampled, weights=weights))


def select_scans(posed: PosedScans, index: slice) -> PosedScans:
    """The scans of ``posed`` that ``index`` picks (slice(0, 10): the first ten; slice(None, None, 4): every
    4th), each with its geometry and its pose distribution in whichever form it has."""
    return posed.select(index)
