"""ADAM-5000/TCP remote I/O over Modbus TCP (seed 002 bench: 5017, 2×5018, 5060).

Points per slot ``n`` (channel ``k`` from 0):

- 5017: ``slot{n}.ai{k}`` (in, float, V), k = 0..7;
- 5018: ``slot{n}.tc{k}`` (in, float, °C), k = 0..6; burn-out (open wire) → BAD
  ``SENSOR_FAILURE`` with value ``None``;
- 5060 / 5069: ``slot{n}.do{k}`` (out, bool, True = relay energised) and
  ``slot{n}.do{k}_fb`` (in, bool, coil read back), k = 0..5 / 0..7.

Each poll reads one block per slot that is due
(:data:`~supervisor.devices.adam.protocol.ANALOG_READ_FUNCTION` for analog slots, FC01 for
relay slots): a slot may have its own period (``AdamModule.poll_period_s``), so that the
slot holding the e-stop sense is read at the scan rate while the thermocouples stay slow
(docs/design.md "Safety"); the driver polls at its fastest slot's period, and every sample keeps
its own acquisition time (stale detection works per slot). A Modbus exception answer makes
that slot's inputs BAD ``DEVICE_ERROR`` (code in ``last_error`` and ``raw_log``), a short
answer makes them BAD ``COMM_FAILURE``; other slots are unaffected. A lost or silent
connection raises :class:`DeviceIOError`, so :class:`PolledDriver` marks every input BAD
and reconnects with backoff. Relay writes are FC05 then an FC01 read-back, which also
refreshes that relay's ``_fb`` input at once; a mismatch is a fault. The safe state
switches every relay off (de-energised = contactor open).

With ``host_watchdog_s`` every connect arms the unit's host (communication) watchdog: safe
values 0 (every relay off) for each relay slot, then the timeout, read back. If this driver
stops talking for ``host_watchdog_s``, the unit switches the relays off by itself, so the
contactor opens when the supervisor dies. Every request keeps it alive (or, if the unit
wants it, a "host OK" write on every poll: ``HOST_WATCHDOG_NEEDS_REFRESH``). A clean close
leaves it armed: the relays are already off, and it is the last layer if they were not.
The register addresses are UNVERIFIED (:mod:`supervisor.devices.adam.protocol`).

The Modbus link is injected (:mod:`supervisor.devices.adam.transport`): Modbus TCP through
pymodbus for a real unit, or a direct call into a simulated unit in the same process.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Mapping
from typing import Final, TypeVar

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError, SupervisorError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.adam.catalog import MIN_POLL_PERIOD_5017_S, SLOTS, slot_points
from supervisor.devices.adam.config import HOST_WATCHDOG_POLL_RATIO
from supervisor.devices.adam.protocol import (
    ANALOG_READ_FUNCTION,
    HOST_WATCHDOG_NEEDS_REFRESH,
    HOST_WATCHDOG_REFRESH_REGISTER,
    HOST_WATCHDOG_REFRESH_VALUE,
    HOST_WATCHDOG_SAFE_VALUES_REGISTER,
    HOST_WATCHDOG_TIMEOUT_REGISTER,
    AdamModule,
    analog_register,
    coil_address,
    host_watchdog_counts,
    is_burnout,
    raw_to_value,
)
from supervisor.devices.adam.transport import ModbusLink
from supervisor.devices.base import PolledDriver
from supervisor.fieldbus.modbus import (
    FC_READ_COILS,
    FC_READ_HOLDING_REGISTERS,
    FC_WRITE_SINGLE_COIL,
    FC_WRITE_SINGLE_REGISTER,
    ModbusExceptionAnswer,
)

log = logging.getLogger(__name__)

__all__ = ["MIN_POLL_PERIOD_5017_S", "AdamDriver", "AdamModule"]


T = TypeVar("T")

DUE_SLACK_FRACTION: Final = 0.25
"""A slot is due when its deadline falls within this fraction of the fastest period: a poll
that wakes a hair early (timer resolution) still reads it, instead of one period late."""


class AdamDriver(PolledDriver):
    """Poll an ADAM-5000/TCP through ``link``: ``modules`` maps slot (0..7) →
    :class:`AdamModule`. The link carries the unit id and the answer timeout.

    ``poll_period_s`` is the period of the slots that do not set their own; the driver polls
    at the fastest slot's period. ``host_watchdog_s``: arm the unit's host watchdog at every
    connect (None: leave it alone). ``host_watchdog_refresh``: write "host OK" on every poll.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        link: ModbusLink,
        modules: dict[int, AdamModule],
        poll_period_s: float = 0.2,
        *,
        host_watchdog_s: float | None = None,
        host_watchdog_refresh: bool = HOST_WATCHDOG_NEEDS_REFRESH,
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
        self._slot_period_s = {
            s: poll_period_s if m.poll_period_s is None else m.poll_period_s
            for s, m in self._modules.items()
        }
        fastest = min(self._slot_period_s.values())
        self._due_slack_s = DUE_SLACK_FRACTION * fastest
        self._slot_next_t = {s: float("-inf") for s in self._modules}
        self._wd_counts: int | None = None
        if host_watchdog_s is not None:
            try:
                self._wd_counts = host_watchdog_counts(host_watchdog_s)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
            if host_watchdog_s < HOST_WATCHDOG_POLL_RATIO * fastest * (1 - 1e-9):
                raise ValueError(
                    f"{name}: host_watchdog_s ({host_watchdog_s} s) must be at least "
                    f"{HOST_WATCHDOG_POLL_RATIO:g} x the fastest poll period ({fastest} s)"
                )
        self.host_watchdog_s = host_watchdog_s
        self._wd_refresh = host_watchdog_refresh and host_watchdog_s is not None
        super().__init__(name, clock, fastest)
        self._warn_fast_5017(poll_period_s)

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

    def slot_period_s(self, slot: int) -> float:
        """How often ``slot`` is read."""
        return self._slot_period_s[slot]

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
        if self._wd_counts is not None:
            try:
                await self._arm_host_watchdog(self._wd_counts)
            except BaseException:
                await self._disconnect()
                raise
        # Everything is read at the first poll after a (re)connect.
        self._slot_next_t = dict.fromkeys(self._modules, float("-inf"))
        log.info("%s: connected to %s", self.name, self._link.address)

    async def _disconnect(self) -> None:
        # The host watchdog stays armed (a clean stop has switched the relays off already;
        # if it had not, the watchdog is what switches them off).
        await self._link.close()

    async def _read(self) -> dict[str, Sample]:
        samples: dict[str, Sample] = {}
        if self._wd_refresh:
            try:
                await self._write_register(
                    "host OK", HOST_WATCHDOG_REFRESH_REGISTER, HOST_WATCHDOG_REFRESH_VALUE
                )
            except ModbusExceptionAnswer as exc:
                raise DeviceIOError(self.name, f"{exc}; host watchdog not kept alive") from exc
        now = self.clock.now()
        for slot, module in self._modules.items():
            deadline = self._slot_next_t[slot]
            period = self._slot_period_s[slot]
            if period > self.poll_period_s and now < deadline - self._due_slack_s:
                continue  # a slower slot, not due: its samples keep their acquisition time
            if deadline == float("-inf"):  # first read after a connect
                nxt = now + period
            else:  # absolute deadlines: keep the grid, skip what a late poll missed
                nxt = deadline + period
                while nxt <= now:
                    nxt += period
            self._slot_next_t[slot] = nxt
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
        # The read-back is this relay's feedback input: publish it now, not a poll later.
        self._image[f"{point}_fb"] = Sample(got, Quality.GOOD, Reason.NONE, self.clock.now())
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
    def _warn_fast_5017(self, default_period_s: float) -> None:
        """MIN_POLL_PERIOD_5017_S: a 5017 polled faster than it converts re-reads old values.
        By accident (the device's default period) that is a warning; chosen for the slot
        (a level such as the e-stop sense, where re-reading is the point) it is said once."""
        for slot, module in self._modules.items():
            period = self._slot_period_s[slot]
            if module.kind != "5017" or period >= MIN_POLL_PERIOD_5017_S:
                continue
            if module.poll_period_s is None:
                log.warning(
                    "%s: poll_period_s=%.3f s is faster than the 5017 in slot %d converts"
                    " (about %.0f samples/s in total): values repeat",
                    self.name,
                    default_period_s,
                    slot,
                    1.0 / MIN_POLL_PERIOD_5017_S,
                )
            else:
                log.info(
                    "%s: slot %d (5017) read every %.3f s on purpose, faster than it converts"
                    " (about %.0f samples/s in total): a level is seen as soon as it is"
                    " converted; values repeat in between",
                    self.name,
                    slot,
                    period,
                    1.0 / MIN_POLL_PERIOD_5017_S,
                )

    async def _arm_host_watchdog(self, counts: int) -> None:
        """Safe values first (every relay off), then the timeout, read back: from here on a
        silent host gets its relays switched off by the unit itself."""
        try:
            for slot, module in self._modules.items():
                if module.spec.family != "relay":
                    continue
                await self._write_register(
                    f"host watchdog safe values slot{slot}",
                    HOST_WATCHDOG_SAFE_VALUES_REGISTER + slot,
                    0,
                )
            reg = HOST_WATCHDOG_TIMEOUT_REGISTER
            await self._write_register("host watchdog timeout", reg, counts)
            what = f"host watchdog timeout FC{FC_READ_HOLDING_REGISTERS:02d} @{reg}x1"
            back = await self._request(what, lambda link: link.read_holding_registers(reg, 1))
        except ModbusExceptionAnswer as exc:
            raise DeviceIOError(
                self.name,
                f"host watchdog not armed: {exc} (its register addresses are UNVERIFIED, see"
                " supervisor/devices/adam/protocol.py; or set host_watchdog_s: null)",
            ) from exc
        self.raw_log.append(f"{what} -> {back}")
        if back[:1] != [counts]:
            raise DeviceIOError(
                self.name, f"host watchdog not armed: wrote {counts}, read back {back}"
            )
        log.info(
            "%s: host watchdog armed: every relay off after %g s without a request",
            self.name,
            self.host_watchdog_s,
        )

    async def _write_register(self, name: str, register: int, value: int) -> None:
        what = f"{name} FC{FC_WRITE_SINGLE_REGISTER:02d} @{register}={value}"
        await self._request(what, lambda link: link.write_register(register, value))
        self.raw_log.append(f"{what} -> ok")

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
