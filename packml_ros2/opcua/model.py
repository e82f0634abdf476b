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
offered; RemoteCommand, SetInterlock, MaterialInterlock are not. The Status object gets the v2
draft members of :data:`STATUS_EXTENSIONS` and the unit object SetRecipe, in the server's own
namespace (the v1.01 model stays as the official NodeSet has it).

The instances live in the server's own namespace (``urn:packml_ros2:<cell>``, index 1) with string
NodeIds ``<unit>.<path>`` (e.g. ``filler.Status.StateRequested``). :class:`UnitNodes` maps the
relative browse paths used by :mod:`.mapping` (``Status/StateRequested``,
``BaseStateMachine/MachineState/CurrentState/Number``) to those NodeIds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.manage_nodes import create_data_type
from asyncua.common.ua_utils import get_node_supertypes

from .mapping import EXTENSION_METHODS, Member, Step
from .nodeset import NODESET, PACKML_URI, MethodDef, PackMLModel, load

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

#: What this implementation adds to the Status object, in the server's own namespace (the
#: OPC 30050 v2 draft's names, so the v1.01 model stays as the official NodeSet has it): path below
#: Status, DataType (None: an object), ValueRank, description. A child of a variable is a property.
_X = "(OPC 30050 v2 draft, packml_ros2 extension)"
STATUS_EXTENSIONS: tuple[tuple[str, int | None, int, str], ...] = (
    ("StateCurrent", I.Int32, -1, f"PackTags Status.StateCurrent: the TR88 state number {_X}"),
    ("EquipmentInterlock", None, -1, f"EquipmentInterlock {{Blocked, Starved}} {_X}"),
    ("EquipmentInterlock/Blocked", I.Boolean, -1, "downstream cannot take material"),
    ("EquipmentInterlock/Starved", I.Boolean, -1, "upstream cannot deliver material"),
    (
        "StackLight",
        I.UInt32,
        1,
        "one UInt32 per light, top to bottom: bits 0-1 the mode (0 off, 1 on, 2 blink); bit 2 of "
        f"the first element: the horn {_X}",
    ),
    ("StackLight/Colors", I.String, 1, "the colour of each light of StackLight, top to bottom"),
    ("RecipeCurrent", I.Int32, -1, f"the ID of the recipe in use (0 = none) {_X}"),
    ("RecipeRequested", I.Int32, -1, f"the ID of the recipe requested last (0 = none) {_X}"),
    ("RecipeChangeInProcess", I.Boolean, -1, f"a changeover runs {_X}"),
    ("RecipeResult", I.String, -1, "how the last changeover ended ('' = none yet; extension)"),
    ("Recipe", None, -1, f"the unit's recipes, one object each (Recipe_<ID>) {_X}"),
)
#: The description of SetRecipe (:data:`.mapping.EXTENSION_METHODS`).
SET_RECIPE_TEXT = (
    "Change the unit's recipe (Command.SelectedRecipe + RecipeChangeRequest of TR88): the "
    "changeover runs across the unit's EMs after a Good answer; follow it in Status/RecipeCurrent, "
    "RecipeChangeInProcess, RecipeResult (packml_ros2 extension)"
)


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
    async def _folder(
        self, nodeid: ua.NodeId, bname: ua.QualifiedName, parent: ua.NodeId, text: str
    ) -> ua.NodeId:
        """A plain object under ``parent`` (a folder of the draft's members or of a recipe)."""
        return await self._add(
            ua.NodeClass.Object,
            nodeid,
            bname,
            parent,
            I.HasComponent,
            ua.ObjectAttributes(),
            I.BaseObjectType,
            text,
        )

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

    async def enum(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        values: Mapping[int, str],
        values_id: ua.NodeId,
    ) -> ua.NodeId:
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
            values_id,
            ua.QualifiedName("EnumValues", 0),
            node.nodeid,
            ua.NodeId(I.EnumValueType),
            ua.Variant(enum_values, ua.VariantType.ExtensionObject),
            1,
            I.PropertyType,
            I.HasProperty,
        )
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
                    nodeid,
                    ref.BrowseName,
                    parent,
                    overrides.get(child_path, dtype.Value.Value),
                    value.Value,
                    rank.Value.Value,
                    ref.TypeDefinition,
                    ref.ReferenceTypeId,
                    description,
                )
                nodes.variables[child_path] = node
            elif ref.NodeClass == ua.NodeClass.Object:
                attrs = ua.ObjectAttributes()
                attrs.EventNotifier = 0
                node = await self._add(
                    ua.NodeClass.Object,
                    nodeid,
                    ref.BrowseName,
                    parent,
                    ref.ReferenceTypeId,
                    attrs,
                    ref.TypeDefinition,
                    description,
                )
            elif ref.NodeClass == ua.NodeClass.Method:
                attrs = ua.MethodAttributes()
                attrs.Executable = attrs.UserExecutable = True
                node = await self._add(
                    ua.NodeClass.Method,
                    nodeid,
                    ref.BrowseName,
                    parent,
                    ref.ReferenceTypeId,
                    attrs,
                    None,
                    description,
                )
                nodes.methods[child_path] = node
                if child_path in callbacks:
                    self.server.link_method(self.server.get_node(node), callbacks[child_path])
            else:
                continue
            await self.instantiate(
                nodes, child_path, node, ref.NodeId, ref.TypeDefinition, overrides, callbacks
            )

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
        recipes: Sequence[Member] = (),
    ) -> UnitNodes:
        """One unit: ``Objects/PackMLObjects/<unit>`` of PackMLBaseObjectType. ``callbacks``: method
        path (``BaseStateMachine/Abort``, ``SetUnitMode``) -> async callback; ``extra_steps``:
        transitions of the unit's rules the NodeSet lacks -> the method that causes them;
        ``recipes``: the nodes below Status/Recipe (:func:`.mapping.recipe_members`)."""
        u = self.u
        root = await self._add(
            ua.NodeClass.Object,
            ua.NodeId(unit, u),
            ua.QualifiedName(unit, u),
            self.pid(self.model.objects_folder),
            I.Organizes,
            ua.ObjectAttributes(),
            self.pid(self.model.base_object_type),
            description or unit,
        )
        nodes = UnitNodes(unit, root)
        nodes.mode_enum = await self.enum(
            ua.NodeId(f"{unit}.UnitModeEnum", u),
            ua.QualifiedName(f"{unit}UnitModeEnum", u),
            {0: "Invalid", **modes},
            ua.NodeId(f"{unit}.UnitModeEnum.EnumValues", u),
        )
        await self.instantiate(
            nodes,
            "",
            root,
            ua.NodeId(),
            self.pid(self.model.base_object_type),
            {"Status/UnitModeCurrent": nodes.mode_enum},
            callbacks,
        )
        constants = {
            "TagID": ua.Variant(tag_id, ua.VariantType.String),
            "PackMLVersion": ua.Variant(version, ua.VariantType.String),
            "Status/UnitSupportedModes": ua.Variant(nodes.mode_enum, ua.VariantType.NodeId),
        }
        for path, value in constants.items():
            await self.server.write_attribute_value(nodes.variables[path], ua.DataValue(value))
        await self._status_extensions(nodes, recipes)
        for name, definition in EXTENSION_METHODS.items():
            await self._method(nodes, name, root, definition, callbacks[name], SET_RECIPE_TEXT)
        await self._extra_transitions(nodes, extra_steps)
        waiting = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData))
        for path in variable_paths(nodes):
            await self.server.write_attribute_value(nodes.variables[path], waiting)
        return nodes

    async def _status_extensions(self, nodes: UnitNodes, recipes: Sequence[Member]) -> None:
        """:data:`STATUS_EXTENSIONS` and the recipe tree (constants: not in ``nodes.variables``,
        so they keep their value while the unit is lost)."""
        u, unit = self.u, nodes.unit
        parents: dict[str, ua.NodeId] = {"": ua.NodeId(f"{unit}.Status", u)}
        for path, dtype, rank, text in STATUS_EXTENSIONS:
            folder, _, name = path.rpartition("/")
            nodeid = ua.NodeId(f"{unit}.Status.{path.replace('/', '.')}", u)
            bname, parent = ua.QualifiedName(name, u), parents[folder]
            if dtype is None:
                parents[path] = await self._folder(nodeid, bname, parent, text)
                continue
            prop = f"Status/{folder}" in nodes.variables
            parents[path] = nodes.variables[f"Status/{path}"] = await self.var(
                nodeid,
                bname,
                parent,
                ua.NodeId(dtype),
                rank=rank,
                typedef=I.PropertyType if prop else I.BaseDataVariableType,
                ref=I.HasProperty if prop else I.HasComponent,
                description=text,
            )
        folders: dict[tuple[str, ...], ua.NodeId] = {(): parents["Recipe"]}
        for member in recipes:
            key = tuple(part for _, part in member.path)
            nodeid = ua.NodeId(f"{unit}.Status.Recipe.{'.'.join(key)}", u)
            bname, parent = ua.QualifiedName(member.path[-1][0], u), folders[key[:-1]]
            if member.value is None:
                folders[key] = await self._folder(nodeid, bname, parent, member.description)
                continue
            folders[key] = await self.var(
                nodeid,
                bname,
                parent,
                ua.NodeId(member.value.vtype.value),
                ua.Variant(member.value.value, member.value.vtype),
                typedef=I.PropertyType if member.prop else I.BaseDataVariableType,
                ref=I.HasProperty if member.prop else I.HasComponent,
                description=member.description,
            )

    async def _method(
        self,
        nodes: UnitNodes,
        name: str,
        parent: ua.NodeId,
        definition: MethodDef,
        callback: Callable[..., Any],
        description: str,
    ) -> None:
        """A method of this server's own (``<unit>.<name>``) with its InputArguments."""
        attrs = ua.MethodAttributes()
        attrs.Executable = attrs.UserExecutable = True
        nodeid = ua.NodeId(f"{nodes.unit}.{name}", self.u)
        node = await self._add(
            ua.NodeClass.Method,
            nodeid,
            ua.QualifiedName(name, self.u),
            parent,
            I.HasComponent,
            attrs,
            None,
            description,
        )
        arguments = [
            ua.Argument(
                Name=a.name,
                DataType=ua.NodeId(a.data_type[1], self.p if a.data_type[0] else 0),
                ValueRank=a.value_rank,
                ArrayDimensions=[],
                Description=ua.LocalizedText(a.name),
            )
            for a in definition.arguments
        ]
        await self.var(
            ua.NodeId(f"{nodes.unit}.{name}.InputArguments", self.u),
            ua.QualifiedName("InputArguments", 0),
            node,
            ua.NodeId(I.Argument),
            ua.Variant(arguments, ua.VariantType.ExtensionObject),
            1,
            I.PropertyType,
            I.HasProperty,
        )
        nodes.methods[name] = node
        self.server.link_method(self.server.get_node(node), callback)

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
                ua.NodeClass.Object,
                ua.NodeId(f"{nodes.unit}.{tpath.replace('/', '.')}", self.u),
                ua.QualifiedName(name, self.u),
                ua.NodeId(f"{nodes.unit}.{path.replace('/', '.')}", self.u),
                I.HasComponent,
                ua.ObjectAttributes(),
                I.TransitionType,
                f"{frm} -> {to}: a transition of this unit's rules (packml_ros2 extension)",
            )
            await self.instantiate(
                nodes, tpath, node, ua.NodeId(), ua.NodeId(I.TransitionType), {}, {}
            )
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
