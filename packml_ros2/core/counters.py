"""Production counters (docs/packml.md §6): ProdConsumed/Processed/DefectiveCount[i] with a
resettable ``Count`` and a lifetime ``AccCount``; EMs increment them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

INT32_MAX = 2**31 - 1
KINDS = ("consumed", "processed", "defective")


@dataclass(frozen=True, slots=True)
class CounterDef:
    id: int
    name: str
    unit: str = ""


@dataclass(slots=True)
class Counter:
    """``{ID, Name, Unit, Count, AccCount}``."""

    id: int
    name: str
    unit: str
    count: int = 0
    acc_count: int = 0


def _wrap(value: int) -> int:
    """Int32 counters roll over to 0 after 2^31-1; they never go negative."""
    if value < 0:
        return 0
    return value % (INT32_MAX + 1)


class Counters:
    """The three counter arrays, each of a fixed capacity."""

    def __init__(self, capacity: int, defs: dict[str, tuple[CounterDef, ...]]) -> None:
        self.capacity = capacity
        self.version = 0  # +1 on every change
        self.arrays: dict[str, list[Counter]] = {}
        for kind in KINDS:
            configured = defs.get(kind, ())
            self.arrays[kind] = [Counter(d.id, d.name, d.unit) for d in configured] + [
                Counter(0, "", "") for _ in range(capacity - len(configured))
            ]

    def add(self, kind: str, index: int, increment: int) -> str | None:
        """Add to counter ``index`` of ``kind``; the reason when that is impossible, else None."""
        array = self.arrays.get(kind)
        if array is None:
            return f"no counter kind {kind!r} (one of {', '.join(KINDS)})"
        if not 0 <= index < len(array):
            return f"{kind} counter index {index} outside 0..{len(array) - 1}"
        if increment < 0:
            return (
                f"increment {increment} is negative: counters only count up (Count is reset with "
                "reset_counters, AccCount never)"
            )
        c = array[index]
        self.version += 1
        c.count = _wrap(c.count + increment)
        c.acc_count = _wrap(c.acc_count + increment)
        return None

    def reset(self) -> None:
        """``Count`` of every counter to 0; ``AccCount`` is lifetime and stays."""
        self.version += 1
        for array in self.arrays.values():
            for c in array:
                c.count = 0

    def snapshot(self, kind: str) -> tuple[Counter, ...]:
        """Copies of the counters of ``kind``, shared until the next change (Admin views are taken
        every second; counts change less often)."""
        cache: dict[str, tuple[int, tuple[Counter, ...]]] = self.__dict__.setdefault(
            "_snapshots", {}
        )
        hit = cache.get(kind)
        if hit is None or hit[0] != self.version:
            copies = tuple(
                Counter(c.id, c.name, c.unit, c.count, c.acc_count) for c in self.arrays[kind]
            )
            cache[kind] = hit = (self.version, copies)
        return hit[1]

    def total(self, kind: str) -> int:
        return sum(c.count for c in self.arrays[kind])

    def to_dict(self) -> dict[str, Any]:
        return {k: [[c.count, c.acc_count] for c in a] for k, a in self.arrays.items()}

    def restore(self, data: dict[str, Any]) -> None:
        for kind, values in data.items():
            for c, pair in zip(self.arrays.get(kind, []), values, strict=False):
                c.count, c.acc_count = int(pair[0]), int(pair[1])
