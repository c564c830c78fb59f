"""Pose bundles: the coherence of a scan's pose samples, used to walk fewer rays (opt-in, ``--bundle TOL``).

The samples of a real pose distribution are coherent: most of them put a beam's end in the same few cells, so
their rays cross nearly the same cells. A bundle is a set of samples whose rays all end close to those of one of
them, its **leader**; the scan is then walked from the leaders alone, each carrying its bundle's summed weight.
The cost of a scan follows the number of bundles, which is bounded by how far the samples spread, not by how
many there are: a thousand samples of a tight cloud walk about as many rays as a hundred.

**The bound.** For a laser pose (x, y, yaw) and a beam of length r, moving the pose by (dp, dyaw) moves the beam's
end by at most |dp| + r |dyaw| (m). A sample joins a leader when

    |p - p_leader| + reach * |yaw - yaw_leader| <= tolerance,

``reach`` the mean length of the scan's rays (m). So each ray of a bundled sample is cast from a pose at most
``tolerance`` m from its own, and averaged over the scan's rays its end moves at most ``tolerance`` m; a ray of
length r moves at most |dp| + r |dyaw|. Leaders are samples (not means), so the bundles do not pull the cloud
together: a mean would shrink the spread the map's variance is made of.

**Order.** Samples are taken by decreasing weight (ties: first in order); each joins the first leader within the
tolerance, else leads a bundle of its own. Same samples, same bundles: the result does not depend on anything
but the input.

What it costs the map, measured against the exact fusion: docs/performance.md, "Bundled samples"; the tests hold
the office map within 0.001 AUC and 1 % Brier score of the exact map at the recommended 0.1 m.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.errors import InputError
from mapping.jit import kernel

#: tolerance (m) the benches use: two cells at 0.05 m, chosen on the simulated office (60 samples, 400 scans), where
#: the map stays within 0.001 AUC and 1 % Brier score of the exact fusion's. Not a default, and not that bound
#: elsewhere: on the office's first 120 scans AUC +0.0024, on the warehouse (30 m rays) +0.045 (docs/performance.md,
#: "Bundled samples"); what always holds is the geometric bound of the module docstring
RECOMMENDED_TOLERANCE = 0.1


@kernel(nogil=True)
def _leaders(lasers, order, weights, tolerance, reach):  # pragma: no cover - compiled
    """(leader indices (K,) into ``lasers``, bundle weights (K,)) of the samples taken in ``order``."""
    m = lasers.shape[0]
    leaders = np.empty(m, np.int64)
    summed = np.empty(m)
    count = 0
    for n in range(m):
        j = order[n]
        joined = False
        for k in range(count):
            lead = leaders[k]
            turn = lasers[j, 2] - lasers[lead, 2]
            if abs(turn) > math.pi:  # (wrapped only when it must be: a wrap rounds away differences of 1e-16 rad)
                turn -= 2.0 * math.pi * round(turn / (2.0 * math.pi))
            moved = math.hypot(lasers[j, 0] - lasers[lead, 0], lasers[j, 1] - lasers[lead, 1])
            if moved + reach * abs(turn) <= tolerance:
                summed[k] += weights[j]
                joined = True
                break
        if not joined:
            leaders[count] = j
            summed[count] = weights[j]
            count += 1
    return leaders[:count], summed[:count]


def bundle_samples(
    lasers: np.ndarray, weights: np.ndarray, tolerance: float, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """The bundles' leaders (K, 3) (laser poses, map frame, m and rad) and summed weights (K,) of laser poses
    ``lasers`` (M, 3) with ``weights`` (M,): every sample within ``tolerance`` m (|dp| + ``reach`` |dyaw|, reach in
    m) of its leader (module docstring). A tolerance of 0 bundles only identical poses. InputError for arrays of
    other shapes (the compiled search read past the shorter one: garbage, or a crash), values that are not finite, or
    a reach (m) that is not finite and >= 0."""
    lasers = np.asarray(lasers, np.float64)
    weights = np.asarray(weights, np.float64)
    if lasers.ndim != 2 or lasers.shape[1] != 3 or weights.shape != lasers.shape[:1]:
        raise InputError(f"need laser poses (M, 3) and weights (M,), got {lasers.shape} and {weights.shape}")
    if not (np.isfinite(lasers).all() and np.isfinite(weights).all()):
        raise InputError("the laser poses and weights must be finite")
    if not (math.isfinite(reach) and reach >= 0.0):
        raise InputError(f"the reach must be a finite number of metres >= 0, got {reach}")
    tolerance = check_tolerance(tolerance)
    if len(weights) < 2:
        return lasers, weights
    order = np.argsort(-weights, kind="stable")
    leaders, summed = _leaders(np.ascontiguousarray(lasers), order, weights, tolerance, float(reach))
    return lasers[leaders], summed


def check_tolerance(tolerance: float) -> float:
    """``tolerance`` (m) as a float when it is finite and >= 0; ValueError naming it otherwise."""
    value = float(tolerance)
    if not (math.isfinite(value) and value >= 0.0):
        raise ValueError(f"the bundle tolerance must be a finite number of metres >= 0, got {tolerance!r}")
    return value
