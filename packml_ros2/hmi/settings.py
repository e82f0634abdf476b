"""The ``hmi:`` block of a cell file::

    hmi:
      host: 127.0.0.1     # interface to serve on; anything but loopback only when asked
      port: 8080          # TCP port (0 = any free port)
      token: env:LINE3_HMI_TOKEN  # optional, env:VAR or file:PATH (never the token itself):
                          #   required for every action; without it the page is read-only
      title: Line 3       # optional: shown in the page header (default: the cell name)
      allowed_hosts: [hmi.line3.example]  # optional: host names the page is reached by (the
                          #   Host header), besides IP addresses, localhost and this machine's name

Every problem names its key path (``hmi.port``) like the rest of the configuration.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from pathlib import Path

from ..core import CellConfig, secrets
from ..core import schema as sc
from ..core.schema import ConfigError, Node

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
KEYS = {"host", "port", "token", "title", "allowed_hosts"}


@dataclass(frozen=True)
class HmiSettings:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    token: str | None = field(default=None, repr=False)  # None: every visitor may operate
    title: str = ""
    allowed_hosts: tuple[str, ...] = ()  # more names for the Host header (hmi.guard)

    @property
    def loopback(self) -> bool:
        """Whether only this machine can reach the server."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


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


def hmi_settings(cell: CellConfig) -> HmiSettings:
    """The validated ``hmi:`` block of ``cell`` (defaults when it has none); raises ConfigError
    listing every problem with its key path."""
    root = Node(dict(cell.hmi), "hmi")
    root.check_keys(KEYS)
    base = Path(cell.file).resolve().parent
    settings = HmiSettings(
        host=root.get("host", _host, DEFAULT_HOST),
        port=root.get("port", sc.integer(0, 65535), DEFAULT_PORT),
        token=root.get("token", lambda n: _token(n, base), None),
        title=root.get("title", sc.text, ""),
        allowed_hosts=tuple(n.parse(_host_name, "") for n in root.list_at("allowed_hosts")),
    )
    if root.problems:
        raise ConfigError(cell.file, root.problems)
    return settings
