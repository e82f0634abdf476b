"""Issue 15, item 6: the HMI against a hostile web. A page on another site cannot make a visitor's
browser command the cell (Origin, Sec-Fetch-Site, JSON content type); a foreign Host header is
refused (DNS rebinding); the token is checked before a byte of the body is read and bodies are
bounded; integers are range-checked (no wrap-around); NaN never breaks the page's JSON; a
malformed request gets a 4xx JSON answer with a reason code, never a 500; token guesses are
throttled per client and logged without the guess."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from packml_interfaces.msg import Descriptor, Status

from packml_ros2 import qos
from packml_ros2.hmi.server import Server, bind
from test.hmi.test_bridge import TOKEN, UNIT, Cell, serving
from test.hostile.http import raw

pytestmark = pytest.mark.ros

JSON = {"Content-Type": "application/json"}
AUTH = {"Authorization": f"Bearer {TOKEN}", **JSON}


@pytest.fixture
def make_cell(ros: Any, tmp_path: Path) -> Iterator[Callable[..., Cell]]:
    made: list[Cell] = []

    def make(token: str | None = None) -> Cell:
        made.append(Cell(ros, tmp_path, token, 3.0))
        return made[-1]

    yield make
    for cell in made:
        cell.close()


def strict_json(text: str) -> Any:
    """JSON as a browser's JSON.parse reads it: NaN and Infinity are errors."""

    def refuse(name: str) -> Any:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def refused(r: httpx.Response, status: int, code: str) -> dict[str, Any]:
    assert r.status_code == status, (r.status_code, r.text)
    body = strict_json(r.text)
    assert body["accepted"] is False and body["code"] == code, body
    assert isinstance(body["result"], int) and body["result_name"] and body["message"], body
    return body


def rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS")).split()[1]) / 1024


# -- cross-site requests and the Host header ------------------------------------------------------------
def test_a_page_of_another_site_cannot_command_the_cell(make_cell: Any) -> None:
    cell = make_cell()  # no token: the shipped demo
    seq = cell.client.status.last.sequence
    with serving(cell.bridge) as http:
        # what a hostile page's <form> or fetch(..., {mode: "no-cors"}) sends
        text = {"Content-Type": "text/plain", "Origin": "http://evil.example"}
        refused(http.post(f"/api/units/{UNIT}/command", content='{"command": "reset"}',
                          headers=text), 403, "CROSS_SITE")  # fmt: skip
        refused(http.post(f"/api/units/{UNIT}/command", json={"command": 1},
                          headers={"Sec-Fetch-Site": "cross-site"}), 403, "CROSS_SITE")  # fmt: skip
        refused(http.post(f"/api/units/{UNIT}/command", json={"command": 1},
                          headers={"Origin": "null"}), 403, "CROSS_SITE")  # fmt: skip
        refused(http.post("/api/cell/command", json={"command": 1},
                          headers={"Sec-Fetch-Site": "same-site"}), 403, "CROSS_SITE")  # fmt: skip
        # a simple request without Origin (an old browser, a form) is still not JSON
        for kind in ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data"):
            refused(http.post(f"/api/units/{UNIT}/command", content='{"command": 1}',
                              headers={"Content-Type": kind}), 415, "UNSUPPORTED_MEDIA_TYPE")  # fmt: skip
        refused(http.post(f"/api/units/{UNIT}/reset_counters"), 415, "UNSUPPORTED_MEDIA_TYPE")
        assert cell.client.status.last.sequence == seq  # nothing reached the unit
        # the page itself: same origin, JSON
        own = {"Origin": str(http.base_url).rstrip("/"), "Sec-Fetch-Site": "same-origin"}
        ok = http.post(f"/api/units/{UNIT}/command", json={"command": "reset"}, headers=own)
        assert ok.status_code == 200 and ok.json()["accepted"], ok.text


def test_answers_are_not_held_back_by_nagle() -> None:
    # asyncio sets TCP_NODELAY only on sockets created for TCP (accepted ones inherit it): every
    # answer of the HMI waited ~40 ms for a delayed ACK (3 000 requests: 118 s, now 4 s)
    sock = bind("127.0.0.1", 0)
    try:
        assert sock.proto == socket.IPPROTO_TCP
    finally:
        sock.close()


def test_a_foreign_host_name_is_refused(make_cell: Any) -> None:
    cell = make_cell()
    server = Server(cell.bridge, bind("127.0.0.1", 0), allowed_hosts=["hmi.line3.example"])
    server.start()
    try:
        _wait(server.started, "the HMI server")
        port = server.sock.getsockname()[1]
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
            for host in ("evil.example", f"rebind.evil.example:{port}", "localhost.evil",
                         "127.0.0.1.nip.io", "", "[::1", "a:b:c"):  # fmt: skip
                refused(http.get("/api/snapshot", headers={"Host": host}), 403, "HOST_NOT_ALLOWED")
                refused(http.post(f"/api/units/{UNIT}/command", json={"command": 1},
                                  headers={"Host": host}), 403, "HOST_NOT_ALLOWED")  # fmt: skip
            for host in (f"127.0.0.1:{port}", f"localhost:{port}", "LOCALHOST", "[::1]:80",
                         "hmi.line3.example", f"{socket.gethostname()}:{port}"):  # fmt: skip
                assert http.get("/api/config", headers={"Host": host}).status_code == 200, host
    finally:
        server.stop()


def test_packml_hmi_serves_the_names_of_hmi_allowed_hosts(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump({"cell": f"hosts{os.getpid()}", "units": {"u": {"persistence": False}},
                                    "hmi": {"port": 0, "allowed_hosts": ["hmi.line3.example"]}}))  # fmt: skip
    log = tmp_path / "hmi.log"
    with log.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "packml_ros2.cli.main", "hmi", str(path)],
                                stdout=out, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONUNBUFFERED="1"))  # fmt: skip
    try:
        found: list[str] = []

        def served() -> bool:
            found[:] = re.findall(r"http://127\.0\.0\.1:\d+/", log.read_text())
            assert proc.poll() is None, log.read_text()
            return bool(found)

        _wait(served, "packml hmi", 30)
        url = found[0]
        assert (
            httpx.get(f"{url}api/config", headers={"Host": "hmi.line3.example"}).status_code == 200
        )
        refused(httpx.get(f"{url}api/config", headers={"Host": "other.example"}), 403,
                "HOST_NOT_ALLOWED")  # fmt: skip
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(15)


# -- bodies ---------------------------------------------------------------------------------------------
def test_the_token_is_checked_before_the_body_and_bodies_are_bounded(make_cell: Any) -> None:
    cell = make_cell(token=TOKEN)
    with serving(cell.bridge) as http:
        port = http.base_url.port
        assert port is not None
        head = (f"POST /api/units/{UNIT}/command HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                "Content-Type: application/json\r\nContent-Length: 100000000\r\n")  # fmt: skip
        # no token: refused at once, the 100 MB announced are never waited for
        started = time.monotonic()
        status, answer = raw(port, (head + "\r\n").encode() + b'{"command"')
        assert status == 403 and b"TOKEN_MISSING" in answer
        # the token: refused as too large, without reading it
        status, answer = raw(port, (head + f"Authorization: Bearer {TOKEN}\r\n\r\n").encode())
        assert status == 413 and b"BODY_TOO_LARGE" in answer
        assert time.monotonic() - started < 5
        # chunked, no length announced: 100 MB sent, the server stops reading at 64 kB
        before = rss_mb()
        chunked = (f"POST /api/units/{UNIT}/command HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                   f"Authorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\n"
                   "Transfer-Encoding: chunked\r\n\r\n").encode()  # fmt: skip
        chunk = b"10000\r\n" + b" " * 0x10000 + b"\r\n"
        status, answer = raw(port, chunked, iter([chunk] * 1600))
        assert status == 413 and b"BODY_TOO_LARGE" in answer
        assert rss_mb() - before < 30  # was +200 MB for a 100 MB body
        ok = http.post(f"/api/units/{UNIT}/command", json={"command": "reset"}, headers=AUTH)
        assert ok.status_code == 200, ok.text


@pytest.mark.parametrize(
    ("body", "what"),
    [
        (b'{"command": "reset"', "truncated"),
        (b"\xff\xfe{}", "not UTF-8"),
        (b"[" * 30_000 + b"]" * 30_000, "nested"),
        (b'{"a": ' * 30 + b"1" + b"}" * 30, "nested 30"),
        (b'{"command": ' + b"9" * 5000 + b"}", "5000 digits"),
        (b'{"mach_speed": NaN}', "NaN"),
        (b'{"mach_speed": -Infinity}', "Infinity"),
        (b'["reset"]', "a list"),
        (b'"reset"', "a string"),
        (b'{"command": 1, "command": 2}', "a key twice"),
    ],
)
def test_a_malformed_body_gets_400_with_a_reason(make_cell: Any, body: bytes, what: str) -> None:
    cell = make_cell()
    with serving(cell.bridge) as http:
        for action in ("command", "set_mach_speed"):
            answer = refused(http.post(f"/api/units/{UNIT}/{action}", content=body, headers=JSON),
                             400, "MALFORMED_JSON")  # fmt: skip
            assert len(answer["message"]) < 200, what


@pytest.mark.parametrize(
    ("action", "args"),
    [
        ("set_mode", {"mode": 4294967298}),  # was: mode 2 (wrapped), Maintenance
        ("set_mode", {"mode": "4294967298"}),
        ("set_mode", {"mode": -1}),
        ("set_mode", {"mode": 2.0}),
        ("set_mode", {"mode": "x" * 1000}),
        ("command", {"command": 2**32 + 2}),
        ("command", {"command": 0}),
        ("command", {"command": ["reset"]}),
        ("command", {"command": "reset", "source": "remote:mes"}),  # no caller-chosen source
        ("ack_alarms", {"id": 2**31}),
        ("ack_alarms", {"all": False, "id": 1, "value": -(2**31) - 1}),
        ("set_mach_speed", {"mach_speed": math.inf}),
        ("set_mach_speed", {"mach_speed": -5}),
        ("set_em_active", {"em": "nozzle/../x", "active": True}),
        ("set_em_active", {"em": "n" * 300}),
        ("reset_times", {"scope": ["all"]}),
        ("reset_counters", {"all": True}),
    ],
)
def test_arguments_are_range_checked_and_nothing_wraps(make_cell: Any, action: str,
                                                        args: dict[str, Any]) -> None:  # fmt: skip
    cell = make_cell()
    status = cell.client.status.last
    with serving(cell.bridge) as http:
        body = json.dumps(args, allow_nan=True).encode()
        answer = http.post(f"/api/units/{UNIT}/{action}", content=body, headers=JSON)
        if b"Infinity" in body:
            refused(answer, 400, "MALFORMED_JSON")
        else:
            refused(answer, 400, "BAD_ARGUMENT")
            assert answer.json()["result_name"] == "INVALID_ARGUMENT"
    assert cell.client.status.last.sequence == status.sequence
    assert cell.client.status.last.unit_mode_current == status.unit_mode_current


def test_nan_from_a_unit_never_breaks_the_pages_json(make_cell: Any, ros: Any) -> None:
    cell = make_cell()
    publisher = ros.node.create_publisher(Status, f"/{cell.cell}/{UNIT}/status", qos.STATUS)
    try:
        with serving(cell.bridge) as http:
            nan = Status(unit=UNIT, mach_speed=math.nan, cur_mach_speed=math.inf, sequence=10**6,
                         parameter=[Descriptor(id=1, name="p", value=math.nan)])  # fmt: skip
            mark = len(cell.events)
            publisher.publish(nan)
            cell.wait_event(lambda e: e["topic"] == "status" and e["data"]["sequence"] == 10**6,
                            "the NaN status", mark)  # fmt: skip
            snap = strict_json(http.get("/api/snapshot").text)  # was: HTTP 500
            status = snap["units"][UNIT]["status"]
            assert status["mach_speed"] is None and status["cur_mach_speed"] is None
            assert status["parameters"][0]["value"] is None
            with http.stream("GET", "/api/events", timeout=10) as events:
                data = next(line for line in events.iter_lines() if line.startswith("data: "))
            strict_json(data[6:])  # was: a NaN token JSON.parse rejects
    finally:
        ros.node.destroy_publisher(publisher)


def test_unknown_paths_and_methods_answer_json(make_cell: Any) -> None:
    cell = make_cell()
    with serving(cell.bridge) as http:
        refused(http.get("/api/nothing"), 404, "NOT_FOUND")
        refused(http.post("/api/units/nope/command", json={}), 404, "NOT_FOUND")
        refused(http.post(f"/api/units/{UNIT}/launch", json={}), 404, "NOT_FOUND")
        refused(http.put(f"/api/units/{UNIT}/command", json={}), 405, "METHOD_NOT_ALLOWED")
        refused(http.delete("/api/snapshot"), 405, "METHOD_NOT_ALLOWED")


def test_event_streams_are_bounded(make_cell: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    from packml_ros2.hmi import server

    monkeypatch.setattr(server, "MAX_STREAMS", 2)
    monkeypatch.setattr(server, "OPERATOR_STREAMS", 0)  # (none kept for operators here)
    cell = make_cell()
    with serving(cell.bridge) as http, ExitStack() as streams:
        open_ = []  # (an abandoned line iterator closes its stream: keep them)
        for _ in range(2):
            r = streams.enter_context(http.stream("GET", "/api/events", timeout=10))
            open_.append(r.iter_lines())
            assert next(open_[-1]).startswith("retry:")
        refused(http.get("/api/events"), 503, "TOO_MANY_STREAMS")


# -- guessing the token ------------------------------------------------------------------------------------
def test_token_guesses_are_throttled_per_client_and_logged_without_the_guess(
    make_cell: Any, caplog: pytest.LogCaptureFixture
) -> None:
    from packml_ros2.core.throttle import FREE_FAILURES

    cell = make_cell(token=TOKEN)
    now = [1000.0]
    cell.bridge.access.throttle.clock = lambda: now[0]
    caplog.set_level(logging.WARNING, "packml_ros2.hmi")
    with serving(cell.bridge) as http:
        for i in range(FREE_FAILURES):
            refused(http.post("/api/auth", headers={"Authorization": f"Bearer guess-{i}"}),
                    403, "TOKEN_WRONG")  # fmt: skip
        # blocked now: even the right token, even claiming another address
        blocked = http.post("/api/auth", headers={**AUTH, "X-Forwarded-For": "10.9.8.7"})
        refused(blocked, 429, "THROTTLED")
        assert int(blocked.headers["retry-after"]) >= 1
        refused(http.post(f"/api/units/{UNIT}/command", json={"command": 1}, headers=AUTH),
                429, "THROTTLED")  # fmt: skip
        now[0] += 1.5  # the first back-off: 1 s, doubling with each further failure
        refused(http.post("/api/auth", headers={"Authorization": "Bearer guess-x"}), 403,
                "TOKEN_WRONG")  # fmt: skip
        again = http.post("/api/auth", headers=AUTH)
        refused(again, 429, "THROTTLED")
        assert int(again.headers["retry-after"]) >= 2
        now[0] += 2.5
        assert http.post("/api/auth", headers=AUTH).status_code == 200  # clears the count
        refused(http.post("/api/auth", headers={"Authorization": "Bearer guess-y"}), 403,
                "TOKEN_WRONG")  # fmt: skip
    text = caplog.text
    assert "wrong access token from 127.0.0.1 (5 in a row); its next attempts are refused" in text
    assert "guess-" not in text and TOKEN not in text and "10.9.8.7" not in text


def _wait(predicate: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"{what} not within {timeout} s"
        time.sleep(0.01)
