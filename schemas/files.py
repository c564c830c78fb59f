"""File contracts that outside tools rely on (see docs/formats.md): posed scans, pose distributions,
maps and truth rasters, all NumPy ``.npz``.

Every loader validates the whole file and raises :class:`FormatError` with one sentence naming the file,
the key and the problem. Every saver writes exactly the documented keys, so a file written here loads in
any tool that follows the contract.

Frames and units: poses are (x, y, yaw) of the robot in the map frame, metres and radians; ranges are
metres along the beam from the laser; angles are radians in the laser frame, counter-clockwise from +x.
"""

from __future__ import annotations

import contextlib
import errno
import io
import math
import os
import secrets
import stat
import zipfile
import zlib
from collections.abc import Callable, Iterator, Mapping
from contextvars import ContextVar
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple

import numpy as np

from schemas.errors import FormatError

#: weights must sum to 1 within this absolute tolerance (float32 writers lose ~1e-7 per element)
WEIGHT_SUM_TOLERANCE = 1e-4
#: a raster's origin lies within this many m of the map frame's origin, and its cells are this many m wide
RASTER_ORIGIN_LIMIT = 1e9
RASTER_RESOLUTION_LIMITS = (1e-6, 1e3)


@dataclass(frozen=True)
class PoseSet:
    """Pose distributions for T steps, in one of two forms.

    Either ``samples`` (T, M, 3) float64 with ``weights`` (T, M) summing to 1 per row, or ``mean`` (T, 3)
    with ``cov`` (T, 3, 3). Exactly one form is set; the other pair is None.
    """

    samples: np.ndarray | None = None
    weights: np.ndarray | None = None
    mean: np.ndarray | None = None
    cov: np.ndarray | None = None

    @property
    def is_gaussian(self) -> bool:
        return self.mean is not None

    def gaussian(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean, cov) of the Gaussian form; FormatError unless both are set."""
        if self.mean is None or self.cov is None:
            raise FormatError("a Gaussian pose set needs both 'mean' and 'cov'")
        return self.mean, self.cov

    def weighted_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(samples, weights) of the sample form; FormatError unless both are set."""
        if self.samples is None or self.weights is None:
            raise FormatError("a sampled pose set needs both 'samples' and 'weights'")
        return self.samples, self.weights

    def __len__(self) -> int:
        return len(self.gaussian()[0]) if self.is_gaussian else len(self.weighted_samples()[0])

    def arrays(self) -> dict[str, np.ndarray]:
        """The keys this form writes to a file."""
        if self.is_gaussian:
            mean, cov = self.gaussian()
            return {"mean": mean, "cov": cov}
        samples, weights = self.weighted_samples()
        return {"samples": samples, "weights": weights}


class ScanGeometry(NamedTuple):
    """One scan's laser geometry as the fusion passes take it (mapping.fusion.MonteCarloFusion's arguments after
    the grid and the model): beam angles (B,) rad in the laser frame, range limits m, and the laser's (x m, y m,
    yaw rad) in the robot frame."""

    beam_angles: np.ndarray
    range_min: float
    range_max: float
    sensor_offset: np.ndarray


def _per_scan(value: Any, steps: int, columns: int = 0) -> np.ndarray:
    """``value`` (one for every scan, or one per scan) as a float64 array of one row per scan: (steps,), or
    (steps, columns) when ``columns``. ValueError on another shape."""
    array = np.asarray(value, np.float64)
    shape = (steps, columns) if columns else (steps,)
    if array.shape not in (shape, shape[1:]):
        raise ValueError(f"expected one value per scan {shape} or one for all {shape[1:]}, got shape {array.shape}")
    return np.array(np.broadcast_to(array, shape))


#: the geometry keys of a posed-scan file, each a scalar (every scan) or (T,) (one per scan)
GEOMETRY_KEYS = ("angle_min", "angle_increment", "range_min", "range_max")


@dataclass(frozen=True)
class PosedScans:
    """A posed-scan file: T laser scans, each with its own laser geometry and the robot's pose distribution.

    The geometry fields may be given as one value for every scan (a number; (3,) for the offset) and are kept
    per scan. Scan t's readings are ``ranges[t, :beams[t]]``; the rest of the row is padding (NaN) that nothing
    reads; ``beams`` defaults to every scan using its whole row."""

    ranges: np.ndarray  # float32 (T, Bmax) m; NaN, inf or > range_max: no return (within the scan's beams)
    angle_min: np.ndarray  # float64 (T,) rad, laser frame
    angle_increment: np.ndarray  # float64 (T,) rad
    range_min: np.ndarray  # float64 (T,) m
    range_max: np.ndarray  # float64 (T,) m
    stamps: np.ndarray  # float64 (T,) s
    sensor_offset: np.ndarray  # float64 (T, 3): laser (x, y, yaw) in the robot frame, m and rad
    poses: PoseSet
    beams: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # int64 (T,); empty: whole rows

    def __post_init__(self) -> None:
        steps = len(self.stamps)
        for name in GEOMETRY_KEYS:
            object.__setattr__(self, name, _per_scan(getattr(self, name), steps))
        object.__setattr__(self, "sensor_offset", _per_scan(self.sensor_offset, steps, 3))
        width = self.ranges.shape[1] if np.ndim(self.ranges) == 2 else 0
        beams = np.asarray(self.beams, np.int64)
        if beams.size == 0:  # (the default: every scan's readings fill its row)
            beams = np.full(steps, width, np.int64)
        if np.shape(self.ranges) != (steps, width) or beams.shape != (steps,) or (beams > width).any():
            raise ValueError(f"ranges {np.shape(self.ranges)} and beams {beams.shape} do not fit {steps} scans")
        object.__setattr__(self, "beams", beams)

    def scan_beams(self, t: int) -> int:
        """Scan t's beam count."""
        return int(self.beams[t])

    def scan_ranges(self, t: int) -> np.ndarray:
        """Scan t's own readings (beams[t],) in m."""
        return self.ranges[t, : self.scan_beams(t)]

    def beam_angles(self, t: int) -> np.ndarray:
        """Scan t's beam angles (beams[t],) in rad, laser frame."""
        return self.angle_min[t] + self.angle_increment[t] * np.arange(self.scan_beams(t))

    def geometry(self, t: int) -> ScanGeometry:
        """Scan t's geometry as the fusion passes take it."""
        return ScanGeometry(
            self.beam_angles(t), float(self.range_min[t]), float(self.range_max[t]), self.sensor_offset[t].copy()
        )

    @property
    def uniform(self) -> bool:
        """Whether every scan has the first one's beam count and geometry (a file then holds scalars)."""
        columns = (self.beams, *(getattr(self, name) for name in GEOMETRY_KEYS), self.sensor_offset)
        return all(bool((column == column[:1]).all()) for column in columns)

    def single_geometry(self) -> ScanGeometry:
        """The geometry every scan shares, for a consumer that takes one laser; ValueError when they differ."""
        if not len(self.stamps) or not self.uniform:
            raise ValueError("the scans do not share one laser geometry; take each scan's own (PosedScans.geometry)")
        return self.geometry(0)

    def select(self, index: Any) -> PosedScans:
        """The scans that ``index`` (a slice, a boolean mask or indices) picks, each with its geometry and poses."""
        beams = self.beams[index]
        width = int(beams.max()) if beams.size else 0
        poses = PoseSet(**{key: value[index] for key, value in self.poses.arrays().items()})
        return replace(
            self,
            ranges=self.ranges[index][:, :width],
            stamps=self.stamps[index],
            poses=poses,
            beams=beams,
            sensor_offset=self.sensor_offset[index],
            **{name: getattr(self, name)[index] for name in GEOMETRY_KEYS},
        )

    @classmethod
    def from_scans(cls, scans: Any, poses: PoseSet) -> PosedScans:
        """The scans of ``scans`` (anything with this class's fields but poses, e.g. a slam.simulator.SimRun or a
        slam.laserlog.LaserLog; ``beams`` optional) with the pose distributions ``poses``."""
        names = [member.name for member in fields(cls) if member.name != "poses"]
        return cls(**{name: getattr(scans, name) for name in names if hasattr(scans, name)}, poses=poses)


@dataclass(frozen=True)
class PoseDistributionFile:
    """SLAM output without scans: per step a stamp and a pose distribution."""

    stamps: np.ndarray  # float64 (T,) s
    poses: PoseSet


@dataclass(frozen=True)
class MapFile:
    """An occupancy map raster. Row i covers y in [origin_y + i*res, origin_y + (i+1)*res)."""

    logodds: np.ndarray  # float32 (H, W)
    probability: np.ndarray  # float32 (H, W)
    observed: np.ndarray  # bool (H, W)
    origin: np.ndarray  # float64 (2,): map-frame (x, y) of the lower-left corner of cell [0, 0], m
    resolution: float  # m
    variance: np.ndarray | None = None  # float32 (H, W)
    level: np.ndarray | None = None  # int8 (H, W), adaptive maps only

    @classmethod
    def from_raster(cls, raster: Mapping[str, Any]) -> MapFile:
        """The map file of a grid's ``rasterize()`` dict (its keys are this class's fields; the resolution, m, may
        be a NumPy scalar there)."""
        fields = {name: raster[name] for name in cls.__dataclass_fields__ if name in raster}
        return cls(**{**fields, "resolution": float(raster["resolution"])})


@dataclass(frozen=True)
class TruthRaster:
    """What maps are scored against; same row order and frame as :class:`MapFile`."""

    occupied: np.ndarray  # bool (H, W)
    visible: np.ndarray  # bool (H, W)
    origin: np.ndarray  # float64 (2,)
    resolution: float  # m


# --------------------------------------------------------------------------------------------- reading


def read_npz(path: str | Path, what: str) -> dict[str, np.ndarray]:
    """Every array of the .npz file ``path`` (a ``what``, for messages), read in full; FormatError with one
    sentence when the file is missing, not a .npz archive (a bare .npy array, say) or damaged."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: {not_a_file(path)} (expected a {what} .npz)")
    with open(path, "rb") as handle:
        magic = handle.read(6)
    if magic[:2] != b"PK" and magic != b"\x93NUMPY":  # numpy would call anything else pickled data
        raise FormatError(
            f"{path}: not a .npz archive (a zip of .npy arrays, as numpy.savez writes); expected a {what}"
        )
    try:
        loaded = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise FormatError(f"{path}: not a readable .npz {what} ({exc})") from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):
        raise FormatError(f"{path}: holds one bare array (a .npy file), not the named arrays of a .npz {what}")
    try:
        with loaded as data:  # members are read (and inflated) here, once their headers have been checked
            _check_npz_members(data.zip, path, what)
            return {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, zlib.error) as exc:
        raise FormatError(f"{path}: not a readable .npz {what} ({exc})") from None


#: bytes all arrays of one .npz file may hold once inflated (2 GiB: a map of 2.7 * 10^8 cells); a file past it is
#: refused before anything is inflated (a 2 MB zip bomb inflated to 4.25 GB before it was refused)
MAX_NPZ_BYTES = 2 * 2**30


def _check_npz_members(archive: zipfile.ZipFile, path: Path, what: str) -> None:
    """Refuse (FormatError) a .npz whose members inflate past MAX_NPZ_BYTES, or whose .npy header declares an array
    of another size than the member holds (a header declaring 10^12 elements in a few bytes), reading only the
    zip directory and each member's header."""
    members = [info for info in archive.infolist() if info.filename.endswith(".npy")]
    total = sum(info.file_size for info in members)
    if total > MAX_NPZ_BYTES:
        raise FormatError(
            f"{path}: its arrays would take {total / 2**30:.1f} GiB once inflated, more than the "
            f"{MAX_NPZ_BYTES / 2**30:.0f} GiB a {what} may (a damaged or hostile file?)"
        )
    for info in members:
        with archive.open(info) as member:
            version = np.lib.format.read_magic(member)
            if version not in ((1, 0), (2, 0), (3, 0)):
                raise FormatError(f"{path}: array {info.filename!r} has an unknown .npy version {version}")
            header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )(member, max_header_size=10_000)
            shape, _, dtype = header
            declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if dtype.hasobject or declared + member.tell() != info.file_size:
                raise FormatError(
                    f"{path}: array {info.filename!r} declares shape {shape} of {dtype} "
                    f"({declared} bytes) but holds {info.file_size - member.tell()} bytes"
                )


def _require(data: dict, key: str, path, what: str) -> np.ndarray:
    if key not in data:
        raise FormatError(f"{path}: missing key '{key}' (a {what} needs {_KEYS_HELP[what]})")
    return data[key]


_KEYS_HELP = {
    "posed-scan file": "ranges, angle_min, angle_increment, range_min, range_max, stamps and either "
    "samples+weights or mean+cov",
    "pose-distribution file": "stamps and either samples+weights or mean+cov",
    "map file": "logodds, probability, observed, origin, resolution",
    "truth raster": "occupied, visible, origin, resolution",
}


def _scalar(data: dict, key: str, path, what: str) -> float:
    array = np.asarray(_require(data, key, path, what))
    if array.size != 1 or array.dtype.kind not in "iuf":
        raise FormatError(f"{path}: '{key}' must be a number, got shape {array.shape} dtype {array.dtype}")
    value = float(array.reshape(()))
    if not np.isfinite(value):
        raise FormatError(f"{path}: '{key}' must be finite, got {value}")
    return value


def _numeric(array: np.ndarray, key: str, path) -> np.ndarray:
    """``array`` if it holds real numbers (integers or floats; not text, objects or complex numbers)."""
    array = np.asarray(array)
    if array.dtype.kind not in "iuf":
        raise FormatError(f"{path}: '{key}' must hold real numbers, got dtype {array.dtype}")
    return array


def _flags(array: np.ndarray, key: str, path) -> np.ndarray:
    """``array`` as booleans, if it holds booleans or the integers 0 and 1 only."""
    array = np.asarray(array)
    if array.dtype.kind not in "biu" or (array.dtype.kind != "b" and not np.isin(array, (0, 1)).all()):
        raise FormatError(f"{path}: '{key}' must be boolean (or 0/1), got dtype {array.dtype}")
    return array.astype(bool)


def _within(array: np.ndarray, key: str, path, low: float, high: float) -> np.ndarray:
    """``array`` (real numbers) if every value is finite and in [low, high]."""
    array = _numeric(array, key, path)
    bad = ~(np.isfinite(array) & (array >= low) & (array <= high))
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        bounds = "" if (low, high) == (-np.inf, np.inf) else f" and in [{low:g}, {high:g}]"
        raise FormatError(f"{path}: '{key}' holds {array[index]} at {index}; its values must be finite{bounds}")
    return array


#: how far a map file's ``probability`` may lie from the logistic of its ``logodds`` (float32 writers: about 3e-8)
PROBABILITY_TOLERANCE = 1e-4


def _agrees_with_logodds(probability: np.ndarray, logodds: np.ndarray, path) -> None:
    """Refuse a map whose two occupancy layers disagree (say, a tool that wrote 1 - p): eval scores
    ``probability``, the tiles and exports draw it, and fusion reads ``logodds``."""
    expected = 1.0 / (1.0 + np.exp(-np.asarray(logodds, np.float64)))
    off = np.abs(np.asarray(probability, np.float64) - expected) > PROBABILITY_TOLERANCE
    if off.any():
        index = tuple(int(i) for i in np.argwhere(off)[0])
        raise FormatError(
            f"{path}: 'probability' is not the logistic of 'logodds': at {index} it holds "
            f"{probability[index]:.6g} where logodds {logodds[index]:.6g} gives {expected[index]:.6g}"
        )


def _raster_frame(data: dict, path, what: str) -> tuple[np.ndarray, float]:
    """A raster's ``origin`` (2,) and ``resolution``: within RASTER_ORIGIN_LIMIT m of the map frame's origin and
    RASTER_RESOLUTION_LIMITS m, so every cell index computed from them is exact."""
    origin = _numeric(_require(data, "origin", path, what), "origin", path).astype(np.float64)
    if origin.shape != (2,) or not (np.abs(origin) <= RASTER_ORIGIN_LIMIT).all():
        raise FormatError(
            f"{path}: 'origin' must be 2 finite numbers (x, y) in m within +-{RASTER_ORIGIN_LIMIT:g}, got {origin}"
        )
    resolution = _scalar(data, "resolution", path, what)
    low, high = RASTER_RESOLUTION_LIMITS
    if not low <= resolution <= high:
        raise FormatError(f"{path}: 'resolution' must be in [{low:g}, {high:g}] m, got {resolution:g}")
    return origin, resolution


#: the largest |yaw| a pose file may hold, rad: a full turn (headings wrapped to [-pi, pi) or [0, 2 pi) lie within)
YAW_LIMIT = 2.0 * math.pi


def check_yaw(yaw: np.ndarray, where: str, key: str) -> None:
    """Refuse yaws beyond a full turn (YAW_LIMIT): radians are expected, and a heading in degrees (90, 180, ...)
    would be taken as radians silently (a probe's yaws in degrees gave a map of AUC 0.61 against 0.94, exit 0).
    ``yaw``: (T, ...) rad, one row per step."""
    beyond = np.abs(yaw) > YAW_LIMIT
    if beyond.any():
        step = int(np.argmax(beyond.reshape(len(yaw), -1).any(axis=1)))
        value = float(np.asarray(yaw[step]).flat[int(np.argmax(np.abs(np.asarray(yaw[step]).ravel())))])
        raise FormatError(
            f"{where}: '{key}' holds a yaw of {value:.6g} rad at step {step}, more than a full turn: yaws are radians "
            "wrapped to [-pi, pi] or [0, 2 pi) (headings in degrees: numpy.radians; unwrapped ones: "
            "numpy.angle(numpy.exp(1j * yaw)))"
        )


def validate_pose_set(poses: PoseSet, steps: int, where: str) -> None:
    """Check shapes, finiteness, yaws within a turn, weight sums and covariance symmetry of ``poses`` for ``steps``
    steps."""
    if poses.is_gaussian:
        mean, cov = poses.gaussian()
        if mean.shape != (steps, 3):
            raise FormatError(f"{where}: 'mean' must have shape ({steps}, 3), got {mean.shape}")
        if cov.shape != (steps, 3, 3):
            raise FormatError(f"{where}: 'cov' must have shape ({steps}, 3, 3), got {cov.shape}")
        for key, arr in (("mean", mean), ("cov", cov)):
            bad = ~np.isfinite(arr).all(axis=tuple(range(1, arr.ndim)))
            if bad.any():
                raise FormatError(f"{where}: '{key}' has NaN or inf at step {int(np.argmax(bad))}")
        check_yaw(mean[:, 2], where, "mean")
        asym = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2)) > 1e-9 * (1 + np.abs(cov).max())
        if asym.any():
            raise FormatError(f"{where}: 'cov' is not symmetric at step {int(np.argmax(asym))}")
        eig_min = np.linalg.eigvalsh(cov).min(axis=1) if steps else np.zeros(0)
        neg = eig_min < -1e-12
        if neg.any():
            step = int(np.argmax(neg))
            raise FormatError(
                f"{where}: 'cov' is not positive semi-definite at step {step} (smallest eigenvalue {eig_min[step]:.3g})"
            )
        return
    samples, weights = poses.weighted_samples()
    if samples.ndim != 3 or samples.shape[0] != steps or samples.shape[2] != 3 or samples.shape[1] < 1:
        raise FormatError(f"{where}: 'samples' must have shape ({steps}, M, 3) with M >= 1, got {samples.shape}")
    if weights.shape != samples.shape[:2]:
        raise FormatError(f"{where}: 'weights' must have shape {samples.shape[:2]}, got {weights.shape}")
    bad = ~np.isfinite(samples).all(axis=(1, 2))
    if bad.any():
        raise FormatError(f"{where}: 'samples' has NaN or inf at step {int(np.argmax(bad))}")
    check_yaw(samples[:, :, 2], where, "samples")
    bad = ~np.isfinite(weights).all(axis=1) | (weights < 0).any(axis=1)
    if bad.any():
        raise FormatError(f"{where}: 'weights' has a negative, NaN or inf value at step {int(np.argmax(bad))}")
    sums = weights.sum(axis=1)
    off = np.abs(sums - 1.0) > WEIGHT_SUM_TOLERANCE
    if off.any():
        step = int(np.argmax(off))
        raise FormatError(f"{where}: 'weights' at step {step} sum to {sums[step]:.6g}, not 1")


def _read_pose_set(data: dict, steps: int, path, what: str) -> PoseSet:
    has_samples = "samples" in data or "weights" in data
    has_gauss = "mean" in data or "cov" in data
    if has_samples and has_gauss:
        raise FormatError(f"{path}: holds both samples/weights and mean/cov; keep one pose form")
    if has_gauss:
        poses = PoseSet(
            mean=_numeric(_require(data, "mean", path, what), "mean", path).astype(np.float64),
            cov=_numeric(_require(data, "cov", path, what), "cov", path).astype(np.float64),
        )
    elif has_samples:
        poses = PoseSet(
            samples=_numeric(_require(data, "samples", path, what), "samples", path).astype(np.float64),
            weights=_numeric(_require(data, "weights", path, what), "weights", path).astype(np.float64),
        )
    else:
        raise FormatError(f"{path}: has no poses (a {what} needs samples+weights or mean+cov)")
    validate_pose_set(poses, steps, str(path))
    return poses


def _read_stamps(data: dict, path, what: str, steps: int | None = None) -> np.ndarray:
    stamps = _numeric(_require(data, "stamps", path, what), "stamps", path)
    if stamps.dtype.kind == "f" and stamps.dtype.itemsize < 8:
        raise FormatError(
            f"{path}: 'stamps' must be float64 seconds, got {stamps.dtype} (a float32 or "
            "smaller holds a Unix time only to about 2 minutes)"
        )
    stamps = stamps.astype(np.float64)
    if stamps.ndim != 1 or (steps is not None and stamps.shape[0] != steps):
        raise FormatError(
            f"{path}: 'stamps' must have shape ({steps if steps is not None else 'T'},), got {stamps.shape}"
        )
    if not np.isfinite(stamps).all():
        raise FormatError(f"{path}: 'stamps' has NaN or inf at step {int(np.argmax(~np.isfinite(stamps)))}")
    if stamps.shape[0] == 0:
        raise FormatError(f"{path}: holds no steps (T = 0); a {what} needs at least one")
    return stamps


def require_time_order(stamps: np.ndarray, path, what: str) -> None:
    """FormatError unless ``stamps`` (s) never run backwards: a trajectory scored against another (eval-traj,
    eval-relations) is in time order, and one that is not (its stamps reversed or swapped against its poses) was
    sorted, scored and reported with exit 0 (ATE 5.78 m for 0.059). ``what`` names the file's role."""
    back = np.flatnonzero(np.diff(stamps) < 0.0)
    if len(back):
        k = int(back[0])
        raise FormatError(
            f"{path}: the stamps of {what} run backwards at step {k + 1} ({stamps[k + 1]:.6f} s after "
            f"{stamps[k]:.6f} s); a trajectory is scored in time order: write its rows sorted by time"
        )


def load_posed_scans(path: str | Path) -> PosedScans:
    """Read and validate a posed-scan file (contract in docs/formats.md): its geometry keys as scalars shared
    by every scan or one value per scan, and the optional per-scan beam counts."""
    return _posed_scans_from(read_npz(path, "posed-scan file"), path)


def _posed_scans_from(data: dict, path) -> PosedScans:
    """:func:`load_posed_scans` of the file's arrays ``data``; ``path`` names it in errors."""
    what = "posed-scan file"
    ranges = _numeric(_require(data, "ranges", path, what), "ranges", path)
    if ranges.ndim != 2 or ranges.shape[1] < 1:
        raise FormatError(f"{path}: 'ranges' must have shape (T, B) with B >= 1, got {ranges.shape}")
    steps = ranges.shape[0]
    beams = _read_beams(data, ranges.shape, path)
    geometry = {key: _read_per_scan(data, key, steps, path, what) for key in GEOMETRY_KEYS}
    _check_geometry(geometry, beams, path)
    ranges = ranges.astype(np.float32)
    ranges[np.arange(ranges.shape[1]) >= beams[:, None]] = np.nan  # the padding: nothing reads it
    return PosedScans(
        ranges=ranges,
        stamps=_read_stamps(data, path, what, steps),
        sensor_offset=_read_offset(data, steps, path),
        poses=_read_pose_set(data, steps, path, what),
        beams=beams,
        **geometry,
    )


def _read_beams(data: dict, shape: tuple[int, ...], path) -> np.ndarray:
    """The per-scan beam counts (T,) of a posed-scan file whose ranges have ``shape`` (T, B): its ``beams`` key,
    integers in [1, B], or B for every scan without one."""
    steps, width = shape
    if "beams" not in data:
        return np.full(steps, width, np.int64)
    beams = np.asarray(data["beams"])
    if beams.dtype.kind not in "iu" or beams.shape != (steps,):
        raise FormatError(
            f"{path}: 'beams' must be ({steps},) integers, one beam count per scan, got shape {beams.shape} of "
            f"{beams.dtype}"
        )
    bad = np.flatnonzero((beams < 1) | (beams > width))
    if bad.size:
        raise FormatError(f"{path}: 'beams' is {beams[bad[0]]} at scan {bad[0]}; each must be in [1, {width}]")
    return beams.astype(np.int64)


def _read_per_scan(data: dict, key: str, steps: int, path, what: str) -> np.ndarray:
    """Key ``key`` of a posed-scan file: a finite number shared by every scan, or (T,) finite numbers."""
    array = np.asarray(_require(data, key, path, what))
    if array.size == 1:
        return np.full(steps, _scalar(data, key, path, what))
    if array.shape != (steps,):
        raise FormatError(f"{path}: '{key}' must be a number or ({steps},) numbers (one per scan), got {array.shape}")
    return _within(array, key, path, -np.inf, np.inf).astype(np.float64)


def _check_geometry(geometry: dict[str, np.ndarray], beams: np.ndarray, path) -> None:
    """Refuse a scan whose range limits or beam angles cannot be used (the first such scan named, when the
    file gives the scans different values)."""
    range_min, range_max = geometry["range_min"], geometry["range_max"]
    increment = geometry["angle_increment"]
    bad = np.flatnonzero(~((range_min >= 0) & (range_min < range_max)))
    if bad.size:
        t = int(bad[0])
        raise FormatError(
            f"{path}: need 0 <= range_min < range_max, got {range_min[t]} and {range_max[t]}"
            + _which_scan(t, range_min, range_max)
        )
    bad = np.flatnonzero((increment == 0) & (beams > 1))
    if bad.size:
        t = int(bad[0])
        raise FormatError(
            f"{path}: 'angle_increment' is 0 but the scans have {beams[t]} beams" + _which_scan(t, increment, beams)
        )
    for key in ("angle_min", "angle_increment"):
        bad = np.flatnonzero(np.abs(geometry[key]) > 2 * np.pi)  # beyond a turn, the angles lose the precision
        if bad.size:  # that tells beams apart
            t = int(bad[0])
            raise FormatError(
                f"{path}: '{key}' = {geometry[key][t]} rad is more than a full turn" + _which_scan(t, geometry[key])
            )
    bad = np.flatnonzero(fan_past_a_turn(beams, increment))
    if bad.size:
        t = int(bad[0])
        raise FormatError(
            f"{path}: {beams[t]} beams {increment[t]} rad apart sweep {(beams[t] - 1) * abs(increment[t]):.6g} rad, "
            "more than a full turn, so beams would repeat directions; check 'angle_increment'"
            + _which_scan(t, increment, beams)
        )


def fan_past_a_turn(beams: int | np.ndarray, increment: float | np.ndarray) -> np.bool_ | np.ndarray:
    """Whether a scan's beams sweep more than a full turn (bool, per scan for arrays): the beams then repeat
    directions and the map would count the same walls twice. A fan of exactly a turn (first and last beam on one
    direction, as some 360 deg scanners report) passes; half a beam of slack absorbs rounding."""
    span = (np.asarray(beams, np.float64) - 1) * np.abs(increment)
    return span > 2 * np.pi + 0.5 * np.abs(increment)


def _which_scan(t: int, *columns: np.ndarray) -> str:
    """ " at scan t" when one of the per-scan ``columns`` differs between scans (a file of per-scan values), else
    "" (every scan has the value)."""
    return f" at scan {t}" if any(bool((column != column[0]).any()) for column in columns) else ""


def _read_offset(data: dict, steps: int, path) -> np.ndarray:
    """The laser's pose on the robot, (3,) for every scan or (T, 3) per scan (zeros when absent)."""
    if "sensor_offset" not in data:
        return np.zeros(3)
    offset = _numeric(data["sensor_offset"], "sensor_offset", path).astype(np.float64)
    if offset.shape not in ((3,), (steps, 3)):
        raise FormatError(
            f"{path}: 'sensor_offset' must be 3 finite numbers (x m, y m, yaw rad), or ({steps}, 3) of them (one "
            f"row per scan), got shape {offset.shape}"
        )
    if not np.isfinite(offset).all():
        raise FormatError(f"{path}: 'sensor_offset' holds NaN or inf; it is (x m, y m, yaw rad), finite numbers")
    check_yaw(offset.reshape(-1, 3)[:, 2], str(path), "sensor_offset")  # (a mount of 90 deg turned every scan)
    return offset


def load_pose_distribution(path: str | Path) -> PoseDistributionFile:
    """Read and validate a pose-distribution file (SLAM output without scans)."""
    what = "pose-distribution file"
    data = read_npz(path, what)
    stamps = _read_stamps(data, path, what)
    return PoseDistributionFile(stamps=stamps, poses=_read_pose_set(data, len(stamps), path, what))


def load_map(path: str | Path) -> MapFile:
    """Read and validate a map file."""
    return _map_from(read_npz(path, "map file"), path)


def _map_from(data: dict, path) -> MapFile:
    """:func:`load_map` of the file's arrays ``data``; ``path`` names it in errors."""
    what = "map file"
    logodds = _within(_require(data, "logodds", path, what), "logodds", path, -np.inf, np.inf)
    if logodds.ndim != 2:
        raise FormatError(f"{path}: 'logodds' must be 2-D (H, W), got shape {logodds.shape}")
    shape = logodds.shape
    _require(data, "probability", path, what)
    _require(data, "observed", path, what)
    layers = {}
    for key in ("probability", "observed", "variance", "level"):
        if key in data:
            if data[key].shape != shape:
                raise FormatError(f"{path}: '{key}' has shape {data[key].shape}, 'logodds' has {shape}")
            layers[key] = data[key]
    layers["probability"] = _within(layers["probability"], "probability", path, 0.0, 1.0)
    _agrees_with_logodds(layers["probability"], logodds, path)
    layers["observed"] = _flags(layers["observed"], "observed", path)
    if "variance" in layers:
        layers["variance"] = _within(layers["variance"], "variance", path, 0.0, np.inf)
    if "level" in layers:
        if np.asarray(layers["level"]).dtype.kind not in "iu":
            raise FormatError(f"{path}: 'level' must hold integers, got dtype {np.asarray(layers['level']).dtype}")
        layers["level"] = _within(layers["level"], "level", path, -1, np.iinfo(np.int8).max)
    origin, resolution = _raster_frame(data, path, what)
    return MapFile(
        logodds=logodds.astype(np.float32),
        probability=layers["probability"].astype(np.float32),
        observed=layers["observed"],
        origin=origin,
        resolution=resolution,
        variance=layers["variance"].astype(np.float32) if "variance" in layers else None,
        level=layers["level"].astype(np.int8) if "level" in layers else None,
    )


#: cells a truth raster may hold (2^25: 290 m x 290 m of 0.05 m cells). Scoring takes about 80 bytes a visible
#: cell (their indices, the map's probability over them, the sort for the AUC), so this bounds it near 2.7 GB; a
#: 778 KB file of 20 000 x 20 000 cells took past 19 GB before it was bounded.
MAX_TRUTH_CELLS = 2**25


def load_truth(path: str | Path) -> TruthRaster:
    """Read and validate a truth raster (at most :data:`MAX_TRUTH_CELLS` cells)."""
    return _truth_from(read_npz(path, "truth raster"), path)


def _truth_from(data: dict, path) -> TruthRaster:
    """:func:`load_truth` of the file's arrays ``data``; ``path`` names it in errors."""
    what = "truth raster"
    occupied = _flags(_require(data, "occupied", path, what), "occupied", path)
    visible = _flags(_require(data, "visible", path, what), "visible", path)
    if occupied.ndim != 2 or visible.shape != occupied.shape:
        raise FormatError(
            f"{path}: 'occupied' and 'visible' must be 2-D of one shape, got {occupied.shape} and {visible.shape}"
        )
    if occupied.size > MAX_TRUTH_CELLS:
        rows, columns = occupied.shape
        raise FormatError(
            f"{path}: {rows} x {columns} cells, more than the {MAX_TRUTH_CELLS} a truth raster may hold (scoring "
            "takes about 80 bytes a cell); crop it to the mapped area or give it coarser cells"
        )
    origin, resolution = _raster_frame(data, path, what)
    return TruthRaster(occupied, visible, origin, resolution)


# --------------------------------------------------------------------------------------------- writing


#: what a path that exists but is neither a regular file nor a folder is, by its stat mode (never written to)
_SPECIAL_KINDS = (
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
)


def not_a_file(path: Path) -> str:
    """What ``path``, no regular file, is instead: missing, a folder, a device, a FIFO or a socket."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return "no such file"
    if stat.S_ISDIR(mode):
        return "is a folder, not a file"
    kind = next((name for test, name in _SPECIAL_KINDS if test(mode)), "not a regular file")
    return f"is {kind}, not a regular file"


def output_path_problem(path: str | Path) -> str | None:
    """Why :func:`write_atomically` cannot write ``path``, as a phrase that says what to do (to follow "PATH: "),
    or None when it can: ``path`` is, or links to, a regular file or nothing yet, in a writable folder.

    Refused: an empty path, a name ending in "/", a folder, a device, FIFO or socket (which a rename would replace
    and a write would not store), a path whose folder does not exist or cannot be written (permissions, a
    read-only file system)."""
    text = os.fspath(path)
    if not text:
        return "an empty path names no file; give a file name"
    if text.endswith(os.sep):
        return "ends in a separator, so it names a folder; give a file name"
    target = os.path.realpath(text)  # a symlink is written through: its target takes the file
    subject = f"links to {target}, which is" if os.path.islink(text) else "is"
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:  # a part of the path is a file, a loop of links, a folder it may not search
        return f"cannot be used as a file name ({exc.strerror}); give another path"
    if mode is not None and stat.S_ISDIR(mode):
        return f"{subject} a folder, not a file; give a file name (inside it, if that is where it goes)"
    kind = next((name for test, name in _SPECIAL_KINDS if test(mode)), None) if mode is not None else None
    if kind is not None:
        return f"{subject} {kind}, not a regular file; give the path of a regular file"
    special = _through_system_folder(text)
    if special is not None:
        return (
            f"{special[0]} lies in {special[1]}, which holds devices and process entries, not files (standard "
            "output cannot take a binary file); give the path of a file"
        )
    folder = os.path.dirname(target)
    if not os.path.isdir(folder):
        return f"folder {folder} does not exist; create it first or give a path in an existing folder"
    if not os.access(folder, os.W_OK | os.X_OK):
        return (
            f"folder {folder} cannot be written (its permissions or a read-only file system); give a path in a "
            "writable folder"
        )
    refusal = _trial_file_refused(folder)
    if refusal is not None:
        return f"folder {folder} takes no new file ({refusal}); give a path in a folder of a disk's file system"
    return None


def output_folder_problem(path: str | Path) -> str | None:
    """Why ``path`` cannot be the folder a command writes into (made when missing, in a folder that exists: a mistyped
    parent is not made, as no output path's is), in words with what to do; None when it can."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        return "it exists and is not a folder; give a folder"
    parent = folder.absolute().parent
    if parent.exists() and not parent.is_dir():
        return f"{parent} is a file, not a folder; give a path in a folder"
    if not parent.is_dir():
        return f"folder {parent} does not exist; create it first"
    return None


#: folders of devices and process entries: a link into them (or one that passes through one, as /dev/stdout ->
#: /proc/self/fd/1 does) names no file to write a map into, even where it ends at one (standard output redirected
#: to a file: the map went into the terminal's log, or a pipe's "pipe:[N]" read as a missing folder)
SYSTEM_FOLDERS = ("/dev", "/proc", "/sys")


def _through_system_folder(text: str) -> tuple[str, str] | None:
    """(path, folder): for a ``text`` that is a link, the first of it and the links it passes through (then each
    target, at most 40) that lies in one of SYSTEM_FOLDERS, and that folder; None when none does, or ``text`` is no
    link (a device or a /proc path itself is refused as what it is: output_path_problem)."""
    path = os.path.abspath(text)
    if not os.path.islink(path):
        return None
    for _ in range(40):
        for folder in SYSTEM_FOLDERS:
            if path == folder or path.startswith(folder + os.sep):
                return path, folder
        if not os.path.islink(path):
            return None
        path = os.path.abspath(os.path.join(os.path.dirname(path), os.readlink(path)))
    return None


def _trial_file_refused(folder: str) -> str | None:
    """Why ``folder`` refuses a new file (the error's text), or None when it takes one: permissions pass for root
    in /sys or /proc, whose file systems create no file. The trial is a file with no name (O_TMPFILE), which
    nothing can leave behind; where the file system has none (EOPNOTSUPP), a named one made with O_EXCL and
    removed at once."""
    unnamed = getattr(os, "O_TMPFILE", 0)  # (Linux only)
    if unnamed:
        try:
            os.close(os.open(folder, unnamed | os.O_WRONLY, 0o600))
            return None
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
                return exc.strerror or str(exc)
    trial = os.path.join(folder, f".posegrid-trial.{os.getpid()}.{secrets.token_hex(4)}")
    try:
        os.close(os.open(trial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as exc:
        return exc.strerror or str(exc)
    _discard(trial)
    return None


def write_atomically(path: str | Path, write: Callable[[BinaryIO], object]) -> None:
    """Call ``write`` on a new file beside ``path``, flush it to disk (fsync) and move it onto ``path`` once
    complete, so a failed write (a full disk, an I/O error, an error while writing) leaves no partial file and
    the old contents, and ``path`` is written as given (``np.savez`` would add ".npz" to a name without it).

    A symlink is followed: its target is replaced and the link stays. A replaced file keeps its permission bits.
    A path :func:`output_path_problem` refuses (a device, FIFO, socket or folder, a missing folder) raises an
    OSError before anything is written; every OSError names ``path``."""
    problem = output_path_problem(path)
    if problem is not None:
        raise OSError(errno.EINVAL, problem, os.fspath(path))
    target = os.path.realpath(path)
    partial = os.path.join(
        os.path.dirname(target), f".{os.path.basename(target)[:64]}.{os.getpid()}.{secrets.token_hex(4)}.partial"
    )
    try:
        # O_EXCL: a file or link already at the temporary name is never written through
        with os.fdopen(os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        _keep_permissions(target, partial)
        deferred = _DEFERRED.get()
        if deferred is not None:  # (inside written_together: moved there with the others)
            deferred.append((partial, target, os.fspath(path)))
            return
        os.replace(partial, target)
        _sync_folder(os.path.dirname(target))
    except OSError as exc:
        _discard(partial)
        raise OSError(exc.errno, exc.strerror or str(exc), os.fspath(path)) from None
    except BaseException:
        _discard(partial)
        raise


#: inside :func:`written_together`: the files written so far, (partial, target, path as given)
_DEFERRED: ContextVar[list[tuple[str, str, str]] | None] = ContextVar("_DEFERRED", default=None)


@contextlib.contextmanager
def written_together() -> Iterator[None]:
    """A block whose files are one output: inside it :func:`write_atomically` (and every saver here) writes each file
    beside its place and moves none there; at the block's clean end all are moved into place, one after the other.
    A failed write or an error in the block leaves every old file as it was and no partial one, so an output of
    several files (a PGM and its YAML, a simulator's folder) is never half new and half old. (Not across a crash in
    the moves themselves, which take microseconds.) Not nested."""
    if _DEFERRED.get() is not None:
        raise RuntimeError("written_together blocks do not nest")
    moves: list[tuple[str, str, str]] = []
    token = _DEFERRED.set(moves)
    try:
        yield
    except BaseException:
        for partial, _, _ in moves:
            _discard(partial)
        raise
    finally:
        _DEFERRED.reset(token)
    for done, (partial, target, path) in enumerate(moves):
        try:
            os.replace(partial, target)
        except OSError as exc:
            for left, _, _ in moves[done:]:
                _discard(left)
            raise OSError(exc.errno, exc.strerror or str(exc), path) from None
    for folder in sorted({os.path.dirname(target) for _, target, _ in moves}):
        _sync_folder(folder)


def _keep_permissions(target: str, partial: str) -> None:
    """Give ``partial`` the permission bits of the file ``target`` it replaces (none: the umask's, as created)."""
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        return
    os.chmod(partial, stat.S_IMODE(mode))


def _sync_folder(folder: str) -> None:
    """fsync ``folder`` so the rename into it is on disk too (skipped where folders cannot be opened or synced)."""
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(descriptor)


def _discard(partial: str) -> None:
    """Remove a temporary file left by a failed write, if it is there."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(partial)


def save_posed_scans(path: str | Path, scans: PosedScans) -> None:
    """Write a posed-scan file with exactly the contract's keys; refuses (FormatError) what its loader would refuse,
    so that no file is written that cannot be read back."""
    validate_pose_set(scans.poses, len(scans.stamps), f"the poses to write to {path}")
    # Any: np.savez_compressed's stubs give its ** keywords the type of its own allow_pickle (bool)
    arrays: dict[str, Any] = {
        **_geometry_arrays(scans),
        "stamps": np.asarray(scans.stamps, np.float64),
        **{k: np.asarray(v, np.float64) for k, v in scans.poses.arrays().items()},
    }
    _posed_scans_from(arrays, f"the scans to write to {path}")
    write_atomically(path, lambda handle: np.savez_compressed(handle, **arrays))


def _geometry_arrays(scans: PosedScans) -> dict[str, np.ndarray]:
    """The ranges and geometry keys of a posed-scan file. Scans of one geometry: ``ranges`` (T, B) and scalars,
    as every version of the contract writes them. Otherwise every geometry key per scan ((T,), sensor_offset
    (T, 3)) and ``beams`` (T,), ``ranges`` (T, Bmax) NaN past each scan's beams: a tool that knows only the
    scalar form refuses such a file instead of misreading it."""
    width = int(scans.beams.max()) if len(scans.beams) else scans.ranges.shape[1]
    ranges = np.array(scans.ranges[:, :width], np.float32)
    if scans.uniform:
        return {
            "ranges": ranges,
            **{key: np.float64(getattr(scans, key)[0] if len(scans.stamps) else 0.0) for key in GEOMETRY_KEYS},
            "sensor_offset": np.asarray(scans.sensor_offset[0] if len(scans.stamps) else np.zeros(3), np.float64),
        }
    ranges[np.arange(width) >= scans.beams[:, None]] = np.nan
    return {
        "ranges": ranges,
        **{key: np.asarray(getattr(scans, key), np.float64) for key in GEOMETRY_KEYS},
        "sensor_offset": np.asarray(scans.sensor_offset, np.float64),
        "beams": np.asarray(scans.beams, np.int64),
    }


def save_pose_distribution(path: str | Path, dist: PoseDistributionFile) -> None:
    """Write a pose-distribution file; refuses poses its loader would refuse (a filter that diverged to NaN)."""
    validate_pose_set(dist.poses, len(dist.stamps), f"the poses to write to {path}")
    # Any: as in save_posed_scans
    arrays: dict[str, Any] = {
        "stamps": np.asarray(dist.stamps, np.float64),
        **{k: np.asarray(v, np.float64) for k, v in dist.poses.arrays().items()},
    }
    # stored, not deflated: particles are noisy floats that deflate by about a fifth at 30x the time to write (a
    # 15-minute run of 2 000 particles: 438 MB in 0.8 s against 351 MB in 26 s)
    write_atomically(path, lambda handle: np.savez(handle, **arrays))


def write_npz_deterministic(path: str | Path | BinaryIO, arrays: dict[str, np.ndarray]) -> None:
    """Write an uncompressed ``.npz`` whose bytes depend only on ``arrays`` (fixed zip timestamps).

    ``np.savez`` stamps each member with the wall-clock time, so two saves of one map differ; this
    writer gives byte-identical files for identical maps, which the reproducibility tests rely on.
    """
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for key, value in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            archive.writestr(info, buffer.getvalue())


def save_map(path: str | Path | BinaryIO, map_file: MapFile) -> None:
    """Write a map file. Deterministic: the same map gives the same bytes. Refuses (FormatError) what its loader
    would refuse, so that no file is written that cannot be read back."""
    where = f"the map to write to {path}" if isinstance(path, (str, Path)) else "the map to write"
    arrays = {
        "logodds": np.asarray(map_file.logodds, np.float32),
        "probability": np.asarray(map_file.probability, np.float32),
        "observed": np.asarray(map_file.observed),
        "origin": np.asarray(map_file.origin, np.float64),
        "resolution": np.float64(map_file.resolution),
    }
    if map_file.variance is not None:
        arrays["variance"] = np.asarray(map_file.variance, np.float32)
    if map_file.level is not None:
        arrays["level"] = np.asarray(map_file.level)  # (checked within int8's range before it is cast)
    _map_from(arrays, where)
    arrays["observed"] = arrays["observed"].astype(bool)
    if map_file.level is not None:
        arrays["level"] = arrays["level"].astype(np.int8)
    if isinstance(path, (str, Path)):
        write_atomically(path, lambda handle: write_npz_deterministic(handle, arrays))
    else:  # an open binary file (the API writes into a buffer)
        write_npz_deterministic(path, arrays)


def save_arrays(path: str | Path, arrays: Mapping[str, Any]) -> None:
    """``arrays`` as a compressed .npz at ``path``, written atomically: files whose contents another package defines
    and reads (the simulator's controls.npz and landmarks.npz, slam.simlog)."""
    write_atomically(path, lambda handle: np.savez_compressed(handle, **arrays))


def save_truth(path: str | Path, truth: TruthRaster) -> None:
    """Write a truth raster; refuses (FormatError) what its loader would refuse."""
    arrays = {
        "occupied": np.asarray(truth.occupied),
        "visible": np.asarray(truth.visible),
        "origin": np.asarray(truth.origin, np.float64),
        "resolution": np.float64(truth.resolution),
    }
    _truth_from(arrays, f"the truth raster to write to {path}")
    arrays["occupied"] = arrays["occupied"].astype(bool)
    arrays["visible"] = arrays["visible"].astype(bool)
    write_atomically(path, lambda handle: np.savez_compressed(handle, **arrays))
