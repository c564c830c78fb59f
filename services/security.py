"""Access control for posegrid's Zenoh traffic, with Zenoh's own mechanisms (docs/security.md).

One function, :func:`write_material`, writes everything a secured deployment needs into one folder:

- a certificate authority (``ca.pem``; its private key is never written) that signs
- the router's TLS certificate (``router.pem``, ``router.key``) for the names and addresses clients reach it by,
- one client certificate per role (``<user>.pem``, ``<user>.key``; common name = the role's user name), since
  the router asks every client for one (mutual TLS),
- the router's user/password dictionary (``users.txt``, passwords from :func:`secrets.token_urlsafe`),
- ``router.json5``: TLS listen endpoint, mTLS, the dictionary and an ``access_control`` block that denies by
  default and allows each role only the messages it sends and receives on its own keys (:func:`acl_config`),
- ``<user>.json5`` per role: a client config that connects over TLS with the role's certificate and password.

Every file is 0600 and the folder 0700. A process takes its file with ``--zenoh-config`` (services/zenoh_config.py).

Roles (user names): ``source-<robot>``, ``slam-<robot>`` (the SLAM node of one robot), ``mapper-<map>`` (every
shard of one map), ``api`` (reads everything, writes nothing), ``launcher`` (`posegrid run`'s own session: map
stats, tiles and shard liveliness, read only).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from services import keys

#: the robot streams a source publishes (a posed-scan file's source publishes the poses too)
SOURCE_STREAMS = (keys.SCAN, keys.ODOM, keys.LANDMARKS, keys.POSE, keys.PRIOR, keys.END)
#: the robot streams a SLAM node subscribes to
SLAM_INPUTS = (keys.SCAN, keys.ODOM, keys.LANDMARKS, keys.PRIOR, keys.END)
#: the robot streams a mapper shard subscribes to
MAPPER_INPUTS = (keys.SCAN, keys.POSE, keys.END)
#: names the router certificate always holds, so a client on the router's machine can use either
LOOPBACK_NAMES = ("localhost", "127.0.0.1")
#: how long generated certificates are valid unless told otherwise (`posegrid secure-init`), days
DEFAULT_VALID_DAYS = 365
#: the longest validity `posegrid secure-init` gives its certificates, days (100 years; X.509 dates end in 9999)
MAX_VALID_DAYS = 36_500
#: how long the certificates of one `posegrid run --secure` are valid, days
RUN_VALID_DAYS = 7
#: bytes of randomness in each password (secrets.token_urlsafe: 32 bytes -> 43 characters)
PASSWORD_BYTES = 32

# the Zenoh ACL message kinds, by direction of use
_PUT, _SUB, _QUERY, _REPLY, _QUERYABLE = "put", "declare_subscriber", "query", "reply", "declare_queryable"
_TOKEN, _LIVE_SUB, _LIVE_QUERY = "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"


@dataclass(frozen=True)
class Role:
    """One Zenoh identity: a user name (also its certificate's common name) and the ACL rules it gets."""

    kind: str  # one of SCOPED_KINDS, "api" or "launcher"
    scope: str | None = None  # the robot (source, slam) or the map (mapper)

    @property
    def user(self) -> str:
        return self.kind if self.scope is None else f"{self.kind}-{self.scope}"


#: the role kinds with a scope (the robot of a source or SLAM node, the map of a mapper): users "<kind>-<scope>"
SCOPED_KINDS = ("source", "slam", "mapper")


@dataclass
class Material:
    """Where :func:`write_material` put everything (absolute paths)."""

    folder: Path
    ca: Path
    router_config: Path
    dictionary: Path
    clients: dict[str, Path] = field(default_factory=dict)  # user name -> its client config

    def config_for(self, role: Role | None) -> Path:
        """The Zenoh config of ``role`` (None: the router's)."""
        return self.router_config if role is None else self.clients[role.user]


def roles_for(robots: list[str], maps: list[str]) -> list[Role]:
    """Every role of a deployment with these robots and maps."""
    robots, maps = list(dict.fromkeys(robots)), list(dict.fromkeys(maps))
    return (
        [Role("source", r) for r in robots]
        + [Role("slam", r) for r in robots]
        + [Role("mapper", m) for m in maps]
        + [Role("api"), Role("launcher")]
    )


# --------------------------------------------------------------------------------------------- ACL


def _streams(robot: str, streams) -> list[str]:
    return [keys.robot_key(robot, s) for s in streams]


def role_permissions(role: Role) -> list[tuple[str, list[str], list[str]]]:
    """What ``role`` may do, as (flow, message kinds, key expressions) triples; everything else is denied.

    "ingress" is what the role sends to the router, "egress" what the router may hand it: the publications it
    subscribes to, the replies to its queries, the queries to its queryables, the liveliness tokens it asks for
    or watches, and the subscriber declarations that tell a publisher someone listens (matching status).
    """
    any_robot, any_map = "*", "*"
    r = role.scope or ""
    if role.kind == "source":
        return [
            ("ingress", [_PUT], _streams(r, SOURCE_STREAMS)),
            ("ingress", [_QUERYABLE, _REPLY], [keys.history_key(r)]),
            ("ingress", [_TOKEN], [keys.robot_alive_key(r, "source")]),
            ("ingress", [_QUERY], [keys.stats_key(any_map, "*"), keys.slam_stats_key(r)]),
            ("ingress", [_LIVE_QUERY], [keys.shard_alive_key(any_map, "*"), keys.robot_alive_key(r, "slam")]),
            ("egress", [_QUERY], [keys.history_key(any_robot)]),
            ("egress", [_REPLY], [keys.stats_key(any_map, "*"), keys.slam_stats_key(r)]),
            ("egress", [_TOKEN], [keys.shard_alive_key(any_map, "*"), keys.robot_alive_key(r, "slam")]),
            ("egress", [_SUB], [*_streams(any_robot, SOURCE_STREAMS), keys.robot_key(any_robot, "*")]),
        ]
    if role.kind == "slam":
        return [
            ("ingress", [_PUT], [keys.robot_key(r, keys.POSE)]),
            ("ingress", [_SUB], [keys.robot_key(r, "*")]),
            ("ingress", [_QUERYABLE, _REPLY], [keys.slam_stats_key(r), keys.history_key(r)]),
            ("ingress", [_QUERY], [keys.history_key(r)]),
            ("ingress", [_TOKEN], [keys.robot_alive_key(r, "slam")]),
            ("egress", [_PUT], _streams(r, SLAM_INPUTS)),
            ("egress", [_QUERY], [keys.slam_stats_key(r), keys.history_key(any_robot)]),
            ("egress", [_REPLY], [keys.history_key(r)]),
            ("egress", [_SUB], [keys.robot_key(any_robot, keys.POSE), keys.robot_key(any_robot, "*")]),
        ]
    if role.kind == "mapper":
        m = role.scope or ""
        own = f"{keys.ROOT}/map/{m}/**"
        return [
            ("ingress", [_PUT, _QUERYABLE, _REPLY], [own]),
            ("ingress", [_TOKEN], [keys.shard_alive_key(m, "*")]),
            ("ingress", [_SUB], [keys.robot_key(any_robot, "*")]),
            ("ingress", [_QUERY], [keys.history_key(any_robot)]),
            # (a shard resuming from its state asks which robots' sources and SLAM nodes are up: services.nodes.mapper)
            ("ingress", [_LIVE_QUERY], [keys.robot_alive_key(any_robot, "*")]),
            ("egress", [_PUT], _streams(any_robot, MAPPER_INPUTS)),
            ("egress", [_QUERY], [own]),
            ("egress", [_REPLY], [keys.history_key(any_robot)]),
            ("egress", [_TOKEN], [keys.robot_alive_key(any_robot, "*")]),
        ]
    everything = f"{keys.ROOT}/**"
    if role.kind == "api":
        return [
            ("ingress", [_SUB, _QUERY, _LIVE_SUB, _LIVE_QUERY], [everything]),
            ("egress", [_PUT, _REPLY, _TOKEN], [everything]),
        ]
    if role.kind == "launcher":
        maps = f"{keys.ROOT}/map/**"
        slam_stats = keys.slam_stats_key(any_robot)  # (why the shards gave up on scans: services.nodes.launcher)
        return [
            ("ingress", [_QUERY, _LIVE_QUERY], [maps]),
            ("ingress", [_QUERY], [slam_stats]),
            ("egress", [_REPLY, _TOKEN], [maps]),
            ("egress", [_REPLY], [slam_stats]),
        ]
    raise ValueError(f"unknown role kind {role.kind!r}")


def acl_config(roles: list[Role]) -> dict:
    """The router's ``access_control`` block: deny by default; each role's subject (its user name, which is
    also its certificate's common name: both must match) gets the allow rules of :func:`role_permissions`."""
    rules, subjects, policies = [], [], []
    for role in roles:
        ids = []
        for index, (flow, messages, key_exprs) in enumerate(role_permissions(role)):
            rule_id = f"{role.user}/{index}"
            rules.append(
                {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}
            )
            ids.append(rule_id)
        subjects.append({"id": role.user, "usernames": [role.user], "cert_common_names": [role.user]})
        policies.append({"id": role.user, "rules": ids, "subjects": [role.user]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def role_of_user(user: str) -> Role | None:
    """The role whose user name is ``user`` (``mapper-main``, ``api``), None for a name no role has."""
    if user in ("api", "launcher"):
        return Role(user)
    kind, _, scope = user.partition("-")
    return Role(kind, scope) if kind in SCOPED_KINDS and scope else None


#: the fields of a rule :func:`acl_config` writes (zenoh's copy of a config adds others)
_RULE_FIELDS = ("id", "permission", "flows", "messages", "key_exprs")


def stale_roles(block: object) -> list[str]:
    """The user names in a router's ``access_control`` block whose allow rules (as :func:`acl_config` names them) are
    not the ones this posegrid writes for their role: material made by an older posegrid. Its router denies, silently,
    what the processes now declare (a mapper's one subscriber on pg/*/*: services.intake), and they wait for messages
    that never come. Users that are no posegrid role, and rules of other names, are not looked at."""
    if not isinstance(block, dict) or not block.get("enabled"):
        return []
    rules = {rule.get("id"): rule for rule in block.get("rules") or [] if isinstance(rule, dict)}
    stale = []
    for subject in block.get("subjects") or []:
        user = subject.get("id") if isinstance(subject, dict) else None
        role = role_of_user(user) if isinstance(user, str) else None
        if role is None:
            continue
        for expected in acl_config([role])["rules"]:
            held = rules.get(expected["id"])
            if held is None or any(held.get(name) != expected[name] for name in _RULE_FIELDS):
                stale.append(role.user)
                break
    return stale


# --------------------------------------------------------------------------------------------- certificates


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def _new_key():
    from cryptography.hazmat.primitives.asymmetric import ec

    return ec.generate_private_key(ec.SECP256R1())


def _certificate(subject_cn: str, public_key, issuer_cn: str, issuer_key, days: float, extensions):
    """An X.509 certificate for ``subject_cn`` signed by ``issuer_key`` (SHA-256), valid from 5 min ago."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    start = _now() - dt.timedelta(minutes=5)
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject_cn)]))
        .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer_cn)]))
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + dt.timedelta(days=days))
    )
    for extension, critical in extensions:
        builder = builder.add_extension(extension, critical=critical)
    return builder.sign(issuer_key, hashes.SHA256())


#: every flag of a certificate's key usage extension (RFC 5280, 4.2.1.3)
_KEY_USAGES = (
    "digital_signature",
    "content_commitment",
    "key_encipherment",
    "data_encipherment",
    "key_agreement",
    "key_cert_sign",
    "crl_sign",
    "encipher_only",
    "decipher_only",
)


def _key_usage(*granted: str):
    """The key usage extension that grants ``granted`` (names of :data:`_KEY_USAGES`) and nothing else."""
    from cryptography import x509

    return x509.KeyUsage(**{name: name in granted for name in _KEY_USAGES})


def _leaf_extensions(ca_key, usage, names: list[str] | None):
    """Extensions of a router (``names``: its subject alternative names) or client certificate."""
    from cryptography import x509

    extensions = [
        (x509.BasicConstraints(ca=False, path_length=None), True),
        (_key_usage("digital_signature"), True),
        (x509.ExtendedKeyUsage([usage]), False),
        (x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), False),
    ]
    if names:
        extensions.append((x509.SubjectAlternativeName([_general_name(n) for n in names]), False))
    return extensions


def _general_name(name: str):
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path``, readable and writable by the owner only (0600) from the first byte."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o600)
    with os.fdopen(descriptor, "wb") as out:
        out.write(data)
    os.chmod(path, 0o600)


def _pem_key(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _pem_cert(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def write_certificates(folder: Path, router_names: list[str], users: list[str], days: float) -> Path:
    """A CA (``ca.pem``), the router's certificate for ``router_names`` (``router.pem``/``router.key``) and one
    client certificate per user (``<user>.pem``/``<user>.key``, common name = the user) in ``folder``.
    The CA's key stays in memory. Returns the CA certificate's path."""
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    ca_key = _new_key()
    ca_name = f"posegrid CA {secrets.token_hex(4)}"
    ca = _certificate(
        ca_name,
        ca_key.public_key(),
        ca_name,
        ca_key,
        days,
        [
            (x509.BasicConstraints(ca=True, path_length=0), True),
            (_key_usage("digital_signature", "key_cert_sign", "crl_sign"), True),
            (x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False),
        ],
    )
    _write_private(folder / "ca.pem", _pem_cert(ca))
    leaves: list[tuple[str, x509.ObjectIdentifier, list[str] | None]] = [
        ("router", ExtendedKeyUsageOID.SERVER_AUTH, router_names)
    ]
    leaves += [(user, ExtendedKeyUsageOID.CLIENT_AUTH, None) for user in users]
    for name, usage, names in leaves:
        key = _new_key()
        cert = _certificate(name, key.public_key(), ca_name, ca_key, days, _leaf_extensions(ca_key, usage, names))
        _write_private(folder / f"{name}.key", _pem_key(key))
        _write_private(folder / f"{name}.pem", _pem_cert(cert))
    return folder / "ca.pem"


# --------------------------------------------------------------------------------------------- configs


def _tls_config(folder: Path, mode: str, endpoint: str, name: str, usrpwd: dict) -> dict:
    """The Zenoh config both ends share: a router listens on ``endpoint``, a client connects to it; over TLS only,
    trusting only the run's CA (``folder``/ca.pem), presenting the certificate of ``name`` and asking for the
    peer's (mutual TLS), with the user/password settings ``usrpwd``; no scouting."""
    side = "listen" if mode == "router" else "connect"
    return {
        "mode": mode,
        side: {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(folder / "ca.pem"),
                    f"{side}_certificate": str(folder / f"{name}.pem"),
                    f"{side}_private_key": str(folder / f"{name}.key"),
                    "enable_mtls": True,
                },
            },
            "auth": {"usrpwd": usrpwd},
        },
    }


def router_config(folder: Path, listen: str, roles: list[Role]) -> dict:
    """The router's Zenoh config: TLS on ``listen`` with client certificates required, the user/password
    dictionary, and :func:`acl_config`."""
    config = _tls_config(folder, "router", listen, "router", {"dictionary_file": str(folder / "users.txt")})
    config["access_control"] = acl_config(roles)
    return config


def client_config(folder: Path, connect: str, user: str, password: str) -> dict:
    """A client's Zenoh config: connect to ``connect`` over TLS, trusting only the run's CA, presenting
    ``user``'s certificate and password."""
    return _tls_config(folder, "client", connect, user, {"user": user, "password": password})


def prepare_folder(folder: Path) -> Path:
    """Create ``folder`` (and its parents) if needed and make it the owner's only (0700); returns it absolute."""
    folder = folder.resolve()
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    return folder


#: the files of a role's that secure-init writes, by suffix
ROLE_SUFFIXES = (".pem", ".key", ".json5")


def material_files(users: list[str]) -> list[str]:
    """The names of the files :func:`write_material` writes for ``users``."""
    leaves = ["router", *users]  # (each with a certificate and a key; the router's config and each user's)
    return [
        "ca.pem",
        "users.txt",
        "router.json5",
        *(f"{name}.pem" for name in leaves),
        *(f"{name}.key" for name in leaves),
        *(f"{user}.json5" for user in users),
    ]


def _check_targets(folder: Path, names: list[str]) -> None:
    """UsageError naming a file of ``names`` in ``folder`` that a write would fail on or go through: something there
    that is not a plain file (a folder, a link). Checked before anything is written, so a failure leaves the old
    material whole."""
    from services.errors import UsageError

    for name in names:
        path = folder / name
        if os.path.lexists(path) and not (path.is_file() and not path.is_symlink()):
            raise UsageError(f"{path} is not a plain file (a folder or a link?): remove it, then run secure-init again")


def _stale_files(folder: Path, users: list[str]) -> list[Path]:
    """The role files in ``folder`` of users a previous material had and ``users`` has not (their old passwords)."""
    prefixes = tuple(f"{kind}-" for kind in SCOPED_KINDS)
    return [
        path
        for path in sorted(folder.iterdir())
        if path.suffix in ROLE_SUFFIXES
        and path.stem.startswith(prefixes)
        and path.stem not in users
        and path.is_file()
        and not path.is_symlink()
    ]


def write_material(
    folder: Path,
    robots: list[str],
    maps: list[str],
    listen: str,
    connect: str,
    router_names: list[str] | None = None,
    days: float = DEFAULT_VALID_DAYS,
) -> Material:
    """Write the CA, certificates, passwords and Zenoh configs of a deployment with ``robots`` and ``maps`` into
    ``folder`` (created 0700; files 0600). The router listens on ``listen``, clients connect to ``connect``; its
    certificate names ``router_names`` besides localhost and 127.0.0.1. Existing files are replaced."""
    roles = roles_for(robots, maps)
    users = [role.user for role in roles]
    _check_targets(folder, material_files(users))  # (before anything is written: no half-replaced material)
    folder = prepare_folder(folder)
    for stale in _stale_files(folder, users):  # a role the new material drops (--force with fewer robots)
        stale.unlink()
    names = list(dict.fromkeys([*(router_names or []), *LOOPBACK_NAMES]))
    ca = write_certificates(folder, names, users, days)
    passwords = {user: secrets.token_urlsafe(PASSWORD_BYTES) for user in users}
    dictionary = folder / "users.txt"
    _write_private(dictionary, "".join(f"{user}:{password}\n" for user, password in passwords.items()).encode())
    material = Material(folder=folder, ca=ca, router_config=folder / "router.json5", dictionary=dictionary)
    _write_private(material.router_config, json.dumps(router_config(folder, listen, roles), indent=2).encode())
    for user, password in passwords.items():
        path = folder / f"{user}.json5"
        _write_private(path, json.dumps(client_config(folder, connect, user, password), indent=2).encode())
        material.clients[user] = path
    return material


# --------------------------------------------------------------------------------------------- `posegrid run`


def run_material(robot: str, map_name: str, endpoint: str) -> Material:
    """The material of one `posegrid run --secure` (one robot, one map; the router on ``endpoint``, a tls/
    endpoint) in a new 0700 folder under the system's temporary directory."""
    folder = Path(tempfile.mkdtemp(prefix="posegrid-secure-"))
    return write_material(folder, [robot], [map_name], endpoint, endpoint, days=RUN_VALID_DAYS)


def zenoh_argv(material: Material | None, role: Role | None) -> list[str]:
    """The ``--zenoh-config`` arguments of a child with ``role`` (None: the router); none without material."""
    return [] if material is None else ["--zenoh-config", str(material.config_for(role))]


def remove_material(material: Material | None) -> None:
    """Delete a run's material (its passwords and keys) once every child has stopped."""
    if material is not None:
        shutil.rmtree(material.folder, ignore_errors=True)
