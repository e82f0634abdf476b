"""Who may do what on the OPC UA server, and how a refusal's reason reaches the client.

- :class:`Users`: asyncua user manager. A session is a *user* with a configured user name and
  password, or with a configured certificate (X509 identity token, or the client's application
  instance certificate of a signed channel); otherwise *anonymous*, if anonymous sessions are
  allowed at all. A wrong password is refused (no fall-back to anonymous); wrong passwords and
  unknown user names are throttled per address and per account as the HMI's
  (:mod:`packml_ros2.core.throttle`), and a password is checked off the event loop.
- :class:`Rules`: the permission ruleset: everybody may browse, read, subscribe and send a
  Write request; nobody may manage nodes (no Admin role is ever given out). Writes are answered
  per node (:func:`guard_writes`, OPC UA Part 4 5.10.4): a read-only variable or attribute
  ``BadNotWritable``, a writable one an anonymous session may not write
  ``BadUserAccessDenied`` (not a ServiceFault for the whole request). Calls pass the service
  level and are checked per method (:func:`may_call`), so a refused method answers
  ``BadUserAccessDenied`` for that method.
- Diagnostics: a method that refuses records its reason with :func:`refuse`; the CallResponse
  then carries, per refused method, a DiagnosticInfo with the text (AdditionalInfo, and
  LocalizedText through the string table) when the client asked for operation-level diagnostics
  (RequestHeader.ReturnDiagnostics), as OPC UA Part 4 describes.

asyncua has no hook for the calling session in a method, nor for response diagnostics: :func:`install`
wraps ``UaProcessor.process_message`` / ``send_response`` once per process. The wrappers only act
through context variables that this package sets, so other asyncua servers are unaffected.
"""

from __future__ import annotations

import contextvars
import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.crypto import uacrypto
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.server import uaprocessor
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary, struct_to_binary

from ..core.rules import source_of
from ..core.throttle import Blocked, Throttle, login, shown
from .config import ANONYMOUS, OpcUaConfig

_logger = logging.getLogger(__name__)

#: The user of the session whose request is being processed.
CURRENT_USER: contextvars.ContextVar[User | None] = contextvars.ContextVar(
    "packml_opcua_user", default=None
)
#: (user name, verdict) of the ActivateSession request being processed (Users.judge).
_LOGIN: contextvars.ContextVar[tuple[str, bool | Blocked] | None] = contextvars.ContextVar(
    "packml_opcua_login", default=None
)
#: RequestHeader.ReturnDiagnostics of the Call request being processed.
_RETURN_DIAGNOSTICS: contextvars.ContextVar[int] = contextvars.ContextVar(
    "packml_opcua_return_diagnostics", default=0
)
#: id(CallMethodResult) -> (symbolic id, text) of the methods refused in the current request.
_REFUSALS: contextvars.ContextVar[dict[int, tuple[str, str]] | None] = contextvars.ContextVar(
    "packml_opcua_refusals", default=None
)

# RequestHeader.ReturnDiagnostics, operation level (OPC UA Part 4, 7.33)
DIAG_SYMBOLIC_ID, DIAG_LOCALIZED_TEXT, DIAG_ADDITIONAL_INFO = 0x20, 0x40, 0x80
_CALL_REQUEST = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_ACTIVATE_REQUEST = ua.NodeId(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary)


class Users:
    """asyncua user manager from the ``opcua:`` block. A user name and password are judged
    before asyncua asks (:meth:`judge`, from the ``install`` hook): under the login throttle
    shared with the HMI (:mod:`packml_ros2.core.throttle`: per address and per account), the
    password checked in a worker thread, never in the event loop that serves every client;
    :meth:`get_user` then answers with that verdict."""

    def __init__(self, config: OpcUaConfig, certificates: Mapping[str, bytes]) -> None:
        self.config = config
        self._certificates = {der: name for name, der in certificates.items()}
        self.throttle = Throttle("OPC UA", log=_logger)

    async def judge(self, processor: Any, body: Buffer) -> tuple[str, bool | Blocked] | None:
        """The verdict on the user name and password of an ActivateSession request (``body``
        after its type id), or None when it carries none."""
        header = struct_from_binary(ua.RequestHeader, body)
        params = struct_from_binary(ua.ActivateSessionParameters, body)
        token = params.UserIdentityToken
        if not isinstance(token, ua.UserNameIdentityToken) or not token.UserName:
            return None
        iserver = processor.iserver
        session = processor.session or iserver.lookup_external_session(header.AuthenticationToken)
        if session is None:
            return None
        name, password = iserver.decrypt_user_token(session, token)
        peer = processor.name
        address = str(peer[0]) if isinstance(peer, tuple) and peer else "unknown"
        stored = self.config.users.get(name)
        verdict = await login(
            self.throttle, address, name, stored, password, f"password for user {shown(name)!r}"
        )
        if isinstance(verdict, Blocked):
            _logger.warning("OPC UA: refused a login: %s", verdict.message)
        return name, verdict

    @classmethod
    async def load(cls, config: OpcUaConfig) -> Users:
        certs = {}
        for name, path in config.user_certificates.items():
            certs[name] = uacrypto.der_from_x509(await uacrypto.load_certificate(path))
        return cls(config, certs)

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: bytes | None = None,
    ) -> User | None:
        if username:
            # judged before (judge: throttled, off the event loop; failures logged there)
            verdict = _LOGIN.get()
            if verdict is not None and verdict[0] == username and verdict[1] is True:
                return User(role=UserRole.User, name=username)
            return None
        if certificate:
            name = self._certificates.get(bytes(certificate))
            if name is not None:
                return User(role=UserRole.User, name=name)
        if self.config.allow_anonymous:
            return User(role=UserRole.Anonymous, name=None)
        return None

    def identity_tokens(self) -> list[type]:
        tokens: list[type] = []
        if self.config.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        if self.config.users:
            tokens.append(ua.UserNameIdentityToken)
        if self.config.user_certificates:
            tokens.append(ua.X509IdentityToken)
        return tokens


class Rules(PermissionRuleset):
    """Service-level permissions (see the module text)."""

    def __init__(self) -> None:
        user = {ua.NodeId(t) for t in USER_TYPES}
        self._allowed = {
            UserRole.Anonymous: user,  # a write is answered per node: guard_writes
            UserRole.User: user,
            UserRole.Admin: user,
        }

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return action_type_id in self._allowed.get(user.role, set())


def write_refusal(aspace: Any, item: ua.WriteValue, user: User) -> int | None:
    """The status code a write of ``item`` by ``user`` is refused with (None: asyncua writes
    it). OPC UA Part 4 7.34: a node that is not writable at all is ``BadNotWritable``;
    ``BadUserAccessDenied`` is for a writable node this user may not write."""
    node_class = aspace.read_attribute_value(item.NodeId, ua.AttributeIds.NodeClass)
    if node_class.StatusCode is not None and not node_class.StatusCode.is_good():
        return int(node_class.StatusCode.value)  # BadNodeIdUnknown
    if item.AttributeId != ua.AttributeIds.Value:
        return ua.StatusCodes.BadNotWritable  # no node here has a WriteMask
    level = aspace.read_attribute_value(item.NodeId, ua.AttributeIds.AccessLevel)
    if (
        level.StatusCode is None
        or not level.StatusCode.is_good()
        or level.Value is None
        or not ua.ua_binary.test_bit(level.Value.Value, ua.AccessLevel.CurrentWrite)
    ):
        return ua.StatusCodes.BadNotWritable
    if user.role not in (UserRole.User, UserRole.Admin):
        return ua.StatusCodes.BadUserAccessDenied
    return None


#: The user asyncua's own writes run as (its default).
SERVER = User(role=UserRole.Admin)


def guard_writes(server: Any) -> None:
    """Answer every node of a Write request of a session with its own status
    (:func:`write_refusal`); what passes is written by asyncua as before. The server's own
    writes (an Admin user) are not checked."""
    service = server.iserver.attribute_service
    aspace = server.iserver.aspace
    write = service.write

    async def checked(params: ua.WriteParameters, user: User = SERVER) -> list[ua.StatusCode]:
        if user.role == UserRole.Admin:
            return list(await write(params, user))
        refused = [write_refusal(aspace, item, user) for item in params.NodesToWrite]
        passing = [i for i, r in zip(params.NodesToWrite, refused, strict=True) if r is None]
        written = iter(
            await write(ua.WriteParameters(NodesToWrite=passing), user) if passing else []
        )
        return [next(written) if r is None else ua.StatusCode(r) for r in refused]

    service.write = checked


def may_call(config: OpcUaConfig) -> tuple[bool, str]:
    """Whether the current session may call methods; the user name (``''`` = anonymous)."""
    user = CURRENT_USER.get()
    if user is not None and user.role in (UserRole.User, UserRole.Admin):
        return True, user.name or ""
    return config.allow_anonymous_write, ""


def command_source(user: str) -> str:
    """The ``source`` of every command and request sent from OPC UA: ``opcua:<user>`` for a user
    session, ``opcua:anonymous`` for an anonymous one allowed to write (the rule book's grammar,
    :func:`packml_ros2.core.rules.source_of`: a remote source). Units record it with every
    transition, and their remote lock refuses it while ``remote_commands_enabled`` is false."""
    return source_of("opcua", user or ANONYMOUS)


def executable_callbacks(
    server: Any, method: ua.NodeId, executable: Callable[[], bool], config: OpcUaConfig
) -> None:
    """``Executable`` of ``method``: ``executable()`` (e.g. the unit is not lost);
    ``UserExecutable``: that and whether the reading session may call methods at all
    (:func:`may_call`), so a read-only session sees false on every method it would be refused."""
    aspace = server.iserver.aspace

    def boolean(value: bool) -> ua.DataValue:
        return ua.DataValue(ua.Variant(value, ua.VariantType.Boolean))

    aspace.set_attribute_value_callback(
        method, ua.AttributeIds.Executable, lambda *_: boolean(executable())
    )
    aspace.set_attribute_value_callback(
        method,
        ua.AttributeIds.UserExecutable,
        lambda *_: boolean(executable() and may_call(config)[0]),
    )


def refuse(
    status: int, symbol: str, text: str, argument_results: list[int] | None = None
) -> ua.CallMethodResult:
    """A refused method call: ``status`` (and per input argument, ``argument_results``) and, for
    diagnostics, the reason."""
    result = ua.CallMethodResult(StatusCode=ua.StatusCode(status))
    if argument_results is not None:
        result.InputArgumentResults = [ua.StatusCode(code) for code in argument_results]
    refusals = _REFUSALS.get()
    if refusals is not None:
        refusals[id(result)] = (symbol, text)
    return result


def _localized_text_field() -> str:
    """The DiagnosticInfo attribute asyncua encodes with the LocalizedText bit (0x04) of OPC UA
    Part 6, 5.2.2.12. asyncua 2.1 numbers the optional fields in declaration order and so swaps
    Locale (0x08) and LocalizedText; both are Int32 at the same place in the stream when only
    one of them is present, so setting the other attribute puts the right bit on the wire."""
    mask = struct_to_binary(ua.DiagnosticInfo(LocalizedText=0))[0]
    return "LocalizedText" if mask == 0x04 else "Locale"


_LOCALIZED_TEXT = _localized_text_field()


def _diagnostics(
    response: ua.CallResponse, refusals: dict[int, tuple[str, str]], mask: int
) -> None:
    table: list[str] = []

    def index(text: str) -> int:
        table.append(text)
        return len(table) - 1

    infos = []
    for result in response.Results:
        info = ua.DiagnosticInfo()
        found = refusals.get(id(result))
        if found is not None:
            symbol, text = found
            if mask & DIAG_SYMBOLIC_ID:
                info.SymbolicId = index(symbol)
            if mask & DIAG_LOCALIZED_TEXT:
                setattr(info, _LOCALIZED_TEXT, index(text))
            if mask & DIAG_ADDITIONAL_INFO:
                info.AdditionalInfo = text
        infos.append(info)
    response.DiagnosticInfos = infos
    response.ResponseHeader.StringTable = table


def install() -> None:
    """Wrap asyncua's request processing once (see the module text)."""
    processor = uaprocessor.UaProcessor
    if getattr(processor, "_packml_hooks", False):
        return
    process_message, send_response = processor.process_message, processor.send_response

    async def wrapped_process_message(self: Any, seqhdr: Any, body: Buffer) -> Any:
        session = getattr(self, "session", None)
        user_token = CURRENT_USER.set(getattr(session, "user", None))
        diag_token = _RETURN_DIAGNOSTICS.set(0)
        refusal_token = _REFUSALS.set({})
        login_token = _LOGIN.set(None)
        try:
            try:
                peek = body.copy()
                typeid = nodeid_from_binary(peek)
                if typeid == _CALL_REQUEST:
                    _RETURN_DIAGNOSTICS.set(
                        struct_from_binary(ua.RequestHeader, peek).ReturnDiagnostics
                    )
                users = getattr(self.iserver, "user_manager", None)
                if typeid == _ACTIVATE_REQUEST and isinstance(users, Users):
                    _LOGIN.set(await users.judge(self, peek))
            except Exception:  # the original reports malformed requests (a login: refused)
                pass
            return await process_message(self, seqhdr, body)
        finally:
            _LOGIN.reset(login_token)
            _REFUSALS.reset(refusal_token)
            _RETURN_DIAGNOSTICS.reset(diag_token)
            CURRENT_USER.reset(user_token)

    def wrapped_send_response(
        self: Any, requesthandle: Any, seqhdr: Any, response: Any, *args: Any, **kwargs: Any
    ) -> Any:
        refusals = _REFUSALS.get()
        mask = _RETURN_DIAGNOSTICS.get() & (
            DIAG_SYMBOLIC_ID | DIAG_LOCALIZED_TEXT | DIAG_ADDITIONAL_INFO
        )
        if refusals and mask and isinstance(response, ua.CallResponse):
            _diagnostics(response, refusals, mask)
        return send_response(self, requesthandle, seqhdr, response, *args, **kwargs)

    processor.process_message = wrapped_process_message
    processor.send_response = wrapped_send_response
    processor._packml_hooks = True


async def trusted_validator(paths: tuple[Path, ...]) -> Any:
    """A certificate validator that admits only these client certificates."""
    trusted = {uacrypto.der_from_x509(await uacrypto.load_certificate(p)) for p in paths}

    async def validate(certificate: Any, app_description: Any) -> None:
        if uacrypto.der_from_x509(certificate) not in trusted:
            _logger.warning(
                "OPC UA: refused an untrusted client certificate (%s)", certificate.subject
            )
            raise ua.uaerrors.BadCertificateUntrusted

    return validate
