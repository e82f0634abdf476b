"""Reading a few fields of a serialized message without decoding the rest.

A ROS message is decoded field by field into Python objects: the unit's ``status`` with 8 EM
entries takes an EM 47 us (an empty one 16 us), and an EM needs five numbers and its own entry of
it. :func:`field_reader` compiles, from the message's own type description, straight-line code
that walks the CDR bytes (XCDR1, as rmw_fastrtps sends them), reads the fields asked for, skips
the others and stops after the last one it needs.

    read = field_reader(Status, ["state_current", "sequence"], {"equipment_modules": ["name"]})
    state, sequence, entries = read(raw)   # entries: [(name,), ...]

A buffer it cannot read (another encoding, cut short, inconsistent lengths) raises
:class:`Unreadable`; callers decode it in full then (``rclpy.serialization``), which refuses it or
reads it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from .bag import cdr
from .bag.cdr import _SEQ, SIZES, message_class

Reader = Callable[[bytes], tuple[Any, ...]]

_FORMATS = {"boolean": "?", "byte": "B", "char": "B", "octet": "B", "uint8": "B", "int8": "b",
            "int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float": "f", "int64": "q",
            "uint64": "Q", "double": "d"}  # fmt: skip
#: the encapsulations read here: plain CDR, big- and little-endian (XCDR1)
_LITTLE = {b"\x00\x00": False, b"\x00\x01": True}


class Unreadable(ValueError):
    """The buffer is not a plain CDR serialization of the type (decode it in full instead)."""


class _Gen(cdr._Gen):
    """Straight-line reading code: the layout walker's generator (``field`` skips a field, its
    padding not noted) and ``read``."""

    def align(self, indent: int, size: int) -> None:
        if size > 1:
            self.emit(indent, f"p = (p + {size - 1}) & {-size}")

    # -- reading -----------------------------------------------------------------------------------
    def read(self, indent: int, t: str, into: str) -> None:
        """Read a primitive or a string field at ``p`` into variable ``into``."""
        if t in SIZES:
            size = SIZES[t]
            self.align(indent, size)
            self.emit(indent, f"{into} = R['{t}'](b, p)[0]")
            self.emit(indent, f"p += {size}")
        elif t == "string" or t.startswith("string<="):
            self.align(indent, 4)
            n = self.var()
            self.emit(indent, f"{n} = U(b, p)[0]")
            self.emit(indent, f"if {n} == 0 or p + 4 + {n} > len(b): raise X")
            self.emit(indent, f"{into} = bytes(b[p + 4 : p + 3 + {n}]).decode()")
            self.emit(indent, f"p += 4 + {n}")
        else:
            raise ValueError(f"only primitives and strings are read, not {t!r}")


def field_reader(
    cls: Any, fields: Iterable[str], entries: Mapping[str, Iterable[str]] | None = None
) -> Reader:
    """A reader of ``cls`` serializations: ``read(raw)`` returns the values of ``fields``
    (primitives and strings, in the order given) and, per sequence field of ``entries``, the list
    of its elements' chosen fields as tuples; the sequence fields come after ``fields`` in the
    order of ``entries``."""
    wanted = list(fields)
    per_entry = {name: list(subs) for name, subs in (entries or {}).items()}
    types = cls.get_fields_and_field_types()
    unknown = [f for f in [*wanted, *per_entry] if f not in types]
    if unknown:
        raise ValueError(f"{cls.__name__} has no field {unknown[0]!r}")
    last = max(list(types).index(f) for f in [*wanted, *per_entry])
    gen = _Gen()
    gen.emit(0, "def read(b):")
    gen.emit(1, "p, gaps, probes, u = 0, [], [], U")  # what the walker's code uses
    out: dict[str, str] = {}
    for i, (name, t) in enumerate(types.items()):
        if i > last:
            break
        if name in wanted:
            out[name] = gen.var()
            gen.read(1, t, out[name])
        elif name in per_entry:
            m = _SEQ.match(t)
            if m is None or "/" not in m.group(1):
                raise ValueError(f"{name} is not a sequence of messages")
            sub_types = message_class(m.group(1)).get_fields_and_field_types()
            subs = per_entry[name]
            count, items = gen.var(), gen.var()
            out[name] = items
            gen.align(1, 4)
            gen.emit(1, f"{count} = U(b, p)[0]")
            gen.emit(1, "p += 4")
            gen.emit(1, f"if {count} > len(b): raise X")
            gen.emit(1, f"{items} = []")
            gen.emit(1, f"for _ in range({count}):")
            values = {s: gen.var() for s in subs}
            for sub, st in sub_types.items():
                if sub in values:
                    gen.read(2, st, values[sub])
                else:
                    gen.field(2, st)
            gen.emit(2, f"{items}.append(({', '.join(values[s] for s in subs)},))")
        else:
            gen.field(1, t)
    gen.emit(1, "if p > len(b): raise X")
    gen.emit(1, f"return ({', '.join(out[f] for f in [*wanted, *per_entry])},)")
    source = "\n".join(gen.lines)
    readers: dict[bytes, Any] = {}  # per encapsulation header
    for header, little in _LITTLE.items():
        order = "<" if little else ">"
        env: dict[str, Any] = {
            **gen.env,  # the walkers of nested messages it skips
            "U": struct.Struct(order + "I").unpack_from,
            "R": {t: struct.Struct(order + f).unpack_from for t, f in _FORMATS.items()},
            "X": Unreadable,
        }
        exec(compile(source, f"<cdr reader {cls.__name__}>", "exec"), env)
        readers[header] = env["read"]

    def read(raw: bytes) -> tuple[Any, ...]:
        read_data = readers.get(bytes(raw[:2]))
        if read_data is None:
            raise Unreadable("not a plain CDR serialization")
        try:
            return read_data(memoryview(raw)[4:])  # type: ignore[no-any-return]
        except (struct.error, IndexError, UnicodeDecodeError, MemoryError) as exc:
            raise Unreadable(str(exc)) from None

    return read
