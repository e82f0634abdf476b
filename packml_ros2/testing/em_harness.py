"""Test an equipment module against a real unit in the test's own process.

:class:`EmTestUnit` writes a cell file with one unit that lists the EMs under test, runs the unit
node on the test's :class:`~packml_ros2.testing.harness.RosHarness` (the ``ros`` fixture), and
commands it as an operator would. It follows what the EMs report on ``em_reports`` too, so a test
asserts State Complete per ``(state, sequence)``, counts, alarms and timeouts::

    def test_gripper(ros, tmp_path):
        unit = EmTestUnit(ros, tmp_path, {"gripper": {}})
        ros.add(Gripper("gripper", unit.unit, unit.cell, context=ros.context))
        unit.wait_online("gripper")
        unit.check_lifecycle("gripper")          # reset, start, hold, unhold, stop, abort, clear
        unit.to_execute()
        unit.wait_count("processed", 3)

The EM may be any node that speaks the EM protocol (docs/em-protocol.md), started in this process
or in another one (``unit.cell_file`` is the cell file to give it).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from packml_interfaces.msg import Alarm, EmReport, TransitionEvent

from .. import qos
from ..core import load_cell
from ..core.numbers import State
from .harness import Collector, RosHarness
from .unit_client import UnitClient

_cells = itertools.count()

#: What :meth:`EmTestUnit.check_lifecycle` commands, and the acting state each command leads
#: through before the unit rests again: (trigger service, acting state, wait state).
LIFECYCLE: tuple[tuple[str, str, str], ...] = (
    ("reset", "RESETTING", "IDLE"),
    ("start", "STARTING", "EXECUTE"),
    ("hold", "HOLDING", "HELD"),
    ("unhold", "UNHOLDING", "EXECUTE"),
    ("stop", "STOPPING", "STOPPED"),
    ("reset", "RESETTING", "IDLE"),
    ("start", "STARTING", "EXECUTE"),
    ("abort", "ABORTING", "ABORTED"),
    ("clear", "CLEARING", "STOPPED"),
)

COUNTER_FIELDS = {"consumed": "prod_consumed_count", "processed": "prod_processed_count",
                  "defective": "prod_defective_count"}  # fmt: skip


@dataclass(frozen=True)
class Completion:
    """One acting state the unit went through, and what the EM reported for it."""

    state: str
    sequence: int
    reports: int  # State Complete reports of the EM for exactly (state, sequence); > 1: resent


class EmTestUnit(UnitClient):
    """A unit ``unit`` of a cell of its own, in this process, with the EMs ``ems`` (name -> the
    EM's cell-file entry, e.g. ``{"lost_reaction": "stop"}``); ``unit_config`` adds to the unit's
    entry (``em_lease``, ``alarms``, ``parameters``...)."""

    def __init__(
        self,
        ros: RosHarness,
        tmp_path: Path,
        ems: Mapping[str, Mapping[str, Any]],
        unit: str = "u",
        unit_config: Mapping[str, Any] | None = None,
        cell: str | None = None,
    ) -> None:
        from ..unit_node import UnitNode

        self.cell = cell or f"emtest{os.getpid()}_{next(_cells)}"
        self.unit = unit
        entry: dict[str, Any] = {
            "em_lease": 2.0,
            "persistence": {"path": str(tmp_path / "{unit}.sqlite3")},
            **dict(unit_config or {}),
            "equipment_modules": {name: dict(cfg) for name, cfg in ems.items()},
        }
        self.document = {"cell": self.cell, "units": {unit: entry}}
        self.cell_file = tmp_path / f"{self.cell}.yaml"
        self.cell_file.write_text(yaml.safe_dump(self.document, sort_keys=False))
        super().__init__(ros, self.cell, unit)
        self.reports: Collector[EmReport] = ros.subscribe(
            EmReport, f"{self.base}/em_reports", qos.EM_REPORTS
        )
        config = load_cell(self.cell_file).units[unit]
        self.node = ros.add(UnitNode(config, context=ros.context))
        self.ready()

    # -- commands ----------------------------------------------------------------------------------
    def command_to(self, trigger: str, state: str, timeout: float = 10.0) -> TransitionEvent:
        """Trigger ``trigger`` (``reset``, ``start``, ``hold``...; accepted, or AssertionError)
        and wait until the unit enters ``state``; the transition into it."""
        answer = self.trigger(trigger)
        assert answer.success, f"{trigger} refused: {answer.message}; {self.recent()}"
        return self.wait_entered(state, timeout)

    def recent(self, n: int = 4) -> str:
        """The last ``n`` transitions, for a failure's message."""
        last = list(self.transitions.messages)[-n:]
        steps = [
            f"{t.from_state_name}->{t.to_state_name} ({t.trigger_name} {t.source} {t.detail})".replace(
                " )", ")"
            )
            for t in last
        ]
        return "last transitions: " + "; ".join(steps)

    def to_execute(self, timeout: float = 10.0) -> None:
        """From Stopped (or Idle): Reset and Start, back once the unit is in Execute."""
        if self.status.last.state_current_name != "IDLE":
            self.command_to("reset", "IDLE", timeout)
        self.command_to("start", "EXECUTE", timeout)

    # -- what the EMs did -----------------------------------------------------------------------
    def wait_online(self, em: str, timeout: float = 10.0) -> None:
        self.status.wait_for(
            lambda s: any(e.name == em and e.online for e in s.equipment_modules),
            timeout,
            f"EM {em} online",
        )

    def wait_offline(self, em: str, timeout: float = 10.0) -> None:
        self.status.wait_for(
            lambda s: any(e.name == em and not e.online for e in s.equipment_modules),
            timeout,
            f"EM {em} offline",
            max(0, len(self.status) - 1),
        )

    def completions(self, em: str, state: str, sequence: int) -> int:
        """How many State Complete reports ``em`` sent for (``state``, ``sequence``)."""
        number = int(State[state])
        return sum(
            1
            for r in list(self.reports.messages)
            if r.em == em
            and r.kind == EmReport.KIND_STATE_COMPLETE
            and (r.state, r.sequence) == (number, sequence)
        )

    def wait_completed(self, em: str, state: str, sequence: int, timeout: float = 10.0) -> None:
        """``em`` reports State Complete for (``state``, ``sequence``)."""
        number = int(State[state])
        self.reports.wait_for(
            lambda r: (
                r.em == em
                and r.kind == EmReport.KIND_STATE_COMPLETE
                and (r.state, r.sequence) == (number, sequence)
            ),
            timeout,
            f"State Complete of {em} for {state} seq {sequence}",
        )

    def wait_count(self, counter: str, at_least: int, index: int = 0, timeout: float = 10.0) -> int:
        """The unit's ``counter`` (consumed / processed / defective) ``[index]`` reaches
        ``at_least``; its value then."""
        name = COUNTER_FIELDS[counter]
        admin = self.admin.wait_for(
            lambda a: len(getattr(a, name)) > index and getattr(a, name)[index].count >= at_least,
            timeout,
            f"{counter}[{index}] >= {at_least}",
        )
        return int(getattr(admin, name)[index].count)

    def wait_alarm(self, alarm_id: int, timeout: float = 10.0, warning: bool = False) -> Alarm:
        """Alarm (``warning``: warning) ``alarm_id`` in the unit's list, active or latched (an
        EM may raise and clear it at once: an event; it stays latched until Reset)."""
        field = "warnings" if warning else "alarms"
        alarms = self.alarms.wait_for(
            lambda a: any(x.id == alarm_id and (x.trigger or x.latched) for x in getattr(a, field)),
            timeout,
            f"alarm {alarm_id}",
        )
        return next(x for x in getattr(alarms, field) if x.id == alarm_id)

    def stale_reports(self, em: str) -> int:
        """State Complete reports of ``em`` the unit ignored as stale (not for the current pair)."""
        entry = next((e for e in self.status.last.equipment_modules if e.name == em), None)
        return 0 if entry is None else int(entry.stale_reports)

    def assert_waits_in(self, state: str, seconds: float) -> None:
        """The unit is in ``state`` and does not leave it for ``seconds`` (an EM that has not
        reported holds it there): a bounded wait for something that must not happen."""
        start = len(self.transitions)
        last = self.transitions.last.to_state_name
        assert last == state, f"the unit is in {last}, not {state}"
        try:
            left = self.transitions.wait_for(lambda t: True, seconds, "any transition", start)
        except TimeoutError:
            return
        raise AssertionError(
            f"the unit left {state}: {left.from_state_name} -> {left.to_state_name}"
        )

    # -- the standard checks ---------------------------------------------------------------------
    def check_lifecycle(self, em: str, timeout: float = 10.0) -> list[Completion]:
        """Drive the unit from Stopped through every step of :data:`LIFECYCLE` and check that
        ``em`` reported State Complete for each acting state it went through, at the sequence
        the unit entered it with, and for no other (state, sequence) (a report repeated for the
        same pair is a retransmission, docs/em-protocol.md). Returns what was seen, one
        :class:`Completion` per acting state."""
        self.wait_online(em, timeout)
        if self.status.last.state_current_name != "STOPPED":
            self.command_to("stop", "STOPPED", timeout)
        seen: list[Completion] = []
        for trigger, acting, rest in LIFECYCLE:
            entered = self.command_to(trigger, acting, timeout)
            self.wait_entered(rest, timeout)
            self.wait_completed(em, acting, entered.sequence, timeout)
            seen.append(
                Completion(acting, entered.sequence, self.completions(em, acting, entered.sequence))
            )
        visited = {(int(State[c.state]), c.sequence) for c in seen}
        strays = [
            (r.state, r.sequence)
            for r in list(self.reports.messages)
            if r.em == em
            and r.kind == EmReport.KIND_STATE_COMPLETE
            and (r.state, r.sequence) not in visited
        ]
        # (a report repeated for a visited pair is the protocol's retransmission: allowed)
        assert not strays, f"{em} reported State Complete for pairs the unit was not in: {strays}"
        return seen
