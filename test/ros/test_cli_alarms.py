"""``packml alarms`` lists the current alarms from the units' latched ``alarms`` topic (no service
round trip: issue 13's one-second budget for read-only verbs). What it prints must be what the
``query_alarms`` service would give, for every filter and order; a list longer than the topic
holds, and the history, still come from the service."""

from __future__ import annotations

import argparse
import itertools
from typing import Any

import pytest
from packml_interfaces.srv import AckAlarms, SetAlarm

from packml_ros2.cli import alarms as cli
from packml_ros2.cli.main import build_parser
from packml_ros2.client import UnitProxy
from packml_ros2.core.alarms import ORDERS
from test.ros.test_unit_services import make_unit

__all__ = ["make_unit"]  # the fixture

RAISED = [  # id, category, warning, message
    (11, 7, False, "glue low"),
    (12, 5, True, "label roll near end"),
    (13, 9, False, "door ajar"),
    (14, 5, False, "vacuum weak"),
    (15, 8, True, "filter due"),
]


def args(**given: Any) -> argparse.Namespace:
    defaults = {"action": "list", "history": False, "active": False, "category": None}
    return argparse.Namespace(**{**defaults, "sort": "time", **given})


def test_the_latched_list_prints_what_query_alarms_answers(ros: Any, make_unit: Any) -> None:
    unit = make_unit()
    for alarm_id, category, warning, message in RAISED:
        resp = unit.call(SetAlarm, "set_alarm", id=alarm_id, category=category, warning=warning,
                         message=message, active=True)  # fmt: skip
        assert resp.accepted, resp.message_out
    assert unit.call(SetAlarm, "set_alarm", id=13, active=False).accepted  # cleared, not acked
    assert unit.call(AckAlarms, "ack_alarms", id=11).accepted
    unit.wait_alarms(lambda a: len(a.alarms) + len(a.warnings) == 5 and any(
        a.id == 11 and a.acknowledged for a in a.alarms), what="the list")  # fmt: skip

    proxy = UnitProxy(ros.node, unit.base, topics=("alarms",))
    proxy.wait_alarms(10)
    orders = list(ORDERS)
    assert set(orders) == set(cli.SORTS)  # every order of the service
    for sort, active, category in itertools.product(orders, (False, True), (None, 5, 3)):
        given = args(sort=sort, active=active, category=category)
        latched, code = cli._listed(proxy, given, 10)
        asked, _ = cli._list(proxy, given, 10)
        assert code == 0 and latched == asked, (sort, active, category, latched, asked)
    text, _ = cli._listed(proxy, args(), 10)
    lines = text.splitlines()[1:]
    assert [line.split()[1].split("/")[0] for line in lines] == ["11", "12", "13", "14", "15"]
    assert "acked" in lines[0] and "cleared" in lines[2] and "warning" in lines[1]
    assert cli._listed(proxy, args(category=3), 10)[0] == f"{proxy.name}: no alarms"


def test_an_overflowing_list_is_asked_for(ros: Any, make_unit: Any) -> None:
    """The topic holds the configured capacity and counts the rest: then the service answers."""
    unit = make_unit({"sizes": {"alarms": 2}})
    for alarm_id in range(21, 25):
        resp = unit.call(SetAlarm, "set_alarm", id=alarm_id, category=7, message=f"a{alarm_id}",
                         active=True)  # fmt: skip
        assert resp.accepted, resp.message_out
    unit.wait_alarms(lambda a: a.alarm_overflow == 2, what="the overflow")
    proxy = UnitProxy(ros.node, unit.base, topics=("alarms",))
    text, _ = cli._listed(proxy, args(), 10)
    assert [line.split()[1].split("/")[0] for line in text.splitlines()[1:]] == [
        "21", "22", "23", "24"]  # fmt: skip


@pytest.mark.parametrize(
    ("typed", "action", "unit"),
    [
        ("", "list", None),
        ("robot_cell", "list", "robot_cell"),  # was a usage error (issue 24)
        ("--history robot_cell", "list", "robot_cell"),  # was a usage error (issue 24)
        ("robot_cell --history", "list", "robot_cell"),
        ("list robot_cell --history", "list", "robot_cell"),
        ("ack robot_cell", "ack", "robot_cell"),
        ("robot_cell ack", "ack", "robot_cell"),
        ("reset", "reset", None),
    ],
)
def test_the_forms_people_type(typed: str, action: str, unit: str | None) -> None:
    args = build_parser("alarms").parse_args(["alarms", *typed.split()])
    assert cli.words(args) is None
    assert (args.action, args.unit, args.history) == (action, unit, "--history" in typed)


def test_two_words_that_are_not_an_action_and_a_unit_are_a_usage_error() -> None:
    args = build_parser("alarms").parse_args(["alarms", "lsit", "robot_cell"])
    assert cli.words(args) == (
        "alarms: neither 'lsit' nor 'robot_cell' is one of list, ack, reset"
        " (packml alarms [ACTION] [UNIT])"
    )
