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

from dataclasses import dataclass

from supervisor.core.clock import Clock
from supervisor.core.driver import Value
from supervisor.core.quality import Quality
from supervisor.tags import Tag, TagDB

__all__ = ["ChangeFeed", "Sample"]


@dataclass(frozen=True, slots=True)
class Sample:
    """One stored value of one tag."""

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

    def take(self) -> list[Sample]:
        """The samples to store since the last call, oldest first."""
        db = self.db
        changed = db.changed_since(self._version)
        out: list[Sample] = []
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
        for tag in changed:
            sample = self._keep(tag)
            if sample is not None:
                out.append(sample)
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
        value = tag.value if tag.quality is not Quality.BAD else None
        last = self._last.get(tag.index)
        if last is not None:
            last_value, last_quality, last_t = last
            if tag.quality is last_quality:
                if value == last_value:
                    return None
                if _is_number(value) and _is_number(last_value):
                    if abs(float(value) - float(last_value)) <= history.deadband:  # type: ignore[arg-type]
                        return None
                    if gate_t - last_t < history.min_interval_s:
                        self._pending[tag.index] = tag
                        return None
        self._pending.pop(tag.index, None)
        self._last[tag.index] = (value, tag.quality, gate_t)
        return Sample(tag.name, value, tag.quality, t, self.clock.to_wall(t))


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)
