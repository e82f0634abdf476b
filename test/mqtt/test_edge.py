"""packml_ros2.mqtt.edge: the Sparkplug B rules of the edge node, without a broker or ROS (real
interface messages, a clock of our own); payloads read back with Tahu's protobuf."""

from __future__ import annotations

import json
from typing import Any

import pytest
from packml_interfaces.msg import Admin, Count, EmSummary, StackLight, Status
from pysparkplug._protobuf import Payload as TahuPayload

from packml_ros2.core.config import parse_cell
from packml_ros2.mqtt import edge as e
from packml_ros2.mqtt import sparkplug as sp
from packml_ros2.mqtt.config import parse_mqtt
from packml_ros2.mqtt.sparkplug import DataType as T
from packml_ros2.mqtt.sparkplug import Metric, Payload
from test.mqtt.host import metric_value


def make_edge(**mqtt: Any) -> e.Edge:
    cell = parse_cell({"cell": "c1", "units": {"filler": {}, "capper": {}}, "mqtt": mqtt})
    clock = iter(range(1_000_000, 10**9, 10))
    return e.Edge(parse_mqtt(cell), lambda: next(clock))


def status(state: int = 2, ems: tuple[str, ...] = ("nozzle",), speed: float = 10.0) -> Status:
    return Status(unit="filler", state_current=state, state_current_name=f"S{state}",
                  unit_mode_current=1, unit_mode_current_name="PRODUCTION", mach_speed=speed,
                  equipment_modules=[EmSummary(name=n, online=True, active=True) for n in ems])  # fmt: skip


def admin(count: int = 0) -> Admin:
    a = Admin(unit="filler", state_current_time=[0] * 32 * 18, mode_current_time=[0] * 32)
    a.prod_processed_count = [Count(id=1, name="bottles", count=count, acc_count=count)]
    return a


def decoded(m: e.Message) -> tuple[Any, dict[str, Any]]:
    p = TahuPayload.FromString(m.payload)
    return p, {(x.name or x.alias): metric_value(x) for x in p.metrics}


def born(edge: e.Edge) -> list[e.Message]:
    edge.connecting()
    out = edge.connected_births()
    out += edge.update("filler", "status", status())
    out += edge.update("filler", "admin", admin())
    return out


def test_births_sequence_numbers_and_the_will() -> None:
    edge = make_edge()
    will = edge.connecting()
    assert will.topic == "spBv1.0/packml/NDEATH/c1" and will.qos == 1 and not will.retain
    assert decoded(will)[1] == {"bdSeq": 0}
    (nbirth,) = edge.connected_births()
    p, metrics = decoded(nbirth)
    assert p.seq == 0 and metrics == {"bdSeq": 0, "Node Control/Rebirth": False}
    assert edge.update("filler", "status", status()) == []  # born with the admin data too
    (dbirth,) = edge.update("filler", "admin", admin())
    p, metrics = decoded(dbirth)
    assert dbirth.topic == "spBv1.0/packml/DBIRTH/c1/filler" and p.seq == 1
    assert metrics["Admin/ProdProcessedCount/1/Count"] == 0 and metrics["EM/nozzle/Online"] is True
    assert all(m.name and m.HasField("alias") for m in p.metrics)
    # bdSeq: +1 per connection, modulo 256; the will carries the connection's
    for expected in [*range(1, 256), 0]:
        assert decoded(edge.connecting())[1] == {"bdSeq": expected}
    # seq: +1 per message, modulo 256
    edge.connected_births()
    seqs = [
        decoded(m)[0].seq for i in range(300) for m in edge.update("filler", "admin", admin(i + 1))
    ]
    assert seqs[:3] == [2, 3, 4] and seqs[253:256] == [255, 0, 1], seqs[250:258]


def test_data_is_what_changed_by_alias_and_a_new_em_is_a_new_birth() -> None:
    edge = make_edge()
    out = born(edge)
    aliases = {m.name: m.alias for m in decoded(out[-1])[0].metrics}
    assert edge.update("filler", "status", status()) == []  # nothing changed: nothing sent
    (ddata,) = edge.update("filler", "status", status(state=6, speed=12.0))
    _, metrics = decoded(ddata)
    assert ddata.topic == "spBv1.0/packml/DDATA/c1/filler"
    assert metrics == {aliases["State/Current"]: 6, aliases["State/CurrentName"]: "S6",
                       aliases["MachSpeed"]: 12.0}  # fmt: skip
    rebirth, = edge.update("filler", "status", status(state=6, speed=12.0, ems=("nozzle", "capper")))  # fmt: skip
    assert rebirth.topic.startswith("spBv1.0/packml/DBIRTH/")
    assert "EM/capper/Online" in decoded(rebirth)[1]
    assert edge.update("nobody", "status", status()) == []


def test_a_lost_unit_dies_once_and_is_born_from_fresh_messages() -> None:
    edge = make_edge()
    born(edge)
    (ddeath,) = edge.presence("filler", False)
    p, metrics = decoded(ddeath)
    assert ddeath.topic == "spBv1.0/packml/DDEATH/c1/filler" and metrics == {} and p.seq == 2
    assert edge.presence("filler", False) == []
    assert edge.presence("filler", True) == []
    assert edge.update("filler", "status", status()) == []  # the admin data first
    (birth,) = edge.update("filler", "admin", admin())
    assert birth.topic.endswith("DBIRTH/c1/filler")
    # a rebirth request: NBIRTH and every DBIRTH again, the same bdSeq
    again = edge.node_command(sp.encode(Payload(1, (Metric(e.REBIRTH, T.Boolean, True),))))
    assert [m.topic.split("/")[2] for m in again] == ["NBIRTH", "DBIRTH"]
    with pytest.raises(e.Refused):
        edge.node_command(sp.encode(Payload(1, (Metric(e.REBIRTH, T.Boolean, False),))))


def dcmd(*metrics: Metric) -> bytes:
    return sp.encode(Payload(42, metrics))


@pytest.mark.parametrize(
    ("metrics", "service", "fields", "shown"),
    [
        ((Metric("Command/CntrlCmd", T.Int32, 2),), "command", {"command": 2}, "Command/CntrlCmd=START"),
        ((Metric("Command/CntrlCmd", T.String, " reset "),), "command", {"command": 1}, "Command/CntrlCmd=RESET"),
        ((Metric("Command/UnitMode", T.Int32, 2),), "set_mode", {"mode": 2}, "Command/UnitMode=2"),
        ((Metric("Command/UnitMode", T.String, "Manual"),), "set_mode", {"mode": 0, "mode_name": "Manual"}, "Command/UnitMode=Manual"),
        ((Metric("Command/MachSpeed", T.Float, 12.5),), "set_mach_speed", {"mach_speed": 12.5}, "Command/MachSpeed=12.5"),
        ((Metric("Command/AckAlarms", T.Int32, 0),), "ack_alarms", {"all": True, "id": 0}, "Command/AckAlarms=0"),
        ((Metric("Command/AckAlarms", T.UInt32, 201),), "ack_alarms", {"all": False, "id": 201}, "Command/AckAlarms=201"),
        ((Metric("Command/Recipe", T.Int32, 2),), "set_recipe", {"recipe_id": 2, "recipe_name": ""}, "Command/Recipe=2"),
        ((Metric("Command/Recipe", T.UInt64, 7),), "set_recipe", {"recipe_id": 7, "recipe_name": ""}, "Command/Recipe=7"),
        ((Metric("Command/Recipe", T.String, " water 1.0 "),), "set_recipe", {"recipe_id": 0, "recipe_name": "water 1.0"}, "Command/Recipe=water 1.0"),
    ],
)  # fmt: skip
def test_a_command_becomes_one_request(metrics: Any, service: str, fields: Any, shown: str) -> None:
    edge = make_edge()
    born(edge)
    r = edge.command("filler", dcmd(Metric(e.REQUEST_ID, T.String, "q1"), *metrics))
    assert (r.service, r.fields, r.shown, r.request_id) == (service, fields, shown, "q1")
    # without a request id, the answer names the metric and the payload's timestamp
    assert edge.command("filler", dcmd(*metrics)).request_id == f"{metrics[0].name}@42"


def test_a_command_by_alias() -> None:
    edge = make_edge()
    birth = born(edge)[-1]
    alias = next(m.alias for m in decoded(birth)[0].metrics if m.name == "Command/CntrlCmd")
    r = edge.command("filler", dcmd(Metric(None, T.Int32, 3, alias=alias)))
    assert (r.service, r.fields) == ("command", {"command": 3})


@pytest.mark.parametrize(
    ("unit", "metrics", "reason"),
    [
        ("nobody", (Metric("Command/CntrlCmd", T.Int32, 2),), "unknown_device"),
        ("filler", (), "one_command"),
        ("filler", (Metric("Command/CntrlCmd", T.Int32, 2), Metric("Command/CntrlCmd", T.Int32, 3)), "one_command"),
        ("filler", (Metric("State/Current", T.Int32, 6),), "unknown_metric"),  # not writable
        ("filler", (Metric(None, T.Int32, 6, alias=99_999),), "unknown_metric"),
        ("filler", (Metric("Command/CntrlCmd", T.Int32, 11),), "out_of_range"),
        ("filler", (Metric("Command/CntrlCmd", T.Int32, 0),), "out_of_range"),
        ("filler", (Metric("Command/CntrlCmd", T.String, "undefined"),), "out_of_range"),
        ("filler", (Metric("Command/CntrlCmd", T.Double, 2.0),), "wrong_type"),
        ("filler", (Metric("Command/CntrlCmd", T.Int32, None),), "wrong_type"),
        ("filler", (Metric("Command/UnitMode", T.Int32, 32),), "out_of_range"),
        ("filler", (Metric("Command/UnitMode", T.String, " "),), "out_of_range"),
        ("filler", (Metric("Command/MachSpeed", T.Boolean, True),), "wrong_type"),
        ("filler", (Metric("Command/AckAlarms", T.Int32, -1),), "out_of_range"),
        ("filler", (Metric("Command/Recipe", T.Int32, 0),), "out_of_range"),  # 0: by name
        ("filler", (Metric("Command/Recipe", T.Int32, -2),), "out_of_range"),
        ("filler", (Metric("Command/Recipe", T.Int64, 2**31),), "out_of_range"),
        ("filler", (Metric("Command/Recipe", T.String, "  "),), "out_of_range"),
        ("filler", (Metric("Command/Recipe", T.String, "x" * 256),), "out_of_range"),
        ("filler", (Metric("Command/Recipe", T.Double, 2.0),), "wrong_type"),
        ("filler", (Metric("Command/Recipe", T.Boolean, True),), "wrong_type"),
        ("filler", (Metric("Command/Recipe", T.Int32, 1), Metric("Command/CntrlCmd", T.Int32, 2)), "one_command"),
        ("filler", (Metric(e.REQUEST_ID, T.Int32, 1), Metric("Command/CntrlCmd", T.Int32, 2)), "wrong_type"),
    ],
)  # fmt: skip
def test_a_command_that_cannot_be_taken_is_refused_whole(
    unit: str, metrics: Any, reason: str
) -> None:
    edge = make_edge()
    born(edge)
    with pytest.raises(e.Refused) as refused:
        edge.command(unit, dcmd(*metrics))
    assert refused.value.reason == reason, refused.value


def test_a_refusal_of_the_edge_names_the_request_and_the_command_metric() -> None:
    edge = make_edge()
    born(edge)
    refusals = [
        # the request id after the command, or before a metric that is not one: named
        (
            dcmd(Metric("Command/Recipe", T.Int32, 0), Metric(e.REQUEST_ID, T.String, "q9")),
            ("out_of_range", "q9", "Command/Recipe"),
        ),
        (
            dcmd(Metric("Command/Nonsense", T.Int32, 1), Metric(e.REQUEST_ID, T.String, "q10")),
            ("unknown_metric", "q10", ""),
        ),
        # none given: the metric and the payload's timestamp, as an accepted command's answer
        (
            dcmd(Metric("Command/Recipe", T.String, "")),
            ("out_of_range", "Command/Recipe@42", "Command/Recipe"),
        ),
        (dcmd(), ("one_command", "", "")),
    ]
    for raw, expected in refusals:
        with pytest.raises(e.Refused) as refused:
            edge.command("filler", raw)
        r = refused.value
        assert (r.reason, r.request_id, r.shown) == expected, r


def test_every_answer_is_sent_whole_and_counted() -> None:
    edge = make_edge()
    birth = born(edge)[-1]
    names = {m.alias: m.name for m in decoded(birth)[0].metrics}
    for n in (1, 2):
        msg, = edge.answer("filler", "q1", "Command/CntrlCmd=START", False, 4, "REMOTE_DISABLED", "locked")  # fmt: skip
        metrics = {names[k]: v for k, v in decoded(msg)[1].items()}
        assert metrics == {"Command/Answer/Count": n, "Command/Answer/RequestId": "q1",
                           "Command/Answer/Command": "Command/CntrlCmd=START",
                           "Command/Answer/Accepted": False, "Command/Answer/Result": 4,
                           "Command/Answer/Reason": "REMOTE_DISABLED",
                           "Command/Answer/Message": "locked"}  # fmt: skip


def test_uns_documents_are_retained_published_on_change_and_unknown_when_lost() -> None:
    edge = make_edge(uns={"prefix": "acme/site/area/line"})
    born(edge)
    (doc,) = edge.uns("filler", True)
    assert doc.topic == "acme/site/area/line/c1/filler/packml" and doc.retain and doc.qos == 1
    body = json.loads(doc.payload)
    assert (body["state"], body["umh_state"], body["online"]) == ("S2", e.UMH_STOP, True)
    assert (body["recipe_id"], body["recipe"]) == (0, "")  # a unit without recipes
    assert body["counts"]["ProdProcessedCount"]["1"] == {"count": 0, "acc_count": 0}
    assert edge.uns("filler", True) == []  # unchanged
    edge.update("filler", "status", status(state=6))
    assert json.loads(edge.uns("filler", True)[0].payload)["umh_state"] == e.UMH_PRODUCING
    edge.update("filler", "status", recipe_status(state=6, recipe=(2, "water 1.0")))
    body = json.loads(edge.uns("filler", True)[0].payload)
    assert (body["recipe_id"], body["recipe"]) == (2, "water 1.0")
    lost = json.loads(edge.uns("filler", False)[0].payload)
    assert (lost["online"], lost["umh_state"], lost["state"]) == (False, e.UMH_UNKNOWN, "UNKNOWN")
    assert (lost["recipe_id"], lost["recipe"]) == (0, "")
    assert make_edge().uns("filler", True) == []  # no prefix: no UNS


@pytest.mark.parametrize(
    ("state", "code"),
    [(6, 10000), (10, 20000), (3, 20000), (8, 20000), (1, 40000), (2, 40000), (4, 40000),
     (5, 40000), (9, 40000), (11, 40000), (17, 40000), (0, 30000), (99, 30000)],
)  # fmt: skip
def test_umh_codes(state: int, code: int) -> None:
    assert e.umh_code(state, True) == code
    assert e.umh_code(state, False) == e.UMH_UNKNOWN


# -- recipes and the stack light --------------------------------------------------------------------
LIGHTS = ["red", "amber", "green", "blue"]
INT32, UINT32, BOOLEAN, STRING = 3, 7, 11, 12  # Tahu's DataType numbers


def recipe_status(
    state: int = 2,
    recipe: tuple[int, str] = (1, "cola 0.5"),
    requested: int = 0,
    changeover: int = 0,
    result: str = "",
    modes: tuple[int, ...] = (0, 1, 0, 0),
    horn: bool = False,
) -> Status:
    """A status of a unit with recipes and the OMAC stack light (red, amber, green, blue)."""
    s = status(state)
    s.recipe_current, s.recipe_current_name = recipe
    s.recipe_requested, s.recipe_change_in_process = requested, requested != 0
    s.recipe_changeover, s.recipe_result = changeover, result
    s.stack_light = StackLight(colors=LIGHTS, modes=list(modes), horn=horn)
    return s


def born_with_recipes(edge: e.Edge) -> tuple[Any, dict[str, int]]:
    """The DBIRTH of a unit whose first status has a recipe and a stack light, and its aliases."""
    edge.connecting()
    edge.connected_births()
    edge.update("filler", "status", recipe_status())
    (birth,) = edge.update("filler", "admin", admin())
    p = TahuPayload.FromString(birth.payload)
    return p, {m.name: m.alias for m in p.metrics}


def named(message: e.Message, aliases: dict[str, int]) -> dict[str, Any]:
    names = {alias: name for name, alias in aliases.items()}
    return {names[k]: v for k, v in decoded(message)[1].items()}


def test_the_recipe_and_the_stack_light_are_in_the_first_birth_with_their_types() -> None:
    p, _ = born_with_recipes(make_edge())
    metrics = {m.name: (m.datatype, metric_value(m)) for m in p.metrics}
    expected = {
        "Recipe/Current": (INT32, 1),
        "Recipe/CurrentName": (STRING, "cola 0.5"),
        "Recipe/Requested": (INT32, 0),
        "Recipe/ChangeInProcess": (BOOLEAN, False),
        "Recipe/Changeover": (UINT32, 0),
        "Recipe/Result": (STRING, ""),
        "Command/Recipe": (INT32, 1),  # the recipe in use
        "StackLight/Horn": (BOOLEAN, False),
    }
    for i, (color, mode, name) in enumerate(
        [("red", 0, "off"), ("amber", 1, "on"), ("green", 0, "off"), ("blue", 0, "off")]
    ):
        expected[f"StackLight/{i}/Color"] = (STRING, color)
        expected[f"StackLight/{i}/Mode"] = (INT32, mode)
        expected[f"StackLight/{i}/ModeName"] = (STRING, name)
    assert {k: metrics.get(k) for k in expected} == expected
    assert not {k for k in metrics if k.startswith("StackLight/4/")}


def test_a_unit_without_recipes_or_stack_light_has_recipe_zero_and_no_lights() -> None:
    edge = make_edge()
    _, metrics = decoded(born(edge)[-1])
    assert (metrics["Recipe/Current"], metrics["Recipe/CurrentName"]) == (0, "")
    assert metrics["Command/Recipe"] == 0
    assert not [k for k in metrics if k.startswith("StackLight/")]  # a PLC's: no stack light
    assert edge.update("filler", "status", status()) == []


def test_a_changeover_is_data_of_what_changed_and_never_a_new_birth() -> None:
    edge = make_edge()
    _, aliases = born_with_recipes(edge)
    # asked for recipe 2: the changeover runs
    (ddata,) = edge.update("filler", "status", recipe_status(requested=2, changeover=1))
    assert ddata.topic == "spBv1.0/packml/DDATA/c1/filler"
    assert named(ddata, aliases) == {
        "Recipe/Requested": 2,
        "Recipe/ChangeInProcess": True,
        "Recipe/Changeover": 1,
    }
    # refused by an EM: rolled back, the result says why
    why = "recipe 2 'water 1.0' refused: EM gripper refused it"
    (ddata,) = edge.update("filler", "status", recipe_status(changeover=1, result=why))
    assert named(ddata, aliases) == {
        "Recipe/Requested": 0,
        "Recipe/ChangeInProcess": False,
        "Recipe/Result": why,
    }
    # again, and through: the recipe in use changes (Command/Recipe with it)
    edge.update("filler", "status", recipe_status(requested=2, changeover=2, result=why))
    done = recipe_status(recipe=(2, "water 1.0"), changeover=2, result="recipe 2 applied")
    (ddata,) = edge.update("filler", "status", done)
    assert named(ddata, aliases) == {
        "Recipe/Current": 2,
        "Recipe/CurrentName": "water 1.0",
        "Recipe/Requested": 0,
        "Recipe/ChangeInProcess": False,
        "Recipe/Result": "recipe 2 applied",
        "Command/Recipe": 2,
    }
    assert edge.update("filler", "status", done) == []


def test_the_stack_light_is_data_on_change_only() -> None:
    edge = make_edge()
    _, aliases = born_with_recipes(edge)
    # Idle -> Execute: amber off, green on; the colours do not change, so they are not sent
    (ddata,) = edge.update("filler", "status", recipe_status(state=6, modes=(0, 0, 1, 0)))
    sent = named(ddata, aliases)
    assert {k: v for k, v in sent.items() if k.startswith("StackLight/")} == {
        "StackLight/1/Mode": 0,
        "StackLight/1/ModeName": "off",
        "StackLight/2/Mode": 1,
        "StackLight/2/ModeName": "on",
    }, sent
    # a state change that leaves the light as it is sends none of it
    (ddata,) = edge.update("filler", "status", recipe_status(state=4, modes=(0, 0, 1, 0)))
    assert not [k for k in named(ddata, aliases) if k.startswith("StackLight/")]
    # an unacknowledged alarm: red blinks, the horn sounds
    (ddata,) = edge.update("filler", "status", recipe_status(4, modes=(2, 0, 1, 0), horn=True))
    assert named(ddata, aliases) == {
        "StackLight/0/Mode": 2,
        "StackLight/0/ModeName": "blink",
        "StackLight/Horn": True,
    }
