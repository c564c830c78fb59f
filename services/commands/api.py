"""`posegrid api`: the HTTP API and browser viewer over the mapper shards (docs/api.md)."""
from __future__ import annotations

import argparse

from services.commands.argtypes import finite_float

DEFAULT_PORT = 8000


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.zenoh_config import add_zenoh_arguments

    api = subparsers.add_parser(
        "api", help="HTTP API and browser viewer of the maps (a Zenoh client of the mapper shards)",
        description="Serve the maps the mapper shards hold over HTTP: map summaries, PNG and .npz tiles at every "
        "zoom level (cached, with ETags), whole-map exports (npz, pgm+yaml, png), shard statistics, health, robot "
        "poses, a server-sent event stream, and the viewer at / (OpenAPI document at /openapi.json; /docs loads "
        "Swagger UI from a CDN). Connects to the Zenoh router as a client. Stops on Ctrl-C or SIGTERM.",
    )
    api.add_argument("--host", default="127.0.0.1",
                     help="address to listen on (default 127.0.0.1; 0.0.0.0 exposes the API to the network)")
    api.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})")
    api.add_argument("--cache-mb", type=finite_float, default=256.0,
                     help="memory for cached tiles, MiB (default 256; least recently used tiles go first)")
    api.add_argument("--query-timeout", type=finite_float, default=10.0,
                     help="how long a query to the shards may take, s (default 10)")
    add_zenoh_arguments(api)
    api.set_defaults(func=run_api)


def check_port_free(host: str, port: int) -> None:
    """Raise UsageError when nothing can listen on host:port (taken, or not an address of this machine)."""
    import socket

    from services.cli import UsageError

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise UsageError(f"cannot listen on {host}:{port} ({exc.strerror}); pick another --port "
                             "(`posegrid run`: --api-port)") from None


def run_api(args: argparse.Namespace) -> int:
    from services.cli import UsageError

    if not 0 < args.port < 65536:
        raise UsageError(f"--port must be a TCP port (1..65535), got {args.port}")
    if not args.cache_mb > 0 or not args.query_timeout > 0:
        raise UsageError("--cache-mb and --query-timeout must be > 0")
    check_port_free(args.host, args.port)
    from services.api.server import serve
    from services.zenoh_config import config_from_args

    return serve(args.host, args.port, config_from_args(args, "client"), int(args.cache_mb * 2 ** 20),
                 args.query_timeout)
