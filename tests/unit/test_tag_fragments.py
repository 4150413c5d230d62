"""Snapshots from each tag's kept JSON text (``supervisor.hmi.server.TagFragments``,
docs/adr/0019-http-off-the-scan.md "Kept texts"): whatever happened to the tags between
two snapshots, each is exactly the text of ``json_dumps`` of the same ``tag_json`` list
(or object by name); only the tags whose version moved are encoded again, a source time
that moved without a new version is shown as it is now, and a snapshot with few changes
is built without giving the event loop a turn."""

from __future__ import annotations

import asyncio
import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.hmi.server import SLICE_TAGS, TagFragments, TagSnapshots, json_dumps, tag_json
from supervisor.tags import Access, TagDB, TagSpec


def _list_text(db: TagDB, clock: VirtualClock, names: list[str] | None = None) -> str:
    tags = list(db) if names is None else [db[n] for n in names]
    return json_dumps([tag_json(t, clock) for t in tags])


def _map_text(db: TagDB, clock: VirtualClock, names: list[str] | None = None) -> str:
    tags = list(db) if names is None else [db[n] for n in names]
    by_name: dict[str, Any] = {}
    for t in tags:
        entry = tag_json(t, clock)
        del entry["name"]
        by_name[t.name] = entry
    return json_dumps(by_name)


def _expected(db: TagDB, clock: VirtualClock, as_map: bool, names: list[str] | None) -> str:
    return _map_text(db, clock, names) if as_map else _list_text(db, clock, names)


# --- any history of the tags ----------------------------------------------------------------
values = st.one_of(
    st.floats(),  # NaN and ±inf included: sent as null, quality BAD
    st.sampled_from([0.0, -0.0, 1e16, 1e-7, 5e-324, 1.7976931348623157e308, 0.1]),
    st.integers(min_value=-(2**80), max_value=2**80),
    st.booleans(),
    st.none(),
    st.text(),  # quotes, backslashes, control characters, unicode, lone surrogates
    st.sampled_from(['a "quoted" text, with ü', "\\", "\n\t", "°C", "\u2028", "\ud800"]),
)
operation = st.one_of(
    st.tuples(
        st.just("update"),
        st.integers(0, 99),
        values,
        st.sampled_from(list(Quality)),
        st.sampled_from(list(Reason)),
    ),
    st.tuples(st.just("poll"), st.integers(0, 99)),  # the source time moves, no new version
    st.tuples(st.just("force"), st.integers(0, 99), st.floats(-10, 10)),
    st.tuples(st.just("unforce"), st.integers(0, 99)),
    st.tuples(st.just("time"), st.floats(0.001, 100.0)),
    st.tuples(st.just("add"), st.sampled_from(["float", "int", "bool", "str"]), st.text()),
    st.tuples(
        st.just("snapshot"),
        st.booleans(),  # as_map
        st.one_of(st.none(), st.lists(st.integers(0, 99), max_size=8)),  # all, or some
    ),
)
UNITS = ["V", "", "°C", 'a "unit"', "Ω\\"]


def _start(clock: VirtualClock) -> TagDB:
    db = TagDB()
    for k, dtype in enumerate(["float", "float", "int", "bool", "str", "float"]):
        db.add(TagSpec(f"t{k}", dtype=dtype, unit=UNITS[k % len(UNITS)], access=Access(k % 3)))
    return db


def _run(ops: list[tuple[Any, ...]]) -> None:
    clock = VirtualClock()
    db = _start(clock)
    snapshots = TagSnapshots(db, clock)
    fragments = {as_map: TagFragments(db, clock, as_map) for as_map in (False, True)}
    tags = list(db)
    images: dict[bool, tuple[int, str]] = {}  # as_map → the last full image's version, text
    for op in [*ops, ("snapshot", False, None), ("snapshot", True, None)]:
        kind = op[0]
        if kind == "update":
            tag = tags[op[1] % len(tags)]
            db.update(tag, op[2], op[3], op[4])
        elif kind == "poll":
            db.update(tags[op[1] % len(tags)], tags[op[1] % len(tags)].value)
        elif kind == "force":
            tag = tags[op[1] % len(tags)]
            if tag.spec.dtype == "float":
                db.force(tag.name, op[2])
        elif kind == "unforce":
            db.unforce(tags[op[1] % len(tags)].name)
        elif kind == "time":
            clock.advance(op[1])
            db.set_scan_time(clock.now())
        elif kind == "add":
            spec = TagSpec(f"added{len(tags)}", dtype=op[1], unit=op[2])
            tags.append(db.add(spec))
        else:
            as_map, picks = op[1], op[2]
            # Each tag once, as in a delta (an object has each name once).
            names = (
                None
                if picks is None
                else list(dict.fromkeys(tags[k % len(tags)].name for k in picks))
            )
            expected = _expected(db, clock, as_map, names)
            if names is None:
                version, text = asyncio.run(snapshots.image(as_map))
                assert version == db.version
                # One image per version (shared, ADR 0019): at the version of the last one,
                # it is that one, though a source time moved since without a new version.
                last = images.get(as_map)
                if last is not None and last[0] == version:
                    expected = last[1]
                images[as_map] = (version, expected)
            else:
                text = asyncio.run(fragments[as_map].encode(db[n] for n in names))
            assert text == expected


@settings(max_examples=300, deadline=None)
@given(st.lists(operation, max_size=40))
def test_every_snapshot_is_the_text_of_json_dumps_whatever_happened_before(
    ops: list[tuple[Any, ...]],
) -> None:
    _run(ops)


def test_the_edge_cases_of_values_are_written_as_json_dumps_writes_them() -> None:
    ops: list[tuple[Any, ...]] = [("snapshot", False, None), ("snapshot", True, None)]
    for k, value in enumerate([math.nan, math.inf, -math.inf, -0.0, 2**70, "\ud800", None]):
        ops += [
            ("update", k, value, Quality.GOOD, Reason.NONE),
            ("time", 0.01),
            ("poll", k + 1),
            ("snapshot", False, None),
            ("snapshot", True, [k, k + 1, k]),
        ]
    ops += [("force", 0, 2.5), ("snapshot", False, None), ("unforce", 0), ("snapshot", True, None)]
    _run(ops)


# --- what is encoded again ------------------------------------------------------------------
def _db(n: int) -> TagDB:
    db = TagDB()
    for k in range(n):
        db.update(db.add(TagSpec(f"t{k:04d}", unit="V")), k * 0.5)
    return db


def test_a_snapshot_encodes_again_only_the_tags_whose_version_moved(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(100)
    snapshots = TagSnapshots(db, virtual_clock)
    fragments = snapshots.fragments[False]
    asyncio.run(snapshots.image())
    assert fragments.encoded == 100
    for k in range(0, 100, 10):
        db.update(db[f"t{k:04d}"], -1.0)
    _, text = asyncio.run(snapshots.image())
    assert fragments.encoded == 110
    assert text == _list_text(db, virtual_clock)


def test_a_source_time_that_moved_without_a_new_version_is_shown_as_it_is_now(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(5)
    fragments = TagFragments(db, virtual_clock, as_map=False)
    asyncio.run(fragments.encode(db))
    virtual_clock.advance(2.5)
    db.set_scan_time(virtual_clock.now())
    version = db.version
    for t in db:  # a poll that found the same values: no new version, a new source time
        db.update(t, t.value, source_t=db.scan_t)
    assert db.version == version
    text = asyncio.run(fragments.encode(db))
    assert text == _list_text(db, virtual_clock)
    assert fragments.encoded == 5
    assert f'"source_time": {virtual_clock.to_wall(2.5)!r}' in text


def test_a_snapshot_with_at_most_a_slice_of_changes_is_built_without_a_turn_of_the_loop(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(3 * SLICE_TAGS)
    snapshots = TagSnapshots(db, virtual_clock)

    async def changes_then_image(changed: int) -> str:
        for t in list(db)[:changed]:
            db.update(t, t.as_float() + 1.0)
        coro = snapshots.image()
        try:
            coro.send(None)  # runs it until it would wait for the loop
        except StopIteration as done:
            _, text = done.value
            return str(text)
        coro.close()
        raise AssertionError(f"the image waited for the loop with {changed} tags changed")

    async def scenario() -> None:
        await snapshots.image()  # the first image encodes everything, in slices
        for changed in (0, 1, SLICE_TAGS // 2, SLICE_TAGS):
            assert await changes_then_image(changed) == _list_text(db, virtual_clock)

    asyncio.run(scenario())


def test_an_image_of_many_changes_is_the_tags_at_its_version_though_scans_run_between_slices(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(3 * SLICE_TAGS)
    snapshots = TagSnapshots(db, virtual_clock)

    async def scenario() -> None:
        await snapshots.image()
        for t in db:  # every tag changed: more than one slice to encode again
            db.update(t, t.as_float() + 1.0)
        expected = _list_text(db, virtual_clock)
        version_before = db.version
        task = asyncio.get_running_loop().create_task(snapshots.image())
        for scan in range(10):  # a "scan" in every yield of the encoder
            await asyncio.sleep(0)
            for t in db:
                db.update(t, float(-scan), Quality.UNCERTAIN, Reason.STALE)
        version, text = await task
        assert (version, text) == (version_before, expected)
        assert db.version > version_before
        # What was encoded at the old version is not kept for the tags that moved since.
        assert (await snapshots.image())[1] == _list_text(db, virtual_clock)

    asyncio.run(scenario())


def test_a_tag_declared_after_the_first_snapshot_is_in_the_next_one(
    virtual_clock: VirtualClock,
) -> None:
    db = _db(3)
    snapshots = TagSnapshots(db, virtual_clock)
    asyncio.run(snapshots.image(as_map=True))
    db.update(db.add(TagSpec("hmi.ws_clients", dtype="int")), 2)
    _, text = asyncio.run(snapshots.image(as_map=True))
    assert text == _map_text(db, virtual_clock)
