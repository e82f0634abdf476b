"""Reading a YAML configuration file as hostile input.

:func:`read_document` reads and parses a file, :func:`parse_document` a text; both raise
:class:`~.schema.ConfigError` with one line per problem, never a traceback:

- a file that cannot be read, is not a regular file (a FIFO would block), is larger than :data:`MAX_BYTES` or is not UTF-8 (with the line of
  the first bad byte);
- YAML syntax errors (with their line);
- a key written twice in one mapping (with both lines): YAML parsers silently keep the last one;
- documents nested deeper than :data:`MAX_DEPTH` or whose aliases expand to more than
  :data:`MAX_EXPANDED` nodes and characters (an "alias bomb": 300 bytes of anchors can stand for
  gigabytes), and aliases that contain themselves.

Anchors, aliases and merge keys (``<<: *defaults``) of ordinary size are fine.
"""

from __future__ import annotations

import os
from contextlib import suppress
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from .files import open_regular
from .schema import ConfigError, shown

MAX_BYTES = 4 * 1024 * 1024
MAX_DEPTH = 100
MAX_EXPANDED = 4_000_000
_MERGE = "tag:yaml.org,2002:merge"
#: libyaml's parser when PyYAML has it (ten times faster), else PyYAML's own; both safe loaders
_LOADER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class _Refused(Exception):
    def __init__(self, where: str, problem: str) -> None:
        super().__init__(problem)
        self.where, self.problem = where, problem


def read_text(path: str | os.PathLike[str]) -> str:
    """The text of a configuration file (ConfigError when unreadable, too big or not UTF-8)."""
    p = Path(path)
    try:
        with open_regular(p) as f:
            data = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise ConfigError(str(p), [("", f"cannot read: {exc.strerror or exc}")]) from None
    if len(data) > MAX_BYTES:
        raise ConfigError(
            str(p), [("", f"larger than {MAX_BYTES // (1024 * 1024)} MB: not a configuration file")]
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ConfigError(
            str(p),
            [
                (
                    f"line {line}",
                    f"not UTF-8 text (byte 0x{data[exc.start]:02x}): save the file as UTF-8",
                )
            ],
        ) from None


def read_document(path: str | os.PathLike[str]) -> Any:
    """The parsed YAML document of a file."""
    return parse_document(read_text(path), str(path))


def parse_document(text: str, file: str = "<memory>") -> Any:
    """The parsed YAML document of ``text`` (``file`` names it in errors)."""
    loader: Any = None
    try:
        _depth_first(text)  # before anything recursive sees the document
        loader = _LOADER(text)
        node = loader.get_single_node()
        if node is None:
            return None
        _check(node)
        return loader.construct_document(node)
    except _Refused as exc:
        raise ConfigError(file, [(exc.where, exc.problem)]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else ""
        if isinstance(exc, yaml.reader.ReaderError):  # a control character, a bad code point
            where = f"line {text.count(chr(10), 0, exc.position) + 1}"
            problem = f"character #x{exc.character:04x} is not allowed in YAML"
        else:
            problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(file, [(where, f"not valid YAML: {problem}")]) from None
    except RecursionError:
        raise ConfigError(file, [("", f"nested more than {MAX_DEPTH} levels deep")]) from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. "!!int x", "!!float 1e99999"
        raise ConfigError(
            file, [("", f"not valid YAML: a value cannot be read ({type(exc).__name__})")]
        ) from None
    finally:
        if loader is not None:
            loader.dispose()


def _depth_first(text: str) -> None:
    """Refuse a document nested deeper than MAX_DEPTH, from its events (the parser keeps its own
    stack; composing a deep document recurses: a RecursionError in Python, a crash in libyaml's
    binding).

    libyaml may stop a deep document first, in its own words (PyYAML 6.0.4: "exceeded maximum
    nesting depth"): at 1000 levels, deeper than MAX_DEPTH, but scanning ahead of the events it has
    given. So on any error, the text up to where it stopped is counted again: deeper than MAX_DEPTH
    there, the refusal is ours whatever the library says; else its error stands (a plain syntax
    error, with its line)."""
    try:
        _count_depth(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        if mark is not None and 0 < mark.index < len(text):
            with suppress(yaml.YAMLError):  # (the text cut there ends in an error of its own)
                _count_depth(text[: mark.index])
        raise


def _count_depth(text: str) -> None:
    probe = _LOADER(text)
    try:
        depth = 0
        while probe.check_event():
            event = probe.get_event()
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    line = event.start_mark.line + 1 if event.start_mark else 0
                    raise _Refused(f"line {line}", f"nested more than {MAX_DEPTH} levels deep")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
    finally:
        probe.dispose()


def _line(node: Node) -> int:
    return int(node.start_mark.line) + 1


def _check(root: Node) -> None:
    """Duplicate keys, depth, self-containing aliases and the expanded size, on the composed
    graph (an alias is the same node object: sizes are memoised, so the walk is linear)."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def walk(node: Node, path: str, depth: int) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise _Refused(path or f"line {_line(node)}", "an alias contains itself")
        if depth > MAX_DEPTH:
            raise _Refused(f"line {_line(node)}", f"nested more than {MAX_DEPTH} levels deep")
        active.add(key)
        size = 1
        if isinstance(node, ScalarNode):
            size += len(node.value)
        elif isinstance(node, SequenceNode):
            for i, item in enumerate(node.value):
                size += walk(item, f"{path}[{i}]", depth + 1)
        elif isinstance(node, MappingNode):
            _duplicates(node, path)
            for k, v in node.value:
                name = k.value if isinstance(k, ScalarNode) else f"<{k.id}>"
                where = f"{path}.{name}" if path else str(name)
                size += walk(k, where, depth + 1) + walk(v, where, depth + 1)
        active.discard(key)
        if size > MAX_EXPANDED:
            raise _Refused(
                path or f"line {_line(node)}",
                f"its aliases expand to more than {MAX_EXPANDED:,} nodes and characters: "
                "refused (an alias bomb?)",
            )
        sizes[key] = size
        return size

    walk(root, "", 0)


def _duplicates(node: MappingNode, path: str) -> None:
    seen: dict[tuple[str, str], int] = {}
    for k, _ in node.value:
        if not isinstance(k, ScalarNode) or k.tag == _MERGE:
            continue
        ident = (k.tag, k.value)
        if ident in seen:
            where = f"{path}.{k.value}" if path else str(k.value)
            raise _Refused(
                where,
                f"key {shown(k.value)} is written twice in one mapping (lines {seen[ident]} and "
                f"{_line(k)}): keep one",
            )
        seen[ident] = _line(k)
