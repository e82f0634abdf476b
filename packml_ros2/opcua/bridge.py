"""The ROS side of the OPC UA server, and the method handlers.

:class:`RosSide` runs an rclpy node (its own Context) in a thread: a
:class:`~packml_ros2.client.CellProxy` subscribes to every exposed unit's latched ``status``,
``admin`` topics (the proxy also subscribes ``alarms``; the Admin message carries the same lists)
and hands each status and admin message to the asyncio loop with ``call_soon_threadsafe`` (values
follow the topics: no polling). Service calls go the other way:
the proxy's concurrent future is awaited with ``asyncio.wrap_future``.

:class:`Methods` builds the method callbacks of one unit: each checks the caller
(:func:`.security.may_call`), calls the unit's service with source ``opcua:<user>`` (``opcua`` for
an anonymous session allowed to write) and answers Good, or a Bad status code with the unit's
message as the reason (:func:`.security.refuse`).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import Any

from asyncua import ua

from ..client import CellProxy, Unavailable
from .config import OpcUaConfig
from .mapping import GOOD, RESULT_NAMES, result_status
from .model import MACHINE_PATHS, MODE_ENUM, MethodDef, machine_methods
from .security import may_call, refuse

#: The unit services the methods use (clients are created before spinning starts).
USED_SERVICES = ("command", "set_mode", "set_mach_speed", "set_unit_parameters", "set_product")
S = ua.StatusCodes


class RosSide:
    """An rclpy node in a thread of its own, feeding ``on_message(unit, topic, msg)`` into ``loop``."""

    def __init__(
        self,
        cell: str,
        units: Sequence[str],
        loop: asyncio.AbstractEventLoop,
        on_message: Callable[[str, str, Any], None],
    ) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.loop = loop
        self._on_message = on_message
        self.context = Context()
        rclpy.init(
            context=self.context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO
        )
        self.node = Node("packml_opcua", namespace=f"/{cell}", context=self.context)
        self.cell = CellProxy(self.node, cell, units, on_change=self._changed)
        for proxy in self.cell.units.values():
            for service in USED_SERVICES:
                proxy.client(service)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="packml-opcua-ros", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _spin(self) -> None:
        while not self._stopping.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def _changed(self, path: str, topic: str, msg: Any) -> None:
        if topic not in ("status", "admin"):
            return
        unit = path.rsplit("/", 1)[-1]
        with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
            self.loop.call_soon_threadsafe(self._on_message, unit, topic, msg)

    async def call(self, unit: str, service: str, timeout: float, **fields: Any) -> Any:
        """Call a unit's service from the asyncio loop; Unavailable when it does not answer."""
        proxy = self.cell.units[unit]
        client = proxy.client(service)
        deadline = time.monotonic() + timeout
        while not client.service_is_ready():
            if time.monotonic() >= deadline:
                raise Unavailable(f"{proxy.path}/{service} is not available")
            await asyncio.sleep(0.05)
        future = proxy.call(service, **fields)
        try:
            return await asyncio.wait_for(
                asyncio.wrap_future(future), max(0.1, deadline - time.monotonic())
            )
        except TimeoutError:
            raise Unavailable(
                f"{proxy.path}/{service} did not answer within {timeout:g} s"
            ) from None

    def stop(self) -> None:
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


# -- method arguments -------------------------------------------------------------------------------------
class BadArguments(Exception):
    def __init__(self, status: int, text: str) -> None:
        super().__init__(text)
        self.status = status


def _args(args: Sequence[Any], names: Sequence[str], required: int) -> list[Any]:
    values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
    if len(values) < required:
        raise BadArguments(S.BadArgumentsMissing, f"expected {', '.join(names)}")
    if len(values) > len(names):
        raise BadArguments(S.BadTooManyArguments, f"expected only {', '.join(names) or 'nothing'}")
    return values + [None] * (len(names) - len(values))


def _struct_list(value: Any, type_name: str, what: str) -> list[Any]:
    if value is None:
        return []
    items = value if isinstance(value, list) else [value]
    for item in items:
        if type(item).__name__ != type_name:
            raise BadArguments(S.BadTypeMismatch, f"{what}: expected {type_name}[]")
    return items


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


# -- the methods of one unit ------------------------------------------------------------------------------
Callback = Callable[..., Awaitable[ua.CallMethodResult]]


class Methods:
    """The method callbacks of one unit object: path -> async callback(parent, *args)."""

    def __init__(
        self,
        unit: str,
        config: OpcUaConfig,
        ros: Callable[[], RosSide | None],
        mode_enum: Callable[[], ua.NodeId | None],
        packml_ns: Callable[[], int],
    ) -> None:
        self.unit = unit
        self.config = config
        self._ros = ros
        self._mode_enum = mode_enum
        self._packml_ns = packml_ns

    def callbacks(self) -> dict[str, Callback]:
        out: dict[str, Callback] = {}
        for machine, method in machine_methods():
            out[f"{MACHINE_PATHS[machine.name]}/{method.name}"] = self._state_command(method)
        out["SetUnitMode"] = self._set_unit_mode
        out["SetMachSpeed"] = self._set_mach_speed
        out["SetParameter"] = self._set_parameter
        out["SetProduct"] = self._set_product
        return out

    async def _invoke(
        self, what: str, steps: Sequence[tuple[str, Mapping[str, Any]]]
    ) -> ua.CallMethodResult:
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
        source = f"opcua:{user}" if user else "opcua"
        for service, fields in steps:
            try:
                answer = await ros.call(
                    self.unit, service, self.config.call_timeout, source=source, **fields
                )
            except Unavailable as exc:
                return refuse(S.BadNoCommunication, "UNIT_UNAVAILABLE", str(exc))
            status = result_status(answer.accepted, answer.result)
            if status != GOOD:
                message = getattr(answer, "message", "") or f"{what} refused"
                return refuse(status, RESULT_NAMES.get(int(answer.result), "REFUSED"), message)
        return ua.CallMethodResult(StatusCode=ua.StatusCode(GOOD))

    def _state_command(self, method: MethodDef) -> Callback:
        async def call(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
            steps: list[tuple[str, Mapping[str, Any]]] = []
            try:
                if method.args:  # Start(Parameter[]): set the parameters, then start
                    (params,) = _args(args, [a[0] for a in method.args], 0)
                    items = _struct_list(params, "PackMLDescriptorDataType", "Parameter")
                    if items:
                        steps.append(
                            (
                                "set_unit_parameters",
                                {"parameter": [descriptor_msg(d) for d in items]},
                            )
                        )
                else:
                    _args(args, [], 0)
            except BadArguments as exc:
                return refuse(exc.status, "INVALID_ARGUMENT", f"{method.name}: {exc}")
            steps.append(("command", {"command": method.command}))
            return await self._invoke(method.name, steps)

        return call

    async def _set_unit_mode(self, parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
        try:
            selection, mode = _args(args, ["ModeSelection", "RequestedMode"], 2)
            if not isinstance(mode, int) or isinstance(mode, bool):
                raise BadArguments(S.BadTypeMismatch, "RequestedMode: expected an Int32")
            enum = self._mode_enum()
            accepted = {enum, ua.NodeId(MODE_ENUM, self._packml_ns())}
            if (
                isinstance(selection, ua.NodeId)
                and not selection.is_null()
                and selection not in accepted
            ):
                expected = enum.to_string() if enum is not None else "?"
                raise BadArguments(
                    S.BadInvalidArgument,
                    f"ModeSelection: expected {expected} (the value of Status/UnitSupportedModes)",
                )
        except BadArguments as exc:
            return refuse(exc.status, "INVALID_ARGUMENT", f"SetUnitMode: {exc}")
        return await self._invoke(f"SetUnitMode({mode})", [("set_mode", {"mode": mode})])

    async def _set_mach_speed(self, parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
        try:
            (speed,) = _args(args, ["RequestedMachineSpeed"], 1)
            if not isinstance(speed, int | float) or isinstance(speed, bool):
                raise BadArguments(S.BadTypeMismatch, "RequestedMachineSpeed: expected a Float")
        except BadArguments as exc:
            return refuse(exc.status, "INVALID_ARGUMENT", f"SetMachSpeed: {exc}")
        return await self._invoke(
            "SetMachSpeed", [("set_mach_speed", {"mach_speed": float(speed)})]
        )

    async def _set_parameter(self, parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
        try:
            (params,) = _args(args, ["Parameter"], 1)
            items = _struct_list(params, "PackMLDescriptorDataType", "Parameter")
        except BadArguments as exc:
            return refuse(exc.status, "INVALID_ARGUMENT", f"SetParameter: {exc}")
        parameter = [descriptor_msg(d) for d in items]
        return await self._invoke(
            "SetParameter", [("set_unit_parameters", {"parameter": parameter})]
        )

    async def _set_product(self, parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
        try:
            (products,) = _args(args, ["Product"], 1)
            items = _struct_list(products, "PackMLProductDataType", "Product")
        except BadArguments as exc:
            return refuse(exc.status, "INVALID_ARGUMENT", f"SetProduct: {exc}")
        product = [product_msg(p) for p in items]
        return await self._invoke("SetProduct", [("set_product", {"product": product})])
