"""An asyncio lock that says, through a public method, whether taking it now would wait."""

from __future__ import annotations

import asyncio
from typing import Literal


class CountingLock(asyncio.Lock):
    """``asyncio.Lock`` that counts the tasks holding it or waiting inside :meth:`acquire`,
    so that :meth:`free` can say that a task asking for it now gets it without yielding:
    nobody holds it and nobody waits for it (the lock is fair: a waiting task goes first).

    A driver that does its exchange without an await when its locks are free
    (``devices/chadeche/driver.py``: a dry run's polls) asks :meth:`free` (reads ``users``);
    asyncio keeps its own waiters private."""

    def __init__(self) -> None:
        super().__init__()
        self.users = 0
        """Tasks that hold the lock or wait for it (read-only: counted by ``acquire`` and
        ``release``); 0 is :meth:`free`, read without a call where a scan asks (issue 29:
        the dry run's polls ask three times a scan)."""

    async def acquire(self) -> Literal[True]:
        self.users += 1
        try:
            return await super().acquire()
        except BaseException:  # cancelled while waiting: it neither waits nor holds
            self.users -= 1
            raise

    def release(self) -> None:
        super().release()
        self.users -= 1

    def free(self) -> bool:
        """True: :meth:`acquire` called now returns without yielding. False: it may wait
        (also while a cancelled waiter has not run yet: then the caller takes the awaited
        way, which is always right)."""
        return self.users == 0
