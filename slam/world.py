"""The simulated office (the paper's section VII.A setting): straight-edge obstacles, point landmarks and a route.

An office of 20 m x 12 m (map frame, origin at its lower-left outer corner): a corridor 2 m wide along
y in [5, 7], three rooms south of it and three north, each with a 1 m door onto the corridor, one door
between the two south-eastern rooms, and furniture boxes. The robot's route drives east along the corridor,
through the south-eastern room into its neighbour, back onto the corridor where it passed before (a loop),
west to the far end and into a northern room; the route repeats for longer runs.
"""

from __future__ import annotations

import numpy as np

#: a wall from (x0, y0) to (x1, y1) in m; doors are the gaps between collinear pieces
WALLS = (
    # outer walls
    (0.0, 0.0, 20.0, 0.0),
    (20.0, 0.0, 20.0, 12.0),
    (20.0, 12.0, 0.0, 12.0),
    (0.0, 12.0, 0.0, 0.0),
    # corridor, south side (doors at x 3-4, 9.5-10.5, 16-17)
    (0.0, 5.0, 3.0, 5.0),
    (4.0, 5.0, 9.5, 5.0),
    (10.5, 5.0, 16.0, 5.0),
    (17.0, 5.0, 20.0, 5.0),
    # corridor, north side (doors at x 2.5-3.5, 8.5-9.5, 15.5-16.5)
    (0.0, 7.0, 2.5, 7.0),
    (3.5, 7.0, 8.5, 7.0),
    (9.5, 7.0, 15.5, 7.0),
    (16.5, 7.0, 20.0, 7.0),
    # walls between the south rooms (a door at y 2-3 between the middle and the eastern room)
    (7.0, 0.0, 7.0, 5.0),
    (13.0, 0.0, 13.0, 2.0),
    (13.0, 3.0, 13.0, 5.0),
    # walls between the north rooms
    (6.0, 7.0, 6.0, 12.0),
    (12.0, 7.0, 12.0, 12.0),
)

#: furniture as axis-aligned boxes (xmin, ymin, xmax, ymax) in m
BOXES = (
    (1.0, 1.0, 2.5, 1.8),
    (5.5, 0.3, 6.7, 0.9),  # south-west room: desk, cabinet
    (7.5, 0.5, 9.0, 1.3),
    (11.5, 0.3, 12.5, 1.0),  # south-middle room
    (18.0, 1.0, 19.5, 2.5),
    (14.0, 0.4, 15.0, 1.0),  # south-east room
    (1.0, 10.0, 3.0, 11.0),
    (4.6, 8.0, 5.6, 8.6),  # north-west room
    (7.0, 9.5, 8.5, 10.5),
    (10.5, 10.5, 11.5, 11.5),  # north-middle room
    (17.5, 9.5, 19.5, 11.0),
    (13.0, 11.0, 14.0, 11.7),  # north-east room
    (19.4, 5.3, 19.8, 5.7),  # corridor: a bin at the eastern end
)

#: the route's waypoints (m), driven in order and then again from the first
WAYPOINTS = (
    (1.5, 6.0),
    (16.5, 6.0),
    (16.5, 4.0),
    (15.0, 2.5),
    (13.0, 2.5),
    (11.0, 2.8),
    (10.0, 4.0),
    (10.0, 6.0),
    (3.0, 6.0),
    (3.0, 9.0),
    (3.0, 6.0),
)


def box_segments(box: tuple[float, float, float, float]) -> list[tuple[float, float, float, float]]:
    """The four edges (x0, y0, x1, y1) of an axis-aligned box (xmin, ymin, xmax, ymax), counter-clockwise."""
    x0, y0, x1, y1 = box
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def office_segments() -> np.ndarray:
    """All obstacle edges (S, 4) as rows (x0, y0, x1, y1) in m, map frame."""
    rows = list(WALLS)
    for box in BOXES:
        rows.extend(box_segments(box))
    return np.array(rows, dtype=np.float64)


def office_landmarks() -> np.ndarray:
    """Point landmarks (L, 2) in m: along both corridor walls and in every room, 0.15 m off the walls or on a
    furniture corner; two landmarks on either side of one wall are at least 1.5 m apart, so that telling them
    apart is no harder than telling any two apart."""
    corridor = [(x, 5.15) for x in np.arange(1.25, 20.0, 2.5)] + [(x, 6.85) for x in np.arange(2.5, 20.0, 2.5)]
    rooms = [
        (0.15, 2.5),
        (4.0, 0.15),
        (2.5, 1.8),  # south-west (the last on the desk's corner)
        (7.15, 2.5),
        (10.0, 0.15),
        (12.85, 4.0),
        (9.0, 1.3),  # south-middle
        (16.5, 0.15),
        (19.85, 3.5),
        (15.0, 4.0),
        (14.0, 1.0),  # south-east
        (0.15, 9.5),
        (3.0, 11.85),
        (5.85, 8.0),
        (0.8, 7.15),
        (3.0, 10.0),  # north-west
        (9.0, 11.85),
        (11.85, 8.5),
        (6.15, 11.0),  # north-middle
        (16.0, 11.85),
        (19.85, 8.5),
        (12.15, 11.0),  # north-east
    ]
    return np.array(corridor + rooms, dtype=np.float64)
