"""The unit's Admin and Command tags as inputs: resetting times and counters, the machine speed,
parameters and products (docs/packml.md sections 5, 6). Times are
:class:`~.times.ModeStateTimes`', counters :class:`~.counters.Counters`'.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from . import inputlog
from .config import Descriptor, Product
from .limits import speed_refusal
from .machine import UnitMachine
from .reasons import Answer, Reason
from .rules import (
    OPERATOR,
)


class TagInputs(UnitMachine):
    """The tag inputs of a :class:`~.unit.Unit` (times, counters, speed, parameters, products)."""

    __slots__ = ()

    # -- times, counters, speed, parameters --------------------------------------------------------
    def reset_times(self, all_times: bool = False, source: str = OPERATOR) -> Answer:
        """Reset the current mode's times (and its states'), or every time with ``all_times``."""
        source = source or OPERATOR
        with self._input(inputlog.TIMES_RESET, all_times, source):
            refused = self._locked("resetting times", source)
            if refused is not None:
                return refused
            if all_times:
                self.times.reset_all(self._t)
                msg = "all times reset"
            else:
                self.times.reset_current_mode(self._t)
                msg = f"times of {self.mode_def.name} reset"
            self.alarms.log_event(f"{msg} by {source}", self._t, source=source)
            return Answer.ok(msg)

    def reset_counters(self, source: str = OPERATOR) -> Answer:
        """``Count`` of every counter to 0; ``AccCount`` is never reset."""
        source = source or OPERATOR
        with self._input(inputlog.COUNTERS_RESET, source):
            refused = self._locked("resetting counters", source)
            if refused is not None:
                return refused
            self.counters.reset()
            self.alarms.log_event(f"counters reset by {source}", self._t, source=source)
            return Answer.ok("counters reset (AccCount kept)")

    def set_mach_speed(self, speed: float, source: str = OPERATOR) -> Answer:
        source = source or OPERATOR
        with self._input(inputlog.SPEED, speed, source):
            refused = self._locked(f"MachSpeed {speed:g}", source)
            if refused is not None:
                return refused
            why = speed_refusal(speed, self.config)
            if why is not None:
                return Answer.no(Reason.INVALID_ARGUMENT, why)
            self.mach_speed = float(speed)
            self._rev += 1
            return Answer.ok(f"MachSpeed {speed:g}")

    def set_parameters(self, parameters: Iterable[Descriptor], source: str = OPERATOR) -> Answer:
        """Set ``Command.Parameter[#]`` entries, matched by ID (a new ID takes a free slot)."""
        params = list(parameters)
        source = source or OPERATOR
        with self._input(inputlog.PARAMETERS, params, source):
            return self._locked("setting parameters", source) or self._merge(
                self.parameters, params, lambda p: p.id, self.config.sizes.parameters, "parameter"
            )

    def set_product(self, products: Iterable[Product], source: str = OPERATOR) -> Answer:
        """Set ``Command.Product[#]`` entries, matched by ProductID."""
        items = list(products)
        source = source or OPERATOR
        with self._input(inputlog.PRODUCTS, items, source):
            refused = self._locked("setting products", source)
            if refused is not None:
                return refused
            sizes = self.config.sizes
            for p in items:
                too_many = (
                    len(p.process_variables) > sizes.process_variables
                    or len(p.ingredients) > sizes.ingredients
                )
                if too_many:
                    return Answer.no(
                        Reason.INVALID_ARGUMENT,
                        f"product {p.product_id}: more entries than the arrays hold "
                        f"({sizes.process_variables} process variables, {sizes.ingredients} ingredients)",
                    )
            return self._merge(
                self.products, items, lambda p: p.product_id, sizes.products, "product"
            )

    def _merge(
        self,
        target: list[Any],
        items: list[Any],
        key: Callable[[Any], int],
        capacity: int,
        what: str,
    ) -> Answer:
        index = {key(x): i for i, x in enumerate(target)}
        new = {key(x) for x in items} - set(index)
        if len(target) + len(new) > capacity:
            return Answer.no(
                Reason.INVALID_ARGUMENT,
                f"{len(target) + len(new)} {what}s would not fit; the array holds {capacity}",
            )
        for x in items:
            if key(x) in index:
                target[index[key(x)]] = x
            else:
                index[key(x)] = len(target)
                target.append(x)
        self._rev += 1
        return Answer.ok(f"{len(items)} {what}(s) set")
