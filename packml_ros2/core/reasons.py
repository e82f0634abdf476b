"""Reason codes of every answer, mirroring ``packml_interfaces/msg/Result`` (a test keeps them equal)."""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple


class Reason(IntEnum):
    ACCEPTED = 0
    UNKNOWN_COMMAND = 1
    COMMAND_NOT_ALLOWED = 2
    STATE_DISABLED = 3
    REMOTE_DISABLED = 4
    MODE_UNKNOWN = 5
    MODE_CHANGE_NOT_ALLOWED = 6
    MODE_CHANGE_IN_PROCESS = 7
    ALARM_ACTIVE = 8
    EM_UNKNOWN = 9
    EM_SWITCH_IN_PRODUCTION = 10
    EM_MISSING = 11
    ALARM_UNKNOWN = 12
    INVALID_ARGUMENT = 13
    SUPERSEDED = 14
    UNIT_UNAVAILABLE = 15
    UNAUTHORIZED = 16
    NOTHING_TO_DO = 17
    INTERLOCK_ACTIVE = 18
    NOT_SUPPORTED = 19
    RECIPE_UNKNOWN = 20
    RECIPE_NOT_ALLOWED = 21
    RECIPE_CHANGE_IN_PROCESS = 22


class Answer(NamedTuple):
    """What every request gets back: accepted or not, a reason code and a sentence for people."""

    accepted: bool
    reason: Reason
    message: str

    @classmethod
    def ok(cls, message: str) -> Answer:
        return cls(True, Reason.ACCEPTED, message)

    @classmethod
    def no(cls, reason: Reason, message: str) -> Answer:
        return cls(False, reason, message)
