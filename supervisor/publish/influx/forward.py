"""The forwarder: one thread that sends the spool's oldest chunks to InfluxDB, in order.

A batch (the oldest chunks, up to ``batch_size`` points) is sent when it is full or when
its oldest point has waited ``flush_interval_s``; it leaves the spool only after a 2xx.
What a failure does depends on what it says (``client.classify``):

- connection refused or reset, no answer within ``timeout_s``, 5xx, 408, 429: the server
  is away or busy. Back off (capped exponential with jitter, ``Retry-After`` honoured) and
  send the same batch again; after ``alarm_after_s`` of it the ``influx.unreachable`` alarm.
- 400 (and 413, 422): some line of the batch is bad. The batch is halved until the bad
  lines are alone; each one InfluxDB still refuses goes to the dead-letter table with the
  server's reason, the rest is delivered. (1.8 writes the good points of a 400 "partial
  write" already; sending them again overwrites them with themselves.)
- 401, 403, 404 and other 4xx: the token, the bucket or the URL is wrong, which applies to
  every point: nothing is dead-lettered, the batch stays, the ``influx.config`` alarm is
  raised and the write is retried every ``retry_max_s`` until the configuration is fixed
  (e.g. the database is created).

Each failure kind is logged once when it starts (with its cause) and once when writes are
accepted again; every failed request is counted.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from supervisor.core.threads import run_restarting
from supervisor.publish.influx.client import (
    CONFIGURATION,
    TRANSIENT,
    Failure,
    Outcome,
    Reply,
    WriteClient,
    classify,
    describe,
)
from supervisor.publish.influx.spool import Batch, DeadLetter, Spool

__all__ = ["Delivery", "Forwarder", "ForwarderStatus"]

log = logging.getLogger(__name__)

RETRY_INITIAL_S = 0.5
"""First back-off after a transient failure; doubled up to ``retry_max_s``."""
RETRY_AFTER_MAX_S = 600.0
"""A server's ``Retry-After`` is honoured up to this."""
JITTER = 0.2
"""± this fraction on each back-off, so that many benches do not retry in step."""
STOP_GRACE_S = 5.0
"""After the flush deadline, how long a stop waits for the aborted request to return."""
RATE_WINDOW_S = 10.0
"""The drain rate is the points delivered over this many seconds."""


@dataclass(frozen=True, slots=True)
class Delivery:
    """A batch InfluxDB took: its chunks and the lines it accepted (after a bisection,
    without the dead letters), in the order they were sent."""

    ids: tuple[int, ...]
    points: int
    body: bytes


@dataclass(frozen=True, slots=True)
class ForwarderStatus:
    connected: bool  # the last request was answered with a 2xx
    failure: Failure | None  # the failure going on now
    failing_s: float  # for how long (0 when none)
    last_error: str  # the last failure's cause ("" when none yet)
    failed_writes: int  # failed requests since start
    timeouts: int  # of them, requests that timed out
    drain_rate: float  # points/s delivered over the last RATE_WINDOW_S
    delivered: int  # points delivered since start (incl. resent halves once)
    dead_alarm: str  # the last dead letter's reason while the alarm holds ("" when none)


class Forwarder:
    """Sends ``spool``'s chunks through ``client``; runs on its own thread."""

    def __init__(
        self,
        spool: Spool,
        client: WriteClient,
        *,
        batch_size: int = 5000,
        flush_interval_s: float = 1.0,
        retry_max_s: float = 30.0,
        wall: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
        rng: random.Random | None = None,
    ) -> None:
        self.spool = spool
        self.client = client
        self.batch_size = batch_size
        self.flush_interval_s = flush_interval_s
        self.retry_max_s = retry_max_s
        self._wall = wall
        self._mono = monotonic
        self._rng = rng or random.Random()
        self.listeners: list[Callable[[Delivery], None]] = []
        """Called on the forwarder's thread after each acknowledged request."""
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stopping = False
        self._deadline: float | None = None
        self._kick = False
        # Status (under _cond).
        self._connected = False
        self._failure: Failure | None = None
        self._failing_since = 0.0
        self._failed_in_row = 0
        self._last_error = ""
        self._failed_writes = 0
        self._timeouts = 0
        self._delivered = 0
        self._recent: deque[tuple[float, int]] = deque()
        self._dead_alarm = ""
        self._last_dead_reason = ""
        self.crashes = 0  # exceptions that escaped the thread's loop (it started again)

    # --- control ----------------------------------------------------------------------
    def start(self) -> None:
        if self._thread is not None:
            return
        self._stopping = False
        self._deadline = None
        self._thread = threading.Thread(
            target=self._thread_main, name="influx-forwarder", daemon=True
        )
        self._thread.start()

    def notify(self) -> None:
        """New chunks are in the spool."""
        with self._cond:
            self._kick = True
            self._cond.notify_all()

    def stop(self, flush_s: float) -> bool:
        """Send what can be sent within ``flush_s``, then stop; the rest stays in the spool.
        A request still in flight at the deadline is aborted (its batch stays). Returns
        whether the thread ended (False only if it is stuck outside a request)."""
        thread = self._thread
        if thread is None:
            return True
        with self._cond:
            self._stopping = True
            self._deadline = self._mono() + flush_s
            self._cond.notify_all()
        thread.join(flush_s)
        if thread.is_alive():
            self.client.abort()  # a request that started before the stop keeps its timeout
            thread.join(STOP_GRACE_S)
        stopped = not thread.is_alive()
        if not stopped:
            log.error("InfluxDB forwarder did not stop within %g s", flush_s + STOP_GRACE_S)
        self._thread = None
        self.client.close()
        return stopped

    def status(self) -> ForwarderStatus:
        now = self._mono()
        with self._cond:
            while self._recent and now - self._recent[0][0] > RATE_WINDOW_S:
                self._recent.popleft()
            rate = sum(n for _, n in self._recent) / RATE_WINDOW_S
            return ForwarderStatus(
                connected=self._connected,
                failure=self._failure,
                failing_s=now - self._failing_since if self._failure is not None else 0.0,
                last_error=self._last_error,
                failed_writes=self._failed_writes,
                timeouts=self._timeouts,
                drain_rate=rate,
                delivered=self._delivered,
                dead_alarm=self._dead_alarm,
            )

    # --- the thread -------------------------------------------------------------------
    def _thread_main(self) -> None:
        # A bug must not end forwarding for good: the points stay in the spool, the loop
        # starts again (``core/threads.py``).
        run_restarting(
            "InfluxDB forwarder", self._run, self._crashed, self._stop_due, self._wait, 1.0
        )

    def _crashed(self, exc: Exception) -> None:
        with self._cond:
            self.crashes += 1
            self._connected = False
            self._last_error = f"forwarder crashed ({type(exc).__name__}: {exc}); restarted"

    def _run(self) -> None:
        while True:
            delay = self._step()
            if delay is None:
                return
            if delay > 0:
                self._wait(delay)

    def _stop_due(self) -> bool:
        with self._cond:
            return self._stopping and (self._deadline is None or self._mono() >= self._deadline)

    def _wait(self, delay_s: float, until_kicked: bool = False) -> None:
        """Sleep ``delay_s`` (None: until new data); a stop wakes it, and so does new data
        when ``until_kicked``."""
        end = self._mono() + delay_s
        with self._cond:
            while not self._stopping:
                if until_kicked and self._kick:
                    break
                left = end - self._mono()
                if left <= 0:
                    break
                self._cond.wait(left)
            self._kick = False

    def _step(self) -> float | None:
        """One decision: send, or wait. Returns how long to wait (0: go on at once), or
        None to end the thread."""
        if self._stop_due():
            return None
        with self._cond:
            stopping = self._stopping
        spool = self.spool
        if spool.waiting == 0:
            if stopping:
                return None
            self._wait(3600.0, until_kicked=True)
            return 0.0
        if not stopping and spool.waiting < self.batch_size:
            oldest = spool.oldest_wall()
            age = self._wall() - oldest if oldest is not None else 0.0
            if 0 <= age < self.flush_interval_s:
                self._wait(self.flush_interval_s - age, until_kicked=True)
                return 0.0
        batch = spool.next_batch(self.batch_size)
        if batch is None:
            return 0.0
        return self._send(batch)

    def _timeout(self) -> float:
        with self._cond:
            deadline = self._deadline
        if deadline is None:
            return self.client.timeout_s
        return max(0.05, min(self.client.timeout_s, deadline - self._mono()))

    def _post(self, body: bytes) -> Reply | tuple[Failure, str]:
        try:
            return self.client.write(body, self._timeout())
        except Exception as exc:  # OSError, HTTPException: the transport, not the data
            return describe(exc)

    def _send(self, batch: Batch) -> float | None:
        """Send one batch; returns the wait before the next step (None: stop now)."""
        reply = self._post(batch.body)
        if isinstance(reply, tuple):
            return self._failed(batch, *reply)
        outcome, failure = classify(reply.status)
        if outcome is Outcome.DELIVERED:
            self._delivered_batch(batch, [], batch.body)
            return 0.0
        if outcome is Outcome.SPLIT:
            return self._bisect(batch, reply)
        assert failure is not None
        return self._failed(batch, failure, reply.reason, reply.retry_after_s)

    def _bisect(self, batch: Batch, first: Reply) -> float | None:
        """Halve a refused batch until every refused line is alone; those are dead letters,
        the rest is delivered. A transient failure midway leaves the whole batch in the
        spool (what was sent of it is sent again later: it overwrites itself)."""
        lines = batch.lines()
        dead: list[DeadLetter] = []
        accepted: list[bytes] = []
        parts: list[tuple[list[bytes], Reply | None]] = [(lines, first)]
        while parts:
            part, reply = parts.pop()
            if reply is None:
                answer = self._post(b"\n".join(part))
                if isinstance(answer, tuple):
                    return self._failed(batch, *answer)
                reply = answer
            outcome, failure = classify(reply.status)
            if outcome is Outcome.DELIVERED:
                accepted.extend(part)
                continue
            if outcome is not Outcome.SPLIT:
                assert failure is not None
                return self._failed(batch, failure, reply.reason, reply.retry_after_s)
            if len(part) == 1:
                dead.append(DeadLetter(part[0], reply.status, reply.reason))
                continue
            half = len(part) // 2
            # Pushed right first: the left half (older lines) is sent first.
            parts.append((part[half:], None))
            parts.append((part[:half], None))
            if self._stop_due():
                self.spool.release()
                return None
        self._delivered_batch(batch, dead, b"\n".join(accepted))
        return 0.0

    # --- bookkeeping --------------------------------------------------------------------
    def _delivered_batch(self, batch: Batch, dead: list[DeadLetter], body: bytes) -> None:
        self.spool.ack(batch, dead)
        now = self._mono()
        with self._cond:
            recovered = self._failure
            failed_in_row = self._failed_in_row
            failing_s = now - self._failing_since
            self._failure = None
            self._failed_in_row = 0
            self._connected = True
            good = batch.points - len(dead)
            self._delivered += good
            self._recent.append((now, good))
            self._dead_alarm = dead[-1].reason if dead else ""
            if dead:
                self._last_error = dead[-1].reason
        if recovered is not None:
            log.warning(
                "InfluxDB %s: writes accepted again after %d failed attempts in %.1f s (%s)",
                self.client.url,
                failed_in_row,
                failing_s,
                recovered.value,
            )
        if dead:
            reason = dead[-1].reason
            level = logging.WARNING if reason != self._last_dead_reason else logging.INFO
            log.log(
                level,
                "InfluxDB refused %d of %d points for good (%s; first: %.200s):"
                " kept in the dead-letter table of %s",
                len(dead),
                batch.points,
                reason,
                dead[0].line.decode("utf-8", "replace"),
                self.spool.path,
            )
            self._last_dead_reason = reason
        delivery = Delivery(batch.ids, batch.points - len(dead), body)
        for fn in self.listeners:
            try:
                fn(delivery)
            except Exception:
                log.exception("InfluxDB delivery listener failed")

    def _failed(
        self,
        batch: Batch,
        failure: Failure,
        cause: str,
        retry_after_s: float | None = None,
    ) -> float | None:
        """Count and report a failed request; returns the wait before the next attempt."""
        self.spool.release()
        now = self._mono()
        with self._cond:
            first = self._failure is not failure
            if self._failure is None:
                self._failing_since = now
            self._failure = failure
            self._failed_in_row += 1
            self._failed_writes += 1
            if failure is Failure.TIMEOUT:
                self._timeouts += 1
            self._connected = False
            self._last_error = f"{failure.value}: {cause}"
            attempt = self._failed_in_row
            stopping = self._stopping
        if first:
            what = (
                "the configuration is wrong; every point stays in the spool"
                if failure in CONFIGURATION
                else "points stay in the spool"
            )
            log.error(
                "InfluxDB %s: write of %d points failed, %s (%s); %s, retrying",
                self.client.url,
                batch.points,
                failure.value,
                cause,
                what,
            )
        if stopping:
            return None  # a clean stop does not wait out a failure: the rest stays
        if failure in TRANSIENT:
            delay: float = min(self.retry_max_s, RETRY_INITIAL_S * 2.0 ** min(attempt - 1, 30))
            delay *= 1 + self._rng.uniform(-JITTER, JITTER)
        else:
            delay = self.retry_max_s  # a configuration problem: slowly
        if retry_after_s is not None:
            delay = max(delay, min(retry_after_s, RETRY_AFTER_MAX_S))
        return delay
