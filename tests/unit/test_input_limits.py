"""Input limits (README "Input limits", ``supervisor/config/limits.py``; issue 9): what a
file may hold, each refused with one message naming the file, the place of the first item
over the limit, and the limit.

Big files are refused by their size before anything is parsed: the tests generate them
(20 MB each, in ``tmp_path``; nothing that size is committed) and make the parser fail the
test if it is ever reached. The small over-limit files are in the corpora of
``tests/data`` (``too_many_cycles.yaml``, ``too_many_groups.yaml``,
``initial_charge_too_large.yaml``, ``chadeche/bad-too-many-rows.txt``), tested with the
other broken files; the ones whose count takes hundreds of kilobytes are made here.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

import supervisor.config.yamlpos as yamlpos
import supervisor.importers.chadeche as chadeche
from supervisor.chains.compiler import compile_recipe
from supervisor.cli.main import main
from supervisor.config.limits import (
    MAX_CYCLES,
    MAX_INITIAL_CHARGE_AH,
    MAX_IO_MAP_TAGS,
    MAX_PROFILE_CSV_BYTES,
    MAX_PROFILE_ROWS,
    MAX_RECIPE_GROUPS,
    MAX_RECIPE_STEPS,
    MAX_SEQUENCE_ROWS,
    MAX_TEXT_BYTES,
    MAX_YAML_BYTES,
    MAX_YAML_TEXT_CHARS,
    MAX_YAML_VALUES,
    RECIPE_COMPILE_TIMEOUT_S,
    size_text,
)
from supervisor.config.recipe import check_sizes, load_recipe, load_recipe_text
from supervisor.config.yamlpos import Positions
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.registry import load_bench
from supervisor.importers import import_chadeche

ROOT = Path(__file__).resolve().parents[2]
MB20 = 20 * 1000 * 1000
SEQUENCE_HEADER = "ADR\tC/D\tmA\tSD\tTL\tTH\tLmAh\tHmAh\tTRUE\tCTRLZ\tCOMMENT\n"
SEQUENCE_ROW = "{n}\tD\t0\t60\tI\tI\tI\tI\tI\tS\t#Repos\n"


def first_error(info: pytest.ExceptionInfo[ConfigErrors]) -> ConfigError:
    return info.value.errors[0]


@pytest.fixture
def never_parsed(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Fail the test if a YAML document or a Chadèche file is parsed at all."""

    def parsed(*args: object, **kw: object) -> None:
        raise AssertionError("parsed: the size limit should have refused the file first")

    monkeypatch.setattr(yamlpos, "_compose", parsed)
    monkeypatch.setattr(chadeche, "decode_text", parsed)
    yield


def write_lines(path: Path, head: str, line: str, until_bytes: int) -> int:
    """``head`` then ``line`` (formatted with ``n``) until the file holds ``until_bytes``;
    returns the number of lines written after ``head``."""
    n = 0
    size = len(head.encode())
    with path.open("w", encoding="utf-8", newline="\n") as f:
        f.write(head)
        while size < until_bytes:
            text = line.format(n=n + 1)
            f.write(text)
            size += len(text.encode())
            n += 1
    return n


def too_large(path: Path, what: str) -> str:
    return (
        f"file is too large: {path.stat().st_size:,} bytes; {what} may have at most 1 MiB"
        " (README: Input limits)"
    )


# --- big files: refused by their size, before anything is parsed -----------------------------
def test_a_20_mb_recipe_is_refused_by_its_size(tmp_path: Path, never_parsed: None) -> None:
    path = tmp_path / "big.yaml"
    steps = write_lines(path, "recipe: big\nsteps:\n", "  - {{id: s{n}, rest: 1 s}}\n", MB20)
    assert steps > 600_000
    with pytest.raises(ConfigErrors) as info:
        load_recipe(path)
    assert first_error(info).location_message() == (
        f"{path}: {too_large(path, 'a recipe or an I/O map')}"
    )


def test_a_recipe_that_is_one_20_mb_comment_is_refused_by_its_size(
    tmp_path: Path, never_parsed: None, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "comment.yaml"
    with path.open("w", encoding="utf-8") as f:
        f.write("# " + "x" * MB20 + "\n")
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err
    assert err == f"{path}: {too_large(path, 'a recipe or an I/O map')}\n"


def test_a_20_mb_io_map_with_327_000_tags_is_refused_by_its_size(
    tmp_path: Path, never_parsed: None
) -> None:
    path = tmp_path / "map.yaml"
    sim = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    head, _, rest = sim.partition("tags:\n")
    line = "  - {{name: t{n:06d}, device: adam, point: slot1.tc2, unit: degC}}\n"
    tags = write_lines(path, head + "tags:\n", line, MB20)
    with path.open("a", encoding="utf-8") as f:
        f.write(rest)
    assert tags > 300_000
    with pytest.raises(ConfigErrors) as info:
        load_bench(path)
    assert first_error(info).location_message() == (
        f"{path}: {too_large(path, 'a recipe or an I/O map')}"
    )


def test_a_20_mb_sequence_file_with_700_000_rows_is_refused_by_its_size(
    tmp_path: Path, never_parsed: None
) -> None:
    path = tmp_path / "seq.txt"
    rows = write_lines(path, SEQUENCE_HEADER, SEQUENCE_ROW, MB20)
    assert rows > 500_000
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    assert first_error(info).location_message() == f"{path}: {too_large(path, 'a Chadèche file')}"


# --- counts: refused at the first item over, before the model validates them ------------------
def test_a_recipe_of_10_001_steps_is_refused_at_the_first_step_over(tmp_path: Path) -> None:
    path = tmp_path / "steps.yaml"
    n = write_lines(
        path, "recipe: long\nsteps:\n", "  - {{id: s{n}, rest: 1 s}}\n", (MAX_RECIPE_STEPS + 1) * 30
    )
    assert n > MAX_RECIPE_STEPS
    with pytest.raises(ConfigErrors) as info:
        load_recipe(path)
    e = first_error(info)
    assert (e.line, e.col) == (2 + MAX_RECIPE_STEPS + 1, 5)  # the 10 001st step
    assert e.message == (
        f"too many steps: {n:,}; a recipe may have at most 10,000 (README: Input limits)"
    )


def test_steps_are_counted_once_yaml_aliases_are_expanded() -> None:
    aliases = ", ".join(["*s"] * MAX_RECIPE_STEPS)
    text = f"recipe: r\ndefs: &s {{id: a, rest: 1 s}}\nsteps: [*s, {aliases}]\n"
    with pytest.raises(ConfigErrors) as info:
        load_recipe_text(text, "aliases.yaml")
    assert first_error(info).message == (
        "too many steps: 10,001; a recipe may have at most 10,000 (README: Input limits)"
    )


def test_the_limits_themselves_are_accepted() -> None:
    pos = Positions()
    data = {
        "cycles": MAX_CYCLES,
        "steps": [{"profile": {"rows": [{}] * MAX_PROFILE_ROWS}}] * MAX_RECIPE_STEPS,
        "groups": [{}] * MAX_RECIPE_GROUPS,
    }
    check_sizes(data, pos, "limits.yaml")  # nothing refused


@pytest.mark.parametrize(
    ("key", "data", "message"),
    [
        (
            "cycles",
            {"cycles": MAX_CYCLES + 1},
            "cycles: 1,000,001 is too many; a recipe may run at most 1,000,000 cycles",
        ),
        (
            "steps",
            {"steps": [{}] * 10_001},
            "too many steps: 10,001; a recipe may have at most 10,000",
        ),
        (
            "groups",
            {"groups": [{}] * 1_001},
            "too many groups: 1,001; a recipe may have at most 1,000",
        ),
        (
            "rows",
            {"steps": [{}, {"profile": {"rows": [{}] * (MAX_PROFILE_ROWS + 1)}}]},
            "too many profile rows: 100,001; a profile may have at most 100,000",
        ),
    ],
)
def test_each_count_over_its_limit_is_refused(
    key: str, data: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigErrors) as info:
        check_sizes(data, Positions(), "r.yaml")
    assert first_error(info).message == f"{message} (README: Input limits)"


def test_inline_profile_rows_over_the_limit_are_refused() -> None:
    # 100 001 rows cannot fit in a 1 MiB file (a row takes 20 bytes), nor in 500 000 YAML
    # values: the row limit also holds for data validated without a file.
    text = "recipe: p\nsteps:\n  - id: p\n    profile:\n      rows:\n        - {t: 0, current: 1}\n"
    data, pos = yamlpos.load_yaml_text(text, "p.yaml")
    rows = data["steps"][0]["profile"]["rows"]
    rows *= MAX_PROFILE_ROWS + 1
    with pytest.raises(ConfigErrors) as info:
        check_sizes(data, pos, "p.yaml")
    assert first_error(info).message.startswith("too many profile rows: 100,001;")


def test_an_io_map_of_more_than_10_000_tags_is_refused_at_the_first_tag_over(
    tmp_path: Path,
) -> None:
    path = tmp_path / "map.yaml"
    sim = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")
    head, _, rest = sim.partition("tags:\n")
    line = "  - {{name: t{n:05d}, device: adam, point: slot1.tc2}}\n"
    extra = write_lines(path, head + "tags:\n", line, (MAX_IO_MAP_TAGS + 1) * len(line))
    with path.open("a", encoding="utf-8") as f:
        f.write(rest)
    total = extra + len(yaml.safe_load(sim)["tags"])
    with pytest.raises(ConfigErrors) as info:
        load_bench(path)
    e = first_error(info)
    first_tag_line = head.count("\n") + 2
    assert (e.line, e.col) == (first_tag_line + MAX_IO_MAP_TAGS, 5)  # the 10 001st tag
    assert e.message == (
        f"too many tags: {total:,}; an I/O map may have at most 10,000 (README: Input limits)"
    )


def test_a_sequence_file_of_2_001_rows_is_refused_and_2_000_are_read(tmp_path: Path) -> None:
    path = tmp_path / "seq.txt"
    body = "".join(SEQUENCE_ROW.format(n=n) for n in range(1, MAX_SEQUENCE_ROWS + 1))
    path.write_text(SEQUENCE_HEADER + body, encoding="utf-8")
    result = import_chadeche(path)  # within the limit: imported
    assert len(result.recipe["steps"]) >= MAX_SEQUENCE_ROWS
    path.write_text(
        SEQUENCE_HEADER + body + SEQUENCE_ROW.format(n=MAX_SEQUENCE_ROWS + 1), encoding="utf-8"
    )
    with pytest.raises(ConfigErrors) as info:
        import_chadeche(path)
    e = first_error(info)
    assert (e.line, e.col) == (MAX_SEQUENCE_ROWS + 2, 1)
    assert e.message == (
        "too many rows: 2,001; a sequence file may have at most 2,000 (README: Input limits)"
    )


# --- initial_charge: literal, a parameter, an override ------------------------------------------
INITIAL = (
    "recipe: r\nparameters: {{q0: 0.5 Ah}}\ninitial_charge: {q}\nsteps:\n  - {{id: a, rest: 1 h}}\n"
)


@pytest.mark.parametrize(
    ("written", "overrides"),
    [("1e300 Ah", {}), ("-200000 Ah", {}), ("q0", {"q0": "1e300 Ah"})],
    ids=["literal", "negative", "override"],
)
def test_an_initial_charge_beyond_100_kah_either_way_is_refused(
    written: str, overrides: dict[str, str]
) -> None:
    recipe, pos = load_recipe_text(INITIAL.format(q=written), "r.yaml")
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, "r.yaml", overrides=overrides)
    e = first_error(info)
    assert (e.line, e.col) == (3, 17)
    assert e.message.endswith(
        "Ah is too large; a recipe may start from at most 100,000 Ah either way"
        " (README: Input limits)"
    )


def test_an_initial_charge_within_the_limit_is_kept() -> None:
    recipe, pos = load_recipe_text(INITIAL.format(q="100000 Ah"), "r.yaml")
    assert compile_recipe(recipe, pos, "r.yaml").initial_charge_ah == 100_000.0


# --- the compiler's own cost ----------------------------------------------------------------
def test_every_duplicate_step_id_but_the_last_is_reported() -> None:
    text = (
        "recipe: r\nsteps:\n  - {id: a, rest: 1 s}\n  - {id: b, rest: 1 s}\n"
        "  - {id: a, rest: 1 s}\n  - {id: a, rest: 1 s}\n"
    )
    recipe, pos = load_recipe_text(text, "r.yaml")
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, pos, "r.yaml")
    dupes = [(e.line, e.message) for e in info.value.errors if "duplicate" in e.message]
    assert dupes == [(3, "duplicate step id 'a'"), (5, "duplicate step id 'a'")]


def test_the_readme_documents_every_limit_enforced_here() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Input limits", 1)[1].split("\n## ", 1)[0]
    for shown in (
        size_text(MAX_YAML_BYTES),
        f"{MAX_YAML_VALUES:,}",
        f"{MAX_YAML_TEXT_CHARS:,}",
        f"{MAX_RECIPE_STEPS:,}",
        f"{MAX_RECIPE_GROUPS:,}",
        f"{MAX_CYCLES:,}",
        f"{MAX_INITIAL_CHARGE_AH:,g} Ah",
        f"{MAX_PROFILE_ROWS:,}",
        size_text(MAX_PROFILE_CSV_BYTES),
        f"{MAX_IO_MAP_TAGS:,}",
        size_text(MAX_TEXT_BYTES),
        f"{MAX_SEQUENCE_ROWS:,}",
        f"{RECIPE_COMPILE_TIMEOUT_S:g} s",
    ):
        assert shown in section, shown
