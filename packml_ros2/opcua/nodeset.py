"""The official OPC 30050 v1.01 NodeSet (``nodeset/Opc.Ua.PackML.NodeSet2.xml``, OPC Foundation,
MIT license: ``nodeset/LICENSE.txt``), read as data.

The server imports the file as it is (asyncua ``import_xml``) and instantiates the units from its
types (:mod:`.model`). This module reads the same file without a server (xml.etree) for what the
rest of the package needs to know about it: the three state machine types with their states
(NodeId, StateNumber), transitions (from, to, cause) and methods (input arguments), and the model's
version. Nothing here is written by hand: the Cleared state is ``i=71`` with StateNumber 19 and
Running ``i=75`` with 18 because the NodeSet says so.

Identifiers are the NodeSet's numeric ids in the PackML namespace; the server's index of that
namespace is known only at run time (``ua.NodeId(state.id, packml_ns)``).
"""

from __future__ import annotations

import datetime as dt
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

from ..core.numbers import State

NODESET = Path(__file__).resolve().parent / "nodeset" / "Opc.Ua.PackML.NodeSet2.xml"
PACKML_URI = "http://opcfoundation.org/UA/PackML/"

_UA = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
_TYPES = "{http://opcfoundation.org/UA/2008/02/Types.xsd}"
# standard (namespace 0) ids the reader needs
_HAS_COMPONENT, _HAS_PROPERTY, _HAS_TYPE_DEFINITION = "i=47", "i=46", "i=40"
_FROM_STATE, _TO_STATE, _HAS_CAUSE, _HAS_SUBSTATEMACHINE = "i=51", "i=52", "i=53", "i=117"
_STATE_TYPE, _TRANSITION_TYPE = "i=2307", "i=2310"


@dataclass(frozen=True)
class StateDef:
    name: str  # browse name, e.g. "Execute"
    id: int  # NodeId of the state object of the type (PackML namespace)
    number: int  # its StateNumber


@dataclass(frozen=True)
class TransitionDef:
    name: str  # e.g. "ExecuteToHolding"
    id: int
    from_state: str  # state names of the same machine
    to_state: str
    cause: str  # the method that causes it ("" = none, e.g. State Complete)


@dataclass(frozen=True)
class ArgumentDef:
    name: str
    data_type: tuple[int, int]  # (0 = standard or 1 = PackML namespace, numeric id)
    value_rank: int  # -1 scalar, 1 array


@dataclass(frozen=True)
class MethodDef:
    name: str
    id: int
    arguments: tuple[ArgumentDef, ...]


@dataclass(frozen=True)
class MachineDef:
    """One of the three nested state machine types and where it sits in a unit object."""

    name: str  # browse name of its instance: BaseStateMachine, MachineState, ExecuteState
    path: str  # relative path of the instance in a PackMLBaseObjectType object
    type_id: int
    states: tuple[StateDef, ...]
    transitions: tuple[TransitionDef, ...]
    methods: tuple[MethodDef, ...]
    sub_state: str  # the state whose sub state machine is the next machine ("" for the last)

    def state(self, name: str) -> StateDef:
        return next(s for s in self.states if s.name == name)


@dataclass(frozen=True)
class PackMLModel:
    version: str  # NamespaceVersion, e.g. "1.01"
    publication_date: dt.datetime
    base_object_type: int  # PackMLBaseObjectType
    objects_folder: int  # PackMLObjects, the entry point under Objects
    machines: tuple[MachineDef, ...]  # BaseStateMachine, MachineState, ExecuteState
    object_methods: tuple[MethodDef, ...]  # SetUnitMode, SetMachSpeed, ... of the object type
    #: the model's DataTypes by id, e.g. 16: PackMLDescriptorDataType
    data_types: Mapping[int, str] = field(hash=False, compare=False)

    def method(self, path: str) -> MethodDef:
        """A method by its path in a unit object: ``SetUnitMode``, ``BaseStateMachine/MachineState/
        ExecuteState/Start``."""
        folder, _, name = path.rpartition("/")
        methods = self.object_methods
        if folder:
            methods = next(m.methods for m in self.machines if m.path == folder)
        return next(m for m in methods if m.name == name)

    def places(self, state: int) -> tuple[StateDef | None, ...]:
        """The current state of each machine for a PackML state number (None: that sub state
        machine is not active), e.g. Execute -> (Cleared, Running, Execute)."""
        return _places(self).get(int(state), (None,) * len(self.machines))


@cache
def _places(model: PackMLModel) -> Mapping[int, tuple[StateDef | None, ...]]:
    """PackML state number -> current state per machine, from the names (Execute = EXECUTE)."""
    out: dict[int, tuple[StateDef | None, ...]] = {}
    outer: list[StateDef] = []  # the composite states containing the current machine
    for i, machine in enumerate(model.machines):
        for s in machine.states:
            if s.name == machine.sub_state:
                continue
            packml = State[s.name.upper()]
            out[int(packml)] = (*outer, s) + (None,) * (len(model.machines) - i - 1)
        if machine.sub_state:
            outer.append(machine.state(machine.sub_state))
    return out


class _Reader:
    def __init__(self, root: ET.Element) -> None:
        aliases = root.find(f"{_UA}Aliases")
        self.aliases = {a.get("Alias", ""): a.text or "" for a in aliases or ()}
        self.nodes = {e.get("NodeId", ""): e for e in root if e.tag.startswith(f"{_UA}UA")}
        self.root = root

    def refs(self, node: ET.Element, kind: str, forward: bool = True) -> Iterator[str]:
        for r in node.iter(f"{_UA}Reference"):
            rtype = r.get("ReferenceType", "")
            if (
                self.aliases.get(rtype, rtype) == kind
                and (r.get("IsForward") != "false") == forward
            ):
                yield r.text or ""

    def children(self, node: ET.Element) -> Iterator[ET.Element]:
        for kind in (_HAS_COMPONENT, _HAS_PROPERTY):
            for target in self.refs(node, kind):
                if target in self.nodes:
                    yield self.nodes[target]

    def by_name(self, name: str) -> ET.Element:
        return next(e for e in self.nodes.values() if e.get("BrowseName") == f"1:{name}")

    def typedef(self, node: ET.Element) -> str:
        return next(self.refs(node, _HAS_TYPE_DEFINITION), "")

    def child(self, node: ET.Element, name: str) -> ET.Element | None:
        return next((c for c in self.children(node) if _name(c) == name), None)

    def value(self, node: ET.Element) -> ET.Element | None:
        value = node.find(f"{_UA}Value")
        return value[0] if value is not None and len(value) else None

    def arguments(self, method: ET.Element) -> tuple[ArgumentDef, ...]:
        inputs = self.child(method, "InputArguments")
        value = self.value(inputs) if inputs is not None else None
        out = []
        for arg in value.iter(f"{_TYPES}Argument") if value is not None else ():
            data_type = arg.findtext(f"{_TYPES}DataType/{_TYPES}Identifier", "")
            out.append(
                ArgumentDef(
                    arg.findtext(f"{_TYPES}Name", ""),
                    _numeric(self.aliases.get(data_type, data_type)),
                    int(arg.findtext(f"{_TYPES}ValueRank", "-1")),
                )
            )
        return tuple(out)

    def methods(self, node: ET.Element) -> tuple[MethodDef, ...]:
        return tuple(
            MethodDef(_name(c), _numeric(c.get("NodeId", ""))[1], self.arguments(c))
            for c in self.children(node)
            if c.tag == f"{_UA}UAMethod"
        )

    def machine(self, type_node: ET.Element, name: str, path: str) -> MachineDef:
        states, transitions, sub_state = [], [], ""
        for c in self.children(type_node):
            kind = self.typedef(c)
            if kind == _STATE_TYPE:
                number = self.child(c, "StateNumber")
                value = self.value(number) if number is not None else None
                states.append(
                    StateDef(
                        _name(c),
                        _numeric(c.get("NodeId", ""))[1],
                        int(value.text or 0) if value is not None else 0,
                    )
                )
                if next(self.refs(c, _HAS_SUBSTATEMACHINE), None):
                    sub_state = _name(c)
            elif kind == _TRANSITION_TYPE:
                ends = [_name(self.nodes[next(self.refs(c, k))]) for k in (_FROM_STATE, _TO_STATE)]
                cause = next(self.refs(c, _HAS_CAUSE), "")
                transitions.append(
                    TransitionDef(
                        _name(c),
                        _numeric(c.get("NodeId", ""))[1],
                        ends[0],
                        ends[1],
                        _name(self.nodes[cause]) if cause else "",
                    )
                )
        return MachineDef(
            name,
            path,
            _numeric(type_node.get("NodeId", ""))[1],
            tuple(states),
            tuple(transitions),
            self.methods(type_node),
            sub_state,
        )


def _name(node: ET.Element) -> str:
    """The browse name without its namespace prefix."""
    return node.get("BrowseName", "").split(":", 1)[-1]


def _numeric(nodeid: str) -> tuple[int, int]:
    """``ns=1;i=16`` -> (1, 16); ``i=6`` -> (0, 6)."""
    ns, _, ident = nodeid.rpartition(";")
    return (int(ns[3:]) if ns else 0), int(ident.removeprefix("i="))


@cache
def load(path: Path = NODESET) -> PackMLModel:
    """The PackML model of the NodeSet at ``path`` (read once)."""
    r = _Reader(ET.parse(path).getroot())
    model = r.root.find(f"{_UA}Models/{_UA}Model")
    if model is None or model.get("ModelUri") != PACKML_URI:
        raise ValueError(f"{path} is not the OPC 30050 PackML NodeSet")
    base = r.by_name("PackMLBaseObjectType")
    machines = []
    parent, prefix = base, ""
    for type_name in (
        "PackMLBaseStateMachineType",
        "PackMLMachineStateMachineType",
        "PackMLExecuteStateMachineType",
    ):
        type_node = r.by_name(type_name)
        decl = next(c for c in r.children(parent) if r.typedef(c) == type_node.get("NodeId"))
        prefix = f"{prefix}/{_name(decl)}" if prefix else _name(decl)
        machines.append(r.machine(type_node, _name(decl), prefix))
        parent = type_node
    return PackMLModel(
        version=model.get("Version", ""),
        publication_date=dt.datetime.fromisoformat(model.get("PublicationDate", "")),
        base_object_type=_numeric(base.get("NodeId", ""))[1],
        objects_folder=_numeric(r.by_name("PackMLObjects").get("NodeId", ""))[1],
        machines=tuple(machines),
        object_methods=r.methods(base),
        data_types={
            _numeric(e.get("NodeId", ""))[1]: _name(e)
            for e in r.nodes.values()
            if e.tag == f"{_UA}UADataType"
        },
    )
