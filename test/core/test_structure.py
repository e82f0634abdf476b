"""Issue 28: the engine's modules import in one direction (no import circle in
``packml_ros2/core``), read from the source with :mod:`ast`: every import counts, those inside a
function and under ``TYPE_CHECKING`` too, since each is a dependency a reader has to follow."""

from __future__ import annotations

import ast
from collections.abc import Mapping
from pathlib import Path

import packml_ros2.core

CORE = Path(packml_ros2.core.__file__).parent
PACKAGE = "packml_ros2"


def modules(root: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, whether it is a package's ``__init__``)."""
    found: dict[str, tuple[Path, bool]] = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts.pop()
        found[".".join((PACKAGE, *parts))] = (path, is_package)
    return found


def import_graph(found: Mapping[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """Module -> the modules of ``found`` it imports (``from . import x`` is the module ``x``)."""
    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in found.items():
        package = name if is_package else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                base = package
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                if node.level:
                    target = f"{base}.{node.module}" if node.module else base
                else:
                    target = node.module or ""
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    if sub in found:
                        targets.add(sub)
                    elif target in found:
                        targets.add(target)
            elif isinstance(node, ast.Import):
                targets.update(a.name for a in node.names if a.name in found)
        graph[name] = targets - {name}
    return graph


def circles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, successors = work[-1]
            for w in successors:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def test_the_finder_finds_a_circle_and_only_circles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"e"}, "e": set(), "f": set()}
    assert circles(graph) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_every_kind_of_import() -> None:
    graph = import_graph(modules(CORE))
    core = f"{PACKAGE}.core"
    assert f"{core}.rules" in graph[f"{core}.machine"]  # from .rules import ...
    assert f"{core}.inputlog" in graph[f"{core}.machine"]  # from . import inputlog
    assert f"{core}.numbers" in graph[f"{core}.line.line"]  # from ..numbers import ...
    assert f"{core}.unit" in graph[core]  # under TYPE_CHECKING


def test_no_import_circle_in_the_engine() -> None:
    assert circles(import_graph(modules(CORE))) == []


def test_every_deadline_kind_has_one_handler_in_one_table() -> None:
    from packml_ros2.core.deadline_handlers import DeadlineHandlers
    from packml_ros2.core.deadlines import Due
    from packml_ros2.core.unit import Unit

    table = Unit.DEADLINE_HANDLERS
    assert table is DeadlineHandlers.DEADLINE_HANDLERS
    assert set(table) == set(Due)
    assert len({id(handler) for handler in table.values()}) == len(Due)
    # The machine fires them from the table, not by a name it makes up (``_on_<kind>``).
    source = (CORE / "machine.py").read_text()
    assert 'getattr(self, f"_on_' not in source


def test_every_input_is_framed_by_the_one_mechanism() -> None:
    """Each input method opens its frame with ``Unit._input`` (enter, record, and on leaving
    settle, publish, journal); nothing else opens or closes an evaluation by hand. The two that
    run most (``command``, ``em_complete``) frame themselves with the same steps."""
    import inspect

    from packml_ros2.core import inputlog
    from packml_ros2.core.unit import Unit

    hot = {"command", "em_complete"}
    for d in inputlog.INPUTS.values():
        if d.method in hot:
            continue
        source = inspect.getsource(getattr(Unit, d.method))
        assert "with self._input(" in source, d.method
        assert "self._enter()" not in source and "self._leave()" not in source, d.method
    for path in sorted(CORE.glob("*.py")):
        text = path.read_text()
        opened = text.count("self._enter()")
        closed = text.count("self._leave()")
        if path.name == "machine.py":  # _input opens, the frame and _fire close
            assert (opened, closed) == (1, 2), (opened, closed)
        else:
            assert (opened, closed) == (0, 0), path.name


def test_a_framed_input_records_encoded_fields_and_settles() -> None:
    from packml_ros2.core import Cmd, CommandRequest, State, Unit, unit_config
    from packml_ros2.core.config import Descriptor

    t = [0.0]
    unit = Unit(unit_config("framed", timeouts={State.STOPPED: 1.0}), clock=lambda: t[0])
    log: list[tuple[float, str, dict[str, object]]] = []
    unit.on_input = lambda at, name, fields: log.append((at, name, fields))
    t[0] = 5.0  # the timeout fell due at 1.0: the frame fires it before the input
    answer = unit.set_parameters([Descriptor(3, "p", "mm", 1.5)], "")
    assert answer.accepted
    assert log == [(5.0, "parameters", {"parameters": [{"id": 3, "name": "p", "unit": "mm",
                                                         "value": 1.5}], "source": "operator"})]  # fmt: skip
    assert any(e.id == unit.config.system_alarms.state_timeout for e in unit.alarms.history)
    unit.step([CommandRequest(Cmd.RESET)])
    assert log[-1][1:] == ("step", {"requests": [{"kind": "command", "command": int(Cmd.RESET),
                                                  "source": "operator"}]})  # fmt: skip
    assert unit.state is State.IDLE  # settled: Resetting completed at once (no EMs)
