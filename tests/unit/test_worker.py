"""``run_in_worker``: a job off the event loop, in a daemon thread, with a time limit."""

from __future__ import annotations

import asyncio
import gc
import logging
import threading

import pytest

from supervisor.commands.worker import WorkerTimeout, run_in_worker


async def test_the_job_runs_in_another_thread_and_its_result_comes_back() -> None:
    ran_on: list[threading.Thread] = []

    def job() -> int:
        ran_on.append(threading.current_thread())
        return 42

    assert await run_in_worker(job, 5.0, "job") == 42
    assert ran_on[0] is not threading.current_thread() and ran_on[0].daemon


async def test_the_job_s_exception_is_raised_to_the_caller() -> None:
    def job() -> None:
        raise ValueError("refused")

    with pytest.raises(ValueError, match="refused"):
        await run_in_worker(job, 5.0, "job")


async def test_full_collections_wait_while_the_job_runs_and_resume_after() -> None:
    before = gc.get_threshold()
    seen: list[tuple[int, ...]] = []
    assert await run_in_worker(lambda: seen.append(gc.get_threshold()), 5.0, "job") is None
    assert seen[0][:2] == before[:2] and seen[0][2] > 10**9  # young ones go on
    assert gc.get_threshold() == before


async def test_a_job_past_its_time_limit_is_abandoned_and_its_result_dropped(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, "supervisor.commands.worker")
    release = threading.Event()
    threads: list[threading.Thread] = []
    before = gc.get_threshold()

    def stuck() -> str:
        threads.append(threading.current_thread())
        release.wait(10.0)
        return "too late"

    with pytest.raises(WorkerTimeout) as info:
        await run_in_worker(stuck, 0.05, "stuck job")
    assert str(info.value) == "stuck job took more than 0.05 s"
    # The caller gave up: full collections are back even though the thread still waits.
    assert gc.get_threshold() == before and threads[0].is_alive()
    release.set()
    await asyncio.to_thread(threads[0].join, 10.0)
    await asyncio.sleep(0.01)  # the dropped result's callback has had its turn
    assert "stuck job: finished after its time limit; result dropped" in caplog.text
