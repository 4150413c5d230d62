"""The tag database: typed values with quality, access levels, forcing, change feed."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.tags import Access, Scaling, TagDB, TagSpec


def make_db() -> TagDB:
    db = TagDB()
    db.add(TagSpec("ch0.voltage", unit="V", range=(0.0, 5.0)))
    db.add(TagSpec("ch0.setpoint", unit="A", range=(-1.0, 1.0), access=Access.OPERATOR))
    db.add(TagSpec("ch0.gain", access=Access.ENGINEER))
    db.add(TagSpec("ch0.mode", dtype="str", access=Access.OPERATOR, choices=("manual", "auto")))
    return db


def test_a_new_tag_is_bad_until_the_process_gives_it_a_value() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    assert tag.quality is Quality.BAD
    assert tag.reason is Reason.INITIAL
    db.update(tag, 1.2)
    assert tag.good and tag.value == 1.2


def test_changed_since_returns_each_changed_tag_once_in_change_order() -> None:
    db = make_db()
    v0 = db.version
    db.update(db["ch0.voltage"], 1.0)
    db.update(db["ch0.gain"], 2.0)
    db.update(db["ch0.voltage"], 1.1)
    changed = db.changed_since(v0)
    assert [t.name for t in changed] == ["ch0.gain", "ch0.voltage"]
    assert db.changed_since(db.version) == []


def test_an_unchanged_value_does_not_bump_the_version() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    db.update(tag, 1.0)
    v = db.version
    db.update(tag, 1.0)
    assert db.version == v


def test_a_quality_change_alone_is_a_change() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    db.update(tag, 1.0)
    v = db.version
    db.update(tag, 1.0, Quality.BAD, Reason.STALE)
    assert [t.name for t in db.changed_since(v)] == ["ch0.voltage"]


def test_a_reader_too_far_behind_the_change_log_gets_every_tag() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    for k in range(70_000):
        db.update(tag, float(k))
    assert len(db.changed_since(0)) == len(db)


def test_read_only_tags_refuse_operator_writes() -> None:
    db = make_db()
    with pytest.raises(OperatorError, match="read-only"):
        db.write("ch0.voltage", 1.0)


def test_engineer_tags_refuse_operator_writes_and_accept_engineer_writes() -> None:
    db = make_db()
    with pytest.raises(OperatorError, match="engineer"):
        db.write("ch0.gain", 2.0, Access.OPERATOR)
    assert db.write("ch0.gain", 2.0, Access.ENGINEER).value == 2.0


def test_a_write_outside_the_range_is_refused_with_the_range_in_the_message() -> None:
    db = make_db()
    with pytest.raises(OperatorError, match=r"outside its range \[-1.0, 1.0\]"):
        db.write("ch0.setpoint", 2.5)


def test_a_string_tag_with_choices_refuses_other_values() -> None:
    db = make_db()
    with pytest.raises(OperatorError, match="manual, auto"):
        db.write("ch0.mode", "turbo")
    assert db.write("ch0.mode", "auto").value == "auto"


def test_a_write_of_the_wrong_type_is_refused() -> None:
    db = make_db()
    with pytest.raises(OperatorError):
        db.write("ch0.setpoint", "fast")


def test_a_forced_tag_ignores_the_process_and_says_it_is_forced() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    db.update(tag, 1.0)
    db.force("ch0.voltage", 3.3)
    db.update(tag, 1.5)
    assert tag.value == 3.3
    assert tag.forced and tag.reason is Reason.FORCED
    db.unforce("ch0.voltage")
    assert tag.quality is Quality.UNCERTAIN
    db.update(tag, 1.5)
    assert tag.value == 1.5 and tag.good and not tag.forced


def test_a_non_finite_float_is_stored_as_bad_out_of_range() -> None:
    db = make_db()
    tag = db["ch0.voltage"]
    db.update(tag, math.nan)
    assert tag.quality is Quality.BAD and tag.reason is Reason.OUT_OF_RANGE


def test_duplicate_tag_names_are_refused() -> None:
    db = make_db()
    with pytest.raises(ValueError, match="duplicate"):
        db.add(TagSpec("ch0.voltage"))


def test_linear_scaling_round_trips_and_two_point_scaling_matches_the_lem_sensor() -> None:
    lem = Scaling.from_spans((-4.0, 4.0), (-300.0, 300.0))
    assert lem.to_eu(2.0) == pytest.approx(150.0)
    assert lem.to_raw(lem.to_eu(1.234)) == pytest.approx(1.234)


def test_a_scaling_with_zero_span_is_refused() -> None:
    with pytest.raises(ValueError, match="zero"):
        Scaling(0.0, 1.0)
    with pytest.raises(ValueError, match="zero"):
        Scaling.from_spans((1.0, 1.0), (0.0, 10.0))


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**300), 10**300)))
def test_a_float_update_is_bad_out_of_range_exactly_when_the_number_is_not_finite(
    x: float | int,
) -> None:
    """The update's finiteness test (``x - x != 0.0``, no call) says what ``isfinite``
    says, for every float and for integers turned into floats."""
    db = TagDB()
    tag = db.add(TagSpec("x"))
    db.update(tag, x)
    expected = float(x)
    if math.isfinite(expected):
        assert (tag.value, tag.quality, tag.reason) == (expected, Quality.GOOD, Reason.NONE)
    else:
        assert tag.quality is Quality.BAD and tag.reason is Reason.OUT_OF_RANGE
