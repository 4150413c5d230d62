"""Must show (issue 10): InfluxDB down for 30 s during a simulated run at full rate (every
scan's changes, deadband 0), brought back, and every point counted on the server: zero
lost, order kept. The bench is io_maps/sim.yaml on the real clock (its simulators served
on loopback, as ``supervisor run`` has them) with an ``influxdb:`` section pointing at the
test's real InfluxDB; the outage is the server process stopped and started on the same
port and data. Wall time is needed: the outage is 30 real seconds.

What was produced is every line the writer handed to its queue (a wrapper in the test);
what was sent, in order, is every request InfluxDB acknowledged (the forwarder's listener).
"""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import pytest
from influxrig import InfluxServer, expected_points, parse_line, server_points, sim_map

from supervisor.app import Bench, build_bench
from supervisor.commands import Command
from supervisor.core.clock import RealClock
from supervisor.devices.registry import load_bench
from supervisor.publish.influx import Delivery, Failure
from supervisor.publish.influx.writer import Encode
from supervisor.testing import wait_until

OUTAGE_S = 30.0
LIMIT_S = 120.0  # a bound for a loaded machine, not a timing claim
pytestmark = pytest.mark.integration
log = logging.getLogger(__name__)


def assert_sent_in_order(deliveries: list[Delivery]) -> int:
    """Chunks acknowledged oldest first, and each series' field timestamps increasing in
    the order the requests were sent. Returns the lines sent."""
    ids = [i for d in deliveries for i in d.ids]
    assert ids == sorted(ids) and len(set(ids)) == len(ids), "chunks out of order"
    last: dict[tuple[str, frozenset[tuple[str, str]], str], int] = {}
    n = 0
    for d in deliveries:
        for raw in d.body.split(b"\n"):
            m, tags, fields, ts = parse_line(raw.decode())
            n += 1
            for f in fields:
                key = (m, frozenset(tags.items()), f)
                assert ts > last.get(key, -1), f"{key}: {ts} sent after {last[key]}"
                last[key] = ts
    return n


def tap(bench: Bench, produced: list[str], deliveries: list[Delivery]) -> None:
    """Record every line handed to the writer's queue and every acknowledged request."""
    assert bench.influx is not None
    writer = bench.influx.writer
    put = writer.put

    def recording_put(measurement: str, lines: list[str]) -> None:
        produced.extend(lines)
        put(measurement, lines)

    writer.put = recording_put  # type: ignore[method-assign]
    put_deferred = writer.put_deferred

    def recording_deferred(points: int, encode: Encode) -> None:
        # The scan's samples become lines on the spool writer's thread (ADR 0021).
        def recorded() -> dict[str, list[str]]:
            lines_by = encode()
            for lines in lines_by.values():
                produced.extend(lines)
            return lines_by

        put_deferred(points, recorded)

    writer.put_deferred = recording_deferred  # type: ignore[method-assign]
    bench.influx.forwarder.listeners.append(deliveries.append)


@pytest.mark.timeout(300)
async def test_a_30_s_outage_at_full_rate_loses_no_point_and_keeps_the_order(
    tmp_path: Path, influx: InfluxServer
) -> None:
    produced: list[str] = []
    bench = build_bench(load_bench(sim_map(tmp_path, influx)), RealClock())
    writer = bench.influx
    assert writer is not None
    deliveries: list[Delivery] = []
    tap(bench, produced, deliveries)
    db = bench.db
    stop = asyncio.Event()
    await bench.start()
    task = asyncio.create_task(bench.run(stop))
    try:
        await wait_until(lambda: db["chadeche.connected"].value is True, "the boards", LIMIT_S)
        for ch in ("ch0", "ch1", "ch2", "ch3"):  # currents, voltages and counters move
            db.write(f"{ch}.manual_current", 0.2)
            db.write(f"{ch}.enable", True)
        await wait_until(lambda: writer.status().spool.sent > 0, "the first delivery", LIMIT_S)

        # The server's stop and start block (a process, its pid): off the loop, so that
        # the scan goes on meanwhile.
        await asyncio.to_thread(influx.stop)
        t_down = time.monotonic()
        await wait_until(
            lambda: writer.status().forwarder.failure is Failure.UNREACHABLE, "the outage seen"
        )
        # Events during the outage too (annotations must not be lost either).
        for verb_value in ("auto", "manual"):
            bench.commands.execute(Command.write("ch3.mode", verb_value, actor="outage test"))
            await asyncio.sleep(1.0)
        await asyncio.sleep(max(0.0, OUTAGE_S - (time.monotonic() - t_down)))
        during = writer.status()
        assert during.spool.waiting > 0 and not during.forwarder.connected
        assert db["influx.spool_depth"].value > 0  # (as of the last scan)
        assert db["influx.connected"].value is False
        await asyncio.to_thread(influx.start)

        await wait_until(
            lambda: writer.status().forwarder.connected and writer.status().spool.waiting < 200,
            "the backlog drained",
            LIMIT_S,
        )
        await asyncio.sleep(2.0)  # a little more of normal running after the drain
    finally:
        stop.set()
        await task
        await bench.shutdown()  # spools what is queued and sends it (stop_flush_s)

    c = writer.status().spool
    log.info(
        "outage run: %d lines produced, %d sent, %d requests; waiting %d, dropped %d, dead %d",
        len(produced),
        c.sent,
        len(deliveries),
        c.waiting,
        c.dropped,
        c.dead,
    )
    # The spool's own books: everything produced was acknowledged, nothing dropped.
    assert (c.waiting, c.dropped, c.dead) == (0, 0, 0)
    assert c.produced == c.sent == len(produced)
    # Sent oldest first; every series in time order.
    assert assert_sent_in_order(deliveries) == len(produced)
    # Every point on the server, with its values: zero lost.
    expected = expected_points(produced)
    assert len(expected) == len(produced)  # one line per point: none overwrites another
    on_server = server_points(influx)
    missing = [k for k in expected if k not in on_server]
    assert not missing, f"{len(missing)} of {len(expected)} points missing, e.g. {missing[:3]}"
    wrong = [k for k, fields in expected.items() if on_server[k] != fields]
    assert not wrong, f"{len(wrong)} points differ, e.g. {wrong[0]}: {on_server[wrong[0]]}"
    assert len(on_server) == len(expected)
    events = [k for k in expected if k[0] == "event"]
    assert any(dict(k[1])["kind"] == "command" for k in events)
    assert writer.status().forwarder.failed_writes > 0  # there was an outage
