"""Record and replay PackML units as rosbag2 bags (``packml record`` / ``packml replay``).

- :mod:`.record`: a recorder node writing a unit's (or a cell's) inputs and outputs to a bag;
- :mod:`.recording`: reading a bag (ours, rosbag2's or any other writer's) per unit;
- :mod:`.replay`: the offline replay-check (the engine on the bag's own clock), ``--update``;
- :mod:`.live`: feeding a recording to running nodes (``--live``);
- :mod:`.cdr`: comparing serialized messages with their padding ignored;
- :mod:`.synthetic`: recordings made offline by driving an engine like the node (bench, tests).

Bags hold per unit ``/<cell>/<unit>/{input_log,config,status,transitions,admin,alarms,em_reports}``
and, for a cell, ``/<cell>/coordinator/status``.
"""

from __future__ import annotations

from .topics import INPUT_TOPICS, OUTPUT_TOPICS, UNIT_TOPICS

__all__ = ["INPUT_TOPICS", "OUTPUT_TOPICS", "UNIT_TOPICS"]
