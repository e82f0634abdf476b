"""The ``hmi:`` block of a cell file::

    hmi:
      host: 127.0.0.1     # interface to serve on; anything but loopback only when asked
      port: 8080          # TCP port (0 = any free port)
      users:              # optional: user logins with levels (operator, maintenance, engineer)
        anna: {level: operator, password: "pbkdf2_sha256$..."}  # a hash (packml hmi
        ben: {level: engineer, password: env:LINE3_BEN_PW}       #   --hash-password), env: or file:
      users_file: hmi-users.yaml  # or: the users in a file of their own (a users: mapping as
                          #   above, relative to the cell file)
      logout_after: 900   # s without an action before a login ends (default 900)
      token: env:LINE3_HMI_TOKEN  # or: one shared access token, env:VAR or file:PATH (never the
                          #   token itself); without users or token whoever opens the page operates
      title: Line 3       # optional: shown in the page header (default: the cell name)
      allowed_hosts: [hmi.line3.example]  # optional: host names the page is reached by (the
                          #   Host header), besides IP addresses, localhost and this machine's name

With users or a token the page is read-only until someone logs in (or enters the token); who may
do what is :mod:`.access`'s table. Every problem names its key path (``hmi.port``) like the rest of
the configuration; a users file's problems name the file and their key path in it.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

from ..core import CellConfig, secrets
from ..core import schema as sc
from ..core.safe_yaml import read_document
from ..core.schema import ConfigError, Node
from .access import LEVELS, LOGOUT_AFTER, User

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
KEYS = {"host", "port", "token", "users", "users_file", "logout_after", "title", "allowed_hosts"}
USER_KEYS = {"level", "password"}
MAX_USERS = 1000


@dataclass(frozen=True)
class HmiSettings:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    token: str | None = field(default=None, repr=False)  # None: every visitor may operate
    title: str = ""
    allowed_hosts: tuple[str, ...] = ()  # more names for the Host header (hmi.guard)
    users: Mapping[str, User] = field(default_factory=dict, repr=False)  # name -> login
    logout_after: float = LOGOUT_AFTER

    @property
    def loopback(self) -> bool:
        """Whether only this machine can reach the server."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    @property
    def exposure(self) -> str | None:
        """The warning for a server other machines can reach that lets anyone operate (None:
        loopback only, or logins or a token guard the commands)."""
        if self.loopback or self.token or self.users:
            return None
        return (
            f"serving on {self.host} without logins or a token: every machine that reaches "
            "it can operate the cell (set hmi.users, or hmi.token: env:VAR or file:PATH)"
        )


def _host(n: Node) -> str:
    value = sc.text(n).strip()
    if not value or any(c.isspace() for c in value):
        raise sc.invalid(f"{value!r} is not a host name or IP address")
    return value


def _token(n: Node, base: Path) -> str | None:
    if n.value is None:
        return None
    if n.value == "":
        raise sc.invalid("an empty token would let anyone operate: remove the key instead")
    return check_token(secrets.resolve(n, base))


def check_token(value: str) -> str:
    """A usable access token (raises the schema's invalid otherwise; never quotes it)."""
    if len(value) < 8:
        raise sc.invalid("a token needs at least 8 characters")
    if len(value) > 1024 or not value.isprintable() or value != value.strip():
        raise sc.invalid("a token is 8 to 1024 printable characters without surrounding spaces")
    return value


def _host_name(n: Node) -> str:
    value = _host(n).lower()
    if len(value) > 253 or not all(c.isalnum() or c in "-._:[]" for c in value):
        raise sc.invalid(f"{sc.shown(value)} is not a host name")
    return value


def _user_name(name: str, _: Node) -> str:
    if not 1 <= len(name) <= 32 or not all(
        c.isascii() and (c.isalnum() or c in "._-") for c in name
    ):
        raise sc.invalid(f"{sc.shown(name)} is not a user name (1 to 32 letters, digits, . _ -)")
    return name


def _password(n: Node, base: Path) -> str:
    value = secrets.resolve(n, base, hashed=True)
    if value.startswith(secrets.HASH_PREFIX):
        return secrets.check_hash(value)
    if len(value) < 8:
        raise sc.invalid("a password needs at least 8 characters")
    return value


def _users(root: Node, base: Path) -> dict[str, User]:
    """The users of ``root`` (a ``users:`` mapping), each with its level and password."""
    users: dict[str, User] = {}
    entries = root.items()
    if len(entries) > MAX_USERS:
        root.error(f"{len(entries)} users: at most {MAX_USERS}")
        return users
    for name, n in entries:
        if n.parse(partial(_user_name, name), None) is None:
            continue
        if not isinstance(n.value, Mapping):
            n.error(f"expected {{level: ..., password: ...}}, got {sc.shown(n.value)}")
            continue
        n.check_keys(USER_KEYS)
        for key in sorted(USER_KEYS - set(n.mapping())):
            n.child(key, None).error("missing")
        level = n.get("level", sc.choice({x: x for x in LEVELS}), None)
        password = n.get("password", lambda x: _password(x, base), None)
        if level is not None and password is not None:
            users[name] = User(name, level, password)
    return users


def _users_file(n: Node, base: Path) -> tuple[dict[str, User], list[tuple[str, str]], str]:
    """The users of the file ``n`` names: (users, problems, the file's path)."""
    path = Path(sc.text(n)).expanduser()
    path = path if path.is_absolute() else base / path
    document: Any = read_document(path)  # (a ConfigError of its own: unreadable, not YAML)
    root = Node(document if document is not None else {}, "")
    root.check_keys({"users"})
    plain = secrets.plain_secrets({"hmi": {"users": root.mapping().get("users")}})
    if plain:  # (the same rule as in a cell file: a password is a hash, env: or file:)
        root.problems.extend((where.removeprefix("hmi."), problem) for where, problem in plain)
        return {}, root.problems, str(path)
    users = _users(root.child("users", root.mapping().get("users")), path.parent)
    return users, root.problems, str(path)


def hmi_settings(cell: CellConfig) -> HmiSettings:
    """The validated ``hmi:`` block of ``cell`` (defaults when it has none); raises ConfigError
    listing every problem with its key path."""
    root = Node(dict(cell.hmi), "hmi")
    root.check_keys(KEYS)
    base = Path(cell.file).resolve().parent
    users = _users(root.child("users", root.mapping().get("users")), base)
    if "users_file" in root.mapping():
        if "users" in root.mapping():
            root.child("users_file", None).error("give users or users_file, not both")
        else:
            found = root.get("users_file", lambda n: _users_file(n, base), None)
            if found is not None:
                users, problems, path = found
                if problems:
                    raise ConfigError(path, problems)
                if not users:
                    root.child("users_file", None).error(f"{path} lists no user")
    given = root.mapping()
    if ("users" in given or "users_file" in given) and "token" in given:
        root.child("token", None).error(
            "give users or a token, not both (with users every action is recorded with the "
            "name of who logged in)"
        )
    settings = HmiSettings(
        host=root.get("host", _host, DEFAULT_HOST),
        port=root.get("port", sc.integer(0, 65535), DEFAULT_PORT),
        token=root.get("token", lambda n: _token(n, base), None),
        title=root.get("title", sc.text, ""),
        allowed_hosts=tuple(n.parse(_host_name, "") for n in root.list_at("allowed_hosts")),
        users=users,
        logout_after=root.get("logout_after", sc.number(lo=10, hi=86400), LOGOUT_AFTER),
    )
    if root.problems:
        raise ConfigError(cell.file, root.problems)
    return settings
