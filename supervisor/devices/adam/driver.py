"""ADAM-5000/TCP remote I/O over Modbus TCP (seed 002 bench: 5017, 2×5018, 5060).

Points per slot ``n`` (channel ``k`` from 0):

- 5017: ``slot{n}.ai{k}`` (in, float, V), k = 0..7;
- 5018: ``slot{n}.tc{k}`` (in, float, °C), k = 0..6; burn-out (open wire) → BAD
  ``SENSOR_FAILURE`` with value ``None``;
- 5060 / 5069: ``slot{n}.do{k}`` (out, bool, True = relay energised) and
  ``slot{n}.do{k}_fb`` (in, bool, coil read back), k = 0..5 / 0..7.

Each poll reads one block per slot (:data:`~supervisor.devices.adam.protocol.ANALOG_READ_FUNCTION`
for analog slots, FC01 for relay slots). A Modbus exception answer makes that slot's inputs
BAD ``DEVICE_ERROR`` (code in ``last_error`` and ``raw_log``), a short answer makes them BAD
``COMM_FAILURE``; other slots are unaffected. A lost or silent connection raises
:class:`DeviceIOError`, so :class:`PolledDriver` marks every input BAD and reconnects with
backoff (the pymodbus client's own reconnect is off). Relay writes are FC05 then an FC01
read-back; a mismatch is a fault. The safe state switches every relay off (de-energised =
contactor open).
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Mapping

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError, SupervisorError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.config import MIN_POLL_PERIOD_5017_S, SLOTS, slot_points
from supervisor.devices.adam.protocol import (
    ANALOG_READ_FUNCTION,
    FC_READ_COILS,
    FC_READ_HOLDING_REGISTERS,
    FC_READ_INPUT_REGISTERS,
    FC_WRITE_SINGLE_COIL,
    AdamModule,
    analog_register,
    coil_address,
    is_burnout,
    raw_to_value,
)
from supervisor.devices.base import PolledDriver

log = logging.getLogger(__name__)

__all__ = ["MIN_POLL_PERIOD_5017_S", "AdamDriver", "AdamModule"]


class _ExceptionAnswer(Exception):
    """The device answered a request with a Modbus exception (slot-local, not a comm loss)."""

    def __init__(self, what: str, code: int) -> None:
        self.code = code
        try:
            meaning = ExcCodes(code).name.lower().replace("_", " ")
        except ValueError:
            meaning = "unknown code"
        super().__init__(f"{what}: Modbus exception 0x{code:02X} ({meaning})")


class AdamDriver(PolledDriver):
    """Poll an ADAM-5000/TCP: ``modules`` maps slot (0..7) → :class:`AdamModule`."""

    def __init__(
        self,
        name: str,
        clock: Clock,
        host: str,
        port: int,
        modules: dict[int, AdamModule],
        unit_id: int = 1,
        poll_period_s: float = 0.2,
        timeout_s: float = 1.0,
    ) -> None:
        if not modules:
            raise ValueError(f"{name}: at least one module is needed")
        for slot, module in modules.items():
            if isinstance(slot, bool) or slot not in SLOTS:
                raise ValueError(f"{name}: ADAM slot must be 0..{SLOTS[-1]}, got {slot!r}")
            if not isinstance(module, AdamModule):
                raise TypeError(f"{name}: slot {slot}: expected AdamModule, got {module!r}")
        if not 0 <= unit_id <= 255:
            raise ValueError(f"{name}: unit_id must be 0..255, got {unit_id!r}")
        if timeout_s <= 0:
            raise ValueError(f"{name}: timeout_s must be > 0")
        self._host = host
        self._port = port
        self._unit_id = unit_id
        self._timeout_s = timeout_s
        self._modules = {s: modules[s] for s in sorted(modules)}
        self._client: AsyncModbusTcpClient | None = None
        self._points: dict[str, PointInfo] = {}
        self._outputs: dict[str, tuple[int, int]] = {}
        self._slot_inputs: dict[int, list[str]] = {}
        for slot, module in self._modules.items():
            names: list[str] = []
            for info in slot_points(slot, module.kind):
                self._points[info.name] = info
                if info.direction == "out":
                    self._outputs[info.name] = (slot, int(info.name.rsplit("do", 1)[1]))
                else:
                    names.append(info.name)
            self._slot_inputs[slot] = names
        # Logged once per change, not on every poll.
        self._slot_fault: dict[int, str] = {}
        self._burnt: set[str] = set()
        super().__init__(name, clock, poll_period_s)
        if poll_period_s < MIN_POLL_PERIOD_5017_S and any(
            m.kind == "5017" for m in self._modules.values()
        ):
            log.warning(
                "%s: poll_period_s=%.3f s is faster than the 5017 converts (about %.0f "
                "samples/s in total): values repeat",
                self.name,
                poll_period_s,
                1.0 / MIN_POLL_PERIOD_5017_S,
            )

    # --- public surface --------------------------------------------------------
    def points(self) -> Mapping[str, PointInfo]:
        return self._points

    @property
    def modules(self) -> Mapping[int, AdamModule]:
        return self._modules

    def write(self, point: str, value: Value) -> None:
        """Queue a relay write; only ``True``/``False`` (or 1/0) are accepted."""
        if point in self._outputs and not (
            isinstance(value, bool) or (isinstance(value, int) and value in (0, 1))
        ):
            raise ValueError(f"{self.name}: {point} needs a bool, got {value!r}")
        super().write(point, value)

    # --- PolledDriver hooks ----------------------------------------------------
    async def _connect(self) -> None:
        await self._disconnect()
        client = AsyncModbusTcpClient(
            self._host,
            port=self._port,
            name=self.name,
            timeout=self._timeout_s,
            retries=0,
            reconnect_delay=0,  # PolledDriver reconnects, with backoff
        )
        self._client = client
        if not await client.connect():
            await self._disconnect()
            raise DeviceIOError(self.name, f"cannot connect to {self._host}:{self._port}")
        log.info("%s: connected to %s:%d", self.name, self._host, self._port)

    async def _disconnect(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()

    async def _read(self) -> dict[str, Sample]:
        samples: dict[str, Sample] = {}
        for slot, module in self._modules.items():
            try:
                samples.update(await self._read_slot(slot, module))
            except _ExceptionAnswer as exc:
                self._slot_failed(slot, str(exc), Reason.DEVICE_ERROR, samples)
            except ProtocolError as exc:
                message = str(exc).removeprefix(f"{self.name}: ")
                self._slot_failed(slot, message, Reason.COMM_FAILURE, samples)
            else:
                if self._slot_fault.pop(slot, None) is not None:
                    log.info("%s: slot %d answers again", self.name, slot)
        return samples

    async def _write(self, point: str, value: Value) -> None:
        slot, ch = self._outputs[point]
        want = bool(value)
        address = coil_address(slot, ch)
        what = f"{point} FC{FC_WRITE_SINGLE_COIL:02d} @{address}={int(want)}"
        try:
            await self._request(
                what, lambda c: c.write_coil(address, want, device_id=self._unit_id)
            )
            what = f"{point} FC{FC_READ_COILS:02d} @{address}x1"
            rsp = await self._request(
                what, lambda c: c.read_coils(address, count=1, device_id=self._unit_id)
            )
        except _ExceptionAnswer as exc:
            raise DeviceIOError(self.name, f"{exc}; write did not verify") from exc
        if not rsp.bits:
            raise ProtocolError(self.name, f"{what}: no coil in the answer")
        got = bool(rsp.bits[0])
        self.raw_log.append(f"{what} -> {int(got)}")
        if got != want:
            raise DeviceIOError(
                self.name, f"{point}: write did not verify (wrote {want}, read back {got})"
            )
        log.debug("%s: %s set %s", self.name, point, want)

    async def _safe(self) -> None:
        """Every relay off (de-energised = contactor open); go on past failures."""
        if not self._outputs:
            return
        if self._client is None or not self._client.connected:
            await self._connect()
        failed: list[str] = []
        for point in self._outputs:
            try:
                await self._write(point, False)
            except (SupervisorError, OSError, TimeoutError) as exc:
                log.error("%s: safe state: %s not switched off: %s", self.name, point, exc)
                failed.append(point)
        if failed:
            raise DeviceIOError(self.name, f"safe state: relay(s) not verified off: {failed}")
        log.info("%s: safe state: every relay off", self.name)

    # --- internals -------------------------------------------------------------
    async def _request(
        self, what: str, call: Callable[[AsyncModbusTcpClient], Awaitable[ModbusPDU]]
    ) -> ModbusPDU:
        """One Modbus transaction; comm failures raise DeviceIOError, exception answers
        raise :class:`_ExceptionAnswer`."""
        client = self._client
        # pymodbus would silently reconnect on its own: reconnecting is PolledDriver's job.
        if client is None or not client.connected:
            raise DeviceIOError(self.name, f"{what}: not connected")
        try:
            rsp = await call(client)
        except ConnectionException as exc:
            raise DeviceIOError(self.name, f"{what}: {exc}") from exc
        except ModbusIOException as exc:
            if "No response" in str(exc):
                raise DeviceTimeout(self.name, f"{what}: no answer in {self._timeout_s} s") from exc
            raise DeviceIOError(self.name, f"{what}: {exc}") from exc
        except ModbusException as exc:
            raise DeviceIOError(self.name, f"{what}: {exc}") from exc
        except TimeoutError as exc:
            raise DeviceTimeout(self.name, f"{what}: no answer in {self._timeout_s} s") from exc
        if rsp.isError():
            code = int(rsp.exception_code)
            answer = _ExceptionAnswer(what, code)
            self.raw_log.append(f"{what} -> exception 0x{code:02X}")
            raise answer
        return rsp

    async def _read_slot(self, slot: int, module: AdamModule) -> dict[str, Sample]:
        spec = module.spec
        n = spec.points
        if spec.family == "relay":
            address = coil_address(slot, 0)
            what = f"slot{slot} FC{FC_READ_COILS:02d} @{address}x{n}"
            rsp = await self._request(
                what, lambda c: c.read_coils(address, count=n, device_id=self._unit_id)
            )
            bits = [bool(b) for b in rsp.bits]
            self.raw_log.append(f"{what} -> {''.join(str(int(b)) for b in bits[:n])}")
            if len(bits) < n:
                raise ProtocolError(
                    self.name, f"{what}: {len(bits)} coils back for {n}", bytes(bits)
                )
            t = self.clock.now()
            return {
                f"slot{slot}.do{ch}_fb": Sample(bits[ch], Quality.GOOD, Reason.NONE, t)
                for ch in range(n)
            }

        address = analog_register(slot, 0)
        what = f"slot{slot} FC{ANALOG_READ_FUNCTION:02d} @{address}x{n}"
        rsp = await self._request(what, lambda c: self._read_registers(c, address, n))
        regs = [int(r) & 0xFFFF for r in rsp.registers]
        raw = b"".join(r.to_bytes(2, "big") for r in regs)
        self.raw_log.append(f"{what} -> {raw.hex()}")
        if len(regs) < n:
            raise ProtocolError(self.name, f"{what}: {len(regs)} registers back for {n}", raw)
        t = self.clock.now()
        samples: dict[str, Sample] = {}
        for ch in range(n):
            code = regs[ch]
            if spec.family == "thermocouple":
                point = f"slot{slot}.tc{ch}"
                if is_burnout(code, module.raw_format):
                    if point not in self._burnt:
                        log.warning(
                            "%s: %s burn-out (raw 0x%04X): open thermocouple?",
                            self.name,
                            point,
                            code,
                        )
                        self._burnt.add(point)
                    samples[point] = Sample(None, Quality.BAD, Reason.SENSOR_FAILURE, t)
                    continue
                if point in self._burnt:
                    log.info("%s: %s reads again", self.name, point)
                    self._burnt.discard(point)
            else:
                point = f"slot{slot}.ai{ch}"
            value = raw_to_value(code, module.kind, module.raw_format)
            samples[point] = Sample(value, Quality.GOOD, Reason.NONE, t)
        return samples

    def _read_registers(
        self, client: AsyncModbusTcpClient, address: int, count: int
    ) -> Awaitable[ModbusPDU]:
        if ANALOG_READ_FUNCTION == FC_READ_INPUT_REGISTERS:
            return client.read_input_registers(address, count=count, device_id=self._unit_id)
        assert ANALOG_READ_FUNCTION == FC_READ_HOLDING_REGISTERS
        return client.read_holding_registers(address, count=count, device_id=self._unit_id)

    def _slot_failed(
        self, slot: int, message: str, reason: Reason, samples: dict[str, Sample]
    ) -> None:
        self.last_error = message
        if self._slot_fault.get(slot) != message:
            log.warning("%s: %s", self.name, message)
        self._slot_fault[slot] = message
        for point in self._slot_inputs[slot]:
            old = self._image.get(point)
            value, t = (old.value, old.t) if old is not None else (None, 0.0)
            # Keep the last value for diagnostics, never let it look GOOD.
            samples[point] = Sample(value, Quality.BAD, reason, t)
