"""Issues 7 and 17: the operator HMI in a real browser (Debian's headless Chromium driven by
Playwright) against a running demo-like cell: `packml launch <cell> --hmi` (units, simulated EMs,
coordinator and the HMI server), the page loaded over HTTP, buttons clicked like an operator
does, at the two screen sizes of an operator panel (1600x1000 and 1024x768).

Issue 17: a dead cell shown dead on every screen within the unit lease; state, diagram, commands
and mode on screen without scrolling at 1024x768; the diagram drawn from each unit's compiled
rules (model 2022 and 2015, the edges lit that the unit allows now, disabled states greyed);
user logins with levels; confirmation of Abort and of the resets; mode buttons and commands that
say why they are disabled; alarms, unacknowledged alarms and warnings in the banner; the cell not
shown STOPPED while a unit executes; the answer box not keeping an old answer.

Screenshots of the main screens go to $PACKML_SCREENSHOTS_DIR (`make screenshots` writes them to
docs/screenshots/), else to a temporary directory.

Every status of the Reset/Start sequence the test itself receives, or a newer one, must be
applied to the page (``window.__hmi.renders``, by the unit's stamps). No test here asserts a
duration measured on the wall clock (how fast is for benchmarks), and every wait is on a condition:
a line of the launcher's output, an event of the HMI's stream, a state of the page."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import signal
import sys
import time
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from packml_interfaces.msg import Status
from packml_interfaces.srv import Command, SetAlarm, SetRemoteCommands

from packml_ros2 import qos
from packml_ros2.core import Cmd, load_cell
from packml_ros2.core.numbers import ACTING, State
from packml_ros2.core.rules import rules_of
from packml_ros2.core.secrets import hash_password
from packml_ros2.testing.harness import Collector, RosHarness
from packml_ros2.testing.launched import Launched
from test.hmi.readable import contrast_failures, fit_failures

pytestmark = [pytest.mark.browser, pytest.mark.ros, pytest.mark.slow]

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
ROOT = Path(__file__).resolve().parents[2]
TOKEN = "line3-operator"
#: name -> (level, password): the users file of the test cell (hashes only)
USERS = {
    "anna": ("operator", "anna-pass-1"),
    "ben": ("maintenance", "ben-pass-22"),
    "carla": ("engineer", "carla-pass-333"),
}
SPEEDUP = 0.25  # the demo's simulated durations, shortened
LEASE = 3.0  # coordinator.unit_lease of the demo cell (its default)
BIG = {"width": 1600, "height": 1000}
PANEL = {"width": 1024, "height": 768}
SIZES = {"1600x1000": BIG, "1024x768": PANEL}
VIEWPORT = BIG
UNITS = ("robot_cell", "case_packer")
ACTING_NAMES = {s.name for s in ACTING}

if not CHROMIUM.exists():
    pytest.skip("Debian's chromium (/usr/bin/chromium) is not installed", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is missing")
expect = sync_api.expect
CURRENT = re.compile(r"\bcurrent\b")


# -- the cell --------------------------------------------------------------------------------------------
def demo_like_cell(tmp: Path) -> tuple[Path, str]:
    """config/demo_cell.yaml in a namespace of its own, faster, with persistence under ``tmp``,
    case_packer on the 2015 model with a complete_from of its own, and an HMI on a free port with
    user logins (a users file of password hashes)."""
    doc = yaml.safe_load((ROOT / "config" / "demo_cell.yaml").read_text())
    cell = f"hmi{os.getpid()}"
    doc["cell"] = cell
    doc["defaults"]["persistence"] = {"path": str(tmp / "{unit}.sqlite3")}
    for unit in doc["units"].values():
        for em in unit["equipment_modules"].values():
            sim = em["sim"]
            sim["durations"] = {
                k: round(v * SPEEDUP, 3) for k, v in sim.get("durations", {}).items()
            }
            sim["cycle_time"] = round(sim["cycle_time"] * SPEEDUP, 3)
            sim["lease"] = 3.0  # 10 nodes in one process on a busy 2-core machine: no false EM loss
            # case_packer runs on its own here (these tests stop robot_cell while it runs): the
            # demo's buffer fed by robot_cell would starve it (test/line covers that)
            sim.pop("fed_by", None)
            sim.pop("buffer", None)
        for key in ("mach_speed", "mach_design_speed"):  # OEE performance as in the real demo
            unit[key] = round(unit[key] / SPEEDUP, 3)
    doc["units"]["case_packer"]["model"] = "2015"
    doc["units"]["case_packer"]["complete_from"] = ["Execute", "Held"]  # its own: 2015 + Held
    users = {name: {"level": level, "password": hash_password(pw, iterations=1000)}
             for name, (level, pw) in USERS.items()}  # fmt: skip
    (tmp / "hmi-users.yaml").write_text(yaml.safe_dump({"users": users}))
    doc["hmi"] = {"host": "127.0.0.1", "port": 0, "users_file": "hmi-users.yaml",
                  "title": "Demo line"}  # fmt: skip
    path = tmp / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path, cell


def token_hmi_file(cell_file: Path) -> Path:
    """The same cell with one shared access token instead of users (a second HMI serves it)."""
    doc = yaml.safe_load(cell_file.read_text())
    (cell_file.parent / "hmi.token").write_text(TOKEN + "\n")  # pointed to, never written in
    doc["hmi"] = {"host": "127.0.0.1", "port": 0, "token": "file:hmi.token", "title": "Demo line"}
    path = cell_file.parent / "cell-token.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def launched_cell(cell_file: Path, log: Path, argv: list[str] | None = None) -> Launched:
    """`packml launch <cell> --hmi` (or ``argv``) in the background, its output waited on."""
    cli = [sys.executable, "-m", "packml_ros2.cli.main"]
    return Launched(argv or [*cli, "launch", str(cell_file), "--hmi"], log)


class Env:
    """What the tests share: the running cell, its HMI address, a ROS client, the browser."""

    def __init__(self, url: str, cell: str, cell_file: Path, launched: Launched, ros: RosHarness,
                 browser: Any, shots: Path) -> None:  # fmt: skip
        self.url = url
        self.cell = cell
        self.cell_file = cell_file
        self.launched = launched
        self.ros = ros
        self.browser = browser
        self.shots = shots
        self.status: dict[str, Collector[Status]] = {
            unit: ros.subscribe(Status, f"/{cell}/{unit}/status", qos.STATUS) for unit in UNITS
        }
        self.receipts: list[tuple[str, int, float]] = []  # unit, sequence, stamp ms
        for unit, collector in self.status.items():
            ros.node.create_subscription(
                Status, f"/{cell}/{unit}/status", self._receipt(unit), qos.STATUS
            )
            collector.wait_for(lambda m: True, 20, f"{unit} status")

    def _receipt(self, unit: str) -> Any:
        def note(msg: Status) -> None:
            stamp = msg.stamp.sec * 1000.0 + msg.stamp.nanosec / 1e6
            self.receipts.append((unit, msg.sequence, stamp))

        return note

    def page(self, user: str | None = "anna", hash_: str = "", size: dict[str, int] = BIG,
             url: str | None = None, token: str | None = None) -> Any:  # fmt: skip
        """A new page on ``hash_`` at ``size``, logged in as ``user`` (None: not logged in)."""
        page = self.browser.new_page()
        page.set_viewport_size(size)
        page.set_default_timeout(10_000)
        page.problems = []  # console errors, page errors, requests that leave the HMI server
        page.on(
            "console", lambda m: m.type == "error" and page.problems.append(f"console: {m.text}")
        )
        page.on("pageerror", lambda e: page.problems.append(f"page error: {e}"))
        base = (url or self.url).rstrip("/")
        page.on(
            "request", lambda r: r.url.startswith(base) or page.problems.append(f"request: {r.url}")
        )
        page.goto(f"{base}/{f'?token={token}' if token else ''}#/{hash_}")
        page.wait_for_selector("#nav a")
        if user:
            log_in(page, user)
        return page

    def shot(self, page: Any, name: str, full_page: bool = True) -> Path:
        page.mouse.move(0, 0)
        page.evaluate("document.getElementById('toast').hidden = true")
        path = self.shots / f"{name}.png"
        page.screenshot(path=str(path), full_page=full_page)
        return path

    def call_unit(self, unit: str, srv: Any, name: str, **fields: Any) -> Any:
        return self.ros.call(srv, f"/{self.cell}/{unit}/{name}", srv.Request(**fields))

    def rules(self, unit: str) -> Any:
        return rules_of(load_cell(self.cell_file).units[unit])


def log_in(page: Any, user: str, password: str | None = None) -> None:
    page.click("#login-btn")
    page.fill("#login-user", user)
    page.fill("#login-password", password or USERS[user][1])
    page.click("#login-submit")
    if password is None:
        expect(page.locator("#access-state")).to_have_text(f"{user} · {USERS[user][0]}")


def log_out(page: Any) -> None:
    page.click("#lock-btn")
    expect(page.locator("#access-state")).to_have_text("Read-only")


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory, ros_domain: int) -> Iterator[Env]:
    tmp = tmp_path_factory.mktemp("hmi_cell")
    shots = Path(os.environ.get("PACKML_SCREENSHOTS_DIR") or tmp_path_factory.mktemp("screenshots"))
    shots.mkdir(parents=True, exist_ok=True)
    cell_file, cell = demo_like_cell(tmp)
    launched = launched_cell(cell_file, tmp / "launch.log")
    ros = RosHarness(ros_domain)
    playwright = sync_api.sync_playwright().start()
    url = ""
    try:
        url = launched.wait_for(r"PackML HMI for cell \S+: (http://127\.0\.0\.1:\d+/)").group(1)
        launched.wait_for("is up")
        hmi_sees_every_unit(url)
        browser = playwright.chromium.launch_persistent_context(
            str(tmp / "chromium-profile"),
            executable_path=str(CHROMIUM),
            args=CHROMIUM_ARGS,
            headless=True,
            viewport=VIEWPORT,
        )
        try:
            yield Env(url, cell, cell_file, launched, ros, browser, shots)
        finally:
            browser.close()
    finally:
        playwright.stop()
        ros.close()
        with contextlib.suppress(ProcessLookupError):  # (a test may have frozen it)
            os.kill(launched.proc.pid, signal.SIGCONT)
        code = launched.stop()
        assert code == 0, f"packml launch exited {code}:\n{launched.output()[-3000:]}"
        assert "Traceback" not in launched.output(), launched.output()[-3000:]
        if url:  # Ctrl-C on the launcher stopped its HMI server too
            with pytest.raises(httpx.TransportError):
                httpx.get(url, timeout=2)


def stream_events(response: Any) -> Iterator[tuple[str, dict[str, Any]]]:
    """(event name, data) of a server-sent-events response, as they arrive (pings included)."""
    kind, data = "", ""
    for line in response.iter_lines():
        if line.startswith("event:"):
            kind = line.split(":", 1)[1].strip()
        elif line.startswith("data:"):
            data += line.split(":", 1)[1].strip()
        elif not line and kind:
            yield kind, json.loads(data) if data else {}
            kind, data = "", ""


def hmi_sees_every_unit(url: str, timeout: float = 20.0) -> None:
    """Wait until the HMI server has every unit's status and the coordinator's, each present (its
    bridge discovers the nodes on its own): its event stream, the snapshot then each change (the
    server pings every 5 s, so the deadline is looked at even when nothing changes)."""
    deadline = time.monotonic() + timeout
    units: dict[str, dict[str, Any]] = {}
    cell: dict[str, Any] = {}
    with httpx.stream("GET", f"{url}api/events", timeout=timeout) as response:
        for kind, data in stream_events(response):
            if kind == "snapshot":
                units = {
                    name: {"status": u["status"], "online": u["online"]}
                    for name, u in data["units"].items()
                }
                cell = {"cell": data["cell_status"], "coordinator": data["coordinator"]}
            elif kind == "update" and data["topic"] == "status":
                units[data["unit"]]["status"] = data["data"]
            elif kind == "update" and data["topic"] == "online":
                units[data["unit"]]["online"] = data["data"]["present"] is True
            elif kind == "update" and data["topic"] in ("cell", "coordinator"):
                cell[data["topic"]] = data["data"]
            missing = [n for n, u in units.items() if u["status"] is None or not u["online"]]
            if cell.get("cell") is None or not (cell.get("coordinator") or {}).get("present"):
                missing.append("coordinator")
            if units and not missing:
                return
            assert time.monotonic() < deadline, f"the HMI has no status of {missing}"


def background(page: Any, row: str) -> str:
    """The background colour of the alarm row ``row`` (a selector) once it is on the page (the
    list is redrawn on changes: read in the page, from the row there at that moment)."""
    colour = page.wait_for_function(
        "sel => { const r = document.querySelector(sel); "
        "return r && getComputedStyle(r.cells[2]).backgroundColor; }",
        arg=row,
    )
    return str(colour.json_value())


def no_problems(page: Any, allow: str = "") -> None:
    problems = [p for p in page.problems if not (allow and re.search(allow, p))]
    assert not problems, problems


def why(button: Any) -> str:
    """What a button that cannot act says (it is aria-disabled)."""
    expect(button).to_have_attribute("aria-disabled", "true")
    return str(button.get_attribute("data-why"))


def confirm(page: Any, answer: bool) -> str:
    """Answer the confirmation dialog; its question."""
    dialog = page.locator("#confirm")
    expect(dialog).to_be_visible()
    text = page.locator("#confirm-text").inner_text()
    page.click("#confirm-yes" if answer else "#confirm-no")
    expect(dialog).to_be_hidden()
    return text


def fits(page: Any) -> None:
    """The header is one row, and no table needs sideways scrolling in its card (at 1024x768 the
    nav wrapped to two rows when units were lost, and the EM table's last column was cut off)."""
    boxes = page.eval_on_selector_all(
        ".top .nav a, .top .access, .top .conn",
        "els => els.map(e => { const r = e.getBoundingClientRect(); "
        "return [e.textContent.trim(), r.left, (r.top + r.bottom) / 2, r.right]; })",
    )  # fmt: skip
    middles = [middle for _, _, middle, _ in boxes]
    assert max(middles) - min(middles) < 4, f"the header wraps: {boxes}"
    for (a, _, _, right), (b, left, _, _) in itertools.pairwise(boxes):
        assert right <= left + 1, f"{a!r} overlaps {b!r}: {boxes}"
    assert boxes[-1][3] <= page.viewport_size["width"], boxes
    cut = page.eval_on_selector_all(
        ".screen:not([hidden]) .table-wrap",
        "els => els.filter(e => e.scrollWidth > e.clientWidth + 1)"
        ".map(e => [e.parentElement.querySelector('h2')?.textContent, e.scrollWidth, e.clientWidth])",
    )  # fmt: skip
    assert not cut, f"tables cut off: {cut}"


def in_view(page: Any, selector: str, size: dict[str, int]) -> None:
    """Every element ``selector`` matches is entirely on screen, without scrolling."""
    assert page.evaluate("[window.scrollX, window.scrollY]") == [0, 0]
    boxes = page.eval_on_selector_all(
        selector, "els => els.map(e => { const r = e.getBoundingClientRect(); "
                  "return [e.id || e.textContent.trim(), r.left, r.top, r.right, r.bottom]; })",
    )  # fmt: skip
    assert boxes, selector
    for name, left, top, right, bottom in boxes:
        assert left >= 0 and top >= 0, (selector, name, left, top)
        assert right <= size["width"] and bottom <= size["height"], (
            selector,
            name,
            right,
            bottom,
            size,
        )


def edges_shown(page: Any) -> set[tuple[str, str | None, str]]:
    return {
        tuple(e)
        for e in page.evaluate(
            "async () => (await import('/static/diagram.js'))"
            ".edgesShown(document.getElementById('diagram'))"
        )
    }  # type: ignore[misc]


def lit_edges(page: Any, state: str) -> set[tuple[str, str | None, str]]:
    """(from, command or None, to) of every edge drawn lit in ``state`` (a box's arrow: from
    ``state``)."""
    keys = page.eval_on_selector_all(
        "#diagram path.edge.possible", "els => els.map(e => e.dataset.key)"
    )
    out = set()
    for key in keys:
        for k in key.split(" "):
            frm, cmd, to = k.split("|")
            out.add((state if frm == "*" else frm, cmd or None, to))
    return out


def possible_now(env: Env, unit: str, state: str) -> set[tuple[str, str | None, str]]:
    """What the unit's rules allow from ``state`` in PRODUCTION with the commands it lists as
    valid now (and State Complete in an acting state)."""
    status = env.status[unit].last
    assert status.state_current_name == state
    valid = set(status.commands_valid_names)
    edges = env.rules(unit).available_transitions(1, State[state])
    return {(e.from_state.name, e.trigger.name if e.trigger else None, e.to_state.name)
            for e in edges if (e.trigger.name in valid if e.trigger else status.state_current_name in ACTING_NAMES)}  # fmt: skip


# -- the tests -------------------------------------------------------------------------------------------
def test_reset_and_start_by_buttons_the_diagram_and_banner_follow_every_status(env: Env) -> None:
    page = env.page(hash_="unit/robot_cell")
    assert page.locator("#diagram .st").count() == 17  # every PackML state is drawn
    expect(page.locator("#st-STOPPED")).to_have_class(CURRENT)
    expect(page.locator("#banner-scope")).to_have_text("robot_cell")
    expect(page.locator("#banner-mode")).to_have_text("PRODUCTION (1)")
    expect(page.locator("#banner-state")).to_contain_text("STOPPED")
    buttons = page.locator("#u-cmds button")
    expect(buttons.first).to_have_attribute("aria-disabled", "false")
    enabled = [b.get_attribute("data-cmd") for b in buttons.all() if b.is_enabled()]
    assert enabled == ["RESET", "ABORT"]  # only the commands valid now

    first = len(env.receipts)
    page.click("#u-cmds button[data-cmd=RESET]")
    expect(page.locator("#st-IDLE")).to_have_class(CURRENT, timeout=10_000)
    expect(page.locator("#banner-state")).to_contain_text("IDLE")
    expect(page.locator("#u-feedback")).to_contain_text("RESET accepted")
    expect(page.locator("#u-feedback")).to_have_class(re.compile(r"\baccepted\b"))
    expect(page.locator("#u-feedback")).to_contain_text("anna")  # who did it
    expect(page.locator("#u-cmds button[data-cmd=START]")).to_be_enabled()
    page.click("#u-cmds button[data-cmd=START]")
    expect(page.locator("#st-EXECUTE")).to_have_class(CURRENT, timeout=10_000)
    expect(page.locator("#banner-state")).to_contain_text("EXECUTE")
    expect(page.locator("#u-cmds button[data-cmd=START]")).to_be_disabled()
    env.status["robot_cell"].wait_for(lambda m: m.state_current_name == "EXECUTE", 10)

    # every status on the way (received by this test) is applied to the page, or a newer one. Status
    # keeps only its newest message (latched, depth 1): one superseded a few ms later may never
    # reach the page, and need not. (How fast: a benchmark's question, not a test's.)
    renders = page.evaluate("window.__hmi.renders")
    seen = [r for r in env.receipts[first:] if r[0] == "robot_cell"]
    for unit, seq, stamp in seen:
        newer = [r for r in renders if r["unit"] == unit and r["stamp"] > stamp - 0.01]
        assert newer, f"status {seq} ({stamp}) nor a newer one rendered: {renders[-12:]}"
    states = [
        r["state"] for r in renders if r["unit"] == "robot_cell" and r["stamp"] > seen[0][2] - 0.01
    ]
    assert {"RESETTING", "IDLE", "STARTING", "EXECUTE"} <= set(states), states

    # where Execute goes when the run is finished: the unit's rules say (its edges), not the page
    expect(page.locator("#u-progress")).to_have_text(
        "EXECUTE: producing · leaves by a command, or to COMPLETING when the run is finished "
        "(state complete)"
    )
    # the diagram: the acting state in progress, transitions valid now, no disabled state in PRODUCTION
    assert "acting" in page.get_attribute("#st-EXECUTE", "class")
    assert page.locator("#diagram .st.disabled").count() == 0

    # Production counts arrive; the unit screen shows counters, OEE, EMs, times
    expect(page.locator("#u-counters")).to_contain_text("parts inspected")
    expect(page.locator("#u-ems tbody tr")).to_have_count(5)
    expect(page.locator("#u-times")).to_contain_text("EXECUTE")

    # the second unit from its own screen, then the overview with both running
    page.click("#nav a[data-unit=case_packer]")
    expect(page.locator("#banner-scope")).to_have_text("case_packer")
    page.click("#u-cmds button[data-cmd=RESET]")
    expect(page.locator("#u-cmds button[data-cmd=START]")).to_be_enabled(timeout=10_000)
    page.click("#u-cmds button[data-cmd=START]")
    expect(page.locator("#st-EXECUTE")).to_have_class(CURRENT, timeout=10_000)
    page.click("#nav a[data-screen=overview]")
    expect(page.locator("#banner-scope")).to_have_text("Cell Demo line")  # hmi.title
    expect(page.locator("#banner-state")).to_contain_text("EXECUTE", timeout=10_000)
    cards = page.locator("[data-unit-card]")
    expect(cards).to_have_count(2)
    expect(cards.nth(0)).to_contain_text("EXECUTE")
    expect(cards.nth(1)).to_contain_text("EXECUTE")
    expect(page.locator("#coordinator-state")).to_have_text("Coordinator running")
    expect(page.locator("#cell-cmds button", has_text="STOP")).to_be_enabled()
    env.shot(page, "hmi-overview", full_page=False)
    page.click("[data-unit-card=robot_cell]")
    expect(page.locator("#banner-scope")).to_have_text("robot_cell")
    expect(page.locator("#u-transitions")).to_contain_text("hmi:anna")  # who, as the source
    env.shot(page, "hmi-unit")
    no_problems(page)
    page.close()


@pytest.mark.parametrize("size", SIZES.values(), ids=SIZES.keys())
def test_a_panel_shows_state_diagram_commands_and_mode_without_scrolling(env: Env,
                                                                        size: dict[str, int]) -> None:  # fmt: skip
    # (at 1024x768 the command buttons started below the fold and the mode selector 970 px
    # down: the unit screen was one column 3 386 px tall)
    page = env.page(hash_="unit/robot_cell", size=size)
    for unit in UNITS:
        page.click(f"#nav a[data-unit={unit}]")
        expect(page.locator("#banner-scope")).to_have_text(unit)
        expect(page.locator("#banner-state")).to_contain_text("EXECUTE")
        in_view(page, "#banner-state, #banner-mode, #diagram, #u-cmds button, #u-modes button, "
                      "#u-feedback, #access-state, #lock-btn", size)  # fmt: skip
        assert page.evaluate("document.documentElement.scrollWidth") <= size["width"]
        fits(page)
    if size is PANEL:
        env.shot(page, "hmi-unit-1024x768", full_page=False)
    no_problems(page)
    page.close()


@pytest.mark.parametrize("size", SIZES.values(), ids=SIZES.keys())
def test_the_diagram_is_drawn_from_the_units_own_rules(env: Env, size: dict[str, int]) -> None:
    page = env.page(hash_="unit/robot_cell", size=size)
    extra_2022 = {("SUSPENDED", "HOLD", "HOLDING"), ("HELD", "COMPLETE", "COMPLETING"),
                  ("SUSPENDED", "COMPLETE", "COMPLETING")}  # fmt: skip
    for unit, model in (("robot_cell", "2022"), ("case_packer", "2015")):
        page.click(f"#nav a[data-unit={unit}]")
        expect(page.locator("#diagram")).to_have_attribute(
            "aria-label", re.compile(f"{unit} .model {model}")
        )
        rules = {(e.from_state.name, e.trigger.name if e.trigger else None, e.to_state.name)
                 for e in env.rules(unit).edges()}  # fmt: skip
        shown = edges_shown(page)
        assert shown == rules, (unit, sorted(shown ^ rules))  # exactly the rules' transitions
        assert (extra_2022 <= shown) is (model == "2022"), unit
        # case_packer's own complete_from adds Held -> Completing to its 2015 model
        assert ("HELD", "COMPLETE", "COMPLETING") in shown, unit
        assert (("SUSPENDED", "COMPLETE", "COMPLETING") in shown) is (model == "2022"), unit
        # in EXECUTE (PRODUCTION) the edges the unit can take now are lit: its valid commands
        # and State Complete (EXECUTE completes the run)
        expect(page.locator("#st-EXECUTE")).to_have_class(CURRENT)
        expected = possible_now(env, unit, "EXECUTE")
        assert ("EXECUTE", None, "COMPLETING") in expected and len(expected) >= 5, expected
        assert lit_edges(page, "EXECUTE") == expected, (unit, lit_edges(page, "EXECUTE") ^ expected)
    if size is BIG:
        # Suspended: HOLD is valid there in TR88-2022 and its edge lights (it did not: issue 17)
        page.click("#nav a[data-unit=robot_cell]")
        page.click("#u-cmds button[data-cmd=SUSPEND]")
        expect(page.locator("#st-SUSPENDED")).to_have_class(CURRENT, timeout=10_000)
        expect(page.locator("#u-cmds button[data-cmd=HOLD]")).to_be_enabled()
        lit = lit_edges(page, "SUSPENDED")
        assert lit == possible_now(env, "robot_cell", "SUSPENDED"), lit
        assert {("SUSPENDED", "HOLD", "HOLDING"), ("SUSPENDED", "COMPLETE", "COMPLETING"),
                ("SUSPENDED", "UNSUSPEND", "UNSUSPENDING")} <= lit, lit  # fmt: skip
        env.shot(page, "hmi-diagram-suspended", full_page=False)
        page.click("#u-cmds button[data-cmd=UNSUSPEND]")
        expect(page.locator("#st-EXECUTE")).to_have_class(CURRENT, timeout=10_000)
    no_problems(page)
    page.close()


def test_mode_buttons_say_why_a_change_is_not_allowed(env: Env) -> None:
    seq = env.status["robot_cell"].last.sequence
    for size in (PANEL, BIG):  # (BIG last: it goes on below)
        page = env.page(user="ben", hash_="unit/robot_cell", size=size)
        expect(page.locator("#banner-state")).to_contain_text("EXECUTE")
        expect(page.locator("#lamp-mode-refused")).to_have_attribute("data-on", "false")
        maintenance = page.locator("#u-modes button[data-mode='2']")
        reason = why(maintenance)  # the unit's own rule (Rules.mode_change_refusal), not sent
        assert "not allowed in EXECUTE: PRODUCTION allows mode changes only in" in reason, reason
        assert "STOPPED" in reason and "IDLE" in reason
        assert "is the current mode" in why(page.locator("#u-modes button[data-mode='1']"))
        maintenance.click(force=True)  # a tap on a grey button shows why, and sends nothing
        feedback = page.locator("#u-feedback")
        expect(feedback).to_have_attribute("data-state", "local")
        expect(feedback).to_contain_text("NOT SENT")
        expect(feedback).to_contain_text("not allowed in EXECUTE")
        expect(page.locator("#u-mode-why")).to_contain_text("allows mode changes only in")
        in_view(page, "#u-feedback, #u-mode-why", size)
        if size is PANEL:
            no_problems(page)
            page.close()
    # the server refuses it too, with the same reason, and the unit lights its lamp for 3 s
    answer = page.evaluate("""async () => {
        const r = await fetch('/api/units/robot_cell/set_mode', {method: 'POST', headers: {
            'Content-Type': 'application/json',
            Authorization: 'Bearer ' + sessionStorage.getItem('packml-hmi-credential')},
            body: JSON.stringify({mode: 2})});
        return r.json(); }""")
    assert answer["result_name"] == "MODE_CHANGE_NOT_ALLOWED", answer
    expect(page.locator("#lamp-mode-refused")).to_have_attribute("data-on", "true")
    expect(page.locator("#banner-mode")).to_have_text("PRODUCTION (1)")  # nothing changed
    assert env.status["robot_cell"].last.unit_mode_current == 1
    assert env.status["robot_cell"].last.sequence == seq
    no_problems(page)
    page.close()


def test_alarms_warnings_and_disabled_commands_say_why(env: Env) -> None:
    page = env.page(hash_="unit/robot_cell")
    banner = page.locator("#banner-alarm")
    expect(banner).to_have_class(re.compile(r"\bok\b"))
    # a warning alone: in the banner (it said "No active alarm")
    env.call_unit("robot_cell", SetAlarm, "set_alarm", id=301, active=True, warning=True,
                  category=-1, source="operator:test")  # fmt: skip
    expect(banner).to_have_class(re.compile(r"\bwarn\b"))
    expect(banner).to_contain_text("WARNING 301/0 Vision lighting degraded")
    raised = env.call_unit("robot_cell", SetAlarm, "set_alarm", id=201, active=True, category=-1,
                           source="operator:test")  # fmt: skip
    assert raised.accepted, raised.message_out
    expect(banner).to_have_class(re.compile(r"\bactive\b"))
    expect(banner).to_contain_text("Gripper vacuum lost")
    expect(page.locator("#st-STOPPED")).to_have_class(CURRENT, timeout=10_000)

    # RESET is refused by the unit's rules while the alarm (reaction STOP) is active: it says so
    reset = page.locator("#u-cmds button[data-cmd=RESET]")
    expect(reset).to_be_disabled()
    expect(reset).to_have_attribute(
        "data-why", re.compile(r'RESET refused in STOPPED.*alarm 201/0 "Gripper vacuum lost"')
    )
    expect(page.locator("#u-why")).to_contain_text("Gripper vacuum lost")
    assert "START not allowed in STOPPED" in why(page.locator("#u-cmds button[data-cmd=START]"))
    expect(page.locator("#u-cmds button[data-cmd=ABORT]")).to_be_enabled()
    env.shot(page, "hmi-unit-alarm", full_page=False)
    # the same on an operator panel, on screen without scrolling
    panel = env.page(hash_="unit/robot_cell", size=PANEL)
    expect(panel.locator("#banner-alarm")).to_contain_text("Gripper vacuum lost")
    expect(panel.locator("#u-cmds button[data-cmd=RESET]")).to_have_attribute(
        "data-why", re.compile(r'RESET refused in STOPPED.*alarm 201/0 "Gripper vacuum lost"')
    )
    expect(panel.locator("#u-why")).to_contain_text("Gripper vacuum lost")
    in_view(panel, "#banner-alarm, #u-why, #u-cmds button", PANEL)
    no_problems(panel)
    panel.close()

    page.click("#nav a[data-screen=alarms]")
    row_at = "[data-alarm-unit=robot_cell] tr[data-alarm='201/0']"
    row = page.locator(row_at)
    expect(row).to_have_attribute("data-operator-state", "0")  # active, unacknowledged: red
    expect(row).to_contain_text("Gripper vacuum lost")
    expect(page.locator("[data-alarm-unit=robot_cell]")).to_contain_text("Vision lighting degraded")
    expect(banner).to_contain_text("robot_cell: ALARM 201/0")  # every screen has the banner
    red = background(page, row_at)
    env.shot(page, "hmi-alarms")

    env.call_unit("robot_cell", SetAlarm, "set_alarm", id=201, active=False, category=-1,
                  source="operator:test")  # fmt: skip
    expect(row).to_have_attribute("data-operator-state", "1")  # inactive, unacknowledged: amber
    amber = background(page, row_at)
    # cleared but not acknowledged: the banner says so (it said "No active alarm")
    expect(banner).to_have_class(re.compile(r"\bunack\b"))
    expect(banner).to_contain_text("not acknowledged")
    row.locator("button", has_text="Ack").click()
    expect(row).to_have_attribute("data-operator-state", "2")  # acknowledged
    acked = background(page, row_at)
    assert len({red, amber, acked}) == 3, (red, amber, acked)
    expect(row.locator("button", has_text="Ack")).to_be_disabled()
    expect(row).not_to_contain_text("–")  # acknowledged at a time now shown
    expect(banner).to_have_class(re.compile(r"\bwarn\b"))  # the warning is still active
    # resetting alarms asks first
    reset_alarms = page.locator("[data-alarm-unit=robot_cell] button:has-text('Reset alarms')")
    reset_alarms.click()
    assert "Reset the alarms of robot_cell" in confirm(page, False)
    expect(row).to_have_count(1)  # nothing sent
    reset_alarms.click()
    confirm(page, True)
    expect(row).to_have_count(0)
    env.call_unit("robot_cell", SetAlarm, "set_alarm", id=301, active=False, warning=True,
                  category=-1, source="operator:test")  # fmt: skip
    expect(banner).to_have_class(re.compile(r"\bok\b"))
    expect(banner).to_have_text("No active alarm")
    no_problems(page)
    page.close()


@pytest.mark.parametrize("size", SIZES.values(), ids=SIZES.keys())
def test_the_cell_is_not_shown_stopped_while_a_unit_executes(
    env: Env, size: dict[str, int]
) -> None:
    # robot_cell stopped by its alarm, case_packer in EXECUTE: the coordinator's aggregate is the
    # most severe state (STOPPED); the page shows the units as they are
    env.status["robot_cell"].wait_for(lambda m: m.state_current_name == "STOPPED", 10)
    env.status["case_packer"].wait_for(lambda m: m.state_current_name == "EXECUTE", 10)
    page = env.page(hash_="overview", size=size)
    expect(page.locator("#banner-state")).to_have_text("MIXED")
    expect(page.locator("#cell-state")).to_have_text("MIXED")
    expect(page.locator("#cell-parts")).to_contain_text("STOPPED: robot_cell")
    expect(page.locator("#cell-parts")).to_contain_text("EXECUTE: case_packer")
    expect(page.locator("#ov-cell")).not_to_contain_text("STOPPED 2")
    # the cell's commands are greyed as the server says (the cell status' why, from the
    # coordinator's status), not by rules of the page's own: RESET is not valid for the cell (all
    # or nothing: case_packer executes), STOP is (some unit takes it)
    reasons = httpx.get(f"{env.url}api/snapshot", timeout=5).json()["cell_status"]["why"]
    assert "RESET" in reasons and "STOP" not in reasons and "ABORT" not in reasons, reasons
    for b in page.locator("#cell-cmds button").all():
        expect(b).to_have_attribute("data-why", reasons.get(b.inner_text(), ""))
    if size is BIG:
        env.shot(page, "hmi-overview-mixed", full_page=False)
    no_problems(page)
    page.close()


def test_user_levels_decide_who_may_do_what(env: Env) -> None:
    page = env.page(user=None, hash_="unit/robot_cell")
    expect(page.locator("#access-state")).to_have_text("Read-only")
    assert "log in to operate" in why(page.locator("#u-cmds button[data-cmd=ABORT]"))
    log_in(page, "anna", "wrong-password")
    expect(page.locator("#access-error")).to_contain_text("wrong user name or password")
    page.click("#login-cancel")

    # anna, operator: commands yes; modes and resets of records no (page and server)
    log_in(page, "anna")
    expect(page.locator("#u-cmds button[data-cmd=RESET]")).to_be_enabled()
    # the reasons every page shares are judged for hmi:<user>; each page names its own user
    lock = partial(env.call_unit, "robot_cell", SetRemoteCommands, "set_remote_commands", source="operator")  # fmt: skip
    assert lock(enabled=False).accepted
    try:
        expect(page.locator("#u-cmds button[data-cmd=RESET]")).to_have_attribute(
            "data-why", re.compile(r"^RESET from hmi:anna refused: remote commands are disabled")
        )
    finally:
        assert lock(enabled=True).accepted
    expect(page.locator("#u-cmds button[data-cmd=RESET]")).to_be_enabled()
    assert "needs the maintenance level (anna is operator)" in why(
        page.locator("#u-modes button[data-mode='3']")
    )
    assert "needs the engineer level" in why(page.locator("#u-counter-keys button"))
    answer = page.evaluate("""async () => {
        const r = await fetch('/api/units/robot_cell/reset_counters', {method: 'POST', headers: {
            'Content-Type': 'application/json',
            Authorization: 'Bearer ' + sessionStorage.getItem('packml-hmi-credential')}, body: '{}'});
        return {status: r.status, body: await r.json()}; }""")
    assert answer["status"] == 403 and answer["body"]["code"] == "LEVEL_TOO_LOW", answer
    log_out(page)

    # ben, maintenance: a mode change (recorded as hmi:ben); MAINTENANCE greys the Suspend states
    log_in(page, "ben")
    # switching an EM: in PRODUCTION the unit would refuse, and the button says so in its words
    em_switch = page.locator("#u-ems button").first
    reason = why(em_switch)
    assert "can be switched inactive only outside PRODUCTION (now PRODUCTION, STOPPED)" in reason
    page.click("#u-modes button[data-mode='2']")
    expect(page.locator("#banner-mode")).to_have_text("MAINTENANCE (2)", timeout=10_000)
    expect(em_switch).to_have_attribute("aria-disabled", "false")
    disabled = {s.name for s in load_cell(env.cell_file).units["robot_cell"].modes[2].disabled}
    expect(page.locator("#diagram .st.disabled")).to_have_count(len(disabled))
    for state in disabled:
        expect(page.locator(f"#st-{state}")).to_have_class(re.compile(r"\bdisabled\b"))
    assert "SUSPEND not allowed in STOPPED" in why(page.locator("#u-cmds button[data-cmd=SUSPEND]"))
    expect(page.locator("#u-transitions")).to_contain_text("hmi:ben")
    env.shot(page, "hmi-unit-maintenance", full_page=False)
    page.click("#u-modes button[data-mode='1']")
    expect(page.locator("#banner-mode")).to_have_text("PRODUCTION (1)", timeout=10_000)
    assert "needs the engineer level" in why(page.locator("#u-counter-keys button"))
    log_out(page)

    # carla, engineer: resets of counters and times, each asked first
    log_in(page, "carla")
    counters = page.locator("#u-counter-keys button")
    counters.click()
    assert "Reset the counters of robot_cell" in confirm(page, False)
    expect(page.locator("#u-feedback")).not_to_contain_text("reset_counters")
    counters.click()
    confirm(page, True)
    expect(page.locator("#u-feedback")).to_have_class(re.compile(r"\baccepted\b"))
    page.locator("#u-time-keys button").first.click()
    assert "times of the PRODUCTION mode" in confirm(page, True)
    expect(page.locator("#u-feedback")).to_have_class(re.compile(r"\baccepted\b"))
    no_problems(page, allow=r"status of 40[03]")  # the refusals this test provoked
    page.close()


def test_abort_asks_first_and_the_answer_box_forgets_old_answers(env: Env) -> None:
    page = env.page(hash_="unit/robot_cell", size=PANEL)
    expect(page.locator("#st-STOPPED")).to_have_class(CURRENT)
    seq = env.status["robot_cell"].last.sequence
    page.click("#u-cmds button[data-cmd=ABORT]")
    assert confirm(page, False).startswith("Abort robot_cell?")
    assert env.status["robot_cell"].last.sequence == seq  # nothing sent
    expect(page.locator("#st-STOPPED")).to_have_class(CURRENT)
    page.evaluate("window.__hmi.feedbackMs = 2000")
    page.click("#u-cmds button[data-cmd=ABORT]")
    confirm(page, True)
    expect(page.locator("#st-ABORTED")).to_have_class(CURRENT, timeout=10_000)
    feedback = page.locator("#u-feedback")
    expect(feedback).to_contain_text("ABORT accepted")
    # a few seconds later the box is empty again: an old answer is not today's news
    expect(feedback).to_have_attribute("data-state", "empty", timeout=5_000)
    expect(feedback).not_to_contain_text("ABORT")
    page.click("#u-cmds button[data-cmd=CLEAR]")
    expect(page.locator("#st-STOPPED")).to_have_class(CURRENT, timeout=10_000)
    # the cell's Abort asks too
    page.click("#nav a[data-screen=overview]")
    page.locator("#cell-cmds button", has_text="ABORT").click()
    assert "the whole cell" in confirm(page, False)
    assert env.status["case_packer"].last.state_current_name == "EXECUTE"
    no_problems(page)
    page.close()


def test_read_only_without_the_token(env: Env) -> None:
    # the same cell served by a second HMI with one shared access token instead of users
    other = launched_cell(env.cell_file, env.cell_file.parent / "hmi-token.log",
                     [sys.executable, "-m", "packml_ros2.cli.main", "hmi",
                      str(token_hmi_file(env.cell_file))])  # fmt: skip
    try:
        url = other.wait_for(r"PackML HMI for cell \S+: (http://127\.0\.0\.1:\d+/)").group(1)
        hmi_sees_every_unit(url)
        page = env.page(user=None, hash_="unit/robot_cell", url=url)
        expect(page.locator("#access-state")).to_have_text("Read-only")
        expect(page.locator("#u-ro")).to_contain_text("read-only")
        expect(page.locator("#banner-state")).to_contain_text("STOPPED")
        for b in page.locator("#u-cmds button, #u-modes button").all():
            expect(b).to_be_disabled()
        # the server refuses, too (not only the page)
        answer = page.evaluate("""async () => {
            const r = await fetch('/api/units/robot_cell/command', {method: 'POST',
                headers: {'Content-Type': 'application/json'}, body: JSON.stringify({command: 'reset'})});
            return {status: r.status, body: await r.json()};
        }""")
        assert answer["status"] == 403 and "read-only" in answer["body"]["message"], answer
        assert env.status["robot_cell"].last.state_current_name == "STOPPED"

        page.click("#login-btn")
        page.fill("#token-input", "guess")
        page.click("#login-submit")
        expect(page.locator("#access-error")).to_contain_text("wrong access token")
        page.click("#login-cancel")
        expect(page.locator("#u-cmds button[data-cmd=RESET]")).to_be_disabled()
        page.click("#login-btn")
        page.fill("#token-input", TOKEN)
        page.click("#login-submit")
        expect(page.locator("#access-state")).to_have_text("Operating")
        expect(page.locator("#u-cmds button[data-cmd=RESET]")).to_be_enabled()
        page.click("#u-cmds button[data-cmd=RESET]")
        expect(page.locator("#st-IDLE")).to_have_class(CURRENT, timeout=10_000)
        expect(page.locator("#u-transitions")).to_contain_text("hmi:token")
        no_problems(page, allow=r"status of 403")  # the refusals this test provoked
        page.close()
    finally:
        assert other.stop() == 0


WINDOWS = {
    "1024x768": PANEL,
    "1366x768": {"width": 1366, "height": 768},
    "1920x1080": {"width": 1920, "height": 1080},
    "390x844": {"width": 390, "height": 844},
}
PHONE = WINDOWS["390x844"]


def test_every_screen_is_readable_and_fits_at_four_sizes_with_an_active_alarm(env: Env) -> None:
    """Logged in, robot_cell stopped by an active alarm, case_packer held (amber): every visible
    text of every screen (overview, both units, alarms, line) has WCAG AA contrast against its
    background, nothing is wider than the window, no command is cut; on the desk and panel
    sizes the header is one row and a unit's commands are on screen without scrolling."""
    raised = env.call_unit("robot_cell", SetAlarm, "set_alarm", id=201, active=True, category=-1,
                           source="operator:test")  # fmt: skip
    assert raised.accepted, raised.message_out
    packer = env.status["case_packer"]
    for cmd, state in ((Cmd.RESET, "IDLE"), (Cmd.START, "EXECUTE")):  # (when run alone)
        if packer.last.state_current_name in ("STOPPED", "IDLE"):
            env.call_unit("case_packer", Command, "command", command=int(cmd), source="operator:test")  # fmt: skip
            packer.wait_for(lambda m, s=state: m.state_current_name == s, 15, state)
    held = env.call_unit("case_packer", Command, "command", command=int(Cmd.HOLD), source="operator:test")  # fmt: skip
    assert held.accepted, held.message
    env.status["case_packer"].wait_for(lambda m: m.state_current_name == "HELD", 10, "held")
    try:
        problems: dict[str, Any] = {}
        for name, size in WINDOWS.items():
            page = env.page(hash_="overview", size=size)
            for screen in ("overview", "unit/robot_cell", "unit/case_packer", "alarms", "line"):
                if screen == "line":
                    page.goto(env.url.rstrip("/") + "/line")
                    expect(page.locator("#kpis .kpi")).to_have_count(4)
                else:
                    page.evaluate(f"location.hash = '#/{screen}'")
                    expect(page.locator(f"#screen-{screen.split('/')[0]}")).to_be_visible()
                    if screen != "unit/case_packer":  # (its banner is its own: held, no alarm)
                        expect(page.locator("#banner-alarm")).to_have_class(
                            re.compile(r"\bactive\b")
                        )
                    expect(page.locator("#access-state")).to_have_text("anna · operator")
                if screen.startswith("unit/"):
                    expect(page.locator("#u-cmds button").first).to_be_visible()
                    if size is not PHONE:
                        in_view(page, "#u-cmds button", size)
                if size is not PHONE and screen != "line":
                    fits(page)
                where = f"{name} {screen}"
                if bad := contrast_failures(page):
                    problems[f"{where}: contrast"] = bad
                if bad := fit_failures(page):
                    problems[f"{where}: fit"] = bad
            no_problems(page)
            page.close()
        assert not problems, json.dumps(problems, indent=1)
    finally:
        env.call_unit("case_packer", Command, "command", command=int(Cmd.UNHOLD), source="operator:test")  # fmt: skip
        env.call_unit("robot_cell", SetAlarm, "set_alarm", id=201, active=False, category=-1,
                      source="operator:test")  # fmt: skip


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def test_a_dead_cell_is_shown_dead_on_every_screen_within_its_lease(env: Env) -> None:
    # (last: the cell is frozen, and its units abort when they run again: their EMs were silent)
    pages = {
        "unit": env.page(hash_="unit/robot_cell", size=PANEL),
        "overview": env.page(hash_="overview", size=BIG),
        "alarms": env.page(hash_="alarms", size=PANEL),
        "unit-big": env.page(hash_="unit/case_packer", size=BIG),
    }
    for page in pages.values():
        expect(page.locator("#nav a.lost")).to_have_count(0)
    expect(pages["overview"].locator("#coordinator-state")).to_have_text("Coordinator running")
    # the whole cell stops answering (a frozen process: like a cable pulled or a host hung)
    os.kill(env.launched.proc.pid, signal.SIGSTOP)
    try:
        unit = pages["unit"]
        expect(unit.locator("#banner-alarm")).to_have_class(
            re.compile(r"\blost\b"), timeout=(LEASE + 3) * 1000
        )
        # lost by its lease (DDS liveliness, the unit's own), not by a timer of the page's
        expect(unit.locator("#banner-alarm")).to_contain_text(
            f"no sign of life for {LEASE:g} s (unit_lease)"
        )
        expect(unit.locator("#banner-alarm")).to_contain_text("COMMUNICATION LOST since")
        expect(unit.locator("#u-lost")).to_be_visible()
        expect(unit.locator("#screen-unit")).to_have_class(re.compile(r"\bstale\b"))
        for b in unit.locator("#u-cmds button, #u-modes button").all():
            assert "COMMUNICATION LOST" in why(b)
        expect(unit.locator("#u-ems tbody")).not_to_contain_text("online")
        expect(unit.locator("#diagram path.edge.possible")).to_have_count(0)
        expect(unit.locator("#nav a.lost")).to_have_count(2)
        env.shot(unit, "hmi-lost-1024x768", full_page=False)
        fits(unit)
        big = pages["unit-big"]
        expect(big.locator("#banner-alarm")).to_contain_text("COMMUNICATION LOST since")
        expect(big.locator("#u-lost")).to_be_visible()

        ov = pages["overview"]
        expect(ov.locator("#coordinator-state")).to_contain_text(
            "COMMUNICATION LOST since", timeout=3000
        )
        expect(ov.locator("#coordinator-state")).not_to_contain_text("running")
        for name in UNITS:
            card = ov.locator(f"[data-unit-card={name}]")
            expect(card).to_have_class(re.compile(r"\bstale\b"))
            expect(card).to_contain_text("COMMUNICATION LOST since")
            expect(card).to_contain_text("lost")
        for b in ov.locator("#cell-cmds button").all():
            assert "COMMUNICATION LOST" in why(b)
        expect(ov.locator("#banner-state")).to_have_text("LOST")
        env.shot(ov, "hmi-overview-lost", full_page=False)

        alarms = pages["alarms"]
        expect(alarms.locator("[data-alarm-unit=robot_cell] .lost-line")).to_contain_text(
            "COMMUNICATION LOST since"
        )
        expect(alarms.locator("#banner-alarm")).to_have_class(re.compile(r"\blost\b"))
    finally:
        os.kill(env.launched.proc.pid, signal.SIGCONT)
    # back: every screen live again
    for page in pages.values():
        expect(page.locator("#nav a.lost")).to_have_count(0, timeout=15_000)
        expect(page.locator("#banner-alarm")).not_to_have_class(re.compile(r"\blost\b"))
    expect(pages["overview"].locator("#coordinator-state")).to_have_text("Coordinator running")

    # the HMI server itself goes silent: the page says so (it pings every 5 s)
    server = [pid for pid in _children(env.launched.proc.pid)
              if b"\0hmi\0" in Path(f"/proc/{pid}/cmdline").read_bytes()]  # fmt: skip
    assert len(server) == 1, server
    page = pages["unit"]
    page.evaluate("window.__hmi.silenceMs = 1500")
    os.kill(server[0], signal.SIGSTOP)
    try:
        expect(page.locator("#banner-alarm")).to_contain_text(
            "NO CONNECTION TO THE HMI SERVER", timeout=10_000
        )
        expect(page.locator("body")).to_have_class(re.compile(r"\boffline\b"))
        assert "NO CONNECTION TO THE HMI SERVER" in why(
            page.locator("#u-cmds button[data-cmd=ABORT]")
        )
    finally:
        os.kill(server[0], signal.SIGCONT)
    page.evaluate("window.__hmi.silenceMs = 12000")  # (a ping every 5 s when nothing happens)
    expect(page.locator("body")).not_to_have_class(re.compile(r"\boffline\b"), timeout=15_000)
    for page in pages.values():
        no_problems(page)
        page.close()
