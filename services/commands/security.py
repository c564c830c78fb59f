"""`posegrid secure-init`: the CA, certificates, passwords and Zenoh configs of a secured deployment
(services/security.py, docs/security.md)."""

from __future__ import annotations

import argparse
import ipaddress
import re

from services.commands.argtypes import path_argument
from services.commands.options import add_command

#: where a router listens and clients connect unless told otherwise (the port of DEFAULT_ROUTER_ENDPOINT)
DEFAULT_PORT = 7447


def register(subparsers: argparse._SubParsersAction) -> None:
    init = add_command(subparsers, "secure-init", run_secure_init)
    init.add_argument(
        "folder", type=path_argument, metavar="DIR", help="folder to write into (empty or new, unless --force)"
    )
    init.add_argument(
        "--robot",
        action="append",
        default=None,
        metavar="NAME",
        help="a robot that may publish (repeatable; default robot0)",
    )
    init.add_argument(
        "--map",
        action="append",
        default=None,
        metavar="NAME",
        help="a map whose shards may serve (repeatable; default main)",
    )
    init.add_argument(
        "--host",
        action="append",
        default=[],
        metavar="NAME",
        help="a DNS name or IP address clients reach the router by, put in its certificate; the first "
        "is the one the client configs connect to (repeatable; default the --listen-address, or "
        "127.0.0.1 when that is 0.0.0.0 or ::)",
    )
    init.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"the router's TCP port (default {DEFAULT_PORT})")
    init.add_argument(
        "--listen-address",
        default="127.0.0.1",
        metavar="ADDRESS",
        help="the address the router listens on (default 127.0.0.1; 0.0.0.0 serves other machines)",
    )
    init.add_argument(
        "--days", type=int, default=None, metavar="N", help="days the certificates are valid (default 365)"
    )
    init.add_argument("--force", action="store_true", help="replace what DIR holds")


#: one label of a DNS name (RFC 1123), 1 to 63 characters: letters, digits and inner hyphens, and underscores, which
#: RFC 1123 leaves out but container networks use in service names and TLS libraries accept
_DNS_LABEL = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?")


def _is_host(text: str) -> bool:
    """Whether ``text`` is an IP address or a DNS name (at most 253 characters of dot-separated labels, the last not
    all digits), the forms a certificate's subject alternative name and a Zenoh endpoint both take."""
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        pass
    labels = text.split(".")
    # a last label of digits only is no DNS name (RFC 3696, section 2): 256.0.0.1 or 1.2.3.4.5 is a mistyped address
    return 0 < len(text) <= 253 and all(_DNS_LABEL.fullmatch(label) for label in labels) and not labels[-1].isdigit()


def _endpoint_host(host: str) -> str:
    """``host`` as the address part of a Zenoh endpoint (an IPv6 address in brackets)."""
    return f"[{host}]" if ":" in host else host


def run_secure_init(args: argparse.Namespace) -> int:
    """write a CA, TLS certificates, passwords and per-role Zenoh configs (docs/security.md)

    Write into DIR (created with mode 0700 in a folder that exists; every file 0600) what a deployment secured with
    Zenoh's own mechanisms needs: a certificate authority (ca.pem; its key is not kept), the router's certificate
    for localhost, 127.0.0.1 and every --host, one client certificate and password per role, the router's config
    (router.json5: TLS with client certificates, the password dictionary, access control that denies by default) and
    one client config per role (ROLE.json5). Roles: source-ROBOT and slam-ROBOT per robot, mapper-MAP per map, api,
    launcher. Start each process with --zenoh-config DIR/ROLE.json5; run it again (with --force) to replace the
    material, e.g. for a new robot or before the certificates expire."""
    from schemas.files import output_folder_problem
    from services.commands.pipeline import DEFAULT_MAP, DEFAULT_ROBOT, _check_name
    from services.errors import UsageError
    from services.security import DEFAULT_VALID_DAYS, MAX_VALID_DAYS, write_material

    robots, maps = args.robot or [DEFAULT_ROBOT], args.map or [DEFAULT_MAP]
    for robot in robots:
        _check_name(robot, "--robot")
    for map_name in maps:
        _check_name(map_name, "--map")
    if not 0 < args.port < 65536:
        raise UsageError(f"--port must be a TCP port (1..65535), got {args.port}")
    days = DEFAULT_VALID_DAYS if args.days is None else args.days
    if not 1 <= days <= MAX_VALID_DAYS:
        raise UsageError(f"--days must be 1 to {MAX_VALID_DAYS} (100 years), got {days}")
    for option, value in [*(("--host", host) for host in args.host), ("--listen-address", args.listen_address)]:
        if not _is_host(value):
            raise UsageError(
                f"{option} takes a bare DNS name (letters, digits, '-', '_' and dots) or IP address, with no "
                f"scheme, port or brackets, got {value!r}"
            )
    listen = f"tls/{_endpoint_host(args.listen_address)}:{args.port}"
    problem = output_folder_problem(args.folder)
    if problem is not None:
        raise UsageError(f"{args.folder}: {problem}")
    if args.folder.is_dir() and any(args.folder.iterdir()) and not args.force:
        raise UsageError(f"{args.folder} is not empty; pass --force to replace its material")
    hosts = args.host or [args.listen_address if args.listen_address not in ("0.0.0.0", "::") else "127.0.0.1"]
    if ":" in hosts[0]:  # (material for ::1 was written, and no client could ever connect: "invalid dns name")
        raise UsageError(
            f"the clients would connect to the router at the IPv6 address {hosts[0]}, and Zenoh's TLS cannot check a "
            "certificate against an IPv6 address: give --host localhost (or another DNS name of the router's host) "
            "first"
        )
    connect = f"tls/{_endpoint_host(hosts[0])}:{args.port}"
    material = write_material(args.folder, robots, maps, listen, connect, router_names=hosts, days=days)
    print(f"posegrid secure-init: wrote {material.folder} (certificates valid {days} days)")
    print(f"  CA certificate (clients trust it): {material.ca}")
    print(f"  router: posegrid router --zenoh-config {material.router_config}   (listens on {listen})")
    for user, path in material.clients.items():
        print(f"  {user}: --zenoh-config {path}   (connects to {connect})")
    return 0
