"""The historian and the InfluxDB writer read one copy of each scan's changes (issues 13
and 30): each reader gets every batch once, in order, however the readers interleave, and
filtered by a filter of its own it stores what a feed of its own would have stored."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.publish.changes import ChangeBatch, ChangeFeed, ChangeFilter, SharedChanges
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
    filters = [ChangeFilter(), ChangeFilter()]
    own = [ChangeFeed(db, clock), ChangeFeed(db, clock)]
    got: list[list[object]] = [[], []]

    def take(who: int) -> list[object]:
        return [
            (s.name, s.value, s.t) for b in readers[who].batches() for s in filters[who].apply(b)
        ]

    expected: list[list[object]] = [[], []]
    for k, (changes, takes) in enumerate(plan):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for name, v in changes:
            db.update(db[name], str(v) if name == "c" else float(v) + k * 0.1)
        for who in takes:
            got[who] += take(who)
            expected[who] += [(s.name, s.value, s.t) for s in own[who].take()]
    for who in (0, 1):  # a last take each: nothing is left behind for anyone
        got[who] += take(who)
        expected[who] += [(s.name, s.value, s.t) for s in own[who].take()]
    assert got == expected
    assert len(shared._batches) <= 1


@settings(max_examples=200, deadline=None)
@given(any_takes)
def test_a_reader_that_skips_scans_still_gets_every_batch_once_in_order(
    plan: list[tuple[list[tuple[str, int]], list[int]]],
) -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    readers = [shared.reader(), shared.reader()]
    made: list[ChangeBatch] = []
    snapshot = shared._snapshots.snapshot

    def recording() -> ChangeBatch:
        made.append(snapshot())
        return made[-1]

    shared._snapshots.snapshot = recording  # type: ignore[method-assign]
    got: list[list[ChangeBatch]] = [[], []]
    for k, (changed, takes) in enumerate(plan):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for name, v in changed:
            db.update(db[name], str(v) if name == "c" else float(v) + k * 0.1)
        for who in takes:
            got[who] += readers[who].batches()
    # A reader behind the others gets the batches it missed first, the newest changes at
    # its next take.
    for who in (0, 1, 0, 1):
        got[who] += readers[who].batches()
    for who in (0, 1):  # the one that did not make the last batch gets it now
        if len(got[who]) < len(made):
            got[who] += readers[who].batches()
    assert [id(b) for b in got[0]] == [id(b) for b in made]
    assert [id(b) for b in got[1]] == [id(b) for b in made]


def test_the_changes_are_copied_once_per_scan_for_both_readers() -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    historian, influx = shared.reader(), shared.reader()
    taken: list[int] = []
    snapshot = shared._snapshots.snapshot
    shared._snapshots.snapshot = lambda: taken.append(1) or snapshot()  # type: ignore[method-assign,func-returns-value]
    for k in range(10):
        db.set_scan_time(float(k))
        db.update(db["a"], float(k))
        [mine] = historian.batches()
        [theirs] = influx.batches()
        assert mine is theirs  # the same batch, not a copy
    assert len(taken) == 10


def test_a_closed_reader_holds_no_batches_back() -> None:
    db, clock = _db(), VirtualClock()
    shared = SharedChanges(db, clock)
    historian, influx = shared.reader(), shared.reader()
    influx.close()
    for k in range(100):
        db.update(db["a"], float(k))
        historian.batches()
    assert len(shared._batches) <= 1
