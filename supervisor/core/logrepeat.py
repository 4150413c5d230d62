"""Repeated log lines collapsed (issue 27, finding 3: a flood of 1000 idle connections wrote
71,567 "Too many open files" lines, 32 MB, into the bench's log).

``RepeatFilter`` is a ``logging.Filter`` put on the handler of ``supervisor run``'s log. Per
window of ``window_s`` (10 s):

- a line whose **text** (logger, level, formatted message) was already written in this
  window is dropped: ``asyncio``'s "socket.accept() out of system resource" with its
  traceback, a driver's "cannot connect: Too many open files" — at most once per window;
- lines of one **template** (logger, level, the message before its arguments) with
  different texts pass up to ``burst`` (10) per window, then are dropped: "refusing a
  connection from <peer>" once per peer would still be a flood, while five channels
  tripping at once (five texts of one template) are all written.

The first line of a key written after a window in which lines were dropped says how many:
``… [N similar lines suppressed in the last 10 s]``. Memory is bounded (``MAX_KEYS``: the
oldest keys go first). Thread-safe (the scan's thread and the OPC UA server's thread log).
Times are the clock's ``now`` (virtual in tests).
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

WINDOW_S: Final = 10.0
"""The window lines are counted in."""
BURST: Final = 10
"""Lines of one template (different texts) written per window at most."""
MAX_KEYS: Final = 1024
"""Keys remembered at most per table (a flood of distinct templates cannot grow memory)."""


_Key = tuple[str, int, str]
"""(logger, level, text or template)."""


@dataclass(slots=True)
class _Count:
    start: float
    """When this key's window began."""
    passed: int
    suppressed: int


class RepeatFilter(logging.Filter):
    """Drops the repeats of one line (and the excess of one template) within a window."""

    def __init__(
        self,
        now: Callable[[], float],
        window_s: float = WINDOW_S,
        burst: int = BURST,
    ) -> None:
        super().__init__()
        self.now = now
        self.window_s = window_s
        self.burst = burst
        self.suppressed = 0
        """Lines dropped since the start (all keys)."""
        self._texts: OrderedDict[_Key, _Count] = OrderedDict()
        self._templates: OrderedDict[_Key, _Count] = OrderedDict()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            text = record.getMessage()
        except Exception:  # a bad format: let the handler report it as logging does
            return True
        now = self.now()
        template = str(record.msg)
        with self._lock:
            by_text = self._count(self._texts, (record.name, record.levelno, text), now)
            by_template = self._count(self._templates, (record.name, record.levelno, template), now)
            if by_text.passed >= 1 or by_template.passed >= self.burst:
                by_text.suppressed += 1
                by_template.suppressed += 1
                self.suppressed += 1
                return False
            before = max(by_text.suppressed, by_template.suppressed)
            by_text.passed += 1
            by_template.passed += 1
            by_text.suppressed = by_template.suppressed = 0
        if before:
            # Said with the next line of the key: a filter only sees lines as they come.
            record.msg = (
                f"{text} [{before} similar lines suppressed in the last {self.window_s:g} s]"
            )
            record.args = None
        return True

    def _count(self, table: OrderedDict[_Key, _Count], key: _Key, now: float) -> _Count:
        count = table.get(key)
        if count is None:
            count = table[key] = _Count(now, 0, 0)
            if len(table) > MAX_KEYS:
                table.popitem(last=False)
        elif now - count.start >= self.window_s:
            # A new window: what was suppressed in the last one is still to be said.
            count.start, count.passed = now, 0
            table.move_to_end(key)
        return count
