"""What the screens draw, read from the bench model (no server): sim.yaml's layout names
the real tags of each channel and of the mimic, and a compiled recipe becomes the chain the
channel screen draws."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app import build_bench
from supervisor.chains.compiler import compile_recipe
from supervisor.config.recipe import load_recipe
from supervisor.core.clock import VirtualClock
from supervisor.devices.kind import LINK
from supervisor.devices.registry import REGISTRY, bench_from_data, load_bench
from supervisor.hmi.layout import CHANNEL_TAGS, Layout, program_json

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def layout() -> Layout:
    bench = build_bench(load_bench(ROOT / "io_maps" / "sim.yaml"), VirtualClock(), in_process=True)
    return Layout(bench, bench.clock)


def test_the_bench_layout_names_each_channel_s_tags(layout: Layout) -> None:
    body = layout.bench_json()
    assert (body["bench"], body["period_s"]) == ("sim", 0.1)
    assert [c["name"] for c in body["channels"]] == ["ch0", "ch1", "ch2", "ch3", "ch4"]
    ch0 = body["channels"][0]
    assert (ch0["kind"], ch0["device"], ch0["board"], ch0["unit_prefix"]) == (
        "chadeche",
        "chadeche",
        0,
        "ch0",
    )
    assert ch0["limits"] == {
        "current_a": [-0.4, 0.4],
        "voltage_v": [0.8, 1.9],
        "temperature_c": [None, None],
    }
    assert set(ch0["tags"]) == set(CHANNEL_TAGS)
    assert ch0["tags"]["voltage"] == "ch0.voltage"
    assert ch0["tags"]["charge"] == "ch0.chain.charge_ah"  # the test's charge (issue 26)
    assert ch0["tags"]["charge_counter"] == "ch0.charge_ah"
    assert ch0["tags"]["channel_state"] == "ch0.state"
    assert ch0["tags"]["state"] == "ch0.chain.state"
    assert ch0["tags"]["eta"] == "ch0.chain.eta_s"
    assert ch0["tags"]["output"] is None  # a Chadèche board has no output switch
    ch4 = body["channels"][4]
    assert (ch4["kind"], ch4["tags"]["output"]) == ("ea-psb", "ch4.output_fb")
    assert ch0["trend"] == []  # no BMS
    assert {d["name"]: d["health_tag"] for d in body["devices"]} == {
        "chadeche": "chadeche.connected",
        "adam": "adam.connected",
        "ea": "ea.connected",
        "bms": "bms.connected",
    }


def test_the_mimic_names_the_power_path_s_tags(layout: Layout) -> None:
    assert layout.bench_json()["mimic"] == {
        "estop": "estop.ok",
        "estop_relay": None,  # the contactor is its channel's, not the e-stop's
        "supply": "ch4.output_fb",
        "supply_device": "ea",  # its box's lines are the device's (see below)
        "contactor": "contactor.closed",
        "coil": "contactor.cmd",
        "bms": "bms.connected",
        "bms_device": "bms",
        "channel": "ch4",
    }


def _renamed(data: Any, old: str, new: str, tag_prefix: str) -> Any:
    """The I/O map with device ``old`` called ``new``, and its tags ``<old>.x`` called
    ``<tag_prefix>.x`` wherever they are named (tag names are the I/O map's choice)."""
    tags = {t["name"] for t in data["tags"] if t["device"] == old}

    def rename(node: Any) -> Any:
        if isinstance(node, dict):
            return {
                (new if k == old and node is data["devices"] else k): (
                    new if k == "device" and v == old else rename(v)
                )
                for k, v in node.items()
            }
        if isinstance(node, list):
            return [rename(v) for v in node]
        if isinstance(node, str) and node in tags:
            return tag_prefix + node[len(old) :]
        return node

    return rename(data)


def test_a_supply_named_psu_and_a_bms_named_orion_keep_their_mimic_lines() -> None:
    """Issue 29, item 8: the mimic's lines come from the device kinds' registration (role and
    points) and the I/O map's tags, never from a device's name."""
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text())
    data = _renamed(_renamed(data, "ea", "psu", "psu"), "bms", "orion", "battery")
    bench = build_bench(bench_from_data(data, "psu.yaml"), VirtualClock(), in_process=True)
    body = Layout(bench, bench.clock).bench_json()
    devices = {d["name"]: d for d in body["devices"]}
    assert devices["psu"]["role"] == "supply"
    assert devices["psu"]["shows"] == [
        {"label": "voltage", "tag": "psu.voltage", "format": "n2"},
        {"label": "link", "tag": "psu.connected", "format": "link"},
    ]
    assert devices["orion"]["role"] == "bms"
    assert devices["orion"]["shows"] == [
        {"label": "link", "tag": "orion.connected", "format": "link"},
        {"label": "pack", "tag": "battery.voltage", "format": "n2"},
        {"label": "cell min", "tag": "battery.cell_min", "format": "n3"},
        {"label": "cell max", "tag": "battery.cell_max", "format": "n3"},
        {"label": "temp max", "tag": "battery.temp_max", "format": "n1"},
    ]
    assert (devices["adam"]["role"], devices["chadeche"]["role"]) == ("io", "cycler")
    mimic = body["mimic"]
    assert (mimic["supply"], mimic["supply_device"]) == ("ch4.output_fb", "psu")
    assert (mimic["bms"], mimic["bms_device"]) == ("orion.connected", "orion")


def test_every_kind_shows_only_points_it_has() -> None:
    """sim.yaml has a device of every registered kind: each kind's mimic lines name its own
    points (or its link), so a renamed point cannot silently drop a line."""
    cfg = load_bench(ROOT / "io_maps" / "sim.yaml")
    assert {d.driver for d in cfg.devices.values()} == set(REGISTRY.kinds)
    for name, device in cfg.devices.items():
        kind = REGISTRY.kind_of(device)
        assert kind.shows, f"{kind.name} shows nothing on the mimic"
        points = set(device.points()) | {LINK}
        assert {s.point for s in kind.shows} <= points, name


def test_a_compiled_recipe_is_drawn_as_its_chain() -> None:
    file = str(ROOT / "recipes" / "nimh-ds2710.yaml")
    recipe, positions = load_recipe(file)
    body = program_json("ch0", compile_recipe(recipe, positions, file))
    assert body["recipe"] == "nimh-ds2710" and body["channel"] == "ch0"
    steps = {s["name"]: s for s in body["steps"]}
    assert [s["index"] for s in body["steps"]] == list(range(len(body["steps"])))
    assert steps["discharge"]["kind"] == "discharge"
    assert steps["discharge"]["current_a"] == pytest.approx(-0.2)
    assert steps["discharge"]["transitions"] == [
        {"to": "rest2", "condition": "voltage <= v_min", "action": "next"},
        {"to": "rest2", "condition": "charge <= q_min", "action": "next"},
        {"to": "rest2", "condition": "step time >= 90000 s", "action": "next"},
    ]
    assert steps["pulse"]["transitions"][0] == {
        "to": "topoff",
        "condition": "voltage >= v_max",
        "action": "goto topoff",
    }
    assert steps["loop"]["transitions"] == [
        {"to": "rest2", "condition": "always", "action": "goto"}
    ]
    assert steps["end"]["transitions"] == [
        {"to": "next cycle", "condition": "always", "action": "next_cycle"}
    ]
    assert body["tags"]["step_index"] == "ch0.chain.step_index"


def test_the_bms_channel_s_trend_adds_the_cell_min_and_max(layout: Layout) -> None:
    """Issue 32, finding 6: "Show Graphs" of seed 002 plots the cells beside V, I, T."""
    ch4 = layout.bench_json()["channels"][4]
    assert ch4["trend"] == [
        {"label": "cell min", "tag": "bms.cell_min", "unit": "V", "scale": "cell"},
        {"label": "cell max", "tag": "bms.cell_max", "unit": "V", "scale": "cell"},
    ]
