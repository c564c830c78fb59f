"""Small worlds built in code for tests: a rectangular room seen by a laser, with exact ranges; and the tile-ownership
patterns of a shard that the walk tests take."""

from __future__ import annotations

import numpy as np

from schemas.files import PosedScans, PoseSet


def room_ranges(poses: np.ndarray, angles: np.ndarray, width: float, height: float) -> np.ndarray:
    """Exact ranges (T, B) from laser poses (T, 3) inside the box [0, width] x [0, height] to its walls."""
    theta = poses[:, 2:3] + angles[None, :]
    c, s = np.cos(theta), np.sin(theta)
    x, y = poses[:, 0:1], poses[:, 1:2]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx = np.where(c > 0, (width - x) / c, np.where(c < 0, -x / c, np.inf))
        ty = np.where(s > 0, (height - y) / s, np.where(s < 0, -y / s, np.inf))
    return np.minimum(tx, ty)


def room_posed_scans(
    steps: int = 20, beams: int = 90, seed: int = 0, gaussian: bool = True, particles: int = 10, range_max: float = 8.0
) -> PosedScans:
    """A robot turning in place near the centre of a 4 m x 3 m room, with honest pose distributions."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-np.pi, np.pi, beams, endpoint=False)
    truth = np.column_stack([np.full(steps, 2.0), np.full(steps, 1.5), np.linspace(0, 1.0, steps)])
    ranges = room_ranges(truth, angles, 4.0, 3.0) + rng.normal(0, 0.01, (steps, beams))
    cov = np.tile(np.diag([0.02**2, 0.02**2, 0.01**2]), (steps, 1, 1))
    mean = truth + rng.normal(0, 1, (steps, 3)) * np.array([0.02, 0.02, 0.01])
    if gaussian:
        poses = PoseSet(mean=mean, cov=cov)
    else:
        samples = mean[:, None, :] + rng.normal(0, 1, (steps, particles, 3)) * np.array([0.02, 0.02, 0.01])
        weights = rng.random((steps, particles))
        poses = PoseSet(samples=samples, weights=weights / weights.sum(axis=1, keepdims=True))
    return PosedScans(
        ranges=ranges.astype(np.float32),
        angle_min=float(angles[0]),
        angle_increment=float(angles[1] - angles[0]),
        range_min=0.05,
        range_max=range_max,
        stamps=np.arange(steps) * 0.1,
        sensor_offset=np.zeros(3),
        poses=poses,
    )


#: the names :func:`ownership_pattern` takes
OWNERSHIP_PATTERNS = ("checkerboard", "stripes", "random", "blocks")


def ownership_pattern(name: str, size: int = 16) -> np.ndarray:
    """Which of size x size tiles (rows ty, columns tx) a shard owns: "checkerboard", "stripes" (two columns of three),
    "random" (each tile with probability 1/2, seed 1), or "blocks" (a checkerboard of 4 x 4 tiles, so that many rays
    stay in one shard's tiles)."""
    tx, ty = np.meshgrid(np.arange(size), np.arange(size))
    if name == "random":
        return np.random.default_rng(1).random((size, size)) < 0.5
    return {"checkerboard": (tx + ty) % 2 == 0, "stripes": tx % 3 != 1, "blocks": (tx // 4 + ty // 4) % 2 == 0}[name]
