"""The OPC UA feed reads the scan's one copy of its changes (issue 30): what the server
takes is what a copy of the changed tags made at each hand-over would give — one update
per tag, at its latest value, quality, reason and times — however the scans, hand-overs
and takes interleave; and the historian, InfluxDB and OPC UA share one copy a scan."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.publish.changes import SharedChanges
from supervisor.publish.opcua.feed import OpcUaFeed, Update
from supervisor.tags import TagDB, TagSpec

NAMES = ("a", "b", "c")


class PlainHandOver:
    """The plain path: at each hand-over, a copy of every tag changed since the last."""

    def __init__(self, db: TagDB) -> None:
        self.db = db
        self.version = db.version
        self.pending: dict[int, tuple[object, ...]] = {}

    def hand_over(self) -> None:
        for tag in self.db.changed_since(self.version):
            if tag.name in NAMES:
                self.pending[tag.index] = (
                    tag.index,
                    tag.name,
                    tag.value,
                    tag.quality,
                    tag.reason,
                    tag.source_t,
                    tag.server_t,
                )
        self.version = self.db.version

    def take(self) -> dict[int, tuple[object, ...]]:
        out, self.pending = self.pending, {}
        return out


# One scan: changes (tag, value or None for BAD), whether the scan hands over (its sampling
# grid point) and whether the server takes after it.
scans = st.lists(
    st.tuples(
        st.lists(st.tuples(st.sampled_from(NAMES), st.one_of(st.none(), st.integers(0, 3)))),
        st.booleans(),
        st.booleans(),
    ),
    min_size=1,
    max_size=30,
)


@settings(max_examples=300, deadline=None)
@given(scans)
def test_the_server_takes_what_a_copy_at_each_hand_over_gives(
    plan: list[tuple[list[tuple[str, int | None]], bool, bool]],
) -> None:
    db, clock = TagDB(), VirtualClock()
    for name in NAMES:
        db.add(TagSpec(name, unit="V"))
    shared = SharedChanges(db, clock)
    historian = shared.reader()  # another publisher that makes the scan's copy first
    feed = OpcUaFeed(db, shared.reader())
    feed.sampling_interval_s = 1.0
    plain = PlainHandOver(db)
    feed.start(db, lambda: None)
    grid = 0
    for k, (changes, hands_over, takes) in enumerate(plan):
        clock.advance(0.01)
        db.set_scan_time(clock.now())
        for name, v in changes:
            tag = db[name]
            if v is None:
                db.update(tag, tag.value, Quality.BAD, Reason.STALE, clock.now() - 0.005)
            else:
                db.update(tag, float(v) + k)
        historian.batches()
        grid += hands_over
        feed.on_scan(db, float(grid))  # the first scan and each new grid point: a hand-over
        if hands_over or k == 0:
            plain.hand_over()
        if takes:
            got: dict[int, Update] = {u.tag_index: u for u in feed.take() if u.name in NAMES}
            # The times are those of the tag's last change (an update that only moves
            # the source time is not a change: the plain copy would carry it, the copy
            # made at the change does not; OPC UA notifies changes, not re-stamps).
            assert {i: u[:5] for i, u in got.items()} == {i: u[:5] for i, u in plain.take().items()}


def test_the_historian_influx_and_opcua_share_one_copy_a_scan() -> None:
    db, clock = TagDB(), VirtualClock()
    db.add(TagSpec("a"))
    shared = SharedChanges(db, clock)
    readers = [shared.reader(), shared.reader()]
    feed = OpcUaFeed(db, shared.reader())
    feed.start(db, lambda: None)
    made = 0
    snapshot = shared._snapshots.snapshot

    def counting():  # type: ignore[no-untyped-def]
        nonlocal made
        made += 1
        return snapshot()

    shared._snapshots.snapshot = counting  # type: ignore[method-assign]
    for k in range(10):
        db.update(db["a"], float(k))
        for r in readers:
            r.batches()
        feed.on_scan(db, float(k))
        assert [u.value for u in feed.take() if u.name == "a"] == [float(k)]
    assert made == 10
