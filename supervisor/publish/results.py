"""Result files per test: BDF CSV, the Chadèche ``;`` line, and a summary.

Layout: ``<results>/<test id>/`` with
- ``<test id>.bdf.csv`` — Battery Data Format columns (positive current charges);
- ``<test id>.chadeche.csv`` — seed 000 §III.E.2 result lines, for continuity;
- ``summary.json`` — capacity and energy per cycle, efficiencies, duration, end reason,
  and the step timeline with the cause of every step change.
Rows are flushed as they are written: a crash loses nothing already recorded.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from supervisor.core.records import ChainEvent, Record

log = logging.getLogger(__name__)

BDF_COLUMNS = (
    "Test Time / s",
    "Unix Time / s",
    "Voltage / V",
    "Current / A",
    "Power / W",
    "Cycle Count / 1",
    "Step Count / 1",
    "Step ID",
    "Step Type",
    "Step Time / s",
    "Record Index / 1",
    "Charging Capacity / Ah",
    "Discharging Capacity / Ah",
    "Net Capacity / Ah",
    "Charging Energy / Wh",
    "Discharging Energy / Wh",
    "Cycle Charging Capacity / Ah",
    "Cycle Discharging Capacity / Ah",
    "Temperature T1 / degC",
)


def _f(x: float | None, digits: int = 6) -> str:
    return "" if x is None else f"{x:.{digits}g}"


def chadeche_line(rec: Record, dba: int) -> str:
    """``C;01;07;0; 50; 17520; 159; 17520; 21;1.373;1302.4;Mon May 22 03:21:43 2017``."""
    amps = rec.setpoint_a
    cd = "C" if amps >= 0 else "D"
    sta = max(0.0, rec.step_remaining_s) if rec.step_remaining_s is not None else 0.0
    date = time.strftime("%a %b %d %H:%M:%S %Y", time.localtime(rec.wall))
    v = rec.voltage_v if rec.voltage_v is not None else 0.0
    return (
        f"{cd};{rec.cycle:02d};{rec.step_index + 1:02d};{dba};{abs(amps) * 1000:3.0f};"
        f" {rec.cycle_time_s:.0f}; {rec.step_time_s:.0f}; {rec.test_time_s:.0f}; {sta:.0f};"
        f"{v:.3f};{rec.charge_ah * 1000:.1f};{date}"
    )


@dataclass
class CycleSummary:
    cycle: int
    charged_ah: float = 0.0
    discharged_ah: float = 0.0
    charged_wh: float = 0.0
    discharged_wh: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        ce = self.discharged_ah / self.charged_ah if self.charged_ah > 0 else None
        ee = self.discharged_wh / self.charged_wh if self.charged_wh > 0 else None
        return {
            "cycle": self.cycle,
            "charge_capacity_ah": round(self.charged_ah, 6),
            "discharge_capacity_ah": round(self.discharged_ah, 6),
            "charge_energy_wh": round(self.charged_wh, 6),
            "discharge_energy_wh": round(self.discharged_wh, 6),
            "coulombic_efficiency": None if ce is None else round(ce, 6),
            "energy_efficiency": None if ee is None else round(ee, 6),
        }


@dataclass
class ResultCollector:
    """Keeps the timeline and per-cycle figures in memory; writes files if given a folder."""

    channel: str
    recipe: str
    test_id: str
    folder: Path | None = None
    dba: int = 0
    records: int = 0
    timeline: list[dict[str, Any]] = field(default_factory=list)
    cycles: dict[int, CycleSummary] = field(default_factory=dict)
    first_t: float | None = None
    last_rec: Record | None = None
    _bdf: IO[str] | None = None
    _bdf_writer: Any = None
    _cha: IO[str] | None = None

    def __post_init__(self) -> None:
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._bdf = (self.folder / f"{self.test_id}.bdf.csv").open(
                "w", newline="", encoding="utf-8"
            )
            self._bdf_writer = csv.writer(self._bdf)
            self._bdf_writer.writerow(BDF_COLUMNS)
            self._cha = (self.folder / f"{self.test_id}.chadeche.csv").open("w", encoding="utf-8")

    def on_event(self, ev: ChainEvent) -> None:
        if self.first_t is None:
            self.first_t = ev.t
        # "command": an operator command of the running test, accepted or refused, by whom.
        if ev.kind in ("step", "state", "alarm", "command"):
            self.timeline.append(
                {
                    "test_time_s": round(ev.t - self.first_t, 3),
                    "kind": ev.kind,
                    "cycle": ev.cycle,
                    "step": ev.step_id,
                    "text": ev.text,
                }
            )

    def on_record(self, rec: Record) -> None:
        self.records += 1
        self.last_rec = rec
        c = self.cycles.setdefault(rec.cycle, CycleSummary(rec.cycle))
        c.charged_ah = rec.cycle_charged_ah
        c.discharged_ah = rec.cycle_discharged_ah
        c.charged_wh = rec.cycle_charged_wh
        c.discharged_wh = rec.cycle_discharged_wh
        if self._bdf_writer is not None and self._bdf is not None and self._cha is not None:
            self._bdf_writer.writerow(
                (
                    f"{rec.test_time_s:.3f}",
                    f"{rec.wall:.3f}",
                    _f(rec.voltage_v),
                    _f(rec.current_a),
                    _f(rec.power_w),
                    rec.cycle,
                    rec.step_count,
                    rec.step_id,
                    rec.step_type,
                    f"{rec.step_time_s:.3f}",
                    self.records,
                    _f(rec.charged_ah),
                    _f(rec.discharged_ah),
                    _f(rec.charged_ah - rec.discharged_ah),
                    _f(rec.charged_wh),
                    _f(rec.discharged_wh),
                    _f(rec.cycle_charged_ah),
                    _f(rec.cycle_discharged_ah),
                    _f(rec.temperature_c),
                )
            )
            self._bdf.flush()
            self._cha.write(chadeche_line(rec, self.dba) + "\n")
            self._cha.flush()

    def summary(self, end_reason: str, state: str) -> dict[str, Any]:
        duration = self.last_rec.test_time_s if self.last_rec is not None else 0.0
        return {
            "test_id": self.test_id,
            "channel": self.channel,
            "recipe": self.recipe,
            "state": state,
            "end_reason": end_reason,
            "duration_s": round(duration, 3),
            "records": self.records,
            "cycles": [c.as_dict() for _, c in sorted(self.cycles.items())],
            "timeline": self.timeline,
        }

    def close(self, end_reason: str, state: str) -> dict[str, Any]:
        s = self.summary(end_reason, state)
        if self.folder is not None:
            (self.folder / "summary.json").write_text(
                json.dumps(s, indent=2) + "\n", encoding="utf-8"
            )
        for f in (self._bdf, self._cha):
            if f is not None:
                f.close()
        self._bdf = self._cha = None
        return s
