"""The resource-limit options of `posegrid mapper` and `posegrid run` (services.state.limits, docs/security.md)."""

from __future__ import annotations

import argparse

from services.state.limits import ShardLimits

#: (option, field of ShardLimits, type, help) of each limit
_LIMITS = (
    ("--max-beams", "max_beams", int, "beams one scan may have; a longer scan is refused (default %(default)s)"),
    (
        "--max-work",
        "max_work",
        int,
        (
            "what one scan may cost, samples x (beams x range_max / resolution + its window's cells / 64); a "
            "costlier scan is refused (default %(default)s, about 1 to 2 s of one core)"
        ),
    ),
    (
        "--map-bound",
        "map_bound",
        float,
        (
            "m: pose samples, widened by the length of the scan's sensor offset, must lie within this distance "
            "of the map origin in x and y; a scan posed beyond is refused (default %(default)s)"
        ),
    ),
    (
        "--max-scan-cells",
        "max_scan_cells",
        int,
        (
            "cells of the tiles one scan may reach (its samples' tiles widened "
            "by range_max); a scan reaching more is refused (default %(default)s)"
        ),
    ),
    (
        "--max-map-cells",
        "max_map_cells",
        int,
        (
            "cells of the tiles this shard may hold (about 10 bytes each in memory); a scan that could add tiles "
            "past it is refused (default %(default)s: 1.3 GB, 336 000 m2 of 0.05 m cells)"
        ),
    ),
    (
        "--join-bytes",
        "join_bytes",
        int,
        (
            "bytes of the scans and poses of every robot together that may wait for their partner; beyond, "
            "the oldest of the robot holding the most are evicted (default %(default)s)"
        ),
    ),
    (
        "--intake-bytes",
        "intake_bytes",
        int,
        "bytes of messages that may wait for the fusion thread; more are dropped and counted (default %(default)s)",
    ),
    (
        "--max-robots",
        "max_robots",
        int,
        "robots a shard keeps state for; messages of further robots are refused (default %(default)s)",
    ),
    (
        "--seq-window",
        "seq_window",
        int,
        (
            "seqs beyond what a robot's stream has shown that a live message may lie; "
            "one further ahead is held until the stream gets near it (default %(default)s)"
        ),
    ),
)


def add_limit_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the limit options, with ShardLimits' defaults (every refusal is counted in the shard's stats)."""
    group = parser.add_argument_group("limits on what peers may send (docs/security.md)")
    defaults = ShardLimits()
    for option, field, kind, text in _LIMITS:
        group.add_argument(option, type=kind, default=getattr(defaults, field), help=text)


def limits_from_args(args: argparse.Namespace) -> ShardLimits:
    """The ShardLimits the options give; UsageError (exit 2) for a value out of range."""
    from services.errors import UsageError

    try:
        return ShardLimits(**{field: getattr(args, field) for _, field, _, _ in _LIMITS})
    except ValueError as exc:
        option = next((opt for opt, field, _, _ in _LIMITS if str(exc).startswith(field)), "a limit option")
        raise UsageError(f"{option}: {exc}") from None


def limit_argv(args: argparse.Namespace) -> list[str]:
    """The limit options of ``args`` as command-line arguments for a shard (`posegrid run` passes them on)."""
    return [text for option, field, _, _ in _LIMITS for text in (option, repr(getattr(args, field)))]
