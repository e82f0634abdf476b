"""What an HTTP request must be before the HMI acts on it, and how answers are written.

- **Host** (every request): the ``Host`` header must be an IP address, ``localhost``, this
  machine's name or one of ``hmi.allowed_hosts``. A page on another site whose name was made to
  resolve to this server (DNS rebinding) sends its own name, and is refused.
- **Cross-site** (every POST): a browser's ``Sec-Fetch-Site`` must be ``same-origin`` (or
  ``none``: typed by the user) and an ``Origin`` must be this server's: another page cannot make
  a visitor's browser send a command. Tools (curl, scripts) send neither and pass.
- **Body** (actions): ``Content-Type: application/json`` (a cross-site form or ``text/plain``
  post cannot have it without the browser asking first), at most :data:`MAX_BODY` bytes (413
  before more is read), UTF-8 JSON, one object, no key twice, finite numbers, nested at most
  :data:`MAX_JSON_DEPTH`.
- **Answers**: JSON without ``NaN``/``Infinity`` (a non-finite number is written ``null``), so
  the page's ``JSON.parse`` never fails.

Every refusal is a :class:`~.access.Refusal`: a status, a reason code and a sentence.
"""

from __future__ import annotations

import ipaddress
import json
import math
import socket
from collections.abc import Iterable
from typing import Any

from fastapi import Request
from fastapi.responses import JSONResponse

from ..core.reasons import Reason
from .access import Refusal

MAX_BODY = 64 * 1024
MAX_JSON_DEPTH = 16
_SAME_SITE_OK = {"same-origin", "none"}


def _refusal(status: int, code: str, message: str) -> Refusal:
    reason = Reason.UNAUTHORIZED if status == 403 else Reason.INVALID_ARGUMENT
    return Refusal(status, reason, code, message)


# -- answers ---------------------------------------------------------------------------------------
def finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def dumps(value: Any) -> str:
    """Strict JSON (``null`` for a non-finite number); the common case costs one ``json.dumps``."""
    try:
        return json.dumps(value, separators=(",", ":"), allow_nan=False, ensure_ascii=False)
    except ValueError:
        return json.dumps(finite(value), separators=(",", ":"), allow_nan=False, ensure_ascii=False)


class Json(JSONResponse):
    """A JSON response written by :func:`dumps`."""

    def render(self, content: Any) -> bytes:
        return dumps(content).encode("utf-8")


def refuse(refusal: Refusal) -> Json:
    headers = {}
    if refusal.retry_after is not None:
        headers["Retry-After"] = str(max(1, math.ceil(refusal.retry_after)))
    return Json(refusal.body(), status_code=refusal.status, headers=headers)


# -- Host and cross-site ---------------------------------------------------------------------------
def _split_host(value: str) -> str | None:
    """The host part of a ``Host`` header (lower case), None when malformed."""
    value = value.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        if end < 0 or (value[end + 1 :] and not value[end + 2 :].isdigit()):
            return None
        return value[1:end]
    host, _, port = value.partition(":")
    if port and not port.isdigit():
        return None
    return host


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


class HostGuard:
    """The Host allow-list and the cross-site check (see the module)."""

    def __init__(self, names: Iterable[str] = ()) -> None:
        own = {"localhost", socket.gethostname().lower()}
        self.names = frozenset(own | {n.lower().strip("[]") for n in names if n})

    def host(self, request: Request) -> Refusal | None:
        raw = request.headers.get("host")
        host = _split_host(raw) if raw is not None else None
        if host is not None and host.endswith("."):
            host = host[:-1]
        if host is not None and (_is_ip(host) or host in self.names):
            return None
        return _refusal(
            403,
            "HOST_NOT_ALLOWED",
            "this HMI is not served under that host name (add it to hmi.allowed_hosts if it is "
            "the name operators use)",
        )

    def cross_site(self, request: Request) -> Refusal | None:
        site = request.headers.get("sec-fetch-site")
        if site is not None and site.lower() not in _SAME_SITE_OK:
            return _refusal(403, "CROSS_SITE", "a request from another site is never accepted")
        origin = request.headers.get("origin")
        if origin is not None:
            # an Origin is scheme://host[:port], as the Host header says it for the same server
            host = request.headers.get("host", "").lower()
            if not host or origin.lower() not in (f"http://{host}", f"https://{host}"):
                return _refusal(
                    403, "CROSS_SITE", "a request from another origin is never accepted"
                )
        return None


# -- bodies ----------------------------------------------------------------------------------------
def json_content(request: Request) -> Refusal | None:
    kind = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if kind != "application/json":
        return _refusal(
            415,
            "UNSUPPORTED_MEDIA_TYPE",
            "an action's body is JSON: send it with Content-Type: application/json",
        )
    return None


async def read_body(request: Request, limit: int = MAX_BODY) -> bytes | Refusal:
    """The request body, at most ``limit`` bytes (413 as soon as it is known to be longer)."""
    too_big = _refusal(413, "BODY_TOO_LARGE", f"the body is larger than {limit // 1024} kB")
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            return _refusal(400, "BAD_REQUEST", "Content-Length is not a number")
        if int(declared) > limit:
            return too_big
    chunks: list[bytes] = []
    size = 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            return too_big
        chunks.append(chunk)
    return b"".join(chunks)


class _BadJson(ValueError):
    pass


def _no_constant(name: str) -> Any:
    raise _BadJson(f"{name} is not a number JSON allows")


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _BadJson(f"key {key[:40]!r} is given twice")
        out[key] = value
    return out


def _depth(value: Any, limit: int) -> bool:
    """Whether ``value`` nests at most ``limit`` levels."""
    level = [value]
    for _ in range(limit + 1):
        level = [
            v
            for x in level
            for v in (x.values() if isinstance(x, dict) else x if isinstance(x, list) else ())
        ]
        if not level:
            return True
    return False


def parse_object(body: bytes) -> dict[str, Any] | Refusal:
    """The action's arguments: a JSON object (an empty body is ``{}``)."""
    if not body.strip():
        return {}
    try:
        text = body.decode("utf-8")
        value = json.loads(text, parse_constant=_no_constant, object_pairs_hook=_object)
    except UnicodeDecodeError:
        return _refusal(400, "MALFORMED_JSON", "the body is not UTF-8 text")
    except _BadJson as exc:
        return _refusal(400, "MALFORMED_JSON", f"the body is not valid JSON: {exc}")
    except RecursionError:
        return _refusal(400, "MALFORMED_JSON", "the body is nested too deeply")
    except ValueError as exc:  # JSONDecodeError; an integer of thousands of digits
        where = (
            f" (line {exc.lineno}, column {exc.colno})"
            if isinstance(exc, json.JSONDecodeError)
            else ""
        )
        return _refusal(400, "MALFORMED_JSON", f"the body is not JSON{where}")
    if not isinstance(value, dict):
        return _refusal(400, "MALFORMED_JSON", "the body must be a JSON object ({...})")
    if not _depth(value, MAX_JSON_DEPTH):
        return _refusal(400, "MALFORMED_JSON", "the body is nested too deeply")
    return value
