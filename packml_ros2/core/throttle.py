"""How slow guessing a password or a token is: one throttle for the HMI and the OPC UA server.

Two counts of wrong credentials (a wrong password, an unknown user name, a wrong token, an unknown
session), each cleared by a success:

- **per address** (the client's IP address; an IPv6 address counts as its /64 network, which one
  host holds whole): after :data:`FREE_FAILURES` in a row, every further attempt from it is
  refused for a back-off that doubles with each failure up to :data:`MAX_BACKOFF` s. This is
  what stops the guesser: the right password from a blocked address is refused too.
- **per account** (a configured user name; every unknown name shares one account,
  :data:`UNKNOWN`, so that no guessed name is kept): after :data:`ACCOUNT_FREE_FAILURES` from any
  addresses, the account's attempts are *slowed*, not refused: they are checked one after the
  other, :func:`account_interval` apart (doubling up to :data:`MAX_ACCOUNT_INTERVAL` s). Guesses
  spread over many addresses get no faster than that, and the rightful user, from an address that
  did not guess, still logs in after a wait. Only when more than :data:`MAX_ACCOUNT_WAIT` s of
  attempts are queued is an attempt refused (to try again shortly).

The table of addresses is bounded (:data:`MAX_ADDRESSES`): when it is full, the oldest address
that is not blocked is forgotten; a blocked one never is (flooding from other addresses cannot free
it), and when every kept address is blocked, all others share one more entry, :data:`OTHERS`.
Counts are forgotten :data:`FORGET_AFTER` s after the last failure.

Failures are logged with the address and the count, never the guess, one line per doubling (at
most :data:`LOG_LINES` a minute, then how many were left out); an
account is named only when it is configured (the callers pass :data:`UNKNOWN` otherwise), at most
:data:`MAX_NAME` characters of it. :func:`attempt` runs a check (a password hash: slow on purpose)
in a worker thread, so an event loop serving other clients is never held by it.
"""

from __future__ import annotations

import asyncio
import functools
import ipaddress
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

FREE_FAILURES = 5
MAX_BACKOFF = 60.0
ACCOUNT_FREE_FAILURES = 5
FIRST_ACCOUNT_INTERVAL = 0.25
MAX_ACCOUNT_INTERVAL = 4.0
MAX_ACCOUNT_WAIT = 30.0
FORGET_AFTER = 3600.0  # s without a failure: a count starts again
MAX_ADDRESSES = 4096
MAX_NAME = 64
LOG_LINES, LOG_PERIOD = 30, 60.0  # at most this many lines per period (a flood of addresses)
UNKNOWN = "<unknown user>"  #: the one account of every user name that is not configured
OTHERS = "<other addresses>"  #: the entry of addresses the full table has no room for
#: password checks run here: two at a time, whatever the number of guessers
_CHECKS = ThreadPoolExecutor(max_workers=2, thread_name_prefix="packml-login")


@dataclass(frozen=True)
class Blocked:
    """An attempt refused before its credential is looked at: why, and when to try again."""

    message: str
    retry_after: float


@dataclass
class _Count:
    failures: int = 0
    until: float = 0.0  # an address: blocked until; an account: its next free slot
    last: float = 0.0  # the last failure


def address_key(address: str) -> str:
    """What an address is counted as: itself, an IPv6 address its /64 network."""
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return address[:MAX_NAME]
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.ip_network(f"{ip}/64", strict=False))
    return str(ip)


def account_interval(failures: int) -> float:
    """How far apart a slowed account's attempts are checked after ``failures`` failures."""
    if failures < ACCOUNT_FREE_FAILURES:
        return 0.0
    steps = min(failures - ACCOUNT_FREE_FAILURES, 16)
    return float(min(FIRST_ACCOUNT_INTERVAL * 2.0**steps, MAX_ACCOUNT_INTERVAL))


def shown(account: str) -> str:
    """An account name as a log line or a message may carry it."""
    return account if len(account) <= MAX_NAME else account[:MAX_NAME] + "..."


class Throttle:
    """Per-address and per-account counts of wrong credentials (see the module). Thread-safe;
    ``clock`` is monotonic seconds; ``face`` names the server in log lines (``HMI``, ``OPC UA``)."""

    def __init__(
        self,
        face: str,
        clock: Callable[[], float] = time.monotonic,
        max_addresses: int = MAX_ADDRESSES,
        log: logging.Logger | None = None,
    ) -> None:
        self.face = face
        self.clock = clock
        self.max_addresses = max_addresses
        self.log = log or logging.getLogger("packml_ros2.throttle")
        self._addresses: OrderedDict[str, _Count] = OrderedDict()
        self._others = _Count()
        self._accounts: dict[str, _Count] = {}
        self._lock = threading.Lock()
        self._logged: list[float] = []  # when the lines of the current period were written
        self._left_out = 0

    def _warn(self, message: str, *args: Any) -> None:
        with self._lock:
            now = self.clock()
            self._logged = [at for at in self._logged if now - at < LOG_PERIOD]
            if len(self._logged) >= LOG_LINES:
                self._left_out += 1
                return
            self._logged.append(now)
            left_out, self._left_out = self._left_out, 0
        if left_out:
            message += f" ({left_out} such lines left out before)"
        self.log.warning(message, *args)

    # -- asking ------------------------------------------------------------------------------------
    def admit(self, address: str, account: str | None = None) -> float | Blocked:
        """Whether an attempt from ``address`` (on ``account``, if it names one) may be checked:
        the seconds it must wait first (0: now; its turn is reserved), or why it is refused."""
        with self._lock:
            now = self.clock()
            count = self._address(address_key(address), now)
            if count is not None and count.until > now:
                wait = count.until - now
                return Blocked(
                    f"too many wrong credentials from {address_key(address)}: try again in "
                    f"{wait:.0f} s",
                    wait,
                )
            if account is None:
                return 0.0
            held = self._account(account, now)
            interval = account_interval(held.failures if held else 0)
            if held is None or interval == 0.0:
                return 0.0
            slot = max(now, held.until)
            if slot - now > MAX_ACCOUNT_WAIT:
                return Blocked(
                    f"too many wrong passwords for {shown(account)} from several addresses: "
                    f"its logins are slowed; try again in {slot - now - MAX_ACCOUNT_WAIT:.0f} s",
                    slot - now - MAX_ACCOUNT_WAIT,
                )
            held.until = slot + interval
            return slot - now

    def failures(self, address: str) -> int:
        """Wrong credentials in a row from ``address``."""
        with self._lock:
            count = self._address(address_key(address), self.clock())
            return count.failures if count else 0

    def account_failures(self, account: str) -> int:
        with self._lock:
            count = self._account(account, self.clock())
            return count.failures if count else 0

    # -- telling -----------------------------------------------------------------------------------
    def failed(self, address: str, account: str | None = None, what: str = "access token") -> None:
        """A wrong credential (``what`` it was, for the log line) from ``address``."""
        key = address_key(address)
        with self._lock:
            now = self.clock()
            count = self._addresses.get(key)
            if count is not None and self._stale(count, now):
                del self._addresses[key]
                count = None
            count = count or self._new_address(key, now)
            count.failures += 1
            count.last = now
            others = count is self._others
            if not others:
                self._addresses.move_to_end(key)  # (the oldest failure is forgotten first)
            n = count.failures
            backoff = 0.0
            if n >= FREE_FAILURES:
                backoff = min(2.0 ** min(n - FREE_FAILURES, 16), MAX_BACKOFF)
                count.until = now + backoff
            held = None
            if account is not None:
                held = self._account(account, now) or self._accounts.setdefault(account, _Count())
                held.failures += 1
                held.last = now
        if n == 1 or n & (n - 1) == 0 or n == FREE_FAILURES:  # 1, 2, 4, 5, 8...
            self._warn(
                "%s: wrong %s from %s (%d in a row)%s",
                self.face,
                what,
                OTHERS if others else key,
                n,
                f"; its next attempts are refused for {backoff:g} s" if backoff else "",
            )
        if held is not None and held.failures == ACCOUNT_FREE_FAILURES:
            self._warn(
                "%s: %d wrong passwords for %s: its logins are slowed to one per %g s or less",
                self.face,
                held.failures,
                shown(account or ""),
                account_interval(held.failures),
            )

    def succeeded(self, address: str, account: str | None = None) -> None:
        with self._lock:
            self._addresses.pop(address_key(address), None)
            if account is not None:
                self._accounts.pop(account, None)

    # -- the tables --------------------------------------------------------------------------------
    def _address(self, key: str, now: float) -> _Count | None:
        """The count of ``key``; an address the full table does not hold: the shared one."""
        count = self._addresses.get(key)
        if count is None:
            others = len(self._addresses) >= self.max_addresses and self._others.failures > 0
            if not others or self._stale(self._others, now):
                return None
            return self._others
        if self._stale(count, now):
            del self._addresses[key]
            return None
        return count

    def _stale(self, count: _Count, now: float) -> bool:
        if now - count.last > FORGET_AFTER and count.until <= now:
            if count is self._others:
                self._others = _Count()
            return True
        return False

    def _new_address(self, key: str, now: float) -> _Count:
        if len(self._addresses) >= self.max_addresses:
            for old, count in self._addresses.items():  # the oldest that is not blocked
                if count.until <= now:
                    del self._addresses[old]
                    break
            else:
                self._stale(self._others, now)
                return self._others
        count = self._addresses[key] = _Count()
        return count

    def _account(self, account: str, now: float) -> _Count | None:
        count = self._accounts.get(account)
        if count is not None and self._stale(count, now):
            del self._accounts[account]
            return None
        return count


async def attempt(
    throttle: Throttle,
    address: str,
    account: str,
    check: Callable[[], bool],
    what: str,
) -> bool | Blocked:
    """Check a credential for ``account`` from ``address`` under ``throttle``: refused before
    ``check`` runs when blocked, after the account's wait when it is slowed; ``check`` (a password
    hash) runs in a worker thread. Counts the outcome; True when it held."""
    admitted = throttle.admit(address, account)
    if isinstance(admitted, Blocked):
        return admitted
    if admitted > 0:
        await asyncio.sleep(admitted)  # the account's turn (see the module)
    ok = await asyncio.get_running_loop().run_in_executor(_CHECKS, check)
    if ok:
        throttle.succeeded(address, account)
    else:
        throttle.failed(address, account, what)
    return ok


@functools.cache
def _unknown_user_hash() -> str:
    from .secrets import hash_password

    return hash_password("no such user")


async def login(
    throttle: Throttle, address: str, account: str, stored: str | None, password: str, what: str
) -> bool | Blocked:
    """A password login of ``account`` (its ``stored`` hash; None: no such user) from
    ``address`` under ``throttle`` (:func:`attempt`). An unknown user name is checked against a
    hash of the same cost, under the one account :data:`UNKNOWN`: the answer takes as long as a
    known user's and tells nothing."""
    from .secrets import check_password

    if stored is None:
        dummy = _unknown_user_hash()
        return await attempt(
            throttle,
            address,
            UNKNOWN,
            lambda: check_password(password, dummy) and False,
            "user name",
        )
    known = stored
    return await attempt(throttle, address, account, lambda: check_password(password, known), what)
