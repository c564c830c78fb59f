"""What `posegrid fuse` does, as a function other processes reuse (the mapper shards fuse each scan the
same way, so a sharded map equals the in-process one cell for cell)."""

from __future__ import annotations

import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Generator
from contextlib import closing
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict, TypeVar

import numpy as np
from tqdm import tqdm

from mapping.errors import InputError
from mapping.fusion import FusionThreads, MonteCarloFusion, ScanInput
from mapping.grid import TiledGrid
from mapping.poses import scan_samples
from mapping.sensor_model import SensorModel
from schemas.files import GEOMETRY_KEYS, PosedScans, ScanGeometry

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
        # the fields (mode, n_samples, seed, accuracy) are scan_samples' own arguments
        return scan_samples(
            mean=mean, cov=cov, samples=samples, weights=weights, seq=seq, range_max=range_max, **vars(self)
        )


class FusionOptions(TypedDict, total=False):
    """How :func:`fuse_posed_scans` fuses, every key optional.

    mode: "mc" (all pose samples, the paper's method; the default) or "ml" (the most likely pose only).
    model: the inverse sensor model (default: SensorModel(resolution), resolution in m, default 0.05).
    n_samples: Gaussian draws per scan, None (the default) to derive them from the covariance and ``accuracy``
    (m, default one cell). seed: with the scan's seq, seeds the draws (default 0). progress: show a progress bar.
    threads: scans fused side by side (mapping.fusion.FusionThreads; default 1; the regular grid only): the map is
    the same bit for bit for any count. bundle: the pose bundles' tolerance in m (mapping.bundling; default 0, exact;
    the regular grid only).
    """

    mode: str
    model: SensorModel
    resolution: float
    n_samples: int | None
    seed: int
    accuracy: float | None
    progress: bool
    threads: int
    bundle: float


def fuse_posed_scans(
    posed: PosedScans,
    *,
    grid: TiledGrid | None = None,
    owns_tile: Callable[[int, int], bool] | None = None,
    **options: Unpack[FusionOptions],
) -> TiledGrid:
    """Fuse every scan of a posed-scan file into a tiled grid (``grid``, else a new one; with ``owns_tile``, only
    the tiles it accepts) as ``options`` say, and return it. Raises the InputError of the first scan refused (the
    scans before it fused, none after it)."""
    model = _model(options)
    tiled = grid or TiledGrid(model.resolution)
    threads = FusionThreads(options.get("threads", 1))  # (shared by the fusions of every laser geometry)
    scans = _scans(
        posed,
        lambda geometry: MonteCarloFusion(
            tiled, model, *geometry, owns_tile, threads=threads, bundle=options.get("bundle", 0.0)
        ),
        model,
        options,
    )
    with closing(scans):
        for outcome in threads.fuse_iter(scans):
            if isinstance(outcome, InputError):
                raise outcome
    return tiled


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
    adaptive = grid or AdaptiveGrid(model.resolution)
    scans = _scans(posed, lambda geometry: AdaptiveFusion(adaptive, model, *geometry, params), model, options)
    with closing(scans):
        for fusion, (ranges, samples, weights) in scans:
            fusion.fuse(ranges, samples, weights)
    return adaptive


def _model(options: FusionOptions) -> SensorModel:
    return options.get("model") or SensorModel(resolution=options.get("resolution", 0.05))


#: laser geometries (beam count and angles, range limits, offset) whose fusion pass one fusion keeps at once, most
#: recently used first; past it the least recently used is dropped (its scratch freed) and made again when a scan
#: of its geometry comes back, which costs time, not a different map. 8: an interlaced laser's four geometries,
#: twice (two lasers on one topic)
FUSIONS_KEPT = 8

#: a fusion pass (mapping.fusion.MonteCarloFusion, mapping.adaptive.AdaptiveFusion)
Fusion = TypeVar("Fusion")

#: s one scan of `posegrid fuse` may take before it says why (a scan takes milliseconds; one that needs a kernel
#: not yet compiled, where their cache is cold, waits for the compiler: up to a minute on 2 cores, said by nothing)
SLOW_SCAN = 5.0
SLOW_SCAN_NOTE = (
    "posegrid fuse: the fusion kernels are compiling (once after an install or a change of posegrid, up to a "
    "minute or two on 2 cores; `make install` compiles them ahead)..."
)


class SlowScanWatch:
    """Says :data:`SLOW_SCAN_NOTE` on standard error, once, when no scan has finished for ``seconds`` (a thread
    that looks twice a second; :meth:`beat` after each scan, a float written)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.last = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="slow-scan-watch", daemon=True)
        self._thread.start()

    def beat(self) -> None:
        self.last = time.monotonic()

    def close(self) -> None:
        self._stop.set()
        self._thread.join()

    def _watch(self) -> None:
        while not self._stop.wait(min(0.5, self.seconds)):
            if time.monotonic() - self.last > self.seconds:
                print(SLOW_SCAN_NOTE, file=sys.stderr, flush=True)
                return


def _scans(
    posed: PosedScans, make: Callable[[ScanGeometry], Fusion], model: SensorModel, options: FusionOptions
) -> Generator[tuple[Fusion, ScanInput], None, None]:
    """Every scan, in order, with the fusion pass of its own laser geometry and its pose samples drawn as ``options``
    say: (pass, (ranges (B,) m, samples (M, 3), weights (M,))). ``make(geometry)`` makes the pass of a geometry (all
    passes write into one grid), and the last FUSIONS_KEPT are kept."""
    accuracy = options.get("accuracy")
    sampling = PoseSampling(
        options.get("mode", "mc"),
        options.get("n_samples"),
        options.get("seed", 0),
        accuracy if accuracy is not None else model.resolution,
    )
    progress = options.get("progress", False)
    arrays = posed.poses.arrays()  # mean and cov, or samples and weights: (T, ...) each
    passes: OrderedDict[tuple, Fusion] = OrderedDict()
    steps = range(len(posed.stamps))
    # (disable None: no bar when stderr is no terminal, a log file or a pipe)
    watch = SlowScanWatch(SLOW_SCAN) if progress else None
    with tqdm(total=len(steps), desc="fusing", unit="scan", disable=None if progress else True, mininterval=0.5) as bar:
        try:
            for t in steps:  # the bar closes (its line ends) when the caller closes this generator, before any error
                range_max = float(posed.range_max[t])
                samples, weights = sampling.draw(t, range_max, **{name: array[t] for name, array in arrays.items()})
                yield _pass_for(passes, posed, t, make), (posed.scan_ranges(t), samples, weights)
                bar.update()
                if watch is not None:
                    watch.beat()
        finally:
            if watch is not None:
                watch.close()


def _pass_for(
    passes: OrderedDict[tuple, Fusion], posed: PosedScans, t: int, make: Callable[[ScanGeometry], Fusion]
) -> Fusion:
    """The fusion pass of scan t's geometry from ``passes`` (most recently used last), made when missing."""
    key = (posed.scan_beams(t), *(float(getattr(posed, name)[t]) for name in GEOMETRY_KEYS))
    key += tuple(posed.sensor_offset[t].tolist())
    fuse = passes.get(key)
    if fuse is None:
        fuse = passes[key] = make(posed.geometry(t))
        while len(passes) > FUSIONS_KEPT:
            passes.popitem(last=False)
    else:
        passes.move_to_end(key)
    return fuse
