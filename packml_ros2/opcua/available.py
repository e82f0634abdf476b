"""Which states and transitions a unit has in a mode: the source of OPC 30050's
``AvailableStates`` / ``AvailableTransitions``.

:func:`unit_graph` reads them from the unit's compiled rule book
(:func:`packml_ros2.core.rules.rules_of`: the 2015 or 2022 model with the unit's ``hold_from`` /
``complete_from``, the mode's disabled states, commands passing through disabled acting states),
the same declaration the engine decides transitions with; nothing else in the OPC UA server reads
the rules.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from ..core.config import UnitConfig
from ..core.numbers import Cmd, State
from ..core.rules import rules_of

NUMBERS = frozenset(int(s) for s in State)


@dataclass(frozen=True)
class Graph:
    """A unit's state graph in one mode."""

    states: frozenset[State]  # the states the unit can be in (not disabled)
    #: (from, to) -> the commands that lead there (empty: State Complete). A command into a
    #: disabled acting state is an edge to where it ends (e.g. Stopped -> Idle when Resetting is
    #: disabled); a command or State Complete that would end in a disabled state is no edge.
    edges: Mapping[tuple[State, State], frozenset[Cmd]]


def unit_graph(config: UnitConfig, mode: int, state: int | None = None) -> Graph:
    """The states and transitions of the unit ``config`` in ``mode`` (an unknown mode: the
    model's graph, none disabled); with ``state``, only the transitions out of it (the rule
    book's AvailableTransitions of the current state)."""
    rules = rules_of(config)
    known = mode in config.modes
    states = (
        rules.available_states(mode)
        if known
        else frozenset(s for s in State if s is not State.UNDEFINED)
    )
    edges: dict[tuple[State, State], set[Cmd]] = {}
    now = None if state is None else State(state) if state in NUMBERS else State.UNDEFINED
    if known:
        chosen = rules.available_transitions(mode, now)
    else:
        chosen = tuple(e for e in rules.edges(None) if now is None or e.from_state is now)
    for edge in chosen:
        causes = edges.setdefault((edge.from_state, edge.to_state), set())
        if edge.trigger is not None:
            causes.add(edge.trigger)
    return Graph(frozenset(states) - {State.UNDEFINED}, {e: frozenset(c) for e, c in edges.items()})
