"""The scan's right of way (issue 13, ``core/gate.py``): the scan engine closes the gate
from the approach of a deadline to the end of its scan; the publishers' threads that wait
at it (the OPC UA server's event loop, the InfluxDB spool's encoder, the historian's
writer) do their work between scans, and are only ever delayed, never stopped."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import pytest

from supervisor.core.clock import RealClock
from supervisor.core.gate import ScanGate
from supervisor.core.loops import GatedLoop
from supervisor.publish.influx.spool import Spool
from supervisor.publish.influx.writer import SpoolWriter
from supervisor.publish.results import SummaryWriter
from supervisor.publish.retain import RetainStore
from supervisor.publish.rows import RowWriter
from supervisor.scan import engine as engine_module
from supervisor.scan.engine import LogicPhase, ScanEngine
from supervisor.tags import TagDB
from supervisor.testing import wait_until

LIMIT_S = 10.0  # an upper bound for a slow machine, not a timing claim


async def test_a_thread_waits_at_a_closed_gate_and_goes_on_when_it_opens() -> None:
    gate = ScanGate(max_wait_s=60.0)
    gate.close()
    passed = threading.Event()

    def worker() -> None:
        gate.wait()
        passed.set()

    t = threading.Thread(target=worker)
    t.start()
    await wait_until(lambda: gate.waits == 1, "the worker at the gate", LIMIT_S)
    assert not passed.is_set()
    gate.open()
    await asyncio.to_thread(t.join, LIMIT_S)
    assert passed.is_set()


def test_an_open_gate_does_not_hold_anyone_and_a_closed_one_only_for_a_while() -> None:
    gate = ScanGate(max_wait_s=0.01)
    gate.wait()
    assert gate.waits == 0
    gate.close()  # an engine that stopped with it closed: the others are only delayed
    gate.wait()
    assert gate.waits == 1 and not gate.is_open


async def test_on_a_real_clock_the_gate_is_closed_while_each_scan_runs_and_open_after() -> None:
    db = TagDB()
    seen: list[bool] = []
    engine = ScanEngine(
        RealClock(),
        db,
        0.01,
        phases=[LogicPhase("look", lambda now, dt: seen.append(engine.gate.is_open))],  # type: ignore[union-attr]
    )
    engine.gate = ScanGate()
    await engine.run(asyncio.Event(), max_scans=5)
    assert seen == [False] * 5
    assert engine.gate.is_open


async def test_the_opc_ua_threads_event_loop_runs_nothing_while_a_scan_runs() -> None:
    gate = ScanGate(max_wait_s=60.0)
    loop = GatedLoop(gate)
    ran = threading.Event()
    thread = threading.Thread(target=loop.run_forever)
    thread.start()
    try:
        await wait_until(loop.is_running, "the server's loop", LIMIT_S)
        gate.close()
        loop.call_soon_threadsafe(ran.set)  # a client's request arrives during the scan
        await wait_until(lambda: gate.waits >= 1, "the loop at the gate", LIMIT_S)
        assert not ran.is_set()
        gate.open()
        await wait_until(ran.is_set, "the request served after the scan", LIMIT_S)
    finally:
        gate.open()
        loop.call_soon_threadsafe(loop.stop)
        await asyncio.to_thread(thread.join, LIMIT_S)
        loop.close()


async def test_the_opc_ua_loop_stops_at_the_gate_between_two_callbacks_it_had_ready() -> None:
    # Issue 13's load case: the server's subscriptions and clients made one turn of its
    # loop run a dozen callbacks of 0.5-2 ms; a scan that began during the first met the
    # others taking the interpreter lock from it (the OPC UA thread ran 166 ms inside the
    # scans' 125 ms of lost time, 30 s). Each callback now waits for the gate.
    gate = ScanGate(max_wait_s=60.0)
    loop = GatedLoop(gate)
    ran: list[object] = []
    thread = threading.Thread(target=loop.run_forever)
    thread.start()
    try:
        await wait_until(loop.is_running, "the server's loop", LIMIT_S)

        def first() -> None:
            gate.close()  # a scan begins while the loop runs its first callback
            ran.append("first")

        # Both ready in the same turn of the loop (one wake-up of its selector).
        loop.call_soon_threadsafe(first)
        loop.call_soon_threadsafe(lambda: ran.append(("second", gate.is_open)))
        await wait_until(lambda: gate.waits >= 1, "the loop at the gate", LIMIT_S)
        assert ran == ["first"]
        gate.open()
        await wait_until(lambda: len(ran) == 2, "the second callback after the scan", LIMIT_S)
        assert ran == ["first", ("second", True)]
    finally:
        gate.open()
        loop.call_soon_threadsafe(loop.stop)
        await asyncio.to_thread(thread.join, LIMIT_S)
        loop.close()


async def test_the_influx_spool_encodes_a_scans_samples_only_once_the_scan_is_done(
    tmp_path: Path,
) -> None:
    gate = ScanGate(max_wait_s=60.0)
    writer = SpoolWriter(
        Spool(tmp_path / "spool.sqlite", 10_000_000),
        commit_interval_s=0.01,
        chunk_points=1000,
        max_queue_points=10_000,
    )
    writer.gate = gate
    encoded = threading.Event()

    def encode() -> dict[str, list[str]]:
        encoded.set()
        return {"channel": ["channel,bench=b,channel=ch0 voltage=1.2 1"]}

    writer.start()
    try:
        gate.close()
        writer.put_deferred(1, encode)
        # The idle encoder is not even woken during the scan: that waits for its end.
        assert gate.pending_wakes == 1 and not encoded.is_set()
        gate.open()
        await wait_until(encoded.is_set, "encoded after the scan", LIMIT_S)
        assert gate.pending_wakes == 0
    finally:
        gate.open()
        await asyncio.to_thread(writer.stop)


async def test_result_rows_summaries_and_retained_state_are_written_once_the_scan_is_done(
    tmp_path: Path,
) -> None:
    """The scan hands a row, a summary and a retained document over; their threads are
    woken when the scan is done (and wait at the gate before they write)."""
    gate = ScanGate(max_wait_s=60.0)
    rows, summaries = RowWriter("t"), SummaryWriter("t")
    store = RetainStore(tmp_path / "state.sqlite")
    store.open()
    rows.gate = summaries.gate = store.gate = gate
    row_written = threading.Event()
    summary = tmp_path / "summary.json"
    try:
        # Their threads started and idle (the first hand-over starts a writer's thread).
        rows.put(lambda: None)
        summaries.put(tmp_path / "other.json", "ch1", {})
        store.put("channel:ch1", {})
        assert await asyncio.to_thread(rows.flush) and await asyncio.to_thread(summaries.flush)
        assert await asyncio.to_thread(store.flush, LIMIT_S)
        gate.close()
        rows.put(row_written.set)
        summaries.put(summary, "ch0", {"state": "Running"})
        store.put("channel:ch0", {"chain": None})
        # Woken only once the scan is done, each once.
        assert gate.pending_wakes == 3
        assert not row_written.is_set() and not summary.exists()
        assert "channel:ch0" not in store.read()
        gate.open()
        await wait_until(row_written.is_set, "the row after the scan", LIMIT_S)
        await wait_until(summary.exists, "the summary after the scan", LIMIT_S)
        assert await asyncio.to_thread(store.flush, LIMIT_S)
        assert store.read()["channel:ch0"] == {"chain": None}
    finally:
        gate.open()
        await asyncio.to_thread(rows.stop)
        await asyncio.to_thread(summaries.stop)
        await asyncio.to_thread(store.close)


def test_a_wake_up_asked_for_during_a_scan_is_made_once_when_it_ends() -> None:
    gate = ScanGate()
    woken: list[str] = []

    def wake() -> None:
        woken.append("writer")

    gate.after_scan(wake)
    assert woken == ["writer"]  # no scan runs: at once
    gate.close()
    gate.after_scan(wake)
    gate.after_scan(wake)
    gate.after_scan(lambda: woken.append("other"))
    assert woken == ["writer"] and gate.pending_wakes == 3
    gate.open()
    assert woken == ["writer", "writer", "other"] and gate.pending_wakes == 0


async def test_a_flush_during_a_scan_writes_what_that_scan_handed_over(tmp_path: Path) -> None:
    """A test ending in a scan closes its files, which first waits for its rows: the row
    writer is woken by the flush and does not wait for the gate the scan holds closed."""
    gate = ScanGate(max_wait_s=60.0)  # a writer waiting at it would outlast the flush
    rows, summaries = RowWriter("t"), SummaryWriter("t")
    rows.gate = summaries.gate = gate
    written: list[str] = []
    try:
        rows.put(lambda: written.append("earlier"))
        assert await asyncio.to_thread(rows.flush)
        gate.close()  # the scan runs
        rows.put(lambda: written.append("the test's last row"))
        summaries.put(tmp_path / "summary.json", "ch0", {"state": "Running"})
        assert rows.flush(timeout_s=LIMIT_S) and summaries.flush(timeout_s=LIMIT_S)
        assert written == ["earlier", "the test's last row"]
        assert (tmp_path / "summary.json").exists()
    finally:
        gate.open()
        await asyncio.to_thread(rows.stop)
        await asyncio.to_thread(summaries.stop)


async def test_the_gate_closes_before_a_deadline_even_while_the_event_loop_is_held(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A callback that holds the scan's event loop when it should wake for the deadline
    (here the idle work) does not keep the gate open: a thread of the engine's closes it
    ``GATE_EARLY_S`` before the deadline."""
    monkeypatch.setattr(engine_module, "GATE_EARLY_S", 0.03)
    period_s = 0.1
    engine = ScanEngine(RealClock(), TagDB(), period_s)
    engine.gate = ScanGate()
    seen: list[bool] = []

    def held(left_s: float) -> None:
        time.sleep(max(0.0, left_s - 0.002))  # the loop held until 2 ms before the deadline
        assert engine.gate is not None
        seen.append(engine.gate.is_open)

    engine.idle = held
    await engine.run(asyncio.Event(), max_scans=4)
    assert seen == [False, False, False]  # closed by then (the last scan has no idle)
    assert engine.gate.is_open  # and open once the engine stopped
