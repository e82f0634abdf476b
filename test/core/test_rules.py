"""The rule book's public questions (core/rules.py): what faces (HMI diagram, OPC UA
AvailableStates/AvailableTransitions, the coordinator) read instead of drawing their own, checked
against the spec's table as test/core/helpers.py encodes it independently."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from packml_ros2.core import Cmd as C
from packml_ros2.core import Mode, Reason, State, Unit
from packml_ros2.core.rules import GUARDS, Edge, Watch, rules_of

from .helpers import SPEC_COMMAND_TABLE, SPEC_SC_TABLE, FakeClock, Spec, cell_unit, spec_mode

S = State
USER = {"modes": {"cleaning": {"number": 4, "disabled_states": ["Resetting", "Completed"],
                               "mode_change_states": ["Stopped"]}}}  # fmt: skip
SPEC = Spec(modes={**Spec().modes, 4: spec_mode(4, "CLEANING", {S.RESETTING, S.COMPLETE}, {S.STOPPED})})  # fmt: skip


def test_the_model_graph_is_the_spec_table() -> None:
    rules = rules_of(cell_unit({}))
    edges = set(rules.edges())
    commands = {(e.from_state, e.trigger, e.to_state) for e in edges if e.trigger is not None}
    state_complete = {(e.from_state, e.to_state) for e in edges if e.trigger is None}
    table = {(s, c, to) for (s, c), to in SPEC_COMMAND_TABLE.items()}
    assert table <= commands
    assert {(s, C.STOP) for s, c, _ in commands if c is C.STOP} == {
        (s, C.STOP) for s in State if s not in
        (S.UNDEFINED, S.STOPPING, S.STOPPED, S.ABORTING, S.ABORTED, S.CLEARING)
    }  # fmt: skip
    assert state_complete == set(SPEC_SC_TABLE.items())


@pytest.mark.parametrize("mode", [1, 2, 3, 4])
def test_a_modes_graph_has_its_states_and_the_edges_the_unit_takes(mode: int) -> None:
    rules = rules_of(cell_unit(USER))
    disabled = SPEC.modes[mode].disabled
    assert rules.available_states(mode) == frozenset(s for s in State if s) - disabled
    for edge in rules.edges(mode):
        assert edge.from_state not in disabled and edge.to_state not in disabled
        if edge.trigger is None:
            final, skipped = SPEC.state_complete(edge.from_state, mode)  # type: ignore[misc]
        else:
            reason, final, skipped = SPEC.command(edge.from_state, edge.trigger, mode)
            assert reason is Reason.ACCEPTED
        assert (edge.to_state, edge.skipped) == (final, skipped)
    commands = {(e.from_state, e.trigger) for e in rules.edges(mode) if e.trigger is not None}
    expected = {(s, C(c)) for s in rules.available_states(mode) for c in SPEC.valid(s, mode)}
    assert commands == expected


def test_skip_through_shows_in_the_edges_and_the_transitions_available_now() -> None:
    rules = rules_of(cell_unit(USER))
    assert Edge(S.STOPPED, C.RESET, S.IDLE, (S.RESETTING,)) in rules.edges(4)
    now = rules.available_transitions(Mode.PRODUCTION, S.EXECUTE)
    assert {(e.trigger, e.to_state) for e in now} == {
        (C.HOLD, S.HOLDING), (C.SUSPEND, S.SUSPENDING), (C.COMPLETE, S.COMPLETING),
        (C.STOP, S.STOPPING), (C.ABORT, S.ABORTING), (None, S.COMPLETING),
    }  # fmt: skip
    assert rules.valid_commands(S.HELD, Mode.MANUAL) == ()  # Held is disabled in Manual
    assert rules.valid_commands(S.IDLE, 4) == (C.START, C.STOP, C.ABORT)


def test_targets_and_mode_changes_for_the_coordinator() -> None:
    rules = rules_of(cell_unit(USER))
    targets = {c: rules.command_target(c) for c in C if c}
    assert targets == {C.RESET: S.IDLE, C.START: S.EXECUTE, C.STOP: S.STOPPED, C.HOLD: S.HELD,
                       C.UNHOLD: S.EXECUTE, C.SUSPEND: S.SUSPENDED, C.UNSUSPEND: S.EXECUTE,
                       C.ABORT: S.ABORTED, C.CLEAR: S.STOPPED, C.COMPLETE: S.COMPLETE}  # fmt: skip
    assert rules.command_target(C.COMPLETE, 4) is None  # Complete is disabled in cleaning
    assert rules.target(S.STOPPED, 4, C.RESET) == (S.IDLE, (S.RESETTING,))
    assert rules.settles_in(S.UNHOLDING) is S.EXECUTE and rules.settles_in(S.HELD) is S.HELD
    assert rules.mode_change_refusal(1, 4, S.STOPPED) is None
    assert "CLEANING allows mode changes only in STOPPED" in str(rules.mode_change_refusal(1, 4, S.IDLE))  # fmt: skip
    assert rules.mode_change_refusal(1, 9, S.STOPPED) == "mode 9 is not configured"


def test_every_guard_refuses_with_its_reason_and_its_sentence() -> None:
    """The unit's refusals are the rule book's: each guard's reason code and sentence."""
    config = cell_unit({"equipment_modules": {"em1": {}},
                        "alarms": [{"id": 5, "message": "jam", "category": 3}]})  # fmt: skip
    clock = FakeClock()
    unit = Unit(config, clock)
    by_name = {g.name: g for g in GUARDS}
    assert {g.watch for g in GUARDS} == set(Watch)

    def refused(cmd: int, source: str = "operator") -> tuple[Reason, str]:
        answer = unit.command(cmd, source)
        assert not answer.accepted
        return answer.reason, answer.message

    reason, text = refused(C.RESET, "remote:line")
    assert reason is by_name["remote"].reason and "remote commands are disabled on u" in text
    reason, text = refused(C.RESET)  # em1 configured, never seen: missing
    assert reason is by_name["em_missing"].reason and "active EM em1 offline" in text
    assert unit.em_seen("em1").accepted
    assert unit.set_alarm(5).accepted  # category 3: Stop (nothing to stop in Stopped)
    reason, text = refused(C.RESET)
    assert reason is by_name["alarm"].reason and "alarm 5/0" in text and "reaction STOP" in text
    assert unit.set_alarm(5, active=False).accepted and unit.reset_alarms().accepted
    assert unit.set_mode("maintenance").accepted and unit.mode_change_in_process
    reason, text = refused(C.RESET)
    assert reason is by_name["mode_change"].reason
    assert "mode change PRODUCTION -> MAINTENANCE in process (waiting for EMs: em1)" in text
    assert unit.em_complete("em1", S.STOPPED, unit.sequence).accepted
    assert unit.set_interlock(True, "downstream blocked").accepted
    assert "interlock" in by_name and by_name["interlock"].reason is Reason.INTERLOCK_ACTIVE


def test_a_unit_without_interlock_reaction_compiles_no_interlock_guard() -> None:
    assert "interlock" in {g.name for g in rules_of(cell_unit({})).guards}
    assert "interlock" not in {
        g.name for g in rules_of(cell_unit({"interlock_reaction": "none"})).guards
    }


def test_the_readmes_rule_book_example_runs_verbatim(monkeypatch: pytest.MonkeyPatch) -> None:
    root = Path(__file__).resolve().parents[2]
    text = (root / "README.md").read_text(encoding="utf-8")
    block = text.split("### The rule book", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(root)
    names: dict[str, object] = {}
    exec(compile(block, "README.md", "exec"), names)
    r = names["r"]
    assert r.command_target(C.RESET) is S.IDLE  # type: ignore[attr-defined]


# -- the compiled runs (rules.Run): the command fast path of a unit without EMs ----------------------
RUN_UNIT = {
    **USER,
    "alarms": [{"id": 7, "message": "jam", "category": 3, "reaction": "stop"},
               {"id": 8, "message": "door", "category": 6}],
    "timeouts": {"Holding": 30},
    "persistence": False,
}  # fmt: skip
INPUTS = st.one_of(
    st.tuples(st.just("cmd"), st.sampled_from([int(c) for c in C if c])),
    st.tuples(st.just("mode"), st.sampled_from([1, 2, 3, 4])),
    st.tuples(st.just("alarm"), st.sampled_from([7, 8]), st.booleans()),
    st.tuples(st.just("reset_alarms")),
    st.tuples(st.just("interlock"), st.booleans()),
    st.tuples(st.just("wait"), st.sampled_from([0.01, 1.0, 40.0])),
)


def _apply(unit: Unit, clock: FakeClock, step: tuple[Any, ...]) -> object:
    kind, *args = step
    clock.advance(0.001)
    if kind == "cmd":
        return unit.command(args[0])
    if kind == "mode":
        return unit.set_mode(args[0])
    if kind == "alarm":
        return unit.set_alarm(args[0], 0, args[1])
    if kind == "reset_alarms":
        return unit.reset_alarms()
    if kind == "interlock":
        return unit.set_interlock(args[0], "downstream")
    clock.advance(args[0])
    unit.advance()
    return None


def _plain(x: Any) -> Any:
    """``x`` comparable by value (alarm events compare by identity)."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return (type(x).__name__, _plain(dataclasses.astuple(x)))
    if isinstance(x, tuple | list):
        return tuple(_plain(v) for v in x)
    return x


R, STOP, START, HOLD, UNHOLD = (
    ("cmd", int(c)) for c in (C.RESET, C.STOP, C.START, C.HOLD, C.UNHOLD)
)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(INPUTS, min_size=1, max_size=40))
@example([R, STOP, R, START, ("cmd", int(C.COMPLETE)), R])  # a run re-arms the stop reason
@example([R, START, ("interlock", True), ("wait", 1.0), ("interlock", False), HOLD, UNHOLD])
@example(
    [
        R,
        ("alarm", 8, True),
        ("alarm", 8, False),
        START,
        ("cmd", int(C.COMPLETE)),
        ("alarm", 8, True),
        ("alarm", 8, False),
        R,
    ]
)  # entry actions with something to reset
@example([R, START, ("interlock", True), ("cmd", int(C.COMPLETE)), ("interlock", False), R])
@example([("mode", 4), R, START, ("cmd", int(C.COMPLETE)), R])  # skip-through
@example([R, START, HOLD, ("wait", 40.0), UNHOLD])  # a timed state: no run
def test_a_compiled_run_does_what_the_general_loop_does(steps: list[tuple[Any, ...]]) -> None:
    """The fast path follows a command through the State Completes that come at once as
    compiled (Accepted.run); a unit whose rules compile no run takes the general loop
    (Unit._transition). Same answers, outputs, status and admin after every input."""
    clocks = FakeClock(), FakeClock()
    fast = Unit(cell_unit(RUN_UNIT), clock=clocks[0])
    general_config = cell_unit(RUN_UNIT)
    rules = rules_of(general_config)
    for by_state in rules.accepted.values():
        for by_cmd in by_state:
            for cmd, entry in by_cmd.items():
                by_cmd[cmd] = entry._replace(run=None)
    general = Unit(general_config, clock=clocks[1])
    assert any(e.run for by_state in rules_of(fast.config).accepted.values()
               for by_cmd in by_state for e in by_cmd.values())  # fmt: skip
    for step in steps:
        answers = [
            _apply(unit, clock, step) for unit, clock in zip((fast, general), clocks, strict=True)
        ]
        assert answers[0] == answers[1], step
        assert _plain(fast.drain()) == _plain(general.drain()), step
        assert _plain(fast.status()) == _plain(general.status()), step
        assert _plain(fast.admin()) == _plain(general.admin()), step
        assert (fast.state, fast.sequence, fast.stops.armed, fast.interlocks.suspended) == (
            general.state,
            general.sequence,
            general.stops.armed,
            general.interlocks.suspended,
        ), step


def test_the_fast_path_is_generated_from_the_compiled_runs() -> None:
    """Every accepted command with a run has its code generated from it (core/fastpath.py): the
    run's records unrolled, its constants bound by name; the engine reads the compiled entries by
    name, not by position."""
    import inspect

    from packml_ros2.core import fastpath
    from packml_ros2.core.machine import UnitMachine

    unit = Unit(cell_unit(RUN_UNIT), clock=FakeClock())
    runs = [
        e
        for by_state in rules_of(unit.config).accepted.values()
        for by_cmd in by_state
        for e in by_cmd.values()
        if e.run is not None
    ]
    assert runs
    for e in runs:
        assert e.run is not None and e.go is not None
        assert e.go.__code__.co_filename.startswith("<packml run ")
        source = fastpath.source_of(e.run)
        assert "for " not in source and "while " not in source
        assert source.count("out(('transition'") == 2 + len(e.run.tails)
    command = inspect.getsource(UnitMachine.command)
    assert "entry[" not in command and "run[" not in command


def test_the_category_of_a_reaction_is_derived_from_the_default_reactions() -> None:
    from packml_ros2.core.rules import (
        CATEGORY_OF_REACTION,
        DEFAULT_REACTIONS,
        NUM_CATEGORIES,
        REACTIONS,
    )

    assert set(CATEGORY_OF_REACTION) == set(REACTIONS.values())
    for reaction, category in CATEGORY_OF_REACTION.items():
        if not reaction:
            assert category == NUM_CATEGORIES - 1 and DEFAULT_REACTIONS[category] == 0
        elif reaction in DEFAULT_REACTIONS.values():  # the first category that reacts so
            assert DEFAULT_REACTIONS[category] == reaction
            assert all(DEFAULT_REACTIONS[c] != reaction for c in range(category))
        else:  # no category reacts so by default: the first that does not react by itself
            assert DEFAULT_REACTIONS[category] == 0
            assert all(DEFAULT_REACTIONS[c] for c in range(category))


def test_an_interlock_suspension_passes_through_the_acting_state_of_its_command() -> None:
    from packml_ros2.core.rules import (
        INTERLOCK_PATH,
        INTERLOCK_RESUME,
        INTERLOCK_SUSPEND,
        STATE_COMPLETE,
        build_table,
    )

    on_the_way = build_table().target(*INTERLOCK_SUSPEND)
    assert on_the_way is not None and STATE_COMPLETE[on_the_way] is INTERLOCK_RESUME[0]
    assert {INTERLOCK_SUSPEND[0], on_the_way, INTERLOCK_RESUME[0]} == INTERLOCK_PATH
