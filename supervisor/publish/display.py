"""The Chadèche status line (seed 000 §III.E.1), logged while a test is under way.

``C/01/07 dba=0 mA= 50 CET= 17520 SET= 159 TET= 17520 STA= 21 V=1.373 mAh=1302.4, <date>``:
charge or discharge by the commanded current's sign, cycle, step, board address, the
commanded current in mA, cycle / step / test elapsed time and step time left in s, cell
voltage, charge in mAh, and the local date.
"""

from __future__ import annotations

import logging
import math
import time

from supervisor.core.records import Record

log = logging.getLogger(__name__)


def display_line(rec: Record, dba: int) -> str:
    """The status line of a sample (``rec``) of a channel on board address ``dba``."""
    amps = rec.current_cmd_a
    cd = "C" if amps >= 0 else "D"
    sta = max(0.0, rec.step_remaining_s) if rec.step_remaining_s is not None else 0.0
    wall = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(rec.wall))
    return (
        f"{cd}/{rec.cycle:02d}/{rec.step_index + 1:02d} dba={dba} mA={abs(amps) * 1000:3.0f}"
        f" CET= {rec.cycle_time_s:.0f} SET= {rec.step_time_s:.0f} TET= {rec.test_time_s:.0f}"
        f" STA= {sta:.0f} V={rec.last_voltage_v:.3f} mAh={rec.charge_ah * 1000:.1f},"
        f" {wall}"
    )


class ChadecheDisplay:
    """A chain sampler: asks for a snapshot every ``period_s`` and logs its line."""

    def __init__(self, channel: str, dba: int = 0, period_s: float = 60.0) -> None:
        self.channel = channel
        self.dba = dba  # board address shown in the line
        self.period_s = period_s
        self.last_line = ""
        self._last_t = -math.inf

    def due(self, now: float) -> bool:
        return now - self._last_t >= self.period_s

    def on_sample(self, rec: Record) -> None:
        self._last_t = rec.t
        self.last_line = display_line(rec, self.dba)
        log.info("%s: %s", self.channel, self.last_line)
