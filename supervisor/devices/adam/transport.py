"""The Modbus link the ADAM driver talks through, injected by the composition root.

:class:`ModbusLink` is exactly what :class:`~supervisor.devices.adam.driver.AdamDriver`
needs of Modbus: open/close, FC01, the register read that
:data:`~supervisor.devices.adam.protocol.ANALOG_READ_FUNCTION` names (FC03 or FC04), FC05,
and for the host watchdog's registers FC06 and FC03.
Answers are plain Python values; failures are typed:

- :class:`~supervisor.fieldbus.modbus.ModbusExceptionAnswer` (with the exception
  code): the unit refused this request; the link is fine (slot-local for the driver);
- :class:`~supervisor.core.errors.DeviceTimeout`: no answer within ``timeout_s``;
- :class:`~supervisor.core.errors.DeviceIOError`: the link is down (refused, lost, closed).

Two links: :class:`PymodbusTcpLink` (the generic Modbus TCP master
:class:`~supervisor.fieldbus.modbus.ModbusTcpMaster`, for the real unit and the served
simulator) and :class:`InProcessLink` (calls an
:class:`~supervisor.devices.adam.unit.AdamUnit` directly; its timeouts take time on the
injected clock, so virtual-clock tests of timeouts and reconnects are deterministic).

pymodbus stays behind :mod:`supervisor.fieldbus.modbus` and the ADAM simulator (it is pinned
to a minor range because its bit order changed between minors; golden tests on bit and word
order guard it).
"""

from __future__ import annotations

from typing import Protocol

from supervisor.core.clock import Clock
from supervisor.core.errors import DeviceIOError, DeviceTimeout
from supervisor.devices.adam.protocol import ANALOG_READ_FUNCTION
from supervisor.devices.adam.unit import AdamUnit
from supervisor.fieldbus.modbus import (
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    ModbusExceptionAnswer,
    ModbusTcpMaster,
)

__all__ = ["InProcessLink", "ModbusExceptionAnswer", "ModbusLink", "PymodbusTcpLink"]


class ModbusLink(Protocol):
    """A Modbus master's link to one ADAM unit (addresses are 0-based PDU addresses)."""

    @property
    def address(self) -> str:
        """Where the unit is, for log lines (``host:port``)."""
        ...

    @property
    def connected(self) -> bool:
        """Open, as far as the link knows (a dropped link says False)."""
        ...

    async def connect(self) -> None:
        """Open the link; :class:`DeviceIOError` if the unit cannot be reached."""
        ...

    async def close(self) -> None:
        """Close the link (nothing happens if it is not open)."""
        ...

    async def read_coils(self, address: int, count: int) -> list[bool]:
        """FC01: the states of ``count`` coils from ``address`` (fewer if the answer is
        short)."""
        ...

    async def read_registers(self, address: int, count: int) -> list[int]:
        """:data:`ANALOG_READ_FUNCTION` (FC03/FC04): ``count`` 16-bit unsigned values from
        ``address`` (fewer if the answer is short)."""
        ...

    async def write_coil(self, address: int, value: bool) -> None:
        """FC05: set one coil (the unit echoes the request)."""
        ...

    async def write_register(self, address: int, value: int) -> None:
        """FC06: set one holding register (the unit echoes the request)."""
        ...

    async def read_holding_registers(self, address: int, count: int) -> list[int]:
        """FC03 whatever :data:`ANALOG_READ_FUNCTION` is (configuration registers)."""
        ...


class PymodbusTcpLink(ModbusTcpMaster):
    """Modbus TCP to an ADAM unit (the generic master, plus the ADAM's analog read)."""

    async def read_registers(self, address: int, count: int) -> list[int]:
        if ANALOG_READ_FUNCTION == FC_READ_INPUT_REGISTERS:
            return await self.read_input_registers(address, count)
        assert ANALOG_READ_FUNCTION == FC_READ_HOLDING_REGISTERS
        return await self.read_holding_registers(address, count)


class InProcessLink:
    """A link to ``unit`` in this process: each request is a direct call.

    A muted unit makes a request wait ``timeout_s`` on ``clock`` (virtual time in tests)
    and raise :class:`DeviceTimeout`; an unplugged unit refuses to connect, and a link open
    when the unit was unplugged stays dropped until it connects again (as a TCP connection
    would).
    """

    def __init__(self, name: str, clock: Clock, unit: AdamUnit, timeout_s: float = 1.0) -> None:
        if timeout_s <= 0:
            raise ValueError(f"{name}: timeout_s must be > 0")
        self.name = name
        self.clock = clock
        self.unit = unit
        self.timeout_s = timeout_s
        self._opened_after: int | None = None
        """The unit's outage count when the link was opened; None: closed."""

    @property
    def address(self) -> str:
        return f"in-process simulator {self.unit.name}"

    @property
    def connected(self) -> bool:
        return (
            self._opened_after is not None
            and self.unit.running
            and self.unit.outages == self._opened_after
        )

    async def connect(self) -> None:
        await self.close()
        if not self.unit.running:
            raise DeviceIOError(self.name, f"cannot connect to {self.address}")
        self._opened_after = self.unit.outages

    async def close(self) -> None:
        self._opened_after = None

    async def read_coils(self, address: int, count: int) -> list[bool]:
        await self._exchange()
        return self.unit.read_coils(address, count)

    async def read_registers(self, address: int, count: int) -> list[int]:
        await self._exchange()
        return self.unit.read_registers(ANALOG_READ_FUNCTION, address, count)

    async def write_coil(self, address: int, value: bool) -> None:
        await self._exchange()
        self.unit.write_coils(address, [value])

    async def write_register(self, address: int, value: int) -> None:
        await self._exchange()
        self.unit.write_registers(address, [value])

    async def read_holding_registers(self, address: int, count: int) -> list[int]:
        await self._exchange()
        return self.unit.read_registers(FC_READ_HOLDING_REGISTERS, address, count)

    async def _exchange(self) -> None:
        """Check that the request reaches the unit and that it answers."""
        if not self.connected:
            raise DeviceIOError(self.name, "not connected")
        if self.unit.muted:
            # No answer: the request costs its timeout, on the injected clock.
            await self.clock.sleep_until(self.clock.now() + self.timeout_s)
            raise DeviceTimeout(self.name, f"no answer in {self.timeout_s} s")
