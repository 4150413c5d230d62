"""The chain's steady scan (``ChainRunner.run``'s short way, docs/adr/0018-scan-performance.md)
leaves every tag as the plain scan does: the same values, qualities, reasons, source and
server times and versions, in the same order of changes, with the same records, events and
states, whatever the readings, faults, modes, commands, forced tags and other writers do;
and a dry run of the shipped recipes changes the same tags the same way scan by scan."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.app import dryrun
from supervisor.app.bench import build_bench
from supervisor.app.dryrun import dry_run
from supervisor.chains.compiler import compile_recipe
from supervisor.chains.conditions import ConditionValues
from supervisor.chains.engine import ChainRunner
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import CompiledStep, Program
from supervisor.chains.run import RunState
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.config.recipe import load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.quality import Quality, Reason
from supervisor.core.records import ChainEvent, Record
from supervisor.tags import Tag, TagDB

RECIPES = Path(__file__).parents[2] / "recipes"

# Steps of every kind the steady scan takes (charge, rest, power, cccv) and of kinds it
# leaves to the plain scan (pulse, a group, a sleep), with limits and their delay,
# supervision, an interlock, ΔV/ΔI and period logging rules, two cycles.
STEADY_RECIPE = """
recipe: steady
chemistry: nimh
capacity: 2000 mAh
parameters:
  v_end: 1.0 V
  dv_stop: 3 mV
limits:
  voltage: [0.8 V, 1.9 V]
  current: [-1 A, 1 A]
  temperature: [null, 50 degC]
  delay: 2 s
cycles: 2
logging: {period: 5 s}
steps:
  - id: charge
    charge: 0.1 C
    duration: 25 s
    until:
      - delta_peak >= dv_stop and step_time > 4 s: next
    supervision: {max_time: 20 s, error: "temperature > 45 degC"}
  - {id: rest1, rest: 6 s, log: {delta_v: 5 mV}}
  - id: power
    power: 0.5 W
    duration: 8 s
    interlock: "temperature < 40 degC"
    until:
      - voltage <= v_end: next
  - id: cv
    cccv: {current: 0.2 A, voltage: 1.5 V}
    duration: 6 s
    log: {period: 3 s, delta_i: 10 mA}
  - id: pulse
    pulse: {current: 0.2 A, on_time: 1 s, off_time: 1 s, count: 2}
  - {id: nap, sleep: 2 s}
  - {id: rest2, rest: 4 s}
groups:
  - {id: tail, steps: [rest2], duration: 3 s}
"""

# The values a condition reads beyond the readings: dV/dt, the clocks, the counters, the
# cycle, a parameter (one named like a channel value is refused since issue 28).
READS_MORE_RECIPE = """
recipe: more
chemistry: nimh
capacity: 2000 mAh
parameters:
  q_most: 1 Ah
cycles: 3
steps:
  - id: charge
    charge: 0.1 C
    duration: 12 s
    until:
      - dv_dt < 0 V/s and test_time > 5 s: next
      - step_charge > q_most and cycle_time > 1 h: end
      - charge > 10 Ah or energy > 10 Wh or step_energy > 10 Wh or power > 50 W: end
      - cycle > 2 and step_time > 3 s: next
  - {id: rest, rest: 3 s}
"""

# A parameter in a condition, a charge at 0 A (no ETA), a step ended by its time limit only.
ODD_RECIPE = """
recipe: odd
capacity: 2000 mAh
parameters:
  v_high: 1.5 V
limits:
  voltage: [0.8 V, 1.9 V]
  current: [null, 0.5 A]
  delay: 1 s
logging: {period: 2 s, delta_v: 1 mV, delta_i: 1 mA}
steps:
  - id: idle
    charge: 0 A
    duration: 9 s
    until:
      - voltage > v_high: next
  - {id: push, discharge: 0.1 A, duration: 30 s}
"""

RECIPES_TEXT = {"steady": STEADY_RECIPE, "more": READS_MORE_RECIPE, "odd": ODD_RECIPE}

# Tags a disturbance may force, unforce, set the quality of or write: the chain's and the
# port's request tags (those the steady scan stamps when unchanged) and a clock.
POKED: dict[str, str | int | float | bool] = {
    "ch0.chain.step": "charge",
    "ch0.chain.step_index": 1,
    "ch0.chain.cycle": 1,
    "ch0.chain.interlock": "",
    "ch0.chain.step_time": 1.0,
    "ch0.auto_current": 0.2,
    "ch0.auto_active": True,
    "ch0.auto_voltage": 0.0,
}


class Bench:
    """A channel's tags, written by the test, and a chain on them (no channel logic)."""

    def __init__(
        self, recipe: str, fast: bool, estimate_s: float | None, meddles: bool = False
    ) -> None:
        self.db = db = TagDB()
        self.clock = VirtualClock()
        self.channel = Channel("ch0", db, ChannelLimits((-1.0, 1.0), (0.5, 2.0)), capacity_ah=2.0)
        port = ChannelPort.from_tags(db, "ch0", Mode.AUTO.value, Mode.MANUAL.value)
        self.runner = runner = ChainRunner(port, db, self.clock)
        runner._fast = fast
        self.records: list[Record] = []
        self.events: list[ChainEvent] = []
        self.samples: list[Record] = []
        self.refused: list[str] = []
        runner.recorders.append(self.records.append)
        if meddles:  # a recorder that acts on the chain: holds it at its fourth record
            runner.recorders.append(self.hold_at_the_fourth)
        runner.listeners.append(self.events.append)
        runner.samplers.append(EveryFewScans(self.samples))
        text, pos = load_recipe_text(RECIPES_TEXT[recipe])
        runner.load(compile_recipe(text, pos, "<recipe>"), test_id="t")
        runner.estimated_duration_s = estimate_s
        ch = self.channel
        for tag, value in ((ch.voltage, 1.3), (ch.current, 0.2), (ch.temperature, 25.0)):
            db.update(tag, value)
        db.update(ch.armed, True)
        runner.command("start")

    def hold_at_the_fourth(self, rec: Record) -> None:
        if len(self.records) == 4:
            self.runner.command("hold", actor="recorder")

    def apply(self, op: tuple[Any, ...]) -> None:
        db, ch = self.db, self.channel
        kind = op[0]
        if kind in ("voltage", "current", "temperature"):
            tag = getattr(ch, kind)
            if op[2]:
                db.update(tag, op[1])
            else:
                db.update(tag, op[1], Quality.BAD, Reason.STALE)
        elif kind == "armed":
            db.update(ch.armed, op[1])
        elif kind == "fault":
            db.update(ch.fault, op[1])
            db.update(ch.fault_action, op[2])
        elif kind == "mode":
            db.update(ch.mode, op[1])
        elif kind == "command":  # through the command tag, read in the next scan
            db.write("ch0.command", op[1])
        elif kind == "direct":  # as the bench's command path gives it, between scans
            self.runner.command(op[1])
        elif kind == "force":
            db.force(op[1], POKED[op[1]])
        elif kind == "unforce":
            db.unforce(op[1])
        elif kind == "quality":
            tag = db[op[1]]
            db.set_quality(tag, Quality.UNCERTAIN, Reason.LAST_KNOWN)
        elif kind == "uncertain":  # reason-less but not GOOD
            tag = db[op[1]]
            db.update(tag, tag.value, Quality.UNCERTAIN)
        elif kind == "explained":  # GOOD with a reason
            tag = db[op[1]]
            db.update(tag, tag.value, Quality.GOOD, Reason.LAST_KNOWN)
        elif kind == "write":
            db.update(db[op[1]], POKED[op[1]])
        elif kind == "estimate":
            self.runner.estimated_duration_s = op[1]

    def drift(self, drift_v: float) -> None:
        """A quiet scan's change: the voltage moves by ``drift_v`` (when GOOD), the charge
        by 0.1 mAh."""
        db, ch = self.db, self.channel
        if ch.voltage.good:
            db.update(ch.voltage, ch.voltage.as_float() + drift_v)
        db.update(ch.charge_ah, ch.charge_ah.as_float() + 0.0001)

    def scan(self, dt_s: float) -> None:
        self.clock.advance(dt_s)
        now = self.clock.now()
        self.db.set_scan_time(now)
        self.runner.run(now, dt_s)

    def seen(self) -> tuple[Any, ...]:
        """Everything a client or a result file could tell apart (floats by their repr:
        bit for bit, NaN included)."""
        db, runner = self.db, self.runner
        return (
            tuple(tag_state(t) for t in db),
            db.version,
            tuple(t.name for t in db.changed_since(0)),
            runner.state,
            [repr(e) for e in self.events],
            [repr(r) for r in self.records],
            [repr(r) for r in self.samples],
            self.refused,
        )


class EveryFewScans:
    """A sampler due every third time it is asked (a display's line)."""

    def __init__(self, out: list[Record]) -> None:
        self.out = out
        self.asked = 0

    def due(self, now: float) -> bool:
        self.asked += 1
        return self.asked % 3 == 0

    def on_sample(self, rec: Record) -> None:
        self.out.append(rec)


def tag_state(t: Tag) -> tuple[Any, ...]:
    return (t.name, repr(t.value), t.quality, t.reason, t.source_t, t.server_t, t.version, t.forced)


POKES = ["force", "unforce", "quality", "uncertain", "explained", "write"]
reading = st.one_of(
    st.tuples(st.just("voltage"), st.floats(1.0, 1.8), st.just(True)),
    st.tuples(st.just("voltage"), st.floats(0.6, 2.1), st.booleans()),
    st.tuples(st.just("voltage"), st.sampled_from([0.8, 1.9]), st.just(True)),  # the bounds
    st.tuples(st.just("current"), st.floats(-1.5, 1.5), st.booleans()),
    st.tuples(st.just("current"), st.sampled_from([-1.0, 1.0]), st.just(True)),
    st.tuples(st.just("temperature"), st.floats(20.0, 60.0), st.booleans()),
    st.tuples(st.just("temperature"), st.sampled_from([40.0, 45.0, 50.0]), st.just(True)),
)
command = st.sampled_from(
    ["resume", "resume", "ack", "ack", "advance", "hold", "stop", "abort", "reset", "start"]
)
disturbance = st.one_of(
    st.tuples(st.just("armed"), st.booleans()),
    st.tuples(st.just("fault"), st.sampled_from(["", "trip"]), st.sampled_from(["hold", "abort"])),
    st.tuples(st.just("mode"), st.sampled_from([Mode.AUTO.value, Mode.MANUAL.value])),
    st.tuples(st.sampled_from(["command", "direct"]), command),
    st.tuples(st.sampled_from(POKES), st.sampled_from(sorted(POKED))),
    st.tuples(st.just("estimate"), st.sampled_from([None, 10.0, 60.0, 3600.0])),
)
# A script: stretches of quiet scans (the cell drifting by a few mV a scan, charge moving)
# between a few readings and disturbances.
segments = st.lists(
    st.tuples(
        st.lists(st.one_of(reading, disturbance), max_size=3),
        st.integers(0, 25),
        st.sampled_from([1.0, 1.0, 0.5, 3.0]),
        st.sampled_from([-0.004, -0.001, 0.0, 0.001, 0.002]),
    ),
    min_size=1,
    max_size=12,
)
Script = list[tuple[list[tuple[Any, ...]], int, float, float]]


def compare(make: Callable[[bool], Bench], script: Script) -> None:
    """The script on a fast and a plain bench (``make(fast)``): the same after every scan."""
    fast, plain = make(True), make(False)
    assert fast.seen() == plain.seen()
    for ops, quiet, dt_s, drift_v in script:
        for bench in (fast, plain):
            for op in ops:
                try:
                    bench.apply(op)
                except Exception as exc:  # a refused command or write: refused on both
                    bench.refused.append(repr(exc))
            bench.scan(dt_s)
        assert fast.seen() == plain.seen()
        for _ in range(quiet):
            for bench in (fast, plain):
                bench.drift(drift_v)
                bench.scan(dt_s)
            assert fast.seen() == plain.seen()


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(sorted(RECIPES_TEXT)),
    st.sampled_from([None, 120.0]),
    st.booleans(),
    segments,
)
def test_the_steady_scan_leaves_every_tag_record_and_event_as_the_plain_scan_does(
    recipe: str, estimate_s: float | None, meddles: bool, script: Script
) -> None:
    compare(lambda fast: Bench(recipe, fast, estimate_s, meddles), script)


poke = st.tuples(st.sampled_from(POKES), st.sampled_from(sorted(POKED)))
pokes = st.lists(
    st.tuples(
        st.lists(st.one_of(poke, poke, poke, st.tuples(st.just("direct"), command)), max_size=2),
        st.integers(0, 4),
        st.just(1.0),
        st.sampled_from([-0.001, 0.0, 0.001]),
    ),
    min_size=1,
    max_size=15,
)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(sorted(RECIPES_TEXT)), pokes)
def test_tags_forced_or_written_by_others_in_a_quiet_run_end_as_with_the_plain_scan(
    recipe: str, script: Script
) -> None:
    """The tags the steady scan stamps when they hold, forced, unforced, given another
    quality or reason or written behind its back, with commands between scans."""
    compare(lambda fast: Bench(recipe, fast, None), script)


SCRIPTS: dict[str, tuple[str, Script]] = {
    # A limit crossed in a scan the plain way takes (a command in it), gone the next
    # scan, crossed again: its on-delay starts again from the second crossing.
    "limit delay across both ways": (
        "steady",
        [
            ([("voltage", 1.95, True), ("command", "advance")], 0, 1.0, 0.0),
            ([("voltage", 1.3, True)], 0, 1.0, 0.0),
            ([], 2, 1.0, 0.0),
            ([("voltage", 1.95, True)], 3, 1.0, 0.0),
        ],
    ),
    # The same, every scan a steady one.
    "limit delay in steady scans": (
        "steady",
        [
            ([("voltage", 1.95, True)], 0, 1.0, 0.0),
            ([("voltage", 1.3, True)], 0, 1.0, 0.0),
            ([("voltage", 1.95, True)], 3, 1.0, 0.0),
        ],
    ),
    # A limit on a reading no condition names.
    "current above its limit": (
        "odd",
        [([], 2, 1.0, 0.0), ([("current", 0.9, True)], 3, 1.0, 0.0)],
    ),
    # A period record due to the last bit: 5 s less 1e-9 after the record at the start.
    "period record to the last bit": ("steady", [([], 0, 5.0 - 1e-9, 0.0), ([], 3, 1.0, 0.0)]),
    "period record just short": ("steady", [([], 0, 5.0 - 2e-9, 0.0), ([], 3, 1.0, 0.0)]),
    # An advance given between scans (the bench's command path): the next scan acts on it.
    "advance between scans": (
        "steady",
        [([], 2, 1.0, 0.0), ([("direct", "advance")], 3, 1.0, 0.0)],
    ),
}


@pytest.mark.parametrize("kind", POKES)
@pytest.mark.parametrize("name", sorted(POKED))
def test_each_way_of_touching_a_stamped_tag_in_a_quiet_run_ends_as_with_the_plain_scan(
    kind: str, name: str
) -> None:
    script: Script = [
        ([], 2, 1.0, 0.0),
        ([(kind, name)], 2, 1.0, 0.0),
        ([("unforce", name)], 2, 1.0, 0.0),
    ]
    compare(lambda fast: Bench("steady", fast, None), script)


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_a_scripted_run_leaves_every_tag_as_the_plain_scan_does(name: str) -> None:
    recipe, script = SCRIPTS[name]
    compare(lambda fast: Bench(recipe, fast, None), script)


def test_a_quiet_run_takes_the_steady_way_and_leaves_the_tags_that_hold_as_they_are(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Not a promise of speed: a guard that the short way is the one taken (else the test
    above compares the plain scan with itself). A tag that holds keeps the time it last
    changed (ADR 0037)."""
    bench = Bench("steady", True, None)
    taken: list[float] = []
    original = ChainRunner._steady_outputs

    def spy(
        self: ChainRunner, now: float, r: RunState, program: Program, step: CompiledStep
    ) -> None:
        taken.append(now)
        original(self, now, r, program, step)

    monkeypatch.setattr(ChainRunner, "_steady_outputs", spy)
    step = bench.db["ch0.chain.step"]
    bench.scan(1.0)  # the first scan publishes the step
    version, changed_t = step.version, step.source_t
    for _ in range(3):
        bench.scan(1.0)
    assert taken == [1.0, 2.0, 3.0, 4.0]
    assert (step.value, step.version, step.source_t) == ("charge", version, changed_t)


# --- condition values ---------------------------------------------------------------------
@settings(max_examples=100, deadline=None)
@given(
    st.sampled_from(sorted(RECIPES_TEXT)),
    st.lists(
        st.tuples(st.floats(0.5, 2.0), st.booleans(), st.floats(-0.5, 0.5), st.booleans()),
        min_size=1,
        max_size=80,
    ),
)
def test_observed_values_are_an_observation_then_the_values_read(
    recipe: str, readings: list[tuple[float, bool, float, bool]]
) -> None:
    """``observed_values`` against ``observe`` (when the voltage is GOOD) then ``values``,
    on two condition values fed the same scans: the names read and the peak agree."""
    db = TagDB()
    ch = Channel("ch0", db, ChannelLimits((-1.0, 1.0), (0.5, 2.0)), capacity_ah=2.0)
    port = ChannelPort.from_tags(db, "ch0", Mode.AUTO.value)
    text, pos = load_recipe_text(RECIPES_TEXT[recipe])
    program = compile_recipe(text, pos, "<recipe>")
    one, every = ConditionValues(port, db, program), ConditionValues(port, db, program)
    run = RunState(t_step0=0.5, t_cycle0=0.25, t_test0=0.125, step_q0=0.1, step_e0=0.05)
    for k, (v, v_good, i, i_good) in enumerate(readings):
        now = 2.0 * k
        quality = Quality.GOOD if v_good else Quality.BAD
        db.update(ch.voltage, v, quality, Reason.NONE if v_good else Reason.STALE)
        db.update(ch.current, i, Quality.GOOD if i_good else Quality.BAD)
        db.update(ch.charge_ah, 0.01 * k)
        got = dict(one.observed_values(now, run))
        if v_good:
            every.observe(now, v)
        expected = every.values(now, run)
        assert {n: got[n] for n in one.read} == {n: expected[n] for n in one.read}
        assert one.peak_v == every.peak_v


# --- the shipped recipes, scan by scan ------------------------------------------------------
Changes = list[tuple[Any, ...]]


async def changes_per_scan(
    recipe: Path, max_hours: float, monkeypatch: pytest.MonkeyPatch
) -> Changes:
    """Each scan's changed tags in the order of their change, and every tag's state (but
    the scan engine's own, which measure wall time), in a dry run of ``recipe``."""
    seen: Changes = []

    class Watch:
        name = "watch"

        def __init__(self) -> None:
            self.version = 0

        def on_scan(self, db: TagDB, now: float) -> None:
            changed = [
                t.name for t in db.changed_since(self.version) if not t.name.startswith("scan.")
            ]
            self.version = db.version
            seen.append(
                (
                    tuple(changed),
                    *(
                        (t.name, repr(t.value), t.quality, t.reason, t.source_t, t.server_t)
                        for t in db
                        if not t.name.startswith("scan.")
                    ),
                )
            )

    def watched(*args: Any, **kw: Any) -> Any:
        bench = build_bench(*args, **kw)
        bench.engine.publishers.append(Watch())
        return bench

    monkeypatch.setattr(dryrun, "build_bench", watched)
    await dry_run(recipe, max_hours=max_hours, soc=0.0)
    return seen


@pytest.mark.parametrize(
    ("recipe", "max_hours"),
    [
        ("nimh-25h-slow-cycle.yaml", 0.5),
        ("capacity-test.yaml", 0.5),
        ("liion-cccv-cycle.yaml", 0.3),
        ("nimh-fast-charge-dv.yaml", 1.0),
    ],
)
async def test_a_dry_run_changes_the_same_tags_the_same_way_each_scan_as_the_plain_chain(
    recipe: str, max_hours: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    fast = await changes_per_scan(RECIPES / recipe, max_hours, monkeypatch)
    monkeypatch.setattr(ChainRunner, "_fast", False)
    plain = await changes_per_scan(RECIPES / recipe, max_hours, monkeypatch)
    assert len(fast) == len(plain)
    for k, (a, b) in enumerate(zip(fast, plain, strict=True)):
        assert a == b, f"scan {k}"
