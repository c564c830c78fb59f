"""Who may talk to the API: the Host header it answers to, and the access token, checked before anything else
(and before them, that the path holds no control character, a 404, and that the query gives no parameter twice, a
422).

Host (DNS rebinding: a page from evil.example whose name is made to resolve to this machine would otherwise read
the API as its own origin): the API answers only requests whose Host names it. Always: localhost, 127.0.0.1
and [::1] (a browser sends them only for pages loaded from this machine's own loopback address); when it
listens on a specific non-loopback address, that address too; and every ``--allowed-host`` name (``*``: any
host, for an API behind a proxy that checks the Host itself). Any port. Anything else is 400.

Token (``--token`` or POSEGRID_API_TOKEN): when set, every request needs it, in one of
- ``Authorization: Bearer TOKEN``;
- the ``token`` query parameter (``?token=TOKEN``), for clients that cannot set headers (EventSource);
- the ``posegrid_token`` cookie, which the API sets when the viewer is opened as ``/?token=TOKEN`` (it then
  redirects to ``/`` without the token in the address, and the viewer's requests carry the cookie).
Anything else is 401 with ``WWW-Authenticate: Bearer``. Tokens are compared with secrets.compare_digest.

Starlette's TrustedHostMiddleware does the Host part, but answers in plain text; this API answers every error
as ``{"detail": ...}``, so the check is written here.
"""

from __future__ import annotations

import ipaddress
import json
import re
import secrets
from collections import Counter
from collections.abc import Sequence
from urllib.parse import parse_qsl, urlencode

#: names every API answers to (lower case, IPv6 without brackets)
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
#: the cookie the viewer's token travels in
COOKIE = "posegrid_token"
#: the environment variable that gives the API its access token (a child inherits it: `posegrid run`)
TOKEN_ENV = "POSEGRID_API_TOKEN"
#: what a token may hold: characters that travel unchanged in a URL and a cookie (secrets.token_urlsafe's), at
#: least 16 of them
TOKEN_PATTERN = re.compile(r"^[A-Za-z0-9_.~-]{16,256}$")
#: a Host header: a name or IPv4 address, or an IPv6 address in brackets, then an optional port
HOST_HEADER = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+)(:[0-9]{1,5})?$")


def is_loopback(address: str) -> bool:
    """Whether ``address`` (an IP address or "localhost") is a loopback address."""
    if address.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(address.strip("[]")).is_loopback
    except ValueError:
        return False


def allowed_hosts(bind: str, extra: list[str]) -> frozenset[str]:
    """The Host names an API listening on ``bind`` answers to (see the module docstring); "*" in the set
    means any."""
    names = set(LOOPBACK_NAMES) | {name.lower().strip("[]") for name in extra}
    bound = bind.lower().strip("[]")
    if not is_loopback(bound) and bound not in ("0.0.0.0", "::", ""):
        names.add(bound)
    return frozenset(names)


def host_of(header: str | None) -> str | None:
    """The host of a Host header value, lower case, IPv6 without brackets; None when it is malformed."""
    match = HOST_HEADER.match(header or "")
    if match is None:
        return None
    port = match.group(2)
    if port is not None and not 0 < int(port[1:]) < 65536:
        return None
    return match.group(1).lower().strip("[]")


def _path_problem(path: str) -> tuple[int, list, bytes] | None:
    """The 404 for a path that holds a control character (no route's does), else None. The routes' patterns end in
    ``$``, which also matches before a final newline: /health%0A was answered as /health."""
    bad = next((char for char in path if ord(char) < 0x20 or ord(char) == 0x7F), None)
    if bad is None:
        return None
    return _problem(404, f"no path of this API holds a control character; this one holds {bad!r}")


def _query_problem(query_string: bytes) -> tuple[int, list, bytes] | None:
    """The 422 for a query that gives a parameter more than once (no route takes a list), else None: the routes read
    the last value, so ``vmax=-1&vmax=2`` was served with no word of the bad first one, and ``format=npz&format=png``
    as a PNG."""
    names = Counter(key for key, _ in parse_qsl(query_string.decode("latin-1"), keep_blank_values=True))
    repeated = sorted(name for name, count in names.items() if count > 1)
    if not repeated:
        return None
    shown = ", ".join(repr(name[:40]) for name in repeated[:4])
    return _problem(422, f"query parameter(s) {shown} given more than once; give each parameter once")


def _problem(status: int, detail: str, headers: Sequence[tuple[bytes, bytes]] = ()) -> tuple[int, list, bytes]:
    body = json.dumps({"detail": detail}).encode()
    return (
        status,
        [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), *headers],
        body,
    )


class Guard:
    """ASGI middleware: the Host and token checks of the module docstring, in front of ``app``."""

    def __init__(self, app, hosts: frozenset[str], token: str | None = None) -> None:
        self.app = app
        self.hosts = hosts
        self.token = None if token is None else token.encode()

    def _host_problem(self, scope):
        """None when the request's Host is one the API answers to; else the 400 to answer with."""
        given = [value for key, value in scope["headers"] if key == b"host"]
        if len(given) != 1:
            return _problem(400, f"the request must have one Host header, not {len(given)}")
        text = given[0].decode("latin-1")
        host = host_of(text)
        if host is None:
            return _problem(400, f"the Host header {text[:100]!r} is malformed")
        if "*" not in self.hosts and host not in self.hosts:
            return _problem(
                400,
                f"this API does not answer to the Host {text[:100]!r}; start it with --allowed-host "
                f"{host} (`posegrid run`: --api-allowed-host) to accept that name",
            )
        return None

    def _matches(self, given: str | None) -> bool:
        # only called with a token set (__call__ checks); without one, nothing matches
        return (
            given is not None
            and self.token is not None
            and secrets.compare_digest(given.encode("utf-8", "replace"), self.token)
        )

    def _token_answer(self, scope, headers: dict[bytes, bytes]):
        """None to let the request through; else the (status, headers, body) to answer with."""
        authorization = headers.get(b"authorization", b"").decode("latin-1")
        bearer = authorization[7:].strip() if authorization[:7].lower() == "bearer " else None
        query = parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)
        in_query = next((value for key, value in query if key == "token"), None)
        cookie = _cookie(headers.get(b"cookie", b"").decode("latin-1"), COOKIE)
        if self._matches(in_query) and scope["path"] == "/" and scope["method"] in ("GET", "HEAD"):
            rest = urlencode([(key, value) for key, value in query if key != "token"])
            location = "/" + (f"?{rest}" if rest else "")
            return (
                303,
                [
                    (b"location", location.encode("latin-1")),
                    (b"content-length", b"0"),
                    (b"set-cookie", (f"{COOKIE}={in_query}; Path=/; HttpOnly; SameSite=Lax").encode()),
                ],
                b"",
            )
        if self._matches(bearer) or self._matches(in_query) or self._matches(cookie):
            return None
        detail = (
            "this API needs its access token: send 'Authorization: Bearer TOKEN', or open the viewer as /?token=TOKEN"
            if bearer is None and in_query is None and cookie is None
            else "the access token is wrong"
        )
        return _problem(401, detail, [(b"www-authenticate", b'Bearer realm="posegrid"')])

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        answer = (
            _path_problem(scope["path"]) or _query_problem(scope.get("query_string", b"")) or self._host_problem(scope)
        )
        if answer is None and self.token is not None:
            answer = self._token_answer(scope, dict(scope["headers"]))
        if answer is None:
            await self.app(scope, receive, send)
            return
        status, response_headers, body = answer
        await send({"type": "http.response.start", "status": status, "headers": response_headers})
        await send({"type": "http.response.body", "body": body if scope["method"] != "HEAD" else b""})


def _cookie(header: str, name: str) -> str | None:
    """The value of cookie ``name`` in a Cookie header, None when absent."""
    for part in header.split(";"):
        key, _, value = part.strip().partition("=")
        if key == name:
            return value
    return None
