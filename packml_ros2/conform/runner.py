"""A conformance run: drive a :class:`~.target.Target` through the cases of a plan and judge
every answer and every state it shows by the rule book (:mod:`.expect`).

Pure: no ROS, no OPC UA (the target is the face); the clock is a parameter. The cases come in
the order :func:`.plan.order` gives them (a tour). For each case the runner first brings the target to the case's mode and state by the fewest commands the standard
accepts (a command that misbehaves on the way is a finding of its own and is not used again),
then acts and judges:

- a command: accepted or refused as the standard says; a refusal with the reason code it gives
  (where the face has reason codes) and without any change for a while (``quiet``); an accepted
  command shows the standard's way (every state, where the face shows every state; no state
  outside it, nor a state the mode disables), settles where the standard says within the
  states' timeouts, keeps the mode, and its Status tags agree (state, mode, StatesDisabled, the
  commands valid now, a sequence number that moved);
- a mode change: accepted or refused as the matrix says, shown in UnitModeCurrent, the state
  kept;
- the Admin times and counters (:data:`.plan.PACKTAG_CHECKS`).

Each finding is one sentence that says what and where. At the end the target is brought back
to the state and mode it was found in, unless the run stopped at its first failure
(``stop_on_first``): then it is left where the failure showed, for the engineer to look at.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from ..core.numbers import ACTING, State, command_name, names_of
from ..core.reasons import Reason
from ..core.rules import Rules
from . import expect
from .plan import Case
from .target import AdminView, Reply, Shown, Tags, Target

S = State
#: Seconds two Admin time readings between which the times must have grown are apart.
TIME_WINDOW = 2.0
#: The end of a finding that a state of the standard's way was not shown (tried again once).
_MISSED = ", twice"
#: How far a time PackTag may be from the elapsed time (whole seconds, publication delays).
TIME_TOLERANCE = 1.6


@dataclass(frozen=True)
class Options:
    """``timeout``: seconds any acting state may take (``timeouts``: per state); ``quiet``:
    seconds a refused request is watched for a change; ``answer``: seconds to wait for an
    answer; ``admin_timeout``: seconds to wait for Admin data; ``stop_on_first``."""

    timeout: float = 10.0
    timeouts: Mapping[State, float] = field(default_factory=dict)
    quiet: float = 0.3
    answer: float = 5.0
    admin_timeout: float = 12.0
    mode_timeout: float = 10.0
    stop_on_first: bool = False


@dataclass(frozen=True)
class Result:
    """The judgement of one case: ``outcome`` "pass", "fail" or "skip"; ``message``: what
    happened (for a failure: what is wrong, and where); ``seconds``: how long the case's
    transition took (None where nothing moved)."""

    case: Case
    outcome: str
    message: str
    seconds: float | None = None


@dataclass
class Run:
    """What a run found, did and left."""

    found: Shown | None = None
    results: list[Result] = field(default_factory=list)
    stopped_early: bool = False
    restored: bool | None = None  #: None: not tried (stopped early, or never connected)
    left: Shown | None = None
    note: str = ""
    lost: bool = False  #: the target stopped answering

    def count(self, outcome: str) -> int:
        return sum(1 for r in self.results if r.outcome == outcome)

    @property
    def passed(self) -> bool:
        return not self.stopped_early and self.count("fail") == 0


class _Abandon(Exception):
    """The run stops (``stop_on_first``)."""


class Runner:
    """Runs cases on ``target`` by ``rules``; ``mode_names``: number -> name, for sentences."""

    def __init__(
        self,
        target: Target,
        rules: Rules,
        options: Options,
        mode_names: Mapping[int, str],
        clock: Callable[[], float] = time.monotonic,
        progress: Callable[[Result], None] | None = None,
    ) -> None:
        self.target = target
        self.rules = rules
        self.options = options
        self.mode_names = dict(mode_names)
        self.clock = clock
        self.progress = progress
        #: (mode, state, command) that misbehaved while the runner travelled: not used again
        self.avoid: set[tuple[int, State, int]] = set()
        self.run = Run()
        self._sequence_stuck = False  # the target's sequence number did not move once
        self._unreachable_modes: dict[int, str] = {}  # mode -> why a change to it failed
        #: the last two Admin readings of a stay, with the history's mark they were taken at: the
        #: time checks of one stay share them (the target did not move since)
        self._readings: tuple[int, AdminView, AdminView] | None = None

    # -- names -------------------------------------------------------------------------------------
    def mode_name(self, mode: int) -> str:
        return self.mode_names.get(mode, f"mode {mode}")

    def where(self, state: State, mode: int) -> str:
        return f"{state.name} ({self.mode_name(mode)})"

    # -- the run -----------------------------------------------------------------------------------
    def execute(self, cases: list[Case]) -> Run:
        history = self.target.shown()
        self.run.found = history.last
        try:
            for case in cases:
                self._record(self._case(case))
        except _Abandon:
            self.run.stopped_early = True
        if not self.run.stopped_early and self.run.found is not None:
            self.run.restored = self._restore(self.run.found)
        self.run.left = history.last
        return self.run

    def _record(self, result: Result) -> None:
        self.run.results.append(result)
        if self.progress is not None:
            self.progress(result)
        if result.outcome == "fail" and self.options.stop_on_first:
            raise _Abandon

    def _case(self, case: Case) -> Result:
        why = self.ensure(case.mode, case.state)
        if why is not None:
            return Result(case, "fail", f"not reached: {why}")
        if case.kind == "command":
            result = self._command(case)
            if result.outcome == "fail" and result.message.endswith(_MISSED):
                # a state shorter than the face's sampling may be missed: a real skip shows twice
                why = self.ensure(case.mode, case.state)
                again = self._command(case) if why is None else result
                if again.outcome == "pass":
                    return Result(
                        case,
                        "pass",
                        f"{again.message} (on the second try: "
                        f"{result.message.removesuffix(_MISSED)})",
                        again.seconds,
                    )
                return again
            return result
        if case.kind == "mode":
            return self._mode(case)
        return self._packtag(case)

    def _restore(self, found: Shown) -> bool:
        state = expect.settles_from(self.rules, found.mode, found.state)
        why = self.ensure(found.mode, state)
        if why is not None:
            self.run.note = (
                f"the target was not brought back to {self.where(state, found.mode)}: {why}"
            )
            return False
        return True

    # -- travelling --------------------------------------------------------------------------------
    def _now(self) -> Shown:
        last = self.target.shown().last
        if last is None:
            raise _Abandon
        return last

    def ensure(self, mode: int, state: State) -> str | None:
        """Bring the target to ``state`` in ``mode``; why not (None: there)."""
        for _ in range(12):
            now = self._now()
            stuck = False
            if now.state in ACTING and now.state is not S.EXECUTE:
                self._settle_any(self.clock())
                now = self._now()
                stuck = now.state in ACTING and now.state is not S.EXECUTE
            if stuck:  # an acting state that does not complete: a command leads on
                way = self._route(now.mode, now.state, list(expect.RESTING), stuck=True)
                why = self._travel(way, now.mode) if way else f"{now.state.name} does not complete"
                if why is not None:
                    return f"the target stays in {self.where(now.state, now.mode)}: {why}"
                continue
            if now.mode != mode:
                why = self._unreachable_modes.get(mode) or self._change_mode(now, mode)
                if why is not None:
                    self._unreachable_modes[mode] = why  # (not tried again: each try costs)
                    return why
                continue
            if now.state == state:
                return None
            way = self._route(mode, now.state, [state])
            if way is None:
                return (
                    f"no way from {self.where(now.state, mode)} to {state.name} "
                    "the target has not refused"
                )
            why = self._travel(way, mode)
            if why is not None:
                return why
        return f"{state.name} ({self.mode_name(mode)}) not reached after 12 attempts"

    def _route(
        self, mode: int, start: State, goals: list[State], stuck: bool = False
    ) -> tuple[tuple[int, State], ...] | None:
        avoid = frozenset((s, c) for m, s, c in self.avoid if m == mode)
        return expect.route(self.rules, mode, start, goals, avoid, stuck)

    def _change_mode(self, now: Shown, mode: int) -> str | None:
        goals = [
            s for s in expect.RESTING if expect.mode_change(self.rules, now.mode, mode, s) is None
        ]
        way = self._route(now.mode, now.state, goals)
        if way is None:
            return (
                f"no state of {self.mode_name(now.mode)} allows a change to {self.mode_name(mode)}"
            )
        why = self._travel(way, now.mode)
        if why is not None:
            return why
        here = self._now()
        reply = self.target.set_mode(mode, self.options.answer)
        if not reply.accepted:
            return (
                f"the change from {self.mode_name(here.mode)} to {self.mode_name(mode)} in "
                f"{here.state.name} was refused ({_said(reply)}); the standard allows it"
            )
        if self.target.shown().wait(lambda s: s.mode == mode, self.options.mode_timeout) is None:
            return (
                f"the change from {self.mode_name(here.mode)} to {self.mode_name(mode)} in "
                f"{here.state.name} was accepted, but UnitModeCurrent still shows "
                f"{self.mode_name(self._now().mode)} after {self.options.mode_timeout:g} s"
            )
        return None

    def _travel(self, way: tuple[tuple[int, State], ...], mode: int) -> str | None:
        for cmd, settle in way:
            here = self._now()
            mark, start = self.target.shown().mark(), self.clock()
            reply = self.target.command(cmd, self.options.answer)
            name = command_name(cmd)
            if not reply.accepted:
                self.avoid.add((mode, here.state, cmd))
                return (
                    f"on the way: {name} in {self.where(here.state, mode)} was refused "
                    f"({_said(reply)}); the standard accepts it"
                )
            shown = expect.command(self.rules, mode, here.state, cmd).shown
            got = self._settle(mark, start, shown)
            if got is None or got.state != settle:
                self.avoid.add((mode, here.state, cmd))
                now = self._now()
                return (
                    f"on the way: {name} in {self.where(here.state, mode)} left the target in "
                    f"{now.state.name}, not {settle.name}"
                )
        return None

    # -- waiting -----------------------------------------------------------------------------------
    def _deadline(self, shown: tuple[State, ...]) -> float:
        acting = [s for s in shown if s in ACTING and s is not S.EXECUTE]
        total = sum(self.options.timeouts.get(s, self.options.timeout) for s in acting)
        return max(total, self.options.timeout)

    def _settle(self, mark: int, since: float, shown: tuple[State, ...]) -> Shown | None:
        """The first resting state shown after ``mark`` (None: none within the states'
        timeouts, counted from ``since``)."""
        history = self.target.shown()
        deadline = since + self._deadline(shown)
        seen = mark
        while True:
            for entry in history.since(seen):
                if entry.state in expect.RESTING:
                    return entry
            seen = history.mark()
            remaining = deadline - self.clock()
            if remaining <= 0 or not history.wait_change(seen, remaining):
                return None

    def _settle_any(self, since: float) -> None:
        now = self._now()
        mark = self.target.shown().mark() - 1
        self._settle(mark, since, expect.follow(self.rules, now.mode, now.state)[0])

    # -- a command ---------------------------------------------------------------------------------
    def _command(self, case: Case) -> Result:
        mode, state, cmd = case.mode, case.state, case.cmd
        wanted = expect.command(self.rules, mode, state, cmd)
        history = self.target.shown()
        before = self._tags_now()
        mark = history.mark()
        start = self.clock()
        reply = self.target.command(cmd, self.options.answer)
        name, here = command_name(cmd), self.where(state, mode)
        if not wanted.accepted:
            return self._refused(case, reply, wanted.reason, f"{name} in {here}", mark, before)
        way = " -> ".join(s.name for s in wanted.shown)
        if not reply.accepted:
            self.avoid.add((mode, state, cmd))
            return Result(
                case,
                "fail",
                f"{name} in {here} was refused ({_said(reply)}); the standard accepts it: {way}",
            )
        got = self._settle(mark, start, wanted.shown)
        shown = list(history.since(mark))
        path = [e.state for e in shown]
        if got is not None:
            path = path[: path.index(got.state) + 1] if got.state in path else path
        problems = self._judge_way(wanted, path, mode)
        if got is None or got.state != wanted.settle:
            self.avoid.add((mode, state, cmd))  # not a way the runner travels again
        if got is None:
            now = self._now()
            problems.insert(
                0,
                f"{name} in {here} left the target in {now.state.name} for "
                f"{self._deadline(wanted.shown):g} s; the standard's way is {way}",
            )
        elif got.state != wanted.settle:
            problems.insert(
                0,
                f"{name} in {here} settled in {got.state.name}; the standard's way is {way}",
            )
        modes = {e.mode for e in shown if e.state in path}
        if got is not None and modes - {mode}:
            problems.append(f"the mode changed to {self.mode_name(max(modes - {mode}))}")
        seconds = None if got is None else got.at - start
        if got is not None and not problems:
            problems += self._judge_tags(got.state, mode, before, moved=True)
        if problems:
            if not any(p.startswith(f"{name} in") for p in problems):
                problems[0] = f"{name} in {here}: {problems[0]}"
            return Result(case, "fail", "; ".join(problems), seconds)
        timing = f" in {seconds * 1000:.0f} ms" if seconds is not None else ""
        unseen = [s.name for s in wanted.shown if s not in path]
        if unseen:  # (a face that may not show every state: said, not judged)
            timing += f" ({', '.join(unseen)} not shown)"
        return Result(
            case, "pass", f"accepted: {' -> '.join(s.name for s in path)}{timing}", seconds
        )

    def _judge_way(self, wanted: expect.Expect, path: list[State], mode: int) -> list[str]:
        """What is wrong with the states shown on an accepted command's way."""
        out: list[str] = []
        disabled = self.rules.modes[mode].disabled
        entered = [s for s in path if s in disabled]
        if entered:
            names = ", ".join(s.name for s in dict.fromkeys(entered))
            out.append(f"it entered {names}, which {self.mode_name(mode)} disables")
        foreign = [s for s in path if s not in wanted.shown and s not in disabled]
        if foreign:
            out.append(
                f"it showed {', '.join(s.name for s in dict.fromkeys(foreign))}, "
                "off the standard's way"
            )
        if self.target.complete_path and not out:
            missing = [s for s in wanted.shown if s not in path]
            if missing and path and path[-1] == wanted.settle:
                out.append(
                    f"it never showed {', '.join(s.name for s in missing)} "
                    f"(shown: {' -> '.join(s.name for s in path)}){_MISSED}"
                )
        return out

    def _tags_now(self) -> Tags | None:
        """The Status tags once they caught up with the last state shown (at most 2 s)."""
        history = self.target.shown()
        deadline = self.clock() + 2.0
        while True:
            tags, last = self.target.tags(), history.last
            if tags is None or last is None:
                return tags
            behind = (
                not self._sequence_stuck
                and tags.sequence is not None
                and last.sequence is not None
                and tags.sequence < last.sequence
            )
            if (tags.state, tags.mode) == (last.state, last.mode) and not behind:
                return tags
            if self.clock() >= deadline:
                return tags
            history.wait_change(history.mark(), 0.05)

    def _judge_tags(self, state: State, mode: int, before: Tags | None, moved: bool) -> list[str]:
        """What the Status tags say against where the target is (waiting briefly for them to
        catch up with the transitions)."""
        tags = self._tags_now()
        if tags is None:
            return []
        out: list[str] = []
        if tags.state != state:
            out.append(
                f"StateCurrent shows {tags.state.name if tags.state else 'nothing'}, "
                f"not {state.name}"
            )
        if tags.mode != mode:
            out.append(
                f"UnitModeCurrent shows {self.mode_name(tags.mode)}, not {self.mode_name(mode)}"
            )
        mask = self.rules.modes[mode].disabled_mask
        if tags.disabled_mask is not None and tags.disabled_mask != mask:
            out.append(
                f"StatesDisabled shows {tags.disabled_mask:#x}; "
                f"{self.mode_name(mode)} disables {mask:#x}"
            )
        valid = tuple(int(c) for c in self.rules.valid_commands(state, mode))
        if tags.commands_valid is not None and tuple(sorted(tags.commands_valid)) != valid:
            out.append(
                f"the commands valid now are shown as {names_of(tags.commands_valid) or 'none'}; "
                f"the standard says {names_of(valid) or 'none'}"
            )
        old = None if before is None else before.sequence
        if moved and tags.sequence is not None and old is not None and tags.sequence == old:
            self._sequence_stuck = True  # (no more waiting for it to catch up)
            out.append(f"the transition sequence number stayed {old}")
        return out

    def _refused(
        self, case: Case, reply: Reply, reason: Reason, what: str, mark: int, before: Tags | None
    ) -> Result:
        """Judge a request the standard refuses."""
        history = self.target.shown()
        if reply.accepted:
            # wherever it goes: the next case starts from there
            if history.wait_change(mark, max(self.options.quiet, 1.0)):
                self._settle_any(self.clock())
            now = self._now()
            went = [e.state for e in history.since(mark)]
            disabled = self.rules.modes[now.mode].disabled if now.mode in self.rules.modes else ()
            entered = [s.name for s in dict.fromkeys(went) if s in disabled]
            also = (
                f", entering {', '.join(entered)}, which {self.mode_name(now.mode)} disables"
                if entered
                else ""
            )
            return Result(
                case,
                "fail",
                f"{what} was accepted ({_said(reply)}); the standard refuses it ({reason.name}); "
                f"the target went to {self.where(now.state, now.mode)}{also}",
            )
        problems: list[str] = []
        if reply.reason is not None and reply.reason != int(reason):
            problems.append(f"refused with reason {_said(reply)}, not {reason.name}")
        elif reply.reason is None and not reply.code.startswith("Bad"):
            problems.append(f"refused with status {reply.code}, not a Bad status code")
        if reply.reason is not None and not reply.text.strip():
            problems.append("the refusal says no reason in words")
        if history.wait_change(mark, self.options.quiet):
            self._settle_any(self.clock())
            shown = " -> ".join(e.state.name for e in history.since(mark))
            problems.append(f"it still changed: {shown} within {self.options.quiet:g} s")
        else:
            tags = self.target.tags()
            old = None if before is None else before.sequence
            if (
                tags is not None
                and tags.sequence is not None
                and old is not None
                and tags.sequence != old
            ):
                problems.append(
                    f"the transition sequence number moved from {old} to {tags.sequence}"
                )
        if problems:
            return Result(case, "fail", f"{what}: " + "; ".join(problems))
        return Result(case, "pass", f"refused: {_said(reply)}")

    # -- a mode change -----------------------------------------------------------------------------
    def _mode(self, case: Case) -> Result:
        a, b, state = case.mode, case.to_mode, case.state
        why = expect.mode_change(self.rules, a, b, state)
        history = self.target.shown()
        before = self._tags_now()
        mark = history.mark()
        start = self.clock()
        reply = self.target.set_mode(b, self.options.answer)
        what = f"the change from {self.mode_name(a)} to {self.mode_name(b)} in {state.name}"
        if why is not None:
            result = self._refused(case, reply, Reason.MODE_CHANGE_NOT_ALLOWED, what, mark, before)
            if result.outcome == "fail" and reply.accepted:
                return Result(case, "fail", f"{result.message} (the standard: {why})")
            return result
        if not reply.accepted:
            return Result(
                case, "fail", f"{what} was refused ({_said(reply)}); the standard allows it"
            )
        got = history.wait(lambda s: s.mode == b, self.options.mode_timeout)
        if got is None:
            return Result(
                case,
                "fail",
                f"{what} was accepted, but UnitModeCurrent still shows "
                f"{self.mode_name(self._now().mode)} after {self.options.mode_timeout:g} s",
            )
        seconds = got.at - start
        problems = []
        moved = [e.state.name for e in history.since(mark) if e.state != state]
        if moved:
            problems.append(f"the state changed to {', '.join(moved)}")
        problems += self._judge_tags(state, b, before, moved=False)
        if problems:
            return Result(case, "fail", f"{what}: " + "; ".join(problems), seconds)
        return Result(case, "pass", f"accepted in {seconds * 1000:.0f} ms", seconds)

    # -- Admin PackTags ----------------------------------------------------------------------------
    def _admin(self, newer_than: float | None) -> AdminView | None:
        return self.target.admin(newer_than, self.options.admin_timeout)

    def _packtag(self, case: Case) -> Result:
        mode, state, mode_name = case.mode, case.state, self.mode_name(case.mode)
        if case.check == "state-current-time":
            label = f"StateCurrentTime of {self.where(state, mode)}"
            return self._grows(case, label, lambda a: a.state_time(mode, state))
        if case.check == "mode-current-time":
            return self._grows(case, f"ModeCurrentTime of {mode_name}", lambda a: a.mode_time(mode))
        if case.check == "mode-cumulative-time":
            label = f"ModeCumulativeTime of {mode_name}"
            return self._grows(case, label, lambda a: a.mode_time(mode, cumulative=True))
        if case.check == "state-cumulative-time":
            return self._state_cumulative_time(case)
        return self._counters_reset(case)

    def _two_readings(self, case: Case) -> tuple[AdminView, AdminView] | Result:
        """Two Admin readings :data:`TIME_WINDOW` apart while the target stays put (those of
        the check before, when the target has shown nothing since)."""
        history = self.target.shown()
        mark = history.mark()
        if self._readings is not None and self._readings[0] == mark:
            return self._readings[1], self._readings[2]
        if self._admin(None) is None:
            return Result(case, "skip", "the target shows no Admin PackTags")
        entered = history.last.at if history.last is not None else None
        first = self._admin(entered)  # taken in the stay, not before it
        if first is None:
            return Result(
                case, "fail", f"no Admin PackTags within {self.options.admin_timeout:g} s"
            )
        second = self._admin(first.received + TIME_WINDOW)
        if second is None:
            return Result(
                case,
                "fail",
                f"no Admin PackTags newer than {TIME_WINDOW:g} s "
                f"within {self.options.admin_timeout:g} s",
            )
        if history.since(mark):
            return Result(case, "fail", "the target moved while it was left alone")
        self._readings = (mark, first, second)
        return first, second

    def _growth(
        self, case: Case, label: str, before: int | None, after: int | None, elapsed: float
    ) -> Result:
        """``label`` (a time PackTag and its entry) grew by the ``elapsed`` seconds."""
        if before is None or after is None:
            return Result(case, "fail", f"{label} is missing")
        if abs(after - before - elapsed) > TIME_TOLERANCE:
            return Result(
                case, "fail", f"{label} went from {before} to {after} s in {elapsed:.1f} s"
            )
        return Result(case, "pass", f"{label}: {before} -> {after} s in {elapsed:.1f} s")

    def _grows(self, case: Case, label: str, read: Callable[[AdminView], int | None]) -> Result:
        """The time PackTag ``read`` takes from a reading grows with the stay."""
        readings = self._two_readings(case)
        if isinstance(readings, Result):
            return readings
        a, b = readings
        return self._growth(case, label, read(a), read(b), b.at - a.at)

    def _state_cumulative_time(self, case: Case) -> Result:
        """Leave the state the earlier checks stayed in and come back: its cumulative time keeps
        the earlier stay."""
        first = self._admin(None)
        if first is None:
            return Result(case, "skip", "the target shows no Admin PackTags")
        kept = first.state_time(case.mode, case.state, cumulative=True)
        if kept is None:
            return Result(
                case,
                "fail",
                f"StateCumulativeTime has no entry for {self.where(case.state, case.mode)}",
            )
        way = self._route(case.mode, case.state, [s for s in expect.RESTING if s != case.state])
        if not way:
            return Result(case, "skip", f"no way out of {case.state.name}")
        why = self._travel(way[:1], case.mode) or self.ensure(case.mode, case.state)
        if why is not None:
            return Result(case, "fail", f"not reached again: {why}")
        back = self.clock()
        after = self._admin(back)
        if after is None:
            return Result(
                case, "fail", f"no Admin PackTags within {self.options.admin_timeout:g} s"
            )
        now_total = after.state_time(case.mode, case.state, cumulative=True)
        current = after.state_time(case.mode, case.state) or 0
        label = f"StateCumulativeTime for {self.where(case.state, case.mode)}"
        if now_total is None or now_total < kept:
            return Result(
                case,
                "fail",
                f"{label} went from {kept} s to {now_total} s when the target left and came back "
                "(earlier stays were lost)",
            )
        stay = self.clock() - back
        if current > stay + TIME_TOLERANCE + TIME_WINDOW:
            return Result(
                case,
                "fail",
                f"StateCurrentTime did not restart: {current} s after a new stay of {stay:.1f} s",
            )
        return Result(case, "pass", f"{label} kept {kept} s over a new stay ({now_total} s)")

    def _counters_reset(self, case: Case) -> Result:
        if self.target.admin(None, self.options.admin_timeout) is None:
            return Result(case, "skip", "the target shows no Admin PackTags")
        # produce a while (in Execute), then stop producing and reset
        why = self.ensure(case.mode, S.EXECUTE)
        if why is None:
            first = self._admin(None)
            if first is not None:
                self._admin(first.received + TIME_WINDOW)
        why = why or self.ensure(case.mode, S.STOPPED)
        if why is not None:
            return Result(case, "fail", f"not reached: {why}")
        before = self._admin(None)
        if before is None:
            return Result(case, "fail", "no Admin PackTags")
        reply = self.target.reset_counters(self.options.answer)
        if reply is None:
            return Result(case, "skip", f"the {self.target.face} face has no counter reset")
        if not reply.accepted:
            return Result(case, "fail", f"the counter reset was refused ({_said(reply)})")
        after = self._admin(self.clock())
        if after is None:
            return Result(
                case,
                "fail",
                f"no Admin PackTags after the reset within {self.options.admin_timeout:g} s",
            )
        counted = sum(c for c, _ in before.counts)
        left = [c for c, _ in after.counts if c != 0]
        if left:
            return Result(
                case,
                "fail",
                f"after the counter reset {len(left)} counts are not 0: {left[:5]}",
            )
        lost = [
            f"{a0} -> {a1}"
            for (_, a0), (_, a1) in zip(before.counts, after.counts, strict=False)
            if a1 < a0
        ]
        if lost:
            return Result(case, "fail", f"the counter reset lowered AccCount: {', '.join(lost)}")
        proof = "" if counted else " (the counts were 0 before: shown, not proven)"
        total = f"{len(before.counts)} counts (sum {counted})"
        return Result(case, "pass", f"{total} -> 0, AccCount kept{proof}")


def _said(reply: Reply) -> str:
    said = " ".join(reply.text.split())
    said = said if len(said) <= 120 else said[:119] + "…"
    text = f": {said}" if said else ""
    return f"{reply.code}{text}"
