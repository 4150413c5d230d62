"""The monitored items of one subscription (publish/opcua/monitoring.py) on an address space
of three variables, without a server or a client: what is created, refused, modified,
disabled and deleted, and what each item queues (Part 4 §5.12, §7.22.2, §7.40)."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import ua
from asyncua.server.address_space import AddressSpace, AttributeValue, NodeData

from supervisor.publish.opcua.monitoring import BenchMonitoredItems

S = ua.StatusCodes
T = ua.DataChangeTrigger
TTR = ua.TimestampsToReturn
VT = ua.VariantType
T0 = datetime(2026, 12, 5, 14, 0, tzinfo=UTC)
FRESH = T0 + timedelta(minutes=5)
CURRENT = ua.NodeId("ch0.current", 2)  # Double, EURange −0.4…0.4
COUNT = ua.NodeId("ch0.count", 2)  # Int64, no EURange
LABEL = ua.NodeId("ch0.label", 2)  # String


@dataclass
class Subscription:
    """What ``BenchMonitoredItems`` needs of asyncua's InternalSubscription: what it queues."""

    queued: list[tuple[int, ua.MonitoredItemNotification]] = field(default_factory=list)
    max_queue_size: int = 10_000

    class data:  # asyncua's attribute name
        SubscriptionId = 1
        RevisedPublishingInterval = 50.0

    async def enqueue_datachange_event(
        self, mid: int, event: ua.MonitoredItemNotification, size: int
    ) -> None:
        self.queued.append((mid, event))


def variable(aspace: AddressSpace, nid: ua.NodeId, dtype: int, value: ua.Variant) -> None:
    node = NodeData(nid)
    node.attributes[ua.AttributeIds.Value] = AttributeValue(
        ua.DataValue(value, SourceTimestamp=T0, ServerTimestamp=T0)
    )
    node.attributes[ua.AttributeIds.DataType] = AttributeValue(
        ua.DataValue(ua.Variant(ua.NodeId(dtype), VT.NodeId))
    )
    aspace[nid] = node


def space() -> AddressSpace:
    aspace = AddressSpace()
    variable(aspace, CURRENT, ua.ObjectIds.Double, ua.Variant(0.0, VT.Double))
    variable(aspace, COUNT, ua.ObjectIds.Int64, ua.Variant(0, VT.Int64))
    variable(aspace, LABEL, ua.ObjectIds.String, ua.Variant("a", VT.String))
    rid = ua.NodeId("ch0.current.EURange", 2)
    prop = NodeData(rid)
    prop.attributes[ua.AttributeIds.Value] = AttributeValue(
        ua.DataValue(ua.Variant(ua.Range(-0.4, 0.4), VT.ExtensionObject))
    )
    aspace[rid] = prop
    ref = ua.ReferenceDescription()
    ref.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasProperty)
    ref.IsForward = True
    ref.NodeId = rid
    ref.BrowseName = ua.QualifiedName("EURange", 0)
    aspace[CURRENT].references.append(ref)
    return aspace


def stamp(nid: ua.NodeId, attribute: int, dv: ua.DataValue) -> ua.DataValue:
    """A Freshness that last heard from the scan at FRESH."""
    return ua.DataValue(dv.Value, dv.StatusCode, dv.SourceTimestamp, FRESH)


@dataclass
class Items:
    aspace: AddressSpace
    sub: Subscription
    svc: BenchMonitoredItems

    async def create(
        self, nid: ua.NodeId, flt: object = None, ttr: TTR = TTR.Both, handle: int = 1
    ) -> ua.MonitoredItemCreateResult:
        req = ua.MonitoredItemCreateRequest()
        req.ItemToMonitor = ua.ReadValueId(nid, ua.AttributeIds.Value)
        req.MonitoringMode = ua.MonitoringMode.Reporting
        req.RequestedParameters = ua.MonitoringParameters(
            ClientHandle=handle, SamplingInterval=0, Filter=flt, QueueSize=100
        )
        params = ua.CreateMonitoredItemsParameters(1, ttr, [req])
        (result,) = await self.svc.create_monitored_items(params)
        return result

    async def sample(self, nid: ua.NodeId, value: object, vt: VT) -> None:
        """The server writes a new value: asyncua calls each item's callback."""
        dv = ua.DataValue(ua.Variant(value, vt), SourceTimestamp=T0, ServerTimestamp=T0)
        attribute = self.aspace[nid].attributes[ua.AttributeIds.Value]
        attribute.value = dv
        for handle, callback in list(attribute.datachange_callbacks.items()):
            await callback(handle, dv)

    def values(self, mid: int) -> list[object]:
        return [e.Value.Value.Value for m, e in self.sub.queued if m == mid]


@pytest.fixture
def items() -> Items:
    aspace, sub = space(), Subscription()
    return Items(aspace, sub, BenchMonitoredItems(sub, aspace, stamp))  # type: ignore[arg-type]


def absolute(band: float) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(T.StatusValue, ua.DeadbandType.Absolute, band)


def percent(pct: float) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(T.StatusValue, ua.DeadbandType.Percent, pct)


async def test_an_item_reports_its_first_value_with_a_fresh_server_timestamp(items: Items) -> None:
    made = await items.create(CURRENT)
    assert made.StatusCode.is_good()
    ((mid, first),) = items.sub.queued
    assert mid == made.MonitoredItemId and first.ClientHandle == 1
    assert first.Value.ServerTimestamp == FRESH and first.Value.SourceTimestamp == T0


async def test_the_filter_is_checked_when_the_item_is_created(items: Items) -> None:
    assert (await items.create(COUNT, percent(10.0))).StatusCode.value == (
        S.BadMonitoredItemFilterUnsupported
    )
    assert (await items.create(LABEL, absolute(1.0))).StatusCode.value == S.BadFilterNotAllowed
    unknown = ua.NodeId("nothing", 2)
    assert (await items.create(unknown, absolute(1.0))).StatusCode.value == S.BadNodeIdUnknown
    assert items.sub.queued == []  # nothing refused was sampled
    made = await items.create(CURRENT, percent(10.0))  # 0.08 A of the EURange's 0.8 A
    assert made.StatusCode.is_good()
    for i in range(1, 7):
        await items.sample(CURRENT, round(0.05 * i, 2), VT.Double)
    assert items.values(made.MonitoredItemId) == [0.0, 0.1, 0.2, 0.3]


async def test_modifying_an_item_checks_and_replaces_its_filter_and_timestamps(
    items: Items,
) -> None:
    made = await items.create(COUNT, absolute(5))
    mid = made.MonitoredItemId

    def modify(flt: object, ttr: TTR = TTR.Both) -> ua.MonitoredItemModifyResult:
        req = ua.MonitoredItemModifyRequest()
        req.MonitoredItemId = mid
        req.RequestedParameters = ua.MonitoringParameters(ClientHandle=9, Filter=flt, QueueSize=50)
        (result,) = items.svc.modify_monitored_items(
            ua.ModifyMonitoredItemsParameters(1, ttr, [req])
        )
        return result

    assert modify(percent(5.0)).StatusCode.value == S.BadMonitoredItemFilterUnsupported
    await items.sample(COUNT, 3, VT.Int64)
    assert items.values(mid) == [0]  # the old filter holds
    result = modify(absolute(1), TTR.Neither)
    assert result.StatusCode.is_good() and result.RevisedQueueSize == 50
    await items.sample(COUNT, 4, VT.Int64)  # 4 from the last report (0): more than 1
    _, last = items.sub.queued[-1]
    assert last.Value.Value.Value == 4 and last.ClientHandle == 9
    assert last.Value.SourceTimestamp is None and last.Value.ServerTimestamp is None
    req = ua.MonitoredItemModifyRequest()
    req.MonitoredItemId = 12345
    (unknown,) = items.svc.modify_monitored_items(
        ua.ModifyMonitoredItemsParameters(1, TTR.Both, [req])
    )
    assert unknown.StatusCode.value == S.BadMonitoredItemIdInvalid


async def test_an_item_enabled_again_reports_its_value_afresh(items: Items) -> None:
    made = await items.create(CURRENT, absolute(0.5))
    mid = made.MonitoredItemId
    assert await items.svc.set_monitoring_mode(ua.MonitoringMode.Disabled, [mid]) == [
        ua.StatusCode()
    ]
    await items.sample(CURRENT, 0.1, VT.Double)
    assert items.values(mid) == [0.0]  # disabled: nothing
    await items.svc.set_monitoring_mode(ua.MonitoringMode.Reporting, [mid])
    assert items.values(mid) == [0.0, 0.1]  # within the deadband, yet reported: a new start


async def test_a_deleted_item_reports_nothing_more(items: Items) -> None:
    made = await items.create(CURRENT)
    mid = made.MonitoredItemId
    assert items.svc.delete_monitored_items([mid]) == [ua.StatusCode()]
    await items.sample(CURRENT, 0.3, VT.Double)
    assert items.values(mid) == [0.0]
    assert items.svc.delete_monitored_items([mid])[0].value == S.BadMonitoredItemIdInvalid
