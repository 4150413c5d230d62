"""The values a step's conditions read: channel variables, parameters and bench tags.

Besides plain readings this keeps what needs a memory of the step: the dV/dt window and
the voltage peak since the step started (−ΔV detection, seed 000's "delta peak" wish).
A reading whose tag is not GOOD is None, which makes a comparison unknown (ADR 0004:
an unknown condition never fires).
"""

from __future__ import annotations

from collections import deque

from supervisor.chains.compiler import CHANNEL_VARIABLES
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import Program
from supervisor.chains.run import RunState
from supervisor.tags import TagDB

# dV/dt over the last minute, once it spans at least 10 s (shorter spans are noise).
DV_DT_WINDOW_S = 60.0
DV_DT_MIN_SPAN_S = 10.0

Values = dict[str, float | bool | None]


def names_read(program: Program) -> set[str]:
    """Every name the program's conditions (transitions, interlocks, errors) read."""
    exprs = [t.condition for st in program.steps for t in st.transitions]
    exprs += [t.condition for g in program.groups for t in g.transitions]
    exprs += [e for st in program.steps for e in (st.interlock, st.error) if e is not None]
    used: set[str] = set()
    for e in exprs:
        used |= e.names
    return used


class ConditionValues:
    def __init__(self, port: ChannelPort, db: TagDB, program: Program) -> None:
        self._port = port
        self._db = db
        self._parameters = program.parameters
        self._initial_charge_ah = program.initial_charge_ah
        # Bench tags by full name: only those the program reads are looked up each scan.
        self._tag_names = sorted(
            names_read(program) - set(CHANNEL_VARIABLES) - set(program.parameters)
        )
        self._dv: deque[tuple[float, float]] = deque()
        self.peak_v: float | None = None

    def restart(self) -> None:
        """A step starts: its peak and its dV/dt window start again."""
        self.peak_v = None
        self._dv.clear()

    def observe(self, now: float, voltage_v: float) -> None:
        """A GOOD voltage reading of this scan."""
        dv = self._dv
        dv.append((now, voltage_v))
        while dv and now - dv[0][0] > DV_DT_WINDOW_S:
            dv.popleft()
        self.peak_v = voltage_v if self.peak_v is None else max(self.peak_v, voltage_v)

    def dv_dt(self) -> float | None:
        """V/s over the window, None until it spans ``DV_DT_MIN_SPAN_S``."""
        dv = self._dv
        if len(dv) >= 2 and dv[-1][0] - dv[0][0] >= DV_DT_MIN_SPAN_S:
            (t0, v0), (t1, v1) = dv[0], dv[-1]
            return (v1 - v0) / (t1 - t0)
        return None

    def charge_ah(self, run: RunState) -> float:
        """The cell's charge: the recipe's initial charge plus what moved since the start."""
        return self._initial_charge_ah + self._port.charge_ah.as_float() - run.q0_ah

    def values(self, now: float, run: RunState) -> Values:
        port = self._port
        q = port.charge_ah.as_float()
        energy = port.energy_wh.as_float()
        v = port.voltage.as_float() if port.voltage.good else None
        i, t, p = port.current, port.temperature, port.power
        peak = self.peak_v
        values: Values = {
            "voltage": v,
            "current": i.as_float() if i.good else None,
            "temperature": t.as_float() if t.good else None,
            "power": p.as_float() if p.good else None,
            "charge": self._initial_charge_ah + q - run.q0_ah,
            "energy": energy,
            "step_charge": q - run.step_q0,
            "step_energy": energy - run.step_e0,
            "step_time": now - run.t_step0,
            "cycle_time": now - run.t_cycle0,
            "test_time": now - run.t_test0,
            "cycle": float(run.cycle),
            "dv_dt": self.dv_dt(),
            "delta_peak": (peak - v) if (peak is not None and v is not None) else None,
            "peak_voltage": peak,
        }
        values.update(self._parameters)
        db = self._db
        for name in self._tag_names:
            tag = db.get(name)
            tv = tag.value if tag is not None and tag.good else None
            values[name] = (
                tv if isinstance(tv, bool | float) else float(tv) if isinstance(tv, int) else None
            )
        return values
