"""Equipment modules as their unit sees them, and State Complete aggregation (PACKML.md section 4).

Unit SC for acting state S = every active EM has reported SC for (S, sequence). A report for another
state or sequence is stale: ignored and counted. Which EMs must report is fixed when the unit
enters the state (:meth:`Equipment.begin`) and shrinks when EMs report, are switched inactive or
are excused because they went offline.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field


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


@dataclass
class Equipment:
    """The unit's EMs and the set of EMs still owing State Complete for (state, sequence)."""

    modules: dict[str, EquipmentModule] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.state = 0
        self.sequence = 0
        self.pending: set[str] = set()
        self.aggregating = False
        self.version = 0  # +1 whenever something an EmSummary shows changes
        self.roster_version = 0  # +1 when an EM is added or changes active/online

    def __iter__(self) -> Iterator[EquipmentModule]:
        return iter(self.modules.values())

    def __len__(self) -> int:
        return len(self.modules)

    def get(self, name: str) -> EquipmentModule | None:
        return self.modules.get(name)

    def add(self, name: str, configured: bool, active: bool = True) -> EquipmentModule:
        em = EquipmentModule(name, configured, active, index=len(self.modules) + 1)
        self.modules[name] = em
        self.changed_roster()
        return em

    def changed_roster(self) -> None:
        """An EM was added or switched active/online."""
        self.version += 1
        self.roster_version += 1

    # -- aggregation ---------------------------------------------------------------------------------
    def begin(self, state: int, sequence: int, aggregating: bool, excuse_offline: bool) -> None:
        """The unit entered ``state`` with ``sequence``: who must report SC (if ``aggregating``)."""
        self.state, self.sequence, self.aggregating = state, sequence, aggregating
        if not self.modules:
            self.pending = set()
        elif aggregating:
            self.pending = {
                em.name
                for em in self.modules.values()
                if em.active and (em.online or not (excuse_offline or em.ignore_loss))
            }
        else:
            self.pending = set()
        self.version += 1

    def report(self, name: str, state: int, sequence: int) -> bool:
        """An EM reports SC; False when the report is stale (counted) or unknown."""
        em = self.modules.get(name)
        if em is None:
            return False
        if state != self.state or sequence != self.sequence or not self.aggregating:
            em.stale_reports += 1
            self.version += 1
            return False
        em.last_report = (state, sequence)
        self.pending.discard(name)
        self.version += 1
        return True

    def excuse(self, name: str) -> None:
        """``name`` no longer has to report for the current state."""
        if name in self.pending:
            self.pending.discard(name)
            self.version += 1

    def require(self, name: str) -> None:
        """``name`` (re-)joined while aggregating and has not reported yet: wait for it."""
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

    # -- derived -------------------------------------------------------------------------------------
    def active_count(self) -> int:
        return sum(1 for em in self.modules.values() if em.active)

    def missing(self) -> list[EquipmentModule]:
        """Active EMs that are offline."""
        return [em for em in self.modules.values() if em.active and not em.online]

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
