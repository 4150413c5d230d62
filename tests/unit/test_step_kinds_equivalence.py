"""Every registered step kind runs the same on the chain's fast paths as on its plain path
(issue 29, 1; docs/adr/0018-scan-performance.md, "Dry run").

The kinds are read from the registry (``supervisor.chains.kinds.KINDS``), not listed here:
a kind registered tomorrow enters these tests as it is. Programs of generated steps of
every kind (their setpoints, durations, until conditions and limits drawn at random) run
on the virtual clock against a small cell that follows the chain's requested current, once
with the chain's fast paths and once the plain way (``ChainRunner._fast`` False): every
tag, record and event is the same after every scan, and so are the charge moved and the
end. A step kind added the documented way and saying nothing of its needs runs right in
a dry run; one that says something false (a setpoint declared constant that reads the
voltage) is caught by the same comparison, which this file proves.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from supervisor.app import dryrun
from supervisor.app.dryrun import DryRunResult, dry_run
from supervisor.chains.behaviours import StepBehaviour
from supervisor.chains.compiler import compile_recipe
from supervisor.chains.engine import ChainRunner
from supervisor.chains.kinds import KINDS, StepKind
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import ProfilePoint, Program
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.config.recipe import load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.records import ChainEvent, Record
from supervisor.tags import Tag, TagDB

# --- a cell that follows the chain --------------------------------------------------------
CAPACITY_AH = 2.0
R_INTERNAL_OHM = 0.1


class Bench:
    """A channel's tags and a chain on them; the cell takes the current the chain asks for
    (held below its CV target when it sets one) and its voltage follows its charge."""

    def __init__(self, program: Program, fast: bool) -> None:
        self.db = db = TagDB()
        self.clock = VirtualClock(wall_epoch_s=1_767_254_400.0)  # 2026-01-01 08:00 UTC
        self.channel = Channel(
            "ch0", db, ChannelLimits((-1.0, 1.0), (0.5, 2.0)), capacity_ah=CAPACITY_AH
        )
        port = ChannelPort.from_tags(db, "ch0", Mode.AUTO.value, Mode.MANUAL.value)
        self.port = port
        self.runner = runner = ChainRunner(port, db, self.clock)
        runner._fast = fast
        self.records: list[Record] = []
        self.events: list[ChainEvent] = []
        runner.recorders.append(self.records.append)
        runner.listeners.append(self.events.append)
        runner.load(program, test_id="t")
        self.charge_ah = 1.0
        self.energy_wh = 0.0
        ch = self.channel
        db.update(ch.armed, True)
        db.update(ch.temperature, 25.0)
        self._measure(0.0)
        runner.command("start")

    def _ocv_v(self) -> float:
        return 1.1 + 0.3 * min(max(self.charge_ah / CAPACITY_AH, 0.0), 1.0)

    def _measure(self, current_a: float) -> None:
        db, ch = self.db, self.channel
        db.update(ch.current, current_a)
        db.update(ch.voltage, self._ocv_v() + current_a * R_INTERNAL_OHM)
        db.update(ch.charge_ah, self.charge_ah)
        db.update(ch.energy_wh, self.energy_wh)

    def scan(self, dt_s: float) -> None:
        """The cell runs ``dt_s`` at the current the chain asked for in the last scan, then
        the chain's scan reads it."""
        port = self.port
        amps = float(port.auto_current.value or 0.0) if port.auto_active.value else 0.0
        cv_v = float(port.auto_voltage.value or 0.0)
        if cv_v > 0 and amps > 0:  # the source holds the voltage at its CV target
            amps = max(0.0, min(amps, (cv_v - self._ocv_v()) / R_INTERNAL_OHM))
        amps = max(-1.0, min(1.0, amps))
        self.charge_ah += amps * dt_s / 3600.0
        self.energy_wh += amps * (self._ocv_v() + amps * R_INTERNAL_OHM) * dt_s / 3600.0
        self._measure(amps)
        self.clock.advance(dt_s)
        now = self.clock.now()
        self.db.set_scan_time(now)
        self.runner.run(now, dt_s)

    def seen(self) -> tuple[Any, ...]:
        """Everything a client or a result file could tell apart (floats by their repr)."""
        db, runner = self.db, self.runner
        return (
            tuple(tag_state(t) for t in db),
            db.version,
            runner.state,
            runner.end_reason,
            [repr(e) for e in self.events],
            [repr(r) for r in self.records],
            repr(self.charge_ah),
        )


def tag_state(t: Tag) -> tuple[Any, ...]:
    return (t.name, repr(t.value), t.quality, t.reason, t.source_t, t.server_t, t.version, t.forced)


def differences(program: Program, scans: list[float]) -> str:
    """The program on a fast and a plain bench, scan by scan: "" when they agree after every
    scan, else where they first differ."""
    fast, plain = Bench(program, True), Bench(program, False)
    for k, dt_s in enumerate([0.0, *scans]):
        if k:
            fast.scan(dt_s)
            plain.scan(dt_s)
        a, b = fast.seen(), plain.seen()
        if a != b:
            tags = [f"{x[0]}: {x[1]} vs {y[1]}" for x, y in zip(a[0], b[0], strict=True) if x != y]
            return f"after scan {k}: " + ("; ".join(tags) or "records, events or state differ")
    return ""


# --- programs of every registered kind ------------------------------------------------------
UNTILS = [
    "voltage >= 1.38 V",
    "voltage <= 1.15 V",
    "step_time > 7 s",
    "delta_peak >= 2 mV and step_time > 3 s",
    "current < -0.2 A",
    "step_charge > 0.5 mAh",
    "dv_dt < 0 V/s and step_time > 5 s",
    "temperature > 40 degC",
]
ACTIONS = ["next", "next", "next_cycle", "end", "hold"]
LIMITS = [
    "",
    "limits: {voltage: [1.0 V, 1.45 V], delay: 2 s}\n",
    "limits: {current: [-0.8 A, 0.8 A]}\n",
]


def recipe_text(
    steps: list[tuple[float, list[tuple[str, str]]]],
    limits: str,
    cycles: int,
    period_s: float,
    group: str = "",
) -> str:
    """Rest steps with their durations and until conditions, and a group's line: the frame
    the generated kinds are put in (a rest compiles with any end; its kind and setpoint are
    replaced after)."""
    lines = [
        "recipe: kinds",
        "chemistry: nimh",
        "capacity: 2000 mAh",
        f"cycles: {cycles}",
        f"logging: {{period: {period_s:g} s, delta_v: 5 mV}}",
    ]
    text = "\n".join(lines) + "\n" + limits + "steps:\n"
    for k, (duration_s, untils) in enumerate(steps):
        text += f"  - id: s{k}\n    rest: {duration_s:g} s\n"
        if untils:
            text += "    until:\n" + "".join(f"      - {c}: {a}\n" for c, a in untils)
    return text + (f"groups:\n  - {group}\n" if group else "")


@st.composite
def setpoints(draw: st.DrawFn, n_steps: int) -> dict[str, Any]:
    """Every field a kind may read for its setpoint, drawn for each step whatever its kind
    (a kind reads its own and ignores the others)."""
    times = sorted(draw(st.lists(st.sampled_from([2.0, 4.0, 5.0, 9.0]), max_size=3, unique=True)))
    profile = tuple(
        ProfilePoint(
            t_s=t,
            current_a=draw(st.sampled_from([-0.5, 0.0, 0.3])),
            v_max=draw(st.sampled_from([None, 1.25, 1.5])),
        )
        for t in [0.0, *times]
    )
    return {
        "current_a": draw(st.sampled_from([-0.6, -0.2, 0.0, 0.2, 0.5])),
        "voltage_v": draw(st.sampled_from([None, 1.32, 1.4])),
        "power_w": draw(st.sampled_from([None, -0.4, 0.3])),
        "pulse_on_s": draw(st.sampled_from([1.0, 2.0, 3.0])),
        "pulse_off_s": draw(st.sampled_from([0.0, 1.0, 2.0])),
        "pulse_count": draw(st.integers(1, 3)),
        "profile": profile,
        "profile_repeat": draw(st.integers(1, 2)),
        "sleep_s": draw(st.sampled_from([0.0, 3.0, 8.0])),
        "sleep_until": (8, draw(st.sampled_from([0, 1]))),
        "goto": draw(st.integers(0, n_steps - 1)),
    }


@st.composite
def programs(draw: st.DrawFn) -> Program:
    n = draw(st.integers(1, 5))
    frame = [
        (
            draw(st.sampled_from([3.0, 12.0, 40.0, 600.0])),
            draw(
                st.lists(st.tuples(st.sampled_from(UNTILS), st.sampled_from(ACTIONS)), max_size=2)
            ),
        )
        for _ in range(n)
    ]
    # Sometimes a group over the first steps, ended by its time limit or an until.
    members = ", ".join(f"s{k}" for k in range(draw(st.integers(1, n))))
    group = draw(
        st.sampled_from(
            [
                "",
                f"{{id: g, steps: [{members}], duration: 6 s}}",
                f"{{id: g, steps: [{members}], until: [{{'voltage <= 1.2 V': next}}]}}",
            ]
        )
    )
    text = recipe_text(
        frame,
        draw(st.sampled_from(LIMITS)),
        draw(st.integers(1, 2)),
        draw(st.sampled_from([2.0, 10.0])),
        group,
    )
    recipe, pos = load_recipe_text(text)
    program = compile_recipe(recipe, pos, "<generated>")
    steps = tuple(
        dataclasses.replace(step, kind=draw(st.sampled_from(sorted(KINDS))), **draw(setpoints(n)))
        for step in program.steps
    )
    return dataclasses.replace(program, steps=steps)


scan_periods = st.lists(st.sampled_from([1.0, 1.0, 0.5, 2.0]), min_size=20, max_size=120)


def same_on_both_paths(max_examples: int, shrink: bool = True) -> Callable[[], None]:
    """The property, as a test over generated programs (kinds drawn from the registry as it
    is when the test runs); ``shrink`` False: the first failing example is the answer."""

    @settings(
        max_examples=max_examples,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow],
        phases=list(Phase) if shrink else [Phase.generate],
    )
    @given(programs(), scan_periods)
    def check(program: Program, scans: list[float]) -> None:
        assert differences(program, scans) == ""

    return check


def test_every_registered_kind_runs_the_same_on_the_fast_and_the_plain_path() -> None:
    same_on_both_paths(300)()


# --- a new kind, registered as a maintainer would ------------------------------------------
class ConstantResistance(StepBehaviour):
    """A discharge through a fixed resistance: I = -V / R from the last GOOD voltage. It
    says nothing of its needs (the default): its setpoint must be asked every scan."""

    RESISTANCE_OHM = 5.0

    def setpoint(self, step_time_s: float, voltage_v: float | None) -> float:
        return 0.0 if voltage_v is None else -voltage_v / self.RESISTANCE_OHM


class WronglyConstantResistance(ConstantResistance):
    """The same with a false word: its setpoint declared a constant (it reads the voltage):
    the fast path asks it once, at load, with no voltage, and drives 0 A."""

    setpoint_reads = frozenset()


def resistance_kind(behaviour: type[StepBehaviour]) -> StepKind:
    return StepKind("resistance", behaviour, "CR_DCH")


def test_a_new_kind_that_says_nothing_takes_the_plain_path() -> None:
    assert ConstantResistance.setpoint_varies
    assert not WronglyConstantResistance.setpoint_varies  # what it (wrongly) said


CR_RECIPE = """
recipe: cr
chemistry: nimh
capacity: 2000 mAh
steps:
  - id: load
    discharge: 0.1 A
    duration: 30 min
    until:
      - voltage <= 1.0 V: next
  - {id: after, rest: 1 min}
"""


async def cr_dry_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, behaviour: type[StepBehaviour], fast: bool
) -> DryRunResult:
    """A dry run of ``CR_RECIPE`` with its ``load`` step of the new kind (the recipe model
    has no field for it: the compiled step's kind is replaced)."""
    monkeypatch.setitem(KINDS, "resistance", resistance_kind(behaviour))
    compile_ = compile_recipe  # what the dry run calls (dryrun.compile_recipe)

    def compile_with_cr(*args: Any, **kwargs: Any) -> Program:
        program = compile_(*args, **kwargs)
        steps = tuple(
            dataclasses.replace(s, kind="resistance") if s.id == "load" else s
            for s in program.steps
        )
        return dataclasses.replace(program, steps=steps)

    monkeypatch.setattr(dryrun, "compile_recipe", compile_with_cr)
    monkeypatch.setattr(ChainRunner, "_fast", fast)
    path = tmp_path / "cr.yaml"
    path.write_text(CR_RECIPE)
    return await dry_run(path, max_hours=2.0)


def discharged_mah(res: DryRunResult) -> float:
    return float(res.summary["cycles"][0]["discharge_capacity_ah"]) * 1000


async def test_a_new_kind_with_the_default_needs_runs_right_in_a_dry_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fast = await cr_dry_run(tmp_path, monkeypatch, ConstantResistance, fast=True)
    plain = await cr_dry_run(tmp_path, monkeypatch, ConstantResistance, fast=False)
    # 30 min through 5 ohm at 1.2-1.4 V: 120-140 mAh (issue 29: the fast path gave 0.0).
    assert 110.0 < discharged_mah(fast) < 150.0
    assert fast.summary == plain.summary
    assert (fast.state, fast.end_reason, fast.simulated_s) == (
        plain.state,
        plain.end_reason,
        plain.simulated_s,
    )


async def test_a_kind_with_a_false_need_drives_0_a_in_a_dry_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the equivalence test is there to catch, as a dry run shows it."""
    wrong = await cr_dry_run(tmp_path, monkeypatch, WronglyConstantResistance, fast=True)
    plain = await cr_dry_run(tmp_path, monkeypatch, WronglyConstantResistance, fast=False)
    assert discharged_mah(wrong) == 0.0
    assert discharged_mah(plain) > 110.0


def cr_program(behaviour: type[StepBehaviour]) -> Program:
    recipe, pos = load_recipe_text(CR_RECIPE)
    program = compile_recipe(recipe, pos, "<cr>")
    load = dataclasses.replace(program.steps[0], kind="resistance")
    return dataclasses.replace(program, steps=(load, *program.steps[1:]))


def test_the_equivalence_test_passes_a_new_kind_with_the_default_needs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(KINDS, "resistance", resistance_kind(ConstantResistance))
    assert differences(cr_program(ConstantResistance), [1.0] * 60) == ""
    # And the generated programs take it in, as any registered kind.
    same_on_both_paths(60)()


def test_the_equivalence_test_fails_a_kind_with_a_false_need(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setitem(KINDS, "resistance", resistance_kind(WronglyConstantResistance))
    # The comparison itself tells the paths apart, at the first scan of the step...
    found = differences(cr_program(WronglyConstantResistance), [1.0] * 60)
    assert "ch0.auto_current" in found
    # ...and the generated programs find it with no example written for it.
    with pytest.raises(AssertionError, match="auto_current"):
        same_on_both_paths(300, shrink=False)()


def test_the_generated_steps_are_of_every_registered_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    """The strategy draws kinds from the registry when it runs: a kind registered later is
    drawn too."""
    monkeypatch.setitem(KINDS, "resistance", resistance_kind(ConstantResistance))
    seen: set[str] = set()

    @settings(max_examples=200, deadline=None, database=None)
    @given(programs())
    def collect(program: Program) -> None:
        seen.update(s.kind for s in program.steps)

    collect()
    assert seen == set(KINDS)
