"""``supervisor run`` takes the objects of its start-up out of the garbage collector's
generations before the scan starts (docs/adr/0019-http-off-the-scan.md): the first full
collections after start-up, set off by the first page's allocations, otherwise walked
every start-up object on the scan's thread (the browser tests' ``scan.stall`` right after
a page logged in). In process; the bench's run is replaced by one that only looks."""

from __future__ import annotations

import asyncio
import gc
from collections.abc import Iterator
from pathlib import Path

import pytest
from commandrig import chadeche_map

from supervisor.app.bench import Bench
from supervisor.cli.main import main

pytestmark = pytest.mark.integration


@pytest.fixture
def unfrozen() -> Iterator[None]:
    gc.unfreeze()
    yield
    gc.unfreeze()  # the rest of the test session collects as before


def test_supervisor_run_freezes_its_start_up_objects_before_the_scan_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, unfrozen: None
) -> None:
    seen: dict[str, int] = {}

    async def run(self: Bench, stop: asyncio.Event) -> None:
        seen["frozen"] = gc.get_freeze_count()
        seen["tags"] = len(self.db)

    monkeypatch.setattr(Bench, "run", run)
    code = main(["run", chadeche_map(tmp_path), "--http-port", "0"])
    assert code == 0
    assert seen["tags"] > 0
    # The bench, its servers and the imports: far more objects than tags.
    assert seen["frozen"] > 10 * seen["tags"]
