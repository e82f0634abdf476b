"""The ROS side of the OPC UA server, and the method handlers.

:class:`RosSide` runs an rclpy node (its own Context) in a thread: a
:class:`~packml_ros2.client.CellProxy` subscribes to every exposed unit's latched ``status``,
``admin`` topics (no more: the Admin message carries the alarm lists too) and hands each status and admin message to the asyncio loop with ``call_soon_threadsafe`` (values
follow the topics: no polling). A :class:`~packml_ros2.presence.Presence` follows each unit's
liveliness (lease ``unit_lease``); its changes reach the loop the same way. Service calls go the
other way: the proxy's concurrent future is awaited with ``asyncio.wrap_future`` and abandoned
at once when the unit is lost meanwhile.

:class:`Methods` builds the method callbacks of one unit from the NodeSet's method definitions:
each checks that the method belongs to the object it is called on, the input arguments against
the NodeSet's signature (count, type, array or scalar), the caller (:func:`.security.may_call`)
and the unit's presence, then calls the unit's service with :func:`.security.command_source` as
the source and answers Good, or a Bad status code with the unit's message as the reason
(:func:`.security.refuse`).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import Any

from asyncua import ua

from ..client import CellProxy, Unavailable, UnitProxy
from ..core.config import UnitConfig
from ..core.limits import speed_limit, speed_refusal
from ..core.numbers import Cmd
from ..presence import Presence, Seen
from .config import OpcUaConfig
from .mapping import COMMAND_METHODS, EXTENSION_METHODS, GOOD, RESULT_NAMES, result_status
from .nodeset import MethodDef, PackMLModel
from .security import command_source, may_call, refuse

#: The unit services the methods use (clients are created before spinning starts).
USED_SERVICES = (
    "command",
    "set_mode",
    "set_mach_speed",
    "set_unit_parameters",
    "set_product",
    "set_recipe",
)
#: The unit topics followed: the Admin message carries the alarm lists too.
FOLLOWED = ("status", "admin")
S = ua.StatusCodes
INSTANCE_NS = 1  # the units' objects live in the server's own namespace (see .model)


class RosSide:
    """An rclpy node in a thread of its own, feeding ``on_message(unit, topic, msg)`` and
    ``on_presence(unit, seen)`` into ``loop``."""

    def __init__(
        self,
        cell: str,
        units: Sequence[str],
        loop: asyncio.AbstractEventLoop,
        on_message: Callable[[str, str, Any], None],
        on_presence: Callable[[str, Seen], None],
        lease: float,
        cell_object: bool = False,
    ) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        from ..boundary import GuardedNode as Node

        self.loop = loop
        self._on_message = on_message
        self._on_presence = on_presence
        #: the presence of each unit as the loop knows it, and an event set while it is lost
        names = [*units, cell] if cell_object else list(units)
        self.seen: dict[str, Seen] = {u: Seen(None, time.time()) for u in names}
        self._lost = {u: asyncio.Event() for u in names}
        self.context = Context()
        rclpy.init(
            context=self.context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO
        )
        self.node = Node("packml_opcua", namespace=f"/{cell}", context=self.context)
        # only what is handed on (status, admin): a unit's alarm list and transition events would
        # be deserialized for nothing, in the thread a status waits in
        self.cell = CellProxy(self.node, cell, units, on_change=self._changed, topics=FOLLOWED)
        for proxy in self.cell.units.values():
            for service in USED_SERVICES:
                proxy.client(service)
        #: what a method calls, by object name: the units, and the cell's coordinator
        self.proxies: dict[str, UnitProxy] = dict(self.cell.units)
        self.presence = Presence(
            self.node,
            [proxy.path for proxy in self.cell.units.values()],
            lease,
            on_change=self._presence_changed,
        )
        self.cell_presence: Presence | None = None
        if cell_object:
            self._follow_cell(cell, lease)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="packml-opcua-ros", daemon=True)

    def _follow_cell(self, cell: str, lease: float) -> None:
        """The cell object's side (:mod:`.cell`): the coordinator's status and stop episodes,
        translated to a unit's Status and Admin, its presence, and its command services."""
        from packml_interfaces.msg import CellStatus, LineEpisode

        from .. import qos
        from . import cell as cell_object

        path = cell_object.coordinator_path(cell)
        proxy = self.proxies[cell] = UnitProxy(self.node, path, None, topics=())
        for service in cell_object.SERVICES:
            proxy.client(service)

        def hand(topic: str, msg: Any) -> None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
                self.loop.call_soon_threadsafe(self._on_message, cell, topic, msg)

        def on_status(msg: Any) -> None:
            proxy.status = status = cell_object.cell_status(msg)
            hand("status", status)

        events = qos.quiet_events()
        self.node.create_subscription(
            CellStatus, f"{path}/status", on_status, qos.CELL_STATUS, event_callbacks=events
        )
        self.node.create_subscription(
            LineEpisode,
            f"{path}/line/episodes",
            lambda msg: hand("admin", cell_object.cell_admin(msg)),
            qos.LINE_EPISODES,
            event_callbacks=events,
        )
        self.cell_presence = Presence(
            self.node,
            [path],
            lease,
            on_change=lambda _, seen: self._presence_of(cell, seen),
            message_type=CellStatus,
        )

    def start(self) -> None:
        self._thread.start()

    def _spin(self) -> None:
        while not self._stopping.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def _changed(self, path: str, topic: str, msg: Any) -> None:
        if topic not in FOLLOWED:
            return
        unit = path.rsplit("/", 1)[-1]
        with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
            self.loop.call_soon_threadsafe(self._on_message, unit, topic, msg)

    def _presence_changed(self, path: str, seen: Seen) -> None:
        self._presence_of(path.rsplit("/", 1)[-1], seen)

    def _presence_of(self, name: str, seen: Seen) -> None:
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(self._apply_presence, name, seen)

    def _apply_presence(self, unit: str, seen: Seen) -> None:
        """In the loop: remember, wake the calls waiting on a lost unit, tell the server."""
        self.seen[unit] = seen
        if seen.present is False:
            self._lost[unit].set()
        else:
            self._lost[unit].clear()
        self._on_presence(unit, seen)

    def gone(self, unit: str) -> str:
        """Why ``unit`` cannot be called now ('' = it can)."""
        seen = self.seen[unit]
        return seen.describe(self.proxies[unit].path) if seen.present is False else ""

    async def call(self, unit: str, service: str, timeout: float, **fields: Any) -> Any:
        """Call a unit's service from the asyncio loop; :class:`Unavailable` when it does not
        answer in time, or at once when the unit is (or becomes) lost."""
        proxy = self.proxies[unit]
        client = proxy.client(service)
        lost = self._lost[unit]
        deadline = time.monotonic() + timeout
        while not client.service_is_ready():
            if lost.is_set():
                raise Unavailable(self.gone(unit))
            if time.monotonic() >= deadline:
                raise Unavailable(f"{proxy.path}/{service} is not available")
            await asyncio.sleep(0.05)
        answer = asyncio.ensure_future(asyncio.wrap_future(proxy.call(service, **fields)))
        went = asyncio.ensure_future(lost.wait())
        try:
            await asyncio.wait(
                (answer, went),
                timeout=max(0.1, deadline - time.monotonic()),
                return_when=asyncio.FIRST_COMPLETED,
            )
        finally:
            went.cancel()
        if answer.done():
            return answer.result()
        answer.cancel()
        if lost.is_set():
            raise Unavailable(self.gone(unit))
        raise Unavailable(f"{proxy.path}/{service} did not answer within {timeout:g} s")

    def stop(self) -> None:
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self.presence.destroy()
        if self.cell_presence is not None:
            self.cell_presence.destroy()
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


# -- method arguments ------------------------------------------------------------------------------
class BadArguments(Exception):
    def __init__(self, status: int, text: str, index: int | None = None) -> None:
        super().__init__(text)
        self.status = status
        self.index = index


def check_arguments(model: PackMLModel, method: MethodDef, args: Sequence[Any]) -> list[Any]:
    """The values of ``args`` (Variants) after checking them against the NodeSet's signature of
    ``method``: their number, each one's type and rank; BadArguments otherwise."""
    expected = method.arguments
    names = ", ".join(a.name for a in expected) or "no arguments"
    if len(args) < len(expected):
        raise BadArguments(S.BadArgumentsMissing, f"expected {names}")
    if len(args) > len(expected):
        raise BadArguments(S.BadTooManyArguments, f"expected {names}")
    values: list[Any] = []
    for i, (arg, spec) in enumerate(zip(args, expected, strict=True)):
        variant = arg if isinstance(arg, ua.Variant) else ua.Variant(arg)
        ns, ident = spec.data_type
        type_name = model.data_types.get(ident, "?") if ns else ua.VariantType(ident).name
        array = spec.value_rank > 0
        what = f"{spec.name}: expected {type_name}{'[]' if array else ''}"
        value = variant.Value
        if array and variant.VariantType == ua.VariantType.Null:
            values.append([])  # a null array: no elements
            continue
        if array != isinstance(value, list):
            raise BadArguments(S.BadTypeMismatch, what, i)
        items = value if array else [value]
        if ns:  # a structure of the PackML model
            if variant.VariantType != ua.VariantType.ExtensionObject or any(
                type(item).__name__ != type_name for item in items
            ):
                raise BadArguments(S.BadTypeMismatch, what, i)
        elif variant.VariantType != ua.VariantType(ident):
            raise BadArguments(S.BadTypeMismatch, f"{what}, not {variant.VariantType.name}", i)
        values.append(value)
    return values


def _unit_text(eu: Any) -> str:
    name = getattr(getattr(eu, "DisplayName", None), "Text", None)
    return name or ""


def descriptor_msg(d: Any) -> Any:
    from packml_interfaces.msg import Descriptor

    return Descriptor(
        id=int(d.ID), name=d.Name or "", unit=_unit_text(d.Unit), value=float(d.Value)
    )


def product_msg(p: Any) -> Any:
    from packml_interfaces.msg import Ingredient, Product

    return Product(
        product_id=int(p.ProductID),
        process_variables=[descriptor_msg(d) for d in p.ProcessVariables or []],
        ingredients=[
            Ingredient(
                ingredient_id=int(i.IngredientID),
                parameter=[descriptor_msg(d) for d in i.Parameter or []],
            )
            for i in p.Ingredients or []
        ],
    )


def max_mach_speed(config: OpcUaConfig, unit: UnitConfig) -> float | None:
    """The highest speed SetMachSpeed accepts for ``unit``: ``opcua.max_mach_speed`` (OPC UA may
    take less than the unit), else the unit's own limit (:func:`packml_ros2.core.limits.speed_limit`:
    ``max_mach_speed``, else ``mach_design_speed``), else none."""
    limit = config.max_mach_speed.get(unit.name)
    return speed_limit(unit) if limit is None else limit


# -- the methods of one unit -----------------------------------------------------------------------
Callback = Callable[..., Awaitable[ua.CallMethodResult]]
Steps = list[tuple[str, Mapping[str, Any]]]
#: A handler gets the checked argument values and returns (what, service steps) or a refusal.
Handler = Callable[[list[Any]], "tuple[str, Steps] | ua.CallMethodResult"]


class Methods:
    """The method callbacks of one unit object: path -> async callback(parent, *args)."""

    def __init__(
        self,
        unit: UnitConfig,
        config: OpcUaConfig,
        model: PackMLModel,
        ros: Callable[[], RosSide | None],
    ) -> None:
        self.unit = unit.name
        self.unit_config = unit
        self.config = config
        self.model = model
        self._ros = ros

    def callbacks(self) -> dict[str, Callback]:
        handlers: dict[str, Handler] = {}
        for machine in self.model.machines:
            for method in machine.methods:
                handlers[f"{machine.path}/{method.name}"] = self._state_command(method.name)
        handlers["SetUnitMode"] = self._set_unit_mode
        handlers["SetMachSpeed"] = self._set_mach_speed
        handlers["SetParameter"] = self._set_parameter
        handlers["SetProduct"] = self._set_product
        handlers["SetRecipe"] = self._set_recipe
        return {path: self._callback(path, handler) for path, handler in handlers.items()}

    def _callback(self, path: str, handler: Handler) -> Callback:
        folder = path.rpartition("/")[0]
        owner = ua.NodeId(
            f"{self.unit}.{folder.replace('/', '.')}" if folder else self.unit, INSTANCE_NS
        )
        method = EXTENSION_METHODS.get(path) or self.model.method(path)

        async def call(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
            if parent != owner:  # OPC UA Part 4: the method must be a component of the object
                return refuse(
                    S.BadMethodInvalid,
                    "INVALID_ARGUMENT",
                    f"{method.name} is not a method of {parent.to_string()}",
                )
            try:
                values = check_arguments(self.model, method, args)
            except BadArguments as exc:
                results = None
                if exc.index is not None:
                    results = [GOOD] * len(args)
                    results[exc.index] = exc.status
                status = S.BadInvalidArgument if exc.index is not None else exc.status
                return refuse(status, "INVALID_ARGUMENT", f"{method.name}: {exc}", results)
            outcome = handler(values)
            if isinstance(outcome, ua.CallMethodResult):
                return outcome
            return await self._invoke(*outcome)

        return call

    def executable(self) -> bool:
        """Whether the unit's methods can be executed now (the unit is not lost)."""
        ros = self._ros()
        return ros is not None and not ros.gone(self.unit)

    async def _invoke(self, what: str, steps: Steps) -> ua.CallMethodResult:
        """The one way a command or request goes from OPC UA to the unit."""
        allowed, user = may_call(self.config)
        if not allowed:
            return refuse(
                S.BadUserAccessDenied,
                "UNAUTHORIZED",
                f"{what} on {self.unit} refused: this session is read-only "
                "(log in with a user configured in the opcua: block)",
            )
        ros = self._ros()
        if ros is None:
            return refuse(S.BadNoCommunication, "UNIT_UNAVAILABLE", "the ROS side is not running")
        gone = ros.gone(self.unit)
        if gone:
            return refuse(S.BadNoCommunication, "UNIT_UNAVAILABLE", f"{what} refused: {gone}")
        source = command_source(user)
        for service, fields in steps:
            try:
                answer = await ros.call(
                    self.unit, service, self.config.call_timeout, source=source, **fields
                )
            except Unavailable as exc:
                return refuse(S.BadNoCommunication, "UNIT_UNAVAILABLE", f"{what} refused: {exc}")
            status = result_status(answer.accepted, answer.result)
            if status != GOOD:
                message = getattr(answer, "message", "") or f"{what} refused"
                return refuse(status, RESULT_NAMES.get(int(answer.result), "REFUSED"), message)
        return ua.CallMethodResult(StatusCode=ua.StatusCode(GOOD))

    def _state_command(self, name: str) -> Handler:
        command = next(c for c, m in COMMAND_METHODS.items() if m == name)

        def handle(values: list[Any]) -> tuple[str, Steps]:
            steps: Steps = []
            if values and values[0] and self._valid_now(command):
                # Start(Parameter[]): the parameters, then Start (not when Start would be refused:
                # a refused request changes nothing)
                parameter = [descriptor_msg(d) for d in values[0]]
                steps.append(("set_unit_parameters", {"parameter": parameter}))
            steps.append(("command", {"command": int(command)}))
            return name, steps

        return handle

    def _valid_now(self, command: Cmd) -> bool:
        ros = self._ros()
        status = ros.proxies[self.unit].status if ros is not None else None
        return status is not None and int(command) in status.commands_valid

    def _set_unit_mode(self, values: list[Any]) -> tuple[str, Steps]:
        (mode,) = values
        return f"SetUnitMode({mode})", [("set_mode", {"mode": mode})]

    def _set_mach_speed(self, values: list[Any]) -> tuple[str, Steps] | ua.CallMethodResult:
        (speed,) = values
        face = self.config.max_mach_speed.get(self.unit)  # the unit's rule, with this face's bound
        why = speed_refusal(speed, self.unit_config, face, "opcua.max_mach_speed")
        if why is not None:
            text = f"SetMachSpeed({speed:g}): {why}"
            return refuse(S.BadInvalidArgument, "INVALID_ARGUMENT", text, [S.BadOutOfRange])
        return "SetMachSpeed", [("set_mach_speed", {"mach_speed": float(speed)})]

    def _set_parameter(self, values: list[Any]) -> tuple[str, Steps]:
        parameter = [descriptor_msg(d) for d in values[0]]
        return "SetParameter", [("set_unit_parameters", {"parameter": parameter})]

    def _set_product(self, values: list[Any]) -> tuple[str, Steps]:
        product = [product_msg(p) for p in values[0]]
        return "SetProduct", [("set_product", {"product": product})]

    def _set_recipe(self, values: list[Any]) -> tuple[str, Steps] | ua.CallMethodResult:
        """SetRecipe(SelectedRecipe): the unit's ``set_recipe`` by ID; Good = the changeover was
        accepted as a request (it runs after the answer: Status/RecipeChangeInProcess, then
        RecipeCurrent or, when an EM refused, RecipeResult says why and the recipe stays)."""
        (recipe,) = values
        if recipe <= 0:
            text = f"SetRecipe({recipe}): SelectedRecipe is the ID of a recipe, 1 or more"
            return refuse(S.BadInvalidArgument, "INVALID_ARGUMENT", text, [S.BadOutOfRange])
        return f"SetRecipe({recipe})", [("set_recipe", {"recipe_id": recipe, "recipe_name": ""})]


class CellMethods(Methods):
    """The method callbacks of the cell object (:mod:`.cell`): the state commands and
    SetUnitMode go to the coordinator (``command``, ``set_mode``: every unit, in the cell's
    order, all or nothing); what a cell has no one value for is refused BadNotImplemented."""

    def _not_for_a_cell(self, what: str) -> ua.CallMethodResult:
        return refuse(
            S.BadNotImplemented,
            "NOT_SUPPORTED",
            f"{what} is not a cell command: call it on each unit (PackMLObjects/<unit>)",
        )

    def _state_command(self, name: str) -> Handler:
        plain = super()._state_command(name)

        def handle(values: list[Any]) -> tuple[str, Steps] | ua.CallMethodResult:
            if values and values[0]:  # Start(Parameter[]) with parameters
                return self._not_for_a_cell(f"{name} with parameters")
            return plain(values)

        return handle

    def _set_mach_speed(self, values: list[Any]) -> ua.CallMethodResult:
        return self._not_for_a_cell("SetMachSpeed")

    def _set_parameter(self, values: list[Any]) -> ua.CallMethodResult:
        return self._not_for_a_cell("SetParameter")

    def _set_product(self, values: list[Any]) -> ua.CallMethodResult:
        return self._not_for_a_cell("SetProduct")

    def _set_recipe(self, values: list[Any]) -> ua.CallMethodResult:
        return self._not_for_a_cell("SetRecipe")
