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
backoff. Relay writes are FC05 then an FC01 read-back; a mismatch is a fault. The safe state
switches every relay off (de-energised = contactor open).

The Modbus link is injected (:mod:`supervisor.devices.adam.transport`): Modbus TCP through
pymodbus for a real unit, or a direct call into a simulated unit in the same process.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Mapping
from typing import TypeVar

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError, SupervisorError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.config import MIN_POLL_PERIOD_5017_S, SLOTS, slot_points
from supervisor.devices.adam.protocol import (
    ANALOG_READ_FUNCTION,
    FC_READ_COILS,
    FC_WRITE_SINGLE_COIL,
    AdamModule,
    ModbusExceptionAnswer,
    analog_register,
    coil_address,
    is_burnout,
    raw_to_value,
)
from supervisor.devices.adam.transport import ModbusLink
from supervisor.devices.base import PolledDriver

log = logging.getLogger(__name__)

__all__ = ["MIN_POLL_PERIOD_5017_S", "AdamDriver", "AdamModule"]


T = TypeVar("T")


class AdamDriver(PolledDriver):
    """Poll an ADAM-5000/TCP through ``link``: ``modules`` maps slot (0..7) →
    :class:`AdamModule`. The link carries the unit id and the answer timeout."""

    def __init__(
        self,
        name: str,
        clock: Clock,
        link: ModbusLink,
        modules: dict[int, AdamModule],
        poll_period_s: float = 0.2,
    ) -> None:
        if not modules:
            raise ValueError(f"{name}: at least one module is needed")
        for slot, module in modules.items():
            if isinstance(slot, bool) or slot not in SLOTS:
                raise ValueError(f"{name}: ADAM slot must be 0..{SLOTS[-1]}, got {slot!r}")
            if not isinstance(module, AdamModule):
                raise TypeError(f"{name}: slot {slot}: expected AdamModule, got {module!r}")
        self._link = link
        self._modules = {s: modules[s] for s in sorted(modules)}
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

    @property
    def link(self) -> ModbusLink:
        """The Modbus link the composition root gave it."""
        return self._link

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
        await self._link.connect()
        log.info("%s: connected to %s", self.name, self._link.address)

    async def _disconnect(self) -> None:
        await self._link.close()

    async def _read(self) -> dict[str, Sample]:
        samples: dict[str, Sample] = {}
        for slot, module in self._modules.items():
            try:
                samples.update(await self._read_slot(slot, module))
            except ModbusExceptionAnswer as exc:
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
            await self._request(what, lambda link: link.write_coil(address, want))
            what = f"{point} FC{FC_READ_COILS:02d} @{address}x1"
            bits = await self._request(what, lambda link: link.read_coils(address, 1))
        except ModbusExceptionAnswer as exc:
            raise DeviceIOError(self.name, f"{exc}; write did not verify") from exc
        if not bits:
            raise ProtocolError(self.name, f"{what}: no coil in the answer")
        got = bits[0]
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
        if not self._link.connected:
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
    async def _request(self, what: str, call: Callable[[ModbusLink], Awaitable[T]]) -> T:
        """One Modbus transaction; the link's errors come back naming the request ``what``:
        :class:`DeviceIOError` / :class:`DeviceTimeout` for the link, and
        :class:`ModbusExceptionAnswer` (logged in ``raw_log``) for a refused request."""
        try:
            return await call(self._link)
        except ModbusExceptionAnswer as exc:
            self.raw_log.append(f"{what} -> exception 0x{exc.code:02X}")
            raise exc.about(what) from exc
        except DeviceIOError as exc:
            detail = str(exc).removeprefix(f"{exc.device}: ")
            error = DeviceTimeout if isinstance(exc, DeviceTimeout) else DeviceIOError
            raise error(self.name, f"{what}: {detail}") from exc

    async def _read_slot(self, slot: int, module: AdamModule) -> dict[str, Sample]:
        spec = module.spec
        n = spec.points
        if spec.family == "relay":
            address = coil_address(slot, 0)
            what = f"slot{slot} FC{FC_READ_COILS:02d} @{address}x{n}"
            bits = await self._request(what, lambda link: link.read_coils(address, n))
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
        regs = await self._request(what, lambda link: link.read_registers(address, n))
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
