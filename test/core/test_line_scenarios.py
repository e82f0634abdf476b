"""Scripted line scenarios (issue 19): real engines with simulated EMs and timed faults, the
coordinator's line core in between (test/core/line_sim.py). Each scenario's episodes, root causes
and loss buckets are computed by hand below and must match exactly (integer nanoseconds).

The line: ``filler`` (upstream, EM ``infeed``: a part every 1 s, every 10th defective, design 60
per minute) -> ``packer`` (downstream, EM ``loader``: a case every 2 s, design 30 per minute).
Acting states take 1 s (Suspending, Unsuspending 0.5 s). A cell RESET at 1 s and START at 4 s put
the packer in Execute at 5 s and the filler at 6 s: the line produces from 6 s. Counts reach the
line with the unit's admin data 0.25 s after the part (the engine coalesces admin).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from packml_ros2.core import Cmd, Reason, State
from packml_ros2.core.line import inputs
from packml_ros2.core.line.ledger import Ledger
from packml_ros2.core.line.losses import (
    BLOCKED,
    CHANGEOVER,
    PLANNED,
    RUNNING,
    STARVED,
    UNPLANNED,
    Totals,
    summarize,
)
from packml_ros2.core.line.performance import Performance
from packml_ros2.core.line.store import LineStore
from test.core.line_sim import NS, T0, SimEm, SimLine

D = {State.RESETTING: 1.0, State.STARTING: 1.0, State.STOPPING: 1.0, State.SUSPENDING: 0.5,
     State.UNSUSPENDING: 0.5, State.ABORTING: 0.5, State.CLEARING: 0.5}  # fmt: skip


def cell_doc(**line: Any) -> dict[str, Any]:
    return {
        "cell": "sim",
        "defaults": {"remote_commands_enabled": True, "persistence": False},
        "units": {
            "filler": {"mach_design_speed": 60,
                       "counters": {"processed": [{"id": 1, "name": "parts"}],
                                    "defective": [{"id": 1, "name": "rejects"}]},
                       "alarms": [{"id": 202, "message": "Infeed jam", "category": 2, "em": "infeed"}],
                       "equipment_modules": {"infeed": {}}},
            "packer": {"mach_design_speed": 30,
                       "counters": {"processed": [{"id": 1, "name": "cases"}]},
                       "equipment_modules": {"loader": {}}},
        },
        "coordinator": {"start_order": ["packer", "filler"], "stop_order": ["filler", "packer"],
                        "interlocks": [{"unit": "packer", "when": "blocked", "suspend": ["filler"]}]},
        "line": {"order": ["filler", "packer"], "store": False, **line},
    }  # fmt: skip


def started(doc: dict[str, Any], store: str | None = None) -> SimLine:
    sim = SimLine(doc, [SimEm("filler", "infeed", dict(D), 1.0, 10),
                        SimEm("packer", "loader", dict(D), 2.0)], store)  # fmt: skip
    sim.at(1, lambda: sim.cell_command(Cmd.RESET))
    sim.at(4, lambda: sim.cell_command(Cmd.START))
    return sim


def s(seconds: float) -> int:
    """Seconds (exact in binary: halves and quarters) as ns."""
    return round(seconds * NS)


def at(seconds: float) -> int:
    return round((T0 + seconds) * NS)


def episodes(sim: SimLine) -> list[tuple[Any, ...]]:
    p = sim.line.perf
    out = []
    for e in [*p.closed, *([p.episode] if p.episode else [])]:
        r = p.root(e)
        out.append((e.id, e.start, e.end, r.unit, r.bucket, r.reason,
                    [(d.unit, d.time, d.kind, d.label, d.bucket, d.cause_unit) for d in e.departures]))  # fmt: skip
    return out


def buckets(sim: SimLine, window: str = "lifetime") -> dict[str, Any]:
    view = sim.line.window(window, round(sim.t * NS))
    return {x.scope or "line": x for x in view.scopes}


def times(summary: Any) -> dict[tuple[str, str], int]:
    return {(b, r): ns for b, r, ns in summary.buckets}


def check_waterfall(x: Any, elapsed: int) -> None:
    assert x.elapsed == elapsed
    parts = (x.planned, x.changeover, x.unplanned, x.blocked, x.starved, x.held, x.running)
    assert sum(parts) == elapsed
    assert x.speed_loss + x.quality_loss + x.productive == x.running


def test_jam_upstream_starves_the_packer_root_cause_is_the_filler() -> None:
    sim = started(cell_doc())
    sim.at(20.5, lambda: sim.alarm("filler", "infeed", 202, True))  # the jam: category 2 -> Stop
    sim.at(22, lambda: sim.interlock("packer", "loader", starved=True))  # no parts come
    sim.at(30, lambda: sim.alarm("filler", "infeed", 202, False))
    sim.at(31, lambda: sim.command("filler", Cmd.RESET))
    sim.at(33, lambda: sim.command("filler", Cmd.START))
    sim.at(35, lambda: sim.interlock("packer", "loader", starved=False))
    sim.run_until(40)

    # filler: Stopping 20.5 -> Stopped 21.5, reset 31, start 33, Execute 34; packer: Suspending
    # 22 -> Suspended 22.5, Unsuspending 35 -> Execute 35.5: the line produces again at 35.5
    assert episodes(sim) == [(
        1, at(20.5), at(35.5), "filler", UNPLANNED, "alarm 202: Infeed jam",
        [("filler", at(20.5), "internal", "alarm 202: Infeed jam", UNPLANNED, ""),
         ("packer", at(22), "starved", "loader starved", STARVED, "")],
    )]  # fmt: skip
    b = buckets(sim)
    assert times(b["filler"]) == {(RUNNING, ""): s(14.5 + 6), (UNPLANNED, "unit restarted"): s(6),
                                  (UNPLANNED, "alarm 202: Infeed jam"): s(34 - 20.5)}  # fmt: skip
    assert times(b["packer"]) == {(RUNNING, ""): s(17 + 4.5), (UNPLANNED, "unit restarted"): s(5),
                                  (STARVED, "loader starved"): s(35.5 - 22)}  # fmt: skip
    assert times(b["line"]) == {(RUNNING, ""): s(14.5 + 4.5),
                                (UNPLANNED, "filler: unit restarted"): s(6),
                                (UNPLANNED, "filler: alarm 202: Infeed jam"): s(35.5 - 20.5)}  # fmt: skip
    # counts: filler parts at 7..20 and 35..39 (40's admin comes at 40.25): 19, the 10th
    # defective; packer cases at 7, 9 .. 21 and 37.5, 39.5: 10 (the line's output)
    f, p, line = b["filler"], b["packer"], b["line"]
    assert (f.processed, f.defective, p.processed, p.defective) == (19, 1, 10, 0)
    assert (f.speed_loss, f.quality_loss, f.productive) == (s(20.5 - 19), s(1), s(18))
    assert (p.speed_loss, p.quality_loss, p.productive) == (s(21.5 - 20), 0, s(20))
    # the line ran 19 s and its output took 20 s at design speed: cases made while it stood
    assert (line.processed, line.speed_loss, line.productive) == (10, s(-1), s(20))
    assert line.oee == 20 / 40 and f.oee == 18 / 40
    for x in b.values():
        check_waterfall(x, s(40))


def test_full_case_packer_blocks_the_line_root_cause_is_the_packer() -> None:
    sim = started(cell_doc())
    sim.at(20.5, lambda: sim.interlock("packer", "loader", blocked=True))  # the packer is full
    sim.at(30, lambda: sim.interlock("packer", "loader", blocked=False))
    sim.run_until(40)

    # the packer suspends itself (its loader), the coordinator suspends the filler (rule:
    # packer blocked -> suspend filler) at the same moment; both run again from 30.5
    assert episodes(sim) == [(
        1, at(20.5), at(30.5), "packer", BLOCKED, "loader blocked",
        [("packer", at(20.5), "blocked", "loader blocked", BLOCKED, ""),
         ("filler", at(20.5), "propagated", "packer blocked", BLOCKED, "packer")],
    )]  # fmt: skip
    b = buckets(sim)
    assert times(b["filler"]) == {(RUNNING, ""): s(14.5 + 9.5), (UNPLANNED, "unit restarted"): s(6),
                                  (BLOCKED, "packer blocked"): s(10)}  # fmt: skip
    assert times(b["packer"]) == {(RUNNING, ""): s(15.5 + 9.5), (UNPLANNED, "unit restarted"): s(5),
                                  (BLOCKED, "loader blocked"): s(10)}  # fmt: skip
    assert times(b["line"]) == {(RUNNING, ""): s(24), (UNPLANNED, "filler: unit restarted"): s(6),
                                (BLOCKED, "packer: loader blocked"): s(10)}  # fmt: skip
    # filler: 7..20 and 31.5..39.5 = 23 parts, #10 and #20 (36.5) defective; packer: 7..19 and
    # 32.5..38.5 = 11 cases
    f, p, line = b["filler"], b["packer"], b["line"]
    assert (f.processed, f.defective, p.processed) == (23, 2, 11)
    assert (f.speed_loss, f.quality_loss, f.productive) == (s(1), s(2), s(21))
    assert (p.speed_loss, p.productive) == (s(3), s(22))
    assert (line.running, line.speed_loss, line.productive) == (s(24), s(2), s(22))
    for x in b.values():
        check_waterfall(x, s(40))


def test_planned_stop_over_a_break_is_planned_and_the_cell_is_its_root() -> None:
    # T0 is 2025-06-15 15:06:40 UTC: the late shift (14:00-22:00) has its tea break at 50..70 s
    shifts = {"late": {"start": "14:00", "end": "22:00",
                       "breaks": [{"name": "tea", "start": "15:07:30", "end": "15:07:50"}]}}  # fmt: skip
    sim = started(cell_doc(timezone="UTC", shifts=shifts))
    sim.at(45.5, lambda: sim.cell_command(Cmd.STOP))  # before the break: stop reason 4006 (planned)
    sim.at(72, lambda: sim.cell_command(Cmd.RESET))
    sim.at(75, lambda: sim.cell_command(Cmd.START))
    sim.run_until(90)

    cell_stop = "cell STOP (operator)"
    assert episodes(sim) == [(
        1, at(45.5), at(77), "", PLANNED, cell_stop,
        [("filler", at(45.5), "cell", cell_stop, PLANNED, ""),
         ("packer", at(46.5), "cell", cell_stop, PLANNED, "")],
    )]  # fmt: skip
    for window in ("lifetime", "shift:2025-06-15 late"):
        b = buckets(sim, window)
        # filler: Stopping 45.5-46.5, Stopped to 73 (the break 50-70 planned as the break),
        # Resetting 73-74 (not a planned-stop state), Idle 74-76, Starting 76-77
        assert times(b["filler"]) == {
            (RUNNING, ""): s(39.5 + 13), (UNPLANNED, "unit restarted"): s(6),
            (PLANNED, cell_stop): s(1 + 3.5 + 3 + 2), (PLANNED, "break: tea"): s(20),
            (UNPLANNED, cell_stop): s(1 + 1),
        }  # fmt: skip
        assert times(b["packer"]) == {
            (RUNNING, ""): s(41.5 + 14), (UNPLANNED, "unit restarted"): s(5),
            (PLANNED, cell_stop): s(1 + 2.5 + 2 + 2), (PLANNED, "break: tea"): s(20),
            (UNPLANNED, cell_stop): s(1 + 1),
        }  # fmt: skip
        assert times(b["line"]) == {
            (RUNNING, ""): s(39.5 + 13), (UNPLANNED, "filler: unit restarted"): s(6),
            (PLANNED, "break: tea"): s(20), (PLANNED, f"cell: {cell_stop}"): s(77 - 45.5 - 20),
        }  # fmt: skip
        f, p = b["filler"], b["packer"]
        # filler: 7..45 (39) and 78..89 (12); #10, #20, #30, #40 (78), #50 (88) defective
        assert (f.processed, f.defective, p.processed) == (51, 5, 26)
        for x in b.values():
            check_waterfall(x, s(90))
        assert b["line"].planned_production == s(90 - 20 - 11.5)


def changeover_doc(mode: str, **line: Any) -> dict[str, Any]:
    """The cell with a user mode ``mode`` (5) on the filler, entered and left in Stopped."""
    doc = cell_doc(**line)
    doc["units"]["filler"]["modes"] = {
        mode: {
            "number": 5,
            "disabled_states": ["suspend"],
            "mode_change_states": ["Stopped", "Idle"],
        }
    }
    return doc


def changeover_run(doc: dict[str, Any]) -> SimLine:
    """A cell STOP (planned) at 20.5, the filler in mode 5 from 23 to 31, then back to
    Production, a cell RESET at 32 and START at 35 (the line produces again at 37)."""
    sim = started(doc)
    sim.at(20.5, lambda: sim.cell_command(Cmd.STOP))
    u, d = sim.units["filler"], sim.drivers["filler"]

    def mode(number: int) -> None:
        assert d.call(sim.t, u.set_mode, number, "operator").accepted
        d.call(sim.t, u.em_complete, "infeed", int(u.state), u.sequence)  # its EM acknowledges
        assert u.mode == number

    sim.at(23, lambda: mode(5))
    sim.at(31, lambda: mode(1))
    sim.at(32, lambda: sim.cell_command(Cmd.RESET))
    sim.at(35, lambda: sim.cell_command(Cmd.START))
    sim.run_until(40)
    return sim


def test_a_changeover_mode_is_its_own_planned_bucket_of_the_unit_and_the_line() -> None:
    """Issue "Recipes and changeover": a unit's time in a changeover mode is the bucket
    ``changeover`` (not planned_stop), planned time: out of the planned production time of the
    unit and of the line (whose time is the changeover while a unit changes over, inside the
    episode of the cell STOP)."""
    sim = changeover_run(changeover_doc("changeover"))
    cell_stop = "cell STOP (operator)"
    b = buckets(sim)
    # filler: Stopping 20.5-21.5, Stopped to 23, CHANGEOVER 23-31, Stopped 31-33 (packer resets
    # first), Resetting 33-34, Idle 34-36, Starting 36-37, Execute from 37
    assert times(b["filler"]) == {
        (RUNNING, ""): s(14.5 + 3),
        (UNPLANNED, "unit restarted"): s(6),
        (PLANNED, cell_stop): s(1 + 1.5 + 2 + 2),
        (UNPLANNED, cell_stop): s(1 + 1),
        (CHANGEOVER, "CHANGEOVER mode"): s(8),
    }
    assert CHANGEOVER not in {bucket for bucket, _ in times(b["packer"])}
    # the line: the episode of the cell STOP (20.5-37) is a changeover while the filler is in it
    assert times(b["line"]) == {
        (RUNNING, ""): s(14.5 + 3),
        (UNPLANNED, "filler: unit restarted"): s(6),
        (PLANNED, f"cell: {cell_stop}"): s(37 - 20.5 - 8),
        (CHANGEOVER, "filler: CHANGEOVER mode"): s(8),
    }
    f, line = b["filler"], b["line"]
    assert (f.changeover, line.changeover) == (s(8), s(8))
    assert (line.planned, line.planned_production) == (s(8.5), s(40 - 8.5 - 8))
    assert line.availability == s(17.5) / s(23.5) and line.oee == line.productive / s(23.5)
    assert f.planned_production == s(40 - 6.5 - 8) and f.availability == s(17.5) / s(25.5)
    for x in b.values():
        check_waterfall(x, s(40))


@pytest.mark.parametrize(
    ("mode", "line", "bucket"),
    [
        ("format_change", {"changeover_modes": ["Format_Change"]}, CHANGEOVER),
        ("changeover", {"changeover_modes": []}, PLANNED),
        ("cleaning", {}, PLANNED),
    ],
)
def test_the_changeover_modes_are_the_lines_choice(
    mode: str, line: dict[str, Any], bucket: str
) -> None:
    """``line.changeover_modes`` names them (case-insensitive); default: ``changeover``."""
    sim = changeover_run(changeover_doc(mode, **line))
    b = buckets(sim)
    assert times(b["filler"])[(bucket, f"{mode.upper()} mode")] == s(8)
    assert b["filler"].changeover == b["line"].changeover == (s(8) if bucket == CHANGEOVER else 0)
    for x in b.values():
        check_waterfall(x, s(40))


def test_a_summary_counts_the_changeover_as_planned_time() -> None:
    totals = Totals()
    for bucket, ns in ((RUNNING, s(50)), (PLANNED, s(10)), (CHANGEOVER, s(20)), (UNPLANNED, s(20))):
        totals.add_time(bucket, "why", ns)
    totals.add_count(50, 5, s(50), s(45))
    x = summarize("", totals, 60.0)
    assert (x.elapsed, x.planned, x.changeover) == (s(100), s(10), s(20))
    assert x.planned_production == s(100 - 10 - 20)
    assert x.availability == 50 / 70 and x.oee == 45 / 70 and x.quality == 0.9
    assert [b for b, _, _ in x.buckets] == [RUNNING, PLANNED, CHANGEOVER, UNPLANNED]


def test_replaying_the_input_log_reproduces_episodes_and_facts_exactly() -> None:
    sim = started(cell_doc())
    sim.at(20.5, lambda: sim.alarm("filler", "infeed", 202, True))
    sim.at(22, lambda: sim.interlock("packer", "loader", blocked=True))
    sim.at(25, lambda: sim.interlock("packer", "loader", blocked=False))
    sim.at(26, lambda: sim.alarm("filler", "infeed", 202, False))
    sim.at(27, lambda: sim.command("filler", Cmd.RESET))
    sim.at(29, lambda: sim.command("filler", Cmd.START))
    sim.run_until(45)
    sim.take()
    log = sim.records
    assert log[0].name == inputs.START and log[0].index == 1
    assert [r.index for r in log] == list(range(1, len(log) + 1))

    replayed = Performance(sim.cell.line, sim.cell.units, Ledger())
    for r in log[1:]:
        inputs.apply(replayed, r.name, r.t, json.loads(r.args_json))
    now = round(sim.t * NS)
    original = sim.line.perf
    assert [e.to_dict() for e in replayed.closed] == [e.to_dict() for e in original.closed]
    for window in ("lifetime", "15min", "1h"):
        a, b = replayed.windows(window, now), original.windows(window, now)
        assert {k: v.to_dict() for k, v in a.items()} == {k: v.to_dict() for k, v in b.items()}
    assert [replayed.root(e).unit for e in replayed.closed] == ["filler"]


@pytest.mark.parametrize("admin_first", [False, True])
def test_the_stop_reason_explains_the_episode_whichever_topic_comes_first(
    admin_first: bool,
) -> None:
    """Admin data and status are separate topics: an executor serving the admin subscription
    first hands the StopReason over before the status that opens the episode (once seen in CI)."""
    sim = started(cell_doc())
    sim.at(20.5, lambda: sim.alarm("filler", "infeed", 202, True))
    sim.at(30, lambda: sim.alarm("filler", "infeed", 202, False))
    sim.at(31, lambda: sim.command("filler", Cmd.RESET))
    sim.at(33, lambda: sim.command("filler", Cmd.START))
    sim.run_until(40)
    sim.take()
    log = [(r.name, r.t, json.loads(r.args_json)) for r in sim.records[1:]]
    told = next(i for i, (n, _, f) in enumerate(log) if n == "admin" and f["stop_reason"])
    departed = next(i for i, (n, _, f) in enumerate(log) if n == "transition" and f["to_state"] == State.STOPPING)  # fmt: skip
    assert departed < told
    if admin_first:
        log.insert(departed, log.pop(told))
    replayed = Performance(sim.cell.line, sim.cell.units, Ledger())
    for name, t, fields in log:
        inputs.apply(replayed, name, t, fields)
    [episode] = replayed.closed
    assert replayed.root(episode).unit == "filler"
    assert episode.stop_reason is not None
    assert (episode.stop_reason["id"], episode.stop_reason["message"]) == (202, "Infeed jam")
    if admin_first:  # a StopReason set long before the departure explains nothing
        reason = log[departed][2]["stop_reason"]
        log[departed][2]["stop_reason"] = {**reason, "time": at(10)}
        stale = Performance(sim.cell.line, sim.cell.units, Ledger())
        for name, t, fields in log:
            inputs.apply(stale, name, t, fields)
        assert [e.stop_reason for e in stale.closed] == [None]


def test_a_bag_of_the_line_replays_to_the_same_episodes_and_losses(tmp_path: Path) -> None:
    import yaml

    from packml_ros2.bag import line

    doc = cell_doc(publish_period=5.0)
    sim = started(doc)
    sim.at(20.5, lambda: sim.alarm("filler", "infeed", 202, True))
    sim.at(22, lambda: sim.interlock("packer", "loader", starved=True))
    sim.at(24, lambda: sim.alarm("filler", "infeed", 202, False))
    sim.at(25, lambda: sim.command("filler", Cmd.RESET))
    sim.at(27, lambda: sim.command("filler", Cmd.START))
    sim.at(29, lambda: sim.interlock("packer", "loader", starved=False))
    sim.at(35, lambda: sim.interlock("packer", "loader", blocked=True))
    sim.at(40, lambda: sim.interlock("packer", "loader", blocked=False))
    sim.run_until(50)
    bag = tmp_path / "line_bag"
    sim.write_bag(bag, yaml.safe_dump(doc))
    [result] = line.check(bag)
    assert result.ok, result.report()
    assert result.compared == {
        "episodes": len(sim.episode_views),
        "losses": 4 * len(sim.published),
    }  # no shift calendar
    assert result.compared["episodes"] >= 4 and len(sim.published) == 10
    assert [v.root.unit for v in sim.episode_views if v.episode.end] == ["filler", "packer"]
    # a bag whose recorded episode says another root cause does not match
    sim.episode_views[-1] = type(sim.episode_views[-1])(
        sim.episode_views[-1].episode, sim.episode_views[0].root, sim.episode_views[-1].now
    )
    sim.write_bag(tmp_path / "mutated", yaml.safe_dump(doc))
    [mutated] = line.check(tmp_path / "mutated")
    assert not mutated.ok and "line/episodes: message" in mutated.report()
    assert "root_unit: recorded 'filler', replayed 'packer'" in mutated.report()


CHILD = """
import sys, json
sys.path.insert(0, {root!r})
from test.core.test_line_scenarios import started, cell_doc
from packml_ros2.core import Cmd
sim = started(cell_doc(), {store!r})
sim.at(20.5, lambda: sim.alarm("filler", "infeed", 202, True))
sim.run_until(25)
p = sim.line.perf
print(json.dumps({{"lifetime": {{k: v.to_dict() for k, v in p.ledger.lifetime.items()}},
                  "episode": p.episode.to_dict(), "since": {{n: t.since for n, t in p.trackers.items()}}}}), flush=True)
sys.stdin.read()
"""


def test_a_killed_coordinator_loses_nothing_it_published(tmp_path: Path) -> None:
    store = tmp_path / "line.sqlite3"
    root = str(Path(__file__).resolve().parents[2])
    child = subprocess.Popen([sys.executable, "-c", CHILD.format(root=root, store=str(store))],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        said = json.loads(child.stdout.readline())  # type: ignore[union-attr]
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    db = LineStore(store, "sim")
    try:
        totals = {k: v.to_dict() for k, v in db.totals(None, None).items()}
        assert totals == said["lifetime"]
        state = db.state()
        assert state is not None and state["episode"] == said["episode"]
        assert {n: t["since"] for n, t in state["trackers"].items()} == said["since"]
        eps, total = db.episodes(open_only=True)
        assert total == 1 and eps[0].to_dict() == said["episode"]
    finally:
        db.close()


def test_a_restarted_line_continues_its_windows_from_the_store(tmp_path: Path) -> None:
    store = str(tmp_path / "line.sqlite3")
    sim = started(cell_doc(), store)
    sim.run_until(10)
    before = {k: v.to_dict() for k, v in sim.line.perf.ledger.lifetime.items()}
    doc = sim.line.perf.document()
    sim.line.close()
    again = SimLine(cell_doc(), [], store)
    assert {k: v.to_dict() for k, v in again.line.perf.ledger.lifetime.items()} == before
    assert again.line.perf.document()["trackers"]["filler"]["since"] == doc["trackers"]["filler"]["since"]  # fmt: skip
    again.line.close()
    with pytest.raises(Exception, match="in use"):
        a = LineStore(store, "sim")
        LineStore(store, "sim")
    a.close()


def test_summaries_of_nothing_are_zero() -> None:
    from packml_ros2.core.line.losses import Totals

    x = summarize("", Totals(), 60.0)
    assert (x.elapsed, x.availability, x.oee, x.performance) == (0, 0.0, 0.0, 0.0)


def test_the_coordinator_releases_its_own_interlock_on_a_unit_switched_to_local() -> None:
    """Issue 15: the remote lock guards setting an interlock, not releasing one's own. The filler
    is suspended by the coordinator (packer blocked), then switched to local at the machine; once
    the packer is free the coordinator clears its interlock and the filler runs again (before, the
    clear was refused with REMOTE_DISABLED and retried forever: the filler stayed suspended by a
    hold nobody at the machine may clear). A new interlock on the locked filler is refused."""
    sim = started(cell_doc())
    filler = sim.units["filler"]
    sim.at(20.5, lambda: sim.interlock("packer", "loader", blocked=True))
    sim.at(25, lambda: sim.drivers["filler"].call(sim.t, filler.set_remote_enabled, False))
    sim.at(30, lambda: sim.interlock("packer", "loader", blocked=False))
    sim.run_until(32)
    assert filler.state is State.EXECUTE and not filler.interlock_active, filler.state
    moves = [m for _, unit, topic, m in sim.messages if unit == "filler" and topic == "transitions"]
    resumed = [m for m in moves if m.from_state_name == "SUSPENDED"]
    assert resumed[-1].source == "interlock:coordinator"  # the coordinator's interlock released it
    assert "Log(level='info', text='interlock cleared on filler')" in sim.log
    assert not [line for line in sim.log if "level='info'" not in line], sim.log

    sim.at(33, lambda: sim.interlock("packer", "loader", blocked=True))  # blocked again
    sim.run_until(36)
    assert filler.state is State.EXECUTE and not filler.interlock_active  # the lock holds
    answer = filler.set_interlock(True, "x", "coordinator")
    assert answer.reason is Reason.REMOTE_DISABLED
    assert filler.set_interlock(False, "", "remote:mes").reason is Reason.NOTHING_TO_DO


def test_the_coordinator_wakes_only_when_something_is_due() -> None:
    """No polling (issue 18): the line's one wake-up is armed for ``Line.next_due`` after every
    event, as the node does. At rest it wakes for the leases (renewed by the units' diagnostics
    every second) and the losses' publication every ``publish_period`` (5 s), not every 0.1 s;
    a unit gone silent is lost ``unit_lease`` (3 s) after its last sign of life, not later."""
    sim = SimLine(cell_doc(), [])
    sim.run_until(60)
    assert 12 <= len(sim.published) <= 13  # losses at 0 s, then every 5 s
    assert sim.ticks <= 40  # the leases' checks (every 3 s) and the publications: no polling
    sim.silent.add("packer")  # its last diagnostics arrived at 60 s
    sim.run_until(62.99)
    assert sim.line.cell.units["packer"].online
    sim.run_until(63.01)
    assert sim.line.cell.units["packer"].lost and sim.line.cell.units["filler"].online
    assert any("unit packer lost: no status or diagnostics for 3 s" in line for line in sim.log)
    ticks = sim.ticks
    sim.run_until(120)  # one unit lost: only the other's lease and the publications remain
    assert sim.ticks - ticks <= 35
