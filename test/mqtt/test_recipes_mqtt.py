"""Issue 32 over MQTT: the recipe and the stack light of a unit as Sparkplug B metrics, and the
recipe change as a DCMD, seen by an independent host application (Tahu's protobuf,
:mod:`test.mqtt.host`) on a real broker (Debian's mosquitto).

Issue 32's recipe cell (test/recipe_cell.py: unit ``filler``, EMs robot, gripper, vision, two
recipes, recipe 1 at start) run by ``packml launch``, with ``packml mqtt``:

- the first DBIRTH has ``Recipe/Current`` 1 ``cola 0.5`` and the stack light as the unit's status
  shows it (``StackLight/<n>/Color``, ``Mode``, ``ModeName``, ``StackLight/Horn``);
- ``Command/Recipe`` = 2 is answered accepted, then DDATA shows the changeover run and
  ``Recipe/Current`` 2; by name back to 1; an unknown recipe is answered refused with result 20
  (RECIPE_UNKNOWN) and the unit's sentence; ID 0 is refused by the edge itself;
- Idle -> Execute: the lights that change come in DDATA (and only they); the UNS document names
  the recipe in use.

Every wait is on a message, never a fixed sleep.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.testing.processes import NodeProcess, Processes, wait_until
from test.mqtt.host import Broker, Host, Seen, close_all, closed_cleanly
from test.recipe_cell import recipe_cell
from test.ros.cells import UnitClient

pytestmark = pytest.mark.ros

CELL, GROUP, EDGE_CLIENT, UNS = "recipe_mqtt", "plant", "edge-recipes", "acme/site1/filling/line2"
INT32, STRING = 3, 12
DEVICE = "filler"


def answer_to(request_id: str) -> Any:
    return lambda s: s.kind == "DDATA" and s.metrics.get("Command/Answer/RequestId") == request_id


class Face:
    def __init__(self, tmp: Path) -> None:
        self.broker = Broker(tmp)
        doc = recipe_cell(CELL)
        doc["coordinator"] = {"enabled": False}
        doc["mqtt"] = {
            "port": self.broker.port,
            "group_id": GROUP,
            "client_id": EDGE_CLIENT,
            "keepalive": 2,
            "uns": {"prefix": UNS},
        }
        self.path = tmp / f"{CELL}.yaml"
        self.path.write_text(yaml.safe_dump(doc, sort_keys=False))
        (tmp / "logs").mkdir()
        self.procs = Processes(tmp / "logs")
        self.host = Host(self.broker.port, GROUP, extra=(f"{UNS}/#",))
        self.dcmd = f"spBv1.0/{GROUP}/DCMD/{CELL}/{DEVICE}"
        self.launch: NodeProcess | None = None

    def start(self) -> None:
        self.launch = launch = self.procs.module(
            "launch", "packml_ros2.cli.main", "launch", str(self.path)
        )
        wait_until(lambda: "is up" in launch.output() or not launch.running(), 60, 0.05, "the cell")
        assert launch.running(), launch.output()
        self.procs.module("mqtt", "packml_ros2.cli.main", "mqtt", str(self.path))

    def command(self, request_id: str, metric: str, dtype: int, value: Any) -> Seen:
        mark = self.host.mark()
        self.host.send(
            self.dcmd, [("Command/RequestId", STRING, request_id), (metric, dtype, value)]
        )
        return self.host.wait(answer_to(request_id), 30, f"the answer to {request_id}", after=mark)

    def data(self, predicate: Any, what: str, after: int) -> Seen:
        """The first DBIRTH or DDATA of the unit from ``after`` on whose metrics satisfy it."""
        return self.host.wait(
            lambda s: s.device == DEVICE and s.kind in ("DBIRTH", "DDATA") and predicate(s.metrics),
            30,
            what,
            after=after,
        )

    def values(self) -> dict[str, Any]:
        """The unit's metrics now, as a host application keeps them: its last DBIRTH, updated by
        every DDATA since."""
        now: dict[str, Any] = {}
        for s in self.host.since(0):
            if s.device != DEVICE:
                continue
            if s.kind == "DBIRTH":
                now = dict(s.metrics)
            elif s.kind == "DDATA":
                now.update(s.metrics)
        return now

    def lights(self, modes: list[int], what: str) -> None:
        """Wait until the host's values of every ``StackLight/<n>/Mode`` are ``modes``."""
        wait_until(
            lambda: [self.values().get(f"StackLight/{i}/Mode") for i in range(len(modes))] == modes,
            20,
            0.05,
            what,
        )

    def close(self) -> str:
        return close_all(self.host, self.procs, self.broker)


@pytest.fixture
def face(tmp_path: Path) -> Iterator[Face]:
    with closed_cleanly(Face(tmp_path)) as f:
        yield f


def _answer(seen: Seen) -> tuple[Any, ...]:
    m = seen.metrics
    return (
        m["Command/Answer/Accepted"],
        m["Command/Answer/Result"],
        m["Command/Answer/Reason"],
        m["Command/Answer/Command"],
    )


@pytest.mark.timeout(300)
def test_a_host_application_reads_the_recipe_and_the_stack_light_and_changes_the_recipe(
    face: Face, ros: Any
) -> None:
    face.start()
    host = face.host
    filler = UnitClient(ros, CELL, DEVICE)
    filler.ready(30)
    filler.wait_status(
        lambda m: len(m.equipment_modules) == 3 and all(e.online for e in m.equipment_modules),
        30,
        "the three EMs online",
    )

    # -- the first DBIRTH: the recipe in use and the stack light, as the status has them -----------
    born = host.wait(lambda s: s.kind == "DBIRTH" and s.device == DEVICE, 60, "the DBIRTH")
    assert born.metrics["Recipe/Current"] == 1, born.metrics
    assert born.metrics["Recipe/CurrentName"] == "cola 0.5"
    assert born.metrics["Recipe/Requested"] == 0
    assert born.metrics["Recipe/ChangeInProcess"] is False
    assert born.metrics["Recipe/Result"] == ""
    assert born.metrics["Command/Recipe"] == 1
    types = {m.name: m.datatype for m in born.payload.metrics}
    assert (types["Recipe/Current"], types["Recipe/ChangeInProcess"]) == (INT32, 11)
    assert (types["Command/Recipe"], types["Recipe/CurrentName"]) == (INT32, STRING)
    light = filler.status.last.stack_light
    colors = list(light.colors)
    assert colors and [born.metrics[f"StackLight/{i}/Color"] for i in range(len(colors))] == colors
    assert f"StackLight/{len(colors)}/Color" not in born.metrics
    assert "StackLight/Horn" in born.metrics
    names = {0: "off", 1: "on", 2: "blink"}
    for i in range(len(colors)):
        mode = born.metrics[f"StackLight/{i}/Mode"]
        assert born.metrics[f"StackLight/{i}/ModeName"] == names[mode]
    assert host.errors == []

    # -- Command/Recipe = 2: accepted; the changeover runs; Recipe/Current becomes 2 -----------------
    mark = host.mark()
    answer = face.command("q-recipe-2", "Command/Recipe", INT32, 2)
    assert _answer(answer) == (True, 0, "ACCEPTED", "Command/Recipe=2"), answer.metrics
    assert "recipe 2" in answer.metrics["Command/Answer/Message"], answer.metrics
    face.data(lambda m: m.get("Recipe/ChangeInProcess") is True, "the changeover running", mark)
    changed = face.data(lambda m: m.get("Recipe/Current") == 2, "Recipe/Current 2", mark)
    assert changed.kind == "DDATA" and changed.metrics["Recipe/CurrentName"] == "water 1.0"
    now = face.values()
    assert (now["Recipe/ChangeInProcess"], now["Command/Recipe"]) == (False, 2), now
    assert not [s for s in host.since(mark) if s.kind == "DBIRTH"]  # the metrics stayed the same
    # the unit recorded who asked
    wait_until(
        lambda: f"by mqtt:{EDGE_CLIENT}" in face.launch.output() if face.launch else False,
        10,
        0.05,
        "the changeover's source in the unit's log",
    )
    # the UNS document names the recipe in use
    doc = host.wait(
        lambda s: s.topic == f"{UNS}/{CELL}/{DEVICE}/packml" and s.payload.get("recipe_id") == 2,
        20,
        "the UNS document with recipe 2",
    )
    assert doc.payload["recipe"] == "water 1.0", doc.payload

    # -- by name, back to 1 ------------------------------------------------------------------------
    mark = host.mark()
    answer = face.command("q-recipe-cola", "Command/Recipe", STRING, "cola 0.5")
    assert _answer(answer) == (True, 0, "ACCEPTED", "Command/Recipe=cola 0.5"), answer.metrics
    face.data(lambda m: m.get("Recipe/Current") == 1, "Recipe/Current 1 again", mark)

    # -- refusals come back as answers: the unit's (RECIPE_UNKNOWN 20), the edge's (ID 0) -----------
    mark = host.mark()
    unknown = face.command("q-recipe-99", "Command/Recipe", INT32, 99)
    assert _answer(unknown) == (False, 20, "RECIPE_UNKNOWN", "Command/Recipe=99"), unknown.metrics
    assert "99" in unknown.metrics["Command/Answer/Message"], unknown.metrics
    by_name = face.command("q-recipe-beer", "Command/Recipe", STRING, "beer")
    assert _answer(by_name)[:3] == (False, 20, "RECIPE_UNKNOWN"), by_name.metrics
    zero = face.command("q-recipe-0", "Command/Recipe", INT32, 0)
    assert _answer(zero)[:3] == (False, 13, "out_of_range"), zero.metrics
    assert face.values()["Recipe/Current"] == 1
    assert not [s for s in host.since(mark) if s.metrics.get("Recipe/ChangeInProcess") is True]

    # -- Idle -> Execute: the lights that change, in DDATA --------------------------------------------
    mark = host.mark()
    assert _answer(face.command("q-reset", "Command/CntrlCmd", STRING, "reset"))[0] is True
    face.data(lambda m: m.get("State/CurrentName") == "IDLE", "IDLE", mark)
    in_idle = filler.wait_state("IDLE", 20).stack_light
    face.lights(list(in_idle.modes), "the stack light of IDLE")
    mark = host.mark()
    assert _answer(face.command("q-start", "Command/CntrlCmd", STRING, "start"))[0] is True
    face.data(lambda m: m.get("State/CurrentName") == "EXECUTE", "EXECUTE", mark)
    in_execute = filler.wait_state("EXECUTE", 20).stack_light
    differs = [i for i in range(len(colors)) if in_idle.modes[i] != in_execute.modes[i]]
    assert differs, (list(in_idle.modes), list(in_execute.modes))  # the preset lights Execute
    face.lights(list(in_execute.modes), "the stack light of EXECUTE")
    green = colors.index("green")
    now = face.values()
    assert (now[f"StackLight/{green}/Mode"], now[f"StackLight/{green}/ModeName"]) == (1, "on")
    sent = {k for s in host.since(mark) if s.device == DEVICE for k in s.metrics}
    assert {f"StackLight/{i}/Mode" for i in differs} <= sent, sent
    # on change only: the colours never change, and the lights that stayed are not sent again
    assert not {k for k in sent if k.endswith("/Color")}, sent
    assert not {f"StackLight/{i}/Mode" for i in range(len(colors)) if i not in differs} & sent
    assert host.errors == []
