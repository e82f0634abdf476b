"""Issue 15, item 7: a cell file is hostile input. Non-finite numbers, duplicate keys, references
to EMs that do not exist, alias bombs, non-UTF-8 bytes, unwritable stores and mis-attributed key
paths are refused with one short line each, quickly, in bounded memory, never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from contextlib import suppress
from pathlib import Path

import pytest

from packml_ros2.core import ConfigError, Store, load_cell, parse_cell

# 332 bytes: nine levels of nine aliases, 9**9 (387 million) strings once expanded
ALIAS_BOMB = """cell: c
a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]
b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]
c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]
d: &d [*c,*c,*c,*c,*c,*c,*c,*c,*c]
e: &e [*d,*d,*d,*d,*d,*d,*d,*d,*d]
f: &f [*e,*e,*e,*e,*e,*e,*e,*e,*e]
g: &g [*f,*f,*f,*f,*f,*f,*f,*f,*f]
h: &h [*g,*g,*g,*g,*g,*g,*g,*g,*g]
i: &i [*h,*h,*h,*h,*h,*h,*h,*h,*h]
units: {u: {description: *i}}
"""


def load_text(tmp_path: Path, text: str | bytes) -> list[tuple[str, str]]:
    f = tmp_path / "cell.yaml"
    if isinstance(text, bytes):
        f.write_bytes(text)
    else:
        f.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_cell(f)
    return info.value.problems


@pytest.mark.parametrize(
    ("yaml_text", "path"),
    [
        ("timeouts: {resetting: .nan}", "units.u.timeouts.resetting"),
        ("em_lease: .inf", "units.u.em_lease"),
        ("mach_design_speed: .Inf", "units.u.mach_design_speed"),
        ("mode_change_timeout: .NaN", "units.u.mode_change_timeout"),
        ("parameters: [{id: 1, value: -.inf}]", "units.u.parameters[0].value"),
        ("em_lease: 1.0e+999", "units.u.em_lease"),
    ],
)
def test_non_finite_numbers_are_refused(tmp_path: Path, yaml_text: str, path: str) -> None:
    problems = load_text(tmp_path, f"cell: c\nunits:\n  u:\n    {yaml_text}\n")
    assert [p for p, _ in problems] == [path]
    assert "expected a finite number" in problems[0][1]


def test_a_key_written_twice_is_refused_with_both_lines(tmp_path: Path) -> None:
    text = "cell: c\nunits:\n  u:\n    em_lease: 1.0\n    description: x\n    em_lease: 5.0\n"
    assert load_text(tmp_path, text) == [
        (
            "units.u.em_lease",
            "key 'em_lease' is written twice in one mapping (lines 4 and 6): keep one",
        )
    ]
    # a merge key is not a duplicate: the explicit entry overrides the merged one
    from packml_ros2.core.safe_yaml import parse_document

    ok = "cell: c\nbase: &b {em_lease: 1.0}\nunits:\n  u: {<<: *b, em_lease: 2.0}\n"
    assert parse_document(ok)["units"]["u"]["em_lease"] == 2.0


def test_a_deep_document_is_refused_in_our_words_whatever_libyaml_says(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """PyYAML 6.0.4's libyaml stops a deep document at its own limit, scanning ahead, with its own
    message ("exceeded maximum nesting depth"), before our count reaches MAX_DEPTH (a fresh clone
    took 6.0.4): the refusal must not depend on the library's release or wording (issue 24)."""
    import yaml

    from packml_ros2.core import safe_yaml

    class ScansAhead(yaml.SafeLoader):
        """As libyaml does: refuses past its own limit (here 150 levels) in its own words, before
        giving the events ahead of that point."""

        def check_event(self, *choices: type[yaml.Event]) -> bool:
            if not getattr(self, "looked_ahead", False):
                self.looked_ahead, depth, past = True, 0, None
                with suppress(yaml.YAMLError):  # (other errors: when the parser meets them)
                    for event in yaml.parse(self.buffer.rstrip("\0"), Loader=yaml.SafeLoader):
                        depth += isinstance(event, yaml.CollectionStartEvent)
                        depth -= isinstance(event, yaml.CollectionEndEvent)
                        if depth > 150:
                            past = event.start_mark
                            break
                if past is not None:
                    raise yaml.scanner.ScannerError("while increasing flow level", None,
                                                    "the library's own words", past)  # fmt: skip
            return bool(super().check_event(*choices))

    monkeypatch.setattr(safe_yaml, "_LOADER", ScansAhead)
    with pytest.raises(ConfigError) as refused:
        safe_yaml.parse_document("a: " + "[" * 200_000 + "]" * 200_000 + "\n", "deep.yaml")
    assert refused.value.problems == [("line 1", "nested more than 100 levels deep")]
    with pytest.raises(ConfigError) as refused:  # a syntax error stays one, with its line
        safe_yaml.parse_document("a: " + "[" * 20 + "\nb: ]\n", "bad.yaml")
    assert "not valid YAML" in refused.value.problems[0][1], refused.value.problems


def test_an_alarm_naming_an_em_that_does_not_exist_is_refused() -> None:
    doc = {"cell": "c", "units": {"u": {"equipment_modules": {"robot": {}},
                                        "alarms": [{"id": 1, "em": "robot"},
                                                   {"id": 2, "em": "robto"}]}}}  # fmt: skip
    with pytest.raises(ConfigError) as info:
        parse_cell(doc)
    assert info.value.problems == [
        (
            "units.u.alarms[1].em",
            "no equipment module 'robto' in this unit (equipment_modules: robot)",
        )
    ]


def test_an_alias_bomb_is_refused_at_once_in_bounded_memory(tmp_path: Path) -> None:
    f = tmp_path / "bomb.yaml"
    f.write_text(ALIAS_BOMB)
    assert len(ALIAS_BOMB.encode()) < 400
    # in a fresh process, to measure its peak memory
    script = (
        "import json, resource, sys, time\n"
        "from packml_ros2.core import ConfigError, load_cell\n"
        "peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        "before, t = peak(), time.monotonic()\n"
        "try:\n"
        "    load_cell(sys.argv[1]); text = ''\n"
        "except ConfigError as exc:\n"
        "    text = str(exc)\n"
        "print(json.dumps({'text': text, 'seconds': time.monotonic() - t,\n"
        "                  'grown_mb': peak() - before}))\n"
    )
    out = subprocess.run([sys.executable, "-c", script, str(f)], capture_output=True, text=True,
                         timeout=60, check=True)  # fmt: skip
    result = json.loads(out.stdout)
    assert "alias bomb" in result["text"] and len(result["text"]) < 500, result["text"][:1000]
    # was: minutes, a 522 MB message and +2.1 GB; now a few ms and no measurable growth
    assert result["seconds"] < 2.0 and result["grown_mb"] < 20, {**result, "text": ""}


def test_aliases_of_ordinary_size_are_fine_and_self_reference_is_refused() -> None:
    from packml_ros2.core.safe_yaml import MAX_EXPANDED, parse_document

    doc = parse_document("x: &x [1, 2]\ny: [*x, *x]\n")
    assert doc == {"x": [1, 2], "y": [[1, 2], [1, 2]]}
    with pytest.raises(ConfigError, match="an alias contains itself"):
        parse_document("a: &a [1, *a]\n")
    assert MAX_EXPANDED >= 1_000_000  # a large real cell (100 units, 50 alarms each) fits


def test_error_messages_stay_short_whatever_the_file_holds(tmp_path: Path) -> None:
    huge = "x" * 1_000_000
    problems = load_text(tmp_path, f"cell: c\nunits:\n  u:\n    em_lease: '{huge}'\n")
    assert len(problems) == 1 and len(problems[0][1]) < 200, problems[0][1][:300]
    # ten thousand unknown keys: the report says how many more there are
    keys = "\n".join(f"    k{i}: 1" for i in range(10_000))
    with pytest.raises(ConfigError) as info:
        load_cell(_write(tmp_path, f"cell: c\nunits:\n  u:\n{keys}\n"))
    lines = str(info.value).splitlines()
    assert len(lines) == 51 and lines[-1].endswith("... and 9950 more problems")
    assert len(str(info.value)) < 40_000  # 51 lines of at most ~700 characters
    # a key of a megabyte is cut in the path
    with pytest.raises(ConfigError) as info:
        load_cell(_write(tmp_path, f"cell: c\nunits:\n  u:\n    {huge}: 1\n"))
    assert len(str(info.value)) < 1_000


def _write(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "cell.yaml"
    f.write_text(text)
    return f


def test_a_file_that_is_not_utf8_gets_one_line(tmp_path: Path) -> None:
    problems = load_text(tmp_path, b"cell: c\nunits:\n  u: {description: caf\xe9}\n")
    assert problems == [("line 3", "not UTF-8 text (byte 0xe9): save the file as UTF-8")]
    problems = load_text(tmp_path, b"cell: c\x00\n")
    assert problems == [("line 1", "not valid YAML: character #x0000 is not allowed in YAML")]
    problems = load_text(tmp_path, b"cell: !!int abc\n")
    assert problems[0][1].startswith("not valid YAML: a value cannot be read")


def test_type_errors_in_defaults_are_reported_under_defaults() -> None:
    doc = {"cell": "c", "defaults": {"em_lease": "two", "timeouts": {"Resetting": -1}},
           "units": {"a": {}, "b": {}, "c": {"em_lease": 1.0}}}  # fmt: skip
    with pytest.raises(ConfigError) as info:
        parse_cell(doc, "cell.yaml")
    assert info.value.problems == [
        ("defaults.em_lease", "expected a number, got 'two'"),
        ("defaults.timeouts.Resetting", "must be greater than 0, got -1"),
    ]


def test_persistence_path_only_substitutes_cell_and_unit() -> None:
    doc = {"cell": "c", "units": {"u": {"persistence": {"path": "/x/{0}/{cell}/{unit}{y.z}.db"}}}}
    assert parse_cell(doc).units["u"].persistence_path == "/x/{0}/c/u{y.z}.db"


def test_an_unwritable_store_is_one_line_and_exit_code_2(tmp_path: Path) -> None:
    from packml_ros2.core import StoreError

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    with pytest.raises(StoreError) as info:
        Store(blocker / "sub" / "u.sqlite3", "u")
    text = str(info.value)
    assert "\n" not in text and "cannot open the admin store of unit u" in text
    assert "persistence" in text
    # (a file that is not a store is moved aside and the unit starts: test_edge_cases)
    f = _write(tmp_path, f"cell: c\nunits:\n  u: {{persistence: {{path: '{blocker}/u.db'}}}}\n"
                         "coordinator: {enabled: false}\n")  # fmt: skip
    started = time.monotonic()
    for prefix, argv in (("unit_node", ["-m", "packml_ros2.unit_node", str(f)]),
                         ("packml launch", ["-m", "packml_ros2.cli.main", "launch", str(f)])):  # fmt: skip
        result = subprocess.run([sys.executable, *argv], capture_output=True, text=True,
                                timeout=60, check=False)  # fmt: skip
        assert result.returncode == 2, result
        assert "Traceback" not in result.stderr, result.stderr
        lines = [x for x in result.stderr.splitlines() if x.startswith(f"{prefix}:")]
        assert len(lines) == 1 and "cannot open the admin store" in lines[0], result.stderr
    assert time.monotonic() - started < 60
