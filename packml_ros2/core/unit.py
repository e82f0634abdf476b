"""The PackML unit engine: a :class:`Unit` takes inputs and drives the state machine the rule book
(:mod:`.rules`) declares.

A unit is pure Python: it takes its clock as a parameter and never looks at wall time itself.
Every input (a command, a mode request, an EM report, an alarm...) first advances the engine to the
clock's time, firing due deadlines (timeouts, dwell, periodic admin and saves) *at their own
times*; the results depend only on the inputs and their times, so replaying recorded inputs on the
recorded clock reproduces the outputs exactly.

A :class:`Unit` is composed of its inputs by concern, each in its own module:

- :mod:`.machine`: the state machine (commands, modes, State Complete, the step) and the
  evaluation every input goes through (deadlines, settling, publication, persistence);
- :mod:`.mode_change`: a mode change once accepted (awaited, finished, abandoned), and the
  mode's fields;
- :mod:`.outputs`: the transition record and the queue outputs are drained in;
- :mod:`.em_inputs`: what the equipment modules tell it (seen, lost, requests, interlocks, counts,
  switched active);
- :mod:`.alarm_inputs`: alarms raised, cleared, acknowledged and reset;
- :mod:`.tag_inputs`: Admin and Command tags (times, counters, speed, parameters, products);
- :mod:`.recipe_inputs`: recipe changes and the EMs' answers to a changeover (:mod:`.recipes`);
- :mod:`.deadline_handlers`: what falls due on its own (timeouts, dwell, coalesced and periodic
  status, admin and saves);
- :mod:`.unit_views`: the status and admin views built on request.

Outputs are queued and taken with :meth:`Unit.drain`: transitions, status and alarm-list changes,
admin snapshots due, and log lines. The ROS node (``packml_ros2.unit_node``) publishes them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from . import inputlog
from .alarm_inputs import AlarmInputs
from .deadline_handlers import DeadlineHandlers
from .em_inputs import EquipmentInputs
from .machine import Stats, StatusMark, Transition, Trigger
from .reasons import Answer
from .recipe_inputs import RecipeInputs
from .requests import CommandRequest, CompleteReport, ModeRequest, Request
from .tag_inputs import TagInputs
from .unit_views import UnitViews


class Unit(EquipmentInputs, AlarmInputs, TagInputs, RecipeInputs, DeadlineHandlers, UnitViews):
    """One PackML unit. ``Unit(config, clock)``; optionally a :class:`~.persistence.Store`.

    Inputs are methods (:meth:`command`, :meth:`set_mode`, :meth:`em_complete`, ...) answering
    with an :class:`~.reasons.Answer`; outputs are taken with :meth:`drain`; :meth:`advance` fires
    due deadlines (:meth:`next_deadline` says when the next one is due).
    """

    __slots__ = ()

    def apply_input(self, name: str, fields: Mapping[str, Any]) -> Answer | list[Answer] | None:
        """Apply a logged input (:mod:`.inputlog`, schema 1) again: the replay entry."""
        return inputlog.apply(self, name, fields)


__all__ = [
    "CommandRequest",
    "CompleteReport",
    "ModeRequest",
    "Request",
    "Stats",
    "StatusMark",
    "Transition",
    "Trigger",
    "Unit",
]
