"""Bag regression tests in three lines, with the ``packml_replay`` fixture of the pytest plugin::

    def test_normal_production(packml_replay):
        packml_replay("test/bags/normal_production").assert_matches()

``packml_replay(bag, config=None, units=())`` replays the bag offline (relative paths are taken
from the pytest root directory) and returns a :class:`~packml_ros2.bag.replay.ReplayResult`:
``.ok``, ``.report()``, ``.digest()``, and ``.assert_matches()``, which fails the test with the
first diverging transition and the inputs that led to it. Without pytest: :func:`replay_bag`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from ..bag.replay import ReplayResult, replay

__all__ = ["BagReplayer", "ReplayResult", "replay_bag"]


def replay_bag(
    bag: str | os.PathLike[str],
    config: str | os.PathLike[str] | None = None,
    units: Sequence[str] = (),
) -> ReplayResult:
    """Replay-check ``bag`` (see ``packml replay --check``)."""
    return replay(Path(bag), None if config is None else Path(config), units)


class BagReplayer:
    """What the ``packml_replay`` fixture returns: ``replayer(bag) -> ReplayResult``."""

    def __init__(self, root: str | os.PathLike[str] = ".") -> None:
        self.root = Path(root)

    def path(self, bag: str | os.PathLike[str]) -> Path:
        p = Path(bag)
        return p if p.is_absolute() or p.exists() else self.root / p

    def __call__(
        self,
        bag: str | os.PathLike[str],
        config: str | os.PathLike[str] | None = None,
        units: Sequence[str] = (),
    ) -> ReplayResult:
        return replay_bag(self.path(bag), None if config is None else self.path(config), units)
