"""``packml replay --junit FILE``: the result as JUnit XML, one test case per unit and per check of a
line (its episodes, its losses), so a CI system shows which one failed; a recording that cannot
be replayed is one test case in error with the reason code (``RecordingError.reason``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .line import LineResult
    from .recording import RecordingError
    from .replay import ReplayResult

#: Characters XML 1.0 cannot hold (a recorded text may carry any): replaced.
_BAD = dict.fromkeys((*range(9), 11, 12, *range(14, 32)), "?")


def _text(s: str) -> str:
    return s.translate(_BAD)


def write(
    path: str | Path,
    bag: str | Path,
    seconds: float,
    units: ReplayResult | None,
    lines: list[LineResult],
    error: RecordingError | None = None,
) -> None:
    """Write the JUnit XML report of one replay of ``bag`` to ``path``."""
    name = Path(bag).name or str(bag)
    suite = ET.Element("testsuite", name=f"packml replay {_text(name)}", time=f"{seconds:.3f}")
    cases = 0
    failures = 0
    errors = 0

    def case(classname: str, test: str, took: float) -> ET.Element:
        nonlocal cases
        cases += 1
        return ET.SubElement(
            suite, "testcase", classname=_text(classname), name=_text(test), time=f"{took:.3f}"
        )

    if error is not None:
        c = case(f"packml_replay.{name}", "recording", seconds)
        e = ET.SubElement(c, "error", type=error.reason, message=_text(str(error))[:1000])
        e.text = _text(str(error))
        errors += 1
    if units is not None:
        share = units.seconds / max(len(units.units), 1)
        for u in units.units:
            c = case(
                f"packml_replay.{name}.{u.prefix.strip('/').split('/')[0]}", f"unit {u.unit}", share
            )
            if not u.ok:
                from .replay import explain

                first = u.first()
                f = ET.SubElement(
                    c,
                    "failure",
                    type="mismatch",
                    message=_text(first.headline(u.start_time) if first else "differs"),
                )
                f.text = _text("\n".join(explain(u)))
                failures += 1
    for r in lines:
        for check, problem in r.checks.items():
            c = case(
                f"packml_replay.{name}.{r.cell}",
                f"line {r.cell} {check}",
                r.seconds / max(len(r.checks), 1),
            )
            if problem:
                f = ET.SubElement(c, "failure", type="mismatch", message=_text(problem)[:1000])
                f.text = _text(problem)
                failures += 1
    suite.set("tests", str(cases))
    suite.set("failures", str(failures))
    suite.set("errors", str(errors))
    suites = ET.Element(
        "testsuites",
        tests=str(cases),
        failures=str(failures),
        errors=str(errors),
        time=f"{seconds:.3f}",
    )
    suites.append(suite)
    ET.indent(suites)
    Path(path).write_bytes(ET.tostring(suites, encoding="utf-8", xml_declaration=True) + b"\n")
