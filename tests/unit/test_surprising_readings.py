"""Readings that surprised (issue 28, finding 10): each is refused, located, or read as meant.

A trailing newline slipped through the names and the one-line strings (Python's ``$``
matches before a final newline, and ``strip()`` took it away): ``sleep_until "08:00\\n"``,
an action, a parameter or device name (which then split the log lines that show it) and
``--start``. ``sleep -1 s`` was accepted as an until action. A Chadèche file mixing UTF-8
and CP1252 was read as CP1252, its UTF-8 accents turned to mojibake without a word. A dry
run held by an until's ``hold`` ended with "end: Held: " and no reason.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app.dryrun import dry_run, format_report
from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.states import State
from supervisor.cli.main import build_parser
from supervisor.config.recipe import load_recipe_text
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.registry import load_bench_text
from supervisor.importers import import_chadeche

ROOT = Path(__file__).resolve().parents[2]
FILE = "r.yaml"
HEADER = "ADR\tC/D\tmA\tSD\tTL\tTH\tLmAh\tHmAh\tTRUE\tCTRLZ\tCOMMENT\n"


def errors_of(text: str) -> list[ConfigError]:
    with pytest.raises(ConfigErrors) as info:
        recipe, positions = load_recipe_text(text, FILE)
        compile_recipe(recipe, positions, FILE, Target())
    return info.value.errors


def until_action(action: str) -> str:
    return (
        "recipe: r\nsteps:\n  - id: a\n    rest: 1 min\n    until:\n"
        f'      - "voltage > 1 V": "{action}"\n  - {{id: b, rest: 1 s}}\n'
    )


@pytest.mark.parametrize("action", ["sleep_until 08:00\\n", "08:00\\n", "b\\n", "next\\r"])
def test_an_action_with_a_newline_is_refused_at_the_action(action: str) -> None:
    [error] = errors_of(until_action(action))
    assert (error.file, error.line, error.col) == (FILE, 6, 26)
    assert "has the control character" in error.message
    assert "one line of text only" in error.message


def test_an_action_without_one_still_works() -> None:
    recipe, positions = load_recipe_text(until_action("sleep_until 08:00"), FILE)
    program = compile_recipe(recipe, positions, FILE, Target())
    assert program.steps[0].transitions[0].action.hhmm == (8, 0)


def test_a_negative_sleep_is_refused_as_an_until_action() -> None:
    [error] = errors_of(until_action("sleep -1 s"))
    assert (error.line, error.col) == (6, 26)
    assert "a sleep cannot be negative" in error.message


def test_sleep_until_with_a_trailing_newline_is_refused() -> None:
    text = 'recipe: r\nsteps:\n  - {id: a, rest: 1 s, sleep_until: "08:00\\n"}\n'
    [error] = errors_of(text)
    assert (error.line, error.col) == (3, 37)
    assert "sleep_until needs a time of day HH:MM" in error.message


def test_a_parameter_name_with_a_trailing_newline_is_refused() -> None:
    text = 'recipe: r\nparameters:\n  "v_end\\n": 1 V\nsteps:\n  - {id: a, rest: 1 s}\n'
    [error] = errors_of(text)
    assert error.line == 3
    assert "parameter name 'v_end\\n' must be an identifier" in error.message


def test_a_device_name_with_a_trailing_newline_is_refused() -> None:
    text = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    assert "\n  chadeche:\n    driver: chadeche" in text
    text = text.replace("\n  chadeche:\n    driver:", '\n  "chadeche\\n":\n    driver:', 1)
    with pytest.raises(ConfigErrors) as info:
        load_bench_text(text, "sim.yaml")
    assert any(
        "device name 'chadeche\\n' must be a plain identifier" in e.message
        for e in info.value.errors
    )


@pytest.mark.parametrize("start", ["08:00\n", "08:00\r", "08:\x0000"])
def test_dry_run_start_with_a_control_character_is_refused(
    start: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["dry-run", "recipes/capacity-test.yaml", "--start", start])
    assert info.value.code == 2
    assert "expected a time of day HH:MM" in capsys.readouterr().err


def test_dry_run_start_with_spaces_around_is_still_read() -> None:
    args = build_parser().parse_args(["dry-run", "recipes/capacity-test.yaml", "--start", " 8:00 "])
    assert args.start == "08:00"


def test_a_sequence_file_mixing_utf8_and_cp1252_is_refused_where_it_stops_being_utf8(
    tmp_path: Path,
) -> None:
    path = tmp_path / "mixed.txt"
    utf8_row = "1\tD\t0\t60\tI\tI\tI\tI\tI\tS\t#Répos\n".encode()
    cp1252_row = "2\tD\t0\t60\tI\tI\tI\tI\tI\tS\t#Réveil\n".encode("cp1252")
    path.write_bytes(HEADER.encode() + utf8_row + cp1252_row)
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    [error] = info.value.errors
    assert (error.line, error.col) == (3, 24)
    assert "the file mixes encodings: byte 0xe9 is not UTF-8" in error.message
    assert "line 2, column 24 is UTF-8 ('é')" in error.message  # the same column, row 2


def test_a_sequence_file_all_in_cp1252_still_imports_with_its_accents(tmp_path: Path) -> None:
    path = tmp_path / "cp1252.txt"
    row = "1\tD\t0\t60\tI\tI\tI\tI\tI\tS\t#Réveil\n"
    path.write_bytes((HEADER + row).encode("cp1252"))
    assert import_chadeche(path).recipe["steps"][0]["comment"] == "Réveil"


async def test_a_dry_run_held_at_once_by_an_until_says_why(tmp_path: Path) -> None:
    path = tmp_path / "hold.yaml"
    path.write_text(
        "recipe: hold-at-once\nsteps:\n  - id: wait\n    rest: 1 min\n    until:\n"
        "      - voltage >= 0 V: hold\n",
        encoding="utf-8",
    )
    res = await dry_run(path, max_hours=1)
    assert res.state is State.HELD
    assert res.end_reason == "until #1: voltage >= 0 V"
    assert "end: Held: until #1: voltage >= 0 V" in format_report(res)


def test_a_user_name_with_a_trailing_newline_is_refused() -> None:
    from supervisor.config.users import name_problem

    assert name_problem("alice") == ""
    assert "user name 'alice\\n'" in name_problem("alice\n")
