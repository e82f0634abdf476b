"""The ROS side of the HMI: one node that follows every unit of a cell (latched status, admin,
alarms, transitions) and the coordinator's CellStatus through :class:`~packml_ros2.client.CellProxy`,
keeps the latest of each as a JSON-able dict, and pushes every change to its listeners at once.

Presence: whether each unit and the coordinator is there comes from their status' DDS liveliness
(:mod:`packml_ros2.presence`, lease ``coordinator.unit_lease``): a unit that is gone is reported
within its lease (event ``online``, its ``presence`` with since when and why), its last values
kept for the page to grey out, and actions on it refused at once.

The page draws each unit's state diagram from the unit's compiled rules (:func:`config_dict`:
the model's edges, each mode's edges and disabled states), and shows why a command or mode change
is not available now (:mod:`.why`, recomputed on every status and alarm list: event ``why``),
and why a cell command is not (the cell status' ``why``, from the coordinator's CellStatus).
Recipes (issue 32): each unit's recipes are in its config (:func:`.recipes.recipe_config`), the
recipe in use, the changeover and each EM's answer in its status, and why a recipe change is not
available now in its ``why`` (``recipe``); ``set_recipe`` takes ``{recipe_id}`` or
``{recipe_name}``.

Actions go to the units' (and the coordinator's) services with source
:func:`.access.command_source` (``hmi:<user>``); each returns the service's answer as a dict
``{accepted, result, result_name, message, ...}``. Without the credential the access rule asks for,
or below the level an action needs (:mod:`.access`), an action is refused here with result
``UNAUTHORIZED`` and never reaches the unit.

Threads: the node is spun by one single-threaded executor (:meth:`Bridge.spin_in_background`), so
messages are converted and announced in the order they arrive. Listeners are called from that
thread and must not block (the web server hands events to its event loop).
"""

from __future__ import annotations

import itertools
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from contextlib import suppress
from typing import Any

import rclpy
from packml_interfaces.msg import CellStatus
from packml_interfaces.srv import Command, SetMode
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from ..boundary import GuardedNode
from ..client import CellProxy, Unavailable, call_future
from ..core import CellConfig
from ..core.config import UnitConfig
from ..core.numbers import ACTING, MAX_MODE, Cmd, State, command_name, parse_command, state_name
from ..core.reasons import Reason
from ..core.rules import Edge, rules_of
from ..core.schema import shown
from ..presence import Presence, Seen
from . import why
from .access import (
    CELL_ACTION_LEVEL,
    LEVELS,
    LOGOUT_AFTER,
    UNIT_ACTION_LEVEL,
    Access,
    Principal,
    Refusal,
    User,
    command_source,
    level_refusal,
)
from .recipes import EM_ANSWERS, recipe_config, recipe_reason, set_recipe_args

Event = dict[str, Any]
Listener = Callable[[Event], None]

TRANSITIONS_KEPT = 30
HISTORY_KEPT = 50
CALL_TIMEOUT = 10.0
BAD_ARGUMENT = "BAD_ARGUMENT"  # ``code`` of an answer refused here for its arguments (HTTP 400)
OPERATOR_STATES = ("active_unacknowledged", "inactive_unacknowledged", "acknowledged")
KINDS = ("alarm", "warning", "command", "event")
OEE_FIELDS = (
    "availability", "performance", "quality", "oee", "production_time", "execute_time",
    "planned_stop_time", "internal_downtime", "external_downtime", "stopped_time",
    "aborted_time", "processed", "defective",
)  # fmt: skip
_node_ids = itertools.count()


class ActionError(LookupError):
    """An unknown unit or action (the web server answers 404)."""


# -- messages -> dicts -----------------------------------------------------------------------------
def _sec(t: Any) -> float:
    return float(t.sec + t.nanosec * 1e-9)


def _time_or_none(t: Any) -> float | None:
    return _sec(t) if (t.sec or t.nanosec) else None


def alarm_dict(a: Any) -> dict[str, Any]:
    state = int(a.operator_state)
    return {
        "id": a.id,
        "value": a.value,
        "message": a.message,
        "category": a.category,
        "trigger": a.trigger,
        "latched": a.latched,
        "acknowledged": a.acknowledged,
        "operator_state": state,
        "operator_state_name": OPERATOR_STATES[state] if state < len(OPERATOR_STATES) else "",
        "kind": KINDS[a.kind] if a.kind < len(KINDS) else str(a.kind),
        "em": a.em,
        "source": a.source,
        "reaction": a.reaction,
        "reaction_name": command_name(a.reaction) if a.reaction else "",
        "time": _time_or_none(a.stamp),
        "ack_time": _time_or_none(a.ack_stamp),
        "cleared_time": _time_or_none(a.cleared_stamp),
    }


def status_dict(s: Any) -> dict[str, Any]:
    return {
        "stamp": _sec(s.stamp),
        "unit": s.unit,
        "mode": s.unit_mode_current,
        "mode_name": s.unit_mode_current_name,
        "mode_requested": s.unit_mode_requested,
        "mode_change_in_process": s.unit_mode_change_in_process,
        "mode_change_not_allowed": s.mode_change_not_allowed,
        "state": s.state_current,
        "state_name": s.state_current_name,
        "state_requested": s.state_requested,
        "state_requested_name": state_name(s.state_requested),
        "state_change_in_process": s.state_change_in_process,
        "acting": s.state_current in ACTING,
        "sequence": s.sequence,
        "states_disabled": s.states_disabled,
        "commands_valid": list(s.commands_valid),
        "commands_valid_names": list(s.commands_valid_names),
        "cntrl_cmd": s.cntrl_cmd,
        "mach_speed": s.mach_speed,
        "cur_mach_speed": s.cur_mach_speed,
        "command_mach_speed": s.command_mach_speed,
        "material_interlock": s.material_interlock,
        "blocked": s.equipment_interlock.blocked,
        "starved": s.equipment_interlock.starved,
        "remote_commands_enabled": s.remote_commands_enabled,
        "time_rollover_warning": s.time_rollover_warning,
        "active_alarms": s.active_alarms,
        "unacknowledged_alarms": s.unacknowledged_alarms,
        "alarm_banner": s.alarm_banner,
        "stop_reason_id": s.stop_reason_id,
        "recipe_current": s.recipe_current,
        "recipe_current_name": s.recipe_current_name,
        "recipe_requested": s.recipe_requested,
        "recipe_change_in_process": s.recipe_change_in_process,
        "recipe_changeover": s.recipe_changeover,
        "recipe_result": s.recipe_result,
        "stack_light": {
            "colors": list(s.stack_light.colors),
            "modes": [int(m) for m in s.stack_light.modes],
            "horn": s.stack_light.horn,
        },
        "parameters": [
            {"id": d.id, "name": d.name, "unit": d.unit, "value": d.value} for d in s.parameter
        ],
        "equipment_modules": [
            {
                "name": e.name,
                "active": e.active,
                "online": e.online,
                "configured": e.configured,
                "state_complete": e.state_complete,
                "sequence": e.sequence,
                "command_request": e.command_request,
                "command_request_name": command_name(e.command_request)
                if e.command_request
                else "",
                "blocked": e.blocked,
                "starved": e.starved,
                "stale_reports": e.stale_reports,
                "recipe_answer": e.recipe_answer,
                "recipe_answer_name": EM_ANSWERS.get(e.recipe_answer, str(e.recipe_answer)),
                "recipe_message": e.recipe_message,
            }
            for e in s.equipment_modules
        ],
    }


def _counts(counts: Any) -> list[dict[str, Any]]:
    return [
        {"id": c.id, "name": c.name, "unit": c.unit, "count": c.count, "acc_count": c.acc_count}
        for c in counts
    ]


def admin_dict(a: Any, modes: list[int]) -> dict[str, Any]:
    """Admin with the state times of the configured ``modes`` only (``times[str(mode)]``)."""
    n = a.NUM_STATES
    times: dict[str, Any] = {}
    cur, cum = a.state_current_time, a.state_cumulative_time
    for m in modes:
        times[str(m)] = {
            "mode_current": a.mode_current_time[m] if m < len(a.mode_current_time) else 0,
            "mode_cumulative": a.mode_cumulative_time[m] if m < len(a.mode_cumulative_time) else 0,
            "state_current": list(cur[m * n : (m + 1) * n]),
            "state_cumulative": list(cum[m * n : (m + 1) * n]),
        }
    o = a.oee
    return {
        "stamp": _sec(a.stamp),
        "times": times,
        "acc_time_since_reset": a.acc_time_since_reset,
        "time_rollover_warning": a.time_rollover_warning,
        "counters": {
            "consumed": _counts(a.prod_consumed_count),
            "processed": _counts(a.prod_processed_count),
            "defective": _counts(a.prod_defective_count),
        },
        "mach_design_speed": a.mach_design_speed,
        "stop_reason": alarm_dict(a.stop_reason) if a.stop_reason_extent else None,
        "oee": {name: getattr(o, name) for name in OEE_FIELDS},
        "history": [alarm_dict(x) for x in a.alarm_history[:HISTORY_KEPT]],
        "alarm_overflow": a.alarm_overflow,
    }


def alarm_list_dict(a: Any) -> dict[str, Any]:
    return {
        "stamp": _sec(a.stamp),
        "alarms": [alarm_dict(x) for x in a.alarms],
        "warnings": [alarm_dict(x) for x in a.warnings],
        "first_out": alarm_dict(a.first_out) if a.first_out.id else None,
        "banner": a.banner,
        "alarm_overflow": a.alarm_overflow,
        "warning_overflow": a.warning_overflow,
    }


def transition_dict(t: Any) -> dict[str, Any]:
    return {
        "stamp": _sec(t.stamp),
        "sequence": t.sequence,
        "from_state": t.from_state_name,
        "to_state": t.to_state_name,
        "from_mode": t.from_mode,
        "to_mode": t.to_mode,
        "trigger": t.trigger_name,
        "command": command_name(t.command) if t.command else "",
        "source": t.source,
        "detail": t.detail,
    }


def cell_status_dict(c: Any) -> dict[str, Any]:
    return {
        "stamp": _sec(c.stamp),
        "cell": c.cell,
        "state": c.state_current,
        "state_name": c.state_current_name,
        "mode": c.unit_mode_current,
        "all_online": c.all_online,
        "busy": c.busy,
        "sequence_step": c.sequence_step,
        "lost_units": list(c.lost_units),
        "detail": c.detail,
        "commands_valid": list(c.commands_valid),
        "commands_valid_names": list(c.commands_valid_names),
        "units": [
            {
                "name": u.name,
                "online": u.online,
                "state": u.state_current,
                "state_name": u.state_current_name,
                "mode": u.unit_mode_current,
                "mode_name": u.unit_mode_current_name,
                "em_total": u.em_total,
                "em_online": u.em_online,
                "active_alarms": u.active_alarms,
                "alarm_banner": u.alarm_banner,
                "blocked": u.blocked,
                "starved": u.starved,
                "interlock_suspended": u.interlock_suspended,
                "health": u.health,
            }
            for u in c.units
        ],
    }


def answer_dict(resp: Any) -> dict[str, Any]:
    """A service response as a dict; ``result_name`` spells the reason code."""
    out: dict[str, Any] = {}
    for name in resp.get_fields_and_field_types():
        value = getattr(resp, name)
        out["message" if name == "message_out" else name] = (
            value if isinstance(value, bool | int | float | str) else str(value)
        )
    code = int(out.get("result", 0))
    out["result_name"] = Reason(code).name if code in Reason._value2member_map_ else str(code)
    for key in ("state_current", "state_requested"):
        if key in out:
            out[f"{key}_name"] = state_name(out[key])
    return out


def refusal(reason: Reason, message: str) -> dict[str, Any]:
    return {
        "accepted": False,
        "result": int(reason),
        "result_name": reason.name,
        "message": message,
    }


def _edge(e: Edge) -> list[Any]:
    """``[from, command or None (State Complete), to, [skipped states]]``"""
    return [
        e.from_state.name,
        e.trigger.name if e.trigger else None,
        e.to_state.name,
        [s.name for s in e.skipped],
    ]


def unit_config_dict(name: str, u: UnitConfig) -> dict[str, Any]:
    """One unit for the page: its modes and EMs, and its state diagram from its compiled rules
    (``edges``: the model's graph; each mode's ``edges`` and ``disabled_states``)."""
    rules = rules_of(u)
    commands = rules.table.commands
    return {
        "name": name,
        "description": u.description,
        "model": rules.table.model,
        "hold_from": sorted(s.name for s, c in commands if c is Cmd.HOLD),
        "complete_from": sorted(s.name for s, c in commands if c is Cmd.COMPLETE),
        "edges": [_edge(e) for e in rules.edges()],
        "modes": [
            {
                "number": m.number,
                "name": m.name,
                "disabled": m.disabled_mask,
                "disabled_states": sorted(s.name for s in m.disabled),
                "change_allowed": sorted(s.name for s in m.change_allowed),
                "edges": [_edge(e) for e in rules.edges(m.number)],
            }
            for m in sorted(u.modes.values(), key=lambda m: m.number)
        ],
        "equipment_modules": [e.name for e in u.equipment_modules],
        "mach_design_speed": u.mach_design_speed,
        **recipe_config(u),
    }


def config_dict(cell: CellConfig, title: str = "", access: Access | None = None) -> dict[str, Any]:
    """What the page needs to draw itself: units (their modes, EMs and state diagrams), states,
    commands, how one logs in and which level each action needs."""
    access = access or Access(None)
    return {
        "cell": cell.cell,
        "title": title or cell.cell,
        "login": access.kind,  # users, token or none
        "token_required": access.kind == "token",
        "levels": list(LEVELS),
        "unit_action_level": dict(UNIT_ACTION_LEVEL),
        "cell_action_level": dict(CELL_ACTION_LEVEL),
        # the source the shared reasons of disabled controls are judged for (hmi:<user> with
        # logins: the rule book judges every hmi: user alike); each page names its own user
        "why_source": command_source(access.viewer),
        "logout_after": access.sessions.idle,
        "lease": cell.coordinator.unit_lease,
        "coordinator": cell.coordinator.enabled,
        "states": [{"number": int(s), "name": s.name, "acting": s in ACTING} for s in State if s],
        "commands": [{"number": int(c), "name": c.name} for c in Cmd if c],
        "units": [unit_config_dict(name, u) for name, u in cell.units.items()],
    }


def presence_dict(seen: Seen) -> dict[str, Any]:
    """``{present, since, reason}``: ``present`` None while not known yet; ``since`` in s since
    the epoch."""
    return {"present": seen.present, "since": seen.since, "reason": seen.reason}


# -- the bridge ------------------------------------------------------------------------------------
class Bridge:
    """The cell seen by the HMI. ``context``: an initialised rclpy Context (default: a new one,
    shut down by :meth:`close`). Spin the node with :meth:`spin_in_background`. ``token`` or
    ``users`` (with ``logout_after``): the access rule (:class:`.access.Access`); ``lease``: how
    long a silent unit or coordinator is still present (default ``coordinator.unit_lease``)."""

    def __init__(
        self,
        cell: CellConfig,
        *,
        token: str | None = None,
        users: Mapping[str, User] | None = None,
        logout_after: float = LOGOUT_AFTER,
        title: str = "",
        context: Context | None = None,
        lease: float | None = None,
    ) -> None:
        self.cell = cell
        self.access = Access(token or None, users=users, logout_after=logout_after)
        self.config = config_dict(cell, title, self.access)
        #: the source the reasons of disabled controls are judged for: the one of the actions
        self._why_source: str = self.config["why_source"]
        self.lease = cell.coordinator.unit_lease if lease is None else lease
        self._modes = {name: sorted(m for m in u.modes if m < 32) for name, u in cell.units.items()}
        self._own_context = context is None
        if context is None:
            context = Context()
            rclpy.init(
                context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO
            )
        self.context = context
        self.node = GuardedNode(
            f"hmi_{os.getpid()}_{next(_node_ids)}", namespace=f"/{cell.cell}", context=context
        )
        self._lock = threading.RLock()
        self._listeners: list[Listener] = []
        started = Seen(None, time.time())
        self._units: dict[str, dict[str, Any]] = {
            name: {
                "status": None,
                "admin": None,
                "alarms": None,
                "transitions": [],
                "online": False,
                "presence": presence_dict(started),
                "why": self._reasons(name, None, None),
            }
            for name in cell.units
        }
        self._cell_status: dict[str, Any] | None = None
        self._coordinator_presence: dict[str, Any] | None = (
            presence_dict(started) if cell.coordinator.enabled else None
        )
        self._group = MutuallyExclusiveCallbackGroup()
        self.proxy = CellProxy(self.node, cell.cell, cell.units, on_change=self._on_change)
        self.presence = Presence(
            self.node,
            [f"/{cell.cell}/{name}" for name in cell.units],
            self.lease,
            on_change=self._on_presence,
        )
        self.coordinator_presence: Presence | None = None
        if cell.coordinator.enabled:
            self.coordinator_presence = Presence(
                self.node,
                [f"/{cell.cell}/coordinator"],
                self.lease,
                on_change=self._on_presence,
                message_type=CellStatus,
            )
        self._coordinator: dict[str, Any] = {
            "command": self.node.create_client(
                Command, f"/{cell.cell}/coordinator/command", callback_group=self._group
            ),
            "set_mode": self.node.create_client(
                SetMode, f"/{cell.cell}/coordinator/set_mode", callback_group=self._group
            ),
        }
        self._running = True
        self._executor: SingleThreadedExecutor | None = None
        self._thread: threading.Thread | None = None

    # -- running -----------------------------------------------------------------------------------
    def spin_in_background(self) -> Bridge:
        """Spin the node in a daemon thread (one thread: callbacks run in arrival order)."""
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="hmi-bridge", daemon=True)
        self._thread.start()
        return self

    def _spin(self) -> None:
        assert self._executor is not None
        with suppress(ExternalShutdownException, rclpy.executors.ShutdownException):
            while self._running and self.context.ok():
                self._executor.spin_once(timeout_sec=0.1)

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(3)
        if self._executor is not None:
            self._executor.shutdown(timeout_sec=2)
        with suppress(Exception):
            self.node.destroy_node()
        if self._own_context:
            rclpy.try_shutdown(context=self.context)

    # -- state -------------------------------------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """Everything the page shows, as it is now."""
        with self._lock:
            return {
                "config": self.config,
                "units": {
                    name: {**u, "transitions": list(u["transitions"])}
                    for name, u in self._units.items()
                },
                "cell_status": self._cell_status,
                "coordinator": self._coordinator_presence,
                "time": time.time() * 1000.0,
            }

    def subscribe(self, listener: Listener) -> tuple[dict[str, Any], Callable[[], None]]:
        """The snapshot and, from then on, every change event (no gap, no duplicate); returns
        (snapshot, unsubscribe). ``listener`` runs in the bridge's thread: it must not block."""
        with self._lock:
            self._listeners.append(listener)
            snap = self.snapshot()

        def unsubscribe() -> None:
            with self._lock, suppress(ValueError):
                self._listeners.remove(listener)

        return snap, unsubscribe

    def _emit(self, event: Event) -> None:
        for listener in list(self._listeners):
            try:
                listener(event)
            except Exception as exc:  # one broken listener must not starve the others
                self.node.get_logger().warning(f"HMI listener failed: {exc!r}")

    def _on_presence(self, path: str, seen: Seen) -> None:
        """A unit's or the coordinator's presence changed (the node's thread)."""
        name = path.rsplit("/", 1)[-1]
        with self._lock:
            if path == f"/{self.cell.cell}/coordinator":
                self._coordinator_presence = data = presence_dict(seen)
                self._emit(
                    {
                        "topic": "coordinator",
                        "unit": None,
                        "data": data,
                        "received": time.time() * 1000.0,
                    }
                )
            elif name in self._units:
                self._set_presence(name, seen)

    def _set_presence(self, name: str, seen: Seen) -> None:
        unit = self._units[name]
        unit["online"] = seen.present is True
        unit["presence"] = data = presence_dict(seen)
        self._emit(
            {"topic": "online", "unit": name, "data": data, "received": time.time() * 1000.0}
        )

    def _on_change(self, path: str, topic: str, msg: Any) -> None:
        received = time.time() * 1000.0
        name = path.rsplit("/", 1)[-1]
        with self._lock:
            if topic == "cell_status":
                data = cell_status_dict(msg)
                data["why"] = why.cell_command_reasons(data)  # the page greys what it names
                self._cell_status = data
                self._emit({"topic": "cell", "unit": None, "data": data, "received": received})
                coordinator = self._coordinator_presence
                if coordinator is not None and coordinator["present"] is None:  # a sign of life
                    self._on_presence(path, Seen(True, time.time()))
                return
            unit = self._units.get(name)
            if unit is None:
                return
            if unit["presence"]["present"] is None:  # a sign of life before liveliness says so
                self._set_presence(name, Seen(True, time.time()))
            if topic == "transitions":
                data = transition_dict(msg)
                unit["transitions"].append(data)
                del unit["transitions"][:-TRANSITIONS_KEPT]
                self._emit(
                    {"topic": "transition", "unit": name, "data": data, "received": received}
                )
                return
            if topic == "status":
                data = status_dict(msg)
            elif topic == "admin":
                data = admin_dict(msg, self._modes[name])
            elif topic == "alarms":
                data = alarm_list_dict(msg)
            else:
                return
            # (no reordering by stamp: a unit that catches up a deadline publishes a status
            # stamped at the deadline, which may be earlier than the one before; DDS delivers
            # each topic in order and one thread handles them.)
            unit[topic] = data
            self._emit({"topic": topic, "unit": name, "data": data, "received": received})
            if topic in ("status", "alarms"):
                reasons = self._reasons(name, unit["status"], unit["alarms"])
                if reasons != unit["why"]:
                    unit["why"] = reasons
                    self._emit(
                        {"topic": "why", "unit": name, "data": reasons, "received": received}
                    )

    def _reasons(
        self, name: str, status: dict[str, Any] | None, alarms: dict[str, Any] | None
    ) -> dict[str, Any]:
        """The unit's ``why`` (:func:`.why.reasons`) and ``recipe``: why a recipe change is not
        available now (:func:`.recipes.recipe_reason`, '' = it is)."""
        config = self.cell.units[name]
        return {
            **why.reasons(config, status, alarms, self._why_source),
            "recipe": recipe_reason(config, status, self._why_source),
        }

    def gone(self, unit: str | None) -> str:
        """Why ``unit`` (None: the coordinator) cannot be called now ('' = it can)."""
        with self._lock:
            if unit is None:
                seen = self._coordinator_presence
                what = f"the {self.cell.cell} coordinator"
            else:
                seen = self._units[unit]["presence"]
                what = f"{self.cell.cell}/{unit}"
        if seen is None or seen["present"] is not False:
            return ""
        clock = time.strftime("%H:%M:%S", time.localtime(seen["since"]))
        return f"{what} is not reachable since {clock} ({seen['reason']})"

    # -- actions -----------------------------------------------------------------------------------
    def builder(self, unit: str | None, action: str) -> Builder:
        """The request builder of ``action`` on ``unit`` (None: the cell); raises
        :class:`ActionError` for an unknown unit or action."""
        if unit is not None and unit not in self._units:
            raise ActionError(f"no unit {shown(unit)} in cell {self.cell.cell}")
        builders = UNIT_ACTIONS if unit is not None else CELL_ACTIONS
        if action not in builders:
            raise ActionError(
                f"unknown action {shown(action)} (valid: {', '.join(sorted(builders))})"
            )
        return builders[action]

    def act(
        self,
        unit: str | None,
        action: str,
        args: Mapping[str, Any] | None = None,
        token: str | None = None,
        *,
        who: Principal | None = None,
    ) -> Future[dict[str, Any]]:
        """Call ``action`` of ``unit`` (None: the cell coordinator) for ``who`` (default: whom
        ``token`` stands for) with source :func:`.access.command_source`; a future of the answer
        dict. Refused here below the action's level and when the unit is gone. Raises
        :class:`ActionError` for an unknown unit or action."""
        args = dict(args or {})
        builder = self.builder(unit, action)
        done: Future[dict[str, Any]] = Future()
        verified = self.access.verify(token) if who is None else who
        denied = (
            verified if isinstance(verified, Refusal) else level_refusal(verified, unit, action)
        )
        if denied is not None:
            done.set_result(denied.body())
            return done
        assert isinstance(verified, Principal)
        try:
            service, fields = builder(args)
        except (ValueError, TypeError, KeyError) as exc:
            text = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
            answer = refusal(Reason.INVALID_ARGUMENT, f"{action}: {text[:300]}")
            done.set_result({**answer, "code": BAD_ARGUMENT})
            return done
        gone = self.gone(unit)
        if gone:
            done.set_result(refusal(Reason.UNIT_UNAVAILABLE, f"{action}: {gone}; nothing was sent"))
            return done
        fields["source"] = command_source(verified)
        if unit is not None:
            future = self.proxy.unit(unit).call(service, **fields)
            where = f"{self.cell.cell}/{unit}"
        else:
            future = self._call_coordinator(service, fields)
            where = f"the {self.cell.cell} coordinator"

        def finished(f: Future[Any]) -> None:
            exc = f.exception()
            if isinstance(exc, Unavailable):
                done.set_result(
                    refusal(Reason.UNIT_UNAVAILABLE, f"{where} is not answering ({exc})")
                )
            elif exc is not None:
                done.set_result(refusal(Reason.UNIT_UNAVAILABLE, f"{where}: {exc}"))
            else:
                done.set_result(answer_dict(f.result()))

        future.add_done_callback(finished)
        return done

    def act_sync(
        self,
        unit: str | None,
        action: str,
        args: Mapping[str, Any] | None = None,
        token: str | None = None,
        timeout: float = CALL_TIMEOUT,
        *,
        who: Principal | None = None,
    ) -> dict[str, Any]:
        """:meth:`act` and wait (not from the bridge's thread)."""
        try:
            return self.act(unit, action, args, token, who=who).result(timeout)
        except TimeoutError:
            return refusal(Reason.UNIT_UNAVAILABLE, f"{action}: no answer within {timeout:g} s")

    def _call_coordinator(self, service: str, fields: dict[str, Any]) -> Future[Any]:
        request = (Command if service == "command" else SetMode).Request(**fields)
        path = f"/{self.cell.cell}/coordinator/{service}"
        return call_future(self._coordinator[service], request, path)


# -- request builders: (args from the page) -> (service, request fields) ---------------------------
# Every argument is checked here, before anything is sent: only the keys the action takes, integers
# within the range of their field (no wrap-around: 4294967298 is not mode 2), finite numbers,
# short strings.
INT32 = (-(2**31), 2**31 - 1)
MAX_TEXT = 64


def _only(args: Mapping[str, Any], *keys: str) -> None:
    extra = sorted(k for k in args if k not in keys)
    if extra:
        takes = ", ".join(f"'{k}'" for k in keys) or "no arguments"
        raise ValueError(f"unknown argument {shown(extra[0])} (it takes {takes})")


def _int(
    args: Mapping[str, Any], key: str, default: int = 0, lo: int = INT32[0], hi: int = INT32[1]
) -> int:
    value = args.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"'{key}' must be an integer")
    if not lo <= value <= hi:
        raise ValueError(f"'{key}' must be {lo}..{hi}, not {shown(value)}")
    return value


def _text(args: Mapping[str, Any], key: str) -> str:
    value = args.get(key)
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"'{key}' must be a non-empty string")
    if len(value) > MAX_TEXT or not value.isprintable():
        raise ValueError(f"'{key}' must be at most {MAX_TEXT} printable characters")
    return value


def _command(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "command")
    cmd = args.get("command")
    if isinstance(cmd, int) and not isinstance(cmd, bool):
        return "command", {"command": _int(args, "command", lo=1, hi=max(Cmd))}
    if not isinstance(cmd, str):
        raise ValueError("give 'command': a name (start) or a number (2)")
    return "command", {"command": int(parse_command(_text(args, "command")))}


def _set_mode(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "mode")
    mode = args.get("mode")
    if isinstance(mode, str) and mode.strip().isascii() and mode.strip().isdigit():
        if len(mode) > 12:
            raise ValueError(f"'mode' must be 1..{MAX_MODE}")
        mode = args["mode"] = int(mode.strip())
    if isinstance(mode, int) and not isinstance(mode, bool):
        return "set_mode", {"mode": _int(args, "mode", lo=1, hi=MAX_MODE)}
    if not isinstance(mode, str) or not mode:
        raise ValueError("give 'mode': a number (2) or a configured name (maintenance)")
    return "set_mode", {"mode_name": _text(args, "mode")}


def _flag(args: dict[str, Any], key: str, default: bool) -> bool:
    value = args.get(key, default)
    if not isinstance(value, bool):
        raise ValueError(f"'{key}' must be true or false")
    return value


def _ack(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "all", "id", "value")
    everything = _flag(args, "all", "id" not in args)
    return "ack_alarms", {"all": everything, "id": _int(args, "id"), "value": _int(args, "value")}


def _reset_alarms(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "clear_first_out")
    return "reset_alarms", {"clear_first_out": _flag(args, "clear_first_out", False)}


def _reset_times(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "scope")
    scope = args.get("scope", "mode")
    scopes = {"mode": 0, "all": 1}
    if not isinstance(scope, str) or scope not in scopes:
        raise ValueError("'scope' must be 'mode' (the current mode) or 'all'")
    return "reset_times", {"scope": scopes[scope]}


def _reset_counters(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args)
    return "reset_counters", {}


def _set_em_active(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "em", "active")
    em = args.get("em")
    if not isinstance(em, str) or not em:
        raise ValueError("give 'em': the equipment module's name")
    if (
        len(em) > 255
        or not (em[0].isalpha() or em[0] == "_")
        or not all(c.isascii() and (c.isalnum() or c == "_") for c in em)
    ):
        raise ValueError("'em' must be an equipment module's name (letters, digits and _)")
    return "set_em_active", {"em": em, "active": _flag(args, "active", True)}


def _set_recipe(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    return "set_recipe", set_recipe_args(args)


def _set_mach_speed(args: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    _only(args, "mach_speed")
    speed = args.get("mach_speed")
    if isinstance(speed, bool) or not isinstance(speed, int | float):
        raise ValueError("'mach_speed' must be a number")
    try:
        value = float(speed)
    except OverflowError:
        raise ValueError("'mach_speed' is out of range") from None
    if not math.isfinite(value) or value < 0:
        raise ValueError("'mach_speed' must be a finite number, 0 or more")
    return "set_mach_speed", {"mach_speed": value}


Builder = Callable[[dict[str, Any]], tuple[str, dict[str, Any]]]
UNIT_ACTIONS: dict[str, Builder] = {
    "command": _command,
    "set_mode": _set_mode,
    "ack_alarms": _ack,
    "reset_alarms": _reset_alarms,
    "reset_times": _reset_times,
    "reset_counters": _reset_counters,
    "set_em_active": _set_em_active,
    "set_mach_speed": _set_mach_speed,
    "set_recipe": _set_recipe,
}
CELL_ACTIONS: dict[str, Builder] = {"command": _command, "set_mode": _set_mode}
