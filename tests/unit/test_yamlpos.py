"""YAML loading with positions, and pydantic errors reported at file:line:col."""

from __future__ import annotations

import codecs
from pathlib import Path
from typing import Annotated, Literal

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ConfigDict, Field, model_validator

from supervisor.config.yamlpos import (
    Mark,
    Positions,
    format_validation_error,
    load_yaml,
    load_yaml_text,
    validate,
)
from supervisor.core.errors import ConfigError, ConfigErrors

# --------------------------------------------------------------------------------------------
# Small models shaped like the real configuration


class Scan(BaseModel):
    model_config = ConfigDict(extra="forbid")
    period_s: float = Field(gt=0)
    watchdog_s: float = 5.0


class Board(BaseModel):
    model_config = ConfigDict(extra="forbid")
    address: int
    name: str


class ModbusDevice(BaseModel):
    model_config = ConfigDict(extra="forbid")
    driver: Literal["modbus"]
    host: str
    port: int = 502


class ChadecheDevice(BaseModel):
    model_config = ConfigDict(extra="forbid")
    driver: Literal["chadeche"]
    boards: list[Board]


Device = Annotated[ModbusDevice | ChadecheDevice, Field(discriminator="driver")]


class Window(BaseModel):
    model_config = ConfigDict(extra="forbid")
    start_s: float
    end_s: float

    @model_validator(mode="after")
    def _end_after_start(self) -> Window:
        if self.end_s <= self.start_s:
            raise ValueError("end_s must be after start_s")
        return self


class Bench(BaseModel):
    model_config = ConfigDict(extra="forbid")
    scan: Scan
    devices: dict[str, Device]
    windows: list[Window] = []
    serial_number: str = Field("unknown", alias="serial-number")


GOOD = """\
scan:
  period_s: 0.5
devices:
  plc:
    driver: modbus
    host: 10.0.0.2
  chadeche:
    driver: chadeche
    boards:
      - address: 1
        name: b1
      - address: 2
        name: b2
      - address: 3
        name: b3
"""

FILE = "bench.yaml"


def errors_of(text: str, model: type[BaseModel] = Bench) -> list[ConfigError]:
    data, positions = load_yaml_text(text, FILE)
    with pytest.raises(ConfigErrors) as info:
        validate(model, data, positions, FILE)
    return info.value.errors


def single_error(text: str, model: type[BaseModel] = Bench) -> ConfigError:
    errors = errors_of(text, model)
    assert len(errors) == 1, [e.location_message() for e in errors]
    return errors[0]


def load_error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_yaml_text(text, FILE)
    return info.value


def at(error: ConfigError) -> tuple[str | None, int | None, int | None]:
    return error.file, error.line, error.col


# --------------------------------------------------------------------------------------------
# Loading


def test_valid_document_loads_into_plain_data_and_validates() -> None:
    data, positions = load_yaml_text(GOOD, FILE)
    bench = validate(Bench, data, positions, FILE)
    assert bench.scan.period_s == 0.5
    assert isinstance(bench.devices["chadeche"], ChadecheDevice)
    assert [b.address for b in bench.devices["chadeche"].boards] == [1, 2, 3]


def test_positions_give_one_based_key_and_value_marks_for_every_node() -> None:
    _, positions = load_yaml_text(GOOD, FILE)
    assert positions.key(("scan", "period_s")) == Mark(2, 3)
    assert positions.value(("scan", "period_s")) == Mark(2, 13)
    assert positions.value(("devices", "chadeche", "boards", 2)) == Mark(14, 9)
    assert positions.key(("devices", "chadeche", "boards", 2, "name")) == Mark(15, 9)
    assert positions.value(("devices", "chadeche", "boards", 2, "name")) == Mark(15, 15)
    assert positions.value(()) == Mark(1, 1)


def test_positions_of_list_items_have_no_key_and_unknown_paths_have_no_position() -> None:
    _, positions = load_yaml_text(GOOD, FILE)
    assert positions.key(("devices", "chadeche", "boards", 0)) is None
    assert positions.key(()) is None
    assert positions.value(("devices", "nope")) is None
    assert positions.value(("devices", "chadeche", "boards", 7)) is None
    assert positions.value(("scan", "period_s", "deeper")) is None


def test_nearest_falls_back_to_the_deepest_existing_prefix_then_to_1_1() -> None:
    _, positions = load_yaml_text(GOOD, FILE)
    assert positions.nearest(("devices", "plc", "nope", 3)) == Mark(5, 5)
    assert positions.nearest(("scan", "period_s")) == Mark(2, 13)
    assert Positions().nearest(("anything",)) == Mark(1, 1)


def test_only_plain_data_types_come_out_and_timestamps_stay_strings() -> None:
    text = "a: 1\nb: 1.5\nc: true\nd: ~\ne: text\nf: 2024-01-31\ng: [1, two]\nh: {k: v}\n"
    data, _ = load_yaml_text(text)
    assert data == {
        "a": 1,
        "b": 1.5,
        "c": True,
        "d": None,
        "e": "text",
        "f": "2024-01-31",
        "g": [1, "two"],
        "h": {"k": "v"},
    }


def test_anchors_aliases_and_merge_keys_work_and_point_at_their_definition() -> None:
    text = "base: &base\n  period_s: 1\n  watchdog_s: 2\nscan:\n  <<: *base\n  period_s: 3\n"
    data, positions = load_yaml_text(text)
    assert data["scan"] == {"period_s": 3, "watchdog_s": 2}
    assert positions.value(("scan", "period_s")) == Mark(6, 13)
    assert positions.key(("scan", "watchdog_s")) == Mark(3, 3)


def test_a_recursive_alias_is_refused_at_the_anchored_node() -> None:
    error = load_error("a: &x\n  - *x\n")
    assert at(error) == (FILE, 1, 4)
    assert "recursive alias" in error.message


def test_utf8_byte_order_mark_is_accepted_and_does_not_shift_columns(tmp_path: Path) -> None:
    path = tmp_path / "bom.yaml"
    path.write_bytes(b"\xef\xbb\xbfscan: {period_s: 1}\n")
    data, positions = load_yaml(path)
    assert data == {"scan": {"period_s": 1}}
    assert positions.key(("scan",)) == Mark(1, 1)
    assert positions.value(("scan", "period_s")) == Mark(1, 18)


# --------------------------------------------------------------------------------------------
# Errors found while loading


def test_duplicate_key_is_an_error_at_the_second_key_naming_the_first_line() -> None:
    error = load_error("scan:\n  period_s: 1\n  watchdog_s: 2\n  period_s: 3\n")
    assert at(error) == (FILE, 4, 3)
    assert error.message == "duplicate key 'period_s' (first defined at line 2)"


def test_yaml_syntax_error_from_bad_indentation_names_the_line_and_column() -> None:
    error = load_error("scan:\n  period_s: 1\n watchdog_s: 2\n")
    assert at(error) == (FILE, 3, 2)
    assert error.message.startswith("YAML syntax error: expected <block end>")
    assert "line 1, column 1" in error.message  # where the enclosing mapping started


def test_tab_used_for_indentation_is_a_syntax_error_that_says_so() -> None:
    error = load_error("scan:\n\tperiod_s: 1\n")
    assert at(error) == (FILE, 2, 1)
    assert "'\\t'" in error.message
    assert "tabs are not allowed" in error.message


def test_invalid_utf8_byte_reports_its_line_and_character_column(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes(b"scan:\n  name: " + "\u00e9t\u00e9 caf".encode() + b"\xe9\n")
    with pytest.raises(ConfigError) as info:
        load_yaml(path)
    error = info.value
    # "  name: été caf" is 15 characters (18 bytes): the bad byte is character 16.
    assert at(error) == (str(path), 2, 16)
    assert "0xe9" in error.message
    assert "must be UTF-8" in error.message


def test_a_utf16_file_is_refused_at_1_1_naming_its_encoding(tmp_path: Path) -> None:
    path = tmp_path / "unicode.yaml"
    path.write_bytes(codecs.BOM_UTF16_LE + "scan: {period_s: 1}\n".encode("utf-16-le"))
    with pytest.raises(ConfigError) as info:
        load_yaml(path)
    assert at(info.value) == (str(path), 1, 1)
    assert "UTF-16" in info.value.message
    assert "must be UTF-8" in info.value.message


def test_crlf_and_cr_line_ends_give_the_same_positions_as_lf(tmp_path: Path) -> None:
    for newline in ("\r\n", "\r"):
        path = tmp_path / "crlf.yaml"
        path.write_bytes(f"scan:{newline}  period_s: 1{newline}  perod_s: 2{newline}".encode())
        data, positions = load_yaml(path)
        assert data == {"scan": {"period_s": 1, "perod_s": 2}}
        assert positions.key(("scan", "perod_s")) == Mark(3, 3)
        path.write_bytes(f"scan:{newline}  name: caf".encode() + b"\xe9" + newline.encode())
        with pytest.raises(ConfigError) as info:
            load_yaml(path)
        assert at(info.value) == (str(path), 2, 12)


def test_empty_file_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "empty.yaml"
    path.write_bytes(b"")
    with pytest.raises(ConfigError) as info:
        load_yaml(path)
    assert info.value.file == str(path)
    assert info.value.message == "file is empty"


def test_comment_only_file_counts_as_empty() -> None:
    assert load_error("# nothing here\n\n").message.startswith("file is empty")


def test_missing_file_is_an_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError) as info:
        load_yaml(path)
    assert info.value.file == str(path)
    assert info.value.message == "file not found"
    assert str(path) in str(info.value)


def test_directory_instead_of_file_is_an_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load_yaml(tmp_path)
    assert info.value.file == str(tmp_path)


def test_python_object_tag_is_refused_at_the_tagged_node() -> None:
    error = load_error("scan:\n  period_s: !!python/object:os.system {}\n")
    assert at(error) == (FILE, 2, 13)
    assert "unsupported YAML tag '!!python/object:os.system'" in error.message


def test_custom_local_tag_is_refused_at_the_tagged_node() -> None:
    error = load_error("- !secret password\n")
    assert at(error) == (FILE, 1, 3)
    assert "unsupported YAML tag '!secret'" in error.message


def test_explicit_scalar_tag_with_an_impossible_value_is_an_error() -> None:
    error = load_error("port: !!int fifty\n")
    assert at(error) == (FILE, 1, 7)
    assert error.message == "invalid integer value 'fifty'"


def test_several_documents_in_one_file_are_refused() -> None:
    error = load_error("a: 1\n---\nb: 2\n")
    assert at(error) == (FILE, 2, 1)
    assert "single document" in error.message


def test_control_characters_are_refused_with_their_position() -> None:
    error = load_error("a: 1\nb: x\x07y\n")
    assert at(error) == (FILE, 2, 5)
    assert "U+0007" in error.message


# --------------------------------------------------------------------------------------------
# Validation errors mapped to positions


def test_unknown_key_error_points_at_the_key_and_suggests_the_nearest_name() -> None:
    error = single_error(GOOD.replace("  period_s: 0.5", "  period_s: 0.5\n  perod_s: 1"))
    assert at(error) == (FILE, 3, 3)
    assert error.message == (
        "unknown key 'perod_s' in scan (did you mean 'period_s'? "
        "expected one of: period_s, watchdog_s)"
    )


def test_unknown_key_inside_a_discriminated_union_lists_that_members_fields() -> None:
    error = single_error(GOOD.replace("    host: 10.0.0.2", "    host: 10.0.0.2\n    prot: 503"))
    assert at(error) == (FILE, 7, 5)
    assert error.message == (
        "unknown key 'prot' in devices.plc (did you mean 'port'? "
        "expected one of: driver, host, port)"
    )


def test_unknown_key_without_a_close_match_lists_the_expected_keys_only() -> None:
    error = single_error(GOOD + "colour: blue\n")
    assert at(error) == (FILE, 16, 1)
    assert error.message == (
        "unknown key 'colour' at the top level "
        "(expected one of: scan, devices, windows, serial-number)"
    )


def test_missing_key_error_points_at_the_parent_mapping() -> None:
    error = single_error(GOOD.replace("    host: 10.0.0.2\n", ""))
    assert at(error) == (FILE, 5, 5)
    assert error.message == "missing required key 'host' in devices.plc"


def test_misspelled_key_in_a_list_item_gives_an_unknown_and_a_missing_error_in_order() -> None:
    errors = errors_of(GOOD.replace("      - address: 3", "      - adress: 3"))
    assert [at(e) for e in errors] == [(FILE, 14, 9), (FILE, 14, 9)]
    messages = sorted(e.message for e in errors)
    assert messages == [
        "missing required key 'address' in devices.chadeche.boards[2]",
        "unknown key 'adress' in devices.chadeche.boards[2] (did you mean 'address'? "
        "expected one of: address, name)",
    ]


def test_wrong_type_error_points_at_the_value_and_shows_what_was_received() -> None:
    error = single_error(GOOD.replace("address: 2", "address: two"))
    assert at(error) == (FILE, 12, 18)
    assert error.message.startswith("devices.chadeche.boards[1].address: Input should be")
    assert error.message.endswith("(received 'two')")


def test_mapping_where_a_list_is_expected_says_a_mapping_was_received() -> None:
    error = single_error("scan: {period_s: 1}\ndevices: {}\nwindows: {a: 1}\n")
    assert at(error) == (FILE, 3, 10)
    assert error.message == "windows: Input should be a valid list (received a mapping)"


def test_out_of_range_value_error_points_at_the_value() -> None:
    error = single_error(GOOD.replace("period_s: 0.5", "period_s: -1"))
    assert at(error) == (FILE, 2, 13)
    assert error.message == "scan.period_s: Input should be greater than 0 (received -1)"


def test_field_alias_is_the_key_named_in_errors() -> None:
    error = single_error(GOOD + "serial-number: [1, 2]\n")
    assert at(error) == (FILE, 16, 16)
    assert error.message == "serial-number: Input should be a valid string (received a list)"


def test_validator_value_error_comes_out_with_its_own_message_at_the_model() -> None:
    error = single_error(
        GOOD + "windows:\n  - {start_s: 0, end_s: 10}\n  - start_s: 5\n    end_s: 1\n"
    )
    assert at(error) == (FILE, 18, 5)
    assert error.message == "windows[1]: end_s must be after start_s"


def test_unknown_discriminator_value_points_at_the_tag_value() -> None:
    error = single_error(GOOD.replace("driver: modbus", "driver: profibus"))
    assert at(error) == (FILE, 5, 13)
    assert error.message.startswith("devices.plc.driver: unknown value 'profibus'")
    assert "'modbus', 'chadeche'" in error.message


def test_missing_discriminator_is_reported_as_a_missing_key_with_the_choices() -> None:
    error = single_error(GOOD.replace("    driver: modbus\n", ""))
    assert at(error) == (FILE, 5, 5)
    assert error.message == (
        "missing required key 'driver' in devices.plc (expected one of: 'modbus', 'chadeche')"
    )


def test_missing_top_level_key_points_at_the_document_start() -> None:
    error = single_error("devices: {}\n")
    assert at(error) == (FILE, 1, 1)
    assert error.message == "missing required key 'scan' at the top level"


def test_all_errors_are_reported_sorted_by_line_then_column() -> None:
    text = (
        GOOD.replace("period_s: 0.5", "period_s: 0")
        .replace("address: 1", "address: one")
        .replace("    host: 10.0.0.2\n", "")
    )
    errors = errors_of(text)
    assert [(e.line, e.col) for e in errors] == [(2, 13), (5, 5), (9, 18)]
    assert all(e.file == FILE for e in errors)


def test_format_validation_error_works_from_a_caught_pydantic_error() -> None:
    from pydantic import ValidationError

    data, positions = load_yaml_text("scan: {period_s: 1, perod: 2}\ndevices: {}\n", FILE)
    with pytest.raises(ValidationError) as info:
        Bench.model_validate(data)
    plain = format_validation_error(info.value, positions, FILE)
    assert [(e.line, e.col, e.message) for e in plain.errors] == [
        (1, 21, "unknown key 'perod' in scan")
    ]
    helped = format_validation_error(info.value, positions, FILE, model=Bench)
    assert "did you mean 'period_s'?" in helped.errors[0].message
    assert str(helped) == helped.errors[0].location_message()


# --------------------------------------------------------------------------------------------
# Robustness

YAMLISH = st.text(alphabet=st.sampled_from(list("ab01 :-#&*!|>'\"[]{},?%@`\t\n\r.~=<\\_xé\x00")))


@settings(max_examples=400, deadline=None)
@given(st.one_of(st.text(), YAMLISH))
@example("!!int ")  # PyYAML itself raises IndexError constructing this
@example("x: 0x_")  # ... and ValueError for this implicit "int"
@example("d: 2024-13-45")  # ... and for this impossible timestamp
@example("e: =")  # ... and ConstructorError for the YAML 1.1 value key
@example("[" * 5000)
def test_any_text_either_loads_or_raises_config_error(text: str) -> None:
    try:
        load_yaml_text(text, FILE)
    except ConfigError as error:
        assert error.file == FILE
        assert error.line is None or error.line >= 1
        assert error.col is None or error.col >= 1


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_any_bytes_on_disk_either_load_or_raise_config_error(
    tmp_path_factory: pytest.TempPathFactory, raw: bytes
) -> None:
    path = tmp_path_factory.mktemp("bytes") / "random.yaml"
    path.write_bytes(raw)
    try:
        load_yaml(path)
    except ConfigError as error:
        assert error.file == str(path)
