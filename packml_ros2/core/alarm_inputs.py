"""Alarms as inputs of a unit: raised and cleared (by an operator, a remote source or an EM),
acknowledged, reset (docs/packml.md §9). The alarm list is :class:`~.alarms.AlarmManager`'s; a
rising alarm's reaction is queued for the state machine (:meth:`~.machine.UnitMachine._raise`).
"""

from __future__ import annotations

from . import inputlog
from .alarms import AlarmDef
from .machine import UnitMachine
from .numbers import command_name
from .reasons import Answer, Reason
from .rules import (
    NUM_CATEGORIES,
    OPERATOR,
    Trigger,
    override_refusal,
)


class AlarmInputs(UnitMachine):
    """The alarm inputs of a :class:`~.unit.Unit`."""

    __slots__ = ()

    # -- alarms ------------------------------------------------------------------------------------
    def set_alarm(
        self,
        alarm_id: int,
        value: int = 0,
        active: bool = True,
        source: str = OPERATOR,
        em: str = "",
        warning: bool | None = None,
        category: int = -1,
        message: str = "",
    ) -> Answer:
        """Raise or clear alarm (``alarm_id``, ``value``). Unconfigured alarms need a category and
        a message; ``warning``/``category``/``message`` override the configuration when given."""
        source = source or OPERATOR
        with self._input(
            inputlog.ALARM, alarm_id, value, active, source, em, warning, category, message
        ):
            return self._locked(f"alarm {alarm_id}/{value}", source) or self._set_alarm(
                int(alarm_id), int(value), bool(active), source, em, warning, int(category), message
            )

    def _set_alarm(
        self,
        alarm_id: int,
        value: int,
        active: bool,
        source: str,
        em: str,
        warning: bool | None,
        category: int,
        message: str,
    ) -> Answer:
        name = self.config.name
        if not active:
            ev = self.alarms.clear(alarm_id, value, self._t)
            if ev is None:
                return Answer.no(Reason.NOTHING_TO_DO, f"alarm {alarm_id}/{value} is not active")
            return Answer.ok(f"alarm {ev.label()} cleared (latched until reset)")
        if not -1 <= category < NUM_CATEGORIES:
            return Answer.no(
                Reason.INVALID_ARGUMENT,
                f"category {category} is neither -1 (as configured) nor 0..{NUM_CATEGORIES - 1}",
            )
        d = self.alarms.definition(alarm_id, value)
        if d is None:
            if category < 0 or not message:
                return Answer.no(
                    Reason.ALARM_UNKNOWN,
                    f"alarm {alarm_id}/{value} is not configured on {name}; "
                    "give its category (0..9) and a message",
                )
            if (alarm_id, value) not in self.alarms.current and self.alarms.full():
                return Answer.no(
                    Reason.INVALID_ARGUMENT,
                    f"alarm {alarm_id}/{value} refused: {name} lists {len(self.alarms.current)} "
                    "alarms and warnings already; configure the alarms it should take",
                )
            d = AlarmDef(alarm_id, value, message, category, bool(warning), None, em)
        else:
            changed = override_refusal(d, category, message, warning)
            if changed is not None:
                return Answer.no(Reason.INVALID_ARGUMENT, changed)
        what = "warning" if d.warning else "alarm"
        if not self._raise(d, source=source, em=em, trigger=Trigger.ALARM):
            return Answer.no(Reason.NOTHING_TO_DO, f"{what} {alarm_id}/{value} is already active")
        reaction = self.alarms.reaction_of(d)
        act = f"; reaction {command_name(reaction)}" if reaction else ""
        return Answer.ok(f"{what} {alarm_id}/{value} raised{act}")

    def em_alarm(
        self,
        name: str,
        alarm_id: int,
        value: int,
        active: bool,
        warning: bool = False,
        category: int = -1,
        message: str = "",
    ) -> Answer:
        """An alarm raised or cleared by EM ``name``. A configured alarm is raised as configured:
        the EM's own category, kind or text for it are ignored (and logged), never refused (the
        condition it reports is real)."""
        d = self.alarms.definition(int(alarm_id), int(value))
        if d is not None and active:
            changed = override_refusal(d, int(category), message, warning or None)
            if changed is not None:
                self._log("warn", f"EM {name}: {changed}; raised as configured")
                warning, category, message = False, -1, ""
        return self.set_alarm(
            alarm_id, value, active, f"em:{name}", name, warning or None, category, message
        )

    def ack_alarms(
        self, alarm_id: int | None = None, value: int = 0, source: str = OPERATOR
    ) -> Answer:
        """Acknowledge one alarm, or all with ``alarm_id=None``; AckDateTime is stamped once."""
        source = source or OPERATOR
        with self._input(inputlog.ALARM_ACK, alarm_id, value, source):
            refused = self._locked("acknowledging alarms", source)
            if refused is not None:
                return refused
            key = None if alarm_id is None else (int(alarm_id), int(value))
            if key is not None and key not in self.alarms.current:
                return Answer.no(
                    Reason.ALARM_UNKNOWN, f"alarm {key[0]}/{key[1]} is not in the alarm list"
                )
            n = self.alarms.acknowledge(key, self._t)
            if not n:
                which = "every alarm is" if key is None else f"alarm {key[0]}/{key[1]} is"
                return Answer.no(Reason.NOTHING_TO_DO, f"{which} already acknowledged")
            return Answer.ok(f"{n} acknowledged")

    def reset_alarms(self, clear_first_out: bool = False, source: str = OPERATOR) -> Answer:
        """Clear latched alarms that are no longer active (and optionally the first-outs)."""
        source = source or OPERATOR
        with self._input(inputlog.ALARM_RESET, clear_first_out, source):
            refused = self._locked("resetting alarms", source)
            if refused is not None:
                return refused
            n = self.alarms.reset()
            if clear_first_out:
                self.alarms.clear_first_out()
            still = self.alarms.active_count()
            tail = f"; {still} still active" if still else ""
            return Answer.ok(f"{n} cleared{tail}")
