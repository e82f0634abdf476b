"""The report of a conformance run: a table for people, JSON, JUnit XML (one test suite per
group, one test case per check: a CI system shows each failure with its sentence)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any
from xml.etree import ElementTree as ET

from ..core.rules import Rules
from .plan import Case, describe
from .runner import Result, Run
from .target import Shown

MARK = {"pass": "PASS", "fail": "FAIL", "skip": "SKIP"}


@dataclass(frozen=True)
class About:
    """What was certified against what: the target, its face, the profile, the declared model
    (``model``: "2022" or "2015", the Hold and Complete masks, the modes), when and how long."""

    target: str
    face: str
    profile: str
    model: str
    modes: Mapping[int, str]
    started: str
    seconds: float


def _shown(s: Shown | None, modes: Mapping[int, str]) -> str:
    return "unknown" if s is None else f"{s.state.name} ({modes.get(s.mode, s.mode)})"


def summary(run: Run) -> str:
    verdict = "PASSED" if run.passed else "FAILED"
    return (
        f"{verdict}: {run.count('pass')} passed, {run.count('fail')} failed, "
        f"{run.count('skip')} skipped"
    )


def header(about: About, found: Shown | None) -> str:
    return (
        f"packml conform {about.target} ({about.face}), profile {about.profile}, "
        f"model {about.model}\nfound in {_shown(found, dict(about.modes))}\n"
    )


def line(result: Result, names: Mapping[int, str], width: int) -> str:
    """One check's line of the table."""
    name = result.case.name(dict(names))
    return f"{MARK[result.outcome]}  {result.case.group:<8} {name:<{width}}  {result.message}"


def footer(run: Run, about: About) -> str:
    """What the run left, and the verdict."""
    names = dict(about.modes)
    lines = [""]
    if run.stopped_early:
        lines.append(
            f"stopped at the first failure; the target was left in {_shown(run.left, names)}"
        )
    elif run.restored:
        lines.append(f"the target was brought back to {_shown(run.found, names)}")
    elif run.note:
        lines.append(run.note)
    lines.append(f"the run took {about.seconds:.1f} s")
    lines.append(summary(run))
    return "\n".join(lines)


def text(run: Run, about: About) -> str:
    """The table for people: what was found, one line per check, then the verdict."""
    width = max((len(r.case.name(dict(about.modes))) for r in run.results), default=10)
    body = [line(r, about.modes, width) for r in run.results]
    return "\n".join([header(about, run.found), *body, footer(run, about)])


def _case(case: Case, rules: Rules, names: dict[int, str]) -> dict[str, Any]:
    return {
        "group": case.group,
        "name": case.name(names),
        "kind": case.kind,
        "mode": case.mode,
        "state": case.state.name,
        "command": case.cmd or None,
        "to_mode": case.to_mode or None,
        "check": case.check or None,
        "expected": describe(case, rules, names),
    }


def as_json(run: Run, about: About, rules: Rules) -> str:
    names = dict(about.modes)
    doc = {
        "target": about.target,
        "face": about.face,
        "profile": about.profile,
        "model": about.model,
        "modes": {str(k): v for k, v in about.modes.items()},
        "started": about.started,
        "seconds": round(about.seconds, 3),
        "passed": run.passed,
        "counts": {k: run.count(k) for k in ("pass", "fail", "skip")},
        "found": _shown(run.found, names),
        "stopped_early": run.stopped_early,
        "restored": run.restored,
        "left": _shown(run.left, names),
        "note": run.note,
        "results": [
            {
                **_case(r.case, rules, names),
                "outcome": r.outcome,
                "message": r.message,
                "seconds": None if r.seconds is None else round(r.seconds, 4),
            }
            for r in run.results
        ],
    }
    return json.dumps(doc, indent=2)


def junit(run: Run, about: About, rules: Rules) -> str:
    """JUnit XML: ``<testsuites>`` with one ``<testsuite>`` per group."""
    names = dict(about.modes)
    root = ET.Element(
        "testsuites",
        name=f"packml conform {about.target}",
        tests=str(len(run.results)),
        failures=str(run.count("fail")),
        skipped=str(run.count("skip")),
        time=f"{about.seconds:.3f}",
    )
    groups: dict[str, list[Any]] = {}
    for r in run.results:
        groups.setdefault(r.case.group, []).append(r)
    for group, results in groups.items():
        suite = ET.SubElement(
            root,
            "testsuite",
            name=f"packml.conform.{group}",
            tests=str(len(results)),
            failures=str(sum(r.outcome == "fail" for r in results)),
            skipped=str(sum(r.outcome == "skip" for r in results)),
            errors="0",
            timestamp=about.started,
            time=f"{sum(r.seconds or 0.0 for r in results):.3f}",
        )
        for r in results:
            case = ET.SubElement(
                suite,
                "testcase",
                classname=f"packml.conform.{group}",
                name=r.case.name(names),
                time=f"{r.seconds or 0.0:.3f}",
            )
            if r.outcome == "fail":
                failure = ET.SubElement(case, "failure", message=r.message, type="nonconformance")
                failure.text = f"expected: {describe(r.case, rules, names)}\n{r.message}"
            elif r.outcome == "skip":
                ET.SubElement(case, "skipped", message=r.message)
    if run.stopped_early:
        suite = ET.SubElement(root, "testsuite", name="packml.conform.run", tests="1", failures="1")
        case = ET.SubElement(suite, "testcase", classname="packml.conform.run", name="complete run")
        ET.SubElement(case, "failure", message="stopped at the first failure (--stop-on-first)")
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
