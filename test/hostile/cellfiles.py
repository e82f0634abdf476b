"""Mutated cell files: :func:`mutations` yields ``count`` variants of a valid cell file, each with
one fault an attacker or a slip of the keyboard makes, from ``seed`` (the same seed, the same
files). Text faults (cut, stray bytes, duplicated lines, tabs, alias bombs, deep nesting, unsafe
tags) and document faults (a hostile value at a random key, a removed or unknown key, a plain-text
secret, a reference to nothing)."""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import yaml

#: Values a hostile file puts where something else is expected.
HOSTILE_VALUES: tuple[Any, ...] = (
    math.nan, math.inf, -math.inf, -1, 0, 10**30, -(2**63), 2**64, 1.5e308, -0.0,
    "two", "", " ", "x" * 100_000, "\u202e\u200b", "\x1b[31mred", "{0}{unit}{cell.__class__}",
    "../../../../etc/passwd", "env:", "file:/dev/zero", "pbkdf2_sha256$", "*", "~",
    [], {}, None, True, False, [1, [2, [3, [4]]]], {"nested": {"deep": [None]}}, [math.nan],
)  # fmt: skip
HOSTILE_BYTES = (b"\xff", b"\x00", b"\t", b"\r", b"\x1b", b"\xe2\x80\xae", b"\xc3", b"\x7f", b":")
TAGS = (
    "!!python/object/apply:os.system ['echo owned']", "!!binary 'AAAA'", "!!timestamp 2001-13-45",
    "!!set {a, b}", "!!int 0x", "!!float nope", "!!omap [a, b]", "!custom x", "!!str",
)  # fmt: skip
BOMB = (
    "bomb_a: &ba [x, x, x, x, x, x, x, x, x, x]\n"
    + "".join(
        f"bomb_{c}: &b{c} [{', '.join([f'*b{p}'] * 10)}]\n"
        for p, c in zip("abcdefgh", "bcdefghi", strict=True)
    )
    + "bomb: *bi\n"
)


@dataclass(frozen=True)
class Mutation:
    """One mutated file: what was done (for the failure message) and its bytes."""

    name: str
    data: bytes


def _leaves(doc: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Paths of every value in the document (mappings, lists and scalars)."""
    out = [path] if path else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _leaves(v, (*path, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _leaves(v, (*path, i))
    return out


def _set(doc: Any, path: tuple[Any, ...], value: Any) -> None:
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def _delete(doc: Any, path: tuple[Any, ...]) -> None:
    for key in path[:-1]:
        doc = doc[key]
    del doc[path[-1]]


def _dump(doc: Any) -> bytes:
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True).encode("utf-8")


Doc = dict[str, Any]


def _value_at_random_key(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    path = rng.choice(_leaves(doc))
    value = rng.choice(HOSTILE_VALUES)
    _set(doc, path, value)
    shown = repr(value)[:40]
    return Mutation(f"{'.'.join(map(str, path))} = {shown}", _dump(doc))


def _removed_key(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    path = rng.choice([p for p in _leaves(doc) if not isinstance(p[-1], int)] or [("cell",)])
    _delete(doc, path)
    return Mutation(f"removed {'.'.join(map(str, path))}", _dump(doc))


def _unknown_key(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    mappings = [p for p in _leaves(doc) if isinstance(_get(doc, p), dict)] + [()]
    path = rng.choice(mappings)
    key = rng.choice(("tokn", "em_leese", "x" * 5000, "\u00e9\u00e8", "__class__", "1", "<<<"))
    target = _get(doc, path)
    target[key] = rng.choice(HOSTILE_VALUES)
    return Mutation(f"unknown key {key[:20]!r} at {'.'.join(map(str, path))}", _dump(doc))


def _get(doc: Any, path: tuple[Any, ...]) -> Any:
    for key in path:
        doc = doc[key]
    return doc


def _plain_secret(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    if rng.random() < 0.5:
        doc.setdefault("hmi", {})["token"] = "plain-text-token-123"
        return Mutation("hmi.token in plain text", _dump(doc))
    doc.setdefault("opcua", {}).setdefault("users", {})["op"] = "plain-text-password"
    return Mutation("opcua.users.op in plain text", _dump(doc))


def _dangling_reference(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    unit = rng.choice(list(doc["units"]))
    u = doc["units"][unit]
    choice = rng.randrange(3)
    if choice == 0:
        u.setdefault("alarms", []).append({"id": 4242, "message": "x", "em": "no_such_em"})
        return Mutation(f"alarm of {unit} names an unknown EM", _dump(doc))
    if choice == 1:
        doc.setdefault("coordinator", {})["start_order"] = [unit, "no_such_unit"]
        return Mutation("coordinator.start_order names an unknown unit", _dump(doc))
    u["initial_mode"] = "no_such_mode"
    return Mutation(f"{unit}.initial_mode names an unknown mode", _dump(doc))


def _cut(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    at = rng.randrange(1, len(text))
    return Mutation(f"cut at byte {at}", text[:at])


def _stray_byte(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    at = rng.randrange(len(text))
    byte = rng.choice(HOSTILE_BYTES)
    return Mutation(f"byte {byte!r} at {at}", text[:at] + byte + text[at:])


def _duplicated_line(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    lines = text.split(b"\n")
    i = rng.randrange(len(lines))
    return Mutation(f"line {i + 1} twice", b"\n".join([*lines[: i + 1], *lines[i:]]))


def _indent(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    lines = text.split(b"\n")
    i = rng.randrange(len(lines))
    lines[i] = rng.choice((b" ", b"\t", b"   ")) + lines[i]
    return Mutation(f"line {i + 1} indented", b"\n".join(lines))


def _bomb(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    return Mutation("alias bomb", BOMB.encode() + text)


def _deep(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    depth = rng.choice((200, 2000, 50_000))
    return Mutation(f"nested {depth} deep", text + f"\ndeep: {'[' * depth}{']' * depth}\n".encode())


def _tag(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    tag = rng.choice(TAGS)
    return Mutation(f"tag {tag}", text + f"\ntagged: {tag}\n".encode())


def _undefined_alias(rng: random.Random, doc: Doc, text: bytes) -> Mutation:
    return Mutation("undefined alias", text.replace(b"cell: ", b"cell: *nothing #", 1))


MUTATORS: tuple[Callable[[random.Random, Doc, bytes], Mutation], ...] = (
    _value_at_random_key, _value_at_random_key, _value_at_random_key, _removed_key, _unknown_key,
    _plain_secret, _dangling_reference, _cut, _stray_byte, _duplicated_line, _indent, _bomb,
    _deep, _tag, _undefined_alias,
)  # fmt: skip


def mutations(base: str, seed: int, count: int) -> Iterator[Mutation]:
    """``count`` mutated variants of the cell file text ``base``, from ``seed``."""
    rng = random.Random(seed)
    text = base.encode("utf-8")
    for _ in range(count):
        doc = yaml.safe_load(base)
        yield rng.choice(MUTATORS)(rng, doc, text)
