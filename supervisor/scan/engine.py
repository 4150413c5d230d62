"""One scan, as a PLC does it (DESIGN.md "One scan"; docs/adr/0002-scan-timing.md).

1. Inputs: copy every driver image into the tag database in one synchronous step, so
   logic sees one consistent snapshot; an input older than its stale limit turns BAD.
2. Logic: phases in order (derived values, interlocks and alarms, step chains). An
   exception in a phase is counted and logged; the phase's owner decides what goes safe.
3. Outputs: output tags whose value changed are queued to their driver (never awaited);
   the driver's own task sends them at once (DESIGN.md "Safety": output writes leave when
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
from supervisor.core.quality import Quality, Reason
from supervisor.core.ring import FloatRing
from supervisor.tags.db import Tag, TagDB
from supervisor.tags.spec import Scaling, TagSpec

log = logging.getLogger(__name__)

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
thread (:meth:`ScanEngine._wait_for_deadline`)."""
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
    # 200 ms and a 10 ms scan would copy the same sample ten or twenty times (issue 13).
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
        self.yield_every_scans = 1
        """Virtual clock: let the event loop's other tasks run every this many scans (a
        dry run, with no other task to wait for, sets it high: a turn of the loop per scan
        was a tenth of its time, issue 13). 1: every scan, as a real sleep would."""
        self.stall_after_s = stall_after_s(period_s)
        self.last_scan_mono: float | None = None
        """``time.monotonic()`` at the start of the last scan (read by :class:`StallWatch`)."""
        self._last_t: float | None = None
        self._next_t: float | None = None
        self._next_poll: dict[int, float] = {}
        self._flushes: list[Callable[[], Awaitable[None]]] | None = None
        self._flushes_of: list[Driver] = []
        self._plan: list[tuple[InputBinding, int]] = []
        self._input_drivers: list[Driver] = []
        self._plan_of: list[InputBinding] | None = None
        self._stats_tags = self._declare_stats_tags()
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
        now = self.clock.now()
        for d in self.drivers:
            due = self._next_poll.get(id(d), now)
            if now >= due:
                await d.poll()
                nxt = due + d.poll_period_s
                self._next_poll[id(d)] = nxt if nxt > now else now + d.poll_period_s

    async def flush_drivers(self) -> None:
        """Lockstep mode (virtual clock): send the writes this scan queued, in order, as the
        drivers' own tasks do on a real clock as soon as they are queued."""
        flushes = self._flushes
        if flushes is None or self._flushes_of != self.drivers:
            # A Driver that only polls has none; looked up again only if the drivers change.
            found = (getattr(d, "flush", None) for d in self.drivers)
            flushes = self._flushes = [f for f in found if f is not None]
            self._flushes_of = list(self.drivers)
        for flush in flushes:
            await flush()

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
        t0 = time.perf_counter()
        now = self.clock.now()
        dt = 0.0 if self._last_t is None else now - self._last_t
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
        self._queue_outputs()
        for pub in self.publishers:
            try:
                pub.on_scan(db, now)
            except Exception:
                log.exception("scan: publisher %r failed", pub.name)
        duration = time.perf_counter() - t0
        st = self.stats
        st.count += 1
        st.durations_s.append(duration)
        if duration > self.period_s:
            st.overruns += 1
        tags = self._stats_tags
        db.update(tags["scan.duration_s"], duration)
        if duration > (tags["scan.duration_max_s"].value or 0.0):  # type: ignore[operator]
            db.update(tags["scan.duration_max_s"], duration)
        if tags["scan.overruns"].value != st.overruns:  # rare: no update call per scan
            db.update(tags["scan.overruns"], st.overruns)
        db.update(tags["scan.count"], st.count)
        if tags["scan.logic_errors"].value != st.logic_errors:
            db.update(tags["scan.logic_errors"], st.logic_errors)

    def _copy_inputs(self, now: float) -> None:
        db = self.db
        update = db.update
        for d, ctag, ftag in self._conn_tags:
            update(ctag, d.connected)
            update(ftag, getattr(d, "failures", 0))
        bad = Quality.BAD
        plan = self._input_plan()
        images = [d.image() for d in self._input_drivers]  # once per driver, not per input
        for b, slot in plan:
            s = images[slot].get(b.point)
            tag = b.tag
            if s is None:
                update(tag, None, bad, Reason.NOT_CONNECTED)
                b._sample = None
                continue
            stale_after_s = b.stale_after_s
            stale = stale_after_s is not None and s.quality is not bad and now - s.t > stale_after_s
            if (
                s is b._sample
                and stale is b._stale
                and tag.version == b._version
                and tag.source_t == s.t
            ):
                # The same sample, as fresh as last scan, and nobody touched the tag since:
                # the update would compute what it did then and change nothing.
                continue
            value: Value | None = s.value
            quality, reason = s.quality, s.reason
            if b.scaling is not None and isinstance(value, int | float) and value is not True:
                value = b.scaling.to_eu(float(value))
            if b.threshold is not None and isinstance(value, int | float):
                value = value >= b.threshold
            if stale:
                quality, reason = bad, Reason.STALE
            update(tag, value, quality, reason, s.t)
            # A NaN never equals itself: every copy of it is a change, as update says.
            b._sample = s if tag.value == tag.value else None
            b._stale = stale
            b._version = tag.version

    def _input_plan(self) -> list[tuple[InputBinding, int]]:
        """Each input binding with the index of its driver in ``_input_drivers`` (built
        again if someone replaced ``inputs``)."""
        inputs = self.inputs
        if self._plan_of is not inputs or len(self._plan) != len(inputs):
            slots: dict[int, int] = {}
            drivers: list[Driver] = []
            plan = []
            for b in inputs:
                slot = slots.get(id(b.driver))
                if slot is None:
                    slot = slots[id(b.driver)] = len(drivers)
                    drivers.append(b.driver)
                plan.append((b, slot))
            self._plan, self._input_drivers, self._plan_of = plan, drivers, inputs
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
        if not self.clock.virtual and self.stats.count == 0:
            # First images in before the first scan, so logic never starts on "not connected".
            await asyncio.gather(*(d.poll() for d in self.drivers), return_exceptions=True)
        if not self.clock.virtual:
            for d in self.drivers:
                run = getattr(d, "run", None)
                if run is not None:
                    tasks.append(asyncio.create_task(run(), name=f"driver:{d.name}"))
        try:
            if watch is not None:
                watch.start()
            await self._loop(stop, max_scans, until_t)
        finally:
            if self.gate is not None:
                self.gate.open()
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
        if clock.virtual and self._next_t is not None:
            # Continue the virtual timeline where the previous run stopped.
            await clock.sleep_until(self._next_t)
        start = clock.now()
        k = 0
        done = 0
        jtag = self._stats_tags["scan.jitter_s"]
        while not stop.is_set():
            scheduled = start + k * self.period_s
            if until_t is not None and scheduled >= until_t - 1e-9:
                self._next_t = scheduled
                return
            if clock.virtual:
                await self.poll_due_drivers()
            late = max(0.0, clock.now() - scheduled)
            if not clock.virtual:
                self.stats.jitters_s.append(late)
                self.db.update(jtag, late)
            # On a virtual clock a scan is late only when something moved the clock
            # between two scans: what a held loop looks like in virtual time.
            self.note_start(late)
            if self.gate is not None:
                self.gate.close()  # already, unless this scan came without a wait
            try:
                self.scan_once()
            finally:
                if self.gate is not None:
                    self.gate.open()
            if clock.virtual:
                await self.flush_drivers()
            done += 1
            k += 1
            nxt = start + k * self.period_s
            now = clock.now()
            if nxt <= now:
                # Overrun or stall: skip the deadlines already missed instead of bursting.
                missed = int((now - nxt) / self.period_s) + 1
                self.stats.skipped += missed
                k += missed
                nxt = start + k * self.period_s
            self._next_t = nxt
            if max_scans is not None and done >= max_scans:
                return
            if not clock.virtual and self.idle is not None:
                try:
                    self.idle(nxt - clock.now())
                except Exception:  # the idle work's failure must not stop the scan
                    log.exception("scan: idle work failed")
            if clock.virtual:
                if done % self.yield_every_scans == 0 or not isinstance(clock, VirtualClock):
                    await clock.sleep_until(nxt)
                elif nxt > clock.now():
                    clock.advance(nxt - clock.now())  # no other task's turn this scan
            else:
                await self._wait_for_deadline(nxt)

    async def _wait_for_deadline(self, t: float) -> None:
        """Real clock: until ``t``, on time. The event loop's selector (epoll) rounds its
        timeout up to a whole millisecond, so an ``asyncio.sleep`` to the deadline wakes
        0–1 ms late, the start jitter issue 13 measured. The loop is asked to wake
        ``WAKE_EARLY_S`` before the deadline (everything else on it runs meanwhile); the
        last fraction of a millisecond is slept on the thread."""
        clock = self.clock
        await clock.sleep_until(t - WAKE_EARLY_S)
        if self.gate is not None:
            self.gate.close()  # the threads at the gate keep out of the scan's way
        spin_s = min(START_SPIN_S, self.period_s / 10)
        rest_s = t - clock.now() - spin_s
        if rest_s > 0:
            time.sleep(rest_s)  # noqa: ASYNC251 - under WAKE_EARLY_S, on purpose
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
