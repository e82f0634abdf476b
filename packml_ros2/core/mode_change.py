"""Mode changes of a unit (docs/packml.md §3), once a request is accepted: the EMs'
acknowledgement awaited, the change finished (the mode's compiled rules and times switched, the
transition recorded) or abandoned by a fault command, and the mode-change-not-allowed flag.
:class:`ModeChanges` owns the mode's fields (``mode``, ``mode_requested``,
``mode_change_in_process``...: the fast path reads them) and these steps; the machine's evaluation
calls them (:meth:`~.machine.UnitMachine._settle` finishes a change) and judges a request
(``_apply_mode``, where the guards and the not-allowed lamp's time are)."""

from __future__ import annotations

import math
from collections.abc import Callable

from .config import UnitConfig
from .deadlines import Deadlines
from .equipment import Equipment
from .modes import ModeDef
from .numbers import State
from .outputs import Outputs
from .publication import Publication
from .rules import (
    Accepted,
    Alert,
    Trigger,
    Watch,
)
from .times import ModeStateTimes


class ModeChanges:
    """The mode changes of a unit (a base of :class:`~.machine.UnitMachine`)."""

    __slots__ = (  # noqa: RUF023 (in the order of __init__)
        "mode", "mode_def", "_accepted_mode", "command_unit_mode", "mode_requested",
        "mode_change_in_process", "_mode_source", "mode_change_not_allowed_until",
    )  # fmt: skip

    def __init__(self, config: UnitConfig, accepted: dict[int, list[dict[int, Accepted]]]) -> None:
        self.mode = int(config.initial_mode)
        self.mode_def: ModeDef = config.modes[self.mode]
        self._accepted_mode = accepted[self.mode]  # the current mode's compiled rules
        self.command_unit_mode = self.mode
        self.mode_requested = self.mode
        self.mode_change_in_process = False
        self._mode_source = ""
        self.mode_change_not_allowed_until = -math.inf

    # What they read of the machine (declared and set there).
    config: UnitConfig
    state: State
    sequence: int
    alert: Alert
    equipment: Equipment
    deadlines: Deadlines
    times: ModeStateTimes
    publication: Publication
    _accepted: dict[int, list[dict[int, Accepted]]]
    _t: float
    _out: Outputs
    _status_now: Callable[[], None]
    _changed: Callable[[], None]
    _log: Callable[[str, str], None]
    _planned: Callable[[], bool]

    @property
    def mode_change_not_allowed(self) -> bool:
        return self._t < self.mode_change_not_allowed_until

    def mode_change_text(self) -> str:
        """What a guard says while a mode change is in process."""
        waiting = ", ".join(sorted(self.equipment.pending)) or "none"
        return (
            f"mode change {self.mode_def.name} -> {self._mode_name(self.mode_requested)} in "
            f"process (waiting for EMs: {waiting})"
        )

    def _mode_name(self, number: int) -> str:
        m = self.config.modes.get(number)
        return m.name if m else f"MODE_{number}"

    def _mode_changing(self, on: bool) -> None:
        self.mode_change_in_process = on
        self.alert.set(Watch.MODE_CHANGE, on)

    def _abandon_mode_change(self, why: str) -> None:
        """A fault command arrived while a mode change was in process: the mode stays."""
        target = self.mode_requested
        self.mode_requested = self.mode
        self._mode_changing(False)
        self._changed()
        self._log(
            "warn",
            f"mode change {self.mode_def.name} -> {self._mode_name(target)} abandoned: {why}",
        )

    def _find_mode(self, mode: int | str) -> ModeDef | None:
        if isinstance(mode, str) and not mode.strip().isdigit():
            return self.config.mode_by_name(mode)
        return self.config.modes.get(int(mode))

    def _finish_mode_change(self) -> None:
        frm = self.mode
        self.mode = self.mode_requested
        self.mode_def = self.config.modes[self.mode]
        self._accepted_mode = self._accepted[self.mode]
        self._mode_changing(False)
        self.times.enter(self._t, self.mode, self.state, self._planned())
        self.equipment.end_aggregation()
        detail = f"{self._mode_name(frm)} -> {self.mode_def.name}"
        self._out.append(
            (
                "transition",
                (
                    self._t,
                    self.sequence,
                    (
                        self.state,
                        self.state,
                        frm,
                        self.mode,
                        Trigger.MODE,
                        0,
                        self._mode_source,
                        (),
                        detail,
                    ),
                ),
            )
        )
        self.publication.with_record()
        self._log(
            "info", f"mode {self._mode_name(frm)} -> {self.mode_def.name} ({self._mode_source})"
        )


__all__ = ["ModeChanges"]
