"""An asyncio event loop that calls a hook before every callback it runs and after every
wait for I/O: the one mechanism behind the OPC UA thread's wait at the scan gate
(``GatedLoop``) and the scan's turn ahead of its loop's callbacks (``ScanFirstLoop``),
ADR 0023.

Wrapped: what goes through ``call_soon`` and ``call_soon_threadsafe`` (task steps, futures'
callbacks). The I/O callbacks of a turn are not handed to ``call_soon``: the hook runs
once after the selector's wait, before them.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import logging
import selectors
import threading
from collections.abc import Callable, Coroutine
from typing import Any

from supervisor.core.gate import ScanGate

log = logging.getLogger(__name__)

__all__ = ["GatedLoop", "HookedLoop", "await_thread_end"]


class HookedLoop(asyncio.SelectorEventLoop):
    """A selector event loop calling ``self.before()`` before each callback and after each
    ``select``; subclasses define ``before``."""

    def __init__(self) -> None:
        super().__init__(_HookedSelector(self))

    def before(self) -> None:
        raise NotImplementedError

    def call_soon(  # type: ignore[override]
        self,
        callback: Callable[..., object],
        *args: Any,
        context: contextvars.Context | None = None,
    ) -> asyncio.Handle:
        return super().call_soon(self._hooked(callback), *args, context=context)

    def call_soon_threadsafe(  # type: ignore[override]
        self,
        callback: Callable[..., object],
        *args: Any,
        context: contextvars.Context | None = None,
    ) -> asyncio.Handle:
        return super().call_soon_threadsafe(self._hooked(callback), *args, context=context)

    def _hooked(self, callback: Callable[..., object]) -> Callable[..., object]:
        before = self.before

        def hooked(*args: Any) -> object:
            before()
            return callback(*args)

        return hooked


class _HookedSelector(selectors.DefaultSelector):
    def __init__(self, loop: HookedLoop) -> None:
        super().__init__()
        self._loop = loop

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready: list[tuple[selectors.SelectorKey, int]] = super().select(timeout)
        self._loop.before()  # before the I/O callbacks of this turn
        return ready


class GatedLoop(HookedLoop):
    """A server thread's event loop (OPC UA on a thread, Modbus TCP): after each wait for
    I/O and before every callback it waits while a scan runs (``core/gate.py``), so the
    server's work runs between scans. One turn of the loop runs every callback that is
    ready then (a dozen of 0.5–2 ms each with 10 subscribed OPC UA clients): waiting only
    after the ``select``, a scan that began during the first met the others taking the
    interpreter lock from it (issue 13)."""

    def __init__(self, gate: ScanGate) -> None:
        super().__init__()
        self._gate = gate

    def before(self) -> None:
        gate = self._gate
        if not gate.is_open:
            gate.wait()


async def await_thread_end(
    done: concurrent.futures.Future[None] | None,
    thread: threading.Thread | None,
    timeout_s: float,
    what: str,
) -> None:
    """Wait (from the bench's loop) for a server thread's ``done`` and join the thread;
    a server that does not end in ``timeout_s``, or ends with an error, is logged, never
    raised: the bench's stop goes on."""
    if done is None:
        return
    try:
        await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(done)), timeout_s)
    except TimeoutError:
        log.error("%s did not stop within %g s", what, timeout_s)
    except Exception:
        log.exception("%s ended with an error", what)
    if thread is not None:
        await asyncio.to_thread(thread.join, timeout_s)


def run_gated(
    main: Coroutine[Any, Any, None],
    ready: concurrent.futures.Future[None],
    gate: ScanGate | None,
    what: str,
) -> None:
    """A server thread's body: ``main`` on a loop of its own (a :class:`GatedLoop` waiting
    at the scan gate when there is one). An exception is never lost: before the server said
    ``ready`` it becomes ``ready``'s (the bench's loop awaits it), after that it is logged."""
    factory = None if gate is None else (lambda: GatedLoop(gate))
    try:
        with asyncio.Runner(loop_factory=factory) as runner:
            runner.run(main)
    except BaseException as exc:
        if not ready.done():
            ready.set_exception(exc)
        else:
            log.exception("%s thread failed", what)
