"""The values a step's conditions read: channel variables, parameters and bench tags.

Besides plain readings this keeps what needs a memory of the step: the dV/dt window and
the voltage peak since the step started (−ΔV detection, seed 000's "delta peak" wish).
A reading whose tag is not GOOD is None, which makes a comparison unknown (ADR 0004:
an unknown condition never fires).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

from supervisor.chains.compiler import CHANNEL_VARIABLES
from supervisor.chains.port import ChannelPort
from supervisor.chains.program import Program
from supervisor.chains.run import RunState
from supervisor.core.quality import Quality
from supervisor.tags import TagDB

_GOOD = Quality.GOOD

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
    def __init__(
        self,
        port: ChannelPort,
        db: TagDB,
        program: Program,
        readings: Iterable[str] = ("voltage", "current", "temperature"),
    ) -> None:
        """``readings``: the channel readings the chain looks at besides those its
        conditions name (the limits, a behaviour's own limits or scan); ``values_read``
        and ``observed_values`` compute those, the names the conditions read and the step
        time."""
        self._port = port
        self._voltage = port.voltage
        self._db = db
        self._parameters = program.parameters
        self._initial_charge_ah = program.initial_charge_ah
        # Bench tags by full name: only those the program reads are looked up each scan.
        self._tag_names = sorted(
            names_read(program) - set(CHANNEL_VARIABLES) - set(program.parameters)
        )
        # The dV/dt window as two deques of floats, not one of (t, V) tuples: a minute of a
        # 10 ms scan is 6000 readings per chain, and tuples are objects the garbage
        # collector walks at every full pass, floats are not (issue 13).
        self._dv_t: deque[float] = deque()
        self._dv_v: deque[float] = deque()
        self.peak_v: float | None = None
        # The values handed to the conditions: one dict per chain, filled in place each
        # scan (it never leaves the scan). Parameters are constants: set once, and again
        # each scan only where one has the name of a channel variable (the compiler refuses
        # such a name since issue 28; a program built in code may still have one).
        self._values: Values = {}
        self._parameters_over = {
            k: v for k, v in self._parameters.items() if k in CHANNEL_VALUE_NAMES
        }
        # ``read``: the values the running chain reads (``values_read``): those its
        # conditions name, the readings it looks at itself and the step time. The others
        # are not computed there (issue 13: a 25 h dry run computes the dict 87 000 times
        # and reads three or four of its fifteen channel values).
        read = names_read(program) | {"voltage", "step_time", *readings}
        self.read = frozenset(read)
        self._read_values: Values = {**dict.fromkeys(CHANNEL_VALUE_NAMES), **self._parameters}
        self._reads_current = "current" in read
        self._reads_temperature = "temperature" in read
        self._reads_peak = "delta_peak" in read or "peak_voltage" in read
        # The dV/dt window is kept by ``observed_values`` only for a program that reads
        # dv_dt (``observe`` keeps it always: ``values`` and ``dv_dt`` read it).
        self._keeps_window = "dv_dt" in read
        self._need = tuple(
            name in read
            for name in (
                "power",
                "charge",
                "energy",
                "step_charge",
                "step_energy",
                "cycle_time",
                "test_time",
                "cycle",
                "dv_dt",
            )
        )
        # Anything read beyond the readings, the step time and the peak: ``_fill_more``.
        self._reads_more = any(self._need) or bool(self._parameters_over or self._tag_names)

    def restart(self) -> None:
        """A step starts: its peak and its dV/dt window start again."""
        self.peak_v = None
        self._dv_t.clear()
        self._dv_v.clear()

    def observe(self, now: float, voltage_v: float) -> None:
        """A GOOD voltage reading of this scan."""
        ts, vs = self._dv_t, self._dv_v
        ts.append(now)
        vs.append(voltage_v)
        while ts and now - ts[0] > DV_DT_WINDOW_S:
            ts.popleft()
            vs.popleft()
        peak = self.peak_v
        # max(peak, voltage_v) without the call: the peak unless the reading is above it.
        self.peak_v = voltage_v if peak is None or voltage_v > peak else peak

    def dv_dt(self) -> float | None:
        """V/s over the window, None until it spans ``DV_DT_MIN_SPAN_S``."""
        ts = self._dv_t
        if len(ts) >= 2 and ts[-1] - ts[0] >= DV_DT_MIN_SPAN_S:
            vs = self._dv_v
            return (vs[-1] - vs[0]) / (ts[-1] - ts[0])
        return None

    def charge_ah(self, run: RunState) -> float:
        """The cell's charge: the recipe's initial charge plus what moved since the start."""
        return self._initial_charge_ah + self._port.charge_ah.as_float() - run.q0_ah

    def values(self, now: float, run: RunState) -> Values:
        """This scan's values (the same dict every scan, filled again: read it before the
        next scan, never keep it)."""
        port = self._port
        good = Quality.GOOD
        q = port.charge_ah.as_float()
        energy = port.energy_wh.as_float()
        vt, i, t, p = port.voltage, port.current, port.temperature, port.power
        v = vt.as_float() if vt.quality is good else None
        peak = self.peak_v
        values = self._values
        if not values:
            values.update(dict.fromkeys(CHANNEL_VALUE_NAMES))
            values.update(self._parameters)
        values["voltage"] = v
        values["current"] = i.as_float() if i.quality is good else None
        values["temperature"] = t.as_float() if t.quality is good else None
        values["power"] = p.as_float() if p.quality is good else None
        values["charge"] = self._initial_charge_ah + q - run.q0_ah
        values["energy"] = energy
        values["step_charge"] = q - run.step_q0
        values["step_energy"] = energy - run.step_e0
        values["step_time"] = now - run.t_step0
        values["cycle_time"] = now - run.t_cycle0
        values["test_time"] = now - run.t_test0
        values["cycle"] = float(run.cycle)
        ts = self._dv_t  # self.dv_dt(), inlined
        if len(ts) >= 2 and ts[-1] - ts[0] >= DV_DT_MIN_SPAN_S:
            vs = self._dv_v
            values["dv_dt"] = (vs[-1] - vs[0]) / (ts[-1] - ts[0])
        else:
            values["dv_dt"] = None
        values["delta_peak"] = (peak - v) if (peak is not None and v is not None) else None
        values["peak_voltage"] = peak
        if self._parameters_over:
            values.update(self._parameters_over)
        if self._tag_names:
            db = self._db
            for name in self._tag_names:
                tag = db.get(name)
                tv = tag.value if tag is not None and tag.good else None
                values[name] = (
                    tv
                    if isinstance(tv, bool | float)
                    else float(tv)
                    if isinstance(tv, int)
                    else None
                )
        return values

    def values_read(self, now: float, run: RunState) -> Values:
        """:meth:`values` for the names in ``read`` (what the running chain reads: its
        conditions, limits and behaviours); the other channel values are absent or stale.
        The same dict every scan, filled again: read it before the next scan, never keep
        it."""
        port = self._port
        vt = port.voltage
        v = vt.number if vt.quality is _GOOD else None
        values = self._read_values
        values["voltage"] = v
        if self._reads_current:
            i = port.current
            values["current"] = i.number if i.quality is _GOOD else None
        if self._reads_temperature:
            t = port.temperature
            values["temperature"] = t.number if t.quality is _GOOD else None
        values["step_time"] = now - run.t_step0
        if self._reads_peak:
            peak = self.peak_v
            values["delta_peak"] = (peak - v) if (peak is not None and v is not None) else None
            values["peak_voltage"] = peak
        if self._reads_more:
            self._fill_more(values, now, run)
        return values

    def observed_values(self, now: float, run: RunState) -> Values:
        """:meth:`observe` of this scan's voltage when it is GOOD, then :meth:`values_read`,
        in one call and reading the voltage once: the running chain's steady scan (issue
        13). The dV/dt window is kept only when the program reads dv_dt (nothing else the
        running chain asks reads it)."""
        vt = self._voltage
        v: float | None
        if vt.quality is _GOOD:
            v = vt.number
            if self._keeps_window:  # observe(now, v), inline
                ts, vs = self._dv_t, self._dv_v
                ts.append(now)
                vs.append(v)
                while ts and now - ts[0] > DV_DT_WINDOW_S:
                    ts.popleft()
                    vs.popleft()
            peak = self.peak_v
            self.peak_v = peak = v if peak is None or v > peak else peak
        else:
            v = None
            peak = self.peak_v
        values = self._read_values
        values["voltage"] = v
        if self._reads_current:
            i = self._port.current
            values["current"] = i.number if i.quality is _GOOD else None
        if self._reads_temperature:
            t = self._port.temperature
            values["temperature"] = t.number if t.quality is _GOOD else None
        values["step_time"] = now - run.t_step0
        if self._reads_peak:
            values["delta_peak"] = (peak - v) if (peak is not None and v is not None) else None
            values["peak_voltage"] = peak
        if self._reads_more:
            self._fill_more(values, now, run)
        return values

    def _fill_more(self, values: Values, now: float, run: RunState) -> None:
        """The values read beyond the readings, the step time and the peak: the counters,
        the other clocks, dV/dt, the parameters named like a channel value (they win) and
        the bench tags."""
        port = self._port
        (
            power,
            charge,
            energy,
            step_charge,
            step_energy,
            cycle_time,
            test_time,
            cycle,
            dv_dt,
        ) = self._need
        if power:
            p = port.power
            values["power"] = p.number if p.quality is _GOOD else None
        if charge or step_charge:
            q = port.charge_ah.as_float()
            if charge:
                values["charge"] = self._initial_charge_ah + q - run.q0_ah
            if step_charge:
                values["step_charge"] = q - run.step_q0
        if energy or step_energy:
            e = port.energy_wh.as_float()
            if energy:
                values["energy"] = e
            if step_energy:
                values["step_energy"] = e - run.step_e0
        if cycle_time:
            values["cycle_time"] = now - run.t_cycle0
        if test_time:
            values["test_time"] = now - run.t_test0
        if cycle:
            values["cycle"] = float(run.cycle)
        if dv_dt:
            ts = self._dv_t  # self.dv_dt(), inlined
            if len(ts) >= 2 and ts[-1] - ts[0] >= DV_DT_MIN_SPAN_S:
                vs = self._dv_v
                values["dv_dt"] = (vs[-1] - vs[0]) / (ts[-1] - ts[0])
            else:
                values["dv_dt"] = None
        if self._parameters_over:
            values.update(self._parameters_over)
        if self._tag_names:
            db = self._db
            for name in self._tag_names:
                tag = db.get(name)
                tv = tag.value if tag is not None and tag.good else None
                values[name] = (
                    tv
                    if isinstance(tv, bool | float)
                    else float(tv)
                    if isinstance(tv, int)
                    else None
                )


CHANNEL_VALUE_NAMES = (
    "voltage",
    "current",
    "temperature",
    "power",
    "charge",
    "energy",
    "step_charge",
    "step_energy",
    "step_time",
    "cycle_time",
    "test_time",
    "cycle",
    "dv_dt",
    "delta_peak",
    "peak_voltage",
)
"""The keys ``ConditionValues.values`` fills from the channel and the run, in order."""
