"""The ``hmi:`` block of a cell file::

    hmi:
      host: 127.0.0.1     # interface to serve on; anything but loopback only when asked
      port: 8080          # TCP port (0 = any free port)
      token: s3cret       # optional: required for every action; without it the page is read-only
      title: Line 3       # optional: shown in the page header (default: the cell name)

Every problem names its key path (``hmi.port``) like the rest of the configuration.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass

from ..core import CellConfig
from ..core import schema as sc
from ..core.schema import ConfigError, Node

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
KEYS = {"host", "port", "token", "title"}


@dataclass(frozen=True)
class HmiSettings:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    token: str | None = None  # None: no access control (every visitor may operate)
    title: str = ""

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


def _token(n: Node) -> str | None:
    if n.value is None:
        return None
    value = sc.text(n)
    if not value.strip():
        raise sc.invalid("an empty token would let anyone operate: remove the key instead")
    if len(value) < 4:
        raise sc.invalid("a token needs at least 4 characters")
    return value


def hmi_settings(cell: CellConfig) -> HmiSettings:
    """The validated ``hmi:`` block of ``cell`` (defaults when it has none); raises ConfigError
    listing every problem with its key path."""
    root = Node(dict(cell.hmi), "hmi")
    root.check_keys(KEYS)
    settings = HmiSettings(
        host=root.get("host", _host, DEFAULT_HOST),
        port=root.get("port", sc.integer(0, 65535), DEFAULT_PORT),
        token=root.get("token", _token, None),
        title=root.get("title", sc.text, ""),
    )
    if root.problems:
        raise ConfigError(cell.file, root.problems)
    return settings
