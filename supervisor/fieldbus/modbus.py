"""Modbus as any unit speaks it: function and exception codes, and a Modbus TCP master.

The codes are those of the Modbus Application Protocol V1.1b3; :class:`ModbusExceptionAnswer`
is a unit's refusal of one request. :class:`ModbusTcpMaster` is the plain client a driver
talks through (pymodbus's async client, with pymodbus's failures mapped to the project's
typed errors); which registers mean what is the kind's (e.g.
:mod:`supervisor.devices.adam.protocol`).

pymodbus stays behind this module and a kind's simulator: it is pinned to a minor range
because its bit order changed between minors, and golden tests on bit and word order guard
it (``tests/unit/test_adam_protocol.py``).
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Awaitable, Callable, Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

from supervisor.core.errors import DeviceIOError, DeviceTimeout

if TYPE_CHECKING:
    from pymodbus.client import AsyncModbusTcpClient
    from pymodbus.pdu import ModbusPDU

# pymodbus (and through its package, its simulator's web server) is imported by the master
# that talks, not with the codes: ``supervisor check`` of an I/O map reads the codes only
# (issue 30).
_PYMODBUS_MODULES: Final = ("pymodbus.client", "pymodbus.exceptions")

FC_READ_COILS: Final = 1
FC_READ_HOLDING_REGISTERS: Final = 3
FC_READ_INPUT_REGISTERS: Final = 4
FC_WRITE_SINGLE_COIL: Final = 5
FC_WRITE_MULTIPLE_COILS: Final = 15
FC_WRITE_SINGLE_REGISTER: Final = 6
FC_WRITE_MULTIPLE_REGISTERS: Final = 16

# Modbus exception codes (Modbus Application Protocol V1.1b3 §7) that units commonly answer;
# the full table is :data:`EXCEPTION_MEANINGS`.
EXC_ILLEGAL_FUNCTION: Final = 0x01
EXC_ILLEGAL_ADDRESS: Final = 0x02
EXC_ILLEGAL_VALUE: Final = 0x03
EXC_DEVICE_FAILURE: Final = 0x04

EXCEPTION_MEANINGS: Final[Mapping[int, str]] = MappingProxyType(
    {
        # Worded as pymodbus names them (``ExcCodes``), so log texts read the same as when
        # the driver took them from pymodbus; a golden test keeps the codes in step.
        0x01: "illegal function",
        0x02: "illegal address",
        0x03: "illegal value",
        0x04: "device failure",
        0x05: "acknowledge",
        0x06: "device busy",
        0x07: "negative acknowledge",
        0x08: "memory parity error",
        0x0A: "gateway path unavailable",
        0x0B: "gateway no response",
    }
)


def quiet_pymodbus() -> None:
    """pymodbus logs its servers' and clients' routine at INFO (and a second server's
    identical line as "Repeating...."): the bench's own log says what matters, so its
    INFO is left out unless someone set a level for it."""
    pymodbus_log = logging.getLogger("pymodbus")
    if pymodbus_log.level == logging.NOTSET:
        pymodbus_log.setLevel(logging.WARNING)


class ModbusExceptionAnswer(Exception):
    """The unit answered a request with a Modbus exception (function code | 0x80).

    Slot-local, not a comm loss: the link is fine, the unit refused this one request (an
    address outside its modules, a module that failed). Deliberately not a
    :class:`~supervisor.core.errors.SupervisorError`, so that it can never be mistaken
    for a lost device: a driver turns it into the affected points' BAD ``DEVICE_ERROR``.
    """

    def __init__(self, code: int, what: str = "") -> None:
        self.code = code
        self.what = what
        meaning = EXCEPTION_MEANINGS.get(code, "unknown code")
        text = f"Modbus exception 0x{code:02X} ({meaning})"
        super().__init__(f"{what}: {text}" if what else text)

    def about(self, what: str) -> ModbusExceptionAnswer:
        """The same answer, its message naming the request ``what``."""
        return ModbusExceptionAnswer(self.code, what)


class ModbusTcpMaster:
    """Modbus TCP to ``host:port``, device ``unit_id``, through pymodbus's async client.

    Answers are plain Python values (addresses are 0-based PDU addresses); failures are
    typed: :class:`ModbusExceptionAnswer` (the unit refused this request),
    :class:`~supervisor.core.errors.DeviceTimeout` (no answer within ``timeout_s``),
    :class:`~supervisor.core.errors.DeviceIOError` (refused, lost, closed).

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
        # pymodbus is imported when a master is made (the bench's wiring, before any loop
        # runs), so that its first connect, on the running loop, imports nothing (tens of
        # ms); connect() and _call() then only look their names up.
        for module in _PYMODBUS_MODULES:
            importlib.import_module(module)

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    async def connect(self) -> None:
        from pymodbus.client import AsyncModbusTcpClient

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
        """FC01: the states of ``count`` coils from ``address``."""
        rsp = await self._call(lambda c: c.read_coils(address, count=count, device_id=self.unit_id))
        # pymodbus pads the bits to whole bytes: only the coils asked for count.
        return [bool(b) for b in rsp.bits[:count]]

    async def read_holding_registers(self, address: int, count: int) -> list[int]:
        """FC03: ``count`` 16-bit unsigned values from ``address``."""
        rsp = await self._call(
            lambda c: c.read_holding_registers(address, count=count, device_id=self.unit_id)
        )
        return [int(r) & 0xFFFF for r in rsp.registers]

    async def read_input_registers(self, address: int, count: int) -> list[int]:
        """FC04: ``count`` 16-bit unsigned values from ``address``."""
        rsp = await self._call(
            lambda c: c.read_input_registers(address, count=count, device_id=self.unit_id)
        )
        return [int(r) & 0xFFFF for r in rsp.registers]

    async def write_coil(self, address: int, value: bool) -> None:
        """FC05: set one coil (the unit echoes the request)."""
        await self._call(lambda c: c.write_coil(address, value, device_id=self.unit_id))

    async def write_register(self, address: int, value: int) -> None:
        """FC06: set one holding register (the unit echoes the request)."""
        await self._call(lambda c: c.write_register(address, value, device_id=self.unit_id))

    async def _call(
        self, request: Callable[[AsyncModbusTcpClient], Awaitable[ModbusPDU]]
    ) -> ModbusPDU:
        """One transaction, pymodbus's failures mapped to the link's."""
        from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

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
