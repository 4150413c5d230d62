"""Issue 32, finding 5: a load profile's columns by their header's names, and Unix
timestamps (seed 002, figures 21 and 26) made relative to the first row with a notice."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from supervisor.app.dryrun import dry_run
from supervisor.chains.profile_csv import parse_profile_csv, read_profile_csv, read_profile_table
from supervisor.core.errors import ConfigError
from supervisor.importers import import_profile

# Figure 21 of seed 002: the Tk HMI's sample profile, as its csv.DictWriter writes it.
FIGURE_21 = (
    "Time,Voltage,Current,Temperature,BMS Faults,Cell Voltage,Cell Temperature\n"
    "1736943899.5500178,3.7,0.5,25,No faults,3.7,25\n"
    "1736943899.8000193,3.8,0.6,26,No faults,3.8,26\n"
    "1736943900.0500205,3.9,0.7,27,No faults,3.9,27\n"
    "1736943900.300021,4.0,0.8,28,No faults,4.0,28\n"
    "1736943900.5500214,4.1,0.9,29,No faults,4.1,29\n"
)


def write(tmp_path: Path, text: str, name: str = "p.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_the_current_is_the_column_named_current_not_the_second_one(tmp_path: Path) -> None:
    points = read_profile_csv(write(tmp_path, FIGURE_21))
    assert [p.current_a for p in points] == [0.5, 0.6, 0.7, 0.8, 0.9]
    # Voltage and Temperature are what the seed's run recorded: no window made of them.
    assert all(p.v_min is None and p.t_max is None for p in points)


def test_figure_21_s_unix_timestamps_are_made_relative_to_the_first_row_with_a_notice(
    tmp_path: Path,
) -> None:
    table = read_profile_table(write(tmp_path, FIGURE_21))
    assert [p.t_s for p in table.points] == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0], abs=1e-5)
    assert table.unix_start_s == pytest.approx(1736943899.5500178)
    notes = " | ".join(table.notices)
    assert "Unix timestamps" in notes and "2025-01-15 12:24:59.550 UTC" in notes
    assert "'Voltage'" in notes and "'BMS Faults'" in notes and "'Current'" not in notes


async def test_a_three_row_half_second_profile_in_unix_time_ends_after_half_a_second(
    tmp_path: Path,
) -> None:
    write(tmp_path, "Time,Current\n1736943899.55,0.2\n1736943899.80,0.3\n1736943900.05,0\n")
    recipe = write(tmp_path, "recipe: r\nsteps:\n  - {id: p, profile: {file: p.csv}}\n", "r.yaml")
    res = await dry_run(recipe, max_hours=1)
    assert res.finished, res.end_reason
    assert res.simulated_s < 5.0  # not 55 years cut at the hour


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("TIME;CURRENT\n0;1,5\n9000;0\n", (0.0, 1.5, None, None)),
        ("Temps (s)\tCourant (A)\tTension Min/Max\n0\t-2\t3,0/4,2\n9\t0\t\n", (0, -2, 3, 4.2)),
        (
            "time [ms],current (mA),V min (mV),v_max\n500,250,3000,4.2\n900,0,,\n",
            (0.5, 0.25, 3, 4.2),
        ),
        ("Current_A,t_s,Vmin/Vmax\n0.5,0,3.0/4.2\n0,9000,\n", (0.0, 0.5, 3.0, 4.2)),
        ("Time (min),Courant,Tension Max,Tension Min\n1,0.5,4.2,3.0\n2,0,,\n", (60, 0.5, 3, 4.2)),
    ],
)
def test_usual_names_and_units_in_any_case_and_order_are_read(
    text: str, expected: tuple[float | None, ...]
) -> None:
    first = parse_profile_csv(text.encode(), "p.csv").points[0]
    got = (first.t_s, first.current_a, first.v_min, first.v_max)
    assert got == pytest.approx(expected)


def test_a_sub_unit_is_divided_into_the_value_one_would_write() -> None:
    text = "Time (ms),Current (mA)\n0,700\n300,-100\n700,0\n"
    points = parse_profile_csv(text.encode(), "p.csv").points
    assert [(p.t_s, p.current_a) for p in points] == [(0.0, 0.7), (0.3, -0.1), (0.7, 0.0)]


def test_the_seed_s_profile_form_with_three_min_max_windows_is_read() -> None:
    text = (
        "Temps (s)\tCourant (A)\tTension Min/Max\tCourant Min/Max\tTempérature Min/Max\n"
        "0\t1\t3/4,2\t-2/2\t10/45\n"
        "60\t0\t3/4,2\t-2/2\t10/45\n"
    )
    p = parse_profile_csv(text.encode("cp1252"), "p.csv").points[0]
    assert (p.v_min, p.v_max, p.i_min, p.i_max, p.t_min, p.t_max) == (3, 4.2, -2, 2, 10, 45)


@pytest.mark.parametrize(
    ("text", "col", "words"),
    [
        ("Time,Voltage,Curent\n0,3.7,0.5\n", 14, ("'Curent' is not a column of a load profile",)),
        ("Time,Current (kA)\n0,0.5\n", 6, ("unit 'ka' is not one of A, mA",)),
        ("Time,Voltage\n0,3.7\n", 1, ("the header names no current column",)),
        ("Time,Current,I\n0,0.5,0.6\n", 14, ("column 'I' gives what column 'Current'",)),
    ],
)
def test_a_header_it_does_not_know_is_refused_naming_the_column(
    tmp_path: Path, text: str, col: int, words: tuple[str, ...]
) -> None:
    with pytest.raises(ConfigError) as info:
        read_profile_csv(write(tmp_path, text))
    assert (info.value.line, info.value.col) == (1, col)
    for word in words:
        assert word in info.value.message


def test_a_row_longer_than_a_named_header_is_refused_at_its_first_extra_cell(
    tmp_path: Path,
) -> None:
    with pytest.raises(ConfigError) as info:
        read_profile_csv(write(tmp_path, "Time (s),Current (mA)\n0,500,,7\n"))
    assert (info.value.line, info.value.col) == (2, 8)
    assert "a value in column 4; the header names 2 columns" in info.value.message
    # Empty cells past the names are a spreadsheet's trailing separators.
    assert len(read_profile_csv(write(tmp_path, "Time (s),Current (mA)\n0,500,,\n1,0,\n"))) == 2


def test_the_imported_recipe_says_what_was_noticed(tmp_path: Path) -> None:
    text = import_profile(write(tmp_path, FIGURE_21, "sample_profile.csv"))
    assert "# note: times are Unix timestamps" in text
    step = yaml.safe_load(text)["steps"][0]
    # A result line per row (figure 21: every 250 ms), not the recipe default's 120 s.
    assert step["log"] == {"period": "0.25 s"}
    rows = step["profile"]["rows"]
    assert [r["current"] for r in rows] == [0.5, 0.6, 0.7, 0.8, 0.9]
    assert rows[-1]["t"] == pytest.approx(1.0, abs=1e-5)


def test_the_command_line_prints_the_notices(tmp_path: Path) -> None:
    csv = write(tmp_path, FIGURE_21, "sample_profile.csv")
    out = tmp_path / "sample.yaml"
    # The real command in a child process (its stderr is the command's, nothing else's).
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "supervisor.cli.main",
            "import",
            "profile",
            str(csv),
            "-o",
            str(out),
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert proc.returncode == 0, proc.stderr
    assert "note: times are Unix timestamps" in proc.stderr
    assert "note: columns 'Voltage'" in proc.stderr
    assert "# note: times are Unix timestamps" in out.read_text(encoding="utf-8")
