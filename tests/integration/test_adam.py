"""ADAM-5000/TCP over real Modbus TCP on 127.0.0.1: what only Modbus TCP has.

The driver's contract (word and bit order, exception and short answers over the wire, an
outage with the server back on the same port, the safe state) runs on both transports in
``tests/unit/test_adam_driver.py`` (class ``TestDriverOnBothTransports``; its TCP runs are
marked ``integration`` too). Here: pymodbus's own failures as the link maps them (refused,
lost, no answer on wall time) and a foreign pymodbus client against the simulator.
"""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from adam_rig import TIMEOUT_S, AdamRig, open_rig
from pymodbus.client import AsyncModbusTcpClient
from rig_transports import TCP

from supervisor.core.clock import RealClock
from supervisor.core.errors import DeviceIOError, DeviceTimeout
from supervisor.devices.adam.sim import AdamSimulator
from supervisor.devices.adam.transport import PymodbusTcpLink
from supervisor.devices.adam.unit import AdamUnit
from supervisor.testing import free_tcp_port, wait_until

pytestmark = pytest.mark.integration

SILENT_TIMEOUT_S = 0.2
"""The one test that waits for a timeout on wall time waits this long."""


@pytest.fixture
async def bench() -> AsyncIterator[AdamRig]:
    """The seed 002 unit served on a loopback port the OS picks, a pymodbus link to it."""
    async with open_rig(TCP, RealClock()) as rig:
        yield rig


# --- the pymodbus link's failures, from the real library --------------------------------------
async def test_pymodbus_link_refused_and_lost(bench: AdamRig) -> None:
    nobody = PymodbusTcpLink("adam2", "127.0.0.1", free_tcp_port(), timeout_s=TIMEOUT_S)
    with pytest.raises(DeviceIOError, match=r"^adam2: cannot connect to 127\.0\.0\.1:\d+$"):
        await nobody.connect()
    assert not nobody.connected

    await bench.link.connect()
    await bench.sim.stop()
    await wait_until(lambda: not bench.link.connected, "the link sees the server gone")
    with pytest.raises(DeviceIOError, match=r"^adam1: not connected$"):
        await bench.link.read_coils(48, 6)


async def test_a_silent_server_is_a_timeout(bench: AdamRig) -> None:
    """pymodbus reports a request without answer in words ("No response …") that the link
    must recognise; only the real library can say whether it still does. Wall time: one
    ``SILENT_TIMEOUT_S``."""
    link = PymodbusTcpLink("adam1", bench.sim.host, bench.sim.port, timeout_s=SILENT_TIMEOUT_S)
    await link.connect()
    bench.unit.mute()
    try:
        with pytest.raises(DeviceTimeout, match=rf"^adam1: no answer in {SILENT_TIMEOUT_S} s$"):
            await link.read_registers(0, 8)
        bench.unit.mute(False)
        assert len(await link.read_registers(0, 8)) == 8
    finally:
        await link.close()


# --- a foreign Modbus client against the simulator ---------------------------------------------
async def test_analog_values_are_served_by_fc03_and_fc04(bench: AdamRig) -> None:
    bench.inputs[(1, 2)] = 42.0
    client = AsyncModbusTcpClient(bench.sim.host, port=bench.sim.port, timeout=TIMEOUT_S)
    try:
        assert await client.connect()
        holding = await client.read_holding_registers(8, count=7, device_id=1)
        inputs = await client.read_input_registers(8, count=7, device_id=1)
        assert not holding.isError() and not inputs.isError()
        assert holding.registers == inputs.registers
        assert len(holding.registers) == 7
        # Nothing in slot 5; a 5018 has no 8th channel; analog inputs are read-only.
        empty = await client.read_holding_registers(40, count=8, device_id=1)
        assert empty.isError() and empty.exception_code == 0x02
        eighth = await client.read_holding_registers(8, count=8, device_id=1)
        assert eighth.isError() and eighth.exception_code == 0x02
        write = await client.write_register(8, 1, device_id=1)
        assert write.isError() and write.exception_code == 0x02
        # FC15 on the relay slot calls the callbacks too.
        coils = await client.write_coils(48, [True, False, True], device_id=1)
        assert not coils.isError()
        assert bench.relay_calls == {(3, 0): [True], (3, 1): [False], (3, 2): [True]}
        back = await client.read_coils(48, count=6, device_id=1)
        assert list(back.bits[:6]) == [True, False, True, False, False, False]
    finally:
        client.close()


def test_server_refuses_a_bad_unit_id() -> None:
    with pytest.raises(ValueError, match="unit_id"):
        AdamSimulator(AdamUnit({0: "5017"}), unit_id=300)


async def test_two_simulated_units_log_nothing_of_pymodbus_at_info(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pymodbus logs its servers' routine at INFO, and a second server's identical line as
    "Repeating....", which `make run` printed: the bench's own log says what matters."""
    import logging

    monkeypatch.setattr(logging.getLogger("pymodbus"), "level", logging.NOTSET)
    caplog.set_level(logging.INFO)
    sims = [AdamSimulator(AdamUnit({0: "5017"}), host="127.0.0.1", port=0) for _ in range(2)]
    for sim in sims:
        await sim.start()
    for sim in sims:
        await sim.stop()
    assert [r.getMessage() for r in caplog.records if r.name.startswith("pymodbus")] == []
