"""The tag database: values with quality, timestamps and a cheap change feed.

Every change bumps a global version, stamps it on the tag and moves the tag to the end of
an order of last changes (one entry per tag, docs/adr/0018-scan-performance.md), so a
publisher asks "what changed since version N" each scan in O(changes), however far back
N is, and the database keeps no log that grows with the number of changes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Sequence

from supervisor.core.driver import Value
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality, Reason
from supervisor.tags.spec import Access, TagSpec

_GOOD, _NONE = Quality.GOOD, Reason.NONE
_BAD, _OUT_OF_RANGE = Quality.BAD, Reason.OUT_OF_RANGE


class Tag:
    """Live state of one tag. Mutated only through ``TagDB`` (its ``update``,
    ``update_many``, ``stamp``, ``set_quality``, ``write``, ``force``, ``unforce``), which
    keeps the versions, the change feed and forcing right."""

    __slots__ = (
        "forced",
        "index",
        "is_float",
        "number",
        "quality",
        "reason",
        "server_t",
        "source_t",
        "spec",
        "value",
        "version",
    )

    def __init__(self, spec: TagSpec, index: int) -> None:
        self.spec = spec
        self.index = index
        self.is_float = spec.dtype == "float"  # read by every update: no spec lookup
        self.value: Value | None = spec.initial
        self.number = _number(spec.initial)
        """The value as a float, 0.0 when it is not a number: ``as_float()`` read without
        a call (kept by ``TagDB`` with the value; the channel reads it every scan)."""
        self.quality = Quality.UNCERTAIN if spec.initial is not None else Quality.BAD
        self.reason = Reason.INITIAL
        self.source_t = 0.0
        self.server_t = 0.0
        self.version = 0
        self.forced = False

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def good(self) -> bool:
        return self.quality is Quality.GOOD

    def as_float(self, default: float = 0.0) -> float:
        """The value as a float (``default`` when it is not a number)."""
        v = self.value
        if type(v) is float:  # a float tag's value, the common case: no conversion
            return v
        if isinstance(v, int | float) and not isinstance(v, bool):
            return float(v)
        return default

    def __repr__(self) -> str:
        forced = " FORCED" if self.forced else ""
        return f"<Tag {self.name}={self.value!r} {self.quality.name}({self.reason}){forced}>"


def _number(value: Value | None) -> float:
    """``Tag.as_float()``'s answer for ``value``, but an int beyond a float's range, for
    which ``as_float`` raises, reads as an infinity of its sign (no write of a tag fails
    on what a reader may ask later)."""
    if type(value) is float:
        return value
    if type(value) is int or (isinstance(value, _NUMBER) and type(value) is not bool):
        try:
            return float(value)
        except OverflowError:
            return math.inf if value > 0 else -math.inf
    return 0.0


def _as_float_value(
    value: Value, quality: Quality, reason: Reason
) -> tuple[float | None, Quality, Reason]:
    """What a float tag stores of a value that is not a float: the float it converts to
    (BAD, out of range, when not finite), or None, BAD, a configuration error."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        # A driver or logic handing over the wrong type is a fault, not a crash.
        return None, Quality.BAD, Reason.CONFIG_ERROR
    if number - number != 0.0:
        return number, Quality.BAD, Reason.OUT_OF_RANGE
    return number, quality, reason


_NUMBER = (int, float)
_INT_AS_FLOAT = 2**1023
"""An int strictly within this bound converts to a float without overflow."""


class TagDB:
    def __init__(self) -> None:
        self._tags: dict[str, Tag] = {}
        self._list: list[Tag] = []
        self.version = 0
        # Every tag once, in the order of their last change (the last changed at the end):
        # ``move_to_end`` is O(1) and allocates nothing, where a log of (version, tag)
        # tuples kept 65 536 small objects alive for the collector to walk (issue 13).
        self._order: OrderedDict[int, Tag] = OrderedDict()
        self.scan_t = 0.0
        """This scan's time (:meth:`set_scan_time`): the server time of its changes and the
        source time of what it stamps. Read-only but for ``set_scan_time``: a tag changes
        only through this class (``tests/unit/test_state_writes.py``)."""

    # --- declaration -----------------------------------------------------------
    def add(self, spec: TagSpec) -> Tag:
        if spec.name in self._tags:
            raise ValueError(f"duplicate tag name {spec.name!r}")
        tag = Tag(spec, len(self._list))
        self._tags[spec.name] = tag
        self._list.append(tag)
        self._order[tag.index] = tag
        self._bump(tag)
        return tag

    def __contains__(self, name: object) -> bool:
        return name in self._tags

    def __getitem__(self, name: str) -> Tag:
        try:
            return self._tags[name]
        except KeyError:
            raise KeyError(f"unknown tag {name!r}") from None

    def get(self, name: str) -> Tag | None:
        return self._tags.get(name)

    def __iter__(self) -> Iterator[Tag]:
        return iter(self._list)

    def __len__(self) -> int:
        return len(self._list)

    def names(self) -> list[str]:
        return list(self._tags)

    # --- time ------------------------------------------------------------------
    def set_scan_time(self, t: float) -> None:
        """Server timestamp given to every change in this scan (``Clock.now()`` axis)."""
        self.scan_t = t

    # --- updates ---------------------------------------------------------------
    def update(
        self,
        tag: Tag,
        value: Value | None,
        quality: Quality = Quality.GOOD,
        reason: Reason = Reason.NONE,
        source_t: float | None = None,
    ) -> bool:
        """Set value and quality from the process side; returns True if anything changed.

        The source time (ADR 0037): ``source_t`` when given (a device's sample time, every
        sample, changed or not); else this scan's time when the value, quality or reason
        changes, and unchanged when they do not: what the logic computes carries the time
        it last changed (OPC UA Part 4 §7.11.3: "the time of the last change of the value
        or statusCode"), not the last scan that computed it again.

        A forced tag ignores the process value (commissioning override) but keeps
        its forced value and says so.
        """
        if tag.forced:
            return False
        if tag.is_float:
            # ``x - x == 0.0`` is ``isfinite(x)`` for a float (inf - inf and NaN - NaN are
            # NaN), without a call: this runs for every float update of every scan, a
            # float first (the fewest steps: about 30 updates a scan, issue 13).
            if type(value) is float:
                if value - value != 0.0:
                    quality, reason = Quality.BAD, Reason.OUT_OF_RANGE
            elif value is not None:
                value, quality, reason = _as_float_value(value, quality, reason)
        if value != tag.value or quality is not tag.quality or reason is not tag.reason:
            scan_t = self.scan_t
            tag.source_t = scan_t if source_t is None else source_t
            tag.value = value
            # An int (a counter, every scan) without ``_number``'s call.
            if type(value) is float:
                tag.number = value
            elif type(value) is int and -_INT_AS_FLOAT < value < _INT_AS_FLOAT:
                tag.number = float(value)
            else:
                tag.number = _number(value)
            tag.quality = quality
            tag.reason = reason
            tag.server_t = scan_t
            self.version = version = self.version + 1
            tag.version = version
            self._order.move_to_end(tag.index)
            return True
        if source_t is not None:
            # The source gave the same value again, at ``source_t`` (a device's new sample).
            tag.source_t = source_t
        return False

    def update_many(self, writes: Iterable[tuple[Tag, Value | None]]) -> None:
        """``update(tag, value)`` for each pair in turn: GOOD, without a reason, at this
        scan's time.

        For the outputs a phase writes every scan (the channel's commands, the guard's
        trips and limits, a step chain's request and clocks), most of them unchanged: a
        tag that already holds its value, GOOD and without a reason, is left as it is, as
        its update would leave it (a GOOD float tag holds a finite float; its source time
        says when it last changed, ADR 0037); a float tag given a new finite float takes
        it as its update would; both here rather than in one ``update`` call each
        (issue 29: a profile of the dry run).
        ``test_tagdb_update_many.py`` proves it equal to the updates one by one for every
        kind of tag and value."""
        scan_t = self.scan_t
        for tag, value in writes:
            if tag.forced:
                continue  # ``update`` leaves a forced tag as it is
            if value == tag.value and tag.quality is _GOOD and tag.reason is _NONE:
                continue  # unchanged: ``update`` leaves it as it is
            if type(value) is float and value - value == 0.0:
                # ``update`` of a finite float, inline (any tag: a float tag takes it as it
                # is, GOOD, and so does every other): it changes the tag (its value,
                # quality or reason differs: the test above).
                tag.source_t = tag.server_t = scan_t
                tag.value = tag.number = value
                tag.quality = _GOOD
                tag.reason = _NONE
                self.version = tag.version = self.version + 1
                self._order.move_to_end(tag.index)
            else:
                self.update(tag, value)

    def update_each(self, tags: Sequence[Tag], values: Sequence[Value | None]) -> None:
        """``update_many(zip(tags, values))``: ``update(tags[k], values[k])`` for each ``k``
        in turn, GOOD, without a reason, at this scan's time, by the same rule.

        For a phase that writes the same tags in the same order every scan (a channel's
        outputs, a steady chain scan's): its tags in a tuple made once, this scan's values
        in one sequence (a list it may keep and set in place), no pair made for each tag
        (issue 29: the pairs built for ``update_many`` were the largest allocation left in
        the dry run's profile). ``test_tagdb_update_many.py`` proves it equal to the
        updates one by one."""
        scan_t = self.scan_t
        k = 0
        for tag in tags:
            value = values[k]
            k += 1
            if tag.forced:
                continue  # ``update`` leaves a forced tag as it is
            if value == tag.value and tag.quality is _GOOD and tag.reason is _NONE:
                continue  # unchanged: ``update`` leaves it as it is
            if type(value) is float and value - value == 0.0:
                # ``update`` of a finite float, inline, as in ``update_many``.
                tag.source_t = tag.server_t = scan_t
                tag.value = tag.number = value
                tag.quality = _GOOD
                tag.reason = _NONE
                self.version = tag.version = self.version + 1
                self._order.move_to_end(tag.index)
            else:
                self.update(tag, value)

    def add_many(self, increments: Iterable[tuple[Tag, float]]) -> None:
        """``update(tag, tag.as_float() + delta)`` for each pair in turn: counters moved by
        their deltas (a channel's Ah and Wh, every scan), without a call for each
        ``as_float`` and each update of a float tag (issue 29: a profile of the dry run put
        them first once the channel read plainly). ``test_tagdb_update_many.py`` proves it
        equal to the updates one by one for every kind of tag, value and delta."""
        scan_t = self.scan_t
        for tag, delta in increments:
            v = tag.value
            if type(v) is float and not tag.forced:
                value = v + delta
                if type(value) is float and value - value == 0.0:
                    # ``update`` of a finite float, inline (any tag: a float tag takes it
                    # as it is, GOOD, and so does every other).
                    if value != v or tag.quality is not _GOOD or tag.reason is not _NONE:
                        tag.value = tag.number = value
                        tag.quality = _GOOD
                        tag.reason = _NONE
                        tag.source_t = tag.server_t = scan_t
                        self.version = tag.version = self.version + 1
                        self._order.move_to_end(tag.index)
                    continue
            self.update(tag, tag.as_float() + delta)

    def add_each(self, tags: Sequence[Tag], deltas: Sequence[float]) -> None:
        """``add_many(zip(tags, deltas))``: ``update(tags[k], tags[k].as_float() +
        deltas[k])`` for each ``k`` in turn, by the same rule, with no pair made for each
        tag (the tags in a tuple made once: ``update_each``'s reason).
        ``test_tagdb_update_many.py`` proves it equal to the updates one by one."""
        scan_t = self.scan_t
        k = 0
        for tag in tags:
            delta = deltas[k]
            k += 1
            v = tag.value
            if type(v) is float and not tag.forced:
                value = v + delta
                if type(value) is float and value - value == 0.0:
                    # ``update`` of a finite float, inline, as in ``add_many``.
                    if value != v or tag.quality is not _GOOD or tag.reason is not _NONE:
                        tag.value = tag.number = value
                        tag.quality = _GOOD
                        tag.reason = _NONE
                        tag.source_t = tag.server_t = scan_t
                        self.version = tag.version = self.version + 1
                        self._order.move_to_end(tag.index)
                    continue
            self.update(tag, tag.as_float() + delta)

    def stamp(self, tag: Tag, source_t: float) -> None:
        """The source says the tag's value still holds at ``source_t`` (a device's new
        sample that read the same): its source time moves there, nothing else, as an
        :meth:`update` with the value, quality and reason the tag has and this source time
        does (a forced tag keeps everything). For a caller that knows nothing else
        changed: a third of an update's work (issue 13: half the updates of a dry run's
        scan changed only the source time)."""
        if not tag.forced:
            tag.source_t = source_t

    def set_quality(self, tag: Tag, quality: Quality, reason: Reason) -> bool:
        return self.update(tag, tag.value, quality, reason, tag.source_t)

    def write(self, name: str, value: Value, access: Access = Access.OPERATOR) -> Tag:
        """A write from a person or client: checks access level, type and range."""
        tag = self[name]
        if tag.spec.access is Access.READ_ONLY:
            raise OperatorError(f"{name} is read-only")
        if access < tag.spec.access:
            raise OperatorError(f"{name} needs {tag.spec.access.name.lower()} access")
        try:
            v = tag.spec.coerce(value)
        except (TypeError, ValueError) as exc:
            raise OperatorError(str(exc)) from None
        choices = tag.spec.choices
        if choices is not None and v not in choices:
            raise OperatorError(f"{name}: {v!r} is not one of {', '.join(choices)}")
        rng = tag.spec.range
        if rng is not None and isinstance(v, int | float) and not isinstance(v, bool):
            lo, hi = rng
            if not lo <= v <= hi:
                raise OperatorError(
                    f"{name}: {v} {tag.spec.unit} is outside its range [{lo}, {hi}]".strip()
                )
        self.update(tag, v, Quality.GOOD, Reason.NONE)
        return tag

    def force(self, name: str, value: Value) -> Tag:
        """Override a tag's value for commissioning; shown as forced everywhere."""
        tag = self[name]
        v = tag.spec.coerce(value)
        tag.forced = False
        self.update(tag, v, Quality.GOOD, Reason.FORCED)
        tag.forced = True
        return tag

    def unforce(self, name: str) -> Tag:
        tag = self[name]
        if tag.forced:
            tag.forced = False
            # Until the process writes again the value is only the last forced one.
            self.update(tag, tag.value, Quality.UNCERTAIN, Reason.LAST_KNOWN)
        return tag

    # --- change feed -----------------------------------------------------------
    def changed_since(self, version: int) -> list[Tag]:
        """Tags changed after ``version`` (each once), oldest change first."""
        if version >= self.version:
            return []
        # Walk back from the last change until a tag last changed at or before
        # ``version``: every tag before it in the order changed earlier still.
        out: list[Tag] = []
        append = out.append
        for tag in reversed(self._order.values()):
            if tag.version <= version:
                break
            append(tag)
        out.reverse()
        return out

    def snapshot(self, names: Iterable[str] | None = None) -> dict[str, Value | None]:
        tags = self._list if names is None else [self[n] for n in names]
        return {t.name: t.value for t in tags}

    def _bump(self, tag: Tag) -> None:
        self.version += 1
        tag.version = self.version
        self._order.move_to_end(tag.index)
