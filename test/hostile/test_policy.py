"""Issue 15: the SROS2 permission policy of a cell, generated from the cell file
(``packml policy``), as the README shows it: one enclave per unit, EM and coordinator with exactly
the names it serves, publishes and subscribes (read from the nodes themselves), and the faces'
enclaves; least privilege: only a unit answers its services, an EM publishes its reports and
calls nothing. The command runs verbatim, with HOME in the test's directory (no store of a real
cell is opened: a running cell holds them)."""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from test.workspace.tools import ROOT, code_blocks, console_commands, shell, shown_in

pytestmark = pytest.mark.ros

UNITS = ("robot_cell", "case_packer")
UNIT_SERVICES = ("command", "set_mode", "set_alarm", "set_interlock", "set_remote_commands",
                 "reset", "set_parameters")  # fmt: skip


def readme_policy_command() -> tuple[str, list[str]]:
    found = [
        (command, shown)
        for block in code_blocks("console")
        for command, shown in console_commands(block)
        if command.startswith("packml policy ")
    ]
    assert len(found) == 1, "the README shows one packml policy command"
    return found[0]


def allowed(profile: ET.Element, tag: str, rule: str) -> set[str]:
    return {
        item.text or ""
        for group in profile.findall(tag)
        if group.get(rule) == "ALLOW"
        for item in group
    }


def test_the_readme_policy_command_writes_an_enclave_per_node_with_least_privilege(
    tmp_path: Path,
) -> None:
    command, shown = readme_policy_command()
    (tmp_path / "config").mkdir()
    shutil.copy(ROOT / "config" / "demo_cell.yaml", tmp_path / "config")
    result = shell(command, tmp_path, tmp_path, timeout=60)
    assert result.returncode == 0, result.stdout
    assert shown_in(shown, result.stdout) is None, result.stdout
    assert not (tmp_path / ".local").exists(), "a store was opened"
    output = command.split(" -o ")[1].split()[0]
    root = ET.parse(tmp_path / output).getroot()
    assert root.tag == "policy" and root.get("version") == "0.2.0"
    enclaves = {e.get("path"): e for e in root.find("enclaves") or []}
    ems = {"robot_cell": ("infeed", "robot", "gripper", "vision", "outfeed"),
           "case_packer": ("erector", "loader")}  # fmt: skip
    expected = (
        {f"/demo_cell/{u}" for u in UNITS}
        | {f"/demo_cell/{u}/{em}" for u, names in ems.items() for em in names}
        | {f"/demo_cell/{n}" for n in ("coordinator", "hmi", "opcua", "operator")}
    )
    assert set(enclaves) == expected
    for path, enclave in enclaves.items():
        (profile,) = enclave.findall("profiles/profile")
        assert profile.get("ns") and profile.get("node"), path
        for group in profile:
            assert group.tag in ("topics", "services") and len(group.attrib) == 1, path
            assert all(item.text and item.text.startswith("/") for item in group), path

    def of(path: str, tag: str, rule: str) -> set[str]:
        return allowed(enclaves[path].findall("profiles/profile")[0], tag, rule)

    unit_services = {f"/demo_cell/{u}/{s}" for u in UNITS for s in UNIT_SERVICES}
    for u in UNITS:
        base = f"/demo_cell/{u}"
        assert {f"{base}/{s}" for s in UNIT_SERVICES} <= of(base, "services", "reply")
        assert {f"{base}/status", f"{base}/transitions", f"{base}/config"} <= of(
            base, "topics", "publish"
        )
        assert of(base, "topics", "subscribe") == {
            f"{base}/em_reports",
            f"{base}/em_heartbeats",
            "/parameter_events",
        }
        for em in ems[u]:
            path = f"{base}/{em}"
            assert of(path, "topics", "publish") == {
                f"{base}/em_reports",
                f"{base}/em_heartbeats",
                "/rosout",
                "/parameter_events",
            }
            assert f"{base}/status" in of(path, "topics", "subscribe")
            assert not of(path, "services", "request"), "an EM calls no service"
    for path in enclaves:  # only a unit answers a unit's services
        if path not in {f"/demo_cell/{u}" for u in UNITS}:
            assert not of(path, "services", "reply") & unit_services, path
    for face in ("hmi", "opcua", "operator", "coordinator"):
        path = f"/demo_cell/{face}"
        assert unit_services <= of(path, "services", "request"), path
        assert "/demo_cell/robot_cell/em_reports" not in of(path, "topics", "publish"), path
    assert "/demo_cell/coordinator/command" in of("/demo_cell/operator", "services", "request")


def test_a_bad_cell_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    (tmp_path / "bad.yaml").write_text("cell: [unclosed\n")
    result = shell("packml policy bad.yaml", tmp_path, tmp_path, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stdout, result.stdout
    assert result.stdout.startswith("packml policy: ") and len(result.stdout.splitlines()) <= 3
