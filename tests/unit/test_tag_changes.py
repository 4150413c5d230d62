"""``TagDB.changed_since`` answers from per-tag versions (docs/adr/0018-scan-performance.md):
the same answer as a complete log of every change would give, for any version however far
back, and no memory that grows with the number of changes."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.core.quality import Quality, Reason
from supervisor.tags import Tag, TagDB, TagSpec

N_TAGS = 6

# One operation on the database: (kind, tag number, value, quality).
operation = st.tuples(
    st.sampled_from(["update", "update", "update", "force", "unforce", "add"]),
    st.integers(0, N_TAGS - 1),
    st.sampled_from([0.0, 1.0, 2.5]),
    st.sampled_from([Quality.GOOD, Quality.UNCERTAIN, Quality.BAD]),
)


def logged_changed_since(log: list[tuple[int, Tag]], version: int) -> list[Tag]:
    """What a complete, never-trimmed change log says changed after ``version``: each tag
    once, in the order of its last change."""
    last: dict[str, tuple[int, Tag]] = {}
    for v, tag in log:
        if v > version:
            last[tag.name] = (v, tag)
    return [tag for _, tag in sorted(last.values(), key=lambda e: e[0])]


def apply(db: TagDB, op: tuple[str, int, float, Quality], added: list[Tag]) -> Tag | None:
    """Run ``op``; the tag it may have changed."""
    kind, k, value, quality = op
    if kind == "add" or not added:
        if len(added) >= N_TAGS:
            return None
        tag = db.add(TagSpec(f"t{len(added)}", dtype="float"))
        added.append(tag)
        return tag
    tag = added[k % len(added)]
    if kind == "force":
        db.force(tag.name, value)
    elif kind == "unforce":
        db.unforce(tag.name)
    else:
        reason = Reason.NONE if quality is Quality.GOOD else Reason.STALE
        db.update(tag, value, quality, reason)
    return tag


@settings(max_examples=300, deadline=None)
@given(st.lists(operation, max_size=60), st.data())
def test_changed_since_is_what_a_complete_change_log_says(
    ops: list[tuple[str, int, float, Quality]], data: st.DataObject
) -> None:
    db = TagDB()
    added: list[Tag] = []
    log: list[tuple[int, Tag]] = []
    for op in ops:
        before = db.version
        tag = apply(db, op, added)
        if db.version != before:
            # Every operation here changes at most one tag, at most once.
            assert tag is not None and db.version == before + 1 == tag.version
            log.append((db.version, tag))
    version = data.draw(st.integers(0, db.version + 1), label="since version")
    assert db.changed_since(version) == logged_changed_since(log, version)


def test_a_reader_any_number_of_changes_behind_gets_exactly_the_tags_changed_since() -> None:
    db = TagDB()
    busy, quiet = db.add(TagSpec("busy")), db.add(TagSpec("quiet"))
    db.update(quiet, 1.0)
    seen = db.version
    for k in range(100_000):  # more than any bounded log would have kept
        db.update(busy, float(k))
    assert db.changed_since(seen) == [busy]
    db.update(quiet, 2.0)
    assert db.changed_since(seen) == [busy, quiet]


def test_changes_keep_one_entry_per_tag() -> None:
    db = TagDB()
    tags = [db.add(TagSpec(f"t{k}")) for k in range(10)]
    for k in range(10_000):
        db.update(tags[k % 10], float(k))
    assert len(db._order) == len(db) == 10
