"""Every document the code cites is in the repository, with the section it cites (issue 28, item
5): a user with nothing but a clone can follow each citation, and the documents say what the code
does.

- A citation is ``docs/<file>.md``, optionally followed by ``§N``, ``section N`` or
  ``sections N-M, K``, in any tracked file of packml_ros2/, test/, bench/, tools/, docs/ and the
  README: the file must exist and have a numbered heading for each section cited.
- No file cites a document outside the repository (the specification beside the checkout that a
  clone never has).
- Relative links of docs/*.md and the README's links into docs/ lead to a file, and to a heading
  of it when they name an anchor.
- Names of the code that docs/*.md cite as ``module.NAME`` (``rules.COMMANDS_2022``) exist.
- docs/ros-api.md's service and topic tables are the ones the unit node and the coordinator
  create, with their types and QoS profiles.
"""

from __future__ import annotations

import importlib
import re
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from test.test_machine_paths import tracked_text_files

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SCANNED = ("packml_ros2", "test", "bench", "tools", "docs", "README.md")

#: ``docs/<file>.md`` and what follows it on the line (where a section number would be).
CITATION = re.compile(r"(?<![\w/.-])docs/([\w.-]+?\.md)(?:#([\w-]+))?(?=([^\n]*))")
#: The sections cited right after a document: ``§4``, ``section 4``, ``(sections 2-4, 7)``.
SECTIONS = re.compile(
    r"^,?\s*\(?\s*(?:§\s*|sections?\s+)(\d+(?:\s*-\s*\d+)?(?:\s*,\s*\d+(?:\s*-\s*\d+)?)*)"
)
#: Citations of documents outside the repository: the specification's files by their bare names,
#: the shared folder's specification and sources.
OUTSIDE = re.compile(r"(?<![\w/.-])(?:PACKML|ROS_API)\.md|shared/(?:spec|seeds)\b|\(research/\)")
HEADING = re.compile(r"^(#{1,6})\s+(.+?)\s*$", re.MULTILINE)
LINK = re.compile(r"\]\(([^)\s]+)\)")


def tracked(*paths: str) -> list[Path]:
    """Tracked text files under ``paths`` (git: no venv, caches or node_modules)."""
    return [
        f
        for f in tracked_text_files()
        if any(f.relative_to(ROOT).parts[0] == p.split("/")[0] for p in paths)
    ]


def scanned_files() -> list[Path]:
    files = tracked(*SCANNED)
    own = Path(__file__).resolve()
    if own not in files:  # (before it is committed)
        files.append(own)
    return files


@cache
def headings(doc: Path) -> list[str]:
    text = re.sub(r"^```.*?^```", "", doc.read_text(encoding="utf-8"), flags=re.M | re.S)
    return [m.group(2) for m in HEADING.finditer(text)]


def numbered_sections(doc: Path) -> set[int]:
    """The section numbers of ``doc``'s headings (``## 4. Units, ...``)."""
    return {int(m.group(1)) for h in headings(doc) if (m := re.match(r"(\d+)\.?\s", h))}


def slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def cited_sections(tail: str) -> list[int]:
    m = SECTIONS.match(tail)
    if m is None:
        return []
    out: list[int] = []
    for part in m.group(1).split(","):
        lo, _, hi = part.strip().partition("-")
        out.extend(range(int(lo), int(hi or lo) + 1))
    return out


def citations(text: str) -> list[tuple[str, str, list[int]]]:
    """(document, anchor, sections) of every citation in ``text``."""
    return [(m.group(1), m.group(2) or "", cited_sections(m.group(3)))
            for m in CITATION.finditer(text)]  # fmt: skip


def where(path: Path, text: str, offset: int) -> str:
    return f"{path.relative_to(ROOT)}:{text.count(chr(10), 0, offset) + 1}"


# -- the parser itself --------------------------------------------------------------------------------
def test_citation_forms_are_read_with_their_sections() -> None:
    text = (
        "(docs/packml.md §4): x\n"
        "docs/packml.md section 2, rules section 7\n"
        "docs/packml.md (sections 2-4, 7) written here\n"
        "see docs/em-protocol.md) and docs/packml.md sections 5, 6.\n"
        "[a](docs/ros-api.md#sources)\n"
    )
    assert citations(text) == [
        ("packml.md", "", [4]),
        ("packml.md", "", [2]),
        ("packml.md", "", [2, 3, 4, 7]),
        ("em-protocol.md", "", []),
        ("packml.md", "", [5, 6]),
        ("ros-api.md", "sources", []),
    ]
    assert slug("1. Numbers (all sources agree except where noted)") == (
        "1-numbers-all-sources-agree-except-where-noted"
    )
    assert OUTSIDE.search("as in " + "PACKML" + ".md section 4")
    assert OUTSIDE.search("see ../shared/" + "spec/ROS_API.md")
    assert not OUTSIDE.search("docs/packml.md and ../shared/vendor/ros2-tools")


# -- citations -------------------------------------------------------------------------------------------
def test_every_cited_document_and_section_is_in_the_repository() -> None:
    problems = []
    count = 0
    for path in scanned_files():
        text = path.read_text(encoding="utf-8", errors="replace")
        for m in CITATION.finditer(text):
            count += 1
            doc = DOCS / m.group(1)
            at = where(path, text, m.start())
            if not doc.is_file():
                problems.append(f"{at}: cites docs/{m.group(1)}, which does not exist")
                continue
            missing = set(cited_sections(m.group(3))) - numbered_sections(doc)
            if missing:
                problems.append(f"{at}: cites section(s) {sorted(missing)} of docs/{m.group(1)}, "
                                "which has no such heading")  # fmt: skip
            anchor = m.group(2)
            if anchor and anchor not in {slug(h) for h in headings(doc)}:
                problems.append(f"{at}: cites docs/{m.group(1)}#{anchor}: no such heading")
    assert count >= 40, f"only {count} citations found: is the pattern still right?"
    assert not problems, "\n".join(problems)


def test_nothing_cites_a_document_outside_the_repository() -> None:
    own = Path(__file__).resolve()
    problems = []
    for path in scanned_files():
        if path == own:
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        problems += [f"{where(path, text, m.start())}: {m.group(0)!r}" for m in OUTSIDE.finditer(text)]  # fmt: skip
    assert not problems, (
        "cite docs/packml.md or docs/ros-api.md instead (files a clone has):\n"
        + "\n".join(problems)
    )


def test_packml_md_has_the_nine_sections_the_code_cites() -> None:
    assert numbered_sections(DOCS / "packml.md") == set(range(1, 10))


def test_links_of_the_documents_resolve() -> None:
    problems = []
    sources = [*tracked("docs"), ROOT / "README.md"]
    for path in sources:
        if path.suffix != ".md":
            continue
        text = path.read_text(encoding="utf-8")
        own = {slug(h) for h in headings(path)}
        for m in LINK.finditer(text):
            target, _, anchor = m.group(1).partition("#")
            if re.match(r"[a-z]+:", target):  # https:, mailto:
                continue
            if path.name == "README.md" and not target.startswith("docs/") and target:
                continue  # the README's own links are its tests' business
            at = where(path, text, m.start())
            file = (path.parent / target).resolve() if target else path
            if not file.exists():
                problems.append(f"{at}: link to {target}, which does not exist")
            elif anchor and file.suffix == ".md":
                slugs = own if file == path else {slug(h) for h in headings(file)}
                if anchor not in slugs:
                    problems.append(f"{at}: link to {m.group(1)}: no such heading")
    assert not problems, "\n".join(problems)


@cache
def core_modules() -> frozenset[str]:
    return frozenset(p.stem for p in (ROOT / "packml_ros2" / "core").glob("*.py"))


def test_code_names_the_documents_cite_exist() -> None:
    """``rules.COMMANDS_2022``, ``machine.UnitMachine.step``: a core module (or ``qos``) and a
    name in it. A rule renamed or moved in the code fails here until the document follows."""
    modules = {m: f"packml_ros2.core.{m}" for m in core_modules()} | {"qos": "packml_ros2.qos"}
    problems = []
    count = 0
    for path in tracked("docs"):
        if path.suffix != ".md":
            continue
        for dotted in re.findall(r"`([a-z_]+(?:\.[A-Za-z_]\w*)+)`", path.read_text(encoding="utf-8")):  # fmt: skip
            module, *names = dotted.split(".")
            if module not in modules:
                continue
            count += 1
            obj: Any = importlib.import_module(modules[module])
            for name in names:
                if not hasattr(obj, name):
                    problems.append(f"docs/{path.name}: `{dotted}`: {module} has no {'.'.join(names)}")  # fmt: skip
                    break
                obj = getattr(obj, name)
    assert count >= 50, f"only {count} names found: is the pattern still right?"
    assert not problems, "\n".join(problems)


# -- docs/ros-api.md against the nodes --------------------------------------------------------------------
def doc_section(title: str) -> str:
    text = (DOCS / "ros-api.md").read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def doc_rows(title: str, prefix: str) -> dict[str, tuple[str, str]]:
    """name (relative to ``prefix``) -> (type, QoS profile) of the table rows under ``title``."""
    shortcuts = [verb for verb, _ in trigger_shortcuts()]
    rows: dict[str, tuple[str, str]] = {}
    for line in doc_section(title).splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 3 or cells[0] in ("service", "topic", "name"):
            continue
        names = re.findall(r"`([^`]+)`", cells[0])
        if not names:
            continue
        kind = re.search(r"`([\w/]+)`", cells[1])
        type_name = kind.group(1).rsplit("/", 1)[-1] if kind else ""
        profile = re.match(r"`(\w+)`", cells[2])
        qos = profile.group(1) if profile and title.endswith("topics") else ""
        if "..." in cells[0]:  # `<p>/reset` ... `complete`: every shortcut
            names = [f"{prefix}{verb}" for verb in shortcuts]
        for name in names:
            rows[name.removeprefix(prefix) if name.startswith(prefix) else name] = (type_name, qos)
    return rows


@cache
def trigger_shortcuts() -> tuple[tuple[str, Any], ...]:
    from packml_ros2.responses import TRIGGER_SHORTCUTS

    return TRIGGER_SHORTCUTS


def code_entities(path: str, pattern: str) -> dict[str, tuple[str, str]]:
    """name -> (type, QoS profile) of the services, publishers or subscriptions that ``pattern``
    finds in ``path`` (groups: type, name, profile); ``{verb}`` names are the Trigger shortcuts."""
    text = (ROOT / path).read_text(encoding="utf-8")
    out: dict[str, tuple[str, str]] = {}
    for type_name, found, qos_name in re.findall(pattern, text):
        profile = {"status_publisher": "STATUS"}.get(qos_name, qos_name)
        name = "{verb}" if found == "verb" else found.removeprefix("~/")
        kind = {"TriggerSrv": "Trigger"}.get(type_name, type_name)
        for verb, _ in trigger_shortcuts() if "{verb}" in name else [("", None)]:
            out[name.replace("{verb}", verb)] = (kind, profile)
    return out


def declared_services() -> dict[str, tuple[str, str]]:
    """The unit's services as packml_ros2/ros/interface.py declares them (the unit node, the
    client and the PLC bridge create them from it)."""
    from packml_ros2.ros import interface

    return {s.name: (s.type.__name__, "") for s in interface.SERVICES}


def same_profile(name: str) -> str:
    """The first name qos.py gives the profile ``name`` is (STATUS, ADMIN ... are LATCHED)."""
    from packml_ros2 import qos

    profile = getattr(qos, name, None)
    return next((k for k, v in vars(qos).items() if k.isupper() and v is profile), name)


def declared_topics() -> dict[str, tuple[str, str]]:
    """The unit's topics as declared: name -> (type, the qos.py profile, by its first name)."""
    from packml_ros2 import qos
    from packml_ros2.ros import interface

    first = {id(v): k for k, v in reversed(list(vars(qos).items())) if k.isupper()}
    return {t.name: (t.type.__name__, first.get(id(t.qos), "?")) for t in interface.TOPICS}


PUBLISHER = r'create_publisher\(\s*(\w+),\s*"([~/][\w/]+)",\s*qos\.(?:with_lease\(qos\.)?(\w+)'
SERVE = r'serve\((\w+), f?"(~/[\w/{}]+)", (?:partial\()?self\._srv()'


@pytest.mark.parametrize(
    ("title", "prefix", "found"),
    [
        ("Unit node: services", "<unit>/", declared_services),
        ("Unit node: topics", "<unit>/", declared_topics),
        ("Coordinator node", "<cell>/coordinator/",
         lambda: {k: (t, "") for k, (t, _) in (
             code_entities("packml_ros2/coordinator_node.py", SERVE)
             | code_entities("packml_ros2/coordinator_node.py", PUBLISHER)).items()}),
    ],
)  # fmt: skip
def test_ros_api_lists_what_the_nodes_create(title: str, prefix: str, found: Any) -> None:
    code = found()
    doc = doc_rows(title, prefix)
    if title == "Unit node: topics":  # a profile and its aliases are one
        doc = {k: (t, same_profile(q)) for k, (t, q) in doc.items()}
    if title == "Coordinator node":  # its table has no QoS column of profile names only
        doc = {k: (t, "") for k, (t, _) in doc.items()}
        code = {k: v for k, v in code.items() if k != "/diagnostics"}
    assert len(code) >= 6, f"found only {sorted(code)} in the code: is the pattern still right?"
    assert sorted(set(code) - set(doc)) == [], f"the code creates these, docs/ros-api.md ({title}) omits them"  # fmt: skip
    assert sorted(set(doc) - set(code)) == [], f"docs/ros-api.md ({title}) lists these, the code has none"  # fmt: skip
    wrong = {k: (doc[k], code[k]) for k in code if doc[k] != code[k]}
    assert wrong == {}, "(type, QoS) as documented vs as created"
