"""Per tile of a scan's window, the bounding box of the cells a fusion touched: what a shard publishes of a tile after
the scans it fused (services.state.shard), with no copy of the tile kept to compare against.

A box is kept as (ly0, lx0, ly1, lx1), tile-local cells, inclusive, in an int64 array of one box per tile of the
window (:func:`empty_boxes`), widened by the walks once their cells are marked (the samples pass's
:func:`mapping.samples_pass.listed_boxes`, the one-sample pass's count of its touched blocks). :func:`tile_windows`
gives the touched tiles' boxes as the (row0, col0, rows, cols) windows of a tile update, :func:`join_windows` the
window that holds two.
"""

from __future__ import annotations

import numpy as np

from mapping.jit import kernel

#: a box no cell has widened yet (every widening takes the min of the first two, the max of the last two)
EMPTY = (2**62, 2**62, -1, -1)


def empty_boxes(tiles_shape: tuple[int, int]) -> np.ndarray:
    """(nty, ntx, 4) int64 boxes, all empty, for a window of nty x ntx tiles."""
    boxes = np.empty((*tiles_shape, 4), np.int64)
    boxes[...] = EMPTY
    return boxes


@kernel(nogil=True, error_model="numpy", inline="always")
def widen_box(boxes, ty, tx, ly0, lx0, ly1, lx1):  # pragma: no cover - compiled
    """Widen window tile (ty, tx)'s box to hold the tile-local cells ly0..ly1 x lx0..lx1."""
    boxes[ty, tx, 0] = min(boxes[ty, tx, 0], ly0)
    boxes[ty, tx, 1] = min(boxes[ty, tx, 1], lx0)
    boxes[ty, tx, 2] = max(boxes[ty, tx, 2], ly1)
    boxes[ty, tx, 3] = max(boxes[ty, tx, 3], lx1)


def tile_windows(parts: list[np.ndarray], touched: np.ndarray) -> list[tuple[int, int, int, int]]:
    """The boxes of the touched tiles (``touched``: bool per tile of the window), in row order (as np.nonzero lists
    them), joined over ``parts`` (the boxes of a scan's parts, walked over the same window), each as (row0, col0,
    rows, cols) tile-local cells."""
    joined = parts[0].copy()
    for part in parts[1:]:
        np.minimum(joined[..., :2], part[..., :2], out=joined[..., :2])
        np.maximum(joined[..., 2:], part[..., 2:], out=joined[..., 2:])
    return [
        (int(ly0), int(lx0), int(ly1 - ly0 + 1), int(lx1 - lx0 + 1))
        for ly0, lx0, ly1, lx1 in joined[np.nonzero(touched)].tolist()
    ]


def join_windows(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The smallest window (row0, col0, rows, cols) that holds windows ``a`` and ``b``."""
    row0, col0 = min(a[0], b[0]), min(a[1], b[1])
    return row0, col0, max(a[0] + a[2], b[0] + b[2]) - row0, max(a[1] + a[3], b[1] + b[3]) - col0
