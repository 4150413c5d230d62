"""The AddNodes items the address space is built of, once: a variable, an object and a
method (OPC UA Part 4 §5.7.2), for the instances (``space.py``) and the type declarations
(``objecttypes.py``) alike."""

from __future__ import annotations

from typing import Final

from asyncua import ua

O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation
READ: Final = ua.AccessLevel.CurrentRead.mask


def _node_id(n: int | ua.NodeId) -> ua.NodeId:
    return n if isinstance(n, ua.NodeId) else ua.NodeId(n)


def _item(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    node_class: ua.NodeClass,
    parent: ua.NodeId,
    ref: int,
    typedef: int | ua.NodeId | None,
) -> ua.AddNodesItem:
    it = ua.AddNodesItem()
    it.RequestedNewNodeId = nid
    it.BrowseName = browse
    it.NodeClass = node_class
    it.ParentNodeId = parent
    it.ReferenceTypeId = ua.NodeId(ref)
    if typedef is not None:
        it.TypeDefinition = _node_id(typedef)
    return it


def variable_node(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    ref: int,
    typedef: int,
    dtype: int | ua.NodeId,
    value: ua.Variant | None = None,
    description: str = "",
    access: int = READ,
    value_rank: int = ua.ValueRank.Scalar,
    sampling_ms: float = 0.0,
    historizing: bool = False,
) -> ua.AddNodesItem:
    """A variable (``value`` None: none given, as a type's declaration has)."""
    it = _item(nid, browse, ua.NodeClass.Variable, parent, ref, typedef)
    a = ua.VariableAttributes()
    a.DisplayName = ua.LocalizedText(browse.Name)
    a.Description = ua.LocalizedText(description or browse.Name)
    a.DataType = _node_id(dtype)
    if value is not None:
        a.Value = value
    a.ValueRank = value_rank
    a.AccessLevel = access
    a.UserAccessLevel = access
    a.MinimumSamplingInterval = sampling_ms
    a.Historizing = historizing
    it.NodeAttributes = a
    return it


def object_node(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    ref: int,
    typedef: int | ua.NodeId,
    description: str = "",
    notifier: bool = False,
) -> ua.AddNodesItem:
    it = _item(nid, browse, ua.NodeClass.Object, parent, ref, typedef)
    a = ua.ObjectAttributes()
    a.DisplayName = ua.LocalizedText(browse.Name)
    a.Description = ua.LocalizedText(description or browse.Name)
    a.EventNotifier = ua.EventNotifier.SubscribeToEvents.mask if notifier else 0
    it.NodeAttributes = a
    return it


def method_node(
    nid: ua.NodeId,
    browse: ua.QualifiedName,
    parent: ua.NodeId,
    description: str,
    executable: bool = True,
) -> ua.AddNodesItem:
    """A method (``executable`` False: a type's declaration; its instances' are called)."""
    it = _item(nid, browse, ua.NodeClass.Method, parent, O.HasComponent, None)
    a = ua.MethodAttributes()
    a.DisplayName = ua.LocalizedText(browse.Name)
    a.Description = ua.LocalizedText(description)
    a.Executable = executable
    a.UserExecutable = executable
    it.NodeAttributes = a
    return it
