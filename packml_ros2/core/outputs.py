"""What a unit outputs (:meth:`~.machine.UnitMachine.drain`): the :class:`Transition` record and
:class:`Outputs`, the queue the outputs are drained in.

Every transition makes a record, so the engine queues it as the cheapest objects CPython makes:
plain tuples, ``(time, sequence, tail)`` (:data:`RawTransition`), where ``tail`` holds the other
nine :class:`Transition` fields in their order and is compiled once for the transitions a
command's run makes (:data:`~.rules.Run`: a typed record costs twice as much to make and to free,
bench/engine_instructions.py). It becomes its :class:`Transition` when the outputs are iterated
or indexed. A publisher that reads the fields by position takes the outputs as queued
(:meth:`Outputs.raw`: the unit node does) and never pays for the typed record.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, NamedTuple, SupportsIndex, overload

from .numbers import State
from .rules import RecordTail, Trigger

#: The kind of a transition in the queue (the other kinds: "status", "alarms", "admin", "log").
TRANSITION = "transition"
_new_tuple = tuple.__new__


class Transition(NamedTuple):
    """One state or mode transition (``TransitionEvent``)."""

    time: float
    sequence: int
    from_state: State
    to_state: State
    from_mode: int
    to_mode: int
    trigger: Trigger
    command: int = 0
    source: str = ""
    skipped: tuple[State, ...] = ()
    detail: str = ""


#: A transition as queued: (time, sequence, the other fields in their order).
RawTransition = tuple[float, int, RecordTail]


def _typed(item: tuple[str, Any]) -> tuple[str, Any]:
    kind, value = item
    if kind == TRANSITION and type(value) is tuple:
        time, sequence, tail = value
        return (TRANSITION, _new_tuple(Transition, (time, sequence, *tail)))
    return item


class Outputs(list[tuple[str, Any]]):
    """The output queue: ``(kind, value)`` pairs in order, a transition's value queued as the plain
    tuple of its fields and read as its :class:`Transition`."""

    __slots__ = ()

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        return map(_typed, super().__iter__())

    def raw(self) -> Iterator[tuple[str, Any]]:
        """The outputs as queued: a transition as its :data:`RawTransition` (the fastest read)."""
        return super().__iter__()

    @overload
    def __getitem__(self, i: SupportsIndex) -> tuple[str, Any]: ...
    @overload
    def __getitem__(self, i: slice) -> list[tuple[str, Any]]: ...
    def __getitem__(self, i: SupportsIndex | slice) -> Any:
        if isinstance(i, slice):
            return [_typed(item) for item in super().__getitem__(i)]
        return _typed(super().__getitem__(i))


__all__ = ["TRANSITION", "Outputs", "RawTransition", "Transition"]
