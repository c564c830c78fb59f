"""When four sibling cells merge into their parent (paper, section VI.B, after Einhorn et al.).

Siblings merge if any of three rules holds for their occupancy probabilities p_1..p_4:

1. their standard deviation is below ``std_max`` and their mean is within ``margin`` of 0 (certainly free)
   or of 1 (certainly occupied);
2. all four are above ``above``;
3. all four are below ``below``.

The merged cell takes the mean of the children's log-odds, so little is lost: siblings merge only when they
agree or are all nearly certain. It also takes the mean of their variances and the sum of their carried hits
and misses. Merging is checked from the finest level up and repeats as long as merges happen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapping.adaptive.tree import AdaptiveGrid, children, unique_cells
from mapping.errors import InputError


@dataclass(frozen=True)
class MergeRules:
    """Thresholds of the three merge rules, all on probabilities in [0, 1].

    ``MergeRules(std_max=0, margin=0, above=1, below=0)`` never merges.
    """

    std_max: float = 0.05
    margin: float = 0.15
    above: float = 0.9
    below: float = 0.2

    def __post_init__(self) -> None:
        for name in ("std_max", "margin", "above", "below"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(f"merge threshold {name} must be in [0, 1], got {value}")

    def mergeable(self, logodds: np.ndarray) -> np.ndarray:
        """(N,) bool: which groups of four siblings, log-odds (N, 4), satisfy a rule."""
        p = 1.0 / (1.0 + np.exp(-np.asarray(logodds, dtype=float)))
        mean = p.mean(axis=1)
        agree = (p.std(axis=1) < self.std_max) & ((mean < self.margin) | (mean > 1.0 - self.margin))
        return agree | (p > self.above).all(axis=1) | (p < self.below).all(axis=1)


def merge_siblings(
    grid: AdaptiveGrid,
    level: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    rules: MergeRules,
    max_level: int,
    undone: Callable[[int, np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> int:
    """Merge the active siblings of cells (level, ax, ay) by ``rules``, recursively up to ``max_level``.

    A group of four is merged when all four are active cells of one level and a rule holds, unless
    ``undone(parent_level, px, py, carried)`` (carried: (N, 2) the children's summed hits and misses) says
    the split test would split the parent again. Returns the number of merges.
    """
    level = np.asarray(level, np.int64)
    frontier_x, frontier_y = ax[level == 0], ay[level == 0]
    merges = 0
    for k in range(max_level):
        px, py = unique_cells(frontier_x >> 1, frontier_y >> 1)
        kx, ky = children(px, py)
        kids = grid.find_exact(np.full(kx.shape, k), kx, ky).reshape(-1, 4)
        safe = np.maximum(kids, 0)
        carried = np.stack([grid.hits[safe].sum(axis=1), grid.misses[safe].sum(axis=1)], axis=1)
        merge = (kids >= 0).all(axis=1) & rules.mergeable(grid.logodds[safe])
        if undone is not None and merge.any():
            merge[merge] = ~undone(k + 1, px[merge], py[merge], carried[merge])
        merged_x, merged_y = px[merge], py[merge]
        if merge.any():
            grid.edit(
                kids[merge].ravel(),
                np.full(merged_x.shape, k + 1),
                merged_x,
                merged_y,
                grid.logodds[kids[merge]].astype(np.float64).mean(axis=1),
                grid.variance[kids[merge]].astype(np.float64).mean(axis=1),
                carried[merge, 0],
                carried[merge, 1],
            )
            merges += int(merge.sum())
        at_next = level == k + 1
        frontier_x = np.concatenate([ax[at_next], merged_x])
        frontier_y = np.concatenate([ay[at_next], merged_y])
    return merges
