"""An equipment module made of an existing ROS 2 action server or service, configured in the cell
file, without code (issue 26). An EM entry with an ``action:`` or a ``service:`` block::

    mover:
      action:
        type: test_msgs/action/Fibonacci   # the interface type, by name
        name: /robot/move                  # the server (relative: under /<cell>/<unit>)
        timeout: 10                        # s: the server must answer and the goal end within it
        cancel_on: [holding, stopping, aborting]   # the goal is cancelled when the unit goes there
        alarm: {id: 5001, reaction: stop, message: move failed}
        states:
          starting: {goal: {order: 3}}
          execute:  {goal: {order: "${parameter:order}"}, repeat: true,
                     count: {processed: 1, defective: defects}}
    gripper:
      service:
        type: std_srvs/srv/SetBool
        name: /gripper/grip
        success: success                   # a bool field of the response that must be true
        alarm: {id: 5002, category: 2}
        states:
          starting: {request: {data: true}}
          stopping: {request: {data: false}}

In each listed acting state the EM sends the goal (calls the service) and reports State Complete
when it succeeds; states not listed complete at once. ``repeat: true`` (Execute): the goal is sent
again after each success, until the unit leaves Execute. ``count``: after each success, add to the
unit's counters: a number, or the name of a result field (a number, or a list: its length).
Field values ``"${parameter:<name or id>}"`` come from the unit's ``Status.parameter``,
``"${product:id}"`` / ``"${product:<name>}"`` from its first product (id, process variable).

When the unit leaves the state while a goal runs: to a state listed in ``cancel_on`` (default:
stopping, aborting) the goal is cancelled; otherwise it completes first (a move is never cut
halfway). A service call is never interrupted. Failure (the goal rejected, aborted or cancelled by
the server, a response whose ``success`` field is false, the server not there, lost while the
goal runs, or not done within ``timeout``) raises the configured alarm (value: what went wrong,
:class:`Failure`) and reports nothing: the unit reacts as the alarm's category or reaction says.
``reaction:`` picks the unit's first alarm category with that reaction (its ``reactions:`` table).
The alarm's condition is cleared at once: it stays latched at the unit until Reset (or Clear).

Run: ``interface_em <cell.yaml> <unit> <em> [<em> ...]``.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from action_msgs.msg import GoalStatus
from rclpy.action.client import ActionClient
from rclpy.task import Future

from . import run
from .core import schema as sc
from .core.alarms import REACTIONS
from .core.config import CellConfig, UnitConfig, load_cell
from .core.numbers import ACTING, State, parse_state, state_name
from .core.schema import ConfigError, Node
from .equipment_module import COUNTERS, EquipmentModule, StateContext

KINDS = ("action", "service")
BLOCK_KEYS = {"type", "name", "timeout", "cancel_on", "alarm", "states", "success", "lease"}
STATE_KEYS = {"goal", "request", "repeat", "count"}
ALARM_KEYS = {"id", "category", "reaction", "message"}
DEFAULT_TIMEOUT = 30.0
DEFAULT_CANCEL_ON = frozenset({State.STOPPING, State.ABORTING})
#: s between looks at the server while a goal runs (a server that died: "lost")
WATCH = 0.1
_FILL = re.compile(r"^\$\{(parameter|product):([A-Za-z0-9_]+)\}$")


class Failure(IntEnum):
    """The alarm value: what went wrong."""

    REJECTED = 1  #: the server rejected the goal
    FAILED = 2  #: aborted or cancelled by the server, or the response said no
    TIMEOUT = 3  #: not done within ``timeout``
    NO_SERVER = 4  #: the server was not there
    LOST = 5  #: the server went away while the goal ran


@dataclass(frozen=True)
class Step:
    """What the EM does in one acting state."""

    fields: Mapping[str, Any]  # the goal or request, as in the file (with ${...} references)
    repeat: bool = False
    count: Mapping[str, int | str] = field(default_factory=dict)  # counter -> number or field


@dataclass(frozen=True)
class InterfaceConfig:
    kind: str  # action | service
    type_name: str
    interface: Any  # the imported type
    name: str
    timeout: float
    cancel_on: frozenset[State]
    alarm_id: int
    category: int
    message: str
    steps: Mapping[State, Step]
    success: str = ""  # a bool field of the result / response that must be true
    lease: float = 2.0


def _an(kind: str) -> str:
    return "an action" if kind == "action" else "a service"


def import_interface(name: str, kind: str) -> Any:
    """The type ``pkg/action/Name`` (``pkg/srv/Name``); ValueError with a sentence if not found."""
    part = "action" if kind == "action" else "srv"
    parts = name.split("/")
    if len(parts) != 3 or parts[1] != part or not all(parts):
        raise ValueError(f"{name!r} is not {_an(kind)} type name like package/{part}/Name")
    try:
        module = importlib.import_module(f"{parts[0]}.{part}")
    except ImportError:
        raise ValueError(f"no interface package {parts[0]!r} is installed (for {name})") from None
    found = getattr(module, parts[2], None)
    if found is None:
        raise ValueError(f"package {parts[0]} has no {part} {parts[2]!r}")
    return found


def _field_names(msg_type: Any) -> dict[str, str]:
    return dict(msg_type.get_fields_and_field_types())


def fill(fields: Mapping[str, Any], status: Any) -> dict[str, Any]:
    """``fields`` with every ``${parameter:..}`` / ``${product:..}`` replaced from ``status``
    (a ``Status``; None: zeros). KeyError with a sentence when a reference finds nothing."""
    out: dict[str, Any] = {}
    for key, value in fields.items():
        if isinstance(value, Mapping):
            out[key] = fill(value, status)
            continue
        match = _FILL.match(value) if isinstance(value, str) else None
        if match is None:
            out[key] = value
            continue
        source, ref = match.groups()
        if status is None:
            out[key] = 0.0
        elif source == "parameter":
            found = [p for p in status.parameter if p.name == ref or str(p.id) == ref]
            if not found:
                raise KeyError(f"the unit has no parameter {ref!r}")
            out[key] = found[0].value
        else:
            if not status.product:
                raise KeyError("the unit has no product")
            product = status.product[0]
            if ref == "id":
                out[key] = product.product_id
            else:
                found = [v for v in product.process_variables if v.name == ref]
                if not found:
                    raise KeyError(f"product {product.product_id} has no process variable {ref!r}")
                out[key] = found[0].value
    return out


def build(msg_type: Any, fields: Mapping[str, Any]) -> Any:
    """A ``msg_type`` with ``fields`` set (nested mappings: nested messages; a float for an int
    field is rounded). ValueError with a sentence for a field the type lacks or a wrong value."""
    msg = msg_type()
    names = _field_names(msg_type)
    for key, given in fields.items():
        value = given
        if key not in names:
            raise ValueError(
                f"{msg_type.__name__} has no field {key!r} (fields: {', '.join(names)})"
            )
        current = getattr(msg, key)
        if isinstance(value, Mapping):
            if not hasattr(type(current), "get_fields_and_field_types"):
                raise ValueError(f"field {key!r} is a {names[key]}, not a message")
            value = build(type(current), value)
        elif (
            isinstance(current, int) and isinstance(value, float) and not isinstance(current, bool)
        ):
            value = round(value)  # (a parameter's value is a float)
        problem = _kind_problem(current, value)
        if problem is not None:
            raise ValueError(f"field {key!r} ({names[key]}) cannot be {value!r}: {problem}")
        try:
            setattr(msg, key, value)
        except (AssertionError, TypeError, ValueError) as exc:
            raise ValueError(f"field {key!r} ({names[key]}) cannot be {value!r}: {exc}") from None
    return msg


def _kind_problem(current: Any, value: Any) -> str | None:
    """Why ``value`` cannot go where ``current`` (a field's default) is (None: it can)."""
    if isinstance(current, bool):
        return None if isinstance(value, bool) else "it takes true or false"
    if isinstance(current, int | float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            return "it takes a number"
        return None
    if isinstance(current, str):
        return None if isinstance(value, str) else "it takes text"
    if hasattr(current, "__len__") and not isinstance(value, list):
        return "it takes a list"
    return None


def result_number(result: Any, path: str) -> int:
    """The number at field ``path`` of ``result`` (a list: its length)."""
    value = getattr(result, path)
    return len(value) if hasattr(value, "__len__") else int(value)


def parse_interface(
    data: Mapping[str, Any], kind: str, path: str, file: str, unit: UnitConfig
) -> InterfaceConfig:
    """Validate an EM's ``action:`` / ``service:`` block at ``path``; ConfigError names each
    key path with a sentence. The type must be installed and every field must exist in it."""
    n = Node(dict(data), path)
    n.check_keys(BLOCK_KEYS)
    interface = None
    type_name = n.get("type", sc.text, "")
    if not type_name:
        n.child("type", None).error(f"{_an(kind)} EM needs the type of its {kind}")
    else:
        try:
            interface = import_interface(type_name, kind)
        except ValueError as exc:
            n.child("type", type_name).error(str(exc))
    server = n.get("name", sc.text, "")
    if not server:
        n.child("name", None).error(f"{_an(kind)} EM needs the name of its server")
    request_type = result_type = None
    if interface is not None:
        request_type = interface.Goal if kind == "action" else interface.Request
        result_type = interface.Result if kind == "action" else interface.Response
    cancel_on: frozenset[State] = DEFAULT_CANCEL_ON
    if "cancel_on" in n.mapping():
        states = {e.parse(sc.via(parse_state), State.UNDEFINED): e for e in n.list_at("cancel_on")}
        for s, e in states.items():
            if s is not State.UNDEFINED and s not in ACTING:
                e.error(f"{state_name(s)} is not an acting state")
        cancel_on = frozenset(s for s in states if s in ACTING)
    if kind == "service" and "cancel_on" in n.mapping():
        n.child("cancel_on", None).error(
            "a service call cannot be cancelled: cancel_on is for actions"
        )
    success = n.get("success", sc.text, "")
    if success and result_type is not None and success not in _field_names(result_type):
        n.child("success", success).error(f"{type_name} has no result field {success!r}")
    alarm = n.child("alarm", n.mapping().get("alarm"))
    alarm_id, category, message = 0, -1, ""
    if alarm.value is None:
        alarm.error(
            f"{_an(kind)} EM needs an alarm to raise when it fails: alarm: {{id: ..., category: ...}}"
        )
    else:
        alarm.check_keys(ALARM_KEYS)
        alarm_id = alarm.get("id", sc.integer(1, 2**31 - 1), 0)
        if "id" not in alarm.mapping():
            alarm.error("the alarm needs an id")
        category = alarm.get("category", sc.integer(0, 9), -1)
        reaction = alarm.get("reaction", sc.choice(REACTIONS), None)
        if reaction is not None:
            fitting = sorted(c for c, r in unit.reactions.items() if r == reaction)
            if category >= 0 and category not in fitting:
                alarm.error(
                    f"category {category} of unit {unit.name} reacts otherwise than the reaction given"
                )
            elif category < 0 and not fitting:
                alarm.error(
                    f"no alarm category of unit {unit.name} has that reaction (its reactions: table)"
                )
            elif category < 0:
                category = fitting[0]
        message = alarm.get("message", sc.text, "")
    steps: dict[State, Step] = {}
    word = "goal" if kind == "action" else "request"
    for key, child in n.items_at("states"):
        state = Node(key, child.path, child.problems).parse(sc.via(parse_state), State.UNDEFINED)
        if state not in ACTING:
            child.error(f"{key!r} is not an acting state")
            continue
        child.check_keys(STATE_KEYS)
        other = "request" if kind == "action" else "goal"
        if other in child.mapping():
            child.child(other, None).error(f"{_an(kind)} EM sends a {word}, not a {other}")
        fields: dict[str, Any] = child.get(word, lambda x: dict(x.mapping()), {})
        if request_type is not None:
            try:
                build(request_type, fill(fields, None))
            except ValueError as exc:
                child.child(word, fields).error(str(exc))
        repeat = child.get("repeat", sc.boolean, False)
        if repeat and state is not State.EXECUTE:
            child.child("repeat", True).error("only Execute repeats its goal")
        count: dict[str, int | str] = {}
        for counter, c in child.items_at("count"):
            if counter not in COUNTERS:
                c.error(f"{counter!r} is not a counter ({', '.join(COUNTERS)})")
            elif isinstance(c.value, int) and not isinstance(c.value, bool) and c.value >= 0:
                count[counter] = c.value
            elif isinstance(c.value, str) and result_type is not None:
                if c.value not in _field_names(result_type):
                    c.error(f"{type_name} has no result field {c.value!r} to count")
                count[counter] = c.value
            elif not isinstance(c.value, str):
                c.error("a count is a number >= 0 or the name of a result field")
        steps[state] = Step(fields, repeat, count)
    if not steps and "states" not in n.mapping():
        n.child("states", None).error(
            f"{_an(kind)} EM needs states: which acting states send a {word}"
        )
    timeout = n.get("timeout", sc.number(positive=True), DEFAULT_TIMEOUT)
    lease = n.get("lease", sc.number(positive=True), unit.em_lease)
    if n.problems:
        raise ConfigError(file, n.problems)
    return InterfaceConfig(
        kind,
        type_name,
        interface,
        server,
        timeout,
        cancel_on,
        alarm_id,
        category,
        message,
        steps,
        success,
        lease,
    )


def interface_block(em: Any) -> tuple[str, Mapping[str, Any]] | None:
    """The ``action:`` or ``service:`` block of a configured EM (``EmConfig``), or None."""
    if em.runs in KINDS and isinstance(em.spec, Mapping):
        return em.runs, em.spec
    return None


class StepFailed(Exception):
    def __init__(self, failure: Failure, detail: str) -> None:
        super().__init__(detail)
        self.failure = failure


class InterfaceEm(EquipmentModule):
    """An EM whose acting states are goals of an action server or calls of a service."""

    @classmethod
    def from_cell(
        cls, cell: CellConfig, unit: str, em: str, *, file: str, **node_kwargs: Any
    ) -> InterfaceEm:
        """Built from its cell file's block (the launcher's row in ``EM_RUNS``)."""
        return _from_cell(cell, unit, em, file, **node_kwargs)

    @classmethod
    def check_cell(cls, cell: CellConfig, unit: str, em: str, file: str) -> list[tuple[str, str]]:
        """(key path, problem) of its block, for ``packml launch --check``."""
        try:
            _parsed(cell, unit, em, file)
        except ConfigError as exc:
            return list(exc.problems)
        return []

    def __init__(
        self, name: str, unit: str, cell: str, config: InterfaceConfig, **node_kwargs: Any
    ) -> None:
        super().__init__(name, unit, cell, lease=config.lease, **node_kwargs)
        self.config = config
        self.last_feedback: Any = None
        self.failures: list[tuple[Failure, str]] = []
        if config.kind == "action":
            self._action: ActionClient[Any, Any, Any] | None = ActionClient(
                self, config.interface, config.name
            )
            self._service: Any = None
        else:
            self._action = None
            self._service = self.create_client(config.interface, config.name)

    def hook_for(self, state: State) -> Callable[[StateContext], Any] | None:
        return self._step if state in self.config.steps else None

    # -- a state's work ----------------------------------------------------------------------------
    async def _step(self, ctx: StateContext) -> None:
        step = self.config.steps[ctx.state]
        while not ctx.cancelled.is_set():
            try:
                fields = fill(step.fields, self.unit_status)
            except KeyError as exc:
                self._fail(ctx, Failure.FAILED, str(exc).strip("'\""))
                raise asyncio.CancelledError from None
            try:
                if self._action is not None:
                    result = await self._goal(ctx, fields)
                else:
                    result = await self._call(ctx, fields)
            except StepFailed as exc:
                self._fail(ctx, exc.failure, str(exc))
                raise asyncio.CancelledError from None  # no State Complete
            self._count(step, result)
            if not step.repeat:
                return

    def _fail(self, ctx: StateContext, failure: Failure, detail: str) -> None:
        c = self.config
        text = c.message or f"{self.em_name}: {c.kind} {c.name} failed in {state_name(ctx.state)}"
        text = f"{text}: {detail}"[:200]
        self.failures.append((failure, detail))
        self.get_logger().error(text)
        self.raise_alarm(c.alarm_id, int(failure), text, c.category)
        # A failed step is an event, not a lasting condition: the alarm stays latched at the
        # unit (and its reaction runs) until a Reset clears it.
        self.clear_alarm(c.alarm_id, int(failure))

    def _count(self, step: Step, result: Any) -> None:
        for counter, how in step.count.items():
            n = how if isinstance(how, int) else result_number(result, how)
            if n:
                self.count(counter, n)

    def _check_success(self, result: Any) -> None:
        if self.config.success and not getattr(result, self.config.success):
            detail = getattr(result, "message", "")
            raise StepFailed(Failure.FAILED, f"{self.config.success} is false {detail}".strip())

    async def _ready(self, is_ready: Callable[[], bool]) -> None:
        """Wait (bounded by the timeout) for the server."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.timeout
        while not is_ready():
            if loop.time() >= deadline:
                raise StepFailed(Failure.NO_SERVER, f"{self.config.name} is not there")
            await asyncio.sleep(WATCH)

    def _wrap(self, future: Future[Any]) -> asyncio.Future[Any]:
        """An rclpy future (done in the executor's thread) as an asyncio one on the EM's loop."""
        loop = asyncio.get_running_loop()
        out: asyncio.Future[Any] = loop.create_future()

        def done(f: Future[Any]) -> None:
            def settle() -> None:
                if out.done():
                    return
                exc = f.exception()
                if exc is not None:
                    out.set_exception(exc)
                else:
                    out.set_result(f.result())

            loop.call_soon_threadsafe(settle)

        future.add_done_callback(done)
        return out

    async def _call(self, ctx: StateContext, fields: Mapping[str, Any]) -> Any:
        client = self._service
        assert client is not None
        await self._ready(client.service_is_ready)
        request = build(self.config.interface.Request, fields)
        response = await self._await(
            self._wrap(client.call_async(request)), client.service_is_ready, ctx
        )
        self._check_success(response)
        return response

    async def _goal(self, ctx: StateContext, fields: Mapping[str, Any]) -> Any:
        client = self._action
        assert client is not None
        await self._ready(client.server_is_ready)
        goal = build(self.config.interface.Goal, fields)
        sent = client.send_goal_async(goal, feedback_callback=self._on_feedback)
        try:
            handle = await self._await(self._wrap(sent), client.server_is_ready, ctx)
        except asyncio.CancelledError:
            # The unit left while the goal was on its way: the goal, once accepted, is
            # cancelled or completed like one that was running.
            handle = sent.result() if sent.done() else None
            if handle is not None and handle.accepted:
                await self._await(
                    self._wrap(handle.get_result_async()), client.server_is_ready, ctx, handle
                )
            raise
        if not handle.accepted:
            raise StepFailed(Failure.REJECTED, f"{self.config.name} rejected the goal")
        answer = await self._await(
            self._wrap(handle.get_result_async()), client.server_is_ready, ctx, handle
        )
        if answer.status != GoalStatus.STATUS_SUCCEEDED:
            what = {GoalStatus.STATUS_ABORTED: "aborted", GoalStatus.STATUS_CANCELED: "cancelled"}
            raise StepFailed(
                Failure.FAILED,
                f"the goal was {what.get(answer.status, f'status {answer.status}')} by {self.config.name}",
            )
        self._check_success(answer.result)
        return answer.result

    def _on_feedback(self, msg: Any) -> None:
        self.last_feedback = msg.feedback

    async def _await(
        self,
        fut: asyncio.Future[Any],
        alive: Callable[[], bool],
        ctx: StateContext,
        handle: Any = None,
    ) -> Any:
        """``fut``'s result, within the timeout, while the server is there. The unit leaving the
        state meanwhile (``ctx.cancelled``: the base class sets it before it cancels the hook)
        does not interrupt it: the goal ``handle`` is cancelled at the server when the state the
        unit went to is in ``cancel_on`` (and then awaited), else it completes; then
        CancelledError (no State Complete for the state left). The event, not the task's
        cancellation, is what counts: Python 3.11's ``wait_for`` swallows a cancellation that
        arrives as its future completes."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.timeout
        cancel_sent = False
        while True:
            if ctx.cancelled.is_set() and not cancel_sent and handle is not None:
                cancel_sent = True  # asked once; without cancel_on the goal completes
                if ctx.next_state in self.config.cancel_on:
                    handle.cancel_goal_async()
            if fut.done():
                break
            if not alive():
                raise StepFailed(Failure.LOST, f"{self.config.name} went away")
            if loop.time() >= deadline:
                if handle is not None:
                    handle.cancel_goal_async()
                raise StepFailed(Failure.TIMEOUT, f"not done within {self.config.timeout:g} s")
            with contextlib.suppress(TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(fut), WATCH)
        if ctx.cancelled.is_set():
            raise asyncio.CancelledError
        return fut.result()


def create(cell_file: str, unit: str, em: str, **node_kwargs: Any) -> InterfaceEm:
    """The EM ``em`` of ``unit`` as the cell file configures it; ConfigError / SystemExit."""
    return _from_cell(load_cell(cell_file), unit, em, cell_file, **node_kwargs)


def _parsed(cell: CellConfig, unit: str, em: str, cell_file: str) -> InterfaceConfig:
    config = cell.units[unit]
    ems = {e.name: e for e in config.equipment_modules}
    block = interface_block(ems[em]) if em in ems else None
    if block is None:
        raise SystemExit(f"{cell_file}: EM {unit}/{em} has no action: or service: block")
    kind, data = block
    return parse_interface(
        data, kind, f"units.{unit}.equipment_modules.{em}.{kind}", cell_file, config
    )


def _from_cell(
    cell: CellConfig, unit: str, em: str, cell_file: str, **node_kwargs: Any
) -> InterfaceEm:
    if unit not in cell.units:
        raise SystemExit(f"{cell_file} has no unit {unit!r} (units: {', '.join(cell.units)})")
    return InterfaceEm(em, unit, cell.cell, _parsed(cell, unit, em, cell_file), **node_kwargs)


def main(argv: Sequence[str] | None = None) -> int:
    args = run.init(argv)
    if len(args) < 3:
        print(__doc__)
        return 2
    cell_file, unit, *names = args
    nodes: list[InterfaceEm] = []
    try:
        for name in names:
            nodes.append(create(cell_file, unit, name))
    except (ConfigError, OSError) as exc:
        for node in nodes:
            node.destroy_node()
        print(f"interface_em: {exc}", file=sys.stderr)
        return 2

    def close() -> None:
        for node in nodes:
            node.close()

    return run.spin(nodes, on_shutdown=close)


if __name__ == "__main__":
    sys.exit(main())
