"""A PackML unit written as another vendor would: the packml_interfaces ROS interface served by
its own small TR88-2022 state machine, without the package's engine or rule book (only the
interface declaration, ``packml_ros2.ros.interface``, and the process plumbing of
``packml_ros2.run``).

Tests use it as a target of ``packml conform``: as it is, it must pass; with seeded faults it
must fail.

Usage::

    python test/conform/foreign_unit.py '{"cell": "c", "unit": "u", "dwell": 0.1, "rate": 10,
                                          "faults": []}'

- ``cell``, ``unit``: the node is ``/<cell>/<unit>``.
- ``dwell``: seconds in each acting state (Execute excepted) before its State Complete; 0 = at once.
- ``rate``: pieces per second counted in Execute (``Admin.prod_processed_count[0]``).
- ``faults``: deliberate violations, any of :data:`FAULTS`.

Prints ``ready`` (one line, flushed) once its services exist; exits 0 on SIGINT/SIGTERM.

Serves ``command``, ``set_mode``, ``reset_counters``, ``reset_times`` and the Trigger shortcuts
(``reset`` ... ``complete``); publishes ``status``, ``transitions`` and ``admin`` (on every
transition and every :data:`ADMIN_PERIOD` seconds). Nothing else of the interface (alarms, EMs,
speed, parameters): a unit without them.
"""

from __future__ import annotations

import json
import math
import sys
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import rclpy
from packml_interfaces.msg import Admin, Count, Result, Status, TransitionEvent
from packml_interfaces.srv import ResetTimes
from rclpy.node import Node

from packml_ros2 import run
from packml_ros2.ros import interface

# -- the model (ISA-TR88.00.02-2022) ---------------------------------------------------------------
STATE_NAMES: dict[int, str] = {
    1: "CLEARING", 2: "STOPPED", 3: "STARTING", 4: "IDLE", 5: "SUSPENDED", 6: "EXECUTE",
    7: "STOPPING", 8: "ABORTING", 9: "ABORTED", 10: "HOLDING", 11: "HELD", 12: "UNHOLDING",
    13: "SUSPENDING", 14: "UNSUSPENDING", 15: "RESETTING", 16: "COMPLETING", 17: "COMPLETE",
}  # fmt: skip
ST = {name: number for number, name in STATE_NAMES.items()}
COMMAND_NAMES: dict[int, str] = {
    1: "RESET", 2: "START", 3: "STOP", 4: "HOLD", 5: "UNHOLD", 6: "SUSPEND", 7: "UNSUSPEND",
    8: "ABORT", 9: "CLEAR", 10: "COMPLETE",
}  # fmt: skip
CMD = {name: number for number, name in COMMAND_NAMES.items()}
ALL_STATES = frozenset(STATE_NAMES)
NUM_MODES, NUM_STATES = 32, 18  # Admin.NUM_MODES, Admin.NUM_STATES


def _states(*names: str) -> frozenset[int]:
    return frozenset(ST[n] for n in names)


#: command -> (the states it is valid in, the state it leads to first)
COMMANDS: dict[int, tuple[frozenset[int], int]] = {
    CMD["RESET"]: (_states("STOPPED", "COMPLETE"), ST["RESETTING"]),
    CMD["START"]: (_states("IDLE"), ST["STARTING"]),
    CMD["STOP"]: (ALL_STATES - _states("STOPPING", "STOPPED", "ABORTING", "ABORTED", "CLEARING"),
                  ST["STOPPING"]),
    CMD["HOLD"]: (_states("EXECUTE", "SUSPENDED"), ST["HOLDING"]),
    CMD["UNHOLD"]: (_states("HELD"), ST["UNHOLDING"]),
    CMD["SUSPEND"]: (_states("EXECUTE"), ST["SUSPENDING"]),
    CMD["UNSUSPEND"]: (_states("SUSPENDED"), ST["UNSUSPENDING"]),
    CMD["ABORT"]: (ALL_STATES - _states("ABORTING", "ABORTED"), ST["ABORTING"]),
    CMD["CLEAR"]: (_states("ABORTED"), ST["CLEARING"]),
    CMD["COMPLETE"]: (_states("EXECUTE", "HELD", "SUSPENDED"), ST["COMPLETING"]),
}  # fmt: skip
#: acting state -> where its State Complete leads (Execute is not here: it runs until commanded)
STATE_COMPLETE: dict[int, int] = {
    ST["CLEARING"]: ST["STOPPED"], ST["STARTING"]: ST["EXECUTE"], ST["STOPPING"]: ST["STOPPED"],
    ST["ABORTING"]: ST["ABORTED"], ST["HOLDING"]: ST["HELD"], ST["UNHOLDING"]: ST["EXECUTE"],
    ST["SUSPENDING"]: ST["SUSPENDED"], ST["UNSUSPENDING"]: ST["EXECUTE"],
    ST["RESETTING"]: ST["IDLE"], ST["COMPLETING"]: ST["COMPLETE"],
}  # fmt: skip
TIMED = frozenset(STATE_COMPLETE)  # the acting states that end by themselves after ``dwell``


@dataclass(frozen=True)
class Mode:
    number: int
    name: str
    disabled: frozenset[int]

    @property
    def mask(self) -> int:
        return sum(1 << s for s in self.disabled)


MODES: dict[int, Mode] = {
    1: Mode(1, "PRODUCTION", frozenset()),
    2: Mode(2, "MAINTENANCE", _states("SUSPENDING", "SUSPENDED", "UNSUSPENDING")),
    3: Mode(3, "MANUAL", _states("HOLDING", "HELD", "UNHOLDING", "SUSPENDING", "SUSPENDED",
                                 "UNSUSPENDING", "COMPLETING", "COMPLETE")),
}  # fmt: skip
#: mode changes are accepted only in these states (and not into a mode that disables the state)
MODE_CHANGE_IN = _states("STOPPED", "IDLE", "ABORTED")


def skip_through(first: int, disabled: frozenset[int]) -> tuple[int, list[int]]:
    """Where the unit ends up when sent to ``first``: disabled acting states are passed through
    to their State Complete successor. (final state, skipped states)"""
    state, skipped = first, []
    while state in disabled and state in STATE_COMPLETE:
        skipped.append(state)
        state = STATE_COMPLETE[state]
    return state, skipped


def heading_for(state: int, disabled: frozenset[int]) -> int:
    """StateRequested: the wait state (or Execute) ``state`` settles in if nothing intervenes."""
    while state in STATE_COMPLETE:
        state, _ = skip_through(STATE_COMPLETE[state], disabled)
    return state


def judge(state: int, mode: Mode, cmd: int) -> tuple[int, int, list[int]]:
    """(Result code, final state, skipped states) of command ``cmd`` in ``state`` and ``mode``."""
    if cmd not in COMMANDS:
        return Result.UNKNOWN_COMMAND, state, []
    valid_in, first = COMMANDS[cmd]
    if state not in valid_in:
        return Result.COMMAND_NOT_ALLOWED, state, []
    final, skipped = skip_through(first, mode.disabled)
    if final in mode.disabled:
        return Result.STATE_DISABLED, final, skipped
    return Result.ACCEPTED, final, skipped


def valid_commands(state: int, mode: Mode) -> list[int]:
    return [c for c in COMMANDS if judge(state, mode, c)[0] == Result.ACCEPTED]


# -- the node ----------------------------------------------------------------------------------
#: the deliberate violations a test can seed
FAULTS = frozenset({"counters_not_reset", "no_reason", "wrong_disabled_mask", "sequence_frozen"})
ADMIN_PERIOD = 0.5  # s
RESEND_PERIOD, RESEND_WINDOW = 0.05, 10.0  # s: a response dropped for a client not yet discovered


@dataclass(frozen=True)
class Options:
    cell: str = "c"
    unit: str = "u"
    dwell: float = 0.1
    rate: float = 10.0
    faults: frozenset[str] = frozenset()

    @classmethod
    def parse(cls, text: str) -> Options:
        raw = json.loads(text) if text.strip() else {}
        if not isinstance(raw, dict):
            raise ValueError("options: a JSON object expected")
        unknown = set(raw) - {"cell", "unit", "dwell", "rate", "faults"}
        if unknown:
            raise ValueError(f"unknown options: {', '.join(sorted(unknown))}")
        faults = frozenset(raw.get("faults", ()))
        if faults - FAULTS:
            raise ValueError(f"unknown faults: {', '.join(sorted(faults - FAULTS))} "
                             f"(known: {', '.join(sorted(FAULTS))})")  # fmt: skip
        return cls(str(raw.get("cell", "c")), str(raw.get("unit", "u")),
                   float(raw.get("dwell", 0.1)), float(raw.get("rate", 10)), faults)  # fmt: skip


class Clocks:
    """Mode and state times in float seconds (time.monotonic), published floored."""

    def __init__(self, now: float, mode: int, state: int) -> None:
        self.mode, self.state = mode, state
        self.mode_cumulative = [0.0] * NUM_MODES
        self.state_cumulative = [0.0] * (NUM_MODES * NUM_STATES)
        self.acc = 0.0
        self.closed_at = now  # the cumulative figures are as of this instant
        self.mode_entered = self.state_entered = now

    def close(self, now: float) -> None:
        dt = max(0.0, now - self.closed_at)
        self.mode_cumulative[self.mode] += dt
        self.state_cumulative[self.mode * NUM_STATES + self.state] += dt
        self.acc += dt
        self.closed_at = now

    def enter(self, now: float, mode: int, state: int) -> None:
        self.close(now)
        if mode != self.mode:
            self.mode_entered = now
        self.mode, self.state, self.state_entered = mode, state, now

    def reset(self, now: float, everything: bool) -> None:
        self.close(now)
        if everything:
            self.mode_cumulative = [0.0] * NUM_MODES
            self.state_cumulative = [0.0] * (NUM_MODES * NUM_STATES)
            self.acc = 0.0
        else:
            m = self.mode
            self.mode_cumulative[m] = 0.0
            self.state_cumulative[m * NUM_STATES : (m + 1) * NUM_STATES] = [0.0] * NUM_STATES
        self.mode_entered = self.state_entered = now

    def fill(self, admin: Any, now: float) -> None:
        dt = max(0.0, now - self.closed_at)
        here = self.mode * NUM_STATES + self.state
        mode_current = [0] * NUM_MODES
        mode_current[self.mode] = math.floor(now - self.mode_entered)
        state_current = [0] * (NUM_MODES * NUM_STATES)
        state_current[here] = math.floor(now - self.state_entered)
        mode_cumulative = list(self.mode_cumulative)
        mode_cumulative[self.mode] += dt
        state_cumulative = list(self.state_cumulative)
        state_cumulative[here] += dt
        admin.mode_current_time = mode_current
        admin.mode_cumulative_time = [math.floor(v) for v in mode_cumulative]
        admin.state_current_time = state_current
        admin.state_cumulative_time = [math.floor(v) for v in state_cumulative]
        admin.acc_time_since_reset = math.floor(self.acc + dt)


class ForeignUnit(Node):
    def __init__(self, options: Options) -> None:
        super().__init__(options.unit, namespace=f"/{options.cell}")
        self.opt = options
        self.path = f"/{options.cell}/{options.unit}"
        self.state, self.mode = ST["STOPPED"], MODES[1]
        self.sequence = 0
        self.cntrl_cmd = 0
        self.command_unit_mode = self.mode.number
        now = time.monotonic()
        self.clocks = Clocks(now, self.mode.number, self.state)
        self.executing = 0.0  # s in Execute before ``executing_since``
        self.executing_since: float | None = None
        self.count_offset = 0  # pieces produced before the last counter reset

        def publisher(name: str) -> Any:
            topic = interface.TOPIC[name]
            return self.create_publisher(topic.type, topic.path(self.path), topic.qos)

        self.status_pub = publisher("status")
        self.transitions_pub = publisher("transitions")
        self.admin_pub = publisher("admin")
        self.resends: list[tuple[Callable[[], bool], float]] = []
        self.resend_timer = self.create_timer(RESEND_PERIOD, self._resend, autostart=False)
        self.dwell_timer = (
            self.create_timer(options.dwell, self._dwell_over, autostart=False)
            if options.dwell > 0
            else None
        )
        self.create_timer(ADMIN_PERIOD, self.publish_admin)
        self._serve("command", self.on_command)
        self._serve("set_mode", self.on_set_mode)
        self._serve("reset_counters", self.on_reset_counters)
        self._serve("reset_times", self.on_reset_times)
        for shortcut in interface.SHORTCUTS:
            assert shortcut.command is not None
            self._serve(shortcut.name, self._trigger(int(shortcut.command)))
        self.publish_status()
        self.publish_admin()

    # -- services ------------------------------------------------------------------------------
    def _serve(self, name: str, handler: Callable[[Any, Any], Any]) -> None:
        """Service ``name`` of the interface, whose responses dropped by the middleware (a client
        whose response reader is not discovered yet: rclpy warns "failed to send response") are
        sent again for a while."""
        service = interface.SERVICE[name]
        server = self.create_service(service.type, f"{self.path}/{name}", handler)
        send = server.send_response

        def attempt(response: Any, header: Any) -> bool:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                send(response, header)
            return not any("failed to send response" in str(w.message) for w in caught)

        def send_response(response: Any, header: Any) -> None:
            if not attempt(response, header):
                self.resends.append(
                    (lambda: attempt(response, header), time.monotonic() + RESEND_WINDOW)
                )
                if self.resend_timer.is_canceled():
                    self.resend_timer.reset()

        server.send_response = send_response  # type: ignore[method-assign]

    def _resend(self) -> None:
        now = time.monotonic()
        pending, self.resends = self.resends, []
        for retry, until in pending:
            try:
                sent = retry()
            except Exception:  # the service is gone (shutting down)
                continue
            if not sent and now < until:
                self.resends.append((retry, until))
        if not self.resends:
            self.resend_timer.cancel()

    def _answer_command(self, cmd: int, source: str) -> tuple[bool, int, str]:
        result, final, skipped = judge(self.state, self.mode, cmd)
        here = STATE_NAMES[self.state]
        if result == Result.ACCEPTED:
            self.cntrl_cmd = cmd
            target = heading_for(final, self.mode.disabled)
            path = here + "".join(f" -> {STATE_NAMES[s]}" for s in dict.fromkeys([final, target]))
            trigger = TransitionEvent.TRIGGER_SKIP if skipped else TransitionEvent.TRIGGER_COMMAND
            self.go(final, trigger, cmd, source or "operator", skipped)
            return True, result, f"{COMMAND_NAMES[cmd]} accepted: {path}"
        if "no_reason" in self.opt.faults:
            return False, Result.ACCEPTED, ""
        valid = ", ".join(COMMAND_NAMES[c] for c in valid_commands(self.state, self.mode))
        valid_now = f"(valid now: {valid or 'none'})"
        if result == Result.UNKNOWN_COMMAND:
            why = f"unknown command {cmd}: commands are 1..10 ({', '.join(COMMAND_NAMES.values())})"
        elif result == Result.STATE_DISABLED:
            why = (f"{COMMAND_NAMES[cmd]} not allowed in {here}: it leads to {STATE_NAMES[final]}, "
                   f"which is disabled in {self.mode.name} mode")  # fmt: skip
        else:
            why = f"{COMMAND_NAMES[cmd]} not allowed in {here}"
        return False, result, f"{why} {valid_now}"

    def on_command(self, request: Any, response: Any) -> Any:
        response.accepted, response.result, response.message = self._answer_command(
            request.command, request.source
        )
        response.state_current = self.state
        response.state_requested = heading_for(self.state, self.mode.disabled)
        return response

    def _trigger(self, cmd: int) -> Callable[[Any, Any], Any]:
        def handler(_request: Any, response: Any) -> Any:
            response.success, _, response.message = self._answer_command(cmd, "operator")
            return response

        return handler

    def on_set_mode(self, request: Any, response: Any) -> Any:
        wanted = request.mode_name.strip()
        if wanted:
            target = next((m for m in MODES.values() if m.name == wanted.upper()), None)
        else:
            target = MODES.get(request.mode)
        response.mode_current = self.mode.number
        here = STATE_NAMES[self.state]
        if target is None:
            known = ", ".join(f"{m.number} {m.name}" for m in MODES.values())
            asked = repr(wanted) if wanted else str(request.mode)
            response.accepted, response.result = False, Result.MODE_UNKNOWN
            response.message = f"mode {asked} unknown (known: {known})"
            return response
        if target is self.mode:
            response.accepted, response.result = True, Result.ACCEPTED
            response.message = f"already in {target.name}"
            return response
        why = None
        if self.state not in MODE_CHANGE_IN:
            allowed = ", ".join(STATE_NAMES[s] for s in sorted(MODE_CHANGE_IN))
            why = f"mode changes only in {allowed}"
        elif self.state in target.disabled:
            why = f"{here} is disabled in {target.name}"
        if why is not None:
            response.accepted, response.result = False, Result.MODE_CHANGE_NOT_ALLOWED
            response.message = (
                f"mode change {self.mode.name} -> {target.name} not allowed in {here}: {why}"
            )
            return response
        old = self.mode
        self.command_unit_mode = target.number
        self.mode = target
        now = time.monotonic()
        self.clocks.enter(now, target.number, self.state)
        self.sequence += 1
        self._event(self.state, self.state, old.number, TransitionEvent.TRIGGER_MODE, 0,
                    request.source or "operator", [])  # fmt: skip
        self.publish_status()
        self.publish_admin()
        response.accepted, response.result = True, Result.ACCEPTED
        response.message = f"mode change {old.name} -> {target.name} accepted"
        response.mode_current = self.mode.number
        return response

    def on_reset_counters(self, _request: Any, response: Any) -> Any:
        if "counters_not_reset" not in self.opt.faults:
            self.count_offset = self.pieces(time.monotonic())
        self.publish_admin()
        response.accepted, response.result = True, Result.ACCEPTED
        response.message = "counters reset (AccCount kept)"
        return response

    def on_reset_times(self, request: Any, response: Any) -> Any:
        if request.scope not in (
            ResetTimes.Request.SCOPE_CURRENT_MODE,
            ResetTimes.Request.SCOPE_ALL,
        ):
            response.accepted, response.result = False, Result.INVALID_ARGUMENT
            response.message = f"scope {request.scope} unknown: 0 current mode, 1 all"
            return response
        everything = request.scope == ResetTimes.Request.SCOPE_ALL
        self.clocks.reset(time.monotonic(), everything)
        self.publish_admin()
        response.accepted, response.result = True, Result.ACCEPTED
        response.message = "all times reset" if everything else f"{self.mode.name} times reset"
        return response

    # -- the state machine -----------------------------------------------------------------------
    def go(self, to: int, trigger: int, cmd: int, source: str, skipped: Iterable[int]) -> None:
        """One transition into ``to``, published; an acting state starts its dwell."""
        now = time.monotonic()
        if self.executing_since is not None:
            self.executing += now - self.executing_since
            self.executing_since = None
        if to == ST["EXECUTE"]:
            self.executing_since = now
        came_from, self.state = self.state, to
        self.clocks.enter(now, self.mode.number, to)
        self.sequence += 1
        self._event(came_from, to, self.mode.number, trigger, cmd, source, list(skipped))
        self.publish_status()
        self.publish_admin()
        if to not in TIMED:
            if self.dwell_timer is not None:
                self.dwell_timer.cancel()
        elif self.dwell_timer is not None:
            self.dwell_timer.reset()
        else:
            self._state_complete()

    def _dwell_over(self) -> None:
        # (a command that changed state since the timer fired has reset it: wait for it again)
        if (
            self.state in TIMED
            and time.monotonic() - self.clocks.state_entered >= 0.9 * self.opt.dwell
        ):
            self._state_complete()
        elif self.state not in TIMED and self.dwell_timer is not None:
            self.dwell_timer.cancel()

    def _state_complete(self) -> None:
        final, skipped = skip_through(STATE_COMPLETE[self.state], self.mode.disabled)
        trigger = (
            TransitionEvent.TRIGGER_SKIP if skipped else TransitionEvent.TRIGGER_STATE_COMPLETE
        )
        self.go(final, trigger, 0, "unit", skipped)

    def pieces(self, now: float) -> int:
        """Pieces produced since start: ``rate`` per second of Execute."""
        running = now - self.executing_since if self.executing_since is not None else 0.0
        return math.floor(self.opt.rate * (self.executing + running))

    # -- publication -----------------------------------------------------------------------------
    def _event(self, came_from: int, to: int, from_mode: int, trigger: int, cmd: int, source: str,
               skipped: list[int]) -> None:  # fmt: skip
        names = {
            TransitionEvent.TRIGGER_COMMAND: "command",
            TransitionEvent.TRIGGER_STATE_COMPLETE: "state complete",
            TransitionEvent.TRIGGER_SKIP: "skip",
            TransitionEvent.TRIGGER_MODE: "mode",
        }
        event = TransitionEvent(
            unit=self.opt.unit, sequence=self.sequence, from_state=came_from, to_state=to,
            from_state_name=STATE_NAMES[came_from], to_state_name=STATE_NAMES[to],
            from_mode=from_mode, to_mode=self.mode.number, trigger=trigger,
            trigger_name=names.get(trigger, ""), command=cmd, source=source,
            skipped_states=skipped,
        )  # fmt: skip
        event.stamp = self.get_clock().now().to_msg()
        self.transitions_pub.publish(event)

    def publish_status(self) -> None:
        faults = self.opt.faults
        valid = valid_commands(self.state, self.mode)
        status = Status(
            unit=self.opt.unit,
            unit_mode_current=self.mode.number,
            unit_mode_requested=self.mode.number,
            unit_mode_change_in_process=False,
            state_current=self.state,
            state_requested=heading_for(self.state, self.mode.disabled),
            state_change_in_process=self.state in TIMED,
            cntrl_cmd=self.cntrl_cmd,
            command_unit_mode=self.command_unit_mode,
            state_current_name=STATE_NAMES[self.state],
            unit_mode_current_name=self.mode.name,
            sequence=0 if "sequence_frozen" in faults else self.sequence,
            states_disabled=0 if "wrong_disabled_mask" in faults else self.mode.mask,
            commands_valid=valid,
            commands_valid_names=[COMMAND_NAMES[c] for c in valid],
            remote_commands_enabled=True,
        )
        status.stamp = self.get_clock().now().to_msg()
        self.status_pub.publish(status)

    def publish_admin(self) -> None:
        now = time.monotonic()
        admin = Admin(unit=self.opt.unit, states_disabled=self.mode.mask)
        admin.stamp = self.get_clock().now().to_msg()
        self.clocks.fill(admin, now)
        total = self.pieces(now)
        admin.prod_processed_count = [
            Count(id=1, name="pieces", unit="pcs", count=total - self.count_offset, acc_count=total)
        ]
        self.admin_pub.publish(admin)


def main() -> int:
    args = run.init()  # localhost-only defaults, Ctrl-C / SIGTERM end the spin cleanly
    try:
        options = Options.parse(args[0] if args else "")
    except (ValueError, TypeError) as exc:
        print(f"foreign_unit: {exc}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    node = ForeignUnit(options)
    print("ready", flush=True)
    return run.spin([node])


if __name__ == "__main__":
    sys.exit(main())
