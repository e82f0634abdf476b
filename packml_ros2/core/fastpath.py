"""The command fast path of a unit without EMs, generated from the compiled rules: each
:class:`~.rules.Run` (a command and the State Completes that follow it at once) becomes a Python
function of its own, its states, records and answer bound as constants and its loop unrolled, as
rosbags generates its CDR code from type definitions. What it does is what the general loop
(``UnitMachine._transition``) does for the same run; ``test_a_compiled_run_does_what_the_general_
loop_does`` (test/core/test_rules.py) holds the two to the same outputs.

A generated run first checks that the unit is quiet enough for it (nothing queued, no EM, no
interlock's suspension, no alarm list to publish, no alarm or first-out an entry action would
reset) and answers None when it is not: the engine then takes the general loop.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any

from .reasons import Answer
from .rules import OPERATOR, Entry, Rules, Run
from .times import ModeStateTimes

#: A generated run: (unit, source) -> its answer, or None (the general loop decides).
Go = Callable[[Any, str], Answer | None]

_REARM = int(Entry.REARM)
_generated: weakref.WeakKeyDictionary[Rules, bool] = weakref.WeakKeyDictionary()


def source_of(run: Run) -> str:
    """The Python source of ``run``'s function (its constants are the names :func:`generate`
    binds)."""
    n = len(run.tails)
    quiet = [
        "unit._internal",
        "unit.equipment.modules",
        "unit.interlocks.suspended",
        "alarms.version != unit.publication.alarms_seen",
    ]
    if run.entry:  # an entry action would reset what is listed: the general loop does that
        quiet.append("alarms.current or alarms.first_out_by_category")
    lines = [
        "def go(unit, source):",
        "    alarms = unit.alarms",
        f"    if {' or '.join(quiet)}:",
        "        return None",
        f"    unit.cntrl_cmd = {run.cmd}",
        "    t = unit._t",
        "    seq = unit.sequence",
        "    out = unit._out.append",
        "    if source is OPERATOR:",
        "        out(('transition', (t, seq + 1, TAIL)))",
        "    else:",
        "        out(('transition', (t, seq + 1, (START, FIRST, MODE, MODE, TRIGGER, CMD, source,"
        " SKIPPED, ''))))",
    ]
    lines += [f"    out(('transition', (t, seq + {i + 2}, TAILS[{i}])))" for i in range(n)]
    lines.append("    stops = unit.stops")
    if run.entry & _REARM:
        lines.append("    stops.armed = True  # all the entry actions do: nothing to reset")
    lines += [
        f"    unit.sequence = seq = seq + {n + 1}",
        "    unit.state = FINAL",
        "    unit.entered_at = t",
        "    tm = unit.times",
    ]
    planned = "stops.planned_reason and stops.planned(MODE, FINAL)"
    times = ModeStateTimes.enter_states_source(
        "tm", "t", run.first, run.final, run.between, planned
    )
    lines += ["    " + line for line in times]
    lines += [
        "    equipment = unit.equipment",
        "    if equipment.aggregating:  # (a run ends where the unit waits)",
        "        equipment.begin(FINAL, seq)",
        "    return ANSWER",
    ]
    return "\n".join(lines) + "\n"


def generate(run: Run) -> Go:
    """``run`` as a function of its own (see :func:`source_of`)."""
    names: dict[str, Any] = {
        "OPERATOR": OPERATOR,
        "TAIL": run.tail,
        "TAILS": run.tails,
        "START": run.start,
        "FIRST": run.first,
        "FINAL": run.final,
        "MODE": run.mode,
        "TRIGGER": run.trigger,
        "CMD": run.cmd,
        "SKIPPED": run.skipped,
        "BETWEEN": run.between,
        "ANSWER": run.answer,
    }
    where = f"<packml run {run.start.name} {run.cmd} mode {run.mode}>"
    exec(compile(source_of(run), where, "exec"), names)
    go: Go = names["go"]
    return go


def attach(rules: Rules) -> None:
    """Give every :class:`~.rules.Accepted` with a :class:`~.rules.Run` in ``rules`` its
    generated function (``go``; once per rules)."""
    if rules in _generated:
        return
    for by_state in rules.accepted.values():
        for by_cmd in by_state:
            for cmd, accepted in by_cmd.items():
                if accepted.run is not None and accepted.go is None:
                    by_cmd[cmd] = accepted._replace(go=generate(accepted.run))
    _generated[rules] = True


__all__ = ["Go", "attach", "generate", "source_of"]
