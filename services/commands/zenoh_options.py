"""The Zenoh options every posegrid process takes (--zenoh-config, --listen, --connect) and the config they
give (services.zenoh_config builds it)."""

from __future__ import annotations

import argparse

import zenoh

from services.commands.argtypes import path_argument
from services.zenoh_config import DEFAULT_ROUTER_ENDPOINT, build_config


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add --zenoh-config, --listen and --connect (every posegrid process takes them)."""
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--zenoh-config",
        type=path_argument,
        default=None,
        metavar="FILE",
        help="zenoh JSON5 config file; keys it sets override posegrid's loopback-only defaults",
    )
    group.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; overrides the file)",
    )
    group.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to connect to (repeatable; default {DEFAULT_ROUTER_ENDPOINT}, the router)",
    )


def config_from_args(args: argparse.Namespace, mode: str) -> zenoh.Config:
    """The config for a process of ``mode`` from the arguments :func:`add_zenoh_arguments` added."""
    return build_config(mode, listen=args.listen, connect=args.connect, config_file=args.zenoh_config)
