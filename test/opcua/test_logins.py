"""Issue 25 item 9: OPC UA logins throttled as the HMI's, and checked off the event loop.

Before: 626 guesses a second against an ``env:`` password, and each PBKDF2 check ran in the
server's event loop (a reading client's latency rose from 1.1 to 139 ms). An asyncua server with
this package's user manager and hooks (:mod:`packml_ros2.opcua.security`) on 127.0.0.1, and
asyncua clients over TCP."""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
from asyncua import Client, Server, ua
from asyncua.ua.uaerrors import BadUserAccessDenied

from packml_ros2.core import load_cell
from packml_ros2.core.secrets import MAX_HASH_ITERATIONS, check_password, hash_password
from packml_ros2.core.throttle import FREE_FAILURES
from packml_ros2.opcua import security
from packml_ros2.opcua.config import parse_opcua

PASSWORD = "op-secret-1"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@asynccontextmanager
async def serving(tmp_path: Path, users: dict[str, str]) -> AsyncIterator[tuple[str, Any]]:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump({"cell": "c", "units": {"u": {}}, "opcua": {"users": users}}))
    config = parse_opcua(load_cell(path))
    security.install()
    manager = await security.Users.load(config)
    server = Server(user_manager=manager)
    await server.init()
    endpoint = f"opc.tcp://127.0.0.1:{_port()}/"
    server.set_endpoint(endpoint)
    server.set_security_policy(
        [ua.SecurityPolicyType.NoSecurity], permission_ruleset=security.Rules()
    )
    server.set_identity_tokens(manager.identity_tokens())
    async with server:
        yield endpoint, manager


async def _login(endpoint: str, user: str, password: str) -> bool:
    client = Client(endpoint, timeout=30)
    client.set_user(user)
    client.set_password(password)
    try:
        await client.connect()
    except BadUserAccessDenied:
        return False
    await client.disconnect()
    return True


def test_guesses_are_throttled_and_unknown_names_not_logged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("PACKML_TEST_OP", PASSWORD)

    async def run() -> None:
        async with serving(tmp_path, {"op": "env:PACKML_TEST_OP"}) as (endpoint, users):
            now = [1000.0]
            users.throttle.clock = lambda: now[0]
            assert await _login(endpoint, "op", PASSWORD)
            caplog.set_level(logging.WARNING)
            for i in range(FREE_FAILURES - 1):
                assert not await _login(endpoint, "op", f"guess-{i}")
            assert not await _login(endpoint, "n" * 1_000_000, "guess")
            # blocked now: even the right password
            assert not await _login(endpoint, "op", PASSWORD)
            assert users.throttle.failures("127.0.0.1") == FREE_FAILURES
            now[0] += 1.5  # the back-off (1 s) is over
            assert await _login(endpoint, "op", PASSWORD)
            assert users.throttle.failures("127.0.0.1") == 0

    asyncio.run(run())
    logged = [r.getMessage() for r in caplog.records if r.name.startswith("packml_ros2")]
    assert "OPC UA: wrong password for user 'op' from 127.0.0.1 (1 in a row)" in logged, logged
    assert any(m.startswith("OPC UA: refused a login: too many wrong credentials") for m in logged)
    assert all("nnnn" not in m and "guess" not in m for m in logged)
    assert any("wrong user name from 127.0.0.1 (5 in a row)" in m for m in logged), logged


def test_a_password_hash_is_checked_off_the_event_loop(tmp_path: Path) -> None:
    """A reading client is served while the heaviest hash the loader allows is checked: no read
    waits as long as the check takes (before: one read waited for the whole check)."""
    heavy = hash_password(PASSWORD, MAX_HASH_ITERATIONS)
    started = time.monotonic()
    assert check_password(PASSWORD, heavy)
    check = time.monotonic() - started  # (what one check costs on this machine now)

    async def run() -> float:
        async with serving(tmp_path, {"mes": heavy}) as (endpoint, _):
            reader = Client(endpoint, timeout=30)
            async with reader:
                node = reader.get_node(ua.ObjectIds.Server_ServerStatus_CurrentTime)
                await node.read_value()
                login = asyncio.create_task(_login(endpoint, "mes", PASSWORD))
                longest, last = 0.0, time.monotonic()
                while not login.done():
                    await node.read_value()
                    longest, last = max(longest, time.monotonic() - last), time.monotonic()
                assert await login
            return longest

    longest = asyncio.run(run())
    assert longest < check / 2, (longest, check)
