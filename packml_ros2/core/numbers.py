"""PackML numbers (ISA-TR88.00.02-2022): states, commands and modes, with their names.

Every other module speaks in these numbers; names are for people (messages, logs, HMI).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from enum import IntEnum

from .limits import printable


class State(IntEnum):
    """``Status.StateCurrent`` values."""

    UNDEFINED = 0
    CLEARING = 1
    STOPPED = 2
    STARTING = 3
    IDLE = 4
    SUSPENDED = 5
    EXECUTE = 6
    STOPPING = 7
    ABORTING = 8
    ABORTED = 9
    HOLDING = 10
    HELD = 11
    UNHOLDING = 12
    SUSPENDING = 13
    UNSUSPENDING = 14
    RESETTING = 15
    COMPLETING = 16
    COMPLETE = 17


class Cmd(IntEnum):
    """``Command.CntrlCmd`` values."""

    UNDEFINED = 0
    RESET = 1
    START = 2
    STOP = 3
    HOLD = 4
    UNHOLD = 5
    SUSPEND = 6
    UNSUSPEND = 7
    ABORT = 8
    CLEAR = 9
    COMPLETE = 10


class Mode(IntEnum):
    """The standard ``UnitMode`` values; 4..31 are user-defined and named in the configuration."""

    INVALID = 0
    PRODUCTION = 1
    MAINTENANCE = 2
    MANUAL = 3


MAX_MODE = 31
NUM_MODES = 32
NUM_STATES = 18

#: Left only by State Complete or by a command.
ACTING: frozenset[State] = frozenset(
    {
        State.CLEARING,
        State.STARTING,
        State.EXECUTE,
        State.STOPPING,
        State.ABORTING,
        State.HOLDING,
        State.UNHOLDING,
        State.SUSPENDING,
        State.UNSUSPENDING,
        State.RESETTING,
        State.COMPLETING,
    }
)
#: Left only by a command.
WAIT: frozenset[State] = frozenset(
    {State.STOPPED, State.IDLE, State.SUSPENDED, State.HELD, State.COMPLETE, State.ABORTED}
)
#: Never disabled in any mode.
MANDATORY: frozenset[State] = frozenset({State.STOPPED, State.IDLE, State.EXECUTE, State.ABORTED})

#: Accepted spellings besides the enum names (TR88-2022 calls Complete "Completed").
_STATE_ALIASES = {
    "COMPLETED": State.COMPLETE,
    "SUSPEND": State.SUSPENDED,
    "UN_HOLDING": State.UNHOLDING,
}


def _norm(text: str) -> str:
    return text.strip().upper().replace("-", "_").replace(" ", "_")


_STATE_NAMES = {int(s): s.name for s in State}
_CMD_NAMES = {int(c): c.name for c in Cmd}


def state_name(state: int) -> str:
    """``'EXECUTE'`` for 6; ``'STATE_42'`` for a number outside the model."""
    name = _STATE_NAMES.get(state)
    return name if name is not None else f"STATE_{state}"


def command_name(cmd: int) -> str:
    """``'START'`` for 2; ``'COMMAND_42'`` for a number outside the model."""
    name = _CMD_NAMES.get(cmd)
    return name if name is not None else f"COMMAND_{cmd}"


def parse_state(text: str | int) -> State:
    """A state from its number or name (case-insensitive, ``Completed`` accepted)."""
    number = _number(text, "state", State)
    if number is not None:
        return State(number)
    key = _norm(str(text))
    if key in State.__members__:
        return State[key]
    if key in _STATE_ALIASES:
        return _STATE_ALIASES[key]
    raise ValueError(
        f"{_quoted(text)} is not a PackML state{_did_you_mean(key, State.__members__)}"
    )


def parse_command(text: str | int) -> Cmd:
    """A command from its number or name (case-insensitive)."""
    number = _number(text, "command", Cmd)
    if number is not None:
        return Cmd(number)
    key = _norm(str(text))
    if key in Cmd.__members__:
        return Cmd[key]
    raise ValueError(
        f"{_quoted(text)} is not a PackML command{_did_you_mean(key, Cmd.__members__)}"
    )


#: Characters of a caller's text a parse error quotes (and compares with the names).
MAX_QUOTED = 40


def _quoted(text: str | int) -> str:
    """A caller's text as an error quotes it: control characters escaped, cut to
    :data:`MAX_QUOTED` (an error message never grows with what was sent)."""
    return f"'{printable(str(text), MAX_QUOTED)}'"


def _number(text: str | int, what: str, numbers: Iterable[int]) -> int | None:
    """``text`` as a number when it is one (ASCII digits), checked against ``numbers``."""
    if isinstance(text, str):
        digits = text.strip()
        if not (digits.isascii() and digits.isdigit()):
            return None
        if len(digits) > 3:
            raise ValueError(f"{_quoted(text)} is not a PackML {what} number")
        text = int(digits)
    if text not in {int(n) for n in numbers}:
        raise ValueError(f"{_quoted(text)} is not a PackML {what} number")
    return text


def _did_you_mean(key: str, names: Iterable[str]) -> str:
    if len(key) > MAX_QUOTED:  # difflib is quadratic in the text's length
        return ""
    close = difflib.get_close_matches(key, list(names), n=1)
    return f" (did you mean {close[0]}?)" if close else ""


def names_of(commands: Iterable[int]) -> str:
    """``'RESET, ABORT'`` for a collection of command numbers."""
    return ", ".join(command_name(c) for c in commands)
