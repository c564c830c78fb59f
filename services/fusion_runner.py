"""What `posegrid fuse` does, as a function other processes reuse (the mapper shards fuse each scan the
same way, so a sharded map equals the in-process one cell for cell)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict

import numpy as np
from tqdm import tqdm

from mapping.fusion import MonteCarloFusion
from mapping.grid import TiledGrid
from mapping.poses import scan_samples
from mapping.sensor_model import SensorModel
from schemas.files import PosedScans

if TYPE_CHECKING:
    from typing_extensions import Unpack

    from mapping.adaptive import AdaptiveGrid, AdaptiveParams


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


class FusionOptions(TypedDict, total=False):
    """How :func:`fuse_posed_scans` fuses, every key optional.

    mode: "mc" (all pose samples, the paper's method; the default) or "ml" (the most likely pose only).
    model: the inverse sensor model (default: SensorModel(resolution), resolution in m, default 0.05).
    n_samples: Gaussian draws per scan, None (the default) to derive them from the covariance and ``accuracy``
    (m, default one cell). seed: with the scan's seq, seeds the draws (default 0). progress: show a progress bar.
    """

    mode: str
    model: SensorModel
    resolution: float
    n_samples: int | None
    seed: int
    accuracy: float | None
    progress: bool


def fuse_posed_scans(
    posed: PosedScans,
    *,
    grid: TiledGrid | None = None,
    owns_tile: Callable[[int, int], bool] | None = None,
    **options: Unpack[FusionOptions],
) -> TiledGrid:
    """Fuse every scan of a posed-scan file into a tiled grid (``grid``, else a new one; with ``owns_tile``, only
    the tiles it accepts) as ``options`` say, and return it."""
    model = _model(options)
    grid = grid or TiledGrid(model.resolution)
    fusion = MonteCarloFusion(grid, model, *_beam_geometry(posed), owns_tile)
    _fuse_each_scan(posed, fusion.fuse, model, options)
    return grid


def fuse_posed_scans_adaptive(
    posed: PosedScans,
    *,
    params: AdaptiveParams | None = None,
    grid: AdaptiveGrid | None = None,
    **options: Unpack[FusionOptions],
) -> AdaptiveGrid:
    """As :func:`fuse_posed_scans`, into an adaptive grid (docs/adaptive.md) whose finest cells are the model's
    resolution; ``params`` sets its start level, split test and merge rules."""
    from mapping.adaptive import AdaptiveFusion, AdaptiveGrid  # scipy.stats: only when an adaptive map is made

    model = _model(options)
    grid = grid or AdaptiveGrid(model.resolution)
    fusion = AdaptiveFusion(grid, model, *_beam_geometry(posed), params)
    _fuse_each_scan(posed, fusion.fuse, model, options)
    return grid


def _model(options: FusionOptions) -> SensorModel:
    return options.get("model") or SensorModel(resolution=options.get("resolution", 0.05))


def _beam_geometry(posed: PosedScans) -> tuple[np.ndarray, float, float, np.ndarray]:
    """(beam angles rad, range_min m, range_max m, sensor offset) of the scans, as the fusion passes take them."""
    return posed.beam_angles, posed.range_min, posed.range_max, posed.sensor_offset


def _fuse_each_scan(
    posed: PosedScans,
    fuse: Callable[[np.ndarray, np.ndarray, np.ndarray], object],
    model: SensorModel,
    options: FusionOptions,
) -> None:
    """Call ``fuse(ranges, samples, weights)`` for every scan, in order, with its pose samples drawn as
    ``options`` say."""
    accuracy = options.get("accuracy")
    sampling = PoseSampling(
        options.get("mode", "mc"),
        options.get("n_samples"),
        options.get("seed", 0),
        accuracy if accuracy is not None else model.resolution,
    )
    progress = options.get("progress", False)
    arrays = posed.poses.arrays()  # mean and cov, or samples and weights: (T, ...) each
    steps = range(len(posed.stamps))
    for t in tqdm(steps, desc="fusing", unit="scan", disable=not progress, mininterval=0.5):
        samples, weights = sampling.draw(t, posed.range_max, **{name: array[t] for name, array in arrays.items()})
        fuse(posed.ranges[t], samples, weights)
