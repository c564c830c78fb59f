"""The adaptive grid (paper, section VI): a region quadtree over the tiled world frame that keeps fine cells
only where the scans show structure, fused with the same Monte Carlo rule as the regular grid.

- :mod:`mapping.adaptive.tree`: the active cells in sorted arrays (linear quadtree), lookups, rasterising;
- :mod:`mapping.adaptive.evidence`: one compiled pass per scan gathers log-odds moments and weighted
  hits, misses and unknowns at every level;
- :mod:`mapping.adaptive.splitting`: the chi-square split test and its expected distributions;
- :mod:`mapping.adaptive.merging`: the three merge rules;
- :mod:`mapping.adaptive.fusion`: the per-scan sequence (activate, split, update, merge).

docs/adaptive.md explains the method and its choices.
"""

from mapping.adaptive.fusion import AdaptiveFuseResult, AdaptiveFusion, AdaptiveParams, level_for_cell_size
from mapping.adaptive.merging import MergeRules
from mapping.adaptive.splitting import SplitTest
from mapping.adaptive.tree import AdaptiveGrid

__all__ = [
    "AdaptiveFuseResult",
    "AdaptiveFusion",
    "AdaptiveGrid",
    "AdaptiveParams",
    "MergeRules",
    "SplitTest",
    "level_for_cell_size",
]
