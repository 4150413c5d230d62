"""``CountingLock.free()``: a task that asks for the lock now gets it without yielding.
The Chadèche driver polls without an await only then (issue 29, item 4: it read asyncio's
private ``_locked`` and ``_waiters``)."""

from __future__ import annotations

import asyncio

from supervisor.core.locks import CountingLock


def acquired_at_once(lock: CountingLock) -> bool:
    """Acquire ``lock`` by stepping its coroutine once: True (and released again) when
    it finished without suspending; False (given up) when it would have waited."""
    step = lock.acquire()
    try:
        step.send(None)
    except StopIteration:
        lock.release()
        return True
    step.close()
    return False


async def test_a_free_lock_is_acquired_without_waiting_and_a_lock_that_is_not_free_would_wait() -> (
    None
):
    lock = CountingLock()
    seen: list[tuple[str, bool, bool]] = []

    def look(state: str) -> None:
        free = lock.free()
        assert free is (lock.users == 0)  # what the driver reads without a call
        seen.append((state, free, acquired_at_once(lock)))

    look("never used")
    await lock.acquire()
    look("held")
    waiter = asyncio.ensure_future(lock.acquire())
    await asyncio.sleep(0)
    look("held, a task waiting")
    lock.release()
    look("released, the waiting task not run yet")  # it goes first
    await waiter
    look("held by the task that waited")
    lock.release()
    look("waited for once, free again")
    assert seen == [
        ("never used", True, True),
        ("held", False, False),
        ("held, a task waiting", False, False),
        ("released, the waiting task not run yet", False, False),
        ("held by the task that waited", False, False),
        ("waited for once, free again", True, True),
    ]


async def test_a_cancelled_waiter_leaves_the_lock_free_once_it_has_run() -> None:
    lock = CountingLock()
    await lock.acquire()
    waiter = asyncio.ensure_future(lock.acquire())
    await asyncio.sleep(0)
    waiter.cancel()
    assert not lock.free()  # not run yet: the awaited way, which is always right
    await asyncio.sleep(0)
    lock.release()
    assert waiter.cancelled()
    assert lock.free() and acquired_at_once(lock)
    async with lock:
        assert not lock.free()
    assert lock.free()
