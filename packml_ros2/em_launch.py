"""How each equipment module (EM) of a cell file runs: checked before anything starts, listed by
``packml launch --check``, started alike by ``packml launch`` (one process or ``--processes``) and
``ros2 launch packml_ros2 cell.launch.py``.

An EM entry says how it runs with exactly one key of :data:`packml_ros2.core.config.EM_RUNS`:

- ``sim: {...}``: simulated (:mod:`packml_ros2.sim_em`; ``sim: {}`` for its defaults).
- ``run: my_pkg.gripper:Gripper``: your :class:`~packml_ros2.equipment_module.EquipmentModule`
  subclass, built as ``Gripper(em, unit, cell)`` (or by its classmethod ``from_cell(cell, unit,
  em, file=..., **node_kwargs)`` when it has one). In one process with the cell, or under
  ``--processes`` / ros2 launch in an EM host process (``em_node``); EMs naming the same
  ``process: <name>`` run composed in one process, on one executor.
- ``run: my_pkg.gripper:main`` (a function: an entry point's target), ``run: gripper_node --port
  3`` (a program on PATH, a console_scripts entry point, or a path relative to the cell file) or
  ``run: [gripper_node, --port, "3"]``: a program, started as its own process in every mode.
  ``{cell_file}``, ``{cell}``, ``{unit}`` and ``{em}`` in its arguments are replaced, and
  ``PACKML_CELL_FILE``, ``PACKML_CELL``, ``PACKML_UNIT``, ``PACKML_EM`` are set in its environment.
- ``external: true`` (or ``external: {timeout: 120}``): started elsewhere (the robot's own PC).
  The launcher starts nothing, says which EMs it still waits for, and gives up waiting after the
  timeout (default :data:`EXTERNAL_TIMEOUT` s) with a message; the unit refuses motion commands
  until the EM is online.
- any other key of ``EM_RUNS``: the class of that row, which reads its block (``from_cell``) and
  may check it (classmethod ``check_cell(cell, unit, em, file)`` returning (key path, problem)
  pairs).

An entry that says none of these is refused (an integrator's own EM silently replaced by a
simulated one is what this prevents); ``--sim`` simulates every EM of the file instead (a dry run
of a real cell: each with its ``sim:`` block if it has one, else the defaults).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import re
import shlex
import shutil
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .core.config import EM_RUNS, CellConfig, EmConfig, UnitConfig

#: Seconds the launcher waits for an external EM unless its entry says ``timeout``.
EXTERNAL_TIMEOUT = 60.0
_TARGET = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")
SIM_CLASS = EM_RUNS["sim"]


@dataclass(frozen=True)
class EmRun:
    """How one EM runs, resolved and checked."""

    unit: str
    em: str
    kind: str  # "class": a node the launcher builds | "program" | "external"
    key: str  # the cell-file key that said so (sim, run, external, ...)
    target: str = ""  # class: module:Class
    argv: tuple[str, ...] = ()  # program: the command, placeholders replaced
    process: str = ""  # class: EMs naming one process share it
    timeout: float = 0.0  # external: how long the launcher waits for it

    @property
    def name(self) -> str:
        return f"{self.unit}/{self.em}"

    def describe(self) -> str:
        """One line for ``packml launch --check``."""
        if self.kind == "external":
            return f"external: started elsewhere; waited for {self.timeout:g} s"
        if self.kind == "program":
            return f"run: program {shlex.join(self.argv)[:200]}"
        where = f" (in process {self.process!r})" if self.process else ""
        if self.key == "sim":
            return f"sim: simulated{where}"
        return f"{self.key}: {self.target}{where}"


def resolve(
    cell: CellConfig, file: str | os.PathLike[str], simulate: bool = False
) -> tuple[list[EmRun], list[tuple[str, str]]]:
    """Every EM of the cell and how it runs, and the problems (key path, sentence) found."""
    runs: list[EmRun] = []
    problems: list[tuple[str, str]] = []
    for uname, unit in cell.units.items():
        for em in unit.equipment_modules:
            path = f"units.{uname}.equipment_modules.{em.name}"
            found = _resolve(cell, unit, em, Path(file), path, simulate)
            if isinstance(found, EmRun):
                runs.append(found)
            else:
                problems += found
    return runs, problems


def _resolve(
    cell: CellConfig, unit: UnitConfig, em: EmConfig, file: Path, path: str, simulate: bool
) -> EmRun | list[tuple[str, str]]:
    how = "sim" if simulate else em.runs
    base = EmRun(unit.name, em.name, "class", how, process=em.process)
    if how == "":
        keys = ", ".join(f"{k}:" for k in EM_RUNS)
        return [
            (
                path,
                f"says not how it runs: give one of {keys} (sim: {{}} simulates it with "
                "the defaults; run: module:Class, an entry point or a program starts your "
                "EM; external: true waits for an EM started elsewhere)",
            )
        ]
    if how == "sim":
        return _replace(base, target=SIM_CLASS)
    if em.process and how in ("external",):
        return [(f"{path}.process", "an external EM is not started here: it has no process")]
    if how == "external":
        return _external(base, em.spec, f"{path}.external")
    if how == "run":
        return _run(cell, unit, em, file, base, f"{path}.run")
    target = EM_RUNS[how]  # a row of the table: its class reads the block
    problems = _class_problems(target, f"{path}.{how}")
    if problems:
        return problems
    check = getattr(load_target(target), "check_cell", None)
    if check is not None:
        problems = list(check(cell, unit.name, em.name, str(file)))
        if problems:
            return problems
    return _replace(base, target=target)


def _replace(run: EmRun, **changes: Any) -> EmRun:
    from dataclasses import replace

    return replace(run, **changes)


def _external(base: EmRun, spec: Any, path: str) -> EmRun | list[tuple[str, str]]:
    if spec is True:
        return _replace(base, kind="external", timeout=EXTERNAL_TIMEOUT)
    if isinstance(spec, Mapping):
        unknown = [str(k) for k in spec if k != "timeout"]
        timeout = spec.get("timeout", EXTERNAL_TIMEOUT)
        if unknown:
            return [(f"{path}.{unknown[0]}", "unknown key; valid keys: timeout")]
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or timeout <= 0:
            return [(f"{path}.timeout", "expected seconds > 0 (how long to wait for the EM)")]
        return _replace(base, kind="external", timeout=float(timeout))
    return [
        (
            path,
            "expected true (or {timeout: seconds}): the EM is started elsewhere; to have "
            "the launcher start it, use run: or sim: instead",
        )
    ]


def _run(
    cell: CellConfig, unit: UnitConfig, em: EmConfig, file: Path, base: EmRun, path: str
) -> EmRun | list[tuple[str, str]]:
    spec = em.spec
    if isinstance(spec, str):
        try:
            argv = shlex.split(spec)
        except ValueError as exc:
            return [(path, f"cannot split into a command: {exc}")]
    elif isinstance(spec, list) and all(isinstance(a, (str, int, float)) for a in spec):
        argv = [str(a) for a in spec]
    else:
        argv = []
    if not argv:
        return [
            (
                path,
                "expected module:Class, an entry point or a program with its arguments "
                "(a string or a list of strings)",
            )
        ]
    first, args = argv[0], argv[1:]
    names = {"cell_file": str(file), "cell": cell.cell, "unit": unit.name, "em": em.name}
    try:
        args = [a.format(**names) for a in args]
    except (KeyError, IndexError, ValueError) as exc:
        return [
            (
                path,
                f"unknown placeholder in the arguments ({exc}); valid: "
                "{cell_file}, {cell}, {unit}, {em}",
            )
        ]
    if _TARGET.match(first):
        problems = _class_problems(first, path, functions=True)
        if problems:
            return problems
        if isinstance(load_target(first), type):
            if args:
                return [
                    (
                        path,
                        f"{first} is a class: it takes no arguments (its node is built "
                        "with the EM's name, unit and cell)",
                    )
                ]
            return _replace(base, target=first)
        command = _python_call(first)
    else:
        program = _program(first, file.resolve().parent)
        if program is None:
            return [
                (
                    path,
                    f"executable {first!r} not found (not on PATH, not a console_scripts "
                    "entry point, not a file relative to the cell file)",
                )
            ]
        command = program
    if em.process:
        return [
            (
                path.rsplit(".", 1)[0] + ".process",
                "only Python EM classes (run: module:Class, sim:) share a process; a program "
                "runs as its own process",
            )
        ]
    return _replace(base, kind="program", argv=(*command, *args), target="")


def _python_call(target: str) -> list[str]:
    module, attr = target.split(":")
    code = f"import sys, importlib; sys.exit(importlib.import_module({module!r}).{attr}())"
    return [sys.executable, "-c", code]


def _program(name: str, base: Path) -> list[str] | None:
    """The command for program ``name``: on PATH, a file relative to the cell file, or a
    console_scripts entry point of the installed packages (run with this interpreter)."""
    if "/" in name:
        candidate = Path(name) if Path(name).is_absolute() else base / name
        return [str(candidate)] if os.access(candidate, os.X_OK) and candidate.is_file() else None
    found = shutil.which(name)
    if found is not None:
        return [found]
    for ep in importlib.metadata.entry_points(group="console_scripts", name=name):
        return _python_call(ep.value.split("[")[0].strip())
    return None


def load_target(target: str) -> Any:
    """The object named by ``module:attr.attr``."""
    module, attr = target.split(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _class_problems(target: str, path: str, functions: bool = False) -> list[tuple[str, str]]:
    from .equipment_module import EquipmentModule

    module, attr = target.split(":")
    try:
        importlib.import_module(module)
    except Exception as exc:  # any import-time failure of the integrator's module
        return [(path, f"module {module!r} cannot be imported: {type(exc).__name__}: {exc}")]
    try:
        obj = load_target(target)
    except AttributeError:
        return [(path, f"module {module!r} has no {attr!r}")]
    if isinstance(obj, type):
        if not issubclass(obj, EquipmentModule):
            return [
                (
                    path,
                    f"{target} is a class but not an EquipmentModule (packml_ros2."
                    "equipment_module): subclass it, or name a program to run",
                )
            ]
        return []
    if functions and callable(obj):
        return []
    return [
        (
            path,
            f"{target} is not an EquipmentModule class" + (" or a function" if functions else ""),
        )
    ]


# -- building and starting -------------------------------------------------------------------------
def build(run: EmRun, cell: CellConfig, file: str | os.PathLike[str], **node_kwargs: Any) -> Any:
    """The node of a ``class`` EM."""
    cls = load_target(run.target)
    from_cell = getattr(cls, "from_cell", None)
    if from_cell is not None:
        return from_cell(cell, run.unit, run.em, file=str(file), **node_kwargs)
    return cls(run.em, run.unit, cell.cell, **node_kwargs)


def program_env(run: EmRun, cell: CellConfig, file: str | os.PathLike[str]) -> dict[str, str]:
    """What a program EM finds in its environment, besides the launcher's."""
    return {
        "PACKML_CELL_FILE": str(file),
        "PACKML_CELL": cell.cell,
        "PACKML_UNIT": run.unit,
        "PACKML_EM": run.em,
    }


def groups(runs: Sequence[EmRun]) -> list[list[EmRun]]:
    """The ``class`` EMs by process: one list per process (``process:`` names shared ones)."""
    out: dict[str, list[EmRun]] = {}
    for r in runs:
        if r.kind == "class":
            out.setdefault(r.process or f"/{r.name}", []).append(r)
    return list(out.values())


def host_arguments(group: Sequence[EmRun], file: str, simulate: bool) -> tuple[str, ...]:
    """The arguments of ``em_node`` for one process of EMs."""
    first = group[0]
    names = [r.em if r.unit == first.unit else r.name for r in group]
    return (*(("--sim",) if simulate else ()), file, first.unit, *names)


def host_main(argv: Sequence[str] | None = None) -> int:
    """``em_node [--sim] <cell.yaml> <unit> <em> [<em> | <unit>/<em> ...]``: the named EMs of a
    cell file, composed in one process on one executor, each as the file says it runs (an entry
    that does not say, or all with ``--sim``: simulated)."""
    from . import run as runmod
    from .core import ConfigError, load_cell

    args = runmod.init(argv)
    simulate = "--sim" in args
    args = [a for a in args if a != "--sim"]
    if len(args) < 3:
        print(host_main.__doc__, file=sys.stderr)
        return 2
    cell_file, unit, *names = args
    nodes: list[Any] = []
    try:
        cell = load_cell(cell_file)
        for n in names:
            uname, _, ename = n.rpartition("/")
            uname = uname or unit
            config = cell.units.get(uname)
            em = (
                next((e for e in config.equipment_modules if e.name == ename), None)
                if config
                else None
            )
            if config is None or em is None:
                raise ConfigError(
                    cell_file, [(f"units.{uname}.equipment_modules", f"no EM {ename!r}")]
                )
            # started by hand for an entry that says not how it runs: simulated, as asked
            path = f"units.{uname}.equipment_modules.{ename}"
            r = _resolve(cell, config, em, Path(cell_file), path, simulate or not em.runs)
            if not isinstance(r, EmRun):
                raise ConfigError(cell_file, r)
            if r.kind != "class":
                raise ConfigError(cell_file, [(path, f"{r.describe()}: not an EM of this process")])
            nodes.append(build(r, cell, cell_file))
    except (ConfigError, OSError) as exc:
        for node in nodes:
            node.destroy_node()
        print(f"em_node: {exc}", file=sys.stderr)
        return 2

    def close() -> None:
        for node in nodes:
            node.close()

    return runmod.spin(nodes, on_shutdown=close)
