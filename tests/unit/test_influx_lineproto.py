"""Line protocol as the InfluxDB writer builds it: the schema (measurements, tag keys,
fields), the value types (analog always float), the acquisition timestamp in ns, and an
escaping that a line-protocol parser reads back for any text (hypothesis)."""

from __future__ import annotations

from hypothesis import assume, given, settings
from hypothesis import strategies as st
from influxrig import parse_line

from supervisor.core.quality import Quality
from supervisor.core.records import BenchEvent
from supervisor.publish.changes import Sample
from supervisor.publish.influx.lineproto import (
    LineEncoder,
    escape_field_key,
    escape_measurement,
    escape_string,
    escape_tag,
    line_measurement,
    timestamp_ns,
)

WALL = 1_760_000_000.123456


def encoder(channels: tuple[str, ...] = ("ch0", "ch1"), types: dict[str, str] | None = None):  # type: ignore[no-untyped-def]
    known = types or {}
    return LineEncoder("b1", channels, lambda name: known.get(name))


def sample(name: str, value: object, wall: float = WALL, quality: Quality = Quality.GOOD) -> Sample:
    return Sample(name, value, quality, 0.0, wall)  # type: ignore[arg-type]


# --- the schema ------------------------------------------------------------------------------
def test_a_channel_tag_is_a_field_of_the_channel_measurement_tagged_with_its_test() -> None:
    lines = encoder().encode(
        [sample("ch0.voltage", 1.25), sample("ch0.chain.state", "Running")],
        {"ch0": ("T-0001", "nimh charge")},
    )
    (line,) = lines["channel"]
    m, tags, fields, ts = parse_line(line)
    assert m == "channel"
    assert tags == {"bench": "b1", "channel": "ch0", "test_id": "T-0001", "recipe": "nimh charge"}
    assert fields == {"voltage": 1.25, "chain_state": "Running"}
    assert ts == timestamp_ns(WALL)


def test_a_channel_point_is_tagged_with_the_cell_of_its_test() -> None:
    lines = encoder().encode([sample("ch0.voltage", 1.25)], {"ch0": ("T-0002", "r", "NIMH-42")})
    _, tags, _, _ = parse_line(lines["channel"][0])
    assert tags == {
        "bench": "b1",
        "channel": "ch0",
        "test_id": "T-0002",
        "recipe": "r",
        "cell_id": "NIMH-42",
    }


def test_a_device_point_goes_to_device_and_the_supervisors_own_tags_to_diagnostics() -> None:
    out = encoder().encode(
        [
            sample("pack.voltage", 14.8),
            sample("scan.duration_s", 0.002),
            sample("influx.spool_depth", 12),
            sample("historian.rows", 3),
        ]
    )
    (device,) = out["device"]
    assert parse_line(device)[:3] == (
        "device",
        {"bench": "b1", "device": "pack"},
        {"voltage": 14.8},
    )
    sources = {parse_line(x)[1]["source"]: parse_line(x)[2] for x in out["diagnostics"]}
    assert sources == {
        "scan": {"duration_s": 0.002},
        "influx": {"spool_depth": 12.0},
        "historian": {"rows": 3.0},
    }


def test_tag_keys_are_sorted_and_an_empty_tag_value_is_left_out() -> None:
    (line,) = encoder().encode([sample("ch1.current", 0.3)], {"ch1": ("", "")})["channel"]
    assert line.startswith("channel,bench=b1,channel=ch1 ")
    (line,) = encoder().encode([sample("ch1.current", 0.3)], {"ch1": ("T2", "r")})["channel"]
    assert line.startswith("channel,bench=b1,channel=ch1,recipe=r,test_id=T2 ")


def test_analog_values_are_always_floats_even_from_an_int_tag() -> None:
    enc = encoder(types={"scan.count": "int", "ch0.chain.cycle": "int", "pack.ok": "bool"})
    out = enc.encode([sample("scan.count", 7), sample("ch0.chain.cycle", 2), sample("pack.ok", 1)])
    assert "count=7.0" in out["diagnostics"][0]
    assert "chain_cycle=2.0" in out["channel"][0]
    assert "ok=true" in out["device"][0]
    for lines in out.values():
        for line in lines:
            assert not any(str(v).endswith("i") for v in parse_line(line)[2].values())


def test_a_bad_sample_or_a_non_finite_value_writes_no_field() -> None:
    out = encoder().encode(
        [
            sample("pack.voltage", None, quality=Quality.BAD),
            sample("pack.current", float("nan")),
            sample("pack.temp", float("inf")),
        ]
    )
    assert out == {}


def test_a_good_sample_without_a_value_writes_no_field_of_any_type() -> None:
    # A GOOD tag never set (an ETA before the first estimate) has no value: writing it as
    # a string "None" would fix its field's type and make every later float a conflict.
    out = encoder(types={"ch0.eta_s": "float"}).encode(
        [sample("ch0.eta_s", None), sample("pack.note", None), sample("ch0.voltage", 3.7)]
    )
    assert out == {"channel": [f"channel,bench=b1,channel=ch0 voltage=3.7 {timestamp_ns(WALL)}"]}


def test_samples_of_one_series_at_one_instant_share_a_line_and_go_out_oldest_first() -> None:
    out = encoder().encode(
        [
            sample("pack.voltage", 14.8, WALL + 0.1),
            sample("pack.current", 2.0, WALL + 0.1),
            sample("pack.temp", 25.0, WALL),  # polled earlier (a slower module)
        ]
    )
    parsed = [parse_line(x) for x in out["device"]]
    assert [p[3] for p in parsed] == [timestamp_ns(WALL), timestamp_ns(WALL + 0.1)]
    assert parsed[1][2] == {"voltage": 14.8, "current": 2.0}


def test_a_series_never_gets_the_same_instant_twice_so_no_point_replaces_another() -> None:
    enc = encoder()
    first = enc.encode([sample("ch0.voltage", 1.0), sample("ch0.current", 0.1)])["channel"]
    # Written between two scans: it carries the last scan's time, the same instant.
    again = enc.encode([sample("ch0.enable", False), sample("ch0.voltage", 1.1)])["channel"]
    (a,), (b,) = first, again
    assert parse_line(a)[3] == timestamp_ns(WALL)
    assert parse_line(b)[3] == timestamp_ns(WALL) + 1  # the next free nanosecond
    assert parse_line(b)[2] == {"enable": False, "voltage": 1.1}


def test_the_timestamp_is_the_acquisition_time_in_nanoseconds_and_replays_identically() -> None:
    assert timestamp_ns(1.5) == 1_500_000_000
    a = encoder().encode([sample("pack.voltage", 1.0)])
    b = encoder().encode([sample("pack.voltage", 1.0)])
    assert a == b


def test_a_field_named_time_is_renamed_since_influxdb_refuses_it() -> None:
    (line,) = encoder().encode([sample("pack.time", 3.0)])["device"]
    assert parse_line(line)[2] == {"time_": 3.0}


def test_an_event_line_carries_text_source_actor_and_severity() -> None:
    ev = BenchEvent(
        0.0,
        WALL,
        "alarm",
        "ch0",
        "ch0.trip",
        "ch0.trip activated: V high",
        "safety",
        700,
        "T1",
        "r1",
    )
    m, tags, fields, ts = parse_line(encoder().event(ev))
    assert m == "event"
    assert tags == {
        "bench": "b1",
        "kind": "alarm",
        "channel": "ch0",
        "test_id": "T1",
        "recipe": "r1",
    }
    assert fields == {
        "text": "ch0.trip activated: V high",
        "source": "ch0.trip",
        "actor": "safety",
        "severity": 700.0,
    }
    assert ts == timestamp_ns(WALL)


def test_two_events_of_one_series_in_the_same_nanosecond_are_both_kept_in_order() -> None:
    enc = encoder()
    first = enc.event(BenchEvent(0.0, WALL, "alarm", "", "a", "first"))
    second = enc.event(BenchEvent(0.0, WALL, "alarm", "", "b", "second"))
    assert parse_line(second)[3] == parse_line(first)[3] + 1


def test_the_measurement_of_a_line_is_read_back() -> None:
    assert line_measurement("channel,bench=b1 v=1.0 1") == "channel"
    assert line_measurement(b"scan v=1.0 1") == "scan"


# --- escaping: anything encoded is parsed back -----------------------------------------------
TEXT = st.text(st.characters(blacklist_categories=("Cs",)), max_size=40)


def _key_as_written(text: str) -> str:
    """What a tag key, a tag value or a field key becomes (lineproto module docstring)."""
    return text.replace("\\", "/").replace("\n", " ").replace("\r", " ")


@settings(max_examples=300, deadline=None)
@given(
    tag_value=TEXT.filter(lambda s: s != ""),
    field_key=TEXT.filter(lambda s: s != ""),
    text=TEXT,
    number=st.floats(allow_nan=False, allow_infinity=False),
)
def test_any_tag_value_field_key_and_string_is_parsed_back(
    tag_value: str, field_key: str, text: str, number: float
) -> None:
    assume(_key_as_written(field_key) != "n")  # the other field of the line
    prefix = f"{escape_measurement('m')},{escape_tag('t')}={escape_tag(tag_value)}"
    key = escape_field_key(field_key)
    line = f"{prefix} {key}={escape_string(text)},n={number!r} 1"
    m, tags, fields, ts = parse_line(line)
    assert "\n" not in line and "\r" not in line
    assert (m, tags, ts) == ("m", {"t": _key_as_written(tag_value)}, 1)
    assert fields[_key_as_written(field_key)] == text.replace("\n", " ").replace("\r", " ")
    assert fields["n"] == number


@settings(max_examples=200, deadline=None)
@given(
    test_id=TEXT,
    recipe=TEXT,
    value=st.one_of(TEXT, st.booleans(), st.floats(allow_nan=False, allow_infinity=False)),
)
def test_encoded_channel_lines_parse_for_any_test_id_recipe_and_value(
    test_id: str, recipe: str, value: object
) -> None:
    out = encoder().encode([sample("ch0.x", value)], {"ch0": (test_id, recipe)})
    (line,) = out["channel"]
    _, tags, fields, _ = parse_line(line)
    expected_tags = {"bench": "b1", "channel": "ch0"}
    if test_id:
        expected_tags["test_id"] = _key_as_written(test_id)
    if recipe:
        expected_tags["recipe"] = _key_as_written(recipe)
    assert tags == expected_tags
    want = value.replace("\n", " ").replace("\r", " ") if isinstance(value, str) else value
    assert fields == {"x": want}
