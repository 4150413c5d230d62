"""The scan copies its changes; the writers filter them later, on their own threads
(issue 30): a filter applied to the copies after the tags moved on stores exactly what it
stores at once, and neither the historian nor the InfluxDB writer filters on the scan."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.publish.changes import ChangeBatch, ChangeFeed, ChangeFilter, ChangeSnapshots
from supervisor.publish.historian import Historian
from supervisor.tags import TagDB, TagSpec
from supervisor.tags.spec import HistorySettings

HISTORIES = (
    HistorySettings(),
    HistorySettings(deadband=0.5),
    HistorySettings(min_interval_s=0.03),
    HistorySettings(deadband=0.5, min_interval_s=0.02),
    HistorySettings(enabled=False),
)
# One scan: (tag, value or None for BAD, an explicit source time or not) changes.
scan_changes = st.lists(
    st.tuples(
        st.integers(0, len(HISTORIES)), st.one_of(st.none(), st.integers(0, 4)), st.booleans()
    ),
    max_size=6,
)


def _db() -> TagDB:
    db = TagDB()
    for k, history in enumerate(HISTORIES):
        db.add(TagSpec(f"t{k}", unit="V", history=history))
    db.add(TagSpec("state", dtype="str", initial=""))
    return db


def _change(db: TagDB, clock: VirtualClock, k: int, v: int | None, stamped: bool) -> None:
    tag = db["state"] if k == len(HISTORIES) else db[f"t{k}"]
    source_t = clock.now() - 0.005 if stamped else None
    if v is None:
        db.update(tag, tag.value, Quality.BAD, Reason.NOT_CONNECTED, source_t)
    else:
        db.update(tag, str(v) if tag.spec.dtype == "str" else float(v), source_t=source_t)


@settings(max_examples=300, deadline=None)
@given(st.lists(scan_changes, min_size=1, max_size=40), st.integers(1, 40))
def test_a_filter_applied_to_the_copies_later_stores_what_it_stores_at_once(
    plan: list[list[tuple[int, int | None, bool]]], lag: int
) -> None:
    db, clock = _db(), VirtualClock(wall_epoch_s=1_767_254_400.0)
    at_once, copies = ChangeFeed(db, clock), ChangeSnapshots(db, clock)
    later = ChangeFilter()
    queued: list[ChangeBatch] = []
    stored_at_once, stored_later = [], []
    for n, changes in enumerate(plan, 1):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for k, v, stamped in changes:
            _change(db, clock, k, v, stamped)
        stored_at_once += at_once.take()
        queued += copies.batches()
        if n % lag == 0:  # the writer's turn comes every ``lag`` scans
            for batch in queued:
                stored_later += later.apply(batch)
            queued.clear()
    for batch in queued:
        stored_later += later.apply(batch)
    assert stored_later == stored_at_once


def test_a_held_back_value_that_went_back_to_the_stored_one_is_not_stored() -> None:
    db, clock = _db(), VirtualClock()
    feed = ChangeFeed(db, clock)
    tag = db["t2"]  # a minimum interval of 0.03 s
    feed.take()
    db.set_scan_time(0.0)
    db.update(tag, 1.0, source_t=0.0)
    assert [s.value for s in feed.take() if s.name == "t2"] == [1.0]
    db.update(tag, 2.0, source_t=0.01)  # held back by the interval
    clock.advance(0.01)
    assert feed.take() == []
    db.update(tag, 1.0, source_t=0.02)  # back to what is stored
    clock.advance(0.01)
    assert feed.take() == []
    clock.advance(0.1)
    assert feed.take() == [], "2.0 is no longer the tag's value: never stored"


def test_a_held_back_value_is_stored_at_the_time_it_was_acquired() -> None:
    db, clock = _db(), VirtualClock()
    feed = ChangeFeed(db, clock)
    tag = db["t2"]
    feed.take()
    db.update(tag, 1.0, source_t=0.0)
    feed.take()
    clock.advance(0.01)
    db.update(tag, 2.0, source_t=0.01)  # held back
    feed.take()
    clock.advance(0.01)
    db.stamp(tag, 0.02)  # the source says it still holds
    clock.advance(0.1)
    [sample] = feed.take()
    assert (sample.value, sample.t) == (2.0, 0.01)


def test_the_historian_filters_on_its_writers_thread_never_on_the_scans(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    db, clock = _db(), VirtualClock()
    filtered_on: set[int] = set()
    apply = ChangeFilter.apply

    def spying(self: ChangeFilter, batch: ChangeBatch) -> list:  # type: ignore[type-arg]
        filtered_on.add(threading.get_ident())
        return apply(self, batch)

    monkeypatch.setattr(ChangeFilter, "apply", spying)
    historian = Historian(db, clock, tmp_path / "history.sqlite")
    historian.open()
    try:
        for k in range(20):
            clock.advance(0.01)
            db.set_scan_time(clock.now())
            db.update(db["t0"], float(k))
            historian.on_scan(db, clock.now())
        assert historian.writer.flush()
        stored = historian.query.count("t0", 0.0, clock.wall() + 1.0)
    finally:
        historian.close()
    assert stored == 20
    assert filtered_on and threading.get_ident() not in filtered_on
    assert historian.writer.rows_written >= 20  # every value of t0, and the declarations
