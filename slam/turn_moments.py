"""A linearised pose Gaussian moment-matched to the turn its heading error makes (the "banana" of dead reckoning and
EKF-SLAM), for the poses a Gaussian filter gives out.

A heading error of a Gaussian filter is not only an error in the heading: every position the robot reaches after it
is turned about the place where the error arose. Linearised, a turn by theta about a centre c moves a position p0 by
theta J (p0 - c) (J the quarter turn), so the filter's covariance holds it as a thin strip across the lever arm and
the position and heading errors correlate nearly perfectly. The turn itself is not linear: it also pulls the position
towards c by (1 - cos theta) |p0 - c|, which the strip leaves out. With a heading sd of 0.2 rad and a lever arm of
10 m that is 0.2 m, many times the strip's width: the truth falls outside the 95 % region although the heading is
right to 1 sd (a simulated robot with three times MRCLAM's motion noise, given its true noise: inside95 0.004; with
the moments here 0.85; docs/slam.md, "Turned moments").

**The model.** The position is p = c + R(theta) L + e, with theta ~ N(0, s^2) the heading error, L = p0 - c the lever
arm and e ~ N(0, S_rest) independent of theta (what else the position is unsure of). Its linearisation is the
filter's covariance: Cov(p, theta) = s^2 J L and Cov(p) = s^2 (J L)(J L)^T + S_rest, so L follows from the
covariance alone (no centre is assumed). What the linearisation leaves out is the pull along L: R(theta) L =
|L| (cos theta u + sin theta J u), u = L / |L|, and with E cos theta = exp(-s^2 / 2), E cos^2 theta = (1 +
exp(-2 s^2)) / 2,

    E p      = p0 - (1 - exp(-s^2 / 2)) L
    Cov(p)   = the filter's + ((1 + exp(-2 s^2)) / 2 - exp(-s^2)) L L^T

while the heading, the position across L and their covariance stay the filter's: a real heading error is many small
turns about the places along the path where they arose, and across L the linear terms are right to first order for
each (taking them from one turn of sd s, which shrinks them by exp(-s^2 / 2) and more, covered the truth less often:
0.81 against 0.85 on the robot above). For a small s the pull is s^2 / 2 L and the variance s^4 / 2 |L|^2 along L:
where the heading is sure they change nothing that shows; for a large one they stay bounded (by L and |L|^2 / 2).
Units: m and rad, map frame.
"""

from __future__ import annotations

import numpy as np

#: the quarter turn J (rad): J (x, y) = (-y, x)
QUARTER_TURN = np.array([[0.0, -1.0], [1.0, 0.0]])


def turned_moments(mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean (3,) and covariance (3, 3) of a pose (x m, y m, theta rad) whose linearised Gaussian is ``mean`` and
    ``cov``, with the pull towards the centre of the turn its heading error makes (module docstring). A pose whose
    heading is certain is given back as it is."""
    mean = np.asarray(mean, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    s2 = float(cov[2, 2])
    out_mean, out_cov = mean.copy(), cov.copy()
    if not s2 > 0.0:
        return out_mean, out_cov
    lever = -QUARTER_TURN @ (cov[:2, 2] / s2)  # L = J^-1 (J L), J L the position's move per radian (m/rad)
    decay = np.exp(-0.5 * s2)
    along = 0.5 * (1.0 + decay**4) - decay * decay  # Var(cos theta)
    out_mean[:2] -= (1.0 - decay) * lever
    out_cov[:2, :2] += along * np.outer(lever, lever)
    return out_mean, out_cov
