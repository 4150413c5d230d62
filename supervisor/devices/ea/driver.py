"""EA-PSB 10000 bidirectional supply (seed 002) over SCPI, on an injected line transport.

Points:

- ``voltage`` (in, V), ``current`` (in, A, + = charging the battery, i.e. sourcing; sinking
  reads negative), ``power`` (in, W, same sign as ``current``): one ``MEAS:ARR?``;
- ``output_on`` (in, bool, ``OUTP?``), ``remote`` (in, bool, ``SYST:LOCK:OWN?`` is REMOTE),
  ``ques`` (in, int, ``STAT:QUES:COND?`` bits), ``error`` (in, str, last non-zero
  ``SYST:ERR?`` entry since connect, or ``""``);
- ``output`` (out, bool: ``OUTP ON|OFF``, verified with ``OUTP?``);
- ``current_set`` (out, A signed: + charge, − discharge, 0 = no current), clamped to the
  configured limits with a warning, verified by reading back ``VOLT?; CURR?; SINK:CURR?``.

Safety of the link (devices.md "EA-PSB 10000"):

- a clean ``close()`` zeroes the set values, switches the output off, checks both, then
  releases the remote lock (``SYST:LOCK OFF``); if it cannot, the lock stays and the watchdog
  acts;
- every (re)connect takes remote, zeroes the set values and switches the output OFF, and sets
  the protections from the limits: the driver never re-energises on its own. Energising
  writes (``output`` true, non-zero ``current_set``) queued while a lost link was down are
  discarded at reconnect (logged): the caller must command them again;
- the unit's interface monitoring (watchdog) is armed at connect: if this driver stops
  talking for ``watchdog_s``, the unit leaves remote and switches its output off. Every poll
  keeps it alive, so ``watchdog_s`` must be well above ``poll_period_s``;
- one complete line per write, an ``asyncio.Lock`` around every question/answer pair, and
  on a timeout or a malformed reply the connection is closed, so a late reply can never be
  taken for the answer to the next question.

The transport (:mod:`supervisor.fieldbus.scpi_transport`) is chosen by the composition root:
raw-socket SCPI on ``host:port`` for a unit, or the simulator's interpreter in process
(dry runs, virtual-clock tests).

Modbus TCP (port 502) as a second transport is deliberately NOT implemented: part of its
register map (sink set values, limits, nominal values, the state bits 0–4/9–10/12) is only
[S] and the sign of the sink current over Modbus is [U] in devices.md, whereas the SCPI
subset used here is [V] except for the constants marked in :mod:`supervisor.devices.ea.protocol`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import deque
from collections.abc import AsyncIterator, Mapping

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, ProtocolError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.base import PolledDriver
from supervisor.devices.ea.config import POINTS, WATCHDOG_POLL_RATIO
from supervisor.devices.ea.protocol import (
    QUES_OCP_BIT,
    QUES_OPP_BIT,
    QUES_OT_BIT,
    QUES_OVP_BIT,
    QUES_POWER_FAIL_BIT,
    WATCHDOG_ENABLE_HEADER,
    WATCHDOG_TIME_HEADER,
    LockOwner,
    is_ea,
    model_matches,
    parse_lock_owner,
    parse_meas_array,
)
from supervisor.fieldbus.scpi import (
    Identity,
    ScpiError,
    bit_set,
    decode_line,
    encode_line,
    format_number,
    format_setting,
    join_commands,
    parse_error,
    parse_idn,
    parse_number,
    parse_on_off,
    parse_register,
    split_reply,
)
from supervisor.fieldbus.scpi_transport import ScpiConnection, ScpiTransport

log = logging.getLogger(__name__)

PROTECTION_MARGIN = 1.05
"""Protections (``VOLT:PROT``, ``CURR:PROT``, ``SINK:CURR:PROT``) sit 5 % above the limits
(never above nominal), so regulation at a limit never trips them."""
VERIFY_TOLERANCE_FRACTION = 0.001
"""Read-back tolerance as a fraction of nominal (EA resolution is nominal/52428 over Modbus;
SCPI replies are rounded to the display resolution [U]), with ``VERIFY_TOLERANCE_MIN``."""
VERIFY_TOLERANCE_MIN = 0.01
MAX_ERRORS_PER_POLL = 8
"""``SYST:ERR?`` entries read per poll at most (one round trip each)."""
RAW_LOG_LINES = 64

POLL_QUERIES = ("MEAS:ARR?", "OUTP?", "SYST:LOCK:OWN?", "STAT:QUES:COND?")
"""Asked on one line every poll; ``SYST:ERR?`` follows on its own line because reading the
error queue can acknowledge alarms that have cleared (devices.md): QUES must be read first."""
_POLL_LINE = join_commands(POLL_QUERIES)
_QUES_NAMES = {
    QUES_OVP_BIT: "OVP",
    QUES_OCP_BIT: "OCP",
    QUES_OPP_BIT: "OPP",
    QUES_OT_BIT: "OT",
    QUES_POWER_FAIL_BIT: "power fail",
}


class EaDriver(PolledDriver):
    """One EA-PSB 10000 unit reached through ``transport`` (SCPI; on TCP normally port 5025).

    ``v_min``/``v_max``: voltage set while discharging/charging (the unit regulates CV there,
    so they are the battery's voltage window). ``i_charge_max_a``/``i_discharge_max_a``:
    current limits (magnitudes). ``p_max_w``: power limit for both directions (default:
    nominal). ``expected_model``: refuse another model (e.g. ``"PSB 10060-60"``).
    ``timeout_s``: per reply. Limits above the unit's nominal ratings are refused at connect.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        transport: ScpiTransport,
        *,
        v_min: float,
        v_max: float,
        i_charge_max_a: float,
        i_discharge_max_a: float,
        p_max_w: float | None = None,
        expected_model: str | None = None,
        poll_period_s: float = 0.2,
        watchdog_s: float = 2.0,
        timeout_s: float = 1.0,
    ) -> None:
        numbers = {
            "v_min": v_min,
            "v_max": v_max,
            "i_charge_max_a": i_charge_max_a,
            "i_discharge_max_a": i_discharge_max_a,
            "poll_period_s": poll_period_s,
            "watchdog_s": watchdog_s,
            "timeout_s": timeout_s,
        }
        if p_max_w is not None:
            numbers["p_max_w"] = p_max_w
        for key, value in numbers.items():
            if isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"{name}: {key} must be a finite number, got {value!r}")
        if not 0 <= v_min < v_max:
            raise ValueError(f"{name}: need 0 <= v_min < v_max, got {v_min} and {v_max}")
        for key in ("i_charge_max_a", "i_discharge_max_a", "timeout_s", "poll_period_s"):
            if numbers[key] <= 0:
                raise ValueError(f"{name}: {key} must be > 0")
        if p_max_w is not None and p_max_w <= 0:
            raise ValueError(f"{name}: p_max_w must be > 0")
        if watchdog_s < WATCHDOG_POLL_RATIO * poll_period_s * (1 - 1e-9):  # 3 x 0.1 == 0.3
            raise ValueError(
                f"{name}: watchdog_s ({watchdog_s} s) must be at least "
                f"{WATCHDOG_POLL_RATIO:g} x poll_period_s ({poll_period_s} s): every poll is "
                "the keep-alive, it must come well within the unit's timeout"
            )
        self.transport = transport
        self.v_min = v_min
        self.v_max = v_max
        self._cv_v: float | None = None  # CV target from voltage_set (None: v_max)
        self._last_current = 0.0
        self.i_charge_max_a = i_charge_max_a
        self.i_discharge_max_a = i_discharge_max_a
        self.p_max_w = p_max_w
        self.expected_model = expected_model
        self.watchdog_s = watchdog_s
        self.timeout_s = timeout_s
        self.identity: Identity | None = None
        self.nominal_v = math.nan
        self.nominal_a = math.nan
        self.nominal_w = math.nan
        self._link: ScpiConnection | None = None
        self._io_lock = asyncio.Lock()
        self._direction = 0  # sign of the last commanded current
        self._device_error = ""
        self._last_ques = 0
        self._last_owner: LockOwner | None = None
        self._was_connected = False
        super().__init__(name, clock, poll_period_s)
        self.raw_log = deque(maxlen=RAW_LOG_LINES)

    # --- public surface --------------------------------------------------------
    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    def write(self, point: str, value: Value) -> None:
        """Queue a write; refuses values of the wrong kind at once (the caller's bug)."""
        if point in ("current_set", "voltage_set") and (
            isinstance(value, bool | str) or not math.isfinite(value)
        ):
            raise ValueError(f"{self.name}: {point} needs a finite number, got {value!r}")
        if point == "output" and isinstance(value, str):
            raise ValueError(f"{self.name}: output needs a bool, got {value!r}")
        super().write(point, value)

    # --- PolledDriver hooks ----------------------------------------------------
    async def _connect(self) -> None:
        async with self._io_lock:
            await self._drop_transport()
            # Raises DeviceTimeout / DeviceIOError naming the address.
            self._link = await self.transport.connect(self.name, self.timeout_s)
            try:
                await self._setup()
            except BaseException:
                await self._drop_transport()
                raise
        self._drop_stale_energising_writes()
        self._was_connected = True

    async def _disconnect(self) -> None:
        """A clean close: zero set values, output off (verified), then give the unit back
        to its front panel (``SYST:LOCK OFF``), so that nobody finds it locked in remote
        after a stop. If any of that fails, the lock is kept and the link dropped: the
        unit's watchdog then switches the output off ``watchdog_s`` after the last command
        (as when the supervisor dies)."""
        async with self._io_lock:
            if self._link is not None:
                try:
                    await self._release_remote()
                except (DeviceIOError, ProtocolError) as exc:
                    log.warning(
                        "%s: remote lock kept at close (%s); the unit's watchdog switches the"
                        " output off %g s after the last command",
                        self.name,
                        exc,
                        self.watchdog_s,
                    )
            await self._drop_transport()

    async def _release_remote(self) -> None:
        """De-energise, check it, release the lock (the caller holds the I/O lock)."""
        self._direction = 0
        self._last_current = 0.0
        await self._exchange(join_commands(["CURR 0", "SINK:CURR 0", "VOLT 0"]), 0)
        await self._exchange("OUTP OFF", 0)
        curr, sink, outp = await self._exchange(join_commands(["CURR?", "SINK:CURR?", "OUTP?"]), 3)
        if (
            parse_number(curr, self.name, "A") != 0.0
            or parse_number(sink, self.name, "A") != 0.0
            or parse_on_off(outp, self.name)
        ):
            raise DeviceIOError(
                self.name,
                f"not de-energised before release: CURR? {curr}, SINK:CURR? {sink}, OUTP? {outp}",
            )
        await self._exchange("SYST:LOCK OFF", 0)
        log.info("%s: output off, set values zero, remote lock released", self.name)

    async def _read(self) -> dict[str, Sample]:
        async with self._transaction():
            parts = await self._exchange(_POLL_LINE, len(POLL_QUERIES))
            meas = parse_meas_array(parts[0], self.name, sinking=self._direction < 0)
            output_on = parse_on_off(parts[1], self.name)
            owner = parse_lock_owner(parts[2], self.name)
            ques = parse_register(parts[3], self.name)
            await self._read_errors()
        t = self.clock.now()
        self._note_status(owner, ques)

        def good(value: Value) -> Sample:
            return Sample(value, Quality.GOOD, Reason.NONE, t)

        return {
            "voltage": good(meas.voltage_v),
            "current": good(meas.current_a),
            "power": good(meas.power_w),
            "output_on": good(output_on),
            "remote": good(owner is LockOwner.REMOTE),
            "ques": good(ques),
            "error": good(self._device_error),
        }

    async def _write(self, point: str, value: Value) -> None:
        async with self._transaction():
            if point == "output":
                await self._set_output(bool(value))
            elif point == "voltage_set":
                assert not isinstance(value, str)  # checked in write()
                # The CV target while charging; never above the channel's v_max.
                self._cv_v = min(max(float(value), self.v_min), self.v_max)
                if self._last_current > 0:
                    await self._set_current(self._last_current)
            else:
                assert not isinstance(value, str)  # checked in write()
                await self._set_current(float(value))

    async def _safe(self) -> None:
        self._direction = 0
        self._last_current = 0.0
        failures: list[str] = []
        try:
            async with self._transaction():
                await self._exchange(join_commands(["CURR 0", "SINK:CURR 0"]), 0)
        except DeviceIOError as exc:  # ProtocolError cannot happen: no reply is read
            failures.append(f"CURR 0; SINK:CURR 0: {exc}")
        try:
            async with self._transaction():
                await self._exchange("OUTP OFF", 0)
                (reply,) = await self._exchange("OUTP?", 1)
                if parse_on_off(reply, self.name):
                    failures.append("OUTP? still reads ON after OUTP OFF")
        except (DeviceIOError, ProtocolError) as exc:
            failures.append(f"OUTP OFF: {exc}")
        if failures:
            raise DeviceIOError(
                self.name,
                "safe state not confirmed (" + "; ".join(failures) + "); the unit's watchdog "
                f"switches the output off {self.watchdog_s:g} s after the last command",
            )

    # --- connect sequence --------------------------------------------------------
    async def _setup(self) -> None:
        (idn_text,) = await self._exchange("*IDN?", 1)
        identity = parse_idn(idn_text, self.name)
        raw = idn_text.encode("ascii", "replace")
        if not is_ea(identity):
            raise ProtocolError(self.name, f"an EA unit in the *IDN? reply {idn_text!r}", raw)
        if self.expected_model is not None and not model_matches(
            self.expected_model, identity.model
        ):
            raise ProtocolError(
                self.name,
                f"model {self.expected_model!r} (configured), but *IDN? says {idn_text!r}",
                raw,
            )
        self.identity = identity
        self.nominal_v = await self._query_number("SYST:NOM:VOLT?", "V")
        self.nominal_a = await self._query_number("SYST:NOM:CURR?", "A")
        self.nominal_w = await self._query_number("SYST:NOM:POW?", "W")
        self._check_limits()
        await self._exchange("*CLS", 0)
        self._device_error = ""
        await self._exchange("SYST:LOCK ON", 0)
        (owner_text,) = await self._exchange("SYST:LOCK:OWN?", 1)
        owner = parse_lock_owner(owner_text, self.name)
        if owner is not LockOwner.REMOTE:
            raise DeviceIOError(
                self.name,
                f"SYST:LOCK ON refused: lock owner is {owner.value} (front panel in local?)",
            )
        # De-energise first: whatever a previous session left, nothing flows from here on.
        self._direction = 0
        self._last_current = 0.0
        await self._exchange(join_commands(["CURR 0", "SINK:CURR 0"]), 0)
        await self._exchange("OUTP OFF", 0)
        await self._exchange("VOLT 0", 0)
        p_w = self.p_max_w if self.p_max_w is not None else self.nominal_w
        await self._exchange(
            join_commands([format_setting("POW", p_w), format_setting("SINK:POW", p_w)]), 0
        )
        for header, value in self._protections().items():
            await self._exchange(format_setting(header, value), 0)
        await self._exchange(f"{WATCHDOG_TIME_HEADER} {format_number(self.watchdog_s, 3)}", 0)
        await self._exchange(f"{WATCHDOG_ENABLE_HEADER} ON", 0)  # on its own line
        (outp,) = await self._exchange("OUTP?", 1)
        if parse_on_off(outp, self.name):
            raise DeviceIOError(self.name, "OUTP? reads ON after OUTP OFF at connect")
        refused = await self._read_errors()
        if refused:
            raise DeviceIOError(
                self.name, "connect settings refused: " + "; ".join(str(e) for e in refused)
            )
        log.info(
            "%s: connected to %s %s (serial %s, firmware %s), nominal %g V %g A %g W; "
            "remote, output off, watchdog %g s",
            self.name,
            identity.manufacturer,
            identity.model,
            identity.serial,
            identity.firmware,
            self.nominal_v,
            self.nominal_a,
            self.nominal_w,
            self.watchdog_s,
        )

    def _check_limits(self) -> None:
        over: list[str] = []
        if self.v_max > self.nominal_v:
            over.append(f"v_max {self.v_max:g} V > nominal {self.nominal_v:g} V")
        if self.i_charge_max_a > self.nominal_a:
            over.append(f"i_charge_max_a {self.i_charge_max_a:g} A > nominal {self.nominal_a:g} A")
        if self.i_discharge_max_a > self.nominal_a:
            over.append(
                f"i_discharge_max_a {self.i_discharge_max_a:g} A > nominal {self.nominal_a:g} A"
            )
        if self.p_max_w is not None and self.p_max_w > self.nominal_w:
            over.append(f"p_max_w {self.p_max_w:g} W > nominal {self.nominal_w:g} W")
        if over:
            model = self.identity.model if self.identity else "unit"
            raise DeviceIOError(
                self.name, f"configured limits exceed the {model} ratings: " + ", ".join(over)
            )

    def _protections(self) -> dict[str, float]:
        m = PROTECTION_MARGIN
        return {
            "VOLT:PROT": min(self.v_max * m, self.nominal_v),
            "CURR:PROT": min(self.i_charge_max_a * m, self.nominal_a),
            "SINK:CURR:PROT": min(self.i_discharge_max_a * m, self.nominal_a),
        }

    def _drop_stale_energising_writes(self) -> None:
        if not self._was_connected:
            return
        for point, value in list(self._pending.items()):
            if (point == "output" and bool(value)) or (point == "current_set" and value != 0):
                del self._pending[point]
                log.warning(
                    "%s: reconnected with output off; discarded %s=%r queued while the link "
                    "was down (command it again)",
                    self.name,
                    point,
                    value,
                )

    # --- outputs -----------------------------------------------------------------
    async def _set_output(self, on: bool) -> None:
        word = "ON" if on else "OFF"
        await self._exchange(f"OUTP {word}", 0)
        (reply,) = await self._exchange("OUTP?", 1)
        if parse_on_off(reply, self.name) != on:
            await self._refused(f"OUTP {word}", f"OUTP? reads {reply!r}")

    async def _set_current(self, current_a: float) -> None:
        requested = current_a
        current_a = min(max(current_a, -self.i_discharge_max_a), self.i_charge_max_a)
        if current_a != requested:
            log.warning(
                "%s: current_set %.4f A outside [-%g, %g] A, clamped to %.4f A",
                self.name,
                requested,
                self.i_discharge_max_a,
                self.i_charge_max_a,
                current_a,
            )
        magnitude = abs(current_a)
        self._last_current = current_a
        if current_a > 0:
            v_charge = self.v_max if self._cv_v is None else self._cv_v
            commands = [
                format_setting("CURR", magnitude),
                format_setting("VOLT", v_charge),
                "SINK:CURR 0",
            ]
            expect_v: float | None = v_charge
        elif current_a < 0:
            commands = [
                format_setting("SINK:CURR", magnitude),
                format_setting("VOLT", self.v_min),
                "CURR 0",
            ]
            expect_v = self.v_min
        else:
            commands = ["CURR 0", "SINK:CURR 0"]
            expect_v = None  # the voltage set value stays where it was
        line = join_commands(commands)
        # From here on the direction is unknown until verified: assume the new one.
        self._direction = (current_a > 0) - (current_a < 0)
        await self._exchange(line, 0)
        v_text, i_text, s_text = await self._exchange(
            join_commands(["VOLT?", "CURR?", "SINK:CURR?"]), 3
        )
        volt = parse_number(v_text, self.name, "V")
        curr = parse_number(i_text, self.name, "A")
        sink = parse_number(s_text, self.name, "A")
        tol_a = max(VERIFY_TOLERANCE_MIN, VERIFY_TOLERANCE_FRACTION * self.nominal_a)
        tol_v = max(VERIFY_TOLERANCE_MIN, VERIFY_TOLERANCE_FRACTION * self.nominal_v)
        want_curr = magnitude if current_a > 0 else 0.0
        want_sink = magnitude if current_a < 0 else 0.0
        if (
            abs(curr - want_curr) > tol_a
            or abs(sink - want_sink) > tol_a
            or (expect_v is not None and abs(volt - expect_v) > tol_v)
        ):
            await self._refused(
                line, f"read back VOLT {volt:g} V, CURR {curr:g} A, SINK:CURR {sink:g} A"
            )

    async def _refused(self, command: str, readback: str) -> None:
        """A setting did not verify: fetch the device's reason, publish it, raise."""
        errors = await self._read_errors()
        t = self.clock.now()
        self._image["error"] = Sample(self._device_error, Quality.GOOD, Reason.NONE, t)
        why = "; ".join(str(e) for e in errors) if errors else "no error queued"
        raise DeviceIOError(self.name, f"{command!r} not applied: {readback} (device: {why})")

    # --- status --------------------------------------------------------------------
    async def _read_errors(self) -> list[ScpiError]:
        errors: list[ScpiError] = []
        for _ in range(MAX_ERRORS_PER_POLL):
            (text,) = await self._exchange("SYST:ERR?", 1)
            err = parse_error(text, self.name)
            if err.code == 0:
                break
            log.warning("%s: device error %s", self.name, err)
            errors.append(err)
            self._device_error = str(err)
        return errors

    def _note_status(self, owner: LockOwner, ques: int) -> None:
        if owner is not self._last_owner:
            if owner is not LockOwner.REMOTE:
                log.warning(
                    "%s: not in remote control (lock owner %s): settings will be refused",
                    self.name,
                    owner.value,
                )
            elif self._last_owner is not None:
                log.info("%s: remote control held again", self.name)
            self._last_owner = owner
        new = ques & ~self._last_ques
        if new:
            names = [n for bit, n in _QUES_NAMES.items() if bit_set(new, bit)]
            log.warning(
                "%s: questionable status 0x%04x (%s)",
                self.name,
                ques,
                ", ".join(names) or "unnamed bits",
            )
        self._last_ques = ques

    # --- transport -----------------------------------------------------------------
    @contextlib.asynccontextmanager
    async def _transaction(self) -> AsyncIterator[None]:
        """Hold the I/O lock; on any failure inside, close the connection (no late reply
        may be read as the answer to a later question)."""
        async with self._io_lock:
            if self._link is None:
                raise DeviceIOError(self.name, "not connected")
            try:
                yield
            except BaseException:
                await self._drop_transport()
                raise

    async def _exchange(self, line: str, replies: int) -> list[str]:
        """Send one complete line; read one reply line of ``replies`` parts (0: no reply).

        The caller holds the I/O lock and closes the connection if this raises (the
        transport's DeviceTimeout, DeviceIOError or ProtocolError, naming ``line``).
        """
        link = self._link
        if link is None:
            raise DeviceIOError(self.name, "not connected")
        data = encode_line(line)
        self.raw_log.append(f"> {line}")
        await link.send_line(data, self.timeout_s)
        if replies == 0:
            return []
        raw = await link.receive_line(self.timeout_s)
        self.raw_log.append(f"< {raw.decode('ascii', 'replace').rstrip()}")
        text = decode_line(raw, self.name)
        return split_reply(text, replies, self.name)

    async def _query_number(self, query: str, unit: str) -> float:
        (text,) = await self._exchange(query, 1)
        value = parse_number(text, self.name, unit)
        if value <= 0:
            raise ProtocolError(self.name, f"a positive value for {query}", text.encode())
        return value

    async def _drop_transport(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            await link.close()
