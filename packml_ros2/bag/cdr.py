"""Comparing serialized messages without decoding them: CDR (XCDR1, as rmw_fastrtps and the
``mcap`` writers produce) aligns each field to its size and leaves the padding bytes unset, so two
serializations of equal messages usually differ only there. :func:`same_bytes` compares two
serializations with the padding of the first one's layout ignored.

Why that is a value comparison: the layout walker reads only data bytes (string and sequence
lengths); if both buffers agree on every data byte of the first buffer's layout, the second
buffer has the same lengths at the same places, hence the same layout, hence equal values.
Buffers that do not compare equal this way are decoded and compared field by field (the caller's
slow path), which also settles the rare equal values with different bytes (0.0 and -0.0).
"""

from __future__ import annotations

import array
import importlib
import re
import struct
from collections.abc import Callable
from typing import Any, NamedTuple

Walker = Callable[..., int]
SIZES = {"boolean": 1, "byte": 1, "char": 1, "octet": 1, "int8": 1, "uint8": 1, "int16": 2,
         "uint16": 2, "int32": 4, "uint32": 4, "float": 4, "int64": 8, "uint64": 8,
         "double": 8}  # fmt: skip
_SEQ = re.compile(r"^sequence<(.+?)(?:, *\d+)?>$")
_ARRAY = re.compile(r"^(.+)\[(\d+)\]$")
_U32 = {True: struct.Struct("<I").unpack_from, False: struct.Struct(">I").unpack_from}
_walkers: dict[Any, Walker] = {}


def raw_stamp(raw: bytes) -> float:
    """The leading ``builtin_interfaces/Time stamp`` of a serialized message (every output of a
    unit begins with one), in seconds; ``nan`` when the buffer is too short."""
    if len(raw) < 12:
        return float("nan")
    little = raw[1] & 1
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", raw, 4)
    return float(sec + nanosec * 1e-9)


class _Gen:
    """Generates the walker of one message class as Python source (straight-line code)."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.env: dict[str, Any] = {}
        self.n = 0

    def var(self) -> str:
        self.n += 1
        return f"v{self.n}"

    def emit(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)

    def align(self, indent: int, size: int) -> None:
        if size > 1:
            self.emit(indent, f"if p & {size - 1}:")
            self.emit(indent + 1, f"q = (p + {size - 1}) & {-size}")
            self.emit(indent + 1, "gaps.append((p, q))")
            self.emit(indent + 1, "p = q")

    def field(self, indent: int, t: str) -> None:
        if t in SIZES:
            self.align(indent, SIZES[t])
            self.emit(indent, f"p += {SIZES[t]}")
        elif t == "string" or t.startswith("string<="):
            self.align(indent, 4)
            self.emit(indent, "probes.append(p)")
            self.emit(indent, "p += 4 + u(b, p)[0]")
        elif m := _SEQ.match(t):
            self.align(indent, 4)
            count = self.var()
            self.emit(indent, "probes.append(p)")
            self.emit(indent, f"{count} = u(b, p)[0]")
            self.emit(indent, "p += 4")
            self.repeat(indent, m.group(1), count)
        elif m := _ARRAY.match(t):
            self.repeat(indent, m.group(1), m.group(2))
        elif "/" in t:
            name = nested(t)
            self.env[name] = walker_of(message_class(t))
            self.emit(indent, f"p = {name}(b, p, gaps, u, probes)")
        else:
            raise ValueError(f"unsupported field type {t!r}")

    def repeat(self, indent: int, t: str, count: str) -> None:
        if t in SIZES:
            size = SIZES[t]
            self.emit(indent, f"if {count}:")
            self.align(indent + 1, size)
            self.emit(indent + 1, f"p += {size} * {count}")
        else:
            self.emit(indent, f"for _ in range({count}):")
            self.field(indent + 1, t)


def nested(t: str) -> str:
    return "w_" + re.sub(r"\W", "_", t)


def message_class(t: str) -> Any:
    pkg, _, name = t.replace("/msg/", "/").partition("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def walker_of(cls: Any) -> Walker:
    """The layout walker of ``cls``: ``walk(buf, pos, gaps, u32, probes) -> end``; appends the
    padding ranges to ``gaps`` and the positions of the length fields it read to ``probes``
    (positions relative to the CDR origin, i.e. after the 4-byte encapsulation header)."""
    known = _walkers.get(cls)
    if known is not None:
        return known
    gen = _Gen()
    gen.emit(0, "def walk(b, p, gaps, u, probes):")
    gen.emit(1, "b = b")  # keeps the function valid for messages without fields
    for t in cls.get_fields_and_field_types().values():
        gen.field(1, t)
    gen.emit(1, "return p")
    source = "\n".join(gen.lines)
    env = dict(gen.env)
    exec(compile(source, f"<cdr walker {cls.__name__}>", "exec"), env)
    w: Walker = env["walk"]
    _walkers[cls] = w
    return w


class Layout(NamedTuple):
    """Where a serialization's data bytes are, for buffers with the same length fields."""

    end: int  # absolute end of the data (before trailing padding)
    probes: struct.Struct  # reads every length field at once ...
    lengths: tuple[int, ...]  # ... which must be these for the layout to apply
    data: struct.Struct  # reads every data byte (as segments), skipping the padding


#: (type, length, byte order) -> the layouts seen, newest first (a topic alternates between a
#: few with the same length: a status of another state name of the same length, ...)
_layouts: dict[tuple[Any, int, int], list[Layout]] = {}
LAYOUTS_PER_LENGTH = 8


def layout(a: bytes, cls: Any) -> Layout | None:
    """The layout of serialization ``a`` of ``cls`` (cached per type, length and byte order: the
    next message of a topic usually has one seen before, checked with a single ``unpack``)."""
    key = (cls, len(a), a[1])
    cached = _layouts.get(key)
    if cached is not None:
        for known in cached:
            if known.probes.unpack_from(a) == known.lengths:
                return known
    little = a[1] == 1
    gaps: list[tuple[int, int]] = []
    probes: list[int] = []
    try:
        end = walker_of(cls)(memoryview(a)[4:], 0, gaps, _U32[little], probes) + 4
    except (struct.error, IndexError, ValueError):
        return None
    if end > len(a) or len(a) - end > 7:
        return None
    order = "<" if little else ">"
    fmt, at = [order], 0
    for p in probes:
        fmt.append(f"{p + 4 - at}xI")
        at = p + 8
    probe = struct.Struct("".join(fmt))
    fmt, at = [order, "2s2x"], 4  # encapsulation kind; options (bytes 2-3) are padding info
    for s, e in gaps:
        if s + 4 > at:
            fmt.append(f"{s + 4 - at}s")
        fmt.append(f"{e - s}x")
        at = e + 4
    if end > at:
        fmt.append(f"{end - at}s")
    found = Layout(end, probe, probe.unpack_from(a), struct.Struct("".join(fmt)))
    if len(_layouts) > 256:
        _layouts.clear()
    known_layouts = _layouts.setdefault(key, [])
    known_layouts.insert(0, found)
    del known_layouts[LAYOUTS_PER_LENGTH:]
    return found


def same_bytes(a: bytes, b: bytes, cls: Any) -> bool:
    """Whether serializations ``a`` and ``b`` of ``cls`` hold the same values, padding ignored.
    False means "not shown equal" (decode to be sure)."""
    if a == b:
        return True
    if abs(len(a) - len(b)) > 7 or len(a) < 4 or a[0] != 0 or a[1] not in (0, 1) or b[:2] != a[:2]:
        return False  # other encapsulations (XCDR2, parameter lists): decode
    lay = layout(a, cls)
    # after the last field: padding to a multiple of 4 (DDS payloads; the count is in the
    # encapsulation options, bytes 2-3), or nothing (rclpy.serialization)
    if lay is None or lay.end > len(b) or len(b) - lay.end > 7:
        return False
    return bool(lay.data.unpack_from(a) == lay.data.unpack_from(b))


def canonical(raw: bytes, cls: Any) -> bytes:
    """``raw`` (a serialization of ``cls``) with its padding bytes zeroed: equal values give
    equal bytes (for digests)."""
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1):
        return raw
    gaps: list[tuple[int, int]] = []
    end = walker_of(cls)(memoryview(raw)[4:], 0, gaps, _U32[raw[1] == 1], [])
    out = bytearray(raw)
    out[2:4] = b"\0\0"
    out[end + 4 :] = bytes(len(raw) - end - 4)
    for s, e in gaps:
        out[s + 4 : e + 4] = bytes(e - s)
    return bytes(out)


# -- serializing without rclpy ---------------------------------------------------------------------
# rclpy.serialization costs about 8 us per nested message (an Admin with 50 alarms in its history:
# 0.3-0.4 ms). For comparisons, messages are serialized here instead, little-endian with zeroed
# padding: straight-line code per type, and nested messages that publishers share between
# messages (convert.MessageCache: alarms, counts) are serialized once per object and position.
# Only for comparing: a difference goes on to the decoded comparison anyway.
_PACK = {"boolean": None, "byte": None, "char": None, "octet": None, "uint8": None,
         "int8": "<b", "int16": "<h", "uint16": "<H", "int32": "<i", "uint32": "<I", "float": "<f",
         "int64": "<q", "uint64": "<Q", "double": "<d"}  # fmt: skip
_ARRAY_CODE = {"int8": "b", "int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float": "f",
               "int64": "q", "uint64": "Q", "double": "d", "boolean": "B", "uint8": "B",
               "octet": "B", "byte": "B", "char": "B"}  # fmt: skip
_ZEROS = [bytes(n) for n in range(8)]
_serializers: dict[Any, Callable[..., None]] = {}
#: (id(message), origin offset mod 8) -> (message, bytes): the message is kept so its id stays its own
_blobs: dict[tuple[int, int], tuple[Any, bytes]] = {}
SHARED = {"packml_interfaces/Alarm", "packml_interfaces/Count"}


class _Ser(_Gen):
    def align(self, indent: int, size: int) -> None:
        if size > 1:
            self.emit(indent, f"n = -(len(o) - 4) & {size - 1}")
            self.emit(indent, "if n:")
            self.emit(indent + 1, "o += Z[n]")

    def value(self, indent: int, t: str, v: str) -> None:
        if t in SIZES:
            self.align(indent, SIZES[t])
            fmt = _PACK[t]
            if fmt is None:
                self.emit(
                    indent, f"o.append(int.from_bytes({v}) if isinstance({v}, bytes) else int({v}))"
                )
            else:
                name = "P_" + t
                self.env[name] = struct.Struct(fmt).pack
                self.emit(indent, f"o += {name}({v})")
        elif t == "string" or t.startswith("string<="):
            self.align(indent, 4)
            self.emit(indent, f"e = {v}.encode()")
            self.emit(indent, "o += U(len(e) + 1)")
            self.emit(indent, "o += e")
            self.emit(indent, "o.append(0)")
        elif (m := _SEQ.match(t)) and m.group(1).replace("/msg/", "/") in SHARED:
            # publishers share whole lists of shared messages too (MessageCache: the alarm
            # history, the counts): the list, length included, is serialized once per position
            self.align(indent, 4)
            name = nested(t)
            self.env[name] = _sequence_serializer(m.group(1))
            self.shared(indent, v, name)
        elif m := _SEQ.match(t):
            self.align(indent, 4)
            self.emit(indent, f"o += U(len({v}))")
            self.items(indent, m.group(1), v)
        elif m := _ARRAY.match(t):
            self.items(indent, m.group(1), v)
        elif "/" in t:
            name = nested(t)
            self.env[name] = serializer_of(message_class(t))
            if t.replace("/msg/", "/") in SHARED:
                self.shared(indent, v, name)
            else:
                self.emit(indent, f"{name}({v}, o)")
        else:
            raise ValueError(f"unsupported field type {t!r}")

    def shared(self, indent: int, v: str, name: str) -> None:
        """``v`` serialized by ``name``, or its bytes from the last time at this alignment."""
        self.emit(indent, f"h = B.get((id({v}), (len(o) - 4) & 7))")
        self.emit(indent, f"if h is not None and h[0] is {v}:")
        self.emit(indent + 1, "o += h[1]")
        self.emit(indent, "else:")
        self.emit(indent + 1, f"blob(o, {v}, {name})")

    def items(self, indent: int, t: str, v: str) -> None:
        if t in SIZES:
            code = _ARRAY_CODE[t]
            self.emit(indent, f"if len({v}):")
            self.align(indent + 1, SIZES[t])
            self.emit(indent + 1, f"o += raw({v}, {code!r})")
        else:
            x = self.var()
            self.emit(indent, f"for {x} in {v}:")
            self.value(indent + 1, t, x)


def _raw(values: Any, code: str) -> bytes:
    """Little-endian bytes of an array field (array.array, numpy array or list)."""
    if isinstance(values, array.array) and values.typecode == code:
        return values.tobytes()
    if hasattr(values, "astype"):  # numpy
        return bytes(values.astype(f"<{code}").tobytes())
    return array.array(code, values).tobytes()


def _blob(out: bytearray, msg: Any, ser: Callable[..., None]) -> None:
    """A shared nested message: its bytes at this alignment, made once."""
    key = (id(msg), (len(out) - 4) & 7)
    hit = _blobs.get(key)
    if hit is None or hit[0] is not msg:
        start = len(out)
        ser(msg, out)
        if len(_blobs) > 8192:
            _blobs.clear()  # (the generated code holds this very dict: clear, never replace)
        _blobs[key] = (msg, bytes(out[start:]))
        return
    out += hit[1]


def _compiled(gen: _Ser, what: str) -> Callable[..., None]:
    env = dict(gen.env)
    env.update(U=struct.Struct("<I").pack, Z=_ZEROS, raw=_raw, blob=_blob, B=_blobs)
    exec(compile("\n".join(gen.lines), f"<cdr serializer {what}>", "exec"), env)
    made: Callable[..., None] = env["ser"]
    return made


def serializer_of(cls: Any) -> Callable[..., None]:
    """``ser(msg, out)`` appends ``msg`` (of ``cls``) to the CDR buffer ``out``."""
    f = _serializers.get(cls)
    if f is not None:
        return f
    gen = _Ser()
    gen.emit(0, "def ser(m, o):")
    gen.emit(1, "n = 0")
    for name, t in cls.get_fields_and_field_types().items():
        gen.value(1, t, f"m.{name}")
    made = _serializers[cls] = _compiled(gen, cls.__name__)
    return made


def _sequence_serializer(element: str) -> Callable[..., None]:
    """``ser(items, out)`` appends a ``sequence<element>`` (length, then the items) at an offset
    already aligned to 4."""
    key = f"sequence<{element}>"
    f = _serializers.get(key)
    if f is None:
        gen = _Ser()
        gen.emit(0, "def ser(m, o):")
        gen.emit(1, "n = 0")
        gen.emit(1, "o += U(len(m))")
        gen.items(1, element, "m")
        f = _serializers[key] = _compiled(gen, key)
    return f


def serialize(msg: Any) -> bytes:
    """``msg`` as little-endian CDR with zeroed padding (what rclpy.serialization would give, up
    to the padding bytes)."""
    out = bytearray(b"\x00\x01\x00\x00")
    serializer_of(type(msg))(msg, out)
    return bytes(out)


# -- reading the input log without rclpy -----------------------------------------------------------
_TIME_INDEX = struct.Struct("<iIQ")  # after the header: stamp, then the uint64 index (aligned)
_U32_LE = struct.Struct("<I").unpack_from


def read_unit_input(raw: bytes) -> tuple[int, int, int, str, str, str] | None:
    """A little-endian CDR ``packml_interfaces/msg/UnitInput`` as (sec, nanosec, index, unit,
    name, args_json), about 20x faster than rclpy's deserialization (the input log of a long
    recording holds tens of thousands); None for any other encoding (decode it with rclpy)."""
    if raw[:2] != b"\x00\x01":
        return None
    try:
        sec, nanosec, index = _TIME_INDEX.unpack_from(raw, 4)
        p = 20  # origin 4 + Time (8) + uint64 (8)
        texts = []
        for _ in range(3):
            p += -(p - 4) & 3
            n = _U32_LE(raw, p)[0]
            if n == 0 or p + 4 + n > len(raw):
                return None
            texts.append(raw[p + 4 : p + 3 + n].decode())  # without the terminating NUL
            p += 4 + n
    except (struct.error, UnicodeDecodeError):
        return None
    return sec, nanosec, index, texts[0], texts[1], texts[2]
