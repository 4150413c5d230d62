"""The Recipes screen's preview of a ch4 recipe runs in its child process on ch4's own plant
(issue 32, finding 4): before, every preview ran on the built-in NiMH board and a 5 A step
was refused "channel ch0 allows [-0.4, 0.4] A". The child is a real process (as under
``supervisor run``); the dry run inside it is on the virtual clock.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from supervisor.app.preview import previews_of
from supervisor.devices.registry import load_bench

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
CH4_CHARGE = """recipe: ch4-charge
steps:
  - {id: charge, charge: 5 A, duration: 10 min}
"""


async def test_a_preview_for_ch4_runs_on_the_ea_supply_and_the_pack() -> None:
    previews = previews_of(load_bench(ROOT / "io_maps" / "sim.yaml"))
    answer = await previews("recipes/ch4-charge.yaml", CH4_CHARGE, {}, 10.0, 1.0, 120.0, "ch4")
    assert "errors" not in answer, answer
    assert answer["summary"]["state"] == "Complete"
    (cycle,) = answer["summary"]["cycles"]
    assert cycle["charge_capacity_ah"] == pytest.approx(5.0 * 10 / 60, rel=0.02)


async def test_a_preview_without_a_channel_still_runs_on_the_built_in_board() -> None:
    previews = previews_of(load_bench(ROOT / "io_maps" / "sim.yaml"))
    answer = await previews("recipes/ch4-charge.yaml", CH4_CHARGE, {}, None, 1.0, 120.0)
    (error,) = answer["errors"]
    assert "channel ch0 allows [-0.4, 0.4] A" in error["message"]
