"""A fixed window of the latest floats, allocated once (issue 13's memory growth).

The scan's statistics windows were deques of 10 000 Python floats: a float object and a
pointer each (32 bytes), allocated as the window filled, 17 minutes at a 100 ms scan, so
that the process grew for its first quarter of an hour. Here the window is one array of
doubles (8 bytes each) from the start: nothing grows and nothing is left for the
collector.
"""

from __future__ import annotations

from array import array
from collections.abc import Iterator


class FloatRing:
    """The latest ``maxlen`` floats appended, oldest first (a deque's reading surface:
    ``append``, ``len``, iteration, ``[i]`` with negative ``i``)."""

    __slots__ = ("_count", "_data", "_next", "maxlen")

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError("a ring holds at least one value")
        self.maxlen = maxlen
        self._data = array("d", bytes(8 * maxlen))
        self._next = 0
        self._count = 0

    def append(self, value: float) -> None:
        self._data[self._next] = value
        self._next = (self._next + 1) % self.maxlen
        if self._count < self.maxlen:
            self._count += 1

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[float]:
        start = (self._next - self._count) % self.maxlen
        data = self._data
        if start + self._count <= self.maxlen:
            yield from data[start : start + self._count]
        else:
            yield from data[start:]
            yield from data[: self._next]

    def __getitem__(self, i: int) -> float:
        n = self._count
        if not -n <= i < n:
            raise IndexError("ring index out of range")
        if i < 0:
            i += n
        return self._data[(self._next - n + i) % self.maxlen]
