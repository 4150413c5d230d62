"""What the historian and the InfluxDB writer store: every change worth storing, by each
tag's history settings, in order, with its acquisition time."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.publish.changes import ChangeBatch, ChangeFeed, ChangeFilter, Sample
from supervisor.tags import TagDB, TagSpec
from supervisor.tags.spec import HistorySettings


def setup(history: HistorySettings) -> tuple[TagDB, VirtualClock, ChangeFeed]:
    db, clock = TagDB(), VirtualClock()
    db.add(TagSpec("ch0.voltage", unit="V", history=history))
    db.add(TagSpec("ch0.state", dtype="str", initial=""))
    feed = ChangeFeed(db, clock)
    feed.take()  # the declarations
    return db, clock, feed


def put(db: TagDB, clock: VirtualClock, t: float, value: float | None, **kw: object) -> None:
    at(clock, t)
    db.set_scan_time(t)
    db.update(db["ch0.voltage"], value, source_t=t, **kw)  # type: ignore[arg-type]


def at(clock: VirtualClock, t: float) -> None:
    clock.advance(t - clock.now())


def values(feed: ChangeFeed) -> list[object]:
    return [s.value for s in feed.take()]


def test_a_change_within_the_deadband_is_not_stored_a_larger_one_is() -> None:
    db, clock, feed = setup(HistorySettings(deadband=0.01))
    put(db, clock, 1.0, 1.200)
    assert values(feed) == [1.200]
    put(db, clock, 2.0, 1.205)
    assert values(feed) == []
    put(db, clock, 3.0, 1.215)
    assert values(feed) == [1.215]


def test_a_change_of_quality_is_always_stored_and_a_bad_value_is_a_gap() -> None:
    db, clock, feed = setup(HistorySettings(deadband=1.0))
    put(db, clock, 1.0, 1.2)
    feed.take()
    put(db, clock, 2.0, 1.2, quality=Quality.BAD, reason=Reason.NOT_CONNECTED)
    [sample] = feed.take()
    assert sample.value is None and sample.quality is Quality.BAD


def test_a_change_held_back_by_the_minimum_interval_is_stored_once_it_has_passed() -> None:
    db, clock, feed = setup(HistorySettings(min_interval_s=10.0))
    put(db, clock, 0.0, 1.0)
    assert values(feed) == [1.0]
    put(db, clock, 1.0, 2.0)  # a step, then nothing changes
    assert values(feed) == []
    at(clock, 5.0)
    assert values(feed) == []
    at(clock, 10.0)
    [sample] = feed.take()
    assert sample.value == 2.0 and sample.t == 1.0, "its own acquisition time"
    at(clock, 30.0)
    assert values(feed) == [], "stored once"


def test_text_tags_and_disabled_history() -> None:
    db, clock, feed = setup(HistorySettings(enabled=False))
    put(db, clock, 1.0, 1.0)
    db.update(db["ch0.state"], "running")
    assert [(s.name, s.value) for s in feed.take()] == [("ch0.state", "running")]


class PlainFilter(ChangeFilter):
    """The rule applied one change at a time (``_keep`` for every tag): what the inlined
    path of ``ChangeFilter.apply`` must give."""

    def apply(self, batch: ChangeBatch) -> list[Sample]:
        if batch.first:
            self._last.clear()
            self._pending.clear()
        out: list[Sample] = []
        if self._pending:
            in_batch = {c[0].index for c in batch.changes}
            for index, change in list(self._pending.items()):
                if batch.now - self._last[index][2] >= change[0].spec.history.min_interval_s:
                    del self._pending[index]
                    if index not in in_batch:
                        sample = self._keep(change, batch.wall_offset, batch.now)
                        if sample is not None:
                            out.append(sample)
        for change in batch.changes:
            sample = self._keep(change, batch.wall_offset)
            if sample is not None:
                out.append(sample)
        return out


HISTORIES = (
    HistorySettings(),
    HistorySettings(deadband=0.5),
    HistorySettings(min_interval_s=0.03),
    HistorySettings(enabled=False),
)
# One scan: (tag, value or None for BAD, an explicit source time or not) changes.
scan_changes = st.lists(
    st.tuples(st.integers(0, 4), st.one_of(st.none(), st.integers(0, 4)), st.booleans()),
    max_size=6,
)


@settings(max_examples=300, deadline=None)
@given(st.lists(scan_changes, min_size=1, max_size=40))
def test_the_feed_stores_what_its_rule_applied_to_each_change_stores(
    plan: list[list[tuple[int, int | None, bool]]],
) -> None:
    db, clock = TagDB(), VirtualClock(wall_epoch_s=1_767_254_400.0)
    for k, history in enumerate(HISTORIES):
        db.add(TagSpec(f"t{k}", unit="V", history=history))
    db.add(TagSpec("state", dtype="str", initial=""))
    fast, plain = ChangeFeed(db, clock), ChangeFeed(db, clock)
    plain._filter = PlainFilter()
    for changes in plan:
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for k, v, stamped in changes:
            tag = db["state"] if k == 4 else db[f"t{k}"]
            source_t = clock.now() - 0.005 if stamped else None
            if v is None:
                db.update(tag, tag.value, Quality.BAD, Reason.NOT_CONNECTED, source_t)
            else:
                db.update(tag, str(v) if k == 4 else float(v), source_t=source_t)
        assert fast.take() == plain.take()
