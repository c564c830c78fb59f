"""The resource limits a mapper shard holds every peer to (docs/security.md, "Limits").

A peer on the Zenoh network can send valid messages that would exhaust a machine: scans of millions of beams,
poses of thousands of samples far from anything, streams that never pair up. Each limit below is an option of
`posegrid mapper` (and `posegrid run`) with the default given here; a message or scan past one is refused,
counted under its kind in the shard's stats and logged once, never fused in part.

- ``max_beams``: beams in one LaserScan (checked when it arrives, before it is held anywhere).
- ``max_work``: what one scan may cost, samples x (beams x ceil(range_max / resolution) + the words of 64 cells of
  its window): the most cells the fusion's rays may visit, with the fold and sweep of its window once a sample
  (:func:`window_cells`; one core does about 10^9 in 1 to 2 s).
- ``map_bound``: every pose sample's x and y, widened by the length of the scan's sensor offset, must lie within this
  many metres of the map origin; with the range limit it bounds the map's extent in all.
- ``max_scan_cells``: cells (at the map's resolution) of the tiles one scan may reach at most (the tiles of its
  samples' positions, widened by range_max and the sensor offset's length): the most a single scan can grow the
  map.
- ``max_map_cells``: cells of the tiles one shard holds (about 10 bytes each in memory); a scan that could add
  tiles past it is refused, so a peer's scans spread over the whole ``map_bound`` cannot take the machine's memory.
- ``join_bytes``: bytes of the scans and poses of every robot together waiting in the join buffer (with the count
  bound, ``--join-buffer``; the oldest of the robot holding the most are evicted and asked for again from the
  histories).
- ``intake_bytes``: bytes of messages waiting in the intake queue between the network and the fusion thread.
- ``max_robots``: robots one shard keeps state for; messages of further robot names are refused.
- ``seq_window``: seqs beyond what a robot's stream has shown that a live message may lie
  (services.state.join.DEFAULT_SEQ_WINDOW); an end-of-stream mark beyond it is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.state.join import DEFAULT_SEQ_WINDOW

#: defaults (docs/security.md gives the reasoning; a 1 081-beam lidar to 30 m with 1 000 samples costs 6.5e8)
DEFAULT_MAX_BEAMS = 32_768
DEFAULT_MAX_WORK = 1_000_000_000
DEFAULT_MAP_BOUND = 1_000.0
DEFAULT_MAX_SCAN_CELLS = 25_000_000
DEFAULT_MAX_MAP_CELLS = 2**27  # 1.3 GB of a shard's layers; 336 000 m2 of 0.05 m cells
DEFAULT_JOIN_BYTES = 64 * 2**20
DEFAULT_INTAKE_BYTES = 256 * 2**20
DEFAULT_MAX_ROBOTS = 64

#: tiles of the box that holds a scan's reach up to which :func:`reach_tiles` lists them (a box of 4 MB of counts)
MAX_REACH_BOX = 1_000_000


@dataclass(frozen=True)
class ShardLimits:
    """The limits above; every field is in the unit its name says (beams, ray cells, m, cells, bytes, robots,
    seqs)."""

    max_beams: int = DEFAULT_MAX_BEAMS
    max_work: int = DEFAULT_MAX_WORK
    map_bound: float = DEFAULT_MAP_BOUND
    max_scan_cells: int = DEFAULT_MAX_SCAN_CELLS
    max_map_cells: int = DEFAULT_MAX_MAP_CELLS
    join_bytes: int = DEFAULT_JOIN_BYTES
    intake_bytes: int = DEFAULT_INTAKE_BYTES
    max_robots: int = DEFAULT_MAX_ROBOTS
    seq_window: int = DEFAULT_SEQ_WINDOW

    def __post_init__(self) -> None:
        for name in (
            "max_beams",
            "max_work",
            "max_scan_cells",
            "max_map_cells",
            "join_bytes",
            "intake_bytes",
            "max_robots",
            "seq_window",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.map_bound) and self.map_bound > 0):
            raise ValueError(f"map_bound must be a positive number of metres, got {self.map_bound}")

    def message_bytes(self) -> int:
        """The largest payload a shard takes off the network: a scan of ``max_beams`` beams (4 bytes a range,
        with room for intensities and the envelope) or a pose of the most samples a message may carry."""
        return 16 * self.max_beams + 2**20

    def check_scan(
        self,
        samples: np.ndarray,
        beams: int,
        range_max: float,
        resolution: float,
        tile_size: int,
        sensor_reach: float = 0.0,
    ) -> tuple[tuple[str, str] | None, int]:
        """(problem, cells): (kind, one sentence) when fusing a scan of ``beams`` beams whose walk reaches
        ``range_max`` m from the laser (the sensor model's reach for the scan's range_max,
        mapping.sensor_model.SensorModel.beam_reach) from pose ``samples`` (M, 3: x m, y m, yaw rad in the map frame)
        would pass a limit, else None; and the cells of the tiles it may reach (:func:`reach_cells`; 0 when refused
        before they are counted). ``sensor_reach`` (m): how far from the robot the laser lies (the length of its sensor
        offset's x, y), so that the bound and the extent hold for the laser's positions and the cells its beams reach,
        not only the robot's. The checks go cheapest first: a cloud spread far is refused before its tiles are
        counted."""
        far = np.abs(samples[:, :2]).max(initial=0.0) + sensor_reach
        if not far <= self.map_bound:
            why = (
                f"the laser of a pose sample may lie {far:.1f} m from the map origin, beyond the map bound "
                f"{self.map_bound:g} m (--map-bound)"
            )
            return ("bound", why), 0
        side = tile_size * resolution
        if not (range_max + sensor_reach) / side < math.isqrt(self.max_scan_cells) / tile_size:  # (inf and nan too)
            # the square of tiles within that reach alone holds more cells than the limit (so reach_cells would
            # refuse it), and its count may be too large for a float: refused before it is counted
            why = (
                f"its beams may reach {range_max:.3g} m from the laser, and the tiles within that reach hold more "
                f"cells than one scan may grow the map by ({self.max_scan_cells:.3g}, --max-scan-cells)"
            )
            return ("extent", why), 0
        cells = reach_cells(samples, range_max + sensor_reach, resolution, tile_size)
        if cells > self.max_scan_cells:
            why = (
                f"its samples and range reach tiles of {cells:.3g} cells, more than one scan may grow "
                f"the map by ({self.max_scan_cells:.3g}, --max-scan-cells)"
            )
            return ("extent", why), cells
        ray_cells = math.ceil(range_max / resolution)
        window_words = math.ceil(window_cells(samples, range_max + sensor_reach, resolution) / 64)
        work = samples.shape[0] * (beams * ray_cells + window_words)
        if work > self.max_work:
            why = (
                f"{samples.shape[0]} samples x ({beams} beams x {ray_cells} cells to "
                f"range_max + {window_words:.3g} words of the scan's window) = {work:.3g}, more than the limit "
                f"{self.max_work:.3g} (--max-work)"
            )
            return ("work", why), cells
        return None, cells


def window_cells(samples: np.ndarray, reach: float, resolution: float) -> int:
    """The cells of the window a scan's fusion walks: the box of the samples' positions widened by ``reach`` m (the
    range and the laser's offset) on every side. The fusion folds and sweeps its bit planes over it once a sample, a
    word of 64 cells at a time, so a cloud of samples spread wide costs that much per sample however few its beams
    (mapping.fusion's scratch window)."""
    if samples.shape[0] == 0:
        return 0
    span = samples[:, :2].max(axis=0) - samples[:, :2].min(axis=0) + 2.0 * reach
    return math.ceil(float(span[0]) / resolution) * math.ceil(float(span[1]) / resolution)


def reach_cells(samples: np.ndarray, range_max: float, resolution: float, tile_size: int) -> int:
    """An upper bound on the cells of the tiles a scan can touch: the tiles of the samples' positions, each widened
    by range_max in every direction, counted without double counting (their union), times cells per tile."""
    return _reach(samples, range_max, resolution, tile_size, listed=False)[0] * tile_size * tile_size


def reach_tiles(samples: np.ndarray, range_max: float, resolution: float, tile_size: int) -> np.ndarray | None:
    """The tiles (tx, ty) of :func:`reach_cells`' union as an (n, 2) int64 array; None when it is too large to list
    (the box that holds it has more than :data:`MAX_REACH_BOX` tiles)."""
    return _reach(samples, range_max, resolution, tile_size, listed=True)[1]


def _reach(
    samples: np.ndarray, range_max: float, resolution: float, tile_size: int, listed: bool
) -> tuple[int, np.ndarray | None]:
    """(count, tiles) of the union above: the count exact when it can be listed, else an upper bound from the box
    that holds the samples' tiles; the tiles listed only when ``listed`` and the union can be. The union is the
    samples' tiles marked in that box, widened by ``reach`` tiles every way through a summed-area table (a sort of the
    tiles and their squares' cells took 0.15 ms for samples in two tiles)."""
    side = tile_size * resolution
    reach = math.ceil(range_max / side)
    width = 2 * reach + 1
    tiles = np.floor(samples[:, :2] / side).astype(np.int64)
    if tiles.shape[0] == 0:
        return 0, np.zeros((0, 2), np.int64)
    if not listed and bool((tiles == tiles[0]).all()):  # (a scan's samples mostly share a tile)
        return width * width, None
    low = tiles.min(axis=0) - reach
    rows, cols = (int(n) for n in tiles.max(axis=0) + reach - low + 1)
    if rows * cols > MAX_REACH_BOX:  # too many to list: the box that holds them
        return min(rows * cols, tiles.shape[0] * width * width), None
    marked = np.zeros((rows + 1, cols + 1), np.int32)  # (a row and a column of zeros first: the table's edges)
    marked[tuple((tiles - low + 1).T)] = 1
    table = marked.cumsum(axis=0).cumsum(axis=1)
    r0, c0 = (np.maximum(np.arange(n) - reach, 0) for n in (rows, cols))
    r1, c1 = (np.minimum(np.arange(n) + reach + 1, n) for n in (rows, cols))
    near = table[r1][:, c1] - table[r0][:, c1] - table[r1][:, c0] + table[r0][:, c0]  # marked tiles within reach
    covered = near > 0
    return int(covered.sum()), np.argwhere(covered) + low if listed else None
