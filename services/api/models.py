"""JSON response bodies of the HTTP API; the OpenAPI document's schemas derive from these classes.

Units: metres, radians, seconds; poses are (x, y, yaw) of the robot in the map frame.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class Problem(BaseModel):
    """Why a request failed."""

    detail: str = Field(description="one sentence saying what was wrong and how to fix it")


class TileBounds(BaseModel):
    """Level-0 tile indices a map spans, inclusive."""

    x_min: int
    x_max: int
    y_min: int
    y_max: int


class Extent(BaseModel):
    """A rectangle in the map frame, m."""

    x_min: float = Field(description="m")
    y_min: float = Field(description="m")
    x_max: float = Field(description="m")
    y_max: float = Field(description="m")


class CellCounts(BaseModel):
    """Cells of the level-0 grid."""

    per_tile: int = Field(description="cells per tile (tile_size squared)")
    total: int = Field(description="cells in the tiles that exist")
    observed: int | None = Field(
        description="cells any scan has touched (null while a shard that holds tiles of the map does not answer)"
    )


class MapSummary(BaseModel):
    """One map as the API sees it."""

    name: str
    resolution: float | None = Field(description="side of a level-0 cell, m (null until the first tile exists)")
    tile_size: int | None = Field(description="cells per tile side (null until the first tile exists)")
    shards: int | None = Field(
        description="number of shards the map is split among, as they report it "
        "(null until one has answered a stats query)"
    )
    shards_alive: list[int] = Field(description="shards whose liveliness token is up")
    tiles: int = Field(description="level-0 tiles that exist")
    tile_bounds: TileBounds | None = Field(description="level-0 tiles spanned (null without tiles)")
    extent: Extent | None = Field(description="area the level-0 tiles span, m (tile aligned; null without tiles)")
    observed_extent: Extent | None = Field(
        description="area of the observed cells, m (null when none, or while a "
        "shard that holds tiles of the map does not answer)"
    )
    max_zoom: int | None = Field(
        description="coarsest zoom level served: z ranges over 0..max_zoom (null without tiles)"
    )
    cells: CellCounts
    variance_scale: float | None = Field(
        description="variance (log-odds squared) at the top of the variance "
        "colour ramp when a tile request gives no vmax (null while a shard that "
        "holds tiles of the map does not answer)"
    )


class ShardStatus(BaseModel):
    """One shard: its liveliness and what it reports in its stats."""

    shard: int
    alive: bool = Field(description="its liveliness token is up")
    answered: bool = Field(description="it answered the stats query (the fields below are null when not)")
    scans_fused: dict[str, int] | None = Field(default=None, description="scans fused, by robot")
    scans_discarded: dict[str, int] | None = Field(default=None, description="scans given up on, by robot")
    scans_announced: dict[str, int] | None = Field(
        default=None, description="scans the source's end-of-stream announced, by robot"
    )
    tiles_owned: int | None = Field(default=None, description="level-0 tiles the shard holds")
    cells_updated: int | None = Field(default=None, description="cell updates fused (a cell counts once per scan)")
    tile_updates: int | None = Field(default=None, description="tile updates published")
    join_pending: int | None = Field(default=None, description="scans or poses waiting for their partner")
    uptime_s: float | None = Field(default=None, description="s")
    received: dict[str, int] | None = Field(default=None, description="messages received, by key")
    resent: dict[str, int] | None = Field(
        default=None,
        description="messages of seqs the shard has fused, the same "
        "as the ones fused (a restarted SLAM node or source catching up), by key",
    )
    rejected: dict[str, int] | None = Field(default=None, description="messages dropped as malformed, by key")
    overflow: dict[str, int] | None = Field(
        default=None, description="messages dropped because a buffer was full, by buffer"
    )
    lag_scans: dict[str, int] | None = Field(
        default=None,
        description="by robot: the scans known to exist (the latest pose seq the API has seen + 1, the most scans "
        "a shard fused or gave up on, the source's announced end: the largest) minus the scans the shard fused or "
        "gave up on (how far the shard is behind)",
    )
    tile_updates_received: int = Field(
        description="tile updates of this shard the API has received (equal to tile_updates when none is in flight)"
    )
    last_tile_update_age_s: float | None = Field(
        default=None, description="s since the API received this shard's last tile update (null: none yet)"
    )
    persist: Literal["off", "ok", "failing"] | None = Field(
        default=None,
        description="its state directory (docs/persistence.md): off (none), ok, or failing (its last commit failed: "
        "it serves from memory and retries)",
    )
    committed_scans: dict[str, int] | None = Field(
        default=None, description="by robot: scans fused or given up that its store holds as of its last commit"
    )
    last_commit_age_s: float | None = Field(default=None, description="s since its last commit (null: none)")


class ShardCommit(BaseModel):
    """One shard's last commit to its state directory (docs/persistence.md)."""

    shard: int
    persist: Literal["off", "ok", "failing"] = Field(description="off (no state directory), ok or failing")
    scans: int = Field(description="scans fused or given up (every robot) that its store holds")
    age_s: float | None = Field(description="s since its last commit (null: none)")


class MapStats(BaseModel):
    """A map's shards and what they did."""

    map: str
    shards: int | None = Field(description="number of shards (null when none answered)")
    shards_alive: list[int]
    scans_fused: dict[str, int] = Field(description="by robot: scans fused by every answering shard (the minimum)")
    scans_discarded: dict[str, int] = Field(
        description="by robot: the most scans a shard gave up on (lost in "
        "transit, no pose, could not be fused; see its rejected keys)"
    )
    lag_scans: dict[str, int] = Field(description="by robot: the largest lag over the shards (see ShardStatus)")
    rejected: dict[str, int] = Field(
        description="messages dropped as malformed, by key: the shards' counts plus the API's own"
    )
    refused: dict[str, int] = Field(
        default_factory=dict,
        description="by kind, summed over the shards: what they "
        "refused or gave up (ShardStats.refused: key, ahead, size, work, bound, extent, "
        "robots, malformed, ...)",
    )
    duplicated_shards: list[int] = Field(
        default_factory=list,
        description="shard indices that more than one process answered for in the last stats query (a shard "
        "started twice: its stats and tiles cannot be trusted until one of them stops)",
    )
    per_shard: list[ShardStatus]
    conflict: str | None = Field(
        default=None,
        description="why the map's shards cannot be one map (tiles of two cell or tile sizes: shards started with "
        "another --resolution or --tile-size; a shard index at or past the shard count); its tiles and summary then "
        "show only part of it; null when none",
    )
    tiles_incomplete: str | None = Field(
        default=None,
        description="why the API's last fetch of every tile of the map fell short (a shard that did not answer in "
        "--query-timeout, or sent fewer tiles than it holds): the API then serves part of the map and asks again, "
        "at most every few seconds, at the next request; null when it did not",
    )


class MapHealth(BaseModel):
    shards: int | None
    shards_alive: list[int]
    scans_fused: dict[str, int] = Field(description="by robot, the minimum over the shards")
    scans_discarded: dict[str, int] = Field(description="by robot, the maximum over the shards: scans the map lacks")
    lag_scans: dict[str, int] = Field(description="by robot, the maximum over the shards")
    duplicated_shards: list[int] = Field(
        default_factory=list, description="shard indices more than one process answers for (see MapStats)"
    )
    distrust: list[str] = Field(
        default_factory=list,
        description="one sentence per kind of message the shards "
        "refused that says a peer sends what it should not (forged or stray seqs, keys that "
        "are no posegrid key, messages past a limit): the map holds none of them, but "
        "someone on the network is misbehaving",
    )
    commits: list[ShardCommit] = Field(
        default_factory=list, description="each answering shard's last commit to its state directory"
    )
    conflict: str | None = Field(default=None, description="as in MapStats: why its shards cannot be one map")
    tiles_incomplete: str | None = Field(
        default=None, description="as in MapStats: why the API holds only part of the map's tiles"
    )


class Health(BaseModel):
    """The whole system at a glance."""

    status: Literal["ok", "degraded"] = Field(
        description="ok: every shard of every map is alive and answers, none reports persist failing or answers "
        "from two processes, and no robot is stranded; degraded otherwise"
    )
    uptime_s: float = Field(description="s since the API started")
    maps: dict[str, MapHealth]
    robots: list[str] = Field(description="robots whose poses the API has received")
    processes_alive: list[str] = Field(description="robot processes with a liveliness token, '<robot>/<process>'")
    rejected: dict[str, int] = Field(
        description="messages the API itself dropped (malformed, unproved shard tokens, beyond a limit), by key"
    )
    event_clients: int = Field(description="open /events streams")
    exports_running: int = Field(description="exports being built now")
    refused: dict[str, int] = Field(
        description="what the API refused because a limit was reached, by what: "
        "shard_tokens (--max-maps, or too many tokens waiting for their shard), robots "
        "(--max-robots), processes, event_clients (--max-event-clients), exports "
        "(--max-exports)"
    )
    limits: dict[str, int] = Field(description="the limits: maps, robots, event_clients, exports, export_cells")
    reasons: list[str] = Field(
        default_factory=list, description="why the status is degraded, one sentence each (empty when ok)"
    )


class Pose(BaseModel):
    """A robot's latest pose distribution."""

    robot: str
    seq: int = Field(description="index of the scan the pose belongs to")
    stamp: float = Field(description="sensor time of the scan, s")
    received: float = Field(description="Unix time the API received the pose, s")
    form: Literal["samples", "gaussian"] = Field(
        description="samples: weighted particles from SLAM; gaussian: mean and covariance from SLAM "
        "(the samples are then drawn from it for display)"
    )
    samples: list[list[float]] = Field(description="pose samples [x m, y m, yaw rad], map frame")
    weights: list[float] = Field(description="weight per sample, summing to 1")
    samples_total: int = Field(description="samples in the distribution before max_samples reduced them")
    mean: list[float] = Field(description="[x m, y m, yaw rad]; yaw is the weighted circular mean")
    covariance: list[list[float]] = Field(description="3 x 3 covariance of (x, y, yaw): m^2, m*rad, rad^2")


class Trajectory(BaseModel):
    """A robot's mean poses, oldest first."""

    robot: str
    seq: list[int]
    stamp: list[float] = Field(description="s")
    x: list[float] = Field(description="m")
    y: list[float] = Field(description="m")
    yaw: list[float] = Field(description="rad")


class RobotSummary(BaseModel):
    robot: str
    seq: int = Field(description="seq of the latest pose")
    stamp: float = Field(description="sensor time of the latest pose, s")
    form: Literal["samples", "gaussian"]
    processes_alive: list[str] = Field(description="the robot's processes with a liveliness token")
