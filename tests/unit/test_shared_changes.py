"""The historian and the InfluxDB writer read one change feed (issue 13): each reader gets
exactly what a feed of its own would have given it, however the readers interleave."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.publish.changes import ChangeFeed, SharedChanges
from supervisor.tags import TagDB, TagSpec
from supervisor.tags.spec import HistorySettings

TAGS = ("a", "b", "c")


def _db() -> TagDB:
    db = TagDB()
    db.add(TagSpec("a", unit="V"))
    db.add(TagSpec("b", unit="A", history=HistorySettings(deadband=0.5)))
    db.add(TagSpec("c", dtype="str", initial=""))
    return db


changes = st.lists(st.tuples(st.sampled_from(TAGS), st.integers(0, 5)), max_size=4)
# One scan: tag changes, then the readers' takes (0: the historian, 1: InfluxDB): both take
# at scan end in either order, and one may take again (a stop).
scans = st.lists(
    st.tuples(
        changes,
        st.tuples(st.permutations((0, 1)), st.lists(st.sampled_from((0, 1)), max_size=2)).map(
            lambda t: [*t[0], *t[1]]
        ),
    ),
    min_size=1,
    max_size=30,
)
# Any takes at all: a reader may skip scans.
any_takes = st.lists(
    st.tuples(changes, st.lists(st.sampled_from((0, 1)), max_size=3)), min_size=1, max_size=30
)


@settings(max_examples=200, deadline=None)
@given(scans)
def test_each_reader_gets_what_a_feed_of_its_own_gives_when_both_take_every_scan(
    plan: list[tuple[list[tuple[str, int]], list[int]]],
) -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    readers = [shared.reader(), shared.reader()]
    own = [ChangeFeed(db, clock), ChangeFeed(db, clock)]
    got: list[list[object]] = [[], []]
    expected: list[list[object]] = [[], []]
    for k, (changes, takes) in enumerate(plan):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for name, v in changes:
            db.update(db[name], str(v) if name == "c" else float(v) + k * 0.1)
        for who in takes:
            got[who] += [(s.name, s.value, s.t) for s in readers[who].take()]
            expected[who] += [(s.name, s.value, s.t) for s in own[who].take()]
    for who in (0, 1):  # a last take each: nothing is left behind for anyone
        got[who] += [(s.name, s.value, s.t) for s in readers[who].take()]
        expected[who] += [(s.name, s.value, s.t) for s in own[who].take()]
    assert got == expected
    assert len(shared._batches) <= 1


@settings(max_examples=200, deadline=None)
@given(any_takes)
def test_a_reader_that_skips_scans_still_gets_every_stored_sample_once_in_order(
    plan: list[tuple[list[tuple[str, int]], list[int]]],
) -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    readers = [shared.reader(), shared.reader()]
    stored: list[object] = []
    take = shared._feed.take

    def recording() -> list[object]:
        batch = take()
        stored.extend((s.name, s.value, s.t) for s in batch)
        return batch  # type: ignore[return-value]

    shared._feed.take = recording  # type: ignore[method-assign,assignment]
    got: list[list[object]] = [[], []]
    for k, (changed, takes) in enumerate(plan):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for name, v in changed:
            db.update(db[name], str(v) if name == "c" else float(v) + k * 0.1)
        for who in takes:
            got[who] += [(s.name, s.value, s.t) for s in readers[who].take()]
    # A reader behind the others gets the batches it missed first, the newest changes at
    # its next take: two more takes each and both have everything.
    for who in (0, 1, 0, 1):
        got[who] += [(s.name, s.value, s.t) for s in readers[who].take()]
    assert got[0] == stored and got[1] == stored


def test_the_feed_is_filtered_once_per_scan_for_both_readers() -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    historian, influx = shared.reader(), shared.reader()
    taken: list[int] = []
    take = shared._feed.take
    shared._feed.take = lambda: taken.append(1) or take()  # type: ignore[method-assign,func-returns-value]
    for k in range(10):
        db.set_scan_time(float(k))
        db.update(db["a"], float(k))
        assert historian.take() is influx.take()  # the same batch, not a copy
    assert len(taken) == 10


def test_a_closed_reader_holds_no_batches_back() -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    historian, influx = shared.reader(), shared.reader()
    influx.close()
    for k in range(100):
        db.update(db["a"], float(k))
        historian.take()
    assert len(shared._batches) <= 1
