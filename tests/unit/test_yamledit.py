"""Editing YAML text in place: only the values concerned change, every comment and layout
choice of the engineer's file stays (what ``supervisor calibrate`` needs, seed 000 §III.F)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from supervisor.config.yamledit import YamlText, flow_mapping, yaml_float, yaml_scalar
from supervisor.config.yamlpos import load_yaml_text
from supervisor.core.errors import ConfigError

FILE = "map.yaml"

BLOCK = """\
# comments everywhere
board:   # the board
  address: 0
  cal:
    slope: 0.9851   # -1
    # offsets below
    offset: 0.0  # -2
  sim: {model: nimh-aa}
"""


def edit(text: str) -> YamlText:
    return YamlText(text, FILE)


# --------------------------------------------------------------------------------------------
# Setting scalars


def test_setting_an_existing_scalar_replaces_only_its_text() -> None:
    doc = edit(BLOCK)
    doc.set_scalars(("board", "cal"), {"offset": "-0.25"})
    assert doc.edited() == BLOCK.replace("offset: 0.0  # -2", "offset: -0.25  # -2")


def test_missing_keys_go_after_the_last_entry_of_a_block_mapping_at_its_indent() -> None:
    doc = edit(BLOCK)
    doc.set_scalars(("board", "cal"), {"slope": "1.0", "gain": "2.0", "zero": "0.5"})
    assert doc.edited() == BLOCK.replace("0.9851", "1.0").replace(
        "    offset: 0.0  # -2\n", "    offset: 0.0  # -2\n    gain: 2.0\n    zero: 0.5\n"
    )


def test_missing_keys_go_before_the_closing_brace_of_a_flow_mapping() -> None:
    doc = edit("sim: {model: nimh-aa}   # keep\n")
    doc.set_scalars(("sim",), {"soc": "0.5"})
    assert doc.edited() == "sim: {model: nimh-aa, soc: 0.5}   # keep\n"


def test_keys_go_inside_the_braces_of_an_empty_flow_mapping() -> None:
    doc = edit("cal: {}  # none yet\n")
    doc.set_scalars(("cal",), {"a": "1.0", "b": "2.0"})
    assert doc.edited() == "cal: {a: 1.0, b: 2.0}  # none yet\n"


def test_a_path_goes_through_mapping_keys_and_list_indexes() -> None:
    text = "boards:\n  - {address: 0, x: 1}\n  - address: 1\n    x: 1\n"
    doc = edit(text)
    doc.set_scalars(("boards", 1), {"x": "2"})
    assert doc.edited() == text.replace("    x: 1", "    x: 2")


def test_an_anchor_or_tag_before_a_scalar_is_kept() -> None:
    doc = edit("a: &one !!float 1.0  # x\n")
    doc.set_scalars((), {"a": "2.0"})
    assert doc.edited() == "a: &one !!float 2.0  # x\n"


def test_a_value_that_is_not_a_scalar_or_is_shared_is_refused_at_its_position() -> None:
    doc = edit("base: &b 1.0\nm:\n  x: [1, 2]\n  y: *b\n")
    with pytest.raises(ConfigError) as info:
        doc.set_scalars(("m",), {"x": "3"})
    assert (info.value.file, info.value.line, info.value.col) == (FILE, 3, 6)
    assert "x is not a plain scalar" in info.value.message
    with pytest.raises(ConfigError, match="y is not a plain scalar"):
        doc.set_scalars(("m",), {"y": "3"})
    base = doc.node(("base",))
    assert base is not None and doc.shared(base)


def test_a_null_becomes_the_new_value_and_an_empty_value_gets_its_space() -> None:
    doc = edit("a: ~\nb:\nc: &keep ~\n")
    doc.set_scalar(("a",), "{x: 1}")
    doc.set_scalar(("b",), "{y: 2}")
    doc.set_scalar(("c",), "{z: 3}")
    assert doc.edited() == "a: {x: 1}\nb: {y: 2}\nc: &keep {z: 3}\n"


# --------------------------------------------------------------------------------------------
# Adding a mapping after a key


def test_a_new_mapping_goes_on_the_line_after_the_given_key_at_its_indent() -> None:
    doc = edit(BLOCK)
    doc.add_mapping(("board",), "limits", {"v_max": "1.9"}, after="address")
    assert doc.edited() == BLOCK.replace("  address: 0\n", "  address: 0\n  limits: {v_max: 1.9}\n")


def test_a_new_mapping_goes_right_after_the_given_key_in_a_flow_mapping() -> None:
    doc = edit("- {address: 1, sim: {model: nimh-aa}}\n")
    doc.add_mapping((0,), "cal", {"a": "1.0"}, after="address")
    assert doc.edited() == "- {address: 1, cal: {a: 1.0}, sim: {model: nimh-aa}}\n"


def test_a_last_line_without_a_line_break_gets_one_before_the_new_line() -> None:
    doc = edit("board:\n  address: 0")
    doc.add_mapping(("board",), "cal", {"a": "1.0"}, after="address")
    assert doc.edited() == "board:\n  address: 0\n  cal: {a: 1.0}\n"


@pytest.mark.parametrize("newline", ["\r\n", "\r"], ids=["crlf", "cr"])
def test_new_lines_use_the_files_own_line_ends(newline: str) -> None:
    text = BLOCK.replace("\n", newline)
    doc = edit(text)
    doc.set_scalars(("board", "cal"), {"gain": "2.0"})
    doc.add_mapping(("board",), "limits", {"v_max": "1.9"}, after="address")
    new = doc.edited()
    assert new == BLOCK.replace(
        "    offset: 0.0  # -2\n", "    offset: 0.0  # -2\n    gain: 2.0\n"
    ).replace("  address: 0\n", "  address: 0\n  limits: {v_max: 1.9}\n").replace("\n", newline)
    assert load_yaml_text(new)[0]["board"]["cal"]["gain"] == 2.0


def test_edits_refer_to_the_original_text_and_are_applied_together() -> None:
    doc = edit(BLOCK)
    doc.set_scalars(("board", "cal"), {"slope": "1.5"})
    doc.add_mapping(("board",), "limits", {"v_max": "1.9"}, after="address")
    assert doc.text == BLOCK
    data, _ = load_yaml_text(doc.edited())
    assert data["board"]["cal"]["slope"] == 1.5
    assert data["board"]["limits"] == {"v_max": 1.9}


def test_a_document_that_does_not_load_is_refused_like_any_configuration_file() -> None:
    with pytest.raises(ConfigError) as info:
        edit("a: 1\na: 2\n")
    assert (info.value.file, info.value.line, info.value.col) == (FILE, 2, 1)
    assert "duplicate key 'a'" in info.value.message


# --------------------------------------------------------------------------------------------
# Writing values


def test_a_flow_mapping_is_written_from_keys_and_value_texts() -> None:
    assert flow_mapping({"a": yaml_float(1e-05), "b": yaml_scalar("20:00")}) == (
        '{a: 0.00001, b: "20:00"}'
    )


@given(st.text(alphabet=st.characters(codec="utf-8"), max_size=30))
def test_any_string_is_written_as_a_yaml_scalar_that_reads_back_the_same(text: str) -> None:
    assert load_yaml_text(f"k: {yaml_scalar(text)}\n")[0] == {"k": text}
    assert load_yaml_text(f"{yaml_scalar(text, key=True)}: v\n")[0] == {text: "v"}


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_any_finite_float_is_written_as_a_yaml_float_that_reads_back_exactly(x: float) -> None:
    assert load_yaml_text(f"k: {yaml_float(x)}\n")[0] == {"k": x}
