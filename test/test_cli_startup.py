"""What a ``packml`` verb imports before it can answer (issue 13: read-only verbs in <= 1 s): a
verb's parser only, and from the engine package only what the verb uses."""

from __future__ import annotations

import importlib
import subprocess
import sys

import packml_ros2.core as core
from packml_ros2.cli import main


def subparser_names(parser: object) -> list[str]:
    action = next(a for a in parser._actions if a.dest == "verb")  # type: ignore[attr-defined]
    return list(action.choices)


def test_every_verb_is_declared_with_its_module() -> None:
    declared = [verb for verbs in main.VERB_MODULES.values() for verb in verbs]
    assert subparser_names(main.build_parser()) == declared
    for module, verbs in main.VERB_MODULES.items():
        for verb in verbs:
            assert subparser_names(main.build_parser(verb)) == list(verbs), (module, verb)


def test_the_engine_package_resolves_every_name_it_exports() -> None:
    assert sorted(core._LAZY) == sorted(core.__all__)
    for name, module in core._LAZY.items():
        loaded = importlib.import_module(module, "packml_ros2.core")
        expected = loaded if module == f".{name}" else getattr(loaded, name)
        assert getattr(core, name) is expected, name


def test_packml_status_does_not_load_the_engine_or_the_other_verbs() -> None:
    probe = (
        "import sys; from packml_ros2.cli import main; main.build_parser('status'); "
        "import packml_ros2.cli.status; print(' '.join(sorted(sys.modules)))"
    )
    loaded = set(
        subprocess.run(
            [sys.executable, "-c", probe], check=True, capture_output=True, text=True
        ).stdout.split()
    )
    heavy = {"packml_ros2.core.config", "packml_ros2.core.unit", "packml_ros2.core.persistence",
             "packml_ros2.cli.report", "packml_ros2.cli.bag", "packml_ros2.cli.hmi"}  # fmt: skip
    assert "packml_ros2.cli.status" in loaded
    assert not heavy & loaded, sorted(heavy & loaded)
