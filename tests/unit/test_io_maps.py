"""I/O maps: the shipped files load; broken ones get one clear file:line:col message."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.cli.main import main
from supervisor.config.schema import bench_schema
from supervisor.core.errors import ConfigErrors
from supervisor.devices.ea.config import EaDevice, model_rating
from supervisor.devices.registry import BENCH_MODEL, bench_from_data, load_bench

ROOT = Path(__file__).resolve().parents[2]
BAD = ROOT / "tests" / "data" / "bad_io_maps"


@pytest.mark.parametrize("path", sorted((ROOT / "io_maps").glob("*.yaml")), ids=lambda p: p.name)
def test_every_shipped_io_map_loads_and_checks(path: Path) -> None:
    cfg = load_bench(path)
    assert cfg.bench


# (file, line, col, words the message must contain)
CASES = [
    ("duplicate_tag.yaml", 9, 12, "duplicate tag name 'cell.v'"),
    ("missing_point.yaml", 10, 12, "has no point 'b3.voltage'"),
    ("zero_span.yaml", 11, 14, "raw span is zero"),
    ("unknown_driver.yaml", 4, 13, "unknown value 'siemens-s7'"),
    ("unknown_key.yaml", 3, 3, "did you mean 'period_s'"),
    ("board_owned_twice.yaml", 13, 13, "one owner per board"),
    ("limit_beyond_hardware.yaml", 11, 25, "at most 0.4 A"),
    ("board_not_on_bus.yaml", 7, 18, "board address 0 is already used"),
    ("bad_yaml.yaml", 5, 12, "YAML syntax error"),
    (
        "ea_voltage_above_model_rating.yaml",
        11,
        47,
        "channel 'ch4' limits voltage_v [0, 80] V exceed the PSB 10060-60 rating (60 V)",
    ),
    (
        "ea_current_above_model_rating.yaml",
        12,
        18,
        "channel 'ch0' limits current_a [-60, 40] A exceed the ELR 10200-50 rating (50 A)",
    ),
    (
        "ea_model_unreadable.yaml",
        6,
        21,
        "cannot read a rating from expected_model 'PSB 60V 60A': expected '<series> 1VVVV-A'",
    ),
    (
        "ea_sim_model_not_expected.yaml",
        8,
        16,
        "sim_model 'PSB 10060-60' would be refused at connect (remove it: it defaults to"
        " expected_model): it is not the expected_model 'ELR 10200-50' of device 'ea'",
    ),
    (
        "ea_sim_nominal_not_rating.yaml",
        8,
        20,
        "sim_nominal_v 80 V differs from 60 V (remove it: it defaults to the rating),"
        " the PSB 10060-60 rating of device 'ea'",
    ),
    (
        "ea_limits_above_sim_nominal.yaml",
        12,
        25,
        "channel 'ch4' limits current_a [-20, 20] A exceed the simulated unit's"
        " sim_nominal_v/sim_nominal_a rating (10 A)",
    ),
    # Strict types (issue 9): a YAML boolean is not a number, numbers are finite.
    ("boolean_as_number.yaml", 6, 11, "devices.ea.port: Input should be a valid integer"),
    ("boolean_as_board.yaml", 9, 39, "source.board: Input should be a valid integer"),
    ("boolean_as_capacity.yaml", 10, 18, "capacity_ah: Input should be a valid number"),
    ("boolean_in_a_pair.yaml", 11, 50, "voltage_v[0]: Input should be a valid number"),
    ("infinite_number.yaml", 10, 18, "capacity_ah: Input should be a finite number"),
    # The Modbus register map (issue 36, ADR 0031): explicit addresses that fit.
    (
        "modbus_addresses_overlap.yaml",
        13,
        22,
        "ch0.chain.cycle at input register 40001 overlaps the explicit address of 'ch0.voltage'",
    ),
    (
        "modbus_address_on_a_generated_one.yaml",
        12,
        22,
        "ch0.temperature at input registers 104-105 overlaps the generated place of"
        " 'ch0.voltage' (input registers 104-105)",
    ),
    ("modbus_address_beyond_65535.yaml", 12, 16, "less than or equal to 65535 (received 65536)"),
    ("modbus_float_ends_beyond_65535.yaml", 12, 18, "ch0.voltage: a float at 65535 ends beyond"),
    ("modbus_float_on_an_odd_address.yaml", 12, 18, "a float at the odd address 40001"),
    ("modbus_writer_not_an_ip.yaml", 12, 24, "writers[1]: writer 'panel-1' is not an IP address"),
    ("modbus_address_of_a_text.yaml", 12, 5, "'ch0.chain.recipe' is not a tag the Modbus map"),
    ("modbus_scale_of_a_code.yaml", 13, 5, "'ch0.mode' is not a float the Modbus map places"),
]


@pytest.mark.parametrize(("name", "line", "col", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_broken_io_map_is_refused_with_file_line_and_column(
    name: str, line: int, col: int, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        load_bench(BAD / name)
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(BAD / name), line, col)
    assert words in first.message


def test_every_broken_file_in_the_corpus_has_a_case() -> None:
    assert {p.name for p in BAD.glob("*.yaml")} == {c[0] for c in CASES}


def test_check_exits_2_and_prints_one_line_per_error_without_traceback(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(["check", str(BAD / "unknown_key.yaml"), str(ROOT / "io_maps" / "sim.yaml")])
    out, err = capsys.readouterr()
    assert code == 2
    assert "Traceback" not in err
    assert err.strip().splitlines() == [
        f"{BAD / 'unknown_key.yaml'}:3:3: unknown key 'perod_s' in scan"
        " (did you mean 'period_s'? expected one of: period_s, realtime_priority)"
    ]
    assert "sim.yaml: OK" in out


def test_check_of_good_files_exits_0(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", *map(str, sorted((ROOT / "io_maps").glob("*.yaml")))]) == 0


def test_the_installed_command_reports_a_missing_file_with_exit_2() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", "check", "no/such/file.yaml"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert "no/such/file.yaml" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_committed_json_schema_matches_the_models() -> None:
    committed = json.loads((ROOT / "io_maps" / "bench.schema.json").read_text(encoding="utf-8"))
    assert committed == json.loads(json.dumps(bench_schema(BENCH_MODEL)))


def test_the_schema_rejects_unknown_keys_for_editors() -> None:
    schema = bench_schema(BENCH_MODEL)
    assert schema["additionalProperties"] is False
    assert "period_s" in json.dumps(schema)


# --- an EA channel within its unit's rating ------------------------------------------------
@pytest.mark.parametrize(
    ("model", "volts", "amps"),
    [
        ("ELR 10200-50", 200.0, 50.0),  # seed 002's unit (devices.md)
        ("PSB 10060-60", 60.0, 60.0),
        ("PSB 10750-60", 750.0, 60.0),
        ("ea-psb  10060-1000 4U", 60.0, 1000.0),  # spelt as the driver compares models
    ],
)
def test_an_ea_model_name_gives_its_nominal_voltage_and_current(
    model: str, volts: float, amps: float
) -> None:
    rating = model_rating(model)
    assert rating is not None
    assert (rating.voltage_v, rating.current_a) == (volts, amps)


@pytest.mark.parametrize("model", ["PSB 60V 60A", "PSB10060-60", "PSB 9080-60", "PSB 10000-60"])
def test_a_name_without_the_10000_series_form_gives_no_rating(model: str) -> None:
    assert model_rating(model) is None


def _ea_bench(ea: dict[str, object], limits: dict[str, object]) -> dict[str, object]:
    return {
        "bench": "b",
        "devices": {"ea": {"driver": "ea-psb", "host": "127.0.0.1", **ea}},
        "channels": [
            {"name": "ch0", "source": {"device": "ea"}, "capacity_ah": 10.0, "limits": limits}
        ],
    }


def test_the_simulated_unit_defaults_to_the_expected_model_and_its_rating() -> None:
    cfg = bench_from_data(
        _ea_bench(
            {"sim": True, "expected_model": "ELR 10200-50"},
            {"current_a": [-50, 50], "voltage_v": [40.0, 200.0]},
        )
    )
    ea = cfg.devices["ea"]
    assert isinstance(ea, EaDevice)
    assert (ea.sim_model, ea.sim_nominal_v, ea.sim_nominal_a) == ("ELR 10200-50", 200.0, 50.0)


def test_a_simulated_unit_without_an_expected_model_keeps_its_defaults() -> None:
    cfg = bench_from_data(
        _ea_bench({"sim": True}, {"current_a": [-60, 60], "voltage_v": [0.0, 60.0]})
    )
    ea = cfg.devices["ea"]
    assert isinstance(ea, EaDevice)
    assert (ea.sim_model, ea.sim_nominal_v, ea.sim_nominal_a) == ("PSB 10060-60", 60.0, 60.0)


def test_limits_above_the_simulated_nominal_voltage_are_refused_before_connect() -> None:
    with pytest.raises(ConfigErrors) as info:
        bench_from_data(
            _ea_bench({"sim": True}, {"current_a": [-20, 20], "voltage_v": [12.0, 61.0]})
        )
    assert [e.message for e in info.value.errors] == [
        "channel 'ch0' limits voltage_v [12, 61] V exceed the simulated unit's"
        " sim_nominal_v/sim_nominal_a rating (60 V)"
    ]


def test_a_real_unit_named_by_no_model_is_left_to_the_driver_at_connect() -> None:
    # Nothing tells its rating before *IDN? and SYST:NOM? (the driver checks them then).
    data = _ea_bench({}, {"current_a": [-500, 500], "voltage_v": [0.0, 900.0]})
    data["devices"]["ea"]["host"] = "192.168.0.3"  # type: ignore[index]
    assert bench_from_data(data).channels[0].limits.voltage_v == (0.0, 900.0)
