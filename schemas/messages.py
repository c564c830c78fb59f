"""Every wire message posegrid sends over Zenoh, each defined once (fields, specs, cross-field rules).

Encoding, validating decoding and the JSON Schema docs (docs/messages/) all derive from these
definitions (:mod:`schemas.wire`, :mod:`schemas.jsonschema`). Keys are listed in docs/keys.md.

Frames and units: poses are (x, y, yaw) of the robot in the map frame, metres and radians; ranges are
metres along the beam; beam angles are radians in the laser frame, counter-clockwise from +x; stamps are
seconds (sensor time for sensor data, Unix time for ``published``). ``seq`` numbers a robot's scans
0, 1, 2, ... in publication order; pose, odometry and landmark messages carry the seq of the scan
they belong to, and mappers join scans and poses by (robot, seq).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, TypeVar, overload

import numpy as np

from schemas.files import WEIGHT_SUM_TOLERANCE, fan_past_a_turn
from schemas.wire import Array, Counts, Figures, Float, Int, Message, MessageError, Name, Rule, decode, spec

#: robot names that would collide with other key-space roots (``pg/map/...``)
RESERVED_ROBOT_NAMES = ("map",)

#: pose coordinates on the wire stay within +-this (m, and rad for yaw): 10 000 km, more than any UTM or
#: earth-centred frame needs, and small enough that a pose's spread, its cells and its JSON stay finite
POSE_LIMIT = 1e7

#: the most samples a PoseSamples may carry: every mapper shard ray-casts all of them, and 10 000 already takes
#: it seconds a scan (a slam-node's FastSLAM publishes 500 particles by default, grid FastSLAM 30)
MAX_POSE_SAMPLES = 10_000

#: the largest seq: exact as a JSON number (JavaScript clients read /health's counts as doubles) and in float64
MAX_SEQ = 2**53 - 1
#: the geometry a map's tiles may have on the wire, where a receiver makes a grid of what a peer's update names (a
#: forged tile of 2**20 cells asked the ROS 2 bridge for 16 TiB, one at tx = 2**63 + 1 turned its tile indices into
#: floats, cells of 1e300 m overflowed its OccupancyGrid): a tile side of at most 1024 cells (its three layers 9.4 MB),
#: tile indices within +-2**40 (cell indices of tiles of 1024 cells stay exact in float64), cells of 1 mm to 1 km
MAX_TILE_SIZE = 1024
MAX_TILE_INDEX = 2**40
CELL_SIZE_RANGE = (1e-3, 1e3)
#: the most mapper shards a map may have (a shard's stats name the count, and a tile's owner is found by hashing
#: the tile with every shard's index)
MAX_SHARDS = 1024

ROBOT = Name("robot name, one key chunk", forbidden=RESERVED_ROBOT_NAMES)
SEQ = Int("index of the scan this message belongs to, 0, 1, 2 ... per robot", minimum=0, maximum=MAX_SEQ)
STAMP = Float("sensor time of the scan, s")
#: the counts a shard's and a SLAM node's stats share
RECEIVED = Counts("messages received, by key")
REJECTED = Counts("messages dropped as malformed or of an unknown version, by key")


def _range_limits(v, fail):
    if not 0 <= v["range_min"] < v["range_max"]:
        fail("range", f"need 0 <= range_min < range_max, got {v['range_min']} and {v['range_max']}")


def _no_return_range(v, fail):
    if not 0.0 <= v["no_return_range"] <= v["range_max"]:
        fail("range", f"need 0 <= no_return_range <= range_max, got {v['no_return_range']} and {v['range_max']}")


def _beams(v, fail):
    if v["ranges"].shape[0] < 1:
        fail("shape", "'ranges' needs at least one beam")
    if v["angle_increment"] == 0 and v["ranges"].shape[0] > 1:
        fail("range", f"'angle_increment' is 0 but the scan has {v['ranges'].shape[0]} beams")
    for key in ("angle_min", "angle_increment"):
        if abs(v[key]) > 2 * np.pi:  # beyond a turn, the angles lose the precision that tells beams apart
            fail("range", f"'{key}' = {v[key]} rad is more than a full turn")
    if fan_past_a_turn(v["ranges"].shape[0], v["angle_increment"]):
        fail("range", f"{v['ranges'].shape[0]} beams {v['angle_increment']} rad apart sweep more than a full turn")


def _weights(v, fail):
    weights = v["weights"]
    if weights.shape[0] < 1:
        fail("shape", "'samples' needs at least one pose")
    if weights.shape[0] > MAX_POSE_SAMPLES:
        fail("size", f"'samples' holds {weights.shape[0]} poses, more than the {MAX_POSE_SAMPLES} a message may")
    if (weights < 0).any():
        fail("weights", f"'weights' has a negative value {weights[weights < 0][0]}")
    total = float(weights.sum())
    if abs(total - 1.0) > WEIGHT_SUM_TOLERANCE:
        fail("weights", f"'weights' sum to {total:.6g}, not 1")


def _covariance(v, fail):
    cov = v["cov"]
    scale = 1.0 + float(np.abs(cov).max())
    if np.abs(cov - cov.T).max() > 1e-9 * scale:
        fail("covariance", "'cov' is not symmetric")
    smallest = float(np.linalg.eigvalsh(cov).min())
    if smallest < -1e-12 * scale:
        fail("covariance", f"'cov' is not positive semi-definite (smallest eigenvalue {smallest:.3g})")


def _one_pose_at_most(v, fail):
    if v["pose"].shape[0] > 1:
        fail("shape", f"'pose' holds {v['pose'].shape[0]} rows; at most one is allowed")
    if (v["commands"][:, 2] < 0).any():
        fail("range", "'commands' has a negative dt")


def _window(v, fail):
    rows, cols, size = v["rows"], v["cols"], v["tile_size"]
    if size & (size - 1):
        fail("range", f"'tile_size' = {size} is not a power of two")
    if v["row0"] + rows > size or v["col0"] + cols > size:
        fail("range", f"window at ({v['row0']}, {v['col0']}) of shape ({rows}, {cols}) exceeds the {size}x{size} tile")


#: the bits set in each byte value (a table, not unpacked bits: a peer's message is checked in its own size)
_BITS_SET = np.array([bin(byte).count("1") for byte in range(256)], np.uint8)


def _given_cells(v, fail):
    given = _bits_count(v, "given", v["rows"] * v["cols"], "the window's cells", fail)
    _bits_count(v, "observed", given, "the given cells", fail)
    for name in ("logodds", "variance"):
        count = _bits_count(v, f"{name}_cells", given, "the given cells", fail)
        if count != v[name].shape[0]:
            fail("shape", f"'{name}_cells' marks {count} cells but '{name}' holds {v[name].shape[0]} values")


def _bits_count(v, name: str, count: int, what: str, fail) -> int:
    """How many bits field ``name`` sets, after checking it has one bit for each of ``count`` ``what`` (whole bytes,
    no bit set past the last)."""
    bits = v[name]
    if bits.shape[0] != -(-count // 8):
        fail("shape", f"'{name}' has {bits.shape[0]} bytes; {count} of {what} need {-(-count // 8)}")
    if count % 8 and bits[-1] >> (count % 8):
        fail("range", f"'{name}' sets bits past the last of {what}")
    return int(_BITS_SET[bits].sum(dtype=np.int64))


def _shard_index(v, fail):
    if v["shard"] >= v["shards"]:
        fail("range", f"'shard' = {v['shard']} must be below 'shards' = {v['shards']}")


@dataclass(frozen=True, eq=False)
class ScanMessage(Message):
    """Base of the messages that belong to one of a robot's scans: their first fields say whose scan, which
    (``seq``) and when (``stamp``)."""

    robot: str = spec(ROBOT)
    seq: int = spec(SEQ)
    stamp: float = spec(STAMP)


@dataclass(frozen=True, eq=False)
class LaserScan(ScanMessage):
    """One 2D laser scan. Published on pg/<robot>/scan.

    Version 2 added no_return_range: the sender says how far its laser's beams with no return clear free space
    (a real laser's missing echo may come from a dark or glancing surface close by: 0, they say nothing; a simulated
    laser's means nothing within range_max)."""

    TYPE = "LaserScan"
    VERSION = 2
    RULES = (
        Rule("range", "0 <= range_min < range_max", _range_limits),
        Rule("range", "0 <= no_return_range <= range_max", _no_return_range),
        Rule(
            "range",
            "at least one beam; angle_increment != 0 when there are several; |angle_min| and |angle_increment| <= 2 pi;"
            " the beams sweep at most a turn",
            _beams,
        ),
    )

    angle_min: float = spec(Float("angle of beam 0 in the laser frame, rad"))
    angle_increment: float = spec(Float("angle between consecutive beams, rad"))
    range_min: float = spec(Float("shortest valid range, m", minimum=0.0))
    range_max: float = spec(Float("longest range; longer readings mean no return, m", exclusive_minimum=0.0))
    sensor_offset: np.ndarray = spec(Array("laser (x m, y m, yaw rad) in the robot frame", "<f8", (3,)))
    ranges: np.ndarray = spec(Array("range per beam, m", "<f4", ("B",), values="ranges", minimum=0.0))
    no_return_range: float = spec(
        Float(
            "how far a beam with no return (inf or above range_max) clears free space, m; 0: such beams say nothing",
            minimum=0.0,
        )
    )


@dataclass(frozen=True, eq=False)
class Odometry(ScanMessage):
    """What the robot's wheels report between the previous scan and scan ``seq``: the velocity commands
    applied (for velocity motion models) and, when the robot reports one, its dead-reckoned pose (for
    odometry motion models). Published on pg/<robot>/odom."""

    TYPE = "Odometry"
    VERSION = 1
    RULES = (Rule("shape", "at most one pose row; command dt >= 0", _one_pose_at_most),)

    pose: np.ndarray = spec(
        Array(
            "the dead-reckoned (x m, y m, yaw rad) in the odometry frame; no row when the robot reports none",
            "<f8",
            ("P", 3),
            magnitude=POSE_LIMIT,
        )
    )
    commands: np.ndarray = spec(
        Array("velocity commands since the previous seq, in order: (v m/s, w rad/s, held for dt s)", "<f8", ("K", 3))
    )


@dataclass(frozen=True, eq=False)
class LandmarkObservations(ScanMessage):
    """Landmarks seen at the time of scan ``seq``, as range and bearing from the robot.
    Published on pg/<robot>/landmarks."""

    TYPE = "LandmarkObservations"
    VERSION = 1

    ids: np.ndarray = spec(Array("landmark id per observation, -1 when the correspondence is unknown", "<i8", ("K",)))
    ranges: np.ndarray = spec(Array("distance from the robot per observation, m", "<f8", ("K",), minimum=0.0))
    bearings: np.ndarray = spec(Array("bearing in the robot frame per observation, rad", "<f8", ("K",)))


@dataclass(frozen=True, eq=False)
class PoseSamples(ScanMessage):
    """The robot's pose distribution at scan ``seq`` as weighted samples (particles).
    Published on pg/<robot>/pose."""

    TYPE = "PoseSamples"
    VERSION = 1
    RULES = (
        Rule(
            "weights",
            f"1 to {MAX_POSE_SAMPLES} samples; weights >= 0 and sum to 1 within {WEIGHT_SUM_TOLERANCE}",
            _weights,
        ),
    )

    samples: np.ndarray = spec(
        Array("pose samples (x m, y m, yaw rad) in the map frame", "<f8", ("M", 3), magnitude=POSE_LIMIT)
    )
    weights: np.ndarray = spec(Array("weight per sample", "<f8", ("M",)))


@dataclass(frozen=True, eq=False)
class PoseGaussian(ScanMessage):
    """The robot's pose distribution at scan ``seq`` as a Gaussian. Published on pg/<robot>/pose."""

    TYPE = "PoseGaussian"
    VERSION = 1
    RULES = (Rule("covariance", "cov symmetric positive semi-definite", _covariance),)

    mean: np.ndarray = spec(Array("mean pose (x m, y m, yaw rad) in the map frame", "<f8", (3,), magnitude=POSE_LIMIT))
    cov: np.ndarray = spec(
        Array("covariance of (x, y, yaw), m^2, m*rad, rad^2", "<f8", (3, 3), magnitude=POSE_LIMIT**2)
    )


@dataclass(frozen=True, eq=False)
class StreamEnd(Message):
    """The source has published all of this robot's scans: seqs 0 .. scans-1. Published on pg/<robot>/end."""

    TYPE = "StreamEnd"
    VERSION = 1

    robot: str = spec(ROBOT)
    scans: int = spec(
        Int("number of scans published (and poses, when the source publishes poses)", minimum=0, maximum=MAX_SEQ + 1)
    )


@dataclass(frozen=True, eq=False)
class TileUpdate(Message):
    """Cells of one map tile as its owning shard holds them now (absolute values, not increments).

    Published on pg/map/<map>/tile/<z>/<tx>/<ty> after fusion and sent as the reply to a tile query. The window
    (row0, col0, rows, cols) bounds the cells given, and ``given`` marks which of its cells the update gives: after
    fusion the cells one of whose values changed since the tile was last published, and of each only the values that
    changed (``logodds_cells``, ``variance_cells``; ``observed`` always); a receiver keeps its earlier values of the
    rest, or none while it has none: log-odds 0, variance 0, unobserved. In a query's reply every value of every cell
    of the whole tile (:meth:`is_whole`). Tile (tx, ty) holds the global cells ix in [tx*T, (tx+1)*T), iy in [ty*T,
    (ty+1)*T); window row r, column c is the cell iy = ty*T + row0 + r, ix = tx*T + col0 + c, covering x in
    [ix*resolution, (ix+1)*resolution) of the map frame. The given cells are taken in row-major order of the window
    (:meth:`given_mask`, :meth:`paste`, :meth:`of_window`).
    """

    TYPE = "TileUpdate"
    VERSION = 3  # 2: the window's cells given, not every one; observed as bits; 3: each layer's changed values only
    RULES = (
        Rule("range", "tile_size a power of two; row0 + rows <= tile_size and col0 + cols <= tile_size", _window),
        Rule(
            "shape",
            "given has ceil(rows * cols / 8) bytes and N bits set, none past the window's last cell; observed, "
            "logodds_cells and variance_cells have ceil(N / 8) bytes, no bit set past the last given cell; logodds "
            "and variance hold as many values as their cells' bits set",
            _given_cells,
        ),
    )

    map: str = spec(Name("map name, one key chunk"))
    shard: int = spec(Int("index of the shard that owns the tile", minimum=0, maximum=MAX_SHARDS - 1))
    z: int = spec(Int("zoom level; 0 is the full-resolution grid", minimum=0))
    tx: int = spec(Int("tile column index", minimum=-MAX_TILE_INDEX, maximum=MAX_TILE_INDEX))
    ty: int = spec(Int("tile row index", minimum=-MAX_TILE_INDEX, maximum=MAX_TILE_INDEX))
    tile_size: int = spec(Int("cells per tile side, a power of two", minimum=1, maximum=MAX_TILE_SIZE))
    resolution: float = spec(Float("cell side, m", minimum=CELL_SIZE_RANGE[0], maximum=CELL_SIZE_RANGE[1]))
    row0: int = spec(Int("first window row inside the tile", minimum=0))
    col0: int = spec(Int("first window column inside the tile", minimum=0))
    rows: int = spec(Int("window rows", minimum=1))
    cols: int = spec(Int("window columns", minimum=1))
    robot: str = spec(ROBOT)
    seq: int = spec(Int("seq of the last scan fused into this tile (by robot)", minimum=0, maximum=MAX_SEQ))
    published: float = spec(Float("Unix time the shard sent this update, s"))
    given: np.ndarray = spec(
        Array(
            "the window cells this update gives: bit i (byte i // 8, bit i % 8) for the cell at row i // cols, "
            "column i % cols of the window",
            "|u1",
            ("B",),
            values="bits",
        )
    )
    observed: np.ndarray = spec(
        Array(
            "whether any beam has touched the given cell: bit j (byte j // 8, bit j % 8) for the j-th given cell",
            "|u1",
            ("O",),
            values="bits",
        )
    )
    logodds_cells: np.ndarray = spec(
        Array(
            "the given cells whose log-odds this update gives: bit j for the j-th given cell",
            "|u1",
            ("O",),
            values="bits",
        )
    )
    logodds: np.ndarray = spec(Array("occupancy log-odds of each cell logodds_cells marks", "<f4", ("L",)))
    variance_cells: np.ndarray = spec(
        Array(
            "the given cells whose variance this update gives: bit j for the j-th given cell",
            "|u1",
            ("O",),
            values="bits",
        )
    )
    variance: np.ndarray = spec(
        Array(
            "spread of the per-sample log-odds that pose uncertainty adds, of each cell variance_cells marks",
            "<f4",
            ("V",),
            minimum=0.0,
        )
    )

    @classmethod
    def of_cells(
        cls,
        given: np.ndarray,
        observed: np.ndarray,
        logodds: tuple[np.ndarray, np.ndarray],
        variance: tuple[np.ndarray, np.ndarray],
        **fields: Any,
    ) -> TileUpdate:
        """The update that gives the window cells ``given`` marks (bool (rows, cols)): of those n cells, in the
        window's row-major order, ``observed`` (bool (n,)); ``logodds`` = (cells, values): which of them (bool (n,))
        it gives a log-odds for, and those values; ``variance`` likewise. ``fields``: the others but rows, cols and
        the cells' fields."""
        rows, cols = given.shape
        return cls(
            rows=rows,
            cols=cols,
            given=_bits(given),
            observed=_bits(observed),
            logodds_cells=_bits(logodds[0]),
            logodds=logodds[1],
            variance_cells=_bits(variance[0]),
            variance=variance[1],
            **fields,
        )

    @classmethod
    def of_window(
        cls, layers: tuple[np.ndarray, np.ndarray, np.ndarray], given: np.ndarray | None = None, **fields: Any
    ) -> TileUpdate:
        """The update of a window's (rows, cols) layers (log-odds, variance, observed) that gives every value of the
        cells ``given`` marks (bool (rows, cols); default every cell); ``fields``: as :meth:`of_cells`'."""
        if given is None:
            given = np.ones(np.shape(layers[0]), np.bool_)
        logodds, variance, observed = (np.asarray(layer)[given] for layer in layers)
        every = np.ones(observed.shape[0], np.bool_)
        return cls.of_cells(given, observed, (every, logodds), (every, variance), **fields)

    def given_mask(self) -> np.ndarray:
        """The window cells this update gives, bool (rows, cols)."""
        return _unbits(self.given, self.rows * self.cols).reshape(self.rows, self.cols)

    def given_count(self) -> int:
        """How many cells this update gives (N)."""
        return int(_BITS_SET[self.given].sum(dtype=np.int64))

    def given_observed(self) -> np.ndarray:
        """Whether each given cell is observed, bool (N,) in the window's row-major order."""
        return _unbits(self.observed, self.given_count())

    def layer_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Which given cells this update gives a log-odds for and which a variance for, bool (N,) each."""
        count = self.given_count()
        return _unbits(self.logodds_cells, count), _unbits(self.variance_cells, count)

    def is_whole(self) -> bool:
        """Whether this update gives every value of every cell of its tile (as a tile query's reply does)."""
        cells = self.tile_size * self.tile_size
        return (self.row0, self.col0, self.rows, self.cols) == (0, 0, self.tile_size, self.tile_size) and bool(
            self.logodds.shape[0] == self.variance.shape[0] == cells
        )

    def paste(self, logodds: np.ndarray, variance: np.ndarray, observed: np.ndarray) -> None:
        """Write the values this update gives into a tile's layers (each (tile_size, tile_size), row = y)."""
        rows, cols = np.nonzero(self.given_mask())  # (row-major: the given cells' order)
        rows += self.row0
        cols += self.col0
        logodds_cells, variance_cells = self.layer_cells()
        logodds[rows[logodds_cells], cols[logodds_cells]] = self.logodds
        variance[rows[variance_cells], cols[variance_cells]] = self.variance
        observed[rows, cols] = self.given_observed()

    def whole_layers(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tile's (log-odds, variance, observed), each (tile_size, tile_size), of an update that gives every
        value of every cell of it (:meth:`is_whole`; ValueError otherwise)."""
        if not self.is_whole():
            raise ValueError(f"the update of tile ({self.tx}, {self.ty}) does not give every value of every cell")
        shape = (self.tile_size, self.tile_size)
        return self.logodds.reshape(shape), self.variance.reshape(shape), self.given_observed().reshape(shape)


def _bits(cells: np.ndarray) -> np.ndarray:
    """One bit a cell of ``cells`` (bool, row-major), least significant bit first, as bytes (|u1)."""
    return np.packbits(cells, axis=None, bitorder="little")


def _unbits(bits: np.ndarray, count: int) -> np.ndarray:
    """The first ``count`` bits of ``bits`` (:func:`_bits`' bytes), bool (count,)."""
    return np.unpackbits(bits, count=count, bitorder="little").view(np.bool_)


@dataclass(frozen=True, eq=False)
class ShardStats(Message):
    """What one mapper shard has done. The reply to a query on pg/map/<map>/stats/<shard>."""

    TYPE = "ShardStats"
    VERSION = 4  # 2: resent; 3: refused; 4: persist, committed, commit_age
    RULES = (Rule("range", "shard < shards", _shard_index),)

    map: str = spec(Name("map name"))
    shard: int = spec(Int("this shard's index", minimum=0))
    shards: int = spec(Int("number of shards the tiles are split among", minimum=1, maximum=MAX_SHARDS))
    tiles_owned: int = spec(Int("tiles this shard holds", minimum=0))
    cells_updated: int = spec(Int("cell updates fused so far (a cell counts once per scan)", minimum=0))
    tile_updates: int = spec(Int("tile updates published", minimum=0))
    join_pending: int = spec(Int("scans or poses waiting for their partner", minimum=0))
    uptime: float = spec(Float("seconds since the shard started", minimum=0.0))
    fused: dict = spec(Counts("scans fused, by robot"))
    discarded: dict = spec(Counts("scans given up on (join buffer overflow, no pose), by robot"))
    ended: dict = spec(Counts("scans announced by the source's StreamEnd, by robot"))
    received: dict = spec(RECEIVED)
    resent: dict = spec(
        Counts(
            "messages of seqs this shard has fused, the same as the ones fused (a restarted SLAM "
            "node or source catching up), dropped, by key"
        )
    )
    rejected: dict = spec(REJECTED)
    overflow: dict = spec(Counts("messages dropped because a bounded buffer was full, by buffer"))
    refused: dict = spec(
        Counts(
            "messages and scans refused or given up, by kind: e.g. key (no posegrid key), "
            "ahead (a seq beyond the seq window: forged or stray), size, work, bound and extent "
            "(past a resource limit), robots, malformed, missing, overflow"
        )
    )
    persist: str = spec(
        Name(
            "the shard's state directory (docs/persistence.md): off (none, the map lives in memory only), ok (the "
            "last commit succeeded) or failing (it did not: the shard serves from memory and retries)"
        ),
        default="off",
    )
    committed: dict = spec(
        Counts("scans fused or given up that the shard's store holds as of its last commit, by robot"),
        default_factory=dict,
    )
    commit_age: float = spec(
        Float("seconds since the shard's last commit to its store; -1 when there was none", minimum=-1.0),
        default=-1.0,
    )


@dataclass(frozen=True, eq=False)
class NodeStats(Message):
    """What a SLAM node has done. The reply to a query on pg/<robot>/slam/stats."""

    TYPE = "NodeStats"
    VERSION = 3  # 3: health

    robot: str = spec(ROBOT)
    algorithm: str = spec(Name("SLAM algorithm the node runs"))
    poses_published: int = spec(Int("pose distributions published", minimum=0))
    steps_done: int = spec(Int("steps taken, failed or skipped: every seq below this one is dealt with", minimum=0))
    uptime: float = spec(Float("seconds since the node started", minimum=0.0))
    received: dict = spec(RECEIVED)
    rejected: dict = spec(REJECTED)
    out_of_order: dict = spec(Counts("scans that arrived with a seq at or below one already processed, by key"))
    noise_scale: float = spec(
        Float(
            "landmark filters: the factor on the configured motion and measurement noise covariances that the "
            "consistency watch has set (1: as configured; larger while the filter's innovations showed it "
            "overconfident); 1 for grid FastSLAM",
            minimum=0.0,
        )
    )
    consistency: dict = spec(
        Counts(
            "landmark filters' consistency watch: measurements whose NIS it took, of them dropped by the gate, and "
            "how often it inflated or deflated the noise; empty for grid FastSLAM"
        )
    )
    health: dict = spec(
        Figures(
            "grid FastSLAM: the health of the last integrated scan (slam.gridslam.health.ScanHealth: matched, "
            "score_z, ess, particles, spread_xy m, spread_yaw rad, sigma_xy m, sigma_yaw rad, fallbacks, failed, "
            "widened, resampled, next_particles; flags 0 or 1; a value not yet known is left out) and of the run so "
            "far (scans, failed_scans, loop_closures); empty for the landmark filters"
        ),
        default_factory=dict,
    )


#: every message type, by wire name
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        LaserScan,
        Odometry,
        LandmarkObservations,
        PoseSamples,
        PoseGaussian,
        StreamEnd,
        TileUpdate,
        ShardStats,
        NodeStats,
    )
}

#: the two forms a pose distribution takes on pg/<robot>/pose
PoseDistribution = PoseSamples | PoseGaussian
POSE_TYPES = (PoseSamples, PoseGaussian)


_M1 = TypeVar("_M1", bound=Message)
_M2 = TypeVar("_M2", bound=Message)


@overload
def decode_message(payload: bytes, expected: type[_M1], /) -> _M1: ...


@overload
def decode_message(payload: bytes, first: type[_M1], second: type[_M2], /) -> _M1 | _M2: ...


@overload
def decode_message(payload: bytes, *expected: type[Message]) -> Message: ...


def decode_message(payload: bytes, *expected: type[Message]) -> Message:
    """Decode and validate ``payload``; with ``expected`` types given, any other type is rejected (so the
    result is of one of them: type checkers see it from one or two ``expected`` types).

    Raises :class:`MessageError` (reason in :data:`schemas.wire.REASONS`) on any defect.
    """
    return decode(payload, MESSAGE_TYPES, expected)


__all__ = [
    "MAX_POSE_SAMPLES",
    "MESSAGE_TYPES",
    "POSE_LIMIT",
    "POSE_TYPES",
    "RESERVED_ROBOT_NAMES",
    "LandmarkObservations",
    "LaserScan",
    "MessageError",
    "NodeStats",
    "Odometry",
    "PoseDistribution",
    "PoseGaussian",
    "PoseSamples",
    "ShardStats",
    "StreamEnd",
    "TileUpdate",
    "decode_message",
]
