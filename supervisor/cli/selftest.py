"""``supervisor opcua selftest URL``: what an integrator's client expects of the server,
checked from the client's side (issue 31).

Each check is one request (or a few) a SCADA integrator's client makes, and what OPC UA
Parts 4, 8, 9 and 11 say the answer must be. A check prints ``PASS``, ``FAIL`` (with what
was received and what was expected) or ``SKIP`` (with why: an anonymous session cannot
call methods, a server without the node). Exit 0 when nothing failed, 1 when a check
failed, 2 for a usage error or a server that cannot be reached.

The checks never change the bench: the method calls are made with arguments the server
must refuse before it looks at them (a method on the wrong object, an event the condition
never sent), so even a server that gets them wrong does nothing but answer. They need a
user (``--user``) because an anonymous session may not call methods at all.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

if TYPE_CHECKING:
    from asyncua import Client

CONNECT_TIMEOUT_S: Final = 10.0
BASE_OBJECT_TYPE: Final = 58  # ns=0;i=58
ACKNOWLEDGE: Final = 9111  # AcknowledgeableConditionType.Acknowledge
HUGE: Final = 1e300  # an EURange beyond this is "no range" dressed as one


@dataclass(frozen=True)
class Outcome:
    name: str
    verdict: str  # "PASS" | "FAIL" | "SKIP"
    detail: str = ""

    def line(self) -> str:
        return f"{self.verdict} {self.name}" + (f": {self.detail}" if self.detail else "")


class Skip(Exception):
    """The check cannot be made against this server or session (the reason)."""


class Fail(Exception):
    """The check failed (what was received, what was expected)."""


@dataclass
class Target:
    client: Client
    ns: int
    channels: list[str]
    user: bool


Check = Callable[[Target], Awaitable[str]]


def _code(exc: BaseException) -> str:
    from asyncua import ua

    if isinstance(exc, ua.UaStatusCodeError):
        return str(ua.StatusCode(exc.code).name)
    return type(exc).__name__


def _name(code: Any) -> str:
    return str(code.name)


# --- the Server object (Part 5) -------------------------------------------------------------
async def build_info(t: Target) -> str:
    from asyncua import ua

    info = await t.client.get_node(ua.ObjectIds.Server_ServerStatus_BuildInfo).read_value()
    if not info.ProductName or "FreeOpcUa" in info.ProductName:
        raise Fail(f"ProductName {info.ProductName!r}: expected the product's own name")
    if not info.SoftwareVersion or "pre" in info.SoftwareVersion:
        raise Fail(f"SoftwareVersion {info.SoftwareVersion!r}: expected the product's version")
    return f"{info.ProductName} {info.SoftwareVersion}"


async def capabilities(t: Target) -> str:
    from asyncua import ua

    names = (
        "MaxBrowseContinuationPoints",
        "ServerProfileArray",
        "LocaleIdArray",
        "MinSupportedSampleRate",
    )
    empty = []
    for name in names:
        ident = getattr(ua.ObjectIds, f"Server_ServerCapabilities_{name}")
        dv = await t.client.get_node(ident).read_data_value(raise_on_bad_status=False)
        if not dv.StatusCode.is_good() or dv.Value is None or dv.Value.Value in (None, []):
            empty.append(name)
    if empty:
        raise Fail(f"{', '.join(empty)} read null: expected the server's figures")
    return ""


async def aggregates(t: Target) -> str:
    from asyncua import ua

    folder = t.client.get_node(ua.ObjectIds.Server_ServerCapabilities_AggregateFunctions)
    names = [str((await n.read_browse_name()).Name) for n in await folder.get_children()]
    if not names:
        raise Fail("AggregateFunctions is empty: expected the aggregates HistoryRead serves")
    return ", ".join(sorted(names))


# --- services (Part 4) ----------------------------------------------------------------------
async def read_limit(t: Target) -> str:
    from asyncua import ua

    limit_node = t.client.get_node(
        ua.ObjectIds.Server_ServerCapabilities_OperationLimits_MaxNodesPerRead
    )
    limit = await limit_node.read_value()
    if not limit:
        raise Skip("MaxNodesPerRead is 0 (no limit advertised)")
    params = ua.ReadParameters()
    for _ in range(limit + 1):
        rv = ua.ReadValueId()
        rv.NodeId = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)
        rv.AttributeId = ua.AttributeIds.Value
        params.NodesToRead.append(rv)
    try:
        await t.client.uaclient.read(params)
    except ua.UaStatusCodeError as exc:
        if _code(exc) == "BadTooManyOperations":
            return f"{limit + 1} reads refused (MaxNodesPerRead {limit})"
        raise Fail(f"{_code(exc)} for {limit + 1} reads: expected BadTooManyOperations") from None
    raise Fail(
        f"{limit + 1} reads served past MaxNodesPerRead {limit}: expected BadTooManyOperations"
    )


async def browse_paging(t: Target) -> str:
    from asyncua import ua

    desc = ua.BrowseDescription()
    desc.NodeId = ua.NodeId(ua.ObjectIds.Server)
    desc.BrowseDirection = ua.BrowseDirection.Both
    desc.ReferenceTypeId = ua.NodeId(ua.ObjectIds.References)
    desc.IncludeSubtypes = True
    desc.ResultMask = ua.BrowseResultMask.All
    params = ua.BrowseParameters()
    params.NodesToBrowse = [desc]
    params.RequestedMaxReferencesPerNode = 1
    [first] = await t.client.uaclient.browse(params)
    if len(first.References) > 1:
        raise Fail(f"{len(first.References)} references for requestedMaxReferencesPerNode 1")
    if not first.ContinuationPoint:
        raise Fail("no continuation point though the Server object has more references")
    nxt = ua.BrowseNextParameters()
    nxt.ContinuationPoints = [first.ContinuationPoint]
    nxt.ReleaseContinuationPoints = False
    [second] = await t.client.uaclient.browse_next(nxt)
    if not second.StatusCode.is_good() or not second.References:
        raise Fail(f"BrowseNext answered {_name(second.StatusCode)} with no reference")
    if second.ContinuationPoint:  # leave nothing held on the server
        nxt.ContinuationPoints = [second.ContinuationPoint]
        nxt.ReleaseContinuationPoints = True
        with contextlib.suppress(Exception):
            await t.client.uaclient.browse_next(nxt)
    return ""


async def timestamps(t: Target) -> str:
    from asyncua import ua

    node = ua.NodeId("scan.count", t.ns)
    wanted = {
        ua.TimestampsToReturn.Source: (True, False),
        ua.TimestampsToReturn.Server: (False, True),
        ua.TimestampsToReturn.Neither: (False, False),
        ua.TimestampsToReturn.Both: (True, True),
    }
    wrong = []
    for which, (source, server) in wanted.items():
        params = ua.ReadParameters()
        rv = ua.ReadValueId()
        rv.NodeId = node
        rv.AttributeId = ua.AttributeIds.Value
        params.NodesToRead = [rv]
        params.TimestampsToReturn = which
        [dv] = await t.client.uaclient.read(params)
        if not dv.StatusCode.is_good():
            raise Skip(f"scan.count reads {_name(dv.StatusCode)}")
        got = (dv.SourceTimestamp is not None, dv.ServerTimestamp is not None)
        if got != (source, server):
            wrong.append(f"{which.name}: source {got[0]}, server {got[1]}")
    if wrong:
        raise Fail("; ".join(wrong))
    return ""


async def history_unknown(t: Target) -> str:
    from asyncua import ua

    details = ua.ReadRawModifiedDetails()
    details.IsReadModified = False
    details.NumValuesPerNode = 1
    details.ReturnBounds = False
    params = ua.HistoryReadParameters()
    params.HistoryReadDetails = details
    params.TimestampsToReturn = ua.TimestampsToReturn.Both
    params.ReleaseContinuationPoints = False  # asyncua's default is True: a release only
    item = ua.HistoryReadValueId()
    item.NodeId = ua.NodeId("no.such.tag.selftest", t.ns)
    params.NodesToRead = [item]
    [result] = await t.client.uaclient.history_read(params)
    if _name(result.StatusCode) != "BadNodeIdUnknown":
        raise Fail(f"{_name(result.StatusCode)}: expected BadNodeIdUnknown")
    return ""


async def percent_deadband(t: Target) -> str:
    from asyncua import ua

    sub = await t.client.create_subscription(1000, None)
    try:
        params = ua.MonitoredItemCreateRequest()
        params.ItemToMonitor = ua.ReadValueId()
        params.ItemToMonitor.NodeId = ua.NodeId("scan.count", t.ns)
        params.ItemToMonitor.AttributeId = ua.AttributeIds.Value
        params.MonitoringMode = ua.MonitoringMode.Reporting
        mparams = ua.MonitoringParameters()
        mparams.ClientHandle = 1
        mparams.SamplingInterval = 100
        mparams.QueueSize = 1
        mparams.DiscardOldest = True
        dfilter = ua.DataChangeFilter()
        dfilter.Trigger = ua.DataChangeTrigger.StatusValue
        dfilter.DeadbandType = ua.DeadbandType.Percent
        dfilter.DeadbandValue = 10.0
        mparams.Filter = dfilter
        params.RequestedParameters = mparams
        req = ua.CreateMonitoredItemsParameters()
        req.SubscriptionId = sub.subscription_id
        req.TimestampsToReturn = ua.TimestampsToReturn.Both
        req.ItemsToCreate = [params]
        [result] = await t.client.uaclient.create_monitored_items(req)
    finally:
        with contextlib.suppress(Exception):
            await sub.delete()
    code = _name(result.StatusCode)
    if code in (
        "BadFilterNotAllowed",
        "BadMonitoredItemFilterUnsupported",
        "BadDeadbandFilterInvalid",
    ):
        return f"a percent deadband on a counter: {code}"
    raise Fail(f"a percent deadband on a counter (no EURange): {code}, expected a refusal")


# --- the address space (Parts 3, 8; OPC 40001-1) --------------------------------------------
async def eu_ranges(t: Target) -> str:
    from asyncua import ua

    channel = t.client.get_node(ua.NodeId(f"/Bench/Channels/{t.channels[0]}", t.ns))
    bad = []
    seen = 0
    for var in await channel.get_children(nodeclassmask=ua.NodeClass.Variable):
        for prop in await var.get_properties():
            if (await prop.read_browse_name()).Name != "EURange":
                continue
            seen += 1
            rng = await prop.read_value()
            if (
                not (math.isfinite(rng.Low) and math.isfinite(rng.High))
                or max(abs(rng.Low), abs(rng.High)) > HUGE
            ):
                bad.append(str((await var.read_browse_name()).Name))
    if not seen:
        raise Skip(f"no EURange under {t.channels[0]}")
    if bad:
        raise Fail(f"EURange without a real range: {', '.join(bad)}")
    return f"{seen} EURanges under {t.channels[0]}"


async def channel_type(t: Target) -> str:
    from asyncua import ua

    channel = t.client.get_node(ua.NodeId(f"/Bench/Channels/{t.channels[0]}", t.ns))
    type_id = await channel.read_type_definition()
    if type_id is None or (type_id.NamespaceIndex == 0 and type_id.Identifier == BASE_OBJECT_TYPE):
        raise Fail(f"{t.channels[0]} is a BaseObjectType: expected an instance of a channel type")
    name = (await t.client.get_node(type_id).read_browse_name()).Name
    return f"{t.channels[0]} is a {name}"


async def identification(t: Target) -> str:
    from asyncua import ua

    async def find(node: Any, depth: int) -> Any:
        for child in await node.get_children(refs=ua.ObjectIds.HierarchicalReferences):
            if (await child.read_browse_name()).Name == "Identification":
                return child
            if depth > 1:
                found = await find(child, depth - 1)
                if found is not None:
                    return found
        return None

    ident = await find(t.client.nodes.objects, 3)
    if ident is None:
        raise Fail("no Identification (OPC 40001-1 MachineIdentificationType) under Objects")
    values = {}
    for prop in await ident.get_children():
        name = str((await prop.read_browse_name()).Name)
        with contextlib.suppress(Exception):
            values[name] = await prop.read_value()
    missing = [k for k in ("Manufacturer", "SerialNumber", "SoftwareRevision") if not values.get(k)]
    if missing:
        raise Fail(f"Identification without {', '.join(missing)}")
    return f"{_text(values.get('Manufacturer'))} / {_text(values.get('SerialNumber'))}"


def _text(value: Any) -> str:
    """A value as a person reads it (a LocalizedText's text)."""
    return str(getattr(value, "Text", value))


# --- methods and conditions (Parts 4, 9): with a user only ------------------------------------
async def wrong_object(t: Target) -> str:
    from asyncua import ua

    if not t.user:
        raise Skip("an anonymous session may not call methods: give --user")
    if len(t.channels) < 2:
        raise Skip("one channel: no other object to call its method on")
    a, b = t.channels[:2]
    req = ua.CallMethodRequest()
    req.ObjectId = ua.NodeId(f"/Bench/Channels/{b}", t.ns)
    req.MethodId = ua.NodeId(f"/Bench/Channels/{a}/SetManualCurrent", t.ns)
    # A text where a current is expected: a server that does not check the object first
    # refuses the argument and does nothing either.
    req.InputArguments = [ua.Variant("not a current", ua.VariantType.String)]
    [result] = await t.client.uaclient.call([req])
    code = _name(result.StatusCode)
    if code != "BadMethodInvalid":
        raise Fail(f"{a}'s SetManualCurrent on {b}'s object: {code}, expected BadMethodInvalid")
    return ""


async def acknowledge_unknown(t: Target) -> str:
    from asyncua import ua

    if not t.user:
        raise Skip("an anonymous session may not acknowledge: give --user")
    alarms = t.client.get_node(ua.NodeId("/Bench/Alarms", t.ns))
    children = await alarms.get_children()
    if not children:
        raise Skip("no alarm condition")
    codes = []
    for event_id in (
        ua.Variant(os.urandom(16), ua.VariantType.ByteString),
        ua.Variant("not an event id", ua.VariantType.String),
    ):
        req = ua.CallMethodRequest()
        req.ObjectId = children[0].nodeid
        req.MethodId = ua.NodeId(ACKNOWLEDGE)
        req.InputArguments = [event_id, ua.Variant(ua.LocalizedText("selftest"))]
        [result] = await t.client.uaclient.call([req])
        codes.append(_name(result.StatusCode))
    if codes[0] != "BadEventIdUnknown":
        raise Fail(f"an EventId never sent: {codes[0]}, expected BadEventIdUnknown")
    if codes[1] not in ("BadInvalidArgument", "BadTypeMismatch"):
        raise Fail(f"a String for the EventId: {codes[1]}, expected BadInvalidArgument")
    return ""


CHECKS: Final[tuple[tuple[str, Check], ...]] = (
    ("server.build-info", build_info),
    ("server.capabilities", capabilities),
    ("server.aggregate-functions", aggregates),
    ("services.read-limit", read_limit),
    ("services.browse-max-references", browse_paging),
    ("services.timestamps-to-return", timestamps),
    ("services.history-unknown-node", history_unknown),
    ("subscriptions.percent-deadband-refused", percent_deadband),
    ("space.eu-range", eu_ranges),
    ("space.channel-type", channel_type),
    ("space.identification", identification),
    ("methods.wrong-object", wrong_object),
    ("conditions.acknowledge-unknown-event", acknowledge_unknown),
)


async def run_checks(client: Client, *, user: bool) -> list[Outcome]:
    """Every check against a connected client, in order; one's failure never stops the next."""
    from asyncua import ua

    from supervisor.publish.opcua.layout import URN_PREFIX

    namespaces = await client.get_namespace_array()
    ns = next((i for i, u in enumerate(namespaces) if u.startswith(URN_PREFIX)), None)
    if ns is None:
        return [Outcome("server.namespace", "FAIL", f"no {URN_PREFIX}… namespace")]
    folder = client.get_node(ua.NodeId("/Bench/Channels", ns))
    names = [str((await n.read_browse_name()).Name) for n in await folder.get_children()]
    target = Target(client, ns, names, user)
    out = []
    for name, check in CHECKS:
        try:
            out.append(Outcome(name, "PASS", await check(target)))
        except Skip as exc:
            out.append(Outcome(name, "SKIP", str(exc)))
        except Fail as exc:
            out.append(Outcome(name, "FAIL", str(exc)))
        except ua.UaStatusCodeError as exc:
            out.append(Outcome(name, "FAIL", f"the server answered {_code(exc)}"))
    return out


async def selftest(url: str, user: str | None, password: str | None) -> list[Outcome]:
    """Connect (security None, anonymous or ``user``), run every check, disconnect."""
    from asyncua import Client

    client = Client(url, timeout=CONNECT_TIMEOUT_S)
    if user:
        client.set_user(user)
        client.set_password(password or "")
    await client.connect()
    try:
        return await run_checks(client, user=bool(user))
    finally:
        with contextlib.suppress(Exception):
            await client.disconnect()
