"""Scenarios from docs/packml.md sections 3-7 and the vendor documents it cites, each a short story
told to the engine with a fake clock."""

from __future__ import annotations

from typing import Any

import pytest

from packml_ros2.core import (
    AlarmDef,
    CommandRequest,
    CompleteReport,
    Mode,
    ModeRequest,
    Reason,
    State,
    Trigger,
    Unit,
    flat_tags,
    unit_config,
)
from packml_ros2.core import Cmd as C
from packml_ros2.core.alarms import Kind, OperatorState
from packml_ros2.core.config import EmConfig

from .helpers import FakeClock, cell_unit, transitions

S = State
ROLLOVER = 2**31 - 1


def make(unit: dict[str, Any] | None = None, t: float = 1_000.0) -> tuple[Unit, FakeClock]:
    clock = FakeClock(t)
    return Unit(cell_unit(unit or {}), clock), clock


def online(unit: Unit, *names: str) -> None:
    for name in names:
        assert unit.em_seen(name).accepted


def complete(unit: Unit, *names: str) -> None:
    """The named EMs report State Complete for the unit's current (state, sequence)."""
    state, seq = unit.state, unit.sequence
    for name in names:
        answer = unit.em_complete(name, state, seq)
        assert answer.accepted, answer


def to_execute(unit: Unit, *ems: str) -> None:
    """Stopped -> Resetting -> Idle -> Starting -> Execute, the EMs reporting each acting state."""
    assert unit.command(C.RESET).accepted, unit.command(C.RESET)
    if ems:
        complete(unit, *ems)
    assert unit.command(C.START).accepted
    if ems:
        complete(unit, *ems)
    assert unit.state is S.EXECUTE


# -- Mitsubishi: "Stop PB Pressed" (ID 65, category 2) ----------------------------------------------------------
def test_mitsubishi_stop_pb_pressed_latches_until_resetting() -> None:
    unit, clock = make({"alarms": [{"id": 65, "value": 0, "message": "Stop PB Pressed",
                                    "category": 2, "em": "em00"}],
                        "equipment_modules": {"em00": {}}})  # fmt: skip
    online(unit, "em00")
    to_execute(unit, "em00")
    clock.advance(7.0)
    answer = unit.em_alarm("em00", 65, 0, True)
    assert answer.accepted and "STOP" in answer.message
    assert unit.state is S.STOPPING
    tr = transitions(unit)[-1]
    assert (tr.trigger, tr.command, tr.source) == (Trigger.ALARM, C.STOP, "alarm:65")
    complete(unit, "em00")
    assert unit.state is S.STOPPED
    listed = unit.admin().alarm
    assert [(a.id, a.value, a.message, a.category, a.trigger) for a in listed] == [
        (65, 0, "Stop PB Pressed", 2, True)
    ]
    # Reset refused while the condition is active (a Stop reaction blocks motion).
    refused = unit.command(C.RESET)
    assert refused.reason is Reason.ALARM_ACTIVE and "65" in refused.message
    # Condition clears: still listed (latched), trigger false; first occurrence time kept.
    clock.advance(659.0)
    assert unit.em_alarm("em00", 65, 0, False).accepted
    (ev,) = unit.admin().alarm
    assert not ev.trigger and ev.latched and ev.time == 1_007.0 and ev.cleared_time == 1_666.0
    # Re-activation before the reset is the same event.
    assert unit.em_alarm("em00", 65, 0, True).accepted
    assert unit.state is S.STOPPED  # Stop is not valid in Stopped: nothing happens
    (ev2,) = unit.admin().alarm
    assert ev2 is ev and ev.trigger and ev.activations == 2
    assert unit.em_alarm("em00", 65, 0, False).accepted
    # Entering Resetting resets latched alarms that are no longer active.
    assert unit.command(C.RESET).accepted
    assert unit.state is S.RESETTING
    assert unit.admin().alarm == ()
    assert unit.admin().stop_reason is not None and unit.admin().stop_reason.id == 65


# -- Omron: priority when Abort, Stop and SC arrive in one step ------------------------------------------------
def test_omron_abort_stop_and_state_complete_in_one_step() -> None:
    unit, _ = make({"equipment_modules": {"em1": {}}})
    online(unit, "em1")
    to_execute(unit, "em1")
    unit.drain()
    seq = unit.sequence
    answers = unit.step(
        [
            CompleteReport("em1", S.EXECUTE, seq),
            CommandRequest(C.STOP, "operator"),
            CommandRequest(C.ABORT, "em:em1"),
        ]
    )
    assert [a.reason for a in answers] == [Reason.NOTHING_TO_DO, Reason.SUPERSEDED, Reason.ACCEPTED]
    assert "ABORT" in answers[1].message
    assert unit.state is S.ABORTING
    (tr,) = transitions(unit)
    assert (tr.from_state, tr.to_state, tr.command, tr.sequence) == (
        S.EXECUTE,
        S.ABORTING,
        C.ABORT,
        seq + 1,
    )
    assert unit.stats.stale_reports == 1


def test_state_command_applies_before_mode_change_in_same_step() -> None:
    unit, _ = make()
    assert unit.command(C.RESET).accepted and unit.state is S.IDLE
    # Mode change first in the list, Abort second: Abort is applied first, then the mode change
    # is judged in the new state (Aborting: not allowed), though Idle allowed it.
    answers = unit.step([ModeRequest("maintenance"), CommandRequest(C.ABORT)])
    assert answers[1].accepted
    assert answers[0].reason is Reason.MODE_CHANGE_NOT_ALLOWED and "ABORTING" in answers[0].message
    assert unit.state is S.ABORTED and unit.mode == Mode.PRODUCTION
    # The other order of arrival gives the same result.
    unit.command(C.CLEAR)
    unit.command(C.RESET)
    answers = unit.step([CommandRequest(C.ABORT), ModeRequest("maintenance")])
    assert answers[0].accepted and answers[1].reason is Reason.MODE_CHANGE_NOT_ALLOWED


# -- Schneider: a disabled Resetting is skipped -------------------------------------------------------------
def test_schneider_skip_of_disabled_resetting() -> None:
    unit, _ = make({"modes": {"quick": {"number": 7, "disabled_states": ["Resetting"],
                                        "mode_change_states": ["Stopped"]}},
                    "initial_mode": "quick",
                    "alarms": [{"id": 5, "message": "door", "category": 6}]})  # fmt: skip
    assert unit.set_alarm(5).accepted and unit.set_alarm(5, active=False).accepted
    assert len(unit.admin().alarm) == 1
    unit.drain()
    answer = unit.command(C.RESET)
    assert answer.accepted and answer.message == "RESET accepted: STOPPED -> IDLE"
    (tr,) = transitions(unit)
    assert (tr.from_state, tr.to_state, tr.trigger, tr.skipped) == (
        S.STOPPED, S.IDLE, Trigger.SKIP, (S.RESETTING,)
    )  # fmt: skip
    assert unit.admin().alarm == ()  # the skipped Resetting counts as entered: alarm reset
    assert unit.status().states_disabled == 1 << S.RESETTING


# -- textbook: a mode change in Stopped keeps the state ------------------------------------------------------
def test_textbook_mode_change_keeps_state() -> None:
    unit, clock = make()
    unit.drain()
    clock.advance(3.0)
    answer = unit.set_mode(Mode.MAINTENANCE)
    assert answer.accepted
    assert unit.mode == Mode.MAINTENANCE and unit.state is S.STOPPED
    (tr,) = transitions(unit)
    assert (tr.from_state, tr.to_state, tr.from_mode, tr.to_mode, tr.trigger) == (
        S.STOPPED, S.STOPPED, Mode.PRODUCTION, Mode.MAINTENANCE, Trigger.MODE
    )  # fmt: skip
    status = unit.status()
    assert (status.unit_mode_current, status.unit_mode_requested) == (2, 2)
    assert status.unit_mode_current_name == "MAINTENANCE"
    assert not status.unit_mode_change_in_process


def test_mode_change_not_allowed_lamp_for_three_seconds() -> None:
    unit, clock = make()
    to_execute(unit)
    answer = unit.set_mode("manual")
    assert answer.reason is Reason.MODE_CHANGE_NOT_ALLOWED
    assert "EXECUTE" in answer.message and "PRODUCTION" in answer.message
    assert unit.mode == Mode.PRODUCTION and unit.state is S.EXECUTE
    assert unit.status().mode_change_not_allowed
    clock.advance(2.9)
    unit.advance()
    assert unit.status().mode_change_not_allowed
    clock.advance(0.1)
    unit.advance()
    assert not unit.status().mode_change_not_allowed


def test_disabled_target_wait_state_is_rejected() -> None:
    unit, _ = make({"initial_mode": "maintenance"})
    to_execute(unit)
    answer = unit.command(C.SUSPEND)
    assert answer.reason is Reason.STATE_DISABLED
    assert answer.message == (
        "SUSPEND not allowed in EXECUTE in MAINTENANCE mode: SUSPENDED is disabled in MAINTENANCE "
        "(valid now: STOP, HOLD, ABORT, COMPLETE)"
    )
    assert unit.state is S.EXECUTE


def test_mode_change_waits_for_ems_and_blocks_commands_but_not_abort() -> None:
    unit, clock = make({"equipment_modules": {"em1": {}, "em2": {}}, "mode_change_timeout": 5})
    online(unit, "em1", "em2")
    assert unit.set_mode("maintenance").accepted
    assert unit.mode_change_in_process and unit.mode == Mode.PRODUCTION
    refused = unit.command(C.RESET)
    assert refused.reason is Reason.MODE_CHANGE_IN_PROCESS
    assert "STOPPED" in refused.message and "em1, em2" in refused.message
    assert unit.set_mode("manual").reason is Reason.MODE_CHANGE_IN_PROCESS
    complete(unit, "em1")
    assert unit.mode_change_in_process
    complete(unit, "em2")
    assert not unit.mode_change_in_process and unit.mode == Mode.MAINTENANCE
    # A second change that the EMs never confirm times out: the mode stays, an alarm says why.
    assert unit.set_mode("production").accepted
    clock.advance(5.0)
    unit.advance()
    assert not unit.mode_change_in_process and unit.mode == Mode.MAINTENANCE
    assert unit.status().unit_mode_requested == Mode.MAINTENANCE
    (ev,) = [a for a in unit.admin().alarm if a.id == 9003]
    assert "em1" in ev.message and not ev.trigger
    # Abort is valid in every state, also while a mode change is in process: the change is
    # abandoned.
    assert unit.set_mode("production").accepted
    answer = unit.command(C.ABORT)
    assert answer.accepted, answer
    assert unit.state is S.ABORTING and unit.mode == Mode.MAINTENANCE
    assert not unit.mode_change_in_process
    assert unit.status().unit_mode_requested == Mode.MAINTENANCE


def test_alarm_reaction_during_mode_change_is_applied() -> None:
    unit, _ = make({"equipment_modules": {"em1": {}}})
    online(unit, "em1")
    assert unit.set_mode("maintenance").accepted
    assert unit.set_alarm(77, category=1, message="light curtain").accepted
    assert unit.state is S.ABORTING and not unit.mode_change_in_process


# -- EM aggregation ------------------------------------------------------------------------------------
def test_em_aggregation_stale_inactive_and_registration() -> None:
    unit, _ = make(
        {"equipment_modules": {"feeder": {}, "sealer": {}, "labeler": {"active": False}},
         "allow_registration": True}  # (a listed EM set is closed by default)
    )  # fmt: skip
    online(unit, "feeder", "sealer")  # the inactive labeler never shows up
    assert unit.command(C.RESET).accepted
    seq = unit.sequence
    assert unit.em_complete("feeder", S.RESETTING, seq).accepted
    assert unit.state is S.RESETTING
    # Stale reports (older sequence, other state) are ignored and counted.
    assert unit.em_complete("sealer", S.RESETTING, seq - 1).reason is Reason.NOTHING_TO_DO
    assert unit.em_complete("sealer", S.STOPPING, seq).reason is Reason.NOTHING_TO_DO
    assert unit.em_complete("ghost", S.RESETTING, seq).reason is Reason.EM_UNKNOWN
    assert unit.state is S.RESETTING
    views = {v.name: v for v in unit.status().equipment}
    assert views["feeder"].state_complete and not views["sealer"].state_complete
    assert views["sealer"].stale_reports == 2 and unit.stats.stale_reports == 2
    assert not views["labeler"].active
    assert unit.em_complete("sealer", S.RESETTING, seq).accepted
    assert unit.state is S.IDLE
    # A new EM registers at run time and is waited for from the next state on.
    assert unit.em_seen("capper").accepted
    assert unit.command(C.START).accepted
    complete(unit, "feeder", "sealer")
    assert unit.state is S.STARTING
    complete(unit, "capper")
    assert unit.state is S.EXECUTE


def test_registration_refused_when_not_allowed() -> None:
    unit, _ = make({"allow_registration": False, "equipment_modules": {"em1": {}}})
    answer = unit.em_seen("intruder")
    assert answer.reason is Reason.EM_UNKNOWN and "allow_registration" in answer.message
    assert [v.name for v in unit.status().equipment] == ["em1"]


def test_unit_without_active_em_completes_acting_states_but_execute_waits() -> None:
    unit, _ = make()
    assert unit.command(C.RESET).accepted and unit.state is S.IDLE
    assert unit.command(C.START).accepted and unit.state is S.EXECUTE
    unit.drain()
    unit.advance()
    assert unit.state is S.EXECUTE
    assert unit.command(C.COMPLETE).accepted and unit.state is S.COMPLETE
    assert [r.to_state for r in transitions(unit)] == [S.COMPLETING, S.COMPLETE]


def test_a_step_judges_later_requests_in_the_acting_state_the_first_reached() -> None:
    """A command alone follows immediate State Complete in the same input; in a step, the other
    requests see the acting state the winner entered, and State Complete comes after them."""
    unit, _ = make()
    unit.drain()
    answers = unit.step([CommandRequest(C.RESET), CommandRequest(C.START)])
    assert answers[0].accepted
    assert answers[1].reason is Reason.COMMAND_NOT_ALLOWED
    assert answers[1].message.startswith("START not allowed in RESETTING")
    assert unit.state is S.IDLE  # State Complete of Resetting, after the step's requests
    records = transitions(unit)
    assert [(r.to_state, r.trigger, r.source) for r in records] == [
        (S.RESETTING, Trigger.COMMAND, "operator"),
        (S.IDLE, Trigger.STATE_COMPLETE, "unit"),
    ]
    assert [r.sequence for r in records] == [records[0].sequence, records[0].sequence + 1]
    answer = unit.command(C.START)
    assert answer.accepted and unit.state is S.EXECUTE
    assert [(r.from_state, r.to_state, r.trigger) for r in transitions(unit)] == [
        (S.IDLE, S.STARTING, Trigger.COMMAND),
        (S.STARTING, S.EXECUTE, Trigger.STATE_COMPLETE),
    ]


def test_execute_state_complete_ends_the_run() -> None:
    unit, _ = make({"equipment_modules": {"em1": {}}})
    online(unit, "em1")
    to_execute(unit, "em1")
    complete(unit, "em1")
    assert unit.state is S.COMPLETING
    complete(unit, "em1")
    assert unit.state is S.COMPLETE


def test_manual_mode_execute_state_complete_is_ignored_and_counted() -> None:
    unit, _ = make({"initial_mode": "manual", "equipment_modules": {"em1": {}}})
    online(unit, "em1")
    to_execute(unit, "em1")
    complete(unit, "em1")
    assert unit.state is S.EXECUTE and unit.stats.sc_ignored == 1
    assert unit.command(C.STOP).accepted


@pytest.mark.parametrize(
    ("reaction", "expected", "category", "kind"),
    [
        (None, S.ABORTING, 0, Kind.ALARM),
        ("abort", S.ABORTING, 0, Kind.ALARM),
        ("stop", S.STOPPING, 2, Kind.ALARM),
        ("hold", S.HOLDING, 5, Kind.ALARM),
        ("ignore", S.EXECUTE, 9, Kind.WARNING),
    ],
)
def test_em_lost_reactions(
    reaction: str | None, expected: State, category: int, kind: Kind
) -> None:
    em1: dict[str, Any] = {} if reaction is None else {"lost_reaction": reaction}
    unit, _ = make({"equipment_modules": {"em0": {}, "em1": em1}})
    online(unit, "em0", "em1")
    to_execute(unit, "em0", "em1")
    answer = unit.em_lost("em1", "lease expired")
    assert answer.accepted
    assert unit.state is expected
    (ev,) = [a for a in unit.alarms.current.values() if a.id == 9001]
    assert (ev.value, ev.category, ev.kind, ev.trigger) == (2, category, kind, True)
    assert "em1" in ev.message and "lease expired" in ev.message
    if reaction != "ignore":
        assert transitions(unit)[-1].trigger is Trigger.EM_LOST
        # While the active EM is offline, motion commands are refused.
        assert [c for c in unit.valid_commands() if c in (C.RESET, C.START, C.UNHOLD)] == []
    assert unit.em_lost("em1").reason is Reason.NOTHING_TO_DO  # already offline


def test_em_returns_and_rejoins_current_state() -> None:
    unit, _ = make({"equipment_modules": {"em0": {}, "em1": {"lost_reaction": "hold"}}})
    online(unit, "em0", "em1")
    to_execute(unit, "em0", "em1")
    assert unit.em_lost("em1").accepted and unit.state is S.HOLDING
    complete(unit, "em0")
    assert unit.state is S.HOLDING  # em1 is waited for: Holding does not excuse lost EMs
    assert set(unit.equipment.pending) == {"em1"}
    assert unit.em_seen("em1").accepted
    (ev,) = [a for a in unit.alarms.current.values() if a.id == 9001]
    assert not ev.trigger and ev.latched  # cleared, latched until a reset
    complete(unit, "em1")
    assert unit.state is S.HELD
    assert unit.command(C.UNHOLD).accepted
    complete(unit, "em0", "em1")
    assert unit.state is S.EXECUTE


def test_em_lost_in_stopping_is_excused_and_rejoins_when_back() -> None:
    unit, _ = make({"equipment_modules": {"em0": {}, "em1": {"lost_reaction": "stop"}}})
    online(unit, "em0", "em1")
    to_execute(unit, "em0", "em1")
    assert unit.command(C.STOP).accepted
    assert unit.em_lost("em1").accepted
    assert set(unit.equipment.pending) == {"em0"}
    assert unit.em_seen("em1").accepted  # back before Stopping completed: it has to report
    complete(unit, "em0")
    assert unit.state is S.STOPPING
    complete(unit, "em1")
    assert unit.state is S.STOPPED


def test_em_missing_refuses_motion_and_diagnosis_switch_recovers() -> None:
    """Textbook power-loss scenario: an EM dies, the unit aborts; outside Production the EM is
    switched inactive (logged) and Clear and Reset recover without it."""
    unit, _ = make({"equipment_modules": {"robot": {}, "conveyor": {}}})
    online(unit, "robot", "conveyor")
    to_execute(unit, "robot", "conveyor")
    assert unit.em_lost("robot").accepted and unit.state is S.ABORTING
    complete(unit, "conveyor")  # the lost robot is excused in Aborting
    assert unit.state is S.ABORTED
    refused = unit.set_em_active("robot", False)
    assert refused.reason is Reason.EM_SWITCH_IN_PRODUCTION
    assert unit.command(C.CLEAR).reason is Reason.ALARM_ACTIVE  # the abort alarm is active
    assert unit.set_mode("maintenance").accepted
    complete(unit, "conveyor")
    assert unit.mode == Mode.MAINTENANCE
    assert unit.set_em_active("robot", False, source="operator:technician").accepted
    assert any(
        "robot switched inactive by operator:technician" in e.message
        for e in unit.admin().alarm_history
    )
    assert unit.command(C.CLEAR).accepted
    complete(unit, "conveyor")
    assert unit.state is S.STOPPED
    assert unit.command(C.RESET).accepted
    complete(unit, "conveyor")
    assert unit.state is S.IDLE
    # Losing an inactive EM again is no fault.
    assert unit.em_seen("robot").accepted
    assert unit.em_lost("robot").accepted and unit.state is S.IDLE
    # Switched active again while offline: it is missing, motion is refused.
    assert unit.set_em_active("robot", True).accepted
    refused = unit.command(C.START)
    assert refused.reason is Reason.EM_MISSING and "robot" in refused.message


def test_em_requests_are_commands_of_active_ems_only() -> None:
    unit, _ = make({"initial_mode": "maintenance", "equipment_modules": {"em1": {}, "em2": {}}})
    online(unit, "em1", "em2")
    to_execute(unit, "em1", "em2")
    assert unit.set_em_active("em2", False).accepted
    assert unit.em_request("em2", C.HOLD).reason is Reason.EM_UNKNOWN
    assert unit.em_request("em1", 0).accepted and unit.state is S.EXECUTE
    assert unit.em_request("em1", C.HOLD).accepted and unit.state is S.HOLDING
    assert transitions(unit)[-1].source == "em:em1"


# -- timeouts and minimum dwell ------------------------------------------------------------------------------
def test_state_timeout_raises_alarm_naming_missing_ems() -> None:
    unit, clock = make({"equipment_modules": {"em1": {}, "em2": {}, "em3": {}},
                        "timeouts": {"Starting": 5}})  # fmt: skip
    online(unit, "em1", "em2", "em3")
    assert unit.command(C.RESET).accepted
    complete(unit, "em1", "em2", "em3")
    assert unit.command(C.START).accepted
    complete(unit, "em2")
    clock.advance(4.99)
    unit.advance()
    assert unit.state is S.STARTING and not unit.alarms.current
    clock.advance(0.01)
    unit.advance()
    (ev,) = unit.admin().alarm
    assert (ev.id, ev.value, ev.category) == (9002, S.STARTING, 2)
    assert ev.message == "STARTING timed out waiting for em1, em3"
    assert unit.state is S.STOPPING  # category 2: Stop
    tr = transitions(unit)[-1]
    assert tr.trigger is Trigger.TIMEOUT and tr.time == 1_005.0
    assert unit.stop_reason is not None and unit.stop_reason.id == 9002


def test_timeout_category_is_configurable() -> None:
    unit, clock = make({"equipment_modules": {"em1": {}}, "timeouts": {"Holding": 2},
                        "system_alarms": {"state_timeout": 4711, "state_timeout_category": 1}})  # fmt: skip
    online(unit, "em1")
    to_execute(unit, "em1")
    assert unit.command(C.HOLD).accepted
    clock.advance(2.0)
    unit.advance()
    assert unit.state is S.ABORTING
    (ev,) = unit.admin().alarm
    assert (ev.id, ev.value, ev.category) == (4711, S.HOLDING, 1)
    assert unit.stop_reason is not None and unit.stop_reason.id == 33  # the Hold came first


def published(unit: Unit) -> list[tuple[str, Any]]:
    """The drained outputs that publish a status: transitions and status marks."""
    return [(kind, x) for kind, x in unit.drain() if kind in ("transition", "status")]


@pytest.mark.parametrize("refused_between", [False, True])
def test_a_change_after_a_command_is_published_once_and_no_change_never(
    refused_between: bool,
) -> None:
    """Each transition publishes the status itself. A later change that is not a transition
    (MachSpeed here) is published once, 50 ms later (changes coalesce); inputs that change
    nothing the status shows (a refused command, time passing) publish nothing."""
    unit, clock = make()
    unit.drain()
    assert unit.command(C.RESET).accepted  # Stopped -> Resetting -> Idle
    assert [kind for kind, _ in published(unit)] == ["transition", "transition"]
    clock.advance(0.2)  # (no periodic admin due on the way: it flushes)
    if refused_between:
        assert not unit.command(C.UNHOLD).accepted  # not valid in Idle: changes nothing
        assert published(unit) == []
    assert unit.set_mach_speed(42.0).accepted
    clock.advance(0.01)
    unit.advance()
    assert published(unit) == []  # not yet
    clock.advance(0.05)
    unit.advance()
    marks = published(unit)
    assert [kind for kind, _ in marks] == ["status"]
    assert marks[0][1].time == pytest.approx(1_000.25)
    assert unit.status_at(marks[0][1]).mach_speed == 42.0
    clock.advance(5.0)
    unit.advance()
    assert published(unit) == []  # nothing changed since


def test_min_dwell_without_ems() -> None:
    unit, clock = make({"min_dwell": {"Resetting": 2.0}})
    unit.drain()
    assert unit.command(C.RESET).accepted
    assert unit.state is S.RESETTING
    clock.advance(1.5)
    unit.advance()
    assert unit.state is S.RESETTING
    clock.advance(10.0)  # the deadline fires at its own time, not at the clock's
    unit.advance()
    assert unit.state is S.IDLE
    assert transitions(unit)[-1].time == 1_002.0


def test_min_dwell_with_ems_waits_for_both() -> None:
    unit, clock = make({"min_dwell": {"Resetting": 2.0}, "equipment_modules": {"em1": {}}})
    online(unit, "em1")
    assert unit.command(C.RESET).accepted
    complete(unit, "em1")
    assert unit.state is S.RESETTING
    clock.advance(2.0)
    unit.advance()
    assert unit.state is S.IDLE


# -- alarms -----------------------------------------------------------------------------------------------
# The EMs that own ALARM_CELL's alarms, inactive: they take no part in State Complete.
QUIET_EMS = {"em1": {"active": False}, "em2": {"active": False}}
ALARM_CELL = {
    "equipment_modules": {"em1": {}, "em2": {}},
    "alarms": [
        {"id": 10, "message": "jam", "category": 3, "em": "em1"},
        {"id": 11, "message": "jam", "category": 3, "em": "em2"},
        {"id": 12, "message": "door", "category": 6},
        {"id": 13, "message": "vacuum low", "category": 5, "reaction": "hold"},
        {"id": 14, "message": "air low", "category": 0, "warning": True},
        {"id": 15, "message": "e-stop", "category": 1},
    ],
}


def test_acknowledge_stamps_once() -> None:
    unit, clock = make(ALARM_CELL)
    assert unit.set_alarm(12).accepted
    (ev,) = unit.admin().alarm
    assert ev.operator_state is OperatorState.ACTIVE_UNACKNOWLEDGED
    assert unit.set_alarm(12, active=False).accepted
    assert ev.operator_state is OperatorState.INACTIVE_UNACKNOWLEDGED
    clock.advance(4.0)
    assert unit.ack_alarms(12).accepted
    assert ev.ack_time == 1_004.0 and ev.operator_state is OperatorState.ACKNOWLEDGED
    clock.advance(4.0)
    again = unit.ack_alarms(12)
    assert again.reason is Reason.NOTHING_TO_DO and ev.ack_time == 1_004.0
    assert unit.ack_alarms(99).reason is Reason.ALARM_UNKNOWN
    assert unit.status().unacknowledged_alarms == 0


def test_alarm_reset_keeps_active_alarms() -> None:
    unit, _ = make(ALARM_CELL)
    for alarm_id in (12, 13):
        assert unit.set_alarm(alarm_id).accepted
    assert unit.set_alarm(12, active=False).accepted
    answer = unit.reset_alarms()
    assert answer.accepted and "1 cleared" in answer.message and "1 still active" in answer.message
    assert [a.id for a in unit.admin().alarm] == [13]
    assert unit.set_alarm(13).reason is Reason.NOTHING_TO_DO  # already active
    assert unit.set_alarm(99).reason is Reason.ALARM_UNKNOWN  # not configured, no category
    assert unit.set_alarm(12, active=False).reason is Reason.NOTHING_TO_DO


def test_first_out_per_em_unit_and_category_kept_across_reset_cleared_on_starting() -> None:
    unit, clock = make(ALARM_CELL)
    online(unit, "em1", "em2")
    to_execute(unit, "em1", "em2")
    unit.em_alarm("em2", 11, 0, True)  # Stop
    clock.advance(1.0)
    unit.em_alarm("em1", 10, 0, True)
    unit.set_alarm(12)
    alarms = unit.alarms
    assert alarms.first_out is not None and alarms.first_out.id == 11
    assert {c: e.id for c, e in alarms.first_out_by_category.items()} == {3: 11, 6: 12}
    assert {em: e.id for em, e in alarms.first_out_by_em.items()} == {"em2": 11, "em1": 10}
    assert unit.status().alarm_banner.startswith("ALARM 11/0 cat 3: jam [em2] (+2 more)")
    complete(unit, "em1", "em2")
    assert unit.state is S.STOPPED
    for alarm_id in (10, 11, 12):
        unit.set_alarm(alarm_id, active=False)
    assert unit.command(C.RESET).accepted  # entering Resetting resets the alarms ...
    assert unit.admin().alarm == ()
    assert alarms.first_out is not None and alarms.first_out.id == 11  # ... not the first-out
    assert set(alarms.first_out_by_category) == {3, 6}
    complete(unit, "em1", "em2")
    assert unit.command(C.START).accepted  # entering Starting clears the first-outs
    assert alarms.first_out is None and not alarms.first_out_by_category
    assert not alarms.first_out_by_em


def test_first_out_cleared_by_its_service() -> None:
    unit, _ = make(ALARM_CELL)
    unit.set_alarm(12)
    unit.set_alarm(12, active=False)
    assert unit.alarms.first_out is not None
    unit.reset_alarms(clear_first_out=True)
    assert unit.alarms.first_out is None


def test_history_is_newest_first_ring_and_lists_count_overflow() -> None:
    cell = {**ALARM_CELL, "sizes": {"history": 4, "alarms": 2, "warnings": 1}}
    unit, clock = make(cell)
    for alarm_id in (12, 13, 15):
        clock.advance(1.0)
        unit.set_alarm(alarm_id)
    clock.advance(1.0)
    unit.set_alarm(14)
    unit.set_alarm(700, category=7, message="extra", warning=True)
    admin = unit.admin()
    assert [a.id for a in admin.alarm] == [12, 13] and admin.alarm_overflow == 1
    assert [w.id for w in admin.warning] == [14] and admin.warning_overflow == 1
    history = [a.id for a in admin.alarm_history]
    assert history == [700, 14, 15, 13]  # newest first, the ring holds 4
    assert unit.alarms.history_dropped == 1
    assert flat_tags(unit.status(), admin)["Admin.AlarmExtent"] == 2


def test_alarm_query_filter_and_sort() -> None:
    unit, clock = make(ALARM_CELL)
    for alarm_id in (13, 12, 15):
        clock.advance(1.0)
        unit.set_alarm(alarm_id)
    unit.set_alarm(13, active=False)
    by_time = [a.id for a in unit.alarms.query()]
    assert by_time == [13, 12, 15]
    assert [a.id for a in unit.alarms.query(sort="category")] == [15, 13, 12]
    assert [a.id for a in unit.alarms.query(active_only=True)] == [12, 15]
    assert [a.id for a in unit.alarms.query(category=6)] == [12]
    assert [a.id for a in unit.alarms.query(sort="newest")] == [15, 12, 13]
    with pytest.raises(ValueError, match="sort"):
        unit.alarms.query(sort="random")


@pytest.fixture
def running() -> tuple[Unit, FakeClock]:
    unit, clock = make({"alarms": ALARM_CELL["alarms"], "equipment_modules": QUIET_EMS})
    to_execute(unit)
    return unit, clock


def test_warning_in_execute_changes_nothing(running: tuple[Unit, FakeClock]) -> None:
    unit, _ = running
    answer = unit.set_alarm(14)
    assert answer.accepted and "warning" in answer.message and "reaction" not in answer.message
    assert unit.state is S.EXECUTE
    assert unit.command(C.HOLD).accepted and unit.command(C.UNHOLD).accepted
    assert unit.state is S.EXECUTE
    assert [w.id for w in unit.admin().warning] == [14] and unit.admin().alarm == ()


@pytest.mark.parametrize(
    ("alarm_id", "expected"),
    [(15, S.ABORTED), (10, S.STOPPED), (13, S.HELD), (12, S.EXECUTE)],
)
def test_alarm_reaction_by_category_and_override(
    running: tuple[Unit, FakeClock], alarm_id: int, expected: State
) -> None:
    unit, _ = running
    assert unit.set_alarm(alarm_id).accepted
    assert unit.state is expected


def test_abort_alarm_also_refuses_clear(running: tuple[Unit, FakeClock]) -> None:
    unit, _ = running
    unit.set_alarm(15)
    assert unit.state is S.ABORTED
    refused = unit.command(C.CLEAR)
    assert refused.reason is Reason.ALARM_ACTIVE and "15" in refused.message
    assert C.CLEAR not in unit.valid_commands()
    unit.set_alarm(15, active=False)
    assert unit.command(C.CLEAR).accepted and unit.state is S.STOPPED
    assert unit.admin().alarm == ()  # entering Clearing reset the latched alarm


def test_stop_alarm_refuses_motion_not_clear(running: tuple[Unit, FakeClock]) -> None:
    unit, _ = running
    unit.set_alarm(10)
    assert unit.state is S.STOPPED
    assert unit.command(C.RESET).reason is Reason.ALARM_ACTIVE
    assert unit.command(C.ABORT).accepted and unit.state is S.ABORTED
    assert unit.command(C.CLEAR).accepted and unit.state is S.STOPPED
    assert [a.id for a in unit.admin().alarm] == [10]  # still active: stays after the reset


# -- StopReason --------------------------------------------------------------------------------------------
def test_stop_reason_operator_then_first_event_only() -> None:
    unit, clock = make()
    to_execute(unit)
    clock.advance(1.0)
    assert unit.command(C.HOLD, "operator").accepted
    reason = unit.admin().stop_reason
    assert reason is not None
    assert (reason.id, reason.value, reason.source, reason.time) == (
        33,
        C.HOLD,
        "operator",
        1_001.0,
    )
    assert unit.command(C.ABORT).accepted  # not re-armed: the first event stays
    assert unit.admin().stop_reason is reason
    assert unit.status().stop_reason_id == 33


def test_stop_reason_remote_and_remote_commands_refused_unless_enabled() -> None:
    unit, _ = make({"remote_interfaces": [{"number": 3, "name": "line"}]})
    refused = unit.command(C.RESET, "remote:line")
    assert refused.reason is Reason.REMOTE_DISABLED and "remote_commands_enabled" in refused.message
    assert unit.set_mode("maintenance", "remote:line").reason is Reason.REMOTE_DISABLED
    unit.set_remote_enabled(True)
    assert unit.status().remote_commands_enabled
    assert unit.command(C.RESET, "remote:line").accepted
    assert unit.command(C.START, "remote:line").accepted
    assert unit.command(C.STOP, "remote:line").accepted
    reason = unit.admin().stop_reason
    assert reason is not None and (reason.id, reason.source) == (4006, "remote:line")
    (ri,) = unit.status().remote_interface
    assert (ri.number, ri.control_cmd_number, ri.cmd_value) == (3, C.STOP, 1)


def test_remote_enabled_by_configuration() -> None:
    unit, _ = make({"remote_commands_enabled": True})
    assert unit.command(C.RESET, "remote").accepted


def test_stop_reason_alarm_and_rearm() -> None:
    unit, _ = make({"alarms": ALARM_CELL["alarms"], "equipment_modules": QUIET_EMS})
    to_execute(unit)
    unit.set_alarm(13)  # Hold reaction
    reason = unit.admin().stop_reason
    assert reason is not None and (reason.id, reason.message) == (13, "vacuum low")
    unit.set_alarm(13, active=False)
    assert unit.command(C.UNHOLD).accepted  # entering Unholding re-arms
    assert unit.command(C.SUSPEND, "em:em1").accepted
    reason = unit.admin().stop_reason
    assert reason is not None and (reason.id, reason.value, reason.source) == (
        33,
        C.SUSPEND,
        "em:em1",
    )


# -- times -------------------------------------------------------------------------------------------------
def test_times_current_and_cumulative_per_mode_and_state() -> None:
    unit, clock = make()
    clock.advance(10.0)  # Production, Stopped 10 s
    assert unit.command(C.RESET).accepted  # -> Idle
    clock.advance(5.0)  # Idle 5 s
    assert unit.set_mode("maintenance").accepted
    clock.advance(7.0)  # Maintenance Idle 7 s
    assert unit.set_mode("production").accepted
    clock.advance(3.0)  # Production Idle 3 s
    unit.advance()
    times = unit.admin().times
    P, M, N = Mode.PRODUCTION, Mode.MAINTENANCE, 18
    assert times.mode_current[P] == 3 and times.mode_cumulative[P] == 18
    assert times.mode_current[M] == 0 and times.mode_cumulative[M] == 7  # docs/packml.md §6
    assert times.state_current[P * N + S.IDLE] == 3
    assert times.state_cumulative[P * N + S.IDLE] == 8
    assert times.state_cumulative[P * N + S.STOPPED] == 10
    assert times.state_cumulative[M * N + S.IDLE] == 7
    assert times.acc_time_since_reset == 25
    tags = flat_tags(unit.status(), unit.admin())
    assert tags["Admin.StateCurrentTime[1,4]"] == 3
    assert tags["Admin.StateCumulativeTime[1,4]"] == 8
    assert tags["Admin.ModeCumulativeTime[2]"] == 7
    assert tags["Admin.AccTimeSinceReset"] == 25


def test_time_resets_current_mode_and_all() -> None:
    unit, clock = make()
    clock.advance(10.0)
    assert unit.set_mode("maintenance").accepted
    clock.advance(4.0)
    assert unit.reset_times().accepted  # Maintenance and its states only
    clock.advance(1.0)
    unit.advance()
    t = unit.admin().times
    assert t.mode_cumulative[Mode.MAINTENANCE] == 1
    assert t.state_cumulative[Mode.MAINTENANCE * 18 + S.STOPPED] == 1
    assert t.mode_cumulative[Mode.PRODUCTION] == 10
    assert t.acc_time_since_reset == 15
    assert unit.reset_times(all_times=True).accepted
    clock.advance(2.0)
    unit.advance()
    t = unit.admin().times
    assert t.mode_cumulative[Mode.PRODUCTION] == 0 and t.mode_cumulative[Mode.MAINTENANCE] == 2
    assert t.acc_time_since_reset == 2
    assert any("all times reset" in e.message for e in unit.admin().alarm_history)


def test_time_rollover_warning_with_a_clock_far_in_the_future() -> None:
    start = 4_102_444_800.0  # 2100-01-01
    unit, clock = make(t=start)
    clock.advance(ROLLOVER - 1.0)
    unit.advance()
    assert not unit.status().time_rollover_warning
    assert not unit.admin().times.rollover_warning
    assert unit.admin().times.acc_time_since_reset == ROLLOVER - 1
    clock.advance(11.0)
    unit.advance()
    times = unit.admin().times
    assert times.rollover_warning and unit.status().time_rollover_warning
    assert times.acc_time_since_reset == 10
    assert times.state_cumulative[Mode.PRODUCTION * 18 + S.STOPPED] == 10
    assert unit.admin().plc_date_time[0] == 2168


# -- counters and OEE -----------------------------------------------------------------------------------------
def test_counters_count_and_acc_count() -> None:
    unit, _ = make({"counters": {"processed": [{"id": 1, "name": "bottles", "unit": "pcs"}],
                                 "defective": [{"id": 2, "name": "rejects"}]}})  # fmt: skip
    assert unit.em_count("filler", "processed", 0, 5).accepted
    assert unit.em_count("filler", "processed", 0, 7).accepted
    assert unit.em_count("filler", "defective", 0, 1).accepted
    bad = unit.em_count("filler", "processed", 10, 1)
    assert bad.reason is Reason.INVALID_ARGUMENT and "index 10" in bad.message
    assert unit.em_count("filler", "bogus", 0, 1).reason is Reason.INVALID_ARGUMENT
    c = unit.admin().prod_processed_count[0]
    assert (c.id, c.name, c.unit, c.count, c.acc_count) == (1, "bottles", "pcs", 12, 12)
    assert unit.reset_counters().accepted
    unit.em_count("filler", "processed", 0, 2)
    c = unit.admin().prod_processed_count[0]
    assert (c.count, c.acc_count) == (2, 14)
    assert unit.admin().prod_defective_count[0].count == 0
    assert unit.admin().prod_defective_count[0].acc_count == 1
    assert len(unit.admin().prod_consumed_count) == 10


def test_oee_buckets() -> None:
    unit, clock = make({"mach_design_speed": 60.0, "remote_commands_enabled": True})
    to_execute(unit)
    clock.advance(100.0)
    unit.em_count("em", "processed", 0, 150)
    unit.em_count("em", "defective", 0, 15)
    assert unit.command(C.HOLD).accepted and unit.state is S.HELD
    clock.advance(10.0)
    assert unit.command(C.UNHOLD).accepted
    clock.advance(50.0)
    assert unit.command(C.SUSPEND).accepted and unit.state is S.SUSPENDED
    clock.advance(5.0)
    assert unit.command(C.UNSUSPEND).accepted
    clock.advance(30.0)
    assert unit.command(C.STOP, "remote").accepted and unit.state is S.STOPPED  # planned: 4006
    clock.advance(20.0)
    assert unit.command(C.ABORT).accepted and unit.state is S.ABORTED
    clock.advance(7.0)
    unit.advance()
    oee = unit.admin().oee
    assert oee.production_time == pytest.approx(222.0)
    assert oee.execute_time == pytest.approx(180.0)
    assert oee.planned_stop_time == pytest.approx(20.0)
    assert oee.internal_downtime == pytest.approx(10.0)
    assert oee.external_downtime == pytest.approx(5.0)
    assert oee.stopped_time == pytest.approx(0.0)
    assert oee.aborted_time == pytest.approx(7.0)
    assert oee.availability == pytest.approx(180.0 / 202.0)
    assert oee.performance == pytest.approx(150.0 / 180.0)
    assert oee.quality == pytest.approx(0.9)
    assert oee.oee == pytest.approx(180.0 / 202.0 * 150.0 / 180.0 * 0.9)


def test_oee_unplanned_operator_stop() -> None:
    unit, clock = make({"mach_design_speed": 60.0})
    to_execute(unit)
    clock.advance(10.0)
    assert unit.command(C.STOP).accepted  # operator: StopReason 33, not planned
    clock.advance(10.0)
    unit.advance()
    oee = unit.admin().oee
    assert oee.planned_stop_time == 0.0 and oee.stopped_time == pytest.approx(10.0)
    assert oee.availability == pytest.approx(0.5)
    assert (oee.performance, oee.quality) == (0.0, 0.0)  # nothing processed


# -- PackTags names ---------------------------------------------------------------------------------------
def test_flat_tags_standard_names() -> None:
    unit, clock = make({"counters": {"processed": [{"id": 1, "name": "bottles"}]},
                        "parameters": [{"id": 1, "name": "speed", "unit": "bpm", "value": 80}],
                        "mach_design_speed": 120})  # fmt: skip
    to_execute(unit)
    clock.advance(12.0)
    unit.em_count("em", "processed", 0, 3)  # advances the unit to the clock
    assert unit.set_mach_speed(90.0).accepted
    tags = flat_tags(unit.status(), unit.admin())
    assert tags["Status.StateCurrent"] == 6
    assert tags["Status.UnitModeCurrent"] == 1
    assert tags["Status.UnitModeRequested"] == 1
    assert tags["Status.StateRequested"] == 6
    assert tags["Status.StateChangeInProcess"] is False
    assert tags["Status.CurMachSpeed"] == 90.0
    assert tags["Command.CntrlCmd"] == C.START
    assert tags["Admin.ProdProcessedCount[0].Count"] == 3
    assert tags["Admin.ProdProcessedCount[0].Name"] == "bottles"
    assert tags["Admin.StateCurrentTime[1,6]"] == 12
    assert tags["Admin.MachDesignSpeed"] == 120
    assert tags["Admin.StopReason.ID"] == 0
    assert tags["Status.Parameter[0].Name"] == "speed"
    for name in ("Command.UnitMode", "Command.UnitModeChangeRequest", "Command.MachSpeed",
                 "Command.MaterialInterlock", "Command.CmdChangeRequest",
                 "Status.UnitModeChangeInProcess", "Status.MachSpeed",
                 "Status.EquipmentInterlock.Blocked", "Status.EquipmentInterlock.Starved",
                 "Admin.ProdDefectiveCount[0].Count", "Admin.StatesDisabled",
                 "Admin.PLCDateTime", "Admin.ModeCurrentTime[31]",
                 "Admin.StateCumulativeTime[31,17]"):  # fmt: skip
        assert name in tags, name
    status = flat_tags(unit.status())
    assert "Admin.AccTimeSinceReset" not in status and status["Status.StateCurrent"] == 6


def test_state_requested_and_change_in_process() -> None:
    unit, _ = make({"equipment_modules": {"em1": {}}})
    online(unit, "em1")
    assert unit.command(C.RESET).accepted
    status = unit.status()
    assert (status.state_current, status.state_requested) == (S.RESETTING, S.IDLE)
    assert status.state_change_in_process
    complete(unit, "em1")
    status = unit.status()
    assert (status.state_current, status.state_requested) == (S.IDLE, S.IDLE)
    assert not status.state_change_in_process
    assert status.commands_valid_names == ("START", "STOP", "ABORT")


def test_unit_config_in_code() -> None:
    clock = FakeClock()
    config = unit_config(
        "capper",
        equipment_modules=(EmConfig("torque"),),
        alarms=(AlarmDef(65, 0, "Stop PB Pressed", 2),),
    )
    unit = Unit(config, clock)
    assert unit.state is S.STOPPED and unit.sequence == 1
    assert unit.command(C.RESET).reason is Reason.EM_MISSING
    online(unit, "torque")
    assert unit.command(C.RESET).accepted


def test_skipped_starting_clears_first_out_and_start_up_clears_commands() -> None:
    unit, _ = make({"modes": {"quick": {"number": 9, "disabled_states": ["Starting"],
                                        "mode_change_states": ["Stopped"]}},
                    "initial_mode": 9})  # fmt: skip
    assert unit.status().cntrl_cmd == 0 and unit.status().state_current == S.STOPPED
    unit.set_alarm(50, category=6, message="note")
    unit.set_alarm(50, active=False)
    assert unit.command(C.RESET).accepted and unit.alarms.first_out is not None
    assert unit.command(C.START).accepted and unit.state is S.EXECUTE
    assert transitions(unit)[-1].skipped == (S.STARTING,)
    assert unit.alarms.first_out is None
    assert unit.status().cntrl_cmd == C.START
