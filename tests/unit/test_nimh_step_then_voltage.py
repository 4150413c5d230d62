"""A NiMH cell stepped and read in one call (``NiMHCell.step_then_voltage_v``, what a
simulated Chadèche board asks at every poll; docs/adr/0018-scan-performance.md, "Dry run")
is the cell stepped then read, bit for bit: the same state, the same voltage, the same
errors, whatever the currents, step lengths and readings in between. Its shortcuts (the
voltage a substep leaves for the next one, the OCV table segment it remembers) answer
what the cell's own methods compute from scratch. The plain read-outs that replaced two
properties (``temperature_c``, ``fault``) read what the properties did."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.sim.battery import NiMHCell


class Afresh(NiMHCell):
    """The plain cell: every substep and every reading computed by the methods
    (``_arrhenius``, ``_ocv``, ``_overpotential``), nothing reused."""

    def _advance(self, current_a: float, h: float) -> float:
        self._at = None
        return super()._advance(current_a, h)

    def voltage_at(self, current_a: float) -> float:
        self._at = None
        return super().voltage_at(current_a)


def bits(x: float | None) -> object:
    """A float's bit pattern (tells 0.0 from -0.0 and NaN payloads); None as is."""
    return None if x is None else struct.pack("<d", x)


def state(cell: NiMHCell) -> tuple[object, ...]:
    return (
        bits(cell.soc),
        bits(cell.temperature_c),
        bits(cell.charge_ah),
        bits(cell.current_a),
        bits(cell.reversal_ah),
        cell.fault,
    )


def fault_as_the_property_said(cell: NiMHCell) -> str | None:
    """What the former ``NiMHCell.fault`` property computed from the deepest reversal."""
    if cell._reversed_max == 0.0:
        return None
    depth_mah = cell._reversed_max * cell.capacity_ah * 1000.0
    return f"cell driven past empty into reversal (deepest {depth_mah:.3g} mAh past empty)"


CURRENTS = [0.0, -0.0, 0.1, 0.2, 0.4, 2.0, 40.0, -0.1, -0.4, -2.0, -40.0, 1, -1, 1e200]
LENGTHS = [0.0, 0.25, 0.5, 1.0, 1, 2.5, 60.0]


@settings(max_examples=300, deadline=None)
@given(
    st.floats(0.0, 1.05),
    st.floats(-20.0, 60.0),
    st.lists(
        st.tuples(
            st.sampled_from(["fused", "step", "read", "read other"]),
            st.sampled_from(CURRENTS),
            st.sampled_from(LENGTHS),
        ),
        max_size=80,
    ),
)
def test_a_step_then_reading_in_one_call_is_the_step_then_the_reading(
    soc: float, temperature_c: float, program: list[tuple[str, float, float]]
) -> None:
    fused = NiMHCell(soc=soc, temperature_c=temperature_c)
    plain = Afresh(soc=soc, temperature_c=temperature_c)
    for how, current_a, dt_s in program:
        if how == "fused":
            got = fused.step_then_voltage_v(current_a, dt_s)
            plain.step(current_a, dt_s)
            want = plain.voltage_at(current_a)
        elif how == "step":
            fused.step(current_a, dt_s)
            plain.step(current_a, dt_s)
            got = want = 0.0
        elif how == "read":
            got, want = fused.voltage_at(current_a), plain.voltage_at(current_a)
        else:  # a reading at another current than the last step's
            other = -current_a if current_a else 0.3
            got, want = fused.voltage_at(other), plain.voltage_at(other)
        assert bits(got) == bits(want)
        assert state(fused) == state(plain)
        assert bits(fused.terminal_voltage_v) == bits(plain.terminal_voltage_v)
        assert bits(fused.ocv_v) == bits(plain.ocv_v)
        assert fused.fault == fault_as_the_property_said(fused)


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 1.05), st.sampled_from([0.05, 0.4, 2.0, -0.4, -2.0]))
def test_a_long_run_of_one_second_polls_crosses_ocv_segments_as_the_plain_cell(
    soc: float, current_a: float
) -> None:
    """Hours of a board's 1 s polls: the OCV segment remembered from one substep to the
    next (and the voltage each leaves) gives what the table lookup gives, through every
    segment edge, the knee, the clamps and a reversal."""
    fused, plain = NiMHCell(soc=soc), Afresh(soc=soc)
    plain.step(current_a, 1.0)  # the first step caches the substep's thermal decay
    fused.step(current_a, 1.0)
    for _ in range(3000):
        got = fused.step_then_voltage_v(current_a, 1.0)
        plain.step(current_a, 1.0)
        assert bits(got) == bits(plain.voltage_at(current_a))
        assert state(fused) == state(plain)


def test_it_refuses_what_step_refuses() -> None:
    for bad_current, bad_dt, message in [
        (math.nan, 1.0, "current_a must be finite"),
        (math.inf, 1.0, "current_a must be finite"),
        (0.1, math.nan, "dt_s must be finite"),
        (0.1, -1.0, "dt_s must be >= 0"),
    ]:
        cell = NiMHCell()
        cell.step(0.1, 1.0)  # a cached decay of 1 s: the one-call path is open
        with pytest.raises(ValueError, match=message):
            cell.step_then_voltage_v(bad_current, bad_dt)
        with pytest.raises(ValueError, match=message):
            cell.step(bad_current, bad_dt)


def test_the_temperature_and_fault_read_outs_read_the_state() -> None:
    cell = NiMHCell(capacity_ah=0.5, soc=0.01, temperature_c=30.0)
    assert (cell.temperature_c, cell.fault) == (30.0, None)
    for _ in range(200):  # driven past empty: the fault latches and deepens
        cell.step_then_voltage_v(-0.5, 1.0)
        assert cell.fault == fault_as_the_property_said(cell)
    assert cell.fault is not None
    deepest = cell.fault
    for _ in range(10):  # charging ends the reversal, the fault stays as it was
        cell.step(0.5, 1.0)
    assert cell.reversal_ah == 0.0 and cell.fault == deepest
