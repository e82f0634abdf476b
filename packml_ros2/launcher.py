"""Start a whole PackML cell from its YAML file: units, EMs (each as its entry says it runs:
packml_ros2.em_launch) and the coordinator, in one process (a multi-threaded executor) or one
process per node (``processes=True``). It waits until every unit and the coordinator answer and
every EM is online at its unit (so the first ``reset`` is not refused for a missing EM; an
external EM is waited for up to its timeout, naming it meanwhile), prints what to try, and stops
everything on Ctrl-C.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import rclpy
from packml_interfaces.msg import Status
from packml_interfaces.srv import Command
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from . import dds_profile, run
from .children import spawn
from .core import CellConfig, ConfigError, load_cell
from .em_launch import EmRun, groups, host_arguments, program_env, resolve
from .ros import interface
from .sim_em import SimConfig, parse_sim

READY_TIMEOUT = 60.0
#: Seconds between the launcher's notes on the external EMs it still waits for.
WAITING_NOTE_EVERY = 5.0


@dataclass
class Plan:
    """What a cell file starts, validated before anything starts."""

    file: Path
    cell: CellConfig
    source: str
    sims: dict[tuple[str, str], SimConfig] = field(default_factory=dict)
    #: every EM and how it runs (packml_ros2.em_launch)
    ems: list[EmRun] = field(default_factory=list)
    simulate: bool = False  # --sim: every EM simulated

    @property
    def node_count(self) -> int:
        started = sum(1 for r in self.ems if r.kind != "external")
        return len(self.cell.units) + started + (1 if self.cell.coordinator.enabled else 0)


def plan(file: str | os.PathLike[str], simulate: bool = False) -> Plan:
    """Load and validate the cell, including how every EM runs and every ``sim:`` block
    (ConfigError lists all). ``simulate``: every EM simulated (a dry run of a real cell)."""
    path = Path(file)
    cell = load_cell(path)
    p = Plan(path, cell, path.read_text(encoding="utf-8"), simulate=simulate)
    p.ems, problems = resolve(cell, path, simulate)
    problems += dds_profile.missing(cell)  # dds.interfaces: this host has one at least
    for uname, unit in cell.units.items():
        if unit.plc is not None:
            problems += _plc_problems(cell, uname)
        for em in unit.equipment_modules:
            if not simulate and em.runs != "sim":
                continue
            key = f"units.{uname}.equipment_modules.{em.name}.sim"
            try:
                p.sims[(uname, em.name)] = parse_sim(em.sim, key, str(path), unit.em_lease)
            except ConfigError as exc:
                problems += exc.problems
    if problems:
        raise ConfigError(str(path), problems)
    return p


def how_ems_run(p: Plan) -> str:
    """``packml launch --check``: one line per EM."""
    width = max((len(r.name) for r in p.ems), default=0)
    return "\n".join(f"  {r.name:<{width}}  {r.describe()}" for r in p.ems)


def _plc_problems(cell: CellConfig, unit: str) -> list[tuple[str, str]]:
    """What is wrong with the ``plc:`` block of ``unit`` (a PLC unit: :mod:`packml_ros2.plc`)."""
    from .plc.config import parse_plc

    try:
        parse_plc(cell, unit)
    except ConfigError as exc:
        return exc.problems
    return []


# -- readiness and the summary ---------------------------------------------------------------------
def wait_ready(
    node: Node,
    p: Plan,
    timeout: float = READY_TIMEOUT,
    alive: Callable[[], bool] = lambda: True,
    spin: Callable[[float], None] = time.sleep,
    note: Callable[[str], None] = lambda _: None,
) -> list[str]:
    """Wait until every unit's and the coordinator's command service answers and every EM is
    online in its unit's status (an external one: up to its own timeout; ``note`` hears every
    :data:`WAITING_NOTE_EVERY` s which external EMs are still awaited); returns what is still
    missing (empty: all ready). ``spin(seconds)`` lets ``node``'s subscriptions run (default:
    another thread spins it)."""
    cell = p.cell.cell
    services = [f"/{cell}/{u}/command" for u in p.cell.units]
    if p.cell.coordinator.enabled:
        services.append(f"/{cell}/coordinator/command")
    clients: dict[str, Any] = {name: node.create_client(Command, name) for name in services}
    latest: dict[str, Status] = {}
    status = interface.TOPIC["status"]
    subscriptions = [
        node.create_subscription(
            status.type,
            status.path(f"/{cell}/{u}"),
            lambda m, u=u: latest.__setitem__(u, m),
            status.qos,
        )
        for u in {r.unit for r in p.ems}
    ]
    start = time.monotonic()
    deadline = start + timeout
    silent = list(services)
    while silent and time.monotonic() < deadline and alive():
        silent = [name for name in silent if not clients[name].service_is_ready()]
        if silent:
            clients[silent[0]].wait_for_service(timeout_sec=0.2)
    missing = silent
    noted = start - WAITING_NOTE_EVERY  # the first note at once, then every few seconds
    while not silent and alive():
        now = time.monotonic()
        offline = [r for r in p.ems if not _online(latest.get(r.unit), r.em)]
        late = [
            r for r in offline if now >= (start + r.timeout if r.kind == "external" else deadline)
        ]
        awaited = [r for r in offline if r.kind == "external" and r not in late]
        if not offline or len(late) == len(offline):
            missing = [f"EM {r.name} ({_why_missing(r)})" for r in late]
            break
        if awaited and now - noted >= WAITING_NOTE_EVERY:
            noted = now
            note(
                "waiting for external EM(s) "
                + ", ".join(
                    f"{r.name} ({max(0.0, start + r.timeout - now):.0f} s left)" for r in awaited
                )
            )
        spin(0.05)
    for client in clients.values():
        node.destroy_client(client)
    for subscription in subscriptions:
        node.destroy_subscription(subscription)
    return missing


def _why_missing(r: EmRun) -> str:
    if r.kind == "external":
        return (
            f"external, not online after {r.timeout:g} s: start it where it runs; the unit "
            "refuses Reset and Start until it is online"
        )
    return "offline"


def _online(status: Status | None, em: str) -> bool:
    return status is not None and any(e.name == em and e.online for e in status.equipment_modules)


def summary(p: Plan, mode: str) -> str:
    """The ready message: what runs, and the exact lines to try."""
    cell = p.cell.cell
    ems = sum(len(u.equipment_modules) for u in p.cell.units.values())
    first = next(iter(p.cell.units))
    faults = [(u, em, f) for (u, em), sim in p.sims.items() for f in sim.faults]

    def row(command: str, note: str = "") -> str:
        return f"  {command:<48} # {note}" if note else f"  {command}"

    lines = [
        f"PackML cell {cell} is up ({mode}): {len(p.cell.units)} unit(s), {ems} equipment module(s)"
        + (", coordinator" if p.cell.coordinator.enabled else ""),
        "",
        "In another terminal (. .venv/bin/activate first, or use .venv/bin/packml):",
        row("packml status", "every unit: state, mode, EMs, alarms, counts"),
        row("packml watch", "a live view, redrawn on every change"),
    ]
    if p.cell.coordinator.enabled:
        lines.append(row(f"packml cmd {cell} reset", "the whole cell, in the configured order"))
        lines.append(row(f"packml cmd {cell} start"))
    lines.append(row(f"packml cmd {first} hold", "one unit: reset start stop hold unhold ..."))
    lines.append(row(f"packml mode {first} maintenance", "mode changes: in Stopped, Idle, Aborted"))
    for u, em, f in faults[:3]:
        lines.append(row(f"packml fault {u}/{em} {f} on", "a simulated fault; off clears it"))
    lines += [
        row("packml alarms", "then: packml alarms ack; packml cmd <unit> reset"),
        "",
        "With the ROS 2 command line:",
        row(f"ros2 service call /{cell}/{first}/start std_srvs/srv/Trigger"),
        row(f"ros2 topic echo /{cell}/{first}/status"),
        "",
        "Ctrl-C stops the cell.",
    ]
    return "\n".join(lines)


# -- one process -----------------------------------------------------------------------------------
def build_nodes(p: Plan, **node_kwargs: Any) -> list[Node]:
    """Every node of the cell, in start order: units first, then EMs, then the coordinator."""
    from .em_launch import build
    from .sim_em import SimulatedEm
    from .unit_node import UnitNode

    lease = p.cell.coordinator.unit_lease
    nodes: list[Node] = []
    for u in p.cell.units.values():
        if u.plc is not None:  # a PLC unit: its bridge (packml_ros2.plc)
            from .plc.node import make_node

            nodes.append(make_node(p.cell, u.name, p.source, **node_kwargs))
        else:
            nodes.append(UnitNode(u, source=p.source, unit_lease=lease, **node_kwargs))
    for r in p.ems:
        if r.kind != "class":
            continue  # a program runs as its own process (start_programs); an external one elsewhere
        sim = p.sims.get((r.unit, r.em))
        nodes.append(
            SimulatedEm(r.em, r.unit, p.cell.cell, sim, **node_kwargs)
            if sim is not None
            else build(r, p.cell, p.file, **node_kwargs)
        )
    if p.cell.coordinator.enabled:
        from .coordinator_node import CoordinatorNode

        nodes.append(CoordinatorNode(p.cell, **node_kwargs))
    return nodes


def _interfaces(p: Plan, note: Callable[[str], None]) -> None:
    """The cell's ``dds.interfaces``: a Fast DDS profile for this process and its children."""
    profile = dds_profile.apply(p.cell)
    if profile is not None:
        note(
            f"DDS on {', '.join(i for i in p.cell.dds_interfaces if dds_profile.on_this_host(i))}"
            f", 127.0.0.1 and shared memory only (dds.interfaces: {profile})"
        )


def launch_in_process(p: Plan, threads: int = 0, ready: Callable[[str], None] = print) -> int:
    _interfaces(p, ready)
    run.default_environment()
    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.ALL)
    run.catch_stop_signals()
    try:
        nodes = build_nodes(p)
    except BaseException:  # StoreError: an admin store cannot be opened
        rclpy.try_shutdown()
        raise
    programs = start_programs(p)

    def announce() -> None:
        # The probe has its own executor and is gone once the cell is up: the ROS graph shows
        # the cell's nodes only.
        probe = Node("packml_launch_probe")
        executor = SingleThreadedExecutor()
        executor.add_node(probe)
        try:
            missing = wait_ready(
                probe,
                p,
                alive=rclpy.ok,
                spin=lambda s: executor.spin_once(timeout_sec=s),
                note=ready,
            )
        finally:
            executor.shutdown(timeout_sec=1)
            probe.destroy_node()
        if rclpy.ok():
            ready(
                summary(p, f"{p.node_count} nodes in one process")
                if not missing
                else f"not answering: {', '.join(missing)}"
            )

    threading.Thread(target=announce, daemon=True).start()

    def shutdown() -> None:
        for node in nodes:
            close = getattr(node, "close", None)
            if close is not None:
                close()
        _stop_children(programs)

    # Units and EMs never block in a callback: one thread spins them all (idle, they cost
    # nothing). The coordinator's and a PLC bridge's service handlers wait for other nodes: they
    # get a multi-threaded executor of their own. ``threads`` > 1: one such executor for all.
    if threads > 1:
        return run.spin(nodes, threads=threads, on_shutdown=shutdown)
    from .equipment_module import EquipmentModule
    from .sim_em import SimulatedEm
    from .unit_node import UnitNode

    # (an integrator's EM may wait in a callback: it is not light)
    light = [
        n for n in nodes if isinstance(n, (UnitNode, SimulatedEm)) or type(n) is EquipmentModule
    ]
    blocking = [n for n in nodes if n not in light]
    return run.spin(light, on_shutdown=shutdown, blocking=blocking)


# -- one process per node --------------------------------------------------------------------------
@dataclass(frozen=True)
class NodeSpec:
    """One node of a cell as an executable of this package (setup.py entry points)."""

    name: str
    executable: str  # unit_node | plc_bridge | em_node | coordinator ("": a program, argv)
    module: str
    arguments: tuple[str, ...]
    argv: tuple[str, ...] = ()  # a program EM (run: ...): its whole command
    env: tuple[tuple[str, str], ...] = ()  # set for it besides the launcher's environment


def node_specs(p: Plan) -> list[NodeSpec]:
    """Every node of the cell: units, EMs, the coordinator. The launch file (launch/
    cell.launch.py) and ``--processes`` both start exactly these."""
    f = str(p.file)
    out = [
        NodeSpec(f"plc {u}", "plc_bridge", "packml_ros2.plc.node", (f, u))
        if unit.plc is not None
        else NodeSpec(f"unit {u}", "unit_node", "packml_ros2.unit_node", (f, u))
        for u, unit in p.cell.units.items()
    ]
    for group in groups(p.ems):
        label = " ".join(r.name for r in group)
        out.append(
            NodeSpec(
                f"em {label}", "em_node", "packml_ros2.sim_em", host_arguments(group, f, p.simulate)
            )
        )
    out += [
        NodeSpec(f"em {r.name}", "", "", (), r.argv, tuple(program_env(r, p.cell, f).items()))
        for r in p.ems
        if r.kind == "program"
    ]
    if p.cell.coordinator.enabled:
        out.append(NodeSpec("coordinator", "coordinator", "packml_ros2.coordinator_node", (f,)))
    return out


def argv_of(spec: NodeSpec) -> list[str]:
    """The command of a node process, with this interpreter (a program EM: its own command)."""
    return list(spec.argv) if spec.argv else [sys.executable, "-m", spec.module, *spec.arguments]


def commands(p: Plan) -> list[tuple[str, list[str]]]:
    """(name, argv) of every node process, with this interpreter."""
    return [(s.name, argv_of(s)) for s in node_specs(p)]


def _popen(spec: NodeSpec, out: Any = None) -> subprocess.Popen[bytes]:
    # Own process group: Ctrl-C reaches the launcher only, which stops the children in order.
    env = {**os.environ, **dict(spec.env)} if spec.env else None
    # (children.spawn: a launcher killed outright takes its nodes with it)
    return spawn(argv_of(spec), stdout=out, stderr=subprocess.STDOUT if out else None, env=env)


def start_programs(p: Plan) -> list[tuple[str, subprocess.Popen[bytes]]]:
    """One-process mode: the EMs that are programs (``run:`` a program or function) still run
    as processes of their own."""
    return [(s.name, _popen(s)) for s in node_specs(p) if s.argv]


def launch_processes(
    p: Plan, ready: Callable[[str], None] = print, log_dir: Path | None = None
) -> int:
    _interfaces(p, ready)
    run.default_environment()
    children: list[tuple[str, subprocess.Popen[bytes]]] = []
    stopping = threading.Event()

    def on_signal(signum: int, _: Any) -> None:
        stopping.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    logs = ExitStack()
    try:
        for spec in node_specs(p):
            name = spec.name
            out = (
                logs.enter_context(
                    open(log_dir / f"{name.replace(' ', '_').replace('/', '_')}.log", "ab")  # noqa: SIM115
                )
                if log_dir
                else None
            )
            children.append((name, _popen(spec, out)))
        rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        probe = Node("packml_launch_probe")
        missing = wait_ready(
            probe,
            p,
            alive=lambda: not stopping.is_set() and all(c.poll() is None for _, c in children),
            spin=lambda seconds: rclpy.spin_once(probe, timeout_sec=seconds),
            note=ready,
        )
        probe.destroy_node()
        rclpy.try_shutdown()
        dead = [name for name, c in children if c.poll() is not None]
        if dead:
            ready(f"packml launch: {', '.join(dead)} exited during start-up; stopping the cell")
            stopping.set()
        elif not stopping.is_set():
            ready(
                summary(p, f"{len(children)} processes")
                if not missing
                else f"not answering: {', '.join(missing)}"
            )
        while not stopping.wait(0.2):
            for name, c in children:
                if c.poll() is not None and c.returncode not in (0, -signal.SIGINT):
                    print(f"packml launch: {name} exited with {c.returncode}", file=sys.stderr)
                    children.remove((name, c))
                    break
        return _stop_children(children)
    finally:
        logs.close()
        for s, handler in previous.items():
            signal.signal(s, handler)


def _stop_children(
    children: Sequence[tuple[str, subprocess.Popen[bytes]]], timeout: float = 15.0
) -> int:
    """SIGINT to everyone at once, in start order (units first, as ``ros2 launch`` does: a unit
    that stops with its EMs records no lost EM), then wait; 0 when every child exited cleanly.
    ``timeout``: SIGKILL after it, like ``ros2 launch`` (5 s to SIGTERM, 10 more to SIGKILL); a
    node whose exit is stuck ends itself before, with the stacks of its threads
    (run.TEARDOWN_LIMIT + run.HELD_GIL_GRACE after the stop)."""
    for _, c in children:
        if c.poll() is None:
            c.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout
    code = 0
    for name, c in children:
        try:
            rc = c.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            c.kill()
            rc = c.wait()
            print(f"packml launch: {name} did not stop in time; killed", file=sys.stderr)
        if rc not in (0, -signal.SIGINT):
            code = 1
    return code
