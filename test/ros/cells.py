"""Helpers for tests that run real nodes: a cell YAML per test (unique namespace), units and EMs
in-process or as separate processes, and a client for a unit's services and topics."""

from __future__ import annotations

import itertools
import os
import re
from pathlib import Path
from typing import Any

import yaml
from packml_interfaces.msg import Admin, AlarmList, Status, TransitionEvent
from packml_interfaces.srv import Command
from std_srvs.srv import Trigger

from packml_ros2 import qos
from packml_ros2.core import Cmd, Store, load_cell
from packml_ros2.core.alarms import Kind as AlarmKind
from packml_ros2.testing.harness import Collector, RosHarness
from packml_ros2.testing.processes import NodeProcess, Processes

_counter = itertools.count()


def write_cell(
    tmp_path: Path, units: dict[str, Any], coordinator: dict[str, Any] | None = None
) -> tuple[Path, str]:
    """A cell file with a namespace unique to this test; persistence goes under tmp_path."""
    cell = f"t{os.getpid()}_{next(_counter)}"
    for u in units.values():
        u.setdefault("persistence", {"path": str(tmp_path / "{unit}.sqlite3")})
    doc: dict[str, Any] = {"cell": cell, "units": units}
    if coordinator is not None:
        doc["coordinator"] = coordinator
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path, cell


class UnitClient:
    """Services and topics of one unit, seen from the test process."""

    def __init__(self, ros: RosHarness, cell: str, unit: str) -> None:
        self.ros = ros
        self.base = f"/{cell}/{unit}"
        self.status: Collector[Status] = ros.subscribe(Status, f"{self.base}/status", qos.STATUS)
        self.transitions: Collector[TransitionEvent] = ros.subscribe(
            TransitionEvent, f"{self.base}/transitions", qos.TRANSITIONS
        )
        self.admin: Collector[Admin] = ros.subscribe(Admin, f"{self.base}/admin", qos.ADMIN)
        self.alarms: Collector[AlarmList] = ros.subscribe(
            AlarmList, f"{self.base}/alarms", qos.ALARMS
        )

    _since = 0  # status count at the last call: waits skip older statuses
    _transitions_since = 0  # transition count at the last call

    def ready(self, timeout: float = 15.0) -> None:
        self.ros.wait_for_service(Command, f"{self.base}/command", timeout)
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
            lambda t: t.to_state_name == state, timeout, f"a transition into {state}",
            self._transitions_since,
        )  # fmt: skip

    def wait_status(self, predicate: Any, timeout: float = 10.0, what: str = "") -> Status:
        """A status for which ``predicate`` holds, from the last one before the last call on."""
        return self.status.wait_for(predicate, timeout, what, max(0, self._since - 1))


def start_unit_process(
    processes: Processes, cell_file: Path, unit: str, *ros_args: str
) -> NodeProcess:
    args = [str(cell_file), unit]
    if ros_args:
        args += ["--ros-args", *ros_args]
    return processes.module(f"unit_{unit}", "packml_ros2.unit_node", *args)


def start_em_process(processes: Processes, cell_file: Path, unit: str, em: str) -> NodeProcess:
    return processes.module(f"em_{unit}_{em}", "packml_ros2.sim_em", str(cell_file), unit, em)


def unit_config_of(cell_file: Path, unit: str) -> Any:
    return load_cell(cell_file).units[unit]


# -- a cell's shutdown ------------------------------------------------------------------------------
#: What a terminal may show after Ctrl-C: the nodes' goodbye lines (a unit or the coordinator
#: "shut down (SIGINT)", an EM "left unit ... (SIGINT)") and, under ros2 launch, launch's own
#: lines about stopping its processes.
GOODBYE = re.compile(
    r"shut down \(SIG(INT|TERM)\)|EM \S+ left unit \S+ \(SIG(INT|TERM)\)|\[launch\]|"
    r"sending signal 'SIG(INT|TERM)'|process has finished cleanly|^\s*$"
)


def shutdown_noise(output: str) -> list[str]:
    """The lines of ``output`` (a terminal after Ctrl-C) that are not goodbye lines."""
    return [line for line in output.splitlines() if not GOODBYE.search(line)]


def saved_admin(path: Path, unit: str) -> dict[str, Any]:
    """The admin data ``unit`` saved in ``path`` (the store the next start restores)."""
    store = Store(path, unit)
    try:
        document = store.load()
    finally:
        store.close()
    assert document is not None, f"{unit}: nothing saved in {path}"
    return document


def saved_faults(document: dict[str, Any], since: float = 0.0) -> list[str]:
    """Faults in saved admin data: alarms or warnings in the history (raised at or after
    ``since``, wall-clock seconds), a StopReason that was one."""
    events = (AlarmKind.EVENT, AlarmKind.COMMAND)
    faults = [
        f"history: {e['id']} {e['message']}"
        for e in document["alarms"]["history"]
        if e["kind"] not in events and e["time"] >= since
    ]
    stop = document.get("stop_reason")
    if stop and stop["kind"] not in events:
        faults.append(f"stop reason: {stop['id']} {stop['message']}")
    return faults
