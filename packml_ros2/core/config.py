"""Cell configuration: one YAML file describes a cell, its units, their modes, EMs, alarms,
reactions, array sizes, persistence, timeouts and leases, and the coordinator.

:func:`load_cell` validates everything at load; :class:`~.schema.ConfigError` lists every problem
with the file, the key path and what is wrong. ``config/reference_cell.yaml`` shows every option.
"""

from __future__ import annotations

import ipaddress
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from . import schema as sc
from .alarms import DEFAULT_REACTIONS, NUM_CATEGORIES, REACTIONS, AlarmDef
from .counters import KINDS, CounterDef
from .discovery import DiscoveryConfig, parse_discovery
from .line.config import LINE_STORE, LineConfig, parse_line
from .modes import GROUPS, ModeDef, default_modes, make_mode
from .numbers import ACTING, MANDATORY, MAX_MODE, WAIT, Cmd, Mode, State, parse_state
from .recipes import RECIPE_KEYS, RecipeBook, recipe_book
from .rules import (
    COMPLETE_CONFIGURABLE,
    HOLD_CONFIGURABLE,
    MODELS,
    TransitionTable,
    build_table,
    corrected_disabled,
)
from .safe_yaml import read_document
from .schema import ConfigError, Node, invalid
from .secrets import plain_secrets
from .stacklight import DEFAULT as DEFAULT_STACK_LIGHT
from .stacklight import StackLightConfig, stack_light

__all__ = [
    "ArraySizes",
    "CellConfig",
    "ConfigError",
    "CoordinatorConfig",
    "EmConfig",
    "InterlockRule",
    "SystemAlarms",
    "UnitConfig",
    "load_cell",
    "parse_cell",
    "unit_config",
]

DEFAULT_STATE_DIR = "~/.local/state/packml_ros2"


@dataclass(frozen=True)
class ArraySizes:
    """PackTags array capacities; the defaults are Mitsubishi's (docs/packml.md §5)."""

    parameters: int = 10
    admin_parameters: int = 10
    products: int = 5
    process_variables: int = 10
    ingredients: int = 10
    ingredient_parameters: int = 10
    remote_interfaces: int = 10
    remote_parameters: int = 10
    alarms: int = 64
    warnings: int = 64
    history: int = 256
    counters: int = 10


@dataclass(frozen=True)
class Descriptor:
    """PackTags ``{ID, Name, Unit, Value}``."""

    id: int
    name: str = ""
    unit: str = ""
    value: float = 0.0


@dataclass(frozen=True)
class Ingredient:
    ingredient_id: int
    parameter: tuple[Descriptor, ...] = ()


@dataclass(frozen=True)
class Product:
    product_id: int
    process_variables: tuple[Descriptor, ...] = ()
    ingredients: tuple[Ingredient, ...] = ()


@dataclass(frozen=True)
class RemoteInterfaceDef:
    number: int
    name: str = ""


#: How an EM of a cell file runs: the key of its entry that says so -> the EquipmentModule class
#: (``module:Class``) started for it, which reads that block (packml_ros2.em_launch). ``run``
#: names its own class, entry point or program; ``external`` is started elsewhere (not by the
#: launcher). One row per kind: a new kind of EM is one row here and its class.
EM_RUNS: dict[str, str] = {
    "sim": "packml_ros2.sim_em:SimulatedEm",
    "run": "",
    "external": "",
    "action": "packml_ros2.interface_em:InterfaceEm",  # an existing action server's goals
    "service": "packml_ros2.interface_em:InterfaceEm",  # an existing service's calls
}


@dataclass(frozen=True)
class EmConfig:
    name: str
    active: bool = True
    lost_reaction: int | None = None  # None: the unit's em_lost_reaction
    sim: Mapping[str, Any] = field(default_factory=dict)  # simulated behaviour (packml_ros2.sim_em)
    runs: str = ""  # how it runs: a key of EM_RUNS ("": the entry does not say)
    spec: Any = None  # that key's value in the entry (checked by packml_ros2.em_launch)
    process: str = ""  # EMs naming one process run composed in it (--processes, ros2 launch)


@dataclass(frozen=True)
class SystemAlarms:
    """IDs of the alarms the unit raises itself."""

    em_lost: int = 9001
    state_timeout: int = 9002
    mode_change_timeout: int = 9003
    store_unreadable: int = 9004  #: the persistence store could not be read (moved aside)
    #: the persistence store cannot be written (a full disk): the admin data since is not durable
    persistence_failing: int = 9005
    state_timeout_category: int = 2
    mode_change_timeout_category: int = 5
    store_unreadable_category: int = 5
    persistence_failing_category: int = 5


@dataclass(frozen=True)
class UnitConfig:
    name: str
    cell: str = ""
    description: str = ""
    modes: Mapping[int, ModeDef] = field(default_factory=default_modes)
    initial_mode: int = Mode.PRODUCTION
    table: TransitionTable = field(default_factory=build_table)
    remote_commands_enabled: bool = False
    equipment_modules: tuple[EmConfig, ...] = ()
    allow_registration: bool = True
    em_lease: float = 2.0
    em_lost_reaction: int = Cmd.ABORT
    timeouts: Mapping[State, float] = field(default_factory=dict)
    min_dwell: Mapping[State, float] = field(default_factory=dict)
    mode_change_timeout: float = 10.0
    alarms: tuple[AlarmDef, ...] = ()
    reactions: Mapping[int, int] = field(default_factory=lambda: dict(DEFAULT_REACTIONS))
    interlock_reaction: int = Cmd.SUSPEND
    sizes: ArraySizes = ArraySizes()
    counters: Mapping[str, tuple[CounterDef, ...]] = field(default_factory=dict)
    mach_speed: float = 0.0
    mach_design_speed: float = 0.0  # units per minute
    #: the highest MachSpeed the unit takes (None: mach_design_speed when set, else unbounded)
    max_mach_speed: float | None = None
    parameters: tuple[Descriptor, ...] = ()
    admin_parameters: tuple[Descriptor, ...] = ()
    products: tuple[Product, ...] = ()
    remote_interfaces: tuple[RemoteInterfaceDef, ...] = ()
    persistence_path: str | None = None
    persistence_period: float = 5.0
    admin_period: float = 5.0  # a slow heartbeat: Admin also goes out on every change
    system_alarms: SystemAlarms = SystemAlarms()
    planned_stop_ids: tuple[int, int] = (4000, 4999)
    #: ``plc:`` block (a unit whose state machine runs in a PLC, reached over OPC UA): validated
    #: by packml_ros2.plc.config; None for a unit of this package's own engine
    plc: Mapping[str, Any] | None = None
    #: recipes and the rules of changing them (``recipes``, ``recipe_dir``, ``recipe_states``,
    #: ``recipe_timeout``, ``initial_recipe``: core/recipes.py)
    recipes: RecipeBook = field(default_factory=RecipeBook)
    #: the stack light: lights, blink and horn per state and alarm category (core/stacklight.py)
    stack_light: StackLightConfig = DEFAULT_STACK_LIGHT

    def mode_by_name(self, text: str) -> ModeDef | None:
        key = text.strip().upper()
        return next((m for m in self.modes.values() if m.name == key), None)


@dataclass(frozen=True)
class InterlockRule:
    """When ``unit`` reports ``condition`` (blocked / starved), suspend ``suspend``."""

    unit: str
    condition: str
    suspend: tuple[str, ...]


@dataclass(frozen=True)
class CoordinatorConfig:
    enabled: bool = True
    start_order: tuple[str, ...] = ()
    stop_order: tuple[str, ...] = ()
    step_timeout: float = 15.0
    unit_lease: float = 3.0
    interlocks: tuple[InterlockRule, ...] = ()
    propagate_interlocks: bool = True
    #: Command sent to the other online units when a unit is lost (0 = none)
    lost_unit_reaction: int = 0


@dataclass(frozen=True)
class CellConfig:
    cell: str
    units: Mapping[str, UnitConfig]
    coordinator: CoordinatorConfig
    file: str = "<memory>"
    #: ``hmi:`` and ``opcua:`` blocks, validated by packml_ros2.hmi / packml_ros2.opcua
    hmi: Mapping[str, Any] = field(default_factory=dict)
    opcua: Mapping[str, Any] = field(default_factory=dict)
    #: ``mqtt:``: the Sparkplug B edge node (validated by packml_ros2.mqtt)
    mqtt: Mapping[str, Any] = field(default_factory=dict)
    #: ``line:``: the units' order on the line, its output, shifts, the store of its losses
    line: LineConfig = field(default_factory=LineConfig)
    #: ``discovery:``: the cell's domain and Discovery Server (core/discovery.py)
    discovery: DiscoveryConfig = field(default_factory=DiscoveryConfig)
    #: ``dds.interfaces``: the network interfaces (names or IPv4 addresses) DDS may use; empty:
    #: as the environment says (packml_ros2.dds_profile applies them)
    dds_interfaces: tuple[str, ...] = ()


# -- parsing ---------------------------------------------------------------------------------------
def _state(n: Node) -> State:
    if isinstance(n.value, bool) or not isinstance(n.value, str | int) or len(str(n.value)) > 40:
        raise invalid(f"{sc.shown(n.value)} is not a PackML state")
    return sc.via(parse_state)(n)


def _states(
    n: Node, allowed: frozenset[State] | None = None, groups: bool = False
) -> frozenset[State]:
    out: set[State] = set()
    for e in n.elements():
        key = str(e.value).strip().upper()
        if groups and key in ("HOLD", "SUSPEND", "COMPLETE_GROUP"):
            out |= GROUPS[key]
            continue
        s = e.parse(_state, None)
        if s is None:
            continue
        if allowed is not None and s not in allowed:
            e.error(
                f"{s.name} is not allowed here (allowed: {', '.join(x.name for x in sorted(allowed))})"
            )
            continue
        out.add(s)
    return frozenset(out)


def _state_seconds(n: Node, allowed: frozenset[State]) -> dict[State, float]:
    out: dict[State, float] = {}
    for key, child in n.items():
        s = Node(key, child.path, child.problems).parse(_state, None)
        if s is None:
            continue
        if s not in allowed:
            child.error(f"{s.name} is not an acting state")
            continue
        out[s] = child.parse(sc.number(positive=True), 0.0)
    return out


_REACTION = sc.choice(REACTIONS)
_LOST_REACTION = sc.choice({**REACTIONS, "ignore": 0})


def _descriptor(n: Node) -> Descriptor:
    n.check_keys({"id", "name", "unit", "value"})
    return Descriptor(
        n.get("id", sc.integer(), 0),
        n.get("name", sc.text, ""),
        n.get("unit", sc.text, ""),
        n.get("value", sc.number(), 0.0),
    )


def _descriptors(n: Node, capacity: int) -> tuple[Descriptor, ...]:
    items = tuple(e.parse(_descriptor, Descriptor(0)) for e in n.elements())
    if len(items) > capacity:
        n.error(f"{len(items)} entries, but the array holds {capacity} (sizes)")
    return items


def _product(sizes: ArraySizes) -> Callable[[Node], Product]:
    def parse(n: Node) -> Product:
        n.check_keys({"product_id", "process_variables", "ingredients"})
        ingredients = []
        for e in n.list_at("ingredients"):
            e.check_keys({"ingredient_id", "parameter"})
            ingredients.append(
                Ingredient(
                    e.get("ingredient_id", sc.integer(), 0),
                    e.get("parameter", lambda x: _descriptors(x, sizes.ingredient_parameters), ()),
                )
            )
        if len(ingredients) > sizes.ingredients:
            n.child("ingredients", None).error(
                f"{len(ingredients)} entries, the array holds {sizes.ingredients}"
            )
        return Product(
            n.get("product_id", sc.integer(), 0),
            n.get("process_variables", lambda x: _descriptors(x, sizes.process_variables), ()),
            tuple(ingredients),
        )

    return parse


def _sizes(n: Node) -> ArraySizes:
    fields = ArraySizes.__dataclass_fields__
    n.check_keys(set(fields))
    return ArraySizes(
        **{k: n.get(k, sc.integer(1, 100_000), getattr(ArraySizes(), k)) for k in fields}
    )


def _modes(n: Node) -> dict[int, ModeDef]:
    modes = default_modes()
    names = {m.name.lower(): num for num, m in modes.items()}
    for key, child in n.items():
        child.check_keys({"number", "disabled_states", "mode_change_states", "enabled"})
        number = names.get(key.lower())
        if number is None:
            number = child.get("number", sc.integer(4, MAX_MODE), None)
            if number is None:
                child.error(f"user mode {key!r} needs a number in 4..{MAX_MODE}")
                continue
        elif "number" in child.mapping() and child.mapping()["number"] != number:
            child.child("number", child.mapping()["number"]).error(f"{key} is mode {number}")
        if not child.get("enabled", sc.boolean, True):
            modes.pop(number, None)
            continue
        base = modes.get(number)
        disabled = child.get(
            "disabled_states",
            lambda x: _states(x, groups=True),
            base.disabled if base else frozenset(),
        )
        change = child.get(
            "mode_change_states", _states, base.change_allowed if base else frozenset()
        )
        # Both checks of make_mode, reported together and at their keys.
        mandatory = corrected_disabled(disabled) & MANDATORY
        if mandatory:
            listed = ", ".join(s.name for s in sorted(mandatory))
            child.child("disabled_states", None).error(f"{listed} can never be disabled")
        not_wait = change - WAIT
        if not_wait:
            listed = ", ".join(s.name for s in sorted(not_wait))
            child.child("mode_change_states", None).error(
                f"mode changes can only be allowed in wait states, not in {listed}"
            )
        if mandatory or not_wait:
            continue
        modes[number] = make_mode(number, key.upper(), disabled, change)
    return modes


def _alarm(n: Node) -> AlarmDef:
    n.check_keys({"id", "value", "message", "category", "warning", "reaction", "em"})
    if "id" not in n.mapping():
        raise invalid("an alarm needs an id")
    reaction = n.get("reaction", _REACTION, None)
    return AlarmDef(
        id=n.get("id", sc.integer(1, 2**31 - 1), 0),
        value=n.get("value", sc.integer(), 0),
        message=n.get("message", sc.text, ""),
        category=n.get("category", sc.integer(0, NUM_CATEGORIES - 1), 5),
        warning=n.get("warning", sc.boolean, False),
        reaction=reaction,
        em=n.get("em", sc.text, ""),
    )


def _counters(n: Node, capacity: int) -> dict[str, tuple[CounterDef, ...]]:
    n.check_keys(set(KINDS))
    out = {}
    for kind, child in n.items():
        defs = []
        for e in child.elements():
            e.check_keys({"id", "name", "unit"})
            defs.append(
                CounterDef(
                    e.get("id", sc.integer(), 0),
                    e.get("name", sc.text, ""),
                    e.get("unit", sc.text, ""),
                )
            )
        if len(defs) > capacity:
            child.error(f"{len(defs)} counters, but the array holds {capacity} (sizes.counters)")
        out[kind] = tuple(defs)
    return out


def _ems(n: Node) -> tuple[EmConfig, ...]:
    out = []
    for key, child in n.items():
        Node(key, child.path, child.problems).parse(sc.name, "")
        child.check_keys({"active", "lost_reaction", "process", *EM_RUNS})
        sim: dict[str, Any] = child.get("sim", lambda x: dict(x.mapping()), {})
        kinds = [k for k in EM_RUNS if k in child.mapping()]
        if len(kinds) > 1:
            child.error(f"both {' and '.join(kinds)} given: an EM runs one way only")
        out.append(
            EmConfig(
                key,
                child.get("active", sc.boolean, True),
                child.get("lost_reaction", _LOST_REACTION, None),
                sim,
                kinds[0] if kinds else "",
                child.mapping().get(kinds[0]) if kinds else None,
                child.get("process", sc.name, ""),
            )
        )
    return tuple(out)


_UNIT_KEYS = {
    "description", "initial_mode", "model", "hold_from", "complete_from", "remote_commands_enabled",
    "modes", "equipment_modules", "allow_registration", "em_lease", "em_lost_reaction", "timeouts",
    "min_dwell", "mode_change_timeout", "alarms", "reactions", "interlock_reaction", "sizes",
    "counters", "mach_speed", "mach_design_speed", "max_mach_speed", "parameters",
    "admin_parameters", "products", "remote_interfaces", "persistence", "admin_period",
    "system_alarms", "planned_stop_ids", "plc", *RECIPE_KEYS, "stack_light",
}  # fmt: skip


def _unit(name: str, n: Node, cell: str, base_dir: Path) -> UnitConfig:
    n.check_keys(_UNIT_KEYS)
    d = UnitConfig(name=name)
    sizes = n.get("sizes", _sizes, ArraySizes())
    modes = n.get("modes", _modes, default_modes())
    model = n.get("model", sc.choice({m: m for m in MODELS}), "2022")
    hold_from = n.get("hold_from", lambda x: _states(x, HOLD_CONFIGURABLE), None)
    complete_from = n.get("complete_from", lambda x: _states(x, COMPLETE_CONFIGURABLE), None)

    def mode_ref(x: Node) -> int:
        by_name = {m.name.lower(): num for num, m in modes.items()}
        if isinstance(x.value, int) and not isinstance(x.value, bool):
            if x.value not in modes:
                raise invalid(
                    f"mode {x.value} is not configured (configured: {', '.join(map(str, sorted(modes)))})"
                )
            return x.value
        return sc.choice(by_name)(x)

    reactions = dict(DEFAULT_REACTIONS)
    for key, child in n.items_at("reactions"):
        cat = Node(key, child.path, child.problems).parse(sc.via(int), -1)
        if not 0 <= cat < NUM_CATEGORIES:
            child.error(f"category must be 0..{NUM_CATEGORIES - 1}")
            continue
        reactions[cat] = child.parse(_REACTION, reactions[cat])

    ems: tuple[EmConfig, ...] = n.get("equipment_modules", _ems, ())
    em_names = {e.name for e in ems}
    alarm_nodes = n.list_at("alarms")
    alarms = [(e, e.parse(_alarm, None)) for e in alarm_nodes]
    seen: set[tuple[int, int]] = set()
    for e, a in alarms:
        if a is None:
            continue
        if (a.id, a.value) in seen:
            e.error(f"alarm {a.id}/{a.value} is defined twice")
        seen.add((a.id, a.value))
        if a.em and a.em not in em_names:
            listed = ", ".join(sorted(em_names)) or "none"
            e.child("em", a.em).error(
                f"no equipment module {sc.shown(a.em)} in this unit (equipment_modules: {listed})"
            )
    alarm_defs = tuple(a for _, a in alarms if a is not None)

    persistence_path: str | None = str(Path(DEFAULT_STATE_DIR) / "{cell}" / "{unit}.sqlite3")
    persistence_period = d.persistence_period
    pn = n.mapping().get("persistence", {})
    if pn is None or pn is False:
        persistence_path = None
    else:
        pnode = n.child("persistence", pn)
        pnode.check_keys({"path", "period"})
        persistence_path = pnode.get("path", sc.text, persistence_path)
        persistence_period = pnode.get("period", sc.number(positive=True), persistence_period)
    if persistence_path is not None:
        named = persistence_path.replace("{cell}", cell or "cell").replace("{unit}", name)
        p = Path(os.path.expanduser(named))
        persistence_path = str(p if p.is_absolute() else base_dir / p)

    sys_node = n.mapping().get("system_alarms")
    system_alarms = SystemAlarms()
    if sys_node is not None:
        sn = n.child("system_alarms", sys_node)
        sn.check_keys(set(SystemAlarms.__dataclass_fields__))
        system_alarms = SystemAlarms(
            **{
                k: sn.get(
                    k,
                    sc.integer(0, 9) if k.endswith("category") else sc.integer(1, 2**31 - 1),
                    getattr(system_alarms, k),
                )
                for k in SystemAlarms.__dataclass_fields__
            }
        )

    def remote(x: Node) -> RemoteInterfaceDef:
        x.check_keys({"number", "name"})
        return RemoteInterfaceDef(x.get("number", sc.integer(), 0), x.get("name", sc.text, ""))

    remotes = tuple(e.parse(remote, RemoteInterfaceDef(0)) for e in n.list_at("remote_interfaces"))
    if len(remotes) > sizes.remote_interfaces:
        n.child("remote_interfaces", None).error(
            f"{len(remotes)} entries, the array holds {sizes.remote_interfaces}"
        )

    def id_range(x: Node) -> tuple[int, int]:
        v = x.value
        if not (
            isinstance(v, list)
            and len(v) == 2
            and all(isinstance(i, int) for i in v)
            and v[0] <= v[1]
        ):
            raise invalid("expected [first, last] stop-reason IDs")
        return (v[0], v[1])

    products = tuple(e.parse(_product(sizes), Product(0)) for e in n.list_at("products"))
    if len(products) > sizes.products:
        n.child("products", None).error(
            f"{len(products)} products, the array holds {sizes.products}"
        )

    interlock_reaction = n.get(
        "interlock_reaction", sc.choice({"suspend": int(Cmd.SUSPEND), "none": 0}), int(Cmd.SUSPEND)
    )
    initial_mode = n.get(
        "initial_mode",
        mode_ref,
        Mode.PRODUCTION if Mode.PRODUCTION in modes else min(modes, default=1),
    )
    mode = modes.get(initial_mode)
    if mode is not None and State.STOPPED in mode.disabled:
        n.child("initial_mode", None).error("the unit starts in STOPPED, which is disabled there")
    min_dwell: dict[State, float] = n.get(
        "min_dwell", lambda x: _state_seconds(x, ACTING - {State.EXECUTE}), {}
    )
    design_speed = n.get("mach_design_speed", sc.number(lo=0), 0.0)
    max_speed = n.get("max_mach_speed", sc.number(lo=0), None)
    speed = n.get("mach_speed", sc.number(lo=0), 0.0)
    limit = max_speed if max_speed is not None else (design_speed or None)
    if limit is not None and speed > limit:
        where = "max_mach_speed" if max_speed is not None else "mach_design_speed"
        n.child("mach_speed", None).error(
            f"{speed:g} is above the highest speed the unit takes, {limit:g} ({where})"
        )
    return UnitConfig(
        name=name,
        cell=cell,
        description=n.get("description", sc.text, ""),
        modes=modes,
        initial_mode=initial_mode,
        table=build_table(model, hold_from, complete_from),
        remote_commands_enabled=n.get("remote_commands_enabled", sc.boolean, False),
        equipment_modules=ems,
        # an EM list is closed unless said otherwise; a unit without one learns its EMs
        allow_registration=n.get("allow_registration", sc.boolean, not ems),
        em_lease=n.get("em_lease", sc.number(positive=True), d.em_lease),
        em_lost_reaction=n.get("em_lost_reaction", _LOST_REACTION, int(Cmd.ABORT)),
        timeouts=n.get("timeouts", lambda x: _state_seconds(x, ACTING), {}),
        min_dwell=min_dwell,
        mode_change_timeout=n.get(
            "mode_change_timeout", sc.number(positive=True), d.mode_change_timeout
        ),
        alarms=alarm_defs,
        reactions=reactions,
        interlock_reaction=interlock_reaction,
        sizes=sizes,
        counters=n.get("counters", lambda x: _counters(x, sizes.counters), {}),
        mach_speed=speed,
        mach_design_speed=design_speed,
        max_mach_speed=max_speed,
        parameters=n.get("parameters", lambda x: _descriptors(x, sizes.parameters), ()),
        admin_parameters=n.get(
            "admin_parameters", lambda x: _descriptors(x, sizes.admin_parameters), ()
        ),
        products=products,
        remote_interfaces=remotes,
        persistence_path=persistence_path,
        persistence_period=persistence_period,
        admin_period=n.get("admin_period", sc.number(positive=True), d.admin_period),
        system_alarms=system_alarms,
        planned_stop_ids=n.get("planned_stop_ids", id_range, d.planned_stop_ids),
        plc=n.get("plc", lambda x: dict(x.mapping()), None),
        recipes=recipe_book(n, sizes, base_dir),
        stack_light=n.get("stack_light", stack_light, DEFAULT_STACK_LIGHT),
    )


def _coordinator(n: Node, units: Mapping[str, UnitConfig]) -> CoordinatorConfig:
    n.check_keys(
        {
            "enabled",
            "start_order",
            "stop_order",
            "step_timeout",
            "unit_lease",
            "interlocks",
            "propagate_interlocks",
            "lost_unit_reaction",
        }
    )
    unit_names = {k: k for k in units}

    def order(x: Node) -> tuple[str, ...]:
        out = tuple(e.parse(sc.choice(unit_names), "") for e in x.elements())
        if len(set(out)) != len(out):
            x.error("a unit is listed twice")
        return out

    def rule(x: Node) -> InterlockRule:
        x.check_keys({"unit", "when", "suspend"})
        return InterlockRule(
            x.get("unit", sc.choice(unit_names), ""),
            x.get("when", sc.choice({"blocked": "blocked", "starved": "starved"}), "blocked"),
            x.get("suspend", order, ()),
        )

    default_order = tuple(units)
    return CoordinatorConfig(
        enabled=n.get("enabled", sc.boolean, True),
        start_order=n.get("start_order", order, default_order),
        stop_order=n.get("stop_order", order, tuple(reversed(default_order))),
        step_timeout=n.get("step_timeout", sc.number(positive=True), 15.0),
        unit_lease=n.get("unit_lease", sc.number(positive=True), 3.0),
        interlocks=tuple(
            r
            for e in n.list_at("interlocks")
            if (r := e.parse(rule, InterlockRule("", "", ()))).unit
        ),
        propagate_interlocks=n.get("propagate_interlocks", sc.boolean, True),
        lost_unit_reaction=n.get("lost_unit_reaction", _REACTION, 0),
    )


#: The top-level keys of a cell file (config/reference_cell.yaml shows each).
CELL_KEYS = (
    "cell", "defaults", "units", "coordinator", "line", "hmi", "opcua", "mqtt", "discovery", "dds",
)  # fmt: skip
MAX_DDS_INTERFACES = 16
_INTERFACE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.:@-]{0,14}")  # Linux: 15 characters


def _dds_interface(n: Node) -> str:
    """An interface DDS may use: its name (``eth1``) or an IPv4 address of this host."""
    s = sc.text(n).strip()
    try:
        ip = ipaddress.ip_address(s)
    except ValueError:
        if not _INTERFACE_NAME.fullmatch(s):
            raise invalid(
                f"{sc.shown(s)} is neither an interface name (at most 15 letters, "
                "digits, _ . : @ -) nor an IPv4 address"
            ) from None
        return s
    if ip.version != 4 or ip.is_multicast or ip.is_unspecified:
        raise invalid(
            f"{s} is not an address of an interface: give an interface name or a "
            "unicast IPv4 address (DDS runs on UDPv4)"
        )
    return str(ip)


def _dds(n: Node) -> tuple[str, ...]:
    n.check_keys({"interfaces"})
    found = tuple(e.parse(_dds_interface, "") for e in n.list_at("interfaces"))
    if len(found) > MAX_DDS_INTERFACES:
        n.child("interfaces", None).error(f"at most {MAX_DDS_INTERFACES} interfaces")
    if "interfaces" in n.mapping() and not found:
        n.child("interfaces", None).error("name at least one interface, or leave the key out")
    return tuple(dict.fromkeys(i for i in found if i))


def parse_cell(data: Any, file: str = "<memory>", base_dir: Path | None = None) -> CellConfig:
    """Validate a cell document (already parsed YAML). Raises ConfigError listing every problem."""
    root = Node(data, "")
    root.check_keys(set(CELL_KEYS))
    cell = root.get("cell", sc.name, "")
    if "cell" not in root.mapping():
        root.error("missing key 'cell' (the cell namespace, e.g. demo_cell)")
    defaults = root.mapping().get("defaults") or {}
    if not isinstance(defaults, Mapping):
        root.child("defaults", defaults).error("expected a mapping")
        defaults = {}
    units_node = root.child("units", root.mapping().get("units"))
    if units_node.value is None or units_node.value == {}:
        units_node.error("a cell needs at least one unit")
    units: dict[str, UnitConfig] = {}
    for uname, un in units_node.items():
        Node(uname, un.path, un.problems).parse(sc.name, "")
        own = un.mapping()
        merged = {**defaults, **own}
        # a unit's entry taken from defaults: is reported where it is written
        origins = {str(k): f"defaults.{k}" for k in defaults if k not in own}
        units[uname] = _unit(
            uname, Node(merged, un.path, un.problems, origins), cell, base_dir or Path.cwd()
        )
    coord = root.get(
        "coordinator",
        lambda x: _coordinator(x, units),
        CoordinatorConfig(start_order=tuple(units), stop_order=tuple(reversed(list(units)))),
    )
    dds: tuple[str, ...] = root.get("dds", _dds, ())
    stores = [u.persistence_path for u in units.values() if u.persistence_path]
    line = parse_line(
        root.child("line", root.mapping().get("line")),
        cell,
        list(units),
        coord.interlocks,
        base_dir or Path.cwd(),
        str(Path(stores[0]).parent / LINE_STORE) if stores else None,
    )
    discovery = root.get("discovery", parse_discovery, DiscoveryConfig())
    root.problems.extend(plain_secrets(data))
    if root.problems:
        raise ConfigError(file, root.problems)
    extras = {
        k: dict(root.child(k, root.mapping().get(k)).mapping()) for k in ("hmi", "opcua", "mqtt")
    }
    if root.problems:
        raise ConfigError(file, root.problems)
    return CellConfig(
        cell, units, coord, file, **extras, line=line, discovery=discovery, dds_interfaces=dds
    )


def load_cell(path: str | os.PathLike[str]) -> CellConfig:
    """Read and validate a cell YAML file."""
    p = Path(path)
    return parse_cell(read_document(p), str(p), p.resolve().parent)


def unit_config(name: str = "unit", **overrides: Any) -> UnitConfig:
    """A unit configuration in code (tests, embedding), e.g. ``unit_config(em_lease=1.0)``."""
    return replace(UnitConfig(name=name, persistence_path=None), **overrides)
