"""EM liveliness by heartbeat leases, on a clock passed in (the unit node's clock).

Every report from an EM renews its lease; an EM silent for longer than the unit's configured
``em_lease`` is lost. The configuration decides, not the EM: the lease an EM announces in its
reports only tells how often it beats (a quarter of it), and one announcing more than the unit's
lease is warned about once, since it will be lost between its heartbeats. The unit node feeds the
changes to the engine (``em_seen`` / ``em_lost``), so the engine only ever sees the events and
replays exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class Liveliness:
    lease: float = 2.0  #: the unit's em_lease (seconds): authoritative
    last_seen: dict[str, float] = field(default_factory=dict)
    alive: set[str] = field(default_factory=set)
    announced: dict[str, float] = field(default_factory=dict)  #: what each EM said it keeps

    def seen(self, name: str, now: float) -> bool:
        """A report from ``name`` at ``now``; True when it was not alive before (new or back)."""
        self.last_seen[name] = now
        if name in self.alive:
            return False
        self.alive.add(name)
        return True

    def announce(self, name: str, lease: float) -> str | None:
        """The lease ``name`` announces: a warning, once per announced value, when its heartbeats
        (every quarter of it) would not keep it alive under the unit's lease."""
        if lease <= 0 or self.announced.get(name) == lease:
            return None
        self.announced[name] = lease
        if lease <= self.lease:
            return None
        return (
            f"EM {name} announces a {lease:g} s lease (a heartbeat every {lease / 4:g} s), longer "
            f"than the unit's em_lease {self.lease:g} s, which decides: it will be lost when it "
            "is silent that long; give it the unit's lease"
        )

    def expired(self, now: float) -> list[tuple[str, float]]:
        """EMs silent for longer than the lease since the last call, with the lease; they are no
        longer alive."""
        lease = self.lease
        gone = [(name, lease) for name in sorted(self.alive) if now - self.last_seen[name] > lease]
        for name, _ in gone:
            self.alive.discard(name)
        return gone

    def next_expiry(self) -> float:
        """When the next alive EM expires if it stays silent (``inf``: none is alive): the unit
        node arms its timer for it instead of polling."""
        if not self.alive:
            return math.inf
        last_seen = self.last_seen
        return min(last_seen[name] for name in self.alive) + self.lease

    def forget(self, name: str) -> None:
        """``name`` is not an EM of the unit (its registration was refused): keep nothing of it
        (a flood of made-up names must not grow memory)."""
        self.last_seen.pop(name, None)
        self.alive.discard(name)
        self.announced.pop(name, None)

    def left(self, name: str) -> bool:
        """``name`` said goodbye; True if it was alive."""
        if name in self.alive:
            self.alive.discard(name)
            return True
        return False
