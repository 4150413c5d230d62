"""Monitored items as Part 4 wants them: deadbands and TimestampsToReturn (ADR 0014).

asyncua's ``MonitoredItemService`` compares each sample with the previous *sample* (a slow
ramp under an absolute deadband is never reported), ignores a percent deadband (with a
warning at every change), accepts any filter on any variable, and sends both timestamps
whatever the client asked. Here it is subclassed (``BenchMonitoredItems``): the filter is
checked when the item is created or modified and kept as a ``deadband.ValueFilter``, each
item keeps the DataValue it last reported, and each notification carries the timestamps
the item asked for (``timestamps.returned``). Event items and everything else stay
asyncua's.

Each subscription gets one: ``BenchSubscriptions`` (asyncua's ``SubscriptionService``
subclassed) swaps it in when a subscription is created; ``serve_subscriptions`` installs
that service on the server before ``Server.init`` binds anything to the old one.

Speed: asyncua deep-copied every sample into each item (``set_current_datavalue``); a
DataValue written into the address space is a new object each time and never changed
after (server.py ``_value``, and asyncua's own writes), so the last reported one is kept
by reference.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

from asyncua import ua
from asyncua.server.address_space import AddressSpace
from asyncua.server.internal_server import InternalServer
from asyncua.server.internal_subscription import InternalSubscription
from asyncua.server.monitored_item_service import MonitoredItemService
from asyncua.server.subscription_service import SubscriptionService

from supervisor.publish.opcua.deadband import ValueFilter, reports, value_filter
from supervisor.publish.opcua.timestamps import check, returned

log = logging.getLogger(__name__)

S = ua.StatusCodes
Stamp = Callable[[ua.NodeId, int, ua.DataValue], ua.DataValue]
"""The address space's value as a reader gets it (timestamps.Freshness.stamp)."""

NUMBER_TYPES: Final = frozenset(
    ua.NodeId(i)
    for i in (
        ua.ObjectIds.Number,
        ua.ObjectIds.Integer,
        ua.ObjectIds.UInteger,
        ua.ObjectIds.Decimal,
        ua.ObjectIds.SByte,
        ua.ObjectIds.Byte,
        ua.ObjectIds.Int16,
        ua.ObjectIds.UInt16,
        ua.ObjectIds.Int32,
        ua.ObjectIds.UInt32,
        ua.ObjectIds.Int64,
        ua.ObjectIds.UInt64,
        ua.ObjectIds.Float,
        ua.ObjectIds.Double,
    )
)
"""Number and its subtypes in namespace 0 (Part 3 §8.41, Part 5 §12.2.9)."""
SUPERTYPE_HOPS: Final = 16
"""A DataType's supertypes followed at most this far (a loop in a broken model ends)."""
EU_RANGE: Final = ua.QualifiedName("EURange", 0)
HAS_SUBTYPE: Final = ua.NodeId(ua.ObjectIds.HasSubtype)
HAS_PROPERTY: Final = ua.NodeId(ua.ObjectIds.HasProperty)


@dataclass(slots=True)
class Item:
    """What this override keeps per data item, beside asyncua's ``MonitoredItemData``."""

    rule: ValueFilter
    ttr: ua.TimestampsToReturn
    last: ua.DataValue | None = None  # the value last queued for the client (Part 4)


def is_number(aspace: AddressSpace, nid: ua.NodeId) -> bool:
    """The variable's DataType is Number or a subtype of it."""
    dtype = _attribute(aspace, nid, ua.AttributeIds.DataType)
    for _ in range(SUPERTYPE_HOPS):
        if not isinstance(dtype, ua.NodeId):
            return False
        if dtype in NUMBER_TYPES:
            return True
        node = aspace.get(dtype)
        if node is None:
            return False
        supers = (r for r in node.references if r.ReferenceTypeId == HAS_SUBTYPE)
        dtype = next((r.NodeId for r in supers if not r.IsForward), None)
    return False


def eu_range(aspace: AddressSpace, nid: ua.NodeId) -> tuple[float, float] | None:
    """The EURange property's (Low, High) as the node has it now; None without one."""
    node = aspace.get(nid)
    if node is None:
        return None
    for r in node.references:
        if r.ReferenceTypeId == HAS_PROPERTY and r.IsForward and r.BrowseName == EU_RANGE:
            value = _attribute(aspace, r.NodeId, ua.AttributeIds.Value)
            if isinstance(value, ua.Range):
                return float(value.Low), float(value.High)
            return None
    return None


def _attribute(aspace: AddressSpace, nid: ua.NodeId, attribute: ua.AttributeIds) -> Any:
    dv = aspace.read_attribute_value(nid, attribute)
    if dv.StatusCode is not None and not dv.StatusCode.is_good():
        return None
    return dv.Value.Value if dv.Value is not None else None


class BenchMonitoredItems(MonitoredItemService):  # type: ignore[misc]
    """asyncua's monitored items of one subscription, with Part 4's data change filter and
    TimestampsToReturn (module docstring)."""

    def __init__(self, isub: InternalSubscription, aspace: AddressSpace, stamp: Stamp) -> None:
        super().__init__(isub, aspace)
        self._items: dict[int, Item] = {}
        self._stamp = stamp

    async def create_monitored_items(
        self, params: ua.CreateMonitoredItemsParameters
    ) -> list[ua.MonitoredItemCreateResult]:
        ttr = check(params.TimestampsToReturn)
        results: list[ua.MonitoredItemCreateResult] = []
        for item in params.ItemsToCreate:
            if item.ItemToMonitor.AttributeId == ua.AttributeIds.EventNotifier:
                results.append(self._create_events_monitored_item(item))
            else:
                results.append(await self._create_value_item(item, ttr))
        return results

    async def _create_value_item(
        self, params: ua.MonitoredItemCreateRequest, ttr: ua.TimestampsToReturn
    ) -> ua.MonitoredItemCreateResult:
        """asyncua's ``_create_data_change_monitored_item`` with the filter checked first
        and kept, and the item's state registered before its first value is sampled."""
        target = params.ItemToMonitor
        rule = self._rule(target, params.RequestedParameters.Filter)
        if isinstance(rule, int):
            log.info(
                "monitored item on %s refused: %s (filter %r)",
                target.NodeId.to_string(),
                ua.StatusCode(rule).name,
                params.RequestedParameters.Filter,
            )
            refused = ua.MonitoredItemCreateResult()
            refused.StatusCode = ua.StatusCode(rule)
            return refused
        result, mdata = self._make_monitored_item_common(params)
        result.StatusCode, handle = self.aspace.add_datachange_callback(
            target.NodeId, target.AttributeId, self.datachange_callback
        )
        mdata.callback_handle = handle
        self._commit_monitored_item(result, mdata)
        if result.StatusCode.is_good():
            self._items[result.MonitoredItemId] = Item(rule, ttr)
            self._monitored_datachange[handle] = result.MonitoredItemId
            if mdata.mode != ua.MonitoringMode.Disabled:
                await self.trigger_datachange(handle, target.NodeId, target.AttributeId)
        return result

    def _rule(self, target: ua.ReadValueId, flt: object) -> ValueFilter | int:
        node = self.aspace.get(target.NodeId)
        if node is None:
            return int(S.BadNodeIdUnknown)
        if target.AttributeId not in node.attributes:
            return int(S.BadAttributeIdInvalid)
        value = target.AttributeId == ua.AttributeIds.Value
        return value_filter(
            flt,
            value_attribute=value,
            number=value and is_number(self.aspace, target.NodeId),
            eu_range=eu_range(self.aspace, target.NodeId) if value else None,
        )

    def modify_monitored_items(
        self, params: ua.ModifyMonitoredItemsParameters
    ) -> list[ua.MonitoredItemModifyResult]:
        ttr = check(params.TimestampsToReturn)
        return [self._modify(item, ttr) for item in params.ItemsToModify]

    def _modify(
        self, req: ua.MonitoredItemModifyRequest, ttr: ua.TimestampsToReturn
    ) -> ua.MonitoredItemModifyResult:
        """asyncua's ``_modify_monitored_item`` (whose unknown-id branch raises) with the new
        filter checked and the new TimestampsToReturn kept."""
        result = ua.MonitoredItemModifyResult()
        mdata = self._monitored_items.get(req.MonitoredItemId)
        if mdata is None:
            result.StatusCode = ua.StatusCode(S.BadMonitoredItemIdInvalid)
            return result
        wanted = req.RequestedParameters
        item = self._items.get(req.MonitoredItemId)
        if item is not None and mdata.read_value_id is not None:
            # Part 4 §5.13.3: the filter given replaces the item's (none: no filter).
            rule = self._rule(mdata.read_value_id, wanted.Filter)
            if isinstance(rule, int):
                result.StatusCode = ua.StatusCode(rule)
                return result
            item.rule, item.ttr = rule, ttr
        elif wanted.Filter:
            mdata.filter = wanted.Filter  # an event item's select clauses, as asyncua does
        result.RevisedSamplingInterval = self.isub.data.RevisedPublishingInterval
        result.RevisedQueueSize = self._revise_queue_size(wanted.QueueSize)
        mdata.queue_size = result.RevisedQueueSize
        mdata.client_handle = wanted.ClientHandle
        return result

    async def _set_monitoring_mode(self, mode: ua.MonitoringMode, mid: int) -> ua.StatusCode:
        item = self._items.get(mid)
        if item is not None and mode == ua.MonitoringMode.Disabled:
            item.last = None  # enabled again, the item reports its value afresh (Part 4)
        status: ua.StatusCode = await super()._set_monitoring_mode(mode, mid)
        return status

    def _delete_monitored_items(self, mid: int) -> ua.StatusCode:
        self._items.pop(mid, None)
        status: ua.StatusCode = super()._delete_monitored_items(mid)
        return status

    async def trigger_datachange(
        self, handle: int, nodeid: ua.NodeId, attr: ua.AttributeIds
    ) -> None:
        """An item's first value: the address space's, with its fresh ServerTimestamp."""
        dv = self._stamp(nodeid, attr, self.aspace.read_attribute_value(nodeid, attr))
        await self.datachange_callback(handle, dv)

    async def datachange_callback(
        self, handle: int, value: ua.DataValue, error: ua.StatusCode | None = None
    ) -> None:
        if error:
            await super().datachange_callback(handle, value, error)
            return
        mid = self._monitored_datachange.get(handle)
        item = self._items.get(mid) if mid is not None else None
        if mid is None or item is None:
            return
        mdata = self._monitored_items[mid]
        if mdata.mode == ua.MonitoringMode.Disabled or not reports(item.rule, item.last, value):
            return
        item.last = value
        event = ua.MonitoredItemNotification()
        event.ClientHandle = mdata.client_handle
        attribute = mdata.read_value_id.AttributeId if mdata.read_value_id is not None else 0
        event.Value = returned(value, item.ttr, attribute == ua.AttributeIds.Value)
        await self.isub.enqueue_datachange_event(mid, event, mdata.queue_size)


class BenchSubscriptions(SubscriptionService):  # type: ignore[misc]
    """asyncua's subscription service whose subscriptions monitor with ``BenchMonitoredItems``."""

    def __init__(self, aspace: AddressSpace, iserver: InternalServer, stamp: Stamp) -> None:
        super().__init__(aspace, iserver)
        self.stamp = stamp

    async def create_subscription(
        self,
        params: ua.CreateSubscriptionParameters,
        callback: Callable[..., Any],
        session_id: ua.NodeId,
        request_callback: Callable[..., Any] | None = None,
    ) -> ua.CreateSubscriptionResult:
        result: ua.CreateSubscriptionResult = await super().create_subscription(
            params, callback, session_id, request_callback
        )
        sub = self.subscriptions[result.SubscriptionId]
        sub.monitored_item_srv = BenchMonitoredItems(sub, self.aspace, self.stamp)
        return result


def serve_subscriptions(iserver: InternalServer, stamp: Stamp) -> BenchSubscriptions:
    """Install ``BenchSubscriptions`` on a server not yet initialised (``Server.init`` binds
    ConditionRefresh and the refresh events to the service it finds)."""
    service = BenchSubscriptions(iserver.aspace, iserver, stamp)
    iserver.subscription_service = service
    iserver.isession.subscription_service = service
    return service
