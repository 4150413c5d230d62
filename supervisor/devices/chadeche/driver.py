"""Chadèche boards (seed 000): constant current charge/discharge and cell voltage over SPI.

One driver per SPI bus, up to four boards (addresses 0..3). Points per board ``n``:

- ``b{n}.voltage`` (in, V): cell voltage from the MCP3201, calibrated (``-s``/``-o``).
- ``b{n}.current`` (in, A, + charge): the current the board is commanded to drive after the
  last successful write. The board has NO current sensor (seed §II.B: the DAC sets a
  constant current source, only the voltage is measured), so this is a command echo through
  the ``-1``/``-2`` calibration, not a measurement.
- ``b{n}.charging`` (in, bool): relay latch position last written.
- ``b{n}.current_set`` (out, A, + charge / − discharge), ``b{n}.led_duty`` (out, 0..1).
- ``b{n}.temperature`` (in, degC), only with a ``temperature_probe``: a SIMULATED board's
  cell temperature (the boards have no sensor; see ``sim_board_points``).

The DAC and the latch are write-only chips: a write is "verified" when its transfers
completed without error; nothing can be read back.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, ProtocolError, SupervisorError
from supervisor.core.locks import CountingLock
from supervisor.core.quality import Quality, Reason
from supervisor.devices.base import PolledDriver
from supervisor.devices.chadeche.bus import BoardClaim, ChadecheBus, claim_board
from supervisor.devices.chadeche.config import (
    BOARD_ADDRESSES,
    MAX_CURRENT_A,
    board_points,
    sim_board_points,
)
from supervisor.devices.chadeche.protocol import (
    ADC_MAX_CODE,
    ADC_READ,
    DAC_MAX_CODE,
    Calibration,
    Chip,
    DacChannel,
    adc_code_to_voltage_v,
    current_to_dac_command,
    dac_code_to_current_a,
    dac_transfer,
    decode_adc_reply,
    encode_latch,
)

log = logging.getLogger(__name__)
_ADC = Chip.ADC
_GOOD, _NONE = Quality.GOOD, Reason.NONE
"""Enum members as module constants: a class attribute lookup per use otherwise."""

RELAY_SETTLE_S = 0.02
"""Wait between flipping the relay latch and raising the current again, so the 2RT relay
(seed §II.C.3) has finished moving and never makes contact under current. Small signal
relays operate in about 10 ms; UNVERIFIED for the board's Finder relay."""


_Kept = tuple[tuple[bytes, int, bool, bool], Sample, Sample, Sample]
"""A board's memo of its last GOOD reading (``_Board.kept``)."""


@dataclass(slots=True)
class _Board:
    address: int
    cal: Calibration
    # Point names, built once (read every poll).
    voltage_point: str = ""
    current_point: str = ""
    charging_point: str = ""
    temperature_point: str = ""
    # What the hardware should be (re-asserted on every (re)connect; zeroed by safe state).
    target_code: int = 0
    target_charging: bool = False
    target_led_code: int = 0
    # What the last successful transfers set.
    dac_a_code: int = 0
    charging: bool = False
    clamped: bool = False
    sensor_failed: bool = False

    # The direct poll's memory of its last reading (``ChadecheDriver.poll_now``): the
    # ADC reply, its raw-log line and its calibrated voltage; the current echo and the DAC
    # state it was computed for. Each is computed again as soon as its input differs (the
    # calibration of a board never changes after construction).
    last_adc_reply: bytes | None = None
    last_adc_line: str = ""
    last_adc_code: int = -1
    last_adc_voltage_v: float = 0.0
    last_current_key: tuple[int, bool, Calibration] | None = None
    last_current_a: float = 0.0
    # The direct poll's memory of a reading whose voltage, current and charging samples
    # were all GOOD: what they are a function of (the ADC reply, the DAC code, the relay
    # and the clamp) and the three samples the image got (made or kept). While those
    # inputs are equal and the image still holds these very samples, a poll keeps them
    # as they are (``ChadecheDriver.poll_now``); samples change in place only by time.
    kept: _Kept | None = None

    def __post_init__(self) -> None:
        p = f"b{self.address}."
        self.voltage_point = p + "voltage"
        self.current_point = p + "current"
        self.charging_point = p + "charging"
        self.temperature_point = p + "temperature"

    @property
    def current_a(self) -> float:
        magnitude = dac_code_to_current_a(self.dac_a_code, self.cal)
        if magnitude == 0.0:
            return 0.0
        return magnitude if self.charging else -magnitude

    def current_echo_a(self) -> float:
        """``current_a``, computed again only when the DAC code, the relay or the
        calibration changed since the last call."""
        key = (self.dac_a_code, self.charging, self.cal)
        if key != self.last_current_key:
            self.last_current_key = key
            self.last_current_a = self.current_a
        return self.last_current_a


class ChadecheDriver(PolledDriver):
    """Poll the boards' ADCs; apply current and LED commands safely.

    ``relay_settle_s``: wait after flipping the relay before raising the current (slept on
    ``clock``, so it advances a virtual clock). ``lock_dir``: claim every board with
    :func:`claim_board` there; boards are always claimed (default directory) when ``bus`` is
    a blocking (real) bus. ``close()`` releases the claims, and closes the bus when
    ``owns_bus`` (it was opened for this driver), but leaves outputs as they are.
    ``temperature_probe``: the simulator's thermometer on each board's cell (address →
    degC, None if unknown); given only for a simulated bus, it adds the simulation-only
    ``b{n}.temperature`` points.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        bus: ChadecheBus,
        boards: Mapping[int, Calibration],
        poll_period_s: float = 0.1,
        *,
        relay_settle_s: float = RELAY_SETTLE_S,
        lock_dir: str | Path | None = None,
        owns_bus: bool = False,
        temperature_probe: Callable[[int], float | None] | None = None,
    ) -> None:
        if not boards:
            raise ValueError(f"{name}: at least one board is needed")
        for address in boards:
            if isinstance(address, bool) or address not in BOARD_ADDRESSES:
                raise ValueError(f"{name}: Chadèche board address must be 0..3, got {address!r}")
        if relay_settle_s < 0:
            raise ValueError(f"{name}: relay_settle_s must be >= 0")
        self._bus = bus
        self._owns_bus = owns_bus
        # spidev blocks: run it in a worker thread. The simulator is fast and must stay
        # deterministic on a virtual clock: call it directly.
        self._blocking_bus = bus.blocking
        self._direct = not self._blocking_bus
        """Poll and flush an in-process bus without awaiting (``poll``): False only in the
        tests that check it against the awaited path."""
        self._relay_settle_s = relay_settle_s
        self._boards = {a: _Board(a, boards[a]) for a in sorted(boards)}
        self._temperature_probe = temperature_probe
        self._points: dict[str, PointInfo] = {}
        self._outputs: dict[str, tuple[int, str]] = {}
        for a in self._boards:
            sim_only = sim_board_points(a) if temperature_probe is not None else []
            for info in board_points(a) + sim_only:
                self._points[info.name] = info
                if info.direction == "out":
                    self._outputs[info.name] = (a, info.name.split(".", 1)[1])
        # Output sequences (zero, flip, raise) and the safe state must not interleave.
        self._io_lock = CountingLock()
        super().__init__(name, clock, poll_period_s)
        # One owner per board (seed §III.G.2): always on real hardware, or when asked.
        self._claims: list[BoardClaim] = []
        if lock_dir is not None or self._blocking_bus:
            try:
                for a in self._boards:
                    self._claims.append(claim_board(a, lock_dir))
            except DeviceIOError:
                self._release_claims()
                raise

    # --- public surface --------------------------------------------------------
    def points(self) -> Mapping[str, PointInfo]:
        return self._points

    def write(self, point: str, value: Value) -> None:
        """Queue a write; refuses non-numbers and NaN/inf at once (the caller's bug)."""
        if point in self._outputs and (isinstance(value, bool | str) or not math.isfinite(value)):
            raise ValueError(f"{self.name}: {point} needs a finite number, got {value!r}")
        super().write(point, value)

    async def poll(self) -> None:
        """:meth:`PolledDriver.poll`, without an await when :meth:`poll_now` can."""
        if not self.poll_now():
            await super().poll()

    def poll_now(self) -> bool:
        """On an in-process bus, while connected with nothing to send and nobody holding
        or awaiting the I/O locks, :meth:`PolledDriver.poll` without an await (True):
        acquiring such a lock never yields, there is nothing to write, and the simulated
        bus answers at once, so the awaited path would do exactly this (issue 13: a dry
        run polls 87 000 times; the equivalence is tested in test_chadeche_direct.py).
        Otherwise nothing (False): ``poll()`` must be awaited. The scan engine's lockstep
        calls it directly (``scan/engine.py::DirectDriver``).

        The read is :meth:`_read`'s: the same transfers, raw-log lines and samples. What
        depends only on the ADC reply (its code, its raw-log line, the calibrated
        voltage) is computed again only when the reply changed (:meth:`_new_adc_reply`):
        a cell's voltage moves by one ADC step (1 mV) every few minutes of a slow charge.
        A point that reads the same value (the very object), GOOD and for the same
        reason as its sample in the image keeps that sample, stamped with this poll's
        time once every board has been read (the scan's input copy then only moves its
        tag's source time, ``scan/engine.py``); when none of a board's three such points
        changed, its memo (``_Board.kept``) says so in one test instead of three
        (:meth:`_read_points` is the point-by-point reading).
        """
        if not (
            self._direct
            and self._connected
            and not self._pending
            and not self._lost_logged
            and not self._io_cycle.users  # ``free()``, without the call
            and not self._io_lock.users
        ):
            return False
        now = self.clock.now()
        samples: dict[str, Sample] = {}
        again: list[tuple[_Kept, float]] = []
        image = self._image
        probe = self._temperature_probe
        try:
            for board in self._boards.values():
                try:
                    reply = self._bus.transfer(board.address, _ADC, ADC_READ)
                except OSError as exc:
                    raise DeviceIOError(self.name, f"board {board.address} ADC: {exc}") from exc
                if reply != board.last_adc_reply:
                    self._new_adc_reply(board, reply)
                self.raw_log.append(board.last_adc_line)
                t = self.clock.now()
                kept = board.kept
                if not (
                    kept is not None
                    and kept[0] == (reply, board.dac_a_code, board.charging, board.clamped)
                    # (The image has every input point from the start: ``PolledDriver``.)
                    and image[board.voltage_point] is kept[1]
                    and image[board.current_point] is kept[2]
                    and image[board.charging_point] is kept[3]
                ):
                    kept = self._read_points(board, reply, t, samples)
                again.append((kept, t))
                if probe is not None:
                    temp = probe(board.address)  # a new reading (a new float) every poll
                    samples[board.temperature_point] = (
                        Sample(None, Quality.BAD, Reason.SENSOR_FAILURE, t)
                        if temp is None
                        else Sample(temp, _GOOD, _NONE, t)
                    )
        except (TimeoutError, SupervisorError, OSError) as exc:
            self._fail(exc, now)
            return True
        # Every board read: nothing can fail any more. (A sample made by this poll
        # already has its time.)
        for (_, voltage, current, charging), t in again:
            voltage.t = current.t = charging.t = t
        self.polls += 1
        image.update(samples)
        return True

    async def flush(self) -> None:
        """:meth:`PolledDriver.flush`, without an await when :meth:`flush_now` can."""
        if not self.flush_now():
            await super().flush()

    def flush_now(self) -> bool:
        """:meth:`PolledDriver.flush` does nothing without a queued write while
        connected; on an in-process bus with the I/O lock free that is known without
        taking it (True: done). False: ``flush()`` must be awaited."""
        return self._direct and not (self._connected and self._pending) and not self._io_cycle.users

    # --- PolledDriver hooks ----------------------------------------------------
    async def _connect(self) -> None:
        # The latch powers up in an unknown state and the hardware may have missed commands
        # while the bus was down: re-assert every board's target in the safe order.
        async with self._io_lock:
            for board in self._boards.values():
                await self._drive(board, board.target_code, board.target_charging, force=True)
                await self._xfer(
                    board.address, Chip.DAC, dac_transfer(DacChannel.B, board.target_led_code)
                )

    async def _disconnect(self) -> None:
        # Outputs are left as they are: the caller runs safe_state() first if it wants.
        self._release_claims()
        if self._owns_bus:
            self._bus.close()

    async def _read(self) -> dict[str, Sample]:
        samples: dict[str, Sample] = {}
        async with self._io_lock:
            for board in self._boards.values():
                code = decode_adc_reply(await self._xfer(board.address, Chip.ADC, ADC_READ))
                t = self.clock.now()
                p = f"b{board.address}."
                samples[p + "voltage"] = self._voltage_sample(board, code, t)
                reason = Reason.CLAMPED if board.clamped else Reason.NONE
                samples[p + "current"] = Sample(board.current_a, Quality.GOOD, reason, t)
                samples[p + "charging"] = Sample(board.charging, Quality.GOOD, Reason.NONE, t)
                if self._temperature_probe is not None:
                    temp = self._temperature_probe(board.address)
                    samples[p + "temperature"] = (
                        Sample(None, Quality.BAD, Reason.SENSOR_FAILURE, t)
                        if temp is None
                        else Sample(temp, Quality.GOOD, Reason.NONE, t)
                    )
        return samples

    def _new_adc_reply(self, board: _Board, reply: bytes) -> None:
        """What a new ADC ``reply`` of ``board`` means, kept for the polls that get the
        same reply again (:meth:`poll_now`): its code, raw-log line and calibrated
        voltage. A reply of the wrong length is logged and raises as :meth:`_xfer`."""
        address = board.address
        if len(reply) != len(ADC_READ):
            self.raw_log.append(f"b{address} ADC >{ADC_READ.hex()} <{reply.hex()}")
            raise ProtocolError(
                self.name,
                f"board {address} ADC: {len(reply)} bytes back for {len(ADC_READ)} sent",
                reply,
            )
        code = decode_adc_reply(reply)
        board.last_adc_reply = reply
        board.last_adc_line = f"b{address} ADC >{ADC_READ.hex()} <{reply.hex()}"
        board.last_adc_code = code
        if code < ADC_MAX_CODE:
            board.last_adc_voltage_v = adc_code_to_voltage_v(code, board.cal)

    def _read_points(
        self, board: _Board, reply: bytes, t: float, samples: dict[str, Sample]
    ) -> _Kept:
        """The voltage, current and charging points of ``board`` read at ``t`` after
        ``reply`` (:meth:`poll_now`), point by point: a new sample into ``samples``, or
        the image's own one kept when it reads the same value object, GOOD, for the same
        reason. Returns the three samples (with what they were read for), to be stamped
        with ``t``; the board keeps them as its memo (``_Board.kept``) if all are GOOD."""
        image = self._image
        code = board.last_adc_code
        # The same test for each point, written out (a call per point cost more than
        # the sample it saves).
        if code >= ADC_MAX_CODE or board.sensor_failed:
            voltage = samples[board.voltage_point] = self._voltage_sample(board, code, t)
            good = False
        else:
            value = board.last_adc_voltage_v
            voltage = image[board.voltage_point]
            if not (
                voltage.value is value and voltage.quality is _GOOD and voltage.reason is _NONE
            ):
                voltage = samples[board.voltage_point] = Sample(value, _GOOD, _NONE, t)
            good = True
        # ``board.current_echo_a()``: its cached answer while the DAC code, the relay
        # and the calibration are the very ones it was computed for.
        key = board.last_current_key
        if (
            key is not None
            and key[0] == board.dac_a_code
            and key[1] is board.charging
            and key[2] is board.cal
        ):
            value = board.last_current_a
        else:
            value = board.current_echo_a()
        reason = Reason.CLAMPED if board.clamped else _NONE
        current = image[board.current_point]
        if not (current.value is value and current.quality is _GOOD and current.reason is reason):
            current = samples[board.current_point] = Sample(value, _GOOD, reason, t)
        charging = image[board.charging_point]
        if not (
            charging.value is board.charging
            and charging.quality is _GOOD
            and charging.reason is _NONE
        ):
            charging = samples[board.charging_point] = Sample(board.charging, _GOOD, _NONE, t)
        kept = (
            (reply, board.dac_a_code, board.charging, board.clamped),
            voltage,
            current,
            charging,
        )
        board.kept = kept if good else None
        return kept

    async def _write(self, point: str, value: Value) -> None:
        address, kind = self._outputs[point]
        board = self._boards[address]
        assert not isinstance(value, str)  # checked in write()
        async with self._io_lock:
            if kind == "current_set":
                await self._set_current(board, float(value))
            else:
                await self._set_led(board, float(value))

    async def _safe(self) -> None:
        # Targets first, so a reconnect after a failed attempt also comes back at 0 A.
        for board in self._boards.values():
            board.target_code = 0
        failed: list[int] = []
        async with self._io_lock:
            for board in self._boards.values():
                try:
                    await self._xfer(board.address, Chip.DAC, dac_transfer(DacChannel.A, 0))
                except (SupervisorError, OSError) as exc:
                    log.error(
                        "%s: board %d: could not zero the current: %s",
                        self.name,
                        board.address,
                        exc,
                    )
                    failed.append(board.address)
                    continue
                board.dac_a_code = 0
                board.clamped = False
        if failed:
            raise DeviceIOError(self.name, f"current not zeroed on board(s) {failed}")

    # --- internals -------------------------------------------------------------
    async def _set_current(self, board: _Board, current_a: float) -> None:
        magnitude = abs(current_a)
        clamped = magnitude > MAX_CURRENT_A
        if clamped:
            # The I/O map and the channel limits clamp first; this is the hardware last line.
            log.warning(
                "%s: board %d: %.4f A requested, clamped to %.3f A",
                self.name,
                board.address,
                current_a,
                MAX_CURRENT_A,
            )
            magnitude = MAX_CURRENT_A
        command = current_to_dac_command(magnitude, board.cal)
        if command.clamped:
            log.warning(
                "%s: board %d: calibrated command for %.4f A exceeds 400 mA, DAC clamped to %d",
                self.name,
                board.address,
                magnitude,
                command.code,
            )
        # 0 A keeps the relay where it is: no needless click.
        charging = board.target_charging if current_a == 0 else current_a > 0
        board.target_code = command.code
        board.target_charging = charging
        await self._drive(board, command.code, charging)
        board.clamped = clamped or command.clamped

    async def _set_led(self, board: _Board, duty: float) -> None:
        if not 0.0 <= duty <= 1.0:
            log.warning(
                "%s: board %d: LED duty %.3f clamped to 0..1", self.name, board.address, duty
            )
            duty = min(max(duty, 0.0), 1.0)
        code = round(duty * DAC_MAX_CODE)
        board.target_led_code = code
        await self._xfer(board.address, Chip.DAC, dac_transfer(DacChannel.B, code))

    async def _drive(
        self, board: _Board, code: int, charging: bool, *, force: bool = False
    ) -> None:
        """Set DAC A and the relay, never switching the relay under current."""
        switch = force or charging != board.charging
        if switch:
            if force or board.dac_a_code != 0:
                await self._xfer(board.address, Chip.DAC, dac_transfer(DacChannel.A, 0))
                board.dac_a_code = 0
            await self._xfer(board.address, Chip.LATCH, encode_latch(charging))
            board.charging = charging
            if code != 0 and self._relay_settle_s > 0:
                await self.clock.sleep_until(self.clock.now() + self._relay_settle_s)
        if code != 0 or not switch:
            await self._xfer(board.address, Chip.DAC, dac_transfer(DacChannel.A, code))
        board.dac_a_code = code

    async def _xfer(self, address: int, chip: Chip, data: bytes) -> bytes:
        try:
            if self._blocking_bus:
                reply = await asyncio.to_thread(self._bus.transfer, address, chip, data)
            else:
                reply = self._bus.transfer(address, chip, data)
        except OSError as exc:
            raise DeviceIOError(self.name, f"board {address} {chip.name}: {exc}") from exc
        self.raw_log.append(f"b{address} {chip.name} >{data.hex()} <{reply.hex()}")
        if len(reply) != len(data):
            raise ProtocolError(
                self.name,
                f"board {address} {chip.name}: {len(reply)} bytes back for {len(data)} sent",
                reply,
            )
        return reply

    def _voltage_sample(self, board: _Board, code: int, t: float) -> Sample:
        if code >= ADC_MAX_CODE:
            # Full scale: open input (no cell, no board: MISO floats high) or over-range.
            if not board.sensor_failed:
                log.warning(
                    "%s: board %d: ADC at full scale (open input or over-range)",
                    self.name,
                    board.address,
                )
                board.sensor_failed = True
            return Sample(None, Quality.BAD, Reason.SENSOR_FAILURE, t)
        if board.sensor_failed:
            log.info("%s: board %d: ADC back in range", self.name, board.address)
            board.sensor_failed = False
        return Sample(adc_code_to_voltage_v(code, board.cal), Quality.GOOD, Reason.NONE, t)

    def _release_claims(self) -> None:
        for claim in self._claims:
            claim.release()
        self._claims.clear()
