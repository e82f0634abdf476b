"""Issue 7: `packml hmi <cell.yaml>` as a user runs it: serves on 127.0.0.1 (port from the file or
the options), takes the token from the file, --token or $PACKML_HMI_TOKEN, stops cleanly on
Ctrl-C, and refuses a bad hmi: block naming the key. Issue 17: the README's user logins (a users
file, `packml hmi --hash-password`, `--check`) run verbatim, and the password prompt on a
terminal."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from packml_ros2.core import load_cell
from packml_ros2.core.secrets import check_password
from packml_ros2.hmi.access import LEVELS, Access, Principal, Refusal
from packml_ros2.hmi.settings import hmi_settings
from packml_ros2.testing.launched import Launched
from test.workspace.tools import README, console_commands, shell, shown_in

pytestmark = pytest.mark.ros

PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def cell_file(tmp_path: Path, hmi: dict[str, object]) -> Path:
    doc = {"cell": f"cli{os.getpid()}", "units": {"filler": {"persistence": False}}, "hmi": hmi}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_packml_hmi_serves_locally_and_stops_on_ctrl_c(tmp_path: Path) -> None:
    path = cell_file(tmp_path, {"port": 0, "title": "Filling line"})
    hmi = Launched(
        [*PACKML, "hmi", str(path)], tmp_path / "hmi.log", {"PACKML_HMI_TOKEN": "from-the-env"}
    )
    try:
        url = hmi.wait_for(r"(http://127\.0\.0\.1:\d+/)", 30).group(1)
        assert "an access token is required" in hmi.output()
        config = httpx.get(f"{url}api/config", timeout=10).json()
        assert config["title"] == "Filling line" and config["token_required"] is True
        page = httpx.get(url, timeout=10)
        assert page.status_code == 200 and "/static/app.js" in page.text
        assert "http" not in re.sub(r"http://www\.w3\.org/2000/svg", "", page.text)  # no CDN
        refused = httpx.post(f"{url}api/units/filler/command", json={"command": 1}, timeout=10)
        assert refused.status_code == 403
        # the event stream is open while Ctrl-C arrives: the server still stops, and at once (it
        # ends the open streams itself: uvicorn would wait for them timeout_graceful_shutdown)
        with httpx.stream("GET", f"{url}api/events", timeout=10) as events:
            assert next(events.iter_lines()).startswith("retry:")
            assert hmi.stop(timeout=5) == 0, hmi.output()
    finally:
        if hmi.proc.poll() is None:
            hmi.proc.kill()
    assert "Traceback" not in hmi.output(), hmi.output()


def test_a_bad_hmi_block_is_refused_with_its_key_path(tmp_path: Path) -> None:
    path = cell_file(tmp_path, {"port": "eighty", "tokn": "abcd"})
    for verb in (["hmi", str(path)], ["launch", str(path), "--hmi", "--check"]):
        result = subprocess.run(
            [*PACKML, *verb], check=False, capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 2, result
        assert "hmi.port: expected an integer, got 'eighty'" in result.stderr
        assert "hmi.tokn: unknown key (did you mean 'token'?)" in result.stderr
    ok = cell_file(tmp_path, {"port": 8123})
    checked = subprocess.run(
        [*PACKML, "hmi", str(ok), "--check"],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert checked.returncode == 0 and "127.0.0.1:8123" in checked.stdout, checked


# -- the README's logins, as an integrator types them (issue 17) -------------------------------------------
def readme_logins() -> tuple[dict[str, Any], str, list[tuple[str, list[str]]], list[str]]:
    """The README's "Logins and levels": its hmi: block, its users file (text), its console
    commands with their shown output, and the levels of its table."""
    text = README.read_text(encoding="utf-8")
    part = text[text.index("### Logins and levels") :]
    part = part[: part.index("`make screenshots`")]
    blocks = re.findall(r"^```(\w+)\n(.*?)^```", part, flags=re.MULTILINE | re.DOTALL)
    yamls = [body for lang, body in blocks if lang == "yaml"]
    consoles = [body for lang, body in blocks if lang == "console"]
    assert len(yamls) == 2 and len(consoles) == 1, blocks
    levels = re.findall(r"^\| `(\w+)` \|", part, flags=re.MULTILINE)
    return yaml.safe_load(yamls[0])["hmi"], yamls[1], console_commands(consoles[0]), levels


def test_the_readmes_logins_as_an_integrator_types_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    hmi, users_text, commands, levels = readme_logins()
    assert levels == list(LEVELS)  # the table names the levels the HMI knows, lowest first
    passwords = {"anna": "anna-pass-1", "ben": "ben-pass-22", "carla": "carla-pass-333"}
    (tmp_path / "anna.pw").write_text(passwords["anna"] + "\n")
    (tmp_path / "carla.pw").write_text(passwords["carla"] + "\n")
    cell = {"cell": f"line{os.getpid()}", "units": {"filler": {"persistence": False}}, "hmi": hmi}
    (tmp_path / "line3.yaml").write_text(yaml.safe_dump(cell, sort_keys=False))
    assert [c for c, _ in commands] == [
        "packml hmi --hash-password < anna.pw",
        "packml hmi line3.yaml --check",
    ]

    # the hash of anna's password, as the README shows it (its digits and salt left out)
    (hash_cmd, hash_shown), (check_cmd, check_shown) = commands
    made = shell(hash_cmd, tmp_path, tmp_path)
    assert made.returncode == 0, made.stdout
    hashed = made.stdout.strip()
    assert hash_shown[0].endswith("...") and hashed.startswith(hash_shown[0][:-3]), hashed
    assert check_password(passwords["anna"], hashed) and passwords["anna"] not in made.stdout
    placeholder = re.search(r'"(pbkdf2_sha256\$[^"]*\.\.\.)"', users_text)
    assert placeholder, users_text
    (tmp_path / "hmi-users.yaml").write_text(users_text.replace(placeholder.group(1), hashed))

    checked = shell(f"export LINE3_BEN_PW={passwords['ben']}\n{check_cmd}", tmp_path, tmp_path)
    assert checked.returncode == 0, checked.stdout
    assert shown_in(check_shown, checked.stdout) is None, (check_shown, checked.stdout)

    # each user of the file logs in with their password, at their level
    monkeypatch.setenv("LINE3_BEN_PW", passwords["ben"])
    settings = hmi_settings(load_cell(tmp_path / "line3.yaml"))
    access = Access(None, users=settings.users, logout_after=settings.logout_after)
    for name, level in (("anna", "operator"), ("ben", "maintenance"), ("carla", "engineer")):
        ok = asyncio.run(access.login(name, passwords[name], "127.0.0.1"))
        assert not isinstance(ok, Refusal), (name, ok)
        assert ok[1] == Principal(name, level)
    assert settings.logout_after == hmi["logout_after"]

    # a plain password in the users file: refused, naming the key and never the value
    (tmp_path / "hmi-users.yaml").write_text(
        users_text.replace(f'"{placeholder.group(1)}"', "anna-pass-1")
    )
    refused = shell(f"export LINE3_BEN_PW={passwords['ben']}\n{check_cmd} || echo exit $?",
                    tmp_path, tmp_path)  # fmt: skip
    assert "hmi-users.yaml: users.anna.password:" in refused.stdout, refused.stdout
    assert "exit 2" in refused.stdout and "anna-pass-1" not in refused.stdout, refused.stdout
    assert "Traceback" not in refused.stdout


def test_hash_password_asks_on_a_terminal_without_echo(tmp_path: Path) -> None:
    # `packml hmi --hash-password` typed in a terminal: a prompt, the password not echoed
    primary, secondary = os.openpty()
    proc = subprocess.Popen([*PACKML, "hmi", "--hash-password"], stdin=secondary,
                            stdout=secondary, stderr=secondary, start_new_session=True)  # fmt: skip
    os.close(secondary)
    try:
        out = b""
        while b"password:" not in out:
            out += os.read(primary, 1024)
        os.write(primary, b"line3-secret\n")
        assert proc.wait(30) == 0
        while True:
            try:
                chunk = os.read(primary, 4096)
            except OSError:  # the terminal is closed once the program ended
                break
            if not chunk:
                break
            out += chunk
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(primary)
    text = out.decode()
    assert "line3-secret" not in text, text
    hashed = re.search(r"pbkdf2_sha256\$\S+", text)
    assert hashed and check_password("line3-secret", hashed.group(0)), text
