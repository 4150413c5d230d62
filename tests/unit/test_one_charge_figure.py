"""Issue 26, findings 2 and 3, on the bench model (io_maps/sim.yaml in process, virtual
clock; no server): one charge figure, ``chN.chain.charge_ah``, the test's charge from the
recipe's ``initial_charge`` (what a step's ``charge`` condition tests), read by every
display; and what a channel does shown apart from its step chain's state.

The servers themselves (OPC UA, HTTP, ``supervisor ctl``) show the same figure at the same
moment in tests/integration/test_charge_on_every_display.py."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from supervisor.app import Bench, build_bench
from supervisor.channels.activity import activity_label, chain_label
from supervisor.cli.ctl import FIELDS, status_table, watch_line
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.hmi.layout import Layout
from supervisor.publish.display import display_line
from supervisor.publish.opcua.layout import channel_node, plan

ROOT = Path(__file__).resolve().parents[2]
DS2710 = ROOT / "recipes" / "nimh-ds2710.yaml"
# 500 mAh to start from, 100 mA out for 9 s (0.25 mAh), then the end.
SHORT = """recipe: short
initial_charge: 500 mAh
steps:
  - {id: d, discharge: 100 mA, duration: 9 s}
  - {id: r, rest: 2 s}
"""


@pytest.fixture
async def bench(tmp_path: Path) -> AsyncIterator[Bench]:
    cfg = load_bench(ROOT / "io_maps" / "sim.yaml")
    # Its results in the test's folder, not in the checkout's var/sim.
    cfg = cfg.model_copy(update={"state_dir": str(tmp_path / "state")})
    b = build_bench(cfg, VirtualClock(), in_process=True)
    await b.start()
    try:
        await b.engine.run_for(1.0)
        yield b
    finally:
        await b.shutdown()


def figures(bench: Bench, channel: str) -> dict[str, float]:
    """The charge each display would show now, in mAh, read the way each reads it."""
    db = bench.db
    runner = bench.runners[channel]
    rec = runner.sample()
    assert rec is not None
    mah = re.compile(r"mAh=(-?[\d.]+)")
    line = display_line(rec, dba=0)
    values = {f: db[f"{channel}.{f}"].value for f in FIELDS}
    watch = watch_line(channel, values, 0.0)
    names = [c.name for c in bench.cfg.channels]
    rows = [{f: db[f"{c}.{f}"].value for f in FIELDS} for c in names]
    table = status_table(names, rows)
    status_row = table[1 + names.index(channel)]
    tile_tag = next(
        c for c in Layout(bench, bench.clock).bench_json()["channels"] if c["name"] == channel
    )["tags"]["charge"]
    folder = next(f for f in plan(bench.cfg, db).root.walk() if f.node == channel_node(channel))
    opcua_tag = next(v.tag for v in folder.variables if v.browse == "Charge")
    condition = runner._conditions.values(bench.clock.now(), runner._r)["charge"]  # type: ignore[union-attr]
    assert isinstance(condition, float)
    return {
        "display line": float(mah.findall(line)[0]),
        "ctl watch": float(mah.findall(watch)[0]),
        "ctl status": float(status_row.split()[-1]) * 1000,
        "Overview tile and channel screen": db[tile_tag].as_float() * 1000,
        "OPC UA Charge": db[opcua_tag].as_float() * 1000,
        "the charge condition": condition * 1000,
    }


async def test_every_display_shows_the_recipe_s_charge_that_the_charge_condition_tests(
    bench: Bench,
) -> None:
    """nimh-ds2710 with q_init 1300 mAh on ch3: the display line said 1300.0, ``ctl watch``
    -1.3, ``ctl status``, the tile and OPC UA -0.0017 Ah (the channel's net counter)."""
    runner = bench.load_recipe("ch3", DS2710, {"q_init": "1300 mAh"})
    await bench.engine.run_for(1.0)
    runner.command("start")
    await bench.engine.run_for(2.0)
    runner.command("advance")  # past the 60 s rest: the 200 mA discharge
    await bench.engine.run_for(30.0)
    assert bench.db["ch3.chain.step"].value == "discharge"
    assert bench.db["ch3.charge_ah"].as_float() < -0.001  # the counter moved...
    seen = figures(bench, "ch3")
    # ...and every display shows 1300 mAh less what left the cell (200 mA, 30 s: 1.7 mAh),
    # to one count of the finest resolution (the display line's 0.1 mAh).
    assert seen["the charge condition"] == pytest.approx(1300 - 1.67, abs=0.1)
    for where, mah in seen.items():
        assert mah == pytest.approx(seen["the charge condition"], abs=0.1), (where, seen)


async def test_the_test_charge_is_empty_until_a_load_the_initial_charge_then_kept_after_the_end(
    bench: Bench, tmp_path: Path
) -> None:
    db = bench.db
    tag = db["ch2.chain.charge_ah"]
    assert tag.value is None  # no recipe: no test charge
    (tmp_path / "short.yaml").write_text(SHORT, encoding="utf-8")
    runner = bench.load_recipe("ch2", tmp_path / "short.yaml", results_dir=tmp_path / "results")
    assert tag.value == 0.5  # the recipe's initial_charge, before the start
    assert (tag.spec.unit, db["ch2.charge_ah"].spec.unit) == ("Ah", "Ah")
    await bench.engine.run_for(1.0)
    runner.command("start")
    assert tag.value == 0.5
    await bench.engine.run_for(5.0)
    moving = tag.as_float()
    assert 0.4998 < moving < 0.49995
    await bench.engine.run_for(10.0)
    assert db["ch2.chain.state"].value == "Complete"
    final = tag.as_float()
    assert final == pytest.approx(0.5 - 0.1 * 9 / 3600, abs=1e-4)
    # Reset hands the channel back to the operator: current moved in Manual moves the
    # counters, not the finished test's charge.
    runner.command("reset")
    db.write("ch2.manual_current", 0.2)
    db.write("ch2.enable", True)
    await bench.engine.run_for(5.0)
    assert db["ch2.state"].value == "charging"
    assert tag.value == final
    db.write("ch2.enable", False)
    await bench.engine.run_for(1.0)
    # A new start is a new test: from the recipe's initial charge again.
    runner.command("start")
    assert tag.value == 0.5
    await bench.engine.run_for(1.0)
    assert tag.as_float() == pytest.approx(0.5, abs=1e-4)


async def test_a_channel_driven_in_manual_shows_what_it_does_apart_from_its_chain_s_state(
    bench: Bench,
) -> None:
    """Finding 3: ch4 in Manual at 20 A, the contactor closed, was shown "Idle manual"."""
    db = bench.db
    db.write("ch4.manual_current", 20.0)
    db.write("ch4.enable", True)
    await bench.engine.run_for(5.0)
    assert (db["ch4.state"].value, db["ch4.chain.state"].value) == ("charging", "Idle")
    names = [c.name for c in bench.cfg.channels]
    rows = [{f: db[f"{c}.{f}"].value for f in FIELDS} for c in names]
    head, *lines = status_table(names, rows)
    assert re.split(r"\s{2,}", head) == [
        "channel", "channel state", "chain", "recipe", "step", "V", "I (A)", "charge (Ah)",
    ]  # fmt: skip
    ch4 = re.split(r"\s{2,}", lines[names.index("ch4")])
    assert ch4[:5] == ["ch4", "charging 20.000 A, manual", "Idle", "—", "—"]
    assert re.split(r"\s{2,}", lines[0])[:3] == ["ch0", "idle, manual", "Idle"]
    # The screens draw the same words from the tags /api/bench names for each tile.
    tags = next(
        c for c in Layout(bench, bench.clock).bench_json()["channels"] if c["name"] == "ch4"
    )["tags"]
    label = activity_label(
        db[tags["channel_state"]].value, db[tags["current_cmd"]].value, db[tags["mode"]].value
    )
    assert (label, chain_label(db[tags["state"]].value)) == (
        "charging 20.000 A, manual",
        "chain: Idle",
    )


@pytest.mark.parametrize(
    ("state", "amps", "mode", "label"),
    [
        ("charging", 20.0, "manual", "charging 20.000 A, manual"),
        ("discharging", -0.2, "auto", "discharging 0.200 A, auto"),
        ("idle", 0.0, "auto", "idle, auto"),
        ("faulted", 0.0, "manual", "faulted, manual"),
        (None, None, None, "—"),
    ],
)
def test_the_activity_label_says_the_state_the_commanded_current_and_the_mode(
    state: str | None, amps: float | None, mode: str | None, label: str
) -> None:
    assert activity_label(state, amps, mode) == label
