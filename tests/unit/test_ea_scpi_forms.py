"""The simulated EA accepts every form of a command a real unit accepts (issue 32, finding 9).

SCPI mnemonics come in a long and a short form, in any case, with an optional leading
colon, and a header's optional nodes (``OUTPut[:STATe]``, ``SYSTem:ERRor[:NEXT]``,
``[SOURce:]VOLTage[:LEVel][:IMMediate][:AMPLitude]``) may be given or left out. Seed 002's
script ends with ``OUTP:STAT OFF``: the simulator answered ``-100`` and left the output on.
A command an EA unit does not have (the seed's ``SYST:TIMEOUT 0``) or a mnemonic that is
neither form (``OUTPU``) is still ``-100``. In process, on the virtual clock.
"""

from __future__ import annotations

import pytest

from supervisor.core.clock import VirtualClock
from supervisor.devices.ea import EaSimulator
from supervisor.devices.ea.protocol import OPTIONAL_NODES, parse_command
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant

NO_ERROR = '0,"No error"'
COMMAND_ERROR = '-100,"Command error"'


@pytest.fixture
def ea() -> EaSimulator:
    """A unit in remote with its output on, a pack on its terminals."""
    plant = BenchPlant(VirtualClock(), make_model("liion-pack", cells_series=4, capacity_ah=10.0))
    plant.set_contactor(True)
    unit = EaSimulator(plant)
    for line in (b"SYST:LOCK ON\n", b"OUTP ON\n"):
        unit.handle_line(line)
    assert unit.handle_line(b"SYST:ERR?\n") == NO_ERROR
    return unit


def send(ea: EaSimulator, line: str) -> str | None:
    return ea.handle_line(line.encode("ascii") + b"\n")


@pytest.mark.parametrize(
    "line",
    [
        "OUTP OFF",
        "OUTP:STAT OFF",
        "outp:stat off",
        "Outp:Stat Off",
        "OUTPut:STATe OFF",
        "OUTPUT:STATE OFF",
        ":OUTP:STAT OFF",
        "OUTP:STAT 0",
    ],
)
def test_every_form_of_output_state_off_switches_the_output_off(ea: EaSimulator, line: str) -> None:
    send(ea, line)
    assert send(ea, "SYST:ERR?") == NO_ERROR
    assert send(ea, "OUTP?") == "OFF"
    assert not ea.plant.supply.output_on


@pytest.mark.parametrize("query", ["OUTP?", "OUTP:STAT?", "OUTPut:STATe?", "outp:stat?"])
def test_every_form_of_the_output_query_answers(ea: EaSimulator, query: str) -> None:
    assert send(ea, query) == "ON"


@pytest.mark.parametrize(
    "line",
    [
        "VOLT 10",
        "VOLT:LEV 10",
        "VOLT:LEV:IMM 10",
        "VOLT:LEV:IMM:AMPL 10",
        "SOUR:VOLT 10",
        "SOURce:VOLTage:LEVel:IMMediate:AMPLitude 10",
        "sour:volt:ampl 10 V",
        "VOLT:IMM 10",
    ],
)
def test_every_form_of_a_set_value_sets_it(ea: EaSimulator, line: str) -> None:
    send(ea, line)
    assert send(ea, "SYST:ERR?") == NO_ERROR
    assert send(ea, "VOLT?") == "10.00 V"
    assert send(ea, "SOURce:VOLTage:LEVel?") == "10.00 V"


@pytest.mark.parametrize(
    ("query", "reply"),
    [
        ("SYST:ERR:NEXT?", NO_ERROR),
        ("SYSTem:ERRor:NEXT?", NO_ERROR),
        ("MEAS:SCAL:ARR?", None),
        ("MEASure:SCALar:VOLTage:DC?", None),
        ("SYSTem:LOCK:OWNer?", "REMOTE"),
        ("STATus:QUEStionable:CONDition?", "0"),
    ],
)
def test_queries_in_long_forms_and_with_optional_nodes_answer(
    ea: EaSimulator, query: str, reply: str | None
) -> None:
    answer = send(ea, query)
    assert answer is not None
    if reply is not None:
        assert answer == reply
    assert send(ea, "SYST:ERR?") == NO_ERROR


def test_the_lock_takes_its_optional_state_node(ea: EaSimulator) -> None:
    send(ea, "SYSTem:LOCK:STATe OFF")
    assert send(ea, "SYST:LOCK:OWN?") == "NONE"
    send(ea, "syst:lock:stat on")
    assert send(ea, "SYST:LOCK:OWN?") == "REMOTE"


@pytest.mark.parametrize(
    "line",
    ["SYST:TIMEOUT 0", "OUTPU:STAT OFF", "OUTP:STA OFF", "OUT OFF", "OUTP:STAT:STAT OFF"],
)
def test_a_command_the_unit_does_not_have_is_a_command_error(ea: EaSimulator, line: str) -> None:
    send(ea, line)
    assert send(ea, "SYST:ERR?") == COMMAND_ERROR
    assert send(ea, "OUTP?") == "ON"


@pytest.mark.parametrize("pattern", OPTIONAL_NODES)
def test_each_header_with_all_its_optional_nodes_means_the_header_without_them(
    pattern: str,
) -> None:
    bare = pattern
    while "[" in bare:
        start = bare.index("[")
        bare = bare[:start] + bare[bare.index("]", start) + 1 :]
    full = pattern.replace("[", "").replace("]", "")
    assert parse_command(f"{full}?").header == bare
    assert parse_command(f"{bare}?").header == bare
