"""Issue 26 item 3: EMs made of existing ROS 2 action servers and services, configured in the cell
file (packml_ros2.interface_em), against real rclpy servers in another process
(test/ros/fake_servers.py) and a real unit node over DDS."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.core import load_cell
from packml_ros2.core.schema import ConfigError
from packml_ros2.interface_em import Failure, InterfaceEm, create, parse_interface
from packml_ros2.testing.em_harness import EmTestUnit
from packml_ros2.testing.harness import wait_server_gone
from packml_ros2.testing.processes import wait_until

SERVERS = Path(__file__).with_name("fake_servers.py")
ALARM = 5001


def move_em(states: dict[str, Any], **extra: Any) -> dict[str, Any]:
    block = {"type": "test_msgs/action/Fibonacci", "name": "move", "timeout": 10,
             "alarm": {"id": ALARM, "reaction": "stop"}, "states": states, **extra}  # fmt: skip
    return {"action": block}


def gripper_em(states: dict[str, Any], **extra: Any) -> dict[str, Any]:
    block = {"type": "std_srvs/srv/SetBool", "name": "grip", "timeout": 10, "success": "success",
             "alarm": {"id": ALARM, "category": 2}, "states": states, **extra}  # fmt: skip
    return {"service": block}


def start(ros, processes, tmp_path, em: dict[str, Any], step: float = 0.1, **unit: Any):  # type: ignore[no-untyped-def]
    """The unit with EM ``mover``, the servers (under the unit's namespace) and the EM."""
    test_unit = EmTestUnit(ros, tmp_path, {"mover": em}, unit_config=unit)
    base = f"/{test_unit.cell}/{test_unit.unit}"
    servers = processes.start("servers", str(SERVERS), f"{base}/move", f"{base}/grip", str(step))
    node = create(str(test_unit.cell_file), test_unit.unit, "mover", context=ros.context)
    ros.add(node)
    test_unit.wait_online("mover")
    wait_ready(servers, node)
    return test_unit, servers, node


def wait_ready(servers, node: InterfaceEm, prime: bool = True) -> None:  # type: ignore[no-untyped-def]
    """The servers' process is up and the EM sees its server (a slow start under load), and one
    answer of each kind has come back through the EM's own client: a plain rclpy server drops an
    answer to a client whose response reader it has not discovered yet (Fast DDS waits 100 ms),
    so an EM's first goal could go unanswered in a test only because discovery was slow."""
    wait_until(lambda: "drivers ready" in servers.output(), 60, what="the servers' process")
    client = node._action or node._service
    ready = getattr(client, "server_is_ready", None) or client.service_is_ready
    wait_until(ready, 30, what="the EM seeing its server")
    if not prime:  # (a restarted server: the EM's client is there already; the server sees it)
        if node._action is not None:
            wait_until(lambda: "client seen" in servers.output(), 30, what="the servers seeing the EM's client")  # fmt: skip
        return
    if node._action is not None:
        from test_msgs.action import Fibonacci

        def round_trip() -> bool:  # a one-step move, its goal answered and its result back
            sent = node._action.send_goal_async(Fibonacci.Goal(order=1))
            if not _done(sent, 2.0) or not sent.result().accepted:
                return False
            return _done(sent.result().get_result_async(), 5.0)
    else:
        from std_srvs.srv import SetBool

        def round_trip() -> bool:
            return _done(node._service.call_async(SetBool.Request(data=True)), 2.0)

    wait_until(round_trip, 60, what="an answer through the EM's client")


def _done(future: Any, timeout: float) -> bool:
    """Whether ``future`` (completed by the spinning harness) is done within ``timeout``."""
    import time

    deadline = time.monotonic() + timeout
    while not future.done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_an_action_em_sends_goals_in_its_states_and_counts_results(
    ros, processes, tmp_path
) -> None:
    em = move_em({
        "starting": {"goal": {"order": "${parameter:order}"}},
        "execute": {"goal": {"order": 2}, "repeat": True, "count": {"processed": "sequence"}},
    })  # fmt: skip
    unit, servers, node = start(
        ros, processes, tmp_path, em, parameters=[{"id": 1, "name": "order", "value": 3}]
    )
    unit.check_lifecycle("mover", timeout=15)
    assert "goal 3 succeeded" in servers.output()  # Starting, filled from the parameter
    assert node.last_feedback is not None and list(node.last_feedback.sequence)
    before = unit.admin.last.prod_processed_count[0].count
    unit.to_execute()
    assert unit.wait_count("processed", before + 4) >= before + 4  # 2 per goal (len(sequence))
    assert not node.failures


def test_stop_cancels_the_goal_and_hold_lets_it_finish(ros, processes, tmp_path) -> None:
    em = move_em({"execute": {"goal": {"order": 20}, "repeat": True}})  # a 2 s move
    unit, servers, node = start(ros, processes, tmp_path, em)
    unit.to_execute()
    wait_until(lambda: node.last_feedback is not None, 10, what="the move under way")
    unit.command_to("hold", "HOLDING")
    unit.wait_entered("HELD", timeout=10)
    assert "goal 20 succeeded" in servers.output()  # Hold waited for the move to end
    assert "canceled" not in servers.output()
    unit.command_to("unhold", "EXECUTE")
    node.last_feedback = None
    wait_until(lambda: node.last_feedback is not None, 10, what="the next move under way")
    unit.command_to("stop", "STOPPING")
    unit.wait_entered("STOPPED", timeout=1.5)  # cancelled at its next step, not run to its end
    wait_until(lambda: "goal 20 canceled" in servers.output(), 5, what="the goal cancelled")
    assert not any(a.trigger for a in unit.alarms.last.alarms)  # a cancel asked for: no failure


def test_a_rejected_goal_raises_the_alarm_with_its_reaction(ros, processes, tmp_path) -> None:
    em = move_em({"starting": {"goal": {"order": -1}}})
    unit, _, node = start(ros, processes, tmp_path, em)
    unit.command_to("reset", "IDLE")
    unit.command_to("start", "STARTING")
    alarm = unit.wait_alarm(ALARM)
    assert alarm.value == Failure.REJECTED and "rejected" in alarm.message
    unit.wait_state("STOPPED")  # reaction: stop
    assert node.failures[0][0] is Failure.REJECTED


def test_a_goal_the_server_aborts_raises_the_alarm(ros, processes, tmp_path) -> None:
    em = move_em({"starting": {"goal": {"order": 1000}}})
    unit, _, _ = start(ros, processes, tmp_path, em)
    unit.command_to("reset", "IDLE")
    unit.command_to("start", "STARTING")
    alarm = unit.wait_alarm(ALARM, timeout=30)  # (a loaded CI took more than 10 s)
    assert alarm.value == Failure.FAILED and "aborted" in alarm.message, alarm.message
    unit.wait_state("STOPPED")


def test_a_server_that_dies_mid_goal_raises_the_alarm_and_the_cell_recovers_when_it_is_back(
    ros, processes, tmp_path
) -> None:
    em = move_em({"starting": {"goal": {"order": 50}}})  # a 5 s move
    unit, servers, node = start(ros, processes, tmp_path, em)
    unit.command_to("reset", "IDLE")
    unit.command_to("start", "STARTING")
    wait_until(lambda: node.last_feedback is not None, 10, what="the move under way")
    servers.kill()
    alarm = unit.wait_alarm(ALARM, timeout=15)
    assert alarm.value == Failure.LOST
    unit.wait_state("STOPPED")
    base = f"/{unit.cell}/{unit.unit}"
    # the dead server gone from the EM's graph first: while DDS still counts it (its lease), the
    # EM's client looks ready and a goal sent then can go to it instead of the new server
    wait_server_gone(node, f"{base}/move/_action/send_goal")
    again = processes.start("servers2", str(SERVERS), f"{base}/move", f"{base}/grip", "0.01")
    wait_ready(again, node, prime=False)  # (a restarted server: as a cell sees it)
    unit.command_to("reset", "IDLE", timeout=15)
    unit.command_to("start", "EXECUTE", timeout=15)


def test_a_service_em_calls_in_its_states_and_fails_on_a_no(ros, processes, tmp_path) -> None:
    em = gripper_em(
        {"starting": {"request": {"data": True}}, "stopping": {"request": {"data": False}}}
    )
    unit, _, node = start(ros, processes, tmp_path, em)
    unit.to_execute()
    assert not node.failures
    unit.command_to("stop", "STOPPING")
    alarm = unit.wait_alarm(ALARM)
    assert alarm.value == Failure.FAILED and "jaws jammed" in alarm.message


def test_a_server_that_is_not_there_raises_the_alarm_after_the_timeout(ros, tmp_path) -> None:
    em = gripper_em({"starting": {"request": {"data": True}}}, timeout=0.5)
    unit = EmTestUnit(ros, tmp_path, {"mover": em})
    node = create(str(unit.cell_file), unit.unit, "mover", context=ros.context)
    ros.add(node)
    unit.wait_online("mover")
    unit.command_to("reset", "IDLE")
    unit.command_to("start", "STARTING")
    assert unit.wait_alarm(ALARM).value == Failure.NO_SERVER
    assert isinstance(node, InterfaceEm)


# -- the cell-file block, validated -----------------------------------------------------------------
def problems(tmp_path: Path, em: dict[str, Any]) -> list[tuple[str, str]]:
    unit = unit_of(tmp_path, em)
    kind = "action" if "action" in em else "service"
    with pytest.raises(ConfigError) as info:
        parse_interface(em[kind], kind, f"units.u.equipment_modules.m.{kind}", "cell.yaml", unit)
    return info.value.problems


def unit_of(tmp_path: Path, em: dict[str, Any]) -> Any:
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({"cell": "c", "units": {"u": {"equipment_modules": {"m": em}}}}))
    return load_cell(path).units["u"]


@pytest.mark.parametrize(
    ("change", "where", "words"),
    [
        ({"type": "nope_msgs/action/Move"}, "action.type", "no interface package"),
        ({"type": "test_msgs/action/Nope"}, "action.type", "has no action"),
        ({"type": "test_msgs/srv/Empty"}, "action.type", "not an action type name"),
        (
            {"states": {"starting": {"goal": {"speed": 1}}}},
            "states.starting.goal",
            "no field 'speed'",
        ),
        (
            {"states": {"starting": {"goal": {"order": "fast"}}}},
            "states.starting.goal",
            "cannot be",
        ),
        ({"states": {"idle": {"goal": {}}}}, "states.idle", "not an acting state"),
        ({"states": {"starting": {"goal": {}, "repeat": True}}}, "repeat", "only Execute"),
        (
            {"states": {"execute": {"count": {"processed": "nothing"}}}},
            "count.processed",
            "no result field",
        ),
        ({"cancel_on": ["held"]}, "cancel_on[0]", "not an acting state"),
        ({"alarm": {"category": 2}}, "alarm", "needs an id"),
        ({"alarm": {"id": 5, "reaction": "hold", "category": 1}}, "alarm", "reacts otherwise"),
        ({"success": "ok"}, "success", "no result field 'ok'"),
        ({"speed": 3}, "action.speed", "unknown key"),
    ],
)
def test_a_wrong_action_block_is_refused_with_its_key_path(tmp_path, change, where, words) -> None:
    block = {"type": "test_msgs/action/Fibonacci", "name": "move", "alarm": {"id": 5},
             "states": {"starting": {"goal": {"order": 2}}}}  # fmt: skip
    block.update(change)
    found = problems(tmp_path, {"action": block})
    assert any(where in path and words in text for path, text in found), found


def test_an_em_cannot_be_both_an_action_and_a_service(tmp_path) -> None:
    with pytest.raises(ConfigError, match="both action and service given: an EM runs one way only"):
        unit_of(tmp_path, {"action": {"type": "x"}, "service": {"type": "y"}})


def test_the_launcher_starts_an_action_em_as_interface_em_and_refuses_a_wrong_block(
    tmp_path: Path,
) -> None:
    from packml_ros2 import launcher

    good = move_em({"starting": {"goal": {"order": 2}}})
    path = tmp_path / "cell.yaml"
    cell = {"cell": "c", "units": {"u": {"equipment_modules": {"mover": good, "sim": {"sim": {}}}}}}
    path.write_text(yaml.safe_dump(cell))
    plan = launcher.plan(path)
    runs = {(r.unit, r.em): r for r in plan.ems}
    assert runs[("u", "mover")].key == "action" and runs[("u", "sim")].key == "sim"
    assert runs[("u", "mover")].target == "packml_ros2.interface_em:InterfaceEm"
    specs = {s.name: s for s in launcher.node_specs(plan)}
    assert specs["em u/mover"].executable == "em_node"  # hosted like every EM class
    assert specs["em u/mover"].arguments == (str(path), "u", "mover")
    cell["units"]["u"]["equipment_modules"]["mover"]["action"]["states"]["starting"] = {
        "goal": {"speed": 1}
    }
    path.write_text(yaml.safe_dump(cell))
    with pytest.raises(ConfigError) as info:
        launcher.plan(path)
    assert any(
        p == "units.u.equipment_modules.mover.action.states.starting.goal"
        and "no field 'speed'" in t
        for p, t in info.value.problems
    ), info.value.problems


def test_the_readme_action_and_service_example_is_a_valid_cell(tmp_path: Path) -> None:
    from packml_ros2 import launcher
    from test.workspace.tools import code_blocks

    blocks = [b for b in code_blocks("yaml") if "action:" in b and "service:" in b]
    assert len(blocks) == 1, "the README's action/service EM example was not found"
    path = tmp_path / "cell.yaml"
    path.write_text("cell: readme\n" + blocks[0])
    plan = launcher.plan(path)
    kinds = {(r.unit, r.em): r.key for r in plan.ems}
    assert kinds == {("robot_cell", "mover"): "action", ("robot_cell", "gripper"): "service"}
    from packml_ros2.interface_em import _parsed

    mover = _parsed(plan.cell, "robot_cell", "mover", str(path))
    assert mover.category == 2  # reaction stop: the unit's first category that stops
