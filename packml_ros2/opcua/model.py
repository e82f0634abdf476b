"""The OPC 30050 address space: the official NodeSet loaded at start, the units instantiated from
its types.

:meth:`AddressSpace.load_nodeset` imports ``nodeset/Opc.Ua.PackML.NodeSet2.xml`` (OPC 30050 v1.01,
OPC Foundation) as it is: types, data types with their encodings, reference types, the
``PackMLObjects`` folder and the namespace metadata (NamespaceVersion 1.01, PublicationDate
2020-10-08). Nothing of the model is written here by hand.

:meth:`AddressSpace.build_unit` creates one ``PackMLBaseObjectType`` object per unit under
``Objects/PackMLObjects`` the way OPC UA Part 3 instantiates a type: every Mandatory child of the
type's instance declarations (the object type's own declarations first, then those of each
child's type definition and its supertypes) and the Optional ones this server supports
(:data:`OPTIONAL`), recursively, with the declarations' browse names, data types, value ranks
and defaults. The state machine methods (Abort ... ToComplete) are Optional in the NodeSet and
offered; RemoteCommand, SetInterlock, MaterialInterlock are not.

The instances live in the server's own namespace (``urn:packml_ros2:<cell>``, index 1) with string
NodeIds ``<unit>.<path>`` (e.g. ``filler.Status.StateRequested``). :class:`UnitNodes` maps the
relative browse paths used by :mod:`.mapping` (``Status/StateRequested``,
``BaseStateMachine/MachineState/CurrentState/Number``) to those NodeIds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.manage_nodes import create_data_type
from asyncua.common.ua_utils import get_node_supertypes

from .mapping import Step
from .nodeset import NODESET, PACKML_URI, PackMLModel, load

I = ua.ObjectIds  # noqa: E741
#: Optional instance declarations the units get (paths relative to the unit object). Every
#: method of the three state machines is offered too; see :func:`wanted`.
OPTIONAL = frozenset(
    {
        "PackMLVersion",
        "TagID",
        "Status/UnitModeRequested",
        "Status/UnitModeChangeInProcess",
        "Status/StateRequested",
        "Status/StateChangeInProcess",
        "Status/Parameter",
        "Status/Product",
        "Status/RemoteParameter",
    }
)
#: Optional declarations this server does not offer (no counterpart in the units' services).
NOT_OFFERED = frozenset({"RemoteCommand", "SetInterlock"})

#: Variables this implementation adds to the Status object, in the server's own namespace.
STATUS_EXTENSIONS: tuple[tuple[str, int, str], ...] = (
    ("StateCurrent", I.Int32, "PackTags Status.StateCurrent: the TR88 state number (packml_ros2 extension)"),
)  # fmt: skip


def wanted(path: str, node_class: ua.NodeClass) -> bool:
    """Whether the Optional declaration at ``path`` is instantiated."""
    if path in NOT_OFFERED:
        return False
    return (
        path in OPTIONAL
        or path.startswith("Admin/")  # all of PackMLAdminObjectType except nothing
        or path.endswith("/CurrentState/Number")  # StateVariableType's Number: the StateNumber
        or (node_class == ua.NodeClass.Method and path.startswith("BaseStateMachine/"))
    )


@dataclass
class UnitNodes:
    """The nodes of one unit instance: relative path -> NodeId."""

    unit: str
    object: ua.NodeId
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    methods: dict[str, ua.NodeId] = field(default_factory=dict)
    mode_enum: ua.NodeId | None = None
    #: transitions of the unit's rules that the NodeSet does not model (e.g. Held -> Completing)
    extra_transitions: dict[Step, ua.NodeId] = field(default_factory=dict)


class AddressSpace:
    """Loads the PackML NodeSet (once) and builds the unit instances of a server."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self.session = server.iserver.isession
        self.p = 0  # PackML namespace index
        self.u = 1  # instance namespace index (the server's application URI)
        self.model: PackMLModel = load()
        self._declarations: dict[tuple[ua.NodeId, ua.NodeId], list[ua.ReferenceDescription]] = {}
        self._rules: dict[ua.NodeId, int] = {}

    def pid(self, ident: int) -> ua.NodeId:
        return ua.NodeId(ident, self.p)

    async def load_nodeset(self) -> None:
        await self.server.import_xml(str(NODESET))
        self.p = (await self.server.get_namespace_array()).index(PACKML_URI)
        await self.server.load_data_type_definitions()

    # -- low level ---------------------------------------------------------------------------------
    async def _add(
        self,
        nodeclass: ua.NodeClass,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        ref: ua.NodeId | int,
        attrs: Any,
        typedef: ua.NodeId | int | None = None,
        description: ua.LocalizedText | str = "",
    ) -> ua.NodeId:
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nodeid
        item.BrowseName = bname
        item.NodeClass = nodeclass
        item.ParentNodeId = parent
        item.ReferenceTypeId = ref if isinstance(ref, ua.NodeId) else ua.NodeId(ref)
        if typedef is not None:
            item.TypeDefinition = typedef if isinstance(typedef, ua.NodeId) else ua.NodeId(typedef)
        attrs.DisplayName = ua.LocalizedText(bname.Name)
        if isinstance(description, str):
            description = ua.LocalizedText(description or bname.Name)
        attrs.Description = description
        attrs.WriteMask = 0
        attrs.UserWriteMask = 0
        item.NodeAttributes = attrs
        result = (await self.session.add_nodes([item]))[0]
        result.StatusCode.check()
        return result.AddedNodeId

    async def _ref(self, source: ua.NodeId, target: ua.NodeId, reftype: int) -> None:
        item = ua.AddReferencesItem()
        item.SourceNodeId, item.TargetNodeId = source, target
        item.ReferenceTypeId, item.IsForward = ua.NodeId(reftype), True
        for status in await self.session.add_references([item]):
            status.check()

    async def var(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        dtype: ua.NodeId,
        value: ua.Variant | None = None,
        rank: int = -1,
        typedef: ua.NodeId | int = I.BaseDataVariableType,
        ref: ua.NodeId | int = I.HasComponent,
        description: ua.LocalizedText | str = "",
    ) -> ua.NodeId:
        attrs = ua.VariableAttributes()
        attrs.DataType = dtype
        attrs.ValueRank = rank
        attrs.ArrayDimensions = [0] * rank if rank > 0 else None
        attrs.AccessLevel = ua.AccessLevel.CurrentRead.mask
        attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
        attrs.Historizing = False
        if value is not None:
            attrs.Value = value
        return await self._add(
            ua.NodeClass.Variable, nodeid, bname, parent, ref, attrs, typedef, description
        )

    async def enum(self, nodeid: ua.NodeId, bname: ua.QualifiedName, values: Mapping[int, str],
                   values_id: ua.NodeId) -> ua.NodeId:  # fmt: skip
        """An enumeration DataType with explicit values (gaps allowed: user modes 4..31)."""
        node = await create_data_type(self.server.get_node(ua.NodeId(I.Enumeration)), nodeid, bname)
        edef = ua.EnumDefinition()
        edef.Fields = [
            ua.EnumField(Value=v, DisplayName=ua.LocalizedText(n), Name=n)
            for v, n in values.items()
        ]
        await node.write_data_type_definition(edef)
        enum_values = [
            ua.EnumValueType(Value=v, DisplayName=ua.LocalizedText(n)) for v, n in values.items()
        ]
        await self.var(
            values_id, ua.QualifiedName("EnumValues", 0), node.nodeid, ua.NodeId(I.EnumValueType),
            ua.Variant(enum_values, ua.VariantType.ExtensionObject), 1, I.PropertyType,
            I.HasProperty,
        )  # fmt: skip
        return node.nodeid

    # -- instantiation (OPC UA Part 3, 6.2.6) ------------------------------------------------------
    async def declarations(
        self, decl: ua.NodeId, typedef: ua.NodeId
    ) -> list[ua.ReferenceDescription]:
        """The instance declarations below ``decl`` (a declaration or null), then those of its
        type definition and the supertypes of that; the first one of each browse name wins."""
        key = (decl, typedef)
        if key not in self._declarations:
            sources = [] if decl.is_null() else [decl]
            if not typedef.is_null():
                types = await get_node_supertypes(self.server.get_node(typedef), True, False)
                sources += [t.nodeid for t in types]
            found: dict[str, ua.ReferenceDescription] = {}
            for source in sources:
                for ref in await self.server.get_node(source).get_references(
                    I.Aggregates, ua.BrowseDirection.Forward, includesubtypes=True
                ):
                    found.setdefault(ref.BrowseName.Name, ref)
            self._declarations[key] = list(found.values())
        return self._declarations[key]

    async def _rule(self, decl: ua.NodeId) -> int:
        if decl not in self._rules:
            rules = await self.server.get_node(decl).get_referenced_nodes(I.HasModellingRule)
            self._rules[decl] = rules[0].nodeid.Identifier if rules else 0
        return self._rules[decl]

    async def instantiate(
        self,
        nodes: UnitNodes,
        path: str,
        parent: ua.NodeId,
        decl: ua.NodeId,
        typedef: ua.NodeId,
        overrides: Mapping[str, ua.NodeId],
        callbacks: Mapping[str, Callable[..., Any]],
    ) -> None:
        """The children of the instance ``parent`` (at ``path``) from the declarations of ``decl``
        and ``typedef``; ``overrides``: path -> DataType (UnitModeCurrent: the unit's own
        enumeration)."""
        for ref in await self.declarations(decl, typedef):
            name = ref.BrowseName.Name
            child_path = f"{path}/{name}" if path else name
            rule = await self._rule(ref.NodeId)
            if rule == I.ModellingRule_Optional:
                if not wanted(child_path, ref.NodeClass):
                    continue
            elif rule != I.ModellingRule_Mandatory:
                continue  # states and transitions of the types; placeholders
            nodeid = ua.NodeId(f"{nodes.unit}.{child_path.replace('/', '.')}", self.u)
            source = self.server.get_node(ref.NodeId)
            description = await source.read_description()
            if ref.NodeClass == ua.NodeClass.Variable:
                dtype, rank, value = await source.read_attributes(
                    [ua.AttributeIds.DataType, ua.AttributeIds.ValueRank, ua.AttributeIds.Value]
                )
                node = await self.var(
                    nodeid, ref.BrowseName, parent,
                    overrides.get(child_path, dtype.Value.Value), value.Value,
                    rank.Value.Value, ref.TypeDefinition, ref.ReferenceTypeId, description,
                )  # fmt: skip
                nodes.variables[child_path] = node
            elif ref.NodeClass == ua.NodeClass.Object:
                attrs = ua.ObjectAttributes()
                attrs.EventNotifier = 0
                node = await self._add(ua.NodeClass.Object, nodeid, ref.BrowseName, parent,
                                       ref.ReferenceTypeId, attrs, ref.TypeDefinition, description)  # fmt: skip
            elif ref.NodeClass == ua.NodeClass.Method:
                attrs = ua.MethodAttributes()
                attrs.Executable = attrs.UserExecutable = True
                node = await self._add(ua.NodeClass.Method, nodeid, ref.BrowseName, parent,
                                       ref.ReferenceTypeId, attrs, None, description)  # fmt: skip
                nodes.methods[child_path] = node
                if child_path in callbacks:
                    self.server.link_method(self.server.get_node(node), callbacks[child_path])
            else:
                continue
            await self.instantiate(nodes, child_path, node, ref.NodeId, ref.TypeDefinition,
                                   overrides, callbacks)  # fmt: skip

    # -- units -------------------------------------------------------------------------------------
    async def build_unit(
        self,
        unit: str,
        tag_id: str,
        description: str,
        modes: Mapping[int, str],
        version: str,
        extra_steps: Mapping[Step, str],
        callbacks: Mapping[str, Callable[..., Any]],
    ) -> UnitNodes:
        """One unit: ``Objects/PackMLObjects/<unit>`` of PackMLBaseObjectType. ``callbacks``: method
        path (``BaseStateMachine/Abort``, ``SetUnitMode``) -> async callback; ``extra_steps``:
        transitions of the unit's rules the NodeSet lacks -> the method that causes them."""
        u = self.u
        root = await self._add(
            ua.NodeClass.Object, ua.NodeId(unit, u), ua.QualifiedName(unit, u),
            self.pid(self.model.objects_folder), I.Organizes, ua.ObjectAttributes(),
            self.pid(self.model.base_object_type), description or unit,
        )  # fmt: skip
        nodes = UnitNodes(unit, root)
        nodes.mode_enum = await self.enum(
            ua.NodeId(f"{unit}.UnitModeEnum", u), ua.QualifiedName(f"{unit}UnitModeEnum", u),
            {0: "Invalid", **modes}, ua.NodeId(f"{unit}.UnitModeEnum.EnumValues", u),
        )  # fmt: skip
        await self.instantiate(
            nodes, "", root, ua.NodeId(), self.pid(self.model.base_object_type),
            {"Status/UnitModeCurrent": nodes.mode_enum}, callbacks,
        )  # fmt: skip
        constants = {
            "TagID": ua.Variant(tag_id, ua.VariantType.String),
            "PackMLVersion": ua.Variant(version, ua.VariantType.String),
            "Status/UnitSupportedModes": ua.Variant(nodes.mode_enum, ua.VariantType.NodeId),
        }
        for path, value in constants.items():
            await self.server.write_attribute_value(nodes.variables[path], ua.DataValue(value))
        status = ua.NodeId(f"{unit}.Status", u)
        for name, dtype, text in STATUS_EXTENSIONS:
            path = f"Status/{name}"
            nodes.variables[path] = await self.var(
                ua.NodeId(f"{unit}.{path.replace('/', '.')}", u), ua.QualifiedName(name, u),
                status, ua.NodeId(dtype), description=text,
            )  # fmt: skip
        await self._extra_transitions(nodes, extra_steps)
        waiting = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData))
        for path in variable_paths(nodes):
            await self.server.write_attribute_value(nodes.variables[path], waiting)
        return nodes

    async def _extra_transitions(self, nodes: UnitNodes, steps: Mapping[Step, str]) -> None:
        """TransitionType objects in the unit's machines for ``steps`` (the instance's own
        transitions, in the server's namespace), referring to the NodeSet's state objects."""
        machines = {m.path: m for m in self.model.machines}
        for step, cause in sorted(steps.items()):
            path, frm, to = step
            machine = machines[path]
            name = f"{frm}To{to}"
            tpath = f"{path}/{name}"
            node = await self._add(
                ua.NodeClass.Object, ua.NodeId(f"{nodes.unit}.{tpath.replace('/', '.')}", self.u),
                ua.QualifiedName(name, self.u), ua.NodeId(f"{nodes.unit}.{path.replace('/', '.')}", self.u),
                I.HasComponent, ua.ObjectAttributes(), I.TransitionType,
                f"{frm} -> {to}: a transition of this unit's rules (packml_ros2 extension)",
            )  # fmt: skip
            await self.instantiate(nodes, tpath, node, ua.NodeId(), ua.NodeId(I.TransitionType),
                                   {}, {})  # fmt: skip
            await self._ref(node, self.pid(machine.state(frm).id), I.FromState)
            await self._ref(node, self.pid(machine.state(to).id), I.ToState)
            if f"{path}/{cause}" in nodes.methods:
                await self._ref(node, nodes.methods[f"{path}/{cause}"], I.HasCause)
            nodes.extra_transitions[step] = node


def variable_paths(nodes: UnitNodes) -> Iterable[str]:
    """The paths of the variables that follow the unit (not the constants, not the method
    arguments, not TransitionNumber)."""
    constants = ("TagID", "PackMLVersion", "Status/UnitSupportedModes")
    for path in nodes.variables:
        last = path.rsplit("/", 1)[-1]
        if path not in constants and last not in ("InputArguments", "TransitionNumber", "EURange"):
            yield path
