"""The engine's input log: every input of a :class:`~.unit.Unit`, as a record that can be applied
again (replay, ``packml replay``). Its format is this module's schema, not Python: renaming a
method or an argument of the engine changes nothing in a recorded bag.

A record is ``(time, name, fields)``: the engine's clock at the input, an input name of
:data:`INPUTS` and its fields (JSON values). The log of a unit begins with ``start`` (the node's:
the admin data the unit restored, its start time, whether it has a store, and ``schema``).

Schema 1 (the names and fields of :data:`INPUTS`). Schema 0 (before it had a number: a ``start``
without ``schema``) used the engine's method and argument names; :func:`upgrade` reads it, so the
bags recorded then still replay.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from .config import Descriptor, Ingredient, Product
from .reasons import Answer
from .requests import CommandRequest, CompleteReport, ModeRequest, Request

#: 2: the inputs of schema 1; the outputs name an interlock's holder in the source of the
#: transitions it causes (``interlock:<holder>``, core/interlocks.py), where schema 1 and 0 said
#: ``interlock`` (replay makes their outputs so: :data:`INTERLOCK_HOLDER_SCHEMA`).
SCHEMA = 2
#: The first schema whose units name the interlock's holder in the source.
INTERLOCK_HOLDER_SCHEMA = 2
START = "start"  #: the first record of a unit's log (written by the node, not an engine input)


@dataclass(frozen=True)
class InputDef:
    """One input: its name and fields in the log, the engine method that takes it (fields map to
    the method's parameters in order), and how to decode fields that are not plain values."""

    name: str
    fields: tuple[str, ...]
    method: str
    decode: Mapping[str, Callable[[Any], Any]] | None = None
    #: How the engine's values of fields that are not plain values are written (the inverse of
    #: ``decode``).
    encode: Mapping[str, Callable[[Any], Any]] | None = None


# -- values that are not plain JSON ----------------------------------------------------------------
def descriptor_to_dict(d: Descriptor) -> dict[str, Any]:
    return {"id": d.id, "name": d.name, "unit": d.unit, "value": d.value}


def descriptor_from_dict(d: Mapping[str, Any]) -> Descriptor:
    return Descriptor(
        int(d["id"]), str(d.get("name", "")), str(d.get("unit", "")), float(d.get("value", 0.0))
    )


def product_to_dict(p: Product) -> dict[str, Any]:
    return {
        "product_id": p.product_id,
        "process_variables": [descriptor_to_dict(d) for d in p.process_variables],
        "ingredients": [
            {
                "ingredient_id": i.ingredient_id,
                "parameter": [descriptor_to_dict(d) for d in i.parameter],
            }
            for i in p.ingredients
        ],
    }


def product_from_dict(d: Mapping[str, Any]) -> Product:
    return Product(
        int(d["product_id"]),
        tuple(descriptor_from_dict(v) for v in d.get("process_variables", [])),
        tuple(
            Ingredient(
                int(i["ingredient_id"]),
                tuple(descriptor_from_dict(v) for v in i.get("parameter", [])),
            )
            for i in d.get("ingredients", [])
        ),
    )


def request_to_dict(r: Request) -> dict[str, Any]:
    if isinstance(r, CommandRequest):
        return {"kind": "command", "command": r.cmd, "source": r.source}
    if isinstance(r, ModeRequest):
        return {"kind": "mode", "mode": r.mode, "source": r.source}
    return {"kind": "state_complete", "em": r.em, "state": r.state, "sequence": r.sequence}


def request_from_dict(d: Mapping[str, Any]) -> Request:
    kind = d["kind"]
    if kind == "command":
        return CommandRequest(int(d["command"]), str(d["source"]))
    if kind == "mode":
        return ModeRequest(d["mode"], str(d["source"]))
    return CompleteReport(str(d["em"]), int(d["state"]), int(d["sequence"]))


def _list_of(decode: Callable[[Any], Any]) -> Callable[[Any], Any]:
    return lambda values: [decode(v) for v in values]


# -- schema 1 --------------------------------------------------------------------------------------
Codec = tuple[Callable[[Any], Any], Callable[[Any], Any]]  #: (encode, decode) of a field


def _def(name: str, method: str, *fields: str, **codecs: Codec) -> InputDef:
    """An input; ``codecs``: (encode, decode) of the fields whose values are not plain."""
    encode = {f: enc for f, (enc, _) in codecs.items()}
    decode = {f: dec for f, (_, dec) in codecs.items()}
    return InputDef(name, fields, method, decode or None, encode or None)


def _list_codec(encode: Callable[[Any], Any], decode: Callable[[Any], Any]) -> Codec:
    return _list_of(encode), _list_of(decode)


COMMAND = _def("command", "command", "command", "source")
MODE = _def("mode", "set_mode", "mode", "source")
STEP = _def("step", "step", "requests", requests=_list_codec(request_to_dict, request_from_dict))
EM_STATE_COMPLETE = _def("em.state_complete", "em_complete", "em", "state", "sequence")
EM_SEEN = _def("em.seen", "em_seen", "em", "report")
EM_LOST = _def("em.lost", "em_lost", "em", "detail")
EM_INTERLOCK = _def("em.interlock", "em_interlock", "em", "blocked", "starved", "material")
EM_COUNT = _def("em.count", "em_count", "em", "counter", "index", "increment")
EM_ACTIVE = _def("em.active", "set_em_active", "em", "active", "source")
ALARM = _def(
    "alarm", "set_alarm", "id", "value", "active", "source", "em", "warning", "category", "message"
)
ALARM_ACK = _def("alarm.ack", "ack_alarms", "id", "value", "source")
ALARM_RESET = _def("alarm.reset", "reset_alarms", "clear_first_out", "source")
TIMES_RESET = _def("times.reset", "reset_times", "all", "source")
COUNTERS_RESET = _def("counters.reset", "reset_counters", "source")
SPEED = _def("speed", "set_mach_speed", "speed", "source")
PARAMETERS = _def(
    "parameters",
    "set_parameters",
    "parameters",
    "source",
    parameters=_list_codec(descriptor_to_dict, descriptor_from_dict),
)
PRODUCTS = _def(
    "products",
    "set_product",
    "products",
    "source",
    products=_list_codec(product_to_dict, product_from_dict),
)
REMOTE = _def("remote", "set_remote_enabled", "enabled")
INTERLOCK = _def("interlock", "set_interlock", "active", "reason", "source")
RECIPE = _def("recipe", "set_recipe", "recipe_id", "name", "source")
EM_RECIPE = _def("em.recipe", "em_recipe", "em", "order", "accepted", "reason")
ADVANCE = _def("advance", "advance")
#: The wall clock stepped (NTP) by ``offset`` seconds; stamped with the new clock's time, so it
#: is the one record whose stamp may go back (UnitDriver.clock_step applies it)
CLOCK_STEP = _def("clock.step", "clock_step", "offset")
SHUTDOWN = _def("shutdown", "shutdown", "detail")

#: Every input of schema 1, by name.
INPUTS: Mapping[str, InputDef] = {
    d.name: d
    for d in (
        COMMAND,
        MODE,
        STEP,
        EM_STATE_COMPLETE,
        EM_SEEN,
        EM_LOST,
        EM_INTERLOCK,
        EM_COUNT,
        EM_ACTIVE,
        ALARM,
        ALARM_ACK,
        ALARM_RESET,
        TIMES_RESET,
        COUNTERS_RESET,
        SPEED,
        PARAMETERS,
        PRODUCTS,
        REMOTE,
        INTERLOCK,
        ADVANCE,
        SHUTDOWN,
        RECIPE,
        EM_RECIPE,
        CLOCK_STEP,
    )
}
#: Inputs an EM's reports cause (``packml replay --live`` sends the reports, not these).
EM_INPUTS = frozenset(
    d.name for d in (EM_STATE_COMPLETE, EM_SEEN, EM_LOST, EM_INTERLOCK, EM_COUNT, EM_RECIPE)
)


def fields_of(d: InputDef, values: Sequence[Any]) -> dict[str, Any]:
    """A record's fields from the values of its input, in field order (encoded as ``d`` says)."""
    fields = dict(zip(d.fields, values, strict=True))
    if d.encode:
        for name, encode in d.encode.items():
            fields[name] = encode(fields[name])
    return fields


def apply(unit: object, name: str, fields: Mapping[str, Any]) -> Answer | list[Answer] | None:
    """Apply a logged input (schema 1) to ``unit`` (a :class:`~.unit.Unit`) again: the replay
    entry. (The unit is taken as any object with the inputs' methods: this module is below the
    engine, which records its inputs here.)"""
    d = INPUTS.get(name)
    if d is None:
        raise ValueError(f"{name!r} is not an engine input (inputs: {', '.join(sorted(INPUTS))})")
    values = [d.decode[f](fields[f]) if d.decode and f in d.decode else fields[f] for f in d.fields]
    result: Answer | list[Answer] | None = getattr(unit, d.method)(*values)
    return result


# -- schema 0 --------------------------------------------------------------------------------------
#: Schema 0 name -> (schema 1 input, schema 0 field of each schema 1 field).
_SCHEMA_0: Mapping[str, tuple[InputDef, tuple[str, ...]]] = {
    "command": (COMMAND, ("cmd", "source")),
    "set_mode": (MODE, ("mode", "source")),
    "step": (STEP, ("requests",)),
    "em_complete": (EM_STATE_COMPLETE, ("name", "state", "sequence")),
    "em_seen": (EM_SEEN, ("name",)),
    "em_lost": (EM_LOST, ("name", "detail")),
    "em_interlock": (EM_INTERLOCK, ("name", "blocked", "starved", "material")),
    "em_count": (EM_COUNT, ("name", "kind", "index", "increment")),
    "set_em_active": (EM_ACTIVE, ("name", "active", "source")),
    "set_alarm": (ALARM, ("alarm_id", "value", "active", "source", "em", "warning", "category",
                          "message")),
    "ack_alarms": (ALARM_ACK, ("alarm_id", "value", "source")),
    "reset_alarms": (ALARM_RESET, ("clear_first_out", "source")),
    "reset_times": (TIMES_RESET, ("all_times", "source")),
    "reset_counters": (COUNTERS_RESET, ("source",)),
    "set_mach_speed": (SPEED, ("speed", "source")),
    "set_parameters": (PARAMETERS, ("parameters", "source")),
    "set_product": (PRODUCTS, ("products", "source")),
    "set_remote_enabled": (REMOTE, ("enabled",)),
    "set_interlock": (INTERLOCK, ("active", "reason", "source")),
    "advance": (ADVANCE, ()),
    "shutdown": (SHUTDOWN, ("detail",)),
}  # fmt: skip
_REQUEST_0 = {"command": ("command", {"cmd": "command"}), "mode": ("mode", {}),
              "complete": ("state_complete", {})}  # fmt: skip


def schema_of(start_fields: Mapping[str, Any]) -> int:
    """The schema of a log, from its ``start`` record."""
    return int(start_fields.get("schema", 0))


def upgrade(name: str, fields: Mapping[str, Any], schema: int) -> tuple[str, dict[str, Any]]:
    """A record of ``schema`` as a record of the current schema (name, fields): the inputs of
    schemas 1 and 2 are the same."""
    if 1 <= schema <= SCHEMA or name == START:
        return name, dict(fields)
    if schema != 0:
        raise ValueError(f"input log schema {schema} is newer than this version reads ({SCHEMA})")
    known = _SCHEMA_0.get(name)
    if known is None:
        raise ValueError(f"{name!r} is not an input of schema 0")
    d, old = known
    out = {new: fields[o] for new, o in zip(d.fields, old, strict=False)}
    if d is EM_SEEN:
        out["report"] = False  # schema 0 registered an EM by any report, anywhere
    if d is STEP:
        requests = []
        for r in fields["requests"]:
            kind, renamed = _REQUEST_0[r["kind"]]
            requests.append(
                {"kind": kind, **{renamed.get(k, k): v for k, v in r.items() if k != "kind"}}
            )
        out["requests"] = requests
    return d.name, out


__all__ = [
    "INPUTS",
    "SCHEMA",
    "START",
    "InputDef",
    "apply",
    "fields_of",
    "schema_of",
    "upgrade",
]
