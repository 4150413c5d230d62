"""A NiMH cell's step reuses what its last voltage reading computed from the same state
(docs/adr/0018-scan-performance.md, "Dry run"): the cell comes out bit for bit as when
every step computes everything again, through charge, overcharge, rest, discharge and
reversal, at any step length; and a step given an int or a bad number is treated as
before."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.sim.battery import NiMHCell


def readings(cell: NiMHCell) -> tuple[float, ...]:
    return (
        cell.soc,
        cell.temperature_c,
        cell.charge_ah,
        cell.terminal_voltage_v,
        cell.ocv_v,
        cell.reversal_ah,
    )


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, 1.05),
    st.lists(
        st.tuples(
            st.sampled_from([0.0, -0.0, 0.2, 0.4, 2.0, -0.2, -0.4, -2.0]),
            st.sampled_from([0.0, 0.1, 1.0, 2.5, 60.0]),
            st.booleans(),
        ),
        max_size=60,
    ),
)
def test_a_step_after_a_reading_is_the_step_computed_afresh(
    soc: float, program: list[tuple[float, float, bool]]
) -> None:
    reusing, afresh = NiMHCell(soc=soc), NiMHCell(soc=soc)
    for current_a, dt_s, read in program:
        for cell in (reusing, afresh):
            if read:
                cell.voltage_at(current_a)  # what a simulated board reads after a step
        afresh._at = None  # forget it: this one computes every step from scratch
        reusing.step(current_a, dt_s)
        afresh.step(current_a, dt_s)
        assert readings(reusing) == readings(afresh)


def test_a_step_takes_an_int_and_refuses_what_is_not_finite() -> None:
    a, b = NiMHCell(soc=0.5), NiMHCell(soc=0.5)
    a.step(1, 2)
    b.step(1.0, 2.0)
    assert readings(a) == readings(b)
    with pytest.raises(ValueError, match="current_a must be finite"):
        a.step(math.nan, 1.0)
    with pytest.raises(ValueError, match="dt_s must be finite"):
        a.step(0.1, math.inf)
