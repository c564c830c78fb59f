"""Grid cells crossed by line segments (exact traversal, Amanatides & Woo 1987) and the simulator's truth raster.

Grid convention (DESIGN.md): cell (i, j) covers x in [origin_x + j res, origin_x + (j+1) res) and
y in [origin_y + i res, origin_y + (i+1) res); row i grows with y.
"""

from __future__ import annotations

import math

import numpy as np

from mapping.jit import kernel
from slam.errors import InputError

#: cells a truth raster may hold: schemas.files.MAX_TRUTH_CELLS (load_truth refuses more), stated again here because
#: slam/ does not import schemas/ (tests/test_layers.py); tests/test_slam_inputs.py checks that the two agree
MAX_TRUTH_CELLS = 2**25


@kernel(inline="always")
def _axis_start(g0, i, d):  # pragma: no cover - compiled
    """Along one axis of a segment that starts at grid coordinate g0 (cells), in cell i, and moves d cells
    along it: (the fraction of the segment at which it crosses its first cell border on this axis, the
    fraction between two such crossings); inf for both when d is 0."""
    if d > 0:
        return (i + 1 - g0) / d, abs(1.0 / d)
    if d < 0:
        return (g0 - i) / -d, abs(1.0 / d)
    return math.inf, math.inf


@kernel()
def _mark_traversed(grid, x0, y0, x1, y1, origin_x, origin_y, resolution):  # pragma: no cover - compiled
    height, width = grid.shape
    for k in range(x0.shape[0]):
        gx0 = (x0[k] - origin_x) / resolution
        gy0 = (y0[k] - origin_y) / resolution
        gx1 = (x1[k] - origin_x) / resolution
        gy1 = (y1[k] - origin_y) / resolution
        ix = int(math.floor(gx0))
        iy = int(math.floor(gy0))
        ex = int(math.floor(gx1))
        ey = int(math.floor(gy1))
        dx = gx1 - gx0
        dy = gy1 - gy0
        step_x = 1 if dx > 0 else -1
        step_y = 1 if dy > 0 else -1
        t_max_x, t_delta_x = _axis_start(gx0, ix, dx)
        t_max_y, t_delta_y = _axis_start(gy0, iy, dy)
        if 0 <= iy < height and 0 <= ix < width:
            grid[iy, ix] = True
        for _ in range(abs(ex - ix) + abs(ey - iy)):
            # the guards keep the walk on the end cell whatever rounding does to t_max near it
            if iy == ey or (ix != ex and t_max_x < t_max_y):
                ix += step_x
                t_max_x += t_delta_x
            else:
                iy += step_y
                t_max_y += t_delta_y
            if 0 <= iy < height and 0 <= ix < width:
                grid[iy, ix] = True


def mark_segments(
    grid: np.ndarray, starts: np.ndarray, ends: np.ndarray, origin: np.ndarray, resolution: float
) -> None:
    """Set to True, in place, every cell of the bool ``grid`` (H, W) crossed by a segment from starts (R, 2)
    to ends (R, 2) (m, map frame), both end cells included; cells outside the grid are skipped."""
    starts = np.ascontiguousarray(starts, dtype=np.float64)
    ends = np.ascontiguousarray(ends, dtype=np.float64)
    _mark_traversed(
        grid, starts[:, 0], starts[:, 1], ends[:, 0], ends[:, 1], float(origin[0]), float(origin[1]), float(resolution)
    )


def raster_frame(segments: np.ndarray, resolution: float, margin: float = 1.0) -> tuple[np.ndarray, tuple[int, int]]:
    """Origin (2,) and shape (H, W) of a grid covering the segments (S, 4) with ``margin`` m around them.

    The origin sits half a cell off the segments' bounding box so that walls on round coordinates run
    through cell centres rather than along cell borders.
    """
    low = np.minimum(segments[:, :2], segments[:, 2:]).min(axis=0) - margin - resolution / 2.0
    high = np.maximum(segments[:, :2], segments[:, 2:]).max(axis=0) + margin
    width, height = np.ceil((high - low) / resolution).astype(int) + 1
    return low, (int(height), int(width))


def check_raster_resolution(segments: np.ndarray, resolution: float) -> None:
    """InputError unless ``resolution`` (m) is finite and > 0 and the raster :func:`raster_frame` makes over the
    segments (S, 4) holds at most :data:`MAX_TRUTH_CELLS` cells (what load_truth reads back). Counted in floating
    point, so a tiny resolution does not overflow the count."""
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise InputError(f"truth_resolution must be a finite number of metres > 0, got {resolution!r}")
    low = np.minimum(segments[:, :2], segments[:, 2:]).min(axis=0) - 1.0 - resolution / 2.0
    high = np.maximum(segments[:, :2], segments[:, 2:]).max(axis=0) + 1.0
    with np.errstate(over="ignore"):
        cells = float(np.prod(np.ceil((high - low) / resolution) + 1.0))
    if cells > MAX_TRUTH_CELLS:
        coarsest = float(np.sqrt(np.prod(high - low) / MAX_TRUTH_CELLS))
        raise InputError(
            f"truth_resolution {resolution:g} m makes a truth raster of {cells:.3g} cells, more than the "
            f"{MAX_TRUTH_CELLS} a truth raster may hold; use cells of at least about {coarsest:.3g} m"
        )


def truth_raster(
    segments: np.ndarray, sensor_xy: np.ndarray, endpoints: np.ndarray, resolution: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truth raster of a simulated run: (occupied, visible, origin).

    occupied: cells an obstacle edge (S, 4) passes through. visible: cells crossed by a noise-free beam from
    the sensor position sensor_xy (R, 2) to its endpoint (R, 2) (the hit point, or range_max along the beam
    for no return), end cell included. Both bool (H, W); origin (2,) in m.
    """
    origin, shape = raster_frame(segments, resolution)
    occupied = np.zeros(shape, dtype=bool)
    mark_segments(occupied, segments[:, :2], segments[:, 2:], origin, resolution)
    visible = np.zeros(shape, dtype=bool)
    mark_segments(visible, sensor_xy, endpoints, origin, resolution)
    return occupied, visible, origin
