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
"""

from __future__ import annotations

from collections import deque
from typing import NamedTuple, Protocol

from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality
from supervisor.tags import Tag, TagDB

__all__ = ["ChangeFeed", "ChangeReader", "Changes", "Sample", "SharedChanges"]


class Sample(NamedTuple):
    """One stored value of one tag (a named tuple: a thousand are made every scan)."""

    name: str
    value: Value | None  # None when the quality is BAD
    quality: Quality
    t: float  # Clock.now() axis: when the value was acquired (the tag's source time)
    wall: float  # the same instant in Unix time (s)


class ChangeFeed:
    """The changes of ``db`` since the last call, filtered by each tag's history settings."""

    def __init__(self, db: TagDB, clock: Clock) -> None:
        self.db = db
        self.clock = clock
        self._version = 0
        # Per tag index: the last stored value, quality and time.
        self._last: dict[int, tuple[Value | None, Quality, float]] = {}
        # Tags whose latest change was held back by their minimum interval.
        self._pending: dict[int, Tag] = {}
        self._wall_offset = 0.0

    def take(self) -> list[Sample]:
        """The samples to store since the last call, oldest first."""
        db = self.db
        changed = db.changed_since(self._version)
        out: list[Sample] = []
        # Both clocks map their axis to Unix time by an offset: one call per scan, not one
        # per sample (RealClock.to_wall reads two clocks).
        self._wall_offset = self.clock.to_wall(0.0)
        if self._pending:
            now = self.clock.now()
            for index, tag in list(self._pending.items()):
                last_t = self._last[index][2]
                if now - last_t >= tag.spec.history.min_interval_s:
                    del self._pending[index]
                    if tag.version <= self._version:  # not also in this scan's changes
                        sample = self._keep(tag, now)
                        if sample is not None:
                            out.append(sample)
        # ``_keep`` inlined for what nearly every change is (a tag stored at every change:
        # no deadband, no minimum interval): a hundred changes a scan in the load case,
        # where the call, the named tuple's own constructor and the attribute lookups were
        # most of the feed's time (issue 13). Any other change goes through ``_keep``.
        # (Never held back by a minimum interval, such a tag is never in ``_pending``.)
        last_of, offset = self._last, self._wall_offset
        append = out.append
        for tag in changed:
            history = tag.spec.history
            if not history.enabled:
                continue
            if history.deadband or history.min_interval_s:
                sample = self._keep(tag)
                if sample is not None:
                    append(sample)
                continue
            quality = tag.quality
            value = tag.value if quality is not _BAD else None
            index = tag.index
            last = last_of.get(index)
            if last is not None and quality is last[1] and value == last[0]:
                continue
            t = tag.source_t or tag.server_t
            last_of[index] = (value, quality, t)
            append(_new_sample(Sample, (tag.spec.name, value, quality, t, t + offset)))
        self._version = db.version
        return out

    def _keep(self, tag: Tag, released_t: float | None = None) -> Sample | None:
        """The sample for ``tag``'s current value, or None when it is not worth storing.
        ``released_t``: the value was held back by the minimum interval and is stored now
        (at its own acquisition time, which stays the truth)."""
        history = tag.spec.history
        if not history.enabled:
            return None
        t = tag.source_t or tag.server_t
        gate_t = t if released_t is None else released_t
        quality = tag.quality
        value = tag.value if quality is not Quality.BAD else None
        index = tag.index
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
                    self._pending[index] = tag
                    return None
        if self._pending:
            self._pending.pop(index, None)
        self._last[index] = (value, quality, gate_t)
        return Sample(tag.name, value, quality, t, t + self._wall_offset)


_NUMBERS = (int, float)
_BAD = Quality.BAD
_new_sample = tuple.__new__
"""``Sample(...)`` without its generated ``__new__`` (a named tuple is a tuple)."""


class Changes(Protocol):
    """What a publisher reads its changes from: a ``ChangeFeed`` of its own, or its
    ``ChangeReader`` of a ``SharedChanges``."""

    def take(self) -> list[Sample]: ...


class SharedChanges:
    """One change feed read by several publishers, each getting every batch once.

    The historian and the InfluxDB writer store the same changes by the same rule; at a
    10 ms scan with a thousand tags, filtering them twice was a tenth of the scan (issue
    13). The first reader to ask in a scan takes a batch from the feed; the others get
    that same batch (a list nobody may change). A batch is kept until every reader had it,
    so a reader that asks twice (a stop) or misses a scan loses nothing; a reader that
    stops reading must ``close()``, or the batches would pile up for it.
    """

    def __init__(self, db: TagDB, clock: Clock) -> None:
        self._feed = ChangeFeed(db, clock)
        self._batches: deque[tuple[int, list[Sample]]] = deque()
        self._seq = 0
        self._readers: list[ChangeReader] = []

    def reader(self) -> ChangeReader:
        """A reader from now on (the feed's first batch is every tag: readers made before
        the first take get it)."""
        r = ChangeReader(self, self._seq)
        self._readers.append(r)
        return r

    def _take(self, reader: ChangeReader) -> list[Sample]:
        if reader.seen == self._seq:  # it had every batch: the next one, for everyone
            self._seq += 1
            self._batches.append((self._seq, self._feed.take()))
        pending = [b for seq, b in self._batches if seq > reader.seen]
        reader.seen = self._seq
        oldest = min(r.seen for r in self._readers)
        while self._batches and self._batches[0][0] <= oldest:
            self._batches.popleft()
        if len(pending) == 1:
            return pending[0]
        return [s for b in pending for s in b]

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
    """One publisher's view of a ``SharedChanges``: ``take()`` as a ``ChangeFeed``'s."""

    def __init__(self, shared: SharedChanges, seen: int) -> None:
        self._shared = shared
        self.seen = seen

    def take(self) -> list[Sample]:
        """The samples since this reader's last take, oldest first (do not change it)."""
        return self._shared._take(self)

    def close(self) -> None:
        self._shared._close(self)
