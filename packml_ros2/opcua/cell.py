"""The whole cell as one PackML object (``opcua.cell_object``): ``Objects/PackMLObjects/<cell>``, a
PackMLBaseObjectType like a unit's, whose state is the coordinator's and whose commands are the
cell commands. A line controller, an MES or this project's PLC bridge sees the cell as one
machine: a line of cells is a cell file whose units are other cells' objects (``plc:`` blocks),
sequenced by an ordinary coordinator.

What the object shows, from the coordinator's ``status`` (CellStatus) and ``line/episodes``:

- state and mode: the cell's aggregate state and common mode; ``StateChangeInProcess`` while a
  cell command sequence runs; ``EquipmentBlocked``/``Starved`` while any of its units is;
- ``Admin/StopReason``: the cell's last stop episode, its message ``<unit>: <reason>`` (the
  unit it started at and why; the root unit's StopReason ID when it is known, else 0) — a line
  above sees which unit of which cell stopped it;
- the methods: Abort ... ToComplete, ``SetUnitMode`` go to the coordinator's ``command`` and
  ``set_mode`` (all or nothing, in the cell's order); a method is Executable while the cell
  command is valid (``commands_valid``). What a cell has no one value for (``SetMachSpeed``,
  ``SetParameter``, ``SetProduct``, ``SetRecipe``) is refused BadNotImplemented: set it per unit.

Pure: messages in, messages out (the unit's Status and Admin types, so the unit object's mapping
writes them unchanged).
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import Any

from packml_interfaces.msg import Admin, Alarm, Status

from ..core.config import CellConfig, UnitConfig
from ..core.numbers import Cmd
from ..core.recipes import RecipeBook
from .mapping import COMMAND_METHODS

#: the coordinator's services the object calls (the unit services of the same names and types)
SERVICES = ("command", "set_mode")


def coordinator_path(cell: str) -> str:
    return f"/{cell}/coordinator"


def cell_unit(cell: CellConfig) -> UnitConfig:
    """The rules the cell object is drawn with: those of the cell's first unit in its start order
    (modes, model, disabled states), named for the cell. What is Executable comes from the
    coordinator's ``commands_valid`` instead (all units together)."""
    order = cell.coordinator.start_order
    first = cell.units[order[0] if order else next(iter(cell.units))]
    return replace(
        first,
        name=cell.cell,
        description=f"the cell {cell.cell} ({', '.join(cell.units)}) through its coordinator",
        recipes=RecipeBook(),
    )


def cell_status(msg: Any) -> Status:
    """CellStatus -> the Status the object's mapping writes."""
    blocked = any(u.blocked for u in msg.units)
    starved = any(u.starved for u in msg.units)
    status = Status(
        stamp=msg.stamp,
        unit=str(msg.cell),
        unit_mode_current=int(msg.unit_mode_current),
        unit_mode_requested=int(msg.unit_mode_current),
        state_current=int(msg.state_current),
        state_requested=int(msg.state_current),
        state_change_in_process=bool(msg.busy),
        state_current_name=str(msg.state_current_name),
        commands_valid=[int(c) for c in msg.commands_valid],
        commands_valid_names=list(msg.commands_valid_names),
    )
    status.equipment_interlock.blocked = blocked
    status.equipment_interlock.starved = starved
    return status


def cell_admin(episode: Any) -> Admin:
    """The cell's last stop episode (LineEpisode) -> an Admin whose StopReason names the unit it
    started at (``<unit>: <reason>``) and carries that unit's StopReason ID when known."""
    admin = Admin(stamp=episode.stamp)
    reason = copy.deepcopy(episode.stop_reason) if episode.stop_reason_known else Alarm()
    root = str(episode.root_unit) or "cell"
    text = str(episode.stop_reason.message) if episode.stop_reason_known else ""
    reason.message = f"{root}: {text or episode.reason}"
    reason.source = str(episode.source)
    admin.stop_reason = reason
    admin.stop_reason_extent = 1
    return admin


#: a state machine method's name -> its command
_COMMANDS: dict[str, Cmd] = {name: cmd for cmd, name in COMMAND_METHODS.items()}


def valid(status: Any, path: str) -> bool:
    """Whether the cell command of the method at ``path`` is valid now (the coordinator's
    all-or-nothing view of every unit)."""
    command = _COMMANDS.get(path.rpartition("/")[2])
    return status is not None and command is not None and int(command) in status.commands_valid
