"""Battery models for the bench simulator: a single AA NiMH cell and a Li-ion pack.

The models are deliberately small lumped-parameter models, good enough for a supervisor
to see the behaviour it must react to (IR drop, end-of-charge ``-ΔV``, heating,
voltage collapse when empty, RC relaxation), not for cell design.

Conventions shared by every model:

* **Sign.** Positive current *charges* the cell, negative current discharges it
  (the Battery Data Format convention used everywhere in the supervisor).
* **No clock, no I/O.** The caller advances time with ``step(current_a, dt_s)``; the
  current is held constant over ``dt_s``. Any ``dt_s`` from 1 ms to minutes is
  accepted: steps longer than ``_MAX_SUBSTEP_S`` are split into equal substeps, and the
  stiff parts (thermal relaxation, RC pair) use the exact exponential solution of their
  linear ODE over a substep, so nothing can overshoot whatever the step size.
* **Coulomb counting.** ``charge_ah`` is the exact integral of the applied current,
  ``Σ I·dt / 3600``, accumulated with compensated (Kahan) summation so that millions of
  small steps add no measurable rounding error. ``soc`` moves only by the *accepted*
  part of that charge: all of it for Li-ion (coulombic efficiency ≈ 1), all of it for
  NiMH except near full, where charge acceptance falls off and the excess drives the
  oxygen cycle instead (see :class:`NiMHCell`). Charge drawn from a cell already at
  ``soc == 0``, or pushed into one at the upper clamp, goes to side reactions and is
  not stored, so ``charge_ah`` and ``soc`` can legitimately diverge there. A NiMH cell
  driven on past empty goes into reversal (its voltage through 0 V and below), which it
  reports as a :attr:`~BatteryModel.fault`.
* **SOC range.** ``soc`` is clamped to ``[0, 1.05]``: 1.0 is the rated capacity, and a
  NiMH cell being overcharged creeps slightly above it (real cells typically deliver a
  few percent more than rated); a Li-ion pack can be pushed past 1.0 only by a charger
  that ignores the 4.2 V/cell limit, which is exactly what an overvoltage interlock
  must catch, so the OCV table is extended there rather than held flat.
* **Temperature.** One lumped thermal mass per model, Newton cooling to ambient with a
  time constant ``thermal_time_constant_s`` (conductance = heat capacity / τ).
  Resistances follow an Arrhenius law, ``R(T) = R25·exp(B·(1/T − 1/298.15 K))``, so
  they rise in the cold. Reversible (entropic) heat is neglected.
"""

from __future__ import annotations

import inspect
import math
from abc import ABC, abstractmethod
from bisect import bisect_right
from collections.abc import Callable
from itertools import pairwise
from typing import Protocol, runtime_checkable

__all__ = ["MODEL_KINDS", "BatteryModel", "LiIonPack", "NiMHCell", "make_model"]

_SECONDS_PER_HOUR = 3600.0
_KELVIN_OFFSET = 273.15
_T_REF_K = 25.0 + _KELVIN_OFFSET

# Longest interval integrated in one go. The fastest non-exact dynamics are the SOC
# and temperature couplings, whose time constants are minutes (thermal) to hours (SOC),
# so 1 s substeps keep forward-Euler error far below anything a bench can measure.
_MAX_SUBSTEP_S = 1.0

_SOC_MIN = 0.0
_SOC_MAX = 1.05

# Plausible physical range for the initial and ambient temperatures; outside it the
# Arrhenius extrapolation means nothing.
_T_MIN_C = -60.0
_T_MAX_C = 120.0


@runtime_checkable
class BatteryModel(Protocol):
    """What the simulated benches need from a battery (see module docstring for signs)."""

    capacity_ah: float
    """Rated capacity in Ah."""

    @property
    def soc(self) -> float:
        """State of charge, clamped to [0, 1.05] (1.0 = rated capacity)."""
        ...

    @property
    def ocv_v(self) -> float:
        """Open-circuit voltage at the present state."""
        ...

    @property
    def temperature_c(self) -> float: ...

    @property
    def charge_ah(self) -> float:
        """Net Ah since creation (+ = charged): exact integral of the applied current."""
        ...

    @property
    def terminal_voltage_v(self) -> float:
        """Terminal voltage with the current last applied by :meth:`step` flowing."""
        ...

    @property
    def current_a(self) -> float:
        """Current last applied by :meth:`step` (+ = charging)."""
        ...

    def voltage_at(self, current_a: float) -> float:
        """Terminal voltage if ``current_a`` flowed now; does not change the state."""
        ...

    def step(self, current_a: float, dt_s: float) -> None:
        """Apply ``current_a`` (+ charges) for ``dt_s`` seconds."""
        ...

    @property
    def fault(self) -> str | None:
        """Latched: what was done to the cell that a real one would not survive unharmed
        (NiMH: driven into reversal past empty); None if nothing."""
        ...


class _Table:
    """Piecewise-linear lookup, held flat beyond its ends (so continuous everywhere)."""

    __slots__ = ("_slopes", "_xs", "_ys")

    def __init__(self, points: tuple[tuple[float, float], ...]) -> None:
        xs = tuple(p[0] for p in points)
        ys = tuple(p[1] for p in points)
        if len(xs) < 2 or any(b <= a for a, b in pairwise(xs)):
            raise ValueError("table abscissae must be strictly increasing")
        self._xs = xs
        self._ys = ys
        self._slopes = tuple(
            (y1 - y0) / (x1 - x0) for (x0, y0), (x1, y1) in pairwise(zip(xs, ys, strict=True))
        )

    def __call__(self, x: float) -> float:
        xs = self._xs
        if x <= xs[0]:
            return self._ys[0]
        if x >= xs[-1]:
            return self._ys[-1]
        i = bisect_right(xs, x) - 1
        return self._ys[i] + self._slopes[i] * (x - xs[i])


def _check_finite(name: str, value: float) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return float(value)


def _check_positive(name: str, value: float) -> float:
    value = _check_finite(name, value)
    if value <= 0.0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def _check_range(name: str, value: float, low: float, high: float) -> float:
    value = _check_finite(name, value)
    if not low <= value <= high:
        raise ValueError(f"{name} must be within [{low}, {high}], got {value!r}")
    return value


class _LumpedCell(ABC):
    """Shared plumbing: argument checks, coulomb counter, substepping, thermal node."""

    capacity_ah: float
    # Two read-outs are plain attributes, not properties, written only by the model: a
    # simulated Chadèche board reads both at every poll (its thermometer and its fault
    # report), and a property's call cost more than the rest of such a read (issue 13).
    temperature_c: float
    fault: str | None = None
    """Latched: what was done to the cell that a real one would not survive unharmed
    (``NiMHCell``: driven into reversal past empty); None if nothing."""

    def __init__(
        self,
        *,
        capacity_ah: float,
        soc: float,
        temperature_c: float,
        ambient_c: float,
        heat_capacity_j_per_k: float,
        thermal_time_constant_s: float,
        arrhenius_b_k: float,
    ) -> None:
        self.capacity_ah = _check_positive("capacity_ah", capacity_ah)
        self._soc = _check_range("soc", soc, _SOC_MIN, _SOC_MAX)
        self.temperature_c = _check_range("temperature_c", temperature_c, _T_MIN_C, _T_MAX_C)
        self._ambient_c = _check_range("ambient_c", ambient_c, _T_MIN_C, _T_MAX_C)
        heat_capacity = _check_positive("heat_capacity_j_per_k", heat_capacity_j_per_k)
        self._tau_th_s = _check_positive("thermal_time_constant_s", thermal_time_constant_s)
        # Newton cooling: C·dT/dt = P − G·(T − T_amb) with G = C/τ.
        self._conductance_w_per_k = heat_capacity / self._tau_th_s
        self._arrhenius_b_k = _check_finite("arrhenius_b_k", arrhenius_b_k)
        # Capacity in coulombs, inverted once: SOC changes by I·dt / (3600·Q).
        self._inv_capacity_as = 1.0 / (self.capacity_ah * _SECONDS_PER_HOUR)
        self._current = 0.0
        self._charge_ah = 0.0
        self._charge_comp = 0.0  # Kahan compensation term for _charge_ah
        self._decay_h = -1.0  # substep length for which _decay is cached
        self._decay = 0.0

    # -- common read-outs -------------------------------------------------------------

    @property
    def soc(self) -> float:
        return self._soc

    @property
    def charge_ah(self) -> float:
        return self._charge_ah

    @property
    def current_a(self) -> float:
        return self._current

    @property
    def terminal_voltage_v(self) -> float:
        return self.voltage_at(self._current)

    @property
    @abstractmethod
    def ocv_v(self) -> float: ...

    @abstractmethod
    def voltage_at(self, current_a: float) -> float: ...

    # -- integration --------------------------------------------------------------------

    def step(self, current_a: float, dt_s: float) -> None:
        # A finite float passes _check_finite unchanged: the call only for anything else
        # (a dry run steps its cell 87 000 times).
        # ``x - x != 0.0``: not finite, for a float (inf - inf and NaN - NaN are NaN).
        if type(current_a) is not float or current_a - current_a != 0.0:
            current_a = _check_finite("current_a", current_a)
        if type(dt_s) is not float or dt_s - dt_s != 0.0:
            dt_s = _check_finite("dt_s", dt_s)
        if dt_s < 0.0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s!r}")
        self._current = current_a
        if dt_s == 0.0:
            return
        # Kahan summation: the counter is the bench's reference for charge throughput,
        # so it must stay exact to ~1e-15 even after 10^7 tiny increments.
        y = current_a * dt_s / _SECONDS_PER_HOUR - self._charge_comp
        t = self._charge_ah + y
        self._charge_comp = (t - self._charge_ah) - y
        self._charge_ah = t

        if dt_s <= _MAX_SUBSTEP_S:
            n, h = 1, dt_s
        else:
            n = math.ceil(dt_s / _MAX_SUBSTEP_S)
            h = dt_s / n
        if h != self._decay_h:
            # exp() is the costliest thing per step at fixed dt; cache it.
            self._decay_h = h
            self._decay = math.exp(-h / self._tau_th_s)
        if n == 1:
            self._advance(current_a, h)
        else:
            for _ in range(n):
                self._advance(current_a, h)

    @abstractmethod
    def _advance(self, current_a: float, h: float) -> float | None:
        """Integrate one substep of ``h`` <= ``_MAX_SUBSTEP_S`` seconds (a model may return
        its voltage at the state left, ``NiMHCell``)."""

    def _arrhenius(self, temp_c: float) -> float:
        """Resistance multiplier relative to 25 °C (> 1 when colder)."""
        return math.exp(self._arrhenius_b_k * (1.0 / (temp_c + _KELVIN_OFFSET) - 1.0 / _T_REF_K))

    def _relax_temperature(self, power_w: float) -> None:
        """Exact solution of C·dT/dt = P − G·(T − T_amb) over the cached substep.

        With P held constant over the substep the update is an exponential blend toward
        the steady state ``T_amb + P/G``: unconditionally stable, never overshoots.
        """
        t_inf = self._ambient_c + power_w / self._conductance_w_per_k
        self.temperature_c = t_inf + (self.temperature_c - t_inf) * self._decay


# --------------------------------------------------------------------------------------
# NiMH
# --------------------------------------------------------------------------------------

# OCV of an AA NiMH cell at 25 °C after rest: ~1.0 V when empty, the long flat
# 1.25–1.35 V plateau of the Ni(OH)2/NiOOH couple, steepening to ~1.40 V at full. The
# points beyond 1.0 describe the slight overfill reached while overcharging.
_NIMH_OCV = _Table(
    (
        (0.00, 1.000),
        (0.02, 1.100),
        (0.05, 1.170),
        (0.10, 1.215),
        (0.20, 1.250),
        (0.40, 1.275),
        (0.60, 1.295),
        (0.80, 1.325),
        (0.90, 1.350),
        (0.95, 1.370),
        (1.00, 1.400),
        (1.05, 1.420),
    )
)
_OCV_XS, _OCV_YS, _OCV_SLOPES = _NIMH_OCV._xs, _NIMH_OCV._ys, _NIMH_OCV._slopes
"""The NiMH OCV table's points, for the lookup written out in ``NiMHCell._advance``."""

# Negative temperature coefficient of the cell voltage (≈ −1 to −2 mV/°C per cell for
# NiMH). With the oxygen overpotential's own fall with temperature (below) and the
# resistances falling with it, it turns the heat of overcharge into the end-of-charge
# voltage drop: the DS2710 single-cell NiMH charger ends fast charge when the cell
# voltage falls 2 mV (typ) below its peak (devices.md "NiMH charge termination"), so the
# model must produce clearly more than that at fast-charge rates.
_NIMH_TEMPCO_V_PER_K = -1.5e-3

# Charge acceptance η(soc): 1 up to the knee, then ``sqrt((1.05 − soc)/(1.05 − knee))``,
# 0 at the SOC clamp. Above the knee oxygen evolution at the positive electrode competes
# with charging; the oxygen recombines at the negative electrode, so the unaccepted charge
# turns into heat and gas, not stored charge. The square root makes the stored charge
# reach the clamp in a finite time (dsoc/dt ∝ sqrt(1.05 − soc)) instead of creeping
# toward it for hours: a cell past full really stops storing, the voltage stops rising
# with soc, and the heat of overcharge can turn it over into the -ΔV. With the knee at
# 0.93 a fast charge from empty reaches the clamp after ~117 % of rated input, and the
# voltage peaks a little before that, about where real cells do (~105–115 %).
_NIMH_ACCEPT_KNEE = 0.93

# The oxygen-evolution overpotential falls as the cell warms (its exchange current has a
# large activation energy): ``g·exp(−(T − 25 °C)/θ)``, about −1 mV/K at 25 °C with the
# default g = 50 mV. Together with the OCV coefficient and the resistances this makes the
# overcharge voltage fall ~3–4 mV/K, what makes -ΔV reliable from ~0.3 C up.
_NIMH_O2_THETA_K = 50.0

# Defaults of a cell of another capacity than the reference AA: same chemistry and build,
# scaled in size. Resistance ∝ 1/capacity (electrode area), heat capacity ∝ capacity
# (mass: an AA of ~27–30 g at ~1 J/(g·K) is ~30 J/K for 2 Ah), thermal time constant ∝
# size ∝ capacity^(1/3) (mass over surface; ~15 min for an AA in still air). So the
# behaviour at a given C-rate barely depends on the capacity: a 0.8 Ah cell at 0.5 C
# heats and shows its -ΔV like a 2 Ah one, instead of a 30 J/K mass heated by 0.4 A.
_NIMH_REF_CAPACITY_AH = 2.0
_NIMH_R_OHM_AH = 0.06  # 30 mΩ at 2 Ah
_NIMH_HEAT_CAPACITY_J_PER_K_AH = 15.0  # 30 J/K at 2 Ah
_NIMH_THERMAL_TAU_REF_S = 900.0  # at 2 Ah

# Reversal: a cell driven on past empty (soc == 0, current still drawn) has its positive
# electrode exhausted; it then evolves hydrogen, and the cell's polarity reverses: the
# loaded voltage goes through 0 V to about −0.3 V at 0.2 C. ``V_rev = v·(1 − e^(−d/d0))``
# with ``d`` the charge drawn past empty as a fraction of capacity. It needs current (a
# cell at rest shows its ~1.0 V empty OCV again), and it is a fault the model reports
# (``fault``): a real cell is damaged by it, and a bench must never let it happen.
_NIMH_REVERSAL_V = 0.7
_NIMH_REVERSAL_DEPTH = 0.005  # 10 mAh on a 2 Ah cell


class NiMHCell(_LumpedCell):
    """One AA NiMH cell (default 2.0 Ah), lumped electrical and thermal model.

    Terminal voltage::

        V = OCV(soc) + k_T·(T − 25 °C)           # table + temperature coefficient
            + I·R(T)                             # ohmic drop, sign follows the current
            + b·asinh(I / (2·I0(T)))             # charge-transfer overpotential
            + V_O2(soc, T, I)                    # oxygen evolution, charge only
            − V_dep(soc, I)                      # depletion, discharge only
            − V_rev(d, I)                        # reversal past empty, discharge only

    ``V_O2 = g·e^(−(T − 25)/θ)·(1 − η(soc))·r/(r + 0.1)`` (``r`` = charge C-rate) is the
    extra overpotential of oxygen evolution, which carries the unaccepted fraction of the
    current near full: it gives the steep rise of the charge curve just before the peak,
    and falls as the cell warms.

    ``V_dep = a·r/(r + soc/0.01 + 0.01)`` (``r`` = discharge C-rate) is a
    mass-transport limit whose limiting current is proportional to the active material
    left: negligible on the plateau, it collapses the loaded voltage toward 0.8 V and
    below as the cell empties, while at rest the voltage recovers to the ~1.0 V OCV, as
    with real cells. ``soc`` is clamped at 0; charge drawn beyond that is not stored but
    drives the cell into reversal: ``V_rev = v·(1 − e^(−d/d0))·r/(r + 0.01)``, ``d`` the
    charge drawn past empty (fraction of capacity), takes the loaded voltage through 0 V
    to about −0.3 V (hydrogen evolution on the exhausted positive). Charging ends the
    reversal; the fault it was stays reported (:attr:`fault`, :attr:`reversal_ah`).

    Charging near full, only the fraction ``η(soc)`` of the current is stored; the rest
    feeds the oxygen cycle. Heat is the electrical energy in minus the chemical energy
    stored: ``P = I·(V − OCV) + (1 − η)·I·OCV``, i.e. I²R and overpotential losses plus
    the unaccepted fraction of the charge power. As ``η → 0`` the cell heats at roughly
    I·V, the negative temperature coefficients (OCV, oxygen overpotential, resistances)
    overtake the flattening voltage rise and the charge voltage goes through a peak then
    drops: the ``-ΔV`` NiMH chargers terminate on, with the steep temperature rise dT/dt
    chargers terminate on. With the defaults, a 0.5 C charge from empty peaks at
    ~1.47 V after ~106 % input and has fallen 3 mV after ~111 % (cell at ~41 °C), by
    tens of mV if it goes on; at 1 C the same after ~107 %; at 0.1 C there is no
    measurable drop, which is why chargers cannot rely on -ΔV at low rates.

    Size defaults (``r_internal_ohm``, ``heat_capacity_j_per_k``,
    ``thermal_time_constant_s`` left None) scale from the 2 Ah AA: 30 mΩ, 30 J/K, 15 min
    to still air (see ``_NIMH_R_OHM_AH`` and its neighbours).
    """

    def __init__(
        self,
        *,
        capacity_ah: float = 2.0,
        soc: float = 0.5,
        temperature_c: float = 25.0,
        ambient_c: float = 25.0,
        r_internal_ohm: float | None = None,
        heat_capacity_j_per_k: float | None = None,
        thermal_time_constant_s: float | None = None,
        tafel_slope_v: float = 0.025,
        exchange_current_c: float = 0.1,
        depletion_v: float = 0.6,
        oxygen_overpotential_v: float = 0.05,
        reversal_v: float = _NIMH_REVERSAL_V,
        arrhenius_b_k: float = 2000.0,
    ) -> None:
        """Build a cell.

        Args:
            capacity_ah: rated capacity.
            soc: initial state of charge, 0..1.05.
            temperature_c: initial cell temperature.
            ambient_c: temperature the cell cools toward.
            r_internal_ohm: ohmic resistance at 25 °C (None: 60 mΩ·Ah / capacity, ~30 mΩ
                for a 2 Ah AA cell).
            heat_capacity_j_per_k: lumped thermal mass (None: 15 J/(K·Ah) × capacity).
            thermal_time_constant_s: Newton cooling time constant to ambient (None:
                900 s × (capacity / 2 Ah)^(1/3)).
            tafel_slope_v: ``b`` of the charge-transfer overpotential ``b·asinh(I/2I0)``.
            exchange_current_c: ``I0`` at 25 °C as a C-rate.
            depletion_v: loaded-voltage collapse ``a`` when fully empty.
            oxygen_overpotential_v: ``g``, oxygen-evolution overpotential at full, 25 °C.
            reversal_v: ``v``, how far below the empty loaded voltage reversal goes.
            arrhenius_b_k: ``Ea/R`` of the resistance and exchange current (2000 K makes
                R about 1.85× higher at 0 °C than at 25 °C).
        """
        capacity_ah = _check_positive("capacity_ah", capacity_ah)
        size = capacity_ah / _NIMH_REF_CAPACITY_AH
        if r_internal_ohm is None:
            r_internal_ohm = _NIMH_R_OHM_AH / capacity_ah
        if heat_capacity_j_per_k is None:
            heat_capacity_j_per_k = _NIMH_HEAT_CAPACITY_J_PER_K_AH * capacity_ah
        if thermal_time_constant_s is None:
            thermal_time_constant_s = _NIMH_THERMAL_TAU_REF_S * size ** (1.0 / 3.0)
        super().__init__(
            capacity_ah=capacity_ah,
            soc=soc,
            temperature_c=temperature_c,
            ambient_c=ambient_c,
            heat_capacity_j_per_k=heat_capacity_j_per_k,
            thermal_time_constant_s=thermal_time_constant_s,
            arrhenius_b_k=arrhenius_b_k,
        )
        self._r25 = _check_positive("r_internal_ohm", r_internal_ohm)
        self._tafel_b = _check_positive("tafel_slope_v", tafel_slope_v)
        i0 = _check_positive("exchange_current_c", exchange_current_c) * self.capacity_ah
        self._inv_2i0 = 1.0 / (2.0 * i0)
        self._depletion_v = _check_range("depletion_v", depletion_v, 0.0, 1.0)
        self._oxygen_v = _check_range("oxygen_overpotential_v", oxygen_overpotential_v, 0.0, 0.5)
        self._reversal_v = _check_range("reversal_v", reversal_v, 0.0, 2.0)
        self._reversed = 0.0  # charge drawn past empty now, as a fraction of capacity
        self._reversed_max = 0.0  # the deepest reversal so far (the latched fault)
        # The voltage last computed, by a substep for the state it left or by
        # ``voltage_at``: its inputs (current, soc, temperature, reversal, as the very
        # objects it read) and what it computed (OCV, overpotential, voltage). A
        # simulated board reads the voltage after each step, and the next step starts
        # from that same state at the same current: both reuse them instead of computing
        # the same functions of the same values again (test_battery_reuse.py).
        self._at: tuple[float, float, float, float, float, float, float] | None = None
        # The OCV table's segment the last substep's lookup found: its ends, its value at
        # the lower one and its slope (none yet: no soc lies strictly between inf and -inf).
        self._ocv_segment = (math.inf, -math.inf, 0.0, 0.0)

    # -- reversal -------------------------------------------------------------------------

    @property
    def reversal_ah(self) -> float:
        """Charge drawn past empty in the present reversal (0 when not reversed)."""
        return self._reversed * self.capacity_ah

    # -- electrical -----------------------------------------------------------------------

    def _ocv(self, soc: float, temp_c: float) -> float:
        return _NIMH_OCV(soc) + _NIMH_TEMPCO_V_PER_K * (temp_c - 25.0)

    def _overpotential(self, current_a: float, soc: float, temp_c: float, factor: float) -> float:
        """``V − OCV``; has the sign of the current, so I·(V − OCV) >= 0 always."""
        eta = current_a * self._r25 * factor + self._tafel_b * math.asinh(
            current_a * factor * self._inv_2i0
        )
        rate = current_a / self.capacity_ah
        if current_a > 0.0:
            unaccepted = 1.0 - self._acceptance(soc)
            if unaccepted > 0.0:
                # O2 evolution carries the unaccepted current; saturates above ~0.1 C
                # and falls as the cell warms.
                g = self._oxygen_v * math.exp((25.0 - temp_c) / _NIMH_O2_THETA_K)
                eta += g * unaccepted * rate / (rate + 0.1)
        elif current_a < 0.0:
            # Limiting current ∝ active material left (soc/0.01); the 0.01 floor keeps
            # the term continuous at soc == 0 and I -> 0. ``rate`` < 0 here.
            eta += self._depletion_v * rate / (-rate + soc * 100.0 + 0.01)
            if self._reversed > 0.0:
                depth = 1.0 - math.exp(-self._reversed / _NIMH_REVERSAL_DEPTH)
                eta += self._reversal_v * depth * rate / (-rate + 0.01)
        return eta

    @staticmethod
    def _acceptance(soc: float) -> float:
        if soc <= _NIMH_ACCEPT_KNEE:
            return 1.0
        if soc >= _SOC_MAX:
            return 0.0
        return math.sqrt((_SOC_MAX - soc) / (_SOC_MAX - _NIMH_ACCEPT_KNEE))

    @property
    def ocv_v(self) -> float:
        return self._ocv(self._soc, self.temperature_c)

    def voltage_at(self, current_a: float) -> float:
        at = self._at
        if (
            at is not None
            and at[0] is current_a
            and at[1] is self._soc
            and at[2] is self.temperature_c
            and at[3] is self._reversed
        ):
            # What the last step (or reading) computed from the very same state objects
            # and current: the same values, so the same voltage (test_battery_reuse.py).
            return at[6]
        temp, soc = self.temperature_c, self._soc
        ocv = self._ocv(soc, temp)
        eta = self._overpotential(current_a, soc, temp, self._arrhenius(temp))
        v = ocv + eta
        self._at = (current_a, soc, temp, self._reversed, ocv, eta, v)
        return v

    def step_then_voltage_v(self, current_a: float, dt_s: float) -> float:
        """``step(current_a, dt_s)`` then ``voltage_at(current_a)``, in one call.

        A simulated board steps its cell and reads its voltage at every poll (issue 13:
        87 000 times a dry run). For what such a poll gives (a finite float current, a
        float step of at most one substep, the cached thermal decay of that length),
        ``step``'s checks, counter and substep done here without its call; the substep
        leaves the voltage at the new state for this current (``_advance``). Anything
        else takes ``step`` and ``voltage_at`` themselves (test_battery_reuse.py: bit
        for bit the same cell and voltage).
        """
        if (
            type(current_a) is float
            and type(dt_s) is float
            and current_a - current_a == 0.0  # finite (else NaN)
            # One substep whose decay is cached: ``_decay_h`` is -1.0 or the length of a
            # substep ``step`` made, in (0, _MAX_SUBSTEP_S]; false for NaN.
            and 0.0 < dt_s == self._decay_h
        ):
            self._current = current_a
            # ``step``'s Kahan summation, the same expressions.
            y = current_a * dt_s / _SECONDS_PER_HOUR - self._charge_comp
            t = self._charge_ah + y
            self._charge_comp = (t - self._charge_ah) - y
            self._charge_ah = t
            return self._advance(current_a, dt_s)
        self.step(current_a, dt_s)
        return self.voltage_at(current_a)

    def _advance(self, current_a: float, h: float) -> float:
        """One substep; returns ``voltage_at(current_a)`` at the state it leaves, which it
        computes for the next substep or reading anyway (see ``_at``)."""
        soc = self._soc
        temp = self.temperature_c
        at = self._at
        ocv: float | None
        if at is not None:
            at_current, at_soc, at_temp, at_reversed, ocv, eta, _ = at
            if (
                at_current is not current_a
                or at_soc is not soc
                or at_temp is not temp
                or at_reversed is not self._reversed
            ):
                at = None
            # (Else the same objects: the same values, so the same results.)
        if at is None:
            ocv = None  # computed below only if needed
            eta = self._overpotential(current_a, soc, temp, self._arrhenius(temp))
        loss_w = current_a * eta
        if current_a > 0.0:
            # ``self._acceptance(soc)`` without the call.
            if soc <= _NIMH_ACCEPT_KNEE:
                # All of it is accepted: the lines below with ``accepted`` 1.0. Their heat
                # term ``0.0·I·OCV`` is ±0.0 (or NaN for an OCV that is NaN, but only a
                # NaN temperature makes it so, and then the loss already is NaN), and
                # the loss ``I·η`` is +0.0 or more here (I > 0, η >= 0): adding it would
                # change no bit. ``1.0 * current_a`` is ``current_a``.
                soc += current_a * h * self._inv_capacity_as
            else:
                if soc >= _SOC_MAX:
                    accepted = 0.0
                else:
                    accepted = math.sqrt((_SOC_MAX - soc) / (_SOC_MAX - _NIMH_ACCEPT_KNEE))
                # Unaccepted charge drives O2 evolution + recombination: all of it is heat.
                loss_w += (
                    (1.0 - accepted)
                    * current_a
                    * (ocv if ocv is not None else self._ocv(soc, temp))
                )
                soc += accepted * current_a * h * self._inv_capacity_as
            soc = soc if soc < _SOC_MAX else _SOC_MAX
            self._reversed = 0.0  # charging the exhausted positive ends the reversal
        else:
            soc += current_a * h * self._inv_capacity_as
            if not soc > _SOC_MIN:  # (not ``<=``: the same branch as ever for a NaN)
                # Past empty: nothing more to give; what is drawn drives the reversal.
                self._reversed -= soc
                soc = _SOC_MIN
                if self._reversed > self._reversed_max:
                    self._reversed_max = self._reversed
                    # ``fault``: latched, with the deepest reversal so far.
                    depth_mah = self._reversed_max * self.capacity_ah * 1000.0
                    self.fault = (
                        "cell driven past empty into reversal"
                        f" (deepest {depth_mah:.3g} mAh past empty)"
                    )
        self._soc = soc
        # ``self._relax_temperature(loss_w)``, the same expressions without the call.
        t_inf = self._ambient_c + loss_w / self._conductance_w_per_k
        temp = t_inf + (temp - t_inf) * self._decay
        self.temperature_c = temp

        # The voltage at the new state with ``current_a`` still flowing: what the next
        # substep starts from and what the board reads next. ``self._arrhenius(temp)``,
        # ``self._ocv(soc, temp)`` and ``self._overpotential(current_a, soc, temp,
        # factor)``, the same expressions in the same order without the calls
        # (test_dry_run_fast_paths.py, bit for bit).
        factor = math.exp(self._arrhenius_b_k * (1.0 / (temp + _KELVIN_OFFSET) - 1.0 / _T_REF_K))
        # ``_NIMH_OCV(soc)``: the table's lookup, the same steps without the call; first
        # in the segment the last lookup found (a slow charge stays in one for hours),
        # where the lookup would find it again: strictly between its ends.
        low, high, table_y, table_slope = self._ocv_segment
        if low < soc < high:
            table_v = table_y + table_slope * (soc - low)
        else:
            xs = _OCV_XS
            if soc <= xs[0]:
                table_v = _OCV_YS[0]
            elif soc >= xs[-1]:
                table_v = _OCV_YS[-1]
            else:
                i = bisect_right(xs, soc) - 1
                table_v = _OCV_YS[i] + _OCV_SLOPES[i] * (soc - xs[i])
                self._ocv_segment = (xs[i], xs[i + 1], _OCV_YS[i], _OCV_SLOPES[i])
        ocv = table_v + _NIMH_TEMPCO_V_PER_K * (temp - 25.0)
        eta = current_a * self._r25 * factor + self._tafel_b * math.asinh(
            current_a * factor * self._inv_2i0
        )
        # (``rate``, the C-rate, only where a term uses it.)
        if current_a > 0.0:
            if soc > _NIMH_ACCEPT_KNEE:  # else all of it is accepted
                unaccepted = 1.0 - (
                    0.0
                    if soc >= _SOC_MAX
                    else math.sqrt((_SOC_MAX - soc) / (_SOC_MAX - _NIMH_ACCEPT_KNEE))
                )
                if unaccepted > 0.0:
                    rate = current_a / self.capacity_ah
                    g = self._oxygen_v * math.exp((25.0 - temp) / _NIMH_O2_THETA_K)
                    eta += g * unaccepted * rate / (rate + 0.1)
        elif current_a < 0.0:
            rate = current_a / self.capacity_ah
            eta += self._depletion_v * rate / (-rate + soc * 100.0 + 0.01)
            if self._reversed > 0.0:
                depth = 1.0 - math.exp(-self._reversed / _NIMH_REVERSAL_DEPTH)
                eta += self._reversal_v * depth * rate / (-rate + 0.01)
        v = ocv + eta
        self._at = (current_a, soc, temp, self._reversed, ocv, eta, v)
        return v


# --------------------------------------------------------------------------------------
# Li-ion
# --------------------------------------------------------------------------------------

# Rest OCV of one NMC/graphite cell: 3.0 V empty (the usual discharge cut-off),
# 4.2 V full (the usual charge limit). The 1.05 point extrapolates the top slope so an
# overcharged pack shows a rising voltage for interlocks to catch.
_LIION_OCV = _Table(
    (
        (0.00, 3.000),
        (0.05, 3.450),
        (0.10, 3.550),
        (0.20, 3.620),
        (0.30, 3.675),
        (0.40, 3.725),
        (0.50, 3.780),
        (0.60, 3.850),
        (0.70, 3.930),
        (0.80, 4.010),
        (0.90, 4.100),
        (1.00, 4.200),
        (1.05, 4.260),
    )
)


class LiIonPack(_LumpedCell):
    """Series string of NMC Li-ion cells (default 4S, 10 Ah: ~12.0–16.8 V).

    First-order Thevenin equivalent circuit, all elements at pack level::

        V = cells_series·OCV_cell(soc) + I·R0(T) + V_rc
        dV_rc/dt = I/C1 − V_rc/(R1·C1)

    ``V_rc`` is advanced with the exact exponential solution for constant current,
    ``V_rc ← V_rc·e^(−h/τ) + I·R1·(1 − e^(−h/τ))``, so it is stable for any step.
    Coulombic efficiency is taken as 1 (true to ~99.9 % for Li-ion), so ``soc`` follows
    ``charge_ah`` exactly between the clamps. R0 and R1 follow the Arrhenius law (Ea ≈
    25 kJ/mol → ×2.5 at 0 °C, ×6 at −20 °C), which is why cold packs sag under load.
    Heat is I²·R0 plus the exact energy dissipated in R1 over the substep.

    Defaults: 4 × 10 Ah cells of ~5 mΩ ohmic resistance each (R0 = 20 mΩ), a 30 s
    polarization time constant, ~0.8 kg at ~1 J/(g·K) and a one-hour cooling constant.
    """

    def __init__(
        self,
        *,
        cells_series: int = 4,
        capacity_ah: float = 10.0,
        soc: float = 0.5,
        temperature_c: float = 25.0,
        ambient_c: float = 25.0,
        r0_ohm: float = 0.02,
        r1_ohm: float = 0.015,
        c1_f: float = 2000.0,
        heat_capacity_j_per_k: float = 800.0,
        thermal_time_constant_s: float = 3600.0,
        arrhenius_b_k: float = 3000.0,
    ) -> None:
        """Build a pack.

        Args:
            cells_series: number of cells in series.
            capacity_ah: rated capacity (of each cell, hence of the string).
            soc: initial state of charge, 0..1.05.
            temperature_c: initial pack temperature.
            ambient_c: temperature the pack cools toward.
            r0_ohm: pack ohmic resistance at 25 °C.
            r1_ohm: pack polarization resistance at 25 °C.
            c1_f: pack polarization capacitance.
            heat_capacity_j_per_k: lumped thermal mass of the pack.
            thermal_time_constant_s: Newton cooling time constant to ambient.
            arrhenius_b_k: ``Ea/R`` for R0 and R1.
        """
        super().__init__(
            capacity_ah=capacity_ah,
            soc=soc,
            temperature_c=temperature_c,
            ambient_c=ambient_c,
            heat_capacity_j_per_k=heat_capacity_j_per_k,
            thermal_time_constant_s=thermal_time_constant_s,
            arrhenius_b_k=arrhenius_b_k,
        )
        if isinstance(cells_series, bool) or not isinstance(cells_series, int):
            raise ValueError(f"cells_series must be an int, got {cells_series!r}")
        if not 1 <= cells_series <= 1000:
            raise ValueError(f"cells_series must be within [1, 1000], got {cells_series!r}")
        self._cells = cells_series
        self._r0_25 = _check_positive("r0_ohm", r0_ohm)
        self._r1_25 = _check_positive("r1_ohm", r1_ohm)
        self._c1 = _check_positive("c1_f", c1_f)
        self._v_rc = 0.0

    @property
    def ocv_v(self) -> float:
        return self._cells * _LIION_OCV(self._soc)

    def voltage_at(self, current_a: float) -> float:
        r0 = self._r0_25 * self._arrhenius(self.temperature_c)
        return self._cells * _LIION_OCV(self._soc) + current_a * r0 + self._v_rc

    def _advance(self, current_a: float, h: float) -> None:
        factor = self._arrhenius(self.temperature_c)
        r0 = self._r0_25 * factor
        r1 = self._r1_25 * factor
        tau = r1 * self._c1
        decay = math.exp(-h / tau)
        v_inf = current_a * r1
        dv0 = self._v_rc - v_inf
        self._v_rc = v_inf + dv0 * decay
        # Mean of V_rc²/R1 over the substep, integrated exactly for
        # V_rc(t) = V∞ + ΔV0·e^(−t/τ).
        energy_r1 = (
            v_inf * v_inf * h
            + 2.0 * v_inf * dv0 * tau * (1.0 - decay)
            + dv0 * dv0 * 0.5 * tau * (1.0 - decay * decay)
        ) / r1
        loss_w = current_a * current_a * r0 + energy_r1 / h
        soc = self._soc + current_a * h * self._inv_capacity_as
        self._soc = min(_SOC_MAX, max(_SOC_MIN, soc))
        self._relax_temperature(loss_w)


# --------------------------------------------------------------------------------------
# Factory
# --------------------------------------------------------------------------------------


def _make_nimh(params: dict[str, float]) -> BatteryModel:
    return NiMHCell(**params)


def _make_liion(params: dict[str, float]) -> BatteryModel:
    kwargs = dict(params)
    cells = kwargs.pop("cells_series", 4.0)
    if not (math.isfinite(cells) and float(cells).is_integer()):
        raise ValueError(f"cells_series must be a whole number, got {cells!r}")
    return LiIonPack(cells_series=int(cells), **kwargs)


_FACTORIES: dict[str, tuple[type[_LumpedCell], Callable[[dict[str, float]], BatteryModel]]] = {
    "nimh-aa": (NiMHCell, _make_nimh),
    "liion-pack": (LiIonPack, _make_liion),
}

MODEL_KINDS: tuple[str, ...] = tuple(_FACTORIES)


def _param_names(cls: type[_LumpedCell]) -> tuple[str, ...]:
    return tuple(
        name
        for name, p in inspect.signature(cls.__init__).parameters.items()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    )


def make_model(kind: str, **params: float) -> BatteryModel:
    """Build a battery model by kind name (see ``MODEL_KINDS``) with keyword overrides.

    Raises:
        ValueError: unknown ``kind`` or parameter (the message lists the valid ones),
            or an out-of-range value.
    """
    try:
        cls, factory = _FACTORIES[kind]
    except KeyError:
        raise ValueError(
            f"unknown battery model kind {kind!r}; valid kinds: {', '.join(MODEL_KINDS)}"
        ) from None
    valid = _param_names(cls)
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)} for battery model {kind!r}; "
            f"valid parameters: {', '.join(valid)}"
        )
    return factory(params)
