"""On-delay: a condition counts only once it has held for a while (against chattering)."""

from __future__ import annotations


class OnDelay:
    """``update(cond, now)`` is true once ``cond`` has been true for ``delay_s`` without a
    break (at once when ``delay_s`` is 0); false as soon as ``cond`` is false."""

    __slots__ = ("_since", "delay_s")

    def __init__(self, delay_s: float = 0.0) -> None:
        if delay_s < 0:
            raise ValueError("an on-delay cannot be negative")
        self.delay_s = delay_s
        self._since: float | None = None

    def update(self, cond: bool, now: float) -> bool:
        if not cond:
            self._since = None
            return False
        if self._since is None:
            self._since = now
        return now - self._since >= self.delay_s - 1e-9
