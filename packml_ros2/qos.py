"""QoS profiles of packml_ros2's topics (docs/ros-api.md), shared by nodes, tools and tests."""

from __future__ import annotations

from rclpy.duration import Duration
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)


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
#: ``<unit>/em_heartbeats``: EM -> unit heartbeats (EmReport KIND_HEARTBEAT), best effort and
#: keep-last: a heartbeat is never held behind a reliable report whose loss is being repaired
#: (after a network blip, reliable ``em_reports`` deliver nothing until the gap is filled, which
#: took longer than the lease), and a lost one is replaced by the next.
EM_HEARTBEATS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=20,
    reliability=ReliabilityPolicy.BEST_EFFORT,
    durability=DurabilityPolicy.VOLATILE,
)
#: ``<unit>/input_log``: every input the unit's engine applied, for record/replay; latched deep
#: so a recorder that starts late still gets the inputs since the unit started.
INPUT_LOG = _profile(5000, latched=True)
#: Services of units, bridges and the coordinator, and this package's clients of them: deep
#: enough for every client a cell has (operators, the coordinator, the HMI, OPC UA, scripts)
#: pipelining requests; with the ROS default (10) a burst of 50 lost 40 of them.
SERVICES = _profile(256, latched=False)
#: ``<cell>/coordinator/line/input_log``: the line's inputs, for record/replay (like INPUT_LOG).
LINE_INPUT_LOG = INPUT_LOG
#: ``<cell>/coordinator/line/episodes``: every change of a stop episode; the last 100 reach a
#: late subscriber.
LINE_EPISODES = _profile(100, latched=True)
#: ``<cell>/coordinator/line/losses``: one message per window at each publication; the last set
#: reaches a late subscriber.
LINE_LOSSES = _profile(8, latched=True)
#: ``<unit>/snapshot``: the engine state, published when a subscriber (a recorder) joins; the last
#: one reaches late subscribers at once.
SNAPSHOT = LATCHED
#: ``/diagnostics`` (diagnostic_msgs), as the standard aggregator expects.
DIAGNOSTICS = _profile(10, latched=False)


def with_lease(profile: QoSProfile, lease: float) -> QoSProfile:
    """``profile`` with DDS liveliness AUTOMATIC and a lease of ``lease`` seconds.

    A unit publishes ``status`` with its ``unit_lease`` (:func:`status_publisher`): while its
    process lives, DDS asserts the writer's liveliness by itself (every 2/3 of the lease); a
    killed process or a cut network shows as lost liveliness within the lease, without a
    message. Subscribers that keep the default (an infinite lease) stay compatible and see no
    difference; a subscriber that wants to notice the loss asks for the same lease
    (:mod:`packml_ros2.presence`): Fast DDS measures the silence with the reader's lease, and
    a reader asking for a shorter lease than the writer offers does not match it."""
    return QoSProfile(
        history=profile.history,
        depth=profile.depth,
        reliability=profile.reliability,
        durability=profile.durability,
        liveliness=LivelinessPolicy.AUTOMATIC,
        liveliness_lease_duration=Duration(nanoseconds=int(lease * 1e9)),
    )


def quiet_events() -> SubscriptionEventCallbacks:
    """QoS event callbacks for a subscription spun by a Python executor (the coordinator's
    MultiThreadedExecutor): none. rclpy's default ones (warnings about an incompatible QoS or
    type) wait on the reader's DDS status condition, which a message arriving triggers too: from
    the moment the executor hands the message's callback to a thread until that thread has taken
    the message, the executor woke at once, again and again, rebuilding its wait set of every
    entity each time (an idle coordinator: 450 of 470 wake-ups in 20 s, a core's 1 % of the demo
    cell's 2.5 %). Our subscribers and publishers share this module's profiles; the one lease that
    can differ is followed by :mod:`packml_ros2.presence`, with its own incompatible-QoS warning."""
    return SubscriptionEventCallbacks(use_default_callbacks=False)


def status_publisher(lease: float) -> QoSProfile:
    """The unit's ``status`` writer: :data:`STATUS` with liveliness lease ``lease`` (seconds)."""
    return with_lease(STATUS, lease)
