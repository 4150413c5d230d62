"""Loops that let no time pass (issue 9, ADR 0011).

``supervisor check`` refuses a cycle of steps that can all end in the scan they start,
naming them; a recipe that loops through steps that take time, or that end on measured
conditions, is accepted. The engine bounds what one scan can do: past
``MAX_TRANSITIONS_PER_SCAN`` steps started in one scan the chain is held with a
supervision alarm naming the loop (these programs are built directly: check refuses them).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.chains.compiler import compile_recipe
from supervisor.chains.engine import ChainRunner
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import CompiledStep, Limits, LogRule, Program
from supervisor.chains.states import State
from supervisor.channels import Channel, ChannelLimits, Mode
from supervisor.cli.main import main
from supervisor.config.limits import MAX_TRANSITIONS_PER_SCAN
from supervisor.config.recipe import load_recipe_text
from supervisor.core.clock import VirtualClock
from supervisor.core.errors import ConfigErrors
from supervisor.core.records import ChainEvent
from supervisor.tags import TagDB
from supervisor.testing.recipes import RECIPES_MAP

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_recipes"


def refusal(text: str) -> str:
    """The one refusal of ``text`` as ``check`` prints it (``r.yaml:line:col: message``)."""
    recipe, pos = load_recipe_text(text, "r.yaml")
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, "r.yaml")
    (error,) = info.value.errors
    return f"{error.file}:{error.line}:{error.col}: {error.message}"


def accepted(text: str) -> Program:
    recipe, pos = load_recipe_text(text, "r.yaml")
    return compile_recipe(recipe, pos, "r.yaml")


# --- check: the cases (the corpus files) ---------------------------------------------
ADVICE = "give one of them a duration above 0 s or a condition that takes time"
CORPUS = [
    (
        "zero_rest_loop.yaml",
        "4:24: loop that lets no time pass: settle → again → settle; each of its steps can"
        " end in the scan it starts (settle: rest 0 s; again: goto settle); " + ADVICE,
    ),
    (
        "zero_sleep_loop.yaml",
        "3:22: loop that lets no time pass: nap → again → nap; each of its steps can end in"
        " the scan it starts (nap: sleep 0 s; again: goto nap); " + ADVICE,
    ),
    (
        "until_true_at_once.yaml",
        "6:9: loop that lets no time pass: spin → spin; each of its steps can end in the scan"
        " it starts (spin: until #1 'true' is true at once); " + ADVICE,
    ),
    (
        "zero_group_loop.yaml",
        "3:42: loop that lets no time pass: work → again → work; each of its steps can end"
        " in the scan it starts (work: group burst lasts 0 s; again: goto work); " + ADVICE,
    ),
    (
        "goto_chain_into_zero_step.yaml",
        "4:22: loop that lets no time pass: hop1 → hop2 → idle → back → hop1; each of its"
        " steps can end in the scan it starts (hop1: goto hop2; hop2: goto idle; idle:"
        " duration 0 s; back: goto hop1); " + ADVICE,
    ),
    (
        "zero_cycle_body.yaml",
        "4:24: loop that lets no time pass: settle → (next cycle) → settle; each of its steps"
        " can end in the scan it starts (settle: rest 0 s; cycles: 1000000 starts it again); "
        + ADVICE,
    ),
]


@pytest.mark.parametrize(("name", "message"), CORPUS, ids=[c[0] for c in CORPUS])
def test_check_refuses_each_zero_time_loop_naming_its_steps(
    name: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["check", str(BAD / name)]) == 2
    err = capsys.readouterr().err
    assert err == f"{BAD / name}:{message}\n"


def test_a_loop_of_gotos_only_keeps_its_message() -> None:
    text = "recipe: r\nsteps:\n  - {id: a, rest: 1 s}\n  - {id: b, goto: c}\n  - {id: c, goto: b}\n"
    assert refusal(text) == "r.yaml:4:19: loop with no exit and no duration: b → c → b"


def test_a_goto_to_itself_is_a_loop() -> None:
    text = "recipe: r\nsteps:\n  - {id: a, rest: 1 s}\n  - {id: b, goto: b}\n"
    assert refusal(text) == "r.yaml:4:19: loop with no exit and no duration: b → b"


def test_a_condition_true_at_step_time_0_ends_the_step_at_once() -> None:
    text = """recipe: r
parameters: {t_min: 0 s}
steps:
  - id: a
    charge: 100 mA
    duration: 1 h
    until:
      - step_time >= t_min: a
"""
    assert refusal(text).startswith(
        "r.yaml:8:9: loop that lets no time pass: a → a; each of its steps can end in the"
        " scan it starts (a: until #1 'step_time >= t_min' is true at once); "
    )
    assert accepted(text.replace("t_min: 0 s", "t_min: 5 s")).steps  # 5 s pass each time


def test_a_sleep_of_0_s_as_an_action_is_a_loop_too() -> None:
    text = 'recipe: r\nsteps:\n  - id: a\n    rest: 1 h\n    until:\n      - true: "+00:00"\n'
    text += "  - {id: b, goto: a}\n"
    assert "a → b → a; each of its steps can end in the scan it starts (a: until #1 'true'" in (
        refusal(text)
    )
    assert accepted(text.replace("+00:00", "+00:01")).steps


def test_a_measured_way_out_of_a_step_that_ends_at_once_is_named_with_it() -> None:
    # b ends at once (true); its first condition may hold at once too and leads back to a.
    text = """recipe: r
steps:
  - {id: a, rest: 0 s}
  - id: b
    rest: true
    until:
      - voltage > 1 V: a
      - true: end
"""
    assert refusal(text).startswith(
        "r.yaml:3:19: loop that lets no time pass: a → b → a; each of its steps can end in"
        " the scan it starts (a: rest 0 s; b: until #1 'voltage > 1 V' may be true at once,"
        " else until #2 'true' is true at once); "
    )


def test_every_loop_is_reported_once() -> None:
    text = """recipe: r
steps:
  - {id: a, rest: 0 s}
  - {id: b, goto: a}
  - {id: c, charge: 100 mA, duration: 1 h}
  - {id: d, sleep: 0 s}
  - {id: e, goto: d}
"""
    recipe, pos = load_recipe_text(text, "r.yaml")
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, "r.yaml")
    assert [(e.line, e.message.split(";")[0]) for e in info.value.errors] == [
        (3, "loop that lets no time pass: a → b → a"),
        (6, "loop that lets no time pass: d → e → d"),
    ]


# --- check: what stays accepted --------------------------------------------------------------
VALID = {
    "a rest that takes time, then a goto back": """recipe: r
steps:
  - {id: a, rest: 1 s}
  - {id: b, goto: a}
""",
    "cycling on measured conditions (charge to v_max, discharge to v_min, again)": """recipe: r
steps:
  - id: charge
    charge: 100 mA
    until:
      - voltage >= 1.7 V: discharge
  - id: discharge
    discharge: 100 mA
    until:
      - voltage <= 1.0 V: charge
""",
    "steps that end at once but lead out of the loop": """recipe: r
steps:
  - {id: a, rest: 0 s}
  - {id: b, duration: 0 s, rest: true}
  - {id: c, charge: 100 mA, duration: 1 h}
  - {id: d, goto: a}
""",
    "a step-time condition that needs time": """recipe: r
steps:
  - id: a
    rest: true
    until:
      - step_time >= 10 s: a
      - step_time < 0 s: a
""",
    "a zero-time body run once (cycles: 1)": """recipe: r
steps:
  - {id: a, rest: 0 s}
  - {id: b, end_cycle: true}
""",
    "many cycles of a body that takes time": """recipe: r
cycles: 1000000
steps:
  - {id: tick, rest: 1 s}
  - {id: e, end_cycle: true}
""",
    "a group of 0 s that is left for good": """recipe: r
groups:
  - {id: g, steps: [a], duration: 0 s}
steps:
  - {id: a, rest: 1 h}
  - {id: b, rest: 1 h}
""",
    "a sleep until a time of day in the loop": """recipe: r
steps:
  - {id: wake, sleep_until: "20:00"}
  - {id: a, rest: 0 s}
  - {id: b, goto: wake}
""",
    "a pulse train in the loop (its on_time is above 0 s)": """recipe: r
steps:
  - {id: p, pulse: {current: 100 mA, on_time: 1 s, off_time: 0 s, count: 1}}
  - {id: b, goto: p}
""",
}


@pytest.mark.parametrize("text", VALID.values(), ids=list(VALID))
def test_a_loop_that_lets_time_pass_is_accepted(text: str) -> None:
    assert accepted(text).steps


@pytest.mark.parametrize("path", sorted((ROOT / "recipes").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_recipe_passes_check(path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # With the map of the bench they are written for (the pack's recipes name its BMS tags).
    assert main(["check", str(RECIPES_MAP), str(path)]) == 0
    assert capsys.readouterr().err == ""


# --- the engine: at most MAX_TRANSITIONS_PER_SCAN steps started in one scan -------------------
PERIOD_S = 1.0


def program(*steps: CompiledStep, cycles: int = 1) -> Program:
    """A program built directly, as a hostile or buggy compiler could: no check."""
    return Program(
        name="p",
        file="p.yaml",
        steps=steps,
        groups=(),
        cycles=cycles,
        limits=Limits(),
        parameters={},
        capacity_ah=None,
        initial_charge_ah=0.0,
        log=LogRule(),
    )


def step(index: int, id_: str, kind: str, **kw: object) -> CompiledStep:
    return CompiledStep(index=index, id=id_, kind=kind, **kw)  # type: ignore[arg-type]


class Chain:
    """A chain on a channel (tags only) and a virtual clock, scanned by hand."""

    def __init__(self, prog: Program) -> None:
        self.clock = VirtualClock()
        self.db = TagDB()
        Channel("ch0", self.db, ChannelLimits((-0.4, 0.4), (0.8, 1.9)), capacity_ah=2.0)
        port = ChannelPort.from_tags(self.db, "ch0", Mode.AUTO.value, Mode.MANUAL.value)
        self.runner = ChainRunner(port, self.db, self.clock)
        self.events: list[ChainEvent] = []
        self.runner.listeners.append(self.events.append)
        self.runner.load(prog, test_id="t")

    def scan(self, n: int = 1) -> None:
        for _ in range(n):
            self.clock.advance(PERIOD_S)
            self.runner.run(self.clock.now(), PERIOD_S)

    def started_per_scan(self) -> dict[float, int]:
        out: dict[float, int] = {}
        for ev in self.events:
            if ev.kind == "step" and ev.text.startswith("starting step"):
                out[ev.t] = out.get(ev.t, 0) + 1
        return out

    def state(self) -> State:
        return self.runner.state

    @property
    def alarm(self) -> str:
        return str(self.db["ch0.chain.alarm"].value)


LOOP_ALARM = (
    f"supervision: {MAX_TRANSITIONS_PER_SCAN} steps started in one scan without time"
    f" passing (loop b → c → b); held before step 'b' (at most {MAX_TRANSITIONS_PER_SCAN}"
    " per scan)"
)


def goto_loop() -> Program:
    return program(
        step(0, "a", "rest", duration_s=1.0),
        step(1, "b", "goto", goto=2),
        step(2, "c", "goto", goto=1),
    )


def test_a_goto_loop_holds_the_chain_with_a_supervision_alarm_naming_it() -> None:
    chain = Chain(goto_loop())
    chain.runner.command("start")
    chain.scan()  # rest a ends: b, c, b, c, ... in this scan
    assert chain.state() is State.HOLDING
    assert chain.alarm == LOOP_ALARM
    assert chain.db["ch0.chain.step"].value == "c"
    assert max(chain.started_per_scan().values()) == MAX_TRANSITIONS_PER_SCAN
    alarms = [ev.text for ev in chain.events if ev.kind == "alarm"]
    assert alarms == [LOOP_ALARM]  # into the timeline and the result files
    chain.scan()
    assert chain.state() is State.HELD
    assert chain.db["ch0.auto_current"].value == 0.0


def test_resuming_a_held_goto_loop_carries_on_from_its_step_and_holds_again() -> None:
    chain = Chain(goto_loop())
    chain.runner.command("start")
    chain.scan(2)
    chain.runner.command("ack")
    chain.runner.command("resume")
    chain.scan()  # Resuming → Running, and c's goto acts in the same scan: the loop again
    assert chain.state() is State.HOLDING
    assert chain.alarm == LOOP_ALARM
    assert max(chain.started_per_scan().values()) == MAX_TRANSITIONS_PER_SCAN


def test_a_resumed_goto_chain_that_ends_carries_on_to_its_step() -> None:
    # 150 gotos in a row: more than one scan allows, but not a loop.
    n = 150
    hops = [step(k, f"g{k}", "goto", goto=k + 1) for k in range(1, n + 1)]
    chain = Chain(program(step(0, "a", "rest", duration_s=1.0), *hops, step(n + 1, "z", "rest")))
    chain.runner.command("start")
    chain.scan()
    assert chain.state() is State.HOLDING
    assert "held before step 'g101'" in chain.alarm
    chain.scan()
    chain.runner.command("ack")
    chain.runner.command("resume")
    chain.scan()
    assert chain.state() is State.RUNNING
    assert chain.db["ch0.chain.step"].value == "z"


def test_ends_of_cycles_in_one_scan_are_bounded_too() -> None:
    # A body of one end_cycle step, a million cycles: once unbounded recursion.
    chain = Chain(program(step(0, "e", "end_cycle"), cycles=1_000_000))
    chain.runner.command("start")
    assert chain.state() is State.HOLDING
    assert chain.alarm == (
        f"supervision: {MAX_TRANSITIONS_PER_SCAN} steps started in one scan without time"
        f" passing (loop e → e); held before step 'e' (at most {MAX_TRANSITIONS_PER_SCAN}"
        " per scan)"
    )
    chain.scan()
    assert chain.state() is State.HELD
    assert chain.db["ch0.chain.cycle"].value == MAX_TRANSITIONS_PER_SCAN + 1


def test_a_zero_second_step_lasts_a_scan_so_its_loop_never_reaches_the_bound() -> None:
    # What check refuses still cannot spin inside a scan: one pass per scan.
    chain = Chain(program(step(0, "a", "rest", duration_s=0.0), step(1, "b", "goto", goto=0)))
    chain.runner.command("start")
    chain.scan(10)
    assert chain.state() is State.RUNNING
    assert max(chain.started_per_scan().values()) == 2
