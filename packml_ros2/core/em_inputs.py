"""What a unit's equipment modules tell it, beyond State Complete: an EM seen (registration where
the configuration allows it), lost (its configured reaction), its command requests, interlocks,
counts, and an operator switching it active or inactive (docs/packml.md §4, rules section 7).

State Complete itself (:meth:`~.machine.UnitMachine.em_complete`) is the state machine's: it runs
for every EM in every acting state.
"""

from __future__ import annotations

from . import inputlog
from .alarms import AlarmDef
from .interlocks import STOP_ID_BLOCKED, STOP_ID_STARVED
from .machine import UnitMachine
from .numbers import Mode, command_name, state_name
from .reasons import Answer, Reason
from .rules import (
    CATEGORY_OF_REACTION,
    EXCUSE_OFFLINE,
    OPERATOR,
    Trigger,
    registration_refusal,
)

#: Unknown EMs refused registration are named in the log once each, up to this many.
MAX_STRAYS_LOGGED = 64


class EquipmentInputs(UnitMachine):
    """The EM inputs of a :class:`~.unit.Unit`; the EMs are :class:`~.equipment.Equipment`'s."""

    __slots__ = ()

    def em_seen(self, name: str, report: bool = False) -> Answer:
        """The EM ``name`` is alive (first heartbeat, or back after being lost). An unknown EM
        registers, where the configuration allows it; ``report``: the EM's own report is what
        says so, which registers it in Production only at rest (rules, section 7)."""
        with self._input(inputlog.EM_SEEN, name, report):
            em = self.equipment.get(name)
            if em is None:
                why = registration_refusal(
                    self.mode,
                    self.state,
                    self.config.allow_registration,
                    report,
                    len(self.equipment),
                )
                if why is not None:
                    if name not in self._strays and len(self._strays) < MAX_STRAYS_LOGGED:
                        self._strays.add(name)  # said once per name (its reports keep coming)
                        self._log("warn", f"EM {name!r} not registered: {self.config.name} {why}")
                    return Answer.no(
                        Reason.EM_UNKNOWN,
                        f"EM {name!r} is not configured and {self.config.name} {why}",
                    )
                self._strays.discard(name)
                ignore = not self._lost_reaction(None)
                if not self.equipment.modules:  # the first EM: the equipment follows the unit now
                    self.equipment.begin(self.state, self.sequence)
                em = self.equipment.add(name, False, True, None, ignore)
                self.alarms.log_event(f"EM {name} registered", self._t, source=f"em:{name}")
                self._log("info", f"EM {name} registered (active)")
            if not em.online:
                em.online = True
                self.equipment.changed_roster()
                self.alarms.clear(self.config.system_alarms.em_lost, em.index, self._t)
                self.equipment.require(name)
                self._log(
                    "info", f"EM {name} online at {state_name(self.state)} seq {self.sequence}"
                )
            return Answer.ok(f"EM {name} online")

    def em_lost(self, name: str, detail: str = "") -> Answer:
        """The EM ``name`` missed its lease (or left); the configured reaction applies."""
        with self._input(inputlog.EM_LOST, name, detail):
            em = self.equipment.get(name)
            if em is None or not em.online:
                return Answer.no(Reason.NOTHING_TO_DO, f"EM {name!r} is not online")
            em.online = False
            self.equipment.changed_roster()
            why = f" ({detail})" if detail else ""
            if self.recipes.changeover is not None:
                self._em_gone_from_changeover(name, f"lost{why}")
            # Inactive EMs are ignored (docs/packml.md §4): off for diagnosis, their loss is no fault.
            reaction = self._lost_reaction(em.lost_reaction) if em.active else 0
            if self.state in EXCUSE_OFFLINE or not reaction:
                self.equipment.excuse(name)
            category = CATEGORY_OF_REACTION[reaction]
            definition = AlarmDef(
                id=self.config.system_alarms.em_lost,
                value=em.index,
                message=f"EM {name} lost{why}",
                category=category,
                warning=not reaction,
                reaction=reaction,
                em=name,
            )
            self._raise(definition, source="unit", trigger=Trigger.EM_LOST)
            what = command_name(reaction) if reaction else "none"
            self._log("warn", f"EM {name} lost{why}: reaction {what}")
            return Answer.ok(f"EM {name} lost; reaction {what}")

    def em_request(self, name: str, cmd: int) -> Answer:
        """EM ``name`` asks the unit for command ``cmd`` (0 withdraws a request: nothing to do)."""
        if not cmd:
            return Answer.ok("request withdrawn")
        em = self.equipment.get(name)
        if em is not None and not em.active:
            return Answer.no(Reason.EM_UNKNOWN, f"EM {name} is inactive; its requests are ignored")
        return self.command(cmd, f"em:{name}")

    def em_interlock(self, name: str, blocked: bool, starved: bool, material: int = 0) -> Answer:
        """EM ``name`` reports Blocked/Starved (``Status.EquipmentInterlock``) and material bits."""
        with self._input(inputlog.EM_INTERLOCK, name, blocked, starved, material):
            em = self.equipment.get(name)
            if em is None:
                return Answer.no(Reason.EM_UNKNOWN, f"no EM {name!r} in {self.config.name}")
            em.blocked, em.starved, em.material_interlock = (
                bool(blocked),
                bool(starved),
                int(material),
            )
            self.equipment.version += 1
            key = f"em:{name}"
            if em.active and (blocked or starved):
                what = "blocked" if blocked else "starved"
                self.interlocks.set(
                    key, f"{name} {what}", STOP_ID_BLOCKED if blocked else STOP_ID_STARVED
                )
            else:
                self.interlocks.clear(key)
            self._rev += 1
            return Answer.ok("interlock updated")

    def em_count(self, name: str, kind: str, index: int, increment: int) -> Answer:
        """EM ``name`` adds ``increment`` to counter ``index`` of ``kind``
        (``consumed`` / ``processed`` / ``defective``)."""
        with self._input(inputlog.EM_COUNT, name, kind, index, increment):
            problem = self.counters.add(kind, int(index), int(increment))
            if problem:
                self.stats.bad_reports += 1
                return Answer.no(Reason.INVALID_ARGUMENT, f"count from {name} refused: {problem}")
            return Answer.ok("counted")

    def set_em_active(self, name: str, active: bool, source: str = OPERATOR) -> Answer:
        """Switch ModuleActive; only outside Production, and always logged."""
        source = source or OPERATOR
        with self._input(inputlog.EM_ACTIVE, name, active, source):
            return self._locked(f"switching EM {name}", source) or self._set_em_active(
                name, bool(active), source
            )

    def _set_em_active(self, name: str, active: bool, source: str) -> Answer:
        em = self.equipment.get(name)
        word = "active" if active else "inactive"
        if em is None:
            known = ", ".join(self.equipment.modules) or "none"
            return Answer.no(
                Reason.EM_UNKNOWN, f"no EM {name!r} in {self.config.name} (EMs: {known})"
            )
        if self.mode == Mode.PRODUCTION:
            return Answer.no(
                Reason.EM_SWITCH_IN_PRODUCTION,
                f"EM {name} can be switched {word} only outside PRODUCTION (now PRODUCTION, "
                f"{state_name(self.state)}); change to MAINTENANCE first",
            )
        if em.active == active:
            return Answer.ok(f"EM {name} already {word}")
        em.active = active
        self.equipment.changed_roster()
        self.alarms.log_event(f"EM {name} switched {word} by {source}", self._t, source=source)
        self._log("info", f"EM {name} switched {word} by {source}")
        if active:
            self.equipment.require(name)  # it joins the current state (rules, section 7)
        else:
            self.equipment.excuse(name)
            self.interlocks.clear(f"em:{name}")
            # An inactive EM is no longer missing: its "EM lost" alarm goes inactive (latched), so
            # Clear and Reset recover without it (docs/packml.md §9).
            self.alarms.clear(self.config.system_alarms.em_lost, em.index, self._t)
        return Answer.ok(f"EM {name} {word}")
