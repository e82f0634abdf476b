"""A line simulated on a virtual clock: real engines (:class:`~packml_ros2.core.Unit` driven by the
node's :class:`~packml_ros2.driver.UnitDriver`, their messages made by ``convert``), simulated EMs
(State Complete after a duration per state, a count per cycle in Execute, faults switched at
scripted times) and the coordinator's :class:`~packml_ros2.core.line.line.Line` fed with every
message and carrying out what it asks (interlocks, cell commands unit by unit) — the node's
logic without DDS, so every time is exact and episodes and losses can be computed by hand.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

from packml_ros2.core import ACTING, Cmd, State, Unit, parse_cell
from packml_ros2.core.line.cell import Call, interlock_failure
from packml_ros2.core.line.line import Line
from packml_ros2.core.line.sequence import Answer, Outcome, Run, StopWaits
from packml_ros2.core.line.store import LineStore
from packml_ros2.driver import FrozenClock, UnitDriver

NS = 1_000_000_000
T0 = 1_750_000_000.0  # 2025-06-15 15:06:40 UTC, a Sunday: sim time 0


@dataclass
class SimEm:
    """An EM: State Complete after ``durations[state]`` s; in Execute a count every ``cycle`` s
    (every ``defect_every``-th defective)."""

    unit: str
    name: str
    durations: dict[State, float] = field(default_factory=dict)
    cycle: float = 0.0
    defect_every: int = 0
    parts: int = 0


class SimLine:
    def __init__(self, doc: dict[str, Any], ems: list[SimEm], store: str | None = None,
                 tick: float | None = None) -> None:  # fmt: skip
        """``tick``: the line's tick every so many seconds; None: as the node does it, one
        wake-up armed for :meth:`Line.next_due` after every event (``ticks`` counts them)."""
        self.t = T0
        self.cell = parse_cell(doc)
        self.events: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()
        self.messages: list[tuple[float, str, str, Any]] = []  # (t, unit, topic, msg)
        self.log: list[str] = []
        self.units: dict[str, Unit] = {}
        self.drivers: dict[str, UnitDriver] = {}
        self.ems = {(e.unit, e.name): e for e in ems}
        for name, cfg in self.cell.units.items():
            clock = FrozenClock(lambda: self.t)
            unit = Unit(cfg, clock=clock)
            self.units[name] = unit
            self.drivers[name] = UnitDriver(unit, clock, self._emitter(name))
        self.records: list[Any] = []  # the line's input log
        self.episode_views: list[Any] = []  # every episode change, as published
        self.line = Line(self.cell, lambda: self.t, lambda: round(self.t * NS),
                         LineStore(store, self.cell.cell) if store else None)  # fmt: skip
        self.runs: list[tuple[int, Run, list[Outcome]]] = []
        self.tick = tick
        self.ticks = 0
        self.silent: set[str] = set()  # units whose diagnostics no longer arrive
        self._tick_at = math.inf  # armed mode: when the wake-up armed is due
        self.published: list[Any] = []  # LossesView lists at each publication
        self.snapshots: list[tuple[int, int, dict[str, Any]]] = []  # line/snapshot (snapshot())
        for unit, em in self.ems:
            self.drivers[unit].call(self.t, self.units[unit].em_seen, em, True)
        for driver in self.drivers.values():
            driver.flush()
        if tick is not None:
            self._every(tick, self._tick)
        self._every(1.0, self._diagnostics)  # a unit's /diagnostics every second: its sign of life

    # -- time ---------------------------------------------------------------------------------------
    def at(self, seconds: float, fn: Callable[[], Any]) -> None:
        """``fn`` at sim time ``seconds`` (since T0)."""
        heapq.heappush(self.events, (T0 + seconds, next(self._order), fn))

    def _every(self, period: float, fn: Callable[[], None]) -> None:
        def again() -> None:
            fn()
            heapq.heappush(self.events, (self.t + period, next(self._order), again))

        heapq.heappush(self.events, (self.t + period, next(self._order), again))

    def run_until(self, seconds: float) -> None:
        end = T0 + seconds
        while True:
            due = [(u.next_deadline() or math.inf, n) for n, u in self.units.items()]
            deadline, name = min(due)
            event = self.events[0][0] if self.events else math.inf
            nxt = min(deadline, event)
            if nxt > end:
                break
            self.t = max(self.t, nxt)
            if deadline <= event:
                self.drivers[name].catch_up(self.t)
            else:
                _, _, fn = heapq.heappop(self.events)
                fn()
            self._poll_runs()
            if self.tick is None:
                self._arm()
        self.t = end

    @property
    def now(self) -> float:
        return self.t - T0

    # -- units and EMs ---------------------------------------------------------------------------------
    def _emitter(self, unit: str) -> Callable[[str, Any], None]:
        def emit(topic: str, msg: Any) -> None:
            if topic == "log":
                return
            self.messages.append((self.now, unit, topic, msg))
            if topic == "transitions":
                self._em_schedule(unit, msg)
            _, effects = self.line.on_unit(unit, topic, msg)
            self._effects(effects)
            self.take()

        return emit

    def _em_schedule(self, unit: str, t: Any) -> None:
        state, seq = State(t.to_state), t.sequence
        for (u, _name), em in self.ems.items():
            if u != unit:
                continue
            if state in ACTING and state is not State.EXECUTE:
                delay = em.durations.get(state, 0.0)
                self.at(self.now + delay, lambda em=em, s=state, q=seq: self._complete(em, s, q))
            elif state is State.EXECUTE and em.cycle:
                self.at(self.now + em.cycle, lambda em=em, q=seq: self._cycle(em, q))

    def _complete(self, em: SimEm, state: State, seq: int) -> None:
        u = self.units[em.unit]
        if u.state is state and u.sequence == seq:
            self.drivers[em.unit].call(self.t, u.em_complete, em.name, int(state), seq)

    def _cycle(self, em: SimEm, seq: int) -> None:
        u = self.units[em.unit]
        if u.state is not State.EXECUTE or u.sequence != seq:
            return
        em.parts += 1
        d = self.drivers[em.unit]
        d.call(self.t, u.em_count, em.name, "processed", 0, 1)
        if em.defect_every and em.parts % em.defect_every == 0:
            d.call(self.t, u.em_count, em.name, "defective", 0, 1)
        self.at(self.now + em.cycle, lambda: self._cycle(em, seq))

    def alarm(self, unit: str, em: str, alarm_id: int, on: bool) -> None:
        u = self.units[unit]
        self.drivers[unit].call(self.t, u.em_alarm, em, alarm_id, 0, on, False, -1, "")

    def interlock(self, unit: str, em: str, blocked: bool = False, starved: bool = False) -> None:
        u = self.units[unit]
        self.drivers[unit].call(self.t, u.em_interlock, em, blocked, starved)

    def command(self, unit: str, cmd: Cmd, source: str = "operator") -> Any:
        u = self.units[unit]
        return self.drivers[unit].call(self.t, u.command, int(cmd), source)

    def reset_alarms(self, unit: str) -> None:
        u = self.units[unit]
        self.drivers[unit].call(self.t, u.reset_alarms)

    # -- the coordinator -------------------------------------------------------------------------------
    def _effects(self, effects: list[Any]) -> None:
        for e in effects:
            if isinstance(e, Call):
                if e.purpose == "interlock":
                    self.line.interlock_sending(e)
                    u = self.units[e.unit]
                    a = self.drivers[e.unit].call(self.t, u.set_interlock, e.fields["active"],
                                                  e.fields["reason"], e.fields["source"])  # fmt: skip
                    err = interlock_failure(bool(e.fields["active"]), a.accepted, a.reason, a.message)  # fmt: skip
                    self._effects(self.line.interlock_done(e.unit, bool(e.fields["active"]), e.why, err))  # fmt: skip
                else:
                    u = self.units[e.unit]
                    self.drivers[e.unit].call(self.t, u.command, e.fields["command"], e.fields["source"])  # fmt: skip
            else:
                self.log.append(str(e))

    def _diagnostics(self) -> None:
        for name in self.units:
            if name in self.silent:
                continue
            _, effects = self.line.on_diagnostics(name, False, "")
            self._effects(effects)
        self.take()

    def _arm(self) -> None:
        """The node's timer: armed for the next thing due when that is sooner than the armed one."""
        due = max(self.line.next_due(), self.t)
        if due < self._tick_at:
            self._tick_at = due
            heapq.heappush(self.events, (due, next(self._order), partial(self._armed_tick, due)))

    def _armed_tick(self, at: float) -> None:
        if at != self._tick_at:
            return  # superseded by a sooner one (that one fired and armed again)
        self._tick_at = math.inf
        self._tick()

    def _tick(self) -> None:
        self.ticks += 1
        self._effects(self.line.tick())
        _, views = self.line.losses_due()
        if views:
            self.published.append(views)
        self.take()

    def take(self) -> None:
        """Keep what the line would publish: its input log and the episodes changed."""
        records, episodes = self.line.take()
        self.records.extend(records)
        self.episode_views.extend(episodes)

    def snapshot(self) -> None:
        """The coordinator's answer to a recorder joining now: the line's state on
        ``line/snapshot`` (after what it published)."""
        self.take()
        published = {"episodes": len(self.episode_views), "losses": sum(len(v) for v in self.published)}  # fmt: skip
        self.snapshots.append(self.line.snapshot(published))

    def write_bag(self, path: Any, cell_yaml: str, joined: float | None = None,
                  stop: float | None = None, input_history: int = 5000) -> None:  # fmt: skip
        """What the coordinator would have published, as ``packml record`` writes it: the
        line's input log, episodes and losses, and one unit's configuration. ``joined`` (sim
        seconds): what a recorder that joined then has — the history the publishers keep
        (packml_ros2.qos) and everything after, with the snapshots taken (:meth:`snapshot`);
        ``stop``: when it stopped (it has the outputs stamped before, and notes the time and
        the publication numbers); ``input_history``: the inputs the input log keeps for a late
        subscriber (the coordinator's: 5000)."""
        import json

        from rclpy.serialization import serialize_message
        from rosbags.rosbag2 import Writer

        from packml_ros2 import line_msgs
        from packml_ros2.bag import line
        from packml_ros2.bag.topics import (
            CUSTOM_KEY,
            PUBLISHER_QOS,
            msg_class,
            rosbags_qos,
            typestore,
        )

        self.take()
        cell = self.cell.cell
        unit_input = msg_class("packml_interfaces/msg/UnitInput")
        designs = {s: self.line.perf.design(s) for s in ("", *self.line.perf.order)}
        streams: dict[str, list[tuple[int, bytes]]] = {name: [] for name in line.LINE_TOPICS}
        for r in self.records:
            streams["line/input_log"].append((r.t, serialize_message(unit_input(
                stamp=line_msgs.stamp(r.t), index=r.index, unit=r.unit, name=r.name, args_json=r.args_json))))  # fmt: skip
        for v in self.episode_views:
            streams["line/episodes"].append((v.now, serialize_message(line_msgs.episode_msg(v, cell))))  # fmt: skip
        for views in self.published:
            t = views[0].end
            for v in views:
                streams["line/losses"].append((t, serialize_message(line_msgs.losses_msg(v, cell, t, designs))))  # fmt: skip
        snapshot_cls = msg_class("packml_interfaces/msg/UnitSnapshot")
        for index, t, doc in self.snapshots:
            streams["line/snapshot"].append((t, serialize_message(snapshot_cls(
                stamp=line_msgs.stamp(t), index=index, unit="", state_json=json.dumps(doc)))))  # fmt: skip
        since = None if joined is None else round((T0 + joined) * NS)
        until = None if stop is None else round((T0 + stop) * NS)
        keep = {
            "line/input_log": input_history,
            "line/episodes": 100,
            "line/losses": 8,
            "line/snapshot": 1,
        }
        writer = Writer(path, version=9)
        writer.open()
        store = typestore()
        conns = {}
        for topic, kind, type_name in line.topics(cell):
            conns[topic.split("/coordinator/")[1]] = writer.add_connection(
                topic, type_name, typestore=store, offered_qos_profiles=[rosbags_qos(PUBLISHER_QOS[kind])])  # fmt: skip
        config = writer.add_connection(f"/{cell}/filler/config", "std_msgs/msg/String", typestore=store,
                                       offered_qos_profiles=[rosbags_qos(PUBLISHER_QOS["config"])])  # fmt: skip
        text = json.dumps({"unit": "filler", "cell_yaml": cell_yaml})
        writer.write(config, 1, serialize_message(msg_class("std_msgs/msg/String")(data=text)))
        items: list[tuple[int, str, bytes]] = []
        publications: dict[str, list[list[int]]] = {}
        for name, msgs in streams.items():
            numbers = list(range(len(msgs)))
            if since is not None:
                before = [i for i in numbers if msgs[i][0] < since]
                numbers = before[len(before) - keep[name] :] + numbers[len(before) :]
            if until is not None and name in line.LINE_OUTPUTS:
                numbers = [i for i in numbers if msgs[i][0] < until]
            items += [(max(msgs[i][0], since or 0), name, msgs[i][1]) for i in numbers]
            if name in line.LINE_OUTPUTS and until is not None and numbers:
                publications[f"/{cell}/coordinator/{name}"] = [[numbers[0] + 1, numbers[-1] + 1]]
                assert numbers == list(range(numbers[0], numbers[-1] + 1))
        last = 1
        for t, name, raw in sorted(items, key=lambda x: x[0]):
            last = max(t, last + 1)
            writer.write(conns[name], last, raw)
        if until is not None:
            notes = {"version": 1, "recorder": "test.core.line_sim", "stopped_at_ns": until,
                     "publications": publications}  # fmt: skip
            writer.set_custom_data(CUSTOM_KEY, json.dumps(notes, separators=(",", ":")))
        writer.close()

    def cell_command(self, cmd: Cmd, caller: str = "operator") -> list[Outcome]:
        """Begin a cell command; the list receives its outcome when it ends."""
        out: list[Outcome] = []
        begun = self.line.begin_command(cmd, caller)
        # a STOP waits for the sequence it cancelled (that one ends on its next step)
        for _ in range(100):
            if not isinstance(begun, StopWaits):
                break
            self._poll_runs()
            begun = self.line.begin_command(cmd, caller, begun.since)
        assert not isinstance(begun, StopWaits), "the cancelled sequence did not end"
        if isinstance(begun, Outcome):
            out.append(begun)
            return out
        run_id, run = begun
        self.runs.append((run_id, run, out))
        self._poll_runs()
        return out

    def _poll_runs(self) -> None:
        for entry in list(self.runs):
            run_id, run, out = entry
            while True:
                step = run.next(self.t, lambda unit, service: True)
                if isinstance(step, Outcome):
                    self.line.end(run_id, step.message)
                    out.append(step)
                    self.runs.remove(entry)
                    break
                calls, _ = step
                if not calls:
                    break
                for c in calls:
                    u = self.units[c.unit]
                    if c.service == "command":
                        a = self.drivers[c.unit].call(self.t, u.command, c.fields["command"], c.fields["source"])  # fmt: skip
                    else:
                        a = self.drivers[c.unit].call(self.t, u.set_mode, c.fields["mode"], c.fields["source"])  # fmt: skip
                    run.answer(c.unit, c.service, Answer(a.accepted, int(a.reason), a.message,
                               int(u.state), int(u.state_requested())))  # fmt: skip
