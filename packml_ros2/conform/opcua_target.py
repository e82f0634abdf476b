"""An OPC 30050 server as a conformance target: a PLC's PackML object, or our own OPC UA face.

It is reached as the PLC bridge reaches a PLC (:class:`packml_ros2.plc.link.Link`: endpoint,
browse path or node id, security policy and mode, certificates, user and password) and read as
the bridge reads it (:class:`packml_ros2.plc.mirror.Mirror`: the state from the three nested
state machines). The link follows every value a state machine takes (their monitored items keep
a queue), so every state the server passes through is shown. Refusals are status codes (the
standard has no reason codes): the run checks that a refusal is a Bad one.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from asyncua import ua
from asyncua.ua import status_codes

from ..core.config import UnitConfig
from ..core.numbers import Cmd, State
from ..opcua.nodeset import load
from ..plc.config import PlcConfig
from ..plc.link import Link, NotConnected, command_arguments
from ..plc.mirror import Mirror
from .target import AdminView, History, Reply, Tags, Unreachable

#: Seconds a state read without its inner machine's value waits for it (then it is taken).
INNER_WAIT = 0.3
TIMES = ("StateCurrentTime", "StateCumulativeTime", "ModeCurrentTime", "ModeCumulativeTime")
COUNTS = ("ProdProcessedCount", "ProdDefectiveCount", "ProdConsumedCount")


def _ints(value: Any) -> list[int]:
    """A time array as the server sent it, flattened (hostile: anything else is empty)."""
    out: list[int] = []
    stack = [value]
    while stack and len(out) < 10_000:
        v = stack.pop()
        if isinstance(v, list | tuple):
            stack.extend(reversed(v))
        elif isinstance(v, int) and not isinstance(v, bool):
            out.append(v)
        else:
            return []
    return out


def _counts(value: Any) -> list[tuple[int, int]]:
    out: list[tuple[int, int]] = []
    for item in value if isinstance(value, list) else []:
        if isinstance(item, dict):
            count, acc = item.get("Count"), item.get("AccCount")
            if isinstance(count, int) and isinstance(acc, int):
                out.append((count, acc))
    return out


class OpcuaTarget:
    """The PackML object of ``plc`` (an OPC 30050 server), whose rules ``unit`` declares."""

    face = "opcua"

    def __init__(
        self,
        plc: PlcConfig,
        unit: UnitConfig,
        strict_path: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        #: a server samples its values: a state shorter than its sampling interval may not reach
        #: the client, so a state not shown is judged only when asked (``strict_path``)
        self.complete_path = strict_path
        self.plc = plc
        self.where = plc.where()
        self.clock = clock
        self._history = History(clock)
        self._mirror = Mirror(unit, load())
        self._lock = threading.Lock()
        self._up = threading.Event()
        self._failed = ""
        self._lost = ""
        self._admin_at = 0.0
        self._admin_cond = threading.Condition()
        self._inner: threading.Timer | None = None
        self.link = Link(plc, self._connected, self._values, self._on_lost, self._on_failed)

    # -- connection --------------------------------------------------------------------------------
    def connect(self, timeout: float) -> None:
        self.link.start()
        deadline = time.monotonic() + timeout
        while not self._up.wait(0.05):
            if self._failed:
                raise Unreachable(f"{self.where}: {self._failed}")
            if time.monotonic() > deadline:
                raise Unreachable(f"{self.where}: no session within {timeout:g} s")

    def close(self) -> None:
        if self._inner is not None:
            self._inner.cancel()
        self.link.stop()

    def _on_failed(self, reason: str) -> None:
        self._failed = reason

    def _on_lost(self, reason: str) -> None:
        self._lost = reason
        self._up.clear()

    def _connected(self, values: dict[str, Any], methods: frozenset[str], detail: str) -> None:
        with self._lock:
            self._mirror.values = dict(values)
            self._take(self._mirror.read_state()[0])
            self._admin_at = self.clock()
        self._up.set()

    def _values(self, batch: dict[str, Any]) -> None:
        with self._lock:
            self._mirror.values.update(batch)
            state, settled = self._mirror.read_state(batch)
            if settled:
                self._take(state)
            else:  # the inner machine's value is on its way
                self._inner = threading.Timer(INNER_WAIT, self._reread)
                self._inner.daemon = True
                self._inner.start()
            if any(p.startswith("Admin/") for p in batch):
                with self._admin_cond:
                    self._admin_at = self.clock()
                    self._admin_cond.notify_all()

    def _reread(self) -> None:
        with self._lock:
            self._take(self._mirror.read_state()[0])

    def _take(self, state: State | None) -> None:
        mode = self._mode()
        if state is None:
            state = self._mirror.state if self._mirror.state is not State.UNDEFINED else None
        if state is None:
            return
        self._mirror.state = state
        self._mirror.mode = mode
        self._history.add(state, mode)

    def _mode(self) -> int:
        value = self._mirror.values.get("Status/UnitModeCurrent")
        return value if isinstance(value, int) and not isinstance(value, bool) else 0

    # -- what it shows -----------------------------------------------------------------------------
    def shown(self) -> History:
        return self._history

    def tags(self) -> Tags | None:
        last = self._history.last
        if last is None:
            return None
        return Tags(last.state, self._mode())

    def admin(self, newer_than: float | None, timeout: float) -> AdminView | None:
        values: Mapping[str, Any] = self._mirror.values
        if not any(f"Admin/{name}" in values for name in TIMES):
            return None
        with self._admin_cond:
            if not self._admin_cond.wait_for(
                lambda: newer_than is None or self._admin_at >= newer_than, timeout
            ):
                return None
            at = self._admin_at
        with self._lock:
            values = dict(self._mirror.values)
        times = [_ints(values.get(f"Admin/{name}")) for name in TIMES]
        counts = [c for name in COUNTS for c in _counts(values.get(f"Admin/{name}"))]
        return AdminView(at, at, times[0], times[1], times[2], times[3], counts)

    # -- requests ----------------------------------------------------------------------------------
    def _call(self, method: str, args: list[ua.Variant], timeout: float) -> Reply:
        if self._lost:
            raise Unreachable(f"{self.where}: {self._lost}")
        try:
            outcome = self.link.submit(self.link.call(method, args)).result(timeout)
        except NotConnected as exc:
            raise Unreachable(f"{self.where}: {exc}") from None
        except TimeoutError:
            raise Unreachable(f"{self.where}: {method} not answered within {timeout:g} s") from None
        text = outcome.text
        if text == status_codes.get_name_and_doc(outcome.status)[1]:
            text = ""  # the code's own description says nothing of this server's reason
        return Reply(outcome.good, outcome.name, text)

    def command(self, cmd: int, timeout: float) -> Reply:
        with self._lock:
            method = self._mirror.method_for(Cmd(cmd))
        return self._call(method, command_arguments(cmd == Cmd.START), timeout)

    def set_mode(self, mode: int, timeout: float) -> Reply:
        return self._call("SetUnitMode", [ua.Variant(int(mode), ua.VariantType.Int32)], timeout)

    def reset_counters(self, timeout: float) -> Reply | None:
        return None  # OPC 30050 v1.01 has no method for it
