"""What the OPC UA server decides without a server (issue 31, findings 3, 5, 7 and 8): which
occurrence of a condition an EventId names (Acknowledge, Confirm), which alarm views a
ConditionRefresh must send first, on which object a method may be called, and what each
served aggregate answers for an interval."""

from __future__ import annotations

import dataclasses

import pytest
from asyncua import ua

from supervisor.core.quality import Quality
from supervisor.publish.historian import Bucket
from supervisor.publish.opcua.events import REMEMBERED, Occurrences, stale
from supervisor.publish.opcua.feed import AlarmView
from supervisor.publish.opcua.history import SERVED, aggregate_of, bucket_value
from supervisor.publish.opcua.methods import METHODS, not_on

S = ua.StatusCodes
O = ua.ObjectIds  # noqa: E741


def status(found: tuple[int, str] | None) -> int | None:
    return None if found is None else found[0]


# --- Acknowledge and Confirm: the occurrence an EventId names ------------------------------
def test_an_eventid_sent_while_unacknowledged_acknowledges_that_occurrence() -> None:
    o = Occurrences()
    o.record(b"activated", acked=False, confirmed=False)
    o.record(b"cleared", acked=False, confirmed=False)  # still the same occurrence
    assert status(o.refusal(b"activated", "acked")) is None
    assert status(o.refusal(b"cleared", "acked")) is None
    assert status(o.refusal(b"never sent", "acked")) == S.BadEventIdUnknown


def test_an_occurrence_acknowledged_before_does_not_acknowledge_the_next() -> None:
    o = Occurrences()
    o.record(b"first", acked=False, confirmed=True)
    o.record(b"first acked", acked=True, confirmed=True)
    o.record(b"second", acked=False, confirmed=True)
    assert status(o.refusal(b"first", "acked")) == S.BadConditionBranchAlreadyAcked
    assert status(o.refusal(b"first acked", "acked")) == S.BadConditionBranchAlreadyAcked
    assert status(o.refusal(b"second", "acked")) is None


def test_confirm_follows_the_confirmed_state_as_acknowledge_the_acked_state() -> None:
    o = Occurrences()
    o.record(b"tripped", acked=False, confirmed=False)
    o.record(b"acked", acked=True, confirmed=False)  # acknowledged, not yet reset
    assert status(o.refusal(b"tripped", "confirmed")) is None
    assert status(o.refusal(b"acked", "confirmed")) is None
    assert status(o.refusal(b"tripped", "acked")) == S.BadConditionBranchAlreadyAcked
    o.record(b"reset", acked=True, confirmed=True)
    assert status(o.refusal(b"tripped", "confirmed")) == S.BadConditionBranchAlreadyConfirmed
    assert status(o.refusal(b"never", "confirmed")) == S.BadEventIdUnknown


def test_a_condition_remembers_its_last_eventids_only() -> None:
    o = Occurrences()
    for k in range(REMEMBERED + 1):
        o.record(k.to_bytes(4, "big"), acked=False, confirmed=True)
    assert status(o.refusal((0).to_bytes(4, "big"), "acked")) == S.BadEventIdUnknown
    assert status(o.refusal((1).to_bytes(4, "big"), "acked")) is None
    assert len(o.sent) == REMEMBERED


# --- ConditionRefresh: the alarm model's views the server has not sent ----------------------
ACTIVE = AlarmView("x", "", 500, "m", "active, unacknowledged", True, False, wall=10.0)
NORMAL = AlarmView("x", "", 500, "m", "normal", False, True, wall=20.0)


def test_a_newer_view_in_another_state_is_sent_before_a_refresh() -> None:
    assert stale({"x": ACTIVE}, [NORMAL]) == [NORMAL]


def test_a_view_older_than_the_last_sent_changes_nothing() -> None:
    """The server's process holds the snapshot it was started with (ADR 0029): its views
    are older than any event since and must not bring a closed condition back."""
    assert stale({"x": NORMAL}, [ACTIVE]) == []


def test_the_state_sent_already_or_a_normal_alarm_never_sent_is_not_sent_again() -> None:
    now = dataclasses.replace(ACTIVE, wall=30.0)
    assert stale({"x": ACTIVE}, [now]) == []
    assert stale({}, [NORMAL]) == []
    assert stale({}, [ACTIVE]) == [ACTIVE]


# --- a method on the object it belongs to --------------------------------------------------
def test_a_method_is_called_on_its_own_object_only() -> None:
    ch1, ch2 = ua.NodeId("/Bench/Channels/ch1", 1), ua.NodeId("/Bench/Channels/ch2", 1)
    for method in METHODS:
        assert not_on(method, ch1, ch1) is None
        refused = not_on(method, ch2, ch1)
        assert refused is not None and refused.status == S.BadMethodInvalid


# --- aggregates ----------------------------------------------------------------------------
def test_every_served_aggregate_is_a_standard_aggregate_function() -> None:
    assert set(SERVED) == {
        O.AggregateFunction_Average,
        O.AggregateFunction_Minimum,
        O.AggregateFunction_Maximum,
        O.AggregateFunction_Count,
        O.AggregateFunction_TimeAverage,
    }
    for nid, what in SERVED.items():
        assert aggregate_of([ua.NodeId(nid)], 0) == what
    assert aggregate_of([ua.NodeId(O.AggregateFunction_Total)], 0) == S.BadAggregateNotSupported
    assert aggregate_of([ua.NodeId(O.AggregateFunction_Count, 2)], 0) == (
        S.BadAggregateNotSupported
    )
    two = [ua.NodeId(O.AggregateFunction_Count), ua.NodeId(O.AggregateFunction_Average)]
    assert aggregate_of(two, 1) == "mean"
    assert aggregate_of(two, 2) == S.BadAggregateListMismatch


def bucket(count: int, samples: int, quality: Quality) -> Bucket:
    mean = 1.5 if count else None
    return Bucket(0.0, count, samples, mean, mean, mean, None, None, quality)


@pytest.mark.parametrize(
    ("b", "value", "code"),
    [
        (None, 0, S.Good),  # Part 13: no value in the interval, a count of zero
        (bucket(3, 3, Quality.GOOD), 3, S.Good),
        (bucket(2, 2, Quality.UNCERTAIN), 2, S.Uncertain),  # the worst quality's status
        (bucket(2, 3, Quality.BAD), 2, S.UncertainDataSubNormal),  # the BAD one not counted
        (bucket(0, 2, Quality.BAD), 0, S.UncertainDataSubNormal),
    ],
)
def test_count_is_an_int32_of_the_values_in_the_interval(
    b: Bucket | None, value: int, code: int
) -> None:
    dv = bucket_value(b, "count", 5.0)
    assert (dv.Value.Value, dv.Value.VariantType, dv.StatusCode.value) == (
        value,
        ua.VariantType.Int32,
        code,
    )
    assert dv.SourceTimestamp.timestamp() == 5.0


@pytest.mark.parametrize("what", ["mean", "min", "max"])
def test_the_other_aggregates_of_an_interval_without_values_are_bad_no_data(what: str) -> None:
    assert bucket_value(None, what, 0.0).StatusCode.value == S.BadNoData
    assert bucket_value(bucket(0, 2, Quality.BAD), what, 0.0).StatusCode.value == S.BadNoData
    dv = bucket_value(bucket(3, 3, Quality.GOOD), what, 0.0)
    assert (dv.Value.Value, dv.StatusCode.value) == (1.5, S.Good)
