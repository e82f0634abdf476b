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

Recipes: a changeover sends the unit's recipe to every active EM, which runs ``on_recipe(recipe)``
(a coroutine or a plain function; a :class:`~packml_ros2.core.recipes.Recipe`, whose
``parameter(name)`` gives a value). Returning applies it (``self.recipe``); raising
:class:`RecipeRefused` ("tool 7 not in the magazine") refuses it, and the unit then rolls every
EM back to the previous recipe (another ``on_recipe`` call) and refuses the changeover with that
reason. An EM without the hook accepts every recipe.

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
from packml_interfaces.msg import EmReport, RecipeOrder, Status
from rclpy.duration import Duration
from rclpy.serialization import deserialize_message

from . import run
from .boundary import GuardedNode
from .cdr_fields import Unreadable, field_reader
from .convert import recipe_in
from .core.em_hooks import HOOKS, HookRunner, StateContext, StatusView
from .core.numbers import Cmd, State, state_name
from .core.recipes import Recipe
from .core.reports import Writers
from .presence import with_info
from .ros import interface

__all__ = [
    "HOOKS",
    "EquipmentModule",
    "RecipeRefused",
    "StateContext",
    "StatusView",
    "status_view",
]


class RecipeRefused(Exception):
    """Raised by ``on_recipe``: this EM cannot take the recipe; the message is the reason."""


T = TypeVar("T")

COUNTERS = {"consumed": EmReport.COUNTER_CONSUMED, "processed": EmReport.COUNTER_PROCESSED,
            "defective": EmReport.COUNTER_DEFECTIVE}  # fmt: skip
FAULT_ALARM_ID = 9100  # default ID of the alarm raised when a hook fails
#: Heartbeats per lease on ``em_heartbeats`` (best effort): a cut of the link up to the lease less
#: one period (and the transit) never loses the EM.
BEATS_PER_LEASE = 10
LEAVE_ACK = 1.0  #: seconds a closing EM waits for its goodbye to be acknowledged
_STATUS_FIELDS = ["state_current", "sequence", "unit_mode_current", "unit_mode_requested",
                  "unit_mode_change_in_process"]  # fmt: skip
_EM_FIELDS = ["name", "active", "state_complete"]
#: leases the unit's status writer may be on the graph before an EM that heard no status from it
#: says so (the status is latched: it arrives as soon as the two have matched)
SILENCE = 2.0
#: times an EM that hears no status subscribes again (every SILENCE leases), at most
RESUBSCRIBE = 3

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
    state, sequence, mode, mode_requested, mode_changing = head
    return StatusView(state, sequence, mode, mode_requested, bool(mode_changing), mine)


class EquipmentModule(GuardedNode):
    """An EM node ``name`` under its unit: ``/<cell>/<unit>/<name>``."""

    #: The hook an EM runs when its unit is gone (its status writer left the graph: the unit's
    #: process died, or the network to it is cut): the EM's safe state. None: nothing runs (the
    #: running hook is still cancelled). A constructor argument overrides it.
    unit_lost_state: State | None = State.ABORTING

    def __init__(
        self,
        name: str,
        unit: str,
        cell: str = "",
        *,
        lease: float = 2.0,
        fault_alarm_id: int = FAULT_ALARM_ID,
        unit_lost_state: State | str | None = "",
        **node_kwargs: Any,
    ) -> None:
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
        # the unit's inputs (packml_ros2.ros.interface), relative to this node's namespace: its unit
        reports, beats = interface.TOPIC["em_reports"], interface.TOPIC["em_heartbeats"]
        self._pub = self.create_publisher(reports.type, reports.name, reports.qos)
        self._beats = self.create_publisher(beats.type, beats.name, beats.qos)
        self._follow_unit(unit_lost_state)
        #: the recipe this EM applied last (None: none yet); ``on_recipe`` sets it
        self.recipe: Recipe | None = None
        self._recipe_order = -1  # the last changeover order taken
        self._recipe_lock: asyncio.Lock | None = None
        order = interface.TOPIC["recipe"]
        self._recipe_sub = self.create_subscription(
            order.type, order.name, self._on_recipe_order, order.qos
        )
        self.create_timer(lease / 4.0, self._heartbeat)
        self.create_timer(lease / BEATS_PER_LEASE, self._beat)
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

    # -- what integrators call ---------------------------------------------------------------------
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

    def raise_alarm(
        self,
        alarm_id: int,
        value: int = 0,
        message: str = "",
        category: int = -1,
        warning: bool = False,
    ) -> None:
        """Raise alarm (``alarm_id``, ``value``); category/message default to the unit's configuration."""
        self._send(
            EmReport.KIND_ALARM,
            alarm_id=alarm_id,
            alarm_value=value,
            alarm_active=True,
            warning=warning,
            category=category,
            message=message,
        )

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
        key = (
            int(self.state if state is None else state),
            self.sequence if sequence is None else sequence,
        )
        self._reported = (*key, time.monotonic())
        self._send(EmReport.KIND_STATE_COMPLETE, state=key[0], sequence=key[1])

    # -- plumbing ----------------------------------------------------------------------------------
    def _send(self, kind: int, **fields: Any) -> None:
        if self.unit_lost and kind == EmReport.KIND_STATE_COMPLETE:
            return  # (the safe state's hook ended: nobody to tell; the unit is gone)
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
        self._watch_unit()
        self._watch_silence()
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

    # -- the unit this EM follows: its one status writer, and its loss (issue 25) ------------------
    def _follow_unit(self, unit_lost_state: State | str | None) -> None:
        if unit_lost_state != "":
            self.unit_lost_state = (
                None
                if unit_lost_state is None
                else State[str(unit_lost_state).upper()]
                if isinstance(unit_lost_state, str)
                else State(unit_lost_state)
            )
        #: the unit's status writer (DDS publisher GID), as the unit binds each EM's writer: a
        #: status from another writer (a forger, a second node of the name) is refused
        self._unit_writer = Writers()
        self._candidate: tuple[bytes, bytes] | None = None  # (writer, raw) last refused
        self.unit_lost = False  # the unit's status writer is gone: in the safe state
        self._silent_since = time.monotonic()  # for the silence of a unit seen on the graph
        #: status subscriptions made again because none of them heard the unit (_watch_silence)
        self.status_resubscribed = 0
        self._status_sub = self._subscribe_status()

    @property
    def silence_warned(self) -> bool:
        """This EM said it heard no status from a unit on the graph (and subscribed again)."""
        return self.status_resubscribed > 0

    def _subscribe_status(self) -> Any:
        status = interface.TOPIC["status"]
        return self.create_subscription(
            status.type, status.name, with_info(self._on_status_from), status.qos, raw=True
        )

    def _on_status_from(self, raw: bytes, info: Any) -> None:
        """Executor thread: a status taken only from the writer bound for the unit."""
        gid = info.get("publisher_gid")
        writer = bytes(gid["data"]) if gid else b""
        taken, _ = self._unit_writer.claim(
            self.unit_name, writer, time.monotonic(), self._status_writer_gone
        )
        if not taken:
            self.refused_statuses += 1
            self._candidate = (writer, raw)  # (taken when the bound writer is found gone)
            self.get_logger().warning(
                f"status of unit {self.unit_name} from another writer refused (a forger, or a "
                "restarted unit while its old writer is still on the graph)",
                throttle_duration_sec=10.0,
            )
            return
        self._candidate = None
        self._on_status_from_bound(raw)

    def _status_writer_gone(self, writer: bytes) -> bool:
        return all(
            bytes(bytearray(e.endpoint_gid))[: len(writer)] != writer
            for e in self.get_publishers_info_by_topic(self._status_sub.topic_name)
        )

    def _watch_unit(self) -> None:
        """Timer: the unit's status writer left the graph (its process died: DDS drops it
        within the participant lease): go to the safe state, say so; a status refused from a
        new writer meanwhile (the restarted unit) is taken now."""
        bound = self._unit_writer.bound(self.unit_name)
        if bound is None or not self._status_writer_gone(bound):
            return
        self._unit_writer.release(self.unit_name)
        candidate, self._candidate = self._candidate, None
        if candidate is not None:  # the restarted unit spoke while its old writer was listed
            self._unit_writer.claim(self.unit_name, candidate[0], time.monotonic())
            self._on_status_from_bound(candidate[1])
            return
        self._unit_gone()

    def _watch_silence(self) -> None:
        """Timer: the unit's status writer has been on the graph for :data:`SILENCE` leases and
        no status reached this EM (the status is latched: one arrives as soon as the two
        match): say so once, and subscribe again (up to :data:`RESUBSCRIBE` times, every
        SILENCE leases). Seen in CI: an EM whose reader never got the status of a unit that had
        its heartbeats. A unit that is not there yet is no news."""
        if self.status is not None or self.unit_lost:
            return
        writers = self.get_publishers_info_by_topic(self._status_sub.topic_name)
        if not writers:
            self._silent_since = time.monotonic()  # (counted from when the unit shows up)
            return
        waited = time.monotonic() - self._silent_since
        if waited < SILENCE * self.lease:
            return
        if not self.silence_warned:
            self.get_logger().warning(
                f"unit {self.unit_name}: {len(writers)} status writer(s) on the graph, but no "
                f"status reached this EM in {waited:.1f} s ({self.refused_statuses} refused): "
                "subscribing again"
            )
        if self.status_resubscribed >= RESUBSCRIBE:
            return
        # A new reader matches the writer afresh and takes the latched status at once. The old
        # one stays (destroying a subscription under rclpy 9.1's EventsExecutor can crash it,
        # ros2/rclpy#1644); a status both deliver is the same status twice, which changes nothing.
        self.status_resubscribed += 1
        self._status_sub = self._subscribe_status()
        self._silent_since = time.monotonic()

    def _on_status_from_bound(self, raw: bytes) -> None:
        if self.unit_lost:
            self.unit_lost = False
            self.get_logger().info(f"unit {self.unit_name} is back: following it again")
        self._on_raw_status(raw)

    def _unit_gone(self) -> None:
        """The unit is gone: cancel the running hook and run the safe state's hook; no State
        Complete goes out until the unit is back (it rejoins with the unit's next status)."""
        if self.unit_lost or self.status is None:
            return
        self.unit_lost = True
        safe = self.unit_lost_state
        what = f"running its {state_name(safe)} hook" if safe is not None else "hooks stopped"
        self.get_logger().warning(
            f"unit {self.unit_name} lost (its status writer left): {what} until it is back"
        )
        now = self.status
        view = now._replace(
            state=int(safe) if safe is not None else int(State.STOPPED),
            mode_changing=False,
            mine=(True, False),
        )
        self._on_status(view)

    def _beat(self) -> None:
        """The heartbeat on the best-effort channel the unit's lease follows (qos.EM_HEARTBEATS),
        :data:`BEATS_PER_LEASE` times a lease: the one on ``em_reports`` waits behind a lost
        reliable report for as long as its repair takes; this one arrives as soon as the link is
        back, so a cut of up to 9/10 of the lease never loses the EM. (The one on ``em_reports``
        stays: it registers the EM, and recordings and older units read heartbeats there.)"""
        msg = EmReport(em=self.em_name, kind=EmReport.KIND_HEARTBEAT, lease=self.lease)
        msg.stamp = self._stamp()
        self._beats.publish(msg)

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
        now = self.status
        if self.status_resubscribed and now is not None and view.sequence < now.sequence:
            return  # an older status by another of this EM's readers (subscribed again)
        with self.hooks.lock:
            self._status_raw = raw
        self._on_status(view)

    def _on_status(self, msg: StatusView) -> None:
        """Executor thread: follow the unit (:meth:`HookRunner.on_status`)."""
        self.hooks.on_status(msg)

    def _hook_failed(
        self, hook: Callable[[StateContext], Any], ctx: StateContext, exc: Exception
    ) -> None:
        name = getattr(hook, "__name__", "hook")
        self.get_logger().error(
            f"{name} failed in {state_name(ctx.state)}: {exc}\n{traceback.format_exc()}"
        )
        self.raise_alarm(
            self.fault_alarm_id, 0, f"{self.em_name}: {name} failed: {exc}"[:200], category=2
        )

    # -- recipes -----------------------------------------------------------------------------------
    def _on_recipe_order(self, msg: RecipeOrder) -> None:
        """Executor thread: an order of the unit's changeover; those naming this EM run its
        ``on_recipe`` hook, one after the other, and are answered."""
        if msg.phase == RecipeOrder.PHASE_NONE or self.em_name not in msg.ems:
            return
        if msg.changeover == self._recipe_order:
            return  # (the latched order again)
        self._recipe_order = msg.changeover
        try:
            recipe = recipe_in(msg.recipe)
        except (ValueError, TypeError) as exc:
            self._answer_recipe(msg.changeover, False, f"unreadable recipe: {exc}"[:200])
            return
        self.run_coroutine(self._apply_recipe(msg.changeover, recipe))

    async def _apply_recipe(self, order: int, recipe: Recipe) -> None:
        if self._recipe_lock is None:
            self._recipe_lock = asyncio.Lock()
        async with self._recipe_lock:
            hook = getattr(self, "on_recipe", None)
            try:
                if hook is not None:
                    if asyncio.iscoroutinefunction(hook):
                        await hook(recipe)
                    else:
                        await asyncio.get_running_loop().run_in_executor(None, hook, recipe)
            except RecipeRefused as exc:
                self._answer_recipe(order, False, str(exc) or "refused")
                return
            except Exception as exc:  # a failing hook refuses; its traceback goes to the log
                self.get_logger().error(f"on_recipe failed: {exc}\n{traceback.format_exc()}")
                self._answer_recipe(order, False, f"on_recipe failed: {exc}"[:200])
                return
            self.recipe = recipe
            self._answer_recipe(order, True, "")

    def _answer_recipe(self, order: int, accepted: bool, reason: str) -> None:
        reason = " ".join("".join(c if c.isprintable() else " " for c in reason).split())
        self._send(
            EmReport.KIND_RECIPE, sequence=order, recipe_accepted=accepted, message=reason[:200]
        )
        if not accepted:
            self.get_logger().warning(f"recipe order {order} refused: {reason}"[:300])

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
            # the process ends next: a goodbye lost on the way would not be sent again, and the
            # unit would wait the whole lease instead of the grace (seen in CI)
            self._pub.wait_for_all_acked(Duration(seconds=LEAVE_ACK))
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
