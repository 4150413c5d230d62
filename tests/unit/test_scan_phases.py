"""One scan runs its logic in design order: derived values, safety, step chains, outputs.

So a step chain's conditions see this scan's measurements and counters (docs/design.md "One
scan"), and a chain's request still passes the channel's protection before any output.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app import Bench, build_bench
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import bench_from_data
from supervisor.safety import SafetyPhase
from supervisor.testing import run_scans

PERIOD_S = 1.0
Q_MAX_AH = 0.01  # 10 mAh: crossed after 120 s at 300 mA, between two scans

RECIPE = f"""\
recipe: phases
steps:
  - id: fill
    charge: 300 mA
    duration: 1 h
    until:
      - charge >= {Q_MAX_AH * 1000:g} mAh: next
  - {{id: after, rest: 1 h}}
"""


def one_channel_bench() -> Bench:
    cfg = bench_from_data(
        {
            "bench": "phases",
            "scan": {"period_s": PERIOD_S},
            "devices": {
                "chadeche": {
                    "driver": "chadeche",
                    "poll_period_s": PERIOD_S,
                    "stale_after_s": 3 * PERIOD_S,
                    "boards": [{"address": 0, "sim": {"model": "nimh-aa", "soc": 0.5}}],
                }
            },
            "channels": [
                {
                    "name": "ch0",
                    "source": {"device": "chadeche", "board": 0},
                    "capacity_ah": 2.0,
                    "limits": {"current_a": [-0.4, 0.4], "voltage_v": [0.8, 1.9]},
                }
            ],
        }
    )
    return build_bench(cfg, VirtualClock())


async def test_a_charge_transition_fires_in_the_scan_where_the_counter_crosses(
    tmp_path: Path,
) -> None:
    bench = one_channel_bench()
    recipe = tmp_path / "phases.yaml"
    recipe.write_text(RECIPE, encoding="utf-8")
    bench.load_recipe("ch0", recipe, results_dir=tmp_path)
    await run_scans(bench.engine, 3)  # first images in
    bench.runners["ch0"].command("start", actor="test")
    db = bench.db
    crossed_in: int | None = None
    left_in: int | None = None
    for scan in range(400):
        await run_scans(bench.engine)
        if crossed_in is None and db["ch0.charge_ah"].as_float() >= Q_MAX_AH:
            crossed_in = scan
        if left_in is None and db["ch0.chain.step"].value == "after":
            left_in = scan
        if crossed_in is not None and left_in is not None:
            break
    await bench.shutdown()
    assert crossed_in is not None, "the counter never reached q_max"
    assert left_in == crossed_in  # same scan: the chain saw this scan's counter


async def test_the_logic_phases_run_in_design_order() -> None:
    bench = one_channel_bench()
    names = [p.name for p in bench.engine.phases]
    assert names == ["derive:ch0", "safety", "chain:ch0", "drive:ch0"]
    await bench.shutdown()


class Failing:
    name = "broken check"

    def __init__(self) -> None:
        self.safe_called_with: str | None = None

    def evaluate(self, now: float, dt: float) -> None:
        raise RuntimeError("bug in a check")

    def fail_safe(self, why: str) -> None:
        self.safe_called_with = why


class Counting:
    name = "counting check"

    def __init__(self) -> None:
        self.runs = 0

    def evaluate(self, now: float, dt: float) -> None:
        self.runs += 1

    def fail_safe(self, why: str) -> None:
        raise AssertionError("never called: this check does not fail")


def test_a_failing_safety_check_fails_safe_and_does_not_stop_the_others(
    caplog: pytest.LogCaptureFixture,
) -> None:
    broken, counting = Failing(), Counting()
    phase = SafetyPhase([broken, counting])
    phase.run(0.0, 0.1)
    assert counting.runs == 1
    assert broken.safe_called_with == "safety check broken check failed: bug in a check"
    assert phase.errors == 1
    assert any("broken check" in r.getMessage() for r in caplog.records)
