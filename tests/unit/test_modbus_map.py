"""The Modbus register map is a contract (issue 36, ADR 0031): an address, once given, never
moves — a tag added at the end of the I/O map, a channel added, an explicit address given
to one tag move no other point — and every shipped I/O map plans without overlap."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from supervisor.app.bench import build_bench
from supervisor.app.tagset import declared_tags
from supervisor.chains.states import OPCUA_CODE
from supervisor.cli.main import main
from supervisor.config import modbusmap
from supervisor.core.clock import VirtualClock
from supervisor.devices.registry import bench_from_data
from supervisor.publish.modbus.mapcsv import COLUMNS
from supervisor.publish.modbus.regmap import CHAIN_STATES, Kind, Point, RegisterMap, Table, plan

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = sorted((ROOT / "io_maps").glob("*.yaml"))


def sim_data() -> dict[str, Any]:
    data = yaml.safe_load((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def planned(data: dict[str, Any]) -> RegisterMap:
    """The register map of the bench these I/O map data wire."""
    cfg = bench_from_data(data)
    return plan(cfg, declared_tags(cfg))


def by_tag(m: RegisterMap) -> dict[str, Point]:
    return {p.tag: p for p in m.points if p.tag}


def places(m: RegisterMap) -> dict[tuple[Table, int], Point]:
    """Every register (or bit) a point takes, and the point (asserts none is taken twice)."""
    out: dict[tuple[Table, int], Point] = {}
    for p in m.points:
        for a in range(p.address, p.address + p.words):
            assert (p.table, a) not in out, f"{p} overlaps {out[p.table, a]}"
            out[p.table, a] = p
    return out


@pytest.fixture(scope="module")
def sim_map() -> RegisterMap:
    return planned(sim_data())


def test_a_channels_voltage_is_a_float_in_its_block_of_input_registers(
    sim_map: RegisterMap,
) -> None:
    tags = by_tag(sim_map)
    assert tags["ch0.voltage"] == Point(
        Table.INPUT_REGISTER, 104, Kind.FLOAT32, "ch0.voltage", "ch0", "V"
    )
    assert tags["ch1.voltage"].address == 204
    assert tags["ch0.current"].address == 106
    assert (tags["ch0.manual_current"].table, tags["ch0.manual_current"].address) == (
        Table.HOLDING_REGISTER,
        100,
    )
    assert tags["ch0.manual_current"].writable
    assert (tags["ch0.enable"].table, tags["ch0.enable"].address) == (Table.COIL, 100)
    assert (tags["ch0.armed"].table, tags["ch0.armed"].address) == (Table.DISCRETE_INPUT, 100)


def test_each_channel_and_the_bench_have_a_status_register_and_the_bench_a_heartbeat(
    sim_map: RegisterMap,
) -> None:
    status = {(p.channel, p.address) for p in sim_map.points if p.kind is Kind.STATUS}
    assert status == {("", 0)} | {(f"ch{k}", 100 + 100 * k) for k in range(5)}
    singles = [(p.kind, p.address) for p in sim_map.in_table(Table.INPUT_REGISTER) if p.address < 3]
    assert singles == [(Kind.STATUS, 0), (Kind.HEARTBEAT, 1), (Kind.REFUSAL, 2)]


def test_the_io_maps_own_tags_follow_in_its_order_in_an_area_of_their_own(
    sim_map: RegisterMap,
) -> None:
    tags = by_tag(sim_map)
    assert tags["pack.current"].address == modbusmap.IO_MAP_BASE
    assert tags["pack.voltage"].address == modbusmap.IO_MAP_BASE + 2
    assert (tags["estop.ok"].table, tags["estop.ok"].address) == (
        Table.DISCRETE_INPUT,
        modbusmap.IO_MAP_BASE,
    )
    assert "ea.last_error" not in tags  # a free text: no place in a Modbus map


def test_state_names_are_codes_with_their_table(sim_map: RegisterMap) -> None:
    tags = by_tag(sim_map)
    assert tags["ch0.mode"].codes == ("manual", "auto")
    assert tags["ch0.state"].codes[:3] == ("off", "idle", "charging")
    assert {tags["ch0.chain.state"].codes[n]: n for n in OPCUA_CODE.values()} == {
        s.value: n for s, n in OPCUA_CODE.items()
    }


def test_the_map_is_planned_from_the_tags_the_bench_declares_without_opening_a_device() -> None:
    """``supervisor modbus map`` wires stand-in drivers: the same tags as the bench's."""
    cfg = bench_from_data(sim_data())
    wired = build_bench(cfg, VirtualClock(), in_process=True).db
    assert [(t.name, t.spec) for t in declared_tags(cfg)] == [(t.name, t.spec) for t in wired]


def test_the_chain_state_codes_are_the_opc_ua_numbers() -> None:
    assert {name: n for n, name in enumerate(CHAIN_STATES) if name} == {
        s.value: n for s, n in OPCUA_CODE.items()
    }


def test_the_layout_names_tables_and_kinds_as_the_register_map_does() -> None:
    assert set(modbusmap.TABLES) == {t.value for t in Table}
    assert set(modbusmap.KINDS) == {k.value for k in Kind}


def test_a_tag_added_at_the_end_of_the_io_map_moves_no_other_point(
    sim_map: RegisterMap,
) -> None:
    data = sim_data()
    data["tags"].append({"name": "pack.temp2", "device": "adam", "point": "slot2.tc0"})
    data["tags"].append(
        {"name": "estop.spare", "device": "adam", "point": "slot2.tc1", "threshold": 1}
    )
    after = planned(data)
    new = {p.tag for p in after.points} - {p.tag for p in sim_map.points}
    assert new == {"pack.temp2", "estop.spare"}
    assert [p for p in after.points if p.tag not in new] == list(sim_map.points)


def test_a_channel_added_moves_no_other_point() -> None:
    """load16.yaml's 16 channels against the same map without its last one."""
    data = yaml.safe_load((ROOT / "io_maps" / "load16.yaml").read_text(encoding="utf-8"))
    data["modbus_server"] = {"port": 1502}
    full = planned(data)
    last = data["channels"][-1]["name"]
    data["channels"] = data["channels"][:-1]
    fewer = planned(data)
    assert [p for p in full.points if p.channel != last] == list(fewer.points)
    assert by_tag(full)[f"{last}.voltage"].address == 100 * len(data["channels"]) + 104


def test_an_explicit_address_moves_its_tag_and_no_other(sim_map: RegisterMap) -> None:
    data = sim_data()
    data["modbus_server"]["addresses"] = {"ch0.voltage": 40000, "estop.ok": 7}
    after = planned(data)
    moved = by_tag(after)
    assert (moved["ch0.voltage"].table, moved["ch0.voltage"].address) == (
        Table.INPUT_REGISTER,
        40000,
    )
    assert (moved["estop.ok"].table, moved["estop.ok"].address) == (Table.DISCRETE_INPUT, 7)
    rest = [p for p in after.points if p.tag not in ("ch0.voltage", "estop.ok")]
    assert rest == [p for p in sim_map.points if p.tag not in ("ch0.voltage", "estop.ok")]


def test_a_float_scaled_to_16_bits_keeps_its_place_and_moves_nothing(
    sim_map: RegisterMap,
) -> None:
    data = sim_data()
    data["modbus_server"]["scale"] = {"ch0.voltage": 1000, "pack.current": 10}
    data["modbus_server"]["addresses"] = {"pack.current": 40001}  # 16 bits: odd is fine
    after = planned(data)
    tags = by_tag(after)
    assert tags["ch0.voltage"] == Point(
        Table.INPUT_REGISTER, 104, Kind.INT16, "ch0.voltage", "ch0", "V", 1000.0
    )
    assert (tags["pack.current"].address, tags["pack.current"].kind) == (40001, Kind.INT16)
    same = [p for p in after.points if p.tag not in ("ch0.voltage", "pack.current")]
    assert same == [p for p in sim_map.points if p.tag not in ("ch0.voltage", "pack.current")]


def test_word_order_and_unit_id_come_from_the_io_map() -> None:
    data = sim_data()
    data["modbus_server"].update(word_order="little", unit_id=7)
    m = planned(data)
    assert (m.word_order, m.unit_id) == ("little", 7)


@pytest.mark.parametrize("path", SHIPPED, ids=[p.name for p in SHIPPED])
def test_every_shipped_io_map_plans_without_overlap(path: Path) -> None:
    data = yaml.safe_load(path.read_text(encoding="utf-8"))
    data.setdefault("modbus_server", {"port": 1502})
    m = planned(data)
    places(m)
    assert all(p.address + p.words - 1 <= modbusmap.MAX_ADDRESS for p in m.points)
    floats = [p for p in m.points if p.kind is Kind.FLOAT32]
    assert floats and all(p.address % 2 == 0 for p in floats)


SIM_CFG = bench_from_data(sim_data())
PLACEABLE = sorted(s.tag for s in modbusmap.generated(SIM_CFG) if s.tag)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.dictionaries(
        st.sampled_from(PLACEABLE),
        st.one_of(st.integers(0, 700), st.integers(19990, 20040), st.integers(65530, 65535)),
        max_size=8,
    )
)
def test_explicit_addresses_the_check_accepts_never_overlap(explicit: dict[str, int]) -> None:
    """Random explicit addresses, many of them on generated places or on each other: what
    ``supervisor check`` lets through lays out without an overlap."""
    server = SIM_CFG.modbus_server
    assert server is not None
    cfg = SIM_CFG.model_copy(
        update={"modbus_server": server.model_copy(update={"addresses": explicit})}
    )
    if modbusmap.explicit_problems(cfg):
        return
    slots = modbusmap.layout(cfg)
    taken: set[tuple[str, int]] = set()
    for s in slots:
        for a in range(s.address, s.end + 1):
            assert (s.table, a) not in taken
            taken.add((s.table, a))
        assert s.end <= modbusmap.MAX_ADDRESS
        assert s.kind != modbusmap.FLOAT32 or s.address % 2 == 0


# --- the CSV: what a panel's tool imports ------------------------------------------------
def csv_rows(capsys: pytest.CaptureFixture[str], *argv: str) -> list[dict[str, str]]:
    assert main(["modbus", "map", *argv]) == 0
    return list(csv.DictReader(io.StringIO(capsys.readouterr().out)))


def test_the_csv_has_a_row_per_point_with_the_columns_a_panel_imports(
    capsys: pytest.CaptureFixture[str], sim_map: RegisterMap
) -> None:
    rows = csv_rows(capsys, str(ROOT / "io_maps" / "sim.yaml"))
    assert list(rows[0]) == list(COLUMNS)
    assert len(rows) == len(sim_map.points)
    by_name = {r["tag"]: r for r in rows}
    assert by_name["ch0.voltage"] == {
        "address": "104",
        "reference": "300105",
        "function": "04",
        "type": "float32",
        "word_order": "big",
        "tag": "ch0.voltage",
        "unit": "V",
        "scale": "1",
        "access": "r",
        "codes": "",
    }
    # sim.yaml's server takes no writes: its setpoints read "r", at the same addresses.
    assert (by_name["ch0.manual_current"]["function"], by_name["ch0.manual_current"]["access"]) == (
        "03",
        "r",
    )
    assert by_name["ch0.enable"]["reference"] == "000101"
    assert by_name["ch0.mode"]["codes"] == "0=manual; 1=auto"
    assert by_name["ch0.status"]["codes"].startswith("bit0=bad; bit1=uncertain")
    assert (by_name["bench.heartbeat"]["address"], by_name["bench.heartbeat"]["type"]) == (
        "1",
        "heartbeat",
    )


def test_with_writes_on_the_setpoints_commands_and_coils_read_rw(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    data = sim_data()
    data["modbus_server"].update(writes=True, writers=["127.0.0.1"])
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    rows = {r["tag"]: r for r in csv_rows(capsys, str(path))}
    assert {n for n, r in rows.items() if r["access"] == "rw"} == {
        f"ch{k}.{f}"
        for k in range(5)
        for f in ("manual_current", "command", "mode", "enable", "ack")
    }
    assert rows["ch0.manual_current"]["function"] == "03 06 16"
    assert rows["ch0.enable"]["function"] == "01 05 15"


def test_the_csv_of_a_bench_whose_devices_are_not_here_is_printed_all_the_same(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """chadeche-rpi.yaml names an SPI bus this machine has not: nothing is opened."""
    rows = csv_rows(capsys, str(ROOT / "io_maps" / "chadeche-rpi.yaml"))
    assert {r["tag"] for r in rows} >= {"ch0.voltage", "ch0.status", "bench.heartbeat"}


def test_the_csv_of_a_refused_io_map_is_not_printed(capsys: pytest.CaptureFixture[str]) -> None:
    bad = ROOT / "tests" / "data" / "bad_io_maps" / "modbus_addresses_overlap.yaml"
    assert main(["modbus", "map", str(bad)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert f"{bad}:13:22: ch0.chain.cycle at input register 40001 overlaps" in err


ADR = ROOT / "docs" / "adr" / "0031-modbus-register-map.md"
SHORT = {"IR": "input_register", "HR": "holding_register", "coil": "coil", "DI": "discrete_input"}


def test_the_adr_lists_every_blocks_fields_at_their_offsets() -> None:
    """A newcomer predicts an address from ADR 0031's tables: they are the code's."""
    text = ADR.read_text(encoding="utf-8")
    for title, fields in (
        ("The bench block", modbusmap.BENCH_FIELDS),
        ("A channel's block", modbusmap.CHANNEL_FIELDS),
        ("A device's block", modbusmap.DEVICE_FIELDS),
    ):
        table_text = text.split(f"**{title}", 1)[1].split("\n\n", 2)[1]
        rows = [
            [c.strip().strip("`") for c in line.strip("|").split("|")]
            for line in table_text.splitlines()[2:]
        ]
        documented = [
            (SHORT[t], int(o), f if not f.startswith("(") else "", k) for t, o, f, k in rows
        ]
        assert documented == [
            (s.table, s.address, s.tag, s.kind) for s in modbusmap.blocks(fields)
        ], title


def test_the_integrators_excerpt_is_what_the_command_prints(
    capsys: pytest.CaptureFixture[str],
) -> None:
    guide = (ROOT / "docs" / "integrator.md").read_text(encoding="utf-8")
    excerpt = guide.split("## Modbus TCP", 1)[1].split("```csv\n", 1)[1].split("```", 1)[0]
    assert main(["modbus", "map", str(ROOT / "io_maps" / "sim.yaml")]) == 0
    printed = capsys.readouterr().out.splitlines()
    lines = excerpt.splitlines()
    assert lines[0] == printed[0]
    assert [line for line in lines if line not in printed] == []


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, len(SIM_CFG.tags) - 1), min_size=1, max_size=40))
def test_any_list_of_io_map_tags_lays_out_without_overlap_and_one_more_moves_none(
    picks: list[int],
) -> None:
    """Random I/O maps (the simulated bench's points in any order, repeated under new
    names): no two slots overlap, floats are even, and the map of all but the last tag is
    the map of all with the last one taken out."""
    tags = [SIM_CFG.tags[i].model_copy(update={"name": f"t{n}.x"}) for n, i in enumerate(picks)]
    full = modbusmap.layout(SIM_CFG.model_copy(update={"tags": tags}))
    fewer = modbusmap.layout(SIM_CFG.model_copy(update={"tags": tags[:-1]}))
    assert [s for s in full if s.tag != tags[-1].name] == fewer
    taken: set[tuple[str, int]] = set()
    for s in full:
        for a in range(s.address, s.end + 1):
            assert (s.table, a) not in taken
            taken.add((s.table, a))
        assert s.kind != modbusmap.FLOAT32 or s.address % 2 == 0


def test_a_bench_of_more_channels_than_the_map_holds_is_refused() -> None:
    """Channel k's block is at 100 + 100·k: the 100th would be where the devices' are."""
    ch = SIM_CFG.channels[0]
    many = [ch.model_copy(update={"name": f"c{k}"}) for k in range(modbusmap.MAX_CHANNELS + 1)]
    problems = modbusmap.explicit_problems(SIM_CFG.model_copy(update={"channels": many}))
    assert problems == [
        (("modbus_server",), "the Modbus map holds 99 channels at most, not 100", True)
    ]
    assert modbusmap.explicit_problems(SIM_CFG.model_copy(update={"channels": many[:-1]})) == []


def test_check_warns_of_a_modbus_server_off_loopback(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """Modbus has no login: off loopback, check says so (a warning, exit 0)."""
    data = sim_data()
    data["modbus_server"].update(host="0.0.0.0", writes=True, writers=["192.0.2.7"])
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert main(["check", str(path)]) == 0
    err = capsys.readouterr().err
    assert f"{path}: warning: modbus_server: host '0.0.0.0' is not loopback" in err
    assert "writers' IP addresses alone" in err
    assert main(["check", str(ROOT / "io_maps" / "sim.yaml")]) == 0
    assert "modbus_server" not in capsys.readouterr().err
