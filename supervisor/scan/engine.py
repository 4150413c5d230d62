"""One scan, as a PLC does it (docs/design.md "One scan"; docs/adr/0002-scan-timing.md).

1. Inputs: copy every driver image into the tag database in one synchronous step, so
   logic sees one consistent snapshot; an input older than its stale limit turns BAD.
2. Logic: phases in order (derived values, interlocks and alarms, step chains). An
   exception in a phase is counted and logged; the phase's owner decides what goes safe.
3. Outputs: output tags whose value changed are queued to their driver (never awaited);
   the driver's own task sends them at once (docs/design.md "Safety": output writes leave when
   the scan queues them). On a virtual clock the engine flushes them in lockstep right
   after the scan, so virtual-clock runs see the same order of events.
4. Publish: every publisher gets the scan end; publishers never block the scan.

Deadlines are absolute (start + k·period). After an overrun the engine does not burst
to catch up: missed deadlines are skipped and counted.

A scan that starts late by more than :func:`stall_after_s` (two periods, at least
``STALL_MIN_S``) is a **stall**: something held the event loop between two scans (a parse
on the loop did, issue 9). ``scan.overruns`` cannot see it — no scan ran long, none ran at
all. Stalls are counted (``scan.stalls``, ``scan.stall_max_s``), logged, and raise the
``scan.stall`` supervision alarm (``safety``, from ``scan.stall_s``). While the loop is
held nothing on it can say so; on a real clock a watch thread (:class:`StallWatch`) logs
it at once, with where the loop's thread is.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
import time
import traceback
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from supervisor.core.clock import Clock, VirtualClock
from supervisor.core.driver import Driver, Sample, Value
from supervisor.core.gate import ScanGate
from supervisor.core.loops import HookedLoop
from supervisor.core.quality import Quality, Reason
from supervisor.core.realtime import RealtimePriority
from supervisor.core.ring import FloatRing
from supervisor.tags.db import Tag, TagDB
from supervisor.tags.spec import Scaling, TagSpec

log = logging.getLogger(__name__)
_perf_counter = time.perf_counter
_GOOD, _BAD, _NONE = Quality.GOOD, Quality.BAD, Reason.NONE

STATS_WINDOW = 10_000
DRIVER_STOP_S = 5.0
"""How long the end of a run waits for the drivers' own tasks to stop."""

STALL_PERIODS = 2.0
"""A scan later than this many periods is a stall. One period late is an overrun's tail or
the operating system's scheduler; more than two means at least one whole deadline went by
with the loop busy with something other than the scan."""
STALL_MIN_S = 0.25
"""...and later than this, whatever the period: a 10 ms scan must not alarm on the pauses
every healthy CPython process has (a full garbage collection, a loaded machine: tens of
milliseconds; ISA-18.2: no nuisance alarms). It is a quarter of the shipped I/O maps'
shortest stale limit (1 s) and an eighth of their device watchdogs (2 s): short stalls are
counted and alarmed long before one is long enough to lose an input or a device."""


WAKE_EARLY_S = 0.002
"""On a real clock the scan's event loop wakes this long before a deadline (the selector's
millisecond rounding, and a driver poll or an HTTP slice that is running when the loop
should wake: about a millisecond each in issue 13's load case) and sleeps the rest on the
thread (:meth:`ScanEngine._wait_on_thread`)."""
GATE_EARLY_S = 0.003
"""On a real clock the scan gate is closed this long before each deadline by a thread of
the engine's (``GateCloser``, at most a third of the period)."""
SCAN_FIRST_EARLY_S = 0.001
"""``ScanFirstLoop``: a callback that would start this close to a deadline waits for the
scan instead (the loop sleeps the rest, as the engine does from ``WAKE_EARLY_S`` on when
nothing else runs). Two milliseconds, as ``WAKE_EARLY_S``, left the loop idle up to a
fifth of each 10 ms period while it had work: a full snapshot's request waited for two
scans and two such sleeps (p99 latency 50 ms against 25, issue 13's load case)."""
START_SPIN_S = 0.0008
"""...the last of it spent holding the interpreter lock (at most a tenth of the period):
at the deadline the scan has the lock instead of waiting up to the switch interval for a
publisher's thread to give it back. A 10 ms scan spends about 8 % of a core on it
(load case, back to back on the loaded machine: start jitter p99 8–13 → 5–6 ms)."""


def stall_after_s(period_s: float) -> float:
    """How late a scan may start before it counts as a stall."""
    return max(STALL_PERIODS * period_s, STALL_MIN_S)


@dataclass(slots=True)
class InputBinding:
    tag: Tag
    driver: Driver
    point: str
    scaling: Scaling | None = None
    stale_after_s: float | None = None
    threshold: float | None = None  # analog → boolean (e.g. the e-stop sense voltage)
    # What the last copy saw (``ScanEngine._copy_inputs``): the driver's sample object,
    # whether it was stale, and the tag's version right after. A driver polls every 100 or
    # 200 ms and a 10 ms scan would copy the same sample ten or twenty times (issue 13);
    # a driver whose poll read what its sample says stamps the same object again with the
    # poll's time (value, quality and reason never change in place).
    _sample: Sample | None = field(default=None, init=False, repr=False, compare=False)
    _stale: bool = field(default=False, init=False, repr=False, compare=False)
    _version: int = field(default=-1, init=False, repr=False, compare=False)


@dataclass(slots=True)
class OutputBinding:
    tag: Tag
    driver: Driver
    point: str
    scaling: Scaling | None = None
    sent_version: int = -1


class DirectDriver(Protocol):
    """What a driver may offer the lockstep (virtual clock) besides :class:`Driver`: its
    poll and flush without an await, when it can tell that the awaited ones would not
    yield (an in-process simulator, nothing to wait for). Each returns False, having done
    nothing, when they would: the engine then awaits ``poll()`` or ``flush()``. A dry run
    polls and flushes 87 000 times: a coroutine each was a fifth of the engine's own time
    (issue 13)."""

    def poll_now(self) -> bool:
        """``await poll()``, done without an await (True), or nothing done (False)."""
        ...

    def flush_now(self) -> bool:
        """``await flush()``, done without an await (True), or nothing done (False)."""
        ...


_Stepped = tuple[
    Driver,
    int,  # id(driver): its key in ScanEngine._next_poll
    Callable[[], bool] | None,  # poll_now
    Callable[[], bool] | None,  # flush_now
    Callable[[], Awaitable[None]] | None,  # flush
]


class Publisher(Protocol):
    name: str

    def on_scan(self, db: TagDB, t: float) -> None:
        """Called at scan end; must return quickly (queue, never wait)."""
        ...


@dataclass(slots=True)
class LogicPhase:
    name: str
    run: Callable[[float, float], None]  # (now_s, dt_s)


@dataclass
class ScanStats:
    count: int = 0
    overruns: int = 0
    skipped: int = 0
    logic_errors: int = 0
    stalls: int = 0
    stall_max_s: float = 0.0
    durations_s: FloatRing = field(default_factory=lambda: FloatRing(STATS_WINDOW))
    jitters_s: FloatRing = field(default_factory=lambda: FloatRing(STATS_WINDOW))
    realtime_priority: int | None = None
    """The real-time priority the scan's thread runs at (None: normal priority)."""
    realtime_refused: str | None = None
    """Why the configured real-time priority was refused (None when it was not)."""

    @staticmethod
    def percentile(values: Iterable[float], q: float) -> float:
        s = sorted(values)
        if not s:
            return 0.0
        k = min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))
        return s[k]


class ScanEngine:
    def __init__(
        self,
        clock: Clock,
        db: TagDB,
        period_s: float,
        drivers: Sequence[Driver] = (),
        inputs: Sequence[InputBinding] = (),
        outputs: Sequence[OutputBinding] = (),
        phases: Sequence[LogicPhase] = (),
        publishers: Sequence[Publisher] = (),
    ) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        self.clock = clock
        self.db = db
        self.period_s = period_s
        self.drivers = list(drivers)
        self.inputs = list(inputs)
        self.outputs = list(outputs)
        self.phases = list(phases)
        self.publishers = list(publishers)
        self.stats = ScanStats()
        self.idle: Callable[[float], object] | None = None
        """Real clock: called after each scan with the seconds left before the next one
        (the garbage collector's turn, ``core/heap.py::collect_when_idle``)."""
        self.gate: ScanGate | None = None
        """Real clock: closed from the approach of each deadline to the end of its scan,
        so that the threads that wait at it leave the interpreter lock to the scan
        (``core/gate.py``)."""
        self.realtime: RealtimePriority | None = None
        """Real clock: the scan's thread (and the gate closer's) at this real-time priority
        while the engine runs (``scan.realtime_priority``, ``core/realtime.py``)."""
        self.yield_every_scans = 1
        """Virtual clock: let the event loop's other tasks run every this many scans (a
        dry run, with no other task to wait for, sets it high: a turn of the loop per scan
        was a tenth of its time, issue 13). 1: every scan, as a real sleep would."""
        self.measure_durations = True
        """Each scan's wall-clock duration measured: ``scan.duration_s``,
        ``scan.duration_max_s``, ``scan.overruns`` and ``stats.durations_s``. A dry run
        turns it off (its scans run back to back in virtual time: its speed is measured as
        a whole, simulated over wall time, and nothing reads a scan's; issue 13). They then
        keep their last values."""
        self.stall_after_s = stall_after_s(period_s)
        self.last_scan_mono: float | None = None
        """``time.monotonic()`` at the start of the last scan (read by :class:`StallWatch`)."""
        self._last_t: float | None = None
        self._next_t: float | None = None
        self._scan_end: asyncio.Future[None] | None = None  # ``after_next_scan``'s
        self.next_deadline: float | None = None
        """Real clock: when the next scan is due (the clock's axis)."""
        self._start_t = 0.0  # real clock: the first scan's deadline, and the scans since
        self._k = 0
        self._done = 0
        self._in_scan = False
        self._hook_due: float | None = None
        """The deadline ``_scan_first`` may run the scan of (None: the coroutine's)."""
        self._hook_stop: asyncio.Event | None = None
        self.deadlines_set = 0
        self._deadline_event = threading.Event()
        self._next_poll: dict[int, float] = {}
        # The lockstep's view of the drivers (``_stepped``), built for ``_stepped_of``.
        self._stepped_list: list[_Stepped] = []
        self._flushes: list[tuple[Callable[[], bool] | None, Callable[[], Awaitable[None]]]] = []
        self._stepped_of: list[Driver] | None = None
        self._plan: list[tuple[Driver, list[InputBinding]]] = []
        self._plan_of: list[InputBinding] | None = None
        self._plan_len = 0
        self._stats_tags = self._declare_stats_tags()
        # The ones every scan writes or reads, without a lookup by name.
        tags = self._stats_tags
        self._duration_tag = tags["scan.duration_s"]
        self._jitter_tag = tags["scan.jitter_s"]
        self._duration_max_tag = tags["scan.duration_max_s"]
        self._overruns_tag = tags["scan.overruns"]
        self._count_tag = tags["scan.count"]
        self._logic_errors_tag = tags["scan.logic_errors"]
        self._conn_tags = self._declare_driver_tags()

    # --- declarations ------------------------------------------------------------
    def _declare_stats_tags(self) -> dict[str, Tag]:
        specs = [
            TagSpec("scan.period_s", unit="s", description="Configured scan period"),
            TagSpec("scan.duration_s", unit="s", description="Duration of the last scan"),
            TagSpec("scan.duration_max_s", unit="s", description="Longest scan so far"),
            TagSpec("scan.jitter_s", unit="s", description="Start lateness of the last scan"),
            TagSpec("scan.overruns", dtype="int", description="Scans longer than the period"),
            TagSpec("scan.count", dtype="int", description="Scans since start"),
            TagSpec("scan.logic_errors", dtype="int", description="Exceptions caught in logic"),
            TagSpec(
                "scan.stalls",
                dtype="int",
                description="Scans that started more than max(2 periods, 0.25 s) late:"
                " the event loop was held between two scans",
            ),
            TagSpec("scan.stall_max_s", unit="s", description="Lateness of the worst stall"),
            TagSpec(
                "scan.stall_s",
                unit="s",
                description="How late this scan started if it was a stall, else 0",
            ),
        ]
        out = {}
        for s in specs:
            out[s.name] = self.db.get(s.name) or self.db.add(s)
        self.db.update(out["scan.period_s"], self.period_s)
        for name in ("scan.stalls", "scan.stall_max_s", "scan.stall_s"):
            self.db.update(out[name], 0 if name == "scan.stalls" else 0.0)
        return out

    def _declare_driver_tags(self) -> list[tuple[Driver, Tag, Tag]]:
        out = []
        for d in self.drivers:
            c = self.db.get(f"{d.name}.connected") or self.db.add(
                TagSpec(f"{d.name}.connected", dtype="bool", description="Device answers")
            )
            f = self.db.get(f"{d.name}.comm_failures") or self.db.add(
                TagSpec(f"{d.name}.comm_failures", dtype="int", description="Failed polls")
            )
            out.append((d, c, f))
        return out

    # --- one scan ----------------------------------------------------------------
    async def poll_due_drivers(self) -> None:
        """Lockstep mode (virtual clock): poll drivers whose period is due, in order."""
        await self._poll_due_from(self.clock.now(), 0)

    async def _poll_due_from(self, now: float, first: int) -> None:
        """:meth:`poll_due_drivers` from the driver at ``first`` on, with ``now`` read
        before the first one (a poll may move a virtual clock: a relay's settling time)."""
        for d in self.drivers[first:]:
            due = self._next_poll.get(id(d), now)
            if now >= due:
                await d.poll()
                nxt = due + d.poll_period_s
                self._next_poll[id(d)] = nxt if nxt > now else now + d.poll_period_s

    async def flush_drivers(self) -> None:
        """Lockstep mode (virtual clock): send the writes this scan queued, in order, as the
        drivers' own tasks do on a real clock as soon as they are queued."""
        await self._flush_from(0)

    async def _flush_from(self, first: int) -> None:
        """:meth:`flush_drivers` from the flush at ``first`` on."""
        self._stepped()
        for _, flush in self._flushes[first:]:
            await flush()

    def _stepped(self) -> list[_Stepped]:
        """Each driver with what the lockstep calls of it, looked up again only when the
        drivers change (a Driver that only polls has no ``flush``)."""
        if self._stepped_of != self.drivers:
            stepped: list[_Stepped] = []
            flushes: list[tuple[Callable[[], bool] | None, Callable[[], Awaitable[None]]]] = []
            for d in self.drivers:
                poll_now = getattr(d, "poll_now", None)
                flush_now = getattr(d, "flush_now", None)
                flush = getattr(d, "flush", None)
                stepped.append((d, id(d), poll_now, flush_now, flush))
                if flush is not None:
                    flushes.append((flush_now, flush))
            self._stepped_list, self._flushes = stepped, flushes
            self._stepped_of = list(self.drivers)
        return self._stepped_list

    def note_start(self, late_s: float) -> None:
        """This scan starts ``late_s`` after its deadline: count a stall (before the scan,
        so its safety phase sees ``scan.stall_s``)."""
        self.last_scan_mono = time.monotonic()
        tags, st = self._stats_tags, self.stats
        if late_s <= self.stall_after_s:
            if tags["scan.stall_s"].value != 0.0:
                self.db.update(tags["scan.stall_s"], 0.0)
            return
        st.stalls += 1
        st.stall_max_s = max(st.stall_max_s, late_s)
        log.warning(
            "scan: started %.3f s late (a stall: more than %g s): the event loop was held"
            " between two scans (stall %d)",
            late_s,
            self.stall_after_s,
            st.stalls,
        )
        self.db.update(tags["scan.stalls"], st.stalls)
        self.db.update(tags["scan.stall_max_s"], st.stall_max_s)
        self.db.update(tags["scan.stall_s"], late_s)

    def scan_once(self) -> None:
        """Inputs, logic, outputs, publish — synchronous: the scan never awaits I/O."""
        t0 = _perf_counter() if self.measure_durations else None
        now = self.clock.now()
        last_t = self._last_t
        dt = 0.0 if last_t is None else now - last_t
        self._last_t = now
        db = self.db
        db.set_scan_time(now)
        self._copy_inputs(now)
        for phase in self.phases:
            try:
                phase.run(now, dt)
            except Exception:  # an exception in logic is an alarm, not a crash
                self.stats.logic_errors += 1
                log.exception("scan: logic phase %r failed", phase.name)
        if self.outputs:
            self._queue_outputs()
        for pub in self.publishers:
            try:
                pub.on_scan(db, now)
            except Exception:
                log.exception("scan: publisher %r failed", pub.name)
        st = self.stats
        st.count += 1
        update = db.update
        if t0 is not None:
            duration = _perf_counter() - t0
            st.durations_s.append(duration)
            if duration > self.period_s:
                st.overruns += 1
            update(self._duration_tag, duration)
            if duration > (self._duration_max_tag.value or 0.0):  # type: ignore[operator]
                update(self._duration_max_tag, duration)
            if self._overruns_tag.value != st.overruns:  # rare: no update call per scan
                update(self._overruns_tag, st.overruns)
        update(self._count_tag, st.count)
        if self._logic_errors_tag.value != st.logic_errors:
            update(self._logic_errors_tag, st.logic_errors)

    def _copy_inputs(self, now: float) -> None:
        """``now``: the scan's time, which ``scan_once`` gave the database."""
        db = self.db
        update = db.update
        for d, ctag, ftag in self._conn_tags:
            # Both change a few times a run: an update only when it would change the tag
            # (ADR 0037: an unchanged one is left as it is; no call most scans).
            connected = d.connected
            if connected != ctag.value or ctag.quality is not _GOOD or ctag.reason is not _NONE:
                update(ctag, connected)
            failures = getattr(d, "failures", 0)
            if failures != ftag.value or ftag.quality is not _GOOD or ftag.reason is not _NONE:
                update(ftag, failures)
        inputs = self.inputs
        if self._plan_of is not inputs or self._plan_len != len(inputs):
            self._input_plan()
        for d, bindings in self._plan:
            image = d.image()  # once per driver, not per input: one consistent snapshot
            for b in bindings:
                s = image.get(b.point)
                tag = b.tag
                if s is None:
                    update(tag, None, _BAD, Reason.NOT_CONNECTED)
                    b._sample = None
                    continue
                stale_after_s = b.stale_after_s
                stale = (
                    stale_after_s is not None
                    and s.quality is not _BAD
                    and now - s.t > stale_after_s
                )
                if s is b._sample and stale is b._stale and tag.version == b._version:
                    # The same sample, as fresh as last scan, and nobody changed the tag
                    # since: the update would compute what it did then and change nothing
                    # but the source time (a driver may stamp a sample again in place with
                    # a newer time, never change its value, quality or reason: a new poll
                    # that read the same is the same object, ``devices/chadeche/
                    # driver.py``).
                    db.stamp(tag, s.t)
                    continue
                value: Value | None = s.value
                quality, reason = s.quality, s.reason
                if b.scaling is not None and isinstance(value, int | float) and value is not True:
                    value = b.scaling.to_eu(float(value))
                if b.threshold is not None and isinstance(value, int | float):
                    value = value >= b.threshold
                if stale:
                    quality, reason = _BAD, Reason.STALE
                update(tag, value, quality, reason, s.t)
                # A NaN never equals itself: every copy of it is a change, as update says.
                b._sample = s if tag.value == tag.value else None
                b._stale = stale
                b._version = tag.version

    def _input_plan(self) -> list[tuple[Driver, list[InputBinding]]]:
        """The input bindings grouped by driver, each driver once, in the order of their
        first binding (built again if someone replaced or grew ``inputs``): a driver's
        image is taken once per scan and every one of its inputs copied from it."""
        inputs = self.inputs
        if self._plan_of is not inputs or self._plan_len != len(inputs):
            groups: dict[int, tuple[Driver, list[InputBinding]]] = {}
            for b in inputs:
                group = groups.get(id(b.driver))
                if group is None:
                    group = groups[id(b.driver)] = (b.driver, [])
                group[1].append(b)
            self._plan, self._plan_of, self._plan_len = list(groups.values()), inputs, len(inputs)
        return self._plan

    def _queue_outputs(self) -> None:
        for b in self.outputs:
            tag = b.tag
            if tag.version == b.sent_version or tag.value is None:
                continue
            b.sent_version = tag.version
            value = tag.value
            if b.scaling is not None and isinstance(value, int | float):
                value = b.scaling.to_raw(float(value))
            try:
                b.driver.write(b.point, value)
            except Exception:
                log.exception("scan: write %s → %s.%s failed", tag.name, b.driver.name, b.point)

    # --- loops ---------------------------------------------------------------------
    async def run(
        self, stop: asyncio.Event, max_scans: int | None = None, until_t: float | None = None
    ) -> None:
        """Scan until ``stop`` is set, ``max_scans`` are done or the clock passes ``until_t``.

        On a real clock every driver polls on its own task; on a virtual clock drivers
        are polled in lockstep before each scan so runs are deterministic.
        """
        tasks: list[asyncio.Task[None]] = []
        watch = None if self.clock.virtual else StallWatch(self)
        closer = None if self.clock.virtual or self.gate is None else GateCloser(self, self.gate)
        if not self.clock.virtual and self.stats.count == 0:
            # First images in before the first scan, so logic never starts on "not connected".
            await asyncio.gather(*(d.poll() for d in self.drivers), return_exceptions=True)
        if not self.clock.virtual:
            for d in self.drivers:
                if hasattr(d, "scan_sync"):
                    d.scan_sync = self.after_next_scan
                run = getattr(d, "run", None)
                if run is not None:
                    tasks.append(asyncio.create_task(run(), name=f"driver:{d.name}"))
        realtime = None if self.clock.virtual else self.realtime
        try:
            if realtime is not None:
                # The loop's thread: the scans and the wake-ups for their deadlines.
                raised = realtime.enter()
                self.stats.realtime_priority = realtime.priority if raised else None
                self.stats.realtime_refused = realtime.refused
            if watch is not None:
                watch.start()
            if closer is not None:
                closer.start()
            await self._loop(stop, max_scans, until_t)
        finally:
            if realtime is not None:
                realtime.leave()
                self.stats.realtime_priority = None
            if closer is not None:
                closer.stop()
            if self.gate is not None:
                self.gate.open()
            self._scan_ended()  # nobody waits for a scan that will not come
            self.next_deadline = None  # and none is due
            if watch is not None:
                watch.stop()
            for t in tasks:
                t.cancel()
            # Bounded: a driver task that does not end must not keep the shutdown (and the
            # safe state that follows it) waiting.
            _, stuck = await asyncio.wait(tasks, timeout=DRIVER_STOP_S) if tasks else ((), ())
            for t in stuck:
                log.error("scan: %s did not stop within %g s", t.get_name(), DRIVER_STOP_S)

    async def _loop(
        self, stop: asyncio.Event, max_scans: int | None, until_t: float | None
    ) -> None:
        clock = self.clock
        if clock.virtual:
            await self._lockstep_loop(stop, max_scans, until_t)
            return
        self._start_t = clock.now()
        self._k = 0
        self._done = 0
        # A loop that runs a due scan before its next callback (``ScanFirstLoop``) may
        # start the scans of an unbounded run itself: ``_scan_first``.
        running = asyncio.get_running_loop()
        loop = running if isinstance(running, ScanFirstLoop) else None
        first = loop is not None and max_scans is None and until_t is None
        if first and loop is not None:
            self._hook_stop = stop
            loop.scan_first = self._scan_first
        try:
            waited = False
            while not stop.is_set():
                scheduled = self._start_t + self._k * self.period_s
                if until_t is not None and scheduled >= until_t - 1e-9:
                    self._next_t = scheduled
                    return
                if waited:
                    if clock.now() < scheduled - WAKE_EARLY_S:
                        # The loop ran the scan this coroutine waited for: the next one.
                        await clock.sleep_until(scheduled - WAKE_EARLY_S)
                        continue
                    self._wait_on_thread(scheduled)
                self._hook_due = None  # this scan is the coroutine's
                last = max_scans is not None and self._done + 1 >= max_scans
                nxt = self._scan_at(scheduled, announce=not last)
                if last:
                    return
                if first:
                    self._hook_due = nxt
                await clock.sleep_until(nxt - WAKE_EARLY_S)
                # The loop may have run that scan (and more) meanwhile: the next one due.
                waited = True
        finally:
            self._hook_due = None
            if first and loop is not None:
                loop.scan_first = None

    def _scan_first(self) -> None:
        """``ScanFirstLoop``'s hook, before each of its callbacks: the scan due within
        ``SCAN_FIRST_EARLY_S`` runs now (on time: the rest slept), before that callback,
        rather than after every callback ready in this turn of the loop (issue 13's start
        jitter: the engine's own wake-up is a timer, and a turn runs every ready callback
        before its timers)."""
        t = self._hook_due
        if t is None or self._in_scan or self.clock.now() < t - SCAN_FIRST_EARLY_S:
            return
        if self._hook_stop is not None and self._hook_stop.is_set():
            return
        self._hook_due = None
        try:
            self._wait_on_thread(t)
            self._hook_due = self._scan_at(t)
        except Exception:  # never the callback's failure: the coroutine's loop goes on
            log.exception("scan: the scan run ahead of the loop's callbacks failed")

    def _scan_at(self, scheduled: float, announce: bool = True) -> float:
        """The scan due at ``scheduled`` (real clock), now; returns the next deadline (the
        deadlines missed skipped) and, ``announce``, tells the gate closer and does the
        idle work (not after the last scan of a bounded run)."""
        clock = self.clock
        late = max(0.0, clock.now() - scheduled)
        self.stats.jitters_s.append(late)
        self.db.update(self._jitter_tag, late)
        self.note_start(late)
        if self.gate is not None:
            self.gate.close()  # already, unless this scan came without a wait
        self._in_scan = True
        try:
            self.scan_once()
        finally:
            self._in_scan = False
            if self.gate is not None:
                self.gate.open()
            self._scan_ended()
        self._done += 1
        self._k += 1
        nxt = self._start_t + self._k * self.period_s
        now = clock.now()
        if nxt <= now:
            # Overrun or stall: skip the deadlines already missed instead of bursting.
            missed = int((now - nxt) / self.period_s) + 1
            self.stats.skipped += missed
            self._k += missed
            nxt = self._start_t + self._k * self.period_s
        self._next_t = nxt
        if not announce:
            return nxt
        self.deadline_set(nxt)
        if self.idle is not None:
            try:
                self.idle(nxt - clock.now())
            except Exception:  # the idle work's failure must not stop the scan
                log.exception("scan: idle work failed")
        return nxt

    async def _lockstep_loop(
        self, stop: asyncio.Event, max_scans: int | None, until_t: float | None
    ) -> None:
        """:meth:`_loop` on a virtual clock: the drivers polled before each scan and
        flushed after it, in lockstep, without an await when they offer a direct path
        (:class:`DirectDriver`), so that a dry run's scans run back to back."""
        clock = self.clock
        if self._next_t is not None:
            # Continue the virtual timeline where the previous run stopped.
            await clock.sleep_until(self._next_t)
        start = clock.now()
        period_s = self.period_s
        stats = self.stats
        stall_tag = self._stats_tags["scan.stall_s"]
        next_poll = self._next_poll
        # A virtual clock of another kind sleeps its own way, every scan. Ours is read and
        # moved through its attribute (``VirtualClock.t_s``): three reads and a move a scan,
        # a call each (issue 13's dry run).
        virtual = clock if isinstance(clock, VirtualClock) else None
        now_of = clock.now
        scan_once = self.scan_once
        stopped = stop.is_set
        end_t = None if until_t is None else until_t - 1e-9
        k = 0
        done = 0
        while not stopped():
            scheduled = start + k * period_s
            if end_t is not None and scheduled >= end_t:
                self._next_t = scheduled
                return
            # ``poll_due_drivers`` without an await, for as long as each due driver polls
            # without one (its ``poll_now``, :class:`DirectDriver`); from the first that
            # did nothing on, awaited (the same ``now``). Written out here, as is the
            # flush below: a call less each, every scan.
            now = now_of() if virtual is None else virtual.t_s
            stepped = self._stepped_list if self._stepped_of == self.drivers else self._stepped()
            polled = 0
            for d, key, poll_now, _, _ in stepped:
                due = next_poll.get(key, now)
                if now >= due:
                    if poll_now is None or not poll_now():
                        break
                    nxt = due + d.poll_period_s
                    next_poll[key] = nxt if nxt > now else now + d.poll_period_s
                polled += 1
            if polled < len(stepped):
                await self._poll_due_from(now, polled)
            late = (now_of() if virtual is None else virtual.t_s) - scheduled
            # A scan is late only when something moved the clock between two scans: what
            # a held loop looks like in virtual time. ``note_start`` when it has anything
            # to do (``late`` within the limit and ``scan.stall_s`` at 0: nothing but
            # ``last_scan_mono``, which only the real clock's stall watch reads).
            if late > self.stall_after_s or stall_tag.value != 0.0:
                self.note_start(late if late > 0.0 else 0.0)  # max(0.0, late), no call
            gate = self.gate
            if gate is None:
                scan_once()
            else:
                gate.close()
                try:
                    scan_once()
                finally:
                    gate.open()
            if self._stepped_of != self.drivers:
                self._stepped()
            flushes = self._flushes
            flushed = 0
            for flush_now, _ in flushes:
                if flush_now is None or not flush_now():
                    break
                flushed += 1
            if flushed < len(flushes):
                await self._flush_from(flushed)
            done += 1
            k += 1
            nxt = start + k * period_s
            now = now_of() if virtual is None else virtual.t_s
            if nxt <= now:
                # A poll, a flush or a scan moved the clock past the next deadline: skip
                # the deadlines already missed instead of bursting.
                missed = int((now - nxt) / period_s) + 1
                stats.skipped += missed
                k += missed
                nxt = start + k * period_s
            self._next_t = nxt
            if max_scans is not None and done >= max_scans:
                return
            if virtual is None or done % self.yield_every_scans == 0:
                await clock.sleep_until(nxt)
            elif nxt > now:  # the clock stands at ``now``: nothing ran since
                virtual.t_s = nxt  # ``virtual.advance``: no other task's turn this scan

    async def after_next_scan(self) -> None:
        """Real clock: return once the next scan is done (at most two periods: a scan that
        does not come must not stop a driver). The drivers start their polls here
        (``PolledDriver.scan_sync``): a poll's callbacks on this loop then run in the
        period's first milliseconds, not when the engine should wake for its deadline
        (the ADAM's took 1.5–13 ms on the loaded machine, issue 13's start jitter)."""
        fut = self._scan_end
        if fut is None:
            fut = self._scan_end = asyncio.get_running_loop().create_future()
        await asyncio.wait((fut,), timeout=2 * self.period_s)

    def deadline_set(self, t: float) -> None:
        """The next scan is due at ``t`` (real clock; for the ``GateCloser``)."""
        self.next_deadline = t
        self.deadlines_set += 1
        self._deadline_event.set()

    def _scan_ended(self) -> None:
        fut, self._scan_end = self._scan_end, None
        if fut is not None and not fut.done():
            fut.set_result(None)

    def _wait_on_thread(self, t: float) -> None:
        """Real clock: the last ``WAKE_EARLY_S`` before ``t``, on the thread, on time. The
        event loop's selector (epoll) rounds its timeout up to a whole millisecond, so an
        ``asyncio.sleep`` to the deadline wakes 0–1 ms late, the start jitter issue 13
        measured: the loop is asked to wake ``WAKE_EARLY_S`` before the deadline
        (everything else on it runs meanwhile) and the rest is slept here."""
        clock = self.clock
        if self.gate is not None:
            self.gate.close()  # the threads at the gate keep out of the scan's way
        spin_s = min(START_SPIN_S, self.period_s / 10)
        rest_s = t - clock.now() - spin_s
        if rest_s > 0:
            time.sleep(rest_s)
        # Holding the interpreter lock for the last fraction: a publisher's thread that
        # took it while we slept would otherwise keep it up to the switch interval past
        # the deadline (ADR 0021).
        mono = time.monotonic
        while mono() < t:
            pass

    async def run_for(self, duration_s: float) -> None:
        """Run the scans due in ``[now, now + duration_s)`` (virtual: as fast as the CPU allows).

        On a virtual clock the clock stands at ``now + duration_s`` afterwards and the
        next run continues the same timeline.
        """
        start = self._next_t if (self.clock.virtual and self._next_t is not None) else None
        t0 = self.clock.now() if start is None else start
        await self.run(asyncio.Event(), until_t=t0 + duration_s)


class ScanFirstLoop(HookedLoop):
    """The scan's event loop: before each callback it runs (task steps, futures' callbacks,
    everything handed to ``call_soon``), and after each wait for I/O, it gives the scan
    engine the chance to run a scan that falls due (``ScanEngine._scan_first``). A scan
    then waits for the callback under way at its deadline at most, not for every callback
    ready in the same turn of the loop, which run before any timer's (issue 13). Nothing
    changes for a callback: it runs between two scans, as on any loop; only the order of
    the scan among the ready callbacks does. ``supervisor run`` runs on it."""

    def __init__(self) -> None:
        super().__init__()
        self.scan_first: Callable[[], None] | None = None

    def before(self) -> None:
        hook = self.scan_first
        if hook is not None:
            hook()


class GateCloser:
    """Real clock: a thread that closes the scan gate ``GATE_EARLY_S`` before each deadline,
    whatever the scan's event loop is doing then. The loop closes it too when it wakes for
    the deadline (``WAKE_EARLY_S``), but it wakes late when a callback runs long or when its
    own I/O lets the interpreter lock go to a busy thread (issue 13: the wake-up late by
    p99 5.6 ms in the load case): with the gate closed by then, the threads that wait at it
    have stopped taking the lock, and the loop gets it at once. The engine opens the gate
    when its scan is done, as before."""

    def __init__(self, engine: ScanEngine, gate: ScanGate) -> None:
        self.engine = engine
        self.gate = gate
        self.early_s = min(GATE_EARLY_S, engine.period_s / 3)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="scan gate closer", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.engine._deadline_event.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)

    def _run(self) -> None:
        engine, clock, stop = self.engine, self.engine.clock, self._stop
        event = engine._deadline_event
        if engine.realtime is not None and engine.stats.realtime_priority is not None:
            # As the scan's: a closer waiting for a core would close the gate late.
            RealtimePriority(engine.realtime.priority, "scan gate closer").enter()
        seen = -1
        while not stop.is_set():
            # The deadline the engine set after its last scan (a new one each scan).
            while engine.deadlines_set == seen and not stop.is_set():
                event.wait(2 * engine.period_s)
                event.clear()
            seen, t, scans = engine.deadlines_set, engine.next_deadline, engine.stats.count
            if t is None:
                continue
            left_s = t - self.early_s - clock.now()
            if left_s > 0 and stop.wait(left_s):
                return
            if engine.stats.count == scans:  # that scan has not come and gone meanwhile
                self.gate.close()


class StallWatch:
    """A thread that notices "no scan for a while" while the event loop is held, when
    nothing on the loop can (real clock only): it logs once per stall, at once, with the
    innermost frames of the loop's thread — what holds it. The scan counts and alarms the
    stall itself when it runs again (:meth:`ScanEngine.note_start`)."""

    FRAMES = 8
    """Innermost frames of the loop's thread logged."""

    def __init__(self, engine: ScanEngine) -> None:
        self.engine = engine
        # A scan is due every period; one missing for longer than this is a stall.
        self.after_s = engine.stall_after_s + engine.period_s
        self._loop_thread = threading.get_ident()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="scan stall watch", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)

    def _watch(self) -> None:
        reported: float | None = None
        while not self._stop.wait(self.engine.stall_after_s / 2):
            last = self.engine.last_scan_mono
            if last is None:
                continue
            held_s = time.monotonic() - last
            if held_s > self.after_s and reported != last:
                reported = last
                log.warning(
                    "scan: no scan for %.2f s: the event loop is held; its thread is in:\n%s",
                    held_s,
                    self._where(),
                )

    def _where(self) -> str:
        frame = sys._current_frames().get(self._loop_thread)
        if frame is None:
            return "  (unknown)"
        # File, line and function only: formatting the source lines too would read every
        # file of the stack into linecache for good (megabytes over a day of stalls).
        frames = list(traceback.walk_stack(frame))[: self.FRAMES]
        return "\n".join(
            f'  File "{f.f_code.co_filename}", line {line}, in {f.f_code.co_name}'
            for f, line in reversed(frames)
        )
