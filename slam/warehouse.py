"""A seeded warehouse for a modern lidar (issue 34): a 100 m x 100 m hall of pallet racks, aisles and open areas.

Layout (map frame, origin at the hall's lower-left outer corner; all m):

- the dock, an open area along the south wall (y < 16), with pallets standing about and two rows of pillars;
- the west rack block, x in [4, 46], y in [20, 84.2]: 16 rows of racks 1.2 m deep along x, 3 m aisles between
  them, cut by a cross aisle at x in [24, 27.5];
- a central open lane, x in [46, 56], with pillars along both sides;
- the east rack block, x in [56, 95], y in [22, 84]: 10 rows of racks 1.2 m wide along y, 3 m aisles between
  them, cut by a cross aisle at y in [50, 54];
- a north open area (y > 86) with pallets.

The seed varies the racks (an outer end cut back by up to 1.5 m, one section in twelve left out: an open bay)
and where the pallets stand (never within PATH_CLEARANCE of the route). The route runs north up the west block's
cross aisle, east along an aisle, north up the central lane, east across the north area, south down an east
aisle into the dock and west along it back to the start: about 260 m, repeated for longer runs.

:func:`simulate_warehouse` drives it with :func:`slam.simulator.simulate_world`: a 1081-beam lidar over 270 deg
(angle_min -3 pi / 4, 0.25 deg apart) to 30 m at 40 Hz, the robot at up to 1.5 m/s. The warehouse has no point
landmarks (its runs are for the mapping benchmarks).
"""

from __future__ import annotations

import math

import numpy as np

from slam.simulator import SimRun, World, simulate_world
from slam.world import box_segments

#: the hall's side (m)
SIZE = 100.0
#: rack depth and aisle width (m)
RACK_DEPTH, AISLE = 1.2, 3.0
#: the route (m); the robot starts at the first waypoint facing the second
ROUTE = (
    (25.75, 12.0),
    (25.75, 39.5),
    (51.0, 39.5),
    (51.0, 92.0),
    (75.5, 92.0),
    (75.5, 10.0),
    (25.75, 10.0),
)
#: no pallet comes closer than this to the route (m)
PATH_CLEARANCE = 2.0
#: the lidar: beams, field of view (rad), range (m), rate (Hz); the robot's top speed (m/s)
N_BEAMS, FOV, RANGE_MAX, RATE_HZ, SPEED = 1081, 1.5 * math.pi, 30.0, 40.0, 1.5

Box = tuple[float, float, float, float]


def _rack_sections(
    rows: np.ndarray, spans: tuple[tuple[float, float], ...], along_x: bool, rng: np.random.Generator
) -> list[Box]:
    """Racks (xmin, ymin, xmax, ymax) at the row starts ``rows`` (m across the racks) over the sections ``spans``
    (m along them); each section's outer end (the one away from the cross aisle) is cut back by up to 1.5 m and
    one section in twelve is left out."""
    boxes = []
    for row in rows:
        for index, (start, end) in enumerate(spans):
            if rng.random() < 1 / 12:
                continue
            cut = rng.uniform(0.0, 1.5)
            lo, hi = (start + cut, end) if index == 0 else (start, end - cut)
            across = (float(row), float(row) + RACK_DEPTH)
            boxes.append((lo, across[0], hi, across[1]) if along_x else (across[0], lo, across[1], hi))
    return boxes


def _pillars() -> list[Box]:
    """0.6 m square pillars: two rows across the dock and one down either side of the central lane."""
    half = 0.3
    centres = [(x, y) for x in np.arange(12.0, 96.0, 12.0) for y in (4.0, 14.5) if abs(x - 25.75) > 3.0]
    centres += [(x, y) for x in (46.6, 55.4) for y in np.arange(22.0, 86.0, 12.0)]
    return [(x - half, y - half, x + half, y + half) for x, y in centres if abs(x - 75.5) > 3.0]


def _route_distance(points: np.ndarray) -> np.ndarray:
    """Distance (P,) in m from each point (P, 2) to the closed route."""
    route = np.array(ROUTE)
    starts, ends = route, np.roll(route, -1, axis=0)
    best = np.full(len(points), np.inf)
    for a, b in zip(starts, ends):
        e = b - a
        u = np.clip(((points - a) @ e) / (e @ e), 0.0, 1.0)
        best = np.minimum(best, np.hypot(*(points - a - u[:, None] * e).T))
    return best


def _pallets(rng: np.random.Generator, count: int, area: Box) -> list[Box]:
    """``count`` pallets (1.2 m x 1.0 m, either way round) in ``area``, none within PATH_CLEARANCE of the route
    (a pallet drawn there is drawn again)."""
    x0, y0, x1, y1 = area
    boxes: list[Box] = []
    while len(boxes) < count:
        w, h = (1.2, 1.0) if rng.random() < 0.5 else (1.0, 1.2)
        x, y = rng.uniform(x0, x1 - w), rng.uniform(y0, y1 - h)
        corners = np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h], [x + w / 2, y + h / 2]])
        if _route_distance(corners).min() > PATH_CLEARANCE:
            boxes.append((x, y, x + w, y + h))
    return boxes


def warehouse_world(seed: int = 0) -> World:
    """The warehouse of the module docstring: its obstacle edges, no landmarks, the route."""
    rng = np.random.default_rng(seed)
    pitch = RACK_DEPTH + AISLE
    west = _rack_sections(20.0 + pitch * np.arange(16), ((4.0, 24.0), (27.5, 46.0)), True, rng)
    east = _rack_sections(56.0 + pitch * np.arange(10), ((22.0, 50.0), (54.0, 84.0)), False, rng)
    clutter = _pallets(rng, 24, (1.0, 1.0, 99.0, 15.5)) + _pallets(rng, 12, (1.0, 86.5, 99.0, 99.0))
    rows = [(0.0, 0.0, SIZE, 0.0), (SIZE, 0.0, SIZE, SIZE), (SIZE, SIZE, 0.0, SIZE), (0.0, SIZE, 0.0, 0.0)]
    for box in west + east + _pillars() + clutter:
        rows.extend(box_segments(box))
    return World(np.array(rows, dtype=np.float64), np.zeros((0, 2)), np.array(ROUTE))


def simulate_warehouse(seed: int = 0, steps: int = 400, truth_resolution: float = 0.05) -> SimRun:
    """``steps`` scans of the warehouse (``seed`` picks its layout and the run's noise) at RATE_HZ; the truth
    raster has cells of ``truth_resolution`` m."""
    return simulate_world(
        warehouse_world(seed),
        seed=seed,
        steps=steps,
        n_beams=N_BEAMS,
        range_max=RANGE_MAX,
        fov=FOV,
        dt=1.0 / RATE_HZ,
        truth_resolution=truth_resolution,
        max_speed=SPEED,
    )
