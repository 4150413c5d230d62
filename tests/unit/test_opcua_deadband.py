"""The data change filter's rule (publish/opcua/deadband.py) and the timestamps a client
gets (publish/opcua/timestamps.py), without a server: OPC UA Part 4 §7.22.2, §7.10,
§7.11, §7.40 and Part 8 §6.2.

Part 4's deadband rule is the greedy one: a sample is reported when it is more than the
deadband away from the value last reported. Two properties pin that sequence down for any
signal (hypothesis): every report after the first is more than the deadband from the one
before it, and every sample not reported is within the deadband of the last report
before it.
"""

from __future__ import annotations

import itertools
import math
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import ua
from asyncua.common.utils import ServiceError
from hypothesis import given
from hypothesis import strategies as st

from supervisor.publish.opcua.deadband import ValueFilter, reports, value_filter
from supervisor.publish.opcua.timestamps import Freshness, read, returned

S = ua.StatusCodes
T = ua.DataChangeTrigger
TTR = ua.TimestampsToReturn
VT = ua.VariantType
T0 = datetime(2026, 12, 5, 14, 0, tzinfo=UTC)


def dv(value: object, status: int = S.Good, source: datetime | None = None) -> ua.DataValue:
    vt = VT.Double if isinstance(value, float) else VT.Int64
    return ua.DataValue(
        ua.Variant(value, vt), StatusCode=ua.StatusCode(status), SourceTimestamp=source
    )


def reported(f: ValueFilter, samples: list[ua.DataValue]) -> list[ua.DataValue]:
    """What an item with filter ``f`` queues of ``samples``, in order."""
    out: list[ua.DataValue] = []
    last = None
    for s in samples:
        if reports(f, last, s):
            out.append(s)
            last = s
    return out


def values(dvs: list[ua.DataValue]) -> list[object]:
    return [d.Value.Value for d in dvs]


def absolute(band: float, trigger: T = T.StatusValue) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(trigger, ua.DeadbandType.Absolute, band)


def percent(pct: float) -> ua.DataChangeFilter:
    return ua.DataChangeFilter(T.StatusValue, ua.DeadbandType.Percent, pct)


def checked(flt: object, number: bool = True, rng: tuple[float, float] | None = None) -> object:
    return value_filter(flt, value_attribute=True, number=number, eu_range=rng)


# --- the two cases --------------------------------------------------------------------
def test_a_ramp_in_steps_under_the_deadband_is_reported_each_time_it_passes_it() -> None:
    # 0 → 0.25 A in 0.05 A steps under 0.08 A: the previous sample is never 0.08 away, the
    # last report is (asyncua compared with the previous sample and reported nothing).
    f = checked(absolute(0.08))
    assert isinstance(f, ValueFilter)
    ramp = [dv(round(0.05 * i, 2)) for i in range(6)]
    assert values(reported(f, ramp)) == [0.0, 0.1, 0.2]


def test_a_counter_under_a_deadband_of_five_is_reported_every_six_counts() -> None:
    f = checked(absolute(5))
    assert isinstance(f, ValueFilter)
    counter = [dv(i) for i in range(50)]
    assert values(reported(f, counter)) == [0, 6, 12, 18, 24, 30, 36, 42, 48]


def test_a_percent_deadband_is_that_share_of_the_eu_range_span() -> None:
    f = checked(percent(10.0), rng=(-0.4, 0.4))
    assert isinstance(f, ValueFilter) and f.deadband == pytest.approx(0.08)
    ramp = [dv(round(0.05 * i, 2)) for i in range(6)]
    assert values(reported(f, ramp)) == [0.0, 0.1, 0.2]


# --- the rule for any signal ---------------------------------------------------------------
signals = st.lists(
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False), min_size=1, max_size=60
)
bands = st.floats(min_value=0.0, max_value=1e5, allow_nan=False)


@given(signals, bands)
def test_reports_are_more_than_the_deadband_apart_and_nothing_beyond_it_is_left_out(
    signal: list[float], band: float
) -> None:
    f = ValueFilter(T.StatusValue, band)
    out: list[int] = []  # indexes reported
    last = None
    for i, x in enumerate(signal):
        if reports(f, last, dv(x)):
            out.append(i)
            last = dv(x)
    assert out[0] == 0  # the first sample always
    for a, b in itertools.pairwise(out):
        assert abs(signal[b] - signal[a]) > band
    for i in range(len(signal)):
        before = max(j for j in out if j <= i)
        if i not in out:
            assert abs(signal[i] - signal[before]) <= band


@given(signals)
def test_without_deadband_every_change_of_value_is_reported_and_no_repeat(
    signal: list[float],
) -> None:
    got = values(reported(ValueFilter(), [dv(x) for x in signal]))
    expected = [x for i, x in enumerate(signal) if i == 0 or x != signal[i - 1]]
    assert got == expected


@given(signals, bands, st.lists(st.sampled_from([S.Good, S.UncertainLastUsableValue])))
def test_a_change_of_status_is_reported_whatever_the_deadband(
    signal: list[float], band: float, statuses: list[int]
) -> None:
    codes = (statuses * len(signal))[: len(signal)] or [S.Good] * len(signal)
    samples = [dv(x, c) for x, c in zip(signal, codes, strict=False)]
    got = reported(ValueFilter(T.StatusValue, band), samples)
    changes = [s for i, s in enumerate(samples) if i > 0 and codes[i] != codes[i - 1]]
    assert all(any(g is c for g in got) for c in changes)


def test_trigger_status_reports_status_changes_only() -> None:
    samples = [dv(1.0), dv(2.0), dv(2.0, S.BadNoCommunication), dv(3.0, S.BadNoCommunication)]
    assert reported(ValueFilter(T.Status), samples) == [samples[0], samples[2]]


def test_trigger_status_value_timestamp_also_reports_a_new_source_time() -> None:
    samples = [dv(1.0, source=T0), dv(1.0, source=T0 + timedelta(seconds=1)), dv(1.0)]
    got = reported(ValueFilter(T.StatusValueTimestamp), samples)
    assert got == samples
    # With a deadband it behaves as StatusValue (Part 4 §7.10).
    assert reported(ValueFilter(T.StatusValueTimestamp, 0.5), samples) == samples[:1]


def test_nan_is_reported_once_when_the_value_enters_it_and_when_it_leaves() -> None:
    nan = math.nan
    samples = [dv(1.0), dv(nan), dv(nan), dv(1.0)]
    assert reported(ValueFilter(), samples) == [samples[0], samples[1], samples[3]]
    assert reported(ValueFilter(T.StatusValue, 10.0), samples) == [
        samples[0],
        samples[1],
        samples[3],
    ]


def test_an_array_is_reported_whole_when_one_element_passes_or_its_size_changes() -> None:
    def arr(*xs: float) -> ua.DataValue:
        return ua.DataValue(ua.Variant(list(xs), VT.Double))

    samples = [arr(0.0, 0.0), arr(0.5, 0.5), arr(0.5, 1.5), arr(0.5, 1.5, 0.0)]
    assert reported(ValueFilter(T.StatusValue, 1.0), samples) == [
        samples[0],
        samples[2],
        samples[3],
    ]


def test_integers_subtract_exactly_near_the_int64_limits() -> None:
    top = 2**63 - 1
    f = ValueFilter(T.StatusValue, 1.0)
    assert not reports(f, dv(top - 1), dv(top))
    assert reports(f, dv(top - 2), dv(top))


# --- what is refused, with which code ----------------------------------------------------------
def test_a_filter_as_decoded_from_the_wire_is_one() -> None:
    # asyncua decodes the protocol's class; ``ua.DataChangeFilter`` is a subclass of it.
    wire = ua.uaprotocol_auto.DataChangeFilter(T.StatusValue, ua.DeadbandType.Absolute, 0.5)
    assert checked(wire) == ValueFilter(T.StatusValue, 0.5)
    assert checked(ua.uaprotocol_auto.EventFilter()) == S.BadFilterNotAllowed


def test_no_filter_is_status_value_without_deadband() -> None:
    assert checked(None) == ValueFilter(T.StatusValue, None)
    assert checked(ua.ExtensionObject()) == ValueFilter(T.StatusValue, None)  # null on the wire
    assert checked(ua.DataChangeFilter(T.Status)) == ValueFilter(T.Status, None)


def test_a_percent_deadband_needs_an_eu_range() -> None:
    # An Int64 counter is a Number without EURange: it cannot support this filter.
    assert checked(percent(10.0), rng=None) == S.BadMonitoredItemFilterUnsupported
    assert checked(percent(10.0), rng=(math.inf, math.inf)) == S.BadMonitoredItemFilterUnsupported


def test_a_deadband_on_what_is_not_a_number_is_not_allowed() -> None:
    assert checked(absolute(1.0), number=False) == S.BadFilterNotAllowed
    assert checked(percent(1.0), number=False, rng=(0.0, 1.0)) == S.BadFilterNotAllowed
    other = value_filter(absolute(1.0), value_attribute=False, number=True, eu_range=None)
    assert other == S.BadFilterNotAllowed
    # Without a deadband the trigger applies to any variable.
    assert checked(ua.DataChangeFilter(T.StatusValue), number=False) == ValueFilter()


@pytest.mark.parametrize(
    "flt",
    [
        percent(100.5),
        percent(-1.0),
        absolute(-0.1),
        absolute(math.nan),
        absolute(math.inf),
        ua.DataChangeFilter(T.StatusValue, 3, 1.0),
    ],
    ids=["percent>100", "percent<0", "negative", "nan", "inf", "unknown-type"],
)
def test_an_invalid_deadband_is_bad_deadband_filter_invalid(flt: ua.DataChangeFilter) -> None:
    assert checked(flt, rng=(0.0, 1.0)) == S.BadDeadbandFilterInvalid


def test_event_and_aggregate_filters_on_a_value_are_refused() -> None:
    assert checked(ua.EventFilter()) == S.BadFilterNotAllowed
    assert checked(ua.AggregateFilter()) == S.BadMonitoredItemFilterUnsupported


def test_percent_bounds_are_accepted_zero_is_every_change() -> None:
    assert checked(percent(0.0), rng=(-1e308, 1e308)) == ValueFilter(T.StatusValue, 0.0)
    f = checked(percent(100.0), rng=(0.0, 2.0))
    assert f == ValueFilter(T.StatusValue, 2.0)


# --- timestamps -------------------------------------------------------------------------------
def stamped() -> ua.DataValue:
    return ua.DataValue(
        ua.Variant(1.0, VT.Double),
        SourceTimestamp=T0,
        ServerTimestamp=T0 + timedelta(seconds=1),
        SourcePicoseconds=10,
        ServerPicoseconds=20,
    )


@pytest.mark.parametrize(
    ("ttr", "source", "server"),
    [
        (TTR.Source, True, False),
        (TTR.Server, False, True),
        (TTR.Both, True, True),
        (TTR.Neither, False, False),
    ],
)
def test_timestamps_to_return_keeps_only_what_is_asked(
    ttr: ua.TimestampsToReturn, source: bool, server: bool
) -> None:
    original = stamped()
    got = returned(original, ttr)
    assert (got.SourceTimestamp is not None, got.SourcePicoseconds is not None) == (source,) * 2
    assert (got.ServerTimestamp is not None, got.ServerPicoseconds is not None) == (server,) * 2
    assert original == stamped()  # the address space's own DataValue is not touched
    # An attribute other than Value never has a SourceTimestamp.
    assert returned(original, ttr, value_attribute=False).SourceTimestamp is None


def test_a_tag_unchanged_since_is_stamped_with_the_last_hand_over() -> None:
    tag = ua.NodeId("ch0.voltage", 2)
    other = ua.NodeId(2255)  # the Server's NamespaceArray: not a tag
    fresh = Freshness({tag})
    old = stamped()
    assert fresh.stamp(tag, ua.AttributeIds.Value, old) is old  # nothing heard yet
    later = T0 + timedelta(minutes=5)
    fresh.heard(later)
    fresh.heard(T0)  # an older hand-over never moves it back
    got = fresh.stamp(tag, ua.AttributeIds.Value, old)
    assert got.ServerTimestamp == later and got.SourceTimestamp == T0  # still the change's
    assert fresh.stamp(other, ua.AttributeIds.Value, old) is old
    assert fresh.stamp(tag, ua.AttributeIds.DisplayName, old) is old


def test_a_read_with_an_invalid_timestamps_to_return_is_a_service_fault() -> None:
    params = ua.ReadParameters()
    params.NodesToRead = [ua.ReadValueId(ua.NodeId("ch0.voltage", 2), ua.AttributeIds.Value)]
    params.TimestampsToReturn = TTR.Invalid
    with pytest.raises(ServiceError) as caught:
        read(params, [stamped()], Freshness(set()))
    assert caught.value.code == S.BadTimestampsToReturnInvalid
    params.TimestampsToReturn = TTR.Server
    (got,) = read(params, [stamped()], Freshness(set()))
    assert got.SourceTimestamp is None and got.ServerTimestamp is not None
