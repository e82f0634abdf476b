"""Issue 15, item 1: secrets are pointed to (env:VAR, file:PATH), never written in a cell file; a
plain-text secret is refused at load naming the key and never the value; what units publish and
bags record is redacted."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from packml_ros2.core import ConfigError, load_cell, parse_cell
from packml_ros2.hmi import hmi_settings
from packml_ros2.opcua.config import check_password, hash_password, parse_opcua

TOKEN = "Tok3n-value-never-shown"
PASSWORD = "Passw0rd-never-shown"


def write(tmp_path: Path, doc: dict[str, object]) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump({"cell": "c", "units": {"u": {}}, **doc}, sort_keys=False))
    return path


def test_a_plain_text_secret_is_refused_naming_the_key_never_the_value(tmp_path: Path) -> None:
    doc = {"hmi": {"token": TOKEN},
           "opcua": {"users": {"op": PASSWORD, "mes": hash_password("x" * 8, 1000),
                               "scada": "env:PACKML_SCADA_PW"}}}  # fmt: skip
    path = write(tmp_path, doc)
    with pytest.raises(ConfigError) as info:
        load_cell(path)  # what every loader calls: unit_node and the coordinator too
    text = str(info.value)
    assert [p for p, _ in info.value.problems] == ["hmi.token", "opcua.users.op"]
    assert "a secret is never written in the cell file" in text and "env:VARIABLE" in text
    assert TOKEN not in text and PASSWORD not in text
    # as a user sees it
    for verb in (["launch", str(path), "--check"], ["hmi", str(path), "--check"]):
        result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", *verb],
                                capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
        assert result.returncode == 2, result
        assert "hmi.token: a secret is never written" in result.stderr
        assert TOKEN not in result.stderr + result.stdout
        assert PASSWORD not in result.stderr + result.stdout


def test_secrets_come_from_the_environment_or_a_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "secrets").mkdir()
    (tmp_path / "secrets" / "hmi.token").write_text(TOKEN + "\n")
    monkeypatch.setenv("PACKML_TEST_OP_PW", PASSWORD)
    (tmp_path / "mes.pw").write_text("mes-password\r\n")
    path = write(tmp_path, {"hmi": {"token": "file:secrets/hmi.token"},
                            "opcua": {"users": {"op": "env:PACKML_TEST_OP_PW",
                                                "mes": f"file:{tmp_path / 'mes.pw'}"}}})  # fmt: skip
    cell = load_cell(path)
    assert hmi_settings(cell).token == TOKEN  # relative to the cell file, newline dropped
    users = parse_opcua(cell).users
    assert check_password(PASSWORD, users["op"]) and check_password("mes-password", users["mes"])
    assert TOKEN not in repr(hmi_settings(cell)) and PASSWORD not in repr(parse_opcua(cell))


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("env:PACKML_NO_SUCH_VARIABLE", "environment variable PACKML_NO_SUCH_VARIABLE is not set"),
        ("env:", "env: is not an environment variable name"),
        ("file:missing.token", "cannot read"),
        ("file:big.token", "is larger than 4096 bytes"),
        ("file:short.token", "a token needs at least 8 characters"),
        ("<redacted>", "recorded without its secrets"),
    ],
)
def test_a_secret_that_cannot_be_had_is_refused_without_showing_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, value: str, problem: str
) -> None:
    monkeypatch.delenv("PACKML_NO_SUCH_VARIABLE", raising=False)
    (tmp_path / "big.token").write_text(TOKEN * 1000)
    (tmp_path / "short.token").write_text("abc")
    with pytest.raises(ConfigError) as info:
        hmi_settings(load_cell(write(tmp_path, {"hmi": {"token": value}})))
    ((path, text),) = info.value.problems
    assert path == "hmi.token" and problem in text, text
    assert TOKEN not in str(info.value)


def test_the_published_configuration_is_redacted(tmp_path: Path) -> None:
    from packml_ros2.core.secrets import REDACTED, redacted_yaml

    text = yaml.safe_dump({
        "cell": "c", "units": {"u": {"description": "filler"}},
        "hmi": {"token": "env:HMI_TOKEN", "port": 8080},
        "opcua": {"users": {"op": "env:OP", "mes": hash_password("abcdefgh", 1000)},
                  "private_key": "certs/key.pem", "port": 4840},
    })  # fmt: skip
    redacted = yaml.safe_load(redacted_yaml(text))
    assert redacted["hmi"] == {"token": REDACTED, "port": 8080}
    assert redacted["opcua"]["users"] == {"op": REDACTED, "mes": REDACTED}
    assert redacted["opcua"]["private_key"] == REDACTED and redacted["opcua"]["port"] == 4840
    assert "pbkdf2" not in redacted_yaml(text)
    cell = parse_cell(redacted)  # a recording still loads (replay needs its units)
    assert cell.units["u"].description == "filler"


def test_packml_hmi_token_option_points_to_the_token_too(tmp_path: Path) -> None:
    path = write(tmp_path, {})

    def hmi(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "hmi", str(path), *args,
                               "--check"], capture_output=True, text=True, timeout=60, check=False,
                              env={**os.environ, **env})  # fmt: skip

    plain = hmi("--token", TOKEN)  # would be in every user's process list
    assert plain.returncode == 2 and "--token: give env:VARIABLE or file:PATH" in plain.stderr
    assert TOKEN not in plain.stderr + plain.stdout
    assert hmi("--token", "env:PACKML_TEST_TOKEN", PACKML_TEST_TOKEN=TOKEN).returncode == 0
    short = hmi(PACKML_HMI_TOKEN="abc")
    assert short.returncode == 2 and "$PACKML_HMI_TOKEN: a token needs at least 8" in short.stderr


def test_credentials_in_a_url_are_refused_at_load_and_redacted_wherever_shown(
    tmp_path: Path,
) -> None:
    """Issue 25 item 10: ``opc.tcp://user:pw@host`` as a PLC endpoint was accepted, used, and
    published on ``~/config``, in bags and in refusals."""
    from packml_ros2.core.limits import printable
    from packml_ros2.core.secrets import REDACTED, redact_urls, redacted_yaml

    url = f"opc.tcp://plcuser:{PASSWORD}@10.0.0.21:4840/"
    doc = {"units": {"u": {"plc": {"endpoint": url}}, "v": {"description": f"see http://x:{PASSWORD}@h/"}}}  # fmt: skip
    path = write(tmp_path, doc)
    with pytest.raises(ConfigError) as info:
        load_cell(path)
    assert [p for p, _ in info.value.problems] == ["units.u.plc.endpoint", "units.v.description"]
    assert "a URL never holds a user name or password" in str(info.value)
    assert PASSWORD not in str(info.value) and "plcuser" not in str(info.value)
    result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "launch", str(path), "--check"],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2, result
    assert "units.u.plc.endpoint: a URL never holds" in result.stderr, result.stderr
    assert PASSWORD not in result.stderr + result.stdout
    # wherever a URL is shown: ~/config and bags (redacted_yaml), log lines (printable), messages
    assert redact_urls(f"failed: {url} and mqtt://u@b:1883") == (
        f"failed: opc.tcp://{REDACTED}@10.0.0.21:4840/ and mqtt://{REDACTED}@b:1883")  # fmt: skip
    assert redact_urls("mail a@b.c, opc.tcp://10.0.0.21:4840/x@y") == "mail a@b.c, opc.tcp://10.0.0.21:4840/x@y"  # fmt: skip
    assert PASSWORD not in redacted_yaml(yaml.safe_dump({"cell": "c", "units": {"u": {"plc": {"endpoint": url}}}}))  # fmt: skip
    assert PASSWORD not in printable(f"PLC {url} lost") and "10.0.0.21:4840" in printable(f"PLC {url} lost")  # fmt: skip
