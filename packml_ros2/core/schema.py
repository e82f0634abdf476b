"""A small declarative validator for YAML configuration: every error names the file, the key path
and what is wrong, and all errors of a file are reported together."""

from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T")


class ConfigError(ValueError):
    """Bad configuration. ``problems`` lists ``(key path, problem)``; str() is one line each."""

    def __init__(self, file: str, problems: list[tuple[str, str]]) -> None:
        self.file = file
        self.problems = problems
        lines = [f"{file}: {path or '<top>'}: {problem}" for path, problem in problems]
        super().__init__("\n".join(lines))


class _Invalid(Exception):
    """Raised by a parser for the value at hand; the node turns it into a problem with a path."""


def invalid(problem: str) -> _Invalid:
    return _Invalid(problem)


@dataclass
class Node:
    """A value in the document with its key path; parse children with :meth:`get`."""

    value: Any
    path: str
    problems: list[tuple[str, str]] = field(default_factory=list)

    def child(self, key: str | int, value: Any) -> Node:
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
            self.error(f"expected a mapping, got {type(self.value).__name__} {self.value!r}")
            return {}
        return self.value

    def check_keys(self, allowed: set[str] | Mapping[str, Any]) -> None:
        for key in self.mapping():
            if str(key) not in allowed:
                close = difflib.get_close_matches(str(key), list(allowed), n=1)
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
            self.error(f"expected a list, got {type(self.value).__name__} {self.value!r}")
            return []
        return [self.child(i, v) for i, v in enumerate(self.value)]


# -- leaf parsers ------------------------------------------------------------------------------------
def boolean(n: Node) -> bool:
    if not isinstance(n.value, bool):
        raise invalid(f"expected true or false, got {n.value!r}")
    return n.value


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[Node], int]:
    def parse(n: Node) -> int:
        if isinstance(n.value, bool) or not isinstance(n.value, int):
            raise invalid(f"expected an integer, got {n.value!r}")
        if (lo is not None and n.value < lo) or (hi is not None and n.value > hi):
            raise invalid(
                f"{n.value} is outside {lo if lo is not None else '-inf'}..{hi if hi is not None else 'inf'}"
            )
        return int(n.value)

    return parse


def number(
    lo: float | None = None, hi: float | None = None, positive: bool = False
) -> Callable[[Node], float]:
    def parse(n: Node) -> float:
        if isinstance(n.value, bool) or not isinstance(n.value, int | float):
            raise invalid(f"expected a number, got {n.value!r}")
        v = float(n.value)
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
        raise invalid(f"expected a string, got {n.value!r}")
    return str(n.value)


def name(n: Node) -> str:
    """A ROS name component: letters, digits, underscores, not starting with a digit."""
    s = text(n)
    if not s or not (s[0].isalpha() or s[0] == "_") or not all(c.isalnum() or c == "_" for c in s):
        raise invalid(
            f"{s!r} is not a valid ROS name (letters, digits and _, not starting with a digit)"
        )
    return s


def choice(options: Mapping[str, T]) -> Callable[[Node], T]:
    def parse(n: Node) -> T:
        key = str(n.value).strip().lower()
        if key not in options:
            close = difflib.get_close_matches(key, list(options), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise invalid(f"{n.value!r} is not one of {', '.join(options)}{hint}")
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
