"""Issue 27 (replay speed): ``packml replay`` checks a bag's type hashes against the installed
ones read from rosidl's type descriptions (topics.installed_hash) instead of building a rosbags
typestore; they must be the hashes the typestore computes, and a bag of another definition is
still refused."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from packml_ros2.bag.topics import UNIT_TOPICS, installed_hash, typestore

BAGS = Path(__file__).resolve().parents[2] / "test" / "bags"


@pytest.mark.parametrize("msgtype", sorted(set(UNIT_TOPICS.values())))
def test_installed_hashes_are_the_typestores(msgtype: str) -> None:
    assert installed_hash(msgtype).startswith("RIHS01_")
    assert installed_hash(msgtype) == typestore().hash_rihs01(msgtype)


def test_loading_a_bag_builds_no_typestore() -> None:
    code = (
        "from packml_ros2.bag.recording import load\n"
        "from packml_ros2.bag.topics import typestore\n"
        f"r = load({str(BAGS / 'independent_writer.mcap')!r}, em_reports=False)\n"
        "print(len(r.units), typestore.cache_info().currsize)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    units, built = out.stdout.split()
    assert int(units) >= 1 and built == "0"


def test_a_bag_of_another_definition_is_still_refused(tmp_path: Path) -> None:
    from rosbags.rosbag2 import Writer

    from packml_ros2.bag.recording import RecordingError, load

    bag = tmp_path / "other"
    writer = Writer(bag, version=9)
    writer.open()
    other = "RIHS01_" + "0" * 64
    conn = writer.add_connection("/cell/u/status", "packml_interfaces/msg/Status",
                                 msgdef="int32 x", rihs01=other)  # fmt: skip
    writer.write(conn, 1, b"\x00\x01\x00\x00\x01\x00\x00\x00")
    writer.close()
    with pytest.raises(RecordingError, match="another version of packml_interfaces") as err:
        load(bag)
    assert other in str(err.value) and installed_hash("packml_interfaces/msg/Status") in str(
        err.value
    )
