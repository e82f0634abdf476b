"""The Sparkplug B edge node of a cell, as pure logic: no MQTT, no ROS, the clock a parameter.

The cell is the edge node; each unit is a device. :class:`Edge` turns what the units publish
(their ``status`` and ``admin`` messages, their presence) into Sparkplug messages, and a host
application's commands (NCMD, DCMD) into requests for the units' services:

- NBIRTH (``bdSeq``, ``Node Control/Rebirth``), then a DBIRTH per known unit with every metric
  (:data:`STATUS_METRICS` with the recipe, the stack light's lights, :func:`admin_metrics`, the
  EMs, the command and answer metrics), each with its alias; DDATA with only the metrics that
  changed, by alias; a DBIRTH again when the set of metrics changes (an EM or a count appears);
- DDEATH when a unit is lost, DBIRTH when it is back; NDEATH is the MQTT will (:meth:`death`);
- ``seq`` 0 on NBIRTH, +1 on every later message of the node, modulo 256; ``bdSeq`` +1 on each
  connection (:meth:`connecting`), modulo 256, the same in the NBIRTH and the will;
- NCMD ``Node Control/Rebirth`` = true: NBIRTH and every DBIRTH again;
- DCMD: one command metric (:data:`COMMANDS`) and optionally ``Command/RequestId``, checked whole
  before anything is asked of the unit (:meth:`command`); every DCMD gets an answer in the
  unit's DDATA (:meth:`answer`): the ``Command/Answer/*`` metrics, naming the request.

Every method returns the messages to publish, as :class:`Message` (topic, payload, qos, retain).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from ..core.numbers import ACTING, Cmd, State
from ..core.recipes import MAX_TEXT as MAX_RECIPE_NAME
from ..core.stacklight import MODES as LIGHT_MODES
from . import sparkplug as sp
from .config import MqttConfig
from .sparkplug import DataType as T
from .sparkplug import Metric, Payload, PayloadError

REBIRTH = "Node Control/Rebirth"
BD_SEQ = "bdSeq"
REQUEST_ID = "Command/RequestId"
#: the metrics a host application may write with a DCMD -> the unit's service and its field
COMMANDS: Mapping[str, tuple[str, str]] = {
    "Command/CntrlCmd": ("command", "command"),
    "Command/UnitMode": ("set_mode", "mode"),
    "Command/MachSpeed": ("set_mach_speed", "mach_speed"),
    "Command/AckAlarms": ("ack_alarms", "id"),
    "Command/Recipe": ("set_recipe", "recipe_id"),
}
ANSWER = "Command/Answer/"
MAX_ALARMS_JSON = 32  #: alarms listed in the Alarms/List metric (the count says how many there are)
MAX_ANSWER_TEXT = 300
#: Result codes (packml_interfaces/msg/Result) the edge itself answers with
INVALID_ARGUMENT, UNIT_UNAVAILABLE = 13, 15

#: status field -> (metric, type, how to read it); one table, read by :func:`status_metrics`
STATUS_METRICS: tuple[tuple[str, T, Callable[[Any], Any]], ...] = (
    ("State/Current", T.Int32, lambda s: s.state_current),
    ("State/CurrentName", T.String, lambda s: s.state_current_name),
    ("State/Requested", T.Int32, lambda s: s.state_requested),
    ("State/ChangeInProcess", T.Boolean, lambda s: s.state_change_in_process),
    ("Mode/Current", T.Int32, lambda s: s.unit_mode_current),
    ("Mode/CurrentName", T.String, lambda s: s.unit_mode_current_name),
    ("Mode/ChangeInProcess", T.Boolean, lambda s: s.unit_mode_change_in_process),
    ("MachSpeed", T.Double, lambda s: s.mach_speed),
    ("CurMachSpeed", T.Double, lambda s: s.cur_mach_speed),
    ("CommandsValid", T.String, lambda s: ",".join(s.commands_valid_names)),
    ("RemoteCommandsEnabled", T.Boolean, lambda s: s.remote_commands_enabled),
    ("Blocked", T.Boolean, lambda s: s.equipment_interlock.blocked),
    ("Starved", T.Boolean, lambda s: s.equipment_interlock.starved),
    ("Alarms/Active", T.UInt32, lambda s: s.active_alarms),
    ("Alarms/Unacknowledged", T.UInt32, lambda s: s.unacknowledged_alarms),
    ("Alarms/Banner", T.String, lambda s: s.alarm_banner),
    ("StopReason/ID", T.Int32, lambda s: s.stop_reason_id),
    # the recipe (TR88 / OPC 30050 v2 draft RecipeCurrent, RecipeRequested, RecipeChangeInProcess;
    # 0 and '' on a unit without recipes: always there, so a unit's births never depend on them)
    ("Recipe/Current", T.Int32, lambda s: s.recipe_current),
    ("Recipe/CurrentName", T.String, lambda s: s.recipe_current_name),
    ("Recipe/Requested", T.Int32, lambda s: s.recipe_requested),
    ("Recipe/ChangeInProcess", T.Boolean, lambda s: s.recipe_change_in_process),
    ("Recipe/Changeover", T.UInt32, lambda s: s.recipe_changeover),
    ("Recipe/Result", T.String, lambda s: s.recipe_result),
)
#: a light's mode (StackLight.MODE_*) -> its name, as the cell file's stack_light: spells it
LIGHT_MODE_NAMES: Mapping[int, str] = {number: name for name, number in LIGHT_MODES.items()}
#: the command metrics' values in a birth: the last accepted command of each kind
COMMAND_VALUES: tuple[tuple[str, T, Callable[[Any], Any]], ...] = (
    ("Command/CntrlCmd", T.Int32, lambda s: s.cntrl_cmd),
    ("Command/UnitMode", T.Int32, lambda s: s.command_unit_mode),
    ("Command/MachSpeed", T.Double, lambda s: s.command_mach_speed),
    ("Command/AckAlarms", T.Int32, lambda s: 0),
    ("Command/Recipe", T.Int32, lambda s: s.recipe_current),  # the recipe in use
    (REQUEST_ID, T.String, lambda s: ""),
)
ANSWER_METRICS: tuple[tuple[str, T, Any], ...] = (
    (ANSWER + "Count", T.UInt64, 0),
    (ANSWER + "RequestId", T.String, ""),
    (ANSWER + "Command", T.String, ""),
    (ANSWER + "Accepted", T.Boolean, False),
    (ANSWER + "Result", T.Int32, 0),
    (ANSWER + "Reason", T.String, ""),
    (ANSWER + "Message", T.String, ""),
)
COUNT_KINDS = (
    ("ProdConsumedCount", "prod_consumed_count"),
    ("ProdProcessedCount", "prod_processed_count"),
    ("ProdDefectiveCount", "prod_defective_count"),
)


def _alarms(alarms: Iterable[Any]) -> str:
    return json.dumps(
        [
            {
                "id": a.id,
                "value": a.value,
                "message": a.message,
                "category": a.category,
                "active": a.trigger,
                "acknowledged": a.acknowledged,
                "em": a.em,
            }
            for a in list(alarms)[:MAX_ALARMS_JSON]
        ],
        separators=(",", ":"),
    )


def status_metrics(s: Any) -> dict[str, tuple[T, Any]]:
    out = {name: (dtype, read(s)) for name, dtype, read in STATUS_METRICS}
    for em in s.equipment_modules:
        base = f"EM/{em.name}/"
        out[base + "Online"] = (T.Boolean, em.online)
        out[base + "Active"] = (T.Boolean, em.active)
        out[base + "StateComplete"] = (T.Boolean, em.state_complete)
    out.update(stack_light_metrics(s.stack_light))
    return out


def stack_light_metrics(light: Any) -> dict[str, tuple[T, Any]]:
    """The stack light of a status (``StackLight``): per light, top (0) to bottom,
    ``StackLight/<n>/Color``, ``Mode`` (0 off, 1 on, 2 blink) and ``ModeName``, and
    ``StackLight/Horn``; nothing for a unit without one (a PLC's). The lights are the unit's
    configuration: their number, and so the metrics, stay while the unit runs."""
    out: dict[str, tuple[T, Any]] = {}
    modes = list(light.modes)
    for i, color in enumerate(light.colors):
        mode = int(modes[i]) if i < len(modes) else 0
        out[f"StackLight/{i}/Color"] = (T.String, str(color))
        out[f"StackLight/{i}/Mode"] = (T.Int32, mode)
        out[f"StackLight/{i}/ModeName"] = (T.String, LIGHT_MODE_NAMES.get(mode, str(mode)))
    if out:
        out["StackLight/Horn"] = (T.Boolean, bool(light.horn))
    return out


def admin_metrics(a: Any, mode: int, state: int) -> dict[str, tuple[T, Any]]:
    """The Admin PackTags: counts, times (of the unit's current mode and state), alarms,
    warnings and the stop reason."""
    out: dict[str, tuple[T, Any]] = {
        "Admin/AccTimeSinceReset": (T.Int32, a.acc_time_since_reset),
        "Admin/MachDesignSpeed": (T.Double, a.mach_design_speed),
        "Admin/StopReason/ID": (T.Int32, a.stop_reason.id if a.stop_reason_extent else 0),
        "Admin/StopReason/Message": (
            T.String,
            a.stop_reason.message if a.stop_reason_extent else "",
        ),
        "Admin/Alarms/List": (T.Text, _alarms(a.alarm)),
        "Admin/Alarms/Count": (T.Int32, a.alarm_extent),
        "Admin/Warnings/List": (T.Text, _alarms(a.warning)),
        "Admin/Warnings/Count": (T.Int32, a.warning_extent),
    }
    index = mode * 18 + state  # StateCurrentTime[mode, state], flattened (Admin.NUM_STATES)
    for metric, field in (
        ("StateCurrentTime", a.state_current_time),
        ("StateCumulativeTime", a.state_cumulative_time),
    ):
        out[f"Admin/{metric}"] = (T.Int32, field[index] if 0 <= index < len(field) else 0)
    for metric, field in (
        ("ModeCurrentTime", a.mode_current_time),
        ("ModeCumulativeTime", a.mode_cumulative_time),
    ):
        out[f"Admin/{metric}"] = (T.Int32, field[mode] if 0 <= mode < len(field) else 0)
    for metric, attr in COUNT_KINDS:
        for c in getattr(a, attr):
            out[f"Admin/{metric}/{c.id}/Count"] = (T.Int32, c.count)
            out[f"Admin/{metric}/{c.id}/AccCount"] = (T.Int32, c.acc_count)
    return out


#: UNS state codes (the United Manufacturing Hub's loss-classified taxonomy) of each PackML state
UMH_PRODUCING, UMH_ACTING, UMH_UNKNOWN, UMH_STOP = 10000, 20000, 30000, 40000
UMH_STATE: Mapping[State, int] = {
    s: UMH_PRODUCING if s is State.EXECUTE
    else UMH_ACTING if s in ACTING and s is not State.CLEARING  # Clearing: a stop (UMH's list)
    else UMH_STOP
    for s in State
    if s is not State.UNDEFINED
}  # fmt: skip


def umh_code(state: int | None, present: bool) -> int:
    if not present or state is None:
        return UMH_UNKNOWN
    try:
        return UMH_STATE.get(State(state), UMH_UNKNOWN)
    except ValueError:
        return UMH_UNKNOWN


@dataclass(frozen=True)
class Message:
    topic: str
    payload: bytes
    qos: int = 0
    retain: bool = False


@dataclass
class Request:
    """What a DCMD asks of a unit: ``service`` with ``fields`` (the source is added by the node)."""

    unit: str
    metric: str
    service: str
    fields: dict[str, Any]
    request_id: str
    shown: str  #: the command as the answer names it, e.g. ``Command/CntrlCmd=START``


class Refused(Exception):
    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason
        #: of a DCMD refused by the edge, for its answer: the request (as :class:`Request` names
        #: it) and the command metric, as far as the payload said them ('' otherwise)
        self.request_id = ""
        self.shown = ""


@dataclass
class _Device:
    metrics: dict[str, tuple[T, Any]]
    aliases: dict[str, int]
    born: bool = False
    status: Any = None
    admin: Any = None
    answers: int = 0


class Edge:
    """The edge node's state; ``now()`` gives milliseconds since the epoch."""

    def __init__(self, config: MqttConfig, now: Callable[[], int]) -> None:
        self.config = config
        self.now = now
        self.bd_seq = -1
        self.seq = 0
        self.connected = False
        self.devices = {u: _Device({}, {}) for u in config.units}
        self._next_alias = 1
        self._aliases: dict[tuple[str, str], int] = {}
        self._uns: dict[str, dict[str, Any]] = {}

    # -- sequence numbers ---------------------------------------------------------------------------
    def _seq(self) -> int:
        value, self.seq = self.seq, (self.seq + 1) % 256
        return value

    def connecting(self) -> Message:
        """A new connection: the next bdSeq, and the will (NDEATH) to register with it."""
        self.bd_seq = (self.bd_seq + 1) % 256
        return self.death()

    def death(self) -> Message:
        payload = Payload(self.now(), (Metric(BD_SEQ, T.Int64, self.bd_seq),))
        return Message(self.config.topic("NDEATH"), sp.encode(payload), qos=1)

    # -- births -------------------------------------------------------------------------------------
    def connected_births(self) -> list[Message]:
        """After a connection (or a rebirth request): NBIRTH, then a DBIRTH per present unit."""
        self.connected = True
        self.seq = 0
        self._uns.clear()  # a new session: the retained documents are published again
        node = Payload(
            self.now(),
            (Metric(BD_SEQ, T.Int64, self.bd_seq), Metric(REBIRTH, T.Boolean, False)),
            self._seq(),
        )
        out = [Message(self.config.topic("NBIRTH"), sp.encode(node))]
        for unit, device in self.devices.items():
            device.born = False
            if device.status is not None and device.admin is not None:
                out.append(self._birth(unit))
        return out

    def _alias(self, unit: str, name: str) -> int:
        key = (unit, name)
        if key not in self._aliases:
            self._aliases[key] = self._next_alias
            self._next_alias += 1
        return self._aliases[key]

    def _all_metrics(self, unit: str) -> dict[str, tuple[T, Any]]:
        d = self.devices[unit]
        out = status_metrics(d.status)
        out.update(admin_metrics(d.admin, d.status.unit_mode_current, d.status.state_current))
        for name, dtype, read in COMMAND_VALUES:
            out[name] = (dtype, read(d.status))
        for name, dtype, default in ANSWER_METRICS:
            out[name] = d.metrics.get(name, (dtype, default))
        return out

    def _birth(self, unit: str) -> Message:
        d = self.devices[unit]
        d.metrics = self._all_metrics(unit)
        d.aliases = {name: self._alias(unit, name) for name in d.metrics}
        d.born = True
        now = self.now()
        metrics = tuple(
            Metric(name, dtype, value, d.aliases[name], now)
            for name, (dtype, value) in d.metrics.items()
        )
        payload = Payload(now, metrics, self._seq())
        return Message(self.config.topic("DBIRTH", unit), sp.encode(payload))

    def _data(self, unit: str, changed: Mapping[str, tuple[T, Any]]) -> Message:
        d = self.devices[unit]
        now = self.now()
        metrics = tuple(
            Metric(None, dtype, value, d.aliases[name], now)
            for name, (dtype, value) in changed.items()
        )
        return Message(
            self.config.topic("DDATA", unit), sp.encode(Payload(now, metrics, self._seq()))
        )

    # -- what the units publish ---------------------------------------------------------------------
    def update(self, unit: str, topic: str, msg: Any) -> list[Message]:
        """A unit's ``status`` or ``admin`` message: DDATA of what changed (or a DBIRTH)."""
        d = self.devices.get(unit)
        if d is None or topic not in ("status", "admin"):
            return []
        if topic == "status":
            d.status = msg
        else:
            d.admin = msg
        if d.status is None or d.admin is None or not self.connected:
            return []  # born with every PackTag: the status and the admin data
        if not d.born:
            return [self._birth(unit)]
        now = self._all_metrics(unit)
        if now.keys() != d.metrics.keys():
            return [self._birth(unit)]  # an EM or a count appeared or went: born again
        changed = {k: v for k, v in now.items() if d.metrics[k] != v and not k.startswith(ANSWER)}
        if not changed:
            return []
        d.metrics.update(changed)
        return [self._data(unit, changed)]

    def presence(self, unit: str, present: bool) -> list[Message]:
        """A unit lost: DDEATH (once); back: a DBIRTH when its status comes."""
        d = self.devices.get(unit)
        if d is None or not self.connected:
            return []
        if not present and d.born:
            d.born = False
            d.status = d.admin = None  # born again from fresh messages only
            payload = Payload(self.now(), (), self._seq())
            return [Message(self.config.topic("DDEATH", unit), sp.encode(payload))]
        return []

    # -- what a host application sends --------------------------------------------------------------
    def node_command(self, raw: bytes) -> list[Message]:
        """An NCMD: ``Node Control/Rebirth`` = true gives the births again; anything else is
        ignored (Sparkplug has no answer path for node commands); raises :class:`Refused`."""
        try:
            payload = sp.decode(raw)
        except PayloadError as exc:
            raise Refused(exc.reason, str(exc)) from None
        for m in payload.metrics:
            if m.name == REBIRTH and m.datatype is T.Boolean and m.value is True:
                return self.connected_births()
        raise Refused("unknown_metric", "an NCMD needs Node Control/Rebirth = true")

    def command(self, unit: str, raw: bytes) -> Request:
        """The request a DCMD for ``unit`` makes; :class:`Refused` (nothing asked of the unit)."""
        if unit not in self.devices:
            raise Refused("unknown_device", f"no unit {unit[:64]!r} here")
        try:
            payload = sp.decode(raw)
        except PayloadError as exc:
            raise Refused(exc.reason, str(exc)) from None
        # the request id first: a refusal names it too, wherever it is in the payload
        given = next(
            (
                m.value[:64]
                for m in payload.metrics
                if m.name == REQUEST_ID and m.datatype in (T.String, T.Text) and m.value
            ),
            "",
        )
        try:
            return self._request(unit, payload)
        except Refused as exc:
            exc.request_id = given or exc.request_id
            raise

    def _request(self, unit: str, payload: Payload) -> Request:
        d = self.devices[unit]
        request_id, found = "", list[tuple[str, Metric]]()
        for m in payload.metrics:
            name = m.name
            if name is None and m.alias is not None:
                name = next((n for n, a in d.aliases.items() if a == m.alias), None)
                if name is None:
                    raise Refused("unknown_metric", f"no metric has alias {m.alias}")
            if name == REQUEST_ID:
                if m.datatype not in (T.String, T.Text) or m.value is None:
                    raise Refused("wrong_type", f"{REQUEST_ID} is a String")
                request_id = m.value[:64]
            elif name is not None and name in COMMANDS:
                found.append((name, m))
            else:
                raise Refused(
                    "unknown_metric",
                    f"{str(name)[:80]!r} is not a command metric (commands: {', '.join(COMMANDS)})",
                )
        if len(found) != 1:
            raise Refused(
                "one_command", f"a DCMD carries exactly one command metric, not {len(found)}"
            )
        name, m = found[0]
        service, field = COMMANDS[name]
        try:
            value, shown = _command_value(name, m)
        except Refused as exc:
            exc.request_id, exc.shown = request_id or f"{name}@{payload.timestamp or 0}", name
            raise
        fields = {field: value} if field != "id" else {"all": value == 0, "id": value}
        if name == "Command/UnitMode" and isinstance(value, str):
            fields = {"mode": 0, "mode_name": value}
        elif name == "Command/Recipe":  # by ID, or by name (ID 0)
            by_name = isinstance(value, str)
            fields = {"recipe_id": 0 if by_name else value, "recipe_name": value if by_name else ""}
        return Request(
            unit, name, service, fields, request_id or f"{name}@{payload.timestamp or 0}", shown
        )

    def answer(
        self,
        unit: str,
        request_id: str,
        shown: str,
        accepted: bool,
        result: int,
        reason: str,
        message: str,
    ) -> list[Message]:
        """The answer to a DCMD, in the unit's DDATA (all answer metrics, every time)."""
        d = self.devices.get(unit)
        if d is None:
            return []
        d.answers += 1
        values = {
            ANSWER + "Count": d.answers,
            ANSWER + "RequestId": request_id,
            ANSWER + "Command": shown[:MAX_ANSWER_TEXT],
            ANSWER + "Accepted": accepted,
            ANSWER + "Result": result,
            ANSWER + "Reason": reason,
            ANSWER + "Message": message[:MAX_ANSWER_TEXT],
        }
        answer = {name: (dtype, values[name]) for name, dtype, _ in ANSWER_METRICS}
        d.metrics.update(answer)
        if not (self.connected and d.born):
            return []
        return [self._data(unit, answer)]

    # -- UNS ----------------------------------------------------------------------------------------
    def uns(self, unit: str, present: bool) -> list[Message]:
        """Retained plain JSON at ``<prefix>/<cell>/<unit>/packml`` (empty without a prefix)."""
        if not self.config.uns_prefix:
            return []
        d = self.devices.get(unit)
        s = d.status if d is not None else None
        state = s.state_current if s is not None and present else None
        doc: dict[str, Any] = {
            "timestamp_ms": self.now(),
            "online": bool(present and s is not None),
            "state": s.state_current_name if s is not None and state is not None else "UNKNOWN",
            "state_code": state if state is not None else 0,
            "umh_state": umh_code(state, present),
            "mode": s.unit_mode_current_name if s is not None and present else "",
            "mach_speed": s.cur_mach_speed if s is not None and present else 0.0,
            "recipe": s.recipe_current_name if s is not None and present else "",
            "recipe_id": s.recipe_current if s is not None and present else 0,
        }
        a = d.admin if d is not None else None
        if a is not None and present:
            doc["counts"] = {
                metric: {
                    str(c.id): {"count": c.count, "acc_count": c.acc_count}
                    for c in getattr(a, attr)
                }
                for metric, attr in COUNT_KINDS
            }
            doc["stop_reason"] = a.stop_reason.message if a.stop_reason_extent else ""
        topic = f"{self.config.uns_prefix}/{self.config.cell}/{unit}/packml"
        unchanged = {k: v for k, v in doc.items() if k != "timestamp_ms"}
        if self._uns.get(unit) == unchanged:
            return []  # retained: only what changed is published again (times are not in it)
        self._uns[unit] = unchanged
        return [Message(topic, json.dumps(doc, separators=(",", ":")).encode(), qos=1, retain=True)]


_INT_TYPES = {T.Int32, T.Int64, T.UInt32, T.UInt64}


def _command_value(name: str, m: Metric) -> tuple[Any, str]:
    """The service field's value of a command metric, and how the answer shows it."""
    v = m.value
    if v is None:
        raise Refused("wrong_type", f"{name}: a value is needed")
    if name == "Command/CntrlCmd":
        if m.datatype in _INT_TYPES:
            if not 1 <= v <= 10:
                raise Refused("out_of_range", f"{name}: {v} is not a command (1..10)")
            return int(v), f"{name}={Cmd(v).name}"
        if m.datatype in (T.String, T.Text):
            try:
                cmd = Cmd[v.strip().upper()]
            except KeyError:
                raise Refused("out_of_range", f"{name}: {v[:40]!r} is not a command name") from None
            if not cmd:
                raise Refused("out_of_range", f"{name}: UNDEFINED is not a command")
            return int(cmd), f"{name}={cmd.name}"
    elif name == "Command/UnitMode":
        if m.datatype in _INT_TYPES:
            if not 1 <= v <= 31:
                raise Refused("out_of_range", f"{name}: {v} is not a mode number (1..31)")
            return int(v), f"{name}={v}"
        if m.datatype in (T.String, T.Text):
            if not v.strip() or len(v) > 64:
                raise Refused("out_of_range", f"{name}: a mode name is 1..64 characters")
            return v.strip(), f"{name}={v.strip()}"
    elif name == "Command/MachSpeed":
        if m.datatype in (T.Float, T.Double) or m.datatype in _INT_TYPES:
            return float(v), f"{name}={float(v):g}"
    elif name == "Command/Recipe":
        if m.datatype in _INT_TYPES:
            if not 1 <= v < 2**31:
                raise Refused("out_of_range", f"{name}: {v} is not a recipe ID (1 or more)")
            return int(v), f"{name}={v}"
        if m.datatype in (T.String, T.Text):
            if not v.strip() or len(v.strip()) > MAX_RECIPE_NAME:
                raise Refused(
                    "out_of_range", f"{name}: a recipe name is 1..{MAX_RECIPE_NAME} characters"
                )
            return v.strip(), f"{name}={v.strip()}"
    elif name == "Command/AckAlarms" and m.datatype in _INT_TYPES:
        if not 0 <= v < 2**31:
            raise Refused("out_of_range", f"{name}: {v} is not an alarm id (0: all)")
        return int(v), f"{name}={v}"
    raise Refused("wrong_type", f"{name}: a {m.datatype.name} is not taken here")
