"""Issue 15: thousands of hostile requests against a running HMI (a real unit, the bridge, the
HTTP server on loopback). Each is refused with the status and reason code its fault calls for and
a sentence, as strict JSON; nothing is a 500 or a traceback; nothing reaches the unit (its status
sequence and its input log show no action); the server's memory stays bounded; wrong tokens from
one address get that address throttled, not the others."""

from __future__ import annotations

import json
import os
import time
from typing import Any

import httpx
import pytest
from packml_interfaces.msg import UnitInput

from packml_ros2 import qos
from packml_ros2.hmi.bridge import UNIT_ACTIONS
from test.hmi.test_bridge import TOKEN, UNIT, Cell, serving
from test.hostile.http import Hostile, hostile_requests, raw

pytestmark = pytest.mark.ros

SEED = 1515
COUNT = 5000  # ~7 s on the CI machine (1.4 ms a request)
WARM_UP = 300
MAX_SECONDS = 120
MAX_RSS_GROWTH_MB = 40  # measured: -1..+2 MB over the 4 700 requests after the warm-up
ACTIONS = set(UNIT_ACTIONS)


def rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS")).split()[1]) / 1024


def strict(text: str) -> Any:
    def refuse(name: str) -> Any:
        raise ValueError(f"{name} is not JSON")

    return json.loads(text, parse_constant=refuse)


def send(client: httpx.Client, h: Hostile) -> httpx.Response:
    return client.request(h.method, h.path, headers=h.headers, content=h.body)


def check(h: Hostile, r: httpx.Response) -> None:
    what = f"{h.fault} ({h.method} {h.path[:60]})"
    assert r.status_code != 500 and "Traceback" not in r.text, f"{what}: {r.text[:300]}"
    codes = h.code.split("|")
    expected = {"TOKEN_WRONG": 403, "THROTTLED": 429}
    body = strict(r.text)
    assert body.get("code") in codes, f"{what}: {r.status_code} {r.text[:300]}"
    assert r.status_code == expected.get(body["code"], h.status), f"{what}: {r.status_code}"
    assert body["accepted"] is False and isinstance(body["result"], int), f"{what}: {body}"
    assert body["result_name"] and 10 < len(body["message"]) < 500, f"{what}: {body}"


def test_thousands_of_hostile_requests_change_nothing(
    ros: Any, tmp_path: Any, capfd: pytest.CaptureFixture[str]
) -> None:
    cell = Cell(ros, tmp_path, TOKEN, 3.0)
    inputs = ros.subscribe(UnitInput, f"/{cell.cell}/{UNIT}/input_log", qos.INPUT_LOG)
    try:
        status = cell.client.status.last
        with serving(cell.bridge) as http:
            port = http.base_url.port
            guesser = httpx.Client(
                base_url=str(http.base_url), timeout=10,
                transport=httpx.HTTPTransport(local_address="127.0.0.2"),
            )  # fmt: skip
            clients = {"main": http, "guesser": guesser}
            started = time.monotonic()
            counts: dict[str, int] = {}
            before = 0.0
            for i, h in enumerate(hostile_requests(SEED, COUNT, UNIT, TOKEN)):
                if i == WARM_UP:
                    before = rss_mb()
                check(h, send(clients[h.client], h))
                key = h.code.split("|")[0]
                counts[key] = counts.get(key, 0) + 1
                assert time.monotonic() - started < MAX_SECONDS, f"{i} requests: {counts}"
            grown = rss_mb() - before
            # what a client library cannot send: 100 MB announced, 50 MB streamed
            head = (f"POST /api/units/{UNIT}/command HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                    f"Authorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\n")  # fmt: skip
            assert port is not None
            assert raw(port, (head + "Content-Length: 100000000\r\n\r\n").encode())[0] == 413
            chunk = b"10000\r\n" + b" " * 0x10000 + b"\r\n"
            chunked = (head + "Transfer-Encoding: chunked\r\n\r\n").encode()
            assert raw(port, chunked, [chunk] * 800)[0] == 413
            grown = max(grown, rss_mb() - before)
            # the guesser is throttled, the operator is not
            assert guesser.post("/api/auth", headers={"Authorization": f"Bearer {TOKEN}"}
                                ).status_code == 429  # fmt: skip
            assert http.post("/api/auth", headers={"Authorization": f"Bearer {TOKEN}"}
                             ).status_code == 200  # fmt: skip
            guesser.close()
        elapsed = time.monotonic() - started
        with capfd.disabled():
            print(f"\n{COUNT} hostile requests in {elapsed:.1f} s, RSS +{grown:.1f} MB: {counts}")
        assert len(counts) == 10, counts  # every kind of fault was sent
        assert grown < MAX_RSS_GROWTH_MB, f"RSS grew {grown:.1f} MB"
        # nothing reached the unit
        assert cell.client.status.last.sequence == status.sequence
        acted = [m.name for m in inputs.messages if m.name in ACTIONS]
        assert acted == [], acted
    finally:
        cell.close()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception in ASGI application" not in err, err[-2000:]
    assert TOKEN not in err


LINE_QUERIES = 300
SHIFT_DAYS = ("9999-12-31", "0001-01-01", "2262-04-12", "2038-01-19", "1970-01-01", "2025-06-16",
              "2025-02-30", "0000-00-00", "2025-13-01")  # fmt: skip
SHIFT_TEXT = ("current", "previous", "", "early", "%00", "%0a", "\u202e", "x" * 81, "9" * 5000,
              "<script>", "current ", "2025-06-16", "2025-06-16  early", "2025-06-16 ear%20ly")  # fmt: skip
REPORT_OPTIONS = (["--shift", "9999-12-31 early"], ["--shift", "0001-01-01 night"],
                  ["--shift", "x" * 500], ["--since", "9" * 400 + "h"], ["--since", "0001-01-01T00:00"],
                  ["--since", "9999-12-31T23:59"], ["--since", "1h", "--until", "9999-12-31T00:00"],
                  ["--since", "nan h"], ["--episodes", str(2**70)], ["--shift", "previous"],
                  ["--window", "lifetime"])  # fmt: skip


@pytest.mark.timeout(300)
def test_any_window_from_the_line_page_or_packml_report_leaves_the_coordinator_up(
    tmp_path: Any, processes: Any
) -> None:
    """Issue 25 item 1: an unauthenticated ``GET /api/line?shift=9999-12-31%20early`` (any page
    the operator opens can send it) and ``packml report --shift '9999-12-31 early'`` ended the
    coordinator. A seeded fuzz of the line page's ``shift`` and of ``packml report``'s window
    options against a coordinator process and an HMI process: every answer a refusal or the
    data (never 500 or 503), every report exit 0, 1 (refused) or 2 (usage) with one line, the coordinator up."""
    import random
    import socket
    import subprocess
    import sys
    import urllib.parse

    import yaml

    from packml_ros2.testing.processes import wait_until
    from test.ros.cells import write_cell

    path, cell = write_cell(tmp_path, {"filler": {}, "packer": {}})
    doc = yaml.safe_load(path.read_text())
    doc["line"] = {"order": ["filler", "packer"], "timezone": "UTC", "shifts": {
        "early": {"start": "06:00", "end": "14:00"}, "late": {"start": "14:00", "end": "22:00"},
        "night": {"start": "22:00", "end": "06:00"}}}  # fmt: skip
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    coordinator = processes.module("coordinator", "packml_ros2.coordinator_node", str(path))
    hmi = processes.module("hmi", "packml_ros2.cli.main", "hmi", str(path), "--port", str(port))
    wait_until(lambda: "PackML HMI for cell" in hmi.output(), 60, what="the HMI serving")
    rng = random.Random(SEED)
    statuses: dict[int, int] = {}
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as client:
        # the coordinator's services are discovered by the HMI: wait for a first real answer
        wait_until(
            lambda: client.get("/api/line").status_code == 200, 60, 0.2, "the line page's data"
        )
        for i in range(LINE_QUERIES):
            if i == 0:
                shift = "9999-12-31 early"
            elif rng.random() < 0.6:
                shift = f"{rng.choice(SHIFT_DAYS)} {rng.choice(['early', 'night', 'x', 'a' * 61])}"
            else:
                shift = rng.choice(SHIFT_TEXT)
            query = "shift=" + (urllib.parse.quote(shift) if rng.random() < 0.8 else shift.replace(" ", "%20"))  # fmt: skip
            r = client.get(f"/api/line?{query}")
            assert r.status_code in (200, 400, 404), f"{shift!r}: {r.status_code} {r.text[:300]}"
            body = strict(r.text)
            if r.status_code != 200:
                assert body["accepted"] is False and 10 < len(body["message"]) < 500, body
            statuses[r.status_code] = statuses.get(r.status_code, 0) + 1
            assert coordinator.running(), coordinator.output()[-3000:]
    assert set(statuses) == {200, 400, 404}, statuses
    from concurrent.futures import ThreadPoolExecutor

    def report(options: list[str]) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "report", cell, *options],
                              capture_output=True, text=True, timeout=60, check=False)  # fmt: skip

    with ThreadPoolExecutor(3) as pool:
        results = list(pool.map(report, REPORT_OPTIONS))
    for options, result in zip(REPORT_OPTIONS, results, strict=True):
        assert result.returncode in (0, 1, 2), (
            options[:2],
            result.returncode,
            result.stderr[-2000:],
        )
        assert "Traceback" not in result.stderr, (options[:2], result.stderr[-2000:])
        if result.returncode:
            ours = [
                x for x in result.stderr.strip().splitlines() if "RTPS_" not in x
            ]  # (Fast DDS's own)
            assert len(ours) == 1 and ours[0].startswith("packml: "), (options[:2], result.stderr)
        assert coordinator.running(), coordinator.output()[-3000:]
    assert "Traceback" not in coordinator.output() + hmi.output(), (coordinator.output() + hmi.output())[-3000:]  # fmt: skip


def test_anonymous_event_streams_cannot_crowd_out_an_operator(ros: Any, tmp_path: Any) -> None:
    """Issue 25 item 11: 64 anonymous event streams made every operator page answer 503 until
    they closed. Now one address gets at most MAX_STREAMS_PER_CLIENT anonymous streams, all of
    them together leave OPERATOR_STREAMS to operators, and an operator who has logged in (a
    one-use ticket: EventSource sends no Authorization header) gets a stream; another site's
    page opens none."""
    import contextlib

    from packml_ros2.hmi.server import MAX_STREAMS, MAX_STREAMS_PER_CLIENT, OPERATOR_STREAMS

    cell = Cell(ros, tmp_path, TOKEN, 3.0)
    try:
        with serving(cell.bridge) as http, contextlib.ExitStack() as stack:
            base = str(http.base_url)
            readers: list[Any] = []

            def stream(address: str, query: str = "", **headers: str) -> httpx.Response:
                client = stack.enter_context(httpx.Client(
                    base_url=base, timeout=10, transport=httpx.HTTPTransport(local_address=address)))  # fmt: skip
                r = stack.enter_context(
                    client.stream("GET", f"/api/events{query}", headers=headers)
                )
                if r.status_code == 200:  # the snapshot: the stream is open
                    chunks = r.iter_text()
                    assert next(chunks).startswith("retry:"), address
                    readers.append(chunks)  # (a reader collected closes its stream)
                return r

            anonymous = MAX_STREAMS - OPERATOR_STREAMS
            for n in range(anonymous):
                address = f"127.0.0.{2 + n // MAX_STREAMS_PER_CLIENT}"
                assert stream(address).status_code == 200, n
                if n == MAX_STREAMS_PER_CLIENT - 1:  # this address has its share
                    assert stream(address).status_code == 429
            r = stream("127.0.0.99")
            assert r.status_code == 503, r.status_code  # every anonymous stream is taken
            assert r.read() and strict(r.text)["code"] == "TOO_MANY_STREAMS"
            # another site's page in the operator's browser opens none
            assert stream("127.0.0.1", Origin="http://evil.example").status_code == 403
            # the operator, logged in, gets one; a ticket is used once
            for _ in range(3):
                got = http.post("/api/events/ticket", headers={"Authorization": f"Bearer {TOKEN}"})
                assert got.status_code == 200, got.text
                ticket = got.json()["ticket"]
                assert stream("127.0.0.1", f"?ticket={ticket}").status_code == 200
                assert stream("127.0.0.1", f"?ticket={ticket}").status_code == 503  # used
            assert http.post("/api/events/ticket", headers={"Authorization": "Bearer wrong"}).status_code == 403  # fmt: skip
    finally:
        cell.close()
