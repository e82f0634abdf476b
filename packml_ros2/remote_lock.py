"""The remote lock of a unit node or PLC bridge as ROS sees it: the parameter
``remote_commands_enabled`` (read it with ``ros2 param get``; set at start with the cell file or
``--ros-args -p``) and the service ``<unit>/set_remote_commands``
(``packml_interfaces/srv/SetRemoteCommands``), the one way to switch it at run time: from a local
source only (:func:`packml_ros2.core.rules.lock_change_refusal`). ``ros2 param set`` names no
source and is refused with a sentence that points to the service.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from packml_interfaces.srv import SetRemoteCommands
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from .core.reasons import Reason
from .core.rules import lock_change_refusal
from .ros import interface

NAME = "remote_commands_enabled"


class RemoteLock:
    """``on_change(enabled)`` is called when the lock was switched (from the service)."""

    #: the service (:mod:`.ros.interface`) that switches it
    SERVICE = "set_remote_commands"

    def __init__(
        self,
        node: Node,
        unit: str,
        initial: bool,
        on_change: Callable[[bool], None],
        **service_kwargs: Any,
    ) -> None:
        self.node = node
        self.unit = unit
        self.on_change = on_change
        self._switching = False
        node.declare_parameter(
            NAME,
            initial,
            ParameterDescriptor(
                description="accept requests from remote sources (hmi:, opcua:, coordinator, "
                "remote:); switched only by set_remote_commands from a local source"
            ),
        )
        node.add_on_set_parameters_callback(self._validate)
        interface.create_service(node, self.SERVICE, self._serve, **service_kwargs)

    @property
    def enabled(self) -> bool:
        return bool(self.node.get_parameter(NAME).value)

    def _validate(self, params: list[Parameter[Any]]) -> SetParametersResult:
        for p in params:
            if p.name != NAME:
                continue
            if p.type_ != Parameter.Type.BOOL:
                return SetParametersResult(successful=False, reason=f"{NAME} must be a bool")
            if not self._switching:  # the parameter service names no source: not a local one
                return SetParametersResult(
                    successful=False,
                    reason=f"{NAME} is switched only from a local source: call "
                    f"{self.node.get_fully_qualified_name()}/set_remote_commands "
                    "(packml_interfaces/srv/SetRemoteCommands)",
                )
        return SetParametersResult(successful=True)

    def _serve(
        self, req: SetRemoteCommands.Request, resp: SetRemoteCommands.Response
    ) -> SetRemoteCommands.Response:
        source = req.source or "operator"
        refused = lock_change_refusal(source, self.unit)
        if refused is not None:
            resp.accepted, resp.result, resp.message = False, int(refused.reason), refused.message
            return resp
        word = "enabled" if req.enabled else "disabled"
        resp.accepted, resp.result = True, int(Reason.ACCEPTED)
        if self.enabled == req.enabled:
            resp.message = f"remote commands already {word} on {self.unit}"
            return resp
        self._switching = True
        try:
            self.node.set_parameters([Parameter(NAME, value=bool(req.enabled))])
        finally:
            self._switching = False
        self.on_change(bool(req.enabled))
        resp.message = f"remote commands {word} on {self.unit} by {source}"
        self.node.get_logger().info(resp.message)
        return resp
