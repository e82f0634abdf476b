"""The stack light: the presets show their documented lights, overrides merge over a preset,
alarms lay over the state (higher mode wins, the horn until acknowledged), every kind of bad
configuration is refused naming its key path, and the OPC UA encoding."""

from __future__ import annotations

from typing import Any

import pytest
import yaml

from packml_ros2.core.numbers import State
from packml_ros2.core.schema import ConfigError, Node
from packml_ros2.core.stacklight import (
    DEFAULT,
    MODE_BLINK,
    MODE_OFF,
    MODE_ON,
    PRESETS,
    Shown,
    StackLightConfig,
    encode_opcua,
    parse,
    stack_light,
)

S = State
OFF, ON, BLINK = MODE_OFF, MODE_ON, MODE_BLINK
QUIET = ((), False, False)  # no alarm, nothing unacknowledged, no warning


def lit(config: StackLightConfig, shown: Shown) -> dict[str, int]:
    """The lights that are not off, by colour."""
    return {c: m for c, m in zip(config.lights, shown.modes, strict=True) if m != OFF}


def problems(raw: Any) -> list[tuple[str, str]]:
    with pytest.raises(ConfigError) as info:
        parse(raw)
    return info.value.problems


# -- presets ---------------------------------------------------------------------------------------
#: preset -> (lights, Execute, Aborted, Held)
DOCUMENTED = {
    "omac": (
        ("red", "amber", "green", "blue"),
        {"green": ON},
        {"red": ON},
        {"amber": ON},
    ),
    "iec60204": (
        ("red", "yellow", "green", "blue", "white"),
        {"green": ON},
        {"red": ON, "blue": ON},
        {"yellow": ON},
    ),
    "siemens": (
        ("red", "yellow", "green", "blue", "white"),
        {"green": ON},
        {"red": ON, "blue": ON},
        {"yellow": ON},
    ),
    "rockwell": (("red", "amber", "green"), {"green": ON}, {"red": ON}, {"amber": ON}),
    "ros_industrial": (
        ("red", "amber", "green", "blue"),
        {"green": ON, "blue": BLINK},
        {"red": BLINK, "blue": BLINK},
        {"blue": ON},
    ),
}


def test_every_preset_is_documented_here() -> None:
    assert set(PRESETS) == set(DOCUMENTED)


@pytest.mark.parametrize("preset", sorted(DOCUMENTED))
def test_preset_execute_aborted_held(preset: str) -> None:
    lights, execute, aborted, held = DOCUMENTED[preset]
    c = parse({"preset": preset})
    assert c.lights == lights
    assert c.preset == preset
    assert lit(c, c.show(S.EXECUTE, *QUIET)) == execute
    assert lit(c, c.show(S.ABORTED, *QUIET)) == aborted
    assert lit(c, c.show(S.HELD, *QUIET)) == held
    assert not c.show(S.EXECUTE, *QUIET).horn


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_preset_tables_are_valid_overrides(preset: str) -> None:
    """A preset's own tables pass the strict checks of an override (no unknown light or state)."""
    table = PRESETS[preset]
    c = parse({"preset": preset, "states": table["states"], "alarms": table["alarms"]})
    assert c == parse({"preset": preset})


def test_default_is_omac() -> None:
    assert parse(None) == parse({}) == parse({"preset": "OMAC"}) == DEFAULT
    assert DEFAULT.preset == "omac"


def test_omac_acting_states() -> None:
    c = DEFAULT
    for s in (S.STARTING, S.UNHOLDING, S.UNSUSPENDING):
        assert lit(c, c.show(s, *QUIET)) == {"green": BLINK}, s.name
    for s in (S.IDLE, S.STOPPED, S.SUSPENDED, S.COMPLETE):
        assert lit(c, c.show(s, *QUIET)) == {"amber": ON}, s.name
    for s in (S.HOLDING, S.STOPPING, S.RESETTING):
        assert lit(c, c.show(s, *QUIET)) == {"amber": BLINK}, s.name
    assert lit(c, c.show(S.ABORTING, *QUIET)) == {"red": ON}


def test_undefined_and_out_of_range_show_nothing() -> None:
    for state in (S.UNDEFINED, 18, -1, 1000):
        assert DEFAULT.show(state, *QUIET) == Shown((OFF,) * 4, False)


# -- alarms ----------------------------------------------------------------------------------------
def test_omac_unacknowledged_abort_alarm_blinks_red_and_sounds_the_horn() -> None:
    c = DEFAULT
    shown = c.show(S.ABORTED, frozenset({0}), True, False)
    assert lit(c, shown) == {"red": BLINK, "blue": ON}
    assert shown.horn
    acked = c.show(S.ABORTED, frozenset({0}), False, False)
    assert lit(c, acked) == {"red": ON}
    assert not acked.horn


def test_omac_informational_alarm_has_no_horn() -> None:
    c = DEFAULT
    shown = c.show(S.EXECUTE, [7], True, False)
    assert lit(c, shown) == {"red": BLINK, "amber": ON, "green": ON, "blue": ON}
    assert not shown.horn
    assert lit(c, c.show(S.EXECUTE, {7}, False, False)) == {"amber": ON, "green": ON}


def test_stop_level_alarm_sounds_only_while_unacknowledged() -> None:
    c = DEFAULT
    assert c.show(S.STOPPED, {3}, True, False).horn
    assert not c.show(S.STOPPED, {3}, False, False).horn


def test_warning_and_higher_mode_wins() -> None:
    c = DEFAULT
    # Held lights amber on; the warning blinks it: blink wins over on
    assert lit(c, c.show(S.HELD, (), False, True)) == {"amber": BLINK}
    assert lit(c, c.show(S.HELD, (), False, False)) == {"amber": ON}
    # an informational alarm's amber on does not stop the warning's blink
    assert lit(c, c.show(S.EXECUTE, {5}, False, True)) == {"amber": BLINK, "green": ON}


def test_categories_outside_the_model_are_ignored() -> None:
    assert DEFAULT.show(S.EXECUTE, {42, -1}, False, False) == DEFAULT.show(S.EXECUTE, *QUIET)


def test_show_accepts_any_iterable_and_is_stable() -> None:
    c = DEFAULT
    first = c.show(S.EXECUTE, iter([0, 7]), True, True)
    assert first == c.show(S.EXECUTE, frozenset({7, 0}), True, True)
    assert first == c.show(S.EXECUTE, [7, 0, 7], True, True)


def test_ros_industrial_horn_while_starting() -> None:
    c = parse({"preset": "ros_industrial"})
    assert c.show(S.STARTING, *QUIET).horn
    assert not c.show(S.EXECUTE, *QUIET).horn
    # the source maps no alarms: an alarm changes nothing
    assert c.show(S.EXECUTE, {0}, False, False) == c.show(S.EXECUTE, *QUIET)


# -- overrides -------------------------------------------------------------------------------------
def test_overrides_merge_over_the_preset() -> None:
    c = parse(
        {
            "preset": "omac",
            "states": {"execute": {"blue": "blink"}, "Held": {"amber": "off", "blue": "on"}},
            "alarms": {0: {"red": "blink"}, "warning": {"horn": True}},
        }
    )
    # the preset's green on stays, the override adds blue
    assert lit(c, c.show(S.EXECUTE, *QUIET)) == {"green": ON, "blue": BLINK}
    # off removes what the preset's entry lit
    assert lit(c, c.show(S.HELD, *QUIET)) == {"blue": ON}
    # category 0: red blink now, the preset's horn kept
    shown = c.show(S.STOPPED, {0}, True, False)
    assert lit(c, shown)["red"] == BLINK
    assert shown.horn
    assert lit(c, c.show(S.STOPPED, {0}, False, False)) == {"red": BLINK, "amber": ON}
    # entries not overridden are the preset's
    assert c.show(S.IDLE, *QUIET) == DEFAULT.show(S.IDLE, *QUIET)


def test_overrides_from_yaml_with_bare_on_off() -> None:
    """YAML 1.1 reads unquoted on/off as booleans."""
    raw = yaml.safe_load(
        "stack_light:\n"
        "  preset: omac\n"
        "  states:\n"
        "    Execute: {green: on, blue: on}\n"
        "    Idle: {amber: off}\n"
        "  alarms:\n"
        "    0: {red: blink, horn: true}\n"
    )["stack_light"]
    c = parse(raw)
    assert lit(c, c.show(S.EXECUTE, *QUIET)) == {"green": ON, "blue": ON}
    assert lit(c, c.show(S.IDLE, *QUIET)) == {}


def test_lights_override_drops_preset_lights_left_out() -> None:
    c = parse({"lights": ["green", "amber", "red"], "states": {"Execute": {"red": "on"}}})
    assert c.lights == ("green", "amber", "red")
    assert c.show(S.EXECUTE, *QUIET).modes == (ON, OFF, ON)
    assert c.show(S.HELD, *QUIET).modes == (OFF, ON, OFF)
    # omac's unacknowledged entry lights blue, which this tower lacks: only red blinks
    assert c.show(S.IDLE, {6}, True, False).modes == (OFF, ON, BLINK)


def test_states_by_number_and_alias() -> None:
    c = parse({"states": {6: {"blue": "on"}, "Completed": {"green": "on"}}})
    assert lit(c, c.show(S.EXECUTE, *QUIET)) == {"green": ON, "blue": ON}
    assert lit(c, c.show(S.COMPLETE, *QUIET)) == {"amber": ON, "green": ON}


# -- refusals --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("raw", "path", "words"),
    [
        ({"preset": "fanuc"}, "stack_light.preset", "is not one of"),
        ({"preset": ["omac"]}, "stack_light.preset", "expected one of"),
        ({"colour": 1}, "stack_light.colour", "unknown key"),
        ("omac", "stack_light", "expected a mapping"),
        ({"lights": "red"}, "stack_light.lights", "expected a list"),
        ({"lights": []}, "stack_light.lights", "0 lights"),
        ({"lights": [f"c{i}" for i in range(9)]}, "stack_light.lights", "9 lights"),
        ({"lights": ["red", 3]}, "stack_light.lights[1]", "not a light name"),
        ({"lights": ["Red Light"]}, "stack_light.lights[0]", "not a light name"),
        ({"lights": ["horn"]}, "stack_light.lights[0]", "not a light name"),
        ({"lights": ["red", "RED"]}, "stack_light.lights[1]", "listed twice"),
        ({"states": ["Execute"]}, "stack_light.states", "expected a mapping"),
        ({"states": {"Executee": {}}}, "stack_light.states.Executee", "unknown state"),
        ({"states": {"Undefined": {}}}, "stack_light.states.Undefined", "unknown state"),
        ({"states": {99: {}}}, "stack_light.states.99", "unknown state"),
        ({"states": {"Execute": "on"}}, "stack_light.states.Execute", "expected a mapping"),
        ({"states": {"Execute": {"purple": "on"}}}, "stack_light.states.Execute.purple", "light"),
        (
            {"lights": ["red", "green"], "states": {"Idle": {"amber": "on"}}},
            "stack_light.states.Idle.amber",
            "unknown light",
        ),
        ({"states": {"Execute": {"green": "blnk"}}}, "stack_light.states.Execute.green", "blink"),
        ({"states": {"Execute": {"green": 1}}}, "stack_light.states.Execute.green", "off, on"),
        ({"states": {"Execute": {"horn": "yes"}}}, "stack_light.states.Execute.horn", "true"),
        (
            {"states": {"Execute": {}, "EXECUTE": {}}},
            "stack_light.states.EXECUTE",
            "same entry",
        ),
        ({"alarms": {10: {}}}, "stack_light.alarms.10", "outside 0..9"),
        ({"alarms": {-1: {}}}, "stack_light.alarms.-1", "outside 0..9"),
        ({"alarms": {"fatal": {}}}, "stack_light.alarms.fatal", "unknown alarm entry"),
        ({"alarms": {0: {"red": "strobe"}}}, "stack_light.alarms.0.red", "off, on or blink"),
        ({"alarms": {0: {"horn": 1}}}, "stack_light.alarms.0.horn", "true or false"),
        ({"alarms": {"warning": []}}, "stack_light.alarms.warning", "expected a mapping"),
        ({"alarms": 3}, "stack_light.alarms", "expected a mapping"),
    ],
)
def test_refused(raw: Any, path: str, words: str) -> None:
    found = problems(raw)
    assert any(p == path and words in x for p, x in found), found


def test_refusal_is_one_sentence_per_problem_naming_the_path() -> None:
    with pytest.raises(ConfigError) as info:
        parse({"states": {"Executee": {"green": "on"}}, "alarms": {12: {}}}, file="cell.yaml")
    lines = str(info.value).splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("cell.yaml: stack_light.states.Executee: unknown state")
    assert "did you mean EXECUTE" in lines[0]
    assert lines[1].startswith("cell.yaml: stack_light.alarms.12: ")


def test_node_collects_problems_with_the_rest_of_the_file() -> None:
    root = Node({"stack_light": {"preset": "nope"}, "other": 1}, "")
    root.error("an earlier problem")
    c = root.get("stack_light", stack_light, DEFAULT)
    assert c == DEFAULT  # a usable configuration despite the problem
    assert root.problems[0] == ("", "an earlier problem")
    assert [p for p, _ in root.problems[1:]] == ["stack_light.preset"]


def test_where_prefixes_the_path() -> None:
    with pytest.raises(ConfigError) as info:
        parse({"preset": 1}, where="units.filler.stack_light")
    assert info.value.problems[0][0] == "units.filler.stack_light.preset"


# -- OPC UA ----------------------------------------------------------------------------------------
def test_encode_opcua() -> None:
    assert encode_opcua(Shown((OFF, ON, BLINK, OFF), False)) == [0, 1, 2, 0]
    assert encode_opcua(Shown((BLINK, OFF, ON), True)) == [2 | 4, 0, 1]
    assert encode_opcua(Shown((), True)) == [4]
    assert encode_opcua(Shown((), False)) == []
    shown = DEFAULT.show(S.ABORTED, {0}, True, False)
    assert encode_opcua(shown) == [BLINK | 4, OFF, OFF, ON]
