"""Bounds on what callers send: the one table every boundary applies (the services of units, the
coordinator and PLC bridges; the EM report topic; the HMI and the OPC UA server through the
services they call).

A string longer than its field's bound, a string with a control character, an array with more
entries than :data:`MAX_ITEMS`, or a request with more than :data:`MAX_REQUEST_TEXT` characters of
text in total is refused before anything sees it, with INVALID_ARGUMENT and a sentence that names
the field and the bound (never the value). So the input log (``<unit>/input_log``, 5 000 records
kept) holds no refused request, and no record is larger than a request may be.

Also here: the machine speed rule (``set_mach_speed`` at the unit, ``SetMachSpeed`` over OPC UA:
the same check), and :func:`printable`, what a caller's text becomes in a log line.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Protocol

#: Free text: alarm messages, interlock reasons, descriptor names and units.
MAX_TEXT = 256
#: Names: EMs, modes, a source's kind:name (:data:`.rules.MAX_SOURCE_NAME` for the name part).
MAX_NAME = 64
MAX_SOURCE = 96
#: Bound per field name (any request type); other strings get :data:`MAX_TEXT`.
FIELD_LIMITS: Mapping[str, int] = {
    "source": MAX_SOURCE,
    "em": MAX_NAME,
    "mode_name": MAX_NAME,
    "name": MAX_NAME,
    "unit": MAX_NAME,
    "reason": MAX_TEXT,
    "message": MAX_TEXT,
}
#: Entries of any one array of a request (parameters, products, their process variables,
#: ingredients and ingredient parameters). A unit's own arrays are smaller (``sizes``).
MAX_ITEMS = 64
#: Characters of text in one request, all strings together: what one input log record holds at
#: most (with the numbers around them, under 4 x this in JSON).
MAX_REQUEST_TEXT = 16_384


def text_problem(field: str, value: str, limit: int | None = None) -> str | None:
    """What is wrong with ``value`` as field ``field`` (None: nothing): too long, or a control
    character (a newline, an escape, a bidirectional override: nothing a log or a screen may
    misread). The value itself is never quoted."""
    bound = FIELD_LIMITS.get(field, MAX_TEXT) if limit is None else limit
    if len(value) > bound:
        return f"{field} is {len(value)} characters long (at most {bound})"
    if not value.isprintable():
        bad = next(c for c in value if not c.isprintable())
        return (
            f"{field} holds the control character U+{ord(bad):04X} at {value.index(bad)} "
            "(printable text only)"
        )
    return None


# -- machine speed ---------------------------------------------------------------------------------
class SpeedConfig(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def mach_design_speed(self) -> float: ...
    @property
    def max_mach_speed(self) -> float | None: ...


def speed_limit(config: SpeedConfig) -> float | None:
    """The highest MachSpeed the unit takes: ``max_mach_speed``, else its ``mach_design_speed``
    (when set), else none."""
    if config.max_mach_speed is not None:
        return config.max_mach_speed
    return config.mach_design_speed if config.mach_design_speed > 0 else None


def speed_refusal(
    speed: float, config: SpeedConfig, limit: float | None = None, origin: str = ""
) -> str | None:
    """Why machine speed ``speed`` is refused for the unit ``config`` (None: it is taken). The
    bound is ``limit`` (``origin`` says where it is configured), else :func:`speed_limit`."""
    if limit is None:
        limit = speed_limit(config)
        origin = "max_mach_speed" if config.max_mach_speed is not None else "mach_design_speed"
    if math.isfinite(speed) and speed >= 0 and (limit is None or speed <= limit):
        return None
    shown = f"{speed:g}" if math.isfinite(speed) else str(speed)
    if limit is None:
        return f"machine speed must be a finite number >= 0, not {shown}"
    return f"machine speed {shown} refused: {config.name} takes 0 .. {limit:g} ({origin})"


# -- log lines -------------------------------------------------------------------------------------
#: Characters of a caller's text kept in one log line.
MAX_LOGGED = 300


def printable(text: str, limit: int = MAX_LOGGED) -> str:
    """``text`` as a log line may carry it: every control, format or separator character
    escaped (``\\n``, ``\\x1b``, ``\\u202e``), so nothing a caller sends can start a line of
    its own, forge a severity or reorder what is shown; cut to ``limit`` characters. A URL's
    user information (``opc.tcp://user:password@host``) reads ``<redacted>``."""
    if "@" in text:
        from .secrets import redact_urls  # (secrets reads YAML: not at import)

        text = redact_urls(text)
    if text.isprintable() and len(text) <= limit:
        return text
    out: list[str] = []
    size = 0
    for c in text:
        if c.isprintable():
            piece = c
        elif c == "\n":
            piece = "\\n"
        elif ord(c) < 0x100:
            piece = f"\\x{ord(c):02x}"
        else:
            piece = f"\\u{ord(c):04x}" if ord(c) < 0x10000 else f"\\U{ord(c):08x}"
        size += len(piece)
        if size > limit:
            out.append(f"... ({len(text)} characters)")
            break
        out.append(piece)
    return "".join(out)


class LogLimiter:
    """Repeated lines are written a few times, then counted: at most ``burst`` lines of one kind
    (the line with its digits and quoted parts blanked) and ``total`` lines of every kind per
    ``period`` seconds (the caller's clock); what is held back is summed up in one line when the
    period ends. The kinds remembered are bounded (the oldest forgotten)."""

    def __init__(
        self, burst: int = 5, total: int = 50, period: float = 10.0, kinds: int = 256
    ) -> None:
        self.burst, self.total, self.period, self.kinds = burst, total, period, kinds
        self._window = -math.inf
        self._counts: dict[str, int] = {}
        self._written = 0
        self.suppressed = 0  #: lines held back in the current period
        self.suppressed_total = 0

    @staticmethod
    def kind(text: str) -> str:
        out, quoted = [], ""
        for c in text[:80]:
            if quoted:
                if c == quoted:
                    quoted = ""
                continue
            if c in "'\"":
                quoted = c
                out.append("?")
            elif not c.isdigit():
                out.append(c)
        return "".join(out)

    def admit(self, text: str, now: float) -> tuple[bool, str | None]:
        """Whether to write ``text`` now, and a summary line to write first (None: none)."""
        summary = None
        if now - self._window >= self.period:
            if self.suppressed:
                summary = (
                    f"{self.suppressed} repeated log line(s) held back in the last "
                    f"{self.period:g} s"
                )
            self._window, self._counts, self._written, self.suppressed = now, {}, 0, 0
        key = self.kind(text)
        seen = self._counts.get(key, 0)
        if seen >= self.burst or self._written >= self.total:
            self.suppressed += 1
            self.suppressed_total += 1
            return False, summary
        if key not in self._counts and len(self._counts) >= self.kinds:
            self._counts.pop(next(iter(self._counts)))
        self._counts[key] = seen + 1
        self._written += 1
        return True, summary

    def due(self, now: float) -> str | None:
        """The summary of the period that ended by ``now``, if lines were held back in it (call
        it periodically: without a next line, the summary would wait for one)."""
        if not self.suppressed or now - self._window < self.period:
            return None
        summary = f"{self.suppressed} repeated log line(s) held back in the last {self.period:g} s"
        self._window, self._counts, self._written, self.suppressed = now, {}, 0, 0
        return summary
