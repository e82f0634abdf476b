"""Helpers for tests that run real nodes: a cell YAML per test (unique namespace), units and EMs
in-process or as separate processes, and a client for a unit's services and topics."""

from __future__ import annotations

import itertools
import os
import re
from pathlib import Path
from typing import Any

import yaml

from packml_ros2.core import Store, load_cell
from packml_ros2.core.alarms import Kind as AlarmKind
from packml_ros2.testing.processes import NodeProcess, Processes
from packml_ros2.testing.unit_client import UnitClient  # noqa: F401 (moved there, re-exported)

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
