"""Issue 24 item 10: a PLC's alarm and a fast stop, through the bridge (``packml_ros2.plc.node``)
as processes against the test PLC (``test/opcua_client/plc.mjs``, node-opcua).

- The first alarm the PLC raises is logged as a warning after the bridge logged transitions as
  information: rclpy binds a call site to one severity, and one site for both raised
  ``ValueError: Logger severity cannot be changed between calls`` and dropped the rest of the
  batch (the transitions after it, the status, admin and alarms).
- Connecting logged 42 asyncua "Browsename collision" lines (the PLC's standard enumerations,
  which asyncua ships already) and the PLC's end a 15-line traceback: one line says each.
- The PLC dwells 20 ms in Stopping while the bridge's publishing interval is 1 s: Stopping and
  Stopped come in one publish response; both are transitions (before, the second value of the
  variable overwrote the first and Stopping was only a skipped state).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from packml_interfaces.msg import TransitionEvent

from packml_ros2.core import Cmd
from packml_ros2.testing.processes import Processes, wait_until
from test.opcua.test_opcua import free_port
from test.plc.test_plc_line import PLC_MODULE, TestPlc
from test.ros.cells import UnitClient, write_cell

pytestmark = pytest.mark.ros


def test_a_plc_alarm_and_a_fast_stop_reach_every_output_as_transitions(
    tmp_path: Path, ros: Any, processes: Processes
) -> None:
    plc = TestPlc(tmp_path, free_port(), dwell=20)
    plc.start()
    try:
        endpoint = f"opc.tcp://127.0.0.1:{plc.options['port']}"
        path, cell = write_cell(
            tmp_path,
            {"wrapper": {"remote_commands_enabled": True,
                         "plc": {"endpoint": endpoint, "publishing_interval": 1.0}}},
            coordinator={"unit_lease": 5.0},
        )  # fmt: skip
        bridge = processes.module("plc_wrapper", PLC_MODULE, str(path), "wrapper")
        wrapper = UnitClient(ros, cell, "wrapper")
        wrapper.ready(30)
        assert wrapper.command(Cmd.RESET).accepted
        wrapper.wait_state("IDLE", 15)
        assert wrapper.command(Cmd.START).accepted
        running = wrapper.wait_entered("EXECUTE", 15)
        since = wrapper.transitions.messages.index(running) + 1
        plc.send(fault={"id": 3001, "message": "Film break", "category": 2})
        stopped = wrapper.transitions.wait_for(
            lambda t: t.to_state_name == "STOPPED", 10, "the PLC stopped", since
        )
        after = wrapper.transitions.messages[since:]
        seen = [(t.from_state_name, t.to_state_name, list(t.skipped_states)) for t in after]
        assert seen == [("EXECUTE", "STOPPING", []), ("STOPPING", "STOPPED", [])], seen
        assert (after[0].trigger, after[0].source) == (TransitionEvent.TRIGGER_ALARM, "alarm:3001")
        assert stopped.trigger == TransitionEvent.TRIGGER_STATE_COMPLETE
        # the outputs of the batch were published too
        status = wrapper.wait_status(lambda m: m.state_current_name == "STOPPED", 5, "status")
        assert status.stop_reason_id == 3001
        wrapper.alarms.wait_for(lambda a: any(x.id == 3001 for x in a.alarms), 5, "the alarm")
        assert "EXECUTE -> STOPPING (alarm, STOP, alarm:3001: Film break)" in bridge.output()
        # the PLC goes away (shut down: it closes the session): one line says so
        plc.close()
        wait_until(lambda: "PLC lost:" in bridge.output(), 10, 0.05, "the loss reported")
        output = bridge.output()
        assert "Logger severity" not in output and "Traceback" not in output, output[-3000:]
        assert "Browsename collision" not in output, output[:3000]
        assert output.count("PLC lost:") == 1, output[-3000:]
        assert bridge.running()
    finally:
        plc.close()
