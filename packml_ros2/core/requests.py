"""The requests of one evaluation step (:meth:`~.unit.Unit.step`): a state command, a mode
request, an EM's State Complete; and the order the rule book applies them in. Their own module
so that what records them (:mod:`.inputlog`) and what applies them (:mod:`.machine`) both import
them from below, and the engine's modules import in one direction.
"""

from __future__ import annotations

from dataclasses import dataclass

from .rules import MODE_REQUESTS, OPERATOR, STATE_COMPLETE_REPORTS, command_priority


@dataclass(frozen=True, slots=True)
class CommandRequest:
    cmd: int
    source: str = OPERATOR


@dataclass(frozen=True, slots=True)
class ModeRequest:
    mode: int | str
    source: str = OPERATOR


@dataclass(frozen=True, slots=True)
class CompleteReport:
    em: str
    state: int
    sequence: int


Request = CommandRequest | ModeRequest | CompleteReport


def priority(r: Request) -> int:
    """Where ``r`` goes in its step (lower first): Abort > Stop > Hold > Suspend > other commands
    > mode changes > State Complete (the rule book's priorities)."""
    if isinstance(r, CommandRequest):
        return command_priority(r.cmd)
    if isinstance(r, ModeRequest):
        return MODE_REQUESTS
    return STATE_COMPLETE_REPORTS


__all__ = ["CommandRequest", "CompleteReport", "ModeRequest", "Request", "priority"]
