"""The dry run's fast paths answer what the plain ones do (docs/adr/0018-scan-performance.md,
"Dry run"): a chain that computes only the condition values its program reads and asks a
behaviour only what it answers differently from a rest step gives the same records,
events and end as one that computes and asks everything every scan, on the shipped
recipes; the cell's voltage computed inline is the one its methods compute, bit for bit;
the simulated board's current from its cache is the one computed afresh; and a dry run
settles the heap for the run and leaves the collector as it found it."""

from __future__ import annotations

import asyncio
import gc
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.app.dryrun import DryRunResult, dry_run, settled_heap
from supervisor.chains.behaviours import StepBehaviour
from supervisor.chains.compiler import compile_recipe
from supervisor.chains.conditions import ConditionValues
from supervisor.chains.engine import ChainRunner
from supervisor.chains.kinds import KINDS
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import CompiledStep
from supervisor.chains.run import RunState
from supervisor.chains.sampling import LogRules
from supervisor.channels import Channel, ChannelLimits
from supervisor.config.recipe import load_recipe_text
from supervisor.core.quality import Quality, Reason
from supervisor.core.records import Record
from supervisor.devices.chadeche import ChadecheDriver
from supervisor.devices.chadeche.protocol import (
    ADC_LSB_V,
    ADC_MAX_CODE,
    Chip,
    DacChannel,
    DacWord,
    voltage_to_adc_code,
)
from supervisor.devices.chadeche.sim import SimBoard
from supervisor.sim.battery import NiMHCell
from supervisor.tags import TagDB, TagSpec

RECIPES = Path(__file__).parents[2] / "recipes"


async def run(recipe: Path, max_hours: float) -> tuple[DryRunResult, list[Record]]:
    records: list[Record] = []
    res = await dry_run(recipe, max_hours=max_hours, recorders=[records.append])
    return res, records


def outcome(res: DryRunResult) -> tuple[Any, ...]:
    return (
        res.state,
        res.end_reason,
        res.simulated_s,
        res.summary,
        res.step_sequence,
        res.finished,
        res.steps_omitted,
    )


@pytest.mark.parametrize(
    ("recipe", "max_hours"),
    [
        ("nimh-25h-slow-cycle.yaml", 2.0),
        ("nimh-fast-charge-dv.yaml", 3.0),
        ("nimh-ds2710.yaml", 3.0),
        ("capacity-test.yaml", 2.0),
        ("liion-cccv-cycle.yaml", 2.0),
    ],
)
async def test_the_fast_chain_gives_the_records_and_end_of_the_plain_one(
    recipe: str, max_hours: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    fast, fast_records = await run(RECIPES / recipe, max_hours)
    monkeypatch.setattr(ChainRunner, "_fast", False)
    plain, plain_records = await run(RECIPES / recipe, max_hours)
    assert fast_records == plain_records
    assert outcome(fast) == outcome(plain)


def test_the_chain_is_fast_unless_told_otherwise() -> None:
    assert ChainRunner._fast is True


def overrides(cls: type[StepBehaviour], name: str) -> bool:
    return getattr(cls, name) is not getattr(StepBehaviour, name)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_behaviour_says_which_of_its_answers_differ_from_a_rest_steps(kind: str) -> None:
    cls = KINDS[kind].behaviour
    assert isinstance(cls, type)
    assert cls.has_limits == overrides(cls, "limits")
    assert cls.has_scan == overrides(cls, "scan")
    assert cls.has_done == overrides(cls, "done")
    if not overrides(cls, "setpoint"):
        assert not cls.setpoint_varies


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(sorted(KINDS)),
    st.floats(-2.0, 2.0),
    st.floats(0.0, 1e6),
    st.one_of(st.none(), st.floats(-5.0, 5.0)),
)
def test_a_setpoint_said_not_to_vary_is_the_same_at_any_time_and_voltage(
    kind: str, current_a: float, step_time_s: float, voltage_v: float | None
) -> None:
    step = CompiledStep(index=0, id="s", kind=kind, current_a=current_a, voltage_v=1.5)
    behaviour = KINDS[kind].behaviour(step)
    if not behaviour.setpoint_varies:
        assert behaviour.setpoint(step_time_s, voltage_v) == behaviour.setpoint(0.0, None)


CONDITIONS_RECIPE = """
recipe: values
chemistry: nimh
capacity: 2000 mAh
parameters:
  v_top: 1.6 V
  p_set: 3 W  # a parameter may not be named like the measurement (issue 28)
steps:
  - id: charge
    charge: 0.1 C
    until:
      - {until}: next
"""
CONDITIONS = [
    "voltage >= v_top",
    "delta_peak >= 3 mV and step_time > 4 min",
    "dv_dt < 0 V/s or peak_voltage > 1.5 V",
    "charge > 1 Ah and step_charge > 0.5 Ah and energy > 1 Wh and step_energy > 1 Wh",
    "cycle_time > 1 h and test_time > 2 h and cycle > 1",
    "power > 2 W",
    "temperature > 40 degC and current > 0.1 A",
]


@settings(max_examples=100, deadline=None)
@given(
    st.sampled_from(CONDITIONS),
    st.lists(
        st.tuples(
            st.floats(0.5, 2.0),
            st.floats(-0.5, 0.5),
            st.booleans(),
            st.floats(0.0, 2.0),
            st.integers(1, 3),
        ),
        min_size=1,
        max_size=30,
    ),
)
def test_the_values_read_are_those_of_every_value(
    until: str, scans: list[tuple[float, float, bool, float, int]]
) -> None:
    db = TagDB()
    Channel("ch0", db, ChannelLimits((-1.0, 1.0), (0.0, 2.0)), capacity_ah=2.0)
    recipe, pos = load_recipe_text(CONDITIONS_RECIPE.format(until=until), "values.yaml")
    program = compile_recipe(recipe, pos, "values.yaml")
    port = ChannelPort.from_tags(db, "ch0", "auto")
    cv = ConditionValues(port, db, program)
    r = RunState(t_step0=1.0, t_cycle0=0.5, t_test0=0.25, step_q0=0.1, step_e0=0.05)
    for k, (v, i, good, q, cycle) in enumerate(scans):
        now = 2.0 * k
        if good:
            db.update(port.voltage, v)
            cv.observe(now, v)
        else:
            db.update(port.voltage, v, Quality.BAD, Reason.STALE)
        db.update(port.current, i)
        db.update(port.power, v * i)
        db.update(port.charge_ah, q)
        db.update(port.energy_wh, q * 1.3)
        r.cycle = cycle
        read = dict(cv.values_read(now, r))
        every = cv.values(now, r)
        assert {n: read[n] for n in cv.read} == {n: every[n] for n in cv.read}


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, 1.05),
    st.lists(
        st.tuples(st.sampled_from([0.0, 0.2, 0.4, -0.2, -0.4]), st.sampled_from([0.5, 1.0, 60.0])),
        max_size=40,
    ),
)
def test_the_cells_voltage_is_the_one_its_methods_compute(
    soc: float, program: list[tuple[float, float]]
) -> None:
    cell = NiMHCell(soc=soc)
    for current_a, dt_s in program:
        cell.step(current_a, dt_s)
        temp, s = cell.temperature_c, cell.soc
        factor = cell._arrhenius(temp)
        expected = cell._ocv(s, temp) + cell._overpotential(current_a, s, temp, factor)
        assert cell.voltage_at(current_a) == expected


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.tuples(st.just("dac"), st.integers(0, 4095), st.booleans(), st.booleans()),
            st.tuples(st.just("relay"), st.booleans()),
            st.tuples(st.just("gain"), st.sampled_from([1.0, 0.98, 1.02])),
            st.tuples(st.just("offset"), st.sampled_from([0.0, 1.5, -2.0])),
            st.tuples(st.just("read")),
        ),
        max_size=40,
    )
)
def test_the_boards_cached_current_is_the_one_computed_afresh(ops: list[tuple[Any, ...]]) -> None:
    board = SimBoard(NiMHCell())
    for o in ops:
        if o[0] == "dac":
            board.dac_a = DacWord(DacChannel.A, o[1], gain_1x=o[2], active=o[3])
        elif o[0] == "relay":
            board.charging = o[1]
        elif o[0] == "gain":
            board.true_current_gain = o[1]
        elif o[0] == "offset":
            board.true_current_offset_ma = o[1]
        assert board.current_a == board._current_now()
        assert board.current_a == board._current_now()  # the cached answer, read again


@pytest.fixture
def nothing_frozen() -> Iterator[None]:
    """A process where nothing is frozen (an earlier test of this process may have settled
    the heap: freezing only changes what the collector walks, not what a test sees)."""
    frozen = gc.get_freeze_count()
    gc.unfreeze()
    yield
    if frozen:
        gc.freeze()


@pytest.mark.usefixtures("nothing_frozen")
async def test_a_dry_run_settles_the_heap_for_the_run_and_puts_it_back() -> None:
    thresholds, switch_s = gc.get_threshold(), sys.getswitchinterval()
    assert gc.get_freeze_count() == 0
    seen: list[int] = []

    def look(rec: Record) -> None:
        seen.append(gc.get_freeze_count())

    settled = await dry_run(RECIPES / "nimh-25h-slow-cycle.yaml", max_hours=0.5, recorders=[look])
    assert max(seen) > 0  # frozen while it computed (not yet at the start)
    assert gc.get_freeze_count() == 0
    assert gc.get_threshold() == thresholds
    assert sys.getswitchinterval() == switch_s
    gc.freeze()  # someone else froze objects: a dry run leaves the heap alone
    try:
        with settled_heap() as did:
            assert did is False
        unsettled = await dry_run(RECIPES / "nimh-25h-slow-cycle.yaml", max_hours=0.5)
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
    assert outcome(settled) == outcome(unsettled)


def moved(x: float | None, last: float | None, delta: float | None) -> bool:
    """A logging rule's ΔV / ΔI as it was written before the reason was inlined."""
    return delta is not None and x is not None and last is not None and abs(x - last) >= delta


maybe = st.one_of(st.none(), st.floats(-2.0, 2.0))


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(st.none(), st.sampled_from([1.0, 60.0])),
    st.one_of(st.none(), st.sampled_from([0.001, 0.01])),
    st.one_of(st.none(), st.sampled_from([0.01, 0.1])),
    st.floats(0.0, 200.0),
    maybe,
    maybe,
    maybe,
    maybe,
)
def test_a_records_reason_is_the_rules_answer(
    period: float | None,
    dv: float | None,
    di: float | None,
    now: float,
    v: float | None,
    i: float | None,
    last_v: float | None,
    last_i: float | None,
) -> None:
    text = "recipe: r\nsteps:\n  - {id: a, rest: 1 h}\n"
    recipe, pos = load_recipe_text(text)
    program = compile_recipe(recipe, pos, "<recipe>")
    rules = LogRules(program)
    rules._rules = ((period, dv, di),)
    run = RunState(last_rec_t=100.0, last_rec_v=last_v, last_rec_i=last_i)
    if period is not None and now - run.last_rec_t >= period - 1e-9:
        expected = "period"
    elif moved(v, last_v, dv):
        expected = "delta_v"
    elif moved(i, last_i, di):
        expected = "delta_i"
    else:
        expected = ""
    assert rules.reason(0, now, run, v, i) == expected


# --- third pass: the lockstep without coroutines, stamps, the board's current ----------
@pytest.mark.parametrize(
    ("recipe", "max_hours"),
    [("nimh-25h-slow-cycle.yaml", 2.0), ("nimh-fast-charge-dv.yaml", 3.0)],
)
async def test_the_lockstep_without_awaits_gives_the_records_and_end_of_the_awaited_one(
    recipe: str, max_hours: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    direct, direct_records = await run(RECIPES / recipe, max_hours)
    # Every poll and flush awaited, on the driver's plain path too (PolledDriver's poll
    # and flush: the I/O locks taken, a new sample for every point of every poll).
    monkeypatch.setattr(ChadecheDriver, "poll_now", lambda self: False)
    monkeypatch.setattr(ChadecheDriver, "flush_now", lambda self: False)
    awaited, awaited_records = await run(RECIPES / recipe, max_hours)
    assert awaited_records == direct_records
    assert outcome(awaited) == outcome(direct)


class Paced:
    """A driver without a direct path, polled every other scan, that records the order
    of the lockstep's calls (with the Chadèche driver's, through its methods)."""

    def __init__(self, name: str, calls: list[str]) -> None:
        self.name, self.calls = name, calls
        self.poll_period_s = 2.0
        self.connected = True

    def points(self) -> dict[str, Any]:
        return {}

    def image(self) -> dict[str, Any]:
        return {}

    def write(self, point: str, value: Any) -> None:
        raise KeyError(point)

    async def poll(self) -> None:
        self.calls.append(f"poll {self.name}")

    async def flush(self) -> None:
        self.calls.append(f"flush {self.name}")

    async def safe_state(self) -> str | None:
        return None

    async def close(self) -> None:
        return None


async def test_the_lockstep_polls_and_flushes_direct_and_awaited_drivers_in_their_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from supervisor.app.bench import build_bench
    from supervisor.app.dryrun import dry_run_config
    from supervisor.core.clock import VirtualClock

    def lockstep(direct: bool) -> list[str]:
        calls: list[str] = []
        clock = VirtualClock()
        bench = build_bench(dry_run_config("nimh-aa", 2.0, 0.5, 1.0), clock, in_process=True)
        engine = bench.engine
        chadeche = engine.drivers[0]
        assert isinstance(chadeche, ChadecheDriver)
        chadeche._direct = direct
        engine.drivers = [Paced("a", calls), chadeche, Paced("b", calls)]
        bus = chadeche._bus
        transfer = bus.transfer

        def seen(board: int, chip: Chip, data: bytes) -> bytes:
            calls.append(f"chadeche {chip.name}")  # what a poll or a flush sends
            return transfer(board, chip, data)

        monkeypatch.setattr(bus, "transfer", seen)
        asyncio.run(engine.run_for(5.0))
        calls.append(f"{chadeche.polls} polls at {clock.now()}")
        return calls

    direct = await asyncio.to_thread(lockstep, True)
    awaited = await asyncio.to_thread(lockstep, False)
    assert direct == awaited
    assert direct[-1] == "5 polls at 5.0"
    assert direct[-9:-1] == [
        "chadeche ADC", "flush a", "flush b",  # t = 3: a and b are not due
        "poll a", "chadeche ADC", "poll b", "flush a", "flush b",  # t = 4
    ]  # fmt: skip


FORCED: dict[str, Any] = {"float": 1.5, "int": 2, "bool": True, "str": "idle"}


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(["float", "int", "bool", "str"]),
    st.lists(
        st.tuples(
            st.one_of(
                st.none(),
                st.floats(allow_nan=True, allow_infinity=True),
                st.integers(-3, 3),
                st.booleans(),
                st.sampled_from(["", "idle", "charging"]),
            ),
            st.sampled_from([Quality.GOOD, Quality.UNCERTAIN, Quality.BAD]),
            st.sampled_from([Reason.NONE, Reason.STALE, Reason.LAST_KNOWN]),
            st.booleans(),  # forced before this step
            st.one_of(st.none(), st.floats(0.0, 100.0)),
        ),
        max_size=20,
    ),
)
def test_a_stamp_is_an_update_that_changes_nothing(dtype: str, steps: list[Any]) -> None:
    """What the call sites that stamp rely on: when the value equals a GOOD, reason-less
    tag's value (a float tag's is then finite), the update would change nothing but the
    source time it is given (nothing at all without one: ADR 0037); and ``stamp`` does
    just that, forced or not."""
    db, ref = TagDB(), TagDB()
    spec = TagSpec("t", dtype=dtype)  # type: ignore[arg-type]
    tag, twin = db.add(spec), ref.add(spec)
    for k, (value, quality, reason, forced, source_t) in enumerate(steps):
        db.set_scan_time(float(k))
        ref.set_scan_time(float(k))
        if forced != tag.forced:
            for d in (db, ref):
                if forced:
                    d.force("t", FORCED[dtype])
                else:
                    d.unforce("t")
        if value == tag.value and tag.quality is Quality.GOOD and tag.reason is Reason.NONE:
            if source_t is not None:
                db.stamp(tag, source_t)
            assert ref.update(twin, value, Quality.GOOD, Reason.NONE, source_t) is False
        else:
            db.update(tag, value, quality, reason, source_t)
            ref.update(twin, value, quality, reason, source_t)
        mine = (tag.value, tag.quality, tag.reason, tag.source_t, tag.server_t, tag.version)
        theirs = (
            twin.value,
            twin.quality,
            twin.reason,
            twin.source_t,
            twin.server_t,
            twin.version,
        )
        assert repr(mine) == repr(theirs)


@settings(max_examples=500, deadline=None)
@given(st.floats(allow_nan=False, allow_infinity=True) | st.integers(-10, 10))
def test_the_simulated_adcs_code_is_the_plain_formulas(voltage_v: float) -> None:
    if voltage_v <= 0.0:
        expected = 0
    elif voltage_v >= (ADC_MAX_CODE + 1) * ADC_LSB_V:
        expected = ADC_MAX_CODE
    else:
        expected = min(ADC_MAX_CODE, round(voltage_v / ADC_LSB_V))
    assert voltage_to_adc_code(voltage_v) == expected
    with pytest.raises(ValueError, match="NaN"):
        voltage_to_adc_code(math.nan)
