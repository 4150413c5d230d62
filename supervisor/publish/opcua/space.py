"""Building the bench's address space from its ``Layout`` (layout.py), in one AddNodes batch.

Objects are instances of the types of objecttypes.py (BenchType, ChannelType, a device type
per kind, ChannelStateMachineType); a member its type declares has the types namespace's
browse name, anything else the bench's. Alarm objects are AlarmConditionType instances.

Analog tags with a known range (the tag's, from the configuration: a channel's limits, an
I/O map's range) are variables of type **AnalogItemType** (Part 8 §5.3.2) with DataType
Double, their ``EURange`` and ``EngineeringUnits`` (UNECE, units.py), both with NodeIds in
the bench's namespace; one without a known range is a **BaseAnalogType** (Part 8 1.04,
EURange optional) with its units and no EURange: a made-up range (every finite Double)
misled clients that scale by it or use a percent deadband (issue 31, finding 9).

``asyncua.common.instantiate_util.instantiate`` makes the same nodes, one browse of the
type per call: measured 4.6 s for 150 analog tags against 0.29 s for this one batch (2
loaded cores), which is why the nodes are listed here.

A channel's state is its StateMachine's CurrentState: the PackML name (``Execute``), with
``Number`` (``chN.chain.state_code``, the OPC UA numbering 0 Stopped … 16 Unholding,
reference/semantics.md) and ``Id``; the server rewrites CurrentState and Id whenever the
number changes (``StateMachineNodes.derived``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Final

from asyncua import Server, ua

from supervisor.publish.opcua.layout import Folder, Layout, Variable
from supervisor.publish.opcua.methods import BENCH_METHODS, METHODS, RESULT, Method, argument
from supervisor.publish.opcua.nodes import READ, method_node, object_node, variable_node
from supervisor.publish.opcua.objecttypes import (
    CONDITION_MEMBERS,
    PACKML_STATES,
    TYPES_URI,
    StateMachineNodes,
    build_object_types,
    condition_values,
    declared,
    state_node,
    type_node,
)
from supervisor.publish.opcua.units import eu_information

O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation
VT = ua.VariantType

__all__ = ["PACKML_STATES", "Built", "build_space"]

ALARM_FIELDS: Final = (
    ("State", VT.String, "normal, active, unacknowledged, …"),
    ("Active", VT.Boolean, "The condition is present"),
    ("Acked", VT.Boolean, "Acknowledged"),
    ("Severity", VT.UInt16, "1..1000"),
    ("Message", VT.String, "What happened"),
    ("Tripped", VT.Boolean, "A trip that still holds its channel (until reset)"),
    ("Shelved", VT.Boolean, "Shelved for a time (ISA-18.2): not annunciated meanwhile"),
)

EVENT_FIELDS: Final = ("Channel", "Kind", "Source", "Actor", "TestId", "Recipe")
"""Properties of BenchEventType: where, what, who (the actor of a command)."""

WRITE: Final = ua.AccessLevel.CurrentWrite.mask
HISTORY: Final = ua.AccessLevel.HistoryRead.mask


@dataclass
class Built:
    """The NodeIds of what was built."""

    tags: dict[str, tuple[ua.NodeId, str]] = field(default_factory=dict)  # name → (id, kind)
    channels: dict[str, ua.NodeId] = field(default_factory=dict)
    alarms: dict[str, ua.NodeId] = field(default_factory=dict)
    alarm_fields: dict[tuple[str, str], ua.NodeId] = field(default_factory=dict)
    shelving: dict[str, ua.NodeId] = field(default_factory=dict)  # alarm → its ShelvingState
    methods: dict[ua.NodeId, tuple[str, Method]] = field(default_factory=dict)
    bench: ua.NodeId = field(default_factory=ua.NodeId)
    types_ns: int = 0  # the types namespace's index (objecttypes.py)
    state_machines: dict[ua.NodeId, StateMachineNodes] = field(default_factory=dict)
    """By the NodeId of each channel's state number: what its changes rewrite."""
    bench_event: ua.NodeId = field(default_factory=ua.NodeId)
    chain_event: ua.NodeId = field(default_factory=ua.NodeId)
    command_event: ua.NodeId = field(default_factory=ua.NodeId)


def _object(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    folder: bool,
    description: str = "",
    notifier: bool = False,
    typedef: ua.NodeId | None = None,
) -> ua.AddNodesItem:
    """A folder (organised under its parent) or a component object."""
    ref = O.Organizes if folder else O.HasComponent
    default = O.FolderType if folder else O.BaseObjectType
    return object_node(nid, browse, parent, ref, typedef or default, description, notifier)


def default_variant(kind: str) -> ua.Variant:
    if kind == "analog":
        return ua.Variant(0.0, VT.Double)
    if kind == "int":
        return ua.Variant(0, VT.Int64)
    if kind == "state":
        return ua.Variant(0, VT.UInt32)
    if kind == "statename":
        return ua.Variant(ua.LocalizedText(""), VT.LocalizedText)
    if kind == "bool":
        return ua.Variant(False, VT.Boolean)
    return ua.Variant("", VT.String)


DATA_TYPES: Final = {
    "analog": ua.NodeId(O.Double),
    "int": ua.NodeId(O.Int64),
    "bool": ua.NodeId(O.Boolean),
    "str": ua.NodeId(O.String),
}


async def build_types(
    server: Server, idx: int, built: Built, device_types: Iterable[str] = ()
) -> None:
    """The object types (objecttypes.py, in their own namespace) and the bench's event
    types."""
    tidx = await server.register_namespace(TYPES_URI)
    built.types_ns = tidx
    await build_object_types(server, tidx, device_types)
    base = server.get_node(ua.ObjectIds.BaseEventType)
    bench_event = await base.add_object_type(
        ua.NodeId("/Types/BenchEventType", idx), ua.QualifiedName("BenchEventType", idx)
    )
    for name in EVENT_FIELDS:
        await bench_event.add_property(
            ua.NodeId(f"/Types/BenchEventType/{name}", idx),
            ua.QualifiedName(name, idx),
            ua.Variant("", VT.String),
        )
    chain = await bench_event.add_object_type(
        ua.NodeId("/Types/ChainEventType", idx), ua.QualifiedName("ChainEventType", idx)
    )
    command = await bench_event.add_object_type(
        ua.NodeId("/Types/CommandEventType", idx), ua.QualifiedName("CommandEventType", idx)
    )
    built.bench_event = bench_event.nodeid
    built.chain_event = chain.nodeid
    built.command_event = command.nodeid


def _state_machine_items(
    f: Folder,
    nid: ua.NodeId,
    idx: int,
    built: Built,
    sampling_ms: float,
    historised: frozenset[str],
) -> Iterable[ua.AddNodesItem]:
    """A channel's StateMachine: CurrentState (the ``chain.state`` tag's NodeId, its value
    the PackML name), its Number (the ``chain.state_code`` tag: the state's history) and
    its Id."""
    by_browse = {v.browse: v for v in f.variables}
    name, number = by_browse.get("CurrentState"), by_browse.get("Number")
    if name is None or number is None:
        return
    current = ua.NodeId(name.tag, idx)
    state_id = ua.NodeId(f"{f.node}/CurrentState/Id", idx)
    number_id = ua.NodeId(number.tag, idx)
    built.tags[name.tag] = (current, "statename")
    built.tags[number.tag] = (number_id, "state")
    built.state_machines[number_id] = StateMachineNodes(current, state_id, built.types_ns)
    yield variable_node(
        current,
        ua.QualifiedName("CurrentState", 0),
        nid,
        O.HasComponent,
        O.FiniteStateVariableType,
        ua.NodeId(O.LocalizedText),
        ua.Variant(ua.LocalizedText(PACKML_STATES[2]), VT.LocalizedText),
        "The test's state: its PackML name (ISA-88)",
        sampling_ms=sampling_ms,
    )
    yield variable_node(
        state_id,
        ua.QualifiedName("Id", 0),
        current,
        O.HasProperty,
        O.PropertyType,
        ua.NodeId(O.NodeId),
        ua.Variant(state_node(2, built.types_ns), VT.NodeId),
        "The current state's object in ChannelStateMachineType",
    )
    yield variable_node(
        number_id,
        ua.QualifiedName("Number", 0),
        current,
        O.HasProperty,
        O.PropertyType,
        ua.NodeId(O.UInt32),
        ua.Variant(2, VT.UInt32),
        number.description or "OPC UA StateEnumeration number (0 Stopped … 16 Unholding)",
        READ | (HISTORY if number.tag in historised else 0),
        sampling_ms=sampling_ms,
        historizing=number.tag in historised,
    )


def _data_type(kind: str) -> ua.NodeId:
    """The DataType of a variable of a tag of this kind, analog aside (a state outside a
    channel's state machine: its number, or its name)."""
    if kind == "state":
        return ua.NodeId(O.UInt32)
    if kind == "statename":
        return ua.NodeId(O.LocalizedText)
    return DATA_TYPES[kind]


def _tag_items(
    v: Variable,
    parent: ua.NodeId,
    idx: int,
    built: Built,
    sampling_ms: float,
    historised: frozenset[str],
    browse_ns: int = 0,
) -> Iterable[ua.AddNodesItem]:
    nid = ua.NodeId(v.tag, idx)
    kept = v.tag in historised  # Part 11: Historizing and the HistoryRead access bit
    access = READ | (WRITE if v.writable else 0) | (HISTORY if kept else 0)
    browse = ua.QualifiedName(v.browse, browse_ns or idx)
    built.tags[v.tag] = (nid, v.kind)
    if v.kind != "analog":
        yield variable_node(
            nid,
            browse,
            parent,
            O.HasComponent,
            O.BaseDataVariableType,
            _data_type(v.kind),
            default_variant(v.kind),
            v.description,
            access,
            sampling_ms=sampling_ms,
            historizing=kept,
        )
        return
    # Part 8: an AnalogItemType has a mandatory EURange; without a configured range the tag
    # is a BaseAnalogType (EURange optional) rather than one with a made-up range.
    yield variable_node(
        nid,
        browse,
        parent,
        O.HasComponent,
        O.AnalogItemType if v.range is not None else O.BaseAnalogType,
        DATA_TYPES["analog"],
        default_variant("analog"),
        v.description,
        access,
        sampling_ms=sampling_ms,
        historizing=kept,
    )
    yield from _analog_properties(v, nid, idx)


def _analog_properties(v: Variable, nid: ua.NodeId, idx: int) -> Iterable[ua.AddNodesItem]:
    """An analog tag's EURange (when its range is known) and EngineeringUnits (when it has
    a unit), properties of its variable ``nid``."""
    if v.range is not None:
        low, high = v.range
        yield variable_node(
            ua.NodeId(f"{v.tag}.EURange", idx),
            ua.QualifiedName("EURange", 0),
            nid,
            O.HasProperty,
            O.PropertyType,
            ua.NodeId(O.Range),
            ua.Variant(ua.Range(low, high), VT.ExtensionObject),
            "Range of the value in normal operation",
        )
    if v.unit:
        yield variable_node(
            ua.NodeId(f"{v.tag}.EngineeringUnits", idx),
            ua.QualifiedName("EngineeringUnits", 0),
            nid,
            O.HasProperty,
            O.PropertyType,
            ua.NodeId(O.EUInformation),
            ua.Variant(eu_information(v.unit), VT.ExtensionObject),
            f"Unit: {v.unit} (UNECE)",
        )


def _folder_items(
    f: Folder,
    parent: ua.NodeId,
    idx: int,
    built: Built,
    sampling_ms: float,
    historised: frozenset[str],
    browse_ns: int = 0,
) -> Iterable[ua.AddNodesItem]:
    """``f`` and what it holds; ``browse_ns``: its browse name's namespace (the types
    namespace when its parent's type declares it)."""
    nid = ua.NodeId(f.node, idx)
    notifier = bool(f.channel) or f.node == "/Bench"
    tidx = built.types_ns
    if f.alarm:
        typedef: ua.NodeId | None = ua.NodeId(O.AlarmConditionType)
    else:
        typedef = type_node(f.typedef, tidx) if f.typedef else None
    yield _object(
        nid,
        ua.QualifiedName(f.browse, browse_ns or idx),
        parent,
        f.folder,
        f.description,
        notifier,
        typedef,
    )
    members = declared(f.typedef)

    def ns_of(browse: str) -> int:
        return tidx if browse in members else idx

    if f.typedef == "ChannelStateMachineType":
        yield from _state_machine_items(f, nid, idx, built, sampling_ms, historised)
        return
    if f.node == "/Bench":
        built.bench = nid
    if f.channel:
        built.channels[f.channel] = nid
    if f.alarm:
        yield from _alarm_items(f, nid, idx, built)
    for v in f.variables:
        yield from _tag_items(v, nid, idx, built, sampling_ms, historised, ns_of(v.browse))
    for c in f.children:
        yield from _folder_items(c, nid, idx, built, sampling_ms, historised, ns_of(c.browse))
    yield from _method_items(f, nid, idx, built, ns_of)


def _alarm_items(f: Folder, nid: ua.NodeId, idx: int, built: Built) -> Iterable[ua.AddNodesItem]:
    """An alarm's condition object ``nid``: its ShelvingState, the standard variables of a
    condition (Part 9) and the bench's own fields (``ALARM_FIELDS``)."""
    built.alarms[f.alarm] = nid
    # Part 9: the shelving methods are called on the condition's ShelvingState object.
    sid = ua.NodeId(f"{f.node}/ShelvingState", idx)
    built.shelving[f.alarm] = sid
    yield _object(sid, ua.QualifiedName("ShelvingState", 0), nid, False, "Shelving")
    # Part 9: what a client reads on a condition object, as its events say it.
    initial = condition_values(False, True, False, False, f.alarm, 1, "")
    for member in CONDITION_MEMBERS:
        cid = ua.NodeId(f"{f.node}/{member.path}", idx)
        above = member.path.rpartition("/")[0]  # a state's Id is its property
        owner = ua.NodeId(f"{f.node}/{above}", idx) if above else nid
        built.alarm_fields[(f.alarm, member.path)] = cid
        yield variable_node(
            cid,
            ua.QualifiedName(member.browse, 0),
            owner,
            member.ref,
            member.typedef,
            ua.NodeId(member.dtype),
            initial[member.path],
            member.path,
        )
    for name, vt, description in ALARM_FIELDS:
        fid = ua.NodeId(f"{f.node}/{name}", idx)
        built.alarm_fields[(f.alarm, name)] = fid
        yield variable_node(
            fid,
            ua.QualifiedName(name, idx),
            nid,
            O.HasComponent,
            O.BaseDataVariableType,
            ua.NodeId(vt.value),
            ua.Variant(ua.get_default_value(vt), vt),
            description,
        )


def _method_items(
    f: Folder, nid: ua.NodeId, idx: int, built: Built, ns_of: Callable[[str], int]
) -> Iterable[ua.AddNodesItem]:
    """A channel's or the Bench's methods with their arguments; ``ns_of``: a browse name's
    namespace (the types namespace for a member the object's type declares)."""
    own = METHODS if f.channel else BENCH_METHODS if f.node == "/Bench" else ()
    for m in own:
        mid = ua.NodeId(f"{f.node}/{m.name}", idx)
        built.methods[mid] = (f.channel, m)
        yield method_node(mid, ua.QualifiedName(m.name, ns_of(m.name)), nid, m.description)
        for prop, args in (("InputArguments", m.args), ("OutputArguments", (RESULT,))):
            if not args:
                continue
            yield variable_node(
                ua.NodeId(f"{f.node}/{m.name}/{prop}", idx),
                ua.QualifiedName(prop, 0),
                mid,
                O.HasProperty,
                O.PropertyType,
                ua.NodeId(O.Argument),
                ua.Variant([argument(a) for a in args], VT.ExtensionObject),
                prop,
                value_rank=ua.ValueRank.OneDimension,
            )


async def build_space(
    server: Server,
    idx: int,
    layout: Layout,
    scan_period_s: float,
    historised: frozenset[str] = frozenset(),
) -> Built:
    """Types, then every object, variable and method of ``layout`` under Objects; the tags
    in ``historised`` with Historizing true and the HistoryRead access bit."""
    built = Built()
    device_types = {f.typedef for f in layout.root.walk() if f.typedef.endswith("DeviceType")}
    await build_types(server, idx, built, device_types)
    objects = ua.NodeId(O.ObjectsFolder)
    items = list(
        _folder_items(layout.root, objects, idx, built, scan_period_s * 1000.0, historised)
    )
    results = await server.iserver.isession.add_nodes(items)
    bad = [
        (i.RequestedNewNodeId, r.StatusCode)
        for i, r in zip(items, results, strict=True)
        if not r.StatusCode.is_good()
    ]
    if bad:
        raise RuntimeError(f"OPC UA address space: {len(bad)} nodes refused, first {bad[0]}")
    return built
