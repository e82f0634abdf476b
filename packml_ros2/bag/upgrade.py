"""Recordings made with an older ``packml_interfaces``: a message whose recorded definition
differs from the installed one is read by its own definition (stored in the bag) and carried
into the installed type, the fields added since at their defaults; replay then compares only
the fields the recording has (:func:`Upgrade.mask`). A definition that changed otherwise (a
field removed, or its type changed) is not upgraded: the bag is refused as before.

Messages only gain fields at their end in this package (docs/ros-api.md, "compatibility"), so a
recording of any earlier version replays.
"""

from __future__ import annotations

import array
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.serialization import serialize_message

from .topics import msg_class

#: rclpy's Python types per primitive (what a recorded value must be to be set as it is).
_SCALARS = (bool, int, float, str, bytes)


@dataclass(frozen=True)
class Upgrade:
    """How one recorded type becomes the installed one."""

    msgtype: str
    convert: Callable[[bytes], bytes]  #: recorded CDR -> installed CDR
    absent: frozenset[str]  #: dotted paths of installed fields the recording lacks

    def mask(self, msg: Any) -> Any:
        """``msg`` (installed type) with the fields the recording lacks at their defaults."""
        return _masked(msg, self.absent, "")


def _masked(msg: Any, absent: frozenset[str], prefix: str) -> Any:
    out = type(msg)()
    for name in msg.get_fields_and_field_types():
        path = f"{prefix}{name}"
        if path in absent:
            continue
        value = getattr(msg, name)
        if any(a.startswith(path + ".") for a in absent):
            if isinstance(value, (list, tuple)):
                value = [_masked(v, absent, path + ".") for v in value]
            else:
                value = _masked(value, absent, path + ".")
        setattr(out, name, value)
    return out


def _fields(store: Any, msgtype: str) -> dict[str, Any]:
    return dict(store.fielddefs[msgtype][1])


def _absent(store: Any, msgtype: str, cls: Any, prefix: str, out: set[str]) -> None:
    """Installed fields of ``cls`` the recorded ``msgtype`` lacks; raises TypeError on a field
    removed or retyped (no upgrade then)."""
    recorded = _fields(store, msgtype)
    installed = cls.get_fields_and_field_types()
    for name in recorded:
        if name not in installed:
            raise TypeError(f"{msgtype}.{name} is no longer a field")
    for name in installed:
        if name not in recorded:
            out.add(f"{prefix}{name}")
            continue
        nested = _nested(recorded[name])
        if nested is None:
            continue
        sub = msg_class(nested)
        _absent(store, nested, sub, f"{prefix}{name}.", out)


def _nested(fielddef: Any) -> str | None:
    """The message type name of a (sequence or array of a) message field, else None."""
    kind, detail = fielddef
    if getattr(kind, "name", "") == "NAME":
        return str(detail)
    if getattr(kind, "name", "") in ("ARRAY", "SEQUENCE"):
        inner = detail[0]
        if getattr(inner[0], "name", "") == "NAME":
            return str(inner[1])
    return None


def _copy(value: Any, cls: Any) -> Any:
    """A rosbags-decoded message as an instance of rclpy class ``cls``."""
    out = cls()
    installed = cls.get_fields_and_field_types()
    for name in installed:
        if not hasattr(value, name):
            continue
        v = getattr(value, name)
        current = getattr(out, name)
        if hasattr(current, "get_fields_and_field_types"):
            setattr(out, name, _copy(v, type(current)))
        elif isinstance(v, (list, tuple)) and v and not isinstance(v[0], _SCALARS):
            item = msg_class(_item_type(cls, name))
            setattr(out, name, [_copy(x, item) for x in v])
        elif hasattr(v, "tolist") and not isinstance(v, array.array):
            setattr(out, name, v.tolist())  # (numpy arrays of primitives)
        else:
            setattr(out, name, v)
    return out


def _item_type(cls: Any, name: str) -> str:
    """``pkg/msg/Name`` of the elements of sequence field ``name`` of ``cls``."""
    text = cls.get_fields_and_field_types()[name]  # e.g. sequence<packml_interfaces/EmSummary>
    inner = text.split("<", 1)[1].split(",", 1)[0].rstrip(">")
    pkg, _, typ = inner.partition("/")
    return f"{pkg}/msg/{typ}"


@functools.cache
def _store(msgtype: str, fmt: str, data: str) -> Any:
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    if fmt == "MSG":
        store.register(get_types_from_msg(data, msgtype))
    else:
        sep = "=" * 80 + "\n"
        types: dict[str, Any] = {}
        parts = data.split(sep)[1:] if data.startswith(f"{sep}IDL: ") else [data]
        for part in parts:
            types.update(
                get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part)
            )
        store.register(types)
    return store


def definition_store(msgtype: str, fmt: str, data: str) -> Any:
    """A rosbags typestore of one stored definition (``fmt``: ``MSG`` or ``IDL``)."""
    return _store(msgtype, fmt, data)


def upgrade_for(store: Any, msgtype: str) -> Upgrade | None:
    """The upgrade of ``msgtype`` as ``store`` (the bag's definitions) has it, or None when it
    cannot be upgraded (a field removed or retyped)."""
    cls = msg_class(msgtype)
    absent: set[str] = set()
    try:
        _absent(store, msgtype, cls, "", absent)
    except (TypeError, KeyError, ValueError):
        return None

    def convert(raw: bytes) -> bytes:
        return bytes(serialize_message(_copy(store.deserialize_cdr(raw, msgtype), cls)))

    return Upgrade(msgtype, convert, frozenset(absent))


__all__ = ["Upgrade", "definition_store", "upgrade_for"]
