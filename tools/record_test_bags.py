#!/usr/bin/env python3
"""Record the regression bags of test/bags/ from real nodes (unit and simulated EM processes,
real DDS, the packml recorder), one scenario each, then check that each replays.

    .venv/bin/python tools/record_test_bags.py [scenario ...] [--out test/bags]

The cell is test/bags/cell.yaml (the demo cell with quicker simulated EMs). Every scenario starts
fresh processes on a ROS domain of its own; the recorder starts before the unit (except
hold_unhold, which joins late, after a restart with restored admin data) and stops when the
scenario is done. independent_writer.mcap is normal_production rewritten by the ``mcap`` and
``mcap-ros2-support`` packages (their own CDR encoder, no rosbag2 metadata).
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from packml_ros2.testing.environment import allocate_domain, localhost_environment  # noqa: E402

localhost_environment()
os.environ["ROS_DOMAIN_ID"] = str(allocate_domain())

import rclpy  # noqa: E402
from packml_interfaces.msg import Admin, Status  # noqa: E402
from packml_interfaces.srv import (  # noqa: E402
    AckAlarms,
    Command,
    ResetCounters,
    SetEmActive,
    SetMode,
)
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from std_srvs.srv import SetBool, Trigger  # noqa: E402

from packml_ros2 import qos  # noqa: E402
from packml_ros2.bag.record import Recorder, run_recorder  # noqa: E402
from packml_ros2.bag.replay import replay  # noqa: E402
from packml_ros2.core import load_cell  # noqa: E402
from packml_ros2.testing.harness import Collector, RosHarness  # noqa: E402
from packml_ros2.testing.processes import NodeProcess, Processes  # noqa: E402

CELL_FILE = ROOT / "test" / "bags" / "cell.yaml"
CELL = load_cell(CELL_FILE)


class Scenario:
    """Processes of one unit (its EMs), a recorder, and a client to drive them."""

    def __init__(self, work: Path, unit: str) -> None:
        self.work = work
        self.unit = unit
        self.base = f"/{CELL.cell}/{unit}"
        self.procs = Processes(work)
        self.ems: dict[str, NodeProcess] = {}
        self.ros = RosHarness(int(os.environ["ROS_DOMAIN_ID"]))
        self.status: Collector[Status] = self.ros.subscribe(
            Status, f"{self.base}/status", qos.STATUS
        )
        self.admin: Collector[Admin] = self.ros.subscribe(Admin, f"{self.base}/admin", qos.ADMIN)
        self.recorder: Recorder | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.unit_proc: NodeProcess | None = None

    # -- processes ----------------------------------------------------------------------------------
    def start_unit(self) -> None:
        store = self.work / f"{self.unit}.sqlite3"
        self.unit_proc = self.procs.module(
            f"unit_{self.unit}_{time.monotonic_ns()}", "packml_ros2.unit_node", str(CELL_FILE),
            self.unit, "--ros-args", "-p", f"persistence_path:={store}",
        )  # fmt: skip

    def stop_unit(self) -> None:
        assert self.unit_proc is not None
        self.unit_proc.stop()
        self.status.clear()
        self.admin.clear()

    def start_em(self, em: str) -> None:
        self.ems[em] = self.procs.module(
            f"em_{em}_{time.monotonic_ns()}", "packml_ros2.sim_em", str(CELL_FILE), self.unit, em
        )

    def start_ems(self) -> None:
        for em in CELL.units[self.unit].equipment_modules:
            self.start_em(em.name)

    def kill_em(self, em: str) -> None:
        self.ems[em].kill()

    def freeze_em(self, em: str, frozen: bool = True) -> None:
        """SIGSTOP (a hung EM: alive to the OS, silent to the unit) or SIGCONT."""
        os.kill(self.ems[em].pid, signal.SIGSTOP if frozen else signal.SIGCONT)

    # -- recording --------------------------------------------------------------------------------------
    def record(self, path: Path, storage: str = "mcap") -> None:
        context = Context()
        rclpy.init(context=context, domain_id=int(os.environ["ROS_DOMAIN_ID"]))
        self.recorder = Recorder(path, [self.base], storage=storage, context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(self.recorder.node)

        def spin() -> None:
            assert self.recorder is not None
            run_recorder(self.recorder, executor, self._stop.is_set)
            executor.shutdown()
            rclpy.try_shutdown(context=context)

        self._thread = threading.Thread(target=spin, daemon=True)
        self._thread.start()

    def recorder_ready(self) -> None:
        assert self.recorder is not None
        wait(self.recorder.ready, "the recorder to get the unit's status")

    def finish(self) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join(10)
        self.ros.close()
        print(self.procs.close() or "", end="")

    # -- driving ------------------------------------------------------------------------------------------
    def last(self) -> Status | None:
        return self.status.messages[-1] if len(self.status) else None

    def wait_state(self, state: str, timeout: float = 15.0) -> None:
        wait(lambda: (s := self.last()) is not None and s.state_current_name == state,
             f"{self.unit} in {state}", timeout)  # fmt: skip

    def wait_ems(self, online: bool = True, names: list[str] | None = None) -> None:
        def ok() -> bool:
            s = self.last()
            if s is None:
                return False
            ems = {e.name: e.online for e in s.equipment_modules}
            wanted = names or list(ems)
            return all(ems.get(n) == online for n in wanted)

        wait(ok, f"EMs {'online' if online else 'offline'}")

    def trigger(self, name: str) -> None:
        resp = self.ros.call(Trigger, f"{self.base}/{name}")
        print(f"    {name}: {resp.message}")

    def command(self, cmd: int, source: str = "operator") -> None:
        resp = self.ros.call(
            Command, f"{self.base}/command", Command.Request(command=cmd, source=source)
        )
        print(f"    command {cmd} from {source}: {resp.message}")

    def mode(self, name: str) -> None:
        resp = self.ros.call(
            SetMode, f"{self.base}/set_mode", SetMode.Request(mode_name=name, source="operator")
        )
        print(f"    mode {name}: {resp.message}")

    def em_active(self, em: str, active: bool) -> None:
        resp = self.ros.call(SetEmActive, f"{self.base}/set_em_active",
                             SetEmActive.Request(em=em, active=active, source="operator"))  # fmt: skip
        print(f"    {em} active={active}: {resp.message}")

    def fault(self, em: str, fault: str, on: bool) -> None:
        resp = self.ros.call(SetBool, f"{self.base}/{em}/fault/{fault}", SetBool.Request(data=on))
        print(f"    fault {em}/{fault}: {resp.message}")

    def ack_alarms(self) -> None:
        resp = self.ros.call(
            AckAlarms, f"{self.base}/ack_alarms", AckAlarms.Request(all=True, source="operator")
        )
        print(f"    ack_alarms: {resp.message}")

    def reset_counters(self) -> None:
        resp = self.ros.call(
            ResetCounters, f"{self.base}/reset_counters", ResetCounters.Request(source="operator")
        )
        print(f"    reset_counters: {resp.message}")

    def wait_admins(self, n: int, timeout: float = 15.0) -> None:
        """``n`` more Admin messages (with nothing happening: heartbeats)."""
        target = len(self.admin) + n
        wait(lambda: len(self.admin) >= target, f"{n} more admin messages", timeout)

    def wait_counted(self, n: int) -> None:
        def counted() -> bool:
            if not len(self.admin):
                return False
            a = self.admin.messages[-1]
            return sum(c.count for c in a.prod_processed_count) >= n

        wait(counted, f"{n} products counted")


def wait(predicate: Callable[[], bool], what: str, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting for {what}")
        time.sleep(0.01)


def begin(s: Scenario, path: Path, storage: str = "mcap") -> None:
    """The usual start: recorder first, then the unit and its EMs, all EMs online."""
    s.record(path, storage)
    s.start_unit()
    s.recorder_ready()
    s.start_ems()
    s.wait_ems()


def production(s: Scenario, path: Path) -> None:
    begin(s, path)
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.wait_counted(3)
    s.trigger("stop")
    s.wait_state("STOPPED")


def hold_unhold(s: Scenario, path: Path) -> None:
    # a first run leaves admin data in the store; the recorded run restores it ...
    s.start_unit()
    s.start_ems()
    s.wait_ems()
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("stop")
    s.wait_state("STOPPED")
    s.stop_unit()
    s.start_unit()
    s.wait_ems()
    s.trigger("reset")
    s.wait_state("IDLE")
    # ... and the recorder joins late: the input log and the latched outputs reach it as history
    s.record(path)
    s.recorder_ready()
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.trigger("hold")
    s.wait_state("HELD")
    s.trigger("unhold")
    s.wait_state("EXECUTE")
    s.trigger("stop")
    s.wait_state("STOPPED")


def suspend_interlock(s: Scenario, path: Path) -> None:
    begin(s, path)
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.fault("loader", "full", True)  # the loader reports Blocked: the unit suspends itself
    s.wait_state("SUSPENDED")
    s.fault("loader", "full", False)  # cleared: it unsuspends
    s.wait_state("EXECUTE")
    s.trigger("stop")
    s.wait_state("STOPPED")


def alarm_stop(s: Scenario, path: Path) -> None:
    begin(s, path, storage="sqlite3")
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.fault("gripper", "vacuum_loss", True)  # alarm 201, category 2: Stop
    s.wait_state("STOPPED")
    s.trigger("reset")  # refused: the alarm is still active
    s.fault("gripper", "vacuum_loss", False)
    s.trigger("reset")  # Resetting resets the latched alarm
    s.wait_state("IDLE")


def alarm_abort(s: Scenario, path: Path) -> None:
    begin(s, path)
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.fault("robot", "estop", True)  # alarm 1, category 0: Abort
    s.wait_state("ABORTED")
    s.fault("robot", "estop", False)
    s.trigger("clear")
    s.wait_state("STOPPED")
    s.trigger("reset")
    s.wait_state("IDLE")


def mode_changes(s: Scenario, path: Path) -> None:
    begin(s, path)
    s.mode("MAINTENANCE")
    wait(
        lambda: (st := s.last()) is not None and st.unit_mode_current_name == "MAINTENANCE",
        "MAINTENANCE",
    )
    s.em_active("vision", False)
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.mode("PRODUCTION")  # refused in EXECUTE: the mode-change-not-allowed lamp
    s.trigger("stop")
    s.wait_state("STOPPED")
    s.em_active("vision", True)
    s.mode("MANUAL")
    wait(lambda: (st := s.last()) is not None and st.unit_mode_current_name == "MANUAL", "MANUAL")
    s.mode("PRODUCTION")
    wait(
        lambda: (st := s.last()) is not None and st.unit_mode_current_name == "PRODUCTION",
        "PRODUCTION",
    )


def em_lost(s: Scenario, path: Path) -> None:
    begin(s, path)
    s.trigger("reset")
    s.wait_state("IDLE")
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.kill_em("gripper")  # SIGKILL: no goodbye; the lease runs out, the unit aborts
    s.wait_state("ABORTED")
    s.start_em("gripper")
    s.wait_ems()
    s.trigger("clear")
    s.wait_state("STOPPED")
    s.trigger("reset")
    s.wait_state("IDLE")


def shift(s: Scenario, path: Path) -> None:
    """A longer run with what the short bags do not hold (issue 16): stale EM reports, an
    acknowledged warning, a first-out cleared by the next Start, a StopReason re-armed by
    Resetting, an EM hung in Starting (lost, excused), the mode-change lamp going out, counters
    reset, a mode left and re-entered, and admin heartbeats."""
    begin(s, path)
    s.fault("robot", "flaky_link", True)  # each robot State Complete arrives twice: one stale
    s.trigger("reset")
    s.wait_state("IDLE")

    def stale() -> bool:
        st = s.last()
        return st is not None and any(e.stale_reports for e in st.equipment_modules)

    wait(stale, "a stale report counted")
    s.fault("robot", "flaky_link", False)
    s.trigger("start")
    s.wait_state("EXECUTE")
    s.wait_counted(2)
    s.fault("vision", "lighting", True)  # warning 301: acknowledged, then gone
    s.wait_admins(1)
    s.ack_alarms()
    s.fault("vision", "lighting", False)
    s.fault("gripper", "vacuum_loss", True)  # alarm 201 stops the unit: first-out, StopReason
    s.wait_state("STOPPED")
    s.fault("gripper", "vacuum_loss", False)
    s.ack_alarms()
    s.trigger("reset")  # resets the latched alarm and re-arms the StopReason ...
    s.wait_state("IDLE")
    s.trigger("stop")  # ... so this stop records its own (operator, 33)
    s.wait_state("STOPPED")
    s.trigger("reset")
    s.wait_state("IDLE")
    # hung: Starting waits for it until its lease runs out (lost_reaction ignore: excused)
    s.freeze_em("outfeed")
    s.trigger("start")  # Starting clears the first-out
    s.wait_state("EXECUTE")
    s.freeze_em("outfeed", False)
    s.wait_ems()
    s.mode("MAINTENANCE")  # refused in EXECUTE: the lamp is lit for 3 s
    wait(lambda: (st := s.last()) is not None and st.mode_change_not_allowed, "the lamp on")
    wait(lambda: (st := s.last()) is not None and not st.mode_change_not_allowed, "the lamp off")
    s.trigger("stop")
    s.wait_state("STOPPED")
    s.reset_counters()
    s.mode("MAINTENANCE")
    wait(
        lambda: (st := s.last()) is not None and st.unit_mode_current_name == "MAINTENANCE",
        "MAINTENANCE",
    )
    s.mode("PRODUCTION")  # ModeCurrentTime of Production starts again at 0
    wait(
        lambda: (st := s.last()) is not None and st.unit_mode_current_name == "PRODUCTION",
        "PRODUCTION",
    )
    s.wait_admins(2)  # nothing happens: two heartbeats


SCENARIOS: dict[str, tuple[str, Callable[[Scenario, Path], None]]] = {
    "normal_production": ("robot_cell", production),
    "hold_unhold": ("robot_cell", hold_unhold),
    "suspend_interlock": ("case_packer", suspend_interlock),
    "alarm_stop": ("robot_cell", alarm_stop),
    "alarm_abort_clear_reset": ("robot_cell", alarm_abort),
    "mode_changes": ("robot_cell", mode_changes),
    "em_lost": ("robot_cell", em_lost),
    "shift": ("robot_cell", shift),
}


def plain(value: Any) -> Any:
    """An rclpy message as dicts and lists (what the mcap-ros2 encoder takes)."""
    if hasattr(value, "get_fields_and_field_types"):
        return {name: plain(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if hasattr(value, "tolist"):  # numpy arrays and array.array
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def write_independent(src: Path, dst: Path) -> int:
    """``src`` rewritten by mcap + mcap-ros2-support into a bare .mcap file (their own CDR
    encoder; schemas as ros2msg text; no metadata.yaml)."""
    from mcap_ros2.writer import Writer as McapRos2Writer
    from rclpy.serialization import deserialize_message
    from rosbags.highlevel import AnyReader

    from packml_ros2.bag.topics import msg_class, typestore

    store = typestore()
    count = 0
    with AnyReader([src]) as reader, dst.open("wb") as f:
        writer = McapRos2Writer(f)
        schemas: dict[str, Any] = {}
        for conn, ts, raw in reader.messages():
            if conn.msgtype not in schemas:
                text, _ = store.generate_msgdef(conn.msgtype, ros_version=2)
                schemas[conn.msgtype] = writer.register_msgdef(conn.msgtype, text)
            msg = deserialize_message(bytes(raw), msg_class(conn.msgtype))
            writer.write_message(
                conn.topic, schemas[conn.msgtype], plain(msg), log_time=ts, publish_time=ts
            )
            count += 1
        writer.finish()
    return count


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenarios", nargs="*", help=f"default: all ({', '.join(SCENARIOS)})")
    parser.add_argument("--out", default=str(ROOT / "test" / "bags"))
    args = parser.parse_args()
    out = Path(args.out)
    names = args.scenarios or list(SCENARIOS)
    for name in names:
        unit, drive = SCENARIOS[name]
        path = out / name
        if path.exists():
            shutil.rmtree(path)
        print(f"{name} ({unit}):")
        with tempfile.TemporaryDirectory(prefix=f"packml_bag_{name}_") as tmp:
            s = Scenario(Path(tmp), unit)
            try:
                drive(s, path)
            finally:
                s.finish()
        result = replay(path)
        size = sum(f.stat().st_size for f in path.iterdir())
        print(f"  {result.summary()}; {size / 1024:.0f} KiB")
        if not result.ok:
            print(result.report())
            return 1
    if "normal_production" in names:
        dst = out / "independent_writer.mcap"
        n = write_independent(out / "normal_production", dst)
        result = replay(dst)
        print(f"independent_writer.mcap: {n} messages; {result.summary()}")
        if not result.ok:
            print(result.report())
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
