"""The SPI bus shared by the Chadèche boards, and the one-owner-per-board lock.

Seed §III.G: the Raspberry Pi's address lines and SPI interface are a critical resource
(the original used named semaphores), and two programs must never drive the same board
(the original used a shared-memory table). Here: a ``threading.Lock`` per bus (plus an
optional ``flock`` so several processes can share the bus), and an exclusive ``flock`` per
board address.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import tempfile
import threading
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from supervisor.core.errors import DeviceIOError
from supervisor.devices.chadeche.config import BOARD_ADDRESSES
from supervisor.devices.chadeche.protocol import (
    A0_GPIO,
    A1_GPIO,
    CHIP_SELECT_ACTIVE_HIGH,
    CHIP_SELECT_GPIO,
    Chip,
    address_lines,
)

log = logging.getLogger(__name__)

DEVICE = "chadeche"
DEFAULT_MAX_SPEED_HZ = 500_000
"""Well below the MCP3201's clock limit (about 1.6 MHz at 5 V) to leave margin for the
40-wire ribbon cable to stacked boards (seed §II.D)."""
SPI_MODE = 0
"""MCP4922 and MCP3201 both accept modes 0,0 and 1,1."""


class ChadecheBus(Protocol):
    """One SPI bus to up to four boards; ``transfer`` is atomic (select, xfer, deselect)."""

    blocking: bool
    """Transfers block (real SPI): the driver runs them in a worker thread."""

    def transfer(self, board: int, chip: Chip, data: bytes) -> bytes:
        """Select ``board`` (A0/A1) and ``chip``, shift ``data`` out while reading as many
        bytes in, deselect. Raises DeviceIOError on failure."""
        ...

    def close(self) -> None: ...


# --- one owner per board ------------------------------------------------------------------
def default_lock_dir() -> Path:
    """``/run/lock`` when writable, else the system temporary directory."""
    run_lock = Path("/run/lock")
    if run_lock.is_dir() and os.access(run_lock, os.W_OK):
        return run_lock
    return Path(tempfile.gettempdir())


def board_lock_path(address: int, lock_dir: str | Path | None = None) -> Path:
    directory = Path(lock_dir) if lock_dir is not None else default_lock_dir()
    return directory / f"chadeche-board{address}.lock"


class BoardClaim:
    """Exclusive ownership of one board address; release it (or use ``with``) when done."""

    def __init__(self, address: int, path: Path, fd: int) -> None:
        self.address = address
        self.path = path
        self._fd: int | None = fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Unlock and close; idempotent. The file is left in place (unlinking would race)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def __enter__(self) -> BoardClaim:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()


def claim_board(address: int, lock_dir: str | Path | None = None) -> BoardClaim:
    """Take an exclusive, non-blocking ``flock`` on the board's lock file.

    Raises DeviceIOError naming the board and the lock file if another owner (another
    process, or another open in this one) holds it. The kernel drops the lock when the
    owner dies, so there is no stale-lock cleanup to do.
    """
    if address not in BOARD_ADDRESSES:
        raise ValueError(f"Chadèche board address must be 0..3, got {address!r}")
    path = board_lock_path(address, lock_dir)
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise DeviceIOError(
            f"{DEVICE} board {address}", f"cannot open lock file {path}: {exc}"
        ) from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        holder = _read_holder(fd)
        os.close(fd)
        raise DeviceIOError(
            f"{DEVICE} board {address}",
            f"already driven by another owner{holder} (lock file {path})",
        ) from exc
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
    except OSError:
        log.debug("could not write pid into %s", path)  # the lock itself is what counts
    return BoardClaim(address, path, fd)


def _read_holder(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        return ""
    return f" (pid {text})" if text.isdigit() else ""


# --- Raspberry Pi backend -----------------------------------------------------------------
class SpidevBus:
    """Linux ``spidev`` for data, gpiozero ``OutputDevice`` (BCM numbers) for A0/A1/CS0–2.

    The boards' chip selects are GPIOs, not the SPI controller's CE lines (seed §II.C.2),
    so spidev is opened with ``no_cs``. A ``threading.Lock`` is held from select to
    deselect, and an ``flock`` on ``<lock_dir>/chadeche-spi<bus>.<device>.lock`` (default
    directory: :func:`default_lock_dir`) so several processes can share the bus, as the
    seed's one-program-per-board setup does (§III.G).
    """

    blocking = True

    def __init__(
        self,
        spi_bus: int = 0,
        spi_device: int = 0,
        max_speed_hz: int = DEFAULT_MAX_SPEED_HZ,
        *,
        lock_dir: str | Path | None = None,
    ) -> None:
        try:
            import spidev
            from gpiozero import GPIOZeroError, OutputDevice
        except ImportError as exc:
            raise DeviceIOError(
                DEVICE, "spidev/gpiozero not installed: pip install bench-supervisor[rpi]"
            ) from exc
        self._lock = threading.Lock()
        self._errors: tuple[type[BaseException], ...] = (OSError, GPIOZeroError)
        self._closed = False
        self._bus_lock_fd: int | None = None
        self._pins: list[Any] = []
        where = f"spidev{spi_bus}.{spi_device}"
        self.where = where
        try:
            # Chip selects first, all inactive, so nothing is selected while we set up.
            self._cs = {
                chip: self._pin(OutputDevice, gpio, CHIP_SELECT_ACTIVE_HIGH)
                for chip, gpio in CHIP_SELECT_GPIO.items()
            }
            self._a0 = self._pin(OutputDevice, A0_GPIO, True)
            self._a1 = self._pin(OutputDevice, A1_GPIO, True)
            self._spi = spidev.SpiDev()
            self._spi.open(spi_bus, spi_device)
        except self._errors as exc:
            self._close_pins()
            raise DeviceIOError(DEVICE, f"cannot open {where} and GPIOs: {exc}") from exc
        try:
            self._spi.mode = SPI_MODE
            self._spi.max_speed_hz = max_speed_hz
        except OSError as exc:
            self.close()
            raise DeviceIOError(DEVICE, f"cannot configure {where}: {exc}") from exc
        try:
            self._spi.no_cs = True
        except OSError as exc:
            # Some kernel drivers refuse SPI_NO_CS. Harmless here: the controller's own CE
            # line is not wired to the boards (seed §II.C.2), it just toggles unused.
            log.warning(
                "%s: %s refuses no_cs (%s); its CE line will toggle unused", DEVICE, where, exc
            )
        directory = Path(lock_dir) if lock_dir is not None else default_lock_dir()
        path = directory / f"chadeche-spi{spi_bus}.{spi_device}.lock"
        try:
            self._bus_lock_fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            self.close()
            raise DeviceIOError(DEVICE, f"cannot open bus lock file {path}: {exc}") from exc

    def _pin(self, factory: Any, gpio: int, active_high: bool) -> Any:
        pin = factory(gpio, active_high=active_high, initial_value=False)
        self._pins.append(pin)
        return pin

    def transfer(self, board: int, chip: Chip, data: bytes) -> bytes:
        a0, a1 = address_lines(board)
        with self._lock:
            if self._closed:
                raise DeviceIOError(DEVICE, f"{self.where} is closed")
            fd = self._bus_lock_fd
            try:
                if fd is not None:
                    # Other processes on this bus. Blocks like the seed's sem_wait; the
                    # kernel drops a dead holder's lock.
                    fcntl.flock(fd, fcntl.LOCK_EX)
                try:
                    # Address lines move only while every chip select is inactive.
                    self._a0.value = a0
                    self._a1.value = a1
                    cs = self._cs[chip]
                    cs.on()
                    try:
                        reply = self._spi.xfer2(list(data))
                    finally:
                        cs.off()
                finally:
                    if fd is not None:
                        fcntl.flock(fd, fcntl.LOCK_UN)
            except self._errors as exc:
                raise DeviceIOError(
                    DEVICE, f"board {board} {chip.name}: transfer on {self.where} failed: {exc}"
                ) from exc
        return bytes(reply)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            with contextlib.suppress(*self._errors):
                self._spi.close()
            self._close_pins()
            if self._bus_lock_fd is not None:
                os.close(self._bus_lock_fd)
                self._bus_lock_fd = None

    def _close_pins(self) -> None:
        for pin in self._pins:
            with contextlib.suppress(*self._errors):
                pin.close()
        self._pins.clear()
