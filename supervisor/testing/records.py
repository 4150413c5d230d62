"""A result record for tests: a charge step's sample with every counter at zero, and the
fields a test cares about given."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from supervisor.core.records import Record

_BASE = Record(
    t=0.0,
    wall=1.7e9,
    test_time_s=0.0,
    step_time_s=0.0,
    cycle_time_s=0.0,
    cycle=1,
    step_count=1,
    step_index=0,
    step_id="c",
    step_type="CC_CHG",
    voltage_v=1.3,
    current_a=0.05,
    power_w=0.065,
    temperature_c=None,
    charge_ah=0.0,
    charged_ah=0.0,
    discharged_ah=0.0,
    charged_wh=0.0,
    discharged_wh=0.0,
    cycle_charged_ah=0.0,
    cycle_discharged_ah=0.0,
    cycle_charged_wh=0.0,
    cycle_discharged_wh=0.0,
    setpoint_a=0.05,
    step_remaining_s=None,
    reason="period",
)


def make_record(**fields: Any) -> Record:
    """A record of a 50 mA charge at 1.3 V, with ``fields`` instead."""
    return replace(_BASE, **fields)
