"""Secrets of a cell file: never written in it, only pointed to.

Every secret key (:data:`SECRET_KEYS`: the HMI access token, the HMI and OPC UA users'
passwords, the PLC units' passwords, the MQTT broker password) takes one of:

- ``env:VARIABLE``: the value of an environment variable of the process that needs it;
- ``file:PATH``: the contents of a file (relative to the cell file, ``~`` expanded; one trailing
  newline dropped); keep it readable by the service's user only;
- where the key says so (:data:`HASHED_KEYS`: users' passwords), a one-way hash
  (``pbkdf2_sha256$...``, :func:`hash_password`; ``packml hmi --hash-password``, ``packml opcua
  --hash-password``).

A secret written in plain text is refused when the cell file is loaded (by every loader: units,
coordinator, launcher, HMI, OPC UA), naming the key and never the value: the cell file is
published on each unit's latched ``~/config`` topic and recorded in bags. What is published or
recorded is :func:`redacted_yaml` anyway: every secret key, and every key whose name says it holds
one (token, password, secret, private key), reads :data:`REDACTED`.

A URL with credentials in it (``opc.tcp://user:password@host``) is refused the same way, at any
key: a user name and password come from their own keys (a PLC's ``user`` and ``password``). And
wherever a URL is shown (``~/config``, bags, refusals, log lines: :func:`redact_urls`, which
:func:`~.limits.printable` applies), its user information reads :data:`REDACTED`.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import hmac
import os
import re
import secrets
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml

from .files import open_regular
from .schema import Node, invalid

#: Key paths of secrets (``*``: any key of that mapping).
SECRET_KEYS: tuple[tuple[str, ...], ...] = (
    ("hmi", "token"),
    ("hmi", "users", "*", "password"),
    ("opcua", "users", "*"),
    ("units", "*", "plc", "password"),
    ("mqtt", "password"),
)
#: Secret keys that may also hold a one-way hash (passwords a program only checks) -> the
#: command that makes one.
HASHED_KEYS: Mapping[tuple[str, ...], str] = {
    ("hmi", "users", "*", "password"): "packml hmi --hash-password",
    ("opcua", "users", "*"): "packml opcua --hash-password",
}
REDACTED = "<redacted>"
MAX_SECRET_BYTES = 4096
HASH_PREFIX = "pbkdf2_sha256$"
HASH_PREFIXES = (HASH_PREFIX,)
_SECRET_NAME = re.compile(r"token|passw|secret|private|credential|api_?key", re.IGNORECASE)
_VARIABLE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
#: the user information of a URL (``scheme://user:password@``), up to its last ``@``
_USERINFO = re.compile(r"\b([A-Za-z][A-Za-z0-9+.-]*://)([^/\s?#]*)@")


def redact_urls(text: str) -> str:
    """``text`` with the user information of every URL in it (``opc.tcp://user:pw@host``)
    replaced by :data:`REDACTED`: what a message, a log line or a bag may carry of a URL."""
    return _USERINFO.sub(lambda m: f"{m.group(1)}{REDACTED}@", text) if "@" in text else text


def url_userinfo(text: str) -> bool:
    """Whether ``text`` holds a URL with user information (a user name, a password)."""
    return _USERINFO.search(text) is not None


def is_reference(value: Any, hashed: bool = False) -> bool:
    """Whether ``value`` may stand at a secret key: ``env:``/``file:`` (or a hash if allowed)."""
    if not isinstance(value, str):
        return False
    if value.startswith(("env:", "file:")) or value == REDACTED:
        return True
    return hashed and value.startswith(HASH_PREFIXES)


def _matches(root: Any, pattern: tuple[str, ...], path: str = "") -> list[tuple[str, Any]]:
    """(key path, value) of every entry of ``root`` that ``pattern`` names."""
    if not pattern:
        return [(path, root)]
    if not isinstance(root, Mapping):
        return []
    head, rest = pattern[0], pattern[1:]
    keys = [k for k in root if isinstance(k, str)] if head == "*" else [head] * (head in root)
    return [m for k in keys for m in _matches(root[k], rest, f"{path}.{k}" if path else k)]


def plain_secrets(document: Any) -> list[tuple[str, str]]:
    """Problems for every secret key of a cell document that holds a value instead of a
    reference, and for every URL that holds credentials (the value itself is never quoted)."""
    out = []
    for pattern in SECRET_KEYS:
        out.extend(_plain(document, pattern, HASHED_KEYS.get(pattern, "")))
    out.extend(_url_credentials(document))
    return out


def _url_credentials(value: Any, path: str = "") -> list[tuple[str, str]]:
    if isinstance(value, str):
        if "@" in value and url_userinfo(value):
            return [
                (
                    path,
                    "a URL never holds a user name or password (scheme://user:password@): "
                    "the cell file is published on the units' ~/config topic and recorded "
                    "in bags; give them with their own keys (user:, and password: as "
                    "env:VARIABLE or file:PATH)",
                )
            ]
        return []
    if isinstance(value, Mapping):
        return [
            p
            for k, v in value.items()
            for p in _url_credentials(v, f"{path}.{k}" if path else str(k))
        ]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _url_credentials(v, f"{path}[{i}]")]
    return []


def _plain(document: Any, pattern: tuple[str, ...], hasher: str) -> list[tuple[str, str]]:
    out = []
    for path, value in _matches(document, pattern):
        if value is None or value == "" or is_reference(value, bool(hasher)):
            continue  # (an empty value holds no secret: the key's own check refuses it)
        ways = "env:VARIABLE, file:PATH" + (f" or a hash ({hasher})" if hasher else "")
        out.append(
            (
                path,
                f"a secret is never written in the cell file (it is published "
                f"on the units' ~/config topic and recorded in bags): give {ways}",
            )
        )
    return out


def resolve(n: Node, base: Path, hashed: bool = False) -> str:
    """The secret a reference at ``n`` points to (raises the node's ``invalid`` otherwise).
    Messages name the variable or file, never what it holds."""
    value = n.value
    if isinstance(value, str) and value.startswith("env:"):
        var = value[4:]
        if not _VARIABLE.fullmatch(var):
            raise invalid(f"env:{var[:60]} is not an environment variable name")
        if var not in os.environ:
            raise invalid(f"environment variable {var} is not set")
        secret = os.environ[var]
    elif isinstance(value, str) and value.startswith("file:"):
        p = Path(value[5:]).expanduser()
        p = p if p.is_absolute() else base / p
        try:
            with open_regular(p) as f:
                data = f.read(MAX_SECRET_BYTES + 1)
        except OSError as exc:
            raise invalid(f"cannot read {p}: {exc.strerror or type(exc).__name__}") from None
        if len(data) > MAX_SECRET_BYTES:
            raise invalid(f"{p} is larger than {MAX_SECRET_BYTES} bytes: not a secret file")
        try:
            secret = data.decode("utf-8")
        except UnicodeDecodeError:
            raise invalid(f"{p} is not UTF-8 text") from None
        secret = secret[:-1] if secret.endswith("\n") else secret
        secret = secret[:-1] if secret.endswith("\r") else secret
    elif value == REDACTED:
        raise invalid("this configuration was recorded without its secrets: give the original")
    elif hashed and isinstance(value, str) and value.startswith(HASH_PREFIXES):
        return value
    else:
        raise invalid("give env:VARIABLE or file:PATH")
    if not secret.strip():
        raise invalid(f"{value[:80]} is empty")
    return secret


def hash_password(password: str, iterations: int = 200_000) -> str:
    """``pbkdf2_sha256$<iterations>$<salt>$<hash>`` (base64): what a users' password key may hold
    instead of a reference."""
    salt = secrets.token_bytes(16)
    digest = hashlib.pbkdf2_hmac("sha256", password.encode(), salt, iterations)
    b64 = base64.b64encode
    return f"{HASH_PREFIX}{iterations}${b64(salt).decode()}${b64(digest).decode()}"


def check_password(password: str | None, stored: str) -> bool:
    """Constant-time comparison with a plain or hashed password (``env:``/``file:`` are resolved
    at load)."""
    if password is None:
        return False
    if stored.startswith(HASH_PREFIX):
        try:
            iterations, salt, digest = stored[len(HASH_PREFIX) :].split("$")
            if not MIN_HASH_ITERATIONS <= int(iterations[:12]) <= MAX_HASH_ITERATIONS:
                return False  # (refused at load: check_hash)
            expected = base64.b64decode(digest)
            got = hashlib.pbkdf2_hmac(
                "sha256", password.encode(), base64.b64decode(salt), int(iterations)
            )
        except ValueError:
            return False
        return hmac.compare_digest(got, expected)
    return hmac.compare_digest(password.encode(), stored.encode())


#: iterations a stored hash may ask for: every login attempt costs them (a hash of 10**9 would
#: make each guess, and the rightful user's login, take minutes of a core)
MIN_HASH_ITERATIONS, MAX_HASH_ITERATIONS = 1000, 2_000_000


def check_hash(value: str) -> str:
    """``value`` when it is a well-formed :func:`hash_password` hash with an iteration count in
    ``MIN_HASH_ITERATIONS .. MAX_HASH_ITERATIONS`` (raises ``invalid``)."""
    parts = value[len(HASH_PREFIX) :].split("$")
    if not value.startswith(HASH_PREFIX) or len(parts) != 3 or not parts[0].isdigit():
        raise invalid("malformed password hash (expected pbkdf2_sha256$<n>$<salt>$<hash>)")
    if not MIN_HASH_ITERATIONS <= int(parts[0][:12]) <= MAX_HASH_ITERATIONS:
        raise invalid(
            f"a password hash of {parts[0][:12]} iterations: give "
            f"{MIN_HASH_ITERATIONS} .. {MAX_HASH_ITERATIONS} (a login costs them)"
        )
    return value


def redact(document: Any) -> Any:
    """A copy of a cell document with every secret value replaced by :data:`REDACTED`."""
    secret_paths = {path for pattern in SECRET_KEYS for path, _ in _matches(document, pattern)}

    def copy(value: Any, path: str) -> Any:
        if isinstance(value, Mapping):
            out = {}
            for k, v in value.items():
                where = f"{path}.{k}" if path else str(k)
                hidden = where in secret_paths or (
                    isinstance(k, str)
                    and _SECRET_NAME.search(k)
                    and not isinstance(v, Mapping | list)
                )
                out[k] = REDACTED if hidden and v is not None else copy(v, where)
            return out
        if isinstance(value, list):
            return [copy(v, f"{path}[{i}]") for i, v in enumerate(value)]
        return redact_urls(value) if isinstance(value, str) else value

    return copy(document, "")


@functools.lru_cache(maxsize=4)  # the launcher gives every unit of a cell the same text
def redacted_yaml(
    text: str, file: str = "<memory>", transform: Callable[[Any], Any] | None = None
) -> str:
    """The cell file ``text`` as YAML with its secrets redacted (what units publish on ``~/config``
    and bags record), ``transform`` applied to the document; raises
    :class:`~.schema.ConfigError` when ``text`` is not a document."""
    from .safe_yaml import parse_document

    document = redact(parse_document(text, file))
    if transform is not None:
        document = transform(document)
    return str(yaml.safe_dump(document, sort_keys=False, allow_unicode=True))
