"""Issue 15: a bag is hostile input too. Its YAML (metadata.yaml, the QoS of each topic) is read
by the bounded loader of cell files: a deeply nested or bomb-laden metadata.yaml is a refusal
with a reason, where libyaml's composer crashed `packml replay` (SIGSEGV)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BAG = REPO / "test" / "bags" / "hold_unhold"
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join([f'*{p}'] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)


@pytest.mark.parametrize(
    ("metadata", "reason"),
    [
        ("rosbag2_bagfile_information: " + "[" * 200_000 + "]" * 200_000 + "\n", "nested more"),
        (BOMB + "rosbag2_bagfile_information: *i\n", "alias bomb"),
        ("rosbag2_bagfile_information: {version: 9}\nrosbag2_bagfile_information: {}\n", "twice"),
        ("rosbag2_bagfile_information: [1, 2]\n", "no rosbag2_bagfile_information mapping"),
        ("[1, 2]\n", "no rosbag2_bagfile_information mapping"),
    ],
)
def test_a_hostile_metadata_file_is_refused_with_a_reason(
    tmp_path: Path, metadata: str, reason: str
) -> None:
    bag = tmp_path / "bag"
    shutil.copytree(BAG, bag)
    (bag / "metadata.yaml").write_text(metadata)
    result = subprocess.run([sys.executable, "-m", "packml_ros2.cli.main", "replay", str(bag)],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2, (result.returncode, result.stderr[-500:])  # was -11 (SIGSEGV)
    assert reason in result.stderr and "Traceback" not in result.stderr, result.stderr[-500:]
    assert len(result.stderr) < 2000
