"""Work a client may make as costly as it likes, in a child process that is killed when it
is abandoned (issue 28: three 150 KB recipe texts posted to ``/api/recipes/validate`` were
answered 503 at their time limit, but their worker *threads* ran on — 100 % CPU, the
supervisor's memory 0.79 → 2.0 GB, 11 scan stalls, jitter p99 1.1 → 30 ms, and a SIGTERM
that took 8 to 23 s: a thread cannot be stopped, and it shares the scan's interpreter lock
and heap).

A job is a module-level function and its arguments (pickled; the function returns plain
data). It runs in a process of its own (``python -m supervisor.commands.childjob
MODULES``), one job per process, started ahead of time: the modules the jobs need are
imported before a job comes (2.5 s on a loaded two-core machine), and as many processes as
jobs may run at once wait ready. The process:

- has an address-space limit (``RLIMIT_AS``): a job that needs more gets ``MemoryError``,
  answered as :class:`ChildOutOfMemory` — the supervisor's own memory never grows with it;
- has a CPU-time limit (``RLIMIT_CPU``) a little past its deadline, and dies with its
  parent (``PR_SET_PDEATHSIG``): the kernel ends it even if the supervisor cannot;
- runs in the idle scheduling class (else at the lowest ``nice``): the scan takes the core
  the moment it wakes;
- is killed (``SIGKILL`` by pid) at its deadline, when its caller goes away (the HTTP
  client disconnected: the handler is cancelled) and by :meth:`ChildJobs.kill_all` at
  shutdown. A killed process frees all its memory at once.

At most ``workers`` jobs run at a time and ``queue`` more wait (a wait counts towards the
job's deadline); beyond that a job is refused at once with :class:`ChildJobsBusy` (HTTP:
503 with ``Retry-After``).

Not :mod:`multiprocessing`: its fork server and spawned children import the parent's main
module again (the CLI, or pytest), and its processes are not ours to kill one by one.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import importlib
import logging
import os
import pickle
import resource
import signal
import struct
import sys
from collections.abc import Callable, Sequence
from typing import Any, Final

log = logging.getLogger(__name__)

__all__ = [
    "ChildCrashed",
    "ChildJobError",
    "ChildJobs",
    "ChildJobsBusy",
    "ChildOutOfMemory",
    "ChildTimeout",
]

NICENESS: Final = 19
"""Where there is no idle scheduling class: the lowest priority (``nice``)."""
CPU_MARGIN_S: Final = 5
"""``RLIMIT_CPU`` past the deadline: the parent kills first; the kernel if it cannot."""
RETRY_AFTER_S: Final = 5
"""What a refused caller is told to wait (HTTP ``Retry-After``)."""
IMPORT_NICENESS: Final = 10
"""A waiting process's priority while it imports (its job then runs idle)."""
READY: Final = b"ready\n"
_PR_SET_PDEATHSIG: Final = 1


class ChildJobError(Exception):
    """A job gave no answer: the reason is the message."""


class ChildTimeout(ChildJobError):
    def __init__(self, what: str, timeout_s: float) -> None:
        super().__init__(f"{what} took more than {timeout_s:g} s; stopped")
        self.timeout_s = timeout_s


class ChildOutOfMemory(ChildJobError):
    def __init__(self, what: str, limit_bytes: int) -> None:
        super().__init__(f"{what} needs more than {limit_bytes // (1024 * 1024)} MiB; stopped")
        self.limit_bytes = limit_bytes


class ChildCrashed(ChildJobError):
    pass


class ChildJobsBusy(ChildJobError):
    def __init__(self, what: str, retry_after_s: int) -> None:
        super().__init__(f"{what}: too many at once; try again in {retry_after_s} s")
        self.retry_after_s = retry_after_s


# --- the child ------------------------------------------------------------------------------
def _lowest_priority() -> None:
    idle = getattr(os, "SCHED_IDLE", None)
    if idle is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, idle, os.sched_param(0))
            return
    with contextlib.suppress(OSError):
        os.nice(NICENESS)


def _die_with_parent() -> None:
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def _limit(kind: int, value: int) -> None:
    _, hard = resource.getrlimit(kind)
    if hard != resource.RLIM_INFINITY:
        value = min(value, hard)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(kind, (value, value))


def _write(data: bytes) -> None:
    out = sys.stdout.buffer
    out.write(struct.pack("!Q", len(data)) + data)
    out.flush()


def child_main(modules: Sequence[str]) -> int:
    """The child's entry: import ``modules``, say ready, run the one job read from stdin."""
    _die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C in a terminal: the parent decides
    # Below the scan while importing (our own modules: seconds, bounded), idle once the
    # job — what a client sent — runs.
    with contextlib.suppress(OSError):
        os.nice(IMPORT_NICENESS)
    for m in modules:
        importlib.import_module(m)
    sys.stdout.buffer.write(READY)
    sys.stdout.buffer.flush()
    job = sys.stdin.buffer.read()
    if not job:  # the parent closed us unused (shutdown)
        return 0
    fn, args, memory_limit_bytes, cpu_s = pickle.loads(job)
    del job
    _lowest_priority()
    used_s = resource.getrusage(resource.RUSAGE_SELF)
    _limit(resource.RLIMIT_CPU, int(used_s.ru_utime + used_s.ru_stime) + cpu_s)
    _limit(resource.RLIMIT_AS, memory_limit_bytes)
    try:
        answer: tuple[str, Any] = ("ok", fn(*args))
    except MemoryError:
        answer = ("memory", None)
    except Exception as exc:  # the job returns its refusals as data: this is a bug
        answer = ("crash", f"{type(exc).__name__}: {exc}")
    try:
        data = pickle.dumps(answer)
    except MemoryError:
        data = pickle.dumps(("memory", None))
    _write(data)
    # Not the interpreter's orderly end: it tears down every module, seconds on a busy
    # machine, and nothing here needs it (the answer is written and flushed).
    os._exit(0)


# --- the parent ------------------------------------------------------------------------------
class ChildJobs:
    """Jobs in child processes, each with a deadline and a memory limit (the module)."""

    def __init__(
        self,
        workers: int = 2,
        queue: int = 2,
        memory_limit_bytes: int = 1024 * 1024 * 1024,
        preload: Sequence[str] = (),
    ) -> None:
        if workers < 1 or queue < 0:
            raise ValueError("child jobs: at least one worker, a queue of zero or more")
        self.workers = workers
        self.queue = queue
        self.memory_limit_bytes = memory_limit_bytes
        self.preload = tuple(preload)
        self._slots: asyncio.Semaphore | None = None
        self._pending = 0
        self._spares: list[asyncio.Task[asyncio.subprocess.Process]] = []
        self._running: dict[int, asyncio.subprocess.Process] = {}
        self._reapers: set[asyncio.Task[None]] = set()
        self._closed = False
        self.started = 0
        """Processes started."""
        self.killed = 0
        """Jobs' processes killed: at their deadline, abandoned by their caller, at shutdown."""

    @property
    def running_pids(self) -> list[int]:
        """The processes of the jobs under way."""
        return sorted(self._running)

    async def _spawn(self) -> asyncio.subprocess.Process:
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "supervisor.commands.childjob",
            *self.preload,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            limit=2**31 - 1,  # an answer is read whole (readexactly), never by lines
        )
        self.started += 1
        try:
            assert proc.stdout is not None
            line = await proc.stdout.readline()
        except BaseException:
            self._kill_proc(proc)
            self._reap(proc)
            raise
        if line != READY:
            self._kill_proc(proc)
            await self._reap(proc)
            raise ChildCrashed(f"a child process did not start (exit {proc.returncode})")
        return proc

    def _reap(self, proc: asyncio.subprocess.Process) -> asyncio.Task[None]:
        """Wait for ``proc``'s end and close its pipes (in a task: nothing waits for it)."""

        async def wait() -> None:
            with contextlib.suppress(Exception):
                await proc.communicate()
            # Closed here, not by a callback the loop may never run (the child watcher's
            # exit report comes from another thread): a transport left open when the loop
            # ends is an "unclosed transport" for every process killed at shutdown.
            transport = getattr(proc, "_transport", None)
            if transport is not None:
                transport.close()

        task = asyncio.get_running_loop().create_task(wait())
        self._reapers.add(task)
        task.add_done_callback(self._reapers.discard)
        return task

    def warm(self) -> None:
        """Start the processes the next jobs will take (on the running loop)."""
        while not self._closed and len(self._spares) < self.workers:
            self._spares.append(asyncio.get_running_loop().create_task(self._spawn()))

    def _kill_proc(self, proc: asyncio.subprocess.Process) -> None:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()  # SIGKILL by its pid

    async def close(self) -> None:
        """:meth:`kill_all`, then wait until every process has ended."""
        spares = list(self._spares)
        self.kill_all()
        await asyncio.gather(*spares, return_exceptions=True)
        while self._reapers:  # a spare's end may reap one more while waiting
            await asyncio.gather(*list(self._reapers), return_exceptions=True)

    def kill_all(self) -> None:
        """Kill every job's process and every waiting one now; refuse new jobs (shutdown)."""
        self._closed = True
        for pid, proc in list(self._running.items()):
            self._kill_proc(proc)
            self.killed += 1
            del self._running[pid]
            self._reap(proc)
        for spare in self._spares:
            if spare.done():
                self._kill_spare(spare)
            else:
                spare.cancel()  # killed by _spawn
        self._spares.clear()

    async def _take(self) -> asyncio.subprocess.Process:
        self.warm()
        spare = self._spares.pop(0)
        self.warm()  # its replacement starts now
        try:
            return await asyncio.shield(spare)
        except asyncio.CancelledError:  # the caller left (its deadline): not left running
            spare.add_done_callback(self._kill_spare)
            raise

    def _kill_spare(self, spare: asyncio.Task[asyncio.subprocess.Process]) -> None:
        if not spare.cancelled() and spare.exception() is None:
            self._kill_proc(spare.result())
            self._reap(spare.result())

    async def run(
        self, fn: Callable[..., Any], args: tuple[Any, ...], timeout_s: float, what: str
    ) -> Any:
        """``fn(*args)`` in a child process: its (plain data) result. Raises
        :class:`ChildTimeout`, :class:`ChildOutOfMemory`, :class:`ChildCrashed`,
        :class:`ChildJobsBusy`; cancelled, the child is killed."""
        if self._closed or self._pending >= self.workers + self.queue:
            raise ChildJobsBusy(what, RETRY_AFTER_S)
        if self._slots is None:
            self._slots = asyncio.Semaphore(self.workers)
        job = pickle.dumps((fn, args, self.memory_limit_bytes, int(timeout_s) + CPU_MARGIN_S))
        self._pending += 1
        try:
            async with asyncio.timeout(timeout_s):
                async with self._slots:
                    return await self._run(job, what)
        except TimeoutError:
            log.error("%s: no answer within %g s; stopped", what, timeout_s)
            raise ChildTimeout(what, timeout_s) from None
        finally:
            self._pending -= 1

    async def _run(self, job: bytes, what: str) -> Any:
        if self._closed:
            raise ChildJobsBusy(what, RETRY_AFTER_S)
        proc = await self._take()
        assert proc.stdin is not None and proc.stdout is not None
        self._running[proc.pid] = proc
        answered = False
        try:
            proc.stdin.write(job)
            await proc.stdin.drain()
            proc.stdin.close()
            try:
                size = struct.unpack("!Q", await proc.stdout.readexactly(8))[0]
                kind, value = pickle.loads(await proc.stdout.readexactly(size))
            except (asyncio.IncompleteReadError, ConnectionError):
                kind, value = "died", None
            answered = True
        finally:
            mine = self._running.pop(proc.pid, None) is not None  # else kill_all's
            if mine and not answered:
                # Its deadline (the timeout cancels this), or its caller went away.
                self._kill_proc(proc)
                self.killed += 1
                log.info("%s: child %d killed", what, proc.pid)
            if mine:
                self._reap(proc)  # answered: it is exiting; else killed
        if self._closed and kind != "ok":  # killed at shutdown
            raise ChildJobsBusy(what, RETRY_AFTER_S)
        if kind == "ok":
            return value
        if kind == "memory":
            raise ChildOutOfMemory(what, self.memory_limit_bytes)
        if kind == "crash":
            log.error("%s: child %d failed: %s", what, proc.pid, value)
            raise ChildCrashed(f"{what} failed: {value}")
        code = await proc.wait()  # it has died: quick
        log.error("%s: child %d ended without an answer (exit %s)", what, proc.pid, code)
        if code in (-signal.SIGKILL, -signal.SIGSEGV):
            # The kernel's limits (its address space: a failed allocation in C).
            raise ChildOutOfMemory(what, self.memory_limit_bytes)
        raise ChildCrashed(f"{what}: its process ended without an answer (exit {code})")


if __name__ == "__main__":
    sys.exit(child_main(sys.argv[1:]))
