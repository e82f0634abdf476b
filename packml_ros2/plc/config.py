"""The ``plc:`` block of a unit: a PackML machine whose state machine runs in a PLC and that is
reached over OPC UA for PackML (OPC 30050). Every key but ``endpoint`` is optional::

    units:
      filler:
        remote_commands_enabled: true      # as for any unit: the coordinator may command it
        plc:
          endpoint: opc.tcp://10.0.0.21:4840
          browse_path: PackMLObjects/Filler  # the PackMLBaseObjectType object, from Objects
          # node_id: "ns=3;s=Filler"         #   ... or its NodeId (then browse_path is unused)
          security_policy: Basic256Sha256  # None (default), Basic256Sha256, Aes128Sha256RsaOaep,
          security_mode: SignAndEncrypt    #   Aes256Sha256RsaPss; mode Sign or SignAndEncrypt
          user: packml                     # a user name (default: anonymous session)
          password: env:FILLER_PLC_PASSWORD  # env:VARIABLE or file:PATH, never the password
          certificate: certs/bridge.der    # this client's application instance certificate and
          private_key: certs/bridge.pem    #   key (default: self-signed, made once in state_dir)
          server_certificate: certs/filler.der  # the PLC's certificate: only this one is trusted
          lease: 3.0                       # s without a sign of life from the PLC: lost
          publishing_interval: 0.1         # s between the PLC's data change notifications
          reconnect_min: 0.5               # s before the first reconnection attempt, doubled
          reconnect_max: 10.0              #   after each failed one up to this
          call_timeout: 5.0                # s a method call may take
          state_dir: ~/.local/state/packml_ros2/plc
          application_uri: urn:packml_ros2:<cell>:<unit>

``lease`` defaults to the cell's ``coordinator.unit_lease`` and may not exceed it: every face
considers a unit gone within ``unit_lease``, and the bridge must have noticed by then. Relative
paths are relative to the cell file. Errors name the key path (``units.filler.plc.lease``); a
password is never quoted. The module is pure (no asyncua, no rclpy).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core import schema as sc
from ..core.config import DEFAULT_STATE_DIR, CellConfig
from ..core.schema import ConfigError, Node, invalid
from ..core.secrets import redact_urls, resolve

#: ``security_policy`` names -> asyncua ``security_policies.SecurityPolicy<name>`` suffixes.
POLICIES = {
    "none": "None",
    "basic256sha256": "Basic256Sha256",
    "aes128sha256rsaoaep": "Aes128Sha256RsaOaep",
    "aes256sha256rsapss": "Aes256Sha256RsaPss",
}
MODES = {"none": "None", "sign": "Sign", "signandencrypt": "SignAndEncrypt"}
KEYS = {
    "endpoint",
    "browse_path",
    "node_id",
    "security_policy",
    "security_mode",
    "user",
    "password",
    "certificate",
    "private_key",
    "server_certificate",
    "lease",
    "publishing_interval",
    "reconnect_min",
    "reconnect_max",
    "call_timeout",
    "state_dir",
    "application_uri",
}
#: Keys of a unit that belong to this package's own engine and mean nothing for a PLC unit.
ENGINE_ONLY = ("equipment_modules",)
_NODE_ID = re.compile(r"(ns=\d+;|nsu=[^;]+;)?[isgb]=.+")


@dataclass(frozen=True)
class PlcConfig:
    cell: str
    unit: str
    endpoint: str
    browse_path: tuple[str, ...] = ("PackMLObjects",)
    node_id: str = ""
    security_policy: str = "None"
    security_mode: str = "None"
    user: str = ""
    password: str = field(default="", repr=False)
    certificate: Path | None = None
    private_key: Path | None = None
    server_certificate: Path | None = None
    lease: float = 3.0
    publishing_interval: float = 0.1
    reconnect_min: float = 0.5
    reconnect_max: float = 10.0
    call_timeout: float = 5.0
    state_dir: Path = Path(DEFAULT_STATE_DIR).expanduser() / "plc"
    application_uri: str = ""

    @property
    def secure(self) -> bool:
        return self.security_policy != "None"

    def app_uri(self) -> str:
        return self.application_uri or f"urn:packml_ros2:{self.cell}:{self.unit}"

    def where(self) -> str:
        """The PLC object, for people: ``opc.tcp://host:4840 PackMLObjects/Filler``."""
        return f"{self.endpoint} {self.node_id or '/'.join(self.browse_path)}"


def plc_units(cell: CellConfig) -> list[str]:
    """The units of ``cell`` that are PLC units (a ``plc:`` block)."""
    return [name for name, unit in cell.units.items() if unit.plc is not None]


def secret(n: Node, base: Path) -> str:
    """The PLC password a reference at ``n`` points to (``env:VARIABLE`` or ``file:PATH``), by the
    one mechanism every secret of a cell file uses (:func:`packml_ros2.core.secrets.resolve`)."""
    return resolve(n, base)


def _endpoint(n: Node) -> str:
    s = sc.text(n).strip()
    if not s.startswith("opc.tcp://") or len(s) <= len("opc.tcp://"):
        raise invalid(
            f"{redact_urls(s[:100])!r} is not an OPC UA endpoint (opc.tcp://host:port/...)"
        )
    return s


def _browse_path(n: Node) -> tuple[str, ...]:
    parts = tuple(p.strip() for p in sc.text(n).strip().strip("/").split("/"))
    if not parts or not all(parts):
        raise invalid(
            "expected names separated by / from the Objects folder, e.g. PackMLObjects/Filler"
        )
    return parts


def _node_id(n: Node) -> str:
    s = sc.text(n).strip()
    if not _NODE_ID.fullmatch(s):
        raise invalid(f"{s[:100]!r} is not a NodeId (e.g. ns=3;s=Filler or ns=2;i=5001)")
    return s


def parse_plc(cell: CellConfig, unit: str, base: Path | None = None) -> PlcConfig:
    """Validate the ``plc:`` block of ``unit``; :class:`ConfigError` lists every problem."""
    base = base if base is not None else Path(cell.file).resolve().parent
    config = cell.units[unit]
    where = f"units.{unit}.plc"
    root = Node(dict(config.plc or {}), where)
    root.check_keys(KEYS)
    if config.equipment_modules:
        root.problems.append(
            (
                f"units.{unit}.equipment_modules",
                "a PLC unit's equipment modules live in the PLC: list none here",
            )
        )

    def path(x: Node) -> Path:
        p = Path(sc.text(x)).expanduser()
        return p if p.is_absolute() else base / p

    def existing(x: Node) -> Path:
        p = path(x)
        if not p.is_file():
            raise invalid(f"no such file: {p}")
        return p

    if "endpoint" not in root.mapping():
        root.error(
            "missing key 'endpoint' (the PLC's OPC UA server, e.g. opc.tcp://10.0.0.21:4840)"
        )
    unit_lease = cell.coordinator.unit_lease
    lease = root.get("lease", sc.number(positive=True), unit_lease)
    if lease > unit_lease:
        root.child("lease", lease).error(
            f"{lease:g} s is longer than coordinator.unit_lease {unit_lease:g} s: the cell would "
            "consider the unit gone before the bridge noticed"
        )
    interval = root.get("publishing_interval", sc.number(lo=0.01, hi=10.0), 0.1)
    if interval > lease / 4:
        root.child("publishing_interval", interval).error(
            f"{interval:g} s: at most a quarter of the lease ({lease / 4:g} s), so that the PLC's "
            "keep-alives arrive several times per lease"
        )
    policy = root.get("security_policy", sc.choice(POLICIES), "None")
    mode = root.get(
        "security_mode", sc.choice(MODES), "None" if policy == "None" else "SignAndEncrypt"
    )
    if (policy == "None") != (mode == "None"):
        root.child("security_mode", mode).error(
            f"security_policy {policy} goes with security_mode "
            + ("None" if policy == "None" else "Sign or SignAndEncrypt")
        )
    user = root.get("user", sc.text, "")
    password = root.get("password", lambda x: secret(x, base), "")
    if "password" in root.mapping() and not user:
        root.child("password", None).error("a password needs a user")
    certificate = root.get("certificate", existing, None)
    private_key = root.get("private_key", existing, None)
    if (certificate is None) != (private_key is None):
        root.error("certificate and private_key go together: give both or neither")
    reconnect_min = root.get("reconnect_min", sc.number(positive=True), 0.5)
    reconnect_max = root.get("reconnect_max", sc.number(positive=True), 10.0)
    if reconnect_max < reconnect_min:
        root.child("reconnect_max", reconnect_max).error(
            f"shorter than reconnect_min {reconnect_min:g} s"
        )
    out = PlcConfig(
        cell=cell.cell,
        unit=unit,
        endpoint=root.get("endpoint", _endpoint, ""),
        browse_path=root.get("browse_path", _browse_path, ("PackMLObjects", unit)),
        node_id=root.get("node_id", _node_id, ""),
        security_policy=policy,
        security_mode=mode,
        user=user,
        password=password,
        certificate=certificate,
        private_key=private_key,
        server_certificate=root.get("server_certificate", existing, None),
        lease=lease,
        publishing_interval=interval,
        reconnect_min=reconnect_min,
        reconnect_max=reconnect_max,
        call_timeout=root.get("call_timeout", sc.number(positive=True), 5.0),
        state_dir=root.get("state_dir", path, Path(DEFAULT_STATE_DIR).expanduser() / "plc"),
        application_uri=root.get("application_uri", sc.text, ""),
    )
    if root.problems:
        raise ConfigError(cell.file, root.problems)
    return out


def describe(config: PlcConfig) -> dict[str, Any]:
    """What the bridge says about its PLC in logs and diagnostics (no secret)."""
    return {
        "endpoint": config.endpoint,
        "object": config.node_id or "/".join(config.browse_path),
        "security": "None"
        if not config.secure
        else f"{config.security_policy} {config.security_mode}",
        "user": config.user or "anonymous",
        "lease": f"{config.lease:g} s",
    }
