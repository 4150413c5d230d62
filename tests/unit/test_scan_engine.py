"""The scan: process image, staleness, outputs on change, faults contained, time."""

from __future__ import annotations

import asyncio
import itertools
import time
from pathlib import Path

from supervisor.app.dryrun import dry_run
from supervisor.core.clock import VirtualClock
from supervisor.core.driver import Sample
from supervisor.core.quality import Quality, Reason
from supervisor.scan import InputBinding, LogicPhase, OutputBinding, ScanEngine
from supervisor.tags import Scaling, TagDB, TagSpec
from supervisor.testing import RecordingDriver


def fake_device(clock: VirtualClock, poll_period_s: float = 0.1) -> RecordingDriver:
    """Two inputs the test sets in ``values``, one output whose writes it records."""
    return RecordingDriver("dev", clock, {"ai0": 1.0, "ai1": 2.0}, ["ao0"], poll_period_s)


def make(period_s: float = 0.1, stale_after_s: float = 0.5):  # type: ignore[no-untyped-def]
    clock = VirtualClock()
    db = TagDB()
    dev = fake_device(clock)
    a = db.add(TagSpec("a", unit="V"))
    b = db.add(TagSpec("b", unit="A"))
    out = db.add(TagSpec("out", unit="A"))
    inputs = [
        InputBinding(a, dev, "ai0", None, stale_after_s),
        InputBinding(b, dev, "ai1", Scaling(10.0, 0.5), stale_after_s),
    ]
    outputs = [OutputBinding(out, dev, "ao0")]
    return clock, db, dev, inputs, outputs


async def test_inputs_are_copied_and_scaled_into_tags_at_scan_start() -> None:
    clock, db, dev, inputs, outputs = make()
    engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs)
    await engine.run_for(0.1)
    assert db["a"].value == 1.0 and db["a"].good
    assert db["b"].value == 20.5


async def test_logic_sees_one_snapshot_even_if_the_device_image_changes_mid_scan() -> None:
    clock, db, dev, inputs, outputs = make()
    seen: list[float] = []

    def logic(now: float, dt: float) -> None:
        dev._image["ai0"] = Sample(99.0, t=now)  # the device moves on during logic
        seen.append(float(db["a"].value))  # type: ignore[arg-type]

    engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs, [LogicPhase("l", logic)])
    await engine.run_for(0.1)
    assert seen == [1.0]


async def test_an_input_older_than_its_stale_limit_turns_bad_stale() -> None:
    clock, db, dev, inputs, outputs = make(stale_after_s=0.5)
    engine = ScanEngine(clock, db, 0.1, [], inputs, outputs)  # nobody polls the device
    dev._image["ai0"] = Sample(1.0, t=0.0)
    dev._image["ai1"] = Sample(1.0, t=0.0)
    await engine.run_for(0.4)
    assert db["a"].good
    await engine.run_for(0.3)
    assert db["a"].quality is Quality.BAD and db["a"].reason is Reason.STALE


async def test_a_lost_device_makes_its_inputs_bad_and_they_recover_by_themselves() -> None:
    clock, db, dev, inputs, outputs = make()
    engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs)
    await engine.run_for(0.2)
    assert db["a"].good and db["dev.connected"].value is True
    dev.fail = True
    await engine.run_for(0.2)
    assert db["a"].quality is Quality.BAD and db["a"].reason is Reason.COMM_FAILURE
    assert db["dev.connected"].value is False
    dev.fail = False
    await engine.run_for(5.0)  # past the reconnect backoff
    assert db["a"].good and db["dev.connected"].value is True


async def test_outputs_are_written_only_when_their_tag_changes() -> None:
    clock, db, dev, inputs, outputs = make()
    setpoints = iter([1.0, 1.0, 1.0, 2.0, 2.0])

    def logic(now: float, dt: float) -> None:
        db.update(db["out"], next(setpoints, 2.0))

    engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs, [LogicPhase("l", logic)])
    await engine.run_for(0.7)
    assert dev.writes == [("ao0", 1.0), ("ao0", 2.0)]


async def test_an_exception_in_one_phase_is_counted_and_later_phases_still_run() -> None:
    clock, db, dev, inputs, outputs = make()
    ran: list[float] = []

    def broken(now: float, dt: float) -> None:
        raise ZeroDivisionError("boom")

    engine = ScanEngine(
        clock,
        db,
        0.1,
        [dev],
        inputs,
        outputs,
        [LogicPhase("broken", broken), LogicPhase("ok", lambda now, dt: ran.append(now))],
    )
    await engine.run_for(0.3)
    assert len(ran) == 3
    assert db["scan.logic_errors"].value == 3


async def test_virtual_time_advances_one_period_per_scan_and_runs_continue_seamlessly() -> None:
    clock, db, dev, inputs, outputs = make()
    times: list[float] = []
    engine = ScanEngine(
        clock, db, 0.1, [dev], inputs, outputs, [LogicPhase("t", lambda n, d: times.append(n))]
    )
    await engine.run_for(1.0)
    await engine.run_for(1.0)
    assert len(times) == 20
    steps = {round(b - a, 9) for a, b in itertools.pairwise(times)}
    assert steps == {0.1}
    assert clock.now() == 2.0
    assert db["scan.count"].value == 20


async def test_a_scan_longer_than_the_period_counts_as_an_overrun() -> None:
    clock, db, dev, inputs, outputs = make()

    def slow(now: float, dt: float) -> None:
        time.sleep(0.003)  # certainly longer than the 1 ms period

    engine = ScanEngine(clock, db, 0.001, [dev], inputs, outputs, [LogicPhase("slow", slow)])
    await engine.run_for(0.003)
    assert engine.stats.overruns == 3
    assert db["scan.overruns"].value == 3


async def test_drivers_are_polled_at_their_own_period_in_lockstep() -> None:
    clock, db, dev, inputs, outputs = make()
    dev.poll_period_s = 0.5
    engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs)
    await engine.run_for(2.0)
    assert dev.polls == 4  # t = 0, 0.5, 1.0, 1.5


async def test_a_dry_run_engine_gives_other_tasks_a_turn_less_often_and_computes_the_same() -> None:
    results = {}
    for n in (1, 25):
        clock, db, dev, inputs, outputs = make()
        seen: list[tuple[float, object, object]] = []

        def logic(
            now: float,
            dt: float,
            db: TagDB = db,
            dev: RecordingDriver = dev,
            seen: list[tuple[float, object, object]] = seen,
        ) -> None:
            dev.values["ai0"] = now * 2.0  # the device follows time
            db.update(db["out"], round(now, 6))
            seen.append((round(now, 6), db["a"].value, db["b"].value))

        engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs, [LogicPhase("l", logic)])
        engine.yield_every_scans = n
        turns = [0]
        done = asyncio.Event()

        async def other_task(done: asyncio.Event = done, turns: list[int] = turns) -> None:
            while not done.is_set():
                turns[0] += 1
                await asyncio.sleep(0)

        task = asyncio.create_task(other_task())
        await engine.run_for(10.0)  # 100 scans
        done.set()
        await task
        results[n] = (seen, turns[0], clock.now(), list(dev.writes))
    (seen_1, turns_1, end_1, writes_1) = results[1]
    (seen_25, turns_25, end_25, writes_25) = results[25]
    assert len(seen_1) == 100 and seen_25 == seen_1  # the same scans, the same values
    assert writes_25 == writes_1 and end_25 == end_1
    assert turns_1 >= 100  # a turn every scan, as a real sleep gives
    assert turns_25 <= 10  # a turn every 25 scans


async def test_each_scans_wall_duration_is_measured_unless_the_run_measures_itself() -> None:
    """A dry run measures its speed as a whole (simulated over wall time): its engine does
    not time each scan (the duration tags keep what they held); it still counts them."""
    for measured in (True, False):
        clock, db, dev, inputs, outputs = make()
        engine = ScanEngine(clock, db, 0.1, [dev], inputs, outputs)
        engine.measure_durations = measured
        timed = [db[name] for name in ("scan.duration_s", "scan.duration_max_s")]
        before = [(t.value, t.version) for t in timed]
        await engine.run_for(0.5)
        assert db["scan.count"].value == 5
        if measured:
            assert len(engine.stats.durations_s) == 5
            assert all(isinstance(t.value, float) and t.value > 0.0 for t in timed)
        else:
            assert len(engine.stats.durations_s) == 0
            assert [(t.value, t.version) for t in timed] == before


async def test_a_dry_run_does_not_time_its_scans(root: Path) -> None:
    seen: list[bool] = []
    original = ScanEngine.scan_once

    def spy(self: ScanEngine) -> None:
        seen.append(self.measure_durations)
        original(self)

    from pytest import MonkeyPatch

    with MonkeyPatch.context() as mp:
        mp.setattr(ScanEngine, "scan_once", spy)
        await dry_run(root / "recipes" / "nimh-ds2710.yaml", max_hours=0.01)
    assert seen and seen[-1] is False
