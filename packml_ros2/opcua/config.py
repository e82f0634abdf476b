"""The ``opcua:`` block of a cell file (every key optional)::

    opcua:
      host: 127.0.0.1              # listen address (0.0.0.0: every interface)
      port: 4840
      units: [robot_cell]          # which units to expose (default: all of the cell)
      allow_anonymous: true        # anonymous sessions may connect and read
      allow_anonymous_write: false # anonymous sessions may also call methods (commands)
      users:                       # user name -> password, for methods (commands, mode, speed)
        operator: env:PACKML_OPCUA_OPERATOR   # from the environment, or
        scada: file:secrets/scada.pw          # from a file, or
        mes: pbkdf2_sha256$...                # a hash (packml opcua --hash-password);
                                              # never plain text (packml_ros2.core.secrets)
      user_certificates:           # user name -> certificate (DER or PEM): X509 identity tokens,
        scada: certs/scada.der     #   or the client's application instance certificate
      security_policies: [None, Basic256Sha256_Sign, Basic256Sha256_SignAndEncrypt]
      certificate: certs/server.der    # the server's application instance certificate and key;
      private_key: certs/server.pem    #   default: self-signed, generated into state_dir
      trusted_client_certificates: []  # if set: only these client certificates may open a
                                       #   secure channel (default: any, the user decides rights)
      state_dir: ~/.local/state/packml_ros2/opcua
      application_uri: urn:packml_ros2:<cell>
      call_timeout: 10.0           # seconds a method waits for the unit's answer
      max_mach_speed: 60           # highest speed SetMachSpeed accepts: a number for every unit,
                                   #   or {unit: number}; default: each unit's mach_design_speed
      cell_object: false           # also the whole cell as one PackML object, PackMLObjects/<cell>:
                                   #   its state the coordinator's, its commands the cell commands
                                   #   (for a line of cells or an MES; needs the coordinator)

Relative paths are relative to the cell file. Errors name the key path (``opcua.users.mes``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..core import schema as sc
from ..core import secrets as secret_sources
from ..core.config import DEFAULT_STATE_DIR, CellConfig
from ..core.rules import SOURCE_NAME_GRAMMAR, is_source_name
from ..core.schema import ConfigError, Node, invalid
from ..core.secrets import HASH_PREFIX, check_hash, check_password, hash_password

__all__ = [  # (the password functions live in core.secrets, shared with the HMI's users)
    "DEFAULT_POLICIES", "HASH_PREFIX", "KEYS", "POLICIES", "OpcUaConfig", "check_password",
    "hash_password", "parse_opcua", "with_overrides",
]  # fmt: skip

#: Names accepted in ``security_policies`` -> asyncua SecurityPolicyType member names.
POLICIES = {
    "none": "NoSecurity",
    "basic256sha256_sign": "Basic256Sha256_Sign",
    "basic256sha256_signandencrypt": "Basic256Sha256_SignAndEncrypt",
    "aes128sha256rsaoaep_sign": "Aes128Sha256RsaOaep_Sign",
    "aes128sha256rsaoaep_signandencrypt": "Aes128Sha256RsaOaep_SignAndEncrypt",
    "aes256sha256rsapss_sign": "Aes256Sha256RsaPss_Sign",
    "aes256sha256rsapss_signandencrypt": "Aes256Sha256RsaPss_SignAndEncrypt",
}
DEFAULT_POLICIES = ("NoSecurity", "Basic256Sha256_Sign", "Basic256Sha256_SignAndEncrypt")
ANONYMOUS = "anonymous"  #: the user name of anonymous sessions (opcua:anonymous)
KEYS = {
    "host", "port", "units", "allow_anonymous", "allow_anonymous_write", "users",
    "user_certificates", "security_policies", "certificate", "private_key",
    "trusted_client_certificates", "state_dir", "application_uri", "call_timeout",
    "max_mach_speed", "cell_object",
}  # fmt: skip


@dataclass(frozen=True)
class OpcUaConfig:
    cell: str
    units: tuple[str, ...]
    host: str = "127.0.0.1"
    port: int = 4840
    allow_anonymous: bool = True
    allow_anonymous_write: bool = False
    users: dict[str, str] = field(default_factory=dict, repr=False)  # name -> password or hash
    user_certificates: dict[str, Path] = field(default_factory=dict)
    security_policies: tuple[str, ...] = DEFAULT_POLICIES
    certificate: Path | None = None
    private_key: Path | None = None
    trusted_client_certificates: tuple[Path, ...] = ()
    state_dir: Path = Path(DEFAULT_STATE_DIR).expanduser() / "opcua"
    application_uri: str = ""
    call_timeout: float = 10.0
    max_mach_speed: dict[str, float] = field(default_factory=dict)  # unit -> highest speed
    cell_object: bool = False  #: the cell as one PackML object too (:mod:`.cell`)

    @property
    def endpoint(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}/"

    @property
    def secure(self) -> bool:
        """Whether an endpoint other than None is configured (needs a certificate)."""
        return any(p != "NoSecurity" for p in self.security_policies)

    @property
    def access_control(self) -> bool:
        """Methods need a configured user (anonymous sessions cannot call them)."""
        return not self.allow_anonymous_write

    def app_uri(self) -> str:
        return self.application_uri or f"urn:packml_ros2:{self.cell}"


def _password(n: Node, base: Path) -> str:
    s = secret_sources.resolve(n, base, hashed=True)
    if s.startswith(HASH_PREFIX):
        check_hash(s)
    elif len(s) < 4:
        raise invalid("password too short (at least 4 characters)")
    return s


def _host(n: Node) -> str:
    s = sc.text(n).strip()
    if not s:
        raise invalid("empty host")
    return s


def _policy(n: Node) -> str:
    key = str(n.value).strip().lower().replace("-", "_")
    if key not in POLICIES:
        raise invalid(f"{n.value!r} is not one of None, {', '.join(DEFAULT_POLICIES[1:])}, ...")
    return POLICIES[key]


def _max_mach_speed(root: Node, cell: CellConfig) -> dict[str, float]:
    """``max_mach_speed``: one number for every unit, or a number per unit."""
    value = root.mapping().get("max_mach_speed")
    speed = sc.number(lo=0)
    if value is None or not isinstance(value, dict):
        limit = root.get("max_mach_speed", speed, None)
        return {} if limit is None else dict.fromkeys(cell.units, limit)
    out = {}
    for name, n in root.items_at("max_mach_speed"):
        if name not in cell.units:
            n.error(f"unknown unit {name!r}; the cell has {', '.join(cell.units)}")
        out[name] = n.parse(speed, 0.0)
    return out


def parse_opcua(cell: CellConfig, base: Path | None = None) -> OpcUaConfig:
    """Validate ``cell.opcua``; :class:`ConfigError` lists every problem with its key path."""
    file = cell.file
    base = base if base is not None else Path(file).resolve().parent
    root = Node(dict(cell.opcua), "opcua")
    root.check_keys(KEYS)

    path, existing = sc.file_under(base), sc.file_under(base, must_exist=True)
    units = sc.units_of(root, tuple(cell.units))
    users = {name: n.parse(lambda x: _password(x, base), "") for name, n in root.items_at("users")}
    certs = {name: n.parse(existing, Path()) for name, n in root.items_at("user_certificates")}
    for key in ("users", "user_certificates"):  # each is the source opcua:<user> as it is
        for name, n in root.items_at(key):
            if not is_source_name(name) or name == ANONYMOUS:
                why = "anonymous sessions' name" if name == ANONYMOUS else SOURCE_NAME_GRAMMAR
                n.error(
                    f"{sc.shown(name)} is not a user name ({why}: every action is recorded as opcua:<user>)"
                )
    policies = tuple(n.parse(_policy, "") for n in root.list_at("security_policies"))
    if "security_policies" in root.mapping() and not policies:
        root.child("security_policies", None).error("at least one policy is needed (e.g. None)")
    certificate = root.get("certificate", existing, None)
    private_key = root.get("private_key", existing, None)
    if (certificate is None) != (private_key is None):
        root.error("certificate and private_key go together: give both or neither")
    config = OpcUaConfig(
        max_mach_speed=_max_mach_speed(root, cell),
        cell=cell.cell,
        units=units,
        host=root.get("host", _host, "127.0.0.1"),
        port=root.get("port", sc.integer(0, 65535), 4840),
        allow_anonymous=root.get("allow_anonymous", sc.boolean, True),
        allow_anonymous_write=root.get("allow_anonymous_write", sc.boolean, False),
        users={k: v for k, v in users.items() if v},
        user_certificates=certs,
        security_policies=policies or DEFAULT_POLICIES,
        certificate=certificate,
        private_key=private_key,
        trusted_client_certificates=tuple(
            n.parse(existing, Path()) for n in root.list_at("trusted_client_certificates")
        ),
        state_dir=root.get("state_dir", path, Path(DEFAULT_STATE_DIR).expanduser() / "opcua"),
        application_uri=root.get("application_uri", sc.text, ""),
        call_timeout=root.get("call_timeout", sc.number(positive=True), 10.0),
        cell_object=root.get("cell_object", sc.boolean, False),
    )
    if config.cell_object and not cell.coordinator.enabled:
        root.child("cell_object", True).error(
            "the cell object is the coordinator's: enable the coordinator or leave this out"
        )
    if config.cell_object and cell.cell in cell.units:
        root.child("cell_object", True).error(
            f"a unit is named {cell.cell!r} like the cell: the cell object would take its name"
        )
    if not config.allow_anonymous and not config.users and not config.user_certificates:
        root.child("allow_anonymous", False).error(
            "nobody could connect: allow anonymous sessions or configure users"
        )
    if root.problems:
        raise ConfigError(file, root.problems)
    return config


def with_overrides(config: OpcUaConfig, **changes: Any) -> OpcUaConfig:
    """The configuration with command-line overrides (``None`` = keep)."""
    from dataclasses import replace

    return replace(config, **{k: v for k, v in changes.items() if v is not None})
