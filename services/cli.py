"""The ``posegrid`` console script: one argparse parser, one module per group of subcommands.

Each module in :data:`COMMAND_MODULES` has ``register(subparsers)``, which adds its subcommands and sets
``func`` (taking the parsed args, returning an exit code). Heavy imports (numba, zenoh, fastapi) happen
inside the handlers, so ``posegrid --help`` is instant.

Exit codes: 0 success, 1 runtime failure, 2 bad input or usage (one sentence on stderr, no traceback),
130 interrupted (SIGINT, also when posegrid was started with it ignored, as a script's background job is).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import signal
import sys

from services.errors import UsageError
from services.process import Stopped

#: modules that register subcommands, in the order ``--help`` lists them
COMMAND_MODULES = (
    "services.commands.mapping",
    "services.commands.slam",
    "services.commands.calibrate",
    "services.commands.pipeline",
    "services.commands.ros2",
    "services.commands.logs",
    "services.commands.api",
    "services.commands.security",
)


def input_errors() -> tuple[type[BaseException], ...]:
    """Exception types that mean 'the user's input is wrong' rather than 'posegrid has a bug'."""
    from mapping.errors import InputError
    from schemas.errors import FormatError
    from slam.errors import LogFormatError

    return (UsageError, FormatError, InputError, LogFormatError)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="posegrid",
        description="Occupancy maps that carry SLAM pose uncertainty (Monte Carlo fusion of pose samples). "
        "Units: metres, radians, seconds; poses are (x, y, yaw) in the map frame.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def command_parser(parser: argparse.ArgumentParser, command: str | None) -> argparse.ArgumentParser:
    """The parser of subcommand ``command`` of ``parser`` (``parser`` itself for none)."""
    for action in parser._actions:  # (argparse keeps its subcommands' parsers in its subparsers action)
        if isinstance(action, argparse._SubParsersAction) and command in action.choices:
            return action.choices[command]
    return parser


#: options whose value is a comma-separated list that may start with a minus (argparse takes "-1,2,0.5" for an
#: option, not a negative number, and said "--initial: expected one argument")
SIGNED_LISTS = ("--initial",)


def joined_signed_lists(argv: list[str]) -> list[str]:
    """``argv`` with each ``OPTION VALUE`` of :data:`SIGNED_LISTS` whose value starts with a minus and a digit
    written ``OPTION=VALUE``, as argparse takes it."""
    joined: list[str] = []
    tokens = iter(argv)
    for token in tokens:
        if token in SIGNED_LISTS:
            value = next(tokens, None)
            if value is not None and len(value) > 1 and value[0] == "-" and (value[1].isdigit() or value[1] == "."):
                joined.append(f"{token}={value}")
                continue
            joined.append(token)
            if value is not None:
                joined.append(value)
            continue
        joined.append(token)
    return joined


def main(argv: list[str] | None = None) -> int:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # inherited by a background job of a script: a SIGINT before a service installs its stop handlers (which
        # take it whatever was inherited) would be lost, and the process would run on; it interrupts instead
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        parser = build_parser()  # (imports every command module: a SIGINT may well arrive here)
        args, extras = parser.parse_known_args(joined_signed_lists(sys.argv[1:] if argv is None else argv))
        if extras:  # (said with the command's own usage: the top-level parser's named no option of it)
            command_parser(parser, getattr(args, "command", None)).error(f"unrecognized arguments: {' '.join(extras)}")
    except KeyboardInterrupt:
        print("posegrid: interrupted", file=sys.stderr)
        return 130
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("posegrid: interrupted", file=sys.stderr)
        return 130
    except Stopped as exc:  # (asked to stop while it waited for something it could not interrupt)
        print(f"posegrid {args.command}: {exc}", file=sys.stderr)
        return 0
    except input_errors() as exc:
        print(f"posegrid {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # (the program reading its output stopped: as `head` does)
        devnull = os.open(os.devnull, os.O_WRONLY)  # (else the flush at exit says it again, with a traceback)
        os.dup2(devnull, sys.stdout.fileno())
        print(f"posegrid {args.command}: error: its output's reader stopped reading (broken pipe)", file=sys.stderr)
        return 2
    except OSError as exc:
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"posegrid {args.command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # numpy's names the size it could not allocate
        print(
            f"posegrid {args.command}: error: out of memory ({exc}); fewer particles or samples, fewer scans or "
            "beams, a coarser resolution or a shorter range need less",
            file=sys.stderr,
        )
        return 2


def run_in_process(argv: list[str], quiet: bool = False) -> str:
    """Run `posegrid ARGV` in this process, as a user would from a shell, and return what it printed on stdout
    (``quiet``: its stderr is taken too, and shown only if it fails). A non-zero exit raises RuntimeError naming
    the command and holding its output. For the benchmarks and the install's kernel warm-up."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out) if quiet else contextlib.nullcontext():
        code = main(argv)
    if code != 0:
        raise RuntimeError(f"posegrid {' '.join(argv)} exited {code}: {out.getvalue().strip()}")
    return out.getvalue()


if __name__ == "__main__":
    # run the imported module's main, not this __main__ copy: the subcommands raise services.errors.UsageError,
    # which must be the class main() catches
    from services.cli import main as imported_main

    sys.exit(imported_main())
