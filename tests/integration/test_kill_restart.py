"""The fault case "SIGKILL the supervisor at random points of a running recipe and restart
it" (docs/design.md "Safety"; seed 001's resumable context), three times with real processes:
``supervisor sim`` serves the seed 002 devices in one process (their battery outlives the
supervisor), ``supervisor run --no-sim`` is killed by pid at a seeded random moment and
started again on the same state directory. ``supervisor bench kill-restart`` runs the same
20 times."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from supervisor.bench.killrestart import COUNTER_TOLERANCE, kill_restart

ROOT = Path(__file__).resolve().parents[2]
SEED = 2026
pytestmark = pytest.mark.integration
log = logging.getLogger(__name__)


@pytest.mark.timeout(300)
def test_a_supervisor_killed_during_a_recipe_brings_it_back_held_and_it_completes(
    tmp_path: Path,
) -> None:
    log.info("kill-restart, seed %d", SEED)
    runs = kill_restart(3, SEED, tmp_path, io_map=str(ROOT / "io_maps" / "sim.yaml"), say=log.info)
    assert len(runs) == 3
    for run in runs:
        where = f"kill {run.index} at {run.kill_after_s} s (seed {SEED})"
        assert run.saved_state == "Running", where
        assert run.restored_state == "Held", where
        assert run.restored_step == run.saved_step, where
        assert run.counter_error <= COUNTER_TOLERANCE, where
        assert run.outputs_off, f"{where}: re-energised on its own"
        assert run.final_state == "Complete", f"{where}: {run.problems}"
        assert run.restart_noted, f"{where}: the timeline does not record the restart"
        assert run.bdf_continues, f"{where}: the BDF rows do not append after the restart"
        assert run.ok, f"{where}: {run.problems}"
