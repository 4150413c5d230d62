"""Alarm performance (ISA-18.2 / EEMUA 191), computed live from the alarm model's events.

An *annunciated alarm* is an activation: a transition to active, unacknowledged
(``Transition.ACTIVATED``) of an alarm that is not shelved at that moment (a shelved alarm
is still evaluated and logged, but nobody is asked to act: it is no load on the operator).
Acknowledgements, clears, resets and silences are not counted. The figures (ADR 0048):

- ``alarms.per_10min`` / ``alarms.per_10min_last``: activations in the current and in the
  last completed fixed 10-minute interval (intervals of the wall clock, 20:50–21:00, as
  ISA-18.2 and EEMUA 191 report "alarms per 10 minutes");
- ``alarms.per_day``: activations in the last 24 h (rolling);
- ``alarms.in_flood``, ``alarms.flood_s``, ``alarms.flood_pct``: a flood is more than
  ``FLOOD_COUNT`` activations in any 10 minutes (a rolling window: a burst across an
  interval's boundary is still a flood); the time in flood over the last 24 h and its
  share of them;
- ``alarms.stale``: alarms active (not shelved) for more than 24 h;
- ``alarms.chattering`` / ``alarms.chattering_ids``: alarms with ``CHATTER_COUNT`` or more
  activations within ``CHATTER_WINDOW_S``, at least once in the last 24 h;
- ``alarms.priority.<low|medium|high|critical>`` and ``…_pct``: the last 24 h's
  activations per priority;
- ``alarms.top``: the ten most frequent alarms of the last 24 h, a JSON list of
  ``{"id", "count"}``, most frequent first.

Memory is bounded: an activation is kept only while the longest window (24 h) needs it,
and at most ``max_kept`` of them (the oldest dropped first, counted in
``alarms.kpi_dropped``: past the cap the day's figures are a lower bound). The tags are
written by :meth:`AlarmKpi.on_scan` at most once every ``period_s`` (a scan publisher:
the listener only appends, the figures are made once a second, never on every scan).
"""

from __future__ import annotations

import heapq
import json
import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Final

from supervisor.safety.alarms import AlarmEvent, AlarmManager, Severity, Transition
from supervisor.tags import Tag, TagDB, TagSpec

__all__ = [
    "CHATTER_COUNT",
    "CHATTER_WINDOW_S",
    "DAY_S",
    "FLOOD_COUNT",
    "INTERVAL_S",
    "AlarmKpi",
    "KpiFigures",
]

log = logging.getLogger(__name__)

INTERVAL_S: Final = 600.0
"""The fixed reporting interval of "alarms per 10 minutes", and the flood's window."""
DAY_S: Final = 86_400.0
FLOOD_COUNT: Final = 10
"""More than this many activations in ``INTERVAL_S`` (rolling) is a flood (EEMUA 191)."""
STALE_S: Final = DAY_S
CHATTER_COUNT: Final = 3
CHATTER_WINDOW_S: Final = 60.0
TOP_N: Final = 10
MAX_KEPT: Final = 100_000
"""Activations kept at most (a day of a bench in a permanent flood of one a second fits)."""
PRIORITIES: Final = tuple(s.name.lower() for s in sorted(Severity))


@dataclass(frozen=True, slots=True)
class _Activation:
    t: float  # Clock.now()
    alarm_id: str
    severity: Severity


@dataclass(frozen=True)
class KpiFigures:
    """The figures at one moment (``AlarmKpi.figures``)."""

    per_10min: int
    per_10min_last: int
    per_day: int
    in_flood: bool
    flood_s: float
    flood_pct: float
    stale: int
    chattering: tuple[str, ...]
    priority: dict[str, int]
    priority_pct: dict[str, float]
    top: tuple[tuple[str, int], ...]
    dropped: int


def _pct(part: float, whole: float) -> float:
    return round(100.0 * part / whole, 1) if whole else 0.0


@dataclass
class AlarmKpi:
    """Listens to ``alarms`` (``on_alarm``) and publishes the figures as ``alarms.*`` tags
    of ``db`` (``on_scan``, a scan publisher)."""

    alarms: AlarmManager
    db: TagDB | None = None
    period_s: float = 1.0
    max_kept: int = MAX_KEPT
    name: str = "alarm-kpi"
    dropped: int = 0
    _day: deque[_Activation] = field(default_factory=deque)
    _recent: deque[float] = field(default_factory=deque)  # activation times, last 10 min
    _floods: deque[list[float]] = field(default_factory=deque)  # [start, end) of floods
    _last3: dict[str, deque[float]] = field(default_factory=dict)
    _chattered: dict[str, float] = field(default_factory=dict)  # alarm -> last chatter t
    _per_alarm: Counter[str] = field(default_factory=Counter)  # last 24 h
    _per_priority: Counter[Severity] = field(default_factory=Counter)  # last 24 h
    _interval_k: int | None = None  # the fixed interval of the current count
    _interval_n: int = 0
    _interval_last_n: int = 0
    _next_t: float = -math.inf
    _tags: dict[str, Tag] = field(default_factory=dict)
    only_on_change: bool = True
    """Skip a refresh when no alarm event came and no figure can have moved with time since
    the last one (``_quiet_until``): a bench without alarms computes its figures once per
    10-minute interval, not every second (a dry run scans 50,000 virtual seconds a second,
    and the figures every second halved its speed). False: every ``period_s`` (the plain
    path, which ``tests/unit/test_alarm_kpi.py`` proves this one equal to)."""
    _dirty: bool = True
    _quiet_until: float = -math.inf

    def __post_init__(self) -> None:
        self.alarms.listeners.append(self.on_alarm)
        if self.db is not None:
            self._declare(self.db)

    @property
    def kept(self) -> int:
        """Activations held in memory now (at most ``max_kept``)."""
        return len(self._day)

    # --- the listener (cheap: appends and counts) -------------------------------------
    def on_alarm(self, ev: AlarmEvent) -> None:
        self._dirty = True  # any transition: a clear or a shelve moves the stale count
        if ev.transition is not Transition.ACTIVATED:
            return
        alarm = self.alarms[ev.alarm_id]
        if alarm.shelved(ev.t):
            return  # not annunciated: no load on the operator
        t = ev.t
        self._expire(t)
        self._day.append(_Activation(t, ev.alarm_id, ev.severity))
        self._per_alarm[ev.alarm_id] += 1
        self._per_priority[ev.severity] += 1
        if len(self._day) > self.max_kept:
            self._forget(self._day.popleft())
            self.dropped += 1
        self._count_interval(ev.wall)
        self._count_flood(t)
        self._count_chatter(ev.alarm_id, t)

    def _count_interval(self, wall: float) -> None:
        k = math.floor(wall / INTERVAL_S)
        self._roll_interval(k)
        self._interval_n += 1

    def _roll_interval(self, k: int) -> None:
        """Make ``k`` the current fixed interval (a wall clock set back: kept as it is)."""
        if self._interval_k is None:
            self._interval_k = k
        elif k > self._interval_k:
            self._interval_last_n = self._interval_n if k == self._interval_k + 1 else 0
            self._interval_k = k
            self._interval_n = 0

    def _count_flood(self, t: float) -> None:
        recent = self._recent
        while recent and recent[0] <= t - INTERVAL_S:
            recent.popleft()
        recent.append(t)
        if len(recent) <= FLOOD_COUNT:
            return
        # In flood while the (FLOOD_COUNT + 1)-th newest activation is in the window.
        end = recent[-FLOOD_COUNT - 1] + INTERVAL_S
        while len(recent) > FLOOD_COUNT + 1:
            recent.popleft()  # older ones can no longer end a flood later than this one
        if self._floods and self._floods[-1][1] >= t:
            self._floods[-1][1] = max(self._floods[-1][1], end)
        else:
            self._floods.append([t, end])

    def _count_chatter(self, alarm_id: str, t: float) -> None:
        last = self._last3.get(alarm_id)
        if last is None:
            last = self._last3[alarm_id] = deque(maxlen=CHATTER_COUNT)
        last.append(t)
        if len(last) == CHATTER_COUNT and t - last[0] <= CHATTER_WINDOW_S:
            self._chattered[alarm_id] = t

    def _forget(self, a: _Activation) -> None:
        self._per_alarm[a.alarm_id] -= 1
        if self._per_alarm[a.alarm_id] <= 0:
            del self._per_alarm[a.alarm_id]
        self._per_priority[a.severity] -= 1

    def _expire(self, now: float) -> None:
        """Forget what the longest window (24 h) no longer covers."""
        horizon = now - DAY_S
        day = self._day
        while day and day[0].t <= horizon:
            self._forget(day.popleft())
        while self._floods and self._floods[0][1] <= horizon:
            self._floods.popleft()
        for alarm_id in [a for a, t in self._chattered.items() if t <= horizon]:
            del self._chattered[alarm_id]

    # --- the figures ------------------------------------------------------------------
    def figures(self, now: float | None = None) -> KpiFigures:
        """The figures at ``now`` (the alarm model's clock: ``Clock.now()``)."""
        clock = self.alarms.clock
        now = clock.now() if now is None else now
        self._expire(now)
        self._roll_interval(math.floor(clock.to_wall(now) / INTERVAL_S))
        horizon = now - DAY_S
        flood_s = sum(max(0.0, min(e, now) - max(s, horizon)) for s, e in self._floods)
        in_flood = bool(self._floods) and self._floods[-1][0] <= now < self._floods[-1][1]
        total = len(self._day)
        priority = {s.name.lower(): self._per_priority[s] for s in sorted(Severity)}
        top = heapq.nsmallest(TOP_N, self._per_alarm.items(), key=lambda kv: (-kv[1], kv[0]))
        return KpiFigures(
            per_10min=self._interval_n,
            per_10min_last=self._interval_last_n,
            per_day=total,
            in_flood=in_flood,
            flood_s=round(flood_s, 3),
            flood_pct=_pct(flood_s, DAY_S),
            stale=self._stale(now),
            chattering=tuple(sorted(self._chattered)),
            priority=priority,
            priority_pct={p: _pct(n, total) for p, n in priority.items()},
            top=tuple(top),
            dropped=self.dropped,
        )

    def _next_move(self, now: float) -> float:
        """The earliest time at which a figure can change with time alone (no alarm event):
        the next 10-minute boundary, an activation, a chatter or a flood leaving the 24 h
        window, an active alarm turning stale or its shelve ending; ``now`` while a flood's
        share is moving (in flood, or the window's edge inside a past flood). A moment a
        little early only costs a refresh that finds the same figures."""
        early = 1e-3  # clock arithmetic's rounding: never a tick late
        wall = self.alarms.clock.to_wall(now)
        moves = [now + (math.floor(wall / INTERVAL_S) + 1) * INTERVAL_S - wall - early]
        if self._day:
            moves.append(self._day[0].t + DAY_S - early)
        if self._chattered:
            moves.append(min(self._chattered.values()) + DAY_S - early)
        horizon = now - DAY_S
        for start, end in self._floods:
            if end > now or horizon > start:
                return now
            moves.append(start + DAY_S - early)
        for a in self.alarms:
            if a.shelved_until is not None and now < a.shelved_until:
                moves.append(a.shelved_until - early)
            if a.active and a.activated_t is not None and now - a.activated_t <= STALE_S:
                moves.append(a.activated_t + STALE_S - early)
        return min(moves)

    def _stale(self, now: float) -> int:
        return sum(
            1
            for a in self.alarms
            if a.active
            and a.activated_t is not None
            and now - a.activated_t > STALE_S
            and not a.shelved(now)
        )

    # --- the tags ---------------------------------------------------------------------
    def on_scan(self, db: TagDB, t: float) -> None:
        """A scan publisher: the tags refreshed at most every ``period_s``."""
        if t < self._next_t or not self._tags:
            return
        self._next_t = t + self.period_s
        if self.only_on_change and not self._dirty and t < self._quiet_until:
            return
        f = self.figures(t)
        self._dirty = False
        self._quiet_until = self._next_move(t)
        values: dict[str, bool | int | float | str] = {
            "alarms.per_10min": f.per_10min,
            "alarms.per_10min_last": f.per_10min_last,
            "alarms.per_day": f.per_day,
            "alarms.in_flood": f.in_flood,
            "alarms.flood_s": f.flood_s,
            "alarms.flood_pct": f.flood_pct,
            "alarms.stale": f.stale,
            "alarms.chattering": len(f.chattering),
            "alarms.chattering_ids": ",".join(f.chattering),
            "alarms.top": json.dumps([{"id": a, "count": n} for a, n in f.top]),
            "alarms.kpi_dropped": f.dropped,
        }
        for p in PRIORITIES:
            values[f"alarms.priority.{p}"] = f.priority[p]
            values[f"alarms.priority.{p}_pct"] = f.priority_pct[p]
        for name, value in values.items():
            db.update(self._tags[name], value)

    def _declare(self, db: TagDB) -> None:
        specs = [
            TagSpec("alarms.per_10min", "int", "", "Alarms annunciated in this 10-minute interval"),
            TagSpec(
                "alarms.per_10min_last",
                "int",
                "",
                "Alarms annunciated in the last completed 10-minute interval",
            ),
            TagSpec("alarms.per_day", "int", "", "Alarms annunciated in the last 24 h"),
            TagSpec(
                "alarms.in_flood",
                "bool",
                "",
                f"Alarm flood now: more than {FLOOD_COUNT} alarms in 10 minutes",
            ),
            TagSpec("alarms.flood_s", "float", "s", "Time in alarm flood in the last 24 h"),
            TagSpec("alarms.flood_pct", "float", "%", "Share of the last 24 h in alarm flood"),
            TagSpec("alarms.stale", "int", "", "Alarms active for more than 24 h (stale)"),
            TagSpec(
                "alarms.chattering",
                "int",
                "",
                f"Alarms that chattered ({CHATTER_COUNT}+ activations in"
                f" {CHATTER_WINDOW_S:g} s) in the last 24 h",
            ),
            TagSpec("alarms.chattering_ids", "str", "", "The chattering alarms (ids, commas)"),
            TagSpec(
                "alarms.top",
                "str",
                "",
                'The 10 most frequent alarms of the last 24 h (JSON: [{"id", "count"}])',
            ),
            TagSpec(
                "alarms.kpi_dropped",
                "int",
                "",
                "Alarm activations forgotten past the memory cap (day figures a lower bound)",
            ),
        ]
        for p in PRIORITIES:
            specs.append(
                TagSpec(f"alarms.priority.{p}", "int", "", f"{p.title()} alarms in the last 24 h")
            )
            specs.append(
                TagSpec(
                    f"alarms.priority.{p}_pct",
                    "float",
                    "%",
                    f"Share of {p} alarms in the last 24 h's alarms",
                )
            )
        for spec in specs:
            existing = db.get(spec.name)
            tag = existing if existing is not None else db.add(spec)
            self._tags[spec.name] = tag
        self.on_scan(db, self.alarms.clock.now())
