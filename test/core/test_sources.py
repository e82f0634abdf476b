"""Issue 15, items 2, 3 and 8 in the engine: sources are a grammar the rule book declares, the
remote lock guards every input that changes the unit (and fails closed), configured alarms keep
their definition whoever raises them, and the smaller refusals (category < -1, clearing another
source's interlock, a machine speed above the unit's limit, floods of made-up alarms and
interlocks)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from packml_ros2.core import Cmd, Reason, State, Unit
from packml_ros2.core import rules as R
from packml_ros2.core.config import Descriptor, Product
from packml_ros2.core.interlocks import MAX_EXTERNAL
from packml_ros2.core.limits import LogLimiter, printable, speed_limit
from packml_ros2.core.numbers import parse_command, parse_state
from packml_ros2.core.reports import Writers
from packml_ros2.core.rules import Trigger
from test.core.helpers import FakeClock, transitions
from test.core.test_scenarios import complete, make, online, to_execute

S, C = State, Cmd
#: Sources the lock must hold back: remote kinds, and what no kind names (it fails closed).
LOCKED = ("remote:line", "remote", "hmi:anyone", "opcua:scada", "coordinator", "REMOTE:line",
          "Remote:x", " remote:x", "remote :x", "opcua", "robot", "operator ", "Operator", "x:y")  # fmt: skip
FREE = ("", "operator", "operator:alice", "em:robot", "alarm:1", "interlock", "unit")

#: Every input the lock guards (rules.LOCKED_INPUTS), as a call with a source; and how to tell
#: it changed nothing.
INPUTS: dict[str, Callable[[Unit, str], Any]] = {
    "command": lambda u, s: u.command(C.RESET, s),
    "mode": lambda u, s: u.set_mode("maintenance", s),
    "alarm": lambda u, s: u.set_alarm(50, 0, True, s, category=2, message="guard"),
    "alarm.ack": lambda u, s: u.ack_alarms(None, 0, s),
    "alarm.reset": lambda u, s: u.reset_alarms(True, s),
    "times.reset": lambda u, s: u.reset_times(True, s),
    "counters.reset": lambda u, s: u.reset_counters(s),
    "speed": lambda u, s: u.set_mach_speed(10.0, s),
    "parameters": lambda u, s: u.set_parameters([Descriptor(9, "p", "mm", 1.0)], s),
    "products": lambda u, s: u.set_product([Product(77)], s),
    "em.active": lambda u, s: u.set_em_active("robot", False, s),
    "interlock": lambda u, s: u.set_interlock(True, "blocked", s),
}


def locked_unit() -> tuple[Unit, FakeClock]:
    unit, clock = make(
        {"equipment_modules": {"robot": {}}, "initial_mode": "maintenance",
         "alarms": [{"id": 7, "message": "E-stop", "category": 0, "em": "robot"}]}
    )  # fmt: skip
    online(unit, "robot")
    unit.set_alarm(60, 0, True, category=6, message="low oil")  # something to ack and reset
    unit.set_alarm(60, 0, False)
    return unit, clock


def fingerprint(unit: Unit) -> Any:
    d = unit.document()
    d.pop("saved_at", None)
    return (unit.state, unit.mode, unit.sequence, unit.mach_speed, unit.parameters, unit.products,
            dict(unit.interlocks.active), [em.active for em in unit.equipment], d)  # fmt: skip


def test_every_input_that_changes_the_unit_is_locked_for_remote_sources() -> None:
    assert set(INPUTS) == set(R.LOCKED_INPUTS)
    for name, call in INPUTS.items():
        for source in LOCKED:
            unit, _ = locked_unit()
            before = fingerprint(unit)
            answer = call(unit, source)
            assert answer.reason is Reason.REMOTE_DISABLED, (name, source, answer)
            assert source.strip() in answer.message and "remote_commands_enabled" in answer.message
            assert fingerprint(unit) == before, (name, source)
        for source in FREE:
            unit, _ = locked_unit()
            assert call(unit, source).reason is not Reason.REMOTE_DISABLED, (name, source)


def test_the_lock_opens_for_every_input_when_remote_commands_are_enabled() -> None:
    for name, call in INPUTS.items():
        unit, _ = locked_unit()
        unit.set_remote_enabled(True)
        assert call(unit, "hmi:anyone").reason is not Reason.REMOTE_DISABLED, name


def test_source_grammar_for_callers() -> None:
    for ok in ("", "operator", "operator:alice", "hmi:op-1", "opcua:scada@plant", "remote:mes.line3",
               "coordinator", "remote:" + "x" * R.MAX_SOURCE_NAME):  # fmt: skip
        assert R.source_refusal(ok) is None, ok
    for bad in ("REMOTE:x", "Remote:x", " remote:x", "remote: x", "remote:", "remote:a b",
                "remote:x\n[ERROR] forged", "hmi:\u202eevil", "em:robot", "unit", "alarm:1",
                "interlock", "plc", "operator ", "x", "remote:" + "x" * (R.MAX_SOURCE_NAME + 1)):  # fmt: skip
        why = R.source_refusal(bad)
        assert why is not None and "\n" not in why, bad
    assert R.source_of("hmi", "Jane Doe\n") == "hmi:Jane_Doe_"
    assert R.source_of("opcua", "") == "opcua"
    assert R.source_refusal(R.source_of("hmi", "x" * 500 + "\x1b")) is None


def test_the_lock_itself_is_changed_only_from_a_local_source() -> None:
    for source in LOCKED:
        refused = R.lock_change_refusal(source, "u")
        assert refused is not None and refused.reason is Reason.UNAUTHORIZED, source
    for source in ("", "operator", "operator:alice"):
        assert R.lock_change_refusal(source, "u") is None


def test_stop_reason_of_a_remote_command_is_the_remote_one() -> None:
    unit, _ = make({"remote_commands_enabled": True})
    to_execute(unit)
    assert unit.command(C.STOP, "hmi:anyone").accepted
    assert unit.stop_reason is not None and unit.stop_reason.id == 4006  # remote stop


# -- alarms (items 3 and 8) ----------------------------------------------------------------------------
def test_a_configured_alarm_keeps_its_category_kind_and_text_whoever_raises_it() -> None:
    unit, _ = make({"alarms": [{"id": 1, "message": "E-stop pressed", "category": 0}]})
    to_execute(unit)
    for kwargs in ({"category": 5}, {"message": "all fine"}, {"warning": True},
                   {"category": 9, "warning": True, "message": "x"}):  # fmt: skip
        refused = unit.set_alarm(1, 0, True, **kwargs)
        assert refused.reason is Reason.INVALID_ARGUMENT and "configured" in refused.message
        assert unit.state is S.EXECUTE and not unit.alarms.current
    # asking for what is configured is no change
    assert unit.set_alarm(1, 0, True, category=0, message="E-stop pressed").accepted
    assert unit.state is S.ABORTED  # (no EM: Aborting completes at once)


def test_an_em_raising_a_configured_alarm_as_a_warning_gets_the_configured_reaction() -> None:
    unit, _ = make({"equipment_modules": {"robot": {}},
                    "alarms": [{"id": 1, "message": "E-stop pressed", "category": 0}]})  # fmt: skip
    online(unit, "robot")
    to_execute(unit, "robot")
    unit.drain()
    answer = unit.em_alarm("robot", 1, 0, True, warning=True, category=9, message="relax")
    assert answer.accepted and unit.state is S.ABORTING  # the E-stop's reaction, not a warning's
    ev = unit.alarms.current[(1, 0)]
    assert (ev.category, ev.message, ev.kind.name) == (0, "E-stop pressed", "ALARM")
    logs = [item[1][1] for item in unit.drain() if item[0] == "log"]
    assert any("raised as configured" in text for text in logs), logs


@pytest.mark.parametrize("category", [-2, -100, 10, 2**31 - 1])
def test_set_alarm_categories_outside_minus_one_to_nine_are_refused(category: int) -> None:
    unit, _ = make({"alarms": [{"id": 1, "message": "E-stop", "category": 0}]})
    for alarm_id in (1, 99):  # configured and not
        refused = unit.set_alarm(alarm_id, 0, True, category=category, message="m")
        assert refused.reason is Reason.INVALID_ARGUMENT and str(category) in refused.message
        assert not unit.alarms.current


def test_made_up_alarms_beyond_twice_the_lists_are_refused_configured_ones_never() -> None:
    unit, _ = make({"alarms": [{"id": 1, "message": "E-stop", "category": 0}],
                    "sizes": {"alarms": 4, "warnings": 4}})  # fmt: skip
    answers = [unit.set_alarm(1000 + i, 0, True, category=7, message="x") for i in range(40)]
    assert sum(a.accepted for a in answers) == 16 and len(unit.alarms.current) == 16
    assert answers[-1].reason is Reason.INVALID_ARGUMENT
    assert unit.set_alarm(1, 0, True).accepted  # a configured alarm is always raised
    assert unit.state is S.ABORTED  # (no EM: Aborting completes at once)


# -- interlocks (item 8) ----------------------------------------------------------------------------------
def test_clearing_another_sources_interlock_says_nothing_was_cleared() -> None:
    unit, _ = make({"remote_commands_enabled": True})
    to_execute(unit)
    assert unit.set_interlock(True, "case_packer blocked", "coordinator").accepted
    assert unit.state is S.SUSPENDED
    answer = unit.set_interlock(False, "", "operator")
    assert answer.reason is Reason.NOTHING_TO_DO and "nothing cleared" in answer.message
    assert "coordinator" in answer.message
    assert unit.interlock_active and unit.state is S.SUSPENDED
    cleared = unit.set_interlock(False, "", "coordinator")
    assert cleared.accepted and "cleared" in cleared.message
    assert unit.state is S.EXECUTE


def test_interlocks_from_outside_are_bounded_one_per_source() -> None:
    unit, _ = make({"remote_commands_enabled": True})
    answers = [unit.set_interlock(True, "x", f"remote:n{i}") for i in range(MAX_EXTERNAL + 5)]
    assert sum(a.accepted for a in answers) == MAX_EXTERNAL
    assert answers[-1].reason is Reason.INVALID_ARGUMENT
    assert unit.set_interlock(True, "again", "remote:n0").accepted  # its own: replaced


# -- machine speed (item 8) --------------------------------------------------------------------------------
def test_machine_speed_is_bounded_by_the_design_speed_or_the_configured_maximum() -> None:
    unit, _ = make({"mach_speed": 40, "mach_design_speed": 50})
    for speed in (999.0, 50.001, -1.0, float("nan"), float("inf")):
        refused = unit.set_mach_speed(speed)
        assert refused.reason is Reason.INVALID_ARGUMENT and unit.mach_speed == 40, speed
    assert "0 .. 50 (mach_design_speed)" in unit.set_mach_speed(999.0).message
    assert unit.set_mach_speed(50.0).accepted and unit.mach_speed == 50.0
    over, _ = make({"mach_design_speed": 50, "max_mach_speed": 55})
    assert over.set_mach_speed(55.0).accepted and not over.set_mach_speed(55.5).accepted
    free, _ = make({})
    assert speed_limit(free.config) is None and free.set_mach_speed(1e6).accepted


# -- registration (item 3) ----------------------------------------------------------------------------------
def test_a_unit_with_listed_ems_takes_reports_of_those_only() -> None:
    unit, _ = make({"equipment_modules": {"robot": {}}})
    assert not unit.config.allow_registration
    refused = unit.em_seen("robot2", True)
    assert refused.reason is Reason.EM_UNKNOWN and "robot2" not in unit.equipment.modules
    learning, _ = make({})
    assert learning.config.allow_registration and learning.em_seen("robot2", True).accepted


# -- log lines (item 4) ------------------------------------------------------------------------------------
def test_printable_escapes_what_could_forge_a_line_and_cuts_long_text() -> None:
    assert printable("a\n[ERROR] b\r\x1b[31m\u202e") == "a\\n[ERROR] b\\x0d\\x1b[31m\\u202e"
    long = printable("x" * 100_000)
    assert len(long) < 400 and long.endswith("(100000 characters)")
    assert printable("plain") == "plain"


def test_the_log_limiter_writes_a_few_of_a_kind_then_counts() -> None:
    limiter = LogLimiter(burst=3, total=10, period=10.0)
    written = [limiter.admit(f"refused 'name{i}' #{i}", 100.0 + i * 0.01)[0] for i in range(50)]
    assert sum(written) == 3
    others = [limiter.admit(f"{i} other kind {'x' * (i % 20)}", 101.0)[0] for i in range(50)]
    assert sum(others) == 7  # the total of the period
    assert limiter.due(105.0) is None
    summary = limiter.due(110.5)
    assert summary is not None and "90 repeated log line(s)" in summary
    assert limiter.admit("refused 'name' #1", 111.0) == (True, None)


@pytest.mark.parametrize("parse", [parse_state, parse_command])
def test_a_name_that_is_not_one_is_quoted_bounded_and_escaped(parse: Any) -> None:
    """Issue 15 item 4: a caller's text in a parse error is cut and escaped (it was quoted whole
    with !r: a 1 MB name made a 1 MB error for the HMI, the CLI and the logs)."""
    for text in ("x" * 1_000_000, "9" * 100_000, "HOLD\n[ERROR] forged", "\u202eDLOH", "99"):
        with pytest.raises(ValueError) as caught:
            parse(text)
        message = str(caught.value)
        assert len(message) < 120 and message.isprintable(), message
    assert parse("hold" if parse is parse_command else "held") in (Cmd.HOLD, State.HELD)


def test_one_writer_speaks_for_an_em_until_it_leaves_the_graph_or_the_em_is_lost() -> None:
    """Issue 15 item 3: reports for an EM are taken from the writer that spoke first; another
    writer is refused however long the first was silent (a flood delays the real heartbeats),
    and takes over only when the first left the graph, or after the EM was lost (released)."""
    writers = Writers()
    left: set[bytes] = set()
    assert writers.claim("nozzle", b"em", 0.0, left.__contains__) == (True, None)
    taken, note = writers.claim("nozzle", b"forger", 1000.0, left.__contains__)
    assert not taken and note is not None and "another writer refused" in note
    assert writers.claim("nozzle", b"em", 1000.5, left.__contains__)[0]
    left.add(b"em")
    taken, note = writers.claim("nozzle", b"restarted", 1001.0, left.__contains__)
    assert taken and note is not None and "its writer left" in note
    writers.release("nozzle")
    assert writers.claim("nozzle", b"other", 1002.0, left.__contains__) == (True, None)
    assert writers.bound("nozzle") == b"other" and writers.refused == 1


def test_interlock_transitions_name_whose_interlock_it_is() -> None:
    """Issue 24 item 8: the unit's own EM Blocked and the coordinator's propagated suspend both
    said source ``interlock``; the source names the holder now (``interlock:em:<name>``,
    ``interlock:<setter>``), in the transition and in the StopReason. A replay of a recording
    of input log schema 1 says ``interlock`` as it did (legacy_interlock_source)."""

    def run(legacy: bool) -> tuple[list[tuple[State, str]], str]:
        unit, _ = make({"remote_commands_enabled": True, "equipment_modules": {"loader": {}}})
        unit.legacy_interlock_source = legacy
        online(unit, "loader")
        to_execute(unit, "loader")
        unit.drain()
        assert unit.em_interlock("loader", True, False, 0).accepted  # its own EM: Blocked
        complete(unit, "loader")
        assert unit.state is S.SUSPENDED
        reason = unit.stop_reason
        assert reason is not None
        assert unit.set_interlock(True, "case_packer blocked", "coordinator").accepted
        assert unit.em_interlock("loader", False, False, 0).accepted
        assert unit.state is S.SUSPENDED  # the coordinator's interlock still holds it
        assert unit.set_interlock(False, "", "coordinator").accepted
        complete(unit, "loader")
        assert unit.state is S.EXECUTE
        assert unit.set_interlock(True, "case_packer blocked", "coordinator").accepted
        complete(unit, "loader")
        assert unit.state is S.SUSPENDED
        found = [
            (t.to_state, t.source) for t in transitions(unit) if t.trigger is Trigger.INTERLOCK
        ]
        return found, reason.source

    found, stop_source = run(legacy=False)
    assert found == [(S.SUSPENDING, "interlock:em:loader"), (S.UNSUSPENDING, "interlock:coordinator"),
                     (S.SUSPENDING, "interlock:coordinator")]  # fmt: skip
    assert stop_source == "interlock:em:loader"
    assert not R.is_remote("interlock:coordinator") and not R.is_remote("interlock:em:loader")
    found, stop_source = run(legacy=True)
    assert [source for _, source in found] == ["interlock"] * 3 and stop_source == "interlock"
