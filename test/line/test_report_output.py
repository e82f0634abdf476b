"""Issue 24 item 7: what ``packml report`` prints from the coordinator's answers (real
packml_interfaces messages through the one conversion, line_msgs): CSV times in ISO 8601 (they
were epoch floats), an episodes CSV (there was none), "no data" for a factor with nothing to
divide by (an empty shift, a PLC unit without times showed 0.0 %), and each affected unit once
(a unit that left Execute twice in an episode was listed twice). The whole verb runs on the
demo cell in test/line/test_line_demo.py (the README's commands)."""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import re

from packml_interfaces.msg import LineDeparture, LineEpisode, LineLosses, LossBucket, LossScope

from packml_ros2 import line_msgs
from packml_ros2.cli import report
from packml_ros2.core.line.losses import Totals, summarize

NS = 1_000_000_000
T0 = 1_750_060_800  # 2025-06-16 08:00 UTC


def scope(name: str, **ns: int) -> LossScope:
    s = LossScope(scope=name, mach_design_speed=60.0)
    for key, value in ns.items():
        setattr(s, key, value)
    return s


def window() -> dict:
    producing = scope("robot_cell", elapsed_ns=100 * NS, unplanned_stop_ns=20 * NS,
                      running_ns=80 * NS, productive_ns=80 * NS, processed=80)  # fmt: skip
    producing.availability, producing.performance, producing.quality, producing.oee = 0.8, 1.0, 1.0, 0.8  # fmt: skip
    producing.buckets = [LossBucket(bucket="unplanned_stop", reason="alarm 202: Infeed jam", nanoseconds=20 * NS),
                         LossBucket(bucket="running", reason="", nanoseconds=80 * NS)]  # fmt: skip
    # an empty shift for the line: all of it a planned stop; the core sends 0.0 for the factors
    empty = scope("", elapsed_ns=100 * NS, planned_stop_ns=100 * NS)
    empty.buckets = [LossBucket(bucket="planned_stop", reason="no shift", nanoseconds=100 * NS)]
    plc = scope("plc_filler")  # a PLC unit that reported no times: nothing at all
    msg = LineLosses(cell="demo_cell", window="shift:2025-06-16 early",
                     start=line_msgs.stamp(T0 * NS), end=line_msgs.stamp((T0 + 100) * NS),
                     scopes=[empty, producing, plc])  # fmt: skip
    return line_msgs.losses_dict(msg)


def episodes() -> list[dict]:
    e = LineEpisode(id=1, cell="demo_cell", start=line_msgs.stamp((T0 + 10) * NS),
                    end=line_msgs.stamp((T0 + 45) * NS), open=False, duration_ns=35 * NS,
                    root_unit="robot_cell", bucket="unplanned_stop", reason="alarm 202: Infeed jam",
                    source="alarm:202")  # fmt: skip
    for t, unit, how in ((10, "robot_cell", "internal"), (16, "case_packer", "starved"),
                         (30, "robot_cell", "propagated")):  # fmt: skip
        e.affected.append(LineDeparture(unit=unit, stamp=line_msgs.stamp((T0 + t) * NS), how=how))
    return [line_msgs.episode_dict(e)]


def test_factors_with_nothing_to_divide_by_are_no_data() -> None:
    data = window()
    by_scope = {s["scope"]: s for s in data["scopes"]}
    assert [by_scope["line"][k] for k in ("availability", "performance", "quality", "oee")] == [None] * 4  # fmt: skip
    assert [by_scope["plc_filler"][k] for k in ("availability", "oee")] == [None, None]
    assert by_scope["robot_cell"]["availability"] == 0.8 and by_scope["robot_cell"]["oee"] == 0.8
    text = report.table("demo_cell", data, episodes(), 1)
    rows = {r[0]: r[-4:] for r in (re.split(r"\s{2,}", x.strip()) for x in text.splitlines()[2:5])}
    assert rows["line"] == rows["plc_filler"] == ["no data"] * 4, text
    assert rows["robot_cell"] == ["80.0%", "100.0%", "100.0%", "80.0%"], text


def test_the_loss_csv_has_iso_8601_times() -> None:
    rows = list(csv.DictReader(io.StringIO(report.to_csv(window()))))
    assert rows and {r["window"] for r in rows} == {"shift:2025-06-16 early"}
    for r in rows:
        start, end = dt.datetime.fromisoformat(r["start"]), dt.datetime.fromisoformat(r["end"])
        assert start.tzinfo is not None and end.tzinfo is not None, r
        assert start.timestamp() == T0 and end.timestamp() == T0 + 100, r


def test_the_episodes_csv_and_table_list_each_affected_unit_once() -> None:
    eps = episodes()
    (row,) = list(csv.DictReader(io.StringIO(report.episodes_csv(eps))))
    assert dt.datetime.fromisoformat(row["start"]).timestamp() == T0 + 10
    assert dt.datetime.fromisoformat(row["end"]).timestamp() == T0 + 45
    assert (row["id"], row["seconds"], row["open"], row["root_cause"], row["bucket"]) == (
        "1", "35.000", "no", "robot_cell", "unplanned_stop"
    )  # fmt: skip
    assert row["reason"] == "alarm 202: Infeed jam" and row["source"] == "alarm:202"
    assert row["affected"] == "robot_cell (internal, propagated), case_packer (starved)"
    text = report.table("demo_cell", window(), eps, 1)
    episode_line = text.split("STOP EPISODES", 1)[1].splitlines()[-1]
    assert episode_line.count("robot_cell") == 2, text  # the root cause and the affected unit
    assert episode_line.endswith("robot_cell (internal, propagated), case_packer (starved)")


def test_the_changeover_is_its_own_bucket_in_the_report_table_csv_and_json() -> None:
    """Issue "Recipes and changeover": the line's summary (core) through LossScope (whose
    planned_stop_ns holds all planned time) to what ``packml report`` prints: the changeover is
    its own planned bucket, out of planned_stop, and out of the planned production time."""
    totals = Totals()
    for bucket, reason, seconds in (
        ("running", "", 60),
        ("planned_stop", "break: lunch", 10),
        ("changeover", "filler: CHANGEOVER mode", 20),
        ("unplanned_stop", "filler: alarm 202: Infeed jam", 10),
    ):
        totals.add_time(bucket, reason, seconds * NS)
    totals.add_count(60, 0, 60 * NS, 60 * NS)
    line = summarize("", totals, 60.0)
    scope_msg = line_msgs.scope_msg(line, 60.0)
    assert scope_msg.planned_stop_ns == 30 * NS  # the message's planned time: both
    msg = LineLosses(
        cell="demo_cell",
        window="lifetime",
        start=line_msgs.stamp(T0 * NS),
        end=line_msgs.stamp((T0 + 100) * NS),
        scopes=[scope_msg],
    )
    data = json.loads(json.dumps(line_msgs.losses_dict(msg)))  # what --format json prints
    (s,) = data["scopes"]
    assert s["nanoseconds"] == {
        "elapsed": 100 * NS,
        "planned_stop": 10 * NS,
        "changeover": 20 * NS,
        "unplanned_stop": 10 * NS,
        "blocked": 0,
        "starved": 0,
        "held": 0,
        "running": 60 * NS,
        "speed_loss": 0,
        "quality_loss": 0,
        "productive": 60 * NS,
    }
    assert (s["planned_stop"], s["changeover"]) == (10.0, 20.0)
    assert s["availability"] == 60 / 70 and s["oee"] == 60 / 70  # 100 s - 10 s - 20 s planned
    changeover = {"bucket": "changeover", "reason": "filler: CHANGEOVER mode", "seconds": 20.0}
    assert changeover in s["buckets"]
    text = report.table("demo_cell", data, [], 0)
    head, row = (re.split(r"\s{2,}", x.strip()) for x in text.splitlines()[1:3])
    columns = dict(zip(head, row, strict=True))
    assert (columns["PLANNED"], columns["CHANGEOVER"], columns["OEE"]) == (
        "0:00:10.0",
        "0:00:20.0",
        "85.7%",
    ), text
    losses = text.split("LOSSES OF THE LINE", 1)[1]
    assert re.search(
        r"^\s+changeover\s+filler: CHANGEOVER mode\s+0:00:20\.0\s+20\.0%$", losses, re.M
    ), text
    rows = list(csv.DictReader(io.StringIO(report.to_csv(data))))
    assert [(r["reason"], r["seconds"]) for r in rows if r["bucket"] == "changeover"] == [
        ("filler: CHANGEOVER mode", "20.000")
    ]
    assert sum(float(r["seconds"]) for r in rows if r["bucket"] != "elapsed") == 100.0
