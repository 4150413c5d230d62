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
import contextvars
import selectors
from collections.abc import Callable
from typing import Any

__all__ = ["HookedLoop"]


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
