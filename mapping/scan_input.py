"""What both grids (the regular :class:`mapping.fusion.MonteCarloFusion` and the adaptive
:class:`mapping.adaptive.fusion.AdaptiveFusion`) check and prepare before they fuse a scan, written once: the laser's
geometry checked when a fusion is made (:func:`check_laser`), the scan and its pose samples checked
(:func:`check_scan`, the samples alone :func:`check_samples`), the laser's poses in the map frame (:func:`laser_poses`),
identical samples merged (:func:`merge_duplicates`) and the scratch window bounded (:func:`check_window`).
"""

from __future__ import annotations

import math

import numpy as np

from mapping.errors import InputError
from mapping.jit import kernel
from mapping.raytrace import MAX_CELL_INDEX

#: how far from 1 the pose weights may sum (schemas.files.WEIGHT_SUM_TOLERANCE is the file contract's: the same
#: value, which mapping cannot import)
WEIGHT_SUM_TOLERANCE = 1e-4
#: the most cells one scan's scratch window may span. The samples pass keeps about 43 bytes a cell
#: (mapping.fusion.SAMPLES_SCRATCH_BYTES_PER_CELL), so this is about 0.71 GB; it holds a 100 m laser's reach at 0.05 m
#: cells. Pose samples spread wider than that (a diverged
#: estimate) are refused, not allocated.
MAX_WINDOW_CELLS = 1 << 24


@kernel(nogil=True)
def _finite_weighted(samples, weights):  # pragma: no cover - compiled
    """Whether every sample coordinate and weight is finite and every weight >= 0, and the weights' sum."""
    for j in range(samples.shape[0]):
        for i in range(3):
            if not math.isfinite(samples[j, i]):
                return False, 0.0
    total = 0.0
    for w in weights:
        if not (math.isfinite(w) and w >= 0.0):
            return False, 0.0
        total += w
    return True, total


def check_laser(
    beam_angles: np.ndarray, range_min: float, range_max: float, sensor_offset: np.ndarray | tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Validate a laser's geometry and return its beam angles (B,) (rad, laser frame; contiguous float64) and its
    offset (x m, y m, yaw rad) in the robot frame (3,). Refuses a range limit that is not 0 <= range_min < range_max <
    inf, beam angles that are not one finite value per beam, and an offset that is not three finite values."""
    if not 0 <= range_min < range_max or not np.isfinite(range_max):
        raise InputError(f"need 0 <= range_min < range_max < inf, got {range_min} and {range_max}")
    angles = np.ascontiguousarray(beam_angles, dtype=np.float64)
    if angles.ndim != 1:
        raise InputError(f"beam angles must be one value per beam, shape (B,), got shape {angles.shape}")
    if not np.isfinite(angles).all():
        raise InputError(f"beam angle {int(np.argmax(~np.isfinite(angles)))} is NaN or inf; give every beam's angle")
    offset = np.asarray(sensor_offset, dtype=np.float64)
    if offset.shape != (3,) or not np.isfinite(offset).all():
        raise InputError(
            "the sensor offset must be the laser's finite (x m, y m, yaw rad) in the robot frame, got "
            f"{offset.tolist()}"
        )
    return angles, offset


def check_no_return_range(no_return_range: float | None, range_max: float) -> float:
    """How far (m) a beam with no return clears free space: ``no_return_range`` checked to lie in [0, range_max]
    (0: such beams are skipped), or range_max for None. InputError otherwise."""
    if no_return_range is None:
        return float(range_max)
    value = float(no_return_range)
    if not 0.0 <= value <= range_max:
        raise InputError(
            f"the no-return range {no_return_range!r} m must lie in [0, range_max = {range_max:g} m] (how far a beam "
            "with no return clears free space; 0: such beams say nothing)"
        )
    return value


def check_samples(samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate one scan's pose samples (M, 3) (x m, y m, yaw rad; a single pose (3,) is taken as M = 1) and their
    weights (M,): finite, weights non-negative and summing to 1. Returns them as float64 arrays."""
    for name, values in (("pose samples", samples), ("weights", weights)):
        if np.asarray(values).dtype.kind not in "iuf":  # ("1.0" was read as 1, a complex value lost its part)
            raise InputError(f"{name} must be real numbers, got dtype {np.asarray(values).dtype}")
    samples = np.asarray(samples, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if samples.shape == (3,):  # one pose
        samples = samples[None]
    if weights.ndim == 0:
        weights = weights.reshape(1)
    if samples.ndim != 2 or samples.shape[1] != 3 or samples.shape[0] == 0 or weights.shape != samples.shape[:1]:
        raise InputError(f"need M >= 1 samples (M, 3) and weights (M,), got {samples.shape} and {weights.shape}")
    finite, total = _finite_weighted(samples, weights)
    if not finite:
        raise InputError("pose samples and weights must be finite and the weights non-negative")
    if abs(total - 1.0) > WEIGHT_SUM_TOLERANCE:
        raise InputError(f"weights must sum to 1, got {total:.6g}")
    return samples, weights


def check_scan(
    ranges: np.ndarray, samples: np.ndarray, weights: np.ndarray, beams: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate one scan's inputs and return them as arrays: ranges (B,), samples (M, 3), weights (M,)."""
    if np.ma.isMaskedArray(ranges) and np.ma.getmaskarray(ranges).any():  # (np.asarray drops the mask)
        raise InputError("ranges is a masked array with masked beams: give NaN (no return) for them instead")
    ranges = np.asarray(ranges)
    if ranges.shape != (beams,):
        raise InputError(f"scan has {ranges.shape} ranges but the laser has {beams} beams")
    if ranges.dtype.kind not in "iuf":  # (True and "1.0" read as 1 m, None as no return, complex lost its part)
        raise InputError(f"ranges must be real numbers (m; NaN or inf: no return), got dtype {ranges.dtype}")
    samples, weights = check_samples(samples, weights)
    return ranges, samples, weights


@kernel(nogil=True, error_model="numpy")
def _laser_poses(samples, ox, oy, oyaw):  # pragma: no cover - compiled
    poses = np.empty((samples.shape[0], 3))
    for j in range(samples.shape[0]):
        x, y, yaw = samples[j, 0], samples[j, 1], samples[j, 2]
        c = math.cos(yaw)
        s = math.sin(yaw)
        poses[j, 0] = x + c * ox - s * oy
        poses[j, 1] = y + s * ox + c * oy
        poses[j, 2] = yaw + oyaw
    return poses


def check_window(x_lo: float, y_lo: float, x_hi: float, y_hi: float, reach: float, resolution: float) -> None:
    """Refuse a scan whose scratch window cannot be held, before any cell index is computed from it: one that
    reaches beyond MAX_CELL_INDEX cells from the origin, or spans more than MAX_WINDOW_CELLS cells. The laser
    poses lie in [x_lo, x_hi] x [y_lo, y_hi] (m) and ``reach`` (m) is the rays' longest reach."""
    farthest = max(abs(x_lo), abs(x_hi), abs(y_lo), abs(y_hi))
    if not (farthest + reach) / resolution <= MAX_CELL_INDEX:  # also NaN and inf
        raise InputError(
            f"a scan {farthest:.6g} m from the map origin with rays {reach:.6g} m long reaches beyond "
            f"the {MAX_CELL_INDEX * resolution:.3g} m that {resolution} m cells cover"
        )
    # + the origin's alignment (8 cells, a shard's 64: mapping.fusion), a cell to spare and the samples pass's padding
    # to whole 64-cell words
    width = (x_hi - x_lo + 2 * reach) / resolution + 128
    height = (y_hi - y_lo + 2 * reach) / resolution + 65
    if width * height > MAX_WINDOW_CELLS:
        raise InputError(
            f"one scan would span about {width:.0f} x {height:.0f} cells of {resolution} m, more than the "
            f"{MAX_WINDOW_CELLS} a scan may: its pose samples spread over {x_hi - x_lo:.4g} m x "
            f"{y_hi - y_lo:.4g} m and its rays reach {reach:.4g} m (a diverged pose estimate, or a range "
            f"limit too long for this resolution?)"
        )


def laser_poses(samples: np.ndarray, sensor_offset: np.ndarray) -> np.ndarray:
    """Laser poses (M, 3) in the map frame from robot poses (M, 3) and the laser's (x, y, yaw) in the robot frame
    (compiled: the dozen array operations this takes in numpy cost a tenth of a one-pose scan)."""
    ox, oy, oyaw = np.asarray(sensor_offset, dtype=np.float64).tolist()
    return _laser_poses(np.ascontiguousarray(samples, dtype=np.float64), ox, oy, oyaw)


def merge_duplicates(samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge identical pose samples (summing their weights) and drop zero-weight ones.

    Resampled particle filters repeat many particles; merging them before ray casting gives the same map
    for less work. Order: first occurrence of each distinct pose.
    """
    if len(weights) == 1 and weights[0] > 0:
        return samples, weights
    keep = weights > 0
    samples, weights = samples[keep], weights[keep]
    if len(samples) == 1 or np.unique(samples[:, 0]).size == len(samples):  # distinct x: distinct poses (fast)
        return samples, weights
    unique, first, inverse = np.unique(samples, axis=0, return_index=True, return_inverse=True)
    if len(unique) == len(samples):
        return samples, weights
    merged = np.bincount(inverse.ravel(), weights=weights, minlength=len(unique))
    order = np.argsort(first)
    return unique[order], merged[order]
