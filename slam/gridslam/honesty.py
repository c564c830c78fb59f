"""An honest cloud for grid FastSLAM: the spread resampling loses by chance is kept as a covariance, and the
trajectories the filter writes carry the filter's covariance at each scan.

Why: every particle's pose is pinned to its own map by scan matching, so the cloud's spread is the spread of the
particles' map frames. Resampling keeps some particles and drops others; over a run the survivors descend from one
ancestor, and the spread the dropped ones held is gone although nothing was learnt about where the map lies in the
world (a corridor's length, say). Jittering the poses after resampling (roughening) would not help: the next match
pins each particle to its map again. So each particle j carries a covariance D_j (3 x 3, map frame: x m, y m,
yaw rad) of what the set has lost:

- at a resampling, the weighted covariance of the poses before minus the covariance of the resampled set, where
  positive (its positive semi-definite part), is added to every survivor's D: the mixture's covariance
  E_w[D] + Cov_w(x) does not shrink by chance (a chance gain is kept as it is: it is spread the set still holds);
- when a particle moves by (dx, dy) in the map frame, D moves with it: D <- F D F^T with F the Jacobian of the
  pose composition, [[1, 0, -dy], [0, 1, dx], [0, 0, 1]] (a heading error swings the position);
- every integrated scan adds what the particle's map inherits of its pose's error where the scan was new to it
  (:func:`exploration_covariance`), and a return to where the robot was long ago lowers D to the filter's
  covariance then (:class:`Revisits`).

The filter's covariance at a scan is E_w[D] + Cov_w(x) over the particles at that scan (:func:`cloud_covariance`).
The trajectories the filter writes (each final particle's ancestry, slam.gridslam.run) share ancestors and
collapse to few distinct poses, so :func:`spread_trajectories` adds to sample j at scan t the offset L_t z_j:
L_t L_t^T the filter's covariance at t less the samples' own spread there, z_j one fixed normal draw per
trajectory (so a trajectory stays smooth), whitened over the final weights; the best trajectory gets z = 0 and
stays exactly what the filter tracked (the best map and the relation error use it).
"""

from __future__ import annotations

import math

import numpy as np

from slam.angles import wrap_angle
from slam.resampling import low_variance_resample
from slam.scoring import fit_gaussian
from slam.stats import psd_cholesky


def weighted_covariance(poses: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted covariance (3, 3) of poses (M, 3) (m, m, rad; yaw residuals about the circular mean, wrapped)
    under weights (M,) (slam.scoring.fit_gaussian)."""
    return fit_gaussian(poses[None], np.asarray(weights, np.float64)[None])[1][0]


def psd_part(matrix: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric matrix (..., 3, 3): negative eigenvalues set to 0."""
    values, vectors = np.linalg.eigh(0.5 * (matrix + np.swapaxes(matrix, -1, -2)))
    return (vectors * np.maximum(values, 0.0)[..., None, :]) @ np.swapaxes(vectors, -1, -2)


def transport(drift: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Covariances drift (M, 3, 3) carried along as each particle moves from pose before (M, 3) to after (M, 3)
    (m, rad): F D F^T, F = [[1, 0, -dy], [0, 1, dx], [0, 0, 1]] with (dx, dy) the move in the map frame (m)."""
    jac = np.broadcast_to(np.eye(3), drift.shape).copy()
    jac[:, 0, 2] = -(after[:, 1] - before[:, 1])
    jac[:, 1, 2] = after[:, 0] - before[:, 0]
    return jac @ drift @ np.swapaxes(jac, 1, 2)


def resampled_drift(drift: np.ndarray, poses: np.ndarray, weights: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """The survivors' covariances (N, 3, 3) after resampling particles poses (M, 3) of weights (M,) and
    covariances drift (M, 3, 3) to parents (N,): each parent's own plus the spread the set lost (the positive
    part of the weighted covariance before less the covariance after)."""
    lost = psd_part(weighted_covariance(poses, weights) - weighted_covariance(poses[parents], np.ones(len(parents))))
    return drift[parents] + lost


def cloud_covariance(poses: np.ndarray, weights: np.ndarray, drift: np.ndarray) -> np.ndarray:
    """The filter's covariance (3, 3) at a scan: the particles' weighted spread plus their weighted kept
    covariance, Cov_w(poses) + E_w[drift] for poses (M, 3), weights (M,), drift (M, 3, 3)."""
    w = np.asarray(weights, np.float64) / np.sum(weights)
    return weighted_covariance(poses, weights) + np.einsum("n,nij->ij", w, drift)


def trajectory_draws(weights: np.ndarray, best: int, rng: np.random.Generator) -> np.ndarray:
    """One draw z_j (3,) per trajectory (M, 3) with weighted mean 0 and weighted covariance I under weights (M,),
    and z = 0 for trajectory ``best``. All zeros when the others cannot carry it (fewer than 4 of them, or
    practically no weight besides the best's)."""
    m = len(weights)
    w = np.asarray(weights, np.float64) / np.sum(weights)
    z = np.zeros((m, 3))
    others = np.arange(m) != best
    if others.sum() < 4 or w[others].sum() < 1e-9:
        return z
    draws = rng.standard_normal((int(others.sum()), 3))
    draws -= (w[others] @ draws) / w[others].sum()
    second = np.einsum("n,ni,nj->ij", w[others], draws, draws)
    z[others] = draws @ np.linalg.inv(np.linalg.cholesky(second)).T
    return z


def spread_trajectories(
    samples: np.ndarray, weights: np.ndarray, covariance: np.ndarray, best: int, rng: np.random.Generator
) -> np.ndarray:
    """Trajectories samples (T, M, 3) with final weights (M,), each sample moved by L_t z_j so that row t's
    weighted covariance is (about) covariance[t] (T, 3, 3) where the samples' own spread is smaller: L_t the root of
    the positive part of covariance[t] less the samples' spread at t, z from :func:`trajectory_draws`. The yaw
    stays wrapped; trajectory ``best`` is unchanged."""
    z = trajectory_draws(weights, best, rng)
    own = fit_gaussian(samples, np.broadcast_to(weights, samples.shape[:2]))[1]
    root = psd_cholesky(psd_part(covariance - own))
    out = samples + np.einsum("tij,nj->tni", root, z)
    out[..., 2] = wrap_angle(out[..., 2])
    out[:, best] = samples[:, best]  # (exactly: wrapping would round its yaw)
    return out


def cloud_samples(
    poses: np.ndarray, weights: np.ndarray, covariance: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Equal-weight pose samples (M, 3) (m, rad) for one scan's particles poses (M, 3) of weights (M,) whose spread
    should be ``covariance`` (3, 3), the filter's there (:func:`cloud_covariance`): the particles resampled by weight
    (low-variance: each kept floor(M w) or ceil(M w) times, so the heaviest at least once), each copy moved by L e_i,
    L L^T the positive part of ``covariance`` less the particles' weighted spread and e (M, 3) standard normal draws
    less their mean, scaled by sqrt(M / (M - 1)); yaw wrapped. One copy of the heaviest particle stays where it is and
    comes first (e = 0): the filter's most likely pose, which a fusion of the most likely sample (the first of equal
    weights, `--mode ml`) takes. Their covariance is about ``covariance`` and their mean about the particles' weighted
    mean, and no sample lies farther from its particle than L e_i, whatever the weights: :func:`spread_trajectories`'
    whitening, which keeps the best trajectory where it is, puts the spread on the others, so a particle of weight
    0.92 sent the rest 3.5 times as far (63 m across where the filter's sd was 3.5 m, MIT CSAIL through the node)."""
    kept_index = low_variance_resample(weights, rng)
    first = int(np.argmax(kept_index == int(np.argmax(weights))))  # (a copy of the heaviest: there is one)
    order = np.r_[first, np.delete(np.arange(len(kept_index)), first)]
    kept = poses[kept_index[order]]
    root = psd_cholesky(psd_part(covariance - weighted_covariance(poses, weights)))
    draws = rng.standard_normal(kept.shape)
    out = kept.copy()
    if len(kept) > 1:
        moved = (draws[1:] - draws[1:].mean(axis=0)) * math.sqrt(len(kept) / (len(kept) - 1))  # (the first's share)
        out[1:] += moved @ root.T
        out[1:, 2] = wrap_angle(out[1:, 2])  # (the first as the filter holds it, bit for bit)
    return out


class Revisits:
    """Where the best particle was at each integrated scan and the filter's covariance there, to notice when the
    robot is back where it was long ago: its scans then match a part of the map built at that time, which pins
    its pose to that part, whose place in the world is as uncertain as the filter was when it built it.
    :meth:`shrink` then lowers every particle's kept covariance to that covariance (the smallest over the earlier
    visits), so that the uncertainty a long drive accumulated does not outlive the loop that closes it."""

    def __init__(self, gap: int, radius: float) -> None:
        """gap: how many integrated scans ago a visit must be to count; radius (m): how close it must be."""
        self.gap, self.radius = gap, radius
        self.poses: list[np.ndarray] = []
        self.covariances: list[np.ndarray] = []

    def add(self, pose: np.ndarray, covariance: np.ndarray) -> None:
        """Remember the best particle's pose (3,) and the filter's covariance (3, 3) at an integrated scan."""
        self.poses.append(np.asarray(pose, np.float64).copy())
        self.covariances.append(covariance)

    def moved(self, poses: np.ndarray) -> None:
        """Every visit's pose becomes the row of ``poses`` (N, 3) (the path corrected by a loop closure)."""
        self.poses = [pose.copy() for pose in poses]

    def shrink(self, drift: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """The kept covariances drift (M, 3, 3) after the best particle reached ``pose`` (3,) with a scan that
        matched: each whose trace exceeds that of the smallest covariance (by trace) of the visits at least ``gap``
        scans ago within ``radius`` m and facing within 90 deg of ``pose`` becomes that covariance."""
        old = len(self.poses) - self.gap
        if old <= 0:
            return drift
        earlier = np.array(self.poses[:old])
        near = np.hypot(earlier[:, 0] - pose[0], earlier[:, 1] - pose[1]) <= self.radius
        near &= np.abs(wrap_angle(earlier[:, 2] - pose[2])) <= np.pi / 2
        if not near.any():
            return drift
        candidates = np.array(self.covariances[:old])[near]
        smallest = candidates[np.argmin(np.trace(candidates, axis1=1, axis2=2))]
        larger = np.trace(drift, axis1=1, axis2=2) > np.trace(smallest)
        out = drift.copy()
        out[larger] = smallest
        return out


def exploration_covariance(matched: np.ndarray, resolution: float, mean_range: float) -> np.ndarray:
    """What each particle's map inherits of its pose's error from one scan (M, 3, 3) (m, rad): the part of the
    scan its map did not explain yet, 1 - matched (M,) (its matched-beam fraction), is mapped from a pose the
    matcher knows only to the grid's precision: a cell's uniform error, resolution / sqrt(12) m, in x and y, and
    that over the matching beams' mean range (m) in yaw. Added to the kept covariance at every integrated scan,
    it grows while the robot explores and not while it sees what it has mapped."""
    sd = resolution / np.sqrt(12.0)
    floor = np.diag([sd**2, sd**2, (sd / max(mean_range, resolution)) ** 2])
    return np.clip(1.0 - np.asarray(matched, np.float64), 0.0, 1.0)[:, None, None] * floor
