"""The object types and the naming rule of the address space (issue 31, finding 10), held
against every I/O map the project ships: each channel has what ChannelType declares, with
the declared kind; its StateMachine has CurrentState and Number; each device's type is its
kind's; browse names are PascalCase and unique among siblings; a state machine's name and
Id follow its number for every state; the identification's defaults."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from asyncua import ua

from supervisor.app import build_bench
from supervisor.chains.states import OPCUA_CODE, State
from supervisor.config.models import BenchConfig
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import load_bench
from supervisor.publish.opcua.layout import Folder, Layout, device_type, plan, unique_names
from supervisor.publish.opcua.nameplate import identification_values
from supervisor.publish.opcua.objecttypes import (
    CHANNEL_MEMBERS,
    DEVICE_MEMBERS,
    PACKML_STATES,
    StateMachineNodes,
    declared,
    state_node,
)
from supervisor.publish.opcua.settings import Identification

ROOT = Path(__file__).resolve().parents[2]
# Every shipped I/O map a bench can be built from here (chadeche-rpi opens an SPI bus).
MAPS = sorted(p for p in (ROOT / "io_maps").glob("*.yaml") if p.stem != "chadeche-rpi")
PASCAL = re.compile(r"^[A-Z][A-Za-z0-9]*$")


@pytest.fixture(scope="module", params=MAPS, ids=[p.stem for p in MAPS])
def bench(request: pytest.FixtureRequest) -> tuple[BenchConfig, Layout]:
    b = build_bench(load_bench(request.param), VirtualClock(), in_process=True)
    return b.cfg, plan(b.cfg, b.db, [a.id for a in b.alarms or []])


def test_every_channel_has_what_channel_type_declares_with_its_kind(
    bench: tuple[BenchConfig, Layout],
) -> None:
    _, layout = bench
    channels = [f for f in layout.root.walk() if f.typedef == "ChannelType"]
    assert [f.channel for f in channels] == list(layout.channels)
    for ch in channels:
        kinds = {v.browse: v.kind for v in ch.variables}
        for name, kind in CHANNEL_MEMBERS.items():
            assert kinds.get(name) == kind, (ch.channel, name)
        (machine,) = ch.children
        assert machine.typedef == "ChannelStateMachineType"
        assert [(v.browse, v.kind) for v in machine.variables] == [
            ("CurrentState", "statename"),
            ("Number", "state"),
        ]
        assert machine.variables[1].tag == f"{ch.channel}.chain.state_code"


def test_each_device_is_an_instance_of_its_kind_s_type(bench: tuple[BenchConfig, Layout]) -> None:
    cfg, layout = bench
    devices = next(f for f in layout.root.children if f.browse == "Devices")
    assert [d.browse for d in devices.children] == list(cfg.devices)
    for d in devices.children:
        assert d.typedef == device_type(cfg.devices[d.browse].driver)
        assert declared(d.typedef) == frozenset(DEVICE_MEMBERS)


def test_browse_names_are_pascal_case_and_unique_among_siblings(
    bench: tuple[BenchConfig, Layout],
) -> None:
    _, layout = bench
    instances = {"/Bench/Channels", "/Bench/Devices", "/Bench/Alarms"}
    for f in layout.root.walk():
        names = [v.browse for v in f.variables] + [c.browse for c in f.children]
        assert len(names) == len(set(names)), f.node
        # Channels, devices and alarms are named by the I/O map (ch0, adam, room.temp.h).
        for name in names if f.node not in instances else [v.browse for v in f.variables]:
            assert PASCAL.match(name), (f.node, name)
    assert set(layout.variables) == {v.tag for f in layout.root.walk() for v in f.variables}


def test_one_folder_s_names_stay_unique_when_two_tags_camel_alike() -> None:
    assert unique_names(["a.b_c", "a_b.c", "a.bc"]) == {
        "a.b_c": "ABC",
        "a_b.c": "ABC2",
        "a.bc": "ABc",
    }
    assert unique_names(["connected"], {"Connected"}) == {"connected": "Connected2"}


def test_a_state_machine_s_name_and_id_follow_its_number_for_every_state() -> None:
    machine = StateMachineNodes(ua.NodeId("ch0.chain.state", 1), ua.NodeId("/x/Id", 1), 2)
    for code, name in enumerate(PACKML_STATES):
        dv = ua.DataValue(ua.Variant(code, ua.VariantType.UInt32))
        (current, cv), (state_id, iv) = machine.derived(dv)
        assert (current, cv.Value.Value.Text) == (machine.current, name)
        assert (state_id, iv.Value.Value) == (machine.state_id, state_node(code, 2))
    # Every state of the step chains has its PackML number.
    assert {OPCUA_CODE[s] for s in State} <= set(range(len(PACKML_STATES)))
    assert PACKML_STATES[OPCUA_CODE[State.RUNNING]] == "Execute"
    # Before the first value: no name, the number's status (or waiting for it).
    bad = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadNoCommunication))
    assert all(v.StatusCode == bad.StatusCode for _, v in machine.derived(bad))


def test_the_types_declare_their_members() -> None:
    assert {"Voltage", "StateMachine", "Start", "AcknowledgeAlarms"} <= declared("ChannelType")
    assert {"Channels", "Devices", "Alarms", "Diagnostics", "ForceTag"} <= declared("BenchType")
    assert declared("ChadecheDeviceType") == frozenset(DEVICE_MEMBERS)
    assert declared("") == frozenset()
    assert isinstance(Folder("/x", "X").typedef, str)


def test_identification_defaults_to_the_bench_s_name_and_namespace() -> None:
    rows = {
        name: v.Value for _, name, v, _ in identification_values(Identification(), "b1", "urn:x")
    }
    assert rows["SerialNumber"] == "b1"
    assert rows["ProductInstanceUri"] == "urn:x"
    assert rows["Manufacturer"].Text == ""
    assert "Location" not in rows and "YearOfConstruction" not in rows  # not configured
    full = Identification(location="lab 3", year_of_construction=2026, serial_number="S1")
    rows = {name: v.Value for _, name, v, _ in identification_values(full, "b1", "urn:x")}
    assert (rows["Location"], rows["YearOfConstruction"], rows["SerialNumber"]) == (
        "lab 3",
        2026,
        "S1",
    )


def test_the_identification_is_read_from_the_i_o_map_and_checked(tmp_path: Path) -> None:
    import yaml

    from supervisor.core.errors import ConfigErrors
    from supervisor.publish.opcua.settings import OpcUaSettings

    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    data["identification"] = {"manufacturer": "Lab", "serial_number": "S-1", "location": "B3"}
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    ident = OpcUaSettings.of(load_bench(path)).identification
    assert (ident.manufacturer, ident.serial_number, ident.location) == ("Lab", "S-1", "B3")
    plain = OpcUaSettings.of(load_bench(ROOT / "io_maps" / "bench-adam-ea.yaml"))
    assert plain.identification == Identification()  # none given: the defaults
    for bad in ({"year_of_construction": 1800}, {"serial": "S-1"}):
        data["identification"] = bad
        path.write_text(yaml.safe_dump(data), encoding="utf-8")
        with pytest.raises(ConfigErrors, match="identification"):
            load_bench(path)


def test_a_channel_s_state_number_keeps_its_history_the_name_has_none(
    bench: tuple[BenchConfig, Layout],
) -> None:
    from supervisor.publish.opcua.space import HISTORY, Built, _folder_items

    _, layout = bench
    ch = layout.channels[0]
    number, name = f"{ch}.chain.state_code", f"{ch}.chain.state"
    items = {
        str(i.RequestedNewNodeId.Identifier): i
        for i in _folder_items(layout.root, ua.NodeId(85), 1, Built(), 100.0, frozenset({number}))
    }
    kept = items[number].NodeAttributes
    assert kept.Historizing and kept.AccessLevel & HISTORY
    assert items[number].TypeDefinition == ua.NodeId(ua.ObjectIds.PropertyType)
    assert items[name].TypeDefinition == ua.NodeId(ua.ObjectIds.FiniteStateVariableType)
    assert not items[name].NodeAttributes.Historizing
