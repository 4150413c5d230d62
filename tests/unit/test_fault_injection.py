"""Every device of the simulated bench killed, hung, answering garbage or dropping its link
while a test runs (in process, virtual clock: the times are exact simulated times).

For each case: the channel trips with an alarm saying what was lost, no current flows into
the cell any more, the test is held (not aborted) at the step it was in with its counters,
and once the device is back and the trip reset, the test resumes at the same step.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from supervisor.bench.faults import CASES, FaultCase, run_case

# The slowest detections by design: a BMS frame is stale after 3 periods (3 s), then the
# BMS check's 1 s trip delay; a silent device after its 0.5 s reply timeout.
TRIP_WITHIN_S = {"bms": 4.5}
DEFAULT_TRIP_WITHIN_S = 1.0


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.device}-{c.kind}")
async def test_a_device_fault_holds_the_test_safe_and_it_resumes_when_the_device_is_back(
    case: FaultCase, tmp_path: Path
) -> None:
    r = await run_case(case, tmp_path)
    assert r.trip_s <= TRIP_WITHIN_S.get(case.device, DEFAULT_TRIP_WITHIN_S), r
    assert r.fault, r
    assert r.held_at == "Held at charge", r
    assert r.charge_kept, r
    assert r.safe_after_heal, r  # never re-energised on its own
    assert r.resumed, r
    if case.device == "chadeche":
        # The board keeps its last DAC value while the SPI bus is dead: nothing the
        # supervisor sends can reach it (the board has no watchdog of its own).
        assert math.isinf(r.safe_s)
    else:
        assert r.safe_s <= r.trip_s + 1.0, r
