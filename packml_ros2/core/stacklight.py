"""The unit's stack light (tower light): which lights are off, on or blinking and whether the horn
sounds, from the PackML state and the active alarms; configured by a preset and overrides.

Evaluation: the state's entry is the base; the entry of each active alarm category, then
``warning``, then ``unacknowledged`` are laid over it. A layer only lights what it names, and per
light the higher mode wins (blink > on > off), so the order of the layers does not matter and
``off`` in an override only removes what the preset's entry lit. The horn sounds when the state's
entry or the ``unacknowledged`` entry asks for it, or when an active category's (or ``warning``'s)
entry does while some active alarm is unacknowledged: acknowledging silences it. (The inputs do
not say which alarm is unacknowledged: an unacknowledged category-7 alarm next to an acknowledged
category-0 one sounds the category-0 horn.)

Lights are listed top to bottom. A preset's entries for a light the configured ``lights`` leave
out are dropped; an override naming such a light is refused.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final, NamedTuple

from .numbers import NUM_STATES, State, parse_state
from .rules import NUM_CATEGORIES
from .schema import ConfigError, Node, boolean, choice, invalid, shown

#: Per light, as msg_defs/msg/StackLight.msg.
MODE_OFF: Final = 0
MODE_ON: Final = 1
MODE_BLINK: Final = 2
MODES: Final[Mapping[str, int]] = {"off": MODE_OFF, "on": MODE_ON, "blink": MODE_BLINK}
MAX_LIGHTS: Final = 8
#: The alarm entries besides the categories 0..9.
WARNING: Final = "warning"
UNACKNOWLEDGED: Final = "unacknowledged"
DEFAULT_PRESET: Final = "omac"

_ACTING_TO_EXECUTE = ("Starting", "Unholding", "Unsuspending")

# -- presets: plain tables in the YAML shape (states by name, alarms by category) -----------------
# Source: IEC 60204-1:2016 10.3.2 (Table 4, colours of indicator lights, from IEC 60073): red =
# emergency (hazardous condition), yellow = abnormal (impending critical condition), green =
# normal, blue = mandatory action by the operator, white = neutral; 10.3.3: flashing to attract
# attention, request action or show a change in progress. Mapped to PackML: Execute green, changes
# in progress blink, Held/Suspended abnormal (yellow), Aborted red + blue (Clear required),
# abort-level alarms red, stop-level yellow, informational white, unacknowledged blue (acknowledge).
_IEC60204: Final[Mapping[str, Any]] = {
    "lights": ["red", "yellow", "green", "blue", "white"],
    "states": {
        "Execute": {"green": "on"},
        **{s: {"green": "blink"} for s in _ACTING_TO_EXECUTE},
        "Idle": {"white": "on"},
        "Stopped": {"white": "on"},
        "Complete": {"white": "on"},
        "Resetting": {"white": "blink"},
        "Stopping": {"white": "blink"},
        "Completing": {"white": "blink"},
        "Held": {"yellow": "on"},
        "Suspended": {"yellow": "on"},
        "Holding": {"yellow": "blink"},
        "Suspending": {"yellow": "blink"},
        "Aborting": {"red": "blink"},
        "Aborted": {"red": "on", "blue": "on"},
        "Clearing": {"red": "on", "blue": "blink"},
    },
    "alarms": {
        **{c: {"red": "on", "horn": True} for c in (0, 1)},
        **{c: {"yellow": "on", "horn": True} for c in (2, 3, 4)},
        **{c: {"white": "blink"} for c in range(5, NUM_CATEGORIES)},
        WARNING: {"yellow": "blink"},
        UNACKNOWLEDGED: {"blue": "blink"},
    },
}

# Source: common OMAC PackML / ISA-TR88 machine practice (no table in TR88.00.02 itself): green on
# in Execute, blinking green in the acting states leading to Execute, amber in the waits other
# than Execute/Aborted and blinking amber in the acting states leading to them, red on in
# Aborting/Aborted and for an active stop- or abort-level alarm, blinking red while an alarm is
# unacknowledged, the horn for unacknowledged stop/abort-level alarms; blue (IEC 60204-1:
# mandatory action) while an alarm waits for acknowledgement.
_OMAC: Final[Mapping[str, Any]] = {
    "lights": ["red", "amber", "green", "blue"],
    "states": {
        "Execute": {"green": "on"},
        **{s: {"green": "blink"} for s in _ACTING_TO_EXECUTE},
        **{s: {"amber": "on"} for s in ("Idle", "Stopped", "Held", "Suspended", "Complete")},
        **{
            s: {"amber": "blink"}
            for s in ("Resetting", "Stopping", "Holding", "Suspending", "Completing", "Clearing")
        },
        "Aborting": {"red": "on"},
        "Aborted": {"red": "on"},
    },
    "alarms": {
        **{c: {"red": "on", "horn": True} for c in range(5)},
        **{c: {"amber": "on"} for c in range(5, NUM_CATEGORIES)},
        WARNING: {"amber": "blink"},
        UNACKNOWLEDGED: {"red": "blink", "blue": "on"},
    },
}

# Source: ROS-Industrial packml_stacklight (ros-industrial-consortium/packml,
# packml_stacklight/src/utils.cpp, initDefaultStatusActions): per state only, its buzzer (pulsed
# there) as the horn while starting motion; it maps no alarms.
_ROS_INDUSTRIAL: Final[Mapping[str, Any]] = {
    "lights": ["red", "amber", "green", "blue"],
    "states": {
        "Aborting": {"red": "blink", "blue": "blink"},
        "Aborted": {"red": "blink", "blue": "blink"},
        "Clearing": {"red": "blink", "blue": "blink"},
        "Stopping": {"red": "on", "blue": "blink"},
        "Stopped": {"red": "on", "blue": "blink"},
        "Resetting": {"blue": "blink"},
        "Idle": {"green": "blink", "blue": "blink"},
        **{s: {"green": "on", "blue": "blink", "horn": True} for s in _ACTING_TO_EXECUTE},
        "Execute": {"green": "on", "blue": "blink"},
        "Holding": {"blue": "on"},
        "Held": {"blue": "on"},
        "Suspending": {"amber": "blink", "blue": "blink"},
        "Suspended": {"amber": "blink", "blue": "blink"},
    },
    "alarms": {},
}

# Source: no Rockwell-published stack-light convention for PackML was found. Based on NFPA 79
# (2021) 10.3.2 (same colour meanings as IEC 60204-1, amber for yellow) on the red/amber/green
# three-light tower with horn usual on North American machines: no blue, so an unacknowledged
# alarm blinks red and a warning blinks amber.
_ROCKWELL: Final[Mapping[str, Any]] = {
    "lights": ["red", "amber", "green"],
    "states": {
        "Execute": {"green": "on"},
        **{s: {"green": "blink"} for s in _ACTING_TO_EXECUTE},
        **{s: {"amber": "on"} for s in ("Idle", "Stopped", "Held", "Suspended", "Complete")},
        **{
            s: {"amber": "blink"}
            for s in ("Resetting", "Stopping", "Holding", "Suspending", "Completing")
        },
        "Aborting": {"red": "on"},
        "Aborted": {"red": "on"},
        "Clearing": {"red": "on", "amber": "blink"},
    },
    "alarms": {
        **{c: {"red": "on", "horn": True} for c in range(5)},
        **{c: {"amber": "on"} for c in range(5, NUM_CATEGORIES)},
        WARNING: {"amber": "blink"},
        UNACKNOWLEDGED: {"red": "blink"},
    },
}

#: The presets by name. ``siemens``: no Siemens-published PackML convention was found; machines
#: built with Siemens controls in Europe follow EN 60204-1, so it is the ``iec60204`` table.
PRESETS: Final[Mapping[str, Mapping[str, Any]]] = {
    "iec60204": _IEC60204,
    "omac": _OMAC,
    "ros_industrial": _ROS_INDUSTRIAL,
    "rockwell": _ROCKWELL,
    "siemens": _IEC60204,
}


class Shown(NamedTuple):
    """What the stack light shows: one ``MODE_*`` per light (top to bottom) and the horn."""

    modes: tuple[int, ...]
    horn: bool


AlarmKey = int | str  # a category 0..9, WARNING or UNACKNOWLEDGED


@dataclass(frozen=True)
class StackLightConfig:
    """A configured stack light; :meth:`show` evaluates it (tables compiled at construction)."""

    lights: tuple[str, ...]
    #: per state number (1..17) and alarm key: the layer (lights not named: off)
    states: Mapping[int, Shown] = field(default_factory=dict)
    alarms: Mapping[AlarmKey, Shown] = field(default_factory=dict)
    preset: str = DEFAULT_PRESET
    _base: tuple[Shown, ...] = field(init=False, repr=False, compare=False)
    _layers: tuple[Shown | None, ...] = field(init=False, repr=False, compare=False)
    _memo: dict[tuple[int, frozenset[int], bool, bool], Shown] = field(
        init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        off = Shown((MODE_OFF,) * len(self.lights), False)
        base = tuple(self.states.get(s, off) for s in range(NUM_STATES))
        layers = tuple(self.alarms.get(c) for c in range(NUM_CATEGORIES))
        object.__setattr__(self, "_base", base)
        object.__setattr__(self, "_layers", layers)
        object.__setattr__(self, "_memo", {})

    def show(
        self,
        state: int,
        categories: frozenset[int] | Iterable[int],
        unacknowledged: bool,
        warning: bool,
    ) -> Shown:
        """The lights and horn in ``state`` with alarms of ``categories`` active (numbers outside
        the model show nothing)."""
        cats = categories if isinstance(categories, frozenset) else frozenset(categories)
        key = (state, cats, bool(unacknowledged), bool(warning))
        hit = self._memo.get(key)
        if hit is not None:
            return hit
        out = self._evaluate(*key)
        if len(self._memo) >= 4096:
            self._memo.clear()
        self._memo[key] = out
        return out

    def _evaluate(self, state: int, cats: frozenset[int], unack: bool, warning: bool) -> Shown:
        base = self._base[state] if 0 <= state < NUM_STATES else self._base[0]
        layers = [self._layers[c] for c in cats if 0 <= c < NUM_CATEGORIES]
        if warning:
            layers.append(self.alarms.get(WARNING))
        modes, horn = base
        for layer in layers:
            if layer is not None:
                modes = tuple(map(max, modes, layer.modes))
                horn = horn or (layer.horn and unack)
        last = self.alarms.get(UNACKNOWLEDGED) if unack else None
        if last is not None:
            modes = tuple(map(max, modes, last.modes))
            horn = horn or last.horn
        return Shown(modes, horn)


def encode_opcua(shown: Shown) -> list[int]:
    """The OPC 30050 v2 draft's ``Status.StackLight`` UInt32[] for ``shown``.

    The draft declares the member without an encoding, so this one is ours: one UInt32 per light,
    top to bottom, bits 0-1 the mode (0 off, 1 on, 2 blink), bit 2 of the first element the horn;
    colours are not encoded (a client reads them from the configuration or the ROS message)."""
    out = [m & 0b11 for m in shown.modes]
    if shown.horn:
        if not out:
            out.append(0)
        out[0] |= 0b100
    return out


# -- configuration ---------------------------------------------------------------------------------
_KEYS = {"preset", "lights", "states", "alarms"}
_LIGHT = re.compile(r"[a-z][a-z0-9_]{0,19}")
_PRESET = choice({name: name for name in PRESETS})


def _mode(n: Node) -> int:
    # YAML 1.1 reads unquoted on/off as true/false
    if isinstance(n.value, bool):
        return MODE_ON if n.value else MODE_OFF
    if not isinstance(n.value, str):
        raise invalid(f"expected off, on or blink, got {shown(n.value)}")
    word = n.value.strip().lower()
    if word not in MODES:
        close = difflib.get_close_matches(word[:20], list(MODES), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise invalid(f"{shown(n.value)} is not off, on or blink{hint}")
    return MODES[word]


def _lights(n: Node) -> tuple[str, ...]:
    out: list[str] = []
    for e in n.elements():
        v = e.value
        name = v.strip().lower() if isinstance(v, str) else None
        if name is None or not _LIGHT.fullmatch(name) or name == "horn":
            e.error(
                f"{shown(v)} is not a light name (a colour: lower-case letters, digits and _, "
                "at most 20, not 'horn')"
            )
        elif name in out:
            e.error(f"light {name!r} listed twice")
        else:
            out.append(name)
    if isinstance(n.value, list) and not 1 <= len(n.value) <= MAX_LIGHTS:
        n.error(f"{len(n.value)} lights; a stack light has 1..{MAX_LIGHTS}")
    return tuple(out)


def _entry(n: Node, lights: tuple[str, ...], strict: bool) -> dict[str, int | bool]:
    """One entry (light -> mode, horn -> bool); lights not in ``lights`` are refused when
    ``strict`` (an override), dropped otherwise (a preset's entry)."""
    out: dict[str, int | bool] = {}
    for key, child in n.items():
        light = key.strip().lower()
        if light == "horn":
            out["horn"] = child.parse(boolean, False)
        elif light in lights:
            out[light] = child.parse(_mode, MODE_OFF)
        elif strict:
            close = difflib.get_close_matches(light[:40], [*lights, "horn"], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            child.error(f"unknown light{hint}; the stack light has {', '.join(lights)} and horn")
    return out


def _state_key(n: Node) -> int:
    key = str(n.value)
    try:
        s = parse_state(key.strip()) if len(key) <= 40 else None
    except ValueError as exc:
        raise invalid(f"unknown state: {exc}") from None
    if s is None or s == State.UNDEFINED:
        raise invalid(f"unknown state {shown(key)}: entries are for the states 1..17")
    return int(s)


def _alarm_key(n: Node) -> AlarmKey:
    key = str(n.value)
    word = key.strip().lower()
    if word in (WARNING, UNACKNOWLEDGED):
        return word
    if word.lstrip("-").isdigit() and len(word) <= 4:
        if not 0 <= int(word) < NUM_CATEGORIES:
            raise invalid(f"alarm category {word} is outside 0..{NUM_CATEGORIES - 1}")
        return int(word)
    raise invalid(
        f"unknown alarm entry {shown(key)}; an alarm category 0..{NUM_CATEGORIES - 1}, "
        f"{WARNING!r} or {UNACKNOWLEDGED!r}"
    )


def _table(
    n: Node,
    lights: tuple[str, ...],
    strict: bool,
    key_of: Callable[[Node], Any],
    into: dict[Any, dict[str, Any]],
) -> None:
    """Merge the entries of the mapping at ``n`` into ``into`` (per light)."""
    seen: dict[Any, str] = {}
    for key, child in n.items():
        k = Node(key, child.path, child.problems).parse(key_of, None)
        if k is None:
            continue
        if k in seen:
            child.error(f"the same entry as {seen[k]!r}")
            continue
        seen[k] = key
        into.setdefault(k, {}).update(_entry(child, lights, strict))


def _layer(entry: Mapping[str, Any], lights: tuple[str, ...]) -> Shown:
    return Shown(tuple(int(entry.get(c, MODE_OFF)) for c in lights), bool(entry.get("horn")))


def stack_light(n: Node) -> StackLightConfig:
    """The ``stack_light:`` section at ``n`` (absent or null: the ``omac`` preset); problems are
    added to ``n.problems`` like the rest of the cell file."""
    n.check_keys(_KEYS)
    preset = n.get("preset", _PRESET, DEFAULT_PRESET)
    table = PRESETS[preset]
    no_lights: tuple[str, ...] = ()
    lights = n.get("lights", _lights, no_lights) or tuple(table["lights"])
    states: dict[int, dict[str, Any]] = {}
    alarms: dict[AlarmKey, dict[str, Any]] = {}
    source = Node(table, f"<preset {preset}>")  # presets are checked by the tests: no problems
    _table(source.child("states", table["states"]), lights, False, _state_key, states)
    _table(source.child("alarms", table["alarms"]), lights, False, _alarm_key, alarms)
    m = n.mapping()
    if "states" in m:
        _table(n.child("states", m["states"]), lights, True, _state_key, states)
    if "alarms" in m:
        _table(n.child("alarms", m["alarms"]), lights, True, _alarm_key, alarms)
    return StackLightConfig(
        lights,
        {s: _layer(e, lights) for s, e in states.items()},
        {a: _layer(e, lights) for a, e in alarms.items()},
        preset,
    )


def parse(raw: Any, where: str = "stack_light", file: str = "<memory>") -> StackLightConfig:
    """The stack light configured by ``raw`` (the value of ``stack_light:``); :class:`ConfigError`
    naming ``where.<key path>`` for each problem."""
    n = Node(raw, where)
    out = stack_light(n)
    if n.problems:
        raise ConfigError(file, n.problems)
    return out


DEFAULT: Final = parse(None)

__all__ = [
    "DEFAULT",
    "MAX_LIGHTS",
    "MODES",
    "MODE_BLINK",
    "MODE_OFF",
    "MODE_ON",
    "PRESETS",
    "UNACKNOWLEDGED",
    "WARNING",
    "Shown",
    "StackLightConfig",
    "encode_opcua",
    "parse",
    "stack_light",
]
