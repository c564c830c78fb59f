"""Fixed-point sums of a scan's per-cell moments, so that they add up the same in any order.

The samples pass (:mod:`mapping.samples_pass`) sums, per cell, the weights W of the pose samples that touch it and
the excess moments D1 = sum_j w_j d_ij and D2 = sum_j w_j d_ij^2 (d >= 0: a value's excess over l_free). Summed as
float64, sample after sample, the sums depend on the order of the samples, so a scan's samples could not be split
over threads (each thread summing its share, the shares added after) without changing the map's last bits with the
thread count. Held as int64 counts of 2**-k instead, every term is one integer (``to_fixed``, a truncation: the
same term always gives the same integer), and integers add exactly in any order: the same map for any split of the
samples (:meth:`mapping.fusion.MonteCarloFusion.walk`'s ``part`` and ``parts``).

The steps are as fine as the sums' range allows: D2 <= (sum of the weights) * excess_max**2 with the weights summing
to 1 within mapping.scan_input.WEIGHT_SUM_TOLERANCE, so with the default model (excess_max = logit(0.7) -
logit(0.4) = 1.25) the steps are 2**-60 (about 1e-18), below a float64's rounding of the values themselves; a
model whose log-odds span is wider gets coarser steps (2**-41 at the widest a SensorModel allows).
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel

#: the sums' bound: 2**62 steps, half of int64's range (every term is truncated towards zero, the sums of the
#: weights are below 1 + WEIGHT_SUM_TOLERANCE < 2, so a sum stays below it with room to spare)
SUM_BITS = 62

#: the finest step, 2**-60: finer than a float64's rounding of any value the sums hold
MAX_FRACTION_BITS = 60

#: the steps of a weight sum W when the weights differ (weights >= 0 summing to below 2): 2**-60
WEIGHT_SCALE = 2.0**MAX_FRACTION_BITS


def moment_scale(excess_max: float) -> float:
    """2**k, the steps per unit of the moments D1 and D2 of excesses 0 <= d <= ``excess_max`` (log-odds) under
    weights summing to below 2: the largest k <= MAX_FRACTION_BITS with 2 * max(excess_max, excess_max**2) below
    2**SUM_BITS steps."""
    if not (math.isfinite(excess_max) and excess_max >= 0.0):
        raise ValueError(f"need a finite excess_max >= 0, got {excess_max}")
    bound = 2.0 * max(excess_max, excess_max * excess_max, 1.0)
    return 2.0 ** min(MAX_FRACTION_BITS, SUM_BITS - math.frexp(bound)[1])


@kernel(nogil=True, error_model="numpy", inline="always")
def to_fixed(x):  # pragma: no cover - compiled
    """x >= 0, already multiplied by its scale, as a whole number of steps (truncated: a function of x alone)."""
    return np.int64(x)
