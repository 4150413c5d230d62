"""Safety wiring that is wrong but well-formed (issue 28, finding 5): ``supervisor check``
refuses it, at the offending value, saying why it would be unsafe.

Each case rewires io_maps/sim.yaml (a valid map) by one edit of its text, so that the
position the message must name is where the edit put the wrong reference."""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.cli.main import main
from supervisor.core.errors import ConfigErrors
from supervisor.devices.registry import load_bench_text

ROOT = Path(__file__).resolve().parents[2]
SIM_TEXT = (ROOT / "io_maps" / "sim.yaml").read_text(encoding="utf-8")

ESTOP = "  estop: {tag: estop.ok}\n"
HEARTBEAT = "heartbeat: {tag: watchdog.heartbeat, period_s: 0.5}"
CONTACTOR_TAG = (
    "  - {name: contactor.cmd, device: adam, point: slot3.do0,"
    " description: battery contactor coil}\n"
)
PACK_TEMP_TAG = "  - {name: pack.temp, device: adam, point: slot1.tc0, unit: degC}\n"
CH0 = "    description: AA cell on board 0\n"

# (id, text replaced in sim.yaml, its replacement, where the error is ("|" marks the spot in
# a text unique in the edited map), words the message holds, the reason's word)
CASES = [
    (
        "estop_is_an_analog_current",
        ESTOP,
        "  estop: {tag: pack.current}\n",
        "estop: {tag: |pack.current}",
        "e-stop tag 'pack.current' is an analog input (slot0.ai0 of device 'adam') in A",
        "kind",
    ),
    (
        "estop_is_an_output",
        ESTOP,
        "  estop: {tag: contactor.cmd}\n",
        "estop: {tag: |contactor.cmd}",
        "e-stop tag 'contactor.cmd' is an output (slot3.do0 of device 'adam')",
        "direction",
    ),
    (
        "feedback_is_the_contactors_own_command",
        "contactor_feedback_tag: contactor.closed",
        "contactor_feedback_tag: contactor.cmd",
        "contactor_feedback_tag: |contactor.cmd",
        "contactor_feedback_tag 'contactor.cmd' is the contactor's own command",
        "direction",
    ),
    (
        "heartbeat_drives_the_contactor_coil",
        HEARTBEAT,
        "heartbeat: {tag: contactor.cmd, period_s: 0.5}",
        "heartbeat: {tag: |contactor.cmd",
        "'contactor.cmd' is already the contactor coil of channel 'ch4'; the heartbeat needs"
        " an output of its own",
        "ownership",
    ),
    (
        "estop_relay_is_the_heartbeat_relay",
        ESTOP,
        "  estop: {tag: estop.ok, relay_tag: watchdog.heartbeat}\n",
        "heartbeat: {tag: |watchdog.heartbeat",
        "'watchdog.heartbeat' is already the e-stop relay; the heartbeat needs an output",
        "ownership",
    ),
    (
        "two_channels_share_one_contactor",
        CH0,
        CH0 + "    contactor_tag: contactor.cmd\n",
        "contactor_tag: |contactor.cmd\n    contactor_feedback_tag",
        "'contactor.cmd' is already the contactor coil of channel 'ch0'; the contactor coil of"
        " channel 'ch4' needs an output of its own",
        "ownership",
    ),
    (
        "a_second_tag_on_the_coils_output",
        CONTACTOR_TAG,
        CONTACTOR_TAG + "  - {name: coil.again, device: adam, point: slot3.do0}\n",
        "coil.again, device: adam, point: |slot3.do0",
        "tag 'coil.again' maps output slot3.do0 of device 'adam', already mapped by tag"
        " 'contactor.cmd'",
        "ownership",
    ),
    (
        "voltage_tag_is_a_boolean",
        "voltage_tag: pack.voltage",
        "voltage_tag: estop.ok",
        "voltage_tag: |estop.ok",
        "voltage_tag 'estop.ok' is a boolean input (slot0.ai2 of device 'adam'), not a number",
        "kind",
    ),
    (
        "voltage_tag_is_a_relay",
        "voltage_tag: pack.voltage",
        "voltage_tag: contactor.cmd",
        "voltage_tag: |contactor.cmd",
        "voltage_tag 'contactor.cmd' is an output (slot3.do0 of device 'adam')",
        "direction",
    ),
    (
        "voltage_tag_is_in_degrees_celsius",
        "voltage_tag: pack.voltage",
        "voltage_tag: room.temp",
        "voltage_tag: |room.temp",
        "voltage_tag 'room.temp' is in degC, not V",
        "unit",
    ),
    (
        "temperature_tag_is_in_amperes",
        "temperature_tag: pack.temp\n    contactor_tag",
        "temperature_tag: pack.current\n    contactor_tag",
        "temperature_tag: |pack.current",
        "temperature_tag 'pack.current' is in A, not degC",
        "unit",
    ),
    (
        "alarm_high_high_below_low_low",
        PACK_TEMP_TAG,
        PACK_TEMP_TAG.replace("degC}", "degC, alarms: {hh: 10, ll: 50}}"),
        "alarms: {hh: |10",
        "alarm limit hh 10 of tag 'pack.temp' is not above ll 50",
        "ordering",
    ),
    (
        "interlock_named_estop",
        ESTOP,
        ESTOP + "  interlocks:\n    - {id: estop, tag: pack.temp, above: 60}\n",
        "- {id: |estop",
        "interlock id 'estop' is reserved",
        "reserved",
    ),
    (
        "interlock_equals_on_an_analog_tag",
        ESTOP,
        ESTOP + "  interlocks:\n    - {id: hot, tag: pack.temp, equals: true}\n",
        "id: hot, tag: |pack.temp",
        "interlock 'hot' tests equals: on 'pack.temp'",
        "kind",
    ),
    (
        "feedback_is_an_analog_input",
        "contactor_feedback_tag: contactor.closed",
        "contactor_feedback_tag: pack.voltage",
        "contactor_feedback_tag: |pack.voltage",
        "contactor_feedback_tag 'pack.voltage' is an analog input",
        "kind",
    ),
]


def rewired(old: str, new: str) -> str:
    assert SIM_TEXT.count(old) == 1, old
    return SIM_TEXT.replace(old, new)


def position(text: str, spot: str) -> tuple[int, int]:
    """(line, column), 1-based, of the "|" in ``spot`` found in ``text``."""
    before, after = spot.split("|")
    assert text.count(before + after) == 1, spot
    offset = text.index(before + after) + len(before)
    line = text.count("\n", 0, offset) + 1
    return line, offset - (text.rfind("\n", 0, offset) + 1) + 1


@pytest.mark.parametrize(
    ("old", "new", "spot", "words", "reason"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_a_wrong_safety_wiring_is_refused_at_its_value_saying_why(
    old: str, new: str, spot: str, words: str, reason: str
) -> None:
    text = rewired(old, new)
    with pytest.raises(ConfigErrors) as info:
        load_bench_text(text, "bench.yaml")
    errors = info.value.errors
    assert len(errors) == 1, [str(e) for e in errors]  # one mistake, one message
    e = errors[0]
    assert (e.file, e.line, e.col) == ("bench.yaml", *position(text, spot)), str(e)
    assert words in e.message
    assert f"({reason}" in e.message  # why it would be unsafe, in one word


def test_the_shipped_sim_map_passes_every_wiring_rule() -> None:
    assert load_bench_text(SIM_TEXT, "sim.yaml").safety.estop is not None


def test_check_refuses_a_heartbeat_on_the_contactor_coil_with_exit_2_and_no_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = rewired(HEARTBEAT, "heartbeat: {tag: contactor.cmd, period_s: 0.5}")
    path = tmp_path / "bench.yaml"
    path.write_text(text, encoding="utf-8")
    code = main(["check", str(path)])
    _out, err = capsys.readouterr()
    assert code == 2
    assert "Traceback" not in err
    line, col = position(text, "heartbeat: {tag: |contactor.cmd")
    [message] = err.strip().splitlines()
    assert message.startswith(f"{path}:{line}:{col}: ")
    assert "ownership of outputs" in message
