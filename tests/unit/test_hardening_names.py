"""Issue 28, findings 7, 8 and 9: what the CLI, a profile's ``repeat`` and a load profile
CSV are handed, refused with one clear message (exit 2, no traceback), never misread."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from supervisor.chains.profile_csv import read_profile_csv
from supervisor.config.limits import MAX_PROFILE_REPEAT
from supervisor.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


def cli(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    """The real ``supervisor`` command in a child process."""
    return subprocess.run(
        [sys.executable, "-m", "supervisor.cli.main", *args],
        capture_output=True,
        text=True,
        check=False,
        cwd=cwd,
        timeout=120,
    )


def refused(proc: subprocess.CompletedProcess[str], *words: str) -> str:
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, proc.stderr
    for word in words:
        assert word in proc.stderr
    return proc.stderr


# --- finding 8: profile repeat ------------------------------------------------------------


def test_a_profile_repeated_10_to_the_400_times_is_refused_at_load_at_its_value(
    tmp_path: Path,
) -> None:
    path = tmp_path / "repeat.yaml"
    path.write_text(
        "recipe: rep\nsteps:\n  - id: p\n    profile:\n"
        "      rows: [{t: 0, current: 0.1}, {t: 10, current: 0}]\n"
        f"      repeat: {10**400}\n",
        encoding="utf-8",
    )
    err = refused(cli("check", str(path)), f"{path}:6:15:", "too many")
    assert f"at most {MAX_PROFILE_REPEAT:,} times (README: Input limits)" in err


# --- finding 9: load profile CSVs -------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "col", "words"),
    [
        # Decimal commas with ',' as the separator: 0 s, 0 A and v_min 5 V.
        ("t,i\n0,0,5\n10,0,5\n", 2, 1, ("separate the cells with ';'", "decimal points")),
        ("0,1,2,3,4,5,6,7,8\n10,0\n", 1, 17, ("9 columns", "at most 8: time, current")),
        ("0;1;1/2/3\n10;0\n", 1, 5, ("'1/2/3': a min/max cell holds two numbers",)),
        ("0,1/2\n10,0\n", 1, 3, ("'1/2': the current is one number",)),
        ("0,1e-400\n10,0\n", 1, 3, ("'1e-400' is too small to be told from zero",)),
    ],
)
def test_a_profile_csv_cell_that_would_be_misread_is_refused_where_it_is(
    tmp_path: Path, text: str, line: int, col: int, words: tuple[str, ...]
) -> None:
    path = tmp_path / "p.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        read_profile_csv(path)
    assert (exc.value.line, exc.value.col) == (line, col)
    for word in words:
        assert word in exc.value.message


def test_a_profile_csv_window_with_one_bound_and_french_decimals_still_read(
    tmp_path: Path,
) -> None:
    half = tmp_path / "half.csv"
    half.write_text("0,1,3.0,\n10,0,,\n", encoding="utf-8")
    assert read_profile_csv(half)[0].v_min == 3.0
    french = tmp_path / "fr.csv"
    french.write_text("0;0,5;3,0/4,2\n10;0\n", encoding="utf-8")
    first = read_profile_csv(french)[0]
    assert (first.current_a, first.v_min, first.v_max) == (0.5, 3.0, 4.2)


def test_a_100000_row_profile_within_the_csv_limits_imports_as_a_recipe_naming_the_csv(
    tmp_path: Path,
) -> None:
    csv = tmp_path / "long.csv"
    lines = ["t,i"] + [f"{k},{0.5 if k % 2 else -0.25},2.5,4.2" for k in range(100_000)]
    csv.write_text("\n".join(lines) + "\n", encoding="utf-8")
    out = tmp_path / "recipes" / "long.yaml"
    out.parent.mkdir()
    proc = cli("import", "profile", str(csv), "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "file: ../long.csv" in out.read_text(encoding="utf-8")
    check = cli("check", str(out))
    assert check.returncode == 0, check.stderr


# --- finding 7: the CLI's tracebacks ----------------------------------------------------

NUL_PROFILE = 'recipe: nul\nsteps:\n  - id: p\n    profile: {file: "a\\0b.csv"}\n'


@pytest.mark.parametrize("command", ["check", "dry-run"])
def test_a_profile_file_name_with_a_nul_is_refused_at_its_value(
    tmp_path: Path, command: str
) -> None:
    path = tmp_path / "nul.yaml"
    path.write_text(NUL_PROFILE, encoding="utf-8")
    refused(cli(command, str(path)), f"{path}:4:21:", "NUL")


def test_a_state_dir_with_a_nul_is_refused_by_run_at_its_value(tmp_path: Path) -> None:
    text = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    path = tmp_path / "map.yaml"
    path.write_text(text.replace("state_dir: var/sim", 'state_dir: "st\\0x"'), encoding="utf-8")
    refused(cli("run", str(path), "--http-port", "0"), f"{path}:", "state_dir", "NUL")


def test_dry_run_refuses_a_capacity_too_small_to_model() -> None:
    recipe = str(ROOT / "recipes" / "capacity-test.yaml")
    refused(cli("dry-run", recipe, "--capacity-ah", "1e-300"), "--capacity-ah", "1e-300")


def test_dry_run_refuses_a_results_folder_that_takes_no_folder() -> None:
    recipe = str(ROOT / "recipes" / "capacity-test.yaml")
    refused(cli("dry-run", recipe, "--results", "/proc"), "--results", "/proc")


@pytest.mark.parametrize("kind", ["profile", "chadeche"])
def test_import_refuses_a_bad_recipe_name_and_a_missing_output_folder(kind: str) -> None:
    source = (
        str(ROOT / "tests" / "data" / "chadeche" / "figure10.txt")
        if kind == "chadeche"
        else str(ROOT / "tests" / "data" / "mutation_sources" / "profile.csv")
    )
    if not Path(source).exists():  # any valid load profile
        pytest.skip(f"{source} is not in the repository")
    refused(cli("import", kind, source, "--name", "bad name"), "--name 'bad name'")
    out = "/nonexistent/dir/x.yaml"
    refused(cli("import", kind, source, "-o", out), f"{out}: cannot write")


def test_check_into_a_pipe_closed_early_exits_quietly() -> None:
    recipes = sorted(str(p) for p in (ROOT / "recipes").glob("*.yaml"))
    proc = subprocess.run(
        f"{sys.executable} -m supervisor.cli.main check {' '.join(recipes)} | head -1",
        shell=True,
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
        executable="/bin/bash",
    )
    assert "Traceback" not in proc.stderr
    assert "BrokenPipeError" not in proc.stderr


def test_a_chadeche_sd_of_5000_leading_zeros_is_read_as_its_number(tmp_path: Path) -> None:
    zeros = "0" * 5000
    path = tmp_path / "sd.txt"
    path.write_text(
        "ADR\tC/D\tmA\tSD\tTL\tTH\tLmAh\tHmAh\tTRUE\tCTRLZ\tCOMMENT\n"
        f"1\tD\t0\t{zeros}60\tI\tI\tI\tI\tI\tS\t#Repos\n"
        f"{zeros}2\tD\t{zeros}0\t{zeros}\tI\tI\tI\tI\tI\t{zeros}1\t#fin\n",
        encoding="utf-8",
    )
    proc = cli("import", "chadeche", str(path))
    assert "Traceback" not in proc.stderr
    assert proc.returncode == 0, proc.stderr
    assert "duration: 60 s" in proc.stdout
