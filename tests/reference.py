"""Slow, independent reference implementations the compiled code is tested against.

Cells along a ray are found by collecting every crossing of a vertical or horizontal grid line (no DDA),
sorting them and taking the cell at each piece's midpoint; the model is evaluated with scipy's erf.
"""

from __future__ import annotations

import math
from itertools import pairwise

import numpy as np

from mapping.sensor_model import TAIL_SIGMAS, SensorModel


def cells_on_ray(x0: float, y0: float, angle: float, length: float, res: float) -> list[tuple[int, int, float, float]]:
    """(ix, iy, r_in, r_out) of every cell the ray crosses with positive length, by grid-line crossings."""
    dx, dy = math.cos(angle), math.sin(angle)
    ts = [0.0, length]
    for origin, d in ((x0, dx), (y0, dy)):
        if abs(d) < 1e-15:
            continue
        end = origin + d * length
        lo, hi = sorted((origin, end))
        for k in range(math.floor(lo / res), math.ceil(hi / res) + 1):
            t = (k * res - origin) / d
            if 0.0 < t < length:
                ts.append(t)
    ts = sorted(set(ts))
    out = []
    for t_in, t_out in pairwise(ts):
        if t_out - t_in <= 1e-12:
            continue
        mid = 0.5 * (t_in + t_out)
        out.append((math.floor((x0 + mid * dx) / res), math.floor((y0 + mid * dy) / res), t_in, t_out))
    return out


def reference_cell_logodds(model: SensorModel, r_in: float, r_out: float, z: float) -> float:
    """The model's largest log-odds over [r_in, r_out] for a return at z, by dense evaluation."""
    r = np.linspace(r_in, r_out, 2001)
    r_peak = float(model.peak_range(z))
    if r_in < r_peak < r_out:
        r = np.append(r, r_peak)
    return float(np.max(model.logodds(r, z)))


def reference_fuse(
    model: SensorModel,
    angles: np.ndarray,
    range_min: float,
    range_max: float,
    ranges: np.ndarray,
    samples: np.ndarray,
    weights: np.ndarray,
    offset=(0.0, 0.0, 0.0),
    no_return_range: float | None = None,
) -> tuple[dict, dict]:
    """One scan's per-cell weighted mean and spread {(ix, iy): value}, by brute force; a beam with no return is free
    space up to ``no_return_range`` m (None: range_max; 0: it is left out)."""
    clear = range_max if no_return_range is None else no_return_range
    per_sample = []
    for x, y, yaw in samples:
        lx = x + math.cos(yaw) * offset[0] - math.sin(yaw) * offset[1]
        ly = y + math.sin(yaw) * offset[0] + math.cos(yaw) * offset[1]
        values: dict[tuple[int, int], float] = {}
        for angle, z in zip(angles, ranges):
            no_return = np.isnan(z) or z > range_max  # -inf (too close) falls below range_min
            if (not no_return and z < range_min) or (no_return and clear == 0.0):
                continue
            length = clear if no_return else z + TAIL_SIGMAS * float(model.sigma_at(z))
            for ix, iy, r_in, r_out in cells_on_ray(lx, ly, yaw + offset[2] + angle, length, model.resolution):
                y_cell = model.l_free if no_return else reference_cell_logodds(model, r_in, r_out, float(z))
                values[(ix, iy)] = max(values.get((ix, iy), -np.inf), y_cell)
        per_sample.append(values)
    cells = set().union(*per_sample)
    mean = {c: sum(w * v.get(c, 0.0) for w, v in zip(weights, per_sample)) for c in cells}
    spread = {c: sum(w * v.get(c, 0.0) ** 2 for w, v in zip(weights, per_sample)) - mean[c] ** 2 for c in cells}
    return mean, spread
