"""``packml opcua``: a cell's units as OPC 30050 objects on an asyncua server.

:class:`PackMLServer` loads the official PackML NodeSet and instantiates one object per unit
(:mod:`.model`), configures endpoints, users and certificates from the ``opcua:`` block
(:mod:`.config`, :mod:`.security`), starts the ROS side (:mod:`.bridge`) and writes every status
and admin message of a unit into its object as it arrives. Several messages that arrive while a
write is in progress are coalesced per unit and topic: the newest one wins, so a slow client never
makes the server fall behind the cell.

A unit that is lost (:mod:`packml_ros2.presence`: no sign of life within ``unit_lease``) looks
lost: its Status and state machine values turn Bad_CommunicationError, its Admin values keep their
last value as Uncertain_LastUsableValue (:func:`.mapping.lost_status`), its methods are not
Executable and fail at once. When it is back, its values are Good again.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import ipaddress
import logging
import signal
import socket
from collections import OrderedDict
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from ..core.config import CellConfig, UnitConfig
from ..core.persistence import move_aside, not_a_file, one_line, os_reason
from ..presence import Seen
from . import line, security
from .available import unit_graph
from .bridge import CellMethods, Methods, RosSide
from .cell import cell_unit, coordinator_path
from .cell import valid as cell_valid
from .config import OpcUaConfig
from .mapping import (
    Step,
    Struct,
    Value,
    admin_values,
    available_values,
    lost_status,
    method_paths,
    nodeset_transitions,
    recipe_members,
    status_values,
    transition_steps,
    utc,
    version,
)
from .model import AddressSpace, UnitNodes, variable_paths

_logger = logging.getLogger(__name__)
PAIR_MAX = 1 << 20  #: bytes of a certificate or key file made before (they are a few kB)


def to_ua(value: Any) -> Any:
    """Mapping values -> what asyncua encodes (Structs become the generated data type classes)."""
    if isinstance(value, Struct):
        cls = getattr(ua, value.type)
        return cls(**{k: to_ua(v) for k, v in value.fields.items()})
    if isinstance(value, list):
        return [to_ua(v) for v in value]
    return value


def variant(v: Value) -> ua.Variant:
    if v.dims:
        return ua.Variant(to_ua(v.value), v.vtype, Dimensions=list(v.dims), is_array=True)
    if isinstance(v.value, list):
        return ua.Variant(to_ua(v.value), v.vtype, is_array=True)
    return ua.Variant(to_ua(v.value), v.vtype)


async def ensure_certificate(config: OpcUaConfig) -> tuple[Path, Path]:
    """The configured certificate and key, or a self-signed pair in ``state_dir`` (made once,
    renewed when it no longer matches the application URI or expires within a week)."""
    if config.certificate and config.private_key:
        return config.certificate, config.private_key
    return await own_certificate(
        config.state_dir / config.cell, config.app_uri(), f"packml_ros2 {config.cell}", config.host
    )


async def own_certificate(folder: Path, app_uri: str, name: str, host: str) -> tuple[Path, Path]:
    """A self-signed application instance certificate and its key in ``folder`` (made once,
    renewed when it no longer names ``app_uri`` or expires within a week): for this package's
    OPC UA server and for its clients of PLCs (:mod:`packml_ros2.plc`)."""
    from asyncua.crypto import cert_gen, uacrypto
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    cert_file, key_file = folder / "server_cert.der", folder / "server_key.pem"
    if cert_file.exists() or key_file.exists():
        try:  # files on disk are hostile input too: a bad pair is moved aside and made again
            for f in (cert_file, key_file):
                if (problem := not_a_file(f)) is not None:
                    raise problem
                if f.exists() and f.stat().st_size > PAIR_MAX:
                    raise ValueError(f"{f.name} is larger than {PAIR_MAX} bytes")
            if not (cert_file.exists() and key_file.exists()):  # (one made, then killed)
                raise FileNotFoundError(2, "one of the pair is missing")
            cert = await uacrypto.load_certificate(cert_file)
            key = await uacrypto.load_private_key(key_file)
            if cert.public_key().public_numbers() != key.public_key().public_numbers():
                raise ValueError("the key is not the certificate's")
            uris = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            if app_uri in uris.get_values_for_type(
                x509.UniformResourceIdentifier
            ) and cert.not_valid_after_utc > dt.datetime.now(dt.UTC) + dt.timedelta(days=7):
                return cert_file, key_file
        except (OSError, ValueError, TypeError, x509.ExtensionNotFound) as exc:
            moved = [
                move_aside(f).name for f in (cert_file, key_file) if f.exists() or f.is_symlink()
            ]
            _logger.warning(
                "%s: the certificate made before cannot be used (%s): moved aside (%s), a new "
                "one is made",
                folder,
                one_line(os_reason(exc)),
                ", ".join(moved),
            )
    folder.mkdir(parents=True, exist_ok=True)
    key = cert_gen.generate_private_key()
    names: list[x509.GeneralName] = [
        x509.UniformResourceIdentifier(app_uri),
        x509.DNSName(socket.gethostname()),
        x509.DNSName("localhost"),
        x509.IPAddress(ipaddress.ip_address("127.0.0.1")),
    ]
    try:
        names.append(x509.IPAddress(ipaddress.ip_address(host)))
    except ValueError:
        names.append(x509.DNSName(host))
    cert = cert_gen.generate_self_signed_app_certificate(
        key,
        name,
        {"organizationName": "packml_ros2"},
        list(dict.fromkeys(names)),
        [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        days=3650,
    )
    key_file.write_bytes(cert_gen.dump_private_key_as_pem(key))
    key_file.chmod(0o600)
    cert_file.write_bytes(cert.public_bytes(Encoding.DER))
    return cert_file, key_file


def warnings(config: OpcUaConfig) -> list[str]:
    """What in a configuration weakens security (printed at start)."""
    out = []
    if config.users and not any(p.endswith("SignAndEncrypt") for p in config.security_policies):
        out.append("no SignAndEncrypt policy: user passwords travel in clear text")
    loopback = config.host in ("127.0.0.1", "::1", "localhost")
    if not loopback and config.allow_anonymous_write:
        out.append(f"anyone who reaches {config.host}:{config.port} can command the units")
    if not loopback and "NoSecurity" in config.security_policies:
        out.append("the None policy is offered on a network interface: traffic is not protected")
    return out


def extra_steps(space: AddressSpace, unit: UnitConfig) -> dict[Step, str]:
    """The transitions of ``unit``'s rules, over all its modes, that the NodeSet does not model
    (e.g. Held -> Completing of TR88-2022): the unit object gets its own for them."""
    modelled = nodeset_transitions(space.model)
    out: dict[Step, str] = {}
    for mode in unit.modes:
        for step, cause in transition_steps(space.model, unit_graph(unit, mode)).items():
            if step not in modelled:
                out.setdefault(step, cause)
    return out


def _stamp(msg: Any) -> tuple[int, int]:
    return int(msg.stamp.sec), int(msg.stamp.nanosec)


class PackMLServer:
    """The OPC UA server of one cell."""

    def __init__(self, cell: CellConfig, config: OpcUaConfig) -> None:
        self.cell = cell
        self.config = config
        self.server: Server | None = None
        self.space: AddressSpace | None = None
        self.units: dict[str, UnitNodes] = {}
        self.ros: RosSide | None = None
        self._last: dict[tuple[str, str], tuple[Value, int]] = {}
        self._messages: dict[tuple[str, str], Any] = {}  # the newest status / admin per unit
        #: the rules each object is drawn with: the exposed units', and the cell object's
        self.configs: dict[str, UnitConfig] = {name: cell.units[name] for name in config.units}
        #: the name of the cell object ('' = none: :mod:`.cell`)
        self.cell_object = cell.cell if config.cell_object else ""
        if self.cell_object:
            self.configs[self.cell_object] = cell_unit(cell)
        self._present: dict[str, bool | None] = dict.fromkeys(self.configs)
        # per unit, mode and state
        self._available: dict[tuple[str, int, int], dict[str, Value]] = {}
        self._methods_now: dict[tuple[str, int, int], frozenset[str]] = {}
        self._pending: OrderedDict[tuple[str, str], Any] = OrderedDict()
        self._flushing: asyncio.Task[None] | None = None
        self.users: security.Users | None = None
        self.line: line.LineFace | None = None

    async def start(self) -> None:
        config = self.config
        security.install()
        self.users = await security.Users.load(config)
        server = Server(user_manager=self.users)
        await server.init()
        server.set_endpoint(config.endpoint)
        if config.host in ("0.0.0.0", "::"):  # endpoints name the address the client used
            server.set_match_discovery_client_ip(True)
        server.set_server_name(f"packml_ros2 cell {config.cell}")
        server.product_uri = "urn:packml_ros2"
        server.manufacturer_name = "packml_ros2"
        server.application_type = ua.ApplicationType.Server
        await server.set_application_uri(config.app_uri())
        if config.secure:
            cert, key = await ensure_certificate(config)
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
        server.set_security_policy(
            [ua.SecurityPolicyType[name] for name in config.security_policies],
            permission_ruleset=security.Rules(),
        )
        server.set_identity_tokens(self.users.identity_tokens())
        security.guard_writes(server)
        if config.trusted_client_certificates:
            server.set_certificate_validator(
                await security.trusted_validator(config.trusted_client_certificates)
            )
        self.server = server
        self.space = space = AddressSpace(server)
        await space.load_nodeset()
        await server.set_build_info(
            "urn:packml_ros2",
            "packml_ros2",
            "packml_ros2",
            f"OPC 30050 PackML {space.model.version}",
            "0",
            dt.datetime.now(dt.UTC),
        )
        for name, unit in self.configs.items():
            is_cell = name == self.cell_object
            kind = CellMethods if is_cell else Methods
            methods = kind(unit, config, space.model, ros=lambda: self.ros)
            nodes = self.units[name] = await space.build_unit(
                name,
                coordinator_path(name) if is_cell else f"/{self.cell.cell}/{name}",
                unit.description,
                {m.number: m.name for m in sorted(unit.modes.values(), key=lambda m: m.number)},
                version(unit.table.model),
                extra_steps(space, unit),
                methods.callbacks(),
                recipe_members(unit.recipes.recipes.values()),
            )
            machines = tuple(m.path for m in space.model.machines)
            for path, method in nodes.methods.items():
                executable = methods.executable
                if path.rpartition("/")[0] in machines:  # a state command: the state decides too
                    executable = partial(self._executable, methods.executable, name, path)
                security.executable_callbacks(server, method, executable, config)
        self.line = await line.LineFace.create(server, self.cell.cell)  # Objects/Lines/<cell>
        await server.start()
        self.ros = RosSide(
            self.cell.cell,
            list(config.units),
            asyncio.get_running_loop(),
            self._on_message,
            self._on_presence,
            self.cell.coordinator.unit_lease,
            cell_object=config.cell_object,
        )
        self.line.attach(self.ros.node, asyncio.get_running_loop())
        self.ros.start()

    # -- ROS -> OPC UA -----------------------------------------------------------------------------
    def _on_message(self, unit: str, topic: str, msg: Any) -> None:
        """In the loop: remember the newest message per (unit, topic), write them in order. The
        message's own stamp decides what is newest: one stamped before the message written last
        (an Admin the unit published before a newer one, delivered after it) is not written over
        it, so accumulated values never run backwards."""
        last = self._messages.get((unit, topic))
        if last is not None and _stamp(msg) < _stamp(last):
            return
        self._messages[(unit, topic)] = msg
        self._queue(unit, topic, msg)

    def _on_presence(self, unit: str, seen: Seen) -> None:
        """In the loop: the unit is lost or back; rewrite all its values with their status."""
        self._present[unit] = seen.present
        self._queue(unit, "presence", seen)

    def _queue(self, unit: str, what: str, item: Any) -> None:
        self._pending.pop((unit, what), None)
        self._pending[(unit, what)] = item
        if self._flushing is None or self._flushing.done():
            self._flushing = asyncio.get_running_loop().create_task(self._flush())

    async def _flush(self) -> None:
        while self._pending:
            (unit, what), item = self._pending.popitem(last=False)
            try:
                if what == "presence":
                    await self._rewrite(unit)
                else:
                    await self._apply(unit, what, item)
            except Exception:
                _logger.exception("OPC UA: could not write %s of %s", what, unit)

    def _values(self, unit: str, topic: str, msg: Any) -> dict[str, Value]:
        assert self.space is not None
        space = self.space
        if topic != "status":
            return admin_values(msg)
        values = status_values(msg, space.model, space.p)
        key = (unit, int(msg.unit_mode_current), int(msg.state_current))
        available = self._available.get(key)
        if available is None:
            graph = unit_graph(self.configs[unit], key[1], key[2])
            extra = self.units[unit].extra_transitions
            available = self._available[key] = available_values(space.model, graph, space.p, extra)
        values.update(available)
        return values

    def _executable(self, reachable: Callable[[], bool], unit: str, path: str) -> bool:
        """``Executable`` of the state machine method at ``path``: the unit is there
        (``reachable``) and the method causes a transition out of its current state in its
        current mode (the rule book's graph, :func:`.available.unit_graph`)."""
        status = self._messages.get((unit, "status"))
        if status is None or not reachable():
            return False
        mode, state = int(status.unit_mode_current), int(status.state_current)
        key = (unit, mode, state)
        methods = self._methods_now.get(key)
        if methods is None:
            assert self.space is not None
            graph = unit_graph(self.configs[unit], mode, state)
            methods = self._methods_now[key] = method_paths(self.space.model, graph)
        if path not in methods:
            return False
        # the cell object: the coordinator's all-or-nothing view of every unit decides too
        return unit != self.cell_object or cell_valid(status, path)

    async def _apply(self, unit: str, topic: str, msg: Any) -> None:
        assert self.server is not None
        stamp = utc(msg.stamp)
        source_time = None if stamp.year < 1971 else stamp
        nodes = self.units[unit].variables
        lost = self._present[unit] is False
        for path, value in self._values(unit, topic, msg).items():
            node = nodes.get(path)
            status = lost_status(path) if lost else value.status
            if node is None or self._last.get((unit, path)) == (value, status):
                continue
            self._last[(unit, path)] = (value, status)
            await self.server.write_attribute_value(
                node,
                ua.DataValue(
                    variant(value), StatusCode=ua.StatusCode(status), SourceTimestamp=source_time
                ),
            )

    async def _rewrite(self, unit: str) -> None:
        """Every value of ``unit`` again, with the status its presence gives it; values no message
        brought yet are Bad_CommunicationError while the unit is lost."""
        assert self.server is not None
        for topic in ("status", "admin"):
            msg = self._messages.get((unit, topic))
            if msg is not None:
                await self._apply(unit, topic, msg)
        if self._present[unit] is False:
            nodes = self.units[unit]
            now = dt.datetime.now(dt.UTC)
            for path in variable_paths(nodes):
                if (unit, path) not in self._last:
                    await self.server.write_attribute_value(
                        nodes.variables[path],
                        ua.DataValue(
                            StatusCode=ua.StatusCode(lost_status(path, known=False)),
                            SourceTimestamp=now,
                        ),
                    )

    # -- the rest ----------------------------------------------------------------------------------
    def describe(self) -> str:
        config = self.config
        names = {
            "NoSecurity": "None",
            "Basic256Sha256_Sign": "Basic256Sha256 Sign",
            "Basic256Sha256_SignAndEncrypt": "Basic256Sha256 SignAndEncrypt",
        }
        policies = ", ".join(names.get(p, p) for p in config.security_policies)
        anonymous = (
            "no"
            if not config.allow_anonymous
            else "read and call methods"
            if config.allow_anonymous_write
            else "read-only"
        )
        users = ", ".join([*config.users, *config.user_certificates]) or "none configured"
        lines = [
            f"OPC UA server for cell {config.cell} on {config.endpoint}",
            f"  units: {', '.join(config.units)} under Objects/PackMLObjects (OPC 30050 v1.01 "
            f"PackMLBaseObjectType; lost after {self.cell.coordinator.unit_lease:g} s without a sign of life)",
            f"  the line: Objects/Lines/{config.cell} (OEE of the shift, the current stop episode)",
            *(
                [
                    f"  the cell: Objects/PackMLObjects/{config.cell} (its coordinator's state and commands)"
                ]
                if config.cell_object
                else []
            ),
            f"  security policies: {policies}",
            f"  anonymous: {anonymous}; users for commands: {users}",
        ]
        lines += [f"  WARNING: {w}" for w in warnings(config)]
        return "\n".join(lines)

    async def stop(self) -> None:
        if self.ros is not None:
            await asyncio.get_running_loop().run_in_executor(None, self.ros.stop)
            self.ros = None
        if self._flushing is not None:
            self._flushing.cancel()
        if self.server is not None:
            await self.server.stop()
            self.server = None


class _QuietFaults(logging.Filter):
    """asyncua logs every service fault as an error; a client that deletes a subscription while
    publish requests are pending (BadNoSubscription) is routine, not an error."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "BadNoSubscription" not in record.getMessage()


def quiet_asyncua() -> None:
    """Log levels for a server process: asyncua's warnings and errors, without routine noise."""
    logging.getLogger("asyncua.server.uaprocessor").addFilter(_QuietFaults())
    logging.getLogger("asyncua.server.address_space").setLevel(logging.ERROR)


async def serve(
    cell: CellConfig,
    config: OpcUaConfig,
    ready: Callable[[str], None] = print,
    stop: asyncio.Event | None = None,
) -> int:
    """Run until ``stop`` is set, or SIGINT / SIGTERM; returns the exit code."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):  # not the main thread
            loop.add_signal_handler(sig, stop.set)
    server = PackMLServer(cell, config)
    try:
        await server.start()
        ready(server.describe())
        await stop.wait()
    finally:
        await server.stop()
    return 0
