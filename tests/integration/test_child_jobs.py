"""``ChildJobs`` (supervisor/commands/childjob.py): a costly job runs in a child process with
a deadline and a memory limit, and a job given up on is really stopped — its process killed,
not a thread left running in the supervisor (issue 28, finding 2). Real processes; waits
are bounded, nothing asserts a duration."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import pytest

from supervisor.commands.childjob import (
    ChildJobs,
    ChildJobsBusy,
    ChildOutOfMemory,
    ChildTimeout,
)

pytestmark = pytest.mark.integration

THIS: str = "test_child_jobs"
GONE_WAIT_S = 30.0
"""Upper bound for a killed process to disappear on a loaded machine (not a timing claim)."""


def _importable() -> None:
    # The child imports this module by name to find the job functions (pickled by name).
    here = str(Path(__file__).parent)
    path = os.environ.get("PYTHONPATH", "")
    if here not in path.split(os.pathsep):
        os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (path, here) if p)


def whoami(x: int) -> tuple[int, int]:
    return os.getpid(), x * 2


def spin(pid_file: str) -> None:
    Path(pid_file).write_text(str(os.getpid()), encoding="utf-8")
    while True:
        pass


def hog() -> int:
    blocks = [bytearray(64 * 1024 * 1024) for _ in range(64)]  # 4 GiB
    return len(blocks)


def gone(pid: int) -> bool:
    """``pid`` has ended (no such process, or a zombie waiting for its parent)."""
    deadline = time.monotonic() + GONE_WAIT_S
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.05)
    return False


def _pid_text(pid_file: Path) -> str:
    return pid_file.read_text() if pid_file.exists() else ""


async def pid_of(pid_file: Path) -> int:
    deadline = time.monotonic() + 120.0
    while not (text := await asyncio.to_thread(_pid_text, pid_file)):
        assert time.monotonic() < deadline, "the job never started"
        await asyncio.sleep(0.05)
    return int(text)


@pytest.fixture
async def jobs() -> ChildJobs:
    _importable()
    j = ChildJobs(workers=1, queue=1, memory_limit_bytes=512 * 1024 * 1024, preload=(THIS,))
    yield j  # type: ignore[misc]
    await j.close()


async def test_the_job_runs_in_another_process_and_its_result_comes_back(
    jobs: ChildJobs,
) -> None:
    pid, doubled = await jobs.run(whoami, (21,), 120.0, "whoami")
    assert doubled == 42 and pid != os.getpid()
    assert gone(pid)  # one job per process: it ends with its answer


async def test_a_job_past_its_deadline_is_refused_and_its_process_killed(
    jobs: ChildJobs, tmp_path: Path
) -> None:
    pid_file = tmp_path / "pid"
    task = asyncio.create_task(jobs.run(spin, (str(pid_file),), 120.0, "spinning"))
    pid = await pid_of(pid_file)
    # The deadline is the caller's: a shorter one on a job already running.
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert gone(pid) and jobs.killed == 1 and jobs.running_pids == []

    pid_file.unlink()
    with pytest.raises(ChildTimeout, match="took more than 3 s; stopped"):
        await jobs.run(spin, (str(pid_file),), 3.0, "spinning")
    if pid_file.exists() and pid_file.read_text():  # it had started within its 3 s
        assert gone(int(pid_file.read_text()))
    assert jobs.running_pids == []


async def test_a_job_that_needs_more_memory_than_its_limit_is_refused(jobs: ChildJobs) -> None:
    with pytest.raises(ChildOutOfMemory, match="needs more than 512 MiB"):
        await jobs.run(hog, (), 120.0, "a hog")


async def test_beyond_the_workers_and_the_queue_a_job_is_refused_at_once(
    jobs: ChildJobs, tmp_path: Path
) -> None:
    running = [
        asyncio.create_task(jobs.run(spin, (str(tmp_path / f"pid{i}"),), 120.0, "spinning"))
        for i in range(2)  # one runs, one waits
    ]
    await asyncio.sleep(0)
    with pytest.raises(ChildJobsBusy, match="too many at once; try again in 5 s"):
        await jobs.run(whoami, (1,), 120.0, "one more")
    pid = await pid_of(tmp_path / "pid0")
    await jobs.close()  # shutdown: the running job's process is killed at once
    assert gone(pid)
    for t in running:
        with pytest.raises(ChildJobsBusy):
            await t
