"""Issue 28: the page's scripts (packml_ros2/hmi/static) are ES modules loaded without a build
step, one per screen, and none decides what a unit or the cell accepts: those rules come from the
server with the data (a unit's ``why``: its rule book; the cell status' ``why``: the coordinator's
status). Read as text: what the browser tests (test_browser.py) cannot see missing until a screen
is opened."""

from __future__ import annotations

import re
from pathlib import Path

from packml_ros2.core.numbers import Cmd, Mode, State

STATIC = Path(__file__).resolve().parents[2] / "packml_ros2" / "hmi" / "static"
#: the pages' entry modules (index.html: the operator screens; line.html: the line page)
ENTRIES = {"index.html": STATIC / "app.js", "line.html": STATIC / "line.js"}
MODULES = sorted([*ENTRIES.values(), STATIC / "diagram.js", *(STATIC / "app").glob("*.js")])
IMPORT = re.compile(r"^import (?:\{([^}]*)\}|\* as [\w$]+) from \"([^\"]+)\";", re.M)
EXPORTED = re.compile(r"^export (?:async )?(?:function|const|let|class) ([\w$]+)", re.M)
EXPORT_LIST = re.compile(r"^export \{([^}]*)\}", re.M)
#: PackML names a page might test against to decide for itself what may be sent
NAMES = {c.name for c in Cmd if c} | {s.name for s in State if s} | {m.name for m in Mode}
#: where a name in quotes is the page's own look or words, not a rule: (module, name)
WORDS = {
    ("app/actions.js", "ABORT"),  # which actions are asked twice (they cannot be undone)
}
LOOKS = {"app/dom.js", "diagram.js"}  # colours and button order; the diagram's grid


def _exports(path: Path) -> set[str]:
    text = path.read_text()
    names = set(EXPORTED.findall(text))
    for group in EXPORT_LIST.findall(text):
        names |= {n.strip() for n in group.split(",") if n.strip()}
    return names


def test_the_page_is_es_modules_and_every_import_is_there() -> None:
    for page, entry in ENTRIES.items():
        scripts = re.findall(r"<script[^>]*>", (STATIC / page).read_text())
        module = f'<script type="module" src="/static/{entry.name}">'
        vendor = [s for s in scripts if "/static/vendor/" in s]  # (Chart.js: a classic script)
        assert [s for s in scripts if s not in vendor] == [module], (page, scripts)
    assert len(MODULES) >= 8, MODULES
    for module in MODULES:
        text = module.read_text()
        assert "window.PackmlDiagram" not in text and '"use strict"' not in text, module.name
        for names, source in IMPORT.findall(text):
            target = (module.parent / source).resolve()
            assert target.is_file() and target.is_relative_to(STATIC), (module.name, source)
            wanted = {n.split(" as ")[0].strip() for n in names.split(",") if n.strip()}
            missing = wanted - _exports(target)
            assert not missing, f"{module.name} imports {missing} that {source} does not export"
    imported = {
        (module.parent / source).resolve()
        for module in MODULES
        for _, source in IMPORT.findall(module.read_text())
    }
    assert imported == set(MODULES) - set(ENTRIES.values()), "a module nobody imports"


def test_no_module_decides_what_a_unit_or_the_cell_accepts() -> None:
    """No command, state or mode name is tested against (nor a mode number): "only STOP and ABORT
    while a sequence runs" and "EMs are switched outside PRODUCTION only" were written here."""
    found = []
    for module in MODULES:
        rel = module.relative_to(STATIC).as_posix()
        if rel in LOOKS:
            continue
        text = module.read_text()
        for name in re.findall(r"[\"'`]([A-Z_]+)[\"'`]", text):
            if name in NAMES and (rel, name) not in WORDS:
                found.append((rel, name))
        found += [(rel, m) for m in re.findall(r"\.mode\s*[!=]==?\s*\d+", text)]
    assert not found, found
