"""Mode and state times (docs/packml.md §6): current and cumulative, per mode and per
(mode, state), AccTimeSinceReset, both reset scopes and the Int32 rollover.

Time only advances at state and mode changes (:meth:`ModeStateTimes.enter_states`,
:meth:`ModeStateTimes.enter`) and is read at any instant with :meth:`snapshot`, so results depend
on the clock values passed in, never on when the caller happened to look. A state change (the
hot path: every transition) closes only the current figures and the state's cumulative time;
the mode's cumulative time and AccTimeSinceReset are closed at mode changes and resets, and read
as stored plus the time since.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .numbers import NUM_MODES, NUM_STATES

#: Timers roll over here (OPC UA Int32) and raise the rollover warning.
ROLLOVER = 2**31 - 1


@dataclass(frozen=True, slots=True)
class TimesSnapshot:
    """Whole seconds as published (``Admin.*Time``), already rolled over."""

    mode_current: tuple[int, ...]
    mode_cumulative: tuple[int, ...]
    state_current: tuple[int, ...]  # flattened: mode * NUM_STATES + state
    state_cumulative: tuple[int, ...]
    acc_time_since_reset: int
    rollover_warning: bool


class ModeStateTimes:
    """Accumulates seconds of the current mode and (mode, state) between changes.

    Two clocks: the current times, the (mode, state) cumulative times and the planned stop are
    stored as of ``_since`` (the last state change), ModeCumulativeTime and AccTimeSinceReset as
    of ``_mode_since`` (the last mode change or reset); a reading adds the time since."""

    def __init__(self, now: float, mode: int, state: int) -> None:
        self.mode_current = [0.0] * NUM_MODES
        self.mode_cumulative = [0.0] * NUM_MODES
        self.state_current = [0.0] * (NUM_MODES * NUM_STATES)
        self.state_cumulative = [0.0] * (NUM_MODES * NUM_STATES)
        self.acc_time_since_reset = 0.0
        self.planned_stop = 0.0  # OEE: Production time spent in a planned stop
        self._mode = mode
        self._base = mode * NUM_STATES  # index of (mode, state 0) in the per-state arrays
        self._state = state
        self._planned = False
        self.modes_used: set[int] = {mode}  # only these modes can hold non-zero times
        self._since = now
        self._mode_since = now
        self.resets = 0  # +1 at every reset (persistence compares; state and mode changes it sees)

    # -- accumulation ------------------------------------------------------------------------------
    def _close(self, now: float) -> None:
        """Bring every figure up to ``now`` (a mode change, a reset)."""
        self._close_state(now)
        dt = now - self._mode_since
        if dt <= 0.0:
            return
        self.mode_cumulative[self._mode] += dt
        self.acc_time_since_reset += dt
        self._mode_since = now

    def _close_state(self, now: float) -> None:
        dt = now - self._since
        if dt <= 0.0:
            return
        i = self._base + self._state
        self.mode_current[self._mode] += dt
        self.state_current[i] += dt
        self.state_cumulative[i] += dt
        if self._planned:
            self.planned_stop += dt
        self._since = now

    def enter_states(
        self, now: float, first: int, last: int, between: Sequence[int], planned: bool
    ) -> None:
        """The unit entered ``first``, the states ``between``, then ``last`` (maybe ``first``)
        in the current mode at ``now``: a command and the State Completes that followed at once,
        one call for them all. ``planned``: ``last`` is a planned stop (OEE)."""
        current = self.state_current
        base = self._base
        dt = now - self._since
        if dt > 0.0:  # (_close_state, inline: this runs at every command)
            i = base + self._state
            self.mode_current[self._mode] += dt
            current[i] += dt
            self.state_cumulative[i] += dt
            if self._planned:
                self.planned_stop += dt
            self._since = now
        current[base + first] = 0.0
        if between:  # (rare: a third state in one step)
            for state in between:
                current[base + state] = 0.0
        current[base + last] = 0.0
        self._state = last
        self._planned = planned

    @staticmethod
    def enter_states_source(
        times: str, now: str, first: int, last: int, between: Sequence[int], planned: str
    ) -> list[str]:
        """:meth:`enter_states` as lines of code for a generated run (core/fastpath.py), with
        its states as constants: the same updates without a call, on this hottest path. ``times``,
        ``now`` and ``planned`` are the expressions the generated code passes (the differential
        test of the fast path, test_a_compiled_run_does_what_the_general_loop_does, holds the
        two equal)."""
        return [
            f"current = {times}.state_current",
            f"base = {times}._base",
            f"dt = {now} - {times}._since",
            "if dt > 0.0:",
            f"    i = base + {times}._state",
            f"    {times}.mode_current[{times}._mode] += dt",
            "    current[i] += dt",
            f"    {times}.state_cumulative[i] += dt",
            f"    if {times}._planned:",
            f"        {times}.planned_stop += dt",
            f"    {times}._since = {now}",
            *(f"current[base + {int(state)}] = 0.0" for state in (first, *between, last)),
            f"{times}._state = {int(last)}",
            f"{times}._planned = {planned}",
        ]

    def enter(self, now: float, mode: int, state: int, planned: bool = False) -> None:
        """The unit entered ``state`` and/or ``mode`` at ``now``: restart their current times."""
        self._close(now)
        if mode != self._mode:
            # ModeCurrentTime is "since the unit last entered mode m": 0 for the modes it is not
            # in (docs/packml.md §6)
            self.mode_current[self._mode] = 0.0
            self.mode_current[mode] = 0.0
            self.modes_used.add(mode)
        self.state_current[mode * NUM_STATES + state] = 0.0
        self._mode = mode
        self._base = mode * NUM_STATES
        self._state = state
        self._planned = planned

    def shift(self, offset: float) -> None:
        """The clock stepped by ``offset``: the running times keep their elapsed seconds."""
        self._since += offset
        self._mode_since += offset

    # -- resets ------------------------------------------------------------------------------------
    def reset_current_mode(self, now: float) -> None:
        """The current mode's times and the times of all its states."""
        self.resets += 1
        self._close(now)
        self._since = max(self._since, now)
        self._mode_since = max(self._mode_since, now)
        m = self._mode
        self.mode_current[m] = self.mode_cumulative[m] = 0.0
        for i in range(m * NUM_STATES, (m + 1) * NUM_STATES):
            self.state_current[i] = self.state_cumulative[i] = 0.0

    def reset_all(self, now: float) -> None:
        """Every time, including AccTimeSinceReset."""
        self.resets += 1
        self._close(now)
        self._since = max(self._since, now)
        self._mode_since = max(self._mode_since, now)
        for values in (
            self.mode_current,
            self.mode_cumulative,
            self.state_current,
            self.state_cumulative,
        ):
            values[:] = [0.0] * len(values)
        self.acc_time_since_reset = 0.0
        self.planned_stop = 0.0

    # -- reading -----------------------------------------------------------------------------------
    def live(self, now: float) -> tuple[list[float], list[float], list[float], list[float], float]:
        """Float seconds as of ``now`` without changing anything."""
        dt = max(0.0, now - self._since)
        mode_dt = max(0.0, now - self._mode_since)
        mc, mcum = list(self.mode_current), list(self.mode_cumulative)
        sc, scum = list(self.state_current), list(self.state_cumulative)
        m = self._mode
        i = m * NUM_STATES + self._state
        mc[m] += dt
        mcum[m] += mode_dt
        sc[i] += dt
        scum[i] += dt
        return mc, mcum, sc, scum, self.acc_time_since_reset + mode_dt

    def acc_at(self, now: float) -> float:
        """AccTimeSinceReset as of ``now``."""
        return self.acc_time_since_reset + max(0.0, now - self._mode_since)

    def planned_stop_at(self, now: float) -> float:
        return self.planned_stop + (max(0.0, now - self._since) if self._planned else 0.0)

    def snapshot(self, now: float) -> TimesSnapshot:
        mc, mcum, sc, scum, acc = self.live(now)
        # A current time never exceeds its cumulative one: three max() tell whether anything rolled
        # over, and usually nothing did, so the conversion runs at C speed.
        over = acc >= ROLLOVER or max(mcum) >= ROLLOVER or max(scum) >= ROLLOVER

        used = sorted(self.modes_used)

        def whole(v: float) -> int:
            return int(v) % ROLLOVER if v >= ROLLOVER else int(v)

        def publish(values: list[float], width: int) -> tuple[int, ...]:
            """Whole seconds; only the slices of the modes ever used can be non-zero."""
            out = [0] * len(values)
            for m in used:
                lo, hi = m * width, (m + 1) * width
                out[lo:hi] = map(whole, values[lo:hi]) if over else map(int, values[lo:hi])
            return tuple(out)

        return TimesSnapshot(
            publish(mc, 1),
            publish(mcum, 1),
            publish(sc, NUM_STATES),
            publish(scum, NUM_STATES),
            whole(acc),
            rollover_warning=over,
        )

    # -- persistence -------------------------------------------------------------------------------
    def to_dict(self, now: float) -> dict[str, Any]:
        """Sparse: only non-zero entries of the modes ever used, keyed by index. This runs at
        every transition (persistence), so it touches 18 entries per used mode, not 576."""
        dt = max(0.0, now - self._since)
        mode_dt = max(0.0, now - self._mode_since)
        cur_mode, cur_index = self._mode, self._mode * NUM_STATES + self._state
        indices = [m * NUM_STATES + s for m in sorted(self.modes_used) for s in range(NUM_STATES)]

        def sparse_states(values: list[float]) -> dict[str, float]:
            out = {str(i): values[i] for i in indices if values[i]}
            out[str(cur_index)] = values[cur_index] + dt
            return out

        def sparse_modes(values: list[float], since: float) -> dict[str, float]:
            out = {str(m): values[m] for m in self.modes_used if values[m]}
            out[str(cur_mode)] = values[cur_mode] + since
            return out

        return {
            "mode_current": sparse_modes(self.mode_current, dt),
            "mode_cumulative": sparse_modes(self.mode_cumulative, mode_dt),
            "state_current": sparse_states(self.state_current),
            "state_cumulative": sparse_states(self.state_cumulative),
            "acc_time_since_reset": self.acc_time_since_reset + mode_dt,
            "planned_stop": self.planned_stop_at(now),
        }

    def restore(self, data: dict[str, Any], now: float) -> None:
        """Cumulative values from a saved unit; the current mode/state restart from ``now``."""
        for key in ("mode_current", "mode_cumulative", "state_current", "state_cumulative"):
            target: list[float] = getattr(self, key)
            for index, value in data.get(key, {}).items():
                if 0 <= int(index) < len(target):
                    target[int(index)] = float(value)
                    if key.startswith("mode"):
                        self.modes_used.add(int(index))
                    else:
                        self.modes_used.add(int(index) // NUM_STATES)
        self.acc_time_since_reset = float(data.get("acc_time_since_reset", 0.0))
        self.planned_stop = float(data.get("planned_stop", 0.0))
        self._since = self._mode_since = now
        self.mode_current[:] = [0.0] * NUM_MODES  # a restarted unit entered its mode just now
        self.state_current[self._mode * NUM_STATES + self._state] = 0.0
