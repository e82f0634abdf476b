"""Issue 17, HMI item 4: each disabled command and mode button says why, in the unit's words.

The HMI reads a unit's status and alarm list (as the bridge turns the ROS messages into dicts) and
asks the unit's rule book why a command or a mode change is not available now
(packml_ros2.hmi.why). Here a real engine (packml_ros2.core.Unit, no ROS) is put in each situation
that refuses commands; its status and alarm list go through the same conversions as on the wire;
for every command and mode the HMI shows as unavailable, the unit itself is then asked: it refuses
with the same reason code and, but for an interlock's own words, the same sentence."""

from __future__ import annotations

from typing import Any

import pytest

from packml_ros2 import convert
from packml_ros2.core import Cmd, Reason, State, Unit
from packml_ros2.core.line.sequence import Outcome
from packml_ros2.hmi import why
from packml_ros2.hmi.access import Principal, command_source
from packml_ros2.hmi.bridge import alarm_list_dict, status_dict
from test.core.helpers import FakeClock, cell_unit

UNIT_DOC: dict[str, Any] = {
    "remote_commands_enabled": True,  # the HMI is remote (hmi:<user>): the lock is tested below
    "equipment_modules": {"em1": {}},
    "alarms": [{"id": 201, "message": "Gripper vacuum lost", "category": 2}],
}
#: the source the HMI's actions for the user anna carry (and the HMI's reasons are judged for)
ANNA = command_source(Principal("anna"))


def seen_by_the_hmi(unit: Unit) -> tuple[dict[str, Any], dict[str, Any]]:
    """The unit's status and alarm list as the bridge holds them."""
    now = unit.now
    return (
        status_dict(convert.status(unit.status())),
        alarm_list_dict(convert.alarm_list(unit.config.name, now, unit.alarms)),
    )


def start(doc: dict[str, Any] | None = None) -> tuple[Unit, FakeClock]:
    clock = FakeClock()
    unit = Unit(cell_unit(doc if doc is not None else UNIT_DOC), clock)
    assert unit.em_seen("em1", report=True).accepted
    return unit, clock


def sc(unit: Unit) -> None:
    assert unit.em_complete("em1", unit.state, unit.sequence).accepted


def to_execute(unit: Unit) -> None:
    assert unit.command(Cmd.RESET).accepted
    sc(unit)
    assert unit.command(Cmd.START).accepted
    sc(unit)
    assert unit.state is State.EXECUTE


def check_commands(unit: Unit, interlock: bool = False) -> dict[str, dict[str, Any]]:
    """Every command the HMI shows unavailable is refused by the unit with that reason (and
    sentence); every other one is valid. Returns what the HMI shows."""
    status, alarms = seen_by_the_hmi(unit)
    shown = why.command_reasons(unit.config, status, alarms, ANNA)
    assert set(shown) | set(status["commands_valid_names"]) == {c.name for c in Cmd if c}
    for name, reason in shown.items():
        answer = unit.command(Cmd[name], ANNA)
        assert not answer.accepted, (name, answer)
        assert reason["reason"] == answer.reason.name, (name, reason, answer)
        # a guard's (listed apart on the page), or the state model's own refusal
        model = answer.reason in (Reason.COMMAND_NOT_ALLOWED, Reason.STATE_DISABLED)
        assert reason["guard"] is not model, (name, reason, answer)
        if not (interlock and answer.reason is Reason.INTERLOCK_ACTIVE):
            assert reason["text"] == answer.message, (name, reason, answer)
    return shown


def test_not_allowed_by_the_state_model() -> None:
    unit, _ = start()
    shown = check_commands(unit)
    assert shown["START"] == {
        "reason": "COMMAND_NOT_ALLOWED",
        "text": "START not allowed in STOPPED in PRODUCTION mode (valid now: RESET, ABORT)",
        "guard": False,
    }
    to_execute(unit)
    check_commands(unit)


def test_refused_by_the_remote_lock_in_the_words_the_unit_answers_the_user_with() -> None:
    # the HMI's actions are remote (hmi:<user>): with remote commands disabled the unit refuses
    # each of them naming that source, and the HMI shows exactly that
    unit, _ = start({**UNIT_DOC, "remote_commands_enabled": False})
    shown = check_commands(unit)
    assert set(shown) == {c.name for c in Cmd if c}  # RESET and ABORT are locked too
    assert shown["RESET"]["reason"] == "REMOTE_DISABLED"
    assert shown["RESET"]["text"].startswith("RESET from hmi:anna refused: remote commands")
    status, _ = seen_by_the_hmi(unit)
    modes = why.mode_reasons(unit.config, status, ANNA)
    assert set(modes) == {"1", "2", "3"}
    for number in (1, 2, 3):
        answer = unit.set_mode(number, ANNA)
        assert answer.reason is Reason.REMOTE_DISABLED and modes[str(number)] == answer.message


def test_refused_while_an_alarm_with_a_reaction_is_active() -> None:
    unit, _ = start()
    to_execute(unit)
    assert unit.set_alarm(201).accepted  # category 2: STOP
    sc(unit)  # Stopping -> Stopped
    assert unit.state is State.STOPPED
    shown = check_commands(unit)
    assert shown["RESET"]["reason"] == "ALARM_ACTIVE"
    assert (
        'alarm 201/0 "Gripper vacuum lost" (category 2) with reaction STOP'
        in shown["RESET"]["text"]
    )


def test_refused_while_an_active_em_is_missing() -> None:
    unit, _ = start({**UNIT_DOC, "em_lost_reaction": "stop"})
    assert unit.em_lost("em1").accepted
    sc_free = check_commands(unit)
    assert (
        sc_free["RESET"]["reason"] == "EM_MISSING"
        and "active EM em1 offline" in sc_free["RESET"]["text"]
    )


def test_refused_while_a_mode_change_is_in_process() -> None:
    unit, _ = start()
    assert unit.set_mode(2).accepted  # MAINTENANCE: waits for em1's report
    status, _ = seen_by_the_hmi(unit)
    assert status["mode_change_in_process"]
    shown = check_commands(unit)
    assert shown["RESET"]["reason"] == "MODE_CHANGE_IN_PROCESS"
    modes = why.mode_reasons(unit.config, status, ANNA)
    assert set(modes) == {"1", "2", "3"}  # no other change meanwhile
    answer = unit.set_mode(3)
    assert modes["3"] == answer.message and answer.reason is Reason.MODE_CHANGE_IN_PROCESS


def test_refused_while_an_interlock_holds_the_unit() -> None:
    unit, _ = start()
    to_execute(unit)
    assert unit.set_interlock(True, "case_packer blocked").accepted
    unit.advance()
    sc(unit)
    assert unit.state is State.SUSPENDED
    shown = check_commands(unit, interlock=True)
    assert shown["UNSUSPEND"]["reason"] == "INTERLOCK_ACTIVE"


def test_mode_buttons_follow_the_units_mode_rules() -> None:
    unit, _ = start()
    status, _ = seen_by_the_hmi(unit)
    assert why.mode_reasons(unit.config, status, ANNA) == {"1": "PRODUCTION is the current mode"}
    to_execute(unit)
    status, _ = seen_by_the_hmi(unit)
    modes = why.mode_reasons(unit.config, status, ANNA)
    assert set(modes) == {"1", "2", "3"}
    for number in (2, 3):
        answer = unit.set_mode(number)
        assert not answer.accepted and answer.reason is Reason.MODE_CHANGE_NOT_ALLOWED
        assert modes[str(number)] == answer.message


def check_ems(unit: Unit) -> dict[str, str]:
    """Every EM the HMI shows as not switchable now is refused by the unit with that sentence
    (switched the way its button would: inactive if active); every other one is switched (then
    switched back). Returns what the HMI shows."""
    status, _ = seen_by_the_hmi(unit)
    shown = why.em_reasons(unit.config, status, ANNA)
    for em in status["equipment_modules"]:
        name, active = em["name"], em["active"]
        answer = unit.set_em_active(name, not active, ANNA)
        if name in shown:
            assert not answer.accepted and answer.message == shown[name], (name, shown, answer)
        else:
            assert answer.accepted, (name, answer)
            assert unit.set_em_active(name, active, ANNA).accepted
    return shown


def test_em_switches_follow_the_units_rules() -> None:
    """Issue 28: the page said itself that EMs are switched outside PRODUCTION only (app.js); the
    bridge sends why, in the unit's words (the ``ems`` of a unit's reasons)."""
    unit, _ = start()
    assert "only outside PRODUCTION (now PRODUCTION, STOPPED)" in check_ems(unit)["em1"]
    assert unit.set_mode(2, ANNA).accepted  # MAINTENANCE, once em1 has reported
    sc(unit)
    assert unit.mode == 2 and check_ems(unit) == {}
    locked, _ = start({**UNIT_DOC, "remote_commands_enabled": False})
    assert "remote commands are disabled" in check_ems(locked)["em1"]
    assert unit.set_mode(1, ANNA).accepted
    sc(unit)
    to_execute(unit)
    assert "(now PRODUCTION, EXECUTE)" in check_ems(unit)["em1"]


@pytest.mark.parametrize(
    "status",
    [
        {"state": 99, "mode": 1, "commands_valid": []},
        {"state": 2, "mode": 0, "commands_valid": [1, "x", None]},
        {"state": "STOPPED", "mode": None},
        {},
    ],
)
def test_a_status_the_configuration_does_not_know_is_answered_not_raised(
    status: dict[str, Any],
) -> None:
    config = cell_unit(UNIT_DOC)
    reasons = why.reasons(config, status, {"alarms": [{"trigger": True}]}, ANNA)
    assert set(reasons["commands"]) <= {c.name for c in Cmd if c} and reasons["commands"]
    assert all("does not have" in r["text"] for r in reasons["commands"].values())
    assert all("does not have" in text for text in reasons["modes"].values())


def test_the_shared_reasons_are_each_users_own_once_the_page_names_its_user() -> None:
    """Issue 15: every browser gets the same reasons, judged for the viewer (hmi:<user> with
    logins); the page puts its user's name for the viewer's (app/access.js ownReasons). Sound
    because the rule book judges every hmi: user alike: for each user, in each situation (locked,
    an alarm, a mode change, running), the viewer's reasons so named are exactly that user's, and
    the levels are the page's own (CFG.unit_action_level against its user's level)."""
    from packml_ros2.core import parse_cell
    from packml_ros2.hmi.access import Access
    from packml_ros2.hmi.bridge import config_dict
    from packml_ros2.hmi.settings import User

    users = {n: User(n, "operator", "x") for n in ("anna", "ben.k@line-3")}
    cell = parse_cell({"cell": "c", "units": {"u": UNIT_DOC}})
    viewer = config_dict(cell, "", Access(None, users=users))["why_source"]
    assert viewer == "hmi:<user>"

    def named(reasons: dict[str, Any], user: str) -> dict[str, Any]:
        own = lambda t: t.replace(viewer, f"hmi:{user}")  # noqa: E731 (what app/access.js does)
        return {"commands": {c: {**v, "text": own(v["text"])} for c, v in reasons["commands"].items()},
                "modes": {m: own(t) for m, t in reasons["modes"].items()},
                "ems": {e: own(t) for e, t in reasons["ems"].items()}}  # fmt: skip

    situations = []
    locked, _ = start({**UNIT_DOC, "remote_commands_enabled": False})
    situations.append(locked)
    alarmed, _ = start()
    to_execute(alarmed)
    assert alarmed.set_alarm(201).accepted
    situations.append(alarmed)
    changing, _ = start()
    assert changing.set_mode(2).accepted
    situations.append(changing)
    running, _ = start()
    to_execute(running)
    situations.append(running)
    names_seen = 0
    for unit in situations:
        status, alarms = seen_by_the_hmi(unit)
        shared = why.reasons(unit.config, status, alarms, viewer)
        for user in users:
            own = why.reasons(unit.config, status, alarms, command_source(Principal(user)))
            assert named(shared, user) == own, (user, unit.state)
            names_seen += str(own).count(f"hmi:{user}")
    assert names_seen > 0  # the locked unit's sentences name the user


# -- the cell's commands -----------------------------------------------------------------------
def _line_at(seconds: float, *commands: tuple[float, Cmd]) -> Any:
    """The coordinator's line core (test/core/line_sim.py: real engines, simulated EMs, exact
    times) after ``commands`` (at, cell command), at ``seconds``."""
    from test.core.line_sim import SimEm, SimLine
    from test.core.test_line_scenarios import D, cell_doc

    sim = SimLine(
        cell_doc(),
        [SimEm("filler", "infeed", dict(D), 1.0), SimEm("packer", "loader", dict(D), 2.0)],
    )
    for at, cmd in commands:
        sim.at(at, lambda c=cmd: sim.cell_command(c))
    sim.run_until(seconds)
    return sim


def _seen_by_the_hmi(sim: Any) -> dict[str, str]:
    """The cell's reasons from its status as the coordinator publishes it (CellStatus: busy,
    sequence_step, commands_valid: packml_ros2.coordinator_node)."""
    v = sim.line.view()
    status = {
        "busy": v.busy,
        "sequence_step": v.sequence_step,
        "commands_valid": list(v.commands_valid),
    }
    return why.cell_command_reasons(status)


@pytest.mark.parametrize(
    ("situation", "at", "commands"),
    [
        ("stopped", 0.5, ()),
        ("resetting (a sequence runs)", 1.5, ((1.0, Cmd.RESET),)),
        ("idle", 3.5, ((1.0, Cmd.RESET),)),
        ("starting (a sequence runs)", 4.5, ((1.0, Cmd.RESET), (4.0, Cmd.START))),
        ("executing", 8.0, ((1.0, Cmd.RESET), (4.0, Cmd.START))),
    ],
)
def test_the_cell_commands_the_hmi_greys_are_the_ones_the_coordinator_refuses(
    situation: str, at: float, commands: tuple[tuple[float, Cmd], ...]
) -> None:
    """Issue 28: the page no longer decides the cell's commands itself ("only STOP and ABORT"
    while a sequence ran was written in app.js): the bridge judges them from the coordinator's
    status. For each command, in each situation, a fresh line is asked: a command not named is
    begun (STOP while a sequence runs after the sequence is cancelled, as the coordinator node
    does: coordinator_node.cell_command), one named for the sequence is refused. (One named as not
    valid for the cell, e.g. STOP with every unit stopped, is greyed as the cell's status lists
    it; the coordinator would begin it and find nothing to do.)"""
    reasons = _seen_by_the_hmi(_line_at(at, *commands))
    busy = _line_at(at, *commands).line.view().busy
    assert busy is ("sequence" in situation), situation
    for cmd in (c for c in Cmd if c):
        sim = _line_at(at, *commands)
        if cmd is Cmd.STOP and busy:
            sim.line.runs.cancel_all("STOP")
            sim._poll_runs()  # the cancelled sequence ends
        begun = sim.line.begin_command(cmd, "hmi:anna")
        refused = isinstance(begun, Outcome) and not begun.accepted
        if cmd.name not in reasons:
            assert not refused, (situation, cmd.name, begun)
        elif busy:
            assert refused and "busy" in begun.message, (situation, cmd.name, begun)
            assert reasons[cmd.name].startswith(f"{cmd.name} refused: a cell sequence is running")
            assert "only STOP and ABORT interrupt it" in reasons[cmd.name]
    if busy:
        allowed = sorted(c.name for c in Cmd if c and c.name not in reasons)
        assert allowed == ["ABORT", "STOP"], allowed


def test_the_cell_reasons_of_a_status_that_says_little_or_nonsense() -> None:
    assert why.cell_command_reasons(None) == {}
    nothing = why.cell_command_reasons({})
    assert set(nothing) == {c.name for c in Cmd if c}
    assert all("valid now: none" in text for text in nothing.values())
    odd = why.cell_command_reasons(
        {"commands_valid": [True, "2", 999, int(Cmd.START)], "busy": 1, "sequence_step": None}
    )
    assert "START" in odd and "(…)" in odd["START"] and "ABORT" in odd and "STOP" in odd
