"""Base class for equipment-module (EM) nodes: robots, grippers, conveyors, vision...

An EM follows its unit's state and reports State Complete. Subclass :class:`EquipmentModule` and
define a hook per acting state you care about::

    class Gripper(EquipmentModule):
        async def on_starting(self, ctx):      # a coroutine ...
            await self.open_jaws()

        def on_stopping(self, ctx):            # ... or a plain function (runs in a thread)
            self.hardware.release()

        async def execute(self, ctx):          # production; return = the run is finished
            while True:
                await ctx.finish(self.pick())  # Hold/Stop in the middle: the pick completes first
                self.count("processed")

Hook names: ``on_resetting``, ``on_starting``, ``execute``, ``on_completing``, ``on_holding``,
``on_unholding``, ``on_suspending``, ``on_unsuspending``, ``on_stopping``, ``on_aborting``,
``on_clearing``, and ``on_mode_change`` (during a unit mode change). When a hook returns, the base
class reports State Complete for that (state, sequence); states without a hook are reported
complete at once. When the unit leaves the state, the running hook is cancelled (once: later
statuses only update ``ctx.next_state``): a coroutine gets ``CancelledError`` at its next
``await`` (``ctx.finish(aw)`` lets one step complete first, except when the unit aborts), a plain
function sees ``ctx.cancelled`` set (``ctx.sleep(s)`` returns False; ``ctx.next_state`` tells where
the unit went). The next state's hook starts only after the previous one has ended (the rules:
:mod:`packml_ros2.core.em_hooks`). An exception in a hook raises the EM's fault alarm.

``self.state``, ``self.sequence`` and ``self.mode`` follow the unit; ``self.status`` is its latest
status as the EM reads it (read from the message's bytes: state, sequence, mode, this EM's entry)
and ``self.unit_status`` the whole message, decoded when asked for.

Heartbeats keep the EM's lease alive at the unit; an EM that restarts re-joins at the unit's current
state and sequence (the status topic is latched). An EM switched inactive sits states out; switched
active while the unit waits in an acting state, it joins that state: it runs its hook and reports
(the unit waits for it, packml_ros2.core.rules section 7).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import threading
import time
import traceback
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from builtin_interfaces.msg import Time
from packml_interfaces.msg import EmReport, Status
from rclpy.node import Node
from rclpy.serialization import deserialize_message

from . import qos, run
from .cdr_fields import Unreadable, field_reader
from .core.em_hooks import HOOKS, HookRunner, StateContext, StatusView
from .core.numbers import Cmd, State, state_name

__all__ = ["HOOKS", "EquipmentModule", "StateContext", "StatusView", "status_view"]

T = TypeVar("T")

COUNTERS = {"consumed": EmReport.COUNTER_CONSUMED, "processed": EmReport.COUNTER_PROCESSED,
            "defective": EmReport.COUNTER_DEFECTIVE}  # fmt: skip
FAULT_ALARM_ID = 9100  # default ID of the alarm raised when a hook fails
_STATUS_FIELDS = ["state_current", "sequence", "unit_mode_current", "unit_mode_requested",
                  "unit_mode_change_in_process"]  # fmt: skip
_EM_FIELDS = ["name", "active", "state_complete"]
#: What an EM reads of each status, straight from its bytes (a quarter of a full decode's time;
#: the full message is decoded only for who reads :attr:`EquipmentModule.unit_status`).
_read_status = field_reader(Status, _STATUS_FIELDS, {"equipment_modules": _EM_FIELDS})


def status_view(raw: bytes, em: str) -> StatusView:
    """The view of serialized status ``raw`` for EM ``em``; raises ValueError (and only that)
    when the bytes are no status."""
    try:
        *head, entries = _read_status(raw)
    except Unreadable:
        try:
            msg = deserialize_message(raw, Status)
        except Exception as exc:  # rclpy raises several types for bad bytes
            raise ValueError(f"not a status: {exc}") from None
        head = [getattr(msg, f) for f in _STATUS_FIELDS]
        entries = [tuple(getattr(e, f) for f in _EM_FIELDS) for e in msg.equipment_modules]
    mine = next(((active, done) for name, active, done in entries if name == em), None)
    return StatusView(*head, mine)


class EquipmentModule(Node):
    """An EM node ``name`` under its unit: ``/<cell>/<unit>/<name>``."""

    def __init__(self, name: str, unit: str, cell: str = "", *, lease: float = 2.0,
                 fault_alarm_id: int = FAULT_ALARM_ID, **node_kwargs: Any) -> None:  # fmt: skip
        namespace = "/" + "/".join(p for p in (cell, unit) if p)
        super().__init__(name, namespace=namespace, **node_kwargs)
        self.em_name = name
        self.unit_name = unit
        self.lease = lease
        self.fault_alarm_id = fault_alarm_id
        self._status_raw: bytes | None = None
        self._status_msg: tuple[bytes, Status] | None = None  # decoded on demand (unit_status)
        self.refused_statuses = 0  # messages on the status topic that were no status
        self._reported: tuple[int, int, float] | None = None  # last SC: (state, sequence, when)
        self._pub = self.create_publisher(EmReport, "em_reports", qos.EM_REPORTS)
        self.create_subscription(Status, "status", self._on_raw_status, qos.STATUS, raw=True)
        self.create_timer(lease / 4.0, self._heartbeat)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name=f"em-{name}", daemon=True
        )
        self._thread.start()
        #: what follows the unit's statuses and runs the hooks (packml_ros2.core.em_hooks)
        self.hooks = HookRunner(
            name,
            self._loop,
            self.hook_for,
            lambda: getattr(self, "on_mode_change", None),
            self.report_complete,
            self._hook_failed,
        )
        self._heartbeat()

    @property
    def status(self) -> StatusView | None:
        """The unit's latest status, as this EM reads it."""
        return self.hooks.status

    @property
    def active(self) -> bool:
        """This EM is active in its unit (the unit's status says so)."""
        return self.hooks.active

    # -- what integrators call -------------------------------------------------------------------------
    @property
    def unit_status(self) -> Status | None:
        """The unit's latest status message in full (decoded when asked for)."""
        raw, cached = self._status_raw, self._status_msg
        if raw is None:
            return None
        if cached is None or cached[0] is not raw:
            cached = (raw, deserialize_message(raw, Status))
            self._status_msg = cached
        return cached[1]

    @property
    def state(self) -> State:
        view = self.status
        if view is None or view.state not in State._value2member_map_:
            return State.UNDEFINED
        return State(view.state)

    @property
    def sequence(self) -> int:
        return self.status.sequence if self.status else 0

    @property
    def mode(self) -> int:
        return self.status.mode if self.status else 0

    def request(self, command: Cmd | int) -> None:
        """Ask the unit for a state command (e.g. ``Cmd.STOP``); 0 withdraws."""
        self._send(EmReport.KIND_COMMAND_REQUEST, command=int(command))

    def count(self, counter: str = "processed", increment: int = 1, index: int = 0) -> None:
        """Add to the unit's ProdConsumed/Processed/DefectiveCount[index]."""
        self._send(
            EmReport.KIND_COUNT, counter=COUNTERS[counter], counter_index=index, increment=increment
        )

    def raise_alarm(self, alarm_id: int, value: int = 0, message: str = "", category: int = -1,
                    warning: bool = False) -> None:  # fmt: skip
        """Raise alarm (``alarm_id``, ``value``); category/message default to the unit's configuration."""
        self._send(EmReport.KIND_ALARM, alarm_id=alarm_id, alarm_value=value, alarm_active=True,
                   warning=warning, category=category, message=message)  # fmt: skip

    def clear_alarm(self, alarm_id: int, value: int = 0) -> None:
        """The alarm's condition is gone (it stays latched at the unit until reset)."""
        self._send(
            EmReport.KIND_ALARM,
            alarm_id=alarm_id,
            alarm_value=value,
            alarm_active=False,
            category=-1,
        )

    def set_interlock(
        self, blocked: bool = False, starved: bool = False, material_interlock: int = 0
    ) -> None:
        """Report Blocked (downstream full) / Starved (no infeed): the unit suspends."""
        self._send(
            EmReport.KIND_INTERLOCK,
            blocked=blocked,
            starved=starved,
            material_interlock=material_interlock,
        )

    def report_complete(self, state: int | None = None, sequence: int | None = None) -> None:
        """State Complete for (state, sequence); the base class does this when a hook returns."""
        key = (int(self.state if state is None else state),
               self.sequence if sequence is None else sequence)  # fmt: skip
        self._reported = (*key, time.monotonic())
        self._send(EmReport.KIND_STATE_COMPLETE, state=key[0], sequence=key[1])

    # -- plumbing ------------------------------------------------------------------------------------------
    def _send(self, kind: int, **fields: Any) -> None:
        msg = EmReport(em=self.em_name, kind=kind, lease=self.lease, **fields)
        msg.stamp = self._stamp()
        self._pub.publish(msg)

    def _stamp(self) -> Time:
        return self.get_clock().now().to_msg()

    def _heartbeat(self) -> None:
        """Alive; and State Complete again when the unit still waits for the one sent (a report
        it did not take: lost, or refused while it checked who speaks for this EM after a
        restart, core.reports.Writers)."""
        self._send(EmReport.KIND_HEARTBEAT)
        reported, status = self._reported, self.status
        if reported is None or status is None:
            return
        state, sequence, when = reported
        if status.key != (state, sequence):
            return
        if (
            status.mine is not None
            and not status.mine[1]
            and time.monotonic() - when >= self.lease / 4
        ):
            self.report_complete(state, sequence)

    def hook_for(self, state: State) -> Callable[[StateContext], Any] | None:
        """The hook for an acting state (None: nothing to do, complete at once). Override to
        choose hooks at run time."""
        return getattr(self, HOOKS[state], None)

    def _on_raw_status(self, raw: bytes) -> None:
        """Executor thread: a status as it came (serialized), read for what an EM follows."""
        try:
            view = status_view(raw, self.em_name)
        except ValueError as exc:
            self.refused_statuses += 1
            self.get_logger().warning(f"status refused: {exc}"[:200], throttle_duration_sec=10.0)
            return
        with self.hooks.lock:
            self._status_raw = raw
        self._on_status(view)

    def _on_status(self, msg: StatusView) -> None:
        """Executor thread: follow the unit (:meth:`HookRunner.on_status`)."""
        self.hooks.on_status(msg)

    def _hook_failed(self, hook: Callable[[StateContext], Any], ctx: StateContext,
                     exc: Exception) -> None:  # fmt: skip
        name = getattr(hook, "__name__", "hook")
        self.get_logger().error(
            f"{name} failed in {state_name(ctx.state)}: {exc}\n{traceback.format_exc()}"
        )
        self.raise_alarm(
            self.fault_alarm_id, 0, f"{self.em_name}: {name} failed: {exc}"[:200], category=2
        )

    def run_coroutine(self, coro: Awaitable[T]) -> concurrent.futures.Future[T]:
        """Run a coroutine on the EM's asyncio loop from any thread."""
        return asyncio.run_coroutine_threadsafe(coro, self._loop)  # type: ignore[arg-type]

    def close(self) -> None:
        """Stop the hooks, then say goodbye to the unit (it applies its lost-EM reaction after
        its ``em_leave_grace``, unless it shuts down too) and log it."""
        self._stop_loop()
        if not self.context.ok():
            return  # nobody to tell any more
        with contextlib.suppress(Exception):
            self._send(EmReport.KIND_LEAVE)
        reason = run.shutdown_reason() or "node closed"
        self.get_logger().info(f"EM {self.em_name} left unit {self.unit_name} ({reason})")

    def destroy_node(self) -> None:
        """Stop the hooks' event loop too (without a goodbye: use :meth:`close` for that)."""
        self._stop_loop()
        super().destroy_node()

    def _stop_loop(self) -> None:
        if not self._loop.is_running():
            return
        with contextlib.suppress(concurrent.futures.TimeoutError, RuntimeError):
            asyncio.run_coroutine_threadsafe(self._stop_tasks(), self._loop).result(timeout=5)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(2)
        if not self._loop.is_running():
            self._loop.close()  # else its __del__ complains at interpreter exit

    async def _stop_tasks(self) -> None:
        self.hooks.close()  # a finishing step does not hold the shutdown up
        current = asyncio.current_task()
        tasks = [t for t in asyncio.all_tasks() if t is not current]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
