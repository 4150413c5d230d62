"""Pytest fixtures for the project's tests (``pytest_plugins`` in tests/conftest.py)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from supervisor.core.clock import VirtualClock


@pytest.fixture
def virtual_clock() -> VirtualClock:
    """Time that only moves when the code under test sleeps (scans run back to back)."""
    return VirtualClock()


@pytest.fixture(autouse=True)
async def _no_leftover_tasks() -> AsyncIterator[None]:
    """Fail a test that leaves asyncio tasks running (they would leak into the next one)."""
    before = asyncio.all_tasks()
    yield
    await asyncio.sleep(0)
    left = [
        t for t in asyncio.all_tasks() - before if not t.done() and t is not asyncio.current_task()
    ]
    for t in left:
        t.cancel()
    assert not left, f"test left tasks running: {[t.get_name() for t in left]}"
