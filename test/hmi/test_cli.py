"""Issue 7: `packml hmi <cell.yaml>` as a user runs it: serves on 127.0.0.1 (port from the file or
the options), takes the token from the file, --token or $PACKML_HMI_TOKEN, stops cleanly on
Ctrl-C, and refuses a bad hmi: block naming the key."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

pytestmark = pytest.mark.ros

PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


def cell_file(tmp_path: Path, hmi: dict[str, object]) -> Path:
    doc = {"cell": f"cli{os.getpid()}", "units": {"filler": {"persistence": False}}, "hmi": hmi}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_packml_hmi_serves_locally_and_stops_on_ctrl_c(tmp_path: Path) -> None:
    path = cell_file(tmp_path, {"port": 0, "title": "Filling line"})
    log = tmp_path / "hmi.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [*PACKML, "hmi", str(path)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1", PACKML_HMI_TOKEN="from-the-env"),
        )
        try:
            deadline = time.monotonic() + 30
            while not (found := re.search(r"(http://127\.0\.0\.1:\d+/)", log.read_text())):
                assert proc.poll() is None, log.read_text()
                assert time.monotonic() < deadline, log.read_text()
                time.sleep(0.05)
            url = found.group(1)
            assert "an access token is required" in log.read_text()
            config = httpx.get(f"{url}api/config", timeout=10).json()
            assert config["title"] == "Filling line" and config["token_required"] is True
            page = httpx.get(url, timeout=10)
            assert page.status_code == 200 and "/static/app.js" in page.text
            assert "http" not in re.sub(r"http://www\.w3\.org/2000/svg", "", page.text)  # no CDN
            refused = httpx.post(f"{url}api/units/filler/command", json={"command": 1}, timeout=10)
            assert refused.status_code == 403
            # the event stream is open while Ctrl-C arrives: the server still stops at once
            with httpx.stream("GET", f"{url}api/events", timeout=10) as events:
                assert next(events.iter_lines()).startswith("retry:")
                started = time.monotonic()
                proc.send_signal(signal.SIGINT)
                assert proc.wait(15) == 0, log.read_text()
            assert time.monotonic() - started < 5
        finally:
            if proc.poll() is None:
                proc.kill()
    assert "Traceback" not in log.read_text(), log.read_text()


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
