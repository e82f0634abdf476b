"""The status-following core of an equipment module: which hook runs for which (state, sequence),
when a running hook is cancelled, and when State Complete is reported. No ROS here: the EM node
(:class:`packml_ros2.equipment_module.EquipmentModule`) feeds it the statuses it reads and
publishes the reports it makes; tests drive it on an event loop with a virtual clock.

The rules (README "Writing an equipment module"):

- One hook at a time. The next state's hook starts only after the running one has ended.
- The unit leaving the state cancels the running hook **once**: a coroutine gets ``CancelledError``
  at its next ``await``, a plain function sees ``ctx.cancelled``. Statuses that arrive while it
  winds down (other EMs' alarms, mode changes, repeated commands) only update where the unit went
  (``ctx.next_state``); they never cancel it again, so a hook's own clean-up is not cut.
- ``ctx.finish(aw)`` runs ``aw`` to its end whatever arrives meanwhile — except Abort: the unit
  going to Aborting (at the first cancellation or any time later while ``aw`` still runs)
  cancels ``aw`` at once. Abort is the E-stop path of a cell: a robot moving on after an
  emergency stop is exactly what Abort is there to prevent.
- State Complete is reported once per (state, sequence) whose hook returned while the unit was
  still in that state (a hook cut by the unit leaving owes nothing).
"""

from __future__ import annotations

import asyncio
import inspect
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple, TypeVar

from .numbers import ACTING, State

T = TypeVar("T")
Hook = Callable[["StateContext"], Any]

HOOKS: dict[State, str] = {
    State.RESETTING: "on_resetting",
    State.STARTING: "on_starting",
    State.EXECUTE: "execute",
    State.COMPLETING: "on_completing",
    State.HOLDING: "on_holding",
    State.UNHOLDING: "on_unholding",
    State.SUSPENDING: "on_suspending",
    State.UNSUSPENDING: "on_unsuspending",
    State.STOPPING: "on_stopping",
    State.ABORTING: "on_aborting",
    State.CLEARING: "on_clearing",
}


class StatusView(NamedTuple):
    """What an EM follows of its unit's status."""

    state: int
    sequence: int
    mode: int
    mode_requested: int
    mode_changing: bool
    mine: tuple[bool, bool] | None  # this EM's entry: (active, state_complete); None: not listed

    @property
    def key(self) -> tuple[int, int]:
        return self.state, self.sequence


def _state(number: int) -> State:
    return State(number) if number in State._value2member_map_ else State.UNDEFINED


@dataclass
class StateContext:
    """What a hook gets: the (state, sequence) it works for, the unit mode, and cancellation."""

    state: State
    sequence: int
    mode: int
    cancelled: threading.Event = field(default_factory=threading.Event)
    next_state: State = State.UNDEFINED  # set when the unit leaves the state
    _finishing: set[asyncio.Future[Any]] = field(default_factory=set, repr=False)
    _closing: bool = field(default=False, repr=False)  # the EM shuts down: nothing is finished

    def sleep(self, seconds: float) -> bool:
        """For plain-function hooks: wait ``seconds``; False (early) if the state was left."""
        return not self.cancelled.wait(seconds)

    async def finish(self, aw: Awaitable[T]) -> T:
        """Run ``aw`` to its end even if the unit leaves the state meanwhile (finish the move),
        then let the cancellation proceed. When the unit aborts — before or while ``aw`` runs —
        ``aw`` is cancelled at once (and awaited: its own clean-up ends before the next hook)."""
        task = asyncio.ensure_future(aw)
        self._finishing.add(task)
        if self.next_state is State.ABORTING or self._closing:
            task.cancel()
        interrupted = False
        try:
            while not task.done():
                try:
                    await asyncio.wait((task,))  # (cancelling this wait leaves the task alone)
                except asyncio.CancelledError:
                    interrupted = True
        finally:
            self._finishing.discard(task)
        if interrupted and (task.cancelled() or task.exception() is None):
            raise asyncio.CancelledError
        return task.result()

    def close(self) -> None:
        """The EM shuts down: cut what ``finish`` waits for, now and later (loop thread)."""
        self._closing = True
        self.cancelled.set()
        for task in list(self._finishing):
            task.cancel()

    def left(self, next_state: State) -> None:
        """The unit went on to ``next_state`` (called again for each later status)."""
        self.next_state = next_state
        self.cancelled.set()
        if next_state is State.ABORTING:
            for task in list(self._finishing):
                task.cancel()


class HookRunner:
    """Follows the statuses of one EM's unit and runs its hooks on ``loop``.

    ``hook_for(state)``: the hook of an acting state (None: complete at once); ``mode_hook()``: the
    hook of a mode change; ``report(state, sequence)``: send State Complete; ``failed(hook, ctx,
    exc)``: a hook raised. :meth:`on_status` may be called from any thread.
    """

    def __init__(
        self,
        name: str,
        loop: asyncio.AbstractEventLoop,
        hook_for: Callable[[State], Hook | None],
        mode_hook: Callable[[], Hook | None],
        report: Callable[[State, int], None],
        failed: Callable[[Hook, StateContext, Exception], None],
    ) -> None:
        self.name = name
        self.loop = loop
        self._hook_for, self._mode_hook = hook_for, mode_hook
        self._report, self._failed = report, failed
        self.lock = threading.Lock()
        self.status: StatusView | None = None  # the latest status
        self.active = True
        self._key: tuple[int, int] | None = None  # (state, sequence) being worked on
        self._running = False  # a hook task is in flight (started or finishing)
        self._pending: StatusView | None = None  # newest status that arrived while it was
        self._task: asyncio.Task[None] | None = None
        self._ctx: StateContext | None = None

    def on_status(self, msg: StatusView) -> None:
        """With no hook in flight the decision is taken right here (a state without a hook is
        reported complete at once); otherwise the running hook is told where the unit went and
        the newest status is handled when it has ended."""
        with self.lock:
            self.status = msg
            self.active = msg.mine[0] if msg.mine is not None else True
            if msg.key == self._key:
                return
            if self._running:
                self._pending = msg
                self.loop.call_soon_threadsafe(self._leave)
                return
            self._dispatch(msg)

    def _dispatch(self, msg: StatusView) -> None:
        """Under the lock: start the hook for ``msg``'s (state, sequence), or report at once."""
        if (msg.mine is not None and msg.mine[1]) or not self.active:
            # Already reported (an EM that restarted), or switched inactive: the (state,
            # sequence) is not taken, so an EM switched active while the unit waits in this state
            # joins it with its next status (PACKML rules: it owes State Complete for it).
            return
        self._key = msg.key
        state = _state(msg.state)
        hook: Hook | None
        if msg.mode_changing:
            ctx = StateContext(state, msg.sequence, msg.mode_requested)
            hook = self._mode_hook()
        elif state in ACTING:
            ctx = StateContext(state, msg.sequence, msg.mode)
            hook = self._hook_for(state)
        else:
            return
        if hook is None:
            self._report(ctx.state, ctx.sequence)
            return
        self._running = True
        self.loop.call_soon_threadsafe(self._start, hook, ctx)

    def _start(self, hook: Hook, ctx: StateContext) -> None:
        self._ctx = ctx
        self._task = self.loop.create_task(self._run(hook, ctx))
        self._task.add_done_callback(self._finished)

    def _leave(self) -> None:
        """Loop thread: the unit is no longer in the running hook's state. The hook is cancelled
        the first time only; later statuses just say where the unit went (Abort also cancels
        what ``ctx.finish`` waits for)."""
        task, ctx = self._task, self._ctx
        if task is None or task.done() or ctx is None:
            return
        with self.lock:
            pending = self._pending
        if pending is None:
            return
        first = not ctx.cancelled.is_set()
        ctx.left(_state(pending.state))
        if first:
            task.cancel()

    def close(self) -> None:
        """Loop thread, at shutdown: the running hook's ``finish`` steps end now."""
        if self._ctx is not None:
            self._ctx.close()

    def _finished(self, _: asyncio.Task[None]) -> None:
        """Loop thread: the hook ended; handle a status that arrived meanwhile."""
        with self.lock:
            self._task, self._ctx = None, None
            self._running = False
            pending, self._pending = self._pending, None
            if pending is not None and pending.key != self._key:
                self._dispatch(pending)

    async def _run(self, hook: Hook, ctx: StateContext) -> None:
        try:
            if inspect.iscoroutinefunction(hook):
                await hook(ctx)
            else:
                future = self.loop.run_in_executor(None, hook, ctx)
                cut = False
                while not future.done():  # a plain function cannot be interrupted: let it return
                    try:
                        await asyncio.wait((future,))
                    except asyncio.CancelledError:
                        cut = True
                        ctx.cancelled.set()
                result = future.result()
                if cut:
                    return
                if inspect.isawaitable(result):
                    await result
        except asyncio.CancelledError:
            return
        except Exception as exc:
            self._failed(hook, ctx, exc)
            return
        status = self.status
        if status is not None and status.key == (int(ctx.state), ctx.sequence):
            self._report(ctx.state, ctx.sequence)
