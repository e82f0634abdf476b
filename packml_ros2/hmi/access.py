"""Who may operate through the HMI, at which level, and how slow guessing is.

**Credentials.** A cell's ``hmi:`` block gives one of:

- ``users`` (or ``users_file``): user logins. ``POST /api/login`` with a user name and password
  opens a session (a random bearer credential, ended by ``POST /api/logout`` or after
  ``logout_after`` seconds without an action); each user has a level;
- ``token``: one shared access token (every holder acts as ``token``, at the highest level);
- neither: everyone who reaches the page operates (as ``anyone``, at the highest level).

**Levels** (:data:`LEVELS`), each allowed what the ones before it are, as a PLC HMI splits them
(:data:`UNIT_ACTION_LEVEL`, :data:`CELL_ACTION_LEVEL`):

- ``operator`` runs the line: state commands (Abort included), acknowledging and resetting alarms,
  the machine speed;
- ``maintenance`` changes how the units run: unit modes (Maintenance, Manual), equipment modules
  active or inactive, the recipe (a changeover: at least a mode change's weight);
- ``engineer`` erases records: resets of counters and of the state and mode times (OEE data).

Reading needs nothing. An action above the caller's level is refused (HTTP 403,
``LEVEL_TOO_LOW``) before a byte of its body is read.

**Sources.** Every action reaches the unit with :func:`command_source` as its source
(``hmi:<user>``): the one place that names who acted.

**Guessing** (:class:`~packml_ros2.core.throttle.Throttle`, shared with the OPC UA server): wrong
tokens, passwords, user names and unknown sessions are counted per client address, and wrong
passwords also per account. After :data:`FREE_FAILURES` in a row from one address, every further
attempt from it is refused (HTTP 429, ``THROTTLED``) for a back-off that doubles up to a minute;
an account guessed from several addresses is slowed (its logins checked one after the other,
seconds apart), never locked: its user, from their own address, still logs in. A success clears
the counts. Failures are logged with the client's address and count, never the guess (a wrong
password names the user only when the user exists). The tables are bounded, and so are the
sessions (:data:`MAX_SESSIONS`). A password is checked in a worker thread, never in the event
loop.
"""

from __future__ import annotations

import hmac
import logging
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..core.reasons import Reason
from ..core.throttle import Blocked, Throttle, login

MAX_SESSIONS = 256
LOGOUT_AFTER = 900.0  # s without an action before a login ends (hmi.logout_after)
LOG = logging.getLogger("packml_ros2.hmi")

# -- levels and what each action needs -----------------------------------------------------------
OPERATOR, MAINTENANCE, ENGINEER = "operator", "maintenance", "engineer"
#: The levels, lowest first: each may do what the ones before it may.
LEVELS: tuple[str, ...] = (OPERATOR, MAINTENANCE, ENGINEER)
#: The level each unit action needs.
UNIT_ACTION_LEVEL: Mapping[str, str] = {
    "command": OPERATOR,
    "ack_alarms": OPERATOR,
    "reset_alarms": OPERATOR,
    "set_mach_speed": OPERATOR,
    "set_mode": MAINTENANCE,
    "set_em_active": MAINTENANCE,
    "set_recipe": MAINTENANCE,
    "reset_counters": ENGINEER,
    "reset_times": ENGINEER,
}
#: The level each cell action (through the coordinator) needs.
CELL_ACTION_LEVEL: Mapping[str, str] = {"command": OPERATOR, "set_mode": MAINTENANCE}


def level_needed(unit: str | None, action: str) -> str:
    """The level ``action`` on ``unit`` (None: the cell) needs (the highest for an unknown one)."""
    table = UNIT_ACTION_LEVEL if unit is not None else CELL_ACTION_LEVEL
    return table.get(action, LEVELS[-1])


def level_allows(level: str, needed: str) -> bool:
    return level in LEVELS and LEVELS.index(level) >= LEVELS.index(needed)


@dataclass(frozen=True)
class Principal:
    """Who a request acts for: ``name`` (a user; ``token``: the shared access token;
    ``anyone``: no credential configured) and its ``level``."""

    name: str
    level: str = ENGINEER

    def may(self, needed: str) -> bool:
        return level_allows(self.level, needed)


def command_source(who: Principal) -> str:
    """The source every action of ``who`` reaches the unit with: ``hmi:<name>``. The one place
    that says how the HMI names who acted (transitions, stop reasons and alarm events show it)."""
    return f"hmi:{who.name}"


@dataclass(frozen=True)
class User:
    """A login: ``password`` is a hash (``pbkdf2_sha256$...``) or the resolved secret."""

    name: str
    level: str
    password: str = field(repr=False)


# -- refusals --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Refusal:
    """An HTTP-level refusal: status, reason code (``result``), a finer ``code`` and a sentence."""

    status: int
    reason: Reason
    code: str
    message: str
    retry_after: float | None = None

    def body(self) -> dict[str, Any]:
        return {
            "accepted": False,
            "result": int(self.reason),
            "result_name": self.reason.name,
            "code": self.code,
            "message": self.message,
        }


def _unauthorized(code: str, message: str) -> Refusal:
    return Refusal(403, Reason.UNAUTHORIZED, code, message)


NO_TOKEN = _unauthorized(
    "TOKEN_MISSING", "this HMI is read-only without the access token: enter it to operate"
)
WRONG_TOKEN = _unauthorized("TOKEN_WRONG", "wrong access token: nothing was sent to the unit")
NO_LOGIN = _unauthorized("LOGIN_REQUIRED", "this HMI is read-only until you log in")
WRONG_LOGIN = _unauthorized("LOGIN_WRONG", "wrong user name or password")
#: Failures that count towards the throttle.
_GUESSES = (WRONG_TOKEN, WRONG_LOGIN)


def level_refusal(who: Principal, unit: str | None, action: str) -> Refusal | None:
    """None when ``who`` may do ``action`` on ``unit`` (None: the cell); else the refusal."""
    needed = level_needed(unit, action)
    if who.may(needed):
        return None
    return _unauthorized(
        "LEVEL_TOO_LOW",
        f"{action} needs the {needed} level: {who.name} is logged in as {who.level}",
    )


# -- throttling ------------------------------------------------------------------------------------
def throttled(blocked: Blocked) -> Refusal:
    """The HTTP refusal of an attempt the throttle blocks (429, with Retry-After)."""
    return Refusal(
        429, Reason.UNAUTHORIZED, "THROTTLED", blocked.message, retry_after=blocked.retry_after
    )


# -- sessions --------------------------------------------------------------------------------------
class Sessions:
    """Open logins: a random credential -> (who, last action). One ends by :meth:`close`, after
    ``idle`` seconds without a use, or when :data:`MAX_SESSIONS` newer ones push it out."""

    def __init__(self, idle: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.idle = idle
        self.clock = clock
        self._open: OrderedDict[str, tuple[Principal, float]] = OrderedDict()
        self._lock = threading.Lock()

    def open(self, who: Principal) -> str:
        credential = secrets.token_urlsafe(32)
        with self._lock:
            self._open[credential] = (who, self.clock())
            while len(self._open) > MAX_SESSIONS:
                self._open.popitem(last=False)
        return credential

    def use(self, credential: str) -> Principal | None:
        """Who ``credential`` logged in as (its idle time starts again), or None."""
        with self._lock:
            entry = self._open.get(credential)
            if entry is None:
                return None
            now = self.clock()
            if now - entry[1] > self.idle:
                del self._open[credential]
                return None
            self._open[credential] = (entry[0], now)
            self._open.move_to_end(credential)
            return entry[0]

    def close(self, credential: str) -> Principal | None:
        with self._lock:
            entry = self._open.pop(credential, None)
        return entry[0] if entry else None

    def __len__(self) -> int:
        return len(self._open)


# -- the access rule -------------------------------------------------------------------------------
class Access:
    """The HMI's access rule (see the module): ``users`` (logins), else ``token``, else none.
    :meth:`verify` judges a request's credential; :meth:`authorize` also applies the throttle;
    :meth:`login` checks a password and opens a session."""

    def __init__(
        self,
        token: str | None,
        throttle: Throttle | None = None,
        users: Mapping[str, User] | None = None,
        logout_after: float = LOGOUT_AFTER,
    ) -> None:
        self._token = token.encode() if token else None
        self.users: dict[str, User] = dict(users or {})
        if self.users and self._token is not None:
            raise ValueError("an HMI has user logins or an access token, not both")
        self.throttle = throttle or Throttle("HMI", log=LOG)
        self.sessions = Sessions(logout_after)

    @property
    def kind(self) -> str:
        """``users``, ``token`` or ``none``."""
        return "users" if self.users else "token" if self._token is not None else "none"

    @property
    def required(self) -> bool:
        return self.kind != "none"

    @property
    def viewer(self) -> Principal:
        """Whom the screens every browser shares (the reasons of disabled controls) speak for:
        the principal of every action without logins (``anyone``, ``token``); with logins,
        each user (named ``<user>``: the remote lock refuses every ``hmi:<user>`` alike)."""
        return Principal({"users": "<user>", "token": "token"}.get(self.kind, "anyone"))

    def verify(self, credential: str | None) -> Principal | Refusal:
        if self.users:
            if not credential:
                return NO_LOGIN
            who = self.sessions.use(credential)
            if who is None:
                return _unauthorized(
                    "SESSION_ENDED",
                    f"not logged in (a login ends after {self.sessions.idle:g} s without an "
                    "action, or when the HMI restarts): log in again",
                )
            return who
        if self._token is None:
            return Principal("anyone")
        if not credential:
            return NO_TOKEN
        if not hmac.compare_digest(credential.encode("utf-8", "replace"), self._token):
            return WRONG_TOKEN
        return Principal("token")

    def authorize(self, credential: str | None, client: str) -> Principal | Refusal:
        """:meth:`verify` for a request from ``client`` (its address), throttled."""
        if not self.required:
            return Principal("anyone")
        blocked = self.throttle.admit(client)
        if isinstance(blocked, Blocked):
            return throttled(blocked)
        result = self.verify(credential)
        if isinstance(result, Principal):
            self.throttle.succeeded(client)
        elif result is WRONG_TOKEN or result.code == "SESSION_ENDED":
            self.throttle.failed(client, "access token" if result is WRONG_TOKEN else "session")
        return result

    def blocked(self, client: str) -> Refusal | None:
        """The refusal of any attempt from ``client`` while its address is blocked."""
        blocked = self.throttle.admit(client)
        return throttled(blocked) if isinstance(blocked, Blocked) else None

    async def login(self, name: Any, password: Any, client: str) -> tuple[str, Principal] | Refusal:
        """Check ``password`` of user ``name`` from ``client`` (its address) under the throttle,
        in a worker thread (a hash is slow on purpose); (session credential, who) or a refusal."""
        if not self.users:
            return Refusal(
                400,
                Reason.INVALID_ARGUMENT,
                "NO_USERS",
                "this HMI has no user logins (hmi.users)"
                + (": it asks for the access token" if self._token is not None else ""),
            )
        if not isinstance(name, str) or not isinstance(password, str) or len(password) > 1024:
            blocked = self.blocked(client)
            return blocked or Refusal(
                400,
                Reason.INVALID_ARGUMENT,
                "BAD_ARGUMENT",
                "give 'user' and 'password' as strings",
            )
        user = self.users.get(name)
        stored = None if user is None else user.password
        result = await login(self.throttle, client, name, stored, password, f"password for {name}")
        if isinstance(result, Blocked):
            return throttled(result)
        if not result or user is None:
            return WRONG_LOGIN
        who = Principal(user.name, user.level)
        LOG.info("HMI: %s logged in (%s) from %s", who.name, who.level, client)
        return self.sessions.open(who), who

    def logout(self, credential: str | None) -> Principal | None:
        return self.sessions.close(credential) if credential else None

    def __repr__(self) -> str:  # never the token nor a password
        return f"Access({self.kind}, users={sorted(self.users)})"
