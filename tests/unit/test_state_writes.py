"""A tag changes only through ``TagDB`` (``supervisor/tags/db.py``): it keeps a tag's value,
quality, reason, timestamps, version and the change feed consistent, and a forced tag
forced. No module outside ``supervisor/tags`` assigns those attributes itself (issue 29,
item 3: eleven sites stamped ``tag.source_t`` by hand, each restating ``TagDB.stamp``).
Likewise an alarm changes only through its ``AlarmManager``, which counts every change
for the guard (item 4: an ``Alarm.__setattr__`` counted every write).

The scan reads the source: an assignment to an attribute with one of those names on any
object but ``self`` is taken for a tag's (an alarm's). The few that are not are listed
with why; the lists only shrink (an entry whose site is gone fails the test too)."""

from __future__ import annotations

import ast
import dataclasses
from collections import Counter
from pathlib import Path

import pytest

from supervisor.core.quality import Quality, Reason
from supervisor.safety.alarms import Alarm
from supervisor.tags import Tag, TagDB, TagSpec

ROOT = Path(__file__).parents[2]
PACKAGE = ROOT / "supervisor"
TAG_STATE = frozenset(
    {
        "value",
        "number",
        "quality",
        "reason",
        "source_t",
        "server_t",
        "version",
        "forced",
        "index",
        "spec",
    }
)
"""``Tag``'s attributes (its ``__slots__``, checked below)."""
ALARM_STATE = frozenset(f.name for f in dataclasses.fields(Alarm))

NOT_TAGS: Counter[tuple[str, str]] = Counter(
    {
        # The address lines of the Chadèche bus: GPIO output pins, whose ``value`` drives them.
        ("supervisor/devices/chadeche/bus.py", "self._a0.value"): 1,
        ("supervisor/devices/chadeche/bus.py", "self._a1.value"): 1,
        # A screen client's version: the change feed's version it was last sent.
        ("supervisor/hmi/live.py", "c.version"): 1,
    }
)


def _targets(node: ast.AST) -> list[ast.expr]:
    if isinstance(node, ast.Assign):
        return list(node.targets)
    if isinstance(node, ast.AugAssign | ast.AnnAssign):
        return [node.target]
    return []


def _flatten(target: ast.expr) -> list[ast.expr]:
    if isinstance(target, ast.Tuple | ast.List):
        return [x for t in target.elts for x in _flatten(t)]
    if isinstance(target, ast.Starred):
        return _flatten(target.value)
    return [target]


NOT_ALARMS: Counter[tuple[str, str]] = Counter(
    {
        # The guard's record of one of its checks (``_Check``), which holds an alarm.
        ("supervisor/safety/guard.py", "check.active"): 1,
    }
)


def attribute_writes(path: Path, names: frozenset[str] = TAG_STATE) -> list[str]:
    """Each assignment in ``path`` to an attribute named in ``names``, on an object that
    is not ``self`` (an object's own attribute of that name is its own business); and each
    ``setattr`` of such a name."""
    found: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        for target in (t for top in _targets(node) for t in _flatten(top)):
            if (
                isinstance(target, ast.Attribute)
                and target.attr in names
                and not (isinstance(target.value, ast.Name) and target.value.id == "self")
            ):
                found.append(ast.unparse(target))
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name | ast.Attribute)
            and (node.func.id if isinstance(node.func, ast.Name) else node.func.attr)
            in ("setattr", "__setattr__")
            and len(node.args) >= 2
            and isinstance(node.args[1], ast.Constant)
            and node.args[1].value in names
        ):
            found.append(ast.unparse(node))
    return found


def test_the_names_checked_are_a_tags_attributes() -> None:
    assert frozenset(Tag.__slots__) == TAG_STATE | {"is_float"}  # set in __init__ only


def writes_outside(owner: str, names: frozenset[str]) -> Counter[tuple[str, str]]:
    """The writes of ``names`` in every module of the package but ``owner``'s (a prefix)."""
    writes: Counter[tuple[str, str]] = Counter()
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if not rel.startswith(owner):
            writes.update((rel, w) for w in attribute_writes(path, names))
    return writes


def test_no_module_outside_the_tag_database_writes_a_tag() -> None:
    writes = writes_outside("supervisor/tags/", TAG_STATE)
    unexpected = writes - NOT_TAGS
    assert not unexpected, (
        "a tag changes only through TagDB (update, stamp, set_quality, write, force): "
        + ", ".join(f"{p}: {w}" for p, w in sorted(unexpected))
    )
    gone = NOT_TAGS - writes
    assert not gone, f"no longer written: take them off NOT_TAGS: {sorted(gone)}"


def test_no_module_outside_the_alarm_manager_writes_an_alarm() -> None:
    writes = writes_outside("supervisor/safety/alarms.py", ALARM_STATE)
    unexpected = writes - NOT_ALARMS
    assert not unexpected, (
        "an alarm changes only through its AlarmManager (set, acknowledge, reset, shelve, "
        "unshelve, restore), which counts the change for the guard: "
        + ", ".join(f"{p}: {w}" for p, w in sorted(unexpected))
    )
    gone = NOT_ALARMS - writes
    assert not gone, f"no longer written: take them off NOT_ALARMS: {sorted(gone)}"


def test_the_scan_finds_a_forced_tag_restamped_by_hand(tmp_path: Path) -> None:
    """What the check exists for: the hand-written stamp that forgets a forced tag."""
    source = tmp_path / "phase.py"
    source.write_text(
        "def drive(db, tag, value):\n"
        "    if value == tag.value:\n"
        "        tag.source_t = db.scan_t\n"
        "    else:\n"
        "        db.update(tag, value)\n"
        "    tag.value, (other.quality, self.reason) = value, pair\n"
        "    setattr(tag, 'forced', False)\n"
        "    self.value = value  # the object's own attribute\n",
        encoding="utf-8",
    )
    assert sorted(attribute_writes(source)) == sorted(
        [
            "tag.source_t",
            "tag.value",
            "other.quality",
            "setattr(tag, 'forced', False)",
        ]
    )


@pytest.mark.parametrize("forced", [False, True])
def test_a_stamp_moves_only_the_source_time_of_a_tag_that_is_not_forced(forced: bool) -> None:
    db = TagDB()
    tag = db.add(TagSpec("t"))
    db.set_scan_time(1.0)
    db.update(tag, 1.5)
    if forced:
        db.force("t", 2.5)
    before = (tag.value, tag.quality, tag.reason, tag.server_t, tag.version, db.version)
    source_t = tag.source_t
    db.set_scan_time(2.0)
    db.stamp(tag, 2.0)
    assert (tag.value, tag.quality, tag.reason, tag.server_t, tag.version, db.version) == before
    assert tag.source_t == (source_t if forced else 2.0)


def test_an_output_that_holds_keeps_the_time_it_last_changed_an_input_its_samples() -> None:
    """ADR 0037 (OPC UA Part 4 §7.11.3: the source time is "the time of the last change of
    the value or statusCode"): written again unchanged, by any of the writes the logic
    uses, a tag keeps its source time; a change, of value or quality, moves it; a source
    time given (a device's sample) is taken, changed or not."""
    db = TagDB()
    out, counter, inp = db.add(TagSpec("out")), db.add(TagSpec("counter")), db.add(TagSpec("in"))
    db.set_scan_time(1.0)
    db.update(out, 0.5)
    db.update_many([(counter, 2.0)])
    db.update(inp, 3.0, source_t=0.9)
    db.set_scan_time(2.0)
    db.update(out, 0.5)
    db.update_many([(out, 0.5)])
    db.add_many([(counter, 0.0)])
    db.update(inp, 3.0, source_t=1.9)
    assert (out.source_t, counter.source_t, inp.source_t) == (1.0, 1.0, 1.9)
    db.set_scan_time(3.0)
    db.update(out, 0.5, Quality.UNCERTAIN, Reason.LAST_KNOWN)
    db.add_many([(counter, 1.0)])
    assert (out.source_t, counter.source_t, counter.value) == (3.0, 3.0, 3.0)
