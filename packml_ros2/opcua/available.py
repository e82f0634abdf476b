"""Which states and transitions a unit has in a mode: the source of OPC 30050's
``AvailableStates`` / ``AvailableTransitions``.

:func:`unit_graph` is the one place that reads the engine's rules for them. It derives the graph
from the unit's compiled transition table (``UnitConfig.table``: the 2015 or 2022 model with the
unit's ``hold_from`` / ``complete_from``) and the mode's disabled states (``ModeDef.disabled``,
implications applied), walking a command through disabled acting states with the engine's own
:func:`packml_ros2.core.modes.resolve`, as :class:`packml_ros2.core.Unit` does when it compiles its
tables. When the engine exposes its rule book (``packml_ros2.core.rules``), this function becomes
a call to it; nothing else in the OPC UA server reads the rules.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ..core.config import UnitConfig
from ..core.modes import resolve
from ..core.numbers import Cmd, State


@dataclass(frozen=True)
class Graph:
    """A unit's state graph in one mode."""

    states: frozenset[State]  # the states the unit can be in (not disabled)
    #: (from, to) -> the commands that lead there (empty: State Complete). A command into a
    #: disabled acting state is an edge to where it ends (e.g. Stopped -> Idle when Resetting is
    #: disabled); a command or State Complete that would end in a disabled state is no edge.
    edges: Mapping[tuple[State, State], frozenset[Cmd]]


def unit_graph(config: UnitConfig, mode: int) -> Graph:
    """The states and transitions of the unit ``config`` in ``mode`` (an unknown mode: none
    disabled)."""
    mode_def = config.modes.get(mode)
    disabled = mode_def.disabled if mode_def is not None else frozenset()
    table = config.table
    states = frozenset(s for s in State if s is not State.UNDEFINED and s not in disabled)
    edges: dict[tuple[State, State], set[Cmd]] = {}
    steps: list[tuple[State, State, Cmd | None]] = [
        (frm, first, cmd) for (frm, cmd), first in table.commands.items()
    ]
    steps += [(frm, first, None) for frm, first in table.state_complete.items()]
    for frm, first, cmd in steps:
        if frm in disabled:
            continue
        final, _ = resolve(first, disabled, table.state_complete)
        if final in disabled:
            continue
        causes = edges.setdefault((frm, final), set())
        if cmd is not None:
            causes.add(cmd)
    return Graph(states, {edge: frozenset(c) for edge, c in edges.items()})
