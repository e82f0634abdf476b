"""The line block of a cell file: the order on the line, the shift calendar (night shifts, breaks,
days, daylight saving), and the refusals of a bad calendar."""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

import pytest

from packml_ros2.core import ConfigError, parse_cell
from packml_ros2.core.line.calendar import NO_SHIFT

NS = 1_000_000_000


def cell(line: dict[str, Any] | None = None, **coordinator: Any) -> Any:
    doc: dict[str, Any] = {"cell": "c", "units": {"a": {}, "b": {}, "c": {}}}
    if coordinator:
        doc["coordinator"] = coordinator
    if line is not None:
        doc["line"] = line
    return parse_cell(doc)


def ns(text: str, zone: str = "UTC") -> int:
    from zoneinfo import ZoneInfo

    return int(dt.datetime.fromisoformat(text).replace(tzinfo=ZoneInfo(zone)).timestamp()) * NS


def test_line_order_from_the_interlock_rules_and_the_store_beside_the_units(tmp_path: Any) -> None:
    rules = [
        {"unit": "a", "when": "blocked", "suspend": ["c"]},  # c is upstream of a
        {"unit": "b", "when": "starved", "suspend": ["a"]},
    ]  # a is downstream of b
    config = cell(None, interlocks=rules)
    assert config.line.order == ("b", "c", "a")
    assert config.line.output_unit == config.line.order[-1]
    assert config.line.store is not None and config.line.store.endswith(
        "c/coordinator.line.sqlite3"
    )
    explicit = cell({"order": ["c", "b", "a"], "output_unit": "b", "store": False})
    assert (explicit.line.order, explicit.line.output_unit, explicit.line.store) == (("c", "b", "a"), "b", None)  # fmt: skip


def test_night_shift_across_midnight_with_a_break_after_midnight() -> None:
    line = {"timezone": "Europe/Berlin", "shifts": {
        "early": {"start": "06:00", "end": "14:00", "days": ["mon", "tue", "wed", "thu", "fri"]},
        "night": {"start": "22:00", "end": "06:00", "breaks": [{"name": "meal", "start": "02:00", "end": "02:30"}]}}}  # fmt: skip
    cal = cell(line).line.calendar
    inst = cal.instance_at(ns("2025-03-05T03:00", "Europe/Berlin"))
    assert inst.key == "2025-03-04 night"
    assert (inst.start, inst.end) == (ns("2025-03-04T22:00", "Europe/Berlin"), ns("2025-03-05T06:00", "Europe/Berlin"))  # fmt: skip
    pieces = cal.pieces(ns("2025-03-05T01:00", "Europe/Berlin"), ns("2025-03-05T07:00", "Europe/Berlin"))  # fmt: skip
    assert [(p.shift, p.planned, (p.end - p.start) // (60 * NS)) for p in pieces] == [
        ("2025-03-04 night", "", 60), ("2025-03-04 night", "break: meal", 30),
        ("2025-03-04 night", "", 210), ("2025-03-05 early", "", 60)]  # fmt: skip
    # Saturday: no early shift; the night is the only one
    sat = cal.pieces(ns("2025-03-08T05:00", "Europe/Berlin"), ns("2025-03-08T08:00", "Europe/Berlin"))  # fmt: skip
    assert [(p.shift, p.planned) for p in sat] == [("2025-03-07 night", ""), ("", NO_SHIFT)]
    # the night of the change to summer time is an hour shorter
    dst = cal.instance("2025-03-29 night")
    assert (dst.end - dst.start) // (3600 * NS) == 7
    assert cal.previous(ns("2025-03-05T03:00", "Europe/Berlin")).key == "2025-03-04 early"


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ({"shifts": {"a": {"start": 360, "end": "14:00"}}}, "quote times of day"),
        ({"shifts": {"a": {"start": "25:00", "end": "14:00"}}}, "not a time of day"),
        (
            {
                "shifts": {
                    "a": {"start": "06:00", "end": "14:00"},
                    "b": {"start": "13:00", "end": "20:00"},
                }
            },
            "overlap",
        ),
        (
            {
                "shifts": {
                    "a": {
                        "start": "06:00",
                        "end": "14:00",
                        "breaks": [{"start": "15:00", "end": "15:30"}],
                    }
                }
            },
            "inside the shift",
        ),
        (
            {"shifts": {"a": {"start": "06:00", "end": "14:00", "days": ["mon", "holiday"]}}},
            "not a weekday",
        ),
        ({"timezone": "Mars/Olympus"}, "not a time zone"),
        ({"order": ["a", "b"]}, "every unit is on the line"),
        ({"output_unit": "z"}, "output_unit"),
        ({"shifts": {"a": {"end": "14:00"}}}, "needs start"),
    ],
)
def test_a_bad_line_block_is_refused_at_its_key(line: dict[str, Any], problem: str) -> None:
    with pytest.raises(ConfigError) as err:
        cell(line)
    assert problem in str(err.value) and "line." in str(err.value), str(err.value)


SHIFTS = {"timezone": "Europe/Berlin", "shifts": {
    "early": {"start": "06:00", "end": "14:00"},
    "night": {"start": "22:00", "end": "06:00", "breaks": [{"name": "meal", "start": "02:00", "end": "02:30"}]}}}  # fmt: skip
EXTREMES = (-(2**63), -(10**30), -1, 0, 1, 2**31 * NS, 2**63 - 1, 2**63, 10**30)


@pytest.mark.parametrize("key", ["9999-12-31 early", "0001-01-01 night", "2262-04-12 early",
                                 "1969-12-31 night", "1970-01-01 early"])  # fmt: skip
def test_a_shift_outside_the_calendar_s_dates_is_no_shift_not_an_overflow(key: str) -> None:
    """Issue 25 item 1: ``shift:9999-12-31 early`` raised OverflowError in the date arithmetic
    (and ended the coordinator)."""
    cal = cell(SHIFTS).line.calendar
    assert cal.instance(key) is None
    for t in (t for t in EXTREMES if t != 2**31 * NS):
        assert cal.instance_at(t) is None
        assert cal.previous(t) is None
        assert [p.planned for p in cal.pieces(t, t + 3600 * NS)] == [NO_SHIFT]
    assert cal.instance("2262-04-01 early") is not None  # the last day a ROS time can name


def test_every_window_of_query_losses_with_any_numbers_is_an_answer_or_a_refusal() -> None:
    """Seeded fuzz of ``Line.query_losses`` (what ``line/query_losses``, ``/api/line`` and
    ``packml report`` ask): windows, since/until/step/count at and past their extremes."""
    import random

    from packml_ros2.core.line.line import Line

    now = ns("2025-06-16T10:00", "Europe/Berlin")
    line = Line(cell(SHIFTS), lambda: 0.0, lambda: now)
    rng = random.Random(2525)
    days = ["9999-12-31", "0001-01-01", "2262-04-12", "2262-04-01", "1970-01-01", "2025-06-16",
            "2025-02-30", "+2025-01-01", "20250616", "2025-06-16T06:00"]  # fmt: skip
    windows = ["", "shift", "shift:current", "shift:previous", "15min", "1h", "reset", "lifetime",
               "since", "shifts", "trend", "shift:", "shift: early", "nonsense"]  # fmt: skip
    windows += [f"shift:{d} {s}" for d in days for s in ("early", "night", "none", "")]
    numbers = [*EXTREMES, now, now - 3600 * NS, now + 10**18]
    steps = [0.0, -1.0, 1e-12, 0.5, 900.0, 1e7, 1e12, 1e300, math.inf, -math.inf, math.nan]
    counts = [0, 1, -1, 200, 201, 2**31 - 1, -(2**31)]
    for _ in range(3000):
        window = rng.choice(windows)
        views, why = line.query_losses(window, rng.choice(numbers), rng.choice(numbers),
                                       rng.choice(steps), rng.choice(counts))  # fmt: skip
        assert bool(views) != bool(why), (window, why)
        assert len(views) <= 200
