"""The OPC 30050 "OPC UA for PackML" information model (v1.1, namespace
``http://opcfoundation.org/UA/PackML/``), built in code with asyncua: data types, reference
types, the Status/Admin/BaseObject object types and the three state machine types, with the
specification's names and numeric NodeIds, so that a client that knows the companion
specification finds what it expects. Then one ``PackMLBaseObjectType`` instance per unit under
``Objects/PackMLObjects``.

The instances live in the server's own namespace (``urn:packml_ros2:<cell>``) with string
NodeIds ``<unit>.<path>`` (e.g. ``robot_cell.Status.StateRequested``). :class:`UnitNodes` maps
the relative browse paths used by :mod:`.mapping` (``Status/StateRequested``,
``BaseStateMachine/MachineState/CurrentState/Number``) to those NodeIds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.manage_nodes import create_data_type, create_encoding

PACKML_URI = "http://opcfoundation.org/UA/PackML/"
PACKML_SPEC = "ISA-TR88.00.02-2022"
PACKML_OPC = "1.1.0"  # the version of the companion specification's model followed here

# -- standard (namespace 0) NodeIds used below ----------------------------------------------------
I = ua.ObjectIds  # noqa: E741
HAS_COMPONENT, HAS_PROPERTY, ORGANIZES = I.HasComponent, I.HasProperty, I.Organizes
HAS_SUBTYPE, HAS_ENCODING, HAS_MODELLING_RULE = I.HasSubtype, I.HasEncoding, I.HasModellingRule
FROM_STATE, TO_STATE, HAS_CAUSE, HAS_SUBSTATEMACHINE = (
    I.FromState,
    I.ToState,
    I.HasCause,
    I.HasSubStateMachine,
)
MANDATORY, OPTIONAL = I.ModellingRule_Mandatory, I.ModellingRule_Optional
BASE_DATA_VARIABLE, PROPERTY, ANALOG_ITEM = (
    I.BaseDataVariableType,
    I.PropertyType,
    I.AnalogItemType,
)
FINITE_STATE_VARIABLE, FINITE_STATE_MACHINE = I.FiniteStateVariableType, I.FiniteStateMachineType
STATE_TYPE, TRANSITION_TYPE, FOLDER = I.StateType, I.TransitionType, I.FolderType

# -- OPC 30050 NodeIds (numeric, in the PackML namespace) -----------------------------------------
EXECUTE_SM_TYPE, MACHINE_SM_TYPE, BASE_SM_TYPE = 1, 2, 3
STATUS_TYPE, ADMIN_TYPE, BASE_OBJECT_TYPE = 4, 5, 6
MODE_ENUM = 11  # ProductionMaintenanceModeEnum
VERSION_DT, COUNT_DT, ALARM_DT, DESCRIPTOR_DT = 13, 14, 15, 16
INGREDIENTS_DT, PRODUCT_DT, REMOTE_INTERFACE_DT = 17, 18, 19
HAS_INTERLOCK, HAS_ALARM, HAS_ALARM_HISTORY, HAS_WARNING, HAS_STOP_REASON = 21, 22, 23, 24, 25
PACKML_OBJECTS = 72


@dataclass(frozen=True)
class StructDef:
    """A structured DataType: (field name, field DataType (ns, id), is array)."""

    name: str
    id: int
    encoding: int  # its Default Binary encoding
    fields: tuple[tuple[str, tuple[int, int], bool], ...]


_P = -1  # marks "the PackML namespace" in (ns, id) pairs until the index is known
STRUCTS: tuple[StructDef, ...] = (
    StructDef("PackMLVersionDataType", VERSION_DT, 26,
              (("PackMLSpec", (0, I.String), False), ("PackMLOPC", (0, I.String), False))),
    StructDef("PackMLDescriptorDataType", DESCRIPTOR_DT, 77,
              (("ID", (0, I.Int32), False), ("Name", (0, I.String), False),
               ("Unit", (0, I.EUInformation), False), ("Value", (0, I.Float), False))),
    StructDef("PackMLCountDataType", COUNT_DT, 69,
              (("ID", (0, I.Int32), False), ("Name", (0, I.String), False),
               ("Unit", (0, I.EUInformation), False), ("Count", (0, I.Int32), False),
               ("AccCount", (0, I.Int32), False))),
    StructDef("PackMLAlarmDataType", ALARM_DT, 74,
              (("ID", (0, I.Int32), False), ("Value", (0, I.Int32), False),
               ("Message", (0, I.String), False), ("Category", (0, I.Int32), False),
               ("DateTime", (0, I.UtcTime), False), ("AckDateTime", (0, I.UtcTime), False),
               ("Trigger", (0, I.Boolean), False))),
    StructDef("PackMLIngredientsDataType", INGREDIENTS_DT, 79,
              (("IngredientID", (0, I.Int32), False),
               ("Parameter", (_P, DESCRIPTOR_DT), True))),
    StructDef("PackMLProductDataType", PRODUCT_DT, 81,
              (("ProductID", (0, I.Int32), False),
               ("ProcessVariables", (_P, DESCRIPTOR_DT), True),
               ("Ingredients", (_P, INGREDIENTS_DT), True))),
    StructDef("PackMLRemoteInterfaceDataType", REMOTE_INTERFACE_DT, 83,
              (("Number", (0, I.Int32), False), ("ControlCmdNumber", (0, I.Int32), False),
               ("CmdValue", (0, I.Int32), False), ("Parameter", (_P, DESCRIPTOR_DT), True))),
)  # fmt: skip

REFERENCE_TYPES = (
    (HAS_INTERLOCK, "HasInterlock", "InterlockFor"),
    (HAS_ALARM, "HasAlarm", "AlarmFor"),
    (HAS_ALARM_HISTORY, "HasAlarmHistory", "AlarmHistoryFor"),
    (HAS_WARNING, "HasWarning", "WarningFor"),
    (HAS_STOP_REASON, "HasStopReason", "StopReasonFor"),
)


@dataclass(frozen=True)
class VarDef:
    """A variable of the Status or Admin object: its declaration in the object type (``type_id``)
    and how an instance looks."""

    name: str
    type_id: int
    dtype: tuple[int, int]  # (ns or _P, id)
    vtype: ua.VariantType
    rank: int = -1  # ValueRank: -1 scalar, 1 array, 2 matrix
    mandatory: bool = False
    ref: tuple[int, int] = (0, HAS_COMPONENT)
    typedef: int = BASE_DATA_VARIABLE
    eurange_id: int = 0  # AnalogItemType: the EURange property's id in the type
    instantiate: bool = True  # False: declared in the type only (not supported by the bridge)


F, B, I32 = ua.VariantType.Float, ua.VariantType.Boolean, ua.VariantType.Int32
EO = ua.VariantType.ExtensionObject
STATUS_VARS: tuple[VarDef, ...] = (
    VarDef("UnitModeCurrent", 200, (0, I.Enumeration), I32, mandatory=True),
    VarDef("UnitModeRequested", 192, (0, I.Boolean), B),
    VarDef("UnitModeChangeInProgress", 201, (0, I.Boolean), B),
    VarDef("StateRequested", 209, (0, I.Int32), I32),
    VarDef("StateChangeInProgress", 210, (0, I.Boolean), B),
    VarDef("MachSpeed", 219, (0, I.Float), F, mandatory=True, typedef=ANALOG_ITEM, eurange_id=220),
    VarDef("CurMachSpeed", 232, (0, I.Float), F, mandatory=True, typedef=ANALOG_ITEM, eurange_id=233),
    VarDef("EquipmentBlocked", 211, (0, I.Boolean), B, mandatory=True),
    VarDef("EquipmentStarved", 224, (0, I.Boolean), B, mandatory=True),
    VarDef("Parameter", 121, (_P, DESCRIPTOR_DT), EO, rank=1),
    VarDef("Product", 122, (_P, PRODUCT_DT), EO, rank=1),
    VarDef("RemoteParameter", 123, (_P, REMOTE_INTERFACE_DT), EO, rank=1),
    VarDef("MaterialInterlock", 6010, (0, I.Boolean), B, rank=1, ref=(_P, HAS_INTERLOCK),
           instantiate=False),
    VarDef("MaterialInterlocked", 236, (0, I.Boolean), B, instantiate=False),
)  # fmt: skip
ADMIN_VARS: tuple[VarDef, ...] = (
    VarDef("Alarm", 6024, (_P, ALARM_DT), EO, rank=1, ref=(_P, HAS_ALARM)),
    VarDef("AlarmExtent", 239, (0, I.Int32), I32),
    VarDef("AlarmHistory", 6042, (_P, ALARM_DT), EO, rank=1, ref=(_P, HAS_ALARM_HISTORY)),
    VarDef("AlarmHistoryExtent", 241, (0, I.Int32), I32),
    VarDef("Warning", 6058, (_P, ALARM_DT), EO, rank=1, ref=(_P, HAS_WARNING)),
    VarDef("WarningExtent", 243, (0, I.Int32), I32),
    VarDef("StopReason", 6050, (_P, ALARM_DT), EO, ref=(_P, HAS_STOP_REASON)),
    VarDef("StopReasonExtent", 245, (0, I.Int32), I32),
    VarDef("ModeCurrentTime", 246, (0, I.Int32), I32, rank=1),
    VarDef("ModeCumulativeTime", 247, (0, I.Int32), I32, rank=1),
    VarDef("StateCurrentTime", 248, (0, I.Int32), I32, rank=2),
    VarDef("StateCumulativeTime", 249, (0, I.Int32), I32, rank=2),
    VarDef("ProdConsumedCount", 124, (_P, COUNT_DT), EO, rank=1),
    VarDef("ProdProcessedCount", 120, (_P, COUNT_DT), EO, rank=1),
    VarDef("ProdDefectiveCount", 119, (_P, COUNT_DT), EO, rank=1),
    VarDef("AccTimeSinceReset", 252, (0, I.Int32), I32),
    VarDef("MachDesignSpeed", 253, (0, I.Float), F),
    VarDef("Parameter", 276, (_P, DESCRIPTOR_DT), EO, rank=1),
)  # fmt: skip

#: Variables this implementation adds to the Status object, in the server's own namespace
#: (TR88 PackTags with no OPC 30050 variable of their own).
STATUS_EXTENSIONS: tuple[tuple[str, ua.VariantType, int], ...] = (
    ("StateCurrent", I32, I.Int32),  # Status.StateCurrent: the state number
)


# -- state machines -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StateDef:
    name: str
    id: int
    number: int  # StateNumber = the PackML state number (PACKML.md section 1)
    number_id: int


@dataclass(frozen=True)
class TransitionDef:
    name: str
    id: int
    number_id: int
    from_state: int
    to_state: int
    cause: int = 0  # the method that causes it


@dataclass(frozen=True)
class MethodDef:
    name: str
    id: int
    command: int  # packml Command number (0 = not a state command)
    args: tuple[tuple[str, tuple[int, int], int, str], ...] = ()  # name, dtype, value rank, text
    args_id: int = 0
    mandatory: bool = False


@dataclass(frozen=True)
class MachineDef:
    name: str  # browse name of the instance component (BaseStateMachine, MachineState, ...)
    type_id: int
    type_name: str
    decl_id: int  # the declaration of this sub machine in its parent machine type (0 = top)
    states: tuple[StateDef, ...]
    transitions: tuple[TransitionDef, ...]
    methods: tuple[MethodDef, ...]
    sub_state: int = 0  # the state whose sub state machine the next MachineDef is


START, STOP, RESET, HOLD, UNHOLD, SUSPEND, UNSUSPEND, ABORT, CLEAR, COMPLETE = (
    2, 3, 1, 4, 5, 6, 7, 8, 9, 10,
)  # fmt: skip
_PARAM_ARG = (("Parameter", (_P, DESCRIPTOR_DT), 1, "The array of parameter that can be used by the method"),)  # fmt: skip

BASE_SM = MachineDef(
    "BaseStateMachine", BASE_SM_TYPE, "PackMLBaseStateMachineType", 0,
    (StateDef("Aborting", 61, 8, 168), StateDef("Aborted", 62, 9, 169),
     StateDef("Cleared", 5001, 18, 6020)),
    (TransitionDef("AbortedToCleared", 65, 174, 62, 5001, 363),
     TransitionDef("AbortingToAborted", 66, 175, 61, 62),
     TransitionDef("ClearedToAborting", 67, 176, 5001, 61, 364)),
    (MethodDef("Abort", 364, ABORT), MethodDef("Clear", 363, CLEAR)),
    sub_state=5001,
)  # fmt: skip
MACHINE_SM = MachineDef(
    "MachineState", MACHINE_SM_TYPE, "PackMLMachineStateMachineType", 64,
    (StateDef("Stopped", 53, 2, 155), StateDef("Stopping", 54, 7, 156),
     StateDef("Clearing", 55, 1, 157), StateDef("Running", 75, 19, 171)),
    (TransitionDef("StoppingToStopped", 57, 163, 54, 53),
     TransitionDef("ClearingToStopped", 58, 164, 55, 53),
     TransitionDef("StoppedToRunning", 59, 165, 53, 75, 376),
     TransitionDef("RunningToStopping", 60, 166, 75, 54, 375)),
    (MethodDef("Stop", 375, STOP), MethodDef("Reset", 376, RESET)),
    sub_state=75,
)  # fmt: skip
EXECUTE_SM = MachineDef(
    "ExecuteState", EXECUTE_SM_TYPE, "PackMLExecuteStateMachineType", 56,
    (StateDef("Resetting", 27, 15, 127), StateDef("Idle", 28, 4, 128),
     StateDef("Starting", 29, 3, 129), StateDef("Suspending", 30, 13, 130),
     StateDef("Suspended", 31, 5, 131), StateDef("Unsuspending", 32, 14, 132),
     StateDef("Holding", 33, 10, 133), StateDef("Held", 34, 11, 134),
     StateDef("Unholding", 35, 12, 135), StateDef("Execute", 36, 6, 136),
     StateDef("Completing", 37, 16, 137), StateDef("Complete", 38, 17, 138)),
    (TransitionDef("ResettingToIdle", 39, 139, 27, 28),
     TransitionDef("IdleToStarting", 40, 140, 28, 29, 369),
     TransitionDef("StartingToExecute", 41, 141, 29, 36),
     TransitionDef("ExecuteToSuspending", 42, 142, 36, 30, 367),
     TransitionDef("SuspendingToSuspended", 43, 143, 30, 31),
     TransitionDef("UnsuspendingToExecute", 44, 144, 32, 36),
     TransitionDef("ExecuteToHolding", 45, 145, 36, 33, 366),
     TransitionDef("HoldingToHeld", 46, 146, 33, 34),
     TransitionDef("HeldToUnholding", 47, 147, 34, 35, 368),
     TransitionDef("UnholdingToExecute", 48, 148, 35, 36),
     TransitionDef("ExecuteToCompleting", 49, 149, 36, 37, 365),
     TransitionDef("CompletingToComplete", 50, 150, 37, 38),
     TransitionDef("CompleteToResetting", 51, 151, 38, 27, 361),
     TransitionDef("SuspendedToUnsuspending", 52, 152, 31, 32, 372),
     TransitionDef("StartingToHolding", 99, 179, 29, 33, 366),
     TransitionDef("UnsuspendingToHolding", 100, 208, 32, 33, 366),
     TransitionDef("SuspendedToHolding", 101, 215, 31, 33, 366),
     TransitionDef("SuspendingToHolding", 102, 216, 30, 33, 366),
     TransitionDef("UnholdingToHolding", 103, 217, 35, 33, 366)),
    (MethodDef("Reset", 361, RESET), MethodDef("Start", 369, START, _PARAM_ARG, 342),
     MethodDef("Hold", 366, HOLD), MethodDef("Unhold", 368, UNHOLD),
     MethodDef("Suspend", 367, SUSPEND), MethodDef("Unsuspend", 372, UNSUSPEND),
     MethodDef("ToComplete", 365, COMPLETE)),
)  # fmt: skip
MACHINES = (BASE_SM, MACHINE_SM, EXECUTE_SM)
#: Relative paths of the three machines inside a unit object.
MACHINE_PATHS = {
    BASE_SM.name: "BaseStateMachine",
    MACHINE_SM.name: "BaseStateMachine/MachineState",
    EXECUTE_SM.name: "BaseStateMachine/MachineState/ExecuteState",
}

OBJECT_METHODS: tuple[MethodDef, ...] = (
    MethodDef("SetUnitMode", 362, 0,
              (("ModeSelection", (0, I.NodeId), -1, "The NodeId of the enumeration that describes the available modes"),
               ("RequestedMode", (0, I.Int32), -1, "The requested mode from the list of available modes in the enumeration from ModeSelection")),
              118, mandatory=True),
    MethodDef("SetMachSpeed", 400, 0,
              (("RequestedMachineSpeed", (0, I.Float), -1, "The target machine speed"),), 348, mandatory=True),
    MethodDef("SetProduct", 401, 0,
              (("Product", (_P, PRODUCT_DT), 1, "The array of product definitions: ProductID, ProcessVariables and Ingredients"),),
              349, mandatory=True),
    MethodDef("SetParameter", 402, 0, _PARAM_ARG, 352, mandatory=True),
    MethodDef("RemoteCommand", 403, 0,
              (("RemoteInterface", (_P, REMOTE_INTERFACE_DT), 1, "Number, ControlCmdNumber, CmdValue and Parameter of the remote command"),),
              350),
    MethodDef("SetInterlock", 404, 0,
              (("InterlockId", (0, I.NodeId), -1, "The NodeId of the interlock to set or reset."),
               ("State", (0, I.Boolean), -1, "True: interlocked, false: not interlocked.")),
              351),
)  # fmt: skip
#: The object methods instances get (RemoteCommand and SetInterlock are optional and not offered).
INSTANCE_OBJECT_METHODS = ("SetUnitMode", "SetMachSpeed", "SetProduct", "SetParameter")


def machine_methods() -> Iterable[tuple[MachineDef, MethodDef]]:
    for machine in MACHINES:
        for method in machine.methods:
            yield machine, method


# -- building ---------------------------------------------------------------------------------------------
@dataclass
class UnitNodes:
    """The nodes of one unit instance: relative path -> NodeId."""

    unit: str
    object: ua.NodeId
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    methods: dict[str, ua.NodeId] = field(default_factory=dict)
    mode_enum: ua.NodeId | None = None


class AddressSpace:
    """Builds the PackML types (once) and the unit instances of a server."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self.session = server.iserver.isession
        self.p = 0  # PackML namespace index
        self.u = 0  # instance namespace index

    def pid(self, ident: int) -> ua.NodeId:
        return ua.NodeId(ident, self.p)

    def dtype(self, ref: tuple[int, int]) -> ua.NodeId:
        ns, ident = ref
        return ua.NodeId(ident, self.p if ns == _P else ns)

    def qn(self, name: str, ns: int | None = None) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.p if ns is None else ns)

    # -- low level ----------------------------------------------------------------------------------
    async def _add(
        self,
        nodeclass: ua.NodeClass,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        ref: ua.NodeId | int,
        attrs: Any,
        typedef: ua.NodeId | int | None = None,
        description: str = "",
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
        attrs.Description = ua.LocalizedText(description or bname.Name)
        attrs.WriteMask = 0
        attrs.UserWriteMask = 0
        item.NodeAttributes = attrs
        result = (await self.session.add_nodes([item]))[0]
        result.StatusCode.check()
        return result.AddedNodeId

    async def _ref(
        self, source: ua.NodeId, target: ua.NodeId, reftype: int | ua.NodeId, forward: bool = True
    ) -> None:
        rid = reftype if isinstance(reftype, ua.NodeId) else ua.NodeId(reftype)
        items = []
        for src, dst, fwd in ((source, target, forward), (target, source, not forward)):
            item = ua.AddReferencesItem()
            item.SourceNodeId, item.TargetNodeId, item.ReferenceTypeId = src, dst, rid
            item.IsForward = fwd
            items.append(item)
        for status in await self.session.add_references(items):
            status.check()

    async def _modelling(self, node: ua.NodeId, mandatory: bool) -> None:
        await self._ref(node, ua.NodeId(MANDATORY if mandatory else OPTIONAL), HAS_MODELLING_RULE)

    async def obj(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        typedef: ua.NodeId | int,
        ref: ua.NodeId | int = HAS_COMPONENT,
        description: str = "",
    ) -> ua.NodeId:
        attrs = ua.ObjectAttributes()
        attrs.EventNotifier = 0
        return await self._add(
            ua.NodeClass.Object, nodeid, bname, parent, ref, attrs, typedef, description
        )

    async def var(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        dtype: ua.NodeId,
        value: ua.Variant | None = None,
        rank: int = -1,
        typedef: ua.NodeId | int = BASE_DATA_VARIABLE,
        ref: ua.NodeId | int = HAS_COMPONENT,
        description: str = "",
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

    async def prop(
        self,
        nodeid: ua.NodeId,
        name: str,
        parent: ua.NodeId,
        dtype: ua.NodeId,
        value: ua.Variant,
        ns: int = 0,
        rank: int = -1,
    ) -> ua.NodeId:
        return await self.var(
            nodeid, ua.QualifiedName(name, ns), parent, dtype, value, rank, PROPERTY, HAS_PROPERTY
        )

    async def method(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        parent: ua.NodeId,
        definition: MethodDef,
        args_id: ua.NodeId,
        callback: Callable[..., Any] | None = None,
    ) -> ua.NodeId:
        attrs = ua.MethodAttributes()
        attrs.Executable = True
        attrs.UserExecutable = True
        node = await self._add(ua.NodeClass.Method, nodeid, bname, parent, HAS_COMPONENT, attrs)
        if definition.args:
            arguments = [
                ua.Argument(
                    Name=name,
                    DataType=self.dtype(dtype),
                    ValueRank=rank,
                    ArrayDimensions=[0] if rank == 1 else [],
                    Description=ua.LocalizedText(text),
                )
                for name, dtype, rank, text in definition.args
            ]
            await self.prop(
                args_id,
                "InputArguments",
                node,
                ua.NodeId(I.Argument),
                ua.Variant(arguments, ua.VariantType.ExtensionObject),
                rank=1,
            )
        if callback is not None:
            self.server.link_method(self.server.get_node(node), callback)
        return node

    # -- the companion specification's types -------------------------------------------------------
    async def build_types(self) -> None:
        self.p = await self.server.register_namespace(PACKML_URI)
        await self._data_types()
        for ident, name, inverse in REFERENCE_TYPES:
            attrs = ua.ReferenceTypeAttributes()
            attrs.IsAbstract = False
            attrs.Symmetric = False
            attrs.InverseName = ua.LocalizedText(inverse)
            await self._add(
                ua.NodeClass.ReferenceType,
                self.pid(ident),
                self.qn(name),
                ua.NodeId(HAS_COMPONENT),
                HAS_SUBTYPE,
                attrs,
            )
        await self._status_and_admin_types()
        await self._state_machine_types()
        await self._base_object_type()
        await self.obj(
            self.pid(PACKML_OBJECTS),
            self.qn("PackMLObjects"),
            ua.NodeId(I.ObjectsFolder),
            FOLDER,
            ORGANIZES,
            "The entry point for the PackML objects of this server",
        )

    async def _data_types(self) -> None:
        structure = self.server.get_node(ua.NodeId(I.Structure))
        for s in STRUCTS:
            dtype = await create_data_type(structure, self.pid(s.id), self.qn(s.name))
            enc = await create_encoding(
                dtype, ua.NodeId(s.encoding, self.p), ua.QualifiedName("Default Binary", 0)
            )
            sdef = ua.StructureDefinition()
            sdef.BaseDataType = ua.NodeId(I.Structure)
            sdef.StructureType = ua.StructureType.Structure
            sdef.DefaultEncodingId = enc.nodeid
            sdef.Fields = [
                ua.StructureField(
                    Name=name,
                    DataType=self.dtype(ref),
                    ValueRank=1 if array else -1,
                    ArrayDimensions=[0] if array else None,
                    IsOptional=False,
                )
                for name, ref, array in s.fields
            ]
            await dtype.write_data_type_definition(sdef)
        modes = {0: "Invalid", 1: "Produce", 2: "Maintenance", 3: "Manual"}
        await self.enum(self.pid(MODE_ENUM), self.qn("ProductionMaintenanceModeEnum"), modes, 194)
        await self.server.load_data_type_definitions()

    async def enum(
        self,
        nodeid: ua.NodeId,
        bname: ua.QualifiedName,
        values: Mapping[int, str],
        values_id: int | str | None = None,
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
        await self.prop(
            ua.NodeId(values_id, nodeid.NamespaceIndex)
            if values_id is not None
            else ua.NodeId(NamespaceIndex=nodeid.NamespaceIndex),
            "EnumValues",
            node.nodeid,
            ua.NodeId(I.EnumValueType),
            ua.Variant(enum_values, ua.VariantType.ExtensionObject),
            rank=1,
        )
        return node.nodeid

    async def _object_type(self, ident: int, name: str, base: int) -> ua.NodeId:
        attrs = ua.ObjectTypeAttributes()
        attrs.IsAbstract = False
        return await self._add(
            ua.NodeClass.ObjectType,
            self.pid(ident),
            self.qn(name),
            ua.NodeId(base),
            HAS_SUBTYPE,
            attrs,
        )

    async def _declare_vars(self, type_node: ua.NodeId, defs: Iterable[VarDef]) -> None:
        for d in defs:
            rank = d.rank
            node = await self.var(
                self.pid(d.type_id),
                self.qn(d.name),
                type_node,
                self.dtype(d.dtype),
                None,
                rank,
                d.typedef,
                self.dtype(d.ref),
            )
            await self._modelling(node, d.mandatory)
            if d.eurange_id:
                eurange = await self.prop(
                    self.pid(d.eurange_id),
                    "EURange",
                    node,
                    ua.NodeId(I.Range),
                    ua.Variant(ua.Range()),
                )
                await self._modelling(eurange, True)

    async def _status_and_admin_types(self) -> None:
        status = await self._object_type(STATUS_TYPE, "PackMLStatusObjectType", I.BaseObjectType)
        await self._declare_vars(status, STATUS_VARS)
        supported = await self.prop(
            self.pid(193),
            "UnitSupportedModes",
            status,
            ua.NodeId(I.NodeId),
            ua.Variant(self.pid(MODE_ENUM)),
            ns=self.p,
        )
        await self._modelling(supported, True)
        admin = await self._object_type(ADMIN_TYPE, "PackMLAdminObjectType", I.BaseObjectType)
        await self._declare_vars(admin, ADMIN_VARS)

    async def _state_machine_types(self) -> None:
        types = {}
        for m in MACHINES:
            types[m.name] = await self._object_type(m.type_id, m.type_name, FINITE_STATE_MACHINE)
        sub_machines = []  # (state, sub state machine declaration): linked once states exist
        for parent, child in ((BASE_SM, MACHINE_SM), (MACHINE_SM, EXECUTE_SM)):
            decl = await self.obj(self.pid(child.decl_id), self.qn(child.name), types[parent.name],
                                  self.pid(child.type_id))  # fmt: skip
            await self._modelling(decl, True)
            sub_machines.append((parent.sub_state, decl))
        for m in MACHINES:
            tnode = types[m.name]
            for s in m.states:
                node = await self.obj(self.pid(s.id), self.qn(s.name), tnode, STATE_TYPE)
                await self.prop(self.pid(s.number_id), "StateNumber", node, ua.NodeId(I.UInt32),
                                ua.Variant(s.number, ua.VariantType.UInt32))  # fmt: skip
            for md in m.methods:
                meth = await self.method(self.pid(md.id), self.qn(md.name), tnode, md,
                                         self.pid(md.args_id))  # fmt: skip
                await self._modelling(meth, False)
            # the specification leaves TransitionNumber open: numbered here in table order
            for number, t in enumerate(m.transitions, 1):
                node = await self.obj(self.pid(t.id), self.qn(t.name), tnode, TRANSITION_TYPE)
                await self.prop(self.pid(t.number_id), "TransitionNumber", node, ua.NodeId(I.UInt32),
                                ua.Variant(number, ua.VariantType.UInt32))  # fmt: skip
                await self._ref(node, self.pid(t.from_state), FROM_STATE)
                await self._ref(node, self.pid(t.to_state), TO_STATE)
                if t.cause:
                    await self._ref(node, self.pid(t.cause), HAS_CAUSE)
        for state, decl in sub_machines:
            await self._ref(self.pid(state), decl, HAS_SUBSTATEMACHINE)

    async def _base_object_type(self) -> None:
        base = await self._object_type(BASE_OBJECT_TYPE, "PackMLBaseObjectType", I.BaseObjectType)
        for ident, name, typedef in ((87, "Status", STATUS_TYPE), (73, "Admin", ADMIN_TYPE),
                                     (88, "BaseStateMachine", BASE_SM_TYPE)):  # fmt: skip
            decl = await self.obj(self.pid(ident), self.qn(name), base, self.pid(typedef))
            await self._modelling(decl, True)
        version = await self.var(self.pid(6018), self.qn("PackMLVersion"), base,
                                 self.pid(VERSION_DT), self.version())  # fmt: skip
        await self._modelling(version, False)
        tag = await self.prop(self.pid(218), "TagID", base, ua.NodeId(I.String),
                              ua.Variant("", ua.VariantType.String), ns=self.p)  # fmt: skip
        await self._modelling(tag, False)
        for md in OBJECT_METHODS:
            meth = await self.method(
                self.pid(md.id), self.qn(md.name), base, md, self.pid(md.args_id)
            )
            await self._modelling(meth, md.mandatory)

    def version(self) -> ua.Variant:
        cls = getattr(ua, "PackMLVersionDataType")  # noqa: B009 - generated at run time
        return ua.Variant(
            cls(PackMLSpec=PACKML_SPEC, PackMLOPC=PACKML_OPC), ua.VariantType.ExtensionObject
        )

    # -- instances ------------------------------------------------------------------------------------
    async def build_unit(
        self,
        unit: str,
        tag_id: str,
        description: str,
        modes: Mapping[int, str],
        callbacks: Mapping[str, Callable[..., Any]],
    ) -> UnitNodes:
        """One unit: ``Objects/PackMLObjects/<unit>`` of PackMLBaseObjectType. ``callbacks``: method
        path (``BaseStateMachine/Abort``, ``SetUnitMode``) -> async callback."""
        u = self.u

        def nid(path: str) -> ua.NodeId:
            return ua.NodeId(f"{unit}.{path.replace('/', '.')}" if path else unit, u)

        root = await self.obj(nid(""), ua.QualifiedName(unit, u), self.pid(PACKML_OBJECTS),
                              self.pid(BASE_OBJECT_TYPE), ORGANIZES, description or unit)  # fmt: skip
        nodes = UnitNodes(unit, root)
        await self.prop(nid("TagID"), "TagID", root, ua.NodeId(I.String),
                        ua.Variant(tag_id, ua.VariantType.String), ns=self.p)  # fmt: skip
        await self.var(nid("PackMLVersion"), self.qn("PackMLVersion"), root, self.pid(VERSION_DT),
                       self.version())  # fmt: skip
        nodes.mode_enum = await self.enum(
            ua.NodeId(f"{unit}.UnitModeEnum", u), ua.QualifiedName(f"{unit}UnitModeEnum", u),
            {0: "Invalid", **modes}, f"{unit}.UnitModeEnum.EnumValues",
        )  # fmt: skip
        waiting = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)

        async def variables(folder: str, type_id: int, defs: Iterable[VarDef]) -> ua.NodeId:
            parent = await self.obj(nid(folder), self.qn(folder), root, self.pid(type_id))
            for d in defs:
                if not d.instantiate:
                    continue
                dtype = nodes.mode_enum if d.name == "UnitModeCurrent" else self.dtype(d.dtype)
                path = f"{folder}/{d.name}"
                node = await self.var(nid(path), self.qn(d.name), parent, dtype, None, d.rank,
                                      d.typedef, self.dtype(d.ref))  # fmt: skip
                nodes.variables[path] = node
                if d.eurange_id:
                    eu = await self.prop(nid(f"{path}/EURange"), "EURange", node,
                                         ua.NodeId(I.Range), ua.Variant(ua.Range()))  # fmt: skip
                    nodes.variables[f"{path}/EURange"] = eu
            return parent

        status = await variables("Status", STATUS_TYPE, STATUS_VARS)
        await self.prop(nid("Status/UnitSupportedModes"), "UnitSupportedModes", status,
                        ua.NodeId(I.NodeId), ua.Variant(nodes.mode_enum), ns=self.p)  # fmt: skip
        for name, _, dtype in STATUS_EXTENSIONS:
            path = f"Status/{name}"
            nodes.variables[path] = await self.var(
                nid(path), ua.QualifiedName(name, u), status, ua.NodeId(dtype),
                description=f"PackTags Status.{name} (packml_ros2 extension)",
            )  # fmt: skip
        await variables("Admin", ADMIN_TYPE, ADMIN_VARS)

        parent = root
        for m in MACHINES:
            path = MACHINE_PATHS[m.name]
            machine = await self.obj(nid(path), self.qn(m.name), parent, self.pid(m.type_id))
            current = await self.var(nid(f"{path}/CurrentState"), ua.QualifiedName("CurrentState", 0),
                                     machine, ua.NodeId(I.LocalizedText),
                                     typedef=FINITE_STATE_VARIABLE)  # fmt: skip
            nodes.variables[f"{path}/CurrentState"] = current
            for prop, dtype in (("Id", I.NodeId), ("Number", I.UInt32)):
                nodes.variables[f"{path}/CurrentState/{prop}"] = await self.prop(
                    nid(f"{path}/CurrentState/{prop}"), prop, current, ua.NodeId(dtype),
                    ua.Variant(None, ua.VariantType.Null),
                )  # fmt: skip
            for md in m.methods:
                mpath = f"{path}/{md.name}"
                nodes.methods[mpath] = await self.method(
                    nid(mpath), self.qn(md.name), machine, md, nid(f"{mpath}/InputArguments"),
                    callbacks.get(mpath),
                )  # fmt: skip
            parent = machine
        for md in OBJECT_METHODS:
            if md.name in INSTANCE_OBJECT_METHODS:
                nodes.methods[md.name] = await self.method(
                    nid(md.name), self.qn(md.name), root, md, nid(f"{md.name}/InputArguments"),
                    callbacks.get(md.name),
                )  # fmt: skip
        for node in nodes.variables.values():
            if node.Identifier.endswith(".EURange"):
                continue
            await self.server.write_attribute_value(node, ua.DataValue(StatusCode=waiting))
        return nodes
