"""The chain's clocks are stored once a second, not every scan (issue 13): at a 10 ms scan
the step and test times, the progress and the ETA of 16 channels were half of every
scan's changes, straight lines the historian and InfluxDB stored 100 times a second."""

from __future__ import annotations

from pathlib import Path

from supervisor.app import build_bench
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.changes import ChangeFeed

ROOT = Path(__file__).resolve().parents[2]
CLOCKS = ("chain.step_time", "chain.test_time", "chain.progress", "chain.eta_s")


async def test_a_running_chains_clocks_are_stored_at_most_once_a_second() -> None:
    clock = VirtualClock()
    bench = build_bench(load_bench(ROOT / "io_maps/sim.yaml"), clock, in_process=True)
    await bench.start()
    try:
        runner = bench.load_recipe("ch0", ROOT / "recipes/nimh-ds2710.yaml")
        await bench.engine.run_for(1.0)
        runner.command("start")
        await bench.engine.run_for(2.0)
        feed = ChangeFeed(bench.db, clock)
        feed.take()  # what is there now: from here on, the changes
        stored: dict[str, list[float]] = {}
        scans = 0
        for _ in range(100):  # 10 s of 100 ms scans
            await bench.engine.run_for(bench.engine.period_s)
            scans += 1
            for s in feed.take():
                stored.setdefault(s.name, []).append(s.t)
        assert bench.db["ch0.chain.state"].value == "Running"
        for name in CLOCKS:  # at most one a second over 10 s (progress and ETA move
            # only in steps of a known length)
            assert len(stored.get(f"ch0.{name}", [])) <= 11, name
        for name in ("chain.step_time", "chain.test_time"):  # ...and one a second
            assert len(stored[f"ch0.{name}"]) >= 9, name
        # Other tags are still stored at every change (the scan counter: every scan).
        assert len(stored["scan.count"]) == scans
    finally:
        await bench.shutdown()
