"""Fixtures for the unit tests: which transport a driver rig is built on; the bench of
``io_maps/sim.yaml`` started on a virtual clock (``commandrig.started_bench``)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from commandrig import started_bench
from rig_transports import IN_PROCESS

from supervisor.app.bench import Bench


@pytest.fixture
def transport(request: pytest.FixtureRequest) -> str:
    """``in-process`` unless the test is marked ``on_both_transports`` (then each in turn)."""
    return str(getattr(request, "param", IN_PROCESS))


@pytest.fixture
async def bench(tmp_path: Path) -> AsyncIterator[Bench]:
    """The simulated bench, started (a module that needs another defines its own)."""
    b = await started_bench(tmp_path)
    try:
        yield b
    finally:
        await b.shutdown()
