"""``packml conform`` against ROS units, as a machine builder runs it: the CLI in a process of its
own, the target in others. Green on our units (2022 and 2015, masks, a user mode, with EMs) and
on a unit of another implementation (``foreign_unit.py``); red on that unit with each of its
seeded faults; safe (Production needs --yes, --dry commands nothing, --stop-on-first leaves the
target where the failure showed)."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import pytest
import yaml
from packml_interfaces.msg import Status

from packml_ros2.ros import interface
from packml_ros2.testing.processes import Processes, wait_until
from test.ros.cells import start_unit_process, write_cell
from test.test_replay import PACKML, ROOT

pytestmark = [pytest.mark.ros, pytest.mark.timeout(300)]

FOREIGN = Path(__file__).with_name("foreign_unit.py")
QUIET = "0.1"


def conform(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PACKML, "conform", *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT,
        check=False,
    )  # fmt: skip


def report(path: Path) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(path.read_text())
    return doc


def failures(doc: dict[str, Any]) -> list[str]:
    return [f"{r['name']}: {r['message']}" for r in doc["results"] if r["outcome"] == "fail"]


_count = itertools.count()


def unique(prefix: str) -> str:
    """A cell name no other test of this run uses."""
    return f"{prefix}{os.getpid()}_{next(_count)}"


def start_foreign(processes: Processes, cell: str, faults: tuple[str, ...] = ()) -> str:
    options = {"cell": cell, "unit": "u", "dwell": 0.02, "rate": 20, "faults": list(faults)}
    proc = processes.start("foreign", str(FOREIGN), json.dumps(options))
    wait_until(lambda: "ready" in proc.output() or not proc.running(), 60, 0.05, "the foreign unit")
    assert proc.running(), proc.output()
    return f"/{cell}/u"


def follow_status(ros: Any, path: str) -> Any:
    declared = interface.TOPIC["status"]
    return ros.subscribe(Status, declared.path(path), declared.qos)


def test_our_unit_passes_every_profile_safely_and_is_brought_back(
    tmp_path: Path, processes: Processes, ros: Any
) -> None:
    cell_file, cell = write_cell(tmp_path, {"filler": {"admin_period": 1.0}})
    start_unit_process(processes, cell_file, "filler")
    target = f"/{cell}/filler"
    status = follow_status(ros, target)
    first = status.wait_for(lambda s: True, 30, "the unit's status")

    # in Production it refuses to start without --yes; --dry shows the plan; neither moves it
    refused = conform(target, "--connect-timeout", "30")
    assert refused.returncode == 2, refused.stderr
    assert "PRODUCTION mode" in refused.stderr and "--yes" in refused.stderr, refused.stderr
    dry = conform(target, "--dry", "--profile", "all")
    assert dry.returncode == 0, dry.stderr
    assert "found in STOPPED (PRODUCTION)" in dry.stdout, dry.stdout
    assert "core     PRODUCTION IDLE START: accepted: STARTING -> EXECUTE" in dry.stdout, dry.stdout
    assert "modes    MANUAL EXECUTE HOLD: refused (STATE_DISABLED)" in dry.stdout, dry.stdout
    assert "then bring the target back to STOPPED (PRODUCTION)" in dry.stdout, dry.stdout
    assert status.last.sequence == first.sequence  # nothing was commanded

    out = tmp_path / "report.json"
    xml = tmp_path / "report.xml"
    run = conform(target, "--yes", "--profile", "all", "--quiet", QUIET, "--json", str(out),
                  "--junit", str(xml))  # fmt: skip
    doc = report(out)
    assert run.returncode == 0, (failures(doc), run.stderr)
    assert doc["passed"] and doc["counts"]["fail"] == 0 and doc["counts"]["skip"] == 0, doc[
        "counts"
    ]
    assert doc["counts"]["pass"] >= 200, doc["counts"]  # 70 core, 134 modes, 5 PackTag checks
    assert doc["found"] == "STOPPED (PRODUCTION)" and doc["restored"] is True
    assert "PASSED: " in run.stdout and "the target was brought back to STOPPED" in run.stdout
    by_name = {r["name"]: r for r in doc["results"]}
    assert by_name["PRODUCTION IDLE START"]["message"].startswith("accepted: STARTING -> EXECUTE")
    assert by_name["PRODUCTION IDLE START"]["seconds"] < 1.0
    assert by_name["MANUAL EXECUTE HOLD"]["message"].startswith("refused: STATE_DISABLED")
    assert by_name["PRODUCTION EXECUTE -> MAINTENANCE"]["message"].startswith(
        "refused: MODE_CHANGE_NOT_ALLOWED"
    )
    # the three growth checks of one stay share its two Admin readings (one wait, not three)
    spans = {by_name[c]["message"].rsplit(" in ", 1)[1] for c in (
        "state-current-time (PRODUCTION IDLE)", "mode-current-time (PRODUCTION IDLE)",
        "mode-cumulative-time (PRODUCTION IDLE)")}  # fmt: skip
    assert len(spans) == 1, spans
    # the JUnit XML a CI system reads: one suite per group, every check a test case
    root = ET.parse(xml).getroot()
    assert root.tag == "testsuites" and root.get("failures") == "0", ET.tostring(root)[:300]
    suites = {s.get("name"): int(s.get("tests", 0)) for s in root.iter("testsuite")}
    assert suites == {"packml.conform.core": 70, "packml.conform.modes": 134,
                      "packml.conform.packtags": 5}  # fmt: skip
    # moved, and back where it was found
    final = status.wait_for(lambda s: s.sequence > first.sequence, 10, start=len(status) - 1)
    wait_until(lambda: (status.last.state_current, status.last.unit_mode_current) == (2, 1), 10)
    assert final.sequence > first.sequence


def test_the_declared_model_is_what_is_certified_2015_masks_and_a_user_mode(
    tmp_path: Path, processes: Processes
) -> None:
    unit = {
        "model": "2015",
        "hold_from": ["Execute"],
        "complete_from": ["Execute", "Held"],
        "modes": {
            "maintenance": {"mode_change_states": ["Stopped", "Idle", "Aborted", "Held"]},
            "cleaning": {
                "number": 4,
                "disabled_states": ["Resetting", "Completed"],
                "mode_change_states": ["Stopped", "Aborted"],
            },
        },
    }
    cell_file, cell = write_cell(tmp_path, {"filler": unit})
    start_unit_process(processes, cell_file, "filler")
    target = f"/{cell}/filler"
    out = tmp_path / "r.json"
    run = conform(target, "--config", str(cell_file), "--yes", "--profile", "core,modes", "--quiet",
                  QUIET, "--json", str(out), "--connect-timeout", "30")  # fmt: skip
    doc = report(out)
    assert run.returncode == 0, (failures(doc), run.stderr)
    assert doc["model"].startswith("2015 (Hold from EXECUTE; Complete from EXECUTE,HELD)")
    names = {r["name"] for r in doc["results"]}
    assert "CLEANING STOPPED RESET" in names and "MAINTENANCE HELD -> PRODUCTION" in names
    by_name = {r["name"]: r for r in doc["results"]}
    # Resetting is skipped in Cleaning: Reset goes straight to Idle
    assert by_name["CLEANING STOPPED RESET"]["message"].startswith("accepted: IDLE")
    assert by_name["PRODUCTION SUSPENDED HOLD"]["message"].startswith(
        "refused: COMMAND_NOT_ALLOWED"
    )

    # the same unit certified as a 2022 machine: the differences are caught, each in a sentence
    out = tmp_path / "r2022.json"
    run = conform(target, "--yes", "--quiet", QUIET, "--json", str(out), "--model", "2022")
    doc = report(out)
    assert run.returncode == 1 and not doc["passed"]
    found = failures(doc)
    assert any(
        f.startswith("PRODUCTION SUSPENDED HOLD: HOLD in SUSPENDED (PRODUCTION) was refused "
                     "(COMMAND_NOT_ALLOWED") and "the standard accepts it: HOLDING -> HELD" in f
        for f in found
    ), found  # fmt: skip


def test_another_implementation_passes(tmp_path: Path, processes: Processes) -> None:
    target = start_foreign(processes, unique("fu"))
    out = tmp_path / "r.json"
    run = conform(
        target, "--yes", "--profile", "core,packtags", "--quiet", QUIET, "--json", str(out)
    )
    doc = report(out)
    assert run.returncode == 0, (failures(doc), run.stderr)
    assert doc["counts"] == {"pass": 75, "fail": 0, "skip": 0}
    reset = {r["name"]: r for r in doc["results"]}["counters-reset (PRODUCTION IDLE)"]["message"]
    assert "not proven" not in reset, reset


#: The foreign unit's seeded faults, the profile that meets them, and what the report says.
FOREIGN_FAULTS = {
    "no_reason": (
        "core",
        "PRODUCTION STOPPED START: START in STOPPED (PRODUCTION): refused with reason ACCEPTED, "
        "not COMMAND_NOT_ALLOWED; the refusal says no reason in words",
    ),
    "sequence_frozen": (
        "core",
        "PRODUCTION STOPPED RESET: RESET in STOPPED (PRODUCTION): the transition sequence number "
        "stayed 0",
    ),
    "wrong_disabled_mask": (
        "modes",
        "PRODUCTION STOPPED -> MAINTENANCE: the change from PRODUCTION to MAINTENANCE in STOPPED: "
        "StatesDisabled shows 0x0; MAINTENANCE disables 0x6020",
    ),
    "counters_not_reset": (
        "packtags",
        "counters-reset (PRODUCTION IDLE): after the counter reset 1 counts are not 0",
    ),
}


@pytest.mark.parametrize("fault", sorted(FOREIGN_FAULTS))
def test_a_wrong_unit_fails_with_a_sentence_and_stays_where_it_failed(
    fault: str, tmp_path: Path, processes: Processes, ros: Any
) -> None:
    profile, sentence = FOREIGN_FAULTS[fault]
    target = start_foreign(processes, unique("fu"), (fault,))
    out, xml = tmp_path / "r.json", tmp_path / "r.xml"
    run = conform(target, "--yes", "--profile", profile, "--quiet", QUIET, "--stop-on-first",
                  "--json", str(out), "--junit", str(xml))  # fmt: skip
    doc = report(out)
    assert run.returncode == 1, run.stderr
    found = failures(doc)
    assert len(found) == 1 and found[0].startswith(sentence), found
    assert doc["stopped_early"] and doc["restored"] is None
    assert "stopped at the first failure; the target was left in" in run.stdout
    # left where the failure showed: the run ended there
    status = follow_status(ros, target).wait_for(lambda s: True, 10)
    assert doc["left"].startswith(status.state_current_name), (doc["left"], status)
    root = ET.parse(xml).getroot()
    messages = [f.get("message", "") for f in root.iter("failure")]
    assert any(m.startswith(sentence.split(": ", 1)[1]) for m in messages), messages


def test_a_target_that_is_not_there(tmp_path: Path) -> None:
    started = time.monotonic()
    run = conform("/nocell/nounit", "--yes", "--connect-timeout", "2")
    assert run.returncode == 3, run.stderr
    assert "no status from /nocell/nounit within 2 s" in run.stderr
    assert "Traceback" not in run.stderr
    assert time.monotonic() - started < 30
    bad = conform("justaname")
    assert bad.returncode == 2 and "write the unit as /cell/unit" in bad.stderr, bad.stderr
    cell_file = tmp_path / "c.yaml"
    cell_file.write_text(yaml.safe_dump({"cell": "c", "units": {"a": {}}}))
    bad = conform("/c/b", "--config", str(cell_file), "--unit", "b")
    assert bad.returncode == 2 and "no unit 'b' (units: a)" in bad.stderr, bad.stderr
    bad = conform("/c/a", "--timeout", "EXECUTING=3")
    assert bad.returncode == 2 and "--timeout EXECUTING=3" in bad.stderr, bad.stderr
