"""Why a command or a mode change is not available now, in the unit's own words.

A unit publishes which commands are valid now (``Status.commands_valid``), not why the others are
not. The HMI asks the unit's rule book (:func:`packml_ros2.core.rules.rules_of` of the unit's
configuration: the same compiled table, guards and sentences the unit judges with) about the
situation the unit's status and alarm list show: its state and mode, a mode change in process,
its equipment modules online or not, the active alarms and their reactions, a line interlock.
The rule book judges the command as the unit will when the HMI sends it: from the source the
HMI's actions carry (:func:`.access.command_source` of who acts: ``hmi:<user>``, a remote source,
so the remote lock is judged too, and its sentence names that source). A command the rule book
would accept but the unit does not list (the unit knows more than it publishes) gets a plain
sentence saying so.

The cell's commands (:func:`cell_command_reasons`) are judged from the coordinator's CellStatus:
the commands it lists as valid now (``commands_valid``: its units' rules, all or nothing) and
whether one of its sequences runs (``busy``: then only the commands that interrupt a sequence).

Everything here reads what a unit published, which may be anything: an unknown state or mode is
answered with a sentence, never an exception.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ..core.config import UnitConfig
from ..core.line.sequence import INTERRUPTS_A_SEQUENCE
from ..core.numbers import Cmd, Mode, State, command_name, names_of, state_name
from ..core.reasons import Reason
from ..core.rules import COMMANDS, GUARDS, Rules, locked_refusal, remote_locked, rules_of

#: The reasons of the rule book's guards (a situation: the lock, a mode change, a missing EM, an
#: alarm, an interlock), not of its state model: the page lists these apart ("not now").
GUARD_REASONS = frozenset(g.reason for g in GUARDS)


class StatusSituation:
    """A unit's situation as its status and alarm list show it (the rules' ``Situation``)."""

    def __init__(
        self, config: UnitConfig, status: Mapping[str, Any], alarms: Mapping[str, Any] | None
    ) -> None:
        self.config = config
        self.status = status
        self.alarms = list(alarms.get("alarms", ())) if alarms else []
        lost = {e.name: e.lost_reaction for e in config.equipment_modules}
        self._ignored = {
            name for name, r in lost.items() if (config.em_lost_reaction if r is None else r) == 0
        }
        if config.em_lost_reaction == 0:  # registered EMs follow the unit's reaction
            self._ignored |= {
                e["name"] for e in status.get("equipment_modules", ()) if e.get("name") not in lost
            }

    @property
    def remote_enabled(self) -> bool:
        return bool(self.status.get("remote_commands_enabled", True))

    @property
    def mode_change_in_process(self) -> bool:
        return bool(self.status.get("mode_change_in_process"))

    def missing_names(self) -> list[str]:
        return [
            e["name"]
            for e in self.status.get("equipment_modules", ())
            if e.get("active") and not e.get("online") and e.get("name") not in self._ignored
        ]

    def blocking_alarm(self, blocked: Mapping[int, frozenset[Cmd]], cmd: int) -> str | None:
        for a in self.alarms:
            reaction = a.get("reaction") or 0
            if a.get("trigger") and reaction and cmd in blocked.get(reaction, ()):
                label = f'{a["id"]}/{a["value"]} "{a["message"]}" (category {a["category"]})'
                return f"alarm {label} with reaction {command_name(reaction)}"
        return None

    def recipe_change_text(self) -> str:
        if not self.status.get("recipe_change_in_process"):
            return ""
        return f"the changeover to recipe {self.status.get('recipe_requested', 0)} is in process"

    def interlock_reasons(self) -> list[str]:
        s = self.status
        return [w for w, on in (("blocked", s.get("blocked")), ("starved", s.get("starved"))) if on]

    def mode_change_text(self) -> str:
        s = self.status
        waiting = sorted(
            e["name"]
            for e in s.get("equipment_modules", ())
            if e.get("active") and not e.get("state_complete")
        )
        return (
            f"mode change {s.get('mode_name', '')} -> {_mode_name(self.config, s.get('mode_requested', 0))} "
            f"in process (waiting for EMs: {', '.join(waiting) or 'none'})"
        )


def _mode_name(config: UnitConfig, number: int) -> str:
    m = config.modes.get(number)
    return m.name if m else f"MODE_{number}"


def _known(rules: Rules, status: Mapping[str, Any]) -> tuple[State, int] | str:
    """(state, mode) of ``status``, or why they cannot be judged."""
    state, mode = status.get("state"), status.get("mode")
    if mode not in rules.modes:
        return f"the unit reports mode {mode}, which its configuration does not have"
    if not isinstance(state, int) or state not in State._value2member_map_ or not state:
        return f"the unit reports state {state}, which PackML does not have"
    return State(state), int(mode)


def command_reasons(
    config: UnitConfig, status: Mapping[str, Any], alarms: Mapping[str, Any] | None, source: str
) -> dict[str, dict[str, Any]]:
    """``{command name: {reason, text, guard}}`` for every command the unit would not take from
    ``source`` now (not listed as valid, or locked): its reason code, the sentence the unit
    answers it with, and whether a guard refuses it (:data:`GUARD_REASONS`) rather than the state
    model."""
    rules = rules_of(config)
    valid: Sequence[int] = [c for c in status.get("commands_valid", ()) if isinstance(c, int)]
    known = _known(rules, status)
    out: dict[str, dict[str, Any]] = {}
    situation = StatusSituation(config, status, alarms)
    # the unit lists what its rules allow now, whoever asks: the lock refuses those too
    locked = remote_locked(source, situation.remote_enabled)
    for cmd in COMMANDS:
        if cmd in valid and not locked:
            continue
        if isinstance(known, str):
            out[cmd.name] = {
                "reason": Reason.COMMAND_NOT_ALLOWED.name,
                "text": known,
                "guard": False,
            }
            continue
        state, mode = known
        mode_name = rules.modes[mode].name
        where = f"{state.name} in {mode_name} mode"
        verdict = rules.check(situation, state, mode, cmd, source)
        if verdict.reason is Reason.ACCEPTED:
            text = (
                f"{cmd.name} is not valid now in {where} (valid now: {names_of(valid) or 'none'})"
            )
            out[cmd.name] = {
                "reason": Reason.COMMAND_NOT_ALLOWED.name,
                "text": text,
                "guard": False,
            }
            continue
        text = rules.refusal_text(verdict, cmd, source, where, config.name, mode_name, valid)
        out[cmd.name] = {
            "reason": verdict.reason.name,
            "text": text,
            "guard": verdict.reason in GUARD_REASONS,
        }
    return out


def mode_reasons(config: UnitConfig, status: Mapping[str, Any], source: str) -> dict[str, str]:
    """``{mode number: sentence}`` for every configured mode the unit cannot change to now from
    ``source`` (the current one included: it is where the unit is)."""
    rules = rules_of(config)
    known = _known(rules, status)
    remote_enabled = StatusSituation(config, status, None).remote_enabled
    out: dict[str, str] = {}
    for number, target in sorted(rules.modes.items()):
        if isinstance(known, str):
            out[str(number)] = known
            continue
        what = f"mode change to {target.name}"
        locked = locked_refusal(what, source, remote_enabled, config.name)
        if locked is not None:  # judged first, as the unit does
            out[str(number)] = locked.message
            continue
        state, mode = known
        current = rules.modes[mode]
        if status.get("mode_change_in_process"):
            requested = _mode_name(config, status.get("mode_requested", 0))
            out[str(number)] = (
                f"mode change to {target.name} refused: change to {requested} still in process"
            )
        elif number == mode:
            out[str(number)] = f"{target.name} is the current mode"
        else:
            why = rules.mode_change_refusal(mode, number, state)
            if why is not None:
                out[str(number)] = (
                    f"mode change {current.name} -> {target.name} not allowed in {state.name}: "
                    f"{why}"
                )
    return out


def em_reasons(config: UnitConfig, status: Mapping[str, Any], source: str) -> dict[str, str]:
    """``{EM name: sentence}`` for every EM in the status the unit would not switch from ``source``
    now (to inactive if it is active, else to active): the remote lock, then PRODUCTION (the
    unit's check, :meth:`packml_ros2.core.em_inputs.EquipmentInputs.set_em_active`, in its
    words; test/hmi/test_why.py asks the unit itself)."""
    remote_enabled = StatusSituation(config, status, None).remote_enabled
    out: dict[str, str] = {}
    for em in status.get("equipment_modules", ()):
        name = str(em.get("name", ""))
        word = "inactive" if em.get("active") else "active"
        locked = locked_refusal(f"switching EM {name}", source, remote_enabled, config.name)
        if locked is not None:
            out[name] = locked.message
        elif status.get("mode") == Mode.PRODUCTION:
            out[name] = (
                f"EM {name} can be switched {word} only outside PRODUCTION (now PRODUCTION, "
                f"{_state_text(status.get('state'))}); change to MAINTENANCE first"
            )
    return out


def _state_text(state: Any) -> str:
    return state_name(state) if isinstance(state, int) else f"state {str(state)[:20]}"


def reasons(
    config: UnitConfig,
    status: Mapping[str, Any] | None,
    alarms: Mapping[str, Any] | None,
    source: str,
) -> dict[str, Any]:
    """``{commands: ..., modes: ..., ems: ...}`` (:func:`command_reasons` for ``source``,
    :func:`mode_reasons` and :func:`em_reasons` from ``source``); empty without a status."""
    if status is None:
        return {"commands": {}, "modes": {}, "ems": {}}
    return {
        "commands": command_reasons(config, status, alarms, source),
        "modes": mode_reasons(config, status, source),
        "ems": em_reasons(config, status, source),
    }


def cell_command_reasons(cell_status: Mapping[str, Any] | None) -> dict[str, str]:
    """``{command name: sentence}`` for every cell command the coordinator would not take now,
    judged from its status (a dict of CellStatus): a sequence running, or not in the commands it
    lists as valid. Empty without a status (the page says that itself)."""
    if cell_status is None:
        return {}
    listed = cell_status.get("commands_valid", ())
    valid = [c for c in listed if isinstance(c, int) and not isinstance(c, bool)]
    busy = bool(cell_status.get("busy"))
    step = str(cell_status.get("sequence_step") or "…")
    only = " and ".join(c.name for c in INTERRUPTS_A_SEQUENCE)
    running = f"a cell sequence is running ({step}); only {only} interrupt it"
    out: dict[str, str] = {}
    for cmd in COMMANDS:
        if busy and cmd not in INTERRUPTS_A_SEQUENCE:
            out[cmd.name] = f"{cmd.name} refused: {running}"
        elif cmd not in valid:
            out[cmd.name] = (
                f"{cmd.name} is not valid for the cell now (valid now: {names_of(valid) or 'none'})"
            )
    return out
