"""EM liveliness by heartbeat leases, on a clock passed in (the unit node's clock).

Every report from an EM renews its lease; an EM whose lease ran out is lost. The unit node feeds
the changes to the engine (``em_seen`` / ``em_lost``), so the engine only ever sees the events and
replays exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class Liveliness:
    default_lease: float = 2.0
    last_seen: dict[str, float] = field(default_factory=dict)
    leases: dict[str, float] = field(default_factory=dict)
    alive: set[str] = field(default_factory=set)

    def seen(self, name: str, now: float, lease: float = 0.0) -> bool:
        """A report from ``name`` at ``now``; True when it was not alive before (new or back)."""
        self.last_seen[name] = now
        self.leases[name] = lease if lease > 0 else self.default_lease
        if name in self.alive:
            return False
        self.alive.add(name)
        return True

    def expired(self, now: float) -> list[tuple[str, float]]:
        """EMs whose lease ran out since the last call, with their lease; they are no longer alive."""
        gone = [
            (name, self.leases[name])
            for name in sorted(self.alive)
            if now - self.last_seen[name] > self.leases[name]
        ]
        for name, _ in gone:
            self.alive.discard(name)
        return gone

    def left(self, name: str) -> bool:
        """``name`` said goodbye; True if it was alive."""
        if name in self.alive:
            self.alive.discard(name)
            return True
        return False
