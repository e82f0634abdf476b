"""Equipment modules as their unit sees them, and State Complete aggregation (docs/packml.md §4).

Unit SC for acting state S = every active EM has reported SC for (S, sequence). A report for another
state or sequence is stale: ignored and counted. Which EMs must report is fixed when the unit
enters the state (:meth:`Equipment.begin`, by the rules of :mod:`.rules` section 7) and shrinks
when EMs report, are switched inactive or are excused because they went offline.

:class:`Equipment` owns the EMs, the set still owing State Complete, and the ``EM_MISSING`` bit of
the unit's :class:`~.rules.Alert` (an active EM whose loss is not ignored is offline).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from .numbers import State
from .rules import (
    AGGREGATING,
    AT_ONCE_WITHOUT_EMS,
    EXCUSE_OFFLINE,
    ONLY_WITH_ACTIVE_EMS,
    Alert,
    Watch,
)


@dataclass(slots=True)
class EquipmentModule:
    name: str
    configured: bool
    active: bool = True
    online: bool = False
    lost_reaction: int | None = None  # None: the unit's default
    ignore_loss: bool = False  # effective lost reaction is "ignore": never waited for offline
    index: int = 0  # 1-based position; the Value of its "EM lost" alarm
    last_report: tuple[int, int] | None = None  # (state, sequence) of its last SC
    stale_reports: int = 0
    command_request: int = 0
    blocked: bool = False
    starved: bool = False
    material_interlock: int = 0


class Equipment:
    """The unit's EMs and the set of EMs still owing State Complete for (state, sequence)."""

    __slots__ = ("_owing", "active", "aggregating", "alert", "current", "modules", "pending",
                 "roster_version", "sequence", "state", "version")  # fmt: skip

    def __init__(self, alert: Alert | None = None) -> None:
        self.alert = alert if alert is not None else Alert()
        self.modules: dict[str, EquipmentModule] = {}
        self.state = 0
        self.sequence = 0
        self.current: tuple[int, int] = (0, 0)  # (state, sequence), shared by the reports of it
        self.pending: set[str] = set()
        self.aggregating = False
        self.active = 0  # how many EMs are active
        self.version = 0  # +1 whenever something an EmSummary shows changes
        self.roster_version = 0  # +1 when an EM is added or changes active/online
        #: Who owes State Complete on entering a state (excusing offline EMs or not), as of the
        #: roster: the pending set of a state is a copy (rebuilt when the roster changed).
        self._owing: dict[bool, frozenset[str]] = {}

    def __iter__(self) -> Iterator[EquipmentModule]:
        return iter(self.modules.values())

    def __len__(self) -> int:
        return len(self.modules)

    def get(self, name: str) -> EquipmentModule | None:
        return self.modules.get(name)

    def add(
        self,
        name: str,
        configured: bool,
        active: bool = True,
        lost_reaction: int | None = None,
        ignore_loss: bool = False,
    ) -> EquipmentModule:
        em = EquipmentModule(
            name,
            configured,
            active,
            lost_reaction=lost_reaction,
            ignore_loss=ignore_loss,
            index=len(self.modules) + 1,
        )
        self.modules[name] = em
        self.changed_roster()
        return em

    def changed_roster(self) -> None:
        """An EM was added or switched active/online."""
        self.version += 1
        self.roster_version += 1
        self.active = sum(1 for em in self.modules.values() if em.active)
        self.alert.set(Watch.EM_MISSING, bool(self.missing()))
        self._owing = {
            excuse: frozenset(
                em.name
                for em in self.modules.values()
                if em.active and (em.online or not (excuse or em.ignore_loss))
            )
            for excuse in (False, True)
        }

    # -- aggregation -------------------------------------------------------------------------------
    def begin(self, state: State, sequence: int) -> bool:
        """The unit entered ``state`` with ``sequence``: who must report SC. True when State
        Complete is due at once (the state aggregates and nobody owes it)."""
        self.state = state
        self.sequence = sequence
        self.current = (state, sequence)
        self.version += 1
        if not self.modules:  # (pending stays empty)
            self.aggregating = aggregating = state in AT_ONCE_WITHOUT_EMS
            return aggregating
        if state in AGGREGATING and (self.active or state not in ONLY_WITH_ACTIVE_EMS):
            self.aggregating = True
            self.pending = pending = set(self._owing[state in EXCUSE_OFFLINE])
            return not pending
        self.aggregating = False
        self.pending = set()
        return False

    def begin_mode_change(self, sequence: int) -> None:
        """A mode change was accepted (new ``sequence``): every active online EM confirms it."""
        self.sequence = sequence
        self.current = (self.state, sequence)
        self.aggregating = self.active > 0
        self.pending = {em.name for em in self.modules.values() if em.active and em.online}
        self.version += 1

    def end_aggregation(self) -> None:
        """Nobody owes anything for the current (state, sequence) any more."""
        self.aggregating = False
        self.pending = set()
        self.version += 1

    def report(self, name: str, state: int, sequence: int) -> bool:
        """An EM reports SC; False when the report is stale (counted) or unknown."""
        em = self.modules.get(name)
        if em is None:
            return False
        self.version += 1
        if sequence != self.sequence or state != self.state or not self.aggregating:
            em.stale_reports += 1
            return False
        em.last_report = self.current
        self.pending.discard(name)
        return True

    def excuse(self, name: str) -> None:
        """``name`` no longer has to report for the current state."""
        if name in self.pending:
            self.pending.discard(name)
            self.version += 1

    def require(self, name: str) -> None:
        """``name`` (re-)joined while aggregating and has not reported yet: wait for it (an EM
        switched active joins the current state: rules.ACTIVATED_EM_JOINS_CURRENT_STATE)."""
        em = self.modules[name]
        if (
            self.aggregating
            and em.active
            and em.online
            and em.last_report != (self.state, self.sequence)
        ):
            self.pending.add(name)
            self.version += 1

    @property
    def complete(self) -> bool:
        return self.aggregating and not self.pending

    def has_reported(self, em: EquipmentModule) -> bool:
        return em.last_report == (self.state, self.sequence)

    # -- derived -----------------------------------------------------------------------------------
    def active_count(self) -> int:
        return self.active

    def missing(self) -> list[EquipmentModule]:
        """Active EMs that are offline and whose loss is not ignored."""
        return [
            em for em in self.modules.values() if em.active and not em.online and not em.ignore_loss
        ]

    def blocked(self) -> bool:
        return any(em.blocked for em in self.modules.values() if em.active)

    def starved(self) -> bool:
        return any(em.starved for em in self.modules.values() if em.active)

    def material_interlock(self) -> int:
        bits = 0
        for em in self.modules.values():
            if em.active:
                bits |= em.material_interlock
        return bits
