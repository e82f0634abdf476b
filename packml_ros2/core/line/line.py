"""The line: everything the cell coordinator decides, as one pure object the node drives.

:class:`Line` holds the :class:`~.cell.Cell` (units, presence, interlocks, aggregation), the
running cell commands and mode changes (:mod:`.sequence`) and the line's
:class:`~.performance.Performance` (episodes, losses), with its input log and its store. The node
hands it what arrives and carries out what it returns; it holds one lock around every call. The
clocks are passed in: ``monotonic`` (seconds: leases, timeouts) and ``wall`` (integer ns since the
epoch: the units' stamps, shifts).
"""

from __future__ import annotations

import dataclasses
import json
import sqlite3
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..config import CellConfig
from ..numbers import Cmd
from ..persistence import one_line
from ..reasons import Reason
from . import inputs, snapshot
from .cell import Call, Cell, CellView, Effect
from .episodes import Episode, Root
from .ledger import ROLLING, Fact, History, Ledger, MemoryHistory, add_clipped
from .losses import DOWN, LINE, PLANNED_BUCKETS, Summary, Totals, summarize
from .performance import AHEAD_WAIT, Performance
from .sequence import (
    INTERRUPTS_A_SEQUENCE,
    AbortRun,
    CommandRun,
    ModeRun,
    Outcome,
    Run,
    Runs,
    StopWaits,
)
from .store import LineStore

NS = 1_000_000_000
#: s added to a time due on the wall clock, converted to the monotonic one (rounding)
WALL_SLACK = 1e-6
MEMORY_FACTS = 200_000  # facts a line without a store keeps for its queries
MAX_WINDOWS = 200  # windows one query may ask for (trend, shifts)
MAX_STEP = 1e7  # s: the widest window of a trend (116 days)
MAX_EPISODES = 1000
EPISODE_BUCKETS = (*PLANNED_BUCKETS, *DOWN)  #: the buckets an episode's root cause can be in


@dataclass(frozen=True)
class EpisodeView:
    episode: Episode
    root: Root
    now: int


@dataclass(frozen=True)
class LossesView:
    window: str
    start: int  #: ns, 0 = the beginning of the record
    end: int
    scopes: tuple[Summary, ...]  #: the line first, then the units in line order


@dataclass(frozen=True)
class InputRecord:
    index: int
    t: int
    name: str
    unit: str
    fields: Mapping[str, Any]

    @property
    def args_json(self) -> str:
        return json.dumps(self.fields, separators=(",", ":"), sort_keys=True)


def episode_view(perf: Performance, e: Episode, t: int) -> EpisodeView:
    """Episode ``e`` as published after the input at ``t`` changed it."""
    return EpisodeView(e, perf.root(e), max(t, e.start))


def summaries(perf: Performance, totals: Mapping[str, Totals]) -> tuple[Summary, ...]:
    """The line, then its units in line order."""
    scopes = [LINE, *perf.order]
    return tuple(summarize(s, totals.get(s, Totals()), perf.design(s)) for s in scopes)


def window_view(perf: Performance, which: str, now: int) -> LossesView:
    """A running window (``shift:<key>``, ``15min``, ``1h``, ``reset``, ``lifetime``)."""
    totals = perf.windows(which, now)
    if which in ROLLING:
        start, end = now - ROLLING[which], now
    elif which == "reset":
        start, end = perf.ledger.reset_at or 0, now
    elif which.startswith("shift:"):
        inst = perf.calendar.instance(which[6:])
        start, end = (inst.start, min(now, inst.end)) if inst else (0, now)
    else:
        start, end = 0, now
    return LossesView(which, start, end, summaries(perf, totals))


def published_windows(perf: Performance, now: int) -> list[LossesView]:
    """What ``line/losses`` carries at ``now``: the current shift, 15 min, 1 h, since reset,
    lifetime."""
    names = []
    inst = perf.calendar.instance_at(now)
    if inst is not None:
        names.append(f"shift:{inst.key}")
    names += [*ROLLING, "reset", "lifetime"]
    return [window_view(perf, n, now) for n in names]


#: Seconds past ``step_timeout`` a cell STOP waits for a running sequence to end.
STOP_GIVE_UP = 5.0


class BoundedHistory(MemoryHistory):
    """The facts of a line without a store, the newest :data:`MEMORY_FACTS`."""

    def add(self, facts: Iterable[Fact]) -> None:
        super().add(facts)
        if len(self.facts) > MEMORY_FACTS:
            del self.facts[: len(self.facts) - MEMORY_FACTS]


class Line:
    """See the module docstring."""

    def __init__(
        self,
        cell: CellConfig,
        monotonic: Callable[[], float],
        wall: Callable[[], int],
        store: LineStore | None = None,
    ) -> None:
        self.config = cell
        self.monotonic = monotonic
        self.wall = wall
        self.cell = Cell(cell, monotonic())
        self.runs = Runs()
        self.store = store
        history: History = store if store is not None else BoundedHistory()
        self.memory = None if store is not None else history
        self.perf = Performance(cell.line, cell.units, Ledger(history))
        self._last_result = ""
        self._result_in = 0  # the cell's state when the last result was given
        self.index = 0
        self.inputs: list[InputRecord] = []
        self.episodes_out: list[tuple[Episode, int]] = []
        self._digests: dict[tuple[str, str], Any] = {}
        self._online = dict.fromkeys(cell.units, False)
        self._published = 0  # wall ns of the last losses publication
        state = self._restore(store) if store is not None else None
        now = wall()
        keep = [i.key for i in (self.calendar.instance_at(now), self.calendar.previous(now)) if i]
        self._record(
            inputs.START,
            "",
            {"schema": inputs.SCHEMA, "state": state, "ledger": self.perf.ledger.base(keep)},
            now,
        )

    def _restore(self, store: LineStore) -> dict[str, Any] | None:
        """The open state and the ledger from the store; a store whose content does not restore
        is moved aside and the line starts with an empty one (``store.problems`` says so)."""
        try:
            state = store.state()
            if state is not None:
                self.perf.restore(state, store.recent_episodes(50))
            reset_at = state.get("reset_at") if state else None
            store.restore_ledger(self.perf.ledger, None if reset_at is None else int(reset_at))
            return state
        except (ValueError, TypeError, KeyError, AttributeError, IndexError, sqlite3.Error) as exc:
            store.start_over(f"could not be restored ({type(exc).__name__}: {one_line(exc, 120)})")
        self.perf = Performance(self.config.line, self.config.units, Ledger(store))
        return None

    @property
    def calendar(self) -> Any:
        return self.perf.calendar

    # ==============================================================================================
    # What arrives
    # ==============================================================================================
    def on_unit(self, name: str, topic: str, msg: Any) -> tuple[bool, list[Effect]]:
        """A message of unit ``name`` on ``topic`` (status, transitions, admin, alarms)."""
        news, effects = self.cell.on_message(name, topic, msg, self.monotonic())
        self._presence()
        if name not in self.perf.trackers:
            return news, effects
        if topic == "status":
            self._changed_input(inputs.STATUS, name, inputs.status_fields(name, msg), ("time",))
        elif topic == "transitions" and news:
            self._input(inputs.TRANSITION, name, inputs.transition_fields(name, msg))
        elif topic == "admin":
            self._changed_input(inputs.ADMIN, name, inputs.admin_fields(name, msg), ("time",))
        return news, effects

    def on_diagnostics(self, name: str, stale: bool, message: str) -> tuple[bool, list[Effect]]:
        changed, effects = self.cell.on_diagnostics(name, stale, message, self.monotonic())
        self._presence()
        return changed, effects

    def tick(self) -> list[Effect]:
        """Leases, retries; a tick of the performance when one is due (:meth:`losses_due`)."""
        effects = self.cell.tick(self.monotonic())
        self._presence()
        now = self.wall()
        if any(
            t.ahead is not None and now - t.ahead[1] >= AHEAD_WAIT
            for t in self.perf.trackers.values()
        ):
            self._input(inputs.TICK, "", {}, now)
        return effects

    def next_due(self) -> float:
        """When :meth:`tick` or :meth:`losses_due` has something to do next (monotonic seconds;
        ``-inf``: at once, ``inf``: nothing): the cell's leases and retries
        (:meth:`Cell.next_due`), the next losses publication, a status ahead of its transitions."""
        mono, wall = self.monotonic(), self.wall()
        due = self.cell.next_due(mono)
        at = [self._published + int(self.config.line.publish_period * NS)]
        at += [t.ahead[1] + AHEAD_WAIT for t in self.perf.trackers.values() if t.ahead is not None]
        return min(due, mono + (min(at) - wall) / NS + WALL_SLACK)

    def losses_due(self) -> tuple[int, list[LossesView]]:
        """Every ``line.publish_period``: a tick, its time and the windows to publish (else [])."""
        now = self.wall()
        if now - self._published < self.config.line.publish_period * NS:
            return now, []
        self._published = now
        self._input(inputs.TICK, "", {"publish": True}, now)
        return now, self.published_windows(now)

    def published_windows(self, now: int) -> list[LossesView]:
        return published_windows(self.perf, now)

    def _presence(self) -> None:
        for name, unit in self.cell.units.items():
            if unit.online != self._online[name]:
                self._online[name] = unit.online
                if unit.online:
                    self._input(inputs.ONLINE, name, {"unit": name})
                else:
                    self._input(inputs.LOST, name, {"unit": name, "why": unit.lost_reason})

    def interlock_sending(self, call: Call) -> None:
        """The node sends an interlock ``call`` (the unit's service is there)."""
        self.cell.interlock_sending(call.unit)
        self._input(
            inputs.INTERLOCK,
            call.unit,
            {
                "unit": call.unit,
                "active": bool(call.fields["active"]),
                "reason": str(call.fields["reason"]),
            },
        )

    def interlock_done(self, unit: str, want: bool, reason: str, error: str | None) -> list[Effect]:
        return self.cell.interlock_done(unit, want, reason, error, self.monotonic())

    def reset_losses(self) -> None:
        """The since-reset window begins now."""
        self._input(inputs.RESET, "", {})

    # ==============================================================================================
    # Cell commands and mode changes
    # ==============================================================================================
    def begin_command(
        self, cmd: Cmd, caller: str, asked: float | None = None
    ) -> tuple[int, Run] | Outcome | StopWaits:
        """A run for cell command ``cmd`` (registered), or why not. ABORT cancels what runs and
        begins at once; STOP cancels the sequence that runs and waits for it to end
        (:class:`StopWaits`; ``asked``: when it was first asked, given back when asking again),
        joins a STOP in progress, and is refused as busy after ``step_timeout`` +
        :data:`STOP_GIVE_UP` s; any other command is refused while a sequence runs."""
        if cmd is Cmd.ABORT:
            self.runs.cancel_all("ABORT")
            run: Run = AbortRun(self.cell, self.monotonic())
            exclusive = False
        else:
            if self.runs.sequence is not None:
                if cmd in INTERRUPTS_A_SEQUENCE:  # (ABORT: above)
                    joined = self.runs.running_stop()
                    if joined is not None:
                        return Outcome(
                            True, Reason.ACCEPTED, f"STOP joined the STOP in progress ({joined})"
                        )
                    now = self.monotonic()
                    since = now if asked is None else asked
                    if now < since + self.config.coordinator.step_timeout + STOP_GIVE_UP:
                        self.runs.cancel_all("STOP")
                        return StopWaits(since)
                return self._busy(cmd.name)
            command = CommandRun(self.cell, cmd)
            refused = command.refusals(self.monotonic())
            if refused is not None:
                return refused
            run, exclusive = command, True
        run_id = self.runs.add(run, exclusive)
        if run_id is None:
            return self._busy(cmd.name)
        self._input(inputs.CELL, "", {"command": int(cmd), "caller": caller})
        return run_id, run

    def _busy(self, what: str, mode: int = 0) -> Outcome:
        text = f"{what} refused: busy ({self.runs.busy_text()})"
        return Outcome(False, Reason.COMMAND_NOT_ALLOWED, text, mode, busy=True)

    def begin_mode(self, mode: int, mode_name: str) -> tuple[int, Run] | Outcome:
        run = ModeRun(self.cell, mode, mode_name)
        if self.runs.sequence is not None:
            return self._busy(f"mode {run.wanted}", run.old)
        refused = run.refusals()
        if refused is not None:
            return refused
        run_id = self.runs.add(run, True)
        assert run_id is not None
        return run_id, run

    def end(self, run_id: int, text: str = "") -> None:
        self.runs.remove(run_id)
        if text:
            self.last_result = text

    @property
    def last_result(self) -> str:
        """The outcome of the last cell command or mode change ("START failed (2.1 s)"): shown
        in the cell's detail until the cell's state changes (then it is no longer news: a
        cell that runs is not described by a START that failed before)."""
        return self._last_result

    @last_result.setter
    def last_result(self, text: str) -> None:
        self._last_result = text
        self._result_in = self.cell.view(False, "", "").state_current

    def view(self) -> CellView:
        busy = bool(self.runs.active)
        view = self.cell.view(busy, self.runs.step, self._last_result)
        if self._last_result and not busy and view.state_current != self._result_in:
            self._last_result = ""
            view = self.cell.view(busy, self.runs.step, "")
        if self.runs.sequence is not None:  # only what interrupts it is taken meanwhile
            valid = tuple(c for c in view.commands_valid if c in INTERRUPTS_A_SEQUENCE)
            view = dataclasses.replace(view, commands_valid=valid)
        return view

    # ==============================================================================================
    # Performance
    # ==============================================================================================
    def _changed_input(
        self, name: str, unit: str, fields: dict[str, Any], ignore: Sequence[str]
    ) -> None:
        digest = tuple(v for k, v in sorted(fields.items()) if k not in ignore)
        key = (name, unit)
        if self._digests.get(key) != digest:
            self._digests[key] = digest
            self._input(name, unit, fields)

    def _input(self, name: str, unit: str, fields: Mapping[str, Any], t: int | None = None) -> None:
        now = self.wall() if t is None else t
        inputs.apply(self.perf, name, now, fields)
        self._record(name, unit, fields, now)

    def _record(self, name: str, unit: str, fields: Mapping[str, Any], t: int) -> None:
        facts, episodes = self.perf.take()
        if self.memory is not None:
            self.memory.add(facts)  # type: ignore[attr-defined]
        if self.store is not None and (facts or episodes or name != inputs.START):
            doc = self.perf.document()
            doc["reset_at"] = self.perf.ledger.reset_at
            self.store.commit(facts, [self._row(e) for e in episodes], doc)
        self.index += 1
        self.inputs.append(InputRecord(self.index, t, name, unit, fields))
        self.episodes_out.extend((e, t) for e in episodes)

    def snapshot(self, published: Mapping[str, int]) -> tuple[int, int, dict[str, Any]]:
        """The line's state now, after input ``index`` (:mod:`.snapshot`), for a recorder that
        joins: (index, time ns, JSON object with the state, the input log's schema and
        ``published``: how many messages the node had published per line output topic)."""
        now = self.wall()
        doc = {
            "schema": snapshot.SCHEMA,
            "line": snapshot.capture(self.perf, now),
            "input_schema": inputs.SCHEMA,
            "published": dict(published),
        }
        return self.index, now, doc

    def _row(self, e: Episode) -> tuple[Episode, str, str, str]:
        root = self.perf.root(e)
        return e, root.unit, root.bucket, root.reason

    def take(self) -> tuple[list[InputRecord], list[EpisodeView]]:
        """Inputs to publish on the input log, episodes changed (for line/episodes)."""
        records, self.inputs = self.inputs, []
        episodes, self.episodes_out = self.episodes_out, []
        return records, [episode_view(self.perf, e, t) for e, t in episodes]

    def window(self, which: str, now: int) -> LossesView:
        return window_view(self.perf, which, now)

    def span(self, a: int, b: int, name: str = "since") -> LossesView:
        totals = self.perf.ledger.span(a, b, self.perf.open_parts(self.wall()))
        return LossesView(name, a, b, self._summaries(totals))

    def _summaries(self, totals: Mapping[str, Totals]) -> tuple[Summary, ...]:
        return summaries(self.perf, totals)

    def query_losses(
        self, window: str, since: int = 0, until: int = 0, step: float = 0.0, count: int = 0
    ) -> tuple[list[LossesView], str]:
        """The windows asked for (see ``QueryLosses.srv``), or [] and why not."""
        now = self.wall()
        window = window.strip() or "shift"
        if window in {"shift", "shift:current", "shift:previous"}:
            inst = (
                self.calendar.instance_at(now)
                if window != "shift:previous"
                else self.calendar.previous(now)
            )
            if inst is None:
                return [], self._no_shift(now)
            window = f"shift:{inst.key}"
        if window.startswith("shift:"):
            inst = self.calendar.instance(window[6:])
            if inst is None:
                return [], f"no shift {window[6:]!r} in the calendar (give YYYY-MM-DD <shift name>)"
            if window[6:] in self.perf.ledger.shifts or inst.end > now or self.store is None:
                return [self.window(window, now)], ""
            return [self._stored_shift(inst.key)], ""
        if window in (*ROLLING, "reset", "lifetime"):
            return [self.window(window, now)], ""
        if window == "since":
            if since <= 0:
                return [], "window since needs a since time"
            end = until if until > 0 else now
            if end <= since:
                return [], "until must be after since"
            return [self.span(since, end)], ""
        if window == "shifts":
            n = min(max(count, 1), MAX_WINDOWS)
            found: list[LossesView] = []
            inst = self.calendar.instance_at(now) or self.calendar.previous(now)
            while inst is not None and len(found) < n:
                found.append(
                    self.window(f"shift:{inst.key}", now)
                    if inst.key in self.perf.ledger.shifts or self.store is None
                    else self._stored_shift(inst.key)
                )
                inst = self.calendar.previous(inst.start)
            if not found:
                return [], self._no_shift(now)
            return found[::-1], ""
        if window == "trend":
            n = min(max(count, 1), MAX_WINDOWS)
            if not 0 < step <= MAX_STEP:  # (NaN too)
                return [], f"window trend needs a step in seconds (0 < step <= {MAX_STEP:g})"
            width = int(step * NS)
            end = until if until > 0 else now
            try:
                return [
                    self.span(end - (n - i) * width, end - (n - i - 1) * width, "trend")
                    for i in range(n)
                ], ""
            except LookupError as exc:
                return [], str(exc)
        return (
            [],
            f"unknown window {window[:40]!r} (shift, shift:<YYYY-MM-DD name>, shift:previous, 15min, 1h, reset, lifetime, since, shifts, trend)",
        )

    def _no_shift(self, now: int) -> str:
        if not self.calendar:
            return "no shift calendar (line.shifts in the cell file)"
        return "no shift now (line.shifts in the cell file)"

    def _stored_shift(self, key: str) -> LossesView:
        assert self.store is not None
        totals = self.store.shift_totals([key]).get(key, {})
        inst = self.calendar.instance(key)
        out: dict[str, Totals] = {s: t.copy() for s, t in totals.items()}
        for f in self.perf.open_parts(self.wall()):
            if f.shift == key:
                add_clipped(out, f, None, None)
        return LossesView(
            f"shift:{key}", inst.start if inst else 0, inst.end if inst else 0, self._summaries(out)
        )

    def episode_filter_problem(self, since: int, until: int, unit: str, bucket: str) -> str:
        """Why a QueryEpisodes filter cannot match anything by construction ('' when it can): a
        typo must not read as "no episodes"."""
        if unit and unit != "cell" and unit not in self.perf.order:
            return f"no unit {unit!r} in the line (units: {', '.join(self.perf.order)}; or cell)"
        if bucket and bucket not in EPISODE_BUCKETS:
            return f"no bucket {bucket!r} (buckets: {', '.join(EPISODE_BUCKETS)})"
        if since and until and until <= since:
            return "until must be after since"
        return ""

    def query_episodes(
        self,
        since: int = 0,
        until: int = 0,
        unit: str = "",
        reason: str = "",
        bucket: str = "",
        open_only: bool = False,
        limit: int = 100,
    ) -> tuple[list[EpisodeView], int]:
        now = self.wall()
        limit = min(max(limit, 1) if limit else 100, MAX_EPISODES)
        root_unit = None if not unit else ("" if unit == "cell" else unit)
        if self.store is not None:
            found, total = self.store.episodes(
                since or None, until or None, root_unit, reason, bucket, open_only, limit
            )
            return [EpisodeView(e, self.perf.root(e), now) for e in found], total
        candidates = [*self.perf.closed, *([self.perf.episode] if self.perf.episode else [])]
        out = []
        for e in reversed(candidates):
            root = self.perf.root(e)
            if (since and e.end is not None and e.end < since) or (until and e.start >= until):
                continue
            if root_unit is not None and root.unit != root_unit:
                continue
            if reason and reason.lower() not in root.reason.lower():
                continue
            if (bucket and root.bucket != bucket) or (open_only and not e.open):
                continue
            out.append(EpisodeView(e.copy(), root, now))
        return out[:limit], len(out)

    def close(self) -> None:
        self.cell.closed = True
        self.runs.cancel_all("shutdown")
        if self.store is not None:
            self.store.close()
