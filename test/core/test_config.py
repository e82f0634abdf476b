"""Cell configuration: valid files parse; every class of error names the file, the key path and
the problem, all errors of a file together; config/reference_cell.yaml shows every option."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from packml_ros2.core import Cmd, ConfigError, Mode, State, load_cell, parse_cell
from packml_ros2.core.config import _UNIT_KEYS as UNIT_KEYS
from packml_ros2.core.config import CELL_KEYS, ArraySizes, SystemAlarms
from packml_ros2.core.line.config import KEYS as LINE_KEYS

REPO = Path(__file__).resolve().parents[2]
REFERENCE = REPO / "config" / "reference_cell.yaml"
S = State


def cell(unit: dict[str, Any] | None = None, **top: Any) -> dict[str, Any]:
    return {"cell": "line1", "units": {"u": {"persistence": False, **(unit or {})}}, **top}


def problems(doc: Any, file: str = "cell.yaml") -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        parse_cell(doc, file)
    err = info.value
    assert err.file == file
    lines = str(err).splitlines()
    assert len(lines) == len(err.problems)
    for line, (path, problem) in zip(lines, err.problems, strict=True):
        assert line == f"{file}: {path or '<top>'}: {problem}"
    return err.problems


def only(doc: Any) -> tuple[str, str]:
    found = problems(doc)
    assert len(found) == 1, found
    return found[0]


# -- valid configurations ----------------------------------------------------------------------------------
def test_minimal_cell_takes_defaults() -> None:
    c = parse_cell({"cell": "line1", "units": {"u": {}}})
    u = c.units["u"]
    assert (c.cell, u.name, u.cell) == ("line1", "u", "line1")
    assert u.initial_mode == Mode.PRODUCTION and set(u.modes) == {1, 2, 3}
    assert u.table.model == "2022" and u.em_lost_reaction == Cmd.ABORT
    assert u.em_lease == 2.0 and u.mode_change_timeout == 10.0 and not u.remote_commands_enabled
    assert u.sizes == ArraySizes() and u.sizes.history == 256 and u.sizes.alarms == 64
    assert u.persistence_path is not None and u.persistence_path.endswith("line1/u.sqlite3")
    assert c.coordinator.start_order == ("u",)


def test_options_parse(tmp_path: Path) -> None:
    doc = cell(
        {
            "model": "2015",
            "initial_mode": 4,
            "modes": {
                "jog": {
                    "number": 4,
                    "disabled_states": ["hold", "Completed"],
                    "mode_change_states": ["Stopped"],
                },
                "manual": {"enabled": False},
            },
            "equipment_modules": {"a": {"lost_reaction": "ignore"}, "b": {"active": False}},
            "timeouts": {"Starting": 3},
            "min_dwell": {"Resetting": 0.5},
            "reactions": {5: "hold", "6": "suspend"},
            "alarms": [{"id": 65, "message": "Stop PB Pressed", "category": 2}],
            "persistence": {"path": "data/{cell}_{unit}.db", "period": 1.5},
            "hold_from": ["Execute", "Starting"],
        }
    )
    u = parse_cell(doc, "c.yaml", tmp_path).units["u"]
    assert u.table.model == "2015" and u.initial_mode == 4
    assert set(u.modes) == {1, 2, 4}
    jog = u.modes[4]
    assert jog.name == "JOG" and jog.disabled == {
        S.HOLDING,
        S.HELD,
        S.UNHOLDING,
        S.COMPLETING,
        S.COMPLETE,
    }
    assert [(e.name, e.lost_reaction, e.active) for e in u.equipment_modules] == [
        ("a", 0, True), ("b", None, False)
    ]  # fmt: skip
    assert u.timeouts == {S.STARTING: 3.0} and u.min_dwell == {S.RESETTING: 0.5}
    assert (
        u.reactions[5] == Cmd.HOLD and u.reactions[6] == Cmd.SUSPEND and u.reactions[0] == Cmd.ABORT
    )
    assert (
        u.persistence_path == str(tmp_path / "data" / "line1_u.db") and u.persistence_period == 1.5
    )
    assert u.table.target(S.STARTING, Cmd.HOLD) is S.HOLDING
    assert u.table.target(S.SUSPENDED, Cmd.HOLD) is None


def test_defaults_apply_to_every_unit() -> None:
    doc = {"cell": "c", "defaults": {"em_lease": 0.5, "persistence": False},
           "units": {"a": {}, "b": {"em_lease": 3.0}}}  # fmt: skip
    c = parse_cell(doc)
    assert (c.units["a"].em_lease, c.units["b"].em_lease) == (0.5, 3.0)
    assert c.units["a"].persistence_path is None


# -- every class of error ----------------------------------------------------------------------------------
def test_unknown_key_with_did_you_mean() -> None:
    path, problem = only(cell({"persistance": {}}))
    assert path == "units.u.persistance"
    assert "unknown key (did you mean 'persistence'?)" in problem and "valid keys:" in problem
    path, problem = only({"cell": "c", "units": {"u": {}}, "coordinater": {}})
    assert path == "coordinater" and "did you mean 'coordinator'?" in problem


def test_bad_state_name() -> None:
    path, problem = only(cell({"modes": {"maintenance": {"disabled_states": ["Helld"]}}}))
    assert path == "units.u.modes.maintenance.disabled_states[0]"
    assert problem == "'Helld' is not a PackML state (did you mean HELD?)"


def test_mandatory_state_disabled() -> None:
    path, problem = only(cell({"modes": {"manual": {"disabled_states": ["Idle", "Held"]}}}))
    assert path == "units.u.modes.manual.disabled_states"
    assert problem == "IDLE can never be disabled"


def test_mode_change_state_not_a_wait_state() -> None:
    path, problem = only(
        cell({"modes": {"production": {"mode_change_states": ["Execute", "Idle"]}}})
    )
    assert path == "units.u.modes.production.mode_change_states"
    assert "only be allowed in wait states, not in EXECUTE" in problem


def test_bad_category() -> None:
    found = problems(cell({"alarms": [{"id": 1, "category": 12}], "reactions": {10: "stop"}}))
    assert ("units.u.alarms[0].category", "12 is outside 0..9") in found
    assert ("units.u.reactions.10", "category must be 0..9") in found


def test_duplicate_alarm() -> None:
    path, problem = only(
        cell({"alarms": [{"id": 7, "value": 1}, {"id": 7}, {"id": 7, "value": 1}]})
    )
    assert path == "units.u.alarms[2]" and problem == "alarm 7/1 is defined twice"


def test_bad_yaml(tmp_path: Path) -> None:
    f = tmp_path / "broken.yaml"
    f.write_text("cell: c\nunits:\n  u: {em_lease: [1, 2\n")
    with pytest.raises(ConfigError) as info:
        load_cell(f)
    assert info.value.file == str(f)
    ((where, problem),) = info.value.problems
    assert re.fullmatch(r"line \d+", where) and problem.startswith("not valid YAML")
    assert str(info.value).startswith(f"{f}: line ")


def test_missing_cell_key_and_missing_file(tmp_path: Path) -> None:
    path, problem = only({"units": {"u": {}}})
    assert path == "" and "missing key 'cell'" in problem
    path, problem = only({"cell": "c"})
    assert path == "units" and problem == "a cell needs at least one unit"
    with pytest.raises(ConfigError) as info:
        load_cell(tmp_path / "nowhere.yaml")
    assert info.value.file.endswith("nowhere.yaml") and "cannot read" in str(info.value)


@pytest.mark.parametrize(
    ("unit", "path", "text"),
    [
        ({"initial_mode": "bogus"}, "units.u.initial_mode", "'bogus' is not one of"),
        ({"initial_mode": 9}, "units.u.initial_mode", "mode 9 is not configured"),
        ({"modes": {"jog": {}}}, "units.u.modes.jog", "needs a number in 4..31"),
        ({"modes": {"jog": {"number": 40}}}, "units.u.modes.jog.number", "40 is outside 4..31"),
        ({"timeouts": {"Idle": 3}}, "units.u.timeouts.Idle", "IDLE is not an acting state"),
        ({"timeouts": {"Starting": -1}}, "units.u.timeouts.Starting", "greater than 0"),
        ({"min_dwell": {"Execute": 1}}, "units.u.min_dwell.Execute", "not an acting state"),
        ({"model": "2019"}, "units.u.model", "'2019' is not one of 2022, 2015"),
        ({"hold_from": ["Stopped"]}, "units.u.hold_from[0]", "STOPPED is not allowed here"),
        ({"equipment_modules": {"9em": {}}}, "units.u.equipment_modules.9em", "not a valid ROS name"),
        ({"equipment_modules": {"em": {"lost_reaction": "abrot"}}},
         "units.u.equipment_modules.em.lost_reaction", "(did you mean 'abort'?)"),
        ({"equipment_modules": {"em": {"speed": 1}}}, "units.u.equipment_modules.em.speed",
         "unknown key"),
        ({"em_lease": "fast"}, "units.u.em_lease", "expected a number"),
        ({"remote_commands_enabled": "yes"}, "units.u.remote_commands_enabled", "true or false"),
        ({"alarms": [{"message": "no id"}]}, "units.u.alarms[0]", "an alarm needs an id"),
        ({"alarms": [{"id": 1, "reaction": "explode"}]}, "units.u.alarms[0].reaction", "not one of"),
        ({"sizes": {"counters": 1}, "counters": {"processed": [{"id": 1}, {"id": 2}]}},
         "units.u.counters.processed", "2 counters, but the array holds 1"),
        ({"counters": {"scrap": []}}, "units.u.counters.scrap", "unknown key"),
        ({"sizes": {"alarm": 3}}, "units.u.sizes.alarm", "did you mean 'alarms'?"),
        ({"planned_stop_ids": [10, 1]}, "units.u.planned_stop_ids", "[first, last]"),
        ({"system_alarms": {"state_timeout_category": 11}},
         "units.u.system_alarms.state_timeout_category", "11 is outside 0..9"),
        ({"interlock_reaction": "hold"}, "units.u.interlock_reaction", "not one of suspend, none"),
        ({"persistence": {"pth": "x"}}, "units.u.persistence.pth", "did you mean 'path'?"),
        ({"modes": {"production": {"disabled_states": ["Stopped"]}, "maintenance": {"enabled": True}},
          "initial_mode": "production"},
         "units.u.modes.production.disabled_states", "STOPPED can never be disabled"),
    ],
)  # fmt: skip
def test_error_names_key_path_and_problem(unit: dict[str, Any], path: str, text: str) -> None:
    found = problems(cell(unit))
    assert any(p == path and text in problem for p, problem in found), found


def test_coordinator_errors() -> None:
    doc = cell(coordinator={"start_order": ["u", "v"], "stop_order": ["u", "u"],
                            "interlocks": [{"unit": "u", "when": "blockd", "suspend": ["w"]}]})  # fmt: skip
    found = dict(problems(doc))
    assert "'v' is not one of u" in found["coordinator.start_order[1]"]
    assert found["coordinator.stop_order"] == "a unit is listed twice"
    assert "(did you mean 'blocked'?)" in found["coordinator.interlocks[0].when"]
    assert "'w' is not one of u" in found["coordinator.interlocks[0].suspend[0]"]


def test_all_errors_of_a_file_are_reported_together(tmp_path: Path) -> None:
    f = tmp_path / "many.yaml"
    f.write_text(
        "cell: c\n"
        "units:\n"
        "  u:\n"
        "    persistance: {}\n"
        "    modes:\n"
        "      maintenance: {disabled_states: [Idle, Helld], mode_change_states: [Execute]}\n"
        "    alarms:\n"
        "      - {id: 1, category: 12}\n"
        "      - {id: 2}\n"
        "      - {id: 2}\n"
        "  w:\n"
        "    timeouts: {Idle: 3}\n"
    )
    with pytest.raises(ConfigError) as info:
        load_cell(f)
    paths = [p for p, _ in info.value.problems]
    assert paths == [
        "units.u.persistance",
        "units.u.modes.maintenance.disabled_states[1]",
        "units.u.modes.maintenance.disabled_states",
        "units.u.modes.maintenance.mode_change_states",
        "units.u.alarms[0].category",
        "units.u.alarms[2]",
        "units.w.timeouts.Idle",
    ]
    assert all(line.startswith(f"{f}: units.") for line in str(info.value).splitlines())


# -- the reference cell ---------------------------------------------------------------------------------------
def test_reference_cell_loads() -> None:
    c = load_cell(REFERENCE)
    assert c.cell == "reference_cell" and list(c.units) == ["filler", "capper", "wrapper"]
    assert c.units["wrapper"].plc is not None and c.coordinator.lost_unit_reaction == 0
    filler = c.units["filler"]
    assert filler.persistence_path == "/tmp/packml_ros2/reference/filler.sqlite3"
    assert c.units["capper"].persistence_path == "/tmp/packml_ros2/reference/capper.sqlite3"
    assert filler.modes[4].name == "CLEANING"
    assert [e.name for e in filler.equipment_modules] == ["infeed", "valves", "outfeed"]
    assert all(e.sim == {} for e in filler.equipment_modules)
    assert c.coordinator.start_order == ("capper", "filler")
    assert c.units["capper"].table.model == "2015"
    assert c.line.order == ("filler", "capper", "wrapper") and c.line.output_unit == "wrapper"
    assert [s.name for s in c.line.shifts] == ["early", "late", "night"]
    assert c.line.shifts[0].breaks[0].name == "lunch" and c.line.timezone == "Europe/Berlin"


def _keys(doc: Any, prefix: str = "") -> set[str]:
    """Every key path of the document, list indices as []."""
    out: set[str] = set()
    if isinstance(doc, dict):
        for k, v in doc.items():
            path = f"{prefix}.{k}" if prefix else str(k)
            out.add(path)
            out |= _keys(v, path)
    elif isinstance(doc, list):
        for v in doc:
            out |= _keys(v, f"{prefix}[]")
    return out


def test_reference_cell_shows_every_option() -> None:
    text = REFERENCE.read_text()
    doc = yaml.safe_load(text)
    keys = _keys(doc)
    unit_keys = {k.split(".", 2)[2] for k in keys if k.startswith("units.") and k.count(".") > 1}
    unit_keys |= {k.split(".", 1)[1] for k in keys if k.startswith("defaults.")}
    expected = set(UNIT_KEYS)
    expected |= {f"sizes.{k}" for k in ArraySizes.__dataclass_fields__}
    expected |= {f"system_alarms.{k}" for k in SystemAlarms.__dataclass_fields__}
    expected |= {f"modes.cleaning.{k}" for k in ("number", "disabled_states", "mode_change_states")}
    expected |= {"modes.manual.enabled", "persistence.path", "persistence.period"}
    expected |= {f"equipment_modules.infeed.{k}" for k in ("active", "lost_reaction", "sim")}
    expected |= {f"alarms[].{k}" for k in ("id", "value", "message", "category", "warning",
                                            "reaction", "em")}  # fmt: skip
    expected |= {f"counters.{k}[].{f}" for k in ("consumed", "processed", "defective")
                 for f in ("id", "name", "unit")}  # fmt: skip
    expected |= {f"{k}[].{f}" for k in ("parameters", "admin_parameters")
                 for f in ("id", "name", "unit", "value")}  # fmt: skip
    expected |= {"products[].product_id", "products[].process_variables[].value",
                 "products[].ingredients[].ingredient_id",
                 "products[].ingredients[].parameter[].value",
                 "remote_interfaces[].number", "remote_interfaces[].name"}  # fmt: skip
    assert expected <= unit_keys, sorted(expected - unit_keys)
    coordinator = {"enabled", "start_order", "stop_order", "step_timeout", "unit_lease",
                   "interlocks", "propagate_interlocks", "lost_unit_reaction"}  # fmt: skip
    assert {f"coordinator.{k}" for k in coordinator} <= keys
    assert {"coordinator.interlocks[].unit", "coordinator.interlocks[].when",
            "coordinator.interlocks[].suspend"} <= keys  # fmt: skip
    assert {"cell", "defaults", "units"} <= keys
    # Every option is documented: a comment right above its first appearance (or on its line).
    lines = text.splitlines()
    start = lines.index("coordinator:")
    where = {key: rf" {{2,4}}{key}:" for key in UNIT_KEYS}  # in defaults or units.filler
    where |= {key: rf"{key}:" for key in ("cell", "defaults", "units", "coordinator")}
    for key, pattern in where.items():
        i = next(i for i, line in enumerate(lines) if re.match(pattern, line))
        documented(lines, i, key)
    for key in coordinator:
        i = next(i for i, line in enumerate(lines) if i > start and re.match(rf"  {key}:", line))
        documented(lines, i, key)
    # the line block (issue 19): every key of its parser, each documented
    line = set(LINE_KEYS)  # every key of its parser
    assert {"publish_period", "changeover_modes"} <= line
    assert {f"line.{k}" for k in line} <= keys
    assert {"line.shifts.early.days", "line.shifts.early.breaks[].name"} <= keys
    start = lines.index("line:")
    documented(lines, start, "line")
    for key in line:
        i = next(i for i, text in enumerate(lines) if i > start and re.match(rf"  {key}:", text))
        documented(lines, i, key)


def test_reference_cell_shows_every_top_level_key_and_valid_hmi_and_opcua_blocks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """It had no hmi: and no opcua: block (issue 24). Every key of those blocks is shown, set or,
    where it needs a file of the user's or excludes another, in a commented example."""
    from packml_ros2.hmi.settings import KEYS as HMI_KEYS
    from packml_ros2.hmi.settings import hmi_settings
    from packml_ros2.mqtt.config import KEYS as MQTT_KEYS
    from packml_ros2.mqtt.config import parse_mqtt
    from packml_ros2.opcua.config import KEYS as OPCUA_KEYS
    from packml_ros2.opcua.config import parse_opcua

    text = REFERENCE.read_text()
    doc, lines = yaml.safe_load(text), text.splitlines()
    assert list(doc) == list(CELL_KEYS)
    for key in CELL_KEYS:
        documented(lines, next(i for i, x in enumerate(lines) if x.startswith(f"{key}:")), key)
    for block, keys in (("hmi", HMI_KEYS), ("opcua", OPCUA_KEYS), ("mqtt", MQTT_KEYS)):
        start = lines.index(f"{block}:")
        end = next(
            (i for i in range(start + 1, len(lines)) if re.match(r"\S", lines[i])), len(lines)
        )
        own = [x for x in lines[start + 1 : end] if x.startswith("  ") and not x.startswith("   ")]
        set_keys = {x.split(":")[0].strip() for x in own if not x.lstrip().startswith("#")}
        commented = {m[1] for x in lines[start + 1 : end] for m in re.finditer(r"[`#] *(\w+): ", x)}
        assert set_keys <= keys and keys <= set_keys | commented, (
            block,
            keys - set_keys - commented,
        )
        for i in range(start + 1, end):
            if lines[i] in own and not lines[i].lstrip().startswith("#"):
                documented(lines, i, f"{block}.{lines[i].split(':')[0].strip()}")
    for variable in ("REFERENCE_HMI_ANNA_PW", "REFERENCE_HMI_BEN_PW", "REFERENCE_OPCUA_SCADA_PW",
                     "REFERENCE_MQTT_PW"):  # fmt: skip
        monkeypatch.setenv(variable, "a password of the reference cell")
    cell = load_cell(REFERENCE)
    hmi = hmi_settings(cell)
    assert set(hmi.users) == {"anna", "ben"} and hmi.allowed_hosts == ("hmi.line3.example",)
    opcua = parse_opcua(cell)
    assert opcua.units == ("filler", "capper", "wrapper") and set(opcua.users) == {"scada"}
    assert opcua.max_mach_speed == {"filler": 120, "capper": 120}
    mqtt = parse_mqtt(cell)
    assert mqtt.units == ("filler", "capper", "wrapper") and mqtt.uns_prefix.startswith("acme/")


def documented(lines: list[str], i: int, key: str) -> None:
    """A comment right above the key's line says what it does and its default."""
    j = i
    while j > 0 and lines[j - 1].lstrip().startswith("#"):
        j -= 1
    comment = "\n".join(lines[j:i]).lower()
    assert comment, f"{key} has no comment"
    assert "default" in comment or key == "units", f"{key}: say its default"
