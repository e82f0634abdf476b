"""The engine against an independent oracle over long random sequences of inputs.

The oracle is a small dict-based model of docs/packml.md (sections 2-4, 7) written here: the state
table comes from :class:`helpers.Spec`, everything else (EM aggregation, losses, alarms and their
reactions, mode changes, timeouts, minimum dwell, priorities in one step) is modelled below from
the spec and the decided engine semantics. Every answer's reason and the state, mode, sequence,
pending EMs, alarms, stop reason and per-(mode, state) times are compared after every rule.
"""

from __future__ import annotations

import heapq
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
)

from packml_ros2.core import Cmd as C
from packml_ros2.core import (
    CommandRequest,
    CompleteReport,
    ModeRequest,
    Reason,
    State,
    Trigger,
    Unit,
)
from packml_ros2.core.numbers import NUM_STATES

from .helpers import (
    DEFAULT_SPEC_MODES,
    MOTION,
    SPEC_ACTING,
    SPEC_WAIT,
    FakeClock,
    Spec,
    cell_unit,
    spec_mode,
)

S = State
T0 = 10_000.0

UNIT = {
    "modes": {
        "maintenance": {"mode_change_states": ["Stopped", "Idle", "Aborted", "Held"]},
        "cleaning": {
            "number": 4,
            "disabled_states": ["Resetting", "Complete"],
            "mode_change_states": ["Stopped", "Idle", "Aborted", "Held"],
        },
    },
    "equipment_modules": {
        "a": {},
        "b": {"lost_reaction": "hold"},
        "c": {"lost_reaction": "ignore"},
        "d": {"active": False, "lost_reaction": "stop"},
    },
    "allow_registration": True,  # (a listed EM set is closed by default)
    "alarms": [
        {"id": 101, "message": "e-stop", "category": 0},
        {"id": 102, "message": "guard open", "category": 3},
        {"id": 103, "message": "info", "category": 6},
        {"id": 104, "message": "jam", "category": 7, "reaction": "hold"},
        {"id": 105, "message": "no material", "category": 5, "reaction": "suspend"},
        {"id": 106, "message": "low air", "category": 0, "warning": True},
    ],
    "timeouts": {"Starting": 5, "Holding": 3, "Clearing": 4},
    "min_dwell": {"Clearing": 1, "Completing": 0.5},
    "mode_change_timeout": 4,
    "admin_period": 100000,
}
SPEC = Spec(
    modes={
        1: DEFAULT_SPEC_MODES[1],
        2: spec_mode(2, "MAINTENANCE", DEFAULT_SPEC_MODES[2].disabled,
                     {S.STOPPED, S.IDLE, S.ABORTED, S.HELD}),
        3: DEFAULT_SPEC_MODES[3],
        4: spec_mode(4, "CLEANING", {S.RESETTING, S.COMPLETE}, {S.STOPPED, S.IDLE, S.ABORTED, S.HELD}),
    }
)  # fmt: skip
#: Alarm definitions: id -> (category, reaction override or None, warning).
ALARMS = {
    101: (0, None, False),
    102: (3, None, False),
    103: (6, None, False),
    104: (7, C.HOLD, False),
    105: (5, C.SUSPEND, False),
    106: (0, None, True),
}
#: docs/packml.md §7: 0-1 Abort, 2-4 Stop, 5-9 none.
CATEGORY_REACTION = {0: C.ABORT, 1: C.ABORT, 2: C.STOP, 3: C.STOP, 4: C.STOP}
EM_LOST, STATE_TIMEOUT, MODE_TIMEOUT = 9001, 9002, 9003
TIMEOUTS = {S.STARTING: 5.0, S.HOLDING: 3.0, S.CLEARING: 4.0}
DWELL = {S.CLEARING: 1.0, S.COMPLETING: 0.5}
MODE_CHANGE_TIMEOUT = 4.0
EXCUSED_IN = {S.STOPPING, S.ABORTING, S.CLEARING}
PRIORITY = {C.ABORT: 0, C.STOP: 1, C.HOLD: 2, C.SUSPEND: 3}
STOP_STATES = {S.STOPPING, S.ABORTING, S.HOLDING, S.SUSPENDING}
REARM_STATES = {S.RESETTING, S.STARTING, S.UNHOLDING, S.UNSUSPENDING}
OPERATOR_STOP, REMOTE_STOP = 33, 4006
EM_NAMES = ["a", "b", "c", "d", "x"]


def blocks(reaction: int, cmd: int) -> bool:
    """While an alarm with ``reaction`` is active: motion refused, and Clear when it aborts."""
    if not reaction:
        return False
    return cmd in MOTION or (cmd == C.CLEAR and reaction == C.ABORT)


@dataclass
class OEm:
    name: str
    index: int
    active: bool = True
    online: bool = False
    lost: int = C.ABORT  # reaction on loss; 0 = ignore
    last: tuple[int, int] | None = None


@dataclass
class OAlarm:
    trigger: bool
    reaction: int  # as stored at the first occurrence


@dataclass
class Oracle:
    t: float = T0
    state: State = S.STOPPED
    mode: int = 1
    seq: int = 1  # the start-up transition into Stopped
    entered: float = T0
    ems: dict[str, OEm] = field(default_factory=dict)
    aggregating: bool = False
    pending: set[str] = field(default_factory=set)
    alarms: dict[tuple[int, int], OAlarm] = field(default_factory=dict)
    mode_target: int | None = None
    sc_refused: int = -1
    deadlines: list[tuple[float, int, str, Any]] = field(default_factory=list)
    counter: int = 0
    internal: list[tuple[int, str, int]] = field(default_factory=list)  # (cmd, source, stop id)
    stop_id: int = 0
    armed: bool = True
    remote: bool = False
    winner: int | None = None
    cum: dict[tuple[int, int], float] = field(default_factory=lambda: defaultdict(float))
    since: float = T0

    def __post_init__(self) -> None:
        for i, (name, active, lost) in enumerate(
            [("a", True, C.ABORT), ("b", True, C.HOLD), ("c", True, 0), ("d", False, C.STOP)]
        ):
            self.ems[name] = OEm(name, i + 1, active, False, lost)

    # -- time ----------------------------------------------------------------------------------------
    def _at(self, when: float, kind: str, data: Any) -> None:
        self.counter += 1
        heapq.heappush(self.deadlines, (when, self.counter, kind, data))

    def advance(self, now: float) -> None:
        while self.deadlines and self.deadlines[0][0] <= now:
            when, _, kind, data = heapq.heappop(self.deadlines)
            self.t = max(self.t, when)
            if kind == "timeout" and (self.state, self.seq) == data:
                key = (STATE_TIMEOUT, int(data[0]))
                self._raise(key, C.STOP, f"alarm:{STATE_TIMEOUT}")  # category 2: Stop
                self.alarms[key].trigger = False
            elif kind == "mode_timeout" and self.mode_target is not None and self.seq == data:
                key = (MODE_TIMEOUT, self.mode_target)
                self.mode_target = None
                self.aggregating, self.pending = False, set()
                self._raise(key, 0, "unit")  # category 5: no reaction
                self.alarms[key].trigger = False
            self.settle()
        self.t = max(self.t, now)

    def _close(self) -> None:
        self.cum[(self.mode, int(self.state))] += self.t - self.since
        self.since = self.t

    # -- alarms ----------------------------------------------------------------------------------------
    def _raise(self, key: tuple[int, int], reaction: int, source: str) -> bool:
        ev = self.alarms.get(key)
        if ev is not None and ev.trigger:
            return False
        if ev is None:
            self.alarms[key] = OAlarm(True, reaction)
        else:
            ev.trigger = True
        if reaction:
            self.internal.append((reaction, source, key[0]))
        return True

    def _clear(self, key: tuple[int, int]) -> bool:
        ev = self.alarms.get(key)
        if ev is None or not ev.trigger:
            return False
        ev.trigger = False
        return True

    def reset_alarms(self) -> None:
        self.alarms = {k: ev for k, ev in self.alarms.items() if ev.trigger}

    # -- EMs ---------------------------------------------------------------------------------------------
    def missing(self) -> bool:
        return any(em.active and not em.online and em.lost for em in self.ems.values())

    def _begin(self) -> None:
        s = self.state
        if s is S.EXECUTE:
            self.aggregating = any(em.active for em in self.ems.values())
            excuse = False
        elif s in SPEC_ACTING:
            self.aggregating = True
            excuse = s in EXCUSED_IN
        else:
            self.aggregating, self.pending = False, set()
            return
        self.pending = {
            em.name
            for em in self.ems.values()
            if em.active and (em.online or not (excuse or not em.lost))
        }

    def _require(self, em: OEm) -> None:
        if self.aggregating and em.active and em.online and em.last != (self.state, self.seq):
            self.pending.add(em.name)

    # -- the state machine ------------------------------------------------------------------------------
    def _transition(self, to: State, skipped: tuple[State, ...], stop_id: int) -> None:
        self._close()
        self.seq += 1
        self.state = to
        self.entered = self.t
        for s in (*skipped, to):
            if s in (S.RESETTING, S.CLEARING):
                self.reset_alarms()
            if s in REARM_STATES:
                self.armed = True
            elif s in STOP_STATES and self.armed:
                self.stop_id, self.armed = stop_id, False
        self._begin()
        if to in TIMEOUTS:
            self._at(self.t + TIMEOUTS[to], "timeout", (to, self.seq))
        if to in DWELL:
            self._at(self.t + DWELL[to], "dwell", None)

    def _apply(self, cmd: int, source: str, start: State, stop_id: int) -> Reason:
        if not 1 <= cmd <= 10:
            return Reason.UNKNOWN_COMMAND
        if source.startswith("remote") and not self.remote:
            return Reason.REMOTE_DISABLED
        if self.mode_target is not None and cmd not in (C.ABORT, C.STOP):
            return Reason.MODE_CHANGE_IN_PROCESS
        reason, final, skipped = SPEC.command(self.state, cmd, self.mode)
        if reason is not Reason.ACCEPTED or final is None:
            was_valid = SPEC.command(start, cmd, self.mode)[0] is Reason.ACCEPTED
            if self.winner is not None and reason is Reason.COMMAND_NOT_ALLOWED and was_valid:
                return Reason.SUPERSEDED
            return reason
        if cmd in MOTION and self.missing():
            return Reason.EM_MISSING
        if any(ev.trigger and blocks(ev.reaction, cmd) for ev in self.alarms.values()):
            return Reason.ALARM_ACTIVE
        self.mode_target = None  # Abort/Stop abandon a mode change in process
        if not stop_id:
            stop_id = REMOTE_STOP if source.startswith("remote") else OPERATOR_STOP
        self._transition(final, skipped, stop_id)
        self.winner = cmd
        return Reason.ACCEPTED

    def settle(self) -> None:
        for _ in range(100):
            if self.internal:
                queue = sorted(self.internal, key=lambda r: PRIORITY.get(r[0], 4))
                self.internal = []
                start, self.winner = self.state, None
                for cmd, source, stop_id in queue:
                    self._apply(cmd, source, start, stop_id)
                continue
            if self.mode_target is not None:
                if self.pending and self.aggregating:
                    return
                self._close()
                self.mode, self.mode_target = self.mode_target, None
                self.aggregating, self.pending = False, set()
                continue
            dwell_ok = self.t >= self.entered + DWELL.get(self.state, 0.0)
            if self.aggregating and not self.pending and self.sc_refused != self.seq and dwell_ok:
                sc = SPEC.state_complete(self.state, self.mode)
                assert sc is not None
                final, skipped = sc
                if final not in SPEC.modes[self.mode].disabled:
                    self._transition(final, skipped, 0)
                    continue
                self.sc_refused = self.seq
            return
        raise AssertionError("oracle does not settle")

    # -- inputs (each returns the expected reason) ----------------------------------------------------------
    def command(self, cmd: int, source: str) -> Reason:
        self.winner = None
        reason = self._apply(cmd, source, self.state, 0)
        self.settle()
        return reason

    def _report(self, name: str, state: int, seq: int) -> Reason:
        em = self.ems.get(name)
        if em is None:
            return Reason.EM_UNKNOWN
        if state != self.state or seq != self.seq or not self.aggregating:
            return Reason.NOTHING_TO_DO
        em.last = (state, seq)
        self.pending.discard(name)
        return Reason.ACCEPTED

    def report(self, name: str, state: int, seq: int) -> Reason:
        reason = self._report(name, state, seq)
        if reason is Reason.ACCEPTED and not self.pending:
            self.settle()
        return reason

    def _mode(self, mode: int | str, source: str) -> Reason:
        if isinstance(mode, str):
            number = next((n for n, m in SPEC.modes.items() if m.name == mode.upper()), None)
        else:
            number = mode if mode in SPEC.modes else None
        if number is None:
            return Reason.MODE_UNKNOWN
        if source.startswith("remote") and not self.remote:
            return Reason.REMOTE_DISABLED
        if self.mode_target is not None:
            return Reason.MODE_CHANGE_IN_PROCESS
        if number == self.mode:
            return Reason.ACCEPTED
        a, b = SPEC.modes[self.mode], SPEC.modes[number]
        if not (
            self.state in a.change_allowed
            and self.state in b.change_allowed
            and self.state not in b.disabled
        ):
            return Reason.MODE_CHANGE_NOT_ALLOWED
        self.mode_target = number
        self.seq += 1
        self.aggregating = any(em.active for em in self.ems.values())
        self.pending = {em.name for em in self.ems.values() if em.active and em.online}
        self._at(self.t + MODE_CHANGE_TIMEOUT, "mode_timeout", self.seq)
        return Reason.ACCEPTED

    def set_mode(self, mode: int | str, source: str) -> Reason:
        reason = self._mode(mode, source)
        self.settle()
        return reason

    def step(self, requests: list[Any]) -> list[Reason]:
        start, self.winner = self.state, None
        out: list[Reason] = [Reason.ACCEPTED] * len(requests)

        def prio(i: int) -> int:
            r = requests[i]
            if isinstance(r, CommandRequest):
                return PRIORITY.get(r.cmd, 4)
            return 5 if isinstance(r, ModeRequest) else 6

        for i in sorted(range(len(requests)), key=prio):
            r = requests[i]
            if isinstance(r, CommandRequest):
                out[i] = self._apply(r.cmd, r.source, start, 0)
            elif isinstance(r, ModeRequest):
                out[i] = self._mode(r.mode, r.source)
            else:
                out[i] = self._report(r.em, r.state, r.sequence)
        self.settle()
        return out

    def em_seen(self, name: str) -> Reason:
        em = self.ems.get(name)
        if em is None:
            em = self.ems[name] = OEm(name, len(self.ems) + 1)
        if not em.online:
            em.online = True
            self._clear((EM_LOST, em.index))
            self._require(em)
        self.settle()
        return Reason.ACCEPTED

    def em_lost(self, name: str) -> Reason:
        em = self.ems.get(name)
        if em is None or not em.online:
            self.settle()
            return Reason.NOTHING_TO_DO
        em.online = False
        reaction = em.lost if em.active else 0
        if self.state in EXCUSED_IN or not reaction:
            self.pending.discard(name)
        self._raise((EM_LOST, em.index), reaction, f"em:{name}")
        self.settle()
        return Reason.ACCEPTED

    def set_em_active(self, name: str, active: bool) -> Reason:
        em = self.ems.get(name)
        if em is None:
            reason = Reason.EM_UNKNOWN
        elif self.mode == 1:
            reason = Reason.EM_SWITCH_IN_PRODUCTION
        else:
            reason = Reason.ACCEPTED
            if em.active != active:
                em.active = active
                if active:
                    self._require(em)
                else:
                    self.pending.discard(name)
                    self._clear((EM_LOST, em.index))
        self.settle()
        return reason

    def set_alarm(self, alarm_id: int, active: bool) -> Reason:
        key = (alarm_id, 0)
        if not active:
            reason = Reason.ACCEPTED if self._clear(key) else Reason.NOTHING_TO_DO
        elif alarm_id not in ALARMS:
            reason = Reason.ALARM_UNKNOWN
        else:
            category, override, warning = ALARMS[alarm_id]
            reaction = 0 if warning else (override or CATEGORY_REACTION.get(category, 0))
            ok = self._raise(key, reaction, f"alarm:{alarm_id}")
            reason = Reason.ACCEPTED if ok else Reason.NOTHING_TO_DO
            if ok and reaction:  # the stop reason of an alarm reaction is the alarm
                cmd, source, _ = self.internal[-1]
                self.internal[-1] = (cmd, source, alarm_id)
        self.settle()
        return reason


class EngineVsOracle(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.clock = FakeClock(T0)
        self.unit = Unit(cell_unit(UNIT), self.clock)
        self.oracle = Oracle()
        self.last_seq = 0
        self.last_to: State | None = None

    def check(self, answer: Any, expected: Reason, what: str) -> None:
        assert answer.reason is expected, (what, answer, expected, self.oracle.state)
        assert answer.accepted == (expected is Reason.ACCEPTED)

    @initialize()
    def ems_online(self) -> None:
        for name in ("a", "b", "c"):
            self.check(self.unit.em_seen(name), self.oracle.em_seen(name), "em_seen")

    # -- commands -------------------------------------------------------------------------------------------
    @rule(
        cmd=st.sampled_from([*range(11), 11, -3]),
        source=st.sampled_from(["operator", "operator", "remote"]),
    )
    def command(self, cmd: int, source: str) -> None:
        self.check(self.unit.command(cmd, source), self.oracle.command(cmd, source), "command")

    @rule(i=st.integers(0, 9))
    def valid_command(self, i: int) -> None:
        """A command the table allows now (random commands are mostly refused); Stop and Abort,
        valid nearly everywhere, only when nothing else is."""
        o = self.oracle
        valid = SPEC.valid(o.state, o.mode)
        valid = [c for c in valid if c not in (C.STOP, C.ABORT)] or valid or [C.ABORT]
        cmd = valid[i % len(valid)]
        self.check(self.unit.command(cmd), o.command(cmd, "operator"), "valid_command")

    @rule(choices=st.lists(st.tuples(st.booleans(), st.integers(0, 9)), min_size=1, max_size=6))
    def progress(self, choices: list[tuple[bool, int]]) -> None:
        """Rounds of: every online EM reports State Complete (or not), then a valid command that
        is no Stop/Abort (random inputs alone rarely get far from Stopped and Aborted)."""
        for report, i in choices:
            if report:
                self.report_all()
            o = self.oracle
            valid = [c for c in SPEC.valid(o.state, o.mode) if c not in (C.STOP, C.ABORT)]
            if valid:
                cmd = valid[i % len(valid)]
                self.check(self.unit.command(cmd), o.command(cmd, "operator"), "progress")

    @rule()
    def recover(self) -> None:
        """Clear every alarm and bring every configured EM back."""
        for alarm_id in ALARMS:
            self.alarm(alarm_id, False)
        for name in ("a", "b", "c", "d"):
            self.em_seen(name)

    @rule(name=st.sampled_from([*EM_NAMES, "ghost"]), cmd=st.sampled_from(range(11)))
    def em_request(self, name: str, cmd: int) -> None:
        answer = self.unit.em_request(name, cmd)
        em = self.oracle.ems.get(name)
        if not cmd:
            expected = Reason.ACCEPTED
        elif em is not None and not em.active:
            expected = Reason.EM_UNKNOWN
        else:
            expected = self.oracle.command(cmd, f"em:{name}")
        self.check(answer, expected, "em_request")

    @rule(enabled=st.booleans())
    def remote_enabled(self, enabled: bool) -> None:
        self.unit.set_remote_enabled(enabled)
        self.oracle.remote = enabled
        self.oracle.settle()

    # -- State Complete reports --------------------------------------------------------------------------------
    @rule(name=st.sampled_from(EM_NAMES))
    def report_current(self, name: str) -> None:
        o = self.oracle
        answer = self.unit.em_complete(name, o.state, o.seq)
        self.check(answer, o.report(name, o.state, o.seq), "report")

    @rule()
    def report_all(self) -> None:
        o = self.oracle
        for name, em in list(o.ems.items()):
            if em.online:
                state, seq = o.state, o.seq
                self.check(
                    self.unit.em_complete(name, state, seq), o.report(name, state, seq), "all"
                )

    @rule(
        name=st.sampled_from(EM_NAMES),
        stale=st.sampled_from(["older", "newer", "other_state"]),
    )
    def report_stale(self, name: str, stale: str) -> None:
        o = self.oracle
        state, seq = o.state, o.seq
        if stale == "older":
            seq -= 1
        elif stale == "newer":
            seq += 1
        else:
            state = S.EXECUTE if state is not S.EXECUTE else S.STARTING
        self.check(self.unit.em_complete(name, state, seq), o.report(name, state, seq), "stale")

    @rule(
        requests=st.lists(
            st.one_of(
                st.builds(
                    CommandRequest,
                    st.sampled_from([*range(1, 11), 0]),
                    st.sampled_from(["operator", "remote", "em:a"]),
                ),
                st.builds(ModeRequest, st.sampled_from([1, 2, 3, 4, "cleaning"])),
                st.builds(lambda name: ("report", name), st.sampled_from(["a", "b", "c"])),
            ),
            min_size=1,
            max_size=4,
        )
    )
    def step(self, requests: list[Any]) -> None:
        o = self.oracle
        reqs = [
            CompleteReport(r[1], int(o.state), o.seq) if isinstance(r, tuple) else r
            for r in requests
        ]
        answers = self.unit.step(reqs)
        for answer, expected in zip(answers, o.step(reqs), strict=True):
            self.check(answer, expected, f"step {reqs}")

    # -- EMs -----------------------------------------------------------------------------------------------------
    @rule(name=st.sampled_from(EM_NAMES))
    def em_seen(self, name: str) -> None:
        self.check(self.unit.em_seen(name), self.oracle.em_seen(name), "em_seen")

    @rule(name=st.sampled_from(EM_NAMES))
    def em_lost(self, name: str) -> None:
        self.check(self.unit.em_lost(name), self.oracle.em_lost(name), "em_lost")

    @rule(name=st.sampled_from([*EM_NAMES, "ghost"]), active=st.booleans())
    def set_em_active(self, name: str, active: bool) -> None:
        answer = self.unit.set_em_active(name, active)
        self.check(answer, self.oracle.set_em_active(name, active), "set_em_active")

    # -- modes, alarms, time --------------------------------------------------------------------------------------
    @rule(
        mode=st.sampled_from([1, 2, 3, 4, 9, "maintenance", "cleaning", "MANUAL"]),
        source=st.sampled_from(["operator", "operator", "remote"]),
    )
    def set_mode(self, mode: int | str, source: str) -> None:
        self.check(self.unit.set_mode(mode, source), self.oracle.set_mode(mode, source), "mode")

    @rule(alarm_id=st.sampled_from([*ALARMS, 200]), active=st.booleans())
    def alarm(self, alarm_id: int, active: bool) -> None:
        answer = self.unit.set_alarm(alarm_id, 0, active)
        self.check(answer, self.oracle.set_alarm(alarm_id, active), "alarm")

    @rule()
    def reset_alarms(self) -> None:
        assert self.unit.reset_alarms().accepted
        self.oracle.reset_alarms()
        self.oracle.settle()

    @precondition(lambda self: self.clock.t < T0 + 2**20)
    @rule(dt=st.sampled_from([0.25, 0.5, 1.0, 2.0, 3.5, 6.0]))
    def tick(self, dt: float) -> None:
        now = self.clock.advance(dt)
        self.unit.advance()
        self.oracle.advance(now)

    # -- invariants ----------------------------------------------------------------------------------------------
    @invariant()
    def same_as_oracle(self) -> None:
        u, o = self.unit, self.oracle
        assert (u.state, u.mode, u.sequence) == (o.state, o.mode, o.seq)
        assert u.mode_change_in_process == (o.mode_target is not None)
        assert u.equipment.aggregating == o.aggregating
        if o.aggregating:
            assert set(u.equipment.pending) == o.pending
        assert {k for k, ev in u.alarms.current.items() if ev.trigger} == {
            k for k, ev in o.alarms.items() if ev.trigger
        }
        assert set(u.alarms.current) == set(o.alarms)
        assert (u.stop_reason.id if u.stop_reason else 0) == o.stop_id

    @invariant()
    def one_state_and_transitions(self) -> None:
        u = self.unit
        assert u.state in State and u.state is not S.UNDEFINED
        status = u.status()
        assert status.state_current == int(u.state)
        assert status.state_change_in_process == (
            u.state in SPEC_ACTING and u.state is not S.EXECUTE
        )
        for kind, tr in u.drain():
            if kind != "transition":
                continue
            assert tr.sequence > self.last_seq, "sequence numbers strictly increase"
            self.last_seq = tr.sequence
            if tr.trigger is Trigger.MODE:
                assert tr.from_state is tr.to_state
                continue
            if self.last_to is not None:
                assert tr.from_state is self.last_to
            self.last_to = tr.to_state
            if tr.from_state in SPEC_WAIT and tr.trigger is not Trigger.RESTART:
                assert tr.trigger is not Trigger.STATE_COMPLETE, "wait states leave by command"
                assert tr.command != 0

    @invariant()
    def times_add_up(self) -> None:
        u, o = self.unit, self.oracle
        _, _, _, state_cum, acc = u.times.live(u.now)
        elapsed = u.now - T0
        assert abs(sum(state_cum) - elapsed) < 1e-6
        assert abs(acc - elapsed) < 1e-6
        expected = defaultdict(float, o.cum)
        expected[(o.mode, int(o.state))] += o.t - o.since
        for (mode, state), seconds in expected.items():
            assert abs(state_cum[mode * NUM_STATES + state] - seconds) < 1e-6, (mode, state)
        assert abs(u.now - o.t) < 1e-9


EngineVsOracle.TestCase.settings = settings(
    max_examples=200,
    stateful_step_count=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    database=None,
)
TestEngineVsOracle = EngineVsOracle.TestCase
