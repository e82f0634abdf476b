"""``packml_ros2.client``: a proxy whose first reader of a latched topic stays deaf (its unit's
writer on the graph, nothing delivered: seen in CI about once in 4 600 tests) subscribes again
half way through its wait, or, followed for longer, by its own watch; and gets the sample the
new reader takes at once."""

from __future__ import annotations

import time
from typing import Any

import pytest

from packml_ros2 import client
from packml_ros2.cli.status import wait_cell
from packml_ros2.client import CellProxy, UnitProxy
from test.ros.test_unit_services import UNIT, make_unit

__all__ = ["make_unit"]  # the fixture


class DeafFirst(UnitProxy):
    """A proxy whose first reader of each topic drops everything it receives."""

    def _subscribe(self, topic: str) -> Any:
        first = not hasattr(self, "_deafened")
        if first:
            self._deafened: set[str] = set()
        if topic in self._deafened:
            return super()._subscribe(topic)
        self._deafened.add(topic)
        callback = self._callbacks[topic]
        self._callbacks[topic] = lambda msg: None
        try:
            return super()._subscribe(topic)
        finally:
            self._callbacks[topic] = callback


@pytest.fixture
def no_watch(monkeypatch: pytest.MonkeyPatch) -> None:
    """A watch too slow to act within the test: what remedies deafness is the wait's own."""
    monkeypatch.setattr(client, "DEAF_CHECK", 60.0)


@pytest.mark.usefixtures("no_watch")
def test_a_deaf_proxy_subscribes_again_and_gets_the_status(ros: Any, make_unit: Any) -> None:
    unit = make_unit()
    proxy = DeafFirst(ros.node, unit.base, topics=("status", "admin"))
    assert proxy.wait_status(timeout=8).state_current_name == "STOPPED"
    assert proxy.wait_admin(timeout=8) is not None
    assert not proxy.deaf("status") and not proxy.deaf("admin")
    # a unit that is not there: nothing to subscribe again to; the wait ends with its timeout
    absent = DeafFirst(ros.node, f"/{unit.cell}/nobody", topics=("status",))
    assert absent.deaf("status") is False and absent.publishers("status") == 0


@pytest.mark.usefixtures("no_watch")
def test_packml_status_waits_on_a_deaf_unit_and_subscribes_again(ros: Any, make_unit: Any) -> None:
    unit = make_unit()
    cell = CellProxy(ros.node, unit.cell, topics=("status", "admin"))
    deaf = cell.units[UNIT] = DeafFirst(ros.node, unit.base, topics=("status", "admin"))
    assert wait_cell(cell, 8) == {}
    assert deaf.status is not None and deaf.admin is not None and deaf._deaf_tries == 0


def test_a_deaf_proxy_that_nobody_waits_on_hears_its_unit_by_its_watch(
    ros: Any, make_unit: Any
) -> None:
    """The coordinator, the HMI and the OPC UA face follow units without waiting: the proxy's
    own watch subscribes again to what never came, while the unit's writer is on the graph."""
    unit = make_unit()
    proxy = DeafFirst(ros.node, unit.base, topics=("status", "admin", "alarms"))
    deadline = time.monotonic() + 3 * client.DEAF_CHECK + 5
    while time.monotonic() < deadline and (
        proxy.status is None or proxy.admin is None or proxy.alarms is None
    ):
        time.sleep(0.05)
    assert proxy.status is not None and proxy.admin is not None and proxy.alarms is not None
    assert proxy._deaf_tries == 1  # once was enough
    proxy.destroy()
