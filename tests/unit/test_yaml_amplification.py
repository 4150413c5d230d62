"""YAML that amplifies, and YAML 1.1 readings that surprise (issue 28, findings 2, 3, 10).

An alias repeats its whole anchored node each time it is used and a merge key (``<<: *a``)
its whole mapping: a small file can stand for gigabytes of data or megabytes of conditions
to compile. The loader counts what the document holds *while* it is built, aliases and
merge keys expanded, values and characters of text, and refuses it at the place where it
passes a limit (README "Input limits"). The tests assert on what was built (counters), not
on time.
"""

from __future__ import annotations

import pytest

import supervisor.chains.compiler as compiler_module
from supervisor.chains.compiler import compile_recipe
from supervisor.config.limits import MAX_YAML_TEXT_CHARS, MAX_YAML_VALUES, TooLarge
from supervisor.config.recipe import load_recipe_text
from supervisor.config.yamlpos import _Builder, _compose, load_yaml_text
from supervisor.core.errors import ConfigError, ConfigErrors

FILE = "amp.yaml"
TERM = "voltage >= 5 V"
HEAD = "recipe: r\ncapacity: 2000 mAh\nlimits: {voltage: [0.8 V, 1.9 V]}\ncycles: 1\nsteps:\n"


def big_condition(chars: int) -> str:
    return " or ".join([TERM] * (chars // (len(TERM) + 4)))


def anchored_condition_recipe(steps: int, condition: str) -> str:
    """The issue's file: a condition anchored in the first step's ``until``, aliased by
    every other step's (an explicit key ``?``: an implicit one is at most 1024 characters)."""
    text = HEAD
    for i in range(steps):
        key = f'&c "{condition}"' if i == 0 else "*c"
        text += f"  - id: s{i}\n    rest: 1 s\n    until:\n      - ? {key}\n        : next\n"
    return text + "  - {id: done, end: true}\n"


def built_until_refused(text: str) -> tuple[_Builder, TooLarge]:
    root = _compose(text)
    assert root is not None
    builder = _Builder(FILE)
    with pytest.raises(TooLarge) as info:
        builder.build(root)
    return builder, info.value


def load_error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_yaml_text(text, FILE)
    error = info.value
    return error.errors[0] if isinstance(error, ConfigErrors) else error


# --- finding 2: aliases amplify expressions --------------------------------------------------
def test_a_100_kb_condition_anchored_once_and_used_by_100_steps_is_refused_as_too_much_text() -> (
    None
):
    text = anchored_condition_recipe(100, big_condition(100_000))
    assert len(text) < 110_000  # the file itself is small: its aliases are what is large
    with pytest.raises(ConfigErrors) as info:
        load_recipe_text(text, FILE)
    [error] = info.value.errors
    assert isinstance(error, TooLarge)
    assert "document is too large" in error.message
    assert f"more than {MAX_YAML_TEXT_CHARS:,} characters of text" in error.message
    assert "aliases" in error.message and "(README: Input limits)" in error.message
    # Located at the use of the alias that passes the limit: the 11th step's `until` item
    # (10 uses of 100 kB make 1 MB; the 11th is over).
    assert (error.file, error.line, error.col) == (FILE, 6 + 10 * 5 + 3, 9)


def test_the_text_is_refused_while_built_not_after() -> None:
    builder, _ = built_until_refused(anchored_condition_recipe(1000, big_condition(100_000)))
    # Stopped at the first node over the limit: at most one condition beyond it was counted.
    assert MAX_YAML_TEXT_CHARS < builder.chars <= MAX_YAML_TEXT_CHARS + 100_000


def test_an_anchored_condition_used_by_many_steps_is_compiled_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    compiled: list[str] = []
    real = compiler_module.compile_condition

    def counting(text: str, sig: object) -> object:
        compiled.append(text)
        return real(text, sig)  # type: ignore[arg-type]

    monkeypatch.setattr(compiler_module, "compile_condition", counting)
    condition = big_condition(20_000)
    recipe, positions = load_recipe_text(anchored_condition_recipe(20, condition), FILE)
    program = compile_recipe(recipe, positions, FILE)
    assert compiled.count(condition) == 1
    conditions = [step.transitions[0].condition for step in program.steps[:20]]
    assert all(c is conditions[0] for c in conditions)  # one compiled expression, shared


def test_a_shared_condition_that_is_wrong_is_reported_at_every_step_that_uses_it() -> None:
    text = anchored_condition_recipe(3, "voltage >= 5 A")
    recipe, positions = load_recipe_text(text, FILE)
    with pytest.raises(ConfigErrors) as info:
        compile_recipe(recipe, positions, FILE)
    wrong = [e for e in info.value.errors if "voltage >= 5 A" in e.message]
    # One error per step that uses it, as when each was compiled on its own: the same
    # message, at the faulty part of the anchored text (PyYAML's node graph gives an alias
    # no place of its own: every use is the anchored node).
    assert len(wrong) == 3
    assert len({e.message for e in wrong}) == 1
    assert {(e.line, e.col) for e in wrong} == {(9, 19)}


def test_an_anchored_condition_used_within_the_limit_is_accepted() -> None:
    recipe, positions = load_recipe_text(anchored_condition_recipe(5, big_condition(50_000)), FILE)
    assert len(compile_recipe(recipe, positions, FILE).steps) == 6


# --- finding 3: merge keys amplify mappings ---------------------------------------------------
def merge_bomb(keys: int, merges: int) -> str:
    mapping = ", ".join(f"k{i}: {i}" for i in range(keys))
    return f"recipe: r\ndefs: &a {{{mapping}}}\nsteps:\n" + "- {<<: *a}\n" * merges


def test_50000_merges_of_a_2000_key_mapping_are_refused_before_building_more_than_the_limit() -> (
    None
):
    builder, error = built_until_refused(merge_bomb(2000, 50_000))
    assert "document is too large" in error.message
    # Refused at a `<<` of the list (line 4 is the first), after a few dozen merges: what
    # was built stays within the limits plus one merged mapping.
    assert error.file == FILE and error.line > 4 and error.col == 4
    assert builder.values <= MAX_YAML_VALUES + 2 * 2000 + 1
    assert builder.chars <= MAX_YAML_TEXT_CHARS + 2 * 2000 * 10
    merged = [m for m in builder.mappings.values() if len(m) == 2000]
    assert len(merged) < 200  # the anchor and the merges done before the refusal


def test_merges_of_a_mapping_of_short_keys_are_refused_by_their_count_of_values() -> None:
    letters = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWX"  # one character a key
    mapping = ", ".join(f"{k}: ~" for k in letters)
    text = f"defs: &a {{{mapping}}}\nlist:\n" + "- {<<: *a}\n" * 20_000
    builder, error = built_until_refused(text)
    assert f"more than {MAX_YAML_VALUES:,} values once its aliases and merge keys" in (
        error.message
    )
    assert builder.values <= MAX_YAML_VALUES + 2 * len(letters) + 1


def test_200000_merge_aliases_in_one_merge_key_are_refused_at_the_merge_key() -> None:
    text = "recipe: r\ndefs: &a {id: a, rest: 1 s}\nsteps:\n- {<<: [" + ", ".join(["*a"] * 200_000)
    builder, error = built_until_refused(text + "]}\n")
    assert (error.file, error.line, error.col) == (FILE, 4, 4)
    assert builder.values <= MAX_YAML_VALUES + 4


def test_a_few_merge_keys_still_work() -> None:
    data, _ = load_yaml_text("a: &a {x: 1, y: 2}\nb: {<<: *a, y: 3}\nc: {<<: [*a, {z: 4}]}\n")
    assert data["b"] == {"x": 1, "y": 3}
    assert data["c"] == {"x": 1, "y": 2, "z": 4}


# --- finding 10: YAML 1.1 numbers -------------------------------------------------------------
def test_a_number_with_a_leading_zero_is_refused_instead_of_read_as_octal() -> None:
    error = load_error("recipe: r\ncycles: 010\n")
    assert (error.file, error.line, error.col) == (FILE, 2, 9)
    assert "leading zero, which YAML 1.1 reads as octal (8)" in error.message
    assert "write 10 without the leading zero" in error.message


def test_a_base_60_number_is_refused_instead_of_read_as_minutes() -> None:
    error = load_error("recipe: r\ncycles: 1:30\n")
    assert (error.file, error.line, error.col) == (FILE, 2, 9)
    assert "1:30 is a base-60 number in YAML 1.1 (90)" in error.message
    assert "quote it ('1:30')" in error.message


def test_numbers_that_say_what_they_are_stay_numbers() -> None:
    data, _ = load_yaml_text("a: 0\nb: 0x1F\nc: 1_000\nd: -12\ne: 0.5\nf: '010'\ng: 08:00\n")
    assert data == {"a": 0, "b": 31, "c": 1000, "d": -12, "e": 0.5, "f": "010", "g": "08:00"}


# --- lone surrogates ------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('recipe: r\ndescription: "a\\ud800b"\n', (2, 14)),
        ('recipe: r\n"\\udfff": 1\n', (2, 1)),
        ('recipe: r\ndescription: "\\ud83d\\ude00"\n', (2, 14)),
    ],
)
def test_a_string_with_a_lone_surrogate_is_refused_where_it_is_written(
    text: str, where: tuple[int, int]
) -> None:
    error = load_error(text)
    assert (error.line, error.col) == where
    assert "a string that cannot be encoded as UTF-8" in error.message


def test_a_character_above_the_basic_plane_written_as_one_escape_is_accepted() -> None:
    data, _ = load_yaml_text('description: "\\U0001F600"\n')
    assert data["description"].encode("utf-8") == "\U0001f600".encode()
