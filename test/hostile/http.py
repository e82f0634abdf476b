"""Hostile HTTP requests for the HMI: :func:`hostile_requests` yields ``count`` requests from a
seed, each valid but for one fault (a foreign Host, another site's Origin, no or a wrong token,
the wrong content type, too large a body, malformed JSON, an argument out of range or of the
wrong type, an unknown unit, action, path or method), with the status and refusal code the
server must answer. None of them may change anything. :func:`raw` sends what an HTTP client
library would not (a huge announced length, an endless chunked body)."""

from __future__ import annotations

import contextlib
import json
import random
import re
import socket
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

EVIL_HOSTS = ("evil.example", "rebind.attacker.example:8080", "localhost.evil", "127.0.0.1.nip.io",
              "", "[::1", "a:b:c", "x" * 300, "hmi.example\x7f")  # fmt: skip
EVIL_ORIGINS = ("http://evil.example", "null", "https://127.0.0.1.evil", "file://", "http://[::1")
WRONG_TYPES = ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data",
               "application/jsonx", "text/json", "", "application/xml")  # fmt: skip
MALFORMED = (b'{"command": "reset"', b"\xff\xfe{}", b"[" * 20_000 + b"]" * 20_000, b"{" * 50,
             b'{"command": ' + b"9" * 5000 + b"}", b'{"mach_speed": NaN}', b'{"a": Infinity}',
             b'["reset"]', b'"reset"', b"42", b"null", b'{"command": 1, "command": 2}',
             b'{"a": ' * 40 + b"1" + b"}" * 40, b"\x00\x01\x02", b'{"\\ud800": 1}x')  # fmt: skip
INT_ABUSE: tuple[Any, ...] = (2**32 + 2, 4294967298, -(2**31) - 1, 2**31, 2**63, -1, 10**30,
                              1.5, True, None, "", [], {}, "4294967298", "x" * 200)  # fmt: skip


def _each(key: str, values: Iterable[Any], *more: dict[str, Any]) -> tuple[dict[str, Any], ...]:
    return (*({key: v} for v in values), *more)


#: For each unit action: arguments that must be refused (400 BAD_ARGUMENT).
BAD_ARGS: dict[str, tuple[dict[str, Any], ...]] = {
    "command": _each("command", (*INT_ABUSE, 0, 11, "jump", "\u202e"),
                     {"command": "reset", "source": "remote:x"}, {}),
    "set_mode": _each("mode", (*INT_ABUSE, 0, 32, "1" * 13), {}),
    "ack_alarms": _each("id", (v for v in INT_ABUSE if v != -1 and not isinstance(v, bool)),
                        {"all": "yes"}, {"everything": True}),
    "reset_alarms": ({"clear_first_out": "yes"}, {"clear_first_out": 1}, {"x": 1}),
    "reset_times": _each("scope", ("week", ["all"], None, 1)),
    "reset_counters": ({"all": True}, {"x": None}),
    "set_em_active": (*_each("em", ("a/b", "n" * 300, "", 5, "9x", "\u00e9m")),
                      {"em": "nozzle", "active": "yes"}),
    "set_mach_speed": _each("mach_speed", (-1, "fast", None, True, [1], 10**400)),
}  # fmt: skip
#: For each unit action: arguments that would be accepted (the base of a request with one fault).
GOOD_ARGS: dict[str, dict[str, Any]] = {
    "command": {"command": "reset"}, "set_mode": {"mode": 2}, "ack_alarms": {},
    "reset_alarms": {}, "reset_times": {"scope": "mode"}, "reset_counters": {},
    "set_em_active": {"em": "nozzle", "active": True}, "set_mach_speed": {"mach_speed": 1.0},
}  # fmt: skip


@dataclass
class Hostile:
    """One request and what the server must answer (``status``, refusal ``code``)."""

    fault: str
    method: str
    path: str
    status: int
    code: str
    headers: dict[str, str | bytes] = field(default_factory=dict)
    body: bytes | None = None
    client: str = "main"  # "guesser": sent from another address (wrong tokens get it throttled)


def hostile_requests(seed: int, count: int, unit: str, token: str) -> Iterator[Hostile]:
    """``count`` hostile requests against ``unit``'s actions on a server that requires ``token``."""
    rng = random.Random(seed)
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    makers = (_host, _cross_site, _no_token, _wrong_token, _content_type, _too_large, _malformed,
              _bad_argument, _bad_argument, _bad_argument, _not_found, _method)  # fmt: skip
    for _ in range(count):
        yield rng.choice(makers)(rng, unit, auth)


def _action(rng: random.Random, unit: str) -> tuple[str, str]:
    if rng.random() < 0.15:
        return rng.choice(("command", "set_mode")), "/api/cell/"
    return rng.choice(list(GOOD_ARGS)), f"/api/units/{unit}/"


def _good(rng: random.Random, unit: str) -> tuple[str, bytes]:
    action, prefix = _action(rng, unit)
    return prefix + action, json.dumps(GOOD_ARGS[action]).encode()


def _host(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    host = rng.choice(EVIL_HOSTS)
    if rng.random() < 0.3:
        return Hostile(f"Host {host[:20]!r}", "GET", rng.choice(("/", "/api/snapshot",
                       "/api/events", "/api/config", "/static/app.js")), 403, "HOST_NOT_ALLOWED",
                       {"Host": host})  # fmt: skip
    path, body = _good(rng, unit)
    return Hostile(f"Host {host[:20]!r}", "POST", path, 403, "HOST_NOT_ALLOWED",
                   {**auth, "Host": host}, body)  # fmt: skip


def _cross_site(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, body = _good(rng, unit)
    if rng.random() < 0.5:
        headers = {"Origin": rng.choice(EVIL_ORIGINS)}
    else:
        headers = {"Sec-Fetch-Site": rng.choice(("cross-site", "same-site", "CROSS-SITE"))}
    return Hostile(f"cross-site {headers}", "POST", path, 403, "CROSS_SITE", {**auth, **headers},
                   body)  # fmt: skip


def _no_token(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, body = _good(rng, unit)
    headers = {"Content-Type": "application/json"}
    if rng.random() < 0.5:
        headers["Authorization"] = rng.choice(("Bearer", "Basic abc", "", "bearer", "Token x"))
    return Hostile("no token", "POST", path, 403, "TOKEN_MISSING", headers, body)


def _wrong_token(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, body = _good(rng, unit)
    guess = rng.choice((f"guess-{rng.randrange(10**9)}", "x" * 2000, "\u00e9t\u00e9"))
    headers: dict[str, str | bytes] = {"Content-Type": "application/json"}
    if rng.random() < 0.7:
        headers["Authorization"] = f"Bearer {guess}".encode("latin-1")
    else:
        headers["X-Packml-Token"] = guess.encode("latin-1")
    # throttled after a few: either answer is a refusal of the guess
    return Hostile("wrong token", "POST", path, 403, "TOKEN_WRONG|THROTTLED", headers, body,
                   client="guesser")  # fmt: skip


def _content_type(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, body = _good(rng, unit)
    kind = rng.choice(WRONG_TYPES)
    headers = {**auth, "Content-Type": kind} if kind else {"Authorization": auth["Authorization"]}
    return Hostile(f"content type {kind!r}", "POST", path, 415, "UNSUPPORTED_MEDIA_TYPE", headers,
                   body)  # fmt: skip


def _too_large(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, _ = _good(rng, unit)
    size = rng.choice((64 * 1024 + 1, 100_000, 1_000_000))
    body = b'{"command": "' + b"x" * (size - 15) + b'"}'
    return Hostile(f"{size} bytes", "POST", path, 413, "BODY_TOO_LARGE", auth, body)


def _malformed(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    path, _ = _good(rng, unit)
    body = rng.choice(MALFORMED)
    return Hostile(f"body {body[:20]!r}", "POST", path, 400, "MALFORMED_JSON", auth, body)


def _bad_argument(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    action, prefix = _action(rng, unit)
    args = rng.choice(BAD_ARGS[action])
    body = json.dumps(args).encode()
    return Hostile(f"{action} {body[:40]!r}", "POST", prefix + action, 400, "BAD_ARGUMENT", auth,
                   body)  # fmt: skip


def _not_found(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    choice = rng.randrange(4)
    name = rng.choice(
        ("nope", "%00", "%2e%2e", "x" * 500, "%E2%80%AE", "filler%2Fcommand", "\u00e9")
    )
    path = (f"/api/units/{name}/command", f"/api/units/{unit}/{name}", f"/api/cell/{name}",
            f"/api/{name}")[choice]  # fmt: skip
    return Hostile(f"path {path[:40]!r}", "POST", path, 404, "NOT_FOUND", auth, b"{}")


def _method(rng: random.Random, unit: str, auth: dict[str, str]) -> Hostile:
    method = rng.choice(("PUT", "DELETE", "PATCH"))
    path = rng.choice((f"/api/units/{unit}/command", "/api/snapshot", "/api/auth", "/api/config"))
    return Hostile(f"{method} {path}", method, path, 405, "METHOD_NOT_ALLOWED", auth, b"{}")


def raw(port: int, head: bytes, chunks: Iterable[bytes] = ()) -> tuple[int, bytes]:
    """An HTTP request over a plain socket: ``head``, then ``chunks`` as long as the server has
    not answered; the status and the whole answer."""
    got = b""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head)
        for chunk in chunks:
            s.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                got += s.recv(65536)
            s.setblocking(True)
            if got:
                break
            try:
                s.sendall(chunk)
            except OSError:  # the server answered and closed
                break
        s.settimeout(10)
        while not _complete(got):
            try:
                data = s.recv(65536)
            except OSError:
                break
            if not data:
                break
            got += data
    return int(got.split(b" ", 2)[1]), got


def _complete(got: bytes) -> bool:
    end = got.find(b"\r\n\r\n")
    if end < 0:
        return False
    found = re.search(rb"content-length: (\d+)", got[:end].lower())
    return len(got) >= end + 4 + (int(found.group(1)) if found else 0)
