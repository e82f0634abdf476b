"""The line on the OPC UA face: ``Objects/Lines/<cell>`` with the line's OEE and loss waterfall of
the current shift (the lifetime without a shift calendar) and its current stop episode, fed from
the coordinator's ``line/losses`` and ``line/episodes`` topics. Read-only (no methods).

Variables (server namespace): ``Window`` (String: ``shift:2025-06-16 early``), ``OEE``,
``Availability``, ``Performance``, ``Quality`` (Double, 0..1; Performance is NaN without a design
speed), the waterfall in seconds (Double): ``Elapsed``, ``PlannedStop``, ``Changeover``,
``UnplannedStop``, ``Blocked``, ``Starved``, ``Held``, ``Running``, ``SpeedLoss``, ``QualityLoss``,
``Productive`` (they add up to ``Elapsed``, ``Running`` aside);
``Processed``, ``Defective`` (Int64); and ``CurrentEpisode`` with ``Open`` (Boolean), ``Id``
(UInt32), ``Start`` (DateTime), ``DurationSeconds`` (Double), ``RootCauseUnit``, ``Bucket``,
``Reason``, ``Source`` (String), ``AffectedUnits`` (String[]): the open episode, else the last
one (``Open`` false). Until the coordinator has published, values are Bad_WaitingForInitialData.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
from typing import Any

from asyncua import Server, ua

from ..core.line.losses import times_ns

_logger = logging.getLogger(__name__)
NS = 1  # the server's own namespace (the units' objects are there too)
NANO = 1_000_000_000
#: variable -> (variant type, LossScope field: a part of its time in ns (``<part>_ns``, of
#: :func:`~packml_ros2.core.line.losses.times_ns`) or a value)
LOSSES: dict[str, tuple[ua.VariantType, str]] = {
    "OEE": (ua.VariantType.Double, "oee"),
    "Availability": (ua.VariantType.Double, "availability"),
    "Performance": (ua.VariantType.Double, "performance"),
    "Quality": (ua.VariantType.Double, "quality"),
    "Elapsed": (ua.VariantType.Double, "elapsed_ns"),
    "PlannedStop": (ua.VariantType.Double, "planned_stop_ns"),
    "Changeover": (ua.VariantType.Double, "changeover_ns"),
    "UnplannedStop": (ua.VariantType.Double, "unplanned_stop_ns"),
    "Blocked": (ua.VariantType.Double, "blocked_ns"),
    "Starved": (ua.VariantType.Double, "starved_ns"),
    "Held": (ua.VariantType.Double, "held_ns"),
    "Running": (ua.VariantType.Double, "running_ns"),
    "SpeedLoss": (ua.VariantType.Double, "speed_loss_ns"),
    "QualityLoss": (ua.VariantType.Double, "quality_loss_ns"),
    "Productive": (ua.VariantType.Double, "productive_ns"),
    "Processed": (ua.VariantType.Int64, "processed"),
    "Defective": (ua.VariantType.Int64, "defective"),
}
EPISODE: dict[str, ua.VariantType] = {
    "Open": ua.VariantType.Boolean, "Id": ua.VariantType.UInt32,
    "Start": ua.VariantType.DateTime, "DurationSeconds": ua.VariantType.Double,
    "RootCauseUnit": ua.VariantType.String, "Bucket": ua.VariantType.String,
    "Reason": ua.VariantType.String, "Source": ua.VariantType.String,
    "AffectedUnits": ua.VariantType.String,
}  # fmt: skip


def _time(t: Any) -> dt.datetime:
    return dt.datetime.fromtimestamp(t.sec + t.nanosec / NANO, dt.UTC)


class LineFace:
    """``Objects/Lines/<cell>``; :meth:`attach` subscribes it to the coordinator's topics."""

    def __init__(self, server: Server, cell: str) -> None:
        self.server = server
        self.cell = cell
        self.nodes: dict[str, Any] = {}
        self.loop: asyncio.AbstractEventLoop | None = None
        self._last_episode: Any = None
        self.shifts = False  #: the coordinator publishes shift windows

    @classmethod
    async def create(cls, server: Server, cell: str) -> LineFace:
        face = cls(server, cell)
        objects = server.nodes.objects
        lines = await objects.add_folder(ua.NodeId("Lines", NS), ua.QualifiedName("Lines", NS))
        line = await lines.add_object(ua.NodeId(f"{cell}.Line", NS), ua.QualifiedName(cell, NS))
        waiting = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)
        await face._variable(line, "Window", ua.VariantType.String, "", waiting)
        for name, (vtype, _) in LOSSES.items():
            await face._variable(
                line, name, vtype, 0 if vtype == ua.VariantType.Int64 else 0.0, waiting
            )
        episode = await line.add_object(
            ua.NodeId(f"{cell}.Line.CurrentEpisode", NS), ua.QualifiedName("CurrentEpisode", NS)
        )
        for name, vtype in EPISODE.items():
            default: Any = {
                ua.VariantType.Boolean: False,
                ua.VariantType.UInt32: 0,
                ua.VariantType.Double: 0.0,
                ua.VariantType.DateTime: dt.datetime(1970, 1, 1, tzinfo=dt.UTC),
            }.get(vtype, "")
            if name == "AffectedUnits":
                default = []
            await face._variable(episode, f"CurrentEpisode.{name}", vtype, default, waiting, name)
        return face

    async def _variable(
        self,
        parent: Any,
        key: str,
        vtype: ua.VariantType,
        value: Any,
        status: ua.StatusCode,
        browse: str | None = None,
    ) -> None:
        name = browse or key
        variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
        node = await parent.add_variable(
            ua.NodeId(f"{self.cell}.Line.{key}", NS), ua.QualifiedName(name, NS), variant
        )
        await self.server.write_attribute_value(
            node.nodeid, ua.DataValue(variant, StatusCode=status)
        )
        self.nodes[key] = node

    def attach(self, node: Any, loop: asyncio.AbstractEventLoop) -> None:
        """Subscribe ``node`` (a ROS node, not spinning yet) to the coordinator's line topics."""
        from packml_interfaces.msg import LineEpisode, LineLosses

        from .. import qos

        self.loop = loop
        base = f"/{self.cell}/coordinator/line"
        node.create_subscription(LineLosses, f"{base}/losses", self._from_ros, qos.LINE_LOSSES)
        node.create_subscription(LineEpisode, f"{base}/episodes", self._from_ros, qos.LINE_EPISODES)

    def _from_ros(self, msg: Any) -> None:
        if self.loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closed: shutting down
                self.loop.call_soon_threadsafe(self._schedule, msg)

    def _schedule(self, msg: Any) -> None:
        asyncio.get_running_loop().create_task(self._write(msg))

    async def _write(self, msg: Any) -> None:
        try:
            if hasattr(msg, "scopes"):
                await self._losses(msg)
            else:
                await self._episode(msg)
        except Exception:
            _logger.exception("OPC UA: could not write the line of %s", self.cell)

    async def _set(self, key: str, vtype: ua.VariantType, value: Any, when: dt.datetime) -> None:
        variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
        await self.server.write_attribute_value(
            self.nodes[key].nodeid, ua.DataValue(variant, SourceTimestamp=when)
        )

    async def _losses(self, msg: Any) -> None:
        """Of each publication, the current shift (or the lifetime without shifts)."""
        if not (msg.window.startswith("shift:") or msg.window == "lifetime") or not msg.scopes:
            return
        if msg.window.startswith("shift:"):
            self.shifts = True
        elif self.shifts:
            return  # the lifetime is shown only by a line without a shift calendar
        when = _time(msg.stamp)
        line = msg.scopes[0]
        await self._set("Window", ua.VariantType.String, msg.window, when)
        parts = times_ns(line)  # (the changeover is its own part, out of planned_stop_ns)
        for name, (vtype, field) in LOSSES.items():
            value = parts[field[:-3]] / NANO if field.endswith("_ns") else getattr(line, field)
            await self._set(name, vtype, value, when)

    async def _episode(self, msg: Any) -> None:
        """The open episode; a closed one only when no later episode is open."""
        last = self._last_episode
        if last is not None and last.open and last.id > msg.id:
            return
        self._last_episode = msg
        when = _time(msg.stamp)
        values = {
            "Open": msg.open,
            "Id": msg.id,
            "Start": _time(msg.start),
            "DurationSeconds": msg.duration_ns / NANO,
            "RootCauseUnit": msg.root_unit or "cell",
            "Bucket": msg.bucket,
            "Reason": msg.reason,
            "Source": msg.source,
            "AffectedUnits": [f"{a.unit} ({a.how})" for a in msg.affected],
        }
        for name, vtype in EPISODE.items():
            await self._set(f"CurrentEpisode.{name}", vtype, values[name], when)
