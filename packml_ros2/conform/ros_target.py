"""A ROS unit as a conformance target: ours, or any implementation that serves the interface
of :mod:`packml_ros2.ros.interface` (``<unit>/command``, ``set_mode``, ``reset_counters``;
``status``, ``admin``, ``transitions``).

The states it shows come from its ``transitions`` (every transition, in order, by sequence
number) where it publishes them, else from its ``status`` (which a unit may coalesce: then only
what was shown is judged). Its answers carry the reason codes of
``packml_interfaces/msg/Result``.
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Callable
from typing import Any

from packml_interfaces.msg import Admin, Status, TransitionEvent

from ..cli.session import Session
from ..client import Unavailable, UnitProxy
from ..convert import seconds
from ..core.numbers import State
from ..core.reasons import Reason
from .target import AdminView, History, Reply, Tags, Unreachable

#: Seconds the target waits, after its status came, for its transition writer to be matched.
TRANSITIONS_WAIT = 1.0
SOURCE = "operator"


def _state(number: int) -> State:
    """A state number as shown (hostile: anything else is UNDEFINED)."""
    try:
        return State(int(number))
    except ValueError:
        return State.UNDEFINED


def reply_of(resp: Any) -> Reply:
    """A service response (``accepted``/``success``, ``result``, ``message``): a :class:`Reply`."""
    accepted = bool(getattr(resp, "accepted", getattr(resp, "success", False)))
    result = int(getattr(resp, "result", 0))
    try:
        code = Reason(result).name
    except ValueError:
        code = f"result {result}"
    return Reply(accepted, code, str(getattr(resp, "message", ""))[:500], result)


class RosTarget:
    """The unit ``path`` (``/cell/unit``) over ROS."""

    face = "ros"

    def __init__(self, path: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.path = "/" + path.strip("/")
        self.where = f"ROS unit {self.path}"
        self.clock = clock
        self.complete_path = False
        self._history = History(clock)
        self._lock = threading.Lock()
        self._base: int | None = None  # the sequence number of the status the run began at
        self._last = -1
        self._early: list[TransitionEvent] = []
        self._status: Status | None = None
        self._admin: Admin | None = None
        self._admin_received = 0.0
        self._admin_cond = threading.Condition()
        self._session: Session | None = None
        self._proxy: UnitProxy | None = None

    # -- connection --------------------------------------------------------------------------------
    def connect(self, timeout: float) -> None:
        session = self._session = Session(argparse.Namespace(timeout=timeout, cell=None), ())
        proxy = self._proxy = UnitProxy(
            session.node, self.path, self._on_change, ("status", "admin", "transitions")
        )
        try:
            proxy.wait_status(timeout=timeout)
        except Unavailable:
            raise Unreachable(
                f"no status from {self.path} within {timeout:g} s (is it running? the same "
                "ROS_DOMAIN_ID?)"
            ) from None
        deadline = time.monotonic() + TRANSITIONS_WAIT
        while proxy.publishers("transitions") == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        with self._lock:
            self.complete_path = proxy.publishers("transitions") > 0
        for service in ("command", "set_mode"):
            if not proxy.client(service).wait_for_service(timeout_sec=timeout):
                raise Unreachable(f"{self.path}/{service} did not appear within {timeout:g} s")

    def close(self) -> None:
        if self._proxy is not None:
            self._proxy.destroy()
        if self._session is not None:
            self._session.close()

    # -- what it shows -----------------------------------------------------------------------------
    def _on_change(self, path: str, topic: str, msg: Any) -> None:
        with self._lock:
            if topic == "status":
                self._on_status(msg)
            elif topic == "transitions":
                self._on_transition(msg)
        if topic == "admin":
            with self._admin_cond:
                self._admin = msg
                self._admin_received = self.clock()
                self._admin_cond.notify_all()

    def _on_status(self, msg: Status) -> None:
        self._status = msg
        if self._base is None:
            self._base = self._last = int(msg.sequence)
            self._history.add(_state(msg.state_current), int(msg.unit_mode_current), self._base)
            early, self._early = self._early, []
            for t in early:
                self._on_transition(t)
        elif not self.complete_path:
            self._history.add(
                _state(msg.state_current), int(msg.unit_mode_current), int(msg.sequence)
            )

    def _on_transition(self, msg: TransitionEvent) -> None:
        if self._base is None:
            self._early = [*self._early[-200:], msg]
            return
        if not self.complete_path or int(msg.sequence) <= self._last:
            return
        self._last = int(msg.sequence)
        self._history.add(_state(msg.to_state), int(msg.to_mode), self._last)

    def shown(self) -> History:
        return self._history

    def tags(self) -> Tags | None:
        msg = self._status
        if msg is None:
            return None
        return Tags(
            _state(msg.state_current),
            int(msg.unit_mode_current),
            int(msg.states_disabled),
            tuple(int(c) for c in msg.commands_valid),
            int(msg.sequence),
        )

    def admin(self, newer_than: float | None, timeout: float) -> AdminView | None:
        def fresh() -> bool:
            msg = self._admin
            return msg is not None and (newer_than is None or self._admin_received >= newer_than)

        with self._admin_cond:
            if not self._admin_cond.wait_for(fresh, timeout):
                return None
            msg, received = self._admin, self._admin_received
        assert msg is not None
        counts = [
            (int(c.count), int(c.acc_count))
            for c in (
                *msg.prod_processed_count,
                *msg.prod_defective_count,
                *msg.prod_consumed_count,
            )
        ]
        return AdminView(
            seconds(msg.stamp),
            received,
            list(msg.state_current_time),
            list(msg.state_cumulative_time),
            list(msg.mode_current_time),
            list(msg.mode_cumulative_time),
            counts,
        )

    # -- requests ----------------------------------------------------------------------------------
    def _call(self, service: str, timeout: float, **fields: Any) -> Reply:
        assert self._proxy is not None
        try:
            return reply_of(self._proxy.call_sync(service, timeout, **fields))
        except Unavailable as exc:
            raise Unreachable(str(exc)) from None

    def command(self, cmd: int, timeout: float) -> Reply:
        return self._call("command", timeout, command=int(cmd), source=SOURCE)

    def set_mode(self, mode: int, timeout: float) -> Reply:
        return self._call("set_mode", timeout, mode=int(mode), source=SOURCE)

    def reset_counters(self, timeout: float) -> Reply | None:
        assert self._proxy is not None
        if not self._proxy.client("reset_counters").wait_for_service(timeout_sec=min(timeout, 2.0)):
            return None
        return self._call("reset_counters", timeout, source=SOURCE)
