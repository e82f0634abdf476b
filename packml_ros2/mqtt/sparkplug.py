"""Sparkplug B payloads (Eclipse Sparkplug 3.0, the ``Payload`` protobuf message) encoded and decoded
by hand: the few fields an edge node uses, in protobuf's wire format, with no generated code.

Encoding covers ``Payload.timestamp/metrics/seq`` and ``Metric.name/alias/timestamp/datatype/
is_null`` and the scalar value fields. Decoding is for what a host application sends (NCMD,
DCMD): hostile input, so it is bounded (:data:`MAX_PAYLOAD`, :data:`MAX_METRICS`,
:data:`MAX_TEXT`), skips fields it does not use, and raises :class:`PayloadError` with a reason
code and one sentence for anything else; it never raises anything but that.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

MAX_PAYLOAD = 64 * 1024  #: bytes of one command payload
MAX_METRICS = 64  #: metrics in one command payload
MAX_TEXT = 4096  #: bytes of one string metric or metric name


class DataType(IntEnum):
    """Sparkplug B metric data types (the ones a PackML unit has)."""

    Int32 = 3
    Int64 = 4
    UInt32 = 7
    UInt64 = 8
    Float = 9
    Double = 10
    Boolean = 11
    String = 12
    DateTime = 13
    Text = 14


#: value field of each data type: (field number, wire type)
_VALUE_FIELD = {
    DataType.Int32: (10, 0),
    DataType.UInt32: (10, 0),
    DataType.Int64: (11, 0),
    DataType.UInt64: (11, 0),
    DataType.DateTime: (11, 0),
    DataType.Float: (12, 5),
    DataType.Double: (13, 1),
    DataType.Boolean: (14, 0),
    DataType.String: (15, 2),
    DataType.Text: (15, 2),
}
_TYPE_OF_FIELD = {10: 7, 11: 8, 12: 9, 13: 10, 14: 11, 15: 12}  #: value field -> a type
_INTS = {
    DataType.Int32: 32,
    DataType.UInt32: 32,
    DataType.Int64: 64,
    DataType.UInt64: 64,
    DataType.DateTime: 64,
}
_SIGNED = {DataType.Int32, DataType.Int64}


class PayloadError(ValueError):
    """A payload that cannot be taken: ``reason`` (a code) and the sentence."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


@dataclass(frozen=True)
class Metric:
    """One metric: by name (births, commands) or alias (data), its type and value."""

    name: str | None
    datatype: DataType
    value: Any
    alias: int | None = None
    timestamp: int | None = None


@dataclass(frozen=True)
class Payload:
    timestamp: int | None
    metrics: tuple[Metric, ...]
    seq: int | None = None


# -- encoding ---------------------------------------------------------------------------------------
def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _varint(number << 3 | wire)


def _len(number: int, data: bytes) -> bytes:
    return _key(number, 2) + _varint(len(data)) + data


def encode_metric(m: Metric) -> bytes:
    out = bytearray()
    if m.name is not None:
        out += _len(1, m.name.encode())
    if m.alias is not None:
        out += _key(2, 0) + _varint(m.alias)
    if m.timestamp is not None:
        out += _key(3, 0) + _varint(m.timestamp)
    out += _key(4, 0) + _varint(int(m.datatype))
    if m.value is None:
        return bytes(out + _key(7, 0) + b"\x01")
    number, _ = _VALUE_FIELD[m.datatype]
    if m.datatype in _INTS:
        bits = _INTS[m.datatype]
        out += _key(number, 0) + _varint(int(m.value) & ((1 << bits) - 1))  # two's complement
    elif m.datatype is DataType.Boolean:
        out += _key(number, 0) + (b"\x01" if m.value else b"\x00")
    elif m.datatype is DataType.Float:
        out += _key(number, 5) + struct.pack("<f", float(m.value))
    elif m.datatype is DataType.Double:
        out += _key(number, 1) + struct.pack("<d", float(m.value))
    else:
        out += _len(number, str(m.value).encode())
    return bytes(out)


def encode(payload: Payload) -> bytes:
    out = bytearray()
    if payload.timestamp is not None:
        out += _key(1, 0) + _varint(payload.timestamp)
    for m in payload.metrics:
        out += _len(2, encode_metric(m))
    if payload.seq is not None:
        out += _key(3, 0) + _varint(payload.seq)
    return bytes(out)


# -- decoding ---------------------------------------------------------------------------------------
def _fields(data: bytes, what: str) -> list[tuple[int, int, Any]]:
    """(number, wire type, value) of each field of one message; value: int for varint and
    fixed, bytes for length-delimited."""
    out: list[tuple[int, int, Any]] = []
    i, end = 0, len(data)

    def varint() -> int:
        nonlocal i
        shift = result = 0
        while True:
            if i >= end:
                raise PayloadError("malformed", f"{what}: truncated varint")
            byte = data[i]
            i += 1
            result |= (byte & 0x7F) << shift
            if not byte & 0x80:
                return result
            shift += 7
            if shift >= 70:
                raise PayloadError("malformed", f"{what}: varint longer than 10 bytes")

    while i < end:
        key = varint()
        number, wire = key >> 3, key & 7
        if number == 0:
            raise PayloadError("malformed", f"{what}: field number 0")
        if wire == 0:
            out.append((number, wire, varint()))
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            if i + size > end:
                raise PayloadError("malformed", f"{what}: truncated fixed-size field")
            out.append((number, wire, data[i : i + size]))
            i += size
        elif wire == 2:
            size = varint()
            if size > end - i:
                raise PayloadError("malformed", f"{what}: a field longer than the message")
            out.append((number, wire, data[i : i + size]))
            i += size
        else:
            raise PayloadError("malformed", f"{what}: wire type {wire} is not used by Sparkplug")
    return out


def _text(raw: Any, what: str) -> str:
    if not isinstance(raw, bytes):
        raise PayloadError("wrong_type", f"{what}: expected a string")
    if len(raw) > MAX_TEXT:
        raise PayloadError("too_long", f"{what}: {len(raw)} bytes (at most {MAX_TEXT})")
    try:
        return raw.decode()
    except UnicodeDecodeError:
        raise PayloadError("malformed", f"{what}: not UTF-8") from None


def _signed(value: int, bits: int) -> int:
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def decode_metric(data: bytes, index: int) -> Metric:
    what = f"metric {index}"
    name: str | None = None
    alias = timestamp = datatype = None
    is_null = False
    value: tuple[int, int, Any] | None = None
    for number, wire, raw in _fields(data, what):
        if number == 1:
            name = _text(raw, f"{what} name")
        elif number == 2 and wire == 0:
            alias = raw
        elif number == 3 and wire == 0:
            timestamp = raw
        elif number == 4 and wire == 0:
            datatype = raw
        elif number == 7 and wire == 0:
            is_null = bool(raw)
        elif 10 <= number <= 19:
            value = (number, wire, raw)
    if name is not None:
        what = f"metric {name!r}"
    if datatype is None:
        # a host application may leave the type out of a command: take it from the value field
        datatype = _TYPE_OF_FIELD.get(value[0] if value else 0, 0)
    try:
        dtype = DataType(int(datatype))
    except ValueError:
        raise PayloadError(
            "unsupported_type", f"{what}: data type {datatype} is not one a PackML unit takes"
        ) from None
    if is_null or value is None:
        return Metric(name, dtype, None, alias, timestamp)
    number, wire, raw = value
    expected_number, expected_wire = _VALUE_FIELD[dtype]
    if (number, wire) != (expected_number, expected_wire):
        raise PayloadError("wrong_type", f"{what}: a {dtype.name} with a value of another type")
    if dtype in _INTS:
        bits = _INTS[dtype]
        v: Any = _signed(raw, bits) if dtype in _SIGNED else raw & ((1 << bits) - 1)
    elif dtype is DataType.Boolean:
        v = bool(raw)
    elif dtype is DataType.Float:
        v = struct.unpack("<f", raw)[0]
    elif dtype is DataType.Double:
        v = struct.unpack("<d", raw)[0]
    else:
        v = _text(raw, what)
    if isinstance(v, float) and not math.isfinite(v):
        raise PayloadError("out_of_range", f"{what}: {v} is not a finite number")
    return Metric(name, dtype, v, alias, timestamp)


def decode(data: bytes) -> Payload:
    """A command payload; :class:`PayloadError` (only) for anything that is not one."""
    if not isinstance(data, bytes | bytearray):
        raise PayloadError("malformed", "not bytes")
    if len(data) > MAX_PAYLOAD:
        raise PayloadError("too_long", f"{len(data)} bytes (at most {MAX_PAYLOAD})")
    timestamp = seq = None
    metrics: list[Metric] = []
    for number, wire, raw in _fields(bytes(data), "payload"):
        if number == 1 and wire == 0:
            timestamp = raw
        elif number == 3 and wire == 0:
            seq = raw
        elif number == 2:
            if wire != 2:
                raise PayloadError("malformed", "payload: a metric that is not a message")
            if len(metrics) >= MAX_METRICS:
                raise PayloadError("too_many", f"more than {MAX_METRICS} metrics")
            metrics.append(decode_metric(raw, len(metrics)))
    return Payload(timestamp, tuple(metrics), seq)
