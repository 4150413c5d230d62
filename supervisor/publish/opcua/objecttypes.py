"""The bench's object types (issue 31, finding 10), declared once in their own namespace
``urn:bench-supervisor:types`` (the same on every bench, so that a client's template made
from one bench fits another) and instantiated per channel and device by space.py:

- ``BenchType``: Channels, Devices, Alarms, Diagnostics, ForceTag, UnforceTag;
- ``ChannelType``: the channel's measurements and operator variables (``CHANNEL_MEMBERS``),
  its ``StateMachine`` and its methods (methods.py);
- ``ChannelStateMachineType`` (a ``FiniteStateMachineType``, PackML-style): its
  ``CurrentState`` is the test's state by its PackML name (``Execute``), with ``Number``
  (OPC UA's StateEnumeration numbers, 0 Stopped … 16 Unholding) and ``Id`` (that state's
  object in the type); the 17 PackML states are StateType objects of the type;
- ``BenchDeviceType`` (Connected, CommFailures) and one subtype per device kind (driver):
  ``ChadecheDeviceType``, ``Adam5000tcpDeviceType`` …

Every member a type declares has a modelling rule (Mandatory: every instance has it) and a
browse name in the types namespace; an instance's own extra variables (a channel's other
tags, a device's points) have browse names in the bench's namespace. Browse names are
PascalCase; NodeIds stay the tag names (layout.py).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Final

from asyncua import Server, ua

from supervisor.publish.opcua.methods import BENCH_METHODS, METHODS, RESULT, Method, argument
from supervisor.publish.opcua.nodes import method_node, object_node, variable_node

O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation
VT = ua.VariantType

TYPES_URI: Final = "urn:bench-supervisor:types"

PACKML_STATES: Final = (
    "Stopped",
    "Resetting",
    "Idle",
    "Starting",
    "Execute",
    "Completing",
    "Complete",
    "Aborting",
    "Aborted",
    "Stopping",
    "Clearing",
    "Suspending",
    "Suspended",
    "Unsuspending",
    "Holding",
    "Held",
    "Unholding",
)
"""OPC UA's StateEnumeration numbers (reference/semantics.md): a channel's
``chain.state_code`` is the index of its state here."""

CHANNEL_MEMBERS: Final[dict[str, str]] = {
    "Voltage": "analog",
    "Current": "analog",
    "Temperature": "analog",
    "Power": "analog",
    "Charge": "analog",
    "ChargeCounter": "analog",
    "Energy": "analog",
    "Mode": "str",
    "Recipe": "str",
    "Step": "int",
    "StepName": "str",
    "StepTime": "analog",
    "Cycle": "int",
    "Progress": "analog",
    "ETA": "analog",
    "TestId": "str",
    "TestTime": "analog",
    "DriveState": "str",
    "Enable": "bool",
    "ManualCurrent": "analog",
}
"""What ChannelType declares, by browse name: the variable's kind (layout.py). Every
channel has them (tests/unit/test_opcua_types.py holds a bench's channels to it)."""
STATE_MACHINE: Final = "StateMachine"
DEVICE_MEMBERS: Final[dict[str, str]] = {"Connected": "bool", "CommFailures": "int"}
BENCH_FOLDERS: Final = ("Channels", "Devices", "Alarms", "Diagnostics")

DATA_TYPES: Final = {
    "analog": O.Double,
    "int": O.Int64,
    "bool": O.Boolean,
    "str": O.String,
}
MANDATORY: Final = O.ModellingRule_Mandatory


def type_node(name: str, tidx: int) -> ua.NodeId:
    return ua.NodeId(name, tidx)


def state_node(code: int, tidx: int) -> ua.NodeId:
    """The StateType object of PackML state ``code`` in ChannelStateMachineType."""
    return ua.NodeId(f"ChannelStateMachineType/{PACKML_STATES[code]}", tidx)


@dataclass
class StateMachineNodes:
    """One channel's state machine: what a change of its state number rewrites."""

    current: ua.NodeId
    state_id: ua.NodeId
    tidx: int

    def derived(self, dv: ua.DataValue) -> list[tuple[ua.NodeId, ua.DataValue]]:
        """CurrentState (the state's name) and its Id, from a DataValue of its Number."""
        code = dv.Value.Value if dv.Value is not None else None
        known = isinstance(code, int) and 0 <= code < len(PACKML_STATES)
        stamps = {"SourceTimestamp": dv.SourceTimestamp, "ServerTimestamp": dv.ServerTimestamp}
        if not known:
            bad = ua.StatusCode(ua.StatusCodes.BadWaitingForInitialData)
            if dv.StatusCode is not None and not dv.StatusCode.is_good():
                bad = dv.StatusCode
            return [
                (self.current, ua.DataValue(StatusCode=bad, **stamps)),
                (self.state_id, ua.DataValue(StatusCode=bad, **stamps)),
            ]
        assert isinstance(code, int)
        name = ua.Variant(ua.LocalizedText(PACKML_STATES[code]), VT.LocalizedText)
        nid = ua.Variant(state_node(code, self.tidx), VT.NodeId)
        status = dv.StatusCode
        return [
            (self.current, ua.DataValue(name, StatusCode=status, **stamps)),
            (self.state_id, ua.DataValue(nid, StatusCode=status, **stamps)),
        ]


@dataclass
class TypeNodes:
    """The NodeIds of the declared types, by name."""

    tidx: int = 0
    types: dict[str, ua.NodeId] = field(default_factory=dict)


def _object_type(
    nid: ua.NodeId, name: str, tidx: int, parent: int | ua.NodeId, description: str
) -> ua.AddNodesItem:
    it = ua.AddNodesItem()
    it.RequestedNewNodeId = nid
    it.BrowseName = ua.QualifiedName(name, tidx)
    it.NodeClass = ua.NodeClass.ObjectType
    it.ParentNodeId = parent if isinstance(parent, ua.NodeId) else ua.NodeId(parent)
    it.ReferenceTypeId = ua.NodeId(O.HasSubtype)
    a = ua.ObjectTypeAttributes()
    a.DisplayName = ua.LocalizedText(name)
    a.Description = ua.LocalizedText(description)
    a.IsAbstract = False
    it.NodeAttributes = a
    return it


def _member_object(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    typedef: int | ua.NodeId,
    ref: int = O.HasComponent,
) -> ua.AddNodesItem:
    return object_node(nid, browse, parent, ref, typedef)


def _member_variable(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    typedef: int,
    dtype: int | ua.NodeId,
    ref: int = O.HasComponent,
    value: ua.Variant | None = None,
    value_rank: int = ua.ValueRank.Scalar,
) -> ua.AddNodesItem:
    return variable_node(nid, browse, parent, ref, typedef, dtype, value, value_rank=value_rank)


def _methods(
    owner: ua.NodeId, prefix: str, tidx: int, methods: Iterable[Method]
) -> Iterable[ua.AddNodesItem]:
    for m in methods:
        mid = ua.NodeId(f"{prefix}/{m.name}", tidx)
        # A declaration: the instances' methods are called.
        yield method_node(mid, ua.QualifiedName(m.name, tidx), owner, m.description, False)
        for prop, args in (("InputArguments", m.args), ("OutputArguments", (RESULT,))):
            if args:
                yield _member_variable(
                    ua.NodeId(f"{prefix}/{m.name}/{prop}", tidx),
                    ua.QualifiedName(prop, 0),
                    mid,
                    O.PropertyType,
                    O.Argument,
                    O.HasProperty,
                    ua.Variant([argument(a) for a in args], VT.ExtensionObject),
                    ua.ValueRank.OneDimension,
                )


def _variable_type(kind: str) -> int:
    # A declaration's analog variable is a BaseAnalogType: an instance with a known range
    # is an AnalogItemType (its subtype), one without stays a BaseAnalogType (space.py).
    return int(O.BaseAnalogType if kind == "analog" else O.BaseDataVariableType)


def declared(typedef: str) -> frozenset[str]:
    """The browse names of the members type ``typedef`` declares (a device type: its
    supertype's)."""
    if typedef == "ChannelType":
        return frozenset((*CHANNEL_MEMBERS, STATE_MACHINE, *(m.name for m in METHODS)))
    if typedef == "BenchType":
        return frozenset((*BENCH_FOLDERS, *(m.name for m in BENCH_METHODS)))
    if typedef.endswith("DeviceType"):
        return frozenset(DEVICE_MEMBERS)
    return frozenset()


@dataclass
class _Declaration:
    """The types' nodes in the order AddNodes takes them (a parent before its children),
    and the members among them that take the Mandatory modelling rule."""

    items: list[ua.AddNodesItem] = field(default_factory=list)
    members: list[ua.NodeId] = field(default_factory=list)

    def add(self, it: ua.AddNodesItem) -> None:
        self.items.append(it)

    def member(self, it: ua.AddNodesItem) -> None:
        self.items.append(it)
        self.members.append(it.RequestedNewNodeId)

    def methods(self, items: Iterable[ua.AddNodesItem]) -> None:
        """A type's methods are members; their arguments are not (they are properties)."""
        for it in items:
            (self.member if it.NodeClass is ua.NodeClass.Method else self.add)(it)


def type_items(
    tidx: int, device_types: Iterable[str]
) -> tuple[list[ua.AddNodesItem], list[ua.NodeId]]:
    """Every type's nodes, and the members that take the Mandatory modelling rule."""
    d = _Declaration()
    fsm = _state_machine_type(d, tidx)
    _channel_type(d, tidx, fsm)
    _device_types(d, tidx, device_types)
    _bench_type(d, tidx)
    return d.items, d.members


def _state_machine_type(d: _Declaration, tidx: int) -> ua.NodeId:
    """The state machine: FiniteStateMachineType with the PackML states; its NodeId."""
    fsm = type_node("ChannelStateMachineType", tidx)
    d.add(
        _object_type(
            fsm,
            "ChannelStateMachineType",
            tidx,
            O.FiniteStateMachineType,
            "A channel's test state (ISA-88/PackML): CurrentState, its Number and Id",
        )
    )
    current = ua.NodeId("ChannelStateMachineType/CurrentState", tidx)
    d.member(
        _member_variable(
            current,
            ua.QualifiedName("CurrentState", 0),
            fsm,
            O.FiniteStateVariableType,
            O.LocalizedText,
        )
    )
    for prop, dtype in (("Id", O.NodeId), ("Number", O.UInt32)):
        d.member(
            _member_variable(
                ua.NodeId(f"ChannelStateMachineType/CurrentState/{prop}", tidx),
                ua.QualifiedName(prop, 0),
                current,
                O.PropertyType,
                dtype,
                O.HasProperty,
            )
        )
    for code, name in enumerate(PACKML_STATES):
        sid = state_node(code, tidx)
        d.add(_member_object(sid, ua.QualifiedName(name, tidx), fsm, O.StateType))
        d.add(
            _member_variable(
                ua.NodeId(f"ChannelStateMachineType/{name}/StateNumber", tidx),
                ua.QualifiedName("StateNumber", 0),
                sid,
                O.PropertyType,
                O.UInt32,
                O.HasProperty,
                ua.Variant(code, VT.UInt32),
            )
        )
    return fsm


def _channel_type(d: _Declaration, tidx: int, fsm: ua.NodeId) -> None:
    """The channel: its variables, its StateMachine (of type ``fsm``), its methods."""
    channel = type_node("ChannelType", tidx)
    d.add(_object_type(channel, "ChannelType", tidx, O.BaseObjectType, "A test channel"))
    for name, kind in CHANNEL_MEMBERS.items():
        d.member(
            _member_variable(
                ua.NodeId(f"ChannelType/{name}", tidx),
                ua.QualifiedName(name, tidx),
                channel,
                _variable_type(kind),
                DATA_TYPES[kind],
            )
        )
    d.member(
        _member_object(
            ua.NodeId(f"ChannelType/{STATE_MACHINE}", tidx),
            ua.QualifiedName(STATE_MACHINE, tidx),
            channel,
            fsm,
        )
    )
    d.methods(_methods(channel, "ChannelType", tidx, METHODS))


def _device_types(d: _Declaration, tidx: int, device_types: Iterable[str]) -> None:
    """Devices: BenchDeviceType with their health, and its subtype of each kind."""
    device = type_node("BenchDeviceType", tidx)
    d.add(_object_type(device, "BenchDeviceType", tidx, O.BaseObjectType, "A device: its health"))
    for name, kind in DEVICE_MEMBERS.items():
        d.member(
            _member_variable(
                ua.NodeId(f"BenchDeviceType/{name}", tidx),
                ua.QualifiedName(name, tidx),
                device,
                O.BaseDataVariableType,
                DATA_TYPES[kind],
            )
        )
    for name in sorted(set(device_types)):
        d.add(
            _object_type(
                type_node(name, tidx),
                name,
                tidx,
                device,
                f"A device of kind {name.removesuffix('DeviceType').lower()} and its points",
            )
        )


def _bench_type(d: _Declaration, tidx: int) -> None:
    """The bench: its folders and its methods."""
    bench = type_node("BenchType", tidx)
    d.add(_object_type(bench, "BenchType", tidx, O.BaseObjectType, "A test bench"))
    for name in BENCH_FOLDERS:
        d.member(
            _member_object(
                ua.NodeId(f"BenchType/{name}", tidx),
                ua.QualifiedName(name, tidx),
                bench,
                O.FolderType,
                O.Organizes,
            )
        )
    d.methods(_methods(bench, "BenchType", tidx, BENCH_METHODS))


async def build_object_types(server: Server, tidx: int, device_types: Iterable[str]) -> None:
    """Declare the types (one AddNodes batch) with their members' modelling rules."""
    items, members = type_items(tidx, device_types)
    results = await server.iserver.isession.add_nodes(items)
    bad = [
        (i.RequestedNewNodeId, r.StatusCode)
        for i, r in zip(items, results, strict=True)
        if not r.StatusCode.is_good()
    ]
    if bad:
        raise RuntimeError(f"OPC UA types: {len(bad)} nodes refused, first {bad[0]}")
    # Properties of declared members (InputArguments, Id, Number …) are Mandatory too.
    ruled = list(members) + [
        i.RequestedNewNodeId
        for i in items
        if i.ReferenceTypeId == ua.NodeId(O.HasProperty)
        and i.RequestedNewNodeId not in members
        and "/StateNumber" not in str(i.RequestedNewNodeId.Identifier)
    ]
    refs = []
    for nid in ruled:
        ref = ua.AddReferencesItem()
        ref.IsForward = True
        ref.ReferenceTypeId = ua.NodeId(O.HasModellingRule)
        ref.SourceNodeId = nid
        ref.TargetNodeClass = ua.NodeClass.Object
        ref.TargetNodeId = ua.NodeId(MANDATORY)
        refs.append(ref)
    await server.iserver.isession.add_references(refs)


# --- alarm conditions (Part 9) --------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ConditionMember:
    """A standard child of an AlarmConditionType instance: its path under the condition
    (``ActiveState/Id``), reference, type definition, DataType."""

    path: str
    ref: int
    typedef: int
    dtype: int

    @property
    def browse(self) -> str:
        return self.path.rpartition("/")[2]


CONDITION_MEMBERS: Final = tuple(
    ConditionMember(path, ref, typedef, dtype)
    for path, ref, typedef, dtype in (
        ("EnabledState", O.HasComponent, O.TwoStateVariableType, O.LocalizedText),
        ("EnabledState/Id", O.HasProperty, O.PropertyType, O.Boolean),
        ("ActiveState", O.HasComponent, O.TwoStateVariableType, O.LocalizedText),
        ("ActiveState/Id", O.HasProperty, O.PropertyType, O.Boolean),
        ("AckedState", O.HasComponent, O.TwoStateVariableType, O.LocalizedText),
        ("AckedState/Id", O.HasProperty, O.PropertyType, O.Boolean),
        ("Retain", O.HasProperty, O.PropertyType, O.Boolean),
        ("ConditionName", O.HasProperty, O.PropertyType, O.String),
        ("ConditionClassId", O.HasProperty, O.PropertyType, O.NodeId),
        ("ConditionClassName", O.HasProperty, O.PropertyType, O.LocalizedText),
        ("ClientUserId", O.HasProperty, O.PropertyType, O.String),
        ("BranchId", O.HasProperty, O.PropertyType, O.NodeId),
        ("Quality", O.HasComponent, O.ConditionVariableType, O.StatusCode),
        ("LastSeverity", O.HasComponent, O.ConditionVariableType, O.UInt16),
        ("Comment", O.HasComponent, O.ConditionVariableType, O.LocalizedText),
        ("SuppressedOrShelved", O.HasProperty, O.PropertyType, O.Boolean),
        ("InputNode", O.HasProperty, O.PropertyType, O.NodeId),
    )
)
"""The mandatory variables of ConditionType, AcknowledgeableConditionType and
AlarmConditionType a client reads on the condition object (the event fields of
BaseEventType are in its events, events.py; ShelvingState is built with the alarm)."""


def condition_values(
    active: bool, acked: bool, retained: bool, shelved: bool, name: str, severity: int, actor: str
) -> dict[str, ua.Variant]:
    """The values of ``CONDITION_MEMBERS`` for an alarm in this state, by path."""
    LT = VT.LocalizedText
    return {
        "EnabledState": ua.Variant(ua.LocalizedText("Enabled"), LT),
        "EnabledState/Id": ua.Variant(True, VT.Boolean),
        "ActiveState": ua.Variant(ua.LocalizedText("Active" if active else "Inactive"), LT),
        "ActiveState/Id": ua.Variant(active, VT.Boolean),
        "AckedState": ua.Variant(
            ua.LocalizedText("Acknowledged" if acked else "Unacknowledged"), LT
        ),
        "AckedState/Id": ua.Variant(acked, VT.Boolean),
        "Retain": ua.Variant(retained, VT.Boolean),
        "ConditionName": ua.Variant(name, VT.String),
        "ConditionClassId": ua.Variant(ua.NodeId(O.ProcessConditionClassType), VT.NodeId),
        "ConditionClassName": ua.Variant(ua.LocalizedText("Process"), LT),
        "ClientUserId": ua.Variant(actor, VT.String),
        "BranchId": ua.Variant(ua.NodeId(), VT.NodeId),
        "Quality": ua.Variant(ua.StatusCode(ua.StatusCodes.Good), VT.StatusCode),
        "LastSeverity": ua.Variant(max(1, min(1000, severity)), VT.UInt16),
        "Comment": ua.Variant(ua.LocalizedText(""), LT),
        "SuppressedOrShelved": ua.Variant(shelved, VT.Boolean),
        "InputNode": ua.Variant(ua.NodeId(), VT.NodeId),
    }
