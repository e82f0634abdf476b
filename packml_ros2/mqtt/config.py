"""The ``mqtt:`` block of a cell file (every key optional)::

    mqtt:
      host: 127.0.0.1            # the broker
      port: 1883                 # 8883 is usual with tls
      group_id: packml           # Sparkplug group (spBv1.0/<group_id>/...)
      edge_node_id: <cell>       # Sparkplug edge node: the cell; each unit is a device
      client_id: packml-<cell>   # the MQTT client id; commands are recorded as mqtt:<client_id>
      units: [filler]            # which units to publish (default: all of the cell)
      username: packml           # broker user (optional)
      password: env:PACKML_MQTT_PASSWORD   # or file:PATH; never the password itself
      tls:                       # TLS to the broker (optional)
        ca_file: certs/ca.pem    #   the broker's CA (default: the system's)
        cert_file: certs/edge.pem  # client certificate and key (optional, together)
        key_file: certs/edge.key
      keepalive: 10              # seconds; the broker sends NDEATH after 1.5 x this of silence
      buffer: 1000               # messages kept while the broker is away (the oldest dropped)
      call_timeout: 10.0         # seconds a command waits for the unit's answer
      uns:                       # retained plain-JSON topics for non-Sparkplug consumers (optional)
        prefix: acme/plant1/packing/line1   # ISA-95 enterprise/site/area/line

Relative paths are relative to the cell file. Errors name the key path (``mqtt.port``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..core import schema as sc
from ..core import secrets as secret_sources
from ..core.config import CellConfig
from ..core.rules import SOURCE_NAME_GRAMMAR, is_source_name
from ..core.schema import ConfigError, Node, invalid

KEYS = {
    "host",
    "port",
    "group_id",
    "edge_node_id",
    "client_id",
    "units",
    "username",
    "password",
    "tls",
    "keepalive",
    "buffer",
    "call_timeout",
    "uns",
}
TLS_KEYS = {"ca_file", "cert_file", "key_file"}
#: Sparkplug ids: no topic separators or wildcards (Sparkplug 3.0, tck-id-topic-structure)
_ID_FORBIDDEN = set("/+#")


@dataclass(frozen=True)
class Tls:
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None


@dataclass(frozen=True)
class MqttConfig:
    cell: str
    units: tuple[str, ...]
    host: str = "127.0.0.1"
    port: int = 1883
    group_id: str = "packml"
    edge_node_id: str = ""
    client_id: str = ""
    username: str = ""
    password: str = field(default="", repr=False)
    tls: Tls | None = None
    keepalive: int = 10
    buffer: int = 1000
    call_timeout: float = 10.0
    uns_prefix: str = ""

    @property
    def edge(self) -> str:
        return self.edge_node_id or self.cell

    @property
    def client(self) -> str:
        return self.client_id or f"packml-{self.cell}"

    def topic(self, kind: str, device: str = "") -> str:
        """``spBv1.0/<group>/<kind>/<edge>[/<device>]``."""
        base = f"spBv1.0/{self.group_id}/{kind}/{self.edge}"
        return f"{base}/{device}" if device else base


def _sparkplug_id(n: Node) -> str:
    s = sc.text(n).strip()
    if not s or len(s) > 64 or _ID_FORBIDDEN & set(s):
        raise invalid(f"{sc.shown(s)} is not a Sparkplug id (1..64 characters, no / + #)")
    return s


def _prefix(n: Node) -> str:
    s = sc.text(n).strip().strip("/")
    parts = s.split("/")
    if not s or len(s) > 200 or any(not p or {"+", "#"} & set(p) for p in parts):
        raise invalid(
            f"{sc.shown(s)} is not a topic prefix (levels like enterprise/site/area/line)"
        )
    return s


def parse_mqtt(cell: CellConfig, base: Path | None = None) -> MqttConfig:
    """Validate ``cell.mqtt``; :class:`ConfigError` lists every problem with its key path."""
    base = base if base is not None else Path(cell.file).resolve().parent
    root = Node(dict(cell.mqtt), "mqtt")
    root.check_keys(KEYS)

    existing = sc.file_under(base, must_exist=True)
    units = sc.units_of(root, tuple(cell.units))
    tls = None
    if "tls" in root.mapping():
        t = root.child("tls", root.mapping().get("tls"))
        t.check_keys(TLS_KEYS)
        tls = Tls(*(t.get(k, existing, None) for k in ("ca_file", "cert_file", "key_file")))
        if (tls.cert_file is None) != (tls.key_file is None):
            t.error("cert_file and key_file go together: give both or neither")
    uns = ""
    if "uns" in root.mapping():
        u_node = root.child("uns", root.mapping().get("uns"))
        u_node.check_keys({"prefix"})
        uns = u_node.get("prefix", _prefix, "")
        if not uns:
            u_node.error("give the prefix (enterprise/site/area/line), or leave uns out")
    client_id = root.get("client_id", sc.text, "")
    if client_id and not is_source_name(client_id):
        root.child("client_id", client_id).error(
            f"{sc.shown(client_id)} is not a client id ({SOURCE_NAME_GRAMMAR}: commands are recorded as mqtt:<client_id>)"
        )
    password = ""
    if "password" in root.mapping():
        password = root.child("password", root.mapping()["password"]).parse(
            lambda x: secret_sources.resolve(x, base), ""
        )
    config = MqttConfig(
        cell=cell.cell,
        units=units,
        host=root.get("host", lambda x: sc.text(x).strip() or "127.0.0.1", "127.0.0.1"),
        port=root.get("port", sc.integer(1, 65535), 1883),
        group_id=root.get("group_id", _sparkplug_id, "packml"),
        edge_node_id=root.get("edge_node_id", _sparkplug_id, ""),
        client_id=client_id,
        username=root.get("username", sc.text, ""),
        password=password,
        tls=tls,
        keepalive=root.get("keepalive", sc.integer(2, 3600), 10),
        buffer=root.get("buffer", sc.integer(0, 1_000_000), 1000),
        call_timeout=root.get("call_timeout", sc.number(positive=True), 10.0),
        uns_prefix=uns,
    )
    if config.password and not config.username:
        root.child("username", None).error("a password needs a username")
    if root.problems:
        raise ConfigError(cell.file, root.problems)
    return config
