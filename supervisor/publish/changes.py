"""The tag changes worth storing, in the order they happened: what the historian and the
InfluxDB writer both record.

Each scan a publisher asks the tag database what changed since the version it last saw
(``TagDB.changed_since``, O(changes)) and keeps a change when the tag's history settings
say so (``HistorySettings``: enabled, absolute deadband, minimum interval). A change of
quality is always kept (a value going BAD must show in a trend as a gap, never as a flat
line), and so is any change of a non-numeric tag (a state, a step id). A change held
back by the minimum interval is not lost: once the interval has passed, the tag's latest
value is stored (so a step followed by a constant is stored at its final value). The historian and
the InfluxDB writer use this one rule so that a trend drawn from either shows the same
points.

Two halves, so that the scan only copies (issue 30): ``ChangeSnapshots`` copies, at scan
end, each changed tag's value, quality and time into a ``ChangeBatch`` (the tags go on
changing; the batch does not); ``ChangeFilter`` turns batches into samples by the rule
above, on the writer's thread, as late as it likes. ``ChangeFeed`` is both at once (a
sample list per call, for the tools and the tests): a filter applied to the batches later
stores exactly what it stores at once (tests/unit/test_change_batches.py).
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple, Protocol

from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality, Reason
from supervisor.tags import Tag, TagDB

__all__ = [
    "ChangeBatch",
    "ChangeFeed",
    "ChangeFilter",
    "ChangeReader",
    "ChangeSnapshots",
    "ChangeSource",
    "Changes",
    "RawChange",
    "Sample",
    "SharedChanges",
]


class Sample(NamedTuple):
    """One stored value of one tag (a named tuple: a thousand are made every scan)."""

    name: str
    value: Value | None  # None when the quality is BAD
    quality: Quality
    t: float  # Clock.now() axis: when the value was acquired (the tag's source time)
    wall: float  # the same instant in Unix time (s)


RawChange = tuple[Tag, "Value | None", Quality, Reason, float, float]
"""A changed tag as the scan left it: (tag, value, quality, reason, source time, server
time). Only the tag's spec and index are read from ``tag`` later (they never change). The
historian and InfluxDB store it at its source time, or the server's when the logic set it
without one; the OPC UA server serves all of it."""


class ChangeBatch(NamedTuple):
    """One scan's changes, copied at its end."""

    changes: list[RawChange]  # oldest change first
    now: float  # the clock's time of the copy: releases values held back by an interval
    wall_offset: float  # Unix time − clock time (both clocks map by an offset)
    first: bool  # every tag (the source's first batch): a filter starts afresh


class ChangeSnapshots:
    """``db``'s changes since the last call, copied (the scan's half: no filtering)."""

    def __init__(self, db: TagDB, clock: Clock | None, *, since: int = 0) -> None:
        self.db = db
        self.clock = clock  # None: a reader that needs neither ``now`` nor wall times
        self._version = since  # 0: the first batch is every tag

    def snapshot(self) -> ChangeBatch:
        db, clock = self.db, self.clock
        first = self._version == 0
        changed = db.changed_since(self._version)
        self._version = db.version
        return ChangeBatch(
            [(t, t.value, t.quality, t.reason, t.source_t, t.server_t) for t in changed],
            0.0 if clock is None else clock.now(),
            # One call per scan (RealClock.to_wall reads two clocks).
            0.0 if clock is None else clock.to_wall(0.0),
            first,
        )

    def batches(self) -> list[ChangeBatch]:
        return [self.snapshot()]


class ChangeFilter:
    """Batches → the samples worth storing (the writer's half). One filter sees every batch
    of its source, in order; it keeps what it stored last, per tag."""

    def __init__(self) -> None:
        # Per tag index: the last stored value, quality and time.
        self._last: dict[int, tuple[Value | None, Quality, float]] = {}
        # Changes held back by their tag's minimum interval (the latest per tag).
        self._pending: dict[int, RawChange] = {}

    @property
    def holding(self) -> bool:
        """Some change waits for its minimum interval: an empty batch may release it.
        (Read from the scan's thread: a stale answer delays a release by a scan.)"""
        return bool(self._pending)

    def apply(self, batch: ChangeBatch) -> list[Sample]:
        """The samples to store from ``batch``, oldest first."""
        if batch.first:
            self._last.clear()
            self._pending.clear()
        offset = batch.wall_offset
        out = self._released(batch) if self._pending else []
        # ``_keep`` inlined for what nearly every change is (a tag stored at every change:
        # no deadband, no minimum interval): a hundred changes a scan in the load case,
        # where the call, the named tuple's own constructor and the attribute lookups were
        # most of the filter's time (issue 13). Any other change goes through ``_keep``.
        # (Never held back by a minimum interval, such a tag is never in ``_pending``.)
        last_of = self._last
        append = out.append
        for change in batch.changes:
            tag, value, quality, _, t, server_t = change
            history = tag.spec.history
            if not history.enabled:
                continue
            if history.deadband or history.min_interval_s:
                sample = self._keep(change, offset)
                if sample is not None:
                    append(sample)
                continue
            if quality is _BAD:
                value = None
            index = tag.index
            last = last_of.get(index)
            if last is not None and quality is last[1] and value == last[0]:
                continue
            t = t or server_t  # a value set by the logic has no source time
            last_of[index] = (value, quality, t)
            append(_new_sample(Sample, (tag.spec.name, value, quality, t, t + offset)))
        return out

    def _released(self, batch: ChangeBatch) -> list[Sample]:
        """The held-back values whose minimum interval has passed at ``batch.now``."""
        out: list[Sample] = []
        in_batch = {c[0].index for c in batch.changes}
        now = batch.now
        for index, change in list(self._pending.items()):
            if now - self._last[index][2] >= change[0].spec.history.min_interval_s:
                del self._pending[index]
                if index not in in_batch:  # else its newer change comes in the batch
                    sample = self._keep(change, batch.wall_offset, now)
                    if sample is not None:
                        out.append(sample)
        return out

    def _keep(
        self, change: RawChange, offset: float, released_t: float | None = None
    ) -> Sample | None:
        """The sample for ``change``, or None when it is not worth storing.
        ``released_t``: the value was held back by the minimum interval and is stored now
        (at its own acquisition time, which stays the truth)."""
        tag, value, quality, _, t, server_t = change
        history = tag.spec.history
        if not history.enabled:
            return None
        t = t or server_t  # a value set by the logic has no source time
        index = tag.index
        if self._pending:
            # A newer change replaces a held-back one: held again below, stored, or not
            # worth storing (back at the stored value, or within the deadband of it).
            self._pending.pop(index, None)
        gate_t = t if released_t is None else released_t
        if quality is _BAD:
            value = None
        last = self._last.get(index)
        if last is not None and quality is last[1]:
            last_value = last[0]
            if value == last_value:
                return None
            # A thousand changes a scan come through here: the filters only when set, and
            # type() rather than isinstance (a bool is not a number here).
            if (history.deadband or history.min_interval_s) and (
                type(value) in _NUMBERS and type(last_value) in _NUMBERS
            ):
                if abs(value - last_value) <= history.deadband:  # type: ignore[operator]
                    return None
                if gate_t - last[2] < history.min_interval_s:
                    self._pending[index] = change
                    return None
        self._last[index] = (value, quality, gate_t)
        return Sample(tag.spec.name, value, quality, t, t + offset)


_NUMBERS = (int, float)
_BAD = Quality.BAD
_new_sample = tuple.__new__
"""``Sample(...)`` without its generated ``__new__`` (a named tuple is a tuple)."""


class ChangeFeed:
    """The changes of ``db`` since the last call, filtered by each tag's history settings:
    a ``ChangeSnapshots`` and a ``ChangeFilter`` at once."""

    def __init__(self, db: TagDB, clock: Clock) -> None:
        self.db = db
        self.clock = clock
        self._snapshots = ChangeSnapshots(db, clock)
        self._filter = ChangeFilter()

    def take(self) -> list[Sample]:
        """The samples to store since the last call, oldest first."""
        return self._filter.apply(self._snapshots.snapshot())


class ChangeSource(Protocol):
    """Where a publisher gets its batches from: ``ChangeSnapshots`` of its own, or its
    ``ChangeReader`` of a ``SharedChanges``."""

    def batches(self) -> list[ChangeBatch]: ...


class Changes(Protocol):
    """Something that gives samples (``ChangeFeed``)."""

    def take(self) -> list[Sample]: ...


class SharedChanges:
    """One scan's copy of its changes, read by several publishers, each getting every
    batch once.

    The historian and the InfluxDB writer store the same changes by the same rule; copying
    them once a scan is enough (issue 13). The first reader to ask in a scan takes a batch
    from the snapshots; the others get that same batch (which nobody may change). A batch
    is kept until every reader had it, so a reader that asks twice (a stop) or misses a
    scan loses nothing; a reader that stops reading must ``close()``, or the batches would
    pile up for it.
    """

    def __init__(self, db: TagDB, clock: Clock) -> None:
        self._snapshots = ChangeSnapshots(db, clock)
        self._batches: deque[tuple[int, ChangeBatch]] = deque()
        self._seq = 0
        self._readers: list[ChangeReader] = []

    def reader(self) -> ChangeReader:
        """A reader from now on (the first batch is every tag: readers made before the
        first take get it)."""
        r = ChangeReader(self, self._seq)
        self._readers.append(r)
        return r

    def _take(self, reader: ChangeReader) -> list[ChangeBatch]:
        if reader.seen == self._seq:  # it had every batch: the next one, for everyone
            self._seq += 1
            self._batches.append((self._seq, self._snapshots.snapshot()))
        pending = [b for seq, b in self._batches if seq > reader.seen]
        reader.seen = self._seq
        oldest = min(r.seen for r in self._readers)
        while self._batches and self._batches[0][0] <= oldest:
            self._batches.popleft()
        return pending

    def _close(self, reader: ChangeReader) -> None:
        if reader in self._readers:
            self._readers.remove(reader)
        if self._readers:
            oldest = min(r.seen for r in self._readers)
            while self._batches and self._batches[0][0] <= oldest:
                self._batches.popleft()
        else:
            self._batches.clear()


class ChangeReader:
    """One publisher's view of a ``SharedChanges``: ``batches()`` as a
    ``ChangeSnapshots``'s."""

    def __init__(self, shared: SharedChanges, seen: int) -> None:
        self._shared = shared
        self.seen = seen

    def batches(self) -> list[ChangeBatch]:
        """The batches since this reader's last call, oldest first (do not change them)."""
        return self._shared._take(self)

    def close(self) -> None:
        self._shared._close(self)
