"""QoS profiles of packml_ros2's topics (ROS_API.md), shared by nodes, tools and tests."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def _profile(depth: int, latched: bool) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


#: ``<unit>/status``, ``<unit>/admin``, ``<unit>/alarms``, ``<cell>/coordinator/status``: the last
#: message reaches late subscribers at once.
LATCHED = _profile(1, latched=True)
STATUS = LATCHED
ADMIN = LATCHED
ALARMS = LATCHED
CELL_STATUS = LATCHED
#: ``<unit>/transitions``: every transition, none dropped under bursts; a late subscriber (an HMI,
#: a restarted tool) gets the last 100 at once.
TRANSITIONS = _profile(100, latched=True)
#: ``<unit>/em_reports``: EM -> unit events (State Complete, counts, alarms, heartbeats).
EM_REPORTS = _profile(200, latched=False)
#: ``<unit>/input_log``: every input the unit's engine applied, for record/replay; latched deep
#: so a recorder that starts late still gets the inputs since the unit started.
INPUT_LOG = _profile(5000, latched=True)
#: ``/diagnostics`` (diagnostic_msgs), as the standard aggregator expects.
DIAGNOSTICS = _profile(10, latched=False)
