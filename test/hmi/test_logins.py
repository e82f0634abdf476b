"""Issue 17, HMI item 4: user logins with levels instead of one shared token.

The ``hmi:`` block's users (inline or in a users file; passwords as hashes, ``env:`` or ``file:``,
never plain text), sessions that end after ``logout_after`` seconds without an action, the levels
each action needs (operator, maintenance, engineer) judged before a byte of the body is read, the
one source of every action (``hmi:<user>``), wrong passwords throttled and logged without the guess;
then over HTTP against a real unit."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.core.config import parse_cell
from packml_ros2.core.schema import ConfigError
from packml_ros2.core.secrets import hash_password
from packml_ros2.core.throttle import FREE_FAILURES
from packml_ros2.hmi import hmi_settings
from packml_ros2.hmi.access import (
    CELL_ACTION_LEVEL,
    LEVELS,
    UNIT_ACTION_LEVEL,
    Access,
    Principal,
    Refusal,
    Sessions,
    User,
    command_source,
    level_needed,
    level_refusal,
)
from packml_ros2.hmi.bridge import UNIT_ACTIONS
from test.hmi.test_bridge import UNIT, serving
from test.hostile.http import raw

JSON = {"Content-Type": "application/json"}
PASSWORDS = {"anna": "anna-pass-1", "ben": "ben-pass-22", "carla": "carla-pass-333"}
LEVEL_OF = {"anna": "operator", "ben": "maintenance", "carla": "engineer"}


def log_in(access: Access, name: Any, password: Any, client: str) -> Any:
    """``access.login`` as the server awaits it."""
    return asyncio.run(access.login(name, password, client))


def users() -> dict[str, User]:
    return {
        n: User(n, LEVEL_OF[n], hash_password(pw, iterations=1000)) for n, pw in PASSWORDS.items()
    }


# -- levels ------------------------------------------------------------------------------------------
def test_each_action_needs_a_level_as_a_plc_hmi_splits_them() -> None:
    assert set(UNIT_ACTION_LEVEL) == set(UNIT_ACTIONS)  # every action is in the table
    assert LEVELS == ("operator", "maintenance", "engineer")
    assert {a for a, lvl in UNIT_ACTION_LEVEL.items() if lvl == "operator"} == {
        "command", "ack_alarms", "reset_alarms", "set_mach_speed"}  # fmt: skip
    assert {a for a, lvl in UNIT_ACTION_LEVEL.items() if lvl == "maintenance"} == {
        "set_mode", "set_em_active", "set_recipe"}  # fmt: skip
    assert {a for a, lvl in UNIT_ACTION_LEVEL.items() if lvl == "engineer"} == {
        "reset_counters", "reset_times"}  # fmt: skip
    assert CELL_ACTION_LEVEL == {"command": "operator", "set_mode": "maintenance"}
    assert level_needed("u", "unknown") == "engineer"
    anna, ben = Principal("anna", "operator"), Principal("ben", "maintenance")
    assert level_refusal(anna, "u", "command") is None
    refused = level_refusal(anna, "u", "set_mode")
    assert (
        isinstance(refused, Refusal) and refused.status == 403 and refused.code == "LEVEL_TOO_LOW"
    )
    assert refused.message == "set_mode needs the maintenance level: anna is logged in as operator"
    assert level_refusal(ben, None, "set_mode") is None
    assert level_refusal(ben, "u", "reset_counters") is not None
    assert not Principal("x", "superuser").may("operator")  # an unknown level may nothing


def test_every_action_names_who_as_its_source() -> None:
    assert command_source(Principal("anna", "operator")) == "hmi:anna"
    assert command_source(Principal("token")) == "hmi:token"
    assert command_source(Principal("anyone")) == "hmi:anyone"


# -- sessions and passwords -----------------------------------------------------------------------------
def test_a_session_ends_after_its_idle_time_and_sessions_are_bounded(monkeypatch: Any) -> None:
    from packml_ros2.hmi import access

    now = [0.0]
    sessions = Sessions(idle=60, clock=lambda: now[0])
    anna = Principal("anna", "operator")
    a = sessions.open(anna)
    now[0] = 59
    assert sessions.use(a) == anna  # each use starts the idle time again
    now[0] = 118
    assert sessions.use(a) == anna
    now[0] = 179
    assert sessions.use(a) is None and len(sessions) == 0
    b = sessions.open(anna)
    assert sessions.close(b) == anna and sessions.use(b) is None
    monkeypatch.setattr(access, "MAX_SESSIONS", 3)
    made = [sessions.open(anna) for _ in range(5)]
    assert len(sessions) == 3 and sessions.use(made[0]) is None and sessions.use(made[-1]) == anna


def test_logins_check_hashed_passwords_and_wrong_ones_are_throttled(caplog: Any) -> None:
    access = Access(None, users=users(), logout_after=900)
    now = [100.0]
    access.throttle.clock = lambda: now[0]
    assert access.kind == "users" and access.required
    assert isinstance(access.verify(None), Refusal) and access.verify(None).code == "LOGIN_REQUIRED"
    ok = log_in(access, "anna", PASSWORDS["anna"], "10.0.0.1")
    assert not isinstance(ok, Refusal)
    session, who = ok
    assert who == Principal("anna", "operator") and access.verify(session) == who
    assert access.verify("made-up").code == "SESSION_ENDED"  # type: ignore[union-attr]
    caplog.set_level(logging.WARNING, "packml_ros2.hmi")
    for guess in ("anna-pass-2", "x" * 20, "", "anna-pass-11"):
        assert log_in(access, "anna", guess, "10.0.0.9") == log_in(
            access, "nobody", guess, "10.0.0.8"
        )
    assert log_in(access, "anna", PASSWORDS["ben"], "10.0.0.9").code == "LOGIN_WRONG"  # type: ignore[union-attr]
    blocked = log_in(
        access, "anna", PASSWORDS["anna"], "10.0.0.9"
    )  # the 6th failure before: blocked
    assert isinstance(blocked, Refusal) and blocked.code == "THROTTLED" and blocked.status == 429
    assert access.throttle.failures("10.0.0.9") == FREE_FAILURES
    assert not isinstance(
        log_in(access, "anna", PASSWORDS["anna"], "10.0.0.1"), Refusal
    )  # others not
    text = caplog.text
    assert (
        "wrong password for anna from 10.0.0.9" in text and "wrong user name from 10.0.0.8" in text
    )
    assert "nobody" not in text and "anna-pass" not in text and "x" * 20 not in text
    assert "anna-pass" not in repr(access) and "pbkdf2" not in repr(access)
    bad = log_in(access, ["anna"], None, "10.0.0.7")
    assert isinstance(bad, Refusal) and bad.code == "BAD_ARGUMENT"


def test_users_and_a_shared_token_do_not_mix() -> None:
    with pytest.raises(ValueError, match="not both"):
        Access("a-token-123", users=users())
    token = Access("a-token-123")
    assert token.kind == "token" and token.verify("a-token-123") == Principal("token", "engineer")
    assert log_in(token, "anna", "x", "1.2.3.4").code == "NO_USERS"  # type: ignore[union-attr]
    assert Access(None).kind == "none" and Access(None).authorize(None, "h") == Principal("anyone")


# -- the hmi: block -------------------------------------------------------------------------------------
def _cell(tmp_path: Path, hmi: dict[str, Any]) -> Any:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump({"cell": "c", "units": {"u": {}}, "hmi": hmi}))
    from packml_ros2.core import load_cell

    return load_cell(path)


def test_users_are_given_with_levels_and_hashed_or_pointed_to_passwords(
    tmp_path: Path, monkeypatch: Any
) -> None:
    monkeypatch.setenv("PACKML_TEST_BEN", "ben-pass-22")
    (tmp_path / "carla.pw").write_text("carla-pass-333\n")
    hashed = hash_password("anna-pass-1", iterations=1000)
    settings = hmi_settings(_cell(tmp_path, {"users": {
        "anna": {"level": "operator", "password": hashed},
        "ben": {"level": "Maintenance", "password": "env:PACKML_TEST_BEN"},
        "carla": {"level": "engineer", "password": "file:carla.pw"},
    }, "logout_after": 300}))  # fmt: skip
    assert {n: (u.level, u.password) for n, u in settings.users.items()} == {
        "anna": ("operator", hashed), "ben": ("maintenance", "ben-pass-22"),
        "carla": ("engineer", "carla-pass-333")}  # fmt: skip
    assert settings.logout_after == 300 and "pass" not in repr(settings)
    # the same users in a file the cell file points to
    (tmp_path / "users.yaml").write_text(
        yaml.safe_dump({"users": {"anna": {"level": "operator", "password": hashed}}})
    )
    from_file = hmi_settings(_cell(tmp_path, {"users_file": "users.yaml"}))
    assert from_file.users["anna"].password == hashed


def test_a_plain_password_and_other_mistakes_are_refused_with_their_key_path(
    tmp_path: Path,
) -> None:
    with pytest.raises(ConfigError) as plain:  # refused by every loader of the cell file
        _cell(tmp_path, {"users": {"anna": {"level": "operator", "password": "anna-pass-1"}}})
    assert "hmi.users.anna.password: a secret is never written in the cell file" in str(plain.value)
    assert "packml hmi --hash-password" in str(plain.value) and "anna-pass-1" not in str(
        plain.value
    )
    hashed = hash_password("abcdefgh", iterations=1000)
    with pytest.raises(ConfigError) as exc:
        hmi_settings(parse_cell({"cell": "c", "units": {"u": {}}, "hmi": {
            "users": {"anna": {"level": "boss", "password": hashed}, "ben": {"level": "operator"},
                      "c c": {"level": "operator", "password": hashed},
                      "dan": {"level": "operator", "password": "pbkdf2_sha256$x"},
                      "eve": "operator"},
            "token": "env:NOPE", "logout_after": 1}}, "cell.yaml"))  # fmt: skip
    text = str(exc.value)
    for line in ("hmi.users.anna.level: 'boss' is not one of operator, maintenance, engineer",
                 "hmi.users.ben.password: missing", "hmi.users.c c: 'c c' is not a user name",
                 "hmi.users.dan.password: malformed password hash", "hmi.users.eve: expected {level",
                 "hmi.token: give users or a token, not both", "hmi.logout_after: 1 is outside"):  # fmt: skip
        assert line in text, (line, text)
    (tmp_path / "users.yaml").write_text(
        yaml.safe_dump(
            {"users": {"anna": {"level": "operator", "password": "plain-text-pw"}}, "extra": 1}
        )
    )
    with pytest.raises(ConfigError) as in_file:
        hmi_settings(_cell(tmp_path, {"users_file": "users.yaml"}))
    text = str(in_file.value)
    assert "users.yaml: users.anna.password: a secret is never written" in text
    assert "users.yaml: extra: unknown key" in text and "plain-text-pw" not in text
    with pytest.raises(ConfigError, match="cannot read"):
        hmi_settings(_cell(tmp_path, {"users_file": "missing.yaml"}))


# -- over HTTP, against a real unit -------------------------------------------------------------------
def login(http: Any, user: str, password: str | None = None) -> str:
    r = http.post("/api/login", json={"user": user, "password": password or PASSWORDS[user]})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["user"] == user and body["level"] == LEVEL_OF[user]
    return str(body["session"])


@pytest.fixture
def cell(make_cell: Any) -> Any:
    return make_cell(users=users())


@pytest.fixture
def make_cell(ros: Any, tmp_path: Path) -> Any:
    from test.hmi.test_bridge import Cell

    made: list[Cell] = []

    def make(**kw: Any) -> Cell:
        made.append(Cell(ros, tmp_path, kw.get("token"), 3.0, kw.get("users")))
        return made[-1]

    yield make
    for c in made:
        c.close()


@pytest.mark.ros
def test_a_logged_in_user_acts_under_their_name_at_their_level(cell: Any) -> None:
    with serving(cell.bridge) as http:
        assert http.get("/api/config").json()["login"] == "users"
        nobody = http.post(f"/api/units/{UNIT}/command", json={"command": "reset"})
        assert nobody.status_code == 403 and nobody.json()["code"] == "LOGIN_REQUIRED"
        anna = {"Authorization": f"Bearer {login(http, 'anna')}"}
        assert http.post("/api/auth", headers=anna).json()["user"] == "anna"
        mark = len(cell.events)
        ok = http.post(f"/api/units/{UNIT}/command", json={"command": "reset"}, headers=anna)
        assert ok.status_code == 200 and ok.json()["accepted"], ok.text
        reset = cell.wait_event(lambda e: e["topic"] == "transition" and e["data"]["command"] == "RESET",
                                "the RESET", mark)  # fmt: skip
        assert reset["data"]["source"] == "hmi:anna"
        # above her level: refused before the body is read (a 100 MB body is never waited for)
        port = http.base_url.port
        head = (f"POST /api/units/{UNIT}/set_mode HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                f"{'Authorization: ' + anna['Authorization']}\r\nContent-Type: application/json\r\n"
                "Content-Length: 100000000\r\n\r\n")  # fmt: skip
        started = time.monotonic()
        status, answer = raw(port, head.encode() + b'{"mode"')
        assert status == 403 and b"LEVEL_TOO_LOW" in answer and time.monotonic() - started < 5
        # (RESET's last status, as this test's own subscription has it)
        seq = cell.client.status.wait_for(lambda m: m.state_current_name == "IDLE", 10).sequence
        for action, args in (("set_mode", {"mode": 2}), ("reset_counters", {}),
                             ("set_em_active", {"em": "nozzle", "active": True})):  # fmt: skip
            r = http.post(f"/api/units/{UNIT}/{action}", json=args, headers=anna)
            assert r.status_code == 403 and r.json()["code"] == "LEVEL_TOO_LOW", r.text
        assert cell.client.status.last.sequence == seq  # nothing reached the unit
        # ben may change the mode, carla may reset the counters
        ben = {"Authorization": f"Bearer {login(http, 'ben')}"}
        mode = http.post(f"/api/units/{UNIT}/set_mode", json={"mode": 3}, headers=ben)
        assert mode.json()["accepted"], mode.text
        assert (
            http.post(f"/api/units/{UNIT}/reset_counters", json={}, headers=ben).status_code == 403
        )
        carla = {"Authorization": f"Bearer {login(http, 'carla')}"}
        assert http.post(f"/api/units/{UNIT}/reset_counters", json={}, headers=carla).json()[
            "accepted"
        ]
        # logging out ends the session
        assert (
            http.post("/api/logout", headers={**anna, **JSON}).json()["message"]
            == "anna logged out"
        )
        after = http.post(f"/api/units/{UNIT}/command", json={"command": "stop"}, headers=anna)
        assert after.status_code == 403 and after.json()["code"] == "SESSION_ENDED"


@pytest.mark.ros
def test_a_login_is_json_from_this_site_only(cell: Any) -> None:
    with serving(cell.bridge) as http:
        form = http.post("/api/login", content="user=anna&password=anna-pass-1",
                         headers={"Content-Type": "application/x-www-form-urlencoded"})  # fmt: skip
        assert form.status_code == 415 and form.json()["code"] == "UNSUPPORTED_MEDIA_TYPE"
        other = http.post("/api/login", json={"user": "anna", "password": PASSWORDS["anna"]},
                          headers={"Origin": "http://evil.example"})  # fmt: skip
        assert other.status_code == 403 and other.json()["code"] == "CROSS_SITE"
        wrong = http.post("/api/login", json={"user": "anna", "password": "nope"})
        assert wrong.status_code == 403 and wrong.json()["code"] == "LOGIN_WRONG"
        assert "session" not in wrong.json()
        big = http.post("/api/login", content=b'{"user": "' + b"a" * 10_000 + b'"}', headers=JSON)
        assert big.status_code == 413


@pytest.mark.ros
def test_guesses_from_rotating_addresses_are_slowed_and_the_user_still_logs_in(
    cell: Any, monkeypatch: Any
) -> None:
    """Issue 25 item 9: 40 wrong passwords for one user from 40 rotating 127.x addresses were
    none throttled, and 5 wrong ones locked the user out of their address. Now the account is
    slowed (its attempts checked one after the other; the ones queued too far ahead refused with
    429), and its user, from their own address, logs in."""
    from concurrent.futures import ThreadPoolExecutor

    import httpx

    from packml_ros2.core import throttle

    monkeypatch.setattr(throttle, "FIRST_ACCOUNT_INTERVAL", 0.2)
    monkeypatch.setattr(throttle, "MAX_ACCOUNT_INTERVAL", 0.2)
    monkeypatch.setattr(throttle, "MAX_ACCOUNT_WAIT", 1.0)  # (a test's scale of 4 s and 30 s)
    with serving(cell.bridge) as http:
        url = str(http.base_url)

        def guess(i: int) -> int:
            source = httpx.HTTPTransport(local_address=f"127.0.3.{i + 1}")
            with httpx.Client(base_url=url, transport=source, timeout=30) as client:
                body = {"user": "anna", "password": f"guess-{i}"}
                return client.post("/api/login", json=body).status_code

        for i in range(throttle.ACCOUNT_FREE_FAILURES):  # five wrong: free
            assert guess(i) == 403
        with ThreadPoolExecutor(max_workers=35) as pool:
            answers = list(pool.map(guess, range(5, 40)))
        assert answers.count(429) >= 20 and set(answers) == {403, 429}, answers
        assert cell.bridge.access.throttle.account_failures("anna") == 40 - answers.count(429)
        assert all(cell.bridge.access.throttle.failures(f"127.0.3.{i + 1}") <= 1 for i in range(40))
        login(http, "anna")  # 127.0.0.1: slowed at most, not refused
        assert cell.bridge.access.throttle.account_failures("anna") == 0
