"""The PLC bridge: a PackML machine in a PLC (OPC 30050 over OPC UA) as a unit of the cell.

Node ``/<cell>/<unit>``, one per PLC unit (a ``plc:`` block in the cell file), with the names,
types and QoS of :class:`packml_ros2.unit_node.UnitNode`, so the coordinator, the HMI, ``packml``,
the OPC UA server and ``packml record`` treat it like any other unit:

- the topics :mod:`packml_ros2.ros.interface` marks ``plc``: ``status`` (latched, DDS liveliness
  with ``unit_lease``), ``transitions``, ``admin``, ``alarms``, ``config`` and ``/diagnostics``
  (entry ``packml: <unit>``);
- every service the interface declares: ``command``, ``set_mode`` and the Trigger shortcuts (the
  OPC 30050 state machine methods and SetUnitMode), ``set_mach_speed`` (SetMachSpeed),
  ``set_unit_parameters`` (SetParameter), ``set_product`` (SetProduct), ``set_interlock`` (the
  bridge suspends and unsuspends the PLC, as a unit does), ``query_alarms`` (the PLC's Admin
  lists), ``set_remote_commands`` (the remote lock). What OPC 30050 has no method for (the
  services the interface declares with ``plc_lacks``: ``ack_alarms``, ``reset_alarms``,
  ``set_alarm``, ``reset_times``, ``reset_counters``, ``set_em_active``) is refused with
  NOT_SUPPORTED and a sentence.

A request is checked like a unit checks it, by the unit's rule book (command number, the remote
lock of parameter ``remote_commands_enabled`` over every request that changes the unit, the
rules of its state and mode, the interlock; :meth:`.mirror.Mirror.judge`), then the PLC's method
is called; the PLC's refusal (a Bad status code and its diagnostics) becomes the
unit's reason code and sentence (:func:`.mirror.plc_refusal`). Transitions, with their trigger
and source, come from :class:`.mirror.Mirror`.

**A PLC that is gone looks gone.** When the session ends or the PLC stays silent for ``lease``
(:mod:`.link`), the bridge withdraws its ``status``, ``transitions``, ``admin`` and ``alarms``
publishers, as a unit whose process died: DDS tells every status reader at once (presence), the
latched values disappear for new readers, and its ``/diagnostics`` entry turns STALE with the
reason (the coordinator takes the unit for lost at once). Requests are refused with
UNIT_UNAVAILABLE ("... not reachable since 10:42:07 (...)"). The link reconnects with back-off;
when it is back, the publishers are made again and the first transition is RESTART ("connected to
the PLC at ...").

The PLC unit's own stop reason and alarms are what the PLC says (Admin/StopReason, Admin/Alarm).
Run: ``plc_bridge <cell.yaml> <unit>`` (started by ``packml launch`` for every PLC unit).
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from asyncua import ua
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from packml_interfaces.msg import Admin, AlarmList, Count, Descriptor, Oee
from packml_interfaces.srv import (
    Command,
    QueryAlarms,
    SetInterlock,
    SetMachSpeed,
    SetMode,
    SetProduct,
    SetUnitParameters,
)
from rclpy.callback_groups import ReentrantCallbackGroup
from std_msgs.msg import Header, String

from .. import convert, run
from ..boundary import GuardedNode
from ..core import CellConfig, Cmd, UnitConfig, load_cell, state_name
from ..core import config as cfg
from ..core.alarms import select_events
from ..core.interlocks import interlock_refusal
from ..core.numbers import NUM_STATES, Mode, command_name
from ..core.packtags import EmView, RemoteInterfaceView, StatusView, compute_oee
from ..core.reasons import Reason
from ..core.rules import INTERLOCK_PATH, INTERLOCK_RESUME, INTERLOCK_SUSPEND, locked_refusal
from ..core.unit import Transition, Trigger
from ..opcua.nodeset import load
from ..remote_lock import RemoteLock
from ..ros import interface
from .config import PlcConfig, describe, parse_plc
from .link import Link, NotConnected, Outcome, command_arguments
from .mirror import Mirror, PlcSituation, plc_refusal

TICK = 0.1  # s: held-back state changes, the mode-change lamp, admin period
DIAGNOSTICS_PERIOD = 1.0
MODE_LAMP = 3.0  # s the mode_change_not_allowed flag stays up (as a unit's)
INTERLOCK_SOURCE = "interlock"
Answer = tuple[bool, int, str]


class PlcUnitNode(GuardedNode):
    """The bridge of PLC unit ``config`` (``plc``: its validated ``plc:`` block)."""

    def __init__(
        self,
        config: UnitConfig,
        plc: PlcConfig,
        *,
        unit_lease: float,
        source: str | None = None,
        **node_kwargs: Any,
    ) -> None:
        namespace = node_kwargs.pop("namespace", f"/{config.cell}" if config.cell else "/")
        super().__init__(config.name, namespace=namespace, **node_kwargs)
        self.config = config
        self.plc = plc
        self.unit_lease = unit_lease
        self.mirror = Mirror(config, load())
        self._lock = threading.RLock()
        self._group = ReentrantCallbackGroup()
        self._hardware_id = f"{config.cell}/{config.name}" if config.cell else config.name
        self._unit_pubs: dict[str, Any] = {}
        self._last: dict[str, Any] = {}  # the last message per topic (without its stamp)
        self._admin_at = 0.0
        self._mode_lamp_until = 0.0
        self._interlocks: dict[str, str] = {}  # source -> reason
        self._interlock_suspended = False
        self._interlock_busy = False
        self._closed = False
        self.connected_at: float | None = None
        self.lost_since: float | None = time.time()
        self.lost_reason = "not connected yet"
        self.retry_reason = ""
        self.remote_lock = RemoteLock(
            self,
            config.name,
            config.remote_commands_enabled,
            self._on_remote_lock,
            callback_group=self._group,
        )
        self.remote_enabled = config.remote_commands_enabled
        self.pub_diagnostics = interface.create_publisher(self, "/diagnostics")
        self.pub_config = interface.create_publisher(self, "config")
        if source is not None:
            self.pub_config.publish(
                String(
                    data=json.dumps(
                        {"unit": config.name, "cell_yaml": source, "plc": describe(plc)}
                    )
                )
            )
        self._create_services()
        self._timers = [
            self.create_timer(TICK, self._on_tick, callback_group=self._group),
            self.create_timer(
                DIAGNOSTICS_PERIOD, self._publish_diagnostics, callback_group=self._group
            ),
        ]
        self.link = Link(plc, self._on_connected, self._on_values, self._on_lost, self._on_failed)
        self.link.start()
        details = ", ".join(f"{k} {v}" for k, v in describe(plc).items())
        self.get_logger().info(f"PLC unit {self.get_fully_qualified_name()} up: {details}")

    # -- parameters --------------------------------------------------------------------------------
    def _on_remote_lock(self, enabled: bool) -> None:
        with self._lock:
            self.remote_enabled = enabled
            self._publish_status()

    # -- the link (its loop thread) ----------------------------------------------------------------
    def _on_connected(self, values: dict[str, Any], methods: frozenset[str], detail: str) -> None:
        with self._lock:
            if self._closed:
                return
            if self.connected_at is not None and self.lost_since is not None:
                detail += (
                    f"; back after {time.time() - self.lost_since:.1f} s (lost: {self.lost_reason})"
                )
            self.connected_at, self.lost_since, self.retry_reason = time.time(), None, ""
            self._interlock_suspended = False
            self._make_publishers()
            self._emit(self.mirror.connected(values, self._now(), detail))
            self._publish_all()
        self.get_logger().info(
            f"{detail}: {state_name(self.mirror.state)} in "
            f"{self.mirror.mode_name(self.mirror.mode)}"
        )
        self._reconcile_interlock()

    def _on_values(self, batch: dict[str, Any]) -> None:
        with self._lock:
            if self._closed or self.lost_since is not None:
                return
            self._emit(self.mirror.update(batch, self._now()))
            self._publish_all()
        self._reconcile_interlock()

    def _on_lost(self, reason: str) -> None:
        with self._lock:
            self.lost_since, self.lost_reason = time.time(), reason
            self._drop_publishers()
            self._publish_diagnostics()
        self.get_logger().warning(f"PLC lost: {reason} ({self.plc.where()}); reconnecting")

    def _on_failed(self, reason: str) -> None:
        with self._lock:
            changed = reason != self.retry_reason
            self.retry_reason = reason
            if self.connected_at is None:  # never connected: that is why it is not there
                self.lost_reason = reason
        if changed:
            self.get_logger().warning(f"PLC not reachable: {reason} ({self.plc.where()}); retrying")

    def gone(self) -> str:
        """Why the PLC cannot be asked now ('' = it can)."""
        if self.lost_since is None:
            return ""
        clock = time.strftime("%H:%M:%S", time.localtime(self.lost_since))
        why = self.lost_reason
        if self.retry_reason and self.retry_reason != why:
            why += f"; reconnecting: {self.retry_reason}"
        return f"the PLC of {self.config.name} ({self.plc.endpoint}) is not reachable since {clock} ({why})"

    # -- publishers --------------------------------------------------------------------------------
    def _make_publishers(self) -> None:
        if self._unit_pubs:
            return
        # the unit's outputs (a unit's config and /diagnostics stay while the PLC is gone)
        self._unit_pubs = {
            t.name: interface.create_publisher(self, t.name, lease=self.unit_lease)
            for t in interface.topics(interface.Role.OUTPUT, interface.Role.DERIVED)
            if t.plc
        }
        self._last.clear()

    def _drop_publishers(self) -> None:
        publishers, self._unit_pubs = self._unit_pubs, {}
        for publisher in publishers.values():
            self.destroy_publisher(publisher)
        self._last.clear()

    def _publish(self, topic: str, msg: Any, force: bool = False) -> None:
        """Publish ``msg`` on ``topic`` unless it equals the last one but for its stamp."""
        publisher = self._unit_pubs.get(topic)
        if publisher is None or not self.context.ok():
            return
        last = self._last.get(topic)
        if last is not None and not force:
            stamp, msg.stamp = msg.stamp, last.stamp
            if msg == last:
                return
            msg.stamp = stamp
        self._last[topic] = msg
        publisher.publish(msg)

    def _emit(self, transitions: Sequence[Transition]) -> None:
        modes = {n: m.name for n, m in self.config.modes.items()}
        for t in transitions:
            publisher = self._unit_pubs.get("transitions")
            if publisher is not None and self.context.ok():
                publisher.publish(convert.transition(self.config.name, t, modes))
            line = (
                f"{state_name(t.from_state)} -> {state_name(t.to_state)} ({t.trigger.name.lower()}"
                f"{', ' + command_name(t.command) if t.command else ''}, {t.source}"
                f"{': ' + t.detail if t.detail else ''})"
            )
            # one call site per severity: rclpy binds a call site to the severity it first logged
            # at and raises ValueError when the same site logs at another
            if t.trigger == Trigger.ALARM:
                self.get_logger().warning(line)
            else:
                self.get_logger().info(line)

    def _publish_all(self) -> None:
        self._publish_status()
        self._publish_admin()
        self._publish_alarms()

    def _publish_status(self) -> None:
        if self._unit_pubs:
            self._publish("status", convert.status(self.status_view()))

    def status_view(self) -> StatusView:
        m = self.mirror
        v = m.values
        alarms = m.alarms()
        stop = m.stop_reason()
        requested_mode = m.mode_request[0] if m.mode_request is not None else m.mode
        return StatusView(
            time=self._now(),
            unit=self.config.name,
            unit_mode_current=m.mode,
            unit_mode_requested=requested_mode,
            unit_mode_change_in_process=bool(v.get("Status/UnitModeChangeInProcess")),
            state_current=int(m.state),
            state_requested=int(m.state_requested()),
            state_change_in_process=bool(
                v.get("Status/StateChangeInProcess", m.state_requested() != m.state)
            ),
            mach_speed=_float(v.get("Status/MachSpeed")),
            cur_mach_speed=_float(v.get("Status/CurMachSpeed")),
            material_interlock=1 if v.get("Status/MaterialInterlocked") else 0,
            blocked=bool(v.get("Status/EquipmentBlocked")),
            starved=bool(v.get("Status/EquipmentStarved")),
            remote_interface=tuple(_remote(r) for r in _list(v.get("Status/RemoteParameter"))),
            parameter=tuple(_descriptor(d) for d in _list(v.get("Status/Parameter"))),
            product=tuple(_product(p) for p in _list(v.get("Status/Product"))),
            cntrl_cmd=m.cntrl_cmd,
            command_unit_mode=requested_mode,
            command_mach_speed=m.command_mach_speed,
            state_current_name=state_name(m.state),
            unit_mode_current_name=m.mode_name(m.mode),
            sequence=m.sequence,
            states_disabled=m.states_disabled(),
            commands_valid=tuple(int(c) for c in m.valid_commands()),
            mode_change_not_allowed=time.monotonic() < self._mode_lamp_until,
            remote_commands_enabled=self.remote_enabled,
            time_rollover_warning=False,
            equipment=(
                EmView(
                    "plc",
                    True,
                    self.lost_since is None,
                    True,
                    False,
                    0,
                    0,
                    bool(v.get("Status/EquipmentBlocked")),
                    bool(v.get("Status/EquipmentStarved")),
                    0,
                ),
            ),
            active_alarms=sum(1 for a in alarms if a.trigger),
            unacknowledged_alarms=sum(1 for a in alarms if not a.acknowledged),
            alarm_banner=m.banner(),
            stop_reason_id=stop.id if stop is not None else 0,
        )

    def _publish_admin(self, force: bool = False) -> None:
        if not self._unit_pubs:
            return
        m = self.mirror
        v = m.values
        stop = m.stop_reason()
        # arrays indexed by mode (and state): as long as the unit's highest mode needs, also when
        # the PLC does not have them (they are Optional in OPC 30050)
        modes = max(self.config.modes, default=Mode.PRODUCTION) + 1
        mode_cum = _ints(v.get("Admin/ModeCumulativeTime"), modes)
        state_cum = _ints(v.get("Admin/StateCumulativeTime"), modes * NUM_STATES)
        processed = [_count(c) for c in _list(v.get("Admin/ProdProcessedCount"))]
        defective = [_count(c) for c in _list(v.get("Admin/ProdDefectiveCount"))]
        design = _float(v.get("Admin/MachDesignSpeed")) or self.config.mach_design_speed
        oee = Oee()
        if len(mode_cum) > Mode.PRODUCTION and len(state_cum) >= (Mode.PRODUCTION + 1) * NUM_STATES:
            o = compute_oee(
                [float(x) for x in mode_cum],
                [float(x) for x in state_cum],
                0.0,
                sum(c.count for c in processed),
                sum(c.count for c in defective),
                design,
            )
            oee = Oee(**{k: getattr(o, k) for k in Oee.get_fields_and_field_types()})
        msg = Admin(
            stamp=convert.stamp(self._now()),
            unit=self.config.name,
            parameter=[_descriptor_msg(d) for d in _list(v.get("Admin/Parameter"))],
            alarm=[convert.alarm(a) for a in m.alarms()],
            alarm_extent=_int(v.get("Admin/AlarmExtent"), len(m.alarms())),
            alarm_history=[convert.alarm(a) for a in m.history()],
            alarm_history_extent=_int(v.get("Admin/AlarmHistoryExtent"), len(m.history())),
            stop_reason=convert.alarm(stop),
            stop_reason_extent=1 if stop is not None else 0,
            warning=[convert.alarm(a) for a in m.warnings()],
            warning_extent=_int(v.get("Admin/WarningExtent"), len(m.warnings())),
            mode_current_time=_ints(v.get("Admin/ModeCurrentTime"), modes),
            mode_cumulative_time=mode_cum,
            state_current_time=_ints(v.get("Admin/StateCurrentTime"), modes * NUM_STATES),
            state_cumulative_time=state_cum,
            prod_consumed_count=[_count(c) for c in _list(v.get("Admin/ProdConsumedCount"))],
            prod_processed_count=processed,
            prod_defective_count=defective,
            acc_time_since_reset=_int(v.get("Admin/AccTimeSinceReset"), 0),
            mach_design_speed=design,
            states_disabled=m.states_disabled(),
            plc_date_time=[0] * 7,  # the PLC's clock is not part of OPC 30050
            oee=oee,
        )
        self._publish("admin", msg, force)
        self._admin_at = time.monotonic()

    def _publish_alarms(self) -> None:
        if not self._unit_pubs:
            return
        m = self.mirror
        active = sorted((a for a in m.alarms() if a.trigger), key=lambda a: a.time)
        first = active[0] if active else None
        by_category = [next((a for a in active if a.category == c), None) for c in range(10)]
        self._publish(
            "alarms",
            AlarmList(
                stamp=convert.stamp(self._now()),
                unit=self.config.name,
                alarms=[convert.alarm(a) for a in m.alarms()],
                warnings=[convert.alarm(a) for a in m.warnings()],
                first_out=convert.alarm(first),
                first_out_by_category=[convert.alarm(a) for a in by_category],
                banner=m.banner(),
            ),
        )

    def _publish_diagnostics(self) -> None:
        with self._lock:
            if self._closed or not self.context.ok():
                return
            m = self.mirror
            values = [KeyValue(key=k, value=v) for k, v in describe(self.plc).items()]
            if self.lost_since is None:
                active = [a for a in m.alarms() if a.trigger]
                level = DiagnosticStatus.ERROR if active else DiagnosticStatus.OK
                message = m.banner() or state_name(m.state)
                values += [
                    KeyValue(key="link", value="connected"),
                    KeyValue(key="state", value=state_name(m.state)),
                    KeyValue(key="mode", value=m.mode_name(m.mode)),
                    KeyValue(key="sequence", value=str(m.sequence)),
                ]
            else:
                level = DiagnosticStatus.STALE
                message = self.gone()
                values.append(KeyValue(key="link", value="lost"))
            status = DiagnosticStatus(
                level=level,
                name=f"packml: {self.config.name}",
                message=message,
                hardware_id=self._hardware_id,
                values=values,
            )
            header = Header(stamp=self.get_clock().now().to_msg())
            self.pub_diagnostics.publish(DiagnosticArray(header=header, status=[status]))

    # -- timers ------------------------------------------------------------------------------------
    def _on_tick(self) -> None:
        with self._lock:
            if self._closed or self.lost_since is not None:
                return
            self._emit(self.mirror.tick(self._now()))
            self._publish_status()  # also ends the mode-change lamp
            if time.monotonic() - self._admin_at >= self.config.admin_period:
                self._publish_admin(force=True)
        self._reconcile_interlock()

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    # -- services ----------------------------------------------------------------------------------
    def _create_services(self) -> None:
        """Every service :mod:`..ros.interface` declares: the ones OPC 30050 lacks refused."""
        handlers: dict[str, Callable[[Any, Any], Any]] = {
            "command": self._srv_command,
            "set_mode": self._srv_set_mode,
            "set_mach_speed": self._srv_set_mach_speed,
            "set_unit_parameters": self._srv_set_parameters,
            "set_product": self._srv_set_product,
            "set_interlock": self._srv_set_interlock,
            "query_alarms": self._srv_query_alarms,
        }
        interface.create_services(
            self,
            handlers,
            self._srv_trigger,
            self._srv_unsupported,
            skip=[RemoteLock.SERVICE],
            callback_group=self._group,
        )

    def _call(self, method: str, args: Sequence[ua.Variant]) -> Outcome:
        """Call a method of the PLC from a service thread (blocks it, never the executor)."""
        try:
            return self.link.submit(self.link.call(method, args)).result(
                self.plc.call_timeout + 1.0
            )
        except NotConnected:
            return Outcome(
                ua.StatusCodes.BadNoCommunication, "BadNoCommunication", self.gone() or "no session"
            )
        except TimeoutError:
            return Outcome(
                ua.StatusCodes.BadTimeout,
                "BadTimeout",
                f"no answer within {self.plc.call_timeout:g} s",
            )

    def _usable(self, what: str, source: str) -> tuple[int, str] | None:
        """The refusal every request that changes the unit gets when the source is locked out
        (the rule book's remote lock) or the PLC is gone."""
        locked = locked_refusal(what, source, self.remote_enabled, self.config.name)
        if locked is not None:
            return locked.reason, locked.message
        gone = self.gone()
        if gone:
            return Reason.UNIT_UNAVAILABLE, f"{what} refused: {gone}"
        return None

    def _situation(self, trigger: Trigger) -> PlcSituation:
        """What the rule book's guards read now (the interlock's own commands pass it)."""
        held = () if trigger == Trigger.INTERLOCK else tuple(self._interlocks.values())
        return PlcSituation(self.remote_enabled, self.mirror.mode_change_in_process(), held)

    def command(
        self, cmd: int, source: str, trigger: Trigger = Trigger.COMMAND, detail: str = ""
    ) -> tuple[bool, int, str, int, int]:
        """Send a state command: (accepted, result, message, state_current, state_requested)."""
        with self._lock:
            m = self.mirror
            name = command_name(cmd) if 1 <= cmd <= 10 else str(cmd)
            gone = self.gone() if 1 <= cmd <= 10 else ""
            refused = (
                (Reason.UNIT_UNAVAILABLE, f"{name} refused: {gone}")
                if gone
                else m.judge(cmd, source, self._situation(trigger))
            )
            if refused is not None:
                return False, int(refused[0]), refused[1], int(m.state), int(m.state_requested())
            command = Cmd(cmd)
            method = m.method_for(command)
            if not self.link.offers(method):
                return (
                    False,
                    int(Reason.NOT_SUPPORTED),
                    f"{name} refused: the PLC's object has no method {method}",
                    int(m.state),
                    int(m.state_requested()),
                )
            frm, chain = m.state, m.reach(m.state, command)
            entry = m.expect(command, source, self._now(), trigger, detail)
        outcome = self._call(method, command_arguments(command is Cmd.START))
        with self._lock:
            m = self.mirror
            if not outcome.good:
                m.forget(entry)
                reason, text = plc_refusal(name, m.where(), outcome.name, outcome.text)
                self.get_logger().warning(f"{text} (from {source})")
                return False, int(reason), text, int(m.state), int(m.state_requested())
            message = f"{name} accepted: {state_name(frm)} -> {state_name(chain[0])}"
            return True, int(Reason.ACCEPTED), message, int(m.state), int(chain[-1])

    def _srv_command(self, req: Command.Request, resp: Command.Response) -> Command.Response:
        (resp.accepted, resp.result, resp.message, resp.state_current, resp.state_requested) = (
            self.command(req.command, req.source or "operator")
        )
        return resp

    def _srv_trigger(self, cmd: Cmd, req: Any, resp: Any) -> Any:
        accepted, _, message, _, _ = self.command(int(cmd), "operator")
        resp.success, resp.message = accepted, message
        return resp

    def set_mode(self, mode: int | str, source: str) -> tuple[bool, int, str, int]:
        with self._lock:
            m = self.mirror
            mode_def = (
                self.config.mode_by_name(mode)
                if isinstance(mode, str)
                else self.config.modes.get(mode)
            )
            if mode_def is None:
                known = ", ".join(f"{n} {d.name}" for n, d in sorted(self.config.modes.items()))
                return (
                    False,
                    int(Reason.MODE_UNKNOWN),
                    f"mode {mode} is not configured (configured: {known})",
                    m.mode,
                )
            what = f"mode change {m.mode_name(m.mode)} -> {mode_def.name}"
            refused = self._usable(what, source)
            if refused is not None:
                return False, int(refused[0]), refused[1], m.mode
            m.mode_request = (mode_def.number, source, self._now())
        outcome = self._call("SetUnitMode", [ua.Variant(mode_def.number, ua.VariantType.Int32)])
        with self._lock:
            m = self.mirror
            if not outcome.good:
                m.mode_request = None
                reason, text = plc_refusal(what, m.where(), outcome.name, outcome.text, mode=True)
                if reason == Reason.MODE_CHANGE_NOT_ALLOWED:
                    self._mode_lamp_until = time.monotonic() + MODE_LAMP
                    self._publish_status()
                return False, int(reason), text, m.mode
            self._publish_status()
            return True, int(Reason.ACCEPTED), f"{what} accepted", m.mode

    def _srv_set_mode(self, req: SetMode.Request, resp: SetMode.Response) -> SetMode.Response:
        mode: int | str = req.mode_name if req.mode_name else req.mode
        resp.accepted, resp.result, resp.message, resp.mode_current = self.set_mode(
            mode, req.source or "operator"
        )
        return resp

    def _request(
        self, what: str, source: str, method: str, args: Callable[[], list[ua.Variant]]
    ) -> Answer:
        """A request that is one method call of the unit object (speed, parameters, product)."""
        with self._lock:
            refused = self._usable(what, source)
            if refused is not None:
                return False, int(refused[0]), refused[1]
            where = self.mirror.where()
        try:
            arguments = args()
        except AttributeError:
            return (
                False,
                int(Reason.NOT_SUPPORTED),
                f"{what} refused: the PLC's data types were not read",
            )
        outcome = self._call(method, arguments)
        if not outcome.good:
            reason, text = plc_refusal(what, where, outcome.name, outcome.text)
            return False, int(reason), text
        return True, int(Reason.ACCEPTED), f"{what} accepted"

    def _srv_set_mach_speed(
        self, req: SetMachSpeed.Request, resp: SetMachSpeed.Response
    ) -> SetMachSpeed.Response:
        what = f"SetMachSpeed({req.mach_speed:g})"
        resp.accepted, resp.result, resp.message = self._request(
            what,
            req.source or "operator",
            "SetMachSpeed",
            lambda: [ua.Variant(float(req.mach_speed), ua.VariantType.Float)],
        )
        if resp.accepted:
            with self._lock:
                self.mirror.command_mach_speed = float(req.mach_speed)
        resp.mach_speed = _float(self.mirror.values.get("Status/MachSpeed"))
        return resp

    def _srv_set_parameters(
        self, req: SetUnitParameters.Request, resp: SetUnitParameters.Response
    ) -> SetUnitParameters.Response:
        resp.accepted, resp.result, resp.message = self._request(
            "SetParameter",
            req.source or "operator",
            "SetParameter",
            lambda: [
                ua.Variant(
                    [_ua_descriptor(d) for d in req.parameter],
                    ua.VariantType.ExtensionObject,
                    is_array=True,
                )
            ],
        )
        return resp

    def _srv_set_product(
        self, req: SetProduct.Request, resp: SetProduct.Response
    ) -> SetProduct.Response:
        resp.accepted, resp.result, resp.message = self._request(
            "SetProduct",
            req.source or "operator",
            "SetProduct",
            lambda: [
                ua.Variant(
                    [_ua_product(p) for p in req.product],
                    ua.VariantType.ExtensionObject,
                    is_array=True,
                )
            ],
        )
        return resp

    def _srv_query_alarms(
        self, req: QueryAlarms.Request, resp: QueryAlarms.Response
    ) -> QueryAlarms.Response:
        with self._lock:
            m = self.mirror
            events = m.history() if req.history else m.alarms()
            if req.include_warnings and not req.history:
                events = events + m.warnings()
        category = req.category if req.filter_category else None
        sort = convert.QUERY_SORTS.get(req.sort, "time")
        events = select_events(events, req.active_only, category, sort)
        resp.alarms = [convert.alarm(e) for e in events]
        resp.count = len(events)
        return resp

    def _srv_unsupported(self, what: str, req: Any, resp: Any) -> Any:
        resp.accepted, resp.result = False, int(Reason.NOT_SUPPORTED)
        text = (
            f"{self.config.name} is a PLC unit: {what} is done at the PLC "
            "(OPC 30050 has no method for it)"
        )
        setattr(resp, "message_out" if hasattr(resp, "message_out") else "message", text)
        return resp

    # -- interlocks --------------------------------------------------------------------------------
    def _srv_set_interlock(
        self, req: SetInterlock.Request, resp: SetInterlock.Response
    ) -> SetInterlock.Response:
        source = req.source or "operator"
        with self._lock:
            refused = interlock_refusal(
                self._interlocks, req.active, source, self.remote_enabled, self.config.name
            )
            if refused is not None:
                resp.accepted, resp.result, resp.message = (
                    False,
                    int(refused.reason),
                    refused.message,
                )
                return resp
            if req.active:
                self._interlocks[source] = req.reason or source
                resp.message = f"interlock from {source} on {self.config.name}: {req.reason}"
            else:
                self._interlocks.pop(source, None)
                resp.message = f"interlock from {source} on {self.config.name} cleared"
            resp.accepted, resp.result = True, int(Reason.ACCEPTED)
        self._reconcile_interlock()
        return resp

    def _reconcile_interlock(self) -> None:
        """Suspend the PLC while an interlock holds it in Execute, unsuspend it when the last one
        is cleared (only what the bridge suspended), like a unit's interlock_reaction."""
        with self._lock:
            if (
                self._interlock_busy
                # sent and accepted: its transition has not shown yet
                or any(e.trigger == Trigger.INTERLOCK for e in self.mirror.expected)
                or self.lost_since is not None
                or not self.config.interlock_reaction
            ):
                return
            state = self.mirror.state  # (the unit's rule: core.rules INTERLOCK_*)
            if self._interlocks and state is INTERLOCK_SUSPEND[0]:
                cmd, detail = INTERLOCK_SUSPEND[1], "; ".join(self._interlocks.values())
                source = next(iter(self._interlocks))
            elif (
                not self._interlocks and self._interlock_suspended and state is INTERLOCK_RESUME[0]
            ):
                cmd, detail, source = INTERLOCK_RESUME[1], "interlock cleared", INTERLOCK_SOURCE
            else:
                if state not in INTERLOCK_PATH:
                    self._interlock_suspended = False
                return
            self._interlock_busy = True

        def send() -> None:
            try:
                accepted, _, message, _, _ = self.command(
                    int(cmd), source, Trigger.INTERLOCK, detail
                )
                with self._lock:
                    if accepted:
                        self._interlock_suspended = cmd is INTERLOCK_SUSPEND[1]
                    else:
                        self.get_logger().warning(f"interlock: {message}")
            finally:
                with self._lock:
                    self._interlock_busy = False

        threading.Thread(target=send, name="plc-interlock", daemon=True).start()

    # -- shutdown ----------------------------------------------------------------------------------
    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        link = getattr(self, "link", None)
        if link is not None:
            link.stop()
        for timer in self._timers:
            self.destroy_timer(timer)

    def destroy_node(self) -> None:
        self.close()
        super().destroy_node()


# -- plain PLC values -> messages ------------------------------------------------------------------
def _list(value: Any) -> list[Any]:
    return value if isinstance(value, list) else []


def _float(value: Any) -> float:
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0


def _int(value: Any, default: int) -> int:
    return int(value) if isinstance(value, int) and not isinstance(value, bool) else default


def _ints(value: Any, length: int = 0) -> list[int]:
    """An Int32 array (a matrix flattened by rows), padded with zeros to ``length``."""
    out: list[int] = []
    for item in _list(value):
        if isinstance(item, list):
            out.extend(_ints(item))
        elif isinstance(item, int):
            out.append(int(item))
    return out + [0] * (length - len(out))


def _text(value: Any) -> str:
    return value if isinstance(value, str) else ""


def _descriptor(d: Any) -> cfg.Descriptor:
    d = d if isinstance(d, Mapping) else {}
    return cfg.Descriptor(
        _int(d.get("ID"), 0), _text(d.get("Name")), _text(d.get("Unit")), _float(d.get("Value"))
    )


def _descriptor_msg(d: Any) -> Descriptor:
    return convert.descriptor(_descriptor(d))


def _product(p: Any) -> cfg.Product:
    p = p if isinstance(p, Mapping) else {}
    return cfg.Product(
        _int(p.get("ProductID"), 0),
        tuple(_descriptor(d) for d in _list(p.get("ProcessVariables"))),
        tuple(
            cfg.Ingredient(
                _int(i.get("IngredientID"), 0),
                tuple(_descriptor(d) for d in _list(i.get("Parameter"))),
            )
            for i in _list(p.get("Ingredients"))
            if isinstance(i, Mapping)
        ),
    )


def _remote(r: Any) -> RemoteInterfaceView:
    r = r if isinstance(r, Mapping) else {}
    return RemoteInterfaceView(
        _int(r.get("Number"), 0),
        _int(r.get("ControlCmdNumber"), 0),
        _int(r.get("CmdValue"), 0),
        tuple(_descriptor(d) for d in _list(r.get("Parameter"))),
    )


def _count(c: Any) -> Count:
    c = c if isinstance(c, Mapping) else {}
    return Count(
        id=_int(c.get("ID"), 0),
        name=_text(c.get("Name")),
        unit=_text(c.get("Unit")),
        count=_int(c.get("Count"), 0),
        acc_count=_int(c.get("AccCount"), 0),
    )


def _eu(unit: str) -> Any:
    return ua.EUInformation(DisplayName=ua.LocalizedText(unit), Description=ua.LocalizedText(unit))


def _ua_descriptor(d: Descriptor) -> Any:
    cls = ua.PackMLDescriptorDataType  # generated from the PLC's types
    return cls(ID=d.id, Name=d.name, Unit=_eu(d.unit), Value=float(d.value))


def _ua_product(p: Any) -> Any:
    cls = ua.PackMLProductDataType
    ingredient = ua.PackMLIngredientsDataType
    return cls(
        ProductID=p.product_id,
        ProcessVariables=[_ua_descriptor(d) for d in p.process_variables],
        Ingredients=[
            ingredient(
                IngredientID=i.ingredient_id, Parameter=[_ua_descriptor(d) for d in i.parameter]
            )
            for i in p.ingredients
        ],
    )


# -- running ---------------------------------------------------------------------------------------
def make_node(
    cell: CellConfig, unit: str, source: str | None = None, **node_kwargs: Any
) -> PlcUnitNode:
    """The bridge of ``unit`` (its ``plc:`` block is validated here: ConfigError)."""
    plc = parse_plc(cell, unit)
    return PlcUnitNode(
        cell.units[unit], plc, unit_lease=cell.coordinator.unit_lease, source=source, **node_kwargs
    )


def main(argv: Sequence[str] | None = None) -> int:
    import rclpy

    args = run.init(argv)
    if len(args) != 2 or args[0] in ("-h", "--help"):
        print(__doc__)
        rclpy.try_shutdown()
        return 0 if args and args[0] in ("-h", "--help") else 2
    try:
        cell = load_cell(args[0])
        if args[1] not in cell.units:
            raise ValueError(f"{args[0]} has no unit {args[1]!r} (units: {', '.join(cell.units)})")
        if cell.units[args[1]].plc is None:
            raise ValueError(
                f"{args[1]} is not a PLC unit (no plc: block): run unit_node {args[0]} {args[1]}"
            )
        node = make_node(cell, args[1], Path(args[0]).read_text(encoding="utf-8"))
    except Exception as exc:  # ConfigError and friends: one readable message, exit 2
        print(f"plc_bridge: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    return run.spin([node], threads=4, on_shutdown=node.close)


if __name__ == "__main__":
    sys.exit(main())
