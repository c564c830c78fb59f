"""The state-directory options of `posegrid mapper` and `posegrid run` (docs/persistence.md): where a shard keeps its
map and ledger, how often it commits, and which session it writes."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING, Any

from services.commands.argtypes import finite_float, path_argument

if TYPE_CHECKING:
    from services.nodes.launcher import Plan
    from services.nodes.mapper import PersistOptions

#: the commit interval's defaults, as services.state.store.writer has them (kept here so `--help` stays instant;
#: tests/test_persist.py checks that they agree)
COMMIT_SCANS = 256
COMMIT_INTERVAL = 2.0


def _add_commit_options(group: Any) -> None:
    group.add_argument(
        "--commit-scans",
        type=int,
        default=COMMIT_SCANS,
        metavar="N",
        help=f"commit at least every N scans fused or given up (default {COMMIT_SCANS})",
    )
    group.add_argument(
        "--commit-interval",
        type=finite_float,
        default=COMMIT_INTERVAL,
        metavar="SECONDS",
        help=f"... or once the oldest change not committed is this old, s (default {COMMIT_INTERVAL:g})",
    )


def add_persist_options(parser: argparse.ArgumentParser) -> None:
    """`posegrid mapper`'s state options."""
    group = parser.add_argument_group(
        "durable state (docs/persistence.md)",
        "With --state-dir the shard keeps its tiles and its ledger of fused seqs in a SQLite database there, starts "
        "from it when it holds one, and takes from the histories only the scans after its ledger.",
    )
    group.add_argument(
        "--state-dir", type=path_argument, default=None, metavar="DIR", help="the shard's state directory"
    )
    group.add_argument(
        "--session",
        default=None,
        metavar="ID",
        help="--state-dir: the session this shard writes; a new id starts the robots' seqs afresh on the map on "
        "disk (default: the store's latest session, or a new one)",
    )
    group.add_argument(
        "--run-id",
        default=None,
        metavar="ID",
        help="--state-dir: the posegrid run the store belongs to (posegrid run gives it): a store of another run "
        "is refused, one of none takes it (default: not checked)",
    )
    group.add_argument(
        "--load",
        type=path_argument,
        default=None,
        metavar="MAP.npz",
        help="start from an exported map (posegrid run --export, posegrid fuse): the tiles this shard owns",
    )
    group.add_argument(
        "--state-limit-mb",
        type=finite_float,
        default=None,
        metavar="MB",
        help="--state-dir: the most MiB the database may take; past it commits fail and the shard serves from "
        "memory, reporting persist: failing (default: no limit)",
    )
    _add_commit_options(group)


def _check_commit_options(args: argparse.Namespace) -> None:
    from services.errors import UsageError

    if args.commit_scans < 1:
        raise UsageError(f"--commit-scans must be >= 1, got {args.commit_scans}")
    if not args.commit_interval > 0:
        raise UsageError(f"--commit-interval must be > 0 s, got {args.commit_interval}")


def persist_from_args(args: argparse.Namespace) -> PersistOptions:
    """The services.nodes.mapper.PersistOptions of the mapper's options; UsageError (exit 2) for a bad value."""
    from services.errors import UsageError
    from services.nodes.mapper import PersistOptions

    _check_commit_options(args)
    if args.state_dir is None:
        for option, value in (
            ("--session", args.session),
            ("--state-limit-mb", args.state_limit_mb),
            ("--run-id", args.run_id),
        ):
            if value is not None:
                raise UsageError(f"{option} is an option of the state directory: give it with --state-dir")
    limit = args.state_limit_mb
    if limit is not None and not 0 < limit <= 2**30:  # (1 PiB; 1e308 overflowed into a traceback)
        raise UsageError(f"--state-limit-mb must be > 0 and at most {2**30} (1 PiB), got {limit:g}")
    return PersistOptions(
        state_dir=args.state_dir,
        session=args.session,
        run_id=args.run_id,
        commit_scans=args.commit_scans,
        commit_interval=args.commit_interval,
        max_bytes=None if limit is None else math.floor(limit * 2**20),
        load=args.load,
    )


def add_run_persist_options(parser: argparse.ArgumentParser) -> None:
    """`posegrid run`'s state options."""
    group = parser.add_argument_group(
        "durable state (docs/persistence.md)",
        "Each shard keeps its map and ledger in DIR/shard-I/ (SQLite), and a shard the launcher restarts starts "
        "from there. DIR is --state-dir (a new run), --resume (a run's directory), or by default a new folder "
        "posegrid/runs/MAP-DATE-TIME-PID under $XDG_STATE_HOME (~/.local/state); --no-state keeps the map in "
        "memory only.",
    )
    where = group.add_mutually_exclusive_group()
    where.add_argument(
        "--state-dir", type=path_argument, default=None, metavar="DIR", help="a new directory for this run"
    )
    where.add_argument(
        "--resume",
        type=path_argument,
        default=None,
        metavar="DIR",
        help="start from the map of the run in DIR and add this run to it as a new session",
    )
    where.add_argument(
        "--no-state", action="store_true", help="keep the map in memory only: it is lost when the run stops"
    )
    group.add_argument(
        "--continue-session",
        action="store_true",
        help="--resume: go on with DIR's latest session instead (a replay of the same input that was interrupted: "
        "the shards skip what they had fused)",
    )
    _add_commit_options(group)


def plan_state(args: argparse.Namespace, plan: Plan) -> None:
    """Give ``plan`` the run's state directory (a new one, or the one resumed) and the shards' commit options;
    UsageError (exit 2) when it cannot be used."""
    from services.errors import UsageError

    if args.continue_session and args.resume is None:
        raise UsageError("--continue-session goes on with a resumed run's session: give it with --resume DIR")
    if args.no_state:
        return
    from services.state.store.run import default_run_dir, hold_run_directory, prepare_run

    directory = args.resume if args.resume is not None else args.state_dir
    if directory is None:
        directory = default_run_dir(plan.map_name)
    _check_commit_options(args)
    hold_run_directory(directory, create=args.resume is None)  # (for the rest of the run: one run a directory)
    with_scans: dict[str, set[str]] | None = None  # (sessions of the shards' stores -> the robots of their scans)
    unfinished: dict[str, set[str]] = {}  # (sessions -> the robots whose replay a store holds stopped before its end)
    if args.resume is not None:  # (every shard's store checked before the run's record gets a new session)
        from mapping.grid import TILE_SIZE
        from services.state.store.db import StoreIdentity, check_store, store_exists
        from services.state.store.run import check_run_options, run_id_of, shard_dir

        # (the run's options before the stores: it names the option to give, a store another map's state)
        check_run_options(directory, plan.map_name, plan.shards, plan.resolution)
        with_scans = {}
        run_id = run_id_of(directory)
        holding = []  # (the shards whose stores hold scans of the run)
        for shard in range(plan.shards):
            identity = StoreIdentity(plan.map_name, shard, plan.shards, TILE_SIZE, plan.resolution)
            held = check_store(shard_dir(directory, shard), identity, run_id, unfinished)
            holding += [shard] if held else []
            for session, robots in held.items():
                with_scans.setdefault(session, set()).update(robots)
        missing = [shard for shard in range(plan.shards) if not store_exists(shard_dir(directory, shard))]
        if missing and holding:  # (a shard's store deleted: resumed as a new, empty map, exit 0, half the map gone)
            raise UsageError(
                f"{directory}: the store of shard {missing[0]} ({shard_dir(directory, missing[0])}) is gone while "
                f"shard {holding[0]}'s holds the run's scans: resumed, that shard's tiles would be lost; put its "
                "folder back, or start a new run (--state-dir NEW)"
            )
    plan.state = prepare_run(
        directory,
        args.resume is not None,
        args.continue_session,
        plan.map_name,
        plan.shards,
        plan.resolution,
        with_scans,
        plan.robot,
        unfinished if plan.scans is not None else None,  # (a live robot's stream never ends: no replay to go on with)
    )
    plan.mapper_argv += ["--commit-scans", str(args.commit_scans), "--commit-interval", repr(args.commit_interval)]
