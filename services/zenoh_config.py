"""The one place that builds Zenoh configurations for every posegrid process, opens their sessions and releases
what they declared on them (:func:`undeclare_all`), and closes them (:func:`close_session`).

Defaults (DESIGN.md): multicast scouting and the shared-memory transport off; a router listens on
tcp/127.0.0.1:7447; every other process is a Zenoh *client* that connects to that router and listens nowhere,
so nothing leaves the loopback interface and all traffic follows one path through the router. A user's JSON5 config file
overrides any of these keys it sets; ``--listen`` / ``--connect`` endpoints on the command line
override both.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import sys
import threading
from pathlib import Path

import zenoh

from services.errors import UsageError

#: where the router listens and everyone else connects unless configured otherwise
DEFAULT_ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"

#: the listen endpoints zenoh itself defaults to (any interface): a user file that leaves them unset
#: reads back as this, and posegrid replaces it with loopback-only endpoints
_ZENOH_DEFAULT_LISTEN = {"router": ["tcp/[::]:7447"], "peer": ["tcp/[::]:0"]}

MODES = ("router", "peer", "client")

#: how long a client keeps trying to reach its router before giving up (a router started alongside it,
#: e.g. by docker compose, may come up a little later), ms
CLIENT_CONNECT_TIMEOUT_MS = 10_000


def build_config(
    mode: str,
    *,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config for a process of ``mode`` ("router", "peer" or "client").

    Starts from ``config_file`` (JSON5) when given and fills every key the file leaves unset with
    posegrid's loopback-only defaults; non-empty ``listen`` / ``connect`` endpoint lists replace the
    corresponding keys. Raises :class:`services.errors.UsageError` for an unknown mode, a missing or invalid
    file, or an endpoint zenoh rejects.
    """
    if mode not in MODES:
        raise UsageError(f"zenoh mode must be one of {', '.join(MODES)}, got {mode!r}")
    if config_file is not None:
        path = Path(config_file)
        if not path.is_file():  # (zenoh would say only that it cannot read it)
            from schemas.files import not_a_file  # (numpy's import, for this message only: 70 ms a process start)

            raise UsageError(f"zenoh config file {path}: {not_a_file(path)}")
        try:
            config = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise UsageError(f"zenoh config file {path} is not valid: {_parse_problem(exc)}") from None
    else:
        config = zenoh.Config()
    _default(config, "mode", None, mode)
    _default(config, "scouting/multicast/enabled", None, False)
    # zenoh's shared-memory transport (on by default for messages of 3 KiB and more between processes of one
    # machine) lost blocking puts while the receiver's network thread waited for Python's GIL: 3 of 20 puts of
    # 1.6 MB to one slow subscriber (bench/chaos.py); over TCP on loopback all arrive
    _default(config, "transport/shared_memory/enabled", True, False)
    effective_mode = read_key(config, "mode")
    if effective_mode == "router":
        _default(config, "listen/endpoints", _ZENOH_DEFAULT_LISTEN, [DEFAULT_ROUTER_ENDPOINT])
    elif effective_mode == "peer":
        _default(config, "listen/endpoints", _ZENOH_DEFAULT_LISTEN, ["tcp/127.0.0.1:0"])
        _default(config, "connect/endpoints", [], [DEFAULT_ROUTER_ENDPOINT])
    else:
        _default(config, "listen/endpoints", _ZENOH_DEFAULT_LISTEN, [])
        _default(config, "connect/endpoints", [], [DEFAULT_ROUTER_ENDPOINT])
        _default(config, "connect/timeout_ms", None, CLIENT_CONNECT_TIMEOUT_MS)
    if listen:
        _check_ports(listen, "--listen", 0)
        _insert(config, "listen/endpoints", list(listen))
    if connect:
        _check_ports(connect, "--connect", 1)
        _insert(config, "connect/endpoints", list(connect))
    return config


def _check_ports(endpoints, option: str, lowest: int) -> None:
    """UsageError for an endpoint (proto/address:port[?...][#...]) whose port is digits outside lowest..65535: zenoh
    takes tcp/127.0.0.1:99999 to connect to and times out, or says its port is invalid with a hint about another
    process listening; other forms are left to zenoh."""
    for endpoint in endpoints:
        port = str(endpoint).split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[-1]
        if port.isdigit() and not lowest <= int(port) <= 65535:
            raise UsageError(f"{option} {endpoint}: port {port} is no TCP/UDP port ({lowest}..65535)")


def _default(config: zenoh.Config, key: str, unset_value, value) -> None:
    """Set ``key`` to ``value`` when it still holds ``unset_value`` (zenoh's reading of "not set")."""
    if read_key(config, key) == unset_value:
        _insert(config, key, value)


def read_key(config: zenoh.Config, key: str):
    """The value of ``key`` in ``config`` as a Python object (None when unset)."""
    return json.loads(config.get_json(key))


def _insert(config: zenoh.Config, key: str, value) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise UsageError(f"zenoh rejects {key} = {json.dumps(value)}: {_first_line(exc)}") from None


def _parse_problem(exc: BaseException) -> str:
    """A JSON5 parse error of zenoh's in one line: "line L, column C: expected ..." from its " --> L:C" position and
    "= expected ..." reason (the first line alone, " --> 22:2", said where but not what); else the first line."""
    text = str(exc)
    where = re.search(r"-->\s*(\d+):(\d+)", text)
    what = re.search(r"=\s*(.+?)(?:\s+at \S+\.rs:\d+)?\.?\s*$", text, re.MULTILINE)
    if where is None or what is None:
        return _first_line(exc)
    return f"line {where.group(1)}, column {where.group(2)}: {what.group(1).rstrip('. ')}"


def _first_line(exc: BaseException) -> str:
    """The first line of a zenoh error without the Rust source location it appends."""
    lines = str(exc).strip().splitlines()
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", lines[0]) if lines else type(exc).__name__
    return text.rstrip(". ")


#: s a process waits for its router before it says so on stderr (a router that is up answers in milliseconds)
ROUTER_WAIT_NOTE = 1.0


def _say_waiting(config: zenoh.Config, what: str) -> None:
    print(
        f"posegrid: {what} is waiting for the router at {json.dumps(read_key(config, 'connect/endpoints'))} "
        "(is `posegrid router` running there?)",
        file=sys.stderr,
        flush=True,
    )


#: what zenoh's error says when a listening endpoint's address is taken or not this machine's (the port hint's cue)
ADDRESS_TROUBLE = ("Address already in use", "Cannot assign requested address", "Permission denied")

#: the config keys of a session's own TLS files: (key, what the file is)
TLS_FILES = (
    ("transport/link/tls/root_ca_certificate", "CA certificate"),
    ("transport/link/tls/listen_certificate", "certificate"),
    ("transport/link/tls/listen_private_key", "private key"),
    ("transport/link/tls/connect_certificate", "certificate"),
    ("transport/link/tls/connect_private_key", "private key"),
)


def _no_passphrase() -> bytes:
    """ssl's password callback for a key with a passphrase: none (zenoh reads no passphrase; ssl would prompt)."""
    return b""


def _validity_problem(path: str | None, now: dt.datetime | None = None) -> str | None:
    """Why a certificate of the PEM file ``path`` is not valid at ``now`` (UTC; default: this machine's clock), in
    words with what to do; None when each is (or there is no file). Zenoh refuses such a certificate on either side
    of a connection without saying why: a client only times out, and the router logs nothing."""
    from cryptography import x509

    if path is None:
        return None
    now = now or dt.datetime.now(dt.timezone.utc)
    for certificate in x509.load_pem_x509_certificates(Path(path).read_bytes()):
        subject = certificate.subject.rfc4514_string()
        if now > certificate.not_valid_after_utc:
            return (
                f"expired on {certificate.not_valid_after_utc:%Y-%m-%d %H:%M} UTC ({subject}; this machine's clock "
                f"says {now:%Y-%m-%d %H:%M} UTC): make new material (posegrid secure-init --force, --days N)"
            )
        if now < certificate.not_valid_before_utc:
            return (
                f"is not valid before {certificate.not_valid_before_utc:%Y-%m-%d %H:%M} UTC ({subject}; this "
                f"machine's clock says {now:%Y-%m-%d %H:%M} UTC): set this machine's clock, or make the material on "
                "a machine whose clock is right"
            )
    return None


def check_local_files(config: zenoh.Config, what: str) -> None:
    """UsageError naming a file of ``config`` that the session could not use: a TLS file that is missing, not
    readable or not PEM that Python's ssl loads (a certificate with its key, a CA), or an empty user/password
    dictionary (zenoh then asks no password: docs/security.md), or a certificate that is expired or not valid yet at
    this machine's clock. zenoh would say only that no router answered, or, for the dictionary, nothing."""
    import ssl

    files = {key: read_key(config, key) for key, _ in TLS_FILES}
    for key, kind in TLS_FILES:
        path = files[key]
        if path is not None and not (os.path.isfile(path) and os.access(path, os.R_OK)):
            raise UsageError(f"{what}: its TLS {kind} {path} ({key}) is missing, not a file or not readable")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    pairs = [
        (files[f"transport/link/tls/{side}_certificate"], files[f"transport/link/tls/{side}_private_key"])
        for side in ("listen", "connect")
    ]
    try:
        if files["transport/link/tls/root_ca_certificate"] is not None:
            context.load_verify_locations(cafile=files["transport/link/tls/root_ca_certificate"])
        for certificate, key in pairs:
            if certificate is not None and key is not None:  # (a key with a passphrase: refused, not prompted for)
                context.load_cert_chain(certificate, key, password=_no_passphrase)
    except (ssl.SSLError, OSError) as exc:
        raise UsageError(
            f"{what}: its TLS files {', '.join(str(f) for f in files.values() if f)} do not load "
            f"({getattr(exc, 'reason', None) or exc}): a certificate that is not PEM, a key that is not its "
            "certificate's, or a key with a passphrase, which zenoh cannot take (posegrid secure-init --force)"
        ) from None
    for key, kind in TLS_FILES:
        problem = _validity_problem(files[key]) if kind.endswith("certificate") else None
        if problem is not None:
            raise UsageError(f"{what}: its TLS {kind} {files[key]} ({key}) {problem}")
    dictionary = read_key(config, "transport/auth/usrpwd/dictionary_file")
    if dictionary is not None:
        try:
            users = [line for line in Path(dictionary).read_text().splitlines() if line.strip()]
        except OSError as exc:
            raise UsageError(
                f"{what}: its user/password dictionary {dictionary} cannot be read ({exc.strerror})"
            ) from None
        if not users:
            raise UsageError(
                f"{what}: its user/password dictionary {dictionary} is empty, and zenoh would then ask no client for a "
                "password; write one user:password per line (posegrid secure-init)"
            )


def open_session(config: zenoh.Config, what: str, stop: threading.Event | None = None) -> zenoh.Session:
    """Open a Zenoh session; an unreachable router becomes a one-sentence :class:`UsageError`. With ``stop``, a stop
    while it waits for the router (up to the connect timeout) raises services.process.Stopped at once, and a wait
    longer than :data:`ROUTER_WAIT_NOTE` is said on stderr."""
    if stop is not None:
        from services.process import until_stopped

        note = threading.Timer(ROUTER_WAIT_NOTE, _say_waiting, (config, what))
        note.daemon = True
        note.start()
        try:
            return until_stopped(lambda: open_session(config, what), stop, "waiting for the router")
        finally:
            note.cancel()
    check_local_files(config, what)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        connect = read_key(config, "connect/endpoints")
        if not connect or "listener" in _first_line(exc):  # its own listening endpoint is what failed
            hint = (
                f"; is another process listening on {json.dumps(read_key(config, 'listen/endpoints'))}? pick another "
                "--listen (`posegrid run`: --router-port)"
                if any(words in str(exc) for words in ADDRESS_TROUBLE)
                else ""
            )
            raise UsageError(f"{what} could not open its zenoh session ({_first_line(exc)}){hint}") from None
        secured = any(str(endpoint).startswith("tls/") for endpoint in connect)
        raise UsageError(
            f"{what} could not open its zenoh session ({_first_line(exc)}); is `posegrid router` "
            f"running at {json.dumps(connect)}?"
            + (
                " Does it trust this client's certificate and password, and this client its CA (docs/security.md)?"
                if secured
                else ""
            )
        ) from None


def replier(reply: zenoh.Reply) -> str:
    """The id of the Zenoh session that sent ``reply`` ("?" when zenoh gives none): zenoh sets it, so a peer cannot
    give another session's (services.map_client.sort_answers, services.history.ask)."""
    source = reply.replier_id
    return "?" if source is None else str(source.zid)


#: the payload of the error reply zenoh makes for a queryable that did not answer in time (zenoh 1.x)
ZENOH_TIMEOUT_REPLY = b"Timeout"


def is_timeout_reply(reply: zenoh.Reply) -> bool:
    """Whether a reply is zenoh's own error for a queryable that did not answer before the query's timeout (its
    payload "Timeout"): no message refused, and no answer either (a slow or stalled process). The API counted a
    stalled shard's as a rejection, three a stall; a shard took a slow history's as the histories' whole answer and
    gave up on 359 scans."""
    error = reply.err
    return error is not None and error.payload.to_bytes() == ZENOH_TIMEOUT_REPLY


def close_session(session: zenoh.Session, what: str) -> None:
    """Close ``what``'s session. A close that fails (zenoh gives up after its timeout when the router or the machine
    stalls, "close operation timed out") is said in one line on stderr, not raised: the process is ending either way,
    and its declarations go with it."""
    try:
        session.close()
    except zenoh.ZError as exc:
        note = f"posegrid: {what}'s zenoh session did not close cleanly ({_first_line(exc)})"
        print(note, file=sys.stderr, flush=True)


def undeclare_all(entities: list) -> None:
    """Undeclare what a process declared on its session (publishers, subscribers, liveliness tokens, queryables),
    the newest first, and empty the list; its queryables are left to the session's close.

    Why: zenoh's router (1.10) keeps routing wildcard queries to a queryable that was undeclared while another
    session still declares the same key expression, and waits for that queryable's final answer until the query's
    timeout. Every shard declares pg/map/<map>/tile/**, and a source and a SLAM node pg/<robot>/history/**: once a
    source that had ended undeclared its history, each question to the SLAM node's history of poses (a shard's
    gaps, a restarted shard's catch-up) took its whole timeout. A closed session's queryables the router drops as it
    should (tests/test_pipeline.py, ``test_a_history_left_behind_answers_at_once``)."""
    for entity in reversed(entities):
        if not isinstance(entity, zenoh.Queryable):
            entity.undeclare()
    entities.clear()
