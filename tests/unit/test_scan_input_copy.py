"""Copying inputs skips a sample already copied, or only stamps its new time when its driver
stamped the same sample again, and only stamps the connection tags that did not change
(docs/adr/0018-scan-performance.md): the tags
come out exactly as if every input were updated from its driver's image at every scan, as
the scan did before (value, quality, reason, source and server times, versions, and the
order of changes), whatever the drivers, the clock, forcing and other writers do between
scans."""

from __future__ import annotations

import math
from collections.abc import Mapping

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.quality import Quality, Reason
from supervisor.scan import InputBinding, ScanEngine
from supervisor.tags import Scaling, Tag, TagDB, TagSpec


class ImageDriver:
    """A driver whose image is whatever the test puts there (same Sample objects kept)."""

    poll_period_s = 0.1

    def __init__(self, name: str) -> None:
        self.name = name
        self.samples: dict[str, Sample] = {}
        self.connected = True
        self.failures = 0

    def points(self) -> Mapping[str, PointInfo]:
        return {}

    def image(self) -> Mapping[str, Sample]:
        return self.samples

    def write(self, point: str, value: Value) -> None:
        raise KeyError(point)

    async def poll(self) -> None:
        return None

    async def safe_state(self) -> str | None:
        return None

    async def close(self) -> None:
        return None


def copy_every_input(engine: ScanEngine, now: float) -> None:
    """The input copy as the scan did it before: one ``TagDB.update`` per input per scan."""
    db = engine.db
    for d, ctag, ftag in engine._conn_tags:
        db.update(ctag, d.connected)
        db.update(ftag, getattr(d, "failures", 0))
    for b in engine.inputs:
        s = b.driver.image().get(b.point)
        if s is None:
            db.update(b.tag, None, Quality.BAD, Reason.NOT_CONNECTED)
            continue
        value: Value | None = s.value
        quality, reason = s.quality, s.reason
        if b.scaling is not None and isinstance(value, int | float) and value is not True:
            value = b.scaling.to_eu(float(value))
        if b.threshold is not None and isinstance(value, int | float):
            value = value >= b.threshold
        if (
            b.stale_after_s is not None
            and quality is not Quality.BAD
            and now - s.t > b.stale_after_s
        ):
            quality, reason = Quality.BAD, Reason.STALE
        db.update(b.tag, value, quality, reason, s.t)


POINTS = ("ai0", "ai1", "ai2", "di0")

sample_value = st.sampled_from([0.0, 1.5, 2.0, math.nan, math.inf, 3, True, None])
# Between two scans, one of: (what, point number, value, quality, dt)
event = st.tuples(
    st.sampled_from(
        [
            "scan",
            "scan",
            "new",
            "same",
            "again",
            "drop",
            "force",
            "unforce",
            "write",
            "touch",
            "link",
        ]
    ),
    st.integers(0, len(POINTS) - 1),
    sample_value,
    st.sampled_from([Quality.GOOD, Quality.UNCERTAIN, Quality.BAD]),
    st.sampled_from([0.0, 0.05, 0.1, 0.4, 1.0]),
)


def build() -> tuple[VirtualClock, TagDB, ImageDriver, ScanEngine]:
    clock = VirtualClock()
    db = TagDB()
    drv = ImageDriver("dev")
    specs = [
        InputBinding(db.add(TagSpec("a", unit="V")), drv, "ai0", None, 0.5),
        InputBinding(db.add(TagSpec("b", unit="A")), drv, "ai1", Scaling(10.0, 0.5), None),
        InputBinding(db.add(TagSpec("c", dtype="int")), drv, "ai2", None, 0.3),
        InputBinding(db.add(TagSpec("d", dtype="bool")), drv, "di0", None, 0.5, 1.0),
    ]
    engine = ScanEngine(clock, db, 0.1, [drv], specs)
    return clock, db, drv, engine


def state(db: TagDB) -> list[tuple[object, ...]]:
    def one(t: Tag) -> tuple[object, ...]:
        v = "NaN" if isinstance(t.value, float) and math.isnan(t.value) else t.value
        return (t.name, v, t.quality, t.reason, t.source_t, t.server_t, t.version, t.forced)

    return [one(t) for t in db] + [("changes", [t.name for t in db.changed_since(0)])]


def play(events: list[tuple[str, int, Value | None, Quality, float]], reference: bool) -> list:
    clock, db, drv, engine = build()
    copy = copy_every_input if reference else ScanEngine._copy_inputs
    seen = []
    for what, k, value, quality, dt in events:
        point = POINTS[k]
        tag = engine.inputs[k].tag
        if what == "scan":  # the input step of a scan (the rest times itself: not compared)
            clock.advance(dt)
            db.set_scan_time(clock.now())
            copy(engine, clock.now())
            seen.append(state(db))
        elif what == "new":
            reason = Reason.NONE if quality is Quality.GOOD else Reason.DEVICE_ERROR
            drv.samples[point] = Sample(value, quality, reason, clock.now())
        elif what == "same" and point in drv.samples:
            old = drv.samples[point]  # an equal sample, but another object
            drv.samples[point] = Sample(old.value, old.quality, old.reason, old.t)
        elif what == "again" and point in drv.samples:
            # A poll that read what the sample says: the same object, stamped again in
            # place with the poll's time (devices/chadeche/driver.py::ChadecheDriver.poll_now).
            drv.samples[point].t = clock.now()
        elif what == "link":  # the device lost or back, a failed poll counted
            drv.connected = not drv.connected
            drv.failures += 0 if drv.connected else 1
        elif what == "drop":
            drv.samples.pop(point, None)
        elif what == "force" and value is not None and not isinstance(value, float | bool):
            db.force(tag.name, value if tag.spec.dtype != "bool" else bool(value))
        elif what == "unforce":
            db.unforce(tag.name)
        elif what == "write":
            db.set_quality(tag, Quality.UNCERTAIN, Reason.LAST_KNOWN)
        elif what == "touch":  # another writer, changing nothing but the source time
            clock.advance(dt)
            db.set_scan_time(clock.now())
            db.update(tag, tag.value, tag.quality, tag.reason)
    return seen


@settings(max_examples=400, deadline=None)
@given(st.lists(event, max_size=50))
def test_the_tags_are_those_of_a_copy_of_every_input_at_every_scan(
    events: list[tuple[str, int, Value | None, Quality, float]],
) -> None:
    assert play(events, reference=False) == play(events, reference=True)


def test_a_sample_copied_once_is_not_a_change_at_the_next_scans() -> None:
    clock, db, drv, engine = build()
    drv.samples["ai0"] = Sample(1.0, t=0.0)
    engine.scan_once()
    version = db["a"].version
    for _ in range(3):
        clock.advance(0.1)
        engine.scan_once()
    assert db["a"].version == version and db["a"].good


def test_a_sample_held_past_its_stale_limit_turns_bad_stale() -> None:
    clock, db, drv, engine = build()
    drv.samples["ai0"] = Sample(1.0, t=0.0)
    engine.scan_once()
    clock.advance(0.6)
    engine.scan_once()
    assert (db["a"].quality, db["a"].reason) == (Quality.BAD, Reason.STALE)


def test_an_unforced_input_takes_the_process_value_at_the_next_scan() -> None:
    clock, db, drv, engine = build()
    drv.samples["ai0"] = Sample(1.0, t=0.0)
    engine.scan_once()
    db.force("a", 5.0)
    engine.scan_once()
    assert db["a"].value == 5.0
    db.unforce("a")
    clock.advance(0.1)
    engine.scan_once()
    assert db["a"].value == 1.0 and db["a"].good
