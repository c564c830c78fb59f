"""When to split a cell: a chi-square test of its weighted (hits, misses, unknowns) (paper, section VI.A).

A cell is *homogeneous* when one state fills it. The test asks whether the cell's counts could come from a
homogeneous cell under the range noise sigma, and splits it when they cannot at significance ``alpha``.
docs/adaptive.md derives the expected distributions; in short, with e_k the share of returns that the noise
carries across one boundary of a level-k cell (:func:`spill`) and f a floor for everything the derivation
leaves out:

with unknowns (three outcomes, two degrees of freedom)
    free      misses dominate; hits <= e_k + f (returns of a surface just beyond the cell that fall short),
              unknowns <= f
    occupied  hits dominate; misses <= e_k + f and unknowns <= e_k + f (returns inside the cell that the
              noise carries beyond it or before it)
    hidden    unknowns dominate; hits <= e_k + f (returns of an occluder just before the cell that overshoot
              into it), misses <= f
without unknowns (Einhorn et al.'s rule: hits and misses, one degree of freedom)
    free      misses dominate; hits <= e_k + f
    occupied  hits dominate; misses <= e_k + f

Each hypothesis is a family of distributions (bounds on the non-dominant shares), so the statistic is the
smallest Pearson X^2 = sum (O - n p)^2 / (n p) over the family (:func:`min_chi_square`); the cell splits when
every family's X^2 exceeds the chi-square quantile. Under any member of a family X^2 at the true p is
asymptotically chi-square distributed and the minimum is smaller, so the test rejects a homogeneous cell with
probability at most alpha.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache, cached_property

import numpy as np
from scipy.special import erfc
from scipy.stats import chi2

from mapping.errors import InputError
from mapping.jit import kernel

#: count columns with unknowns; without unknowns the columns are (HIT, MISS)
HIT, MISS, UNKNOWN = 0, 1, 2

#: quadrature points per axis for the average over lines crossing a cell
SPILL_QUADRATURE = 256

#: levels for which the test tabulates the spill (a tile of 2^15 cells a side is the largest tree)
MAX_LEVELS = 16


def outside_fraction(chord: np.ndarray, sigma: float) -> np.ndarray:
    """Probability that a return uniform along a chord of length ``chord`` (m) is measured outside it.

    With range noise N(0, sigma^2) and T = chord / sigma:
    (2 sigma / chord) * (phi(0) - phi(T) + T Phi(-T)), phi and Phi the standard normal density and CDF.
    """
    chord = np.asarray(chord, dtype=float)
    t = chord / sigma
    phi0 = 1.0 / math.sqrt(2.0 * math.pi)
    phi_t = phi0 * np.exp(-0.5 * t * t)
    tail = 0.5 * erfc(t / math.sqrt(2.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 2.0 / t * (phi0 - phi_t + t * tail)
    return np.where(t > 1e-9, out, 1.0)


@cache
def spill(cell_size: float, sigma: float) -> float:
    """Share of returns lying in a square cell that the noise carries across one side of it (one way).

    Half of :func:`outside_fraction` of the chord, averaged over the lines that cross the cell with the
    invariant (Crofton) measure: direction theta uniform, offset p along the normal uniform.
    cell_size and sigma in m.
    """
    n = SPILL_QUADRATURE
    theta = (np.arange(n) + 0.5) * (math.pi / 2) / n  # by symmetry one quadrant of directions suffices
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    u = (np.arange(n) + 0.5) / n
    p = -cell_size * s + u[None, :] * cell_size * (s + c)  # offsets spanning the cell's projection
    # the line {p n + t (c, s)}, n = (-s, c), inside [0, d]^2 for t between the slab bounds
    t_lo = np.maximum(p * s / c, -p * c / s)
    t_hi = np.minimum((cell_size + p * s) / c, (cell_size - p * c) / s)
    chord = np.maximum(t_hi - t_lo, 0.0)
    weight = np.broadcast_to(s + c, chord.shape)  # each theta's offsets span a width d (s + c)
    crossing = chord > 0
    return float(0.5 * np.sum(weight[crossing] * outside_fraction(chord[crossing], sigma)) / np.sum(weight[crossing]))


def min_chi_square(counts: np.ndarray, dominant: int, bounds: np.ndarray) -> np.ndarray:
    """Smallest Pearson X^2 of each row of ``counts`` (N, C) over the distributions p with p_i <= bounds[:, i]
    for every i != dominant (bounds (N, C) or (C,), the dominant column unbounded); 0 for empty rows.

    X^2 is convex in p, so its minimum lies on a face where some set B of bounds is active: p_i = b_i on B
    and p_i = kappa q_i elsewhere (q the observed shares, kappa = P / S with P = 1 - sum_B b_i and
    S = sum_{not B} q_i), giving X^2 = n [(S - P)^2 / P + sum_B (q_i - b_i)^2 / b_i]. Every feasible face
    is tried and the smallest value kept.
    """
    counts = np.ascontiguousarray(counts, dtype=np.float64)
    bounds = np.ascontiguousarray(np.broadcast_to(np.asarray(bounds, dtype=np.float64), counts.shape))
    out = np.empty(counts.shape[0])
    _min_chi_square(counts, int(dominant), bounds, out)
    return out


@kernel(nogil=True, error_model="numpy")
def _min_chi_square(counts, dominant, bounds, out):  # pragma: no cover - compiled
    n_rows, n_cols = counts.shape
    q = np.empty(n_cols)
    for r in range(n_rows):
        n = 0.0
        for i in range(n_cols):
            n += counts[r, i]
        if n <= 0.0:
            out[r] = 0.0
            continue
        for i in range(n_cols):
            q[i] = counts[r, i] / n
        best = np.inf
        for active in range(1 << n_cols):  # the set B of active bounds, as bits; never the dominant column
            if (active >> dominant) & 1:
                continue
            p_free = 1.0
            s_free = 0.0
            value = 0.0
            for i in range(n_cols):
                if (active >> i) & 1:
                    p_free -= bounds[r, i]
                    value += (q[i] - bounds[r, i]) ** 2 / bounds[r, i]
                else:
                    s_free += q[i]
            feasible = True
            for i in range(n_cols):
                if not (active >> i) & 1 and i != dominant:
                    if q[i] * p_free > bounds[r, i] * s_free * (1.0 + 1e-12) + 1e-15:
                        feasible = False
            if feasible:
                best = min(best, n * (value + (s_free - p_free) ** 2 / p_free))
        out[r] = best


@dataclass(frozen=True)
class SplitTest:
    """The split rule for cells of a tree whose finest cells are ``resolution`` m wide.

    sigma: range noise in m; significance: alpha of the test; unknowns: three outcomes (two degrees of
    freedom) or Einhorn et al.'s hits and misses (one); floor: share of any outcome allowed beyond what the
    noise explains (discretisation, rays grazing a corner), > 0.
    """

    resolution: float
    sigma: float
    significance: float = 0.01
    unknowns: bool = True
    floor: float = 0.01

    def __post_init__(self) -> None:
        if not (self.resolution > 0 and self.sigma > 0):
            raise InputError(f"need resolution > 0 and sigma > 0 m, got {self.resolution} and {self.sigma}")
        if not 0 < self.significance < 1:
            raise InputError(f"significance must be in (0, 1), got {self.significance}")
        if not 0 < self.floor < 0.25:
            raise InputError(f"floor must be in (0, 0.25), got {self.floor}")

    @cached_property
    def threshold(self) -> float:
        """The chi-square quantile that X^2 must exceed: 2 degrees of freedom with unknowns, 1 without; the upper tail's
        (isf): ppf(1 - significance) rounded 1 - 1e-17 to 1 and made it infinite, so that no cell ever split."""
        return float(chi2.isf(self.significance, 2 if self.unknowns else 1))

    @cached_property
    def spills(self) -> np.ndarray:
        """e_k of docs/adaptive.md for levels k = 0 .. MAX_LEVELS - 1."""
        return np.array([spill(self.resolution * (1 << k), self.sigma) for k in range(MAX_LEVELS)])

    def families(self, level: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """The homogeneous families for cells of the given levels: (dominant column, bounds (N, C))."""
        level = np.asarray(level, np.int64)
        noise = self.spills[level] + self.floor
        f = np.full(level.shape, self.floor)
        inf = np.full(level.shape, np.inf)
        if self.unknowns:
            return [
                (MISS, np.stack([noise, inf, f], axis=1)),
                (HIT, np.stack([inf, noise, noise], axis=1)),
                (UNKNOWN, np.stack([noise, f, inf], axis=1)),
            ]
        return [(MISS, np.stack([noise, inf], axis=1)), (HIT, np.stack([inf, noise], axis=1))]

    def statistic(self, level: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """The smallest X^2 over the homogeneous families; counts (N, 3) hits, misses, unknowns (the unknowns
        column is ignored without unknowns)."""
        counts = np.asarray(counts, dtype=float).reshape(-1, 3)
        if not self.unknowns:
            counts = counts[:, :2]
        if counts.shape[0] == 0:
            return np.zeros(0)
        return np.min([min_chi_square(counts, dominant, bounds) for dominant, bounds in self.families(level)], axis=0)

    def reject(self, level: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """True where no homogeneous cell explains the counts: split."""
        return self.statistic(level, counts) > self.threshold
