"""What every subcommand module builds its parser from: the subcommand itself (:func:`add_command`), options
that take one of a few words (:func:`add_choice`) and groups of options from a table (:func:`add_group`); and the
way back from parsed options to the command-line arguments that give a child process the same values
(:func:`option_argv`)."""

from __future__ import annotations

import argparse
import inspect
from collections.abc import Callable, Iterable, Sequence
from typing import Any

#: a subcommand's handler: the parsed arguments in, the exit code out
Handler = Callable[[argparse.Namespace], int]
#: a row of an option table (:func:`add_group`): the option's name without its leading "--", and the keywords
#: ``add_argument`` takes for it
OptionRow = tuple[str, dict[str, Any]]


def add_command(subparsers: argparse._SubParsersAction, name: str, func: Handler) -> argparse.ArgumentParser:
    """Add the subcommand ``name``, which runs ``func``. ``func``'s docstring is the command's help, so it is
    written for the user: its first paragraph is the command's line in `posegrid --help`, the rest the description
    `posegrid NAME --help` shows (argparse refills both to the terminal's width)."""
    summary, _, description = (inspect.getdoc(func) or "").partition("\n\n")
    parser = subparsers.add_parser(name, help=summary.replace("%", "%%"), description=description or None)
    parser.set_defaults(func=func)
    return parser


#: :func:`add_choice`'s default: the first of the choices
FIRST = object()


def add_choice(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    option: str,
    choices: Sequence[str],
    help: str,
    default: object = FIRST,
) -> None:
    """Add ``option``, which takes one of ``choices``; unless given, it is ``default`` (by default the first
    choice; None: the option can be told apart from one left alone)."""
    parser.add_argument(option, choices=choices, default=choices[0] if default is FIRST else default, help=help)


def add_scan_topic(parser: argparse.ArgumentParser | argparse._ArgumentGroup, applies_to: str = "ROS bag") -> None:
    """``--scan-topic TOPIC``: which LaserScan topic of a ROS bag to read (the bag reader's default: the only one, or
    /scan), for every command that reads a bag's scans or odometry; ``applies_to`` opens its help."""
    parser.add_argument(
        "--scan-topic",
        type=str,
        default=None,
        metavar="TOPIC",
        help=f"{applies_to}: the LaserScan topic (default: the only one, or /scan)",
    )


def no_return_range_keywords(applies_to: str, default: float | None = None) -> dict[str, Any]:
    """The ``add_argument`` keywords of ``--no-return-range METRES``: how far a real laser's beams with no return
    clear free space, for every command that maps a laser log's or a live laser's scans; ``applies_to`` opens its
    help. ``default`` None: unset, and slam.laserlog.NO_RETURN_RANGE applies (shown in the help)."""
    from services.commands.argtypes import no_return_metres
    from slam.laserlog import NO_RETURN_RANGE

    return {
        "type": no_return_metres,
        "default": default,
        "metavar": "METRES",
        "help": f"{applies_to}how far a beam with no return (inf, or at or past the laser's range_max) clears free "
        f"space in the map, at most the laser's range_max (and grid FastSLAM's --max-range) (default "
        f"{NO_RETURN_RANGE:g}: such beams say nothing, for "
        "a real laser misses dark and glancing surfaces close by too; docs/sensor_model.md, section 3)",
    }


def no_return_range(args: argparse.Namespace) -> float:
    """--no-return-range in m, or slam.laserlog.NO_RETURN_RANGE where it was not given."""
    from slam.laserlog import NO_RETURN_RANGE

    return NO_RETURN_RANGE if args.no_return_range is None else float(args.no_return_range)


def add_group(
    parser: argparse.ArgumentParser,
    title: str,
    description: str | None,
    rows: Iterable[OptionRow],
    prefix: str = "",
) -> argparse._ArgumentGroup:
    """Add the argument group ``title`` (``description`` under it in --help) holding the option --``prefix``NAME of
    each row (NAME, keywords) of ``rows``, in their order; returns the group."""
    group = parser.add_argument_group(title, description)
    for name, keywords in rows:
        group.add_argument(f"--{prefix}{name}", **keywords)
    return group


def dest(option: str) -> str:
    """The attribute of the parsed arguments that holds ``option`` ("--sigma-model": "sigma_model")."""
    return option[2:].replace("-", "_")


def option_argv(args: argparse.Namespace, options: Iterable[str]) -> list[str]:
    """``options`` of ``args`` as command-line arguments that give another process the same values: a flag alone
    when set (store_true), else the option and its value (text as it is, a number by repr, which reads back to the
    same float); an option left unset (None or False) is left out."""
    argv: list[str] = []
    for option in options:
        value = getattr(args, dest(option))
        if value is True:
            argv.append(option)
        elif value is not None and value is not False:
            argv += [option, value if isinstance(value, str) else repr(value)]
    return argv
