"""BMS over CAN (seed 002 §2.1): listen to the pack's periodic frames, decoded with the DBC.

The BMS only broadcasts; there is nothing to write. Points (all inputs):

- ``pack_voltage``, ``min_cell_voltage``, ``max_cell_voltage`` (V) from 0x1B0 (1000 ms);
- ``pack_current`` (A, + charges: BDF convention, see ``BMS_CURRENT_SIGN``) from 0x2B0
  (100 ms);
- ``min_temp``, ``max_temp``, ``avg_temp`` (degC) from 0x3B0 (1000 ms);
- ``frames_unknown``, ``frames_bad`` (int): frames with an identifier not in the DBC, and
  frames that could not be used (shorter than the DBC, non-finite value, error or remote
  frame), counted since the driver was created;
- ``faults`` (int, the BMS's fault bits as this supervisor sees them: this BMS sends none):
  :data:`FAULT_BITS`, 0 when everything is plausible, fresh and decodable.

A frame longer than its DBC message (a controller padding to 8 bytes) decodes, its extra
bytes ignored, unless ``allow_extra_bytes=False``. A decoded value that is no plausible
measurement (:func:`~supervisor.devices.bms.protocol.implausible`: outside the DBC range, a
subnormal float, a minimum above its maximum) is BAD/OUT_OF_RANGE, its value kept for
diagnostics; the rule it breaks is logged once when the episode starts and once when it
ends, not at every frame.

Each poll drains every frame already received (without blocking, at most
``max_frames_per_poll``). A value's ``Sample.t`` is the arrival time of its frame
(``clock.now()`` of the poll that drained it); a value whose frame is older than
``stale_factor`` × the frame's period is BAD/STALE. A bad frame is counted, logged once per
identifier with its raw bytes, and otherwise ignored: the previous value ages into STALE.

A bus on which nothing at all arrives for ``silence_timeout_s`` (default: ``stale_factor`` ×
the longest period, when every value is stale anyway) is treated as a lost link: the poll
fails (BAD/comm failure) and the bus is reopened with backoff: a CAN interface that went
down behind a socketcand daemon, or an adapter that stopped, says nothing else. (A daemon
that closes the connection is seen at once: the socketcand bus raises.)
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

import can

from supervisor.core.clock import Clock
from supervisor.core.driver import PointInfo, Sample, Value
from supervisor.core.errors import DeviceIOError, DeviceTimeout, ProtocolError
from supervisor.core.quality import Quality, Reason
from supervisor.devices.base import PolledDriver
from supervisor.devices.bms.config import POINTS
from supervisor.devices.bms.protocol import (
    BMS_CURRENT_SIGN,
    PACK_CURRENT_ID,
    PACK_TEMPERATURES_ID,
    PACK_VOLTAGES_ID,
    UnknownFrameError,
    decode,
    implausible,
    period_s,
)
from supervisor.fieldbus.socketcand import SocketcandBus

log = logging.getLogger(__name__)

MAX_FRAMES_PER_POLL: Final = 500
"""Frames drained per poll at most (the BMS sends 12 per second; a flood must not stall)."""
CONNECT_TIMEOUT_S: Final = 5.0
"""Time allowed to the bus factory (runs in a worker thread)."""

FRAME_POINTS: Final[Mapping[int, Mapping[str, str]]] = MappingProxyType(
    {
        PACK_VOLTAGES_ID: MappingProxyType(
            {
                "PackVoltage": "pack_voltage",
                "MinCellVoltage": "min_cell_voltage",
                "MaxCellVoltage": "max_cell_voltage",
            }
        ),
        PACK_CURRENT_ID: MappingProxyType({"PackCurrent": "pack_current"}),
        PACK_TEMPERATURES_ID: MappingProxyType(
            {"MinTemp": "min_temp", "MaxTemp": "max_temp", "AvgTemp": "avg_temp"}
        ),
    }
)
"""Frame identifier -> DBC signal -> point name."""

_ERROR_FRAME_KEY = -1  # "logged once" key for error frames

FAULT_PACK_VOLTAGE: Final = 1 << 0
FAULT_CELL_VOLTAGE: Final = 1 << 1
FAULT_CURRENT: Final = 1 << 2
FAULT_TEMPERATURE: Final = 1 << 3
FAULT_STALE: Final = 1 << 4
FAULT_REFUSED: Final = 1 << 5
FAULT_BITS: Final[Mapping[int, str]] = MappingProxyType(
    {
        FAULT_PACK_VOLTAGE: "pack voltage implausible",
        FAULT_CELL_VOLTAGE: "cell voltage implausible",
        FAULT_CURRENT: "current implausible",
        FAULT_TEMPERATURE: "temperature implausible",
        FAULT_STALE: "a frame is stale (not received within its period x stale_factor)",
        FAULT_REFUSED: "the latest frame of an id was refused (short, non-finite)",
    }
)
"""The ``faults`` point's bits: what the seed's HMI records as "BMS Faults"."""
_POINT_FAULT: Final[Mapping[str, int]] = MappingProxyType(
    {
        "pack_voltage": FAULT_PACK_VOLTAGE,
        "min_cell_voltage": FAULT_CELL_VOLTAGE,
        "max_cell_voltage": FAULT_CELL_VOLTAGE,
        "pack_current": FAULT_CURRENT,
        "min_temp": FAULT_TEMPERATURE,
        "max_temp": FAULT_TEMPERATURE,
        "avg_temp": FAULT_TEMPERATURE,
    }
)


@dataclass(slots=True)
class _Frame:
    t: float
    values: dict[str, float]
    implausible: dict[str, str]
    """Point -> the plausibility rule its value breaks."""


class BmsDriver(PolledDriver):
    """Listen to the BMS on the bus that ``bus_factory()`` opens (called in a worker thread).

    ``silence_timeout_s``: ``None`` = ``stale_factor`` × the longest frame period;
    ``math.inf`` never declares the link lost. ``allow_extra_bytes``: accept frames longer
    than the DBC says (extra bytes ignored: a controller pads to 8 bytes); False counts
    them in ``frames_bad``.
    """

    def __init__(
        self,
        name: str,
        clock: Clock,
        bus_factory: Callable[[], can.BusABC],
        poll_period_s: float = 0.05,
        stale_factor: float = 3.0,
        *,
        silence_timeout_s: float | None = None,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        max_frames_per_poll: int = MAX_FRAMES_PER_POLL,
        allow_extra_bytes: bool = True,
    ) -> None:
        if not stale_factor >= 1.0:
            raise ValueError(f"{name}: stale_factor must be >= 1")
        if silence_timeout_s is None:
            silence_timeout_s = stale_factor * max(period_s(i) for i in FRAME_POINTS)
        if not silence_timeout_s > 0:
            raise ValueError(f"{name}: silence_timeout_s must be > 0")
        if not connect_timeout_s > 0:
            raise ValueError(f"{name}: connect_timeout_s must be > 0")
        if max_frames_per_poll < 1:
            raise ValueError(f"{name}: max_frames_per_poll must be >= 1")
        super().__init__(name, clock, poll_period_s)
        self._bus_factory = bus_factory
        self.stale_factor = stale_factor
        self.silence_timeout_s = silence_timeout_s
        self.connect_timeout_s = connect_timeout_s
        self.max_frames_per_poll = max_frames_per_poll
        self.allow_extra_bytes = allow_extra_bytes
        self._bus: can.BusABC | None = None
        self._connect_t = 0.0
        self._last_rx_t = 0.0
        self._frames: dict[int, _Frame] = {}
        self.frames_unknown = 0
        self.frames_bad = 0
        self._unknown_logged: set[int] = set()
        self._bad_logged: set[int] = set()
        self._refused: set[int] = set()  # ids whose latest frame was refused
        self._implausible_now: set[str] = set()  # points in an implausible episode

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    # --- PolledDriver hooks ----------------------------------------------------------
    async def _connect(self) -> None:
        await self._close_bus()
        bus = await self._open_bus()
        now = self.clock.now()
        self._bus = bus
        self._connect_t = now
        self._last_rx_t = now

    async def _read(self) -> dict[str, Sample]:
        bus = self._bus
        if bus is None:
            raise DeviceIOError(self.name, "bus not open")
        now = self.clock.now()
        for _ in range(self.max_frames_per_poll):
            try:
                msg = bus.recv(timeout=0)
            except (can.CanError, OSError, ValueError) as exc:
                raise DeviceIOError(self.name, f"CAN receive failed: {exc}") from exc
            if msg is None:
                break
            self._last_rx_t = now
            self._take(msg, now)
        silent_s = now - self._last_rx_t
        if silent_s > self.silence_timeout_s:
            raise DeviceTimeout(self.name, f"no CAN frame for {silent_s:.1f} s")
        return self._samples(now)

    async def _write(self, point: str, value: Value) -> None:
        raise KeyError(f"{self.name}: the BMS has no output point {point!r}")

    async def _safe(self) -> None:
        """Nothing to drive: the BMS is only listened to."""

    async def _disconnect(self) -> None:
        await self._close_bus()

    # --- internals -------------------------------------------------------------------
    async def _open_bus(self) -> can.BusABC:
        # A daemon thread rather than asyncio.to_thread: a factory that hangs (a socketcand
        # server that accepts and never greets) must neither block the event loop's executor
        # shutdown nor leak the bus it may open late.
        done: concurrent.futures.Future[can.BusABC] = concurrent.futures.Future()

        def run() -> None:
            if not done.set_running_or_notify_cancel():
                return
            try:
                done.set_result(self._bus_factory())
            except BaseException as exc:  # handed over to the awaiting task
                done.set_exception(exc)

        threading.Thread(target=run, name=f"{self.name}-connect", daemon=True).start()
        try:
            return await asyncio.wait_for(asyncio.wrap_future(done), self.connect_timeout_s)
        except BaseException as exc:
            done.add_done_callback(_shutdown_unclaimed)
            if isinstance(exc, TimeoutError):
                raise DeviceTimeout(self.name, "opening the CAN bus timed out") from exc
            if isinstance(exc, can.CanError | OSError):
                raise DeviceIOError(self.name, f"cannot open the CAN bus: {exc}") from exc
            raise

    async def _close_bus(self) -> None:
        bus, self._bus = self._bus, None
        if bus is None:
            return
        try:
            bus.shutdown()
        except (can.CanError, OSError) as exc:
            log.debug("%s: bus shutdown: %s", self.name, exc)

    def _take(self, msg: can.Message, now: float) -> None:
        raw = bytes(msg.data)
        frame_id = msg.arbitration_id
        if msg.is_error_frame or msg.is_remote_frame:
            kind = "error" if msg.is_error_frame else "remote"
            key = _ERROR_FRAME_KEY if msg.is_error_frame else frame_id
            self._count_bad(key, f"{kind} frame 0x{frame_id:03X}", raw)
            return
        if msg.is_extended_id:  # the DBC has standard identifiers only
            self._count_unknown(frame_id, f"0x{frame_id:08X} (extended)", raw)
            return
        try:
            signals = decode(frame_id, raw, allow_extra_bytes=self.allow_extra_bytes)
        except UnknownFrameError:
            self._count_unknown(frame_id, f"0x{frame_id:03X}", raw)
            return
        except ProtocolError as exc:
            self._refused.add(frame_id)
            self._count_bad(frame_id, str(exc), raw)
            return
        self._refused.discard(frame_id)
        names = FRAME_POINTS[frame_id]
        values = {names[signal]: value for signal, value in signals.items()}
        if "pack_current" in values:
            values["pack_current"] *= BMS_CURRENT_SIGN
        why = {names[signal]: text for signal, text in implausible(frame_id, signals).items()}
        self._log_plausibility(names.values(), why, raw)
        self._frames[frame_id] = _Frame(now, values, why)

    def _log_plausibility(self, points: Iterable[str], why: Mapping[str, str], raw: bytes) -> None:
        """Once when a point's implausible episode starts, once when it ends."""
        for point in points:
            if point in why and point not in self._implausible_now:
                self._implausible_now.add(point)
                log.warning(
                    "%s: %s implausible, BAD until a plausible value: %s (data %s)",
                    self.name,
                    point,
                    why[point],
                    raw.hex(" "),
                )
            elif point not in why and point in self._implausible_now:
                self._implausible_now.discard(point)
                log.info("%s: %s plausible again", self.name, point)

    def _count_unknown(self, key: int, what: str, raw: bytes) -> None:
        self.frames_unknown += 1
        if key not in self._unknown_logged:
            self._unknown_logged.add(key)
            log.info("%s: ignoring frames with unknown id %s (data %s)", self.name, what, raw.hex())

    def _count_bad(self, key: int, what: str, raw: bytes) -> None:
        self.frames_bad += 1
        self.raw_log.append(f"bad {what}: {raw.hex(' ')}")
        if key not in self._bad_logged:
            self._bad_logged.add(key)
            log.warning("%s: bad frame (logged once per id): %s", self.name, what)

    def _samples(self, now: float) -> dict[str, Sample]:
        out: dict[str, Sample] = {}
        faults = FAULT_REFUSED if self._refused else 0
        for frame_id, names in FRAME_POINTS.items():
            limit = self.stale_factor * period_s(frame_id)
            frame = self._frames.get(frame_id)
            if frame is None:
                # Never received: "initial" while the first one may still be on its way.
                reason = Reason.INITIAL if now - self._connect_t <= limit else Reason.STALE
                faults |= FAULT_STALE if reason is Reason.STALE else 0
                for point in names.values():
                    out[point] = Sample(None, Quality.BAD, reason, 0.0)
                continue
            fresh = now - frame.t <= limit
            faults |= 0 if fresh else FAULT_STALE
            for point, value in frame.values.items():
                if not fresh:
                    out[point] = Sample(value, Quality.BAD, Reason.STALE, frame.t)
                elif point in frame.implausible:
                    faults |= _POINT_FAULT[point]
                    out[point] = Sample(value, Quality.BAD, Reason.OUT_OF_RANGE, frame.t)
                else:
                    out[point] = Sample(value, Quality.GOOD, Reason.NONE, frame.t)
        out["frames_unknown"] = Sample(self.frames_unknown, Quality.GOOD, Reason.NONE, now)
        out["frames_bad"] = Sample(self.frames_bad, Quality.GOOD, Reason.NONE, now)
        out["faults"] = Sample(faults, Quality.GOOD, Reason.NONE, now)
        return out


def _shutdown_unclaimed(done: concurrent.futures.Future[can.BusABC]) -> None:
    """Shut down a bus the factory opened after nobody was waiting for it any more."""
    if done.cancelled() or done.exception() is not None:
        return
    with contextlib.suppress(Exception):
        done.result().shutdown()


def socketcand_bus_factory(
    host: str,
    port: int,
    channel: str = "can0",
    *,
    connect_timeout_s: float = 1.0,
) -> Callable[[], can.BusABC]:
    """A ``bus_factory`` for a socketcand daemon, read as a stream
    (:class:`~supervisor.fieldbus.socketcand.SocketcandBus`: python-can's own client breaks
    when the daemon sends a frame in the same segment as its ``< ok >``, issue 32)."""

    def factory() -> can.BusABC:
        return SocketcandBus(channel, host, port, connect_timeout_s=connect_timeout_s)

    return factory


__all__ = [
    "BMS_CURRENT_SIGN",
    "CONNECT_TIMEOUT_S",
    "FAULT_BITS",
    "FRAME_POINTS",
    "MAX_FRAMES_PER_POLL",
    "POINTS",
    "BmsDriver",
    "socketcand_bus_factory",
]
