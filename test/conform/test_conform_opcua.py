"""``packml conform`` against OPC 30050 servers: the test PLC (``test/opcua_client/plc.mjs``,
node-opcua, its own state machine) green, and red with each of its seeded faults; and our own
OPC UA face over a unit of ours, reached with a user login."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any
from xml.etree import ElementTree as ET

import pytest
import yaml

from packml_ros2.opcua.config import hash_password
from packml_ros2.testing.processes import Processes
from test.conform.test_conform_ros import QUIET, conform, failures, report
from test.opcua.test_opcua import CLIENT_DIR, free_port, start_face
from test.plc.test_plc_line import TestPlc
from test.ros.cells import start_unit_process, write_cell

pytestmark = pytest.mark.timeout(300)

if not (CLIENT_DIR / "node_modules" / "node-opcua-server").is_dir():
    pytest.skip(
        "node-opcua-server is not installed: run tools/setup.sh --test", allow_module_level=True
    )

#: The PLC's modes as the standard modes are by default (what conform assumes without --config).
MODES = {
    "1": [],
    "2": ["SUSPENDING", "SUSPENDED", "UNSUSPENDING"],
    "3": [
        "HOLDING",
        "HELD",
        "UNHOLDING",
        "SUSPENDING",
        "SUSPENDED",
        "UNSUSPENDING",
        "COMPLETING",
        "COMPLETE",
    ],
}


def plc(tmp_path: Path, **options: Any) -> TestPlc:
    """The test PLC on a free loopback port, with the standard modes, times and ``options``."""
    test_plc = TestPlc(tmp_path, free_port(), dwell=60, times=True, modes=MODES, **options)
    test_plc.start()
    return test_plc


def run_on(
    plc: TestPlc, tmp_path: Path, *args: str
) -> tuple[subprocess.CompletedProcess[str], dict[str, Any]]:
    out = tmp_path / "r.json"
    run = conform(
        f"opc.tcp://127.0.0.1:{plc.options['port']}",
        "--browse-path",
        "PackMLObjects/wrapper",
        "--yes",
        "--quiet",
        QUIET,
        "--json",
        str(out),
        "--junit",
        str(tmp_path / "r.xml"),
        *args,
    )
    assert out.is_file(), run.stderr
    return run, report(out)


def test_the_test_plc_passes_everything_its_face_can_show(tmp_path: Path) -> None:
    test_plc = plc(tmp_path)
    try:
        run, doc = run_on(test_plc, tmp_path, "--profile", "all")
    finally:
        test_plc.close()
    assert run.returncode == 0, (failures(doc), run.stderr)
    assert doc["counts"]["fail"] == 0 and doc["counts"]["pass"] >= 200, doc["counts"]
    skipped = [r for r in doc["results"] if r["outcome"] == "skip"]
    assert [(r["check"], r["message"]) for r in skipped] == [
        ("counters-reset", "the opcua face has no counter reset")
    ]
    assert doc["face"] == "opcua" and doc["restored"] is True
    root = ET.parse(tmp_path / "r.xml").getroot()
    assert root.get("failures") == "0" and root.get("skipped") == "1"


#: The test PLC's seeded faults: how conform is run on it, and what the report says.
CORE, MATRIX, PACKTAGS = ("--profile", "core"), ("--profile", "modes"), ("--profile", "packtags")
PLC_FAULTS: dict[str, tuple[tuple[str, ...], str]] = {
    "missing_transition": (
        CORE,
        "UNSUSPEND in SUSPENDED (PRODUCTION) was refused (BadInvalidState); "
        "the standard accepts it",
    ),
    # a server samples: a state that is not shown fails only with --strict-path
    "skip_acting": (
        (*CORE, "--strict-path"),
        "RESET in STOPPED (PRODUCTION): it never showed RESETTING (shown: IDLE), twice",
    ),
    "wrong_target": (
        CORE,
        "HOLD in EXECUTE (PRODUCTION) settled in SUSPENDED; the standard's way is HOLDING -> HELD",
    ),
    "invalid_accepted": (
        CORE,
        "START in STOPPED (PRODUCTION) was accepted (Good); the standard "
        "refuses it (COMMAND_NOT_ALLOWED)",
    ),
    "refused_moves": (CORE, "START in STOPPED (PRODUCTION): it still changed: RESETTING"),
    "stuck": (CORE, "COMPLETE in EXECUTE (PRODUCTION) left the target in COMPLETING for 2 s"),
    "disabled_entered": (
        (*MATRIX, "--modes", "production,manual"),
        "HOLD in EXECUTE (MANUAL) was "
        "accepted (Good); the standard refuses it (STATE_DISABLED); the target "
        "went to HELD (MANUAL), entering HOLDING, HELD, which MANUAL disables",
    ),
    "mode_matrix": (
        MATRIX,
        "the change from PRODUCTION to MAINTENANCE in EXECUTE was accepted "
        "(Good); the standard refuses it (MODE_CHANGE_NOT_ALLOWED)",
    ),
    "mode_not_shown": (
        MATRIX,
        "the change from PRODUCTION to MAINTENANCE in STOPPED was accepted, "
        "but UnitModeCurrent still shows PRODUCTION",
    ),
    "times_frozen": (PACKTAGS, "StateCurrentTime of IDLE (PRODUCTION) went from 0 to 0 s"),
    "mode_time_frozen": (PACKTAGS, "ModeCurrentTime of PRODUCTION went from 0 to 0 s"),
    "cumulative_lost": (PACKTAGS, "StateCumulativeTime for IDLE (PRODUCTION) went from"),
}


@pytest.mark.parametrize("fault", sorted(PLC_FAULTS))
def test_each_seeded_fault_is_caught_and_said(fault: str, tmp_path: Path) -> None:
    how, sentence = PLC_FAULTS[fault]
    test_plc = plc(tmp_path, faults=[fault])
    try:
        quick = ("--stop-on-first", "--timeout", "2", "--quiet", "0.3")
        run, doc = run_on(test_plc, tmp_path, *how, *quick)
    finally:
        test_plc.close()
    assert run.returncode == 1, run.stderr
    found = failures(doc)
    assert len(found) == 1 and sentence in found[0], found
    assert doc["stopped_early"]
    root = ET.parse(tmp_path / "r.xml").getroot()
    assert any(sentence in (f.get("message") or "") for f in root.iter("failure"))


@pytest.mark.ros
def test_our_opcua_face_passes_with_a_login(tmp_path: Path, processes: Processes) -> None:
    unit = {"remote_commands_enabled": True, "admin_period": 1.0}
    path, _ = write_cell(tmp_path, {"filler": unit}, coordinator={"enabled": False})
    port = free_port()
    doc = yaml.safe_load(path.read_text())
    doc["opcua"] = {
        "port": port,
        "state_dir": str(tmp_path / "state"),
        "users": {"operator": hash_password("s3cret-word", iterations=1000)},
    }
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    start_unit_process(processes, path, "filler")
    start_face(processes, path)
    secret = tmp_path / "password"
    secret.write_text("s3cret-word\n")
    out = tmp_path / "r.json"
    run = conform(
        f"opc.tcp://127.0.0.1:{port}",
        "--browse-path",
        "PackMLObjects/filler",
        "--user",
        "operator",
        "--password-file",
        str(secret),
        "--yes",
        "--profile",
        "all",
        "--quiet",
        QUIET,
        "--json",
        str(out),
        "--connect-timeout",
        "30",
    )
    doc = report(out)
    assert run.returncode == 0, (failures(doc), run.stderr)
    assert doc["counts"]["fail"] == 0 and doc["counts"]["pass"] >= 200, doc["counts"]
    assert "s3cret" not in run.stdout + run.stderr + out.read_text()
    # anonymous: the face refuses commands; the report says so, it does not crash
    anon = conform(
        f"opc.tcp://127.0.0.1:{port}",
        "--browse-path",
        "PackMLObjects/filler",
        "--yes",
        "--stop-on-first",
        "--quiet",
        QUIET,
    )
    assert anon.returncode == 1, anon.stderr
    assert "Traceback" not in anon.stderr and "BadUserAccessDenied" in anon.stdout, anon.stdout
