"""ROS messages of a unit -> OPC 30050 variable values, and unit answers -> OPC UA status codes.

Pure functions (no server, no ROS node): :func:`status_values` and :func:`admin_values` return
``{relative browse path: Value}`` for one unit object (paths as in :class:`.model.UnitNodes`);
structured values are :class:`Struct` (type name + fields) until the server turns them into the
data type classes asyncua generated from the NodeSet. The state machines follow the official
NodeSet (:mod:`.nodeset`): the Cleared and Running states, their NodeIds and StateNumbers are
read from it. The dotted PackTags names of ``packml_ros2.core.packtags.flat_tags`` correspond as
follows (OPC 30050 v1.01 names)::

    Status.UnitModeCurrent            Status/UnitModeCurrent (the unit's mode enumeration)
    Status.UnitModeChangeInProcess    Status/UnitModeChangeInProcess
    Status.StateCurrent               BaseStateMachine/.../CurrentState/Number (+ Status/StateCurrent)
    Status.StateRequested             Status/StateRequested
    Status.StateChangeInProcess       Status/StateChangeInProcess
    Status.EquipmentInterlock.Blocked Status/EquipmentBlocked (Starved likewise), and
                                      Status/EquipmentInterlock/Blocked (v2 draft, our namespace)
    Status.StackLight[#]              Status/StackLight (UInt32[], v2 draft; Colors: String[])
    Status.RecipeCurrent              Status/RecipeCurrent (RecipeRequested,
                                      RecipeChangeInProcess likewise; v2 draft, our namespace)
    Status.Recipe[#]                  Status/Recipe/Recipe_<ID>/... (:func:`recipe_members`)
    Admin.Alarm[#] / AlarmExtent      Admin/Alarm (PackMLAlarmDataType[]) / Admin/AlarmExtent
    Admin.ProdProcessedCount[#]       Admin/ProdProcessedCount (PackMLCountDataType[])
    Admin.StateCurrentTime[m,s]       Admin/StateCurrentTime (Int32[32,18])
    Admin.StatesDisabled / the model  */AvailableStates, */AvailableTransitions (:func:`available_values`)
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua

from ..core.numbers import Cmd
from ..core.recipes import ParamType, Recipe
from ..core.stacklight import Shown, encode_opcua
from .available import Graph
from .nodeset import ArgumentDef, MethodDef, PackMLModel, TransitionDef

UNECE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
#: Engineering units of counters and descriptors -> UN/CEFACT Recommendation 20 common codes.
UNECE_CODES = {
    "pcs": "H87", "piece": "H87", "pieces": "H87", "part": "H87", "parts": "H87",
    "case": "CS", "cases": "CS", "s": "SEC", "sec": "SEC", "min": "MIN", "h": "HUR",
    "kg": "KGM", "g": "GRM", "t": "TNE", "m": "MTR", "mm": "MMT", "l": "LTR", "%": "P1",
    "1/min": "C94", "/min": "C94", "ppm": "C94",
}  # fmt: skip
NULL_TIME = ua.uatypes.FILETIME_EPOCH_AS_UTC_DATETIME  # encodes as 0: "not set"
GOOD = 0
NOT_ACTIVE = ua.StatusCodes.BadStateNotActive


@dataclass(frozen=True)
class Struct:
    """A structured value: the data type's name and its fields (values may be Structs too)."""

    type: str
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Value:
    value: Any
    vtype: ua.VariantType
    status: int = GOOD
    dims: tuple[int, ...] | None = None


def unit_id(code: str) -> int:
    """OPC UA Part 8: the UnitId of a UN/CEFACT common code (up to 3 characters)."""
    n = 0
    for ch in code:
        n = (n << 8) | ord(ch)
    return n


def eu_information(unit: str) -> ua.EUInformation:
    code = UNECE_CODES.get(unit.strip().lower())
    return ua.EUInformation(
        NamespaceUri=UNECE_URI,
        UnitId=unit_id(code) if code else -1,
        DisplayName=ua.LocalizedText(unit),
        Description=ua.LocalizedText(unit),
    )


def utc(stamp: Any) -> dt.datetime:
    """builtin_interfaces/Time -> UTC datetime (zero -> the OPC UA null DateTime)."""
    sec, nanosec = int(getattr(stamp, "sec", 0)), int(getattr(stamp, "nanosec", 0))
    if sec <= 0 and nanosec <= 0:
        return NULL_TIME
    return dt.datetime.fromtimestamp(sec, tz=dt.UTC) + dt.timedelta(microseconds=nanosec // 1000)


# -- structures ------------------------------------------------------------------------------------
def descriptor(d: Any) -> Struct:
    return Struct(
        "PackMLDescriptorDataType",
        {"ID": int(d.id), "Name": d.name, "Unit": eu_information(d.unit), "Value": float(d.value)},
    )


def descriptors(items: Iterable[Any]) -> list[Struct]:
    return [descriptor(d) for d in items]


def product(p: Any) -> Struct:
    return Struct(
        "PackMLProductDataType",
        {
            "ProductID": int(p.product_id),
            "ProcessVariables": descriptors(p.process_variables),
            "Ingredients": [
                Struct(
                    "PackMLIngredientsDataType",
                    {"IngredientID": int(i.ingredient_id), "Parameter": descriptors(i.parameter)},
                )
                for i in p.ingredients
            ],
        },
    )


def remote_interface(r: Any) -> Struct:
    return Struct(
        "PackMLRemoteInterfaceDataType",
        {
            "Number": int(r.number),
            "ControlCmdNumber": int(r.control_cmd_number),
            "CmdValue": int(r.cmd_value),
            "Parameter": descriptors(r.parameter),
        },
    )


def count(c: Any) -> Struct:
    return Struct(
        "PackMLCountDataType",
        {
            "ID": int(c.id),
            "Name": c.name,
            "Unit": eu_information(c.unit),
            "Count": int(c.count),
            "AccCount": int(c.acc_count),
        },
    )


def alarm(a: Any | None) -> Struct:
    """packml_interfaces/Alarm -> PackMLAlarmDataType (None or id 0 -> an empty entry)."""
    if a is None:
        return Struct(
            "PackMLAlarmDataType",
            {
                "ID": 0,
                "Value": 0,
                "Message": "",
                "Category": 0,
                "DateTime": NULL_TIME,
                "AckDateTime": NULL_TIME,
                "Trigger": False,
            },
        )
    return Struct(
        "PackMLAlarmDataType",
        {
            "ID": int(a.id),
            "Value": int(a.value),
            "Message": a.message,
            "Category": int(a.category),
            "DateTime": utc(a.stamp),
            "AckDateTime": utc(a.ack_stamp),
            "Trigger": bool(a.trigger),
        },
    )


# -- the state machines ----------------------------------------------------------------------------
def state_machine_values(model: PackMLModel, state: int, packml_ns: int) -> dict[str, Value]:
    """CurrentState (LocalizedText), its Id (the state object of the NodeSet's state machine type)
    and Number (its StateNumber) of the three nested state machines; a sub state machine that is
    not active is BadStateNotActive."""
    out: dict[str, Value] = {}
    for machine, current in zip(model.machines, model.places(state), strict=True):
        path = f"{machine.path}/CurrentState"
        if current is None:
            out[path] = Value(ua.LocalizedText(""), ua.VariantType.LocalizedText, NOT_ACTIVE)
            out[f"{path}/Id"] = Value(ua.NodeId(), ua.VariantType.NodeId, NOT_ACTIVE)
            out[f"{path}/Number"] = Value(0, ua.VariantType.UInt32, NOT_ACTIVE)
            continue
        out[path] = Value(ua.LocalizedText(current.name, "en"), ua.VariantType.LocalizedText)
        out[f"{path}/Id"] = Value(ua.NodeId(current.id, packml_ns), ua.VariantType.NodeId)
        out[f"{path}/Number"] = Value(current.number, ua.VariantType.UInt32)
    return out


#: The method that causes a command's transition (OPC 30050 names): Reset, Start, ..., ToComplete.
COMMAND_METHODS: Mapping[Cmd, str] = {
    c: "ToComplete" if c is Cmd.COMPLETE else c.name.title() for c in Cmd if c is not Cmd.UNDEFINED
}
#: A transition of one machine: (machine path, from state, to state) by their NodeSet names.
Step = tuple[str, str, str]


def transition_steps(model: PackMLModel, graph: Graph) -> dict[Step, str]:
    """Each edge of ``graph`` as a transition of the machine where it happens (the outermost one
    whose current state changes: Execute -> Stopping is MachineState's Running -> Stopping), with
    the method that causes it ("" = State Complete)."""
    out: dict[Step, str] = {}
    for (frm, to), causes in graph.edges.items():
        for machine, a, b in zip(model.machines, model.places(frm), model.places(to), strict=True):
            if a != b:
                if a is not None and b is not None:
                    cause = min((COMMAND_METHODS[c] for c in causes), default="")
                    out.setdefault((machine.path, a.name, b.name), cause)
                break
    return out


def method_paths(model: PackMLModel, graph: Graph) -> frozenset[str]:
    """The state machine methods (``BaseStateMachine/MachineState/Stop``) that cause an edge of
    ``graph``, each on the machine where its transition happens (as :func:`transition_steps`
    places it): for the graph of the current state (:func:`.available.unit_graph`), the methods
    Executable now."""
    out: set[str] = set()
    for (frm, to), causes in graph.edges.items():
        for machine, a, b in zip(model.machines, model.places(frm), model.places(to), strict=True):
            if a != b:
                out.update(f"{machine.path}/{COMMAND_METHODS[c]}" for c in causes)
                break
    return frozenset(out)


def nodeset_transitions(model: PackMLModel) -> dict[Step, TransitionDef]:
    return {(m.path, t.from_state, t.to_state): t for m in model.machines for t in m.transitions}


def available_values(
    model: PackMLModel, graph: Graph, packml_ns: int, extra: Mapping[Step, ua.NodeId]
) -> dict[str, Value]:
    """``AvailableStates`` and ``AvailableTransitions`` of the three machines for ``graph`` (the
    unit's states and transitions in its current mode): NodeIds of the NodeSet's state and
    transition objects, and of ``extra`` transitions for the edges the NodeSet does not model
    (e.g. Held -> Completing of TR88-2022)."""
    states: dict[str, set[int]] = {m.path: set() for m in model.machines}
    for s in graph.states:
        for machine, place in zip(model.machines, model.places(s), strict=True):
            if place is not None:
                states[machine.path].add(place.id)
    modelled = nodeset_transitions(model)
    transitions: dict[str, list[ua.NodeId]] = {m.path: [] for m in model.machines}
    for step in sorted(transition_steps(model, graph)):
        if step in modelled:
            transitions[step[0]].append(ua.NodeId(modelled[step].id, packml_ns))
        elif step in extra:
            transitions[step[0]].append(extra[step])
    out: dict[str, Value] = {}
    for m in model.machines:
        ids = [ua.NodeId(i, packml_ns) for i in sorted(states[m.path])]
        out[f"{m.path}/AvailableStates"] = Value(ids, ua.VariantType.NodeId)
        out[f"{m.path}/AvailableTransitions"] = Value(transitions[m.path], ua.VariantType.NodeId)
    return out


def version(model_name: str) -> str:
    """``PackMLVersion`` (v1.01: a String, e.g. the NodeSet's default ``TR88.00.02-2015``): the
    TR88 edition whose state model the unit follows."""
    return f"TR88.00.02-{model_name}"


# -- whole messages --------------------------------------------------------------------------------
I32, F, B = ua.VariantType.Int32, ua.VariantType.Float, ua.VariantType.Boolean
EO = ua.VariantType.ExtensionObject
U32, D, STR = ua.VariantType.UInt32, ua.VariantType.Double, ua.VariantType.String


def status_values(msg: Any, model: PackMLModel, packml_ns: int) -> dict[str, Value]:
    """packml_interfaces/Status -> the unit's Status object and state machines."""
    out = {
        "Status/UnitModeCurrent": Value(int(msg.unit_mode_current), I32),
        # OPC 30050 types UnitModeRequested as Boolean: a mode change has been requested
        "Status/UnitModeRequested": Value(
            bool(msg.unit_mode_change_in_process)
            or int(msg.unit_mode_requested) != int(msg.unit_mode_current),
            B,
        ),
        "Status/UnitModeChangeInProcess": Value(bool(msg.unit_mode_change_in_process), B),
        "Status/StateRequested": Value(int(msg.state_requested), I32),
        "Status/StateChangeInProcess": Value(bool(msg.state_change_in_process), B),
        "Status/MachSpeed": Value(float(msg.mach_speed), F),
        "Status/CurMachSpeed": Value(float(msg.cur_mach_speed), F),
        "Status/EquipmentBlocked": Value(bool(msg.equipment_interlock.blocked), B),
        "Status/EquipmentStarved": Value(bool(msg.equipment_interlock.starved), B),
        "Status/Parameter": Value(descriptors(msg.parameter), EO),
        "Status/Product": Value([product(p) for p in msg.product], EO),
        "Status/RemoteParameter": Value([remote_interface(r) for r in msg.remote_interface], EO),
        "Status/StateCurrent": Value(int(msg.state_current), I32),
        **draft_status_values(msg),
    }
    out.update(state_machine_values(model, msg.state_current, packml_ns))
    return out


def draft_status_values(msg: Any) -> dict[str, Value]:
    """The OPC 30050 v2 draft's Status members this server adds in its own namespace (besides
    StateCurrent): EquipmentInterlock {Blocked, Starved}, StackLight (UInt32[]:
    :func:`packml_ros2.core.stacklight.encode_opcua`, the colours in its Colors property) and the
    recipe in use."""
    light = msg.stack_light
    shown = Shown(tuple(int(m) for m in light.modes), bool(light.horn))
    return {
        "Status/EquipmentInterlock/Blocked": Value(bool(msg.equipment_interlock.blocked), B),
        "Status/EquipmentInterlock/Starved": Value(bool(msg.equipment_interlock.starved), B),
        "Status/StackLight": Value(encode_opcua(shown), U32),
        "Status/StackLight/Colors": Value([str(c) for c in light.colors], STR),
        "Status/RecipeCurrent": Value(int(msg.recipe_current), I32),
        "Status/RecipeRequested": Value(int(msg.recipe_requested), I32),
        "Status/RecipeChangeInProcess": Value(bool(msg.recipe_change_in_process), B),
        "Status/RecipeResult": Value(str(msg.recipe_result), STR),
    }


# -- the unit's recipes (Status/Recipe) ------------------------------------------------------------
#: A parameter type -> the v2 draft's array name and the variable's type.
PARAMETER_ARRAYS: Mapping[ParamType, tuple[str, ua.VariantType]] = {
    ParamType.REAL: ("Parameter_REAL", F),
    ParamType.LREAL: ("Parameter_LREAL", D),
    ParamType.DINT: ("Parameter_DINT", I32),
    ParamType.STRING: ("Parameter_STRING", STR),
}
#: One level of a member's path: (browse name, the part of its NodeId).
Level = tuple[str, str]


@dataclass(frozen=True)
class Member:
    """A node below ``Status/Recipe``: an object (``value`` None), a variable, or a property of
    the variable above it (``prop``). Parents come before their children."""

    path: tuple[Level, ...]
    value: Value | None = None
    prop: bool = False
    description: str = ""


def _parameter_members(base: tuple[Level, ...], params: Sequence[Any]) -> list[Member]:
    """The four typed arrays of the draft's PackMLProcessVariablesDataType (or
    PackMLIngredientsDataType) as objects, one variable per parameter: its value (Float, Double,
    Int32 or String), properties ID and Unit. The browse name is the parameter's name (made
    unique with its ID when two share it, ``Parameter_<ID>`` when it has none); the NodeId part
    its ID (unique per recipe list: the configuration checks it)."""
    out: list[Member] = []
    for ptype, (array, vtype) in PARAMETER_ARRAYS.items():
        folder = (*base, (array, array))
        out.append(Member(folder, description=f"{array}: the parameters of type {ptype.name}"))
        items = [p for p in params if p.type is ptype]
        names = [p.name for p in items]
        for p in items:
            name = (
                p.name if p.name and names.count(p.name) == 1 else f"{p.name or 'Parameter'}_{p.id}"
            )
            value = p.text if ptype is ParamType.STRING else p.value
            if ptype is ParamType.DINT:
                value = int(value)
            at = (*folder, (name, str(p.id)))
            text = f"{p.name or name} ({ptype.name}{', ' + p.unit if p.unit else ''})"
            out.append(Member(at, Value(value, vtype), description=text))
            out.append(Member((*at, ("ID", "ID")), Value(int(p.id), I32), prop=True))
            out.append(Member((*at, ("Unit", "Unit")), Value(p.unit, STR), prop=True))
    return out


def recipe_members(recipes: Iterable[Recipe]) -> list[Member]:
    """A unit's recipes as nodes a generic client browses and reads without decoding a custom
    structure (the draft's ``Recipe`` is a ``PackMLRecipeDataType[]`` of a v2 namespace this v1.01
    server cannot have)::

        Recipe_<ID>                        object, one per recipe, in ID order
          ID Int32, Name String, Unit String, PrimaryQty Float
          ProcessVariables
            Parameter_REAL / Parameter_LREAL / Parameter_DINT / Parameter_STRING
              <name>                       Float / Double / Int32 / String; properties ID, Unit
          Ingredients
            Ingredient_<IngredientID>
              IngredientID Int32, Parameter_REAL ... as above
    """
    out: list[Member] = []
    for recipe in sorted(recipes, key=lambda r: r.id):
        base: tuple[Level, ...] = ((f"Recipe_{recipe.id}", str(recipe.id)),)
        out.append(Member(base, description=f"recipe {recipe.label}"))
        for name, value in (
            ("ID", Value(int(recipe.id), I32)),
            ("Name", Value(recipe.name, STR)),
            ("Unit", Value(recipe.unit, STR)),
            ("PrimaryQty", Value(float(recipe.primary_qty), F)),
        ):
            out.append(Member((*base, (name, name)), value))
        pv = (*base, ("ProcessVariables", "ProcessVariables"))
        out.append(Member(pv, description="the recipe's process variables"))
        out += _parameter_members(pv, recipe.process_variables)
        ingredients = (*base, ("Ingredients", "Ingredients"))
        out.append(Member(ingredients, description="the recipe's ingredients"))
        seen: set[str] = set()
        for i, ingredient in enumerate(recipe.ingredients):
            key = str(ingredient.ingredient_id)
            key = key if key not in seen else f"{key}_{i}"
            seen.add(key)
            at = (*ingredients, (f"Ingredient_{key}", key))
            out.append(Member(at, description=f"ingredient {ingredient.ingredient_id}"))
            out.append(
                Member(
                    (*at, ("IngredientID", "IngredientID")), Value(ingredient.ingredient_id, I32)
                )
            )
            out += _parameter_members(at, ingredient.parameters)
    return out


#: Methods this server adds to each unit object (its own namespace): the recipe change, TR88's
#: Command.SelectedRecipe + RecipeChangeRequest in one call, as SetUnitMode is UnitMode +
#: UnitModeChangeRequest (the v2 draft has no method for it).
EXTENSION_METHODS: Mapping[str, MethodDef] = {
    "SetRecipe": MethodDef("SetRecipe", 0, (ArgumentDef("SelectedRecipe", (0, I32.value), -1),)),
}


def _matrix(values: Sequence[int], columns: int) -> tuple[list[int], tuple[int, ...]]:
    rows = len(values) // columns if columns else 0
    return [int(v) for v in values[: rows * columns]], (rows, columns)


def admin_values(msg: Any) -> dict[str, Value]:
    """packml_interfaces/Admin -> the unit's Admin object (and the speeds' EURange)."""
    columns = int(getattr(msg, "NUM_STATES", 18))
    cur, cur_dims = _matrix(msg.state_current_time, columns)
    cum, cum_dims = _matrix(msg.state_cumulative_time, columns)
    design = float(msg.mach_design_speed)
    out = {
        "Admin/Alarm": Value([alarm(a) for a in msg.alarm], EO),
        "Admin/AlarmExtent": Value(int(msg.alarm_extent), I32),
        "Admin/AlarmHistory": Value([alarm(a) for a in msg.alarm_history], EO),
        "Admin/AlarmHistoryExtent": Value(int(msg.alarm_history_extent), I32),
        "Admin/Warning": Value([alarm(a) for a in msg.warning], EO),
        "Admin/WarningExtent": Value(int(msg.warning_extent), I32),
        "Admin/StopReason": Value(alarm(msg.stop_reason if msg.stop_reason_extent else None), EO),
        "Admin/StopReasonExtent": Value(int(msg.stop_reason_extent), I32),
        "Admin/ModeCurrentTime": Value([int(v) for v in msg.mode_current_time], I32),
        "Admin/ModeCumulativeTime": Value([int(v) for v in msg.mode_cumulative_time], I32),
        "Admin/StateCurrentTime": Value(cur, I32, dims=cur_dims),
        "Admin/StateCumulativeTime": Value(cum, I32, dims=cum_dims),
        "Admin/ProdConsumedCount": Value([count(c) for c in msg.prod_consumed_count], EO),
        "Admin/ProdProcessedCount": Value([count(c) for c in msg.prod_processed_count], EO),
        "Admin/ProdDefectiveCount": Value([count(c) for c in msg.prod_defective_count], EO),
        "Admin/AccTimeSinceReset": Value(int(msg.acc_time_since_reset), I32),
        "Admin/MachDesignSpeed": Value(float(design), F),
        "Admin/Parameter": Value(descriptors(msg.parameter), EO),
    }
    if design > 0:
        for speed in ("MachSpeed", "CurMachSpeed"):
            out[f"Status/{speed}/EURange"] = Value(
                ua.Range(Low=0.0, High=design), ua.VariantType.ExtensionObject
            )
    return out


# -- a unit that is gone ---------------------------------------------------------------------------
LOST_STATUS = ua.StatusCodes.BadCommunicationError
LOST_ADMIN = ua.StatusCodes.UncertainLastUsableValue
NEVER_SEEN = ua.StatusCodes.BadWaitingForInitialData


def lost_status(path: str, known: bool = True) -> int:
    """The status of a value while its unit is lost (:mod:`packml_ros2.presence`): the live status
    (Status, the state machines) is Bad_CommunicationError, a dead unit has no known state; the
    accumulated Admin data (counts, times, alarms) and the speeds' EURange (from the unit's
    configuration) keep their last value as Uncertain_LastUsableValue, or, when no message of
    the unit ever brought one (not ``known``), stay Bad_WaitingForInitialData: there is no
    last usable value."""
    if path.startswith("Admin/") or path.endswith("/EURange"):
        return LOST_ADMIN if known else NEVER_SEEN
    return LOST_STATUS


# -- answers ---------------------------------------------------------------------------------------
#: packml_interfaces/Result codes -> (name, OPC UA status code of a refused method call).
_S = ua.StatusCodes
RESULTS = {
    1: ("UNKNOWN_COMMAND", _S.BadInvalidArgument),
    2: ("COMMAND_NOT_ALLOWED", _S.BadInvalidState),  # not valid in the current state
    3: ("STATE_DISABLED", _S.BadInvalidState),  # the target state is disabled in this mode
    4: ("REMOTE_DISABLED", _S.BadUserAccessDenied),
    5: ("MODE_UNKNOWN", _S.BadOutOfRange),
    6: ("MODE_CHANGE_NOT_ALLOWED", _S.BadInvalidState),
    7: ("MODE_CHANGE_IN_PROCESS", _S.BadInvalidState),
    8: ("ALARM_ACTIVE", _S.BadInvalidState),
    9: ("EM_UNKNOWN", _S.BadNotFound),
    10: ("EM_SWITCH_IN_PRODUCTION", _S.BadInvalidState),
    11: ("EM_MISSING", _S.BadInvalidState),
    12: ("ALARM_UNKNOWN", _S.BadNotFound),
    13: ("INVALID_ARGUMENT", _S.BadInvalidArgument),
    14: ("SUPERSEDED", _S.BadInvalidState),
    15: ("UNIT_UNAVAILABLE", _S.BadNoCommunication),
    16: ("UNAUTHORIZED", _S.BadUserAccessDenied),
    17: ("NOTHING_TO_DO", _S.BadNothingToDo),
    18: ("INTERLOCK_ACTIVE", _S.BadInvalidState),
    19: ("NOT_SUPPORTED", _S.BadNotSupported),
    20: ("RECIPE_UNKNOWN", _S.BadNotFound),  # no such recipe in the unit's recipes
    21: ("RECIPE_NOT_ALLOWED", _S.BadInvalidState),  # not in a state that allows a changeover
    22: ("RECIPE_CHANGE_IN_PROCESS", _S.BadInvalidState),  # a changeover runs
}
RESULT_NAMES = {code: name for code, (name, _) in RESULTS.items()}


def result_status(accepted: bool, result: int) -> int:
    """The status code of a method call from a unit's answer (accepted -> Good)."""
    if accepted:
        return GOOD
    return RESULTS.get(int(result), ("", _S.BadInvalidState))[1]
