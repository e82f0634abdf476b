"""Issue 30: ``packml mqtt`` — the cell as a Sparkplug B edge node on a real broker (Debian's
mosquitto), seen by an independent host application (Tahu's protobuf, :mod:`test.mqtt.host`).

One cell (a filler with an EM, counts and alarms, remote commands enabled; a capper with the
remote lock on), its units in their own processes, the face started as the README says. The host
sees the cell born, follows it through reset/start/fault/stop, commands it and reads each answer
(the remote lock's refusal too), sends 10 000 hostile DCMDs, asks for a rebirth, sees a unit's
DDEATH and DBIRTH, the broker killed and back (a new bdSeq), the NDEATH will when the face is
killed and the NDEATH of a clean stop; ``mosquitto_sub`` reads the retained UNS JSON.
"""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from packml_interfaces.srv import SetAlarm

from packml_ros2.testing.processes import Processes
from packml_ros2.testing.unit_client import UnitClient
from test.mqtt.host import Broker, Host, Seen, close_all, closed_cleanly
from test.ros.cells import start_em_process, start_unit_process, write_cell

pytestmark = pytest.mark.ros
FAST = {"resetting": 0.1, "starting": 0.1, "stopping": 0.1, "clearing": 0.1, "aborting": 0.05}
GROUP, EDGE_CLIENT, UNS = "plant", "edge1", "acme/site1/packing/line1"
INT32, STRING, DOUBLE, BOOLEAN = 3, 12, 10, 11


def birth_of(device: str) -> Any:
    return lambda s: s.kind == "DBIRTH" and s.device == device


def answer_to(request_id: str) -> Any:
    return lambda s: s.kind == "DDATA" and s.metrics.get("Command/Answer/RequestId") == request_id


class Face:
    def __init__(self, tmp: Path) -> None:
        self.path, self.cell = write_cell(
            tmp,
            {
                "filler": {
                    "remote_commands_enabled": True,
                    "mach_speed": 40,
                    "mach_design_speed": 50,
                    "counters": {"processed": [{"id": 1, "name": "bottles", "unit": "pcs"}]},
                    "alarms": [
                        {"id": 201, "message": "Nozzle clogged", "category": 2, "em": "nozzle"}
                    ],
                    "equipment_modules": {
                        "nozzle": {"sim": {"durations": FAST, "cycle_time": 0.1}}
                    },
                },
                "capper": {},  # the remote lock on (the default)
            },
            coordinator={"enabled": False},
        )
        self.broker = Broker(tmp)
        doc = yaml.safe_load(self.path.read_text())
        doc["mqtt"] = {
            "port": self.broker.port,
            "group_id": GROUP,
            "client_id": EDGE_CLIENT,
            "keepalive": 2,
            "uns": {"prefix": UNS},
        }
        self.path.write_text(yaml.safe_dump(doc, sort_keys=False))
        self.procs = Processes(tmp)
        self.host = Host(self.broker.port, GROUP, extra=(f"{UNS}/#",))
        self.dcmd = f"spBv1.0/{GROUP}/DCMD/{self.cell}/"
        self.edge: Any = None

    def start_edge(self) -> Any:
        # the README's command
        self.edge = self.procs.module("mqtt", "packml_ros2.cli.main", "mqtt", str(self.path))
        return self.edge

    def command(self, unit: str, request_id: str, metric: str, dtype: int, value: Any) -> Seen:
        mark = self.host.mark()
        self.host.send(
            self.dcmd + unit, [("Command/RequestId", STRING, request_id), (metric, dtype, value)]
        )
        return self.host.wait(answer_to(request_id), 20, f"the answer to {request_id}", after=mark)

    def state(self, unit: str, name: str, after: int = 0) -> Seen:
        return self.host.wait(
            lambda s: (
                s.device == unit
                and s.kind in ("DBIRTH", "DDATA")
                and s.metrics.get("State/CurrentName") == name
            ),
            20,
            f"{unit} {name}",
            after=after,
        )

    def close(self) -> str:
        return close_all(self.host, self.procs, self.broker)


@pytest.fixture
def face(tmp_path: Path) -> Iterator[Face]:
    with closed_cleanly(Face(tmp_path)) as f:
        yield f


@pytest.mark.timeout(400)
def test_a_host_application_follows_commands_and_outlives_the_cell_and_the_broker(
    face: Face, ros: Any
) -> None:
    for unit in ("filler", "capper"):
        start_unit_process(face.procs, face.path, unit)
    start_em_process(face.procs, face.path, "filler", "nozzle")
    filler, capper = UnitClient(ros, face.cell, "filler"), UnitClient(ros, face.cell, "capper")
    filler.ready(30)
    capper.ready(30)
    filler.wait_status(lambda m: "RESET" in m.commands_valid_names, 30, "the nozzle online")
    edge = face.start_edge()
    host = face.host

    # -- born: NBIRTH (bdSeq, Rebirth, seq 0), a DBIRTH per unit with every PackTag -----------------
    nbirth = host.wait(lambda s: s.kind == "NBIRTH", 60, "NBIRTH")
    assert nbirth.topic == f"spBv1.0/{GROUP}/NBIRTH/{face.cell}"
    assert nbirth.payload.seq == 0 and nbirth.metrics["Node Control/Rebirth"] is False
    bd_seq = nbirth.metrics["bdSeq"]
    born = host.wait(birth_of("filler"), 30, "the filler's DBIRTH")
    host.wait(birth_of("capper"), 30, "the capper's DBIRTH")
    names = set(born.metrics)
    for name in (
        "State/Current",
        "State/CurrentName",
        "Mode/CurrentName",
        "MachSpeed",
        "CurMachSpeed",
        "Alarms/Active",
        "Admin/Alarms/List",
        "Admin/Warnings/List",
        "Admin/StopReason/ID",
        "Admin/ProdProcessedCount/1/Count",
        "Admin/ProdProcessedCount/1/AccCount",
        "Admin/AccTimeSinceReset",
        "Admin/StateCurrentTime",
        "EM/nozzle/Online",
        "EM/nozzle/StateComplete",
        "Command/CntrlCmd",
        "Command/UnitMode",
        "Command/MachSpeed",
        "Command/AckAlarms",
        "Command/Answer/Accepted",
        "Command/Answer/RequestId",
        "Command/Recipe",
        "StackLight/0/Color",
        "StackLight/0/Mode",
        "StackLight/Horn",
    ):
        assert name in names, name
    assert born.metrics["MachSpeed"] == 40.0 and born.metrics["EM/nozzle/Online"] is True
    # a unit without recipes has the recipe metrics all the same: none in use
    assert (born.metrics["Recipe/Current"], born.metrics["Recipe/CurrentName"]) == (0, "")
    aliases = [m.alias for m in born.payload.metrics]
    assert all(m.HasField("alias") and m.HasField("datatype") for m in born.payload.metrics)
    assert len(set(aliases)) == len(aliases)  # one alias per metric
    assert host.errors == []

    # -- commands: each answered, naming its request; the state follows in DDATA ---------------------
    mark = host.mark()
    answer = face.command("filler", "r-reset", "Command/CntrlCmd", INT32, 1)
    assert answer.metrics["Command/Answer/Accepted"] is True, answer.metrics
    assert answer.metrics["Command/Answer/Command"] == "Command/CntrlCmd=RESET"
    assert answer.metrics["Command/Answer/Reason"] == "ACCEPTED"
    face.state("filler", "IDLE", after=mark)
    answer = face.command("filler", "r-start", "Command/CntrlCmd", STRING, "start")  # a name too
    assert answer.metrics["Command/Answer/Accepted"] is True, answer.metrics
    face.state("filler", "EXECUTE", after=mark)
    data = [s for s in host.since(mark) if s.kind == "DDATA" and s.device == "filler"]
    assert all(not m.name for s in data for m in s.payload.metrics)  # aliases only after birth
    seqs = [
        s.payload.seq for s in host.since(0) if s.kind in ("NBIRTH", "DBIRTH", "DDATA", "DDEATH")
    ]
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(seqs)), seqs
    # the unit recorded the source: mqtt:<client id>
    filler.wait_state("EXECUTE", 20)
    entered = filler.wait_entered("STARTING", 20)
    assert entered.source == f"mqtt:{EDGE_CLIENT}", entered
    answer = face.command("filler", "r-speed", "Command/MachSpeed", DOUBLE, 45.0)
    assert answer.metrics["Command/Answer/Accepted"] is True, answer.metrics
    host.wait(lambda s: s.device == "filler" and s.metrics.get("MachSpeed") == 45.0, 10, "speed")
    too_fast = face.command("filler", "r-fast", "Command/MachSpeed", DOUBLE, 99.0)
    assert too_fast.metrics["Command/Answer/Accepted"] is False
    assert too_fast.metrics["Command/Answer/Reason"] == "INVALID_ARGUMENT", too_fast.metrics
    assert "50" in too_fast.metrics["Command/Answer/Message"]  # the design speed, from the unit

    # the remote lock: the capper refuses, and says why
    locked = face.command("capper", "r-locked", "Command/CntrlCmd", INT32, 1)
    assert locked.metrics["Command/Answer/Accepted"] is False
    assert locked.metrics["Command/Answer/Reason"] == "REMOTE_DISABLED", locked.metrics
    assert capper.status.last.state_current_name == "STOPPED"

    # -- a fault: the alarm and the stop reason in DDATA; acknowledged over MQTT -------------------
    mark = host.mark()
    raised = filler.call(
        SetAlarm, "set_alarm", id=201, value=0, active=True, category=-1, source="operator:test"
    )
    assert raised.accepted, raised.message_out
    try:
        host.wait(
            lambda s: s.device == "filler" and s.metrics.get("Alarms/Active") == 1,
            20,
            "alarm",
            after=mark,
        )
    except TimeoutError:
        print([s.metrics for s in host.since(mark) if s.kind == "DDATA"][:10], filler.status.last)
        raise
    stopped = host.wait(
        lambda s: s.device == "filler" and s.metrics.get("Admin/StopReason/ID") == 201,
        20,
        "the stop reason",
        after=mark,
    )
    assert stopped.kind == "DDATA"
    face.state("filler", "STOPPED", after=mark)
    ack = face.command("filler", "r-ack", "Command/AckAlarms", INT32, 0)
    assert ack.metrics["Command/Answer/Accepted"] is True, ack.metrics
    host.wait(
        lambda s: s.device == "filler" and s.metrics.get("Alarms/Unacknowledged") == 0,
        20,
        "acknowledged",
    )
    filler.call(
        SetAlarm, "set_alarm", id=201, value=0, active=False, category=-1, source="operator:test"
    )

    # -- 10 000 hostile DCMDs: each refused with a reason, nothing changed, nothing crashed ----------
    before = filler.status.last
    answers_before = next(s for s in reversed(host.since(0)) if "Command/Answer/Count" in s.metrics)
    rng = random.Random(30)
    sent = 0
    hostile = [
        lambda: rng.randbytes(rng.randrange(0, 64)),  # malformed protobuf, mostly
        lambda: b"\x12" + bytes([0xFF] * 11),  # a varint that never ends
        lambda: b"\x12\xff\xff\xff\x0f",  # a metric longer than the message
        lambda: b"\x12" + (70_000).to_bytes(3, "little") + b"x" * 70_000,  # too big
    ]
    base = answers_before.metrics.get("Command/Answer/Count") or 5  # (5 answered above)
    for chunk in range(20):  # 20 x 500, each chunk's answers awaited: a host's flow control
        for i in range(chunk * 500, chunk * 500 + 500):
            kind = i % 8
            if kind < 4:
                face.host.client.publish(face.dcmd + "filler", hostile[kind](), qos=0)
            else:
                metric = [
                    ("Command/CntrlCmd", STRING, "explode"),
                    ("Command/Nonsense", INT32, 1),
                    ("Command/CntrlCmd", DOUBLE, 2.0),
                    ("Command/UnitMode", INT32, 999),
                ][kind - 4]
                face.host.client.publish(face.dcmd + "filler", _encode([metric]), qos=0)
            sent += 1
        # every one answered (refused), in order: the answers' count is the number sent
        done = host.wait(
            lambda s, n=5 + sent: (
                s.device == "filler"
                and isinstance(s.metrics.get("Command/Answer/Count"), int)
                and s.metrics["Command/Answer/Count"] >= n
            ),
            60,
            f"{sent} answers",
        )
    refused = [
        s
        for s in host.since(0)
        if s.device == "filler" and s.metrics.get("Command/Answer/Accepted") is False
    ]
    reasons = {s.metrics["Command/Answer/Reason"] for s in refused}
    assert {"malformed", "too_long", "out_of_range", "unknown_metric", "wrong_type"} <= reasons, (
        reasons
    )
    assert all("Traceback" not in s.metrics["Command/Answer/Message"] for s in refused)
    assert sent == 10_000 and base == 5
    assert done.metrics["Command/Answer/Count"] == 5 + sent, done.metrics
    after = filler.status.last
    assert (after.state_current, after.sequence, after.mach_speed) == (
        before.state_current,
        before.sequence,
        before.mach_speed,
    )
    assert edge.running(), edge.output()[-2000:]
    assert len(edge.output()) < 200_000  # its log stays bounded

    # -- a unit without recipes: a recipe change is the unit's refusal, RECIPE_UNKNOWN --------------
    no_recipe = face.command("filler", "r-recipe", "Command/Recipe", INT32, 1)
    assert no_recipe.metrics["Command/Answer/Accepted"] is False
    assert no_recipe.metrics["Command/Answer/Result"] == 20, no_recipe.metrics
    assert no_recipe.metrics["Command/Answer/Reason"] == "RECIPE_UNKNOWN"

    # -- rebirth on request: NBIRTH (same bdSeq) and every DBIRTH -----------------------------------
    mark = host.mark()
    host.send(f"spBv1.0/{GROUP}/NCMD/{face.cell}", [("Node Control/Rebirth", BOOLEAN, True)])
    again = host.wait(lambda s: s.kind == "NBIRTH", 20, "NBIRTH on rebirth", after=mark)
    assert again.metrics["bdSeq"] == bd_seq and again.payload.seq == 0
    host.wait(birth_of("filler"), 20, "DBIRTH on rebirth", after=mark)

    # -- the UNS: retained JSON, read by mosquitto_sub ---------------------------------------------
    lines = face.broker.sub(f"{UNS}/#", 2)
    docs = {line.split(" ", 1)[0]: yaml.safe_load(line.split(" ", 1)[1]) for line in lines}
    assert docs[f"{UNS}/{face.cell}/filler/packml"]["state"] == "STOPPED"
    assert docs[f"{UNS}/{face.cell}/filler/packml"]["umh_state"] == 40000
    assert (
        docs[f"{UNS}/{face.cell}/filler/packml"]["counts"]["ProdProcessedCount"]["1"]["acc_count"]
        >= 0
    )

    # -- a unit lost: DDEATH within its lease; back: DBIRTH -----------------------------------------
    mark = host.mark()
    lost_at = time.monotonic()
    next(p for p in face.procs.started if p.name == "unit_capper").kill()
    host.wait(
        lambda s: s.kind == "DDEATH" and s.device == "capper", 15, "the capper's DDEATH", after=mark
    )
    assert time.monotonic() - lost_at < 3.0 + 3.0  # the unit lease (3 s) and a margin
    uns = host.wait(
        lambda s: s.topic.endswith("/capper/packml") and s.payload["online"] is False,
        10,
        "UNS offline",
        after=mark,
    )
    assert uns.payload["umh_state"] == 30000
    start_unit_process(face.procs, face.path, "capper")
    host.wait(birth_of("capper"), 60, "the capper born again", after=mark)

    # -- the broker killed and back: a new session, bdSeq + 1, births again -------------------------
    mark = host.mark()
    face.broker.kill()
    face.host.close()
    face.broker.start()
    face.host = host = Host(face.broker.port, GROUP)
    reborn = host.wait(lambda s: s.kind == "NBIRTH", 60, "NBIRTH after the broker came back")
    assert reborn.metrics["bdSeq"] == (bd_seq + 1) % 256, reborn.metrics
    host.wait(birth_of("filler"), 20, "DBIRTH after the broker came back")
    # -- the face killed: the broker sends its will, NDEATH with the same bdSeq ---------------------
    edge.kill()
    death = host.wait(lambda s: s.kind == "NDEATH", 20, "the NDEATH will")
    assert death.metrics["bdSeq"] == reborn.metrics["bdSeq"]
    # -- started again and stopped with Ctrl-C: NBIRTH, then a clean NDEATH --------------------------
    mark = host.mark()
    edge = face.start_edge()
    host.wait(lambda s: s.kind == "NBIRTH", 60, "NBIRTH", after=mark)
    mark = host.mark()
    assert edge.stop(10) == 0, edge.output()[-2000:]
    host.wait(lambda s: s.kind == "NDEATH", 10, "a clean stop's NDEATH", after=mark)
    assert host.errors == []


def _encode(metrics: list[tuple[str, int, Any]]) -> bytes:
    from pysparkplug._protobuf import Payload

    p = Payload()
    for name, dtype, value in metrics:
        m = p.metrics.add()
        m.name, m.datatype = name, dtype
        if dtype == 3:
            m.int_value = value & 0xFFFFFFFF
        elif dtype == 10:
            m.double_value = value
        else:
            m.string_value = value
    return p.SerializeToString()


def test_the_mqtt_block_is_checked_and_secrets_stay_out_of_the_file(tmp_path: Path) -> None:
    import subprocess
    import sys

    path, _ = write_cell(tmp_path, {"filler": {}}, coordinator={"enabled": False})
    doc = yaml.safe_load(path.read_text())

    def check(
        block: dict[str, Any], env: dict[str, str] | None = None
    ) -> subprocess.CompletedProcess[str]:
        import os

        doc["mqtt"] = block
        path.write_text(yaml.safe_dump(doc, sort_keys=False))
        return subprocess.run(
            [sys.executable, "-m", "packml_ros2.cli.main", "mqtt", str(path), "--check"],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
            env={**os.environ, **(env or {})},
        )

    plain = check({"username": "edge", "password": "hunter22"})  # never in the file
    assert plain.returncode == 2 and "mqtt.password" in plain.stderr, plain
    assert "hunter22" not in plain.stderr and "Traceback" not in plain.stderr
    wrong = check(
        {
            "port": 99999,
            "group_id": "a/b",
            "password": "env:PACKML_TEST_NOPE",
            "units": ["nobody"],
            "tls": {"ca_file": "missing.pem"},
            "colour": 1,
        }
    )
    assert wrong.returncode == 2, wrong
    for why in (
        "mqtt.port",
        "mqtt.group_id",
        "mqtt.password",
        "PACKML_TEST_NOPE",
        "mqtt.units",
        "mqtt.tls.ca_file",
        "colour",
    ):
        assert why in wrong.stderr, (why, wrong.stderr)
    good = check(
        {"username": "edge", "password": "env:PACKML_TEST_PW", "uns": {"prefix": "a/b/c/d"}},
        env={"PACKML_TEST_PW": "hunter22"},
    )
    assert good.returncode == 0, good
    assert "hunter22" not in good.stdout + good.stderr


def test_the_reference_cell_shows_every_mqtt_option(monkeypatch: pytest.MonkeyPatch) -> None:
    from packml_ros2.core import load_cell
    from packml_ros2.mqtt.config import KEYS, parse_mqtt

    reference = Path(__file__).resolve().parents[2] / "config" / "reference_cell.yaml"
    text = reference.read_text()
    monkeypatch.setenv("REFERENCE_MQTT_PW", "secret-from-env")
    config = parse_mqtt(load_cell(reference))
    assert (config.client, config.uns_prefix, config.password) == (
        "packml-reference_cell", "acme/plant1/packing/line1", "secret-from-env")  # fmt: skip
    block = text[text.index("\nmqtt:\n") :]
    for key in KEYS:
        assert f"\n  {key}:" in block or f"#   {key}:" in block, key


def test_over_tls_with_a_login_and_a_wrong_password_refused_without_showing_it(
    tmp_path: Path,
) -> None:
    from test.mqtt.host import password_file, tls_files

    ca, cert, key = tls_files(tmp_path)
    logins = password_file(tmp_path, {"edge": "edge-secret-1", "scada": "scada-secret-2"})
    settings = (f"cafile {ca}\ncertfile {cert}\nkeyfile {key}\nallow_anonymous false\n"
                f"password_file {logins}\n")  # fmt: skip
    broker = Broker(tmp_path, settings=settings)
    path, _ = write_cell(tmp_path, {"filler": {}}, coordinator={"enabled": False})
    doc = yaml.safe_load(path.read_text())
    doc["mqtt"] = {"port": broker.port, "username": "edge", "password": "env:PACKML_TEST_MQTT_PW",
                   "tls": {"ca_file": "ca.pem"}, "keepalive": 2}  # fmt: skip
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    procs = Processes(tmp_path)
    host = Host(broker.port, "packml", login=("scada", "scada-secret-2"), ca_file=ca)
    try:
        start_unit_process(procs, path, "filler")
        edge = procs.module("mqtt", "packml_ros2.cli.main", "mqtt", str(path),
                            env={"PACKML_TEST_MQTT_PW": "edge-secret-1"})  # fmt: skip
        host.wait(lambda s: s.kind == "DBIRTH" and s.device == "filler", 60, "the DBIRTH over TLS")
        # the same edge node with a wrong password: refused by the broker, said, never shown
        wrong = procs.module("mqtt_wrong", "packml_ros2.cli.main", "mqtt", str(path), "--port", str(broker.port),
                             env={"PACKML_TEST_MQTT_PW": "not-the-password"})  # fmt: skip
        deadline = time.monotonic() + 30
        while "refused the connection" not in wrong.output() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "refused the connection" in wrong.output(), wrong.output()
        assert "not-the-password" not in wrong.output() and "Traceback" not in wrong.output()
        assert edge.running() and "edge-secret-1" not in edge.output()
        assert host.errors == []
    finally:
        failures = close_all(host, procs, broker)
    assert not failures, failures
