"""The check of pose covariances (x m, y m, yaw rad; m^2, m rad, rad^2) given to the library, written once: for a
Gaussian pose to fuse (mapping.poses), a trajectory to score (slam.scoring) and a pose graph's edges
(slam.posegraph). The file contract checks its own (schemas.files.validate_pose_set), which names the file.
"""

from __future__ import annotations

import numpy as np

from mapping.errors import InputError

#: relative tolerance of a covariance's symmetry and of its negative eigenvalues (rounding), of its largest entry
COVARIANCE_RTOL = 1e-9


def check_covariances(cov: np.ndarray, name: str = "cov") -> None:
    """InputError unless every covariance of the stack (T, 3, 3) is symmetric and positive semi-definite, both to
    :data:`COVARIANCE_RTOL` of its largest entry (rounding); the message names the first bad step. O(T), vectorised.
    A singular one (a pose known exactly along an axis: the known start, a single particle) passes."""
    scale = np.abs(cov).max(axis=(1, 2))
    tolerance = COVARIANCE_RTOL * scale
    asymmetry = np.abs(cov - np.swapaxes(cov, 1, 2)).max(axis=(1, 2))
    bad = np.flatnonzero(asymmetry > tolerance)
    if len(bad):
        t = int(bad[0])
        raise InputError(
            f"{name}[{t}] is not symmetric (|C - C^T| up to {asymmetry[t]:.3g}): give covariances (T, 3, 3) of "
            "(x m, y m, yaw rad); if it is an information matrix or a square root, convert it first"
        )
    lowest = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, 1, 2)))[:, 0]
    bad = np.flatnonzero(lowest < -tolerance)
    if len(bad):
        t = int(bad[0])
        raise InputError(
            f"{name}[{t}] is not positive semi-definite (eigenvalue {lowest[t]:.3g}): a covariance has no negative "
            "variance; check how it was computed"
        )
