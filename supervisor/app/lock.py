"""One bench, one supervisor: an exclusive lock on the bench's state directory.

docs/design.md "Safety": the lock is taken before any device, simulator or port is touched, so
a second ``supervisor run`` of the same bench started by mistake never connects to the
devices the first one drives (it would otherwise switch them safe under a running test).

The lock is a non-blocking ``flock`` on ``<state_dir>/supervisor.lock`` holding the pid of
its owner. The kernel drops it when the owning process dies, however it dies, so there is
never a stale lock to clean up; the pid in the file is only there for the message.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
from pathlib import Path

from supervisor.core.errors import SupervisorError

log = logging.getLogger(__name__)

LOCK_NAME = "supervisor.lock"


class BenchBusy(SupervisorError):
    """Another process holds the bench's lock."""

    def __init__(self, bench: str, pid: int | None, path: Path) -> None:
        who = f"pid {pid}" if pid is not None else "another process (pid not written yet)"
        super().__init__(f"bench {bench!r} is already run by {who} (lock {path})")
        self.bench = bench
        self.pid = pid
        self.path = path


class BenchLockFailed(SupervisorError):
    """The bench's lock could not be taken (its folder not writable, …): not another
    supervisor (that is ``BenchBusy``)."""

    def __init__(self, path: Path, exc: OSError) -> None:
        super().__init__(f"cannot take the bench lock {path}: {exc.strerror or exc}")
        self.path = path


class BenchLock:
    """The exclusive lock of one bench's state directory (``acquire`` / ``release``)."""

    def __init__(self, state_dir: str | Path, bench: str) -> None:
        self.path = Path(state_dir).absolute() / LOCK_NAME
        self.bench = bench
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> BenchLock:
        """Take the lock or raise ``BenchBusy`` naming its holder; never waits."""
        if self._fd is not None:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # No O_TRUNC: the file may be the holder's, with its pid in it.
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = _read_pid(fd)
            os.close(fd)
            raise BenchBusy(self.bench, pid, self.path) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._fd = fd
        log.info("bench %s: lock %s taken (pid %d)", self.bench, self.path, os.getpid())
        return self

    def release(self) -> None:
        """Drop the lock (the kernel does it anyway when the process ends)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
        os.close(fd)  # closing the descriptor releases the flock

    def __enter__(self) -> BenchLock:
        return self.acquire()

    def __exit__(self, *_exc: object) -> None:
        self.release()


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None
