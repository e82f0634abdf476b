"""Issue 25 item 9: the login throttle the HMI and the OPC UA server share.

Per address and per account; bounded without a flood of other addresses freeing a blocked one;
guesses of one account from many addresses slowed, the rightful user never locked out; a password
checked off the event loop."""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

import pytest

from packml_ros2.core import throttle as t
from packml_ros2.core.throttle import (
    ACCOUNT_FREE_FAILURES,
    FREE_FAILURES,
    OTHERS,
    UNKNOWN,
    Blocked,
    Throttle,
    account_interval,
    address_key,
    attempt,
)


def clocked(**kw: Any) -> tuple[Throttle, list[float]]:
    now = [1000.0]
    return Throttle("HMI", clock=lambda: now[0], **kw), now


def test_an_address_is_blocked_after_five_failures_doubling_and_cleared_by_a_success() -> None:
    throttle, now = clocked()
    for _ in range(FREE_FAILURES - 1):
        throttle.failed("10.0.0.9", "anna", "password for anna")
    assert throttle.admit("10.0.0.9") == 0.0
    throttle.failed("10.0.0.9", "anna", "password for anna")
    blocked = throttle.admit("10.0.0.9", "anna")
    assert isinstance(blocked, Blocked) and blocked.retry_after == 1.0
    assert "too many wrong credentials from 10.0.0.9" in blocked.message
    now[0] += 1.5
    throttle.failed("10.0.0.9")
    assert throttle.admit("10.0.0.9").retry_after == 2.0  # type: ignore[union-attr]
    now[0] += 2.5
    throttle.succeeded("10.0.0.9")
    assert throttle.failures("10.0.0.9") == 0 and throttle.admit("10.0.0.9") == 0.0


def test_ipv6_counts_per_64_network_and_mapped_ipv4_as_itself() -> None:
    assert address_key("2001:db8::1") == address_key("2001:db8::ffff:2") == "2001:db8::/64"
    assert (
        address_key("::ffff:10.0.0.1") == "10.0.0.1" and address_key("fe80::1%eth0") == "fe80::/64"
    )
    assert address_key("unknown") == "unknown" and len(address_key("x" * 500)) == t.MAX_NAME
    throttle, _ = clocked()
    for i in range(FREE_FAILURES):
        throttle.failed(f"2001:db8::{i + 1:x}")  # (one host rotating its addresses)
    assert isinstance(throttle.admit("2001:db8::abcd"), Blocked)
    assert throttle.admit("2001:db8:1::1") == 0.0


def test_a_flood_of_other_addresses_never_frees_a_blocked_one() -> None:
    """Before: 4 100 failures from other addresses evicted a blocked address from the table."""
    throttle, now = clocked(max_addresses=64)
    for _ in range(FREE_FAILURES + 6):
        throttle.failed("10.9.9.9")  # (blocked for a minute)
    for i in range(4100):
        throttle.failed(f"127.1.{i // 250}.{i % 250 + 1}")
        now[0] += 0.001
    assert isinstance(throttle.admit("10.9.9.9"), Blocked)
    assert len(throttle._addresses) <= 64
    # every kept address blocked: all others share one entry, blocked with its failures
    throttle, now = clocked(max_addresses=8)
    for i in range(8):
        for _ in range(FREE_FAILURES):
            throttle.failed(f"10.0.0.{i}")
    for i in range(FREE_FAILURES):
        throttle.failed(f"10.1.0.{i}")
    assert len(throttle._addresses) == 8 and all(
        isinstance(throttle.admit(f"10.0.0.{i}"), Blocked) for i in range(8)
    )
    assert isinstance(throttle.admit("10.2.0.1"), Blocked)
    now[0] += t.MAX_BACKOFF + 1  # their back-offs over: an address that is not blocked goes
    throttle.failed("10.3.0.1")
    assert "10.3.0.1" in throttle._addresses and len(throttle._addresses) == 8


def test_one_account_guessed_from_many_addresses_is_slowed_not_locked(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Before: 40 guesses from 40 rotating 127.x addresses, none throttled."""
    throttle, now = clocked()
    caplog.set_level(logging.WARNING)
    waits = []
    for i in range(40):
        admitted = throttle.admit(f"127.0.1.{i + 1}", "anna")
        assert not isinstance(admitted, Blocked)
        waits.append(admitted)
        now[0] += admitted  # (each guesser waits its turn, then guesses wrong)
        throttle.failed(f"127.0.1.{i + 1}", "anna", "password for anna")
    assert waits[: ACCOUNT_FREE_FAILURES + 1] == [0.0] * (ACCOUNT_FREE_FAILURES + 1)
    assert waits[-1] == t.MAX_ACCOUNT_INTERVAL and sum(waits) > 100  # ~4 s a guess, not 626/s
    assert all(throttle.failures(f"127.0.1.{i + 1}") == 1 for i in range(40))
    # the rightful user, from their own address: a wait, then checked (never refused)
    assert throttle.admit("10.0.0.1", "anna") == pytest.approx(t.MAX_ACCOUNT_INTERVAL)
    # guessers queued beyond MAX_ACCOUNT_WAIT are refused (to try again); nobody else is
    queued = [throttle.admit(f"127.0.2.{i}", "anna") for i in range(20)]
    assert any(isinstance(q, Blocked) for q in queued)
    assert throttle.admit("10.0.0.1", "ben") == 0.0
    now[0] += 200
    throttle.succeeded("10.0.0.1", "anna")  # the rightful login clears the account's count
    assert throttle.account_failures("anna") == 0 and throttle.admit("127.0.3.1", "anna") == 0.0
    text = caplog.text
    assert "wrong password for anna from 127.0.1.1 (1 in a row)" in text
    assert f"{ACCOUNT_FREE_FAILURES} wrong passwords for anna: its logins are slowed" in text


def test_five_wrong_passwords_from_elsewhere_do_not_lock_the_user_out() -> None:
    """Before: the account (or the shared address) was refused for a back-off."""
    throttle, _ = clocked()
    for _ in range(FREE_FAILURES):
        throttle.failed("10.0.0.66", "anna", "password for anna")
    assert isinstance(throttle.admit("10.0.0.66", "anna"), Blocked)  # the guesser
    assert throttle.admit("10.0.0.1", "anna") == 0.0  # anna, from her own address
    assert account_interval(ACCOUNT_FREE_FAILURES) == t.FIRST_ACCOUNT_INTERVAL


def test_unknown_names_share_one_account_and_long_names_are_cut() -> None:
    throttle, _ = clocked()
    for i in range(10):
        throttle.failed(f"10.0.{i}.1", UNKNOWN, "user name")
    assert throttle.account_failures(UNKNOWN) == 10 and set(throttle._accounts) == {UNKNOWN}
    assert t.shown("x" * 1_000_000) == "x" * t.MAX_NAME + "..."
    assert OTHERS not in throttle._addresses


def test_a_check_runs_in_a_worker_thread_and_is_counted() -> None:
    throttle = Throttle("OPC UA")
    threads: list[str] = []

    def check(ok: bool) -> bool:
        threads.append(threading.current_thread().name)
        return ok

    async def run() -> list[bool | Blocked]:
        out: list[bool | Blocked] = []
        for ok in (False, False, True):
            out.append(await attempt(throttle, "10.0.0.5", "op", lambda ok=ok: check(ok), "x"))
        return out

    assert asyncio.run(run()) == [False, False, True]
    assert all(name.startswith("packml-login") for name in threads), threads
    assert throttle.failures("10.0.0.5") == 0 and throttle.account_failures("op") == 0


def test_a_flood_of_addresses_writes_a_bounded_log(caplog: pytest.LogCaptureFixture) -> None:
    throttle, now = clocked()
    caplog.set_level(logging.WARNING)
    for i in range(1000):
        throttle.failed(f"127.2.{i // 250}.{i % 250 + 1}", UNKNOWN, "user name")
    assert len(caplog.records) == t.LOG_LINES
    now[0] += t.LOG_PERIOD
    throttle.failed("10.0.0.1", UNKNOWN, "user name")
    assert caplog.records[-1].getMessage().endswith("before)")
    assert "such lines left out" in caplog.records[-1].getMessage()
