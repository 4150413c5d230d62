"""Seed 002's annex V sequence, verbatim, against the simulated EA over TCP (issue 32,
finding 9).

A plain socket client, as the seed's script is: one connection, each command a line, a
query's reply read as a line. After each command the client asks ``SYST:ERR?`` and
``OUTP?`` (not part of the seed's script: what the test looks at). Every command of the
annex is accepted but ``SYST:TIMEOUT 0``, which an EA unit does not have (``-100``), and
the closing ``OUTP:STAT OFF`` switches the output off (it answered ``-100`` and left the
output on before). Real clock (the simulator is served on a loopback port the OS picks).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator
from typing import Final

import pytest

from supervisor.core.clock import RealClock
from supervisor.devices.ea.sim import EaTcpSimulator
from supervisor.sim.battery import make_model
from supervisor.sim.plant import BenchPlant

pytestmark = pytest.mark.integration

NUM_CYCLES: Final = 5
"""The annex's ``NUM_CYCLES``: one ``VOLT 10`` a cycle (its discharge is commented out)."""
ANNEX_V: Final = (
    # initialize_device
    "*IDN?",
    "SYST:LOCK ON",
    "SYST:TIMEOUT 0",
    "*CLS",
    "*RST",
    # the main script
    "OUTP ON",
    *(["VOLT 10"] * NUM_CYCLES),
    "OUTP:STAT OFF",
    # its `finally:`
    "OUTP OFF",
    "OUTP:STAT OFF",
)
REPLY_TIMEOUT_S: Final = 5.0


@pytest.fixture
async def unit() -> AsyncIterator[EaTcpSimulator]:
    plant = BenchPlant(RealClock(), make_model("liion-pack", cells_series=4, capacity_ah=10.0))
    plant.set_contactor(True)
    sim = EaTcpSimulator(plant, port=0)
    await sim.start()
    try:
        yield sim
    finally:
        await sim.stop()


def run_annex(port: int) -> list[tuple[str, str | None, str, str]]:
    """Each command of :data:`ANNEX_V` with its reply (queries), then the error queue's
    head and ``OUTP?``: (command, reply, error, output)."""
    seen: list[tuple[str, str | None, str, str]] = []
    with socket.create_connection(("127.0.0.1", port), timeout=REPLY_TIMEOUT_S) as sock:
        lines = sock.makefile("rb")

        def ask(command: str) -> str:
            sock.sendall(command.encode("ascii") + b"\n")
            return lines.readline().decode("ascii").strip()

        for command in ANNEX_V:
            if command.endswith("?"):
                reply: str | None = ask(command)
            else:
                sock.sendall(command.strip().encode("ascii") + b"\n")
                reply = None
            seen.append((command, reply, ask("SYST:ERR?"), ask("OUTP?")))
    return seen


async def test_the_annex_v_sequence_runs_on_the_simulated_ea(unit: EaTcpSimulator) -> None:
    seen = await asyncio.to_thread(run_annex, unit.port)
    errors = {command: error for command, _, error, _ in seen}
    assert errors.pop("SYST:TIMEOUT 0") == '-100,"Command error"'
    assert set(errors.values()) == {'0,"No error"'}
    idn = seen[0][1]
    assert idn is not None and idn.startswith("EA Elektro-Automatik GmbH & Co. KG, PSB 10060-60")
    output = [(command, out) for command, _, _, out in seen]
    assert output[5:] == [
        ("OUTP ON", "ON"),
        *[("VOLT 10", "ON")] * NUM_CYCLES,
        ("OUTP:STAT OFF", "OFF"),
        ("OUTP OFF", "OFF"),
        ("OUTP:STAT OFF", "OFF"),
    ]
    assert not unit.plant.supply.output_on
    assert unit.plant.supply.volt_set_v == 10.0
