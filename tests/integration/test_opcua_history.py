"""HistoryRead over OPC UA, served from the embedded historian: an asyncua client over
loopback reads what the bench stored (raw with continuation points, Average / Minimum /
Maximum per interval, events) and gets the Bad codes for what the server does not serve.

One server for the module: a bench recording its history (virtual clock) runs a discharge
on ch0 for a few seconds, its history written to the file, then the tests only read.
``room.temp`` is an I/O map tag with ``history: {enabled: false}``.
"""

from __future__ import annotations

import itertools
from collections.abc import AsyncIterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from commandrig import DISCHARGE, recipe
from opcuarig import Rig, opcua_rig

from supervisor.commands import Command, Verb
from supervisor.publish.historian import HistoryQuery, bucket_count

pytestmark = [pytest.mark.integration, pytest.mark.asyncio(loop_scope="module")]
S = ua.StatusCodes
TAG = "ch0.discharged_ah"  # moves every scan of a discharge
NOT_KEPT = "room.temp"


@pytest_asyncio.fixture(loop_scope="module", scope="module")
async def rig(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Rig]:
    tmp = tmp_path_factory.mktemp("opcua-history")
    async with opcua_rig(tmp, history=True, unhistorised=(NOT_KEPT,)) as r:
        started = r.bench.commands.execute(
            Command.channel("ch0", Verb.START, "test", recipe=recipe(tmp, DISCHARGE))
        )
        assert started.accepted, started.reason
        await r.scans(60)  # 6 s of discharge at 0.1 s per scan
        historian = r.bench.historian
        assert historian is not None and historian.writer.flush()
        yield r


def query(rig: Rig) -> HistoryQuery:
    assert rig.bench.historian is not None
    return rig.bench.historian.query


def utc(wall: float) -> datetime:
    return datetime.fromtimestamp(wall, UTC)


def aware(t: datetime) -> datetime:
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def stored(rig: Rig) -> tuple[float, float, list[Any]]:
    samples = query(rig).samples(TAG, 0.0, 1e12).samples
    assert len(samples) > 10, "the discharge stored a moving charge"
    return samples[0].t, samples[-1].t, samples


async def processed(
    c: Client, nid: ua.NodeId, start: float, end: float, interval_s: float, aggregate: int
) -> ua.HistoryReadResult:
    details = ua.ReadProcessedDetails()
    details.StartTime = utc(start)
    details.EndTime = utc(end)
    details.ProcessingInterval = interval_s * 1000.0
    details.AggregateType = [ua.NodeId(aggregate)]
    params = ua.HistoryReadParameters()
    params.HistoryReadDetails = details
    params.TimestampsToReturn = ua.TimestampsToReturn.Source
    params.ReleaseContinuationPoints = False  # (asyncua's default True asks for no data)
    rv = ua.HistoryReadValueId()
    rv.NodeId = nid
    params.NodesToRead = [rv]
    (res,) = await c.uaclient.history_read(params)
    return res


async def test_historised_tags_say_so_and_others_do_not(rig: Rig) -> None:
    async with rig.client("bob") as c:
        ns = await rig.ns(c)
        kept = c.get_node(ua.NodeId(TAG, ns))
        assert (await kept.read_attribute(ua.AttributeIds.Historizing)).Value.Value is True
        levels = await kept.get_access_level()
        assert ua.AccessLevel.HistoryRead in levels and ua.AccessLevel.CurrentRead in levels
        other = c.get_node(ua.NodeId(NOT_KEPT, ns))
        assert (await other.read_attribute(ua.AttributeIds.Historizing)).Value.Value is False
        assert ua.AccessLevel.HistoryRead not in await other.get_access_level()


async def test_raw_history_is_the_stored_samples_with_their_source_times(rig: Rig) -> None:
    start, end, samples = stored(rig)
    async with rig.client("bob") as c:
        node = c.get_node(ua.NodeId(TAG, await rig.ns(c)))
        values = await node.read_raw_history(utc(start), utc(end))
    assert [dv.Value.Value for dv in values] == [s.value for s in samples]
    assert [aware(dv.SourceTimestamp) for dv in values] == [utc(s.t) for s in samples]
    assert all(dv.StatusCode.is_good() for dv in values)


async def test_a_long_range_comes_in_pages_with_continuation_points(rig: Rig) -> None:
    start, end, samples = stored(rig)
    details = ua.ReadRawModifiedDetails()
    details.IsReadModified = False
    details.StartTime = utc(start)
    details.EndTime = utc(end)
    details.NumValuesPerNode = 7
    pages: list[list[ua.DataValue]] = []
    async with rig.client("bob") as c:
        node = c.get_node(ua.NodeId(TAG, await rig.ns(c)))
        cont = None
        while True:
            res = await node.history_read(details, cont)
            res.StatusCode.check()
            pages.append(res.HistoryData.DataValues)
            cont = res.ContinuationPoint
            if not cont:
                break
    assert all(len(p) == 7 for p in pages[:-1]) and 1 <= len(pages[-1]) <= 7
    assert [dv.Value.Value for p in pages for dv in p] == [s.value for s in samples]


async def test_processed_average_min_max_per_interval_match_the_historian(rig: Rig) -> None:
    start, end, _ = stored(rig)
    interval_s = 1.0
    buckets = query(rig).aggregate(TAG, start, end, interval_s).buckets
    assert len(buckets) >= 5
    async with rig.client("bob") as c:
        nid = ua.NodeId(TAG, await rig.ns(c))
        for aggregate, field in (
            (ua.ObjectIds.AggregateFunction_Average, "mean"),
            (ua.ObjectIds.AggregateFunction_Minimum, "min"),
            (ua.ObjectIds.AggregateFunction_Maximum, "max"),
        ):
            res = await processed(c, nid, start, end, interval_s, aggregate)
            res.StatusCode.check()
            values = res.HistoryData.DataValues
            assert len(values) == bucket_count(start, end, interval_s)  # one per interval
            got = [
                (aware(dv.SourceTimestamp).timestamp(), dv.Value.Value)
                for dv in values
                if dv.StatusCode.is_good()
            ]
            want = [(b.t, getattr(b, field)) for b in buckets]
            assert [t for t, _ in got] == pytest.approx([t for t, _ in want]), field
            assert [v for _, v in got] == pytest.approx([v for _, v in want]), field


async def test_other_aggregates_are_not_supported(rig: Rig) -> None:
    start, end, _ = stored(rig)
    async with rig.client("bob") as c:
        nid = ua.NodeId(TAG, await rig.ns(c))
        res = await processed(c, nid, start, end, 1.0, ua.ObjectIds.AggregateFunction_Interpolative)
    assert res.StatusCode.value == S.BadAggregateNotSupported


async def test_a_tag_without_history_answers_history_operation_unsupported(rig: Rig) -> None:
    start, end, _ = stored(rig)
    async with rig.client("bob") as c:
        node = c.get_node(ua.NodeId(NOT_KEPT, await rig.ns(c)))
        with pytest.raises(ua.UaStatusCodeError) as raised:
            await node.read_raw_history(utc(start), utc(end))
        assert raised.value.code == S.BadHistoryOperationUnsupported
        res = await processed(
            c, node.nodeid, start, end, 1.0, ua.ObjectIds.AggregateFunction_Average
        )
        assert res.StatusCode.value == S.BadHistoryOperationUnsupported


async def test_event_history_of_a_channel_is_the_stored_events(rig: Rig) -> None:
    stored_events = query(rig).events(0.0, 1e12, channel="ch0")
    assert any(e.kind == "command" for e in stored_events)
    async with rig.client("bob") as c:
        channel = c.get_node(ua.NodeId("/Bench/Channels/ch0", await rig.ns(c)))
        events = await channel.read_event_history(utc(stored_events[0].wall), utc(1e11))
    assert [e.Message.Text for e in events] == [e.text for e in stored_events]
    assert [aware(e.Time) for e in events] == [utc(e.wall) for e in stored_events]


async def test_a_bench_without_a_historian_serves_no_history(tmp_path: Path) -> None:
    async with opcua_rig(tmp_path) as r, r.client("bob") as c:
        node = c.get_node(ua.NodeId(TAG, await r.ns(c)))
        assert (await node.read_attribute(ua.AttributeIds.Historizing)).Value.Value is False
        with pytest.raises(ua.UaStatusCodeError) as raised:
            await node.read_raw_history(utc(0.0), utc(1e10))
        assert raised.value.code == S.BadHistoryOperationUnsupported


async def test_event_history_gives_each_event_the_type_it_has_live(rig: Rig) -> None:
    """Steps and states are ChainEventType, commands CommandEventType, alarm transitions
    AlarmConditionType with their ConditionName and condition: never BaseEventType."""
    stored_events = query(rig).events(0.0, 1e12)
    kinds = {e.kind for e in stored_events}
    assert {"step", "state", "command", "alarm"} <= kinds
    async with rig.client("bob") as c:
        ns = await rig.ns(c)
        bench = c.get_node(ua.NodeId("/Bench", ns))
        alarm_type = c.get_node(ua.ObjectIds.AlarmConditionType)
        events = await bench.read_event_history(utc(0.0), utc(1e11), evtypes=[alarm_type])
        commands = await bench.read_event_history(
            utc(0.0), utc(1e11), evtypes=[c.get_node(ua.NodeId("/Types/CommandEventType", ns))]
        )
        every = await bench.read_event_history(utc(0.0), utc(1e11))
    want = {
        "step": ua.NodeId("/Types/ChainEventType", ns),
        "state": ua.NodeId("/Types/ChainEventType", ns),
        "command": ua.NodeId("/Types/CommandEventType", ns),
        "alarm": ua.NodeId(ua.ObjectIds.AlarmConditionType),
    }
    assert [e.EventType for e in every] == [want[s.kind] for s in stored_events]
    # A where clause of OfType elements (asyncua's evtypes=…) picks the events of a type.
    alarms = [s for s in stored_events if s.kind == "alarm"]
    assert [e.Message.Text for e in events] == [s.text for s in alarms]
    assert {e.EventType for e in events} == {ua.NodeId(ua.ObjectIds.AlarmConditionType)}
    assert [e.ConditionName for e in events] == [s.source for s in alarms]
    room = next(e for e in events if e.ConditionName == "room.temp.H")
    assert room.NodeId == ua.NodeId("/Bench/Alarms/room.temp.H", ns)
    assert [e.Message.Text for e in commands] == [
        s.text for s in stored_events if s.kind == "command"
    ]


async def raw(
    c: Client, nid: ua.NodeId, start: float, end: float, bounds: bool = True
) -> list[ua.DataValue]:
    details = ua.ReadRawModifiedDetails()
    details.IsReadModified = False
    details.StartTime = utc(start)
    details.EndTime = utc(end)
    details.ReturnBounds = bounds
    res = await c.get_node(nid).history_read(details)
    res.StatusCode.check()
    return list(res.HistoryData.DataValues)


async def test_raw_history_with_bounds_gives_the_values_at_both_ends(rig: Rig) -> None:
    _, _, samples = stored(rig)
    a, b = samples[3], samples[8]
    start, end = a.t + 0.01, b.t - 0.01  # between two samples at each end
    inside = [s for s in samples if start <= s.t <= end]
    after = next(s for s in samples if s.t >= end)
    async with rig.client("bob") as c:
        nid = ua.NodeId(TAG, await rig.ns(c))
        without = await raw(c, nid, start, end, bounds=False)
        values = await raw(c, nid, start, end)
        early = await raw(c, nid, samples[0].t - 100.0, samples[1].t - 1e-3)
    assert [dv.Value.Value for dv in without] == [s.value for s in inside]
    # The sample before StartTime (the value at StartTime), then the range, then the first
    # sample after EndTime.
    assert [dv.Value.Value for dv in values] == [a.value, *(s.value for s in inside), after.value]
    assert aware(values[0].SourceTimestamp) == utc(a.t)
    assert aware(values[-1].SourceTimestamp) == utc(after.t)
    # Nothing stored before the start: Bad_BoundNotFound at StartTime.
    assert early[0].StatusCode.value == S.BadBoundNotFound
    assert aware(early[0].SourceTimestamp) == utc(samples[0].t - 100.0)
    assert early[1].Value.Value == samples[0].value


async def test_time_average_weights_each_value_by_how_long_it_held(rig: Rig) -> None:
    start, end, samples = stored(rig)
    interval_s = 1.0
    async with rig.client("bob") as c:
        nid = ua.NodeId(TAG, await rig.ns(c))
        res = await processed(
            c, nid, start, end, interval_s, ua.ObjectIds.AggregateFunction_TimeAverage
        )
    res.StatusCode.check()
    values = res.HistoryData.DataValues
    assert len(values) == bucket_count(start, end, interval_s)
    # By hand: each stored value holds until the next sample (stepped).
    lo, hi = start, start + interval_s
    area = sum(
        float(s.value) * (min(n.t, hi) - max(s.t, lo))  # type: ignore[arg-type]
        for s, n in itertools.pairwise(samples)
        if s.t < hi and n.t > lo
    )
    assert values[0].StatusCode.is_good()
    assert values[0].Value.Value == pytest.approx(area / interval_s)
