"""A unit's services and topics seen from a test process (or any tool): commands, and waits on
its status, transitions, admin data and alarms."""

from __future__ import annotations

from typing import Any

from packml_interfaces.msg import Admin, AlarmList, Status, TransitionEvent
from packml_interfaces.srv import Command
from std_srvs.srv import Trigger

from ..core import Cmd
from ..ros import interface
from .harness import Collector, RosHarness


class UnitClient:
    """Services and topics of one unit, seen from the test process."""

    def __init__(self, ros: RosHarness, cell: str, unit: str) -> None:
        self.ros = ros
        self.base = f"/{cell}/{unit}"

        def follow(name: str) -> Collector[Any]:  # the unit's output, as declared
            topic = interface.TOPIC[name]
            return ros.subscribe(topic.type, topic.path(self.base), topic.qos)

        self.status: Collector[Status] = follow("status")
        self.transitions: Collector[TransitionEvent] = follow("transitions")
        self.admin: Collector[Admin] = follow("admin")
        self.alarms: Collector[AlarmList] = follow("alarms")

    _since = 0  # status count at the last call: waits skip older statuses
    _transitions_since = 0  # transition count at the last call

    def ready(self, timeout: float = 15.0) -> None:
        self.ros.wait_for_service(Command, f"{self.base}/command", timeout)
        # (a status reader that stays deaf is replaced half way: Collector.wait_for)
        self.status.wait_for(lambda m: True, timeout, "any status")

    def forget(self) -> None:
        """Drop everything received so far (e.g. before restarting the unit)."""
        for collector in (self.status, self.transitions, self.admin, self.alarms):
            collector.clear()
        self._since = self._transitions_since = 0

    def call(self, srv_type: Any, name: str, timeout: float = 10.0, **fields: Any) -> Any:
        self._since = len(self.status)
        self._transitions_since = len(self.transitions)
        return self.ros.call(srv_type, f"{self.base}/{name}", srv_type.Request(**fields), timeout)

    def command(self, cmd: Cmd | int, source: str = "operator") -> Command.Response:
        return self.call(Command, "command", command=int(cmd), source=source)

    def trigger(self, name: str) -> Trigger.Response:
        return self.call(Trigger, name)

    def wait_state(self, state: str, timeout: float = 10.0) -> Status:
        """The unit reaches ``state`` at or after the last call made through this client."""
        return self.wait_status(lambda m: m.state_current_name == state, timeout, f"state {state}")

    def wait_entered(self, state: str, timeout: float = 10.0) -> TransitionEvent:
        """The unit entered ``state`` after the last call made through this client. For states the
        unit leaves on its own: ``status`` keeps only the newest message (depth 1), so a status of
        a short state can be overtaken before it is taken; every transition is kept (depth 100)."""
        return self.transitions.wait_for(
            lambda t: t.to_state_name == state,
            timeout,
            f"a transition into {state}",
            self._transitions_since,
        )

    def wait_status(self, predicate: Any, timeout: float = 10.0, what: str = "") -> Status:
        """A status for which ``predicate`` holds, from the last one before the last call on."""
        return self.status.wait_for(predicate, timeout, what, max(0, self._since - 1))
