"""A small declarative validator for YAML configuration: every error names the file, the key path
and what is wrong, and all errors of a file are reported together."""

from __future__ import annotations

import difflib
import math
import reprlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

#: Bounds of an error report: a hostile file must not turn into megabytes of message.
MAX_PROBLEMS = 50
MAX_PATH = 200
MAX_PROBLEM = 400

_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 60
_repr.maxlist = _repr.maxtuple = _repr.maxset = _repr.maxdict = 6
_repr.maxlevel = 3


def shown(value: Any) -> str:
    """``repr(value)`` cut to a few dozen characters (a value quoted in an error message)."""
    return _repr.repr(value)


def _cut(text: str, limit: int) -> str:
    return text if len(text) <= limit else f"{text[: limit - 15]}... ({len(text)} chars)"


class ConfigError(ValueError):
    """Bad configuration. ``problems`` lists ``(key path, problem)``; str() is one line each.

    Bounded: each path and problem is cut, the same problem is listed once (a ``defaults:`` entry
    seen by every unit), and past :data:`MAX_PROBLEMS` one last line says how many more there are.
    """

    def __init__(self, file: str, problems: list[tuple[str, str]]) -> None:
        unique = list(dict.fromkeys(problems))
        kept = [
            (_cut(p, MAX_PATH), _cut(" ".join(x.splitlines()), MAX_PROBLEM))
            for p, x in unique[:MAX_PROBLEMS]
        ]
        if len(unique) > MAX_PROBLEMS:
            kept.append(("", f"... and {len(unique) - MAX_PROBLEMS} more problems"))
        self.file = file = _cut(file, MAX_PATH)
        self.problems = kept
        lines = [f"{file}: {path or '<top>'}: {problem}" for path, problem in kept]
        super().__init__("\n".join(lines))

    def prefixed(self, prefix: str) -> str:
        """The report for a command line: ``<prefix>: <file>: <path>: <problem>`` per line."""
        return "\n".join(f"{prefix}: {line}" for line in str(self).splitlines())


class _Invalid(Exception):
    """Raised by a parser for the value at hand; the node turns it into a problem with a path."""


def invalid(problem: str) -> _Invalid:
    return _Invalid(problem)


@dataclass
class Node:
    """A value in the document with its key path; parse children with :meth:`get`.

    ``origins`` maps keys of a merged mapping to where they are written in the file (a unit's
    entries taken from ``defaults:`` are reported as ``defaults.<key>``)."""

    value: Any
    path: str
    problems: list[tuple[str, str]] = field(default_factory=list)
    origins: Mapping[str, str] | None = None

    def child(self, key: str | int, value: Any) -> Node:
        if self.origins and isinstance(key, str) and key in self.origins:
            return Node(value, self.origins[key], self.problems)
        path = (
            f"{self.path}[{key}]"
            if isinstance(key, int)
            else f"{self.path}.{key}"
            if self.path
            else str(key)
        )
        return Node(value, path, self.problems)

    def error(self, problem: str) -> None:
        self.problems.append((self.path, problem))

    def mapping(self) -> Mapping[str, Any]:
        if self.value is None:
            return {}
        if not isinstance(self.value, Mapping):
            self.error(f"expected a mapping, got {type(self.value).__name__} {shown(self.value)}")
            return {}
        return self.value

    def check_keys(self, allowed: set[str] | Mapping[str, Any]) -> None:
        for key in self.mapping():
            if str(key) not in allowed:
                close = difflib.get_close_matches(str(key)[:100], list(allowed), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                self.child(str(key), None).error(
                    f"unknown key{hint}; valid keys: {', '.join(sorted(allowed))}"
                )

    def get(self, key: str, parse: Callable[[Node], T], default: T) -> T:
        m = self.mapping()
        if key not in m:
            return default
        return self.child(key, m[key]).parse(parse, default)

    def parse(self, parse: Callable[[Node], T], default: T) -> T:
        try:
            return parse(self)
        except _Invalid as exc:
            self.error(str(exc))
            return default

    def list_at(self, key: str) -> list[Node]:
        """The elements of the list under ``key`` (none when absent)."""
        m = self.mapping()
        return self.child(key, m[key]).elements() if key in m else []

    def items_at(self, key: str) -> list[tuple[str, Node]]:
        """The entries of the mapping under ``key`` (none when absent)."""
        m = self.mapping()
        return self.child(key, m[key]).items() if key in m else []

    def items(self) -> list[tuple[str, Node]]:
        return [(str(k), self.child(str(k), v)) for k, v in self.mapping().items()]

    def elements(self) -> list[Node]:
        if self.value is None:
            return []
        if not isinstance(self.value, list):
            self.error(f"expected a list, got {type(self.value).__name__} {shown(self.value)}")
            return []
        return [self.child(i, v) for i, v in enumerate(self.value)]


# -- leaf parsers ----------------------------------------------------------------------------------
def boolean(n: Node) -> bool:
    if not isinstance(n.value, bool):
        raise invalid(f"expected true or false, got {shown(n.value)}")
    return n.value


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[Node], int]:
    def parse(n: Node) -> int:
        if isinstance(n.value, bool) or not isinstance(n.value, int):
            raise invalid(f"expected an integer, got {shown(n.value)}")
        if (lo is not None and n.value < lo) or (hi is not None and n.value > hi):
            raise invalid(
                f"{shown(n.value)} is outside {lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
            )
        return int(n.value)

    return parse


def number(
    lo: float | None = None, hi: float | None = None, positive: bool = False
) -> Callable[[Node], float]:
    def parse(n: Node) -> float:
        if isinstance(n.value, bool) or not isinstance(n.value, int | float):
            raise invalid(f"expected a number, got {shown(n.value)}")
        try:
            v = float(n.value)
        except OverflowError:
            raise invalid(f"{shown(n.value)} is out of range") from None
        if not math.isfinite(v):
            raise invalid(f"expected a finite number, got {v}")
        if positive and v <= 0:
            raise invalid(f"must be greater than 0, got {v:g}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise invalid(
                f"{v:g} is outside {lo:g}..{hi:g}"
                if lo is not None and hi is not None
                else f"{v:g} is out of range"
            )
        return v

    return parse


def text(n: Node) -> str:
    if not isinstance(n.value, str | int | float) or isinstance(n.value, bool):
        raise invalid(f"expected a string, got {shown(n.value)}")
    return str(n.value)


def name(n: Node) -> str:
    """A ROS name component: ASCII letters, digits, underscores, not starting with a digit (rcl
    refuses any other character: a node named with it could not start)."""
    s = text(n)
    if (
        not s
        or not s.isascii()
        or not (s[0].isalpha() or s[0] == "_")
        or not all(c.isalnum() or c == "_" for c in s)
    ):
        raise invalid(
            f"{shown(s)} is not a valid ROS name (ASCII letters, digits and _, not "
            "starting with a digit)"
        )
    return s


def choice(options: Mapping[str, T]) -> Callable[[Node], T]:
    def parse(n: Node) -> T:
        if not isinstance(n.value, str | int | float) or isinstance(n.value, bool):
            raise invalid(f"expected one of {', '.join(options)}, got {shown(n.value)}")
        key = str(n.value).strip().lower()
        if key not in options:
            close = difflib.get_close_matches(key[:100], list(options), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise invalid(f"{shown(n.value)} is not one of {', '.join(options)}{hint}")
        return options[key]

    return parse


def via(fn: Callable[[Any], T]) -> Callable[[Node], T]:
    """Wrap a function that raises ValueError into a parser."""

    def parse(n: Node) -> T:
        try:
            return fn(n.value)
        except (ValueError, KeyError, TypeError) as exc:
            text = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
            raise invalid(text) from None

    return parse


def file_under(base: Path, must_exist: bool = False) -> Callable[[Node], Path]:
    """A path relative to ``base`` (the cell file's folder), ``~`` expanded; with ``must_exist``,
    of a file that is there."""

    def parse(n: Node) -> Path:
        p = Path(text(n)).expanduser()
        p = p if p.is_absolute() else base / p
        if must_exist and not p.is_file():
            raise invalid(f"no such file: {p}")
        return p

    return parse


def units_of(root: Node, cell_units: Sequence[str]) -> tuple[str, ...]:
    """A face's ``units`` list (default: every unit of the cell), each one of ``cell_units``."""
    units = tuple(n.parse(name, "") for n in root.list_at("units")) or tuple(cell_units)
    for i, u in enumerate(units):
        if u and u not in cell_units:
            root.child("units", None).child(i, u).error(
                f"unknown unit {u!r}; the cell has {', '.join(cell_units)}"
            )
    return units
