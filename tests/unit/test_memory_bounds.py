"""What a bench keeps in memory while it runs has a ceiling (issue 13's memory figure):
the scan's statistics windows and each chain's event log keep the latest entries only,
however long the bench runs. (The EA simulator's line log: tests/unit/test_ea_driver.py;
the historian's page cache: tests/unit/test_historian.py.)"""

from __future__ import annotations

from pathlib import Path

from supervisor.app import build_bench
from supervisor.chains.engine import EVENTS_KEPT
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.scan.engine import STATS_WINDOW, ScanStats
from supervisor.testing import run_scans

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "io_maps" / "sim.yaml"
CHAIN_EVENTS_KEPT = EVENTS_KEPT  # supervisor/chains/engine.py

FAST_STEPS = """\
recipe: fast-steps
cycles: 100000
steps:
  - {id: a, rest: 0.1 s}
  - {id: b, rest: 0.1 s}
"""


def test_the_scan_statistics_keep_a_window_of_the_latest_scans() -> None:
    stats = ScanStats()
    for i in range(3 * STATS_WINDOW):
        stats.durations_s.append(i * 1e-6)
        stats.jitters_s.append(i * 1e-6)
    assert len(stats.durations_s) == len(stats.jitters_s) == STATS_WINDOW
    assert stats.durations_s[-1] == (3 * STATS_WINDOW - 1) * 1e-6  # the newest kept


async def test_a_chain_keeps_its_latest_events_only_however_many_steps_it_runs(
    tmp_path: Path,
) -> None:
    bench = build_bench(load_bench(SIM), VirtualClock(), in_process=True)
    await bench.start()
    try:
        recipe = tmp_path / "fast.yaml"
        recipe.write_text(FAST_STEPS, encoding="utf-8")
        bench.load_recipe("ch0", recipe, results_dir=tmp_path)
        bench.detach_results("ch0")  # the chain's own log only (a test's record is kept)
        runner = bench.runners["ch0"]
        runner.command("start", actor="test")
        seen: list[int] = []
        runner.listeners.append(lambda ev: seen.append(ev.step_index))
        await run_scans(bench.engine, int(1.5 * CHAIN_EVENTS_KEPT))  # a step every scan
        assert len(seen) > CHAIN_EVENTS_KEPT
        assert len(seen) > CHAIN_EVENTS_KEPT
        assert len(runner.events) == CHAIN_EVENTS_KEPT
    finally:
        await bench.shutdown()
