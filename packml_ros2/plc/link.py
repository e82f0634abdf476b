"""The OPC UA session with one PLC (asyncua client): connect, find the unit's PackML object,
follow its values, call its methods; detect a loss within the lease; reconnect with back-off.

:class:`Link` runs in an asyncio loop of its own (:meth:`Link.start` makes the thread). One
session at a time, each made from scratch (:meth:`Link._session`):

1. connect to ``endpoint`` (security policy and mode, the client's certificate, the pinned PLC
   certificate, user and password from the ``plc:`` block), read the PackML namespace's index
   and the data type definitions of the PLC (to decode PackMLAlarmDataType and the others);
2. find the unit object (``node_id``, or ``browse_path`` from Objects) and translate every
   relative path the bridge follows (:data:`.mirror.PATHS`) and every method, in one request;
3. read every value (``on_connected``), then create a subscription (publishing interval
   ``publishing_interval``, a keep-alive at least every quarter lease) with one monitored item per
   value; each publish response is one batch (``on_values``);
4. watch: the PLC is lost when the connection closes, the subscription reports a bad status, or
   nothing (no notification, no keep-alive, no answer) came for ``lease`` seconds.

After a loss (``on_lost``) or a failed attempt the session is thrown away (``disconnect``, bounded
in time) and a new one is tried after ``reconnect_min`` seconds, doubled after every failed
attempt up to ``reconnect_max``. Nothing waits without a bound: every request has
``call_timeout``.

Method calls (:meth:`Link.call`) ask for operation-level diagnostics, so a PLC's reason for a
refusal (OPC UA Part 4 DiagnosticInfo: AdditionalInfo, LocalizedText) reaches the caller.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from asyncua import Client, Node, ua
from asyncua.common.subscription import Subscription
from asyncua.crypto import security_policies
from asyncua.ua.ua_binary import struct_from_binary

from ..opcua.nodeset import PACKML_URI, load
from .config import PlcConfig
from .mirror import MACHINES, PATHS, REQUIRED

_logger = logging.getLogger(__name__)
S = ua.StatusCodes
#: Standard (namespace 0) browse names among the relative paths; every other is PackML's.
STANDARD_NAMES = frozenset({"CurrentState", "Id", "Number", "EURange"})
#: RequestHeader.ReturnDiagnostics: operation-level symbolic id, localized text, additional info.
DIAGNOSTICS = 0x20 | 0x40 | 0x80
TICK = 0.05  # s between watchdog checks
#: Values a state machine's monitored item keeps between two publishes: every state the PLC
#: passed through reaches the mirror (acting states shorter than the publishing interval too).
QUEUE = 16
#: (endpoint, namespace array) of the PLCs whose data type definitions this process has loaded.
_TYPES_LOADED: set[tuple[str, tuple[str, ...]]] = set()


#: Status codes that end a session: the bridge reports the loss itself, in one line.
SESSION_ENDED = frozenset(
    {
        S.BadSessionClosed,
        S.BadSessionIdInvalid,
        S.BadConnectionClosed,
        S.BadSecureChannelClosed,
        S.BadShutdown,
        S.BadServerHalted,
        S.BadCommunicationError,
    }
)


class _Said(logging.Filter):
    """What asyncua logs that is no news:

    - "Browsename collision" of a standard (namespace 0) type: reading a PLC's data type
      definitions reads its standard enumerations too, which asyncua ships as ``ua`` classes
      already (a PLC type that collides is still logged);
    - "Publish iteration crashed" with its traceback when the PLC ended the session (closed,
      shut down, the connection gone): the bridge says "PLC lost: <reason>" once."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.msg.__class__ is str and record.msg.startswith("Browsename collision"):
            data_type = record.args[-1] if isinstance(record.args, tuple) and record.args else None
            return getattr(data_type, "NamespaceIndex", None) != 0
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, ua.UaStatusCodeError) and error.code in SESSION_ENDED:
            return False
        return not isinstance(error, (ConnectionError, asyncio.IncompleteReadError))


_SAID = _Said()


def quiet() -> None:
    """asyncua's client side logs errors only: it warns about every standard type it reads twice,
    every revised subscription parameter and every closed channel (the bridge says what matters);
    what it logs as an error that the bridge says itself is dropped (:class:`_Said`)."""
    for name in ("asyncua.client", "asyncua.common.structures104", "asyncua.common.subscription"):
        logging.getLogger(name).setLevel(logging.ERROR)
    for name in (
        "asyncua.ua.uatypes",
        "asyncua.client.ua_session.UaSession",
        "asyncua.client.ua_client",
    ):
        logger = logging.getLogger(name)
        if _SAID not in logger.filters:
            logger.addFilter(_SAID)


def method_paths() -> tuple[str, ...]:
    """Every method the bridge may call, by its path below the unit object."""
    model = load()
    out = [f"{m.path}/{method.name}" for m in model.machines for method in m.methods]
    out += [
        m.name
        for m in model.object_methods
        if m.name in ("SetUnitMode", "SetMachSpeed", "SetParameter", "SetProduct")
    ]
    return tuple(out)


def command_arguments(start: bool) -> list[ua.Variant]:
    """The input arguments of a state command's method: OPC 30050's Start takes the parameters
    of the run (an array of PackMLDescriptorDataType), sent empty; the others take none."""
    return [ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)] if start else []


@dataclass(frozen=True)
class Outcome:
    """The answer to a method call: its status code, the code's name and the PLC's reason."""

    status: int
    name: str
    text: str = ""

    @property
    def good(self) -> bool:
        return self.status & 0xC0000000 == 0


class Lost(Exception):
    """The session ended: why, in a sentence."""


class NotConnected(Exception):
    """A call while there is no session: why, in a sentence."""


def describe_error(exc: BaseException) -> str:
    """A sentence for a failed connection attempt or a lost session (no secret in it)."""
    if isinstance(exc, Lost | NotConnected):
        return str(exc)
    if isinstance(exc, ua.UaStatusCodeError):
        name = ua.StatusCode(exc.code).name
        hints = {
            "BadUserAccessDenied": "the PLC refused the user (user name or password)",
            "BadIdentityTokenInvalid": "the PLC refused the user (user name or password)",
            "BadIdentityTokenRejected": "the PLC refused the user (user name or password)",
            "BadSecurityChecksFailed": "the PLC refused this client's certificate",
            "BadCertificateUntrusted": "the PLC does not trust this client's certificate",
            "BadSecurityPolicyRejected": "the PLC does not offer the configured security policy",
        }
        return f"{hints.get(name, 'the PLC refused')}: {name}"
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused (no OPC UA server at the endpoint)"
    if isinstance(exc, asyncio.TimeoutError | TimeoutError):
        return "no answer in time"
    if isinstance(exc, OSError):
        return f"network error: {exc.strerror or type(exc).__name__}"
    text = str(exc).splitlines()[0][:200] if str(exc) else ""
    return f"{type(exc).__name__}{': ' + text if text else ''}"


def plain(value: Any) -> Any:
    """An asyncua value as plain Python: structures as dicts of their fields, LocalizedText and
    EUInformation as their text; an undecoded ExtensionObject as None."""
    if isinstance(value, ua.LocalizedText):
        return value.Text or ""
    if isinstance(value, ua.EUInformation):
        return value.DisplayName.Text or "" if value.DisplayName else ""
    if isinstance(value, ua.ExtensionObject):
        return None
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    return value


def diagnostic_text(response: Any) -> str:
    """The reason a CallResponse gives for its first result (AdditionalInfo, else LocalizedText
    or SymbolicId through the string table)."""
    infos = response.DiagnosticInfos or []
    if not infos:
        return ""
    info = infos[0]
    if info.AdditionalInfo:
        return str(info.AdditionalInfo)
    table = response.ResponseHeader.StringTable or []
    for attr in ("LocalizedText", "Locale", "SymbolicId"):  # see opcua.security: asyncua swaps two
        index = getattr(info, attr, None)
        if isinstance(index, int) and 0 <= index < len(table) and table[index]:
            return str(table[index])
    return ""


class _Batches:
    """Subscription handler: collects the notifications of one publish response (asyncua
    dispatches them in order, one task each) and hands them over as the PLC wrote them.

    A response may carry several values of one variable (the state machines' items keep a
    queue, :data:`QUEUE`): Stopping and Stopped of one publishing interval. The notifications
    are put in the order of their source timestamps (the PLC's cycles; arrival order where a
    PLC gives none) and handed over as consecutive batches, a new one where a variable repeats,
    so no value is overwritten by a later one of the same response."""

    def __init__(
        self,
        paths: Mapping[ua.NodeId, str],
        deliver: Callable[[dict[str, Any]], None],
        convert: Callable[[str, Any, Any], Any],
        lost: Callable[[str], None],
    ) -> None:
        self.paths = paths
        self.deliver = deliver
        self.convert = convert
        self.lost = lost
        self.batch: list[tuple[str, Any, Any]] = []

    def datachange_notification(self, node: Node, value: Any, data: Any) -> None:
        path = self.paths.get(node.nodeid)
        if path is None:
            return
        dv = data.monitored_item.Value
        status = dv.StatusCode if dv is not None else None
        why = unknown_state(path, status)
        if why:
            self.lost(why)
            return
        stamp = dv.SourceTimestamp or dv.ServerTimestamp if dv is not None else None
        self.batch.append((path, self.convert(path, value, status), stamp))
        if len(self.batch) == 1:
            asyncio.get_running_loop().call_soon(self._flush)

    def _flush(self) -> None:
        items, self.batch = self.batch, []
        if all(stamp is not None for _, _, stamp in items):
            items.sort(key=lambda item: item[2])  # stable: arrival order within one stamp
        batch: dict[str, Any] = {}
        for path, value, _ in items:
            if path in batch:
                self.deliver(batch)
                batch = {}
            batch[path] = value
        if batch:
            self.deliver(batch)

    def status_change_notification(self, status: Any) -> None:
        code = getattr(status, "Status", None)
        if code is None or code.is_good():
            return
        if code.value in (S.BadShutdown, S.BadCommunicationError, S.BadConnectionClosed):
            self.lost("the connection to the PLC closed")  # (asyncua's word for a lost transport)
        else:
            self.lost(f"the PLC ended the subscription: {code.name}")


def unknown_state(path: str, status: Any) -> str:
    """Why the PLC does not know the unit's state or mode now ('' = it does): a Bad value of a
    :data:`~.mirror.REQUIRED` variable (e.g. a gateway whose machine is gone, or a cell object
    whose coordinator is: this project's own face writes BadCommunicationError then). The unit
    is then as unreachable as a PLC that is gone, not online in an UNDEFINED state."""
    if path not in REQUIRED or status is None or not status.is_bad():
        return ""
    return f"the PLC has no usable {path} for the unit ({status.name})"


class _Watched(Subscription):
    """A subscription that notes when the PLC last answered a publish request (notifications
    and keep-alives alike)."""

    sign_of_life = 0.0

    async def publish_callback(self, publish_result: ua.PublishResult) -> None:
        self.sign_of_life = time.monotonic()
        await super().publish_callback(publish_result)


class Link:
    """The session with the PLC of ``config``; callbacks run in the link's loop thread:
    ``on_connected(values, methods, detail)``, ``on_values(batch)``, ``on_lost(reason)``,
    ``on_failed(reason)`` (an attempt failed while not connected)."""

    def __init__(
        self,
        config: PlcConfig,
        on_connected: Callable[[dict[str, Any], frozenset[str], str], None],
        on_values: Callable[[dict[str, Any]], None],
        on_lost: Callable[[str], None],
        on_failed: Callable[[str], None],
    ) -> None:
        quiet()
        self.config = config
        self.on_connected = on_connected
        self.on_values = on_values
        self.on_lost = on_lost
        self.on_failed = on_failed
        self.loop = asyncio.new_event_loop()
        self.up = False
        self._client: Client | None = None
        self._methods: dict[str, tuple[ua.NodeId, ua.NodeId]] = {}
        self._packml_ns = 0
        self._last_sign = 0.0
        self._calls = 0  #: method calls in flight
        self._lost_reason = ""
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(
            target=self._run_loop, name=f"plc-{config.unit}", daemon=True
        )
        self.attempts = 0

    # -- thread ------------------------------------------------------------------------------------
    def start(self) -> None:
        self._thread.start()

    def _run_loop(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(self._main())
        self.loop.close()

    def stop(self, timeout: float = 5.0) -> None:
        if self._thread.is_alive() and self._stop is not None:
            self.loop.call_soon_threadsafe(self._stop.set)
            self._thread.join(timeout)

    def submit(self, coro: Any) -> Future[Any]:
        """Run ``coro`` in the link's loop (from another thread)."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    # -- the session loop --------------------------------------------------------------------------
    async def _main(self) -> None:
        self._stop = asyncio.Event()
        delay = self.config.reconnect_min
        while not self._stop.is_set():
            self.attempts += 1
            was_up = False
            session = asyncio.ensure_future(self._session())
            stopping = asyncio.ensure_future(self._stop.wait())
            try:
                await asyncio.wait((session, stopping), return_when=asyncio.FIRST_COMPLETED)
                if session.done():
                    session.result()
                    reason = "the session ended"
                else:
                    reason = "stopped"
            except Exception as exc:
                reason = describe_error(exc)
            finally:
                stopping.cancel()
                if not session.done():
                    session.cancel()
                    with contextlib.suppress(BaseException):
                        await session
                was_up, self.up = self.up, False
                if not self._stop.is_set():  # said before the teardown, which may take a while
                    if was_up:
                        delay = self.config.reconnect_min
                        self.on_lost(reason)
                    else:
                        self.on_failed(reason)
                await self._teardown()
            if self._stop.is_set():
                break
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._stop.wait(), delay)
            if not was_up:
                delay = min(delay * 2, self.config.reconnect_max)

    async def _teardown(self) -> None:
        client, self._client = self._client, None
        self._methods = {}
        if client is None:
            return
        with contextlib.suppress(BaseException):
            await asyncio.wait_for(client.disconnect(), min(1.0, self.config.call_timeout))
        with contextlib.suppress(BaseException):
            client.disconnect_socket()

    async def _session(self) -> None:
        config = self.config
        client = self._client = Client(
            config.endpoint,
            timeout=config.call_timeout,
            # asyncua's own probe of the server state would call a silent PLC a closed
            # connection; the subscription's keep-alives and _watch measure the silence
            watchdog_intervall=max(10.0, 5 * config.lease),
        )
        client.name = client.description = f"packml_ros2 {config.cell}/{config.unit}"
        client.application_uri = config.app_uri()
        client.session_timeout = int(max(10.0, config.lease * 10) * 1000)
        if config.user:
            client.set_user(config.user)
            client.set_password(config.password)
        if config.secure:
            await self._security(client)
        await asyncio.wait_for(client.connect(), config.call_timeout)
        namespaces = await asyncio.wait_for(client.get_namespace_array(), config.call_timeout)
        if PACKML_URI not in namespaces:
            raise Lost(f"the PLC's server has no PackML namespace ({PACKML_URI})")
        self._packml_ns = namespaces.index(PACKML_URI)
        # asyncua registers the decoders process-wide, by NodeId: once per PLC namespace table
        # (loading them again at each reconnect rebinds every class: "Browsename collision")
        types_key = (config.endpoint, tuple(namespaces))
        try:
            if types_key not in _TYPES_LOADED:
                await asyncio.wait_for(client.load_data_type_definitions(), 4 * config.call_timeout)
                _TYPES_LOADED.add(types_key)
        except Exception as exc:  # alarms and counts stay unread; states and commands work
            _logger.warning(
                "PLC %s: data type definitions not read (%s): PackML structures "
                "(alarms, counts, stop reason) are not decoded",
                config.endpoint,
                describe_error(exc),
            )
        unit = await self._find_unit(client)
        variables, self._methods = await self._resolve(client, unit)
        missing = [p for p in REQUIRED if p not in variables]
        if missing:
            raise Lost(
                f"the PLC object {config.where()} has no {', '.join(missing)}: not an "
                "OPC 30050 PackML object"
            )
        paths = list(variables)
        nodes = [client.get_node(variables[p]) for p in paths]
        values = await asyncio.wait_for(client.read_attributes(nodes), config.call_timeout)
        for p, dv in zip(paths, values, strict=True):
            why = unknown_state(p, dv.StatusCode)
            if why:
                raise Lost(why)
        snapshot = {
            p: self._convert(p, dv.Value.Value if dv.Value else None, dv.StatusCode)
            for p, dv in zip(paths, values, strict=True)
        }
        lost: asyncio.Future[str] = asyncio.get_running_loop().create_future()

        def lose(reason: str) -> None:
            if not lost.done():
                lost.set_result(reason)

        handler = _Batches({variables[p]: p for p in paths}, self._deliver, self._convert, lose)
        interval_ms = config.publishing_interval * 1000
        params = ua.CreateSubscriptionParameters(
            RequestedPublishingInterval=interval_ms,
            RequestedMaxKeepAliveCount=max(1, int(config.lease / 4 / config.publishing_interval)),
            RequestedLifetimeCount=max(30, int(3 * config.lease / config.publishing_interval)),
            MaxNotificationsPerPublish=0,
            PublishingEnabled=True,
            Priority=0,
        )
        # not client.create_subscription: asyncua's watchdog would "recreate" a silent
        # subscription and count that as a sign of life; this one is the bridge's alone
        subscription = _Watched(client.uaclient.session, params, handler)
        await asyncio.wait_for(subscription.init(), config.call_timeout)
        machines = [n for p, n in zip(paths, nodes, strict=True) if p.startswith(MACHINES)]
        others = [n for p, n in zip(paths, nodes, strict=True) if not p.startswith(MACHINES)]
        # every value as the PLC writes it (sampling 0: not polled, so a state, its StopReason
        # and its alarm of one PLC cycle come together); the state machines keep every change
        # until the next publish, the rest the newest only
        for group, queue in ((machines, QUEUE), (others, 0)):
            await asyncio.wait_for(
                subscription.subscribe_data_change(group, queuesize=queue, sampling_interval=0.0),
                config.call_timeout,
            )
        self._last_sign = time.monotonic()
        self.up = True
        detail = f"connected to the PLC at {config.where()}"
        self.on_connected(snapshot, frozenset(self._methods), detail)
        await self._watch(client, subscription, lost)

    async def _security(self, client: Client) -> None:
        from ..opcua.server import own_certificate

        config = self.config
        if config.certificate and config.private_key:
            cert, key = config.certificate, config.private_key
        else:
            cert, key = await own_certificate(
                config.state_dir / config.cell / config.unit,
                config.app_uri(),
                client.name,
                "localhost",
            )
        policy = getattr(security_policies, f"SecurityPolicy{config.security_policy}")
        pinned = str(config.server_certificate) if config.server_certificate else None
        await asyncio.wait_for(
            client.set_security(
                policy,
                str(cert),
                str(key),
                server_certificate=pinned,
                mode=getattr(ua.MessageSecurityMode, config.security_mode),
            ),
            config.call_timeout,
        )

    async def _watch(self, client: Client, subscription: Any, lost: asyncio.Future[str]) -> None:
        lease = self.config.lease
        from asyncua.client.ua_client import UaClientState

        while True:
            if lost.done():
                raise Lost(lost.result())
            if client.uaclient.state is not UaClientState.CONNECTED:
                raise Lost("the connection to the PLC closed")
            last = max(self._last_sign, subscription.sign_of_life)
            silent = time.monotonic() - last
            # A server may serve one session's requests in order (asyncua does): while a method
            # runs (a cell's ordered start through its cell object takes seconds) no publish is
            # answered. That call has its own timeout; its answer is the next sign of life.
            if self._calls:
                self._last_sign = time.monotonic()
            elif silent > lease - TICK:
                raise Lost(f"no sign of life from the PLC for {silent:.1f} s (lease {lease:g} s)")
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.shield(lost), TICK)

    def _deliver(self, batch: dict[str, Any]) -> None:
        if self.up:
            self.on_values(batch)

    def _convert(self, path: str, value: Any, status: Any) -> Any:
        if status is not None and not status.is_good():
            return None
        if path.endswith("/CurrentState/Id"):
            if isinstance(value, ua.NodeId) and value.NamespaceIndex == self._packml_ns:
                return value.Identifier if isinstance(value.Identifier, int) else -1
            return -1
        return plain(value)

    # -- finding the unit --------------------------------------------------------------------------
    async def _find_unit(self, client: Client) -> ua.NodeId:
        config = self.config
        if config.node_id:
            node = client.get_node(config.node_id)
            await asyncio.wait_for(node.read_browse_name(), config.call_timeout)
            return node.nodeid
        node = client.nodes.objects
        for i, name in enumerate(config.browse_path):
            children = await asyncio.wait_for(node.get_children_descriptions(), config.call_timeout)
            found = [c for c in children if c.BrowseName.Name == name]
            if not found:
                below = "/".join(("Objects", *config.browse_path[:i]))
                names = ", ".join(sorted(c.BrowseName.Name for c in children)[:20]) or "nothing"
                raise Lost(f"the PLC has no {name!r} below {below} (there: {names})")
            node = client.get_node(found[0].NodeId)
        return node.nodeid

    async def _resolve(
        self, client: Client, unit: ua.NodeId
    ) -> tuple[dict[str, ua.NodeId], dict[str, tuple[ua.NodeId, ua.NodeId]]]:
        """NodeIds of the relative paths the PLC has: variables, and methods with their object."""
        methods = method_paths()
        owners = sorted({m.rpartition("/")[0] for m in methods if "/" in m})
        wanted = [*PATHS, *methods, *owners]
        browse_paths = []
        for path in wanted:
            elements = [
                ua.RelativePathElement(
                    ReferenceTypeId=ua.NodeId(ua.ObjectIds.HierarchicalReferences),
                    IsInverse=False,
                    IncludeSubtypes=True,
                    TargetName=ua.QualifiedName(
                        name, 0 if name in STANDARD_NAMES else self._packml_ns
                    ),
                )
                for name in path.split("/")
            ]
            browse_paths.append(
                ua.BrowsePath(StartingNode=unit, RelativePath=ua.RelativePath(Elements=elements))
            )
        results = await asyncio.wait_for(
            client.uaclient.translate_browsepaths_to_nodeids(browse_paths), self.config.call_timeout
        )
        found = {
            path: ua.NodeId(r.Targets[0].TargetId.Identifier, r.Targets[0].TargetId.NamespaceIndex)
            for path, r in zip(wanted, results, strict=True)
            if r.StatusCode.is_good() and r.Targets
        }
        variables = {p: found[p] for p in PATHS if p in found}
        calls = {}
        for m in methods:
            owner = m.rpartition("/")[0]
            owner_id = found.get(owner) if owner else unit
            if m in found and owner_id is not None:
                calls[m] = (owner_id, found[m])
        return variables, calls

    # -- calls -------------------------------------------------------------------------------------
    def offers(self, method: str) -> bool:
        return method in self._methods

    async def call(self, method: str, args: Sequence[ua.Variant]) -> Outcome:
        """Call ``method`` (a path from :func:`method_paths`); NotConnected when there is no
        session, Lost-like errors as an Outcome with BadNoCommunication."""
        client = self._client
        if client is None or not self.up:
            raise NotConnected("no session with the PLC")
        if method not in self._methods:
            return Outcome(
                S.BadNotImplemented,
                "BadNotImplemented",
                f"the PLC's object does not offer {method}",
            )
        owner, method_id = self._methods[method]
        request = ua.CallRequest()
        request.RequestHeader.ReturnDiagnostics = DIAGNOSTICS
        request.Parameters.MethodsToCall = [
            ua.CallMethodRequest(ObjectId=owner, MethodId=method_id, InputArguments=list(args))
        ]
        self._calls += 1  # (the PLC is busy with it: _watch)
        try:
            protocol = client.uaclient.protocol
            if protocol is None:
                raise NotConnected("no session with the PLC")
            data = await asyncio.wait_for(protocol.send_request(request), self.config.call_timeout)
        except ua.UaStatusCodeError as exc:
            return Outcome(exc.code, ua.StatusCode(exc.code).name, describe_error(exc))
        except (OSError, asyncio.TimeoutError, ConnectionError) as exc:
            return Outcome(S.BadNoCommunication, "BadNoCommunication", describe_error(exc))
        finally:
            self._calls -= 1
        self._last_sign = time.monotonic()
        response = struct_from_binary(ua.CallResponse, data)
        service = response.ResponseHeader.ServiceResult
        if not service.is_good():
            return Outcome(service.value, service.name, "")
        result = response.Results[0]
        code = result.StatusCode
        text = diagnostic_text(response)
        if code.is_good():
            return Outcome(code.value, code.name)
        bad_args = [
            f"argument {i + 1}: {c.name}"
            for i, c in enumerate(result.InputArgumentResults or [])
            if not c.is_good()
        ]
        if bad_args and not text:
            text = "; ".join(bad_args)
        return Outcome(code.value, code.name, text)

    def data_type(self, name: str) -> Any:
        """A PackML structure class asyncua generated from the PLC's definitions (None: not
        loaded)."""
        return getattr(ua, name, None)
