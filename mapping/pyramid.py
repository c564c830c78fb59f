"""Zoom levels of a tiled map: each level halves the resolution by combining 2 x 2 blocks of cells.

Level 0 is the grid itself (cells of ``resolution`` m, tiles of T x T cells). A level-z tile (x, y) has
T x T cells of 2^z * resolution m and covers the level-0 tiles [x*2^z, (x+1)*2^z) x [y*2^z, (y+1)*2^z);
its four children are the level-(z-1) tiles (2x + dx, 2y + dy), dx, dy in {0, 1}. Arrays are indexed
[row = y, col = x] as everywhere in posegrid, so child (2x, 2y) fills the lower-left quarter.

The combination rule, applied level by level (a level-z cell is the combination of its four level-(z-1)
cells, not of the 4^z level-0 cells below it):

    observed = any child observed
    logodds  = mean of the observed children's log-odds      (0 when no child is observed)
    variance = mean of the observed children's variances      (0 when no child is observed)

Averaging log-odds keeps the coarse cell's probability between its children's; averaging only over
observed children keeps unknown space from pulling a half-seen block towards 0.5.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapping.errors import InputError

#: (logodds float32, variance float32, observed bool), each (T, T), row = y
TileLayers = tuple[np.ndarray, np.ndarray, np.ndarray]

#: child offsets (dx, dy) in the order :func:`combine_children` takes them
CHILD_OFFSETS = ((0, 0), (1, 0), (0, 1), (1, 1))


def downsample(logodds: np.ndarray, variance: np.ndarray, observed: np.ndarray) -> TileLayers:
    """Combine every 2 x 2 block of (2H, 2W) layers into one cell of (H, W) layers by the module's rule."""
    logodds = np.asarray(logodds)
    if logodds.ndim != 2 or logodds.shape[0] % 2 or logodds.shape[1] % 2:
        raise InputError(f"downsample needs 2-D layers of even shape, got {logodds.shape}")
    if np.shape(variance) != logodds.shape or np.shape(observed) != logodds.shape:
        raise InputError(f"layers differ in shape: {logodds.shape}, {np.shape(variance)}, {np.shape(observed)}")
    rows, cols = logodds.shape[0] // 2, logodds.shape[1] // 2
    seen = np.asarray(observed, bool).reshape(rows, 2, cols, 2)
    count = seen.sum(axis=(1, 3))
    divisor = np.maximum(count, 1)

    def mean_of_seen(layer: np.ndarray) -> np.ndarray:
        blocks = np.asarray(layer, np.float64).reshape(rows, 2, cols, 2)
        return (np.where(seen, blocks, 0.0).sum(axis=(1, 3)) / divisor).astype(np.float32)

    return mean_of_seen(logodds), mean_of_seen(variance), count > 0


def combine_children(children: Sequence[TileLayers | None], tile_size: int) -> TileLayers:
    """The parent tile of four child tiles given in :data:`CHILD_OFFSETS` order; None = a child with no data."""
    if len(children) != 4:
        raise InputError(f"a tile has 4 children, got {len(children)}")
    size = int(tile_size)
    logodds = np.zeros((2 * size, 2 * size), np.float32)
    variance = np.zeros((2 * size, 2 * size), np.float32)
    observed = np.zeros((2 * size, 2 * size), bool)
    for (dx, dy), child in zip(CHILD_OFFSETS, children):
        if child is None:
            continue
        block = (slice(dy * size, (dy + 1) * size), slice(dx * size, (dx + 1) * size))
        for target, layer in zip((logodds, variance, observed), child):
            if np.shape(layer) != (size, size):
                raise InputError(f"child ({dx}, {dy}) has shape {np.shape(layer)}, not ({size}, {size})")
            target[block] = layer
    return downsample(logodds, variance, observed)


def children_of(x: int, y: int) -> list[tuple[int, int]]:
    """The four child tile indices of tile (x, y), in :data:`CHILD_OFFSETS` order."""
    return [(2 * x + dx, 2 * y + dy) for dx, dy in CHILD_OFFSETS]


def tile_range(first: int, last: int, z: int) -> tuple[int, int]:
    """Level-z tile indices covering level-0 tile indices first..last (floor division: works below 0)."""
    return first >> z, last >> z


def top_level(x_range: tuple[int, int], y_range: tuple[int, int]) -> int:
    """The smallest level z at which level-0 tiles x_range x y_range (inclusive) span at most 2 x 2 tiles.

    Not "one tile": tiles on either side of a map-frame axis never share a parent (-1 >> z stays -1,
    0 >> z stays 0), so a map around the origin never fits in one tile.
    """
    z = 0
    while any(last - first > 1 for first, last in (tile_range(*x_range, z), tile_range(*y_range, z))):
        z += 1
    return z
