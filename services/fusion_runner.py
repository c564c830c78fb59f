"""What `posegrid fuse` does, as a function other processes reuse (the mapper shards fuse each scan the
same way, so a sharded map equals the in-process one cell for cell)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from mapping.adaptive import AdaptiveFusion, AdaptiveGrid, AdaptiveParams
from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.poses import scan_samples
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans


@dataclass(frozen=True)
class PoseSampling:
    """How the pose samples a scan is fused with are drawn: the one path `posegrid fuse` and the mapper shards
    (services.state.shard) both take, so that a sharded map equals the in-process one cell for cell.

    mode: "mc" (every sample, or Gaussian draws) or "ml" (the most likely pose only); n_samples: Gaussian draws per
    scan, None to derive them from the covariance and ``accuracy`` (m); seed: with the scan's seq, seeds the draws.
    """

    mode: str = "mc"
    n_samples: int | None = None
    seed: int = 0
    accuracy: float = 0.05

    def draw(
        self,
        seq: int,
        range_max: float,
        *,
        mean: np.ndarray | None = None,
        cov: np.ndarray | None = None,
        samples: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(samples (M, 3): x m, y m, yaw rad; weights (M,)) for scan ``seq`` (laser range limit ``range_max`` m) of a
        Gaussian pose (``mean`` (3,), ``cov`` (3, 3)) or a weighted sample set (``samples`` (K, 3), ``weights``
        (K,)): :func:`mapping.poses.scan_samples`, the Gaussian draws seeded by (seed, seq)."""
        return scan_samples(
            self.mode,
            mean=mean,
            cov=cov,
            samples=samples,
            weights=weights,
            n_samples=self.n_samples,
            seed=self.seed,
            seq=seq,
            accuracy=self.accuracy,
            range_max=range_max,
        )


def fuse_posed_scans(
    posed: PosedScans,
    *,
    mode: str = "mc",
    model: SensorModel | None = None,
    resolution: float = 0.05,
    n_samples: int | None = None,
    seed: int = 0,
    accuracy: float | None = None,
    grid: TiledGrid | None = None,
    owns_tile: Callable[[int, int], bool] | None = None,
    progress: bool = False,
) -> TiledGrid:
    """Fuse every scan of a posed-scan file into a tiled grid and return it.

    mode: "mc" (all pose samples, the paper's method) or "ml" (the most likely pose only).
    model: the inverse sensor model (default: SensorModel(resolution)). n_samples: Gaussian draws per scan,
    None to derive them from the covariance and ``accuracy`` (m, default one cell).
    """
    model = model or SensorModel(resolution=resolution)
    grid = grid or TiledGrid(model.resolution)
    fusion = MonteCarloFusion(
        grid, model, posed.beam_angles, posed.range_min, posed.range_max, posed.sensor_offset, owns_tile
    )
    _fuse_each_scan(posed, fusion.fuse, mode, n_samples, seed, accuracy, model, progress)
    return grid


def fuse_posed_scans_adaptive(
    posed: PosedScans,
    *,
    mode: str = "mc",
    model: SensorModel | None = None,
    resolution: float = 0.05,
    n_samples: int | None = None,
    seed: int = 0,
    accuracy: float | None = None,
    params: AdaptiveParams | None = None,
    grid: AdaptiveGrid | None = None,
    progress: bool = False,
) -> AdaptiveGrid:
    """As :func:`fuse_posed_scans`, into an adaptive grid (docs/adaptive.md) whose finest cells are the model's
    resolution; ``params`` sets its start level, split test and merge rules."""
    model = model or SensorModel(resolution=resolution)
    grid = grid or AdaptiveGrid(model.resolution)
    fusion = AdaptiveFusion(
        grid, model, posed.beam_angles, posed.range_min, posed.range_max, posed.sensor_offset, params
    )
    _fuse_each_scan(posed, fusion.fuse, mode, n_samples, seed, accuracy, model, progress)
    return grid


def _fuse_each_scan(
    posed: PosedScans,
    fuse: Callable[[np.ndarray, np.ndarray, np.ndarray], object],
    mode: str,
    n_samples: int | None,
    seed: int,
    accuracy: float | None,
    model: SensorModel,
    progress: bool,
) -> None:
    """Call ``fuse(ranges, samples, weights)`` for every scan, in order."""
    sampling = PoseSampling(mode, n_samples, seed, accuracy if accuracy is not None else model.resolution)
    arrays = posed.poses.arrays()  # mean and cov, or samples and weights: (T, ...) each
    steps = range(len(posed.stamps))
    for t in tqdm(steps, desc="fusing", unit="scan", disable=not progress, mininterval=0.5):
        samples, weights = sampling.draw(t, posed.range_max, **{name: array[t] for name, array in arrays.items()})
        fuse(posed.ranges[t], samples, weights)
