"""Operation limits, browse paging and fair serving (issue 31, finding 4;
docs/adr/0014-opcua-server.md, "Issue 31: sessions, security and fair serving").

asyncua advertises 10,000 under Server/ServerCapabilities/OperationLimits and enforces none
of it, ignores a Browse's ``RequestedMaxReferencesPerNode``, has no BrowseNext, and serves a
request in one go on the server's loop: an anonymous 10,000-node Browse (both directions,
subtypes) took ~10 ms a node and another client's 100 ms subscription got nothing for 60 to
89 s. Here, called by the connection's processor (``sessions.py``) before asyncua sees the
request:

- **Operation limits** (``LIMITS``): the values advertised are the ones enforced; a request
  with more operations than its limit is answered Bad_TooManyOperations, the reason in the
  fault's diagnostics. The count is read from the request's array length without decoding
  the array (``operation_count``, proven equal to the decoded length for every limited
  request kind by a unit test).
- **Browse and BrowseNext** are served here: the references a node has (asyncua's rules:
  direction, reference type and its subtypes, node class mask), at most
  ``RequestedMaxReferencesPerNode`` of them (``MAX_REFERENCES_PER_NODE`` when the client
  asks for none or more), the rest behind a continuation point of the session
  (``MAX_BROWSE_CONTINUATION_POINTS`` at once, Bad_NoContinuationPoints past them) that
  BrowseNext returns or releases. A reference type's subtypes are computed once (asyncua
  walked the type tree again for every reference: most of the 10 ms).
- **Fair serving**: each node to browse is decoded, browsed and its result encoded in turn,
  in slices of ``SLICE_S``; between two slices the server's loop serves the other clients
  (their publish responses, their connections). The answer's bytes are asyncua's own
  encoding, built result by result (proven equal by a unit test), and nothing of the
  request outlives its node: kept as objects, a 10,000-node request set off the garbage
  collector's full collections (``Answer``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import time
from collections import OrderedDict
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.utils import Buffer
from asyncua.ua.ua_binary import (
    Primitives,
    extensionobject_from_binary,
    from_binary,
    get_safe_type_hints,
    nodeid_to_binary,
    struct_from_binary,
    struct_to_binary,
)
from asyncua.ua.uatypes import type_allow_subclass, type_from_optional, type_is_optional

log = logging.getLogger(__name__)

S = ua.StatusCodes
O = ua.ObjectIds  # noqa: E741 - asyncua's own abbreviation

SLICE_S: Final = 0.005
"""Work done for one request between two turns of the server's loop: a 100 ms subscription's
publish waits at most this long for a browsing client (plus one slice of each other busy
client)."""
MAX_REFERENCES_PER_NODE: Final = 1000
"""References returned per node at most in one answer (the rest behind a continuation
point), whatever the client asks: one answer's size stays bounded."""
MAX_BROWSE_CONTINUATION_POINTS: Final = 16
"""Continuation points a session holds at once (ServerCapabilities/MaxBrowseContinuationPoints)."""


def _request(name: str) -> ua.NodeId:
    return ua.NodeId(getattr(O, f"{name}Request_Encoding_DefaultBinary"))


@dataclasses.dataclass(frozen=True, slots=True)
class Limit:
    """One OperationLimits property and the requests it bounds."""

    name: str
    """Its browse name under Server/ServerCapabilities/OperationLimits."""
    value: int
    requests: tuple[tuple[type, str], ...]
    """(request parameters' type, the field holding its operations)."""


LIMITS: Final = (
    Limit("MaxNodesPerRead", 10_000, ((ua.ReadParameters, "NodesToRead"),)),
    Limit(
        "MaxNodesPerBrowse",
        10_000,
        ((ua.BrowseParameters, "NodesToBrowse"), (ua.BrowseNextParameters, "ContinuationPoints")),
    ),
    Limit(
        "MaxNodesPerTranslateBrowsePathsToNodeIds",
        10_000,
        ((ua.TranslateBrowsePathsToNodeIdsParameters, "BrowsePaths"),),
    ),
    Limit(
        "MaxNodesPerRegisterNodes",
        10_000,
        (
            (ua.RegisterNodesParameters, "NodesToRegister"),
            (ua.UnregisterNodesParameters, "NodesToUnregister"),
        ),
    ),
    Limit(
        "MaxMonitoredItemsPerCall",
        10_000,
        (
            (ua.CreateMonitoredItemsParameters, "ItemsToCreate"),
            (ua.ModifyMonitoredItemsParameters, "ItemsToModify"),
            (ua.DeleteMonitoredItemsParameters, "MonitoredItemIds"),
            (ua.SetMonitoringModeParameters, "MonitoredItemIds"),
        ),
    ),
    # Each write of a tag and each call is a command on the bench's one command path (ADR
    # 0008), run between two scans: a batch stays a batch of commands, not a flood.
    Limit("MaxNodesPerWrite", 1000, ((ua.WriteParameters, "NodesToWrite"),)),
    Limit("MaxNodesPerMethodCall", 100, ((ua.CallParameters, "MethodsToCall"),)),
    # HistoryRead is one limit here for both kinds: the details say which, and a client
    # reads both properties (each answers the same).
    Limit("MaxNodesPerHistoryReadData", 1000, ((ua.HistoryReadParameters, "NodesToRead"),)),
    Limit("MaxNodesPerHistoryReadEvents", 1000, ()),
    Limit(
        "MaxNodesPerHistoryUpdateData",
        1000,
        ((ua.HistoryUpdateParameters, "HistoryUpdateDetails"),),
    ),
    Limit("MaxNodesPerHistoryUpdateEvents", 1000, ()),
    Limit(
        "MaxNodesPerNodeManagement",
        1000,
        (
            (ua.AddNodesParameters, "NodesToAdd"),
            (ua.AddReferencesParameters, "ReferencesToAdd"),
            (ua.DeleteNodesParameters, "NodesToDelete"),
            (ua.DeleteReferencesParameters, "ReferencesToDelete"),
        ),
    ),
)
"""What the server advertises under OperationLimits and enforces (Part 5 §6.3.11)."""


def _encoding_of(params: type) -> ua.NodeId:
    return _request(params.__name__.removesuffix("Parameters"))


BOUNDED: Final[dict[ua.NodeId, tuple[Limit, type, str]]] = {
    _encoding_of(params): (limit, params, field)
    for limit in LIMITS
    for params, field in limit.requests
}
"""Request encoding → its limit, parameters' type and operations' field."""

BROWSE: Final = _request("Browse")
BROWSE_NEXT: Final = _request("BrowseNext")


def operation_count(params: type, field: str, body: Buffer) -> int:
    """The number of operations in a request's ``field`` (an array), read from its length
    prefix: the fields before it are decoded (a few bytes), the array is not. ``body`` is
    left where it was. -1 for a null array, as OPC UA encodes it."""
    data = body.copy()
    hints = get_safe_type_hints(params, {"ua": ua})
    for f in dataclasses.fields(params):
        if f.name == field:
            count: int = Primitives.Int32.unpack(data)
            return count
        t = hints[f.name]
        if type_is_optional(t):
            t = type_from_optional(t)
        if type_allow_subclass(t):
            extensionobject_from_binary(data)
        else:
            from_binary(t, data)
    raise ValueError(f"{params.__name__} has no field {field}")


def too_many(typeid: ua.NodeId, body: Buffer) -> str | None:
    """Why a request has more operations than the server takes (None: it has not)."""
    bound = BOUNDED.get(typeid)
    if bound is None:
        return None
    limit, params, field = bound
    n = operation_count(params, field, body)
    if n <= limit.value:
        return None
    kind = params.__name__.removesuffix("Parameters")
    return f"{kind} of {n} operations: the server's {limit.name} is {limit.value}"


async def advertise(server: Server) -> None:
    """Write the enforced limits under Server/ServerCapabilities (asyncua writes 10,000 for
    each and enforces none)."""
    values: list[tuple[int, ua.Variant]] = [
        (
            getattr(O, f"Server_ServerCapabilities_OperationLimits_{limit.name}"),
            ua.Variant(limit.value, ua.VariantType.UInt32),
        )
        for limit in LIMITS
    ]
    values.append(
        (
            O.Server_ServerCapabilities_MaxBrowseContinuationPoints,
            ua.Variant(MAX_BROWSE_CONTINUATION_POINTS, ua.VariantType.UInt16),
        )
    )
    aspace = server.iserver.aspace
    for nid, variant in values:
        await aspace.write_attribute_value(
            ua.NodeId(nid), ua.AttributeIds.Value, ua.DataValue(variant)
        )


class Slices:
    """Hands the loop back to the other clients every ``SLICE_S`` of work."""

    def __init__(self, slice_s: float = SLICE_S) -> None:
        self.slice_s = slice_s
        self.yields = 0
        self._since = time.perf_counter()

    async def tick(self) -> None:
        if time.perf_counter() - self._since >= self.slice_s:
            await asyncio.sleep(0)
            self.yields += 1
            self._since = time.perf_counter()


@dataclasses.dataclass(slots=True)
class _Pending:
    """What a continuation point still has to return."""

    references: list[ua.ReferenceDescription]
    max_references: int


class ContinuationPoints:
    """One session's browse continuation points (Part 4 §7.9). The processor keeps one per
    connection; a new session on it starts with none."""

    def __init__(self) -> None:
        self._owner: object | None = None
        self._points: OrderedDict[bytes, _Pending] = OrderedDict()

    def of(self, session: object) -> OrderedDict[bytes, _Pending]:
        if session is not self._owner:
            self._owner = session
            self._points = OrderedDict()
        return self._points


class Browser:
    """Browse and BrowseNext over asyncua's address space, a node at a time."""

    def __init__(self, aspace: Any) -> None:
        self._aspace = aspace
        self._subtypes: dict[ua.NodeId, frozenset[ua.NodeId]] = {}

    def subtypes(self, reftype: ua.NodeId) -> frozenset[ua.NodeId]:
        """``reftype`` and all its subtypes (computed once: reference types are not added
        once the server serves)."""
        found = self._subtypes.get(reftype)
        if found is None:
            out: set[ua.NodeId] = {reftype}
            todo = [reftype]
            subtype = ua.NodeId(O.HasSubtype)
            while todo:
                nd = self._aspace.get(todo.pop())
                if nd is None:
                    continue
                for r in nd.references:
                    if r.ReferenceTypeId == subtype and r.IsForward and r.NodeId not in out:
                        out.add(r.NodeId)
                        todo.append(r.NodeId)
            found = self._subtypes[reftype] = frozenset(out)
        return found

    def references(self, desc: ua.BrowseDescription) -> list[ua.ReferenceDescription] | int:
        """The references of ``desc``'s node that it asks for, or the Bad status code."""
        if desc.NodeId not in self._aspace:
            return int(S.BadNodeIdUnknown)
        direction = desc.BrowseDirection
        if direction not in (
            ua.BrowseDirection.Forward,
            ua.BrowseDirection.Inverse,
            ua.BrowseDirection.Both,
        ):
            return int(S.BadBrowseDirectionInvalid)
        wanted: frozenset[ua.NodeId] | None = None
        if not desc.ReferenceTypeId.is_null():
            if desc.ReferenceTypeId not in self._aspace:
                return int(S.BadReferenceTypeIdInvalid)
            wanted = (
                self.subtypes(desc.ReferenceTypeId)
                if desc.IncludeSubtypes
                else frozenset((desc.ReferenceTypeId,))
            )
        mask = desc.NodeClassMask
        out = []
        for ref in self._aspace[desc.NodeId].references:
            if direction == ua.BrowseDirection.Forward and not ref.IsForward:
                continue
            if direction == ua.BrowseDirection.Inverse and ref.IsForward:
                continue
            if wanted is not None and ref.ReferenceTypeId not in wanted:
                continue
            if mask and not (mask & ref.NodeClass):
                continue
            out.append(ref)
        return out

    def page(
        self,
        refs: list[ua.ReferenceDescription],
        max_references: int,
        points: OrderedDict[bytes, _Pending],
    ) -> ua.BrowseResult:
        """The first ``max_references`` of ``refs``; the rest behind a new continuation
        point (or Bad_NoContinuationPoints when the session holds its maximum)."""
        res = ua.BrowseResult()
        if len(refs) <= max_references:
            res.References = refs
            return res
        if len(points) >= MAX_BROWSE_CONTINUATION_POINTS:
            res.StatusCode = ua.StatusCode(S.BadNoContinuationPoints)
            return res
        point = os.urandom(16)
        points[point] = _Pending(refs[max_references:], max_references)
        res.References = refs[:max_references]
        res.ContinuationPoint = point
        return res

    def next(
        self, point: bytes | None, release: bool, points: OrderedDict[bytes, _Pending]
    ) -> ua.BrowseResult:
        res = ua.BrowseResult()
        pending = points.pop(point, None) if point else None
        if pending is None:
            res.StatusCode = ua.StatusCode(S.BadContinuationPointInvalid)
            return res
        if release:
            return res
        return self.page(pending.references, pending.max_references, points)


def references_asked(requested: int) -> int:
    """References per node in one answer: what the client asked, within the server's cap
    (0: the client sets no limit, Part 4 §5.8.2)."""
    if requested <= 0:
        return MAX_REFERENCES_PER_NODE
    return min(requested, MAX_REFERENCES_PER_NODE)


class Answer:
    """A Browse or BrowseNext answer encoded as it is made: a result's bytes as soon as it is
    known, between slices. Bytes are not tracked by the garbage collector: a 10,000-node
    answer kept as objects until the end (descriptions, results) was promoted into the
    oldest generation and set off full collections of 200-700 ms in the server's process,
    during which no client got anything (measured, issue 31). The bytes are asyncua's
    encoding of ``response`` with the results as its ``Results`` (a BrowseResponse's own, a
    BrowseNextResponse's ``Parameters.Results``: either encodes as TypeId, ResponseHeader,
    Results, DiagnosticInfos)."""

    def __init__(self, response: Any) -> None:
        holder = getattr(response, "Parameters", response)
        holder.Results = []
        empty = struct_to_binary(response)
        self._head = nodeid_to_binary(response.TypeId) + struct_to_binary(response.ResponseHeader)
        self._tail = empty[len(self._head) + 4 :]  # after the empty Results' length
        self._parts: list[bytes] = []

    def add(self, result: ua.BrowseResult) -> None:
        self._parts.append(struct_to_binary(result))

    def bytes(self) -> bytes:
        count = Primitives.Int32.pack(len(self._parts))
        return b"".join((self._head, count, *self._parts, self._tail))


async def encode_response(response: Any, results: list[Any], slices: Slices) -> bytes:
    """``struct_to_binary(response)`` with ``results`` as its results, a result at a time
    between slices."""
    answer = Answer(response)
    for r in results:
        answer.add(r)
        await slices.tick()
    return answer.bytes()


def _failed(status: int) -> ua.BrowseResult:
    res = ua.BrowseResult()
    res.StatusCode = ua.StatusCode(status)
    return res


async def browse(
    browser: Browser,
    points: OrderedDict[bytes, _Pending],
    body: Buffer,
    header: ua.RequestHeader,
) -> bytes:
    """A Browse request's answer (its encoded body; ``too_many`` was asked before): the nodes
    decoded, browsed and their results encoded one at a time, between slices."""
    slices = Slices()
    view = struct_from_binary(ua.ViewDescription, body)
    max_refs = references_asked(Primitives.UInt32.unpack(body))
    n = max(Primitives.Int32.unpack(body), 0)
    response = ua.BrowseResponse()
    response.ResponseHeader.RequestHandle = header.RequestHandle
    if not view.ViewId.is_null():
        # No views here (Part 4 §5.8.2): the whole request is refused.
        response.ResponseHeader.ServiceResult = ua.StatusCode(S.BadViewIdUnknown)
        return Answer(response).bytes()
    answer = Answer(response)
    for _ in range(n):
        found = browser.references(struct_from_binary(ua.BrowseDescription, body))
        if isinstance(found, int):
            answer.add(_failed(found))
        else:
            answer.add(browser.page(found, max_refs, points))
        await slices.tick()
    return answer.bytes()


async def browse_next(
    browser: Browser,
    points: OrderedDict[bytes, _Pending],
    body: Buffer,
    header: ua.RequestHeader,
) -> bytes:
    """A BrowseNext request's answer (its encoded body)."""
    slices = Slices()
    params = struct_from_binary(ua.BrowseNextParameters, body)
    response = ua.BrowseNextResponse()
    response.ResponseHeader.RequestHandle = header.RequestHandle
    results = []
    for point in params.ContinuationPoints or ():
        results.append(browser.next(point, params.ReleaseContinuationPoints, points))
        await slices.tick()
    return await encode_response(response, results, slices)
