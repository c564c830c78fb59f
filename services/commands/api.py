"""`posegrid api`: the HTTP API and browser viewer over the mapper shards (docs/api.md)."""

from __future__ import annotations

import argparse
import errno
import os
import socket
from collections.abc import Callable
from typing import Any, NamedTuple

from services.api import limits
from services.api.guard import TOKEN_ENV, TOKEN_PATTERN
from services.commands.argtypes import finite_float, positive_int, positive_seconds
from services.commands.options import add_command

DEFAULT_PORT = 8000
#: the largest --cache-mb (MiB) and --query-timeout (s): 1 TiB, a day (1e308 overflowed into tracebacks)
MAX_CACHE_MB = 2**20
MAX_QUERY_TIMEOUT = 86400.0


def access_token(text: str) -> str:
    """An access token: 16 to 256 of A-Z a-z 0-9 - _ . ~ (what travels unchanged in a URL and a cookie)."""
    if not TOKEN_PATTERN.match(text):
        raise argparse.ArgumentTypeError(
            "a token is 16 to 256 of A-Z a-z 0-9 - _ . ~ (make one with: python -c "
            "'import secrets; print(secrets.token_urlsafe())')"
        )
    return text


def host_name(text: str) -> str:
    """A name or address the Host header may give (``*``: any; an IPv6 address with or without brackets)."""
    import ipaddress

    from services.api.guard import host_of

    try:
        return str(ipaddress.IPv6Address(text))
    except ValueError:
        pass
    if text != "*" and host_of(text) != text.lower().strip("[]"):
        raise argparse.ArgumentTypeError(f"{text!r} is not a host name or address (no port, no scheme)")
    return text


class HttpOption(NamedTuple):
    """An option of `posegrid api`: given as --NAME (`posegrid run`: --api-NAME), parsed by ``type``, ``default``
    unless given, shown as ``metavar`` and ``help`` in --help; ``action`` "append" for a repeatable one."""

    name: str
    type: Callable[[str], Any]
    default: Any
    metavar: str
    help: str
    action: str = "store"


#: the HTTP options, which `posegrid run` takes too, as --api-NAME, and passes on
HTTP_OPTIONS = (
    HttpOption(
        "token",
        access_token,
        None,
        "TOKEN",
        f"require this access token on every request (default: ${TOKEN_ENV}, else none): 'Authorization: "
        "Bearer TOKEN', ?token=TOKEN, or the cookie the viewer gets when opened as /?token=TOKEN; prefer the "
        "environment variable, which other users cannot read in the process list",
    ),
    HttpOption(
        "allowed-host",
        host_name,
        [],
        "NAME",
        "also answer requests whose Host header is NAME (repeatable; localhost, 127.0.0.1 and [::1] always "
        "are, and the address it listens on; '*': any, behind a proxy that checks it). Others are 400 (DNS "
        "rebinding)",
        action="append",
    ),
    HttpOption(
        "max-event-clients",
        positive_int,
        limits.MAX_EVENT_CLIENTS,
        "N",
        f"event streams (GET /events) open at once; the next is 503 (default {limits.MAX_EVENT_CLIENTS})",
    ),
    HttpOption(
        "max-exports",
        positive_int,
        limits.MAX_EXPORTS,
        "N",
        f"exports built at once; the next is 503 (default {limits.MAX_EXPORTS})",
    ),
    HttpOption(
        "max-export-cells",
        positive_int,
        limits.MAX_EXPORT_CELLS,
        "N",
        f"cells the raster of one export may span, else 413: export a window (default "
        f"{limits.MAX_EXPORT_CELLS}, 4096 x 4096; {limits.EXPORT_BYTES_PER_CELL} bytes a cell as npz)",
    ),
    HttpOption(
        "max-connections",
        positive_int,
        limits.MAX_CONNECTIONS,
        "N",
        f"HTTP connections open at once; requests on further ones are 503 (default {limits.MAX_CONNECTIONS})",
    ),
    HttpOption(
        "keep-alive-timeout",
        positive_seconds,
        limits.KEEP_ALIVE,
        "S",
        f"s an idle keep-alive connection stays open (default {limits.KEEP_ALIVE:g})",
    ),
    HttpOption(
        "request-timeout",
        positive_seconds,
        limits.REQUEST_TIMEOUT,
        "S",
        f"s a request may take to arrive whole before its connection is closed (default {limits.REQUEST_TIMEOUT:g})",
    ),
)

#: what `posegrid api` tracks at most (its own options: `posegrid run` leaves them at their defaults)
TRACKING_OPTIONS = (
    HttpOption(
        "max-maps",
        positive_int,
        limits.MAX_MAPS,
        "N",
        f"maps held, announced or proved; further shard tokens are refused (default {limits.MAX_MAPS})",
    ),
    HttpOption(
        "max-robots",
        positive_int,
        limits.MAX_ROBOTS,
        "N",
        f"robots tracked; poses of further robots are refused (default {limits.MAX_ROBOTS})",
    ),
    HttpOption(
        "stray-robot-ttl",
        positive_seconds,
        limits.STRAY_TTL,
        "S",
        "s after its last pose that a robot with no source or SLAM node liveliness token is "
        f"forgotten (default {limits.STRAY_TTL:g})",
    ),
    HttpOption(
        "verify-window",
        positive_seconds,
        limits.VERIFY_WINDOW,
        "S",
        "s a shard's liveliness token may wait for the shard to answer its stats query before it "
        f"is ignored (default {limits.VERIFY_WINDOW:g})",
    ),
)


def _add_options(group: argparse._ArgumentGroup, options: tuple[HttpOption, ...], prefix: str = "") -> None:
    """Add each of ``options`` to ``group`` as --``prefix``NAME."""
    for option in options:
        group.add_argument(
            f"--{prefix}{option.name}",
            type=option.type,
            default=option.default,
            metavar=option.metavar,
            action=option.action,
            help=option.help,
        )


def add_http_arguments(parser: argparse.ArgumentParser, prefix: str = "") -> None:
    """The HTTP options as ``--{prefix}NAME`` (`posegrid run` uses prefix "api-")."""
    _add_options(parser.add_argument_group("HTTP access and limits (docs/api.md)"), HTTP_OPTIONS, prefix)


def _value(args: argparse.Namespace, prefix: str, name: str):
    return getattr(args, f"{prefix}{name}".replace("-", "_"))


def api_child_options(args: argparse.Namespace, prefix: str = "api-") -> list[str]:
    """The arguments that give a `posegrid api` child the HTTP options of ``args`` (those given as
    ``--{prefix}NAME``). The token goes in this process's environment (TOKEN_ENV), which the child inherits,
    not on its command line."""
    argv = []
    for option in HTTP_OPTIONS:
        value = _value(args, prefix, option.name)
        if option.name == "token":
            if value is not None:
                os.environ[TOKEN_ENV] = value
            else:
                env_token()  # (checked before a run starts its children, as --api-token is)
        elif option.name == "allowed-host":
            for host in value:
                argv += [f"--{option.name}", host]
        elif value != option.default:
            argv += [f"--{option.name}", str(value)]
    return argv


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.commands.zenoh_options import add_zenoh_arguments

    api = add_command(subparsers, "api", run_api)
    api.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; 0.0.0.0 exposes the API to the network: set "
        "--token and --allowed-host then)",
    )
    api.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT})")
    api.add_argument(
        "--cache-mb",
        type=finite_float,
        default=256.0,
        help="memory for cached tiles, MiB (default 256; least recently used tiles go first)",
    )
    api.add_argument(
        "--query-timeout",
        type=finite_float,
        default=10.0,
        help="how long a query to the shards may take, s (default 10)",
    )
    add_http_arguments(api)
    _add_options(api.add_argument_group("what the API tracks at most (docs/api.md)"), TRACKING_OPTIONS)
    add_zenoh_arguments(api)


def check_port_free(host: str, port: int, port_option: str = "--port") -> None:
    """Raise UsageError when nothing can listen on host:port (taken, or not an address of this machine); its message
    names ``port_option`` as the option to change when the port is taken."""
    listen_on(host, port, port_option).close()


def listen_on(host: str, port: int, port_option: str = "--port") -> socket.socket:
    """A TCP socket bound to host:port and listening, for the API to serve on; UsageError when it cannot be (taken:
    pick another ``port_option``; or ``host`` no address of this machine: another --host). Bound before the API says
    it serves: two APIs started on one port at once both passed a check that let the port go again, and the loser
    said "serving on ..." and then failed in uvicorn (its raw message, exit 3)."""
    from services.errors import UsageError

    try:
        listener = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
    except OSError as exc:  # (an IPv6 --host on a machine without IPv6)
        why = f"cannot listen on {host}:{port} ({exc.strerror})"
        raise UsageError(f"{why}; give --host an address of this machine") from None
    try:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((host, port))
        listener.listen(LISTEN_BACKLOG)
    except OSError as exc:
        listener.close()
        not_here = isinstance(exc, socket.gaierror) or exc.errno == errno.EADDRNOTAVAIL
        hint = "give --host an address of this machine (e.g. 127.0.0.1)" if not_here else f"pick another {port_option}"
        raise UsageError(f"cannot listen on {host}:{port} ({exc.strerror}); {hint}") from None
    return listener


#: connections the API's socket queues before they are accepted (uvicorn's own default)
LISTEN_BACKLOG = 2048


def token_of(args: argparse.Namespace) -> str | None:
    """--token, else the TOKEN_ENV environment variable (checked like --token), else None."""
    return args.token if args.token is not None else env_token()


def env_token() -> str | None:
    """The TOKEN_ENV environment variable, checked like --token (UsageError), or None when it is unset or empty."""
    from services.errors import UsageError

    value = os.environ.get(TOKEN_ENV) or None
    if value is not None and not TOKEN_PATTERN.match(value):
        raise UsageError(f"${TOKEN_ENV} must be 16 to 256 of A-Z a-z 0-9 - _ . ~")
    return value


def run_api(args: argparse.Namespace) -> int:
    """HTTP API and browser viewer of the maps (a Zenoh client of the mapper shards)

    Serve the maps the mapper shards hold over HTTP: map summaries, PNG and .npz tiles at every zoom level (cached,
    with ETags), whole-map exports (npz, pgm+yaml, png), shard statistics, health, robot poses, a server-sent event
    stream, and the viewer at / (OpenAPI document at /openapi.json; /docs loads Swagger UI from a CDN). Connects to
    the Zenoh router as a client. Stops on Ctrl-C or SIGTERM."""
    from services.errors import UsageError

    if not 0 < args.port < 65536:
        raise UsageError(f"--port must be a TCP port (1..65535), got {args.port}")
    if not 0 < args.cache_mb <= MAX_CACHE_MB:
        raise UsageError(f"--cache-mb must be > 0 and at most {MAX_CACHE_MB} (1 TiB), got {args.cache_mb:g}")
    if not 0 < args.query_timeout <= MAX_QUERY_TIMEOUT:
        raise UsageError(f"--query-timeout must be > 0 and at most {MAX_QUERY_TIMEOUT:g} s, got {args.query_timeout:g}")
    if not args.host:
        raise UsageError("--host '' would listen on every interface: give an address (127.0.0.1, or 0.0.0.0 for all)")
    token = token_of(args)
    listener = listen_on(args.host, args.port)
    from services.api.server import ServeOptions, serve
    from services.commands.zenoh_options import config_from_args

    options = ServeOptions(
        cache_bytes=int(args.cache_mb * 2**20),
        query_timeout=args.query_timeout,
        token=token,
        allowed_hosts=tuple(args.allowed_host),
        limits=limits.HttpLimits(args.max_event_clients, args.max_exports, args.max_export_cells),
        max_connections=args.max_connections,
        keep_alive=args.keep_alive_timeout,
        request_timeout=args.request_timeout,
        max_maps=args.max_maps,
        max_robots=args.max_robots,
        stray_ttl=args.stray_robot_ttl,
        verify_window=args.verify_window,
    )
    return serve(args.host, args.port, config_from_args(args, "client"), options, listener)
