"""No tracked file names a path of this machine: the checkout, the directories above it, the home
directory, the interpreter's venv or the shared folder beside the checkout (``make test`` failed
from a fresh clone elsewhere for a test that named the interpreter of one machine). Standard
system places (/tmp, /usr, /opt ...) are not of a particular machine."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SYSTEM = {"/", "/tmp", "/var", "/var/tmp", "/usr", "/usr/local", "/opt", "/etc", "/dev", "/proc",
          "/srv", "/mnt", "/media", "/run", "/home"}  # fmt: skip


def machine_roots() -> set[str]:
    """Absolute paths that exist only on this machine, as they may be spelled."""
    places = [
        ROOT,
        Path.home(),
        Path(sys.prefix),
        Path(sys.executable).parent,
        ROOT.parent / "shared",
    ]
    roots: set[str] = set()
    for place in places:
        for spelled in {str(place), os.path.realpath(place)}:
            path = Path(spelled)
            roots.update(str(p) for p in (path, *path.parents) if str(p) not in SYSTEM)
    return roots


def mentions(text: str, roots: Iterable[str]) -> list[str]:
    """The places in ``text`` where one of ``roots`` appears as a path (not inside a longer name)."""
    found = []
    for root in sorted(roots, key=len, reverse=True):
        pattern = rf"(?<![\w.~-]){re.escape(root)}(?![\w.-])"
        found += [f"{root!r} at offset {m.start()}" for m in re.finditer(pattern, text)]
    return found


def tracked_text_files() -> list[Path]:
    names = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout.split(b"\0")
    files = []
    for name in filter(None, names):
        path = ROOT / name.decode()
        if path.is_file() and b"\0" not in path.read_bytes()[:8192]:
            files.append(path)
    return files


def test_no_tracked_file_names_a_path_of_this_machine() -> None:
    roots = machine_roots()
    assert str(ROOT) in roots and str(Path.home()) in roots
    problems = []
    for path in tracked_text_files():
        found = mentions(path.read_text(encoding="utf-8", errors="replace"), roots)
        problems += [f"{path.relative_to(ROOT)}: {where}" for where in found]
    assert not problems, "\n".join(problems)


def test_a_machine_path_is_found_and_an_ordinary_one_is_not() -> None:
    """The check itself: it catches the interpreter path of a test that ran elsewhere."""
    roots = machine_roots()
    assert mentions(f'PYTHON = "{sys.executable}"', roots)
    assert mentions(f"see {ROOT}/README.md", roots)
    assert not mentions("lock files in /tmp/packml_ros2_domains, /usr/bin/env bash", roots)
    assert not mentions(f"a name like x{ROOT.name}", {str(ROOT)})
