"""Conformance of the engine with docs/packml.md sections 1-3, table-driven.

The expected behaviour is the spec's table encoded in :mod:`helpers` (``Spec``), not the engine's
``transitions.py``/``modes.py``. Every (configuration, mode, state, command) combination and every
State Complete is its own test id. Units carry one EM ("em1") so acting states wait for its State
Complete report; they are driven into each state along a path of the spec's graph.
"""

from __future__ import annotations

import functools
import itertools
from typing import Any

import pytest

from packml_ros2.core import Cmd as C
from packml_ros2.core import (
    CommandRequest,
    CompleteReport,
    Mode,
    ModeRequest,
    Reason,
    State,
    Trigger,
    Unit,
    parse_state,
)

from .helpers import (
    ALL_STATES,
    BAD_COMMANDS,
    COMMANDS,
    DEFAULT_CHANGE,
    DEFAULT_SPEC_MODES,
    SPEC_ACTING,
    SPEC_COMMAND_NUMBERS,
    SPEC_MODE_NUMBERS,
    SPEC_STATE_NUMBERS,
    SPEC_WAIT,
    FakeClock,
    Spec,
    cell_unit,
    drive,
    spec_mode,
    transitions,
    valid_text,
)

S = State

# -- the configurations under test ------------------------------------------------------------------------
USER_MODES_YAML = {
    # Resetting and Starting skipped; Complete (and so Completing) disabled.
    "cleaning": {
        "number": 4,
        "disabled_states": ["Resetting", "Starting", "Completed"],
        "mode_change_states": ["Stopped", "Idle", "Aborted", "Held"],
    },
    # Stopping, Aborting, Clearing skipped; the Suspend group off.
    "semiauto": {
        "number": 5,
        "disabled_states": ["stopping", "ABORTING", "Clearing", "Suspended"],
        "mode_change_states": ["Stopped", "Held", "Complete"],
    },
    # Hold group off; Unsuspending and Completing skipped; mode change listed in Held, which
    # is disabled here (a change into jog in Held is refused).
    "jog": {
        "number": 6,
        "disabled_states": ["Held", "Unsuspending", "Completing"],
        "mode_change_states": ["Stopped", "Held", "Suspended", "Complete"],
    },
}
USER_SPEC_MODES = {
    4: spec_mode(4, "CLEANING", {S.RESETTING, S.STARTING, S.COMPLETE},
                 {S.STOPPED, S.IDLE, S.ABORTED, S.HELD}),
    5: spec_mode(5, "SEMIAUTO", {S.STOPPING, S.ABORTING, S.CLEARING, S.SUSPENDED},
                 {S.STOPPED, S.HELD, S.COMPLETE}),
    6: spec_mode(6, "JOG", {S.HELD, S.UNSUSPENDING, S.COMPLETING},
                 {S.STOPPED, S.HELD, S.SUSPENDED, S.COMPLETE}),
}  # fmt: skip
MASK_HOLD = frozenset({S.EXECUTE, S.STARTING, S.UNSUSPENDING})
MASK_COMPLETE = frozenset({S.EXECUTE, S.HELD, S.STARTING})

VARIANTS: dict[str, tuple[dict[str, Any], Spec]] = {
    "tr2022": (
        {"modes": USER_MODES_YAML},
        Spec(modes={**DEFAULT_SPEC_MODES, **USER_SPEC_MODES}),
    ),
    "tr2015": ({"model": "2015"}, Spec(model="2015")),
    "masks": (
        {
            "hold_from": ["execute", "starting", "unsuspending"],
            "complete_from": ["EXECUTE", "Held", "starting"],
        },
        Spec(hold_from=MASK_HOLD, complete_from=MASK_COMPLETE),
    ),
}


@functools.cache
def config(variant: str, mode: int, with_em: bool = True) -> Any:
    extra, spec = VARIANTS[variant]
    unit: dict[str, Any] = {**extra, "initial_mode": spec.modes[mode].name.lower()}
    if with_em:
        unit["equipment_modules"] = {"em1": {"sim": {}}}
    else:
        unit["allow_registration"] = False
    return cell_unit(unit)


def make_unit(variant: str, mode: int, with_em: bool = True) -> tuple[Unit, FakeClock]:
    clock = FakeClock()
    unit = Unit(config(variant, mode, with_em), clock)
    if with_em:
        assert unit.em_seen("em1").accepted
    assert unit.state is S.STOPPED and unit.mode == mode
    return unit, clock


def reach(variant: str, mode: int, state: State) -> Unit:
    spec = VARIANTS[variant][1]
    unit, _ = make_unit(variant, mode)
    drive(unit, spec.reachable(mode)[state])
    assert unit.state is state
    unit.drain()
    return unit


def cmd_id(cmd: int) -> str:
    return C(cmd).name if 0 <= cmd <= 10 else f"CMD{cmd}"


def reachable_cases(
    variant_filter: tuple[str, ...] = tuple(VARIANTS),
) -> list[tuple[str, int, State]]:
    out = []
    for variant in variant_filter:
        spec = VARIANTS[variant][1]
        for mode in spec.modes:
            out.extend((variant, mode, s) for s in sorted(spec.reachable(mode)))
    return out


def case_id(variant: str, mode: int, state: State) -> str:
    return f"{variant}-{VARIANTS[variant][1].modes[mode].name}-{state.name}"


COMMAND_CASES = [
    pytest.param(v, m, s, c, id=f"{case_id(v, m, s)}-{cmd_id(c)}")
    for v, m, s in reachable_cases()
    for c in (*COMMANDS, *BAD_COMMANDS)
]
SC_CASES = [pytest.param(v, m, s, id=case_id(v, m, s)) for v, m, s in reachable_cases()]
MODE_CASES = [pytest.param(v, m, id=f"{v}-{spec.modes[m].name}") for v, (_, spec) in VARIANTS.items()
              for m in spec.modes]  # fmt: skip


# -- section 1: numbers ------------------------------------------------------------------------------------
def test_state_numbers_match_spec() -> None:
    assert {s.name: int(s) for s in State} == SPEC_STATE_NUMBERS
    assert SPEC_ACTING | SPEC_WAIT == ALL_STATES
    assert not SPEC_ACTING & SPEC_WAIT


def test_command_and_mode_numbers_match_spec() -> None:
    assert {c.name: int(c) for c in C} == SPEC_COMMAND_NUMBERS
    assert {m.name: int(m) for m in Mode} == SPEC_MODE_NUMBERS


@pytest.mark.parametrize("text", ["Completed", "COMPLETE", "complete", "17"])
def test_complete_accepts_both_names(text: str) -> None:
    assert parse_state(text) is S.COMPLETE


def test_reason_codes_of_refusals_are_distinct() -> None:
    codes = {Reason.UNKNOWN_COMMAND, Reason.COMMAND_NOT_ALLOWED, Reason.STATE_DISABLED,
             Reason.MODE_CHANGE_NOT_ALLOWED, Reason.SUPERSEDED, Reason.ACCEPTED}  # fmt: skip
    assert len({int(c) for c in codes}) == len(codes)


# -- sections 2 and 3: every (mode, state, command) ----------------------------------------------------------
@pytest.mark.parametrize(("variant", "mode", "state", "cmd"), COMMAND_CASES)
def test_command(variant: str, mode: int, state: State, cmd: int) -> None:
    spec = VARIANTS[variant][1]
    unit = reach(variant, mode, state)
    seq = unit.sequence
    reason, final, skipped = spec.command(state, cmd, mode)
    answer = unit.command(cmd)
    records = transitions(unit)
    if reason is Reason.ACCEPTED:
        assert final is not None
        assert answer.accepted and answer.reason is Reason.ACCEPTED, answer
        assert C(cmd).name in answer.message and final.name in answer.message
        assert unit.state is final
        assert len(records) == 1
        tr = records[0]
        assert (tr.from_state, tr.to_state, tr.command, tr.sequence) == (state, final, cmd, seq + 1)
        assert tr.skipped == skipped
        assert tr.trigger is (Trigger.SKIP if skipped else Trigger.COMMAND)
        assert tr.from_mode == tr.to_mode == mode
        return
    assert not answer.accepted
    assert answer.reason is reason, answer
    assert unit.state is state and unit.sequence == seq and records == []
    mode_name = spec.modes[mode].name
    valid = valid_text(spec.valid(state, mode))
    assert answer.message.endswith(f"(valid now: {valid})"), answer.message
    assert state.name in answer.message and f"{mode_name} mode" in answer.message
    if reason is Reason.COMMAND_NOT_ALLOWED:
        expected = (
            f"{C(cmd).name} not allowed in {state.name} in {mode_name} mode (valid now: {valid})"
        )
        assert answer.message == expected
    elif reason is Reason.STATE_DISABLED:
        assert final is not None
        assert answer.message.startswith(f"{C(cmd).name} not allowed in {state.name}")
        assert f"{final.name} is disabled" in answer.message
    else:
        assert reason is Reason.UNKNOWN_COMMAND
        assert answer.message.startswith(f"command {cmd} is not a PackML command")


@pytest.mark.parametrize(("variant", "mode", "state"), SC_CASES)
def test_state_complete(variant: str, mode: int, state: State) -> None:
    spec = VARIANTS[variant][1]
    unit = reach(variant, mode, state)
    seq = unit.sequence
    stale_before = unit.stats.stale_reports
    # Reports for an older sequence number or another state are stale: ignored and counted.
    other = S.RESETTING if state is not S.RESETTING else S.STARTING
    for st, sq in ((state, seq - 1), (other, seq), (state, seq + 1)):
        answer = unit.em_complete("em1", st, sq)
        assert not answer.accepted and answer.reason is Reason.NOTHING_TO_DO
    assert unit.stats.stale_reports == stale_before + 3
    assert unit.status().equipment[0].stale_reports == 3
    assert unit.state is state and transitions(unit) == []

    expected = spec.state_complete(state, mode)
    answer = unit.em_complete("em1", state, seq)
    records = transitions(unit)
    if expected is None:  # a wait state: SC is ignored and counted
        assert state in SPEC_WAIT
        assert not answer.accepted and answer.reason is Reason.NOTHING_TO_DO
        assert unit.stats.stale_reports == stale_before + 4
        assert unit.state is state and records == []
        return
    final, skipped = expected
    assert answer.accepted
    if final in spec.modes[mode].disabled:  # e.g. Execute in Manual: Complete is disabled
        assert unit.state is state and records == []
        assert unit.stats.sc_ignored == 1
        return
    assert unit.state is final
    assert len(records) == 1
    tr = records[0]
    assert (tr.from_state, tr.to_state, tr.sequence, tr.command) == (state, final, seq + 1, 0)
    assert tr.skipped == skipped
    assert tr.trigger is (Trigger.SKIP if skipped else Trigger.STATE_COMPLETE)


@pytest.mark.parametrize(("variant", "mode"), MODE_CASES)
def test_engine_graph_matches_spec(variant: str, mode: int) -> None:
    """Explore the engine's reachable graph by commands and SC; it is the spec's, and a
    disabled state is never reached (nor reported enabled)."""
    spec = VARIANTS[variant][1]
    disabled = spec.modes[mode].disabled
    paths: dict[State, list[tuple[Any, ...]]] = {S.STOPPED: []}
    edges: set[tuple[State, tuple[Any, ...], State]] = set()
    queue = [S.STOPPED]
    while queue:
        state = queue.pop(0)
        actions: list[tuple[Any, ...]] = [("cmd", C(c)) for c in range(1, 11)] + [("sc",)]
        for action in actions:
            unit, _ = make_unit(variant, mode)
            drive(unit, paths[state])
            seq = unit.sequence
            if action[0] == "cmd":
                ok = unit.command(action[1]).accepted
            else:
                ok = unit.em_complete("em1", state, seq).accepted and unit.sequence != seq
            if not ok:
                continue
            edges.add((state, action, unit.state))
            if unit.state not in paths:
                paths[unit.state] = [*paths[state], action]
                queue.append(unit.state)
    expected_edges = {
        (s, action, to) for s in spec.reachable(mode) for action, to in spec.edges(s, mode)
    }
    assert edges == expected_edges
    assert set(paths) == ALL_STATES - disabled
    unit, _ = make_unit(variant, mode)
    mask = sum(1 << int(s) for s in disabled)
    assert unit.status().states_disabled == mask
    assert unit.admin().states_disabled == mask


# -- units without EMs: acting states complete at once, Execute waits for a command ----------------------------
def rest_paths(spec: Spec, mode: int) -> dict[State, list[int]]:
    paths: dict[State, list[int]] = {S.STOPPED: []}
    queue = [S.STOPPED]
    while queue:
        state = queue.pop(0)
        for c in range(1, 11):
            reason, final, _ = spec.command(state, c, mode)
            if reason is not Reason.ACCEPTED or final is None:
                continue
            rest = spec.settle(final, mode)
            if rest not in paths:
                paths[rest] = [*paths[state], c]
                queue.append(rest)
    return paths


NO_EM_CASES = [
    pytest.param(v, m, s, c, id=f"{case_id(v, m, s)}-{cmd_id(c)}")
    for v, (_, spec) in VARIANTS.items()
    for m in spec.modes
    for s in sorted(rest_paths(spec, m))
    for c in range(1, 11)
]


@pytest.mark.parametrize(("variant", "mode", "state", "cmd"), NO_EM_CASES)
def test_command_without_ems(variant: str, mode: int, state: State, cmd: int) -> None:
    spec = VARIANTS[variant][1]
    unit, _ = make_unit(variant, mode, with_em=False)
    for c in rest_paths(spec, mode)[state]:
        assert unit.command(c).accepted
    assert unit.state is state
    unit.drain()
    reason, final, _ = spec.command(state, cmd, mode)
    answer = unit.command(cmd)
    assert answer.reason is reason
    if reason is not Reason.ACCEPTED:
        assert unit.state is state
        return
    assert final is not None
    chain = [final]
    while chain[-1] in SPEC_ACTING and chain[-1] is not S.EXECUTE:
        sc = spec.state_complete(chain[-1], mode)
        assert sc is not None
        if sc[0] in spec.modes[mode].disabled:
            break
        chain.append(sc[0])
    records = transitions(unit)
    assert [r.to_state for r in records] == chain
    assert all(r.trigger in (Trigger.STATE_COMPLETE, Trigger.SKIP) for r in records[1:])
    assert unit.state is chain[-1]


# -- section 3: the mode-change matrix ---------------------------------------------------------------------------
MODE_CHANGE_CASES = [
    pytest.param(m, target, s, id=f"{case_id('tr2022', m, s)}-to-{VARIANTS['tr2022'][1].modes[target].name}")
    for _, m, s in reachable_cases(("tr2022",))
    for target in VARIANTS["tr2022"][1].modes
    if target != m
]  # fmt: skip


@pytest.mark.parametrize(("mode", "target", "state"), MODE_CHANGE_CASES)
def test_mode_change(mode: int, target: int, state: State) -> None:
    spec = VARIANTS["tr2022"][1]
    unit = reach("tr2022", mode, state)
    seq = unit.sequence
    a, b = spec.modes[mode], spec.modes[target]
    allowed = state in a.change_allowed and state in b.change_allowed and state not in b.disabled
    by_name = target % 2 == 0  # by number and by name
    answer = unit.set_mode(b.name.lower() if by_name else target)
    if not allowed:
        assert not answer.accepted and answer.reason is Reason.MODE_CHANGE_NOT_ALLOWED, answer
        assert a.name in answer.message and b.name in answer.message
        assert state.name in answer.message
        assert unit.mode == mode and unit.state is state and unit.sequence == seq
        assert unit.mode_change_not_allowed and unit.status().mode_change_not_allowed
        assert transitions(unit) == []
        return
    assert answer.accepted, answer
    # In process until the (only) EM reports complete for (state, new sequence).
    assert unit.mode_change_in_process and unit.mode == mode
    status = unit.status()
    assert status.unit_mode_requested == target and status.unit_mode_change_in_process
    assert unit.sequence == seq + 1
    assert not unit.em_complete("em1", state, seq).accepted  # stale
    assert unit.em_complete("em1", state, seq + 1).accepted
    assert not unit.mode_change_in_process
    assert unit.mode == target and unit.state is state  # the state never changes with the mode
    records = transitions(unit)
    assert len(records) == 1
    tr = records[0]
    assert (tr.from_mode, tr.to_mode, tr.from_state, tr.to_state) == (mode, target, state, state)
    assert tr.trigger is Trigger.MODE and tr.sequence == seq + 1
    assert unit.status().states_disabled == sum(1 << int(s) for s in b.disabled)


@pytest.mark.parametrize(("variant", "mode"), MODE_CASES)
def test_mode_change_to_same_mode_changes_nothing(variant: str, mode: int) -> None:
    unit, _ = make_unit(variant, mode)
    seq = unit.sequence
    answer = unit.set_mode(mode)
    assert answer.accepted and not unit.mode_change_in_process
    assert unit.sequence == seq and unit.mode == mode


def test_default_modes() -> None:
    unit, _ = make_unit("tr2015", 1)  # any variant: the default modes are the same
    cfg = unit.config
    assert {n: (m.name, set(m.disabled), set(m.change_allowed)) for n, m in cfg.modes.items()} == {
        n: (m.name, set(m.disabled), set(DEFAULT_CHANGE)) for n, m in DEFAULT_SPEC_MODES.items()
    }
    assert cfg.initial_mode == Mode.PRODUCTION


def test_unknown_mode_is_refused() -> None:
    unit, _ = make_unit("tr2022", 1)
    for mode in (0, 7, 31, "nonsense"):
        answer = unit.set_mode(mode)
        assert not answer.accepted and answer.reason is Reason.MODE_UNKNOWN
    assert unit.mode == 1 and unit.state is S.STOPPED


# -- section 2: priority in one evaluation step ------------------------------------------------------------------
PRIORITY = {C.ABORT: 0, C.STOP: 1, C.HOLD: 2, C.SUSPEND: 3}
PRIORITY_CASES = [
    pytest.param(state, c1, c2, id=f"{state.name}-{c1.name}-{c2.name}")
    for state in sorted(ALL_STATES)
    for c1, c2 in itertools.permutations(VARIANTS["tr2022"][1].valid(state, 1), 2)
]


@pytest.mark.parametrize(("state", "c1", "c2"), PRIORITY_CASES)
def test_step_priority(state: State, c1: C, c2: C) -> None:
    """Two valid commands, a State Complete report and a mode change in one step: the
    higher-priority command wins, the other is superseded, the report is stale and the mode
    change is judged in the new state."""
    spec = VARIANTS["tr2022"][1]
    unit = reach("tr2022", 1, state)
    seq = unit.sequence
    winner = min((c1, c2), key=lambda c: (PRIORITY.get(c, 4), (c1, c2).index(c)))
    loser = c2 if winner is c1 else c1
    _, final, _ = spec.command(state, winner, 1)
    requests = [
        CompleteReport("em1", state, seq),
        ModeRequest("maintenance"),
        CommandRequest(c1),
        CommandRequest(c2),
    ]
    answers = unit.step(requests)
    assert unit.state is final
    by_cmd = {c1: answers[2], c2: answers[3]}
    assert by_cmd[winner].accepted
    assert not by_cmd[loser].accepted
    assert by_cmd[loser].reason is Reason.SUPERSEDED, by_cmd[loser]
    assert winner.name in by_cmd[loser].message
    if state in SPEC_ACTING:
        assert not answers[0].accepted and answers[0].reason is Reason.NOTHING_TO_DO
    assert answers[1].reason is Reason.MODE_CHANGE_NOT_ALLOWED
    assert unit.mode == 1
    assert [r.to_state for r in transitions(unit)] == [final]
