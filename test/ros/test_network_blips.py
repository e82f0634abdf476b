"""Issue 25 item 5: a network blip shorter than the EM lease never aborts production.

The EMs' host is cut off from the units' host (its link down) for 0.3 to 1.5 s, five times, while
the unit is in Execute with an EM lease of 2 s. Reliable ``em_reports`` hold the reports sent after
a cut until the lost ones are repaired; the lease follows the heartbeats on their own best-effort
channel (``em_heartbeats``), so the unit keeps its EM and keeps producing. Namespaces as in
test_multihost (real processes, UDP only)."""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from test.ros.cells import saved_admin
from test.ros.test_multihost import HostProcess, Network, Observer, network  # noqa: F401

LEASE = 2.0
CUTS = (0.3, 0.5, 0.6, 1.0, 1.5)
EM_SIM = {"cycle_time": 0.05, "counter": "processed", "lease": LEASE,
          "durations": {"starting": 0.1, "stopping": 0.1, "aborting": 0.1}}  # fmt: skip


def blip(net: Network, host: str, forwarding: bool) -> None:
    """The bridge stops (or starts again) forwarding the host's frames: both links stay up, as in
    a switch's blip (``ip link set ... down`` would add the links' own recovery to the cut)."""
    state = "3" if forwarding else "0"  # (bridge port states: 0 disabled, 3 forwarding)
    done = subprocess.run(["bridge", "-n", net.bridge, "link", "set", "dev", net.port[host], "state", state],
                          capture_output=True, text=True, timeout=10, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr


def _logs(logs: Path) -> str:
    """The last lines of every process's log: what a failure shows."""
    return "\n".join(f"== {f.name}\n" + "\n".join(f.read_text(errors="replace").splitlines()[-15:])
                     for f in sorted(logs.glob("*.log")))  # fmt: skip


@pytest.mark.netns
@pytest.mark.ros
def test_cuts_shorter_than_the_em_lease_never_abort(network: Network, tmp_path: Path) -> None:  # noqa: F811
    if shutil.which("bridge") is None:
        pytest.skip("iproute2's bridge command is not installed")
    cell = f"nb{os.getpid() % 100000}"
    doc = {
        "cell": cell,
        "defaults": {"remote_commands_enabled": True, "em_lease": LEASE,
                     "persistence": {"path": str(tmp_path / "{unit}.sqlite3")}},
        "units": {"filler": {"equipment_modules": {"doser": {"sim": EM_SIM}}}},  # lost: abort
        "coordinator": {"unit_lease": 3.0, "step_timeout": 10.0},
    }  # fmt: skip
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(yaml.safe_dump(doc, sort_keys=False))
    logs = tmp_path / "logs"
    logs.mkdir()
    started: list[HostProcess] = []
    observer = Observer(network, cell, ["filler"], logs)
    started.append(observer)
    try:
        unit = HostProcess(network, "units", "filler", "packml_ros2.unit_node", str(cell_file),
                           "filler", log_dir=logs)  # fmt: skip
        started.append(unit)
        started.append(HostProcess(network, "ems", "doser", "packml_ros2.sim_em", str(cell_file),
                                   "filler", "doser", log_dir=logs))  # fmt: skip
        started.append(HostProcess(network, "coord", "coordinator", "packml_ros2.coordinator_node",
                                   str(cell_file), log_dir=logs))  # fmt: skip

        def online(c: dict[str, Any]) -> bool:
            return c["all_online"] and all(u["em_online"] == u["em_total"] == 1 for u in c["units"])

        observer.wait_cell(online, 30, "the unit and its EM online")
        for verb, settled in (("reset", "IDLE"), ("start", "EXECUTE")):
            answer = observer.ask("trigger", name=verb)
            assert answer["success"], answer["message"]
            observer.wait_cell(lambda c, s=settled: c["state_current_name"] == s, 10, settled)

        for cut in CUTS:
            blip(network, "ems", False)
            time.sleep(cut)  # the blip itself (its length is the stimulus, not a wait)
            blip(network, "ems", True)
            # one lease and a half after the link is back: a loss would have been declared
            # (the unit's own status: the coordinator sits on a third host; its view of the
            # unit is not what a cut between the unit and its EM can change)
            deadline = time.monotonic() + 1.5 * LEASE
            while time.monotonic() < deadline:
                s = observer.ask("unit", unit="filler")
                assert s["state_current_name"] == "EXECUTE", (cut, s, _logs(logs))
                assert all(e["online"] for e in s["equipment_modules"]), (cut, s, _logs(logs))
                time.sleep(0.1)
            observer.wait_cell(online, 2 * doc["coordinator"]["unit_lease"],
                               f"the unit and its EM online after a {cut} s cut")  # fmt: skip
        assert unit.stop() == 0, unit.output()[-3000:]
    finally:
        for proc in reversed(started):
            proc.stop()
    lost = [e for e in saved_admin(tmp_path / "filler.sqlite3", "filler")["alarms"]["history"]
            if e["id"] == 9001]  # fmt: skip
    assert not lost, lost
