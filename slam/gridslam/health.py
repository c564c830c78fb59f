"""Grid FastSLAM's health watch: how well the particles explain each integrated scan, and what the filter does
about it (docs/gridslam.md, "Honesty and health").

Per integrated scan (:class:`ScanHealth`): the best particle's matched-beam fraction (its match score per beam,
the mean over the matching beams of exp(-d^2 / 2 sigma_match^2) with d the distance from a beam's end to the
nearest mapped end point: 1 when every beam ends on a mapped wall, 0 when none does), that fraction's z against its
recent values (:class:`HealthWatch`), N_eff, the particle count, the cloud's spread (the particles' own, and with
the covariance the filter keeps for what resampling lost, slam.gridslam.honesty) and whether the match failed.

The adaptive particle count is KLD-sampling (Fox 2003, "Adapting the sample size in particle filters through
KLD-sampling"): particles are drawn from the weights one at a time, each into a bin of a grid over (x, y, yaw)
centred on the weighted mean, until the count n reaches the bound n(k) at which the sample's Kullback-Leibler
divergence from the weighted set is below epsilon with probability 1 - delta (k: bins occupied so far), within
[minimum, cap]. A tight cloud fills one bin and stays at the minimum; a cloud spread along a corridor fills several
and grows.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from statistics import NormalDist

import numpy as np

from slam.angles import wrap_angle


@dataclass(frozen=True)
class ScanHealth:
    """One integrated scan's health: ``matched`` the best particle's matched-beam fraction [0, 1], ``score_z`` its
    z against the recent scans (NaN until there are enough), ``ess`` N_eff before resampling, ``particles`` the
    count that took the scan, ``spread_xy`` m and ``spread_yaw`` rad the particles' weighted standard deviations
    (position: sqrt(var x + var y)), ``sigma_xy`` m and ``sigma_yaw`` rad the same with the kept covariance,
    ``fallbacks`` particles that sampled the motion model, ``failed`` whether the best match failed (the scan did
    not weigh the particles; the next proposal is wider), ``widened`` whether this scan's proposal was widened,
    ``resampled`` and ``next_particles`` the count after this scan (KLD-sampling)."""

    matched: float
    score_z: float
    ess: float
    particles: int
    spread_xy: float
    spread_yaw: float
    sigma_xy: float
    sigma_yaw: float
    fallbacks: int
    failed: bool
    widened: bool
    resampled: bool
    next_particles: int

    def as_dict(self) -> dict:
        """The fields as a JSON-ready dict (NaN as None)."""
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(self).items()}


class HealthWatch:
    """The matched-beam fractions of the last ``window`` integrated scans, for the z of the next one."""

    def __init__(self, window: int = 50, least: int = 10) -> None:
        self.values: deque[float] = deque(maxlen=window)
        self.least = least

    def zscore(self, matched: float) -> float:
        """(matched - mean) / std over the window (std at least 0.02); NaN while it holds fewer than ``least``."""
        if len(self.values) < self.least:
            return math.nan
        recent = np.fromiter(self.values, np.float64)
        return float((matched - recent.mean()) / max(float(recent.std()), 0.02))

    def add(self, matched: float) -> None:
        self.values.append(matched)


def spreads(covariance: np.ndarray) -> tuple[float, float]:
    """(position sd m, yaw sd rad) of a pose covariance (3, 3): sqrt(var x + var y) and sqrt(var yaw)."""
    return float(math.sqrt(max(covariance[0, 0] + covariance[1, 1], 0.0))), float(math.sqrt(max(covariance[2, 2], 0.0)))


def kld_bound(bins: np.ndarray, epsilon: float, delta: float) -> np.ndarray:
    """Fox's sample count (float array like ``bins``) for k occupied bins: (k - 1) / (2 epsilon) (1 - 2 / (9 (k -
    1)) + sqrt(2 / (9 (k - 1))) z_(1 - delta))^3, the Wilson-Hilferty approximation of the chi-square quantile;
    0 for k = 1."""
    k1 = np.maximum(np.asarray(bins, np.float64) - 1.0, 0.0)
    safe = np.maximum(k1, 1.0)
    z = NormalDist().inv_cdf(1.0 - delta)
    bound = k1 / (2.0 * epsilon) * (1.0 - 2.0 / (9.0 * safe) + np.sqrt(2.0 / (9.0 * safe)) * z) ** 3
    return np.where(k1 > 0, bound, 0.0)


def kld_count(
    poses: np.ndarray,
    weights: np.ndarray,
    rng: np.random.Generator,
    limits: tuple[int, int],
    bin_size: tuple[float, float],
    epsilon: float,
    delta: float,
) -> int:
    """The KLD-sampling count for particles poses (M, 3) of weights (M,): draws from the weights in order, each
    into a bin of ``bin_size`` (m, rad) of a grid centred on the weighted mean, and returns the first count n
    within ``limits`` (minimum, cap) with n >= :func:`kld_bound` of the bins occupied by the first n draws (the
    cap when there is none)."""
    low, cap = limits
    w = np.asarray(weights, np.float64) / np.sum(weights)
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0
    drawn = np.minimum(np.searchsorted(cumulative, rng.random(cap), side="right"), len(w) - 1)
    mean_yaw = math.atan2(float(w @ np.sin(poses[:, 2])), float(w @ np.cos(poses[:, 2])))
    centre = np.array([w @ poses[:, 0], w @ poses[:, 1], mean_yaw])
    offset = poses[drawn] - centre
    offset[:, 2] = wrap_angle(offset[:, 2])
    cells = np.floor(offset / np.array([bin_size[0], bin_size[0], bin_size[1]]) + 0.5).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    occupied = np.cumsum(np.bincount(first, minlength=cap))  # bins occupied by the first n draws, n = 1..cap
    n = np.arange(1, cap + 1)
    ok = (n >= low) & (n >= kld_bound(occupied, epsilon, delta))
    return int(n[np.argmax(ok)]) if ok.any() else cap


@dataclass(frozen=True)
class HealthSummary:
    """A run's health over its integrated scans: ``failed`` scans whose best match failed, ``poor`` scans that
    failed or matched less than :data:`POOR_FRACTION` of the run's median matched-beam fraction, ``longest_poor``
    the longest run of consecutive poor scans, ``median_matched`` and ``low_matched`` (the 5th percentile) of the
    matched-beam fraction, ``mean_particles`` and ``max_particles``, ``widened`` proposals and ``warnings``
    (sentences; empty when the run looked healthy)."""

    scans: int
    failed: int
    poor: int
    longest_poor: int
    median_matched: float
    low_matched: float
    mean_particles: float
    max_particles: int
    widened: int
    warnings: tuple[str, ...]

    def as_dict(self) -> dict:
        out = asdict(self)
        out["warnings"] = list(self.warnings)
        return out


#: a scan is poor when it failed or matched less than this fraction of the run's median matched-beam fraction
POOR_FRACTION = 0.5
#: a run warns when at least this many consecutive integrated scans were poor, or this fraction of them
WARN_POOR_RUN, WARN_POOR_FRACTION = 10, 0.05


def summarize(health: list[ScanHealth]) -> HealthSummary:
    """The :class:`HealthSummary` of a run's per-scan ``health``."""
    failed = np.array([h.failed for h in health], bool)
    every = np.array([h.matched for h in health], np.float64)
    matched = every[~np.isnan(every)]  # (the first scan has nothing to match)
    counts = np.array([h.particles for h in health], np.int64)
    median = float(np.median(matched)) if len(matched) else math.nan
    with np.errstate(invalid="ignore"):
        poor = failed | (every < POOR_FRACTION * median)
    longest, run = 0, 0
    for flag in poor:  # one pass over the scans' flags
        run = run + 1 if flag else 0
        longest = max(longest, run)
    warnings = []
    if len(health) and (longest >= WARN_POOR_RUN or poor.mean() >= WARN_POOR_FRACTION):
        warnings.append(
            f"the scans matched the maps poorly at {int(poor.sum())} of {len(health)} integrated scans (at most "
            f"{longest} in a row; {int(failed.sum())} failed): the map is likely broken there (a changed laser "
            "mounting, a kidnapped robot, odometry the matcher could not follow)"
        )
    return HealthSummary(
        scans=len(health),
        failed=int(failed.sum()),
        poor=int(poor.sum()),
        longest_poor=longest,
        median_matched=median,
        low_matched=float(np.percentile(matched, 5)) if len(matched) else math.nan,
        mean_particles=float(counts.mean()) if len(counts) else 0.0,
        max_particles=int(counts.max()) if len(counts) else 0,
        widened=int(sum(h.widened for h in health)),
        warnings=tuple(warnings),
    )


def reference_errors(best: np.ndarray, odometry: np.ndarray, reference: np.ndarray) -> tuple[float, float] | None:
    """RMS position errors (m) of a trajectory ``best`` (T, 3) and of the ``odometry`` (T, 3) it started from
    against ``reference`` (T, 3), poses a log states besides its odometry (a corrected log's, a simulated log's
    truth), moved rigidly so that its first pose is the odometry's first (the filter's map frame). None when the
    reference is the odometry itself (a raw log states nothing else)."""
    if np.allclose(reference, odometry, atol=1e-6):
        return None
    relative = reference - reference[0]
    c, s = math.cos(odometry[0, 2] - reference[0, 2]), math.sin(odometry[0, 2] - reference[0, 2])
    aligned = odometry[0, :2] + np.column_stack(
        [c * relative[:, 0] - s * relative[:, 1], s * relative[:, 0] + c * relative[:, 1]]
    )

    def rms(poses: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((poses[:, :2] - aligned) ** 2, axis=1))))

    return rms(best), rms(odometry)
