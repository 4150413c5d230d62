"""The Modbus link the ADAM driver talks through, injected by the composition root.

:class:`ModbusLink` is exactly what :class:`~supervisor.devices.adam.driver.AdamDriver`
needs of Modbus: open/close, FC01, the register read that
:data:`~supervisor.devices.adam.protocol.ANALOG_READ_FUNCTION` names (FC03 or FC04), FC05,
and for the host watchdog's registers FC06 and FC03.
Answers are plain Python values; failures are typed:

- :class:`~supervisor.devices.adam.protocol.ModbusExceptionAnswer` (with the exception
  code): the unit refused this request; the link is fine (slot-local for the driver);
- :class:`~supervisor.core.errors.DeviceTimeout`: no answer within ``timeout_s``;
- :class:`~supervisor.core.errors.DeviceIOError`: the link is down (refused, lost, closed).

Two links: :class:`PymodbusTcpLink` (Modbus TCP through pymodbus, for the real unit and the
served simulator) and :class:`InProcessLink` (calls an
:class:`~supervisor.devices.adam.unit.AdamUnit` directly; its timeouts take time on the
injected clock, so virtual-clock tests of timeouts and reconnects are deterministic).

pymodbus stays inside the ADAM package (STYLE.md: it is pinned to a minor range because its
bit order changed between minors; golden tests on bit and word order guard it).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Protocol

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from supervisor.core.clock import Clock
from supervisor.core.errors import DeviceIOError, DeviceTimeout
from supervisor.devices.adam.protocol import (
    ANALOG_READ_FUNCTION,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    ModbusExceptionAnswer,
)
from supervisor.devices.adam.unit import AdamUnit

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


class PymodbusTcpLink:
    """Modbus TCP to ``host:port``, device ``unit_id``, through pymodbus's async client.

    pymodbus's own retries and reconnects are off: :class:`PolledDriver` reconnects, with
    backoff, and a silent reconnect inside pymodbus would hide a lost device.
    """

    def __init__(
        self, name: str, host: str, port: int, unit_id: int = 1, timeout_s: float = 1.0
    ) -> None:
        if not 0 <= unit_id <= 255:
            raise ValueError(f"{name}: unit_id must be 0..255, got {unit_id!r}")
        if timeout_s <= 0:
            raise ValueError(f"{name}: timeout_s must be > 0")
        self.name = name
        self.host = host
        self.port = port
        self.unit_id = unit_id
        self.timeout_s = timeout_s
        self._client: AsyncModbusTcpClient | None = None

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    async def connect(self) -> None:
        await self.close()
        client = AsyncModbusTcpClient(
            self.host,
            port=self.port,
            name=self.name,
            timeout=self.timeout_s,
            retries=0,
            reconnect_delay=0,  # PolledDriver reconnects, with backoff
        )
        self._client = client
        if not await client.connect():
            await self.close()
            raise DeviceIOError(self.name, f"cannot connect to {self.address}")

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    async def read_coils(self, address: int, count: int) -> list[bool]:
        rsp = await self._call(lambda c: c.read_coils(address, count=count, device_id=self.unit_id))
        # pymodbus pads the bits to whole bytes: only the coils asked for count.
        return [bool(b) for b in rsp.bits[:count]]

    async def read_registers(self, address: int, count: int) -> list[int]:
        def read(c: AsyncModbusTcpClient) -> Awaitable[ModbusPDU]:
            if ANALOG_READ_FUNCTION == FC_READ_INPUT_REGISTERS:
                return c.read_input_registers(address, count=count, device_id=self.unit_id)
            assert ANALOG_READ_FUNCTION == FC_READ_HOLDING_REGISTERS
            return c.read_holding_registers(address, count=count, device_id=self.unit_id)

        rsp = await self._call(read)
        return [int(r) & 0xFFFF for r in rsp.registers]

    async def write_coil(self, address: int, value: bool) -> None:
        await self._call(lambda c: c.write_coil(address, value, device_id=self.unit_id))

    async def write_register(self, address: int, value: int) -> None:
        await self._call(lambda c: c.write_register(address, value, device_id=self.unit_id))

    async def read_holding_registers(self, address: int, count: int) -> list[int]:
        rsp = await self._call(
            lambda c: c.read_holding_registers(address, count=count, device_id=self.unit_id)
        )
        return [int(r) & 0xFFFF for r in rsp.registers]

    async def _call(
        self, request: Callable[[AsyncModbusTcpClient], Awaitable[ModbusPDU]]
    ) -> ModbusPDU:
        """One transaction, pymodbus's failures mapped to the link's."""
        client = self._client
        # pymodbus would silently reconnect on its own: reconnecting is PolledDriver's job.
        if client is None or not client.connected:
            raise DeviceIOError(self.name, "not connected")
        try:
            rsp = await request(client)
        except ConnectionException as exc:
            raise DeviceIOError(self.name, str(exc)) from exc
        except ModbusIOException as exc:
            # pymodbus 3.16 reports a request without answer as "No response received …".
            if "No response" in str(exc):
                raise DeviceTimeout(self.name, f"no answer in {self.timeout_s} s") from exc
            raise DeviceIOError(self.name, str(exc)) from exc
        except ModbusException as exc:
            raise DeviceIOError(self.name, str(exc)) from exc
        except TimeoutError as exc:
            raise DeviceTimeout(self.name, f"no answer in {self.timeout_s} s") from exc
        if rsp.isError():
            raise ModbusExceptionAnswer(int(rsp.exception_code))
        return rsp


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
