"""``TagDB.update_many`` and ``update_each`` (the outputs of the channels, guards and
chains, every scan: issue 29's profile of the dry run) leave every tag and the change
feed exactly as ``TagDB.update`` called for each pair in turn does, for every kind of
tag, value, quality, reason and forcing (``add_many`` and ``add_each`` as the updates of
each value plus its delta); ``Tag.as_float`` is the plain rule for every kind of value;
and ``Tag.number``, kept by every way a tag changes, is always ``as_float()`` of its
value."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.tags import TagDB, TagSpec
from supervisor.tags.spec import Access

DTYPES = ("float", "int", "bool", "str")
FORCED: dict[str, Any] = {"float": 1.5, "int": 2, "bool": True, "str": "idle"}


class Real(float):
    """A float of another type (as a numeric library hands over): a number all the same."""


values = st.one_of(
    st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=False).map(Real),
    st.sampled_from([0.0, -0.0, 1.0, 1.5, 2.0]),
    st.integers(-3, 3),
    st.integers(),
    st.booleans(),
    st.sampled_from(["", "idle", "charging", "1.5"]),
)
initials = st.one_of(st.none(), values)
deltas = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    # Non-finite sums (BAD, out of range) drawn often, not left to luck.
    st.sampled_from([0.0, -0.0, 1e-9, -1.5, 1e308, math.inf, -math.inf, math.nan]),
    st.integers(-3, 3),
)
# Before each batch: the process side moves some tags (any value, quality and reason),
# someone forces or unforces some, then the batch writes some (a tag may come twice).
process = st.tuples(
    st.integers(0, 3),
    values,
    st.sampled_from(list(Quality)),
    st.sampled_from([Reason.NONE, Reason.STALE, Reason.LAST_KNOWN, Reason.COMM_FAILURE]),
    st.one_of(st.none(), st.floats(0.0, 100.0)),
)
rounds = st.lists(
    st.tuples(
        st.lists(process, max_size=4),
        st.lists(st.tuples(st.integers(0, 3), st.booleans()), max_size=2),  # force/unforce
        st.lists(st.tuples(st.integers(0, 3), values), max_size=6),  # the batch
    ),
    max_size=8,
)


def state(db: TagDB) -> list[str]:
    """Every tag's state and the change feed, after checking that each tag's ``number`` is
    its value as a float (whichever way the tag last changed)."""
    for t in db:
        assert repr(t.number) == repr(number_of(t.value)), t
        assert type(t.number) is float
    tags = [
        repr((t.value, t.quality, t.reason, t.source_t, t.server_t, t.version, t.forced))
        for t in db
    ]
    return [*tags, repr(db.version), repr([t.name for t in db.changed_since(0)])]


def number_of(value: Any) -> float:
    """``plain_as_float(value, 0.0)``, an int beyond a float's range an infinity of its sign
    (where the plain rule raises)."""
    try:
        return plain_as_float(value, 0.0)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


@settings(max_examples=400, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(DTYPES), initials), min_size=4, max_size=4),
    rounds,
)
def test_a_batch_of_updates_is_each_update_in_turn(
    specs: list[tuple[str, Any]], steps: list[Any]
) -> None:
    many, each, one = _declared(specs), _declared(specs), _declared(specs)
    tags_many, tags_each, tags_one = list(many), list(each), list(one)
    for scan, (moves, forcing, batch) in enumerate(steps):
        for db, tags in ((many, tags_many), (each, tags_each), (one, tags_one)):
            _process_side(db, tags, specs, float(scan + 1), moves, forcing)
        many.update_many([(tags_many[k], value) for k, value in batch])
        each.update_each(tuple(tags_each[k] for k, _ in batch), [value for _, value in batch])
        for k, value in batch:
            one.update(tags_one[k], value)
        assert state(many) == state(one)
        assert state(each) == state(one)


OPERATIONS = ("update", "write", "force", "unforce", "set_quality", "add_many")


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(DTYPES), initials), min_size=4, max_size=4),
    st.lists(
        st.tuples(st.sampled_from(OPERATIONS), st.integers(0, 3), values | deltas), max_size=24
    ),
)
def test_a_tags_number_is_its_value_as_a_float_however_it_changed(
    specs: list[tuple[str, Any]], operations: list[tuple[str, int, Any]]
) -> None:
    """Declared with any initial value, then changed every way there is (a write or a force
    of a value its type refuses, an increment of a value beyond a float's range: refused
    as the plain rule refuses them, nothing changed)."""
    db = _declared(specs, Access.ENGINEER)
    tags = list(db)
    state(db)
    for scan, (operation, k, value) in enumerate(operations):
        db.set_scan_time(float(scan))
        tag = tags[k]
        try:
            if operation == "update":
                db.update(tag, value)
            elif operation == "write":
                db.write(tag.name, value, Access.ENGINEER)
            elif operation == "force":
                db.force(tag.name, value)
            elif operation == "unforce":
                db.unforce(tag.name)
            elif operation == "set_quality":
                db.set_quality(tag, Quality.BAD, Reason.STALE)
            else:
                db.add_many([(tag, value if isinstance(value, int | float) else 1.0)])
        except (OperatorError, TypeError, ValueError, OverflowError):
            pass
        state(db)


def plain_as_float(value: Any, default: float) -> float:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return default


@settings(max_examples=400, deadline=None)
@given(st.sampled_from(DTYPES), values, st.floats(allow_nan=False) | st.just(-1.0))
def test_a_tags_value_as_a_float_is_the_plain_rule(dtype: str, value: Any, default: float) -> None:
    db = TagDB()
    tag = db.add(TagSpec("t", dtype=dtype))  # type: ignore[arg-type]
    tag.value = value  # any value a tag may hold, coerced or not
    try:
        expected: float | type[OverflowError] = plain_as_float(value, default)
    except OverflowError:  # an int beyond the double range
        expected = OverflowError
    try:
        got: float | type[OverflowError] = tag.as_float(default)
    except OverflowError:
        got = OverflowError
    assert repr(got) == repr(expected)
    if isinstance(got, float) and not math.isnan(got):
        assert type(got) is float


@settings(max_examples=400, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(DTYPES), initials), min_size=4, max_size=4),
    st.lists(
        st.tuples(
            st.lists(process, max_size=4),
            st.lists(st.tuples(st.integers(0, 3), st.booleans()), max_size=2),
            st.lists(st.tuples(st.integers(0, 3), deltas), max_size=6),  # the increments
        ),
        max_size=8,
    ),
)
def test_increments_are_each_update_of_the_value_plus_its_delta_in_turn(
    specs: list[tuple[str, Any]], steps: list[Any]
) -> None:
    many, each, one = _declared(specs), _declared(specs), _declared(specs)
    tags_many, tags_each, tags_one = list(many), list(each), list(one)
    for scan, (moves, forcing, increments) in enumerate(steps):
        for db, tags in ((many, tags_many), (each, tags_each), (one, tags_one)):
            _process_side(db, tags, specs, float(scan + 1), moves, forcing)
        pairs_many = [(tags_many[k], delta) for k, delta in increments]
        pairs_one = [(tags_one[k], delta) for k, delta in increments]
        outcome_many = _outcome(many.add_many, pairs_many)
        outcome_each = _outcome(
            each.add_each,
            tuple(tags_each[k] for k, _ in increments),
            tuple(delta for _, delta in increments),
        )
        outcome_one = _outcome(_one_by_one, one, pairs_one)
        assert outcome_many == outcome_one
        assert outcome_each == outcome_one
        assert state(many) == state(one)
        assert state(each) == state(one)


def _declared(specs: list[tuple[str, Any]], access: Access = Access.READ_ONLY) -> TagDB:
    db = TagDB()
    for k, (dtype, initial) in enumerate(specs):
        try:
            db.add(TagSpec(f"t{k}", dtype=dtype, initial=initial, access=access))  # type: ignore[arg-type]
        except (TypeError, ValueError):
            db.add(TagSpec(f"t{k}", dtype=dtype, access=access))  # type: ignore[arg-type]
    return db


def _process_side(
    db: TagDB,
    tags: list[Any],
    specs: list[tuple[str, Any]],
    scan_t: float,
    moves: list[Any],
    forcing: list[tuple[int, bool]],
) -> None:
    """Before a batch: the process side moves some tags, someone forces or unforces some."""
    db.set_scan_time(scan_t)
    for k, value, quality, reason, source_t in moves:
        db.update(tags[k], value, quality, reason, source_t)
    for k, force in forcing:
        if force and not tags[k].forced:
            db.force(f"t{k}", FORCED[specs[k][0]])
        elif not force:
            db.unforce(f"t{k}")


def _one_by_one(db: TagDB, pairs: list[tuple[Any, float]]) -> None:
    for tag, delta in pairs:
        db.update(tag, tag.as_float() + delta)


def _outcome(run: Any, *args: Any) -> str:
    """'done', or 'overflow' for an int beyond the double range (as the plain rule raises)."""
    try:
        run(*args)
    except OverflowError:
        return "overflow"
    return "done"
