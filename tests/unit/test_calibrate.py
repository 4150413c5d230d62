"""Calibration (seed 000 §III.F): a·x + b fits, readings files, the I/O map edited in place,
and the two staircase recipes."""

from __future__ import annotations

import codecs
import math
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.app.calibrate import (
    calibrate_current,
    calibrate_voltage,
    fit_line,
    read_pairs_csv,
    write_calibration,
)
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.config.recipe import load_recipe
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import ChadecheCalibration, ChadecheDevice
from supervisor.devices.registry import load_bench

ROOT = Path(__file__).resolve().parents[2]
SIM = ROOT / "io_maps" / "sim.yaml"


def close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9)


# --------------------------------------------------------------------------------------------
# Fits


def test_the_current_fit_gives_the_seeds_figure_11_coefficients_back() -> None:
    # Seed §III.F.1: setpoint = 0.9823·measured + 0.0008 (mA) → -1 0.9823, -2 0.0008.
    setpoints = [0.0, 50.0, 100.0, 150.0, 200.0, 250.0]
    measured = [(s - 0.0008) / 0.9823 for s in setpoints]
    slope, offset_ma = calibrate_current(setpoints, measured)
    assert close(slope, 0.9823)
    assert close(offset_ma, 0.0008)


def test_the_voltage_fit_gives_the_seeds_figure_12_coefficients_back() -> None:
    # Seed §III.F.2: meter V = 1.0065·ADC V + 0.0003 → -s 1.0065, -o 0.0003.
    adc = [0.0, 0.35, 0.70, 1.05, 1.40, 1.75, 2.10, 2.45]
    meter = [1.0065 * v + 0.0003 for v in adc]
    slope, offset_v = calibrate_voltage(adc, meter)
    assert close(slope, 1.0065)
    assert close(offset_v, 0.0003)


def test_a_noisy_staircase_fits_with_r2_below_one() -> None:
    xs = [0.0, 50.0, 100.0, 150.0, 200.0, 250.0]
    ys = [0.1, 49.2, 101.0, 149.1, 201.3, 249.5]
    a, b, r2 = fit_line(xs, ys)
    assert 0.99 < a < 1.01
    assert abs(b) < 1.0
    assert 0.999 < r2 < 1.0


@given(
    a=st.integers(-(10**6), 10**6),
    b=st.integers(-(10**6), 10**6),
    xs=st.lists(st.integers(-(10**4), 10**4), min_size=2, max_size=40, unique=True),
)
def test_points_on_an_exact_line_are_fitted_back_within_1e_9(a: int, b: int, xs: list[int]) -> None:
    # Dyadic slope, intercept and x: every y = a·x + b is exact in binary floating point.
    slope, intercept = a / 1024, b / 1024
    x = [k / 8 for k in xs]
    y = [slope * v + intercept for v in x]
    fa, fb, r2 = fit_line(x, y)
    assert abs(fa - slope) <= 1e-9
    assert abs(fb - intercept) <= 1e-9
    assert abs(r2 - 1.0) <= 1e-9


@given(
    a=st.floats(-1e3, 1e3),
    b=st.floats(-1e3, 1e3),
    xs=st.lists(st.integers(-10_000, 10_000), min_size=2, max_size=40, unique=True),
    scale=st.sampled_from([1e-3, 0.1, 1.0, 7.5, 100.0]),
)
def test_points_on_a_rounded_line_are_fitted_back_to_the_rounding_of_the_data(
    a: float, b: float, xs: list[int], scale: float
) -> None:
    x = [k * scale for k in xs]
    y = [a * v + b for v in x]
    fa, fb, _ = fit_line(x, y)
    span = max(1.0, *(abs(v) for v in y))
    assert abs(fa - a) <= 1e-9 * max(1.0, abs(a))
    assert abs(fb - b) <= 1e-9 * span


@pytest.mark.parametrize(
    ("xs", "ys"),
    [([], []), ([1.0], [2.0]), ([3.0, 3.0, 3.0], [1.0, 2.0, 3.0])],
    ids=["none", "one", "same-x"],
)
def test_a_fit_needs_two_distinct_x(xs: list[float], ys: list[float]) -> None:
    with pytest.raises(ValueError, match="at least 2 distinct x values"):
        fit_line(xs, ys)


def test_a_fit_refuses_mismatched_or_non_finite_input() -> None:
    with pytest.raises(ValueError, match="as many x as y"):
        fit_line([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="finite"):
        fit_line([1.0, math.nan], [1.0, 2.0])


def test_a_reversed_meter_gives_a_clear_error_not_a_negative_slope() -> None:
    with pytest.raises(ValueError, match="swapped"):
        calibrate_current([0.0, 100.0, 200.0], [0.0, -100.0, -200.0])
    with pytest.raises(ValueError, match="swapped"):
        calibrate_voltage([0.0, 1.0], [1.0, 0.0])


# --------------------------------------------------------------------------------------------
# Readings


def test_readings_with_a_header_semicolons_and_decimal_commas_are_read(tmp_path: Path) -> None:
    path = tmp_path / "courant.csv"
    path.write_bytes(
        "Consigne (mA);Mesuré (mA)\r\n0;0,1\r\n50;50,9\r\n\r\n100;101,8\r\n".encode("cp1252")
    )
    assert read_pairs_csv(path) == ([0.0, 50.0, 100.0], [0.1, 50.9, 101.8])


@pytest.mark.parametrize(
    "text",
    ["0,0.1\n50,50.9\n", "# readings\n0\t0.1\n50\t50.9\n", "0   0.1\n50  50.9\n"],
    ids=["comma", "tab-and-comment", "blanks"],
)
def test_readings_in_any_usual_layout_are_read(tmp_path: Path, text: str) -> None:
    path = tmp_path / "r.csv"
    path.write_text(text, encoding="utf-8")
    assert read_pairs_csv(path) == ([0.0, 50.0], [0.1, 50.9])


@pytest.mark.parametrize(
    ("text", "line", "col", "words"),
    [
        ("set;meas\n0;0\n50;abc\n", 3, 4, "'abc' is not a number"),
        ("0;0\n50;1;2\n", 2, 6, "expected 2 numbers, found 3"),
        ("0;0\n50\n", 2, 3, "expected 2 numbers, found 1"),
    ],
    ids=["not-a-number", "three-fields", "one-field"],
)
def test_a_bad_readings_line_is_refused_at_its_line_and_column(
    tmp_path: Path, text: str, line: int, col: int, words: str
) -> None:
    path = tmp_path / "r.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        read_pairs_csv(path)
    assert (info.value.file, info.value.line, info.value.col) == (str(path), line, col)
    assert words in info.value.message


def test_a_header_may_use_other_separators_than_the_readings(tmp_path: Path) -> None:
    path = tmp_path / "r.txt"
    path.write_text("Consigne, mA   Mesure, mA\n0\t0,1\n50\t50,9\n", encoding="utf-8")
    assert read_pairs_csv(path) == ([0.0, 50.0], [0.1, 50.9])


def test_a_readings_file_that_is_neither_utf8_nor_cp1252_is_refused_where_the_byte_is(
    tmp_path: Path,
) -> None:
    path = tmp_path / "r.csv"
    path.write_bytes(b"set;meas\r\n0;0,1\r\n50;50,9\x81\r\n")
    with pytest.raises(ConfigError) as info:
        read_pairs_csv(path)
    assert (info.value.file, info.value.line, info.value.col) == (str(path), 3, 8)
    assert "0x81 is neither UTF-8 nor CP1252" in info.value.message


def test_a_readings_file_without_readings_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "r.csv"
    path.write_text("setpoint;measured\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="no readings"):
        read_pairs_csv(path)


# --------------------------------------------------------------------------------------------
# Writing the I/O map


def calibration_of(path: Path, board: int, device: str = "chadeche") -> ChadecheCalibration:
    dev = load_bench(path).devices[device]
    assert isinstance(dev, ChadecheDevice)
    return next(b.calibration for b in dev.boards if b.address == board)


def changed_region(old: str, new: str) -> tuple[str, str]:
    """The differing middle of two texts (after the common prefix and suffix)."""
    p = 0
    while p < min(len(old), len(new)) and old[p] == new[p]:
        p += 1
    s = 0
    while s < min(len(old), len(new)) - p and old[-1 - s] == new[-1 - s]:
        s += 1
    return old[p : len(old) - s], new[p : len(new) - s]


@pytest.fixture
def sim_copy(tmp_path: Path) -> Path:
    path = tmp_path / "sim.yaml"
    path.write_bytes(SIM.read_bytes())
    return path


def test_updating_a_flow_calibration_changes_only_those_numbers(sim_copy: Path) -> None:
    old = sim_copy.read_text(encoding="utf-8")
    write_calibration(
        sim_copy, "chadeche", 3, {"current_slope": 0.9823, "current_offset_ma": 0.0008}
    )
    new = sim_copy.read_text(encoding="utf-8")
    assert new == old.replace(
        "{current_slope: 0.9851, current_offset_ma: 0.0,",
        "{current_slope: 0.9823, current_offset_ma: 0.0008,",
    )
    before, after = changed_region(old, new)
    assert "\n" not in before + after  # one line changed, inside its calibration mapping
    assert before.endswith("current_offset_ma: 0.0") and after.endswith("0.0008")
    cal = calibration_of(sim_copy, 3)
    assert (cal.current_slope, cal.current_offset_ma) == (0.9823, 0.0008)
    assert (cal.voltage_slope, cal.voltage_offset_v) == (1.0099, 0.0013)  # kept


def test_a_board_without_calibration_gets_one_line_after_its_address(sim_copy: Path) -> None:
    old = sim_copy.read_text(encoding="utf-8").splitlines(keepends=True)
    write_calibration(
        sim_copy, "chadeche", 1, {"voltage_slope": 1.0065, "voltage_offset_v": 0.0003}
    )
    new = sim_copy.read_text(encoding="utf-8").splitlines(keepends=True)
    at = old.index("      - address: 1\n") + 1
    assert new == [
        *old[:at],
        "        calibration: {voltage_slope: 1.0065, voltage_offset_v: 0.0003}\n",
        *old[at:],
    ]
    cal = calibration_of(sim_copy, 1)
    assert (cal.voltage_slope, cal.voltage_offset_v, cal.current_slope) == (1.0065, 0.0003, 1.0)


BLOCK = """\
# A bench with block-style calibrations and comments everywhere.
bench: t   # name
devices:
  chadeche:
    driver: chadeche   # SPI stack
    boards:
      # board 0: calibrated on 2017-06-06
      - address: 0
        calibration:
          current_slope: 0.9851   # -1
          # offsets below
          current_offset_ma: 0.0  # -2
        sim: {model: nimh-aa}
      - {address: 1, sim: {model: nimh-aa}}
      - address: 2
        calibration: {}
channels:
  - name: ch0   # first
    source: {device: chadeche, board: 0}
    capacity_ah: 2.0
    limits: {current_a: [-0.4, 0.4], voltage_v: [0.8, 1.9]}
"""


def test_a_block_calibration_keeps_its_comments_and_gets_new_keys_at_its_indent(
    tmp_path: Path,
) -> None:
    path = tmp_path / "b.yaml"
    path.write_text(BLOCK, encoding="utf-8")
    write_calibration(
        path,
        "chadeche",
        0,
        {"current_offset_ma": -0.25, "voltage_slope": 1.01, "voltage_offset_v": 0.002},
    )
    new = path.read_text(encoding="utf-8")
    assert new == BLOCK.replace(
        "          current_offset_ma: 0.0  # -2\n",
        "          current_offset_ma: -0.25  # -2\n"
        "          voltage_slope: 1.01\n"
        "          voltage_offset_v: 0.002\n",
    )
    cal = calibration_of(path, 0)
    assert (cal.current_slope, cal.current_offset_ma, cal.voltage_offset_v) == (
        0.9851,
        -0.25,
        0.002,
    )


@pytest.mark.parametrize(
    ("board", "before", "after"),
    [
        (1, "{address: 1, sim:", "{address: 1, calibration: {current_slope: 0.98}, sim:"),
        (2, "calibration: {}\n", "calibration: {current_slope: 0.98}\n"),
        (2, "calibration: {}  # none yet\n", "calibration: {current_slope: 0.98}  # none yet\n"),
        (3, "        calibration:\n", "        calibration: {current_slope: 0.98}\n"),
        (3, "        calibration: ~\n", "        calibration: {current_slope: 0.98}\n"),
    ],
    ids=["flow-board", "empty-flow", "empty-flow-comment", "empty-value", "null"],
)
def test_other_board_layouts_get_the_smallest_edit(
    tmp_path: Path, board: int, before: str, after: str
) -> None:
    path = tmp_path / "b.yaml"
    # An empty or null calibration does not load yet; the edit is what makes it valid.
    text = BLOCK.replace("calibration: {}\n", before) if board == 2 else BLOCK
    if board == 3:
        text = text.replace("channels:", f"      - address: 3\n{before}channels:")
        before, after = f"address: 3\n{before}", f"address: 3\n{after}"
    path.write_text(text, encoding="utf-8")
    write_calibration(path, "chadeche", board, {"current_slope": 0.98})
    assert path.read_text(encoding="utf-8") == text.replace(before, after, 1)
    assert calibration_of(path, board).current_slope == 0.98


def test_a_bom_and_crlf_line_ends_are_kept(tmp_path: Path) -> None:
    path = tmp_path / "crlf.yaml"
    original = codecs.BOM_UTF8 + SIM.read_bytes().replace(b"\n", b"\r\n")
    path.write_bytes(original)
    write_calibration(path, "chadeche", 0, {"current_slope": 0.99})
    data = path.read_bytes()
    assert data.startswith(codecs.BOM_UTF8)
    assert b"\n" not in data.replace(b"\r\n", b"")
    assert data == original.replace(
        b"      - address: 0\r\n",
        b"      - address: 0\r\n        calibration: {current_slope: 0.99}\r\n",
    )
    assert calibration_of(path, 0).current_slope == 0.99


def test_a_cr_only_io_map_gets_its_new_line_with_cr(tmp_path: Path) -> None:
    path = tmp_path / "cr.yaml"
    original = SIM.read_bytes().replace(b"\n", b"\r")
    path.write_bytes(original)
    write_calibration(path, "chadeche", 0, {"current_slope": 0.99})
    assert path.read_bytes() == original.replace(
        b"      - address: 0\r", b"      - address: 0\r        calibration: {current_slope: 0.99}\r"
    )
    assert calibration_of(path, 0).current_slope == 0.99


def test_an_io_map_that_is_not_utf8_is_refused_at_the_bad_byte_and_not_touched(
    tmp_path: Path,
) -> None:
    path = tmp_path / "latin1.yaml"
    text = BLOCK.encode().replace(b"# name", b"# caf\xe9")
    path.write_bytes(text)
    with pytest.raises(ConfigError) as info:
        write_calibration(path, "chadeche", 0, {"current_slope": 0.98})
    assert (info.value.file, info.value.line, info.value.col) == (str(path), 2, 17)
    assert "must be UTF-8" in info.value.message
    assert path.read_bytes() == text


def test_a_device_that_is_not_a_mapping_is_refused_not_a_traceback(tmp_path: Path) -> None:
    path = tmp_path / "odd.yaml"
    path.write_text("devices:\n  chadeche: 5\n", encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        write_calibration(path, "chadeche", 0, {"current_slope": 0.98})
    assert (info.value.line, info.value.col) == (2, 3)
    assert "device 'chadeche' has driver 'none'" in info.value.message


@pytest.mark.parametrize(
    ("device", "board", "words"),
    [
        ("nope", 0, "no device 'nope' in devices: (have: chadeche, adam, ea, bms)"),
        ("ea", 0, "device 'ea' has driver 'ea-psb'"),
        ("chadeche", 7, "device 'chadeche' has no board with address 7 (addresses: 0, 1, 2, 3)"),
    ],
    ids=["unknown-device", "not-chadeche", "unknown-board"],
)
def test_a_wrong_device_or_board_is_refused_naming_the_file_and_nothing_is_written(
    sim_copy: Path, device: str, board: int, words: str
) -> None:
    before = sim_copy.read_bytes()
    with pytest.raises(ConfigError) as info:
        write_calibration(sim_copy, device, board, {"current_slope": 1.0})
    assert info.value.file == str(sim_copy)
    assert info.value.line is not None
    assert words in info.value.message
    assert sim_copy.read_bytes() == before


@pytest.mark.parametrize(
    ("values", "words"),
    [
        ({"current_slope": 0.0}, "current_slope must be > 0"),
        ({"slope": 1.0}, "unknown calibration key"),
        ({"voltage_offset_v": math.inf}, "finite"),
        ({}, "no calibration values"),
    ],
)
def test_bad_values_are_refused_and_nothing_is_written(
    sim_copy: Path, values: dict[str, float], words: str
) -> None:
    before = sim_copy.read_bytes()
    with pytest.raises(ValueError, match=words):
        write_calibration(sim_copy, "chadeche", 3, values)
    assert sim_copy.read_bytes() == before


def test_a_shared_anchor_calibration_is_not_edited_behind_the_other_boards_back(
    tmp_path: Path,
) -> None:
    text = BLOCK.replace(
        "      - address: 2\n        calibration: {}\n",
        "      - address: 2\n        calibration: &cal {current_slope: 0.97}\n"
        "      - address: 3\n        calibration: *cal\n",
    )
    path = tmp_path / "anchor.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match="shared"):
        write_calibration(path, "chadeche", 3, {"current_slope": 0.98})
    assert path.read_text(encoding="utf-8") == text


@pytest.mark.parametrize(
    ("broken", "line", "words"),
    [
        ("driver: chadeche\n    bogus: 1", 6, "unknown key 'bogus'"),
        ("driver: chadeche\n   oops: [", 6, "YAML syntax error"),
    ],
    ids=["invalid", "bad-yaml"],
)
def test_an_io_map_that_does_not_load_is_reported_as_it_is_and_not_touched(
    tmp_path: Path, broken: str, line: int, words: str
) -> None:
    path = tmp_path / "bad.yaml"
    text = BLOCK.replace("driver: chadeche", broken)
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigErrors) as info:
        write_calibration(path, "chadeche", 0, {"current_slope": 0.98})
    first = info.value.errors[0]
    assert first.file == str(path)
    assert first.line is not None and first.line >= line
    assert words in first.message
    assert path.read_text(encoding="utf-8") == text


# --------------------------------------------------------------------------------------------
# Staircase recipes


@pytest.mark.parametrize(
    ("name", "top_ma"),
    [("current-calibration.yaml", 250), ("voltage-calibration.yaml", 350)],
)
def test_the_calibration_staircases_load_compile_and_step_by_50_ma_every_30_s(
    name: str, top_ma: int
) -> None:
    recipe, pos = load_recipe(ROOT / "recipes" / name)
    program = compile_recipe(recipe, pos, name, Target())
    assert [round(s.current_a * 1000) for s in program.steps] == list(range(0, top_ma + 1, 50))
    assert all(s.current_a >= 0 for s in program.steps)  # charge direction
    assert [s.duration_s for s in program.steps] == [30.0] * len(program.steps)
    assert all(s.advance is not None and s.advance.kind == "next" for s in program.steps)
    assert program.log.period_s == 1.0
