"""What a unit shows on request, built from its parts when asked: the status at a drained
transition or mark, the status and admin now (:func:`~.packtags.build_status`,
:func:`~.packtags.build_admin`), whether an interlock is active, the EMs missing. (What the
publication and the guards read while an input is evaluated stays with the machine.)
"""

from __future__ import annotations

from .equipment import EquipmentModule
from .machine import UnitMachine
from .numbers import State
from .outputs import RawTransition, Transition
from .packtags import AdminView, StatusView, build_admin, build_status
from .publication import StatusMark


class UnitViews(UnitMachine):
    """The on-request views of a :class:`~.unit.Unit`."""

    __slots__ = ()

    def status_at(self, mark: StatusMark | Transition | RawTransition) -> StatusView:
        """The status at a drained transition (typed or as queued) or mark: its state, sequence
        and time, the other fields as they are now."""
        if isinstance(mark, StatusMark):
            return build_status(self, mark.time, State(mark.state), mark.sequence)
        if isinstance(mark, Transition):
            return build_status(self, mark.time, mark.to_state, mark.sequence)
        time, sequence, tail = mark
        return build_status(self, time, tail[1], sequence)  # (tail[1]: the state entered)

    def status(self) -> StatusView:
        return build_status(self, self._t, self.state, self.sequence)

    def admin(self, at: float | None = None) -> AdminView:
        return build_admin(self, self._t if at is None else at)

    @property
    def interlock_active(self) -> bool:
        return bool(self.interlocks.active)

    def missing_ems(self) -> list[EquipmentModule]:
        """Active EMs that are offline and whose loss is not ignored."""
        return self.equipment.missing()
