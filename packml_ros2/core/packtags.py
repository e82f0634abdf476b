"""PackTags (docs/packml.md §5): the Command/Status/Admin tag model of a unit.

:class:`StatusView` and :class:`AdminView` are immutable snapshots taken from a
:class:`~.unit.Unit`; :func:`flat_tags` turns them into the standard dotted names
(``Status.StateCurrent``, ``Admin.ProdProcessedCount[0].Count``) for bridges to other systems.
OEE (section 6) is computed here from the times and counters.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from .alarms import AlarmEvent, AlarmManager
from .alarms import Kind as AlarmKind
from .config import Descriptor, Product, UnitConfig
from .counters import Counter, Counters
from .equipment import Equipment
from .interlocks import Interlocks
from .modes import GROUPS, ModeDef
from .numbers import NUM_STATES, Cmd, Mode, State, command_name, state_name
from .recipes import Recipes
from .times import ROLLOVER, ModeStateTimes, TimesSnapshot

S = State


class UnitView(Protocol):
    """What the views are built from: a :class:`~.unit.Unit` (kept abstract here, so this module
    and the engine do not import each other)."""

    config: UnitConfig
    mode: int
    mode_def: ModeDef
    mode_requested: int
    mode_change_in_process: bool
    mach_speed: float
    cntrl_cmd: int
    command_unit_mode: int
    remote_enabled: bool
    remote_commands: dict[int, tuple[int, int]]
    parameters: list[Descriptor]
    products: list[Product]
    entered_at: float
    equipment: Equipment
    alarms: AlarmManager
    times: ModeStateTimes
    counters: Counters
    interlocks: Interlocks
    recipes: Recipes

    @property
    def now(self) -> float: ...
    @property
    def stop_reason(self) -> AlarmEvent | None: ...
    @property
    def mode_change_not_allowed(self) -> bool: ...
    def state_requested(self, state: State | None = None) -> State: ...
    def valid_commands(self, state: State | None = None) -> Sequence[Cmd]: ...


@dataclass(frozen=True, slots=True)
class EmView:
    """``EmSummary``: one EM as the unit sees it."""

    name: str
    active: bool
    online: bool
    configured: bool
    state_complete: bool
    sequence: int
    command_request: int
    blocked: bool
    starved: bool
    stale_reports: int
    recipe_answer: int = 0  #: its answer to the last changeover order (recipes.EmAnswer)
    recipe_message: str = ""  #: the reason it gave


class StackLightView(NamedTuple):
    """``StackLight``: the lights top to bottom (off 0, on 1, blink 2) and the horn."""

    colors: tuple[str, ...] = ()
    modes: tuple[int, ...] = ()
    horn: bool = False


NO_LIGHT = StackLightView()  #: a unit without a stack light (a PLC's)


@dataclass(frozen=True, slots=True)
class RemoteInterfaceView:
    number: int
    control_cmd_number: int
    cmd_value: int
    parameter: tuple[Descriptor, ...] = ()


@dataclass(frozen=True, slots=True)
class StatusView:
    """``Status`` PackTags plus names, sequence, valid commands and the EM summary."""

    time: float
    unit: str
    unit_mode_current: int
    unit_mode_requested: int
    unit_mode_change_in_process: bool
    state_current: int
    state_requested: int
    state_change_in_process: bool
    mach_speed: float
    cur_mach_speed: float
    material_interlock: int
    blocked: bool
    starved: bool
    remote_interface: tuple[RemoteInterfaceView, ...]
    parameter: tuple[Descriptor, ...]
    product: tuple[Product, ...]
    cntrl_cmd: int
    command_unit_mode: int
    command_mach_speed: float
    state_current_name: str
    unit_mode_current_name: str
    sequence: int
    states_disabled: int
    commands_valid: tuple[int, ...]
    mode_change_not_allowed: bool
    remote_commands_enabled: bool
    time_rollover_warning: bool
    equipment: tuple[EmView, ...]
    active_alarms: int
    unacknowledged_alarms: int
    alarm_banner: str
    stop_reason_id: int
    recipe_current: int = 0
    recipe_current_name: str = ""
    recipe_requested: int = 0
    recipe_change_in_process: bool = False
    recipe_changeover: int = 0
    recipe_result: str = ""
    stack_light: StackLightView = NO_LIGHT

    @property
    def commands_valid_names(self) -> tuple[str, ...]:
        return tuple(command_name(c) for c in self.commands_valid)


@dataclass(frozen=True, slots=True)
class Oee:
    availability: float
    performance: float
    quality: float
    oee: float
    production_time: float
    execute_time: float
    planned_stop_time: float
    internal_downtime: float
    external_downtime: float
    stopped_time: float
    aborted_time: float
    processed: int
    defective: int


@dataclass(frozen=True, slots=True)
class AdminView:
    """``Admin`` PackTags plus OEE and overflow counts."""

    time: float
    unit: str
    parameter: tuple[Descriptor, ...]
    alarm: tuple[AlarmEvent, ...]
    alarm_history: tuple[AlarmEvent, ...]
    stop_reason: AlarmEvent | None
    warning: tuple[AlarmEvent, ...]
    times: TimesSnapshot
    prod_consumed_count: tuple[Counter, ...]
    prod_processed_count: tuple[Counter, ...]
    prod_defective_count: tuple[Counter, ...]
    mach_design_speed: float
    states_disabled: int
    plc_date_time: tuple[int, ...]
    alarm_overflow: int
    warning_overflow: int
    oee: Oee
    alarms_version: int = 0  # AlarmManager.version the lists were taken at (publishers cache by it)

    @property
    def acc_time_since_reset(self) -> int:
        return self.times.acc_time_since_reset


def date_time_array(t: float) -> tuple[int, ...]:
    """PackTags DateTime array: year, month, day, hour, minute, second, microsecond (UTC)."""
    d = _dt.datetime.fromtimestamp(max(0.0, t), tz=_dt.UTC)
    return (d.year, d.month, d.day, d.hour, d.minute, d.second, d.microsecond)


def _em_views(unit: UnitView, state: int, sequence: int) -> tuple[EmView, ...]:
    cur = (state, sequence)
    answers = unit.recipes.answers()
    none = (0, "")
    return tuple(
        EmView(
            em.name,
            em.active,
            em.online,
            em.configured,
            em.last_report == cur,
            em.last_report[1] if em.last_report else 0,
            em.command_request,
            em.blocked,
            em.starved,
            em.stale_reports,
            *answers.get(em.name, none),
        )
        for em in unit.equipment.modules.values()
    )


def stack_light(unit: UnitView, state: int) -> StackLightView:
    """The stack light in ``state`` with the unit's alarms now (core/stacklight.py)."""
    light = unit.config.stack_light
    current = unit.alarms.current.values()
    alarms = [ev for ev in current if ev.trigger and ev.kind is AlarmKind.ALARM]
    shown = light.show(
        state,
        frozenset(ev.category for ev in alarms),
        any(ev.ack_time is None and ev.kind is AlarmKind.ALARM for ev in current),
        any(ev.trigger and ev.kind is AlarmKind.WARNING for ev in current),
    )
    return StackLightView(light.lights, shown.modes, shown.horn)


def build_status(unit: UnitView, time: float, state: State, sequence: int) -> StatusView:
    """The status as it was at a transition or mark (``time``, ``state``, ``sequence``); the
    other fields are the unit's current ones."""
    requested = unit.state_requested(state)
    in_execute = state is S.EXECUTE
    eq, recipes = unit.equipment, unit.recipes
    remote = tuple(
        RemoteInterfaceView(ri.number, *unit.remote_commands.get(ri.number, (0, 0)))
        for ri in unit.config.remote_interfaces
    )
    return StatusView(
        time=time,
        unit=unit.config.name,
        unit_mode_current=unit.mode,
        unit_mode_requested=unit.mode_requested,
        unit_mode_change_in_process=unit.mode_change_in_process,
        state_current=int(state),
        state_requested=int(requested),
        state_change_in_process=requested != state,
        mach_speed=unit.mach_speed,
        cur_mach_speed=unit.mach_speed if in_execute else 0.0,
        material_interlock=eq.material_interlock(),
        blocked=eq.blocked() or unit.interlocks.says("blocked"),
        starved=eq.starved() or unit.interlocks.says("starved"),
        remote_interface=remote,
        parameter=tuple(unit.parameters),
        product=tuple(unit.products),
        cntrl_cmd=unit.cntrl_cmd,
        command_unit_mode=unit.command_unit_mode,
        command_mach_speed=unit.mach_speed,
        state_current_name=state_name(state),
        unit_mode_current_name=unit.mode_def.name,
        sequence=sequence,
        states_disabled=unit.mode_def.disabled_mask,
        commands_valid=tuple(int(c) for c in unit.valid_commands(state)),
        mode_change_not_allowed=unit.mode_change_not_allowed,
        remote_commands_enabled=unit.remote_enabled,
        time_rollover_warning=unit.times.acc_at(unit.now) >= ROLLOVER,
        equipment=_em_views(unit, state, sequence),
        active_alarms=unit.alarms.active_count(),
        unacknowledged_alarms=unit.alarms.unacknowledged_count(),
        alarm_banner=unit.alarms.banner(),
        stop_reason_id=unit.stop_reason.id if unit.stop_reason else 0,
        recipe_current=recipes.current.id,
        recipe_current_name=recipes.current.name,
        recipe_requested=recipes.requested,
        recipe_change_in_process=recipes.in_process,
        recipe_changeover=recipes.order,
        recipe_result=recipes.result,
        stack_light=stack_light(unit, state),
    )


#: Held and suspended time: the state groups a configuration names (modes.GROUPS, one
#: declaration), in the states' order
_INTERNAL = tuple(s for s in State if s in GROUPS["HOLD"])
_EXTERNAL = tuple(s for s in State if s in GROUPS["SUSPEND"])
_ABORTED = (S.ABORTING, S.ABORTED, S.CLEARING)
_STOPPED = (S.STOPPING, S.STOPPED, S.RESETTING, S.IDLE, S.STARTING, S.COMPLETING, S.COMPLETE)


def compute_oee(
    mode_cum: list[float],
    state_cum: list[float],
    planned: float,
    processed: int,
    defective: int,
    design_speed: float,
) -> Oee:
    """OEE over Production mode: A = Execute / (Production - planned stops), P = processed /
    (MachDesignSpeed [per minute] x Execute), Q = (processed - defective) / processed."""
    base = Mode.PRODUCTION * NUM_STATES

    def total(states: tuple[State, ...]) -> float:
        return sum(state_cum[base + s] for s in states)

    production = mode_cum[Mode.PRODUCTION]
    execute = state_cum[base + S.EXECUTE]
    available = production - planned
    a = execute / available if available > 0 else 0.0
    p = processed / (design_speed / 60.0 * execute) if design_speed > 0 and execute > 0 else 0.0
    q = (processed - defective) / processed if processed > 0 else 0.0
    return Oee(
        a,
        p,
        q,
        a * p * q,
        production,
        execute,
        planned,
        total(_INTERNAL),
        total(_EXTERNAL),
        max(0.0, total(_STOPPED) - planned),
        total(_ABORTED),
        processed,
        defective,
    )


def build_admin(unit: UnitView, at: float) -> AdminView:
    alarms, alarm_over = unit.alarms.listed(warnings=False)
    warnings, warning_over = unit.alarms.listed(warnings=True)
    _, mcum, _, scum, _ = unit.times.live(at)
    counters = unit.counters
    processed, defective = counters.total("processed"), counters.total("defective")
    oee = compute_oee(
        mcum,
        scum,
        unit.times.planned_stop_at(at),
        processed,
        defective,
        unit.config.mach_design_speed,
    )

    return AdminView(
        time=at,
        unit=unit.config.name,
        parameter=unit.config.admin_parameters,
        alarm=tuple(alarms),
        alarm_history=tuple(unit.alarms.history),
        stop_reason=unit.stop_reason,
        warning=tuple(warnings),
        times=unit.times.snapshot(at),
        prod_consumed_count=counters.snapshot("consumed"),
        prod_processed_count=counters.snapshot("processed"),
        prod_defective_count=counters.snapshot("defective"),
        mach_design_speed=unit.config.mach_design_speed,
        states_disabled=unit.mode_def.disabled_mask,
        plc_date_time=date_time_array(at),
        alarm_overflow=alarm_over,
        warning_overflow=warning_over,
        oee=oee,
        alarms_version=unit.alarms.version,
    )


# -- the flat view ---------------------------------------------------------------------------------
def _descriptor_tags(prefix: str, items: tuple[Descriptor, ...], out: dict[str, Any]) -> None:
    for i, d in enumerate(items):
        out[f"{prefix}[{i}].ID"] = d.id
        out[f"{prefix}[{i}].Name"] = d.name
        out[f"{prefix}[{i}].Unit"] = d.unit
        out[f"{prefix}[{i}].Value"] = d.value


def _alarm_tags(prefix: str, ev: AlarmEvent | None, out: dict[str, Any]) -> None:
    out[f"{prefix}.ID"] = ev.id if ev else 0
    out[f"{prefix}.Value"] = ev.value if ev else 0
    out[f"{prefix}.Message"] = ev.message if ev else ""
    out[f"{prefix}.Category"] = ev.category if ev else 0
    out[f"{prefix}.Trigger"] = ev.trigger if ev else False
    out[f"{prefix}.DateTime"] = date_time_array(ev.time) if ev else (0,) * 7
    out[f"{prefix}.AckDateTime"] = date_time_array(ev.ack_time) if ev and ev.ack_time else (0,) * 7


def flat_tags(status: StatusView, admin: AdminView | None = None) -> dict[str, Any]:
    """Standard dotted PackTags names -> values (``Status.StateCurrent``, ``Command.CntrlCmd``,
    ``Admin.ProdProcessedCount[0].Count``, ``Admin.StateCurrentTime[1,6]``...)."""
    out: dict[str, Any] = {
        "Command.UnitMode": status.command_unit_mode,
        "Command.UnitModeChangeRequest": status.unit_mode_change_in_process,
        "Command.MachSpeed": status.command_mach_speed,
        "Command.MaterialInterlock": status.material_interlock,
        "Command.CntrlCmd": status.cntrl_cmd,
        "Command.CmdChangeRequest": status.state_change_in_process,
        "Status.UnitModeCurrent": status.unit_mode_current,
        "Status.UnitModeRequested": status.unit_mode_requested,
        "Status.UnitModeChangeInProcess": status.unit_mode_change_in_process,
        "Status.StateCurrent": status.state_current,
        "Status.StateRequested": status.state_requested,
        "Status.StateChangeInProcess": status.state_change_in_process,
        "Status.MachSpeed": status.mach_speed,
        "Status.CurMachSpeed": status.cur_mach_speed,
        "Status.MaterialInterlock": status.material_interlock,
        "Status.EquipmentInterlock.Blocked": status.blocked,
        "Status.EquipmentInterlock.Starved": status.starved,
    }
    for i, ri in enumerate(status.remote_interface):
        for side in ("Command", "Status"):
            out[f"{side}.RemoteInterface[{i}].Number"] = ri.number
            out[f"{side}.RemoteInterface[{i}].ControlCmdNumber"] = ri.control_cmd_number
            out[f"{side}.RemoteInterface[{i}].CmdValue"] = ri.cmd_value
    for side in ("Command", "Status"):
        _descriptor_tags(f"{side}.Parameter", status.parameter, out)
        for i, p in enumerate(status.product):
            out[f"{side}.Product[{i}].ProductID"] = p.product_id
            _descriptor_tags(f"{side}.Product[{i}].ProcessVariables", p.process_variables, out)
            for j, ing in enumerate(p.ingredients):
                out[f"{side}.Product[{i}].Ingredients[{j}].IngredientID"] = ing.ingredient_id
                _descriptor_tags(
                    f"{side}.Product[{i}].Ingredients[{j}].Parameter", ing.parameter, out
                )
    if admin is None:
        return out
    t = admin.times
    _descriptor_tags("Admin.Parameter", admin.parameter, out)
    for i, ev in enumerate(admin.alarm):
        _alarm_tags(f"Admin.Alarm[{i}]", ev, out)
    out["Admin.AlarmExtent"] = len(admin.alarm)
    for i, ev in enumerate(admin.alarm_history):
        _alarm_tags(f"Admin.AlarmHistory[{i}]", ev, out)
    out["Admin.AlarmHistoryExtent"] = len(admin.alarm_history)
    _alarm_tags("Admin.StopReason", admin.stop_reason, out)
    out["Admin.StopReasonExtent"] = 1 if admin.stop_reason else 0
    for i, ev in enumerate(admin.warning):
        _alarm_tags(f"Admin.Warning[{i}]", ev, out)
    out["Admin.WarningExtent"] = len(admin.warning)
    for m, v in enumerate(t.mode_current):
        out[f"Admin.ModeCurrentTime[{m}]"] = v
        out[f"Admin.ModeCumulativeTime[{m}]"] = t.mode_cumulative[m]
    for i, v in enumerate(t.state_current):
        m, s = divmod(i, NUM_STATES)
        out[f"Admin.StateCurrentTime[{m},{s}]"] = v
        out[f"Admin.StateCumulativeTime[{m},{s}]"] = t.state_cumulative[i]
    for tag, counters in (
        ("ProdConsumedCount", admin.prod_consumed_count),
        ("ProdProcessedCount", admin.prod_processed_count),
        ("ProdDefectiveCount", admin.prod_defective_count),
    ):
        for i, c in enumerate(counters):
            out[f"Admin.{tag}[{i}].ID"] = c.id
            out[f"Admin.{tag}[{i}].Name"] = c.name
            out[f"Admin.{tag}[{i}].Unit"] = c.unit
            out[f"Admin.{tag}[{i}].Count"] = c.count
            out[f"Admin.{tag}[{i}].AccCount"] = c.acc_count
    out["Admin.AccTimeSinceReset"] = t.acc_time_since_reset
    out["Admin.MachDesignSpeed"] = admin.mach_design_speed
    out["Admin.StatesDisabled"] = admin.states_disabled
    out["Admin.PLCDateTime"] = admin.plc_date_time
    return out
