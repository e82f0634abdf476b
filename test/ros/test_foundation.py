"""Issue 2: the interfaces are real, the runtime runs, and nothing leaves the machine."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from packml_interfaces import msg as pm
from packml_interfaces import srv as ps
from rclpy.serialization import deserialize_message, serialize_message

from packml_ros2.core import Cmd, Mode, Reason, State
from packml_ros2.testing.environment import localhost_environment
from test.netwatch import RtpsWatch, interfaces
from test.ros.cells import UnitClient, start_unit_process, write_cell

MSG_DIR = Path(__file__).resolve().parents[2] / "msg_defs" / "msg"


def _sample_status() -> pm.Status:
    return pm.Status(
        unit="filler",
        state_current=pm.Status.STATE_EXECUTE,
        state_current_name="EXECUTE",
        sequence=42,
        commands_valid=[3, 4, 6, 8, 10],
        commands_valid_names=["STOP", "HOLD", "SUSPEND", "ABORT", "COMPLETE"],
        equipment_interlock=pm.EquipmentInterlock(blocked=True),
        parameter=[pm.Descriptor(id=1, name="speed", unit="ppm", value=60.5)],
        product=[
            pm.Product(
                product_id=7,
                process_variables=[pm.Descriptor(id=2, name="temp", unit="C", value=180.0)],
                ingredients=[
                    pm.Ingredient(ingredient_id=3, parameter=[pm.Descriptor(id=4, value=1.5)])
                ],
            )
        ],
        equipment_modules=[
            pm.EmSummary(name="robot", active=True, online=True, state_complete=True, sequence=41)
        ],
        alarm_banner="ALARM 1/0 cat 0: E-stop",
    )


def _sample_admin() -> pm.Admin:
    alarm = pm.Alarm(
        trigger=True,
        id=65,
        value=0,
        message="Stop PB pressed",
        category=2,
        date_time=[2026, 11, 22, 9, 15, 7, 0],
        ack_date_time=[0] * 7,
        em="robot",
    )
    return pm.Admin(
        unit="filler",
        alarm=[alarm],
        alarm_extent=1,
        stop_reason=alarm,
        stop_reason_extent=1,
        mode_current_time=list(range(32)),
        state_cumulative_time=[i * 3 for i in range(32 * 18)],
        prod_processed_count=[pm.Count(id=1, name="good", unit="pcs", count=10, acc_count=1000)],
        acc_time_since_reset=12345,
        plc_date_time=[2026, 11, 22, 9, 15, 7, 123456],
        oee=pm.Oee(availability=0.9, performance=0.8, quality=0.99, oee=0.9 * 0.8 * 0.99),
    )


def test_constants_match_the_engine_numbers() -> None:
    for s in State:
        assert getattr(pm.Status, f"STATE_{s.name}") == s
    for c in Cmd:
        assert getattr(ps.Command.Request, c.name) == c
    for m in Mode:
        assert getattr(pm.Status, f"MODE_{m.name}") == m
    for r in Reason:
        assert getattr(pm.Result, r.name) == r, r


@pytest.mark.parametrize(
    "message",
    [
        _sample_status(),
        _sample_admin(),
        pm.EmReport(em="gripper", kind=1, state=3, sequence=9),
        pm.TransitionEvent(
            sequence=3, from_state=2, to_state=15, skipped_states=[15], source="remote:line"
        ),
        pm.UnitInput(index=1, name="command", args_json='{"cmd": 1}'),
    ],
    ids=lambda m: type(m).__name__,
)
def test_round_trip_through_cdr(message) -> None:
    data = serialize_message(message)
    assert deserialize_message(data, type(message)) == message


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_round_trip_through_a_rosbag2_file_with_rosbags(tmp_path: Path, storage: str) -> None:
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    for path in sorted(MSG_DIR.glob("*.msg")):
        store.register(get_types_from_msg(path.read_text(), f"packml_interfaces/msg/{path.stem}"))
    status, admin = _sample_status(), _sample_admin()
    bag = tmp_path / f"bag_{storage}"
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(bag, version=9, storage_plugin=plugin) as writer:
        for topic, message in (("/filler/status", status), ("/filler/admin", admin)):
            typename = f"packml_interfaces/msg/{type(message).__name__}"
            conn = writer.add_connection(topic, typename, typestore=store)
            writer.write(conn, 1_000, serialize_message(message))
    assert (bag / "metadata.yaml").exists()
    with Reader(bag) as reader:
        got = {
            c.topic: deserialize_message(
                raw, type(status) if c.topic.endswith("status") else type(admin)
            )
            for c, _, raw in reader.messages()
        }
    # the bag carries the type definitions: a reader without our .msg files decodes it
    from rosbags.highlevel import AnyReader

    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_KILTED)) as any_reader:
        conn = next(c for c in any_reader.connections if c.topic.endswith("status"))
        raw_status = next(raw for c, _, raw in any_reader.messages(connections=[conn]))
        decoded = any_reader.deserialize(raw_status, conn.msgtype)
    assert got["/filler/status"] == status
    assert got["/filler/admin"] == admin
    assert decoded.sequence == 42 and decoded.equipment_modules[0].name == "robot"


def test_a_node_in_another_process_answers_and_latches_status(
    ros, processes, tmp_path: Path
) -> None:
    cell_file, cell = write_cell(tmp_path, {"filler": {}})
    proc = start_unit_process(processes, cell_file, "filler")
    client = UnitClient(ros, cell, "filler")
    client.ready()
    assert client.status.last.state_current == State.STOPPED  # latched: received without any change
    answer = client.command(Cmd.RESET)
    assert answer.accepted and answer.result == Reason.ACCEPTED
    assert answer.state_current == State.IDLE
    # a subscriber that arrives now still gets the current status at once (transient local)
    late = UnitClient(ros, cell, "filler")
    assert late.status.wait_for(lambda m: m.state_current == State.IDLE, 5.0).sequence >= 3
    assert proc.stop() == 0, proc.output()


def test_the_environment_is_localhost_only() -> None:
    env = localhost_environment({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"


def test_no_dds_packet_leaves_the_machine(ros, processes, tmp_path: Path) -> None:
    """A watch on every interface while two processes talk: RTPS is seen on loopback (so the watch
    works) and never on an external interface."""
    try:
        external = RtpsWatch.on(interfaces(include_loopback=False))
        loop = RtpsWatch.on(["lo"])
    except PermissionError:
        pytest.skip("raw sockets need CAP_NET_RAW")
    external.start()
    loop.start()
    try:
        cell_file, cell = write_cell(tmp_path, {"filler": {}})
        start_unit_process(processes, cell_file, "filler")
        client = UnitClient(ros, cell, "filler")
        client.ready()
        client.command(Cmd.RESET)
        deadline = time.monotonic() + 5
        while not loop.packets and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        external.stop()
        loop.stop()
    assert loop.packets, "the watch saw no RTPS on loopback: it cannot be trusted"
    assert not external.packets, external.packets
