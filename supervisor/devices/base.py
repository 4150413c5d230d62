"""Common poller: connect with backoff, flush queued writes, read, keep the image honest.

Every concrete driver implements the four ``_`` hooks; this class owns the policy that
must be the same everywhere: a failed poll never leaves an old value looking GOOD, a
lost device is logged once and its recovery once (Home Assistant practice), reconnects
back off exponentially, and the safe state is attempted even when things are failing.

Output writes leave when the scan queues them (docs/design.md "Safety"): ``write()`` wakes the
driver's own task, which writes the pending outputs at once (:meth:`PolledDriver.flush`),
between its polls, without reading the inputs; on a virtual clock the scan engine calls
:meth:`PolledDriver.flush` right after each scan instead. One lock serialises polls,
flushes, the safe state and close, so a write never interleaves with a poll's requests.
"""

from __future__ import annotations

import asyncio
import logging
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Awaitable, Callable, Mapping

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import SupervisorError
from supervisor.core.quality import Quality, Reason

log = logging.getLogger(__name__)

BACKOFF_START_S = 0.5
BACKOFF_MAX_S = 30.0


class PolledDriver(ABC):
    """Base for drivers that poll a device on their own task."""

    def __init__(self, name: str, clock: Clock, poll_period_s: float) -> None:
        if poll_period_s <= 0:
            raise ValueError(f"{name}: poll_period_s must be > 0")
        self.name = name
        self.clock = clock
        self.poll_period_s = poll_period_s
        self._image: dict[str, Sample] = {}
        self._pending: dict[str, Value] = {}
        self._io_cycle = asyncio.Lock()
        """Held by every exchange with the device (poll, flush, safe state, close)."""
        self._wake = asyncio.Event()
        """Set by ``write()``: the driver's task flushes without waiting for its next poll."""
        self._connected = False
        self._ever_connected = False
        """Connected at least once: it may have energised outputs (:meth:`safe_state`)."""
        self._lost_logged = False
        self._backoff_s = BACKOFF_START_S
        self._next_connect_t = float("-inf")
        self.polls = 0
        self.failures = 0
        self.scan_sync: Callable[[], Awaitable[None]] | None = None
        """Set by the scan engine on a real clock (``ScanEngine.after_next_scan``): a poll
        that is due starts when the next scan is done, so that its work on the loop comes
        in the period's first milliseconds, never when the scan should start."""
        self.last_error: str = ""
        # Last raw exchanges, for diagnostics when a device misbehaves.
        self.raw_log: deque[str] = deque(maxlen=32)
        for p in self.points().values():
            if p.direction == "in":
                self._image[p.name] = Sample(None, Quality.BAD, Reason.NOT_CONNECTED, 0.0)

    # --- hooks -----------------------------------------------------------------
    @abstractmethod
    def points(self) -> Mapping[str, PointInfo]:
        """Points of this device (inputs and outputs)."""

    @abstractmethod
    async def _connect(self) -> None:
        """Open the transport and check the device; raise SupervisorError on failure."""

    @abstractmethod
    async def _read(self) -> dict[str, Sample]:
        """Read every input point; raise SupervisorError if the device cannot be read."""

    @abstractmethod
    async def _write(self, point: str, value: Value) -> None:
        """Write one output and verify it; raise SupervisorError if it does not verify."""

    @abstractmethod
    async def _safe(self) -> None:
        """Drive every output of the device to its safe value."""

    async def _disconnect(self) -> None:  # noqa: B027 - optional hook
        """Close the transport (optional)."""

    # --- public surface --------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._connected

    def image(self) -> Mapping[str, Sample]:
        return self._image

    @property
    def pending(self) -> Mapping[str, Value]:
        """Writes queued and not sent yet (latest value per point)."""
        return self._pending

    def write(self, point: str, value: Value) -> None:
        """Queue a write; the latest value per point wins. Never blocks: it wakes the
        driver's task, which sends it at once (see :meth:`flush`)."""
        info = self.points().get(point)
        if info is None or info.direction != "out":
            raise KeyError(f"{self.name}: no output point {point!r}")
        self._pending[point] = value
        self._wake.set()

    async def poll(self) -> None:
        """One poll cycle: (re)connect if due, flush writes, read inputs."""
        async with self._io_cycle:
            now = self.clock.now()
            if not self._connected:
                if now < self._next_connect_t:
                    return
                try:
                    await self._connect()
                except (TimeoutError, SupervisorError, OSError) as exc:
                    self._fail(exc, now)
                    return
                self._connected = True
                self._ever_connected = True
                self._backoff_s = BACKOFF_START_S
            try:
                await self._write_pending()
                samples = await self._read()
            except (TimeoutError, SupervisorError, OSError) as exc:
                self._fail(exc, now)
                return
            self.polls += 1
            self._image.update(samples)
            if self._lost_logged:
                log.info("%s: device recovered", self.name)
                self._lost_logged = False

    async def flush(self) -> None:
        """Send the queued writes now, each verified by its read-back, without reading the
        inputs. Nothing happens while the device is not connected: the next poll connects
        (with its backoff) and sends them. A write that fails is a failed poll (every input
        BAD, reconnect), as in :meth:`poll`."""
        async with self._io_cycle:
            if not (self._connected and self._pending):
                return
            now = self.clock.now()
            try:
                await self._write_pending()
            except (TimeoutError, SupervisorError, OSError) as exc:
                self._fail(exc, now)

    async def run(self) -> None:
        """Poll forever at ``poll_period_s`` on absolute deadlines (cancel to stop); in
        between, send queued writes as soon as ``write()`` wakes it."""
        next_t = self.clock.now()
        task = asyncio.current_task()
        while True:
            if task is not None and task.cancelling():
                # A cancellation can come back as a TimeoutError when it races a timeout
                # (asyncio.timeout in Python 3.11), and a failed poll swallows those: never
                # let that keep a driver task alive once it was told to stop.
                raise asyncio.CancelledError
            if self.clock.now() >= next_t:
                if self.scan_sync is not None:
                    await self.scan_sync()  # the poll starts as a scan ends
                await self.poll()
                next_t += self.poll_period_s
                now = self.clock.now()
                if next_t < now:  # overrun: no burst catch-up
                    next_t = now
            else:
                await self.flush()
            await self._idle_until(next_t)

    async def safe_state(self) -> str | None:
        """Best effort: drop queued writes and drive outputs safe; log and go on on failure.

        Returns None when the device confirmed its safe state, else why it could not be
        confirmed (for the shutdown report: a stop must never claim what it did not see).
        """
        async with self._io_cycle:
            self._pending.clear()
            try:
                await self._safe()
            except (TimeoutError, SupervisorError, OSError) as exc:
                if not self._ever_connected:
                    # Never reached: it cannot have energised anything, and connecting now
                    # would take the unit from whoever has it.
                    return self._unsafe(exc)
                # The link may be gone for a reason that says nothing about the device: a
                # stop that cancels the driver's task in the middle of an exchange closes
                # it (issue 13's load case, stopped under load). Once, at once (no
                # backoff: this is the stop), connect again and drive the outputs safe.
                log.warning(
                    "%s: safe state failed (%s); connecting again to drive the outputs safe",
                    self.name,
                    exc,
                )
                try:
                    await self._connect()
                    self._connected = True
                    await self._safe()
                except (TimeoutError, SupervisorError, OSError) as again:
                    self._connected = False
                    return self._unsafe(exc, again)
            return None

    def _unsafe(self, exc: BaseException, again: BaseException | None = None) -> str:
        """Why the safe state is not confirmed: the attempt's failure, and the second
        attempt's (the device's own fallback, e.g. a watchdog, is in the first)."""

        def text(e: BaseException) -> str:
            return str(e).removeprefix(f"{self.name}: ") or type(e).__name__

        why = text(exc) if again is None else f"{text(exc)}; connecting again: {text(again)}"
        log.error("%s: could not reach safe state: %s", self.name, why)
        return why

    async def close(self) -> None:
        async with self._io_cycle:
            try:
                await self._disconnect()
            finally:
                self._connected = False

    # --- internals -------------------------------------------------------------
    async def _write_pending(self) -> None:
        """Write every queued output in turn (the caller holds the I/O lock); a point
        written again meanwhile is sent again with its latest value."""
        while self._pending:
            point, value = next(iter(self._pending.items()))
            del self._pending[point]
            await self._write(point, value)

    async def _idle_until(self, t: float) -> None:
        """Wait until ``t`` or until ``write()`` queues something that can be sent."""
        if self._pending and self._connected:
            return
        self._wake.clear()
        delay = t - self.clock.now()
        if delay <= 0:
            return
        if self.clock.virtual:
            # Virtual time only moves when someone sleeps; the engine flushes in lockstep.
            await self.clock.sleep_until(t)
            return
        try:
            async with asyncio.timeout(delay):
                await self._wake.wait()
        except TimeoutError:
            pass

    def _fail(self, exc: BaseException, now: float) -> None:
        self.failures += 1
        self.last_error = str(exc)
        if not self._lost_logged:
            log.warning("%s: device lost: %s", self.name, exc)
            self._lost_logged = True
        self._connected = False
        self._next_connect_t = now + self._backoff_s
        self._backoff_s = min(self._backoff_s * 2, BACKOFF_MAX_S)
        reason = Reason.COMM_FAILURE
        for name, s in self._image.items():
            # Keep the last value for diagnostics, but never let it look GOOD.
            self._image[name] = Sample(s.value, Quality.BAD, reason, s.t)
