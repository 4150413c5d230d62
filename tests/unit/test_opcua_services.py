"""The OPC UA service layer's parts (supervisor/publish/opcua/services.py, issue 31 finding 4):
each shortcut is the plain path's answer — the operation count read from a request's length
prefix is the decoded array's length for every limited request kind, the answer encoded a
result at a time is asyncua's encoding, the browse is asyncua's browse on every node of the
standard address space — plus continuation points, and the refused-certificate log's
window (security.py)."""

from __future__ import annotations

import dataclasses
import typing
from collections import OrderedDict
from collections.abc import AsyncIterator

import pytest
import pytest_asyncio
from asyncua import Server, ua
from asyncua.common.utils import Buffer
from asyncua.ua.ua_binary import get_safe_type_hints, struct_from_binary, struct_to_binary

from supervisor.publish.opcua import services
from supervisor.publish.opcua.security import RefusalLog

S = ua.StatusCodes
BD = ua.BrowseDirection


# --- operation counts -----------------------------------------------------------------------
def _item(t: object) -> object:
    """One operation of a request's array of ``t``."""
    if t is ua.ExtensionObject:
        return ua.UpdateDataDetails(NodeId=ua.NodeId("x", 2))
    if t is ua.ByteString:
        return b"\x01\x02"
    if isinstance(t, type) and issubclass(t, int):
        return 7
    assert isinstance(t, type)
    return t()


def _request(params: type, field: str, n: int | None) -> object:
    """``params`` with ``n`` operations in ``field`` (None: a null array) and its other fields
    not at their defaults where they change the encoding's length."""
    obj = params()
    hints = get_safe_type_hints(params, {"ua": ua})
    (element,) = typing.get_args(hints[field])
    setattr(obj, field, None if n is None else [_item(element) for _ in range(n)])
    if isinstance(obj, ua.BrowseParameters):
        obj.View.ViewId = ua.NodeId("a view with a long string id", 3)
    if isinstance(obj, ua.HistoryReadParameters):
        obj.HistoryReadDetails = ua.ReadRawModifiedDetails(NumValuesPerNode=5)
    return obj


@pytest.mark.parametrize("n", [0, 1, 5, None])
@pytest.mark.parametrize(
    ("params", "field"),
    [(p, f) for _, p, f in services.BOUNDED.values()],
    ids=[p.__name__ for _, p, _ in services.BOUNDED.values()],
)
def test_the_operation_count_is_the_decoded_arrays_length_for_every_limited_request(
    params: type, field: str, n: int | None
) -> None:
    body = Buffer(struct_to_binary(_request(params, field, n)))
    decoded = getattr(struct_from_binary(params, body.copy()), field)
    assert services.operation_count(params, field, body) == (len(decoded) if decoded else 0) or (
        n is None and services.operation_count(params, field, body) == -1
    )
    assert len(body) == len(struct_to_binary(_request(params, field, n)))  # not consumed


def test_every_limit_is_a_property_of_operation_limits_and_every_request_kind_is_bounded() -> None:
    names = {f"Server_ServerCapabilities_OperationLimits_{lim.name}" for lim in services.LIMITS}
    assert all(hasattr(ua.ObjectIds, n) for n in names)
    bounded = {p for _, p, _ in services.BOUNDED.values()}
    many = {
        ua.ReadParameters,
        ua.WriteParameters,
        ua.BrowseParameters,
        ua.BrowseNextParameters,
        ua.CallParameters,
        ua.TranslateBrowsePathsToNodeIdsParameters,
        ua.HistoryReadParameters,
        ua.CreateMonitoredItemsParameters,
        ua.DeleteMonitoredItemsParameters,
    }
    assert many <= bounded


def test_a_request_past_its_limit_is_refused_with_the_limit_named() -> None:
    limit = next(lim for lim in services.LIMITS if lim.name == "MaxNodesPerRead")
    typeid = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
    at = Buffer(struct_to_binary(_request(ua.ReadParameters, "NodesToRead", limit.value)))
    past = Buffer(struct_to_binary(_request(ua.ReadParameters, "NodesToRead", limit.value + 1)))
    assert services.too_many(typeid, at) is None
    assert services.too_many(typeid, past) == (
        f"Read of {limit.value + 1} operations: the server's MaxNodesPerRead is {limit.value}"
    )
    publish = ua.NodeId(ua.ObjectIds.PublishRequest_Encoding_DefaultBinary)
    assert services.too_many(publish, past) is None  # not an operation-bounded request


# --- encoding in slices ---------------------------------------------------------------------
def _ref(i: int, forward: bool = True) -> ua.ReferenceDescription:
    ref = ua.ReferenceDescription()
    ref.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
    ref.IsForward = forward
    ref.NodeId = ua.ExpandedNodeId(f"node.{i}", 1)
    ref.BrowseName = ua.QualifiedName(f"Node{i}", 1)
    ref.DisplayName = ua.LocalizedText(f"Node {i}")
    ref.NodeClass = ua.NodeClass.Variable
    ref.TypeDefinition = ua.ExpandedNodeId(ua.ObjectIds.AnalogItemType)
    return ref


def _results() -> list[ua.BrowseResult]:
    full = ua.BrowseResult(References=[_ref(i, i % 2 == 0) for i in range(7)])
    paged = ua.BrowseResult(References=[_ref(9)], ContinuationPoint=b"\x00" * 16)
    bad = ua.BrowseResult(StatusCode=ua.StatusCode(S.BadNodeIdUnknown))
    return [full, paged, bad, ua.BrowseResult()]


@pytest.mark.parametrize("kind", [ua.BrowseResponse, ua.BrowseNextResponse])
@pytest.mark.parametrize("count", [0, 1, 4, 40])
async def test_an_answer_encoded_a_result_at_a_time_is_asyncuas_encoding(
    kind: type, count: int
) -> None:
    results = (_results() * 10)[:count]
    response = kind()
    response.ResponseHeader.RequestHandle = 42
    response.ResponseHeader.ServiceResult = ua.StatusCode(S.Good)
    sliced = await services.encode_response(response, results, services.Slices(0.0))
    plain = kind()
    plain.ResponseHeader = response.ResponseHeader
    getattr(plain, "Parameters", plain).Results = results
    assert sliced == struct_to_binary(plain)


# --- browsing: asyncua's answer on every node -------------------------------------------------
@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def standard_space() -> AsyncIterator[Server]:
    server = Server()
    await server.init()
    yield server


DESCRIPTIONS: typing.Final = [
    (direction, reftype, subtypes, mask)
    for direction in (BD.Forward, BD.Inverse, BD.Both)
    for reftype, subtypes in (
        (ua.ObjectIds.Null, False),
        (ua.ObjectIds.References, True),
        (ua.ObjectIds.HierarchicalReferences, True),
        (ua.ObjectIds.HierarchicalReferences, False),
        (ua.ObjectIds.HasComponent, True),
        (ua.ObjectIds.HasTypeDefinition, False),
    )
    for mask in (0, int(ua.NodeClass.Variable), int(ua.NodeClass.Object | ua.NodeClass.Method))
]


@pytest.mark.asyncio(loop_scope="module")
async def test_the_browser_finds_asyncuas_references_on_every_node(
    standard_space: Server,
) -> None:
    iserver = standard_space.iserver
    browser = services.Browser(iserver.aspace)
    nodes = list(iserver.aspace.keys())
    assert len(nodes) > 5000
    for i, nid in enumerate(nodes):
        # every node with two descriptions, each description on a seventh of the nodes
        for direction, reftype, subtypes, mask in (
            DESCRIPTIONS[i % len(DESCRIPTIONS)],
            DESCRIPTIONS[(i * 7 + 3) % len(DESCRIPTIONS)],
        ):
            desc = ua.BrowseDescription(
                NodeId=nid,
                BrowseDirection=direction,
                ReferenceTypeId=ua.NodeId(reftype),
                IncludeSubtypes=subtypes,
                NodeClassMask=mask,
            )
            (plain,) = iserver.view_service.browse(ua.BrowseParameters(NodesToBrowse=[desc]))
            assert browser.references(desc) == plain.References, (nid, desc)


@pytest.mark.asyncio(loop_scope="module")
async def test_a_browse_request_is_answered_as_asyncua_answers_it(
    standard_space: Server,
) -> None:
    """The bytes of a whole Browse answer (descriptions decoded, browsed and encoded one at
    a time) decode to asyncua's results for the same request."""
    iserver = standard_space.iserver
    nodes = list(iserver.aspace.keys())[::37]
    params = ua.BrowseParameters()
    params.NodesToBrowse = [
        ua.BrowseDescription(
            NodeId=nid,
            BrowseDirection=d,
            ReferenceTypeId=ua.NodeId(rt),
            IncludeSubtypes=sub,
            NodeClassMask=mask,
            ResultMask=63,
        )
        for i, nid in enumerate(nodes)
        for d, rt, sub, mask in (DESCRIPTIONS[i % len(DESCRIPTIONS)],)
    ]
    header = ua.RequestHeader(RequestHandle=9)
    data = await services.browse(
        services.Browser(iserver.aspace), OrderedDict(), Buffer(struct_to_binary(params)), header
    )
    answer = struct_from_binary(ua.BrowseResponse, Buffer(data))
    assert answer.ResponseHeader.RequestHandle == 9
    assert answer.Results == iserver.view_service.browse(params)
    assert data == struct_to_binary(answer)


@pytest.mark.asyncio(loop_scope="module")
async def test_an_unknown_node_reference_type_or_direction_is_refused_per_node(
    standard_space: Server,
) -> None:
    browser = services.Browser(standard_space.iserver.aspace)
    objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
    assert browser.references(ua.BrowseDescription(NodeId=ua.NodeId("nope", 1))) == (
        S.BadNodeIdUnknown
    )
    unknown_type = ua.BrowseDescription(NodeId=objects, ReferenceTypeId=ua.NodeId("nope", 1))
    assert browser.references(unknown_type) == S.BadReferenceTypeIdInvalid
    wrong_way = ua.BrowseDescription(NodeId=objects)
    wrong_way.BrowseDirection = 7  # type: ignore[assignment]
    assert browser.references(wrong_way) == S.BadBrowseDirectionInvalid


# --- continuation points --------------------------------------------------------------------
def test_references_past_the_maximum_come_back_page_by_page_in_order() -> None:
    browser = services.Browser({})
    points: OrderedDict[bytes, typing.Any] = OrderedDict()
    refs = [_ref(i) for i in range(10)]
    first = browser.page(refs, 4, points)
    got = list(first.References)
    point = first.ContinuationPoint
    pages = [len(first.References)]
    while point:
        nxt = browser.next(point, False, points)
        assert nxt.StatusCode.is_good()
        got += nxt.References
        pages.append(len(nxt.References))
        point = nxt.ContinuationPoint
    assert got == refs
    assert pages == [4, 4, 2]
    assert not points  # each point used is gone


def test_a_released_or_unknown_continuation_point_and_the_sessions_maximum() -> None:
    browser = services.Browser({})
    points: OrderedDict[bytes, typing.Any] = OrderedDict()
    refs = [_ref(i) for i in range(3)]
    held = [browser.page(refs, 1, points) for _ in range(services.MAX_BROWSE_CONTINUATION_POINTS)]
    assert all(r.ContinuationPoint for r in held)
    full = browser.page(refs, 1, points)
    assert full.StatusCode.value == S.BadNoContinuationPoints and not full.References
    assert browser.page(refs, 3, points).StatusCode.is_good()  # no point needed: served
    released = browser.next(held[0].ContinuationPoint, True, points)
    assert released.StatusCode.is_good() and not released.References
    stale = browser.next(held[0].ContinuationPoint, False, points)
    assert stale.StatusCode.value == S.BadContinuationPointInvalid
    assert browser.next(b"never given", False, points).StatusCode.value == (
        S.BadContinuationPointInvalid
    )
    assert browser.page(refs, 1, points).ContinuationPoint  # a released one is free again


def test_a_new_session_on_the_connection_has_no_continuation_points() -> None:
    points = services.ContinuationPoints()
    first, second = object(), object()
    points.of(first)[b"p"] = typing.cast(typing.Any, None)
    assert b"p" in points.of(first)
    assert not points.of(second)


@pytest.mark.parametrize(("requested", "answered"), [(0, 1000), (1, 1), (999, 999), (10**6, 1000)])
def test_references_per_node_are_what_the_client_asks_within_the_servers_cap(
    requested: int, answered: int
) -> None:
    assert services.MAX_REFERENCES_PER_NODE == 1000
    assert services.references_asked(requested) == answered


# --- the refused certificate's log ----------------------------------------------------------
def test_a_refused_certificate_is_logged_once_a_window_then_with_the_count_it_kept_quiet() -> None:
    now = [0.0]
    log = RefusalLog(lambda: now[0], window_s=60.0)
    said = []
    for t in (0.0, 1.0, 2.0, 30.0, 61.0, 62.0, 200.0):
        now[0] = t
        said.append(log.should_log("abc"))
    assert said == [0, None, None, None, 3, None, 1]
    assert log.should_log("another certificate") == 0


def test_the_refusal_log_remembers_a_bounded_number_of_certificates() -> None:
    log = RefusalLog(lambda: 0.0)
    for i in range(10_000):
        log.should_log(f"{i:x}")
    assert len(log._seen) <= 256


_ = dataclasses  # the requests are dataclasses (``operation_count`` walks their fields)
