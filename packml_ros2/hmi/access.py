"""Who may operate through the HMI, and how slow guessing is.

:class:`Access` turns a request's credential into a :class:`Principal` (who asks, at which level)
or a :class:`Refusal`. Today the credential is the cell's one access token (``hmi.token``; none
configured: everyone operates); user logins with levels plug in here, each action then asking
for the level it needs.

:class:`Throttle` slows guessing down: after :data:`FREE_FAILURES` wrong tokens in a row from one
client address, every further attempt from it is refused (HTTP 429, ``THROTTLED``) for a back-off
that doubles with each failure up to :data:`MAX_BACKOFF` s, whatever the token; a right token
clears the count. Failures are logged with the client's address and count, never the guess, one
line per doubling. The table of clients is bounded (:data:`MAX_CLIENTS`, oldest forgotten).
"""

from __future__ import annotations

import hmac
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..core.reasons import Reason

FREE_FAILURES = 5
MAX_BACKOFF = 60.0
FORGET_AFTER = 3600.0  # s without a failure: a client's count starts again
MAX_CLIENTS = 4096
OPERATE = "operate"
LOG = logging.getLogger("packml_ros2.hmi")


@dataclass(frozen=True)
class Principal:
    """Who a request acts for: ``name`` (``operator``: the access token; ``anyone``: no token
    configured) and the ``level`` granted (one level today: operate)."""

    name: str
    level: str = OPERATE


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


NO_TOKEN = Refusal(
    403,
    Reason.UNAUTHORIZED,
    "TOKEN_MISSING",
    "this HMI is read-only without the access token: enter it to operate",
)
WRONG_TOKEN = Refusal(
    403, Reason.UNAUTHORIZED, "TOKEN_WRONG", "wrong access token: nothing was sent to the unit"
)


class Throttle:
    """Per-client back-off after wrong tokens (see the module)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._clients: OrderedDict[str, list[float]] = OrderedDict()  # [failures, until, last]

    def blocked(self, client: str) -> Refusal | None:
        entry = self._entry(client)
        if entry is None or entry[1] <= self.clock():
            return None
        wait = entry[1] - self.clock()
        return Refusal(
            429,
            Reason.UNAUTHORIZED,
            "THROTTLED",
            f"too many wrong access tokens from {client}: try again in {wait:.0f} s",
            retry_after=wait,
        )

    def failed(self, client: str) -> None:
        now = self.clock()
        entry = self._entry(client) or [0.0, 0.0, now]
        entry[0] += 1
        entry[2] = now
        count = int(entry[0])
        backoff = 0.0
        if count >= FREE_FAILURES:
            backoff = min(2.0 ** (count - FREE_FAILURES), MAX_BACKOFF)
            entry[1] = now + backoff
        self._clients[client] = entry
        self._clients.move_to_end(client)
        while len(self._clients) > MAX_CLIENTS:
            self._clients.popitem(last=False)
        if count == 1 or count & (count - 1) == 0 or count == FREE_FAILURES:  # 1, 2, 4, 5, 8...
            LOG.warning(
                "HMI: wrong access token from %s (%d in a row)%s",
                client,
                count,
                f"; its next attempts are refused for {backoff:g} s" if backoff else "",
            )

    def succeeded(self, client: str) -> None:
        self._clients.pop(client, None)

    def failures(self, client: str) -> int:
        entry = self._entry(client)
        return int(entry[0]) if entry else 0

    def _entry(self, client: str) -> list[float] | None:
        entry = self._clients.get(client)
        if (
            entry is not None
            and self.clock() - entry[2] > FORGET_AFTER
            and entry[1] <= self.clock()
        ):
            del self._clients[client]
            return None
        return entry


class Access:
    """The HMI's access rule: ``token`` None lets everyone operate; otherwise a request needs it.
    :meth:`verify` compares (constant time); :meth:`authorize` also applies the throttle."""

    def __init__(self, token: str | None, throttle: Throttle | None = None) -> None:
        self._token = token.encode() if token else None
        self.throttle = throttle or Throttle()

    @property
    def required(self) -> bool:
        return self._token is not None

    def verify(self, credential: str | None) -> Principal | Refusal:
        if self._token is None:
            return Principal("anyone")
        if not credential:
            return NO_TOKEN
        if not hmac.compare_digest(credential.encode("utf-8", "replace"), self._token):
            return WRONG_TOKEN
        return Principal("operator")

    def authorize(self, credential: str | None, client: str) -> Principal | Refusal:
        """:meth:`verify` for a request from ``client`` (its address), throttled."""
        if self._token is None:
            return Principal("anyone")
        blocked = self.throttle.blocked(client)
        if blocked is not None:
            return blocked
        result = self.verify(credential)
        if result is WRONG_TOKEN:
            self.throttle.failed(client)
        elif isinstance(result, Principal):
            self.throttle.succeeded(client)
        return result

    def __repr__(self) -> str:  # never the token
        return f"Access(token={'set' if self._token else 'none'})"
