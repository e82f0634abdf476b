"""Issue 16: the bags of test/bags catch regressions of the engine — a mutation score.

Each mutation below is a plausible engine regression (a rule of the rule book changed, a part
doing its job slightly wrong), applied in-process with monkeypatch (nothing is edited on disk).
With it applied, at least one bag of test/bags must fail to replay; the test names every
mutation no bag catches. Without any mutation, every bag replays (test_replay.py).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.bag import replay as replay_module
from packml_ros2.bag.recording import RecordingError, load
from packml_ros2.core import (
    Cmd,
    State,
    alarms,
    counters,
    equipment,
    interlocks,
    machine,
    publication,
    rules,
    stopreason,
    times,
    unit,
)
from packml_ros2.core.deadlines import Due
from packml_ros2.core.line import episodes as line_episodes
from packml_ros2.core.line import losses as line_losses
from packml_ros2.core.line import performance as line_performance
from packml_ros2.core.rules import Entry

BAGS = Path(__file__).resolve().parent / "bags"
ALL_BAGS = [*sorted(p for p in BAGS.iterdir() if p.is_dir()), BAGS / "independent_writer.mcap"]
S = State
Patch = pytest.MonkeyPatch


def _entry(patch: Patch, state: State, flags: Entry) -> None:
    """ENTRY[state] = flags, where the engine reads it (rules compile it; the machine reads it
    too)."""
    table = {**rules.ENTRY, state: flags}
    patch.setattr(rules, "ENTRY", table)
    patch.setattr(machine, "ENTRY", table)


def _wrap(patch: Patch, cls: Any, name: str, make: Callable[[Any], Any]) -> None:
    """``cls.name`` replaced by ``make(original)``."""
    patch.setattr(cls, name, make(getattr(cls, name)))


def _wrap_deadline(patch: Patch, kind: Due, make: Callable[[Any], Any]) -> None:
    """The handler of deadline ``kind`` replaced by ``make(original)`` (the unit binds its
    handlers from the table ``DEADLINE_HANDLERS``, not by name)."""
    table = dict(unit.Unit.DEADLINE_HANDLERS)
    table[kind] = make(table[kind])
    patch.setattr(unit.Unit, "DEADLINE_HANDLERS", table)


def _stale_twice(original: Any) -> Any:
    def report(self: Any, name: str, state: int, sequence: int) -> bool:
        taken = bool(original(self, name, state, sequence))
        em = self.modules.get(name)
        if not taken and em is not None:
            em.stale_reports += 1  # counted twice
        return taken

    return report


def _history_oldest_first(original: Any) -> Any:
    def push(self: Any, ev: Any) -> None:
        original(self, ev)
        self.history.remove(ev)
        self.history.append(ev)  # newest last: the order reversed

    return push


def _acc_not_counted(original: Any) -> Any:
    def add(self: Any, kind: str, index: int, increment: int) -> str | None:
        array = self.arrays.get(kind)
        before = array[index].acc_count if array and 0 <= index < len(array) else None
        problem = original(self, kind, index, increment)
        if problem is None and before is not None:
            array[index].acc_count = before
        return problem

    return add


def _reset_acc_too(original: Any) -> Any:
    def reset(self: Any) -> None:
        original(self)
        for array in self.arrays.values():
            for c in array:
                c.acc_count = 0

    return reset


def _no_cleared_time(original: Any) -> Any:
    def clear(self: Any, alarm_id: int, value: int, now: float) -> Any:
        ev = original(self, alarm_id, value, now)
        if ev is not None:
            ev.cleared_time = None
        return ev

    return clear


def _reset_keeps_latched(original: Any) -> Any:
    def reset(self: Any) -> int:
        return 0

    return reset


def _no_log_events(original: Any) -> Any:
    def log_event(
        self: Any, message: str, now: float, source: str = "unit", event_id: int = 0
    ) -> None:
        self.version += 1

    return log_event


def _current_time_kept(original: Any) -> Any:
    def enter_states(
        self: Any, now: float, first: int, last: int, between: Any, planned: bool
    ) -> None:
        keep = self.state_current[self._base + last]
        original(self, now, first, last, between, planned)
        self.state_current[self._base + last] = keep  # StateCurrentTime not restarted

    return enter_states


def _mode_times_kept(original: Any) -> Any:
    def enter(self: Any, now: float, mode: int, state: int, planned: bool = False) -> None:
        keep = list(self.mode_current)
        original(self, now, mode, state, planned)
        self.mode_current[:] = keep  # ModeCurrentTime not restarted on a mode change

    return enter


def _no_roster_change(original: Any) -> Any:
    def changed_roster(self: Any) -> None:
        original(self)
        self.version -= 1  # an EM switched online/active: the status does not show it

    return changed_roster


def _em_lost_not_excused(original: Any) -> Any:
    def excuse(self: Any, name: str) -> None:
        return None

    return excuse


def _lost_reaction_default_stop(original: Any) -> Any:
    def lost(self: Any, configured: int | None) -> int:
        return 3 if configured is None else configured  # Stop instead of the unit's Abort

    return lost


def _admin_period_doubled(original: Any) -> Any:
    def on_admin(self: Any, period: float) -> None:
        original(self, period * 2)

    return on_admin


def _operator_stop_id(patch: Patch) -> None:
    patch.setattr(stopreason, "STOP_ID_OPERATOR", 34)


def _interlock_ignored(original: Any) -> Any:
    def action(self: Any, state: State, sequence: int) -> Any:
        return None

    return action


def _ack_not_stamped(original: Any) -> Any:
    def acknowledge(self: Any, key: Any, now: float) -> int:
        return int(original(self, key, now + 1.0))  # AckDateTime one second late

    return acknowledge


#: name -> how to apply it (to a MonkeyPatch).
MUTATIONS: dict[str, Callable[[Patch], None]] = {
    "mode-change-not-allowed flag shortened to 2.5 s":
        lambda p: p.setattr(machine, "MODE_CHANGE_NOT_ALLOWED_SECONDS", 2.5),
    "first-out not cleared on Starting": lambda p: _entry(p, S.STARTING, Entry.REARM),
    "stale EM reports counted twice": lambda p: _wrap(p, equipment.Equipment, "report", _stale_twice),
    "alarm history in reverse order":
        lambda p: _wrap(p, alarms.AlarmManager, "_push_history", _history_oldest_first),
    "latched alarms not reset on Resetting": lambda p: _entry(p, S.RESETTING, Entry.REARM),
    "latched alarms not reset on Clearing": lambda p: _entry(p, S.CLEARING, Entry(0)),
    "StopReason not re-armed by Unholding": lambda p: _entry(p, S.UNHOLDING, Entry(0)),
    "StopReason not re-armed by Unsuspending": lambda p: _entry(p, S.UNSUSPENDING, Entry(0)),
    "StopReason not re-armed by Resetting": lambda p: _entry(p, S.RESETTING, Entry.RESET_ALARMS),
    "Stopping records no StopReason": lambda p: _entry(p, S.STOPPING, Entry(0)),
    "Aborting records no StopReason": lambda p: _entry(p, S.ABORTING, Entry(0)),
    "status coalescing 0.1 s instead of 0.05 s":
        lambda p: p.setattr(publication, "STATUS_COALESCE", 0.1),
    "admin coalescing 0.5 s instead of 0.25 s":
        lambda p: p.setattr(publication, "ADMIN_COALESCE", 0.5),
    "admin heartbeat at twice its period":
        lambda p: _wrap_deadline(p, Due.ADMIN, _admin_period_doubled),
    "AccCount not counted": lambda p: _wrap(p, counters.Counters, "add", _acc_not_counted),
    "reset_counters resets AccCount too":
        lambda p: _wrap(p, counters.Counters, "reset", _reset_acc_too),
    "a cleared alarm keeps no cleared time":
        lambda p: _wrap(p, alarms.AlarmManager, "clear", _no_cleared_time),
    "alarm reset keeps latched alarms":
        lambda p: _wrap(p, alarms.AlarmManager, "reset", _reset_keeps_latched),
    "history events (EM switched, registered) not logged":
        lambda p: _wrap(p, alarms.AlarmManager, "log_event", _no_log_events),
    "StateCurrentTime not restarted on a transition":
        lambda p: _wrap(p, times.ModeStateTimes, "enter_states", _current_time_kept),
    "ModeCurrentTime not restarted on a mode change":
        lambda p: _wrap(p, times.ModeStateTimes, "enter", _mode_times_kept),
    "an EM's online/active change not shown in the status":
        lambda p: _wrap(p, equipment.Equipment, "changed_roster", _no_roster_change),
    "a lost EM is not excused from State Complete":
        lambda p: _wrap(p, equipment.Equipment, "excuse", _em_lost_not_excused),
    "EM loss reaction Stop instead of the configured Abort":
        lambda p: _wrap(p, unit.Unit, "_lost_reaction", _lost_reaction_default_stop),
    "operator stop reason ID 34 instead of 33": _operator_stop_id,
    "interlocks never suspend": lambda p: _wrap(p, interlocks.Interlocks, "action", _interlock_ignored),
    "acknowledgement stamped a second late":
        lambda p: _wrap(p, alarms.AlarmManager, "acknowledge", _ack_not_stamped),
}  # fmt: skip


@contextlib.contextmanager
def applied(mutation: Callable[[Patch], None]) -> Iterator[None]:
    """The mutation applied, with the compiled rules and parsed configurations of the replay
    made again under it (and again after it)."""
    patch = pytest.MonkeyPatch()
    replay_module._recorded_cell.cache_clear()
    try:
        patch.setattr(rules, "_compiled", {})
        mutation(patch)
        yield
    finally:
        patch.undo()
        replay_module._recorded_cell.cache_clear()


def caught_by(recordings: dict[Path, Any]) -> str | None:
    """The first bag that does not replay to its recorded outputs, or None."""
    for path, rec in recordings.items():
        try:
            result = replay_module.replay(path, recording=rec)
        except (RecordingError, AssertionError, LookupError, ValueError, TypeError) as exc:
            return f"{path.name} (replay failed: {type(exc).__name__})"
        if not result.ok:
            return path.name
    return None


def test_every_seeded_engine_mutation_is_caught_by_a_bag() -> None:
    recordings = {path: load(path, em_reports=False) for path in ALL_BAGS}
    assert caught_by(recordings) is None  # unmutated, every bag replays
    assert len(MUTATIONS) >= 20
    missed = []
    for name, mutation in MUTATIONS.items():
        with applied(mutation):
            bag = caught_by(recordings)
        print(f"{name}: {bag or 'NOT CAUGHT'}")
        if bag is None:
            missed.append(name)
    assert caught_by(recordings) is None  # and undone
    print(f"mutation score: {len(MUTATIONS) - len(missed)}/{len(MUTATIONS)}")
    assert not missed, f"{len(missed)} of {len(MUTATIONS)} mutations pass every bag: {missed}"


# -- issue 27: the line's topics ------------------------------------------------------------------------
def _line_bag(path: Path) -> Path:
    """A line recorded late (from the coordinator's snapshot) with jams and a blocked packer,
    stopped before its end: episodes and losses on both sides of the snapshot."""
    import yaml

    from test.core.test_line_scenarios import cell_doc, started

    doc = cell_doc(publish_period=5.0)
    sim = started(doc)
    for t0 in (0, 60):
        sim.at(t0 + 20, lambda: sim.alarm("filler", "infeed", 202, True))
        sim.at(t0 + 24, lambda: sim.alarm("filler", "infeed", 202, False))
        sim.at(t0 + 25, lambda: sim.command("filler", Cmd.RESET))
        sim.at(t0 + 27, lambda: sim.command("filler", Cmd.START))
        sim.at(t0 + 35, lambda: sim.interlock("packer", "loader", blocked=True))
        sim.at(t0 + 40, lambda: sim.interlock("packer", "loader", blocked=False))
    sim.run_until(50)
    sim.snapshot()
    sim.run_until(120)
    sim.write_bag(path, yaml.safe_dump(doc), joined=50, stop=110, input_history=20)
    return path


#: Line regressions (monkeypatched, as MUTATIONS): each must make the line's replay differ.
LINE_MUTATIONS: dict[str, Callable[[Patch], None]] = {
    "a blocked or starved root cause booked as unplanned":
        lambda p: _wrap(p, line_episodes, "root_cause", _blocked_as_unplanned),
    "counts of the output unit not counted for the line":
        lambda p: _wrap(p, line_performance.Performance, "_count", _line_counts_dropped),
}  # fmt: skip


def _blocked_as_unplanned(original: Any) -> Any:
    from dataclasses import replace

    def root_cause(departures: Any, order: Any) -> Any:
        root = original(departures, order)
        down = (line_losses.BLOCKED, line_losses.STARVED)
        return replace(root, bucket=line_losses.UNPLANNED) if root.bucket in down else root

    return root_cause


def _line_counts_dropped(original: Any) -> Any:
    def count(self: Any, scope: str, at: int, dp: int, dd: int, design: float) -> None:
        if scope != "":
            original(self, scope, at, dp, dd, design)

    return count


def test_the_line_topics_are_covered_by_the_mutation_test(tmp_path: Path) -> None:
    """A line bag recorded late replays; its last line/episodes or line/losses message deleted
    or altered, or the line's performance mutated, is caught."""
    from packml_interfaces.msg import LineEpisode, LineLosses
    from rclpy.serialization import deserialize_message, serialize_message

    from packml_ros2.bag import line
    from test.test_replay import _topic_counts, rewrite

    bag = _line_bag(tmp_path / "line")
    [ok] = line.check(bag)
    assert ok.ok and ok.origin > 0 and all(ok.compared.values()), ok.report()
    counts = {t.rsplit("/", 1)[1]: n for t, n in _topic_counts(bag).items()}

    def altered(cls: Any, field: str, value: Any) -> Callable[[bytes], bytes]:
        def change(raw: bytes) -> bytes:
            m = deserialize_message(raw, cls)
            setattr(m, field, value)
            return bytes(serialize_message(m))

        return change

    changes = {"episodes": altered(LineEpisode, "bucket", "planned"),
               "losses": altered(LineLosses, "window", "2h")}  # fmt: skip
    missed = []
    for topic in ("episodes", "losses"):
        last = counts[topic] - 1
        suffix = f"/line/{topic}"
        for how in ("deleted", "altered"):
            dst = tmp_path / f"{how}_{topic}"
            if how == "deleted":
                rewrite(bag, dst, drop=lambda t, i, raw, s=suffix, n=last: t.endswith(s) and i == n)
            else:
                rewrite(bag, dst, change=lambda t, i, raw, s=suffix, n=last, c=changes[topic]: c(raw) if t.endswith(s) and i == n else raw)  # fmt: skip
            [result] = line.check(dst)
            print(f"last line/{topic} message {how}: {'caught' if not result.ok else 'NOT CAUGHT'}")
            if result.ok or not result.checks[topic]:
                missed.append(f"last line/{topic} message {how}")
    for name, mutation in LINE_MUTATIONS.items():
        with applied(mutation):
            [result] = line.check(bag)
        print(f"{name}: {'caught' if not result.ok else 'NOT CAUGHT'}")
        if result.ok:
            missed.append(name)
    [again] = line.check(bag)
    assert again.ok  # and undone
    assert not missed, missed
