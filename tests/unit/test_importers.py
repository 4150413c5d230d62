"""Importers: a Chadèche sequence file (seed 000 §III.D) and a load profile (seed 002 §2.3)
become recipes that load and compile; broken files are refused at file:line:column."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from supervisor.app.calibrate import write_calibration
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.profile_csv import read_profile_csv
from supervisor.chains.program import Program
from supervisor.config.recipe import load_recipe, load_recipe_text
from supervisor.config.yamlpos import load_yaml_text
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import ChadecheDevice
from supervisor.devices.registry import load_bench
from supervisor.importers import ImportResult, import_chadeche, import_profile
from supervisor.importers.chadeche import COLUMNS

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "chadeche"
FIGURE_10 = DATA / "figure10.txt"
FIGURE_10_CP1252 = DATA / "figure10-cp1252-crlf.txt"
PRM = DATA / "chadeche0.prm"


def compiled(text: str) -> Program:
    recipe, pos = load_recipe_text(text, "<test>")
    return compile_recipe(recipe, pos, "<test>", Target())


def shape(program: Program) -> list[tuple[Any, ...]]:
    """What a step chain does, without ids and comments."""
    out = []
    for s in program.steps:
        transitions = tuple(
            (t.text, t.action.kind, t.action.target, t.action.hhmm, t.action.seconds)
            for t in s.transitions
        )
        advance = None if s.advance is None else (s.advance.kind, s.advance.target)
        out.append(
            (
                s.kind,
                round(s.current_a, 12),
                s.duration_s,
                s.sleep_until,
                s.sleep_s,
                s.goto,
                transitions,
                advance,
            )
        )
    return out


def write(tmp_path: Path, text: str, name: str = "seq.txt") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return path


HEADER = "ADR\tC/D\tmA\tSD\tTL\tTH\tLmAh\tHmAh\tTRUE\tCTRLZ\tCOMMENT\n"


# --------------------------------------------------------------------------------------------
# Figure 10 and the hand-written case study


def test_figure_10_imports_to_the_same_chain_as_the_hand_written_case_study() -> None:
    # The case study assumes a charged cell at the start (seed §IV): -i 1300 on the command line.
    result = import_chadeche(FIGURE_10, overrides={"-i": 1300})
    imported = compiled(result.yaml_text)
    hand, pos = load_recipe(ROOT / "recipes" / "nimh-ds2710.yaml")
    reference = compile_recipe(hand, pos, "nimh-ds2710.yaml", Target())

    assert shape(imported) == shape(reference)
    assert imported.parameters == pytest.approx(reference.parameters)
    assert imported.initial_charge_ah == pytest.approx(reference.initial_charge_ah)
    assert imported.cycles == reference.cycles
    assert imported.log.period_s == reference.log.period_s


def test_figure_10_rows_become_steps_named_by_their_address_with_their_comments() -> None:
    result = import_chadeche(FIGURE_10)
    steps = result.recipe["steps"]
    assert [s["id"] for s in steps] == [f"s{n}" for n in range(1, 10)]
    assert steps[0] == {
        "id": "s1",
        "comment": "Repos",
        "rest": True,
        "duration": "60 s",
        "advance": "next",
    }
    assert steps[1]["discharge"] == "200 mA"
    assert steps[1]["duration"] == "90000 s"
    assert steps[1]["until"] == [{"voltage <= v_min": "next"}, {"charge <= q_min": "next"}]
    assert steps[3]["until"] == [{"voltage >= v_max": "s6"}, {"charge >= q_max": "s6"}]
    assert steps[4]["goto"] == "s3"
    assert steps[6]["advance"] is False
    assert steps[7] == {
        "id": "s8",
        "comment": "Reveil à 20 heures",
        "sleep_until": "20:00",
        "advance": "next",
    }
    assert steps[8]["end_cycle"] is True


def test_the_produced_yaml_is_the_recipe_data_and_names_its_source() -> None:
    result = import_chadeche(FIGURE_10, PRM)
    assert isinstance(result, ImportResult)
    assert yaml.safe_load(result.yaml_text) == result.recipe
    data, _ = load_yaml_text(result.yaml_text)
    assert data == result.recipe
    assert str(FIGURE_10) in result.yaml_text
    assert str(PRM) in result.yaml_text
    assert result.yaml_text.startswith("# Imported by supervisor.importers.chadeche")
    # Every source row is repeated above its step.
    assert "# line 6: 5  C  0  5  I  I  I  I  3  S  #NOP et saut incondtionnel" in (
        result.yaml_text
    )
    recipe, pos = load_recipe_text(result.yaml_text)
    compile_recipe(recipe, pos, "<imported>", Target())


def test_without_simplification_every_row_stays_a_timed_step_and_still_compiles() -> None:
    result = import_chadeche(FIGURE_10, simplify=False)
    steps = result.recipe["steps"]
    kinds = [next(k for k in ("rest", "charge", "discharge") if k in s) for s in steps]
    assert kinds == [
        "rest",
        "discharge",
        "rest",
        "charge",
        "rest",
        "charge",
        "charge",
        "rest",
        "rest",
    ]
    assert steps[4]["duration"] == "5 s"
    assert steps[4]["until"] == [{"true": "s3"}]
    assert steps[7]["duration"] == "0 s"
    assert steps[7]["until"] == [{"true": "20:00"}]
    assert steps[8] == {
        "id": "s9",
        "comment": "Fin de cycle",
        "rest": True,
        "duration": "0 s",
        "advance": "next",
    }
    program = compiled(result.yaml_text)
    assert program.steps[4].transitions[0].action.target == 2
    assert program.steps[7].transitions[0].action.hhmm == (20, 0)


def test_a_cp1252_crlf_excel_export_imports_the_same_as_utf8_and_keeps_the_accent() -> None:
    utf8 = import_chadeche(FIGURE_10)
    cp1252 = import_chadeche(FIGURE_10_CP1252)
    assert FIGURE_10_CP1252.read_bytes().count(b"\r\n") >= 9
    assert b"\xe0 20 heures" in FIGURE_10_CP1252.read_bytes()  # "à" in CP1252
    same = {k: v for k, v in cp1252.recipe.items() if k not in ("recipe", "description")}
    assert same == {k: v for k, v in utf8.recipe.items() if k not in ("recipe", "description")}
    assert cp1252.recipe["steps"][7]["comment"] == "Reveil à 20 heures"
    assert "(CP1252, CRLF, 9 rows)" in cp1252.yaml_text
    assert shape(compiled(cp1252.yaml_text)) == shape(compiled(utf8.yaml_text))


@pytest.mark.parametrize(
    ("prefix", "newline"),
    [(b"\xef\xbb\xbf", "\n"), (b"", "\r"), (b"", "\r\n")],
    ids=["utf8-bom", "cr", "crlf"],
)
def test_a_bom_and_any_line_end_are_accepted(tmp_path: Path, prefix: bytes, newline: str) -> None:
    text = FIGURE_10.read_text(encoding="utf-8").replace("\n", newline)
    path = tmp_path / "fig.txt"
    path.write_bytes(prefix + text.encode("utf-8"))
    assert import_chadeche(path).recipe["steps"] == import_chadeche(FIGURE_10).recipe["steps"]


def test_trailing_tabs_and_trailing_empty_lines_are_ignored(tmp_path: Path) -> None:
    text = FIGURE_10.read_text(encoding="utf-8").replace("\n", "\t\t\n") + "\n\t\n\n"
    path = write(tmp_path, text)
    assert import_chadeche(path).recipe["steps"] == import_chadeche(FIGURE_10).recipe["steps"]


def test_the_recipe_name_comes_from_the_file_name_or_the_argument(tmp_path: Path) -> None:
    assert import_chadeche(FIGURE_10).recipe["recipe"] == "figure10"
    assert import_chadeche(FIGURE_10, name="case-study").recipe["recipe"] == "case-study"
    odd = write(tmp_path, FIGURE_10.read_text(encoding="utf-8"), "2017 essai n°3.txt")
    assert import_chadeche(odd).recipe["recipe"] == "chadeche-2017-essai-n-3"
    # A configuration error (exit 2 from the CLI, issue 28 finding 7), not a ValueError.
    with pytest.raises(ConfigError, match="recipe name"):
        import_chadeche(FIGURE_10, name="bad name")


# --------------------------------------------------------------------------------------------
# Actions


def test_every_action_maps_to_its_recipe_action(tmp_path: Path) -> None:
    rows = [
        "1\tD\t100\t600\tS\tI\tC\t2\t+01:30\tC\t#all actions",
        "2\tC\t100\t60\t7:05\tI\tI\tI\tI\t3\t#time of day, goto on CTRL-Z",
        "3\tC\t0\t10\tI\tI\tI\tI\t+00:45\tI\t#sleep for, then next",
        "4\tD\t0\t10\tI\tI\tI\tI\tC\tS\t#end of cycle",
        "5\tD\t0\t10\tI\tI\tI\tI\tS\tS\t#TRUE S stays a step",
        "6\tC\t50\t10\tI\tI\tI\tI\tS\tS\t#50 mA but TRUE acts at once",
    ]
    result = import_chadeche(write(tmp_path, HEADER + "\n".join(rows) + "\n"))
    s = result.recipe["steps"]
    assert s[0]["until"] == [
        {"voltage <= v_min": "next"},
        {"charge <= q_min": "next_cycle"},
        {"charge >= q_max": "s2"},
        {"true": "+01:30"},
    ]
    assert s[0]["advance"] == "next_cycle"
    assert s[1]["until"] == [{"voltage <= v_min": "07:05"}]
    assert s[1]["advance"] == "s3"
    assert s[2]["sleep"] == "45 min"
    assert s[2]["advance"] is False
    assert s[3]["end_cycle"] is True
    assert s[4]["until"] == [{"true": "next"}]
    assert any("+01:30" in w and "not implemented" in w for w in result.warnings)
    assert any("50 mA of ADR 6 flow for one scan" in w for w in result.warnings)
    program = compiled(result.yaml_text)
    assert program.steps[0].transitions[3].action.seconds == 5400
    assert program.steps[1].advance is not None and program.steps[1].advance.target == 2


def test_a_loop_of_instant_rows_is_reported_at_its_source_rows(tmp_path: Path) -> None:
    rows = [
        "1\tC\t100\t60\tI\tI\tI\tI\tI\tS\t#charge",
        "2\tC\t0\t5\tI\tI\tI\tI\t3\tS\t#jump",
        "3\tC\t0\t5\tI\tI\tI\tI\t2\tS\t#jump back",
    ]
    path = write(tmp_path, HEADER + "\n".join(rows) + "\n")
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    first = info.value.errors[0]
    assert (first.file, first.line) == (str(path), 3)
    assert "loop with no exit" in first.message


# --------------------------------------------------------------------------------------------
# Parameters: defaults < .prm < overrides


def test_without_a_prm_file_the_seed_defaults_apply_and_assumptions_are_marked() -> None:
    result = import_chadeche(FIGURE_10)
    assert result.recipe["parameters"] == {
        "v_min": "1 V",
        "v_max": "1.75 V",
        "q_min": "100 mAh",
        "q_max": "1300 mAh",
        "q_init": "0 mAh",
    }
    assert result.recipe["initial_charge"] == "q_init"
    assert result.recipe["cycles"] == 1
    assert result.recipe["logging"] == {"period": "120 s"}
    assert "Assumed defaults (the seed does not state them): -i 0 mAh, -n 1." in result.yaml_text
    assert result.calibration is None and result.calibration_snippet is None
    assert result.warnings == []


def test_the_prm_file_overrides_the_defaults_and_overrides_win_over_the_prm_file() -> None:
    result = import_chadeche(FIGURE_10, PRM, overrides={"-C": 1250, "m": "1.05", "-n": 2})
    assert result.recipe["parameters"] == {
        "v_min": "1.05 V",  # override over the default
        "v_max": "1.7 V",  # prm over the default
        "q_min": "100 mAh",  # default
        "q_max": "1250 mAh",  # override over the prm (1200)
        "q_init": "1300 mAh",  # prm
    }
    assert result.recipe["cycles"] == 2  # override over the prm (3)
    assert result.recipe["logging"] == {"period": "60 s"}  # prm
    text = result.yaml_text
    assert "# -M: chadeche0.prm:2" in text
    assert "# -C: override" in text
    assert "# -c: default, seed §IV" in text
    assert "Assumed defaults" not in text  # -i and -n were given
    program = compiled(text)
    assert program.parameters["q_max"] == pytest.approx(1.25)
    assert program.initial_charge_ah == pytest.approx(1.3)


def test_prm_calibration_becomes_an_io_map_snippet_with_the_offset_in_ma(tmp_path: Path) -> None:
    result = import_chadeche(FIGURE_10, PRM)
    assert result.calibration == {
        "current_slope": 0.9851,
        "current_offset_ma": 0.0,
        "voltage_slope": 1.0099,
        "voltage_offset_v": 0.0013,
    }
    assert result.calibration_snippet is not None
    assert yaml.safe_load(result.calibration_snippet) == result.calibration
    # Pasted under a board's calibration: the I/O map loads with those values.
    io_map = tmp_path / "bench.yaml"
    io_map.write_text((ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8"), "utf-8")
    write_calibration(io_map, "chadeche", 1, result.calibration)
    device = load_bench(io_map).devices["chadeche"]
    assert isinstance(device, ChadecheDevice)
    board = device.boards[1]
    assert board.calibration.current_slope == 0.9851
    assert board.calibration.voltage_offset_v == 0.0013


def test_prm_options_that_are_not_recipe_matters_are_ignored_with_a_warning() -> None:
    result = import_chadeche(FIGURE_10, PRM)
    text = "\n".join(result.warnings)
    assert "-a (board address, line 6) ignored" in text
    assert "-v (verbose display, line 7)" in text
    assert "-f (results file name, line 8)" in text


def test_overrides_name_known_options_only() -> None:
    with pytest.raises(ConfigErrors, match="unknown option '-z'"):
        import_chadeche(FIGURE_10, overrides={"-z": 1})
    with pytest.raises(ConfigErrors, match="-n needs a whole number"):
        import_chadeche(FIGURE_10, overrides={"-n": "0"})
    result = import_chadeche(FIGURE_10, overrides={"-v": "", "-1": 0.98})
    assert result.calibration == {"current_slope": 0.98}
    assert any("-v (verbose display)" in w for w in result.warnings)


def test_a_broken_prm_file_is_refused_at_each_bad_line_and_column() -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, DATA / "bad-option.prm")
    got = [(e.file, e.line, e.col) for e in info.value.errors]
    prm = str(DATA / "bad-option.prm")
    assert got == [(prm, 2, 1), (prm, 3, 4), (prm, 4, 4)]
    messages = [e.message for e in info.value.errors]
    assert "unknown option -x" in messages[0]
    assert "-M needs a number, got 'abc'" in messages[1]
    assert "must be > 0" in messages[2]


# --------------------------------------------------------------------------------------------
# Broken sequence files

# (file, line, col, words the message must contain); columns count a tab as one character.
CASES = [
    ("bad-no-header.txt", 1, 1, "missing header line"),
    ("bad-short-header.txt", 1, 20, "short header: 6 of 11 columns"),
    ("bad-field-count.txt", 3, 25, "row has 10 fields, expected 11"),
    ("bad-letter.txt", 4, 3, "unknown C/D letter 'X'"),
    ("bad-current.txt", 5, 5, "450 mA is over the board's 400 mA maximum"),
    ("bad-adr.txt", 6, 1, "ADR '5b' is not a whole number"),
    ("bad-adr-order.txt", 8, 1, "ADR 5 does not increase (line 7 has ADR 6)"),
    ("bad-action.txt", 5, 15, "TH: unknown action 'Q'"),
    ("bad-goto.txt", 6, 17, "TRUE: goto to a missing ADR 42"),
    ("bad-comment.txt", 8, 25, "comment 'Maintien' must start with '#'"),
    ("bad-several.txt", 3, 3, "unknown C/D letter 'Z'"),
    # Issue 9: a 5000-digit number was a ValueError traceback; '٣' was read as 3.
    ("bad-huge-number.txt", 3, 9, "SD 999999999999… (5000 characters) is too large"),
    ("bad-unicode-digit.txt", 3, 9, "SD '٣600' is not a whole number of seconds (ASCII digits"),
    ("bad-too-many-rows.txt", 2002, 1, "too many rows: 2,001; a sequence file may have at most"),
]


@pytest.mark.parametrize(("name", "line", "col", "words"), CASES, ids=[c[0] for c in CASES])
def test_a_broken_sequence_file_is_refused_at_the_exact_line_and_column(
    name: str, line: int, col: int, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(DATA / name)
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(DATA / name), line, col)
    assert words in first.message


def test_every_broken_fixture_has_a_case() -> None:
    assert {p.name for p in DATA.glob("bad-*.txt")} == {c[0] for c in CASES}


# Broken parameter files: (file, line, col, words of the first error).
PRM_CASES = [
    ("bad-option.prm", 2, 1, "unknown option -x"),
    ("bad-cycles.prm", 5, 4, "-n must be from 1 to 1000000"),
    ("bad-cycles-digits.prm", 2, 4, "-n must be from 1 to 1000000"),
    ("bad-unicode.prm", 2, 4, "-m needs a number, got '١.١' (ASCII digits 0-9 only"),
    ("bad-atof.prm", 2, 4, "-1 needs a number, got '1_000' (the Chadèche program's atof"),
    ("bad-inverted.prm", 2, 4, "-m 1.8 V (bad-inverted.prm:2) must be below -M 1.7 V"),
    ("bad-range.prm", 1, 4, "-M must be more than 0 and at most 4.096 V"),
]


@pytest.mark.parametrize(("name", "line", "col", "words"), PRM_CASES, ids=[c[0] for c in PRM_CASES])
def test_a_broken_parameter_file_is_refused_at_the_exact_line_and_column(
    name: str, line: int, col: int, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, DATA / name)
    first = info.value.errors[0]
    assert (first.file, first.line, first.col) == (str(DATA / name), line, col)
    assert words in first.message


def test_every_broken_parameter_file_has_a_case() -> None:
    assert {p.name for p in DATA.glob("bad-*.prm")} == {c[0] for c in PRM_CASES}


def test_nonsense_option_values_are_each_refused_with_the_reason() -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, DATA / "bad-range.prm")
    assert [e.location_message() for e in info.value.errors] == [
        f"{DATA / 'bad-range.prm'}:1:4: -M must be more than 0 and at most 4.096 V"
        " (the board's ADC reads 0 to 4.096 V), got '0'",
        f"{DATA / 'bad-range.prm'}:2:4: -C must be from 0 to 100000 mAh"
        " (a charge of a cell, at most 100 Ah), got '-5'",
        f"{DATA / 'bad-range.prm'}:3:4: -i must be from 0 to 100000 mAh"
        " (a charge of a cell, at most 100 Ah), got '1e308'",
        f"{DATA / 'bad-range.prm'}:4:4: -p must be from 0.1 to 86400 s"
        " (from one scan to one day), got '1e-320'",
        f"{DATA / 'bad-range.prm'}:5:4: -2 must be from -400 to 400 mA"
        " (within the board's ±400 mA range), got '1e308'",
        f"{DATA / 'bad-range.prm'}:6:4: -s must be from 0.5 to 2"
        " (a calibration slope corrects a few per cent), got '1e308'",
    ]


@pytest.mark.parametrize(
    ("option", "value", "words"),
    [
        ("-M", "-5", "-M must be more than 0 and at most 4.096 V"),
        ("-m", "5", "-m must be more than 0 and at most 4.096 V"),
        ("-i", "-1e308", "-i must be from 0 to 100000 mAh"),
        ("-p", "1e308", "-p must be from 0.1 to 86400 s"),
        ("-p", "0", "-p (logging period) must be > 0 s"),
        ("-2", "1e308", "-2 must be from -400 to 400 mA"),
        ("-o", "5", "-o must be from -4.096 to 4.096 V"),
        ("-1", "1_000", "-1 needs a number, got '1_000'"),
        ("-C", "３", "-C needs a number, got '３' (ASCII digits 0-9 only"),
        ("-n", "1" + "0" * 400, "-n must be from 1 to 1000000"),
        ("-n", "٣", "-n needs a whole number of cycles >= 1, got '٣' (ASCII digits"),
    ],
)
def test_an_override_out_of_range_is_refused_with_the_reason(
    option: str, value: str, words: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, overrides={option: value})
    (error,) = info.value.errors
    assert error.file == "<overrides>"
    assert words in error.message


def test_inverted_thresholds_from_an_override_name_both_sources() -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, PRM, overrides={"-m": "1.8"})  # the .prm has -M 1.70
    (error,) = info.value.errors
    assert error.file == "<overrides>"
    assert error.message.startswith("-m 1.8 V (override) must be below -M 1.7 V (chadeche0.prm:2)")
    with pytest.raises(ConfigErrors, match=r"-c 1300 mAh \(override\) must be below -C 1200"):
        import_chadeche(FIGURE_10, PRM, overrides={"-c": "1300"})


def test_a_refusal_of_the_imported_recipe_about_an_option_is_reported_where_it_was_set(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A backstop: if an option's range ever lets through what the recipe refuses, the
    # refusal still points at the .prm line that set it (it pointed at the sequence file,
    # without a line).
    from supervisor.importers import chadeche

    wide = chadeche._Range(1.0, 1e9, "test: no bound")
    monkeypatch.setitem(chadeche.OPTION_RANGES, "n", wide)
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(FIGURE_10, DATA / "bad-cycles.prm")
    (error,) = info.value.errors
    assert (error.file, error.line, error.col) == (str(DATA / "bad-cycles.prm"), 5, 4)
    assert "the imported recipe is refused: cycles:" in error.message


@pytest.mark.parametrize("column", ["ADR", "mA", "SD", "TRUE"])
def test_a_number_of_thousands_of_digits_is_refused_not_a_traceback(
    tmp_path: Path, column: str
) -> None:
    cells = ["1", "C", "0", "10", "I", "I", "I", "I", "I", "S", "#a"]
    k = COLUMNS.index(column)
    cells[k] = "9" * 5000
    path = write(tmp_path, HEADER + "\t".join(cells) + "\n")
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    (error,) = info.value.errors
    assert (error.line, error.col) == (2, 1 + sum(len(c) + 1 for c in cells[:k]))
    assert "999999999999… (5000 characters)" in error.message
    assert "too large" in error.message or "over the board's 400 mA maximum" in error.message


@pytest.mark.parametrize(
    ("cells", "col", "words"),
    [
        (["1", "C", "0", "٣", "I", "I", "I", "I", "I", "S", "#a"], 7, "SD '٣'"),
        (["1", "C", "３", "10", "I", "I", "I", "I", "I", "S", "#a"], 5, "mA '３'"),
        (["٣", "C", "0", "10", "I", "I", "I", "I", "I", "S", "#a"], 1, "ADR '٣'"),
        (["1", "C", "0", "10", "I", "I", "I", "I", "٢٠:٠٠", "S", "#a"], 18, "TRUE: unknown"),
        (["1", "C", "0", "10", "I", "I", "I", "I", "I", "١", "#a"], 20, "CTRLZ: unknown"),
    ],
    ids=["sd", "ma", "adr", "hhmm", "goto"],
)
def test_unicode_digits_are_not_read_as_numbers(
    tmp_path: Path, cells: list[str], col: int, words: str
) -> None:
    path = write(tmp_path, HEADER + "\t".join(cells) + "\n")
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    (error,) = info.value.errors
    assert (error.line, error.col) == (2, col)
    assert words in error.message and "ASCII digits 0-9 only" in error.message


def test_all_errors_of_a_file_are_reported_together_in_line_order() -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(DATA / "bad-several.txt")
    assert [(e.line, e.col) for e in info.value.errors] == [(3, 3), (9, 5), (9, 27)]


def test_an_error_in_one_row_does_not_make_gotos_to_it_missing() -> None:
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(DATA / "bad-letter.txt")  # row ADR 3 is bad; row 5 jumps to 3
    assert len(info.value.errors) == 1


@pytest.mark.parametrize(
    ("text", "line", "col", "words"),
    [
        ("", 1, 1, "file is empty"),
        (HEADER, 2, 1, "no sequence rows"),
        (
            HEADER + "1\tC\t0\t10\tI\tI\tI\tI\tI\tS\t#a\n\n2\tC\t0\t10\tI\tI\tI\tI\tI\tS\t#b\n",
            3,
            1,
            "empty line",
        ),
        (HEADER + "1\tC\t0\t10\tI\tI\tI", 2, 15, "missing HmAh TRUE CTRLZ COMMENT"),
        (HEADER + "1\tC\t0\tten\tI\tI\tI\tI\tI\tS\t#a\n", 2, 7, "SD 'ten'"),
        (HEADER + "1\tC\t-5\t10\tI\tI\tI\tI\tI\tS\t#a\n", 2, 5, "mA '-5'"),
        (HEADER + "1\tC\t0\t10\tI\tI\tI\tI\t25:00\tS\t#a\n", 2, 18, "TRUE: unknown action"),
        (HEADER + "1\tC\t0\t10\tI\tI\tI\tI\tI\t9\t#a\n", 2, 20, "CTRLZ: goto to a missing ADR 9"),
        (HEADER + "1\tC\t0\t10\tI\tI\tI\tI\tI\tS\tx\ty\n", 2, 24, "row has 12 fields"),
    ],
    ids=[
        "empty",
        "header-only",
        "blank-line",
        "short-row",
        "sd",
        "negative-ma",
        "bad-hhmm",
        "ctrlz-goto",
        "extra-field",
    ],
)
def test_more_broken_rows_are_refused_at_the_exact_line_and_column(
    tmp_path: Path, text: str, line: int, col: int, words: str
) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    first = info.value.errors[0]
    assert (first.line, first.col) == (line, col)
    assert words in first.message


def test_a_comment_may_contain_tabs(tmp_path: Path) -> None:
    path = write(tmp_path, HEADER + "1\tC\t0\t10\tI\tI\tI\tI\tI\tS\t#a\tb\n")
    assert import_chadeche(path).recipe["steps"][0]["comment"] == "a\tb"


def test_a_file_that_is_neither_utf8_nor_cp1252_is_refused_where_the_byte_is(
    tmp_path: Path,
) -> None:
    path = tmp_path / "seq.txt"
    path.write_bytes(HEADER.encode() + b"1\tC\t0\t10\tI\tI\tI\tI\tI\tS\t#\x81\n")
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    first = info.value.errors[0]
    assert (first.line, first.col) == (2, 23)
    assert "0x81" in first.message


# --------------------------------------------------------------------------------------------
# Load profiles (seed 002 §2.3)


def test_a_profile_with_min_max_cells_imports_to_one_profile_step(tmp_path: Path) -> None:
    csv = tmp_path / "profil.csv"
    csv.write_bytes(
        "Temps (s);Courant (A);Tension Min/Max;Courant Min/Max;Température Min/Max\r\n"
        "0;0.5;3.0/4.2;-1/1;0/45\r\n"
        "10;-1.0;3.0/4.2;-2/2;0/45\r\n"
        "20;0;;;\r\n".encode("cp1252")
    )
    text = import_profile(csv)
    assert text.startswith("# Imported by supervisor.importers.profile")
    data = yaml.safe_load(text)
    assert data["recipe"] == "profil"
    (step,) = data["steps"]
    assert step["profile"]["rows"] == [
        {
            "t": 0.0,
            "current": 0.5,
            "v_min": 3.0,
            "v_max": 4.2,
            "i_min": -1.0,
            "i_max": 1.0,
            "t_min": 0.0,
            "t_max": 45.0,
        },
        {
            "t": 10.0,
            "current": -1.0,
            "v_min": 3.0,
            "v_max": 4.2,
            "i_min": -2.0,
            "i_max": 2.0,
            "t_min": 0.0,
            "t_max": 45.0,
        },
        {"t": 20.0, "current": 0.0},
    ]
    program = compiled(text)
    assert program.steps[0].kind == "profile"
    assert [p.current_a for p in program.steps[0].profile] == [0.5, -1.0, 0.0]


def test_a_profile_in_two_columns_per_window_without_header_imports_the_same(
    tmp_path: Path,
) -> None:
    one = tmp_path / "one.csv"
    one.write_text("t,I,V\n0,0.5,3.0/4.2\n10,-1,3.0/4.2\n", encoding="utf-8")
    two = tmp_path / "two.csv"
    two.write_text("0\t0.5\t3.0\t4.2\n10\t-1\t3.0\t4.2\n", encoding="utf-8")
    rows_one = yaml.safe_load(import_profile(one, name="p"))["steps"][0]["profile"]["rows"]
    rows_two = yaml.safe_load(import_profile(two, name="p"))["steps"][0]["profile"]["rows"]
    assert rows_one == rows_two


def test_a_broken_profile_is_refused_with_its_file_and_line(tmp_path: Path) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text("t;I\n0;0.5\n10;x\n", encoding="utf-8")
    with pytest.raises(ConfigErrors) as info:
        import_profile(csv)
    first = info.value.errors[0]
    assert (first.file, first.line) == (str(csv), 3)
    csv.write_text("-0.5;0.5\n10;1\n", encoding="utf-8")
    with pytest.raises(ConfigErrors, match="negative"):
        import_profile(csv)


@pytest.mark.parametrize("byte", [0x81, 0x8D, 0x8F, 0x90, 0x9D], ids=lambda b: f"0x{b:02X}")
def test_a_profile_with_a_byte_undefined_in_cp1252_is_refused_at_that_byte_not_a_traceback(
    tmp_path: Path, byte: int
) -> None:
    # Neither UTF-8 (a lone continuation byte) nor CP1252 (one of its five holes).
    csv = tmp_path / "profil.csv"
    csv.write_bytes(b"Temps;Courant\r\n0;0,5\r\n10;1,0" + bytes([byte]) + b"\r\n")
    with pytest.raises(ConfigError) as info:
        read_profile_csv(csv)
    assert (info.value.file, info.value.line, info.value.col) == (str(csv), 3, 7)
    assert f"byte 0x{byte:02x} is neither UTF-8 nor CP1252" in info.value.message
    with pytest.raises(ConfigErrors) as many:
        import_profile(csv)
    assert [(e.line, e.col) for e in many.value.errors] == [(3, 7)]
