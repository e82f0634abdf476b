"""What a unit does when one of its deadlines falls due (:class:`~.deadlines.Deadlines` keeps
what is due when): a state's timeout, the end of a minimum dwell, a mode change's timeout, the
mode-change-not-allowed flag going out, a coalesced status or admin, the periodic admin and save.

:data:`DeadlineHandlers.DEADLINE_HANDLERS` maps each kind of :class:`~.deadlines.Due` to its
handler, once; :meth:`~.machine.UnitMachine._fire` calls them at their own times, then settles
and publishes as after any input.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from .alarms import AlarmDef
from .deadlines import Due
from .machine import UnitMachine
from .numbers import State, state_name
from .packtags import build_admin
from .recipe_inputs import RecipeInputs
from .rules import Trigger


class DeadlineHandlers(UnitMachine):
    """The deadline handlers of a :class:`~.unit.Unit`."""

    __slots__ = ()

    def _on_timeout(self, data: tuple[State, int]) -> None:
        state, seq = data
        if (self.state, self.sequence) != (state, seq):
            return
        missing = sorted(self.equipment.pending) or ["minimum dwell"]
        sa = self.config.system_alarms
        d = AlarmDef(
            sa.state_timeout,
            int(state),
            f"{state_name(state)} timed out waiting for {', '.join(missing)}",
            sa.state_timeout_category,
        )
        self._raise(d, source="unit", trigger=Trigger.TIMEOUT)
        self.alarms.clear(d.id, d.value, self._t)

    def _on_dwell(self, data: tuple[State, int]) -> None:
        """Nothing to do here: :meth:`_settle`, run after every deadline, completes the state."""

    def _on_mode_timeout(self, seq: int) -> None:
        if not self.mode_change_in_process or self.sequence != seq:
            return
        waiting = ", ".join(sorted(self.equipment.pending))
        target = self.mode_requested
        self.mode_requested = self.mode
        self._mode_changing(False)
        self.equipment.end_aggregation()
        sa = self.config.system_alarms
        d = AlarmDef(
            sa.mode_change_timeout,
            target,
            f"mode change to {self._mode_name(target)} timed out waiting for {waiting}",
            sa.mode_change_timeout_category,
        )
        self._raise(d, source="unit", trigger=Trigger.TIMEOUT)
        self.alarms.clear(d.id, d.value, self._t)
        self._rev += 1
        self._status_now()

    def _on_lamp_off(self, _: Any) -> None:
        """``mode_change_not_allowed`` went out (3 s after the refusal): publish that."""
        if not self.mode_change_not_allowed:
            self._rev += 1
            self._status_now()

    def _on_status(self, _: Any) -> None:
        self.publication.status_deadline(self._t, self.state, self.sequence)

    def _on_admin_change(self, _: Any) -> None:
        self.publication.admin(build_admin(self, self._t), coalesced=True)

    def _on_save(self, period: float) -> None:
        self._snapshot()
        self._every(Due.SAVE, period)

    def _on_admin(self, period: float) -> None:
        self.publication.admin(build_admin(self, self._t), coalesced=False)
        self._every(Due.ADMIN, period)

    DEADLINE_HANDLERS: ClassVar[Mapping[Due, Callable[[Any, Any], None]]] = {
        Due.TIMEOUT: _on_timeout,
        Due.DWELL: _on_dwell,
        Due.MODE_TIMEOUT: _on_mode_timeout,
        Due.STATUS: _on_status,
        Due.LAMP_OFF: _on_lamp_off,
        Due.ADMIN_CHANGE: _on_admin_change,
        Due.SAVE: _on_save,
        Due.ADMIN: _on_admin,
        Due.RECIPE_TIMEOUT: RecipeInputs._on_recipe_timeout,
    }
