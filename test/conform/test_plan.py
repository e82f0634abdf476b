"""The pure parts of ``packml conform``: what the standard expects (from the rule book), the ways
between states, the plan of each profile and the reports (no target)."""

from __future__ import annotations

import json
from xml.etree import ElementTree as ET

import pytest

from packml_ros2.conform import expect, report
from packml_ros2.conform.plan import Case, _Tour, groups_of, order, plan
from packml_ros2.conform.runner import Result, Run
from packml_ros2.conform.target import History
from packml_ros2.core.config import unit_config
from packml_ros2.core.numbers import Cmd, State
from packml_ros2.core.reasons import Reason
from packml_ros2.core.rules import build_table, rules_of

S = State
CONFIG = unit_config("u")
RULES = rules_of(CONFIG)


def test_expectations_follow_the_rule_book_with_skip_through() -> None:
    start = expect.command(RULES, 1, S.IDLE, Cmd.START)
    assert start.accepted and start.shown == (S.STARTING, S.EXECUTE) and start.settle is S.EXECUTE
    assert expect.command(RULES, 1, S.STOPPED, Cmd.START).reason is Reason.COMMAND_NOT_ALLOWED
    # Manual disables the Hold group: Hold is refused, the target being disabled
    assert expect.command(RULES, 3, S.EXECUTE, Cmd.HOLD).reason is Reason.STATE_DISABLED
    assert expect.mode_change(RULES, 1, 2, S.EXECUTE) is not None
    assert expect.mode_change(RULES, 1, 2, S.IDLE) is None


@pytest.mark.parametrize("mode", [1, 2, 3])
def test_every_resting_state_of_a_mode_has_a_way_there_from_every_other(mode: int) -> None:
    resting = expect.reachable(RULES, mode)
    assert S.STOPPED in resting and S.EXECUTE in resting
    for a in resting:
        for b in resting:
            way = expect.route(RULES, mode, a, [b])
            assert way is not None, (mode, a, b)
            here = a
            for cmd, settle in way:  # every step is what the standard does
                assert expect.command(RULES, mode, here, cmd).settle is settle
                here = settle
            assert here is b


def test_a_way_avoids_what_misbehaved_and_leaves_a_stuck_acting_state() -> None:
    direct = expect.route(RULES, 1, S.SUSPENDED, [S.EXECUTE])
    assert direct == ((Cmd.UNSUSPEND, S.EXECUTE),)
    around = expect.route(
        RULES, 1, S.SUSPENDED, [S.EXECUTE], frozenset({(S.SUSPENDED, Cmd.UNSUSPEND)})
    )
    assert around == ((Cmd.HOLD, S.HELD), (Cmd.UNHOLD, S.EXECUTE))
    assert expect.route(RULES, 1, S.COMPLETING, [S.COMPLETE]) == ()  # it completes by itself
    stuck = expect.route(RULES, 1, S.COMPLETING, list(expect.RESTING), stuck=True)
    assert stuck == ((Cmd.STOP, S.STOPPED),)


def test_the_plan_of_each_profile() -> None:
    assert len(plan(RULES, "core", [1, 2, 3])) == 70
    modes = plan(RULES, "modes", [1, 2, 3])
    # 7 + 6 + 4 resting states (Maintenance has no Suspended; Manual no Held, Suspended,
    # Complete), each x 2 other modes; then 60 + 40 commands in Maintenance and Manual
    assert sum(c.kind == "mode" for c in modes) == 34 and len(modes) == 134
    assert [c.kind for c in plan(RULES, "packtags", [1])] == ["packtag"] * 5
    assert groups_of("packtags,core") == ("core", "packtags")
    assert len(plan(RULES, "all", [1, 2, 3])) == 209
    with pytest.raises(ValueError, match="profile must be one of"):
        plan(RULES, "everything", [1])
    # the 2015 table: no Hold from Suspended, no Complete from Held or Suspended
    old = rules_of(unit_config("v", table=build_table("2015")))
    assert not expect.command(old, 1, S.SUSPENDED, Cmd.HOLD).accepted


@pytest.mark.parametrize("profile", ["core", "modes", "all"])
def test_a_run_takes_the_checks_as_a_tour_and_keeps_the_other_cases_in_place(profile: str) -> None:
    cases = plan(RULES, profile, [1, 2, 3])
    toured = order(RULES, cases, 1, S.STOPPED)
    assert sorted(map(repr, toured)) == sorted(map(repr, cases))  # each case once
    assert [i for i, c in enumerate(toured) if c.kind != "command"] == [
        i for i, c in enumerate(cases) if c.kind != "command"
    ]
    assert [c for c in toured if c.kind != "command"] == [c for c in cases if c.kind != "command"]
    for mode in (1, 2, 3):  # a mode's checks: the tour travels far less than the plan's order
        mine = [c for c in cases if c.kind == "command" and c.mode == mode]
        if not mine:
            continue
        tour = _Tour(RULES, mode)
        start = S.STOPPED if mode == 1 and profile == "core" else mine[0].state
        ran = [c for c in toured if c.kind == "command" and c.mode == mode]
        assert tour.travel(start, ran) <= 0.6 * tour.travel(start, mine), mode
    if profile == "core":
        ran = [(c.state, Cmd(c.cmd)) for c in toured]
        # from Stopped first the refusals there (nothing moves), then Reset: Idle is next
        assert ran[:2] == [(S.STOPPED, Cmd.START), (S.STOPPED, Cmd.STOP)]
        assert ran[8] == (S.STOPPED, Cmd.RESET) and ran[9][0] is S.IDLE
        assert _Tour(RULES, 1).travel(S.STOPPED, toured) == 27  # the plan's order: 51


def test_a_tour_from_where_the_target_was_found_or_from_nowhere() -> None:
    cases = plan(RULES, "core", [1])
    assert order(RULES, cases, 1, S.ABORTED)[0].state is S.ABORTED
    assert order(RULES, cases, 1, S.ABORTING)[0].state is S.ABORTED  # it settles there
    assert order(RULES, cases, None, None)[0].state is S.STOPPED  # the plan's first
    assert order(RULES, cases, 2, S.HELD)[0].state is S.STOPPED  # another mode: the plan's


def test_history_keeps_changes_only_and_waits() -> None:
    h = History()
    h.add(S.STOPPED, 1)
    h.add(S.STOPPED, 1)
    mark = h.mark()
    h.add(S.RESETTING, 1, 5)
    assert [e.state for e in h.since(mark)] == [S.RESETTING] and h.last is not None
    assert h.wait(lambda e: e.state is S.RESETTING, 0.01) is not None
    assert not h.wait_change(h.mark(), 0.01)


def test_reports_for_people_json_and_junit() -> None:
    ok = Case("core", "command", 1, S.IDLE, cmd=2)
    bad = Case("core", "command", 1, S.STOPPED, cmd=2)
    run = Run(
        results=[
            Result(ok, "pass", "accepted: STARTING -> EXECUTE in 3 ms", 0.003),
            Result(
                bad,
                "fail",
                "START in STOPPED (PRODUCTION) was accepted (Good); the standard refuses it",
            ),
        ]
    )
    about = report.About(
        "t", "opcua", "core", "2022", {1: "PRODUCTION"}, "2026-11-28T00:00:00+00:00", 1.5
    )
    table = report.text(run, about)
    assert "FAIL  core     PRODUCTION STOPPED START  START in STOPPED" in table
    assert table.endswith("FAILED: 1 passed, 1 failed, 0 skipped")
    doc = json.loads(report.as_json(run, about, RULES))
    assert doc["counts"] == {"pass": 1, "fail": 1, "skip": 0} and not doc["passed"]
    assert doc["results"][1]["expected"] == "refused (COMMAND_NOT_ALLOWED)"
    root = ET.fromstring(report.junit(run, about, RULES).split("\n", 1)[1])
    [suite] = root.iter("testsuite")
    assert suite.get("name") == "packml.conform.core" and suite.get("failures") == "1"
    [failure] = root.iter("failure")
    assert failure.get("message", "").startswith("START in STOPPED (PRODUCTION) was accepted")
