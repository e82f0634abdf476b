"""Engine views -> packml_interfaces messages (and back for request types). Nothing here decides
anything: it only translates field by field."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from packml_interfaces.msg import (
    Admin,
    Alarm,
    AlarmList,
    Count,
    Descriptor,
    EmSummary,
    EquipmentInterlock,
    Ingredient,
    Oee,
    Product,
    Recipe,
    RecipeIngredient,
    RecipeOrder,
    RecipeParameter,
    RemoteInterface,
    StackLight,
    Status,
    TransitionEvent,
)
from packml_interfaces.srv import QueryAlarms

from .core import config as cfg
from .core import recipes
from .core.alarms import AlarmEvent, AlarmManager
from .core.counters import Counter
from .core.numbers import NUM_MODES, NUM_STATES, state_name
from .core.outputs import RawTransition
from .core.packtags import (
    AdminView,
    EmView,
    RemoteInterfaceView,
    StackLightView,
    StatusView,
    date_time_array,
)
from .core.unit import Transition

M = TypeVar("M")

_ZERO7 = [0] * 7


_CHECKED = os.environ.get("ROS_PYTHON_CHECK_FIELDS", "0") == "1"


#: ``QueryAlarms.Request.sort`` -> the order's name (:data:`.core.alarms.ORDERS`)
QUERY_SORTS = {QueryAlarms.Request.SORT_TIME: "time",
               QueryAlarms.Request.SORT_CATEGORY_TIME: "category",
               QueryAlarms.Request.SORT_TIME_NEWEST: "newest"}  # fmt: skip


def build(cls: type[M], **fields: Any) -> M:
    """``cls(**fields)`` without the defaults: rosidl's generated constructors build a default
    for every nested message (``kwargs.get('oee', Oee())`` evaluates ``Oee()`` even when ``oee`` is
    given), which for Admin and Alarm costs more than the fields themselves. Every field must be
    given. With ROS_PYTHON_CHECK_FIELDS=1 (the tests) the normal, checking constructor is used."""
    if _CHECKED:
        return cls(**fields)
    msg = cls.__new__(cls)
    msg._check_fields = False  # type: ignore[attr-defined]
    for name, value in fields.items():
        setattr(msg, name, value)
    return msg


def stamp(seconds: float) -> Time:
    sec = int(seconds // 1)
    return Time(sec=sec, nanosec=min(999_999_999, round((seconds - sec) * 1e9)))


def seconds(t: Time) -> float:
    return float(t.sec + t.nanosec * 1e-9)


# -- descriptors and products ----------------------------------------------------------------------
def descriptor(d: cfg.Descriptor) -> Descriptor:
    return Descriptor(id=d.id, name=d.name, unit=d.unit, value=float(d.value))


def descriptor_in(d: Descriptor) -> cfg.Descriptor:
    return cfg.Descriptor(d.id, d.name, d.unit, d.value)


def product(p: cfg.Product) -> Product:
    return Product(
        product_id=p.product_id,
        process_variables=[descriptor(d) for d in p.process_variables],
        ingredients=[
            Ingredient(
                ingredient_id=i.ingredient_id, parameter=[descriptor(d) for d in i.parameter]
            )
            for i in p.ingredients
        ],
    )


def product_in(p: Product) -> cfg.Product:
    return cfg.Product(
        p.product_id,
        tuple(descriptor_in(d) for d in p.process_variables),
        tuple(
            cfg.Ingredient(i.ingredient_id, tuple(descriptor_in(d) for d in i.parameter))
            for i in p.ingredients
        ),
    )


# -- recipes ---------------------------------------------------------------------------------------
def recipe_parameter(p: recipes.Param) -> RecipeParameter:
    return RecipeParameter(
        id=p.id, name=p.name, unit=p.unit, type=int(p.type), value=float(p.value), text=p.text
    )


def recipe(r: recipes.Recipe) -> Recipe:
    """``Recipe`` of a recipe (core/recipes.py)."""
    return Recipe(
        id=r.id,
        name=r.name,
        unit=r.unit,
        primary_qty=float(r.primary_qty),
        process_variables=[recipe_parameter(p) for p in r.process_variables],
        ingredients=[
            RecipeIngredient(
                ingredient_id=i.ingredient_id,
                parameters=[recipe_parameter(p) for p in i.parameters],
            )
            for i in r.ingredients
        ],
    )


def recipe_in(m: Recipe) -> recipes.Recipe:
    """The recipe a ``Recipe`` message carries (an EM reads its order so)."""

    def param(p: RecipeParameter) -> recipes.Param:
        kind = recipes.ParamType(p.type) if p.type <= 3 else recipes.ParamType.REAL
        return recipes.Param(p.id, p.name, p.unit, kind, p.value, p.text)

    return recipes.Recipe(
        m.id,
        m.name,
        m.unit,
        m.primary_qty,
        tuple(param(p) for p in m.process_variables),
        tuple(
            recipes.RecipeIngredient(i.ingredient_id, tuple(param(p) for p in i.parameters))
            for i in m.ingredients
        ),
    )


def recipe_order(
    time: float, item: tuple[int, int, recipes.Recipe, tuple[str, ...]]
) -> RecipeOrder:
    """``RecipeOrder`` of a unit's ``recipe`` output: (order, phase, recipe, EMs asked)."""
    order, phase, r, ems = item
    return RecipeOrder(
        stamp=stamp(time), changeover=order, phase=phase, recipe=recipe(r), ems=list(ems)
    )


def stack_light(v: StackLightView) -> StackLight:
    return StackLight(colors=list(v.colors), modes=list(v.modes), horn=v.horn)


# -- status ----------------------------------------------------------------------------------------
def _generated(cls: type[M], made: dict[str, str], names: dict[str, Any]) -> Callable[[Any], M]:
    """``f(v)``: a ``cls`` message from the view ``v``, each field the expression ``made`` gives
    for it or else ``v``'s field of the same name; generated as if written by hand, one keyword
    argument per field (a loop over the fields cost a quarter more per message)."""
    fields = cls.get_fields_and_field_types()  # type: ignore[attr-defined]
    body = ", ".join(f"{name}={made.get(name, f'v.{name}')}" for name in fields)
    namespace: dict[str, Any] = {}
    exec(
        f"def make(v):\n    return build(cls, {body})",
        {**names, "build": build, "cls": cls},
        namespace,
    )
    return namespace["make"]  # type: ignore[no-any-return]


def _remote_interface(r: RemoteInterfaceView) -> RemoteInterface:
    return RemoteInterface(
        number=r.number,
        control_cmd_number=r.control_cmd_number,
        cmd_value=r.cmd_value,
        parameter=[descriptor(d) for d in r.parameter],
    )


#: ``EmSummary`` of an EM's view: the view's fields of the same names.
_em_summary: Callable[[EmView], EmSummary] = _generated(EmSummary, {}, {})

#: The Status fields made from other fields of the view ``v`` (expressions of :func:`status`);
#: every other field is the view's field of the same name, copied: a field added to both the
#: message and :class:`~.core.packtags.StatusView` needs nothing here (test/test_convert.py checks
#: that every field of the view reaches the message).
_STATUS_MADE: dict[str, str] = {
    "stamp": "stamp(v.time)",
    "equipment_interlock": "EquipmentInterlock(blocked=v.blocked, starved=v.starved)",
    "remote_interface": "[_remote_interface(r) for r in v.remote_interface]",
    "parameter": "[descriptor(d) for d in v.parameter]",
    "product": "[product(p) for p in v.product]",
    "commands_valid": "list(v.commands_valid)",
    "commands_valid_names": "list(v.commands_valid_names)",
    "equipment_modules": "[_em_summary(e) for e in v.equipment]",
    "stack_light": "stack_light(v.stack_light)",
}

#: ``status(v)``: the ``Status`` message of a status view, the one place it is made (for units,
#: through the driver, and PLC bridges alike).
status: Callable[[StatusView], Status] = _generated(
    Status,
    _STATUS_MADE,
    {
        "stamp": stamp,
        "descriptor": descriptor,
        "product": product,
        "EquipmentInterlock": EquipmentInterlock,
        "_remote_interface": _remote_interface,
        "_em_summary": _em_summary,
        "stack_light": stack_light,
    },
)


def transition(
    unit: str, t: Transition | RawTransition, mode_names: dict[int, str] | None = None
) -> TransitionEvent:
    """``TransitionEvent`` of a record, typed or as queued (time, sequence, the other fields)."""
    if isinstance(t, Transition):
        (
            time,
            sequence,
            from_state,
            to_state,
            from_mode,
            to_mode,
            trigger,
            command,
            source,
            skipped,
            detail,
        ) = t
    else:
        (
            time,
            sequence,
            (from_state, to_state, from_mode, to_mode, trigger, command, source, skipped, detail),
        ) = t
    return TransitionEvent(
        stamp=stamp(time),
        unit=unit,
        sequence=sequence,
        from_state=int(from_state),
        to_state=int(to_state),
        from_state_name=state_name(from_state),
        to_state_name=state_name(to_state),
        from_mode=from_mode,
        to_mode=to_mode,
        trigger=int(trigger),
        trigger_name=trigger.name,
        command=int(command),
        source=source,
        skipped_states=[int(s) for s in skipped],
        detail=detail,
    )


# -- alarms ----------------------------------------------------------------------------------------
def alarm(ev: AlarmEvent | None) -> Alarm:
    if ev is None:
        return Alarm(date_time=_ZERO7, ack_date_time=_ZERO7)
    return build(
        Alarm,
        trigger=ev.trigger,
        id=ev.id,
        value=ev.value,
        message=ev.message,
        category=ev.category,
        date_time=list(date_time_array(ev.time)),
        ack_date_time=list(date_time_array(ev.ack_time)) if ev.ack_time is not None else _ZERO7,
        kind=int(ev.kind),
        latched=ev.latched,
        acknowledged=ev.acknowledged,
        operator_state=int(ev.operator_state),
        em=ev.em,
        source=ev.source,
        reaction=int(ev.reaction),
        stamp=stamp(ev.time),
        ack_stamp=stamp(ev.ack_time) if ev.ack_time is not None else Time(),
        cleared_stamp=stamp(ev.cleared_time) if ev.cleared_time is not None else Time(),
    )


class MessageCache:
    """:func:`alarm` (and :func:`count`) with a memory, for publishers that convert the same
    things again and again (every Admin message carries the alarm history and every counter): an
    event or counter whose fields are unchanged gets the message made the first time. The
    messages are shared: publish them, do not modify them."""

    def __init__(self, size: int = 1024) -> None:
        self.size = size
        self._made: dict[tuple[object, ...] | None, Alarm] = {}
        self._counts: dict[tuple[object, ...], Count] = {}
        self._lists_key: tuple[int, int] = (-1, -1)
        self._lists: tuple[list[Alarm], list[Alarm], list[Alarm]] = ([], [], [])
        self._count_lists: dict[int, tuple[tuple[Counter, ...], list[Count]]] = {}

    def lists(self, v: AdminView) -> tuple[list[Alarm], list[Alarm], list[Alarm]]:
        """Admin's alarm, history and warning lists, made again only when the alarm manager's
        version changed (an Admin message is published every second, the history rarely)."""
        key = (v.alarms_version, len(v.alarm_history))
        if key != self._lists_key:
            self._lists_key, self._lists = key, _alarm_lists(v, self)
        return self._lists

    def count(self, c: Counter) -> Count:
        key = (c.id, c.name, c.unit, c.count, c.acc_count)
        msg = self._counts.get(key)
        if msg is None:
            if len(self._counts) >= self.size:
                self._counts.clear()
            msg = self._counts[key] = count(c)
        return msg

    def counts(self, counters: tuple[Counter, ...]) -> list[Count]:
        """The Count messages of a counter snapshot; the engine shares a snapshot until a count
        changes, so the same tuple gets the same list."""
        hit = self._count_lists.get(id(counters))
        if hit is not None and hit[0] is counters:
            return hit[1]
        if len(self._count_lists) >= 16:
            self._count_lists.clear()
        made = [self.count(c) for c in counters]
        self._count_lists[id(counters)] = (counters, made)
        return made

    def __call__(self, ev: AlarmEvent | None) -> Alarm:
        key = (
            None
            if ev is None
            else (
                ev.id,
                ev.value,
                ev.message,
                ev.category,
                ev.kind,
                ev.time,
                ev.em,
                ev.source,
                ev.reaction,
                ev.trigger,
                ev.latched,
                ev.ack_time,
                ev.cleared_time,
            )
        )
        msg = self._made.get(key)
        if msg is None:
            if len(self._made) >= self.size:
                self._made.clear()
            msg = self._made[key] = alarm(ev)
        return msg


def alarm_list(
    unit: str, now: float, alarms: AlarmManager, cache: MessageCache | None = None
) -> AlarmList:
    alarm_of = alarm if cache is None else cache
    listed, alarm_over = alarms.listed(warnings=False)
    warnings, warning_over = alarms.listed(warnings=True)
    # index = category, up to the highest category with a first-out (none: empty, not 10 blanks)
    top = max(alarms.first_out_by_category, default=-1)
    by_category = [alarm_of(alarms.first_out_by_category.get(c)) for c in range(top + 1)]
    return AlarmList(
        stamp=stamp(now),
        unit=unit,
        alarms=[alarm_of(ev) for ev in listed],
        warnings=[alarm_of(ev) for ev in warnings],
        first_out=alarm_of(alarms.first_out),
        first_out_by_category=by_category,
        first_out_em_names=list(alarms.first_out_by_em),
        first_out_by_em=[alarm_of(ev) for ev in alarms.first_out_by_em.values()],
        alarm_overflow=alarm_over,
        warning_overflow=warning_over,
        banner=alarms.banner(),
    )


# -- admin -----------------------------------------------------------------------------------------
def mode_slots(config: cfg.UnitConfig) -> int:
    """Mode slots of the Admin time arrays: index = mode number, up to the highest configured."""
    return max(config.modes, default=0) + 1


def count(c: Counter) -> Count:
    return Count(id=c.id, name=c.name, unit=c.unit, count=c.count, acc_count=c.acc_count)


def _counts(counters: tuple[Counter, ...]) -> list[Count]:
    return [count(c) for c in counters]


def _alarm_lists(
    v: AdminView, alarm_of: Callable[[AlarmEvent | None], Alarm]
) -> tuple[list[Alarm], list[Alarm], list[Alarm]]:
    return (
        [alarm_of(ev) for ev in v.alarm],
        [alarm_of(ev) for ev in v.alarm_history],
        [alarm_of(ev) for ev in v.warning],
    )


def admin(v: AdminView, cache: MessageCache | None = None, modes: int = NUM_MODES) -> Admin:
    """``modes``: how many mode slots the time arrays carry (the highest configured mode + 1, see
    :func:`mode_slots`): modes above it have no times, and 32 x 18 zeros made every message
    hundreds of lines long in ``ros2 topic echo``."""
    alarm_of: Callable[[AlarmEvent | None], Alarm] = alarm if cache is None else cache
    counts_of: Callable[[tuple[Counter, ...]], list[Count]] = (
        _counts if cache is None else cache.counts
    )
    alarms, history, warnings = _alarm_lists(v, alarm_of) if cache is None else cache.lists(v)
    t = v.times
    o = v.oee
    return build(
        Admin,
        stamp=stamp(v.time),
        unit=v.unit,
        parameter=[descriptor(d) for d in v.parameter],
        alarm=alarms,
        alarm_extent=len(alarms),
        alarm_history=history,
        alarm_history_extent=len(history),
        stop_reason=alarm_of(v.stop_reason),
        stop_reason_extent=1 if v.stop_reason is not None else 0,
        warning=warnings,
        warning_extent=len(warnings),
        mode_current_time=t.mode_current[:modes],  # the int32[] setters take any sequence
        mode_cumulative_time=t.mode_cumulative[:modes],
        state_current_time=t.state_current[: modes * NUM_STATES],
        state_cumulative_time=t.state_cumulative[: modes * NUM_STATES],
        prod_consumed_count=counts_of(v.prod_consumed_count),
        prod_processed_count=counts_of(v.prod_processed_count),
        prod_defective_count=counts_of(v.prod_defective_count),
        acc_time_since_reset=t.acc_time_since_reset,
        mach_design_speed=v.mach_design_speed,
        states_disabled=v.states_disabled,
        plc_date_time=list(v.plc_date_time),
        time_rollover_warning=t.rollover_warning,
        alarm_overflow=v.alarm_overflow,
        warning_overflow=v.warning_overflow,
        oee=build(
            Oee,
            availability=o.availability,
            performance=o.performance,
            quality=o.quality,
            oee=o.oee,
            production_time=o.production_time,
            execute_time=o.execute_time,
            planned_stop_time=o.planned_stop_time,
            internal_downtime=o.internal_downtime,
            external_downtime=o.external_downtime,
            stopped_time=o.stopped_time,
            aborted_time=o.aborted_time,
            processed=o.processed,
            defective=o.defective,
        ),
    )


# -- diagnostics -----------------------------------------------------------------------------------


def diagnostics(
    unit: str, hardware_id: str, now: float, view: StatusView, alarms: AlarmManager
) -> DiagnosticArray:
    """One status for the unit (its alarms and warnings) and one per EM (online, active)."""
    active = [ev for ev in alarms.alarms() if ev.trigger]
    warnings = [ev for ev in alarms.warnings() if ev.trigger]
    level = (
        DiagnosticStatus.ERROR
        if active
        else DiagnosticStatus.WARN
        if warnings
        else DiagnosticStatus.OK
    )
    values = [
        KeyValue(key="state", value=view.state_current_name),
        KeyValue(key="mode", value=view.unit_mode_current_name),
        KeyValue(key="sequence", value=str(view.sequence)),
        KeyValue(key="active_alarms", value=str(len(active))),
        KeyValue(key="unacknowledged_alarms", value=str(view.unacknowledged_alarms)),
    ]
    values += [
        KeyValue(
            key=f"alarm {ev.id}/{ev.value}",
            value=f"cat {ev.category}: {ev.message}" + (f" [{ev.em}]" if ev.em else ""),
        )
        for ev in active + warnings
    ]
    message = view.alarm_banner or (
        f"{len(warnings)} warning(s)" if warnings else view.state_current_name
    )
    statuses = [
        DiagnosticStatus(
            level=level,
            name=f"packml: {unit}",
            message=message,
            hardware_id=hardware_id,
            values=values,
        )
    ]
    for em in view.equipment:
        ok = em.online or not em.active
        statuses.append(
            DiagnosticStatus(
                level=DiagnosticStatus.OK if ok else DiagnosticStatus.ERROR,
                name=f"packml: {unit}/{em.name}",
                message=("online" if em.online else "offline")
                + ("" if em.active else ", inactive"),
                hardware_id=hardware_id,
                values=[
                    KeyValue(key="active", value=str(em.active)),
                    KeyValue(key="online", value=str(em.online)),
                ],
            )
        )
    return DiagnosticArray(header=_header(now), status=statuses)


def _header(now: float):  # type: ignore[no-untyped-def]
    from std_msgs.msg import Header

    return Header(stamp=stamp(now))
