"""Fault injection on the simulated bench: each device killed, hung, answering garbage or
dropping its link while a test runs, and how fast the bench reacts.

Run in process on the virtual clock (``build_bench(..., in_process=True)``), so reaction
times are exact simulated times, not wall-clock noise: ``supervisor bench faults`` prints
the table, and ``tests/unit/test_fault_injection.py`` asserts every case's outcome — the
channel tripped with an alarm naming the device, its outputs safe, its test held at the
same step with the same counters, and resumed once the device is back.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from supervisor.app import Bench, build_bench
from supervisor.chains.states import State
from supervisor.core.clock import VirtualClock
from supervisor.devices.base import BACKOFF_MAX_S
from supervisor.devices.registry import load_bench

SIM_MAP = Path(__file__).resolve().parents[2] / "io_maps" / "sim.yaml"
PERIOD_S = 0.1
RUN_BEFORE_S = 30.0
GIVE_UP_S = 60.0

RECIPE = {
    "ch4": "recipe: fault-ch4\nsteps:\n  - {id: charge, charge: 2 A, duration: 2 h}\n",
    "ch0": "recipe: fault-ch0\nsteps:\n  - {id: charge, charge: 300 mA, duration: 2 h}\n",
}

Inject = Callable[[Bench], Awaitable[None]]


@dataclass(frozen=True)
class FaultCase:
    device: str
    kind: str  # killed | hung | garbage | dropped
    channel: str
    what: str  # how the fault is made, for the table
    inject: Inject
    heal: Inject


@dataclass(frozen=True)
class FaultResult:
    case: FaultCase
    trip_s: float  # fault → the channel's trip latched
    safe_s: float  # fault → no current into the cell (outputs safe)
    fault: str  # the channel's first-out trip text
    held_at: str  # chain state and step after the trip
    safe_after_heal: bool  # no current once the device is back, before anyone resumes
    resumed: bool  # the test went on at the same step once the device was back
    charge_kept: bool  # the Ah counter survived the fault (nothing lost)


def _sim(bench: Bench, name: str) -> Any:
    assert bench.sim is not None
    return bench.sim.devices[name]


async def _stop(bench: Bench, name: str) -> None:
    await _sim(bench, name).stop()


async def _start(bench: Bench, name: str) -> None:
    await _sim(bench, name).start()


def _bms_sender(bench: Bench) -> Any:
    return _sim(bench, "bms").sender


async def _nothing(bench: Bench) -> None:
    return None


def _cases() -> list[FaultCase]:
    async def adam_kill(b: Bench) -> None:
        await _stop(b, "adam")

    async def adam_heal(b: Bench) -> None:
        await _start(b, "adam")

    async def adam_hang(b: Bench) -> None:
        _sim(b, "adam").mute(True)

    async def adam_unhang(b: Bench) -> None:
        _sim(b, "adam").mute(False)

    async def adam_garbage(b: Bench) -> None:
        _sim(b, "adam").short_next_reads(10_000, slot=0)  # the LEM / voltage board slot

    async def adam_ungarbage(b: Bench) -> None:
        _sim(b, "adam").short_next_reads(0)

    async def ea_kill(b: Bench) -> None:
        await _stop(b, "ea")

    async def ea_heal(b: Bench) -> None:
        await _start(b, "ea")

    async def ea_hang(b: Bench) -> None:
        _sim(b, "ea").mute = True

    async def ea_unhang(b: Bench) -> None:
        _sim(b, "ea").mute = False

    async def ea_garbage(b: Bench) -> None:
        for _ in range(50):
            _sim(b, "ea").corrupt_next_reply("MEAS:ARR?")

    async def ea_drop(b: Bench) -> None:
        await _sim(b, "ea").drop_clients()

    async def bms_kill(b: Bench) -> None:
        _bms_sender(b).paused = True

    async def bms_heal(b: Bench) -> None:
        _bms_sender(b).paused = False

    async def bms_garbage(b: Bench) -> None:
        _bms_sender(b).paused = True
        for _ in range(100):
            _bms_sender(b).send_raw(0x1B0, b"\x00\x01")  # too short for the DBC

    async def chadeche_kill(b: Bench) -> None:
        _sim(b, "chadeche").bus.fault = OSError("SPI bus error")

    async def chadeche_heal(b: Bench) -> None:
        _sim(b, "chadeche").bus.fault = None

    return [
        FaultCase("adam", "killed", "ch4", "unit unplugged", adam_kill, adam_heal),
        FaultCase("adam", "hung", "ch4", "accepts, never answers", adam_hang, adam_unhang),
        FaultCase(
            "adam", "garbage", "ch4", "short answers on slot 0", adam_garbage, adam_ungarbage
        ),
        FaultCase("ea", "killed", "ch4", "unit unplugged", ea_kill, ea_heal),
        FaultCase("ea", "hung", "ch4", "accepts, never answers", ea_hang, ea_unhang),
        FaultCase("ea", "garbage", "ch4", "MEAS:ARR? answers garbage", ea_garbage, _nothing),
        FaultCase("ea", "dropped", "ch4", "connection dropped", ea_drop, _nothing),
        FaultCase("bms", "killed", "ch4", "no frame any more", bms_kill, bms_heal),
        FaultCase("bms", "garbage", "ch4", "frames of the wrong length", bms_garbage, bms_heal),
        FaultCase("chadeche", "killed", "ch0", "SPI transfers fail", chadeche_kill, chadeche_heal),
    ]


CASES = _cases()


def _current_into_cell(bench: Bench, channel: str) -> float:
    """What really flows, from the simulation (not from the supervisor's view of it)."""
    assert bench.sim is not None
    if channel == "ch4":
        return bench.sim.plant.pack_current_a
    board = int(
        bench.cfg.channels[[c.name for c in bench.cfg.channels].index(channel)].source.board or 0
    )
    return float(_sim(bench, "chadeche").bus.boards[board].current_a)


async def run_case(case: FaultCase, results: Path) -> FaultResult:
    clock = VirtualClock()
    bench = build_bench(load_bench(SIM_MAP), clock, in_process=True)
    db, ch = bench.db, case.channel
    try:
        await bench.start()
        await bench.engine.run_for(3.0)
        recipe = results / f"{case.device}-{case.kind}.yaml"
        recipe.write_text(RECIPE[ch], encoding="utf-8")
        runner = bench.load_recipe(ch, recipe, results_dir=results)
        runner.command("start", actor="fault injection")
        await bench.engine.run_for(RUN_BEFORE_S)
        step_before = db[f"{ch}.chain.step"].value
        t0 = clock.now()
        await case.inject(bench)
        trip_s = safe_s = math.inf
        while clock.now() - t0 < GIVE_UP_S and (math.isinf(trip_s) or math.isinf(safe_s)):
            await bench.engine.run_for(PERIOD_S)
            t = clock.now() - t0
            if math.isinf(trip_s) and db[f"{ch}.fault"].value:
                trip_s = t
            if math.isinf(safe_s) and _current_into_cell(bench, ch) == 0.0:
                safe_s = t
        fault = str(db[f"{ch}.fault"].value)
        await bench.engine.run_for(2.0)
        held_at = f"{runner.state.value} at {db[f'{ch}.chain.step'].value}"
        charge_at_trip = db[f"{ch}.charge_ah"].as_float()
        await case.heal(bench)
        await bench.engine.run_for(BACKOFF_MAX_S + 5.0)  # the driver reconnects with backoff
        safe_after_heal = _current_into_cell(bench, ch) == 0.0
        resumed = False
        try:
            bench.safety.guards[ch].reset("fault injection")
            await bench.engine.run_for(1.0)
            if runner.state is State.HELD:
                runner.command("resume", actor="fault injection")
            await bench.engine.run_for(10.0)
            resumed = runner.state is State.RUNNING and db[f"{ch}.chain.step"].value == step_before
        except Exception:  # a refusal is a result here: the table says "no"
            resumed = False
        charge_kept = db[f"{ch}.charge_ah"].as_float() >= charge_at_trip > 0
        return FaultResult(
            case, trip_s, safe_s, fault, held_at, safe_after_heal, resumed, charge_kept
        )
    finally:
        await bench.shutdown()


async def run_all() -> list[FaultResult]:
    with tempfile.TemporaryDirectory() as tmp:
        return [await run_case(c, Path(tmp)) for c in CASES]


def table(results: list[FaultResult]) -> list[str]:
    def s(x: float) -> str:
        return "never" if math.isinf(x) else f"{x:.1f} s"

    lines = [
        "fault injection on the simulated bench (virtual clock, 100 ms scan):",
        f"  {'device':<9}{'fault':<9}{'how':<27}{'trip':>8}{'safe':>8}  held at / resumed / trip",
    ]
    for r in results:
        c = r.case
        lines.append(
            f"  {c.device:<9}{c.kind:<9}{c.what:<27}{s(r.trip_s):>8}{s(r.safe_s):>8}"
            f"  {r.held_at} / {'yes' if r.resumed else 'no'} / {r.fault}"
        )
    return lines
