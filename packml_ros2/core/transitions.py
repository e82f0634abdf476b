"""The PackML transition table (TR88-2022 by default, TR88-2015 on request) as data.

``TABLE_2022`` is the spec's table verbatim; the Stop and Abort sets are listed as sets. A
:class:`TransitionTable` answers two questions: where does command C lead from state S, and where
does State Complete lead from S.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from .numbers import ACTING, Cmd, State

S, C = State, Cmd

#: (from, command) -> to, TR88-2022 (PACKML.md section 2), without the Stop and Abort sets.
COMMANDS_2022: Mapping[tuple[State, Cmd], State] = {
    (S.STOPPED, C.RESET): S.RESETTING,
    (S.IDLE, C.START): S.STARTING,
    (S.EXECUTE, C.HOLD): S.HOLDING,
    (S.EXECUTE, C.SUSPEND): S.SUSPENDING,
    (S.EXECUTE, C.COMPLETE): S.COMPLETING,
    (S.COMPLETE, C.RESET): S.RESETTING,
    (S.HELD, C.UNHOLD): S.UNHOLDING,
    (S.HELD, C.COMPLETE): S.COMPLETING,
    (S.SUSPENDED, C.UNSUSPEND): S.UNSUSPENDING,
    (S.SUSPENDED, C.HOLD): S.HOLDING,
    (S.SUSPENDED, C.COMPLETE): S.COMPLETING,
    (S.ABORTED, C.CLEAR): S.CLEARING,
}

#: from -> to on State Complete (acting states only).
STATE_COMPLETE: Mapping[State, State] = {
    S.RESETTING: S.IDLE,
    S.STARTING: S.EXECUTE,
    S.EXECUTE: S.COMPLETING,
    S.COMPLETING: S.COMPLETE,
    S.HOLDING: S.HELD,
    S.UNHOLDING: S.EXECUTE,
    S.SUSPENDING: S.SUSPENDED,
    S.UNSUSPENDING: S.EXECUTE,
    S.STOPPING: S.STOPPED,
    S.ABORTING: S.ABORTED,
    S.CLEARING: S.STOPPED,
}

ALL_STATES: frozenset[State] = frozenset(s for s in State if s is not S.UNDEFINED)
#: Stop -> Stopping from every state except these.
STOP_EXCEPT: frozenset[State] = frozenset(
    {S.STOPPING, S.STOPPED, S.ABORTING, S.ABORTED, S.CLEARING}
)
#: Abort -> Aborting from every state except these.
ABORT_EXCEPT: frozenset[State] = frozenset({S.ABORTING, S.ABORTED})

#: The states each configurable command is accepted in, per model (Siemens holdCmdCfg/completeCmdCfg).
HOLD_FROM = {"2022": frozenset({S.EXECUTE, S.SUSPENDED}), "2015": frozenset({S.EXECUTE})}
COMPLETE_FROM = {
    "2022": frozenset({S.EXECUTE, S.HELD, S.SUSPENDED}),
    "2015": frozenset({S.EXECUTE}),
}
MODELS = ("2022", "2015")


@dataclass(frozen=True)
class TransitionTable:
    """Where commands and State Complete lead. Immutable; build with :func:`build_table`."""

    model: str
    commands: Mapping[tuple[State, Cmd], State]
    state_complete: Mapping[State, State]

    def target(self, state: State, cmd: Cmd) -> State | None:
        """The state command ``cmd`` leads to from ``state``, or None when it is not valid there."""
        return self.commands.get((state, cmd))

    def valid_commands(self, state: State) -> tuple[Cmd, ...]:
        return tuple(c for c in Cmd if (state, c) in self.commands)


def build_table(
    model: str = "2022",
    hold_from: Iterable[State] | None = None,
    complete_from: Iterable[State] | None = None,
) -> TransitionTable:
    """The table of ``model`` with optional explicit Hold and Complete masks."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, not {model!r}")
    hold = frozenset(hold_from) if hold_from is not None else HOLD_FROM[model]
    complete = frozenset(complete_from) if complete_from is not None else COMPLETE_FROM[model]
    commands: dict[tuple[State, Cmd], State] = {
        key: to for key, to in COMMANDS_2022.items() if key[1] not in (C.HOLD, C.COMPLETE)
    }
    commands.update({(s, C.HOLD): S.HOLDING for s in hold})
    commands.update({(s, C.COMPLETE): S.COMPLETING for s in complete})
    commands.update({(s, C.STOP): S.STOPPING for s in ALL_STATES - STOP_EXCEPT})
    commands.update({(s, C.ABORT): S.ABORTING for s in ALL_STATES - ABORT_EXCEPT})
    assert set(STATE_COMPLETE) == ACTING
    return TransitionTable(model, commands, STATE_COMPLETE)
