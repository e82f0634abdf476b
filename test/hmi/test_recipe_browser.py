"""Issue 32: the recipe screen and the stack light in a real browser (Debian's headless Chromium
driven by Playwright, as test_browser.py) against test/recipe_cell.py's cell run by `packml launch
<cell> --hmi` (unit filler, simulated EMs robot, gripper and vision that take 0.3 s to change
over), at the operator panel's size, 1024x768.

Every wait is on a condition: a line of the launcher's output, a state of the page."""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.testing.launched import Launched
from test.hmi.readable import contrast_failures, fit_failures
from test.hmi.test_browser import CHROMIUM, CHROMIUM_ARGS, PANEL, fits, no_problems
from test.recipe_cell import REFUSAL, write_recipe_cell

pytestmark = [pytest.mark.browser, pytest.mark.ros, pytest.mark.slow]

sync_api = pytest.importorskip("playwright.sync_api", reason="the playwright package is missing")
expect = sync_api.expect
PACKML = [sys.executable, "-m", "packml_ros2.cli.main"]


class Env:
    def __init__(self, url: str, cell: str, browser: Any) -> None:
        self.url = url
        self.cell = cell
        self.browser = browser

    def page(self, hash_: str) -> Any:
        page = self.browser.new_page()
        page.set_viewport_size(PANEL)
        page.set_default_timeout(15_000)
        page.problems = []
        page.on(
            "console", lambda m: m.type == "error" and page.problems.append(f"console: {m.text}")
        )
        page.on("pageerror", lambda e: page.problems.append(f"page error: {e}"))
        page.goto(f"{self.url}#/{hash_}")
        page.wait_for_selector("#nav a")
        expect(page.locator("#access-state")).to_have_text("Open access")
        return page


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory, ros_domain: int) -> Iterator[Env]:
    tmp = tmp_path_factory.mktemp("recipe_cell")
    cell = f"rc{os.getpid()}"
    path = write_recipe_cell(tmp, cell)
    doc = yaml.safe_load(path.read_text())
    doc["hmi"] = {"host": "127.0.0.1", "port": 0, "title": "Recipe line"}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    launched = Launched([*PACKML, "launch", str(path), "--hmi"], tmp / "launch.log")
    playwright = sync_api.sync_playwright().start()
    try:
        url = launched.wait_for(r"PackML HMI for cell \S+: (http://127\.0\.0\.1:\d+/)").group(1)
        launched.wait_for("is up")
        browser = playwright.chromium.launch_persistent_context(
            str(tmp / "chromium-profile"),
            executable_path=str(CHROMIUM),
            args=CHROMIUM_ARGS,
            headless=True,
            viewport=PANEL,
        )
        try:
            yield Env(url, cell, browser)
        finally:
            browser.close()
    finally:
        playwright.stop()
        code = launched.stop()
        assert code == 0, f"packml launch exited {code}:\n{launched.output()[-3000:]}"
        assert "Traceback" not in launched.output(), launched.output()[-3000:]


def fault(env: Env, on: bool) -> None:
    em = f"{env.cell}/filler/gripper"
    done = subprocess.run(
        [*PACKML, "fault", "--timeout", "30", em, "wrong_fingers", "on" if on else "off"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr


def lights(page: Any) -> str:
    return str(page.get_attribute("#stack-light", "data-lights"))


def fits_the_panel(page: Any) -> None:
    assert page.evaluate("document.documentElement.scrollWidth") <= PANEL["width"]
    fits(page)
    assert not fit_failures(page), fit_failures(page)
    assert not contrast_failures(page), contrast_failures(page)


WATCH_EMS = """() => {
  window.__answers = {};
  const note = () => document.querySelectorAll('#r-ems tr[data-em]').forEach((r) => {
    const seen = (window.__answers[r.dataset.em] ||= []);
    if (seen[seen.length - 1] !== r.dataset.answer) seen.push(r.dataset.answer);
  });
  note();
  new MutationObserver(note).observe(document.getElementById('screen-recipe'),
                                     { subtree: true, childList: true, attributes: true });
}"""


def test_a_refused_changeover_rolls_back_and_the_next_one_applies(env: Env) -> None:
    page = env.page("unit/filler")
    expect(page.locator("#banner-state")).to_contain_text("STOPPED")
    expect(page.locator("#u-recipe-current")).to_have_text("1 · cola 0.5")
    page.click("#u-recipe-link")
    expect(page.locator("#screen-recipe")).to_be_visible()
    expect(page.locator("#r-current-recipe")).to_have_text("1 · cola 0.5")
    # the chosen recipe beside the one in use, what differs highlighted
    page.select_option("#r-select", "2")
    expect(page.locator("#r-col-chosen")).to_have_text("Chosen: 2 · water 1.0")
    diff = page.eval_on_selector_all(
        "#r-compare tr.diff", "rows => rows.map(r => [...r.cells].map(c => c.textContent))"
    )
    assert diff == [
        ["primary quantity", "1200 bottles", "800 bottles"],
        ["fill_volume", "500 ml", "1000 ml"],
        ["label", "COLA-500", "AQUA-1000"],
        ["valves", "12", "8"],
        ["syrup_ratio", "12.5 %", "–"],
    ], diff
    expect(page.locator("#r-diff-count")).to_have_text("5 parameter(s) differ (highlighted)")
    fits_the_panel(page)

    # the gripper refuses the change once: the screen says who refused, why, and the rollback
    fault(env, True)
    page.evaluate(WATCH_EMS)
    expect(page.locator("#r-change")).to_have_attribute("aria-disabled", "false")
    page.click("#r-change")
    expect(page.locator("#r-feedback")).to_contain_text("changeover to recipe 2 'water 1.0' begun")
    result = page.locator("#r-result")
    expect(result).to_contain_text(f"EM gripper refused it: {REFUSAL}")
    expect(result).to_contain_text("rolled back to 1 'cola 0.5'")
    expect(result).to_have_class(re.compile(r"\brefused\b"))
    gripper = page.locator("#r-ems tr[data-em=gripper]")
    expect(gripper).to_have_attribute("data-answer", "refused")
    expect(gripper.locator("td.reason")).to_have_text(REFUSAL)
    expect(page.locator("#r-current-recipe")).to_have_text("1 · cola 0.5")
    expect(page.locator("#r-progress")).to_have_text("No changeover running")
    if shots := os.environ.get("PACKML_SCREENSHOTS_DIR"):  # (`make screenshots`)
        page.mouse.move(0, 0)
        page.screenshot(path=str(Path(shots) / "hmi-recipe-1024x768.png"))
    answers = page.evaluate("window.__answers")
    assert "pending" in answers["robot"] and "pending" in answers["gripper"], answers
    fits_the_panel(page)

    # again (the fault refuses once): applied, recipe 2 in use, every EM accepted
    page.click("#r-change")
    expect(page.locator("#r-current-recipe")).to_have_text("2 · water 1.0")
    expect(result).to_contain_text("recipe 2 'water 1.0' applied in")
    expect(result).to_have_class(re.compile(r"\bapplied\b"))
    for em in ("robot", "gripper", "vision"):
        expect(page.locator(f"#r-ems tr[data-em={em}]")).to_have_attribute(
            "data-answer", "accepted"
        )
    expect(page.locator("#r-col-current")).to_have_text("In use: 2 · water 1.0")
    page.click("#r-tab-unit")
    expect(page.locator("#u-recipe-current")).to_have_text("2 · water 1.0")
    no_problems(page)
    page.close()


def test_in_execute_a_change_is_refused_with_the_reason_and_the_light_is_green(env: Env) -> None:
    page = env.page("unit/filler")
    expect(page.locator("#banner-state")).to_contain_text("STOPPED")
    # the default preset (omac): amber on while Stopped, green on in Execute
    expect(page.locator("#stack-light")).to_have_attribute(
        "data-lights", "red:off amber:on green:off blue:off"
    )
    expect(page.locator("#stack-light")).to_have_attribute("data-horn", "off")
    for cmd, state in (("RESET", "IDLE"), ("START", "EXECUTE")):
        page.click(f"#u-cmds button[data-cmd={cmd}]")
        expect(page.locator("#banner-state")).to_contain_text(state)
    expect(page.locator("#stack-light")).to_have_attribute(
        "data-lights", "red:off amber:off green:on blue:off"
    )
    assert page.locator("#stack-light .sl-green.on").count() == 1
    try:
        page.evaluate("location.hash = '#/unit/filler/recipe'")
        button = page.locator("#r-change")
        reason = "filler changes its recipe only in STOPPED, IDLE, COMPLETE"
        expect(button).to_have_attribute("aria-disabled", "true")
        assert reason in str(button.get_attribute("data-why"))
        expect(page.locator("#r-why")).to_contain_text(reason)
        current = page.locator("#r-current-recipe").inner_text()
        button.click(force=True)  # not sent: the reason in the answer box
        feedback = page.locator("#r-feedback")
        expect(feedback).to_have_attribute("data-state", "local")
        expect(feedback).to_contain_text(reason)
        # sent all the same (another page's older view): the unit's refusal, code and message
        page.evaluate(
            "async () => (await import('/static/app/actions.js'))"
            ".act('filler', 'set_recipe', { recipe_id: 1 }, 'Recipe 1')"
        )
        expect(feedback).to_have_attribute("data-state", "refused")
        expect(feedback).to_contain_text("RECIPE_NOT_ALLOWED")
        expect(feedback).to_contain_text(f"refused in EXECUTE (PRODUCTION): {reason}")
        expect(page.locator("#r-current-recipe")).to_have_text(current)
        fits_the_panel(page)
        page.evaluate("location.hash = '#/overview'")
        expect(page.locator("[data-unit-card=filler] .stack-light")).to_have_attribute(
            "data-lights", "red:off amber:off green:on blue:off"
        )
        fits_the_panel(page)
    finally:
        with contextlib.suppress(Exception):
            page.evaluate("location.hash = '#/unit/filler'")
            page.click("#u-cmds button[data-cmd=STOP]")
            expect(page.locator("#banner-state")).to_contain_text("STOPPED")
    no_problems(page)
    page.close()
