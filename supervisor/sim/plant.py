"""The simulated seed-002 bench: one battery behind the EA supply, ADAM, BMS and e-stop.

Every protocol simulator (ADAM Modbus server, EA SCPI server, BMS CAN sender) reads and
writes this one object, so a current set on the supply shows up in the LEM sensor
voltage, the voltage board, the BMS frames and the thermocouples alike.

Physics is integrated lazily: every access first calls ``advance()``, which steps the
battery from the last update to ``clock.now()`` with the current that was flowing.

The battery contactor (seed 002 §1.5) is closed only while its coil is energised: through
the ADAM 5060 relay (the software e-stop) and, when fitted, through the contact of a
hardware watchdog relay in series with it (docs/design.md "Safety"). That watchdog relay is fed by
a heartbeat output the supervisor toggles; its contact opens ``watchdog_timeout_s`` after
the last toggle, so a dead supervisor disconnects the battery. Its opening instant is
integrated like everything else: the current stops at that instant, not when someone next
looks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from supervisor.config.models import SimCell, SimulationConfig
from supervisor.core.clock import Clock
from supervisor.sim.battery import BatteryModel, make_model

# The EA unit's own bounds on how hard it regulates (its internal R is irrelevant here:
# it is an ideal CV source with a source and a sink current limit).
_BISECT_ITERATIONS = 40


@dataclass
class SupplyState:
    """What the EA supply has been told (SCPI ``OUTP``, ``VOLT``, ``CURR``, ``SINK:CURR``)."""

    output_on: bool = False
    remote: bool = False
    volt_set_v: float = 0.0
    curr_set_a: float = 0.0
    sink_curr_set_a: float = 0.0
    pow_set_w: float = float("inf")
    sink_pow_set_w: float = float("inf")


@dataclass
class BenchPlant:
    clock: Clock
    battery: BatteryModel
    ambient_c: float = 25.0
    supply: SupplyState = field(default_factory=SupplyState)
    # The contactor coil relay (ADAM 5060, the software e-stop, seed 002 §1.5).
    contactor_coil_on: bool = False
    # Hardware e-stop: cuts the supply's mains through its own contactor (seed 002 §1.5).
    estop_pressed: bool = False
    watchdog_timeout_s: float | None = None
    """The hardware watchdog relay in series with the coil: its contact opens this long after
    the heartbeat output last changed state. None: not fitted (the coil relay alone)."""
    heartbeat_on: bool = False
    """Last state of the heartbeat output feeding the watchdog relay."""
    heartbeat_toggles: int = 0
    _heartbeat_t: float | None = None  # last toggle; None: never toggled (contact open)
    _watchdog_open: bool = True  # the watchdog relay's contact, as of ``_t``
    _t: float | None = None
    _current_a: float = 0.0

    # --- time ------------------------------------------------------------------------
    def advance(self) -> None:
        now = self.clock.now()
        if self._t is None:
            self._t = now
            self._current_a = self._regulate()
        expiry = self._watchdog_expiry()
        if expiry is not None and expiry < now:
            # The watchdog relay opened in between: the current flowed until then only.
            if expiry > self._t:
                self.battery.step(self._current_a, expiry - self._t)
                self._t = expiry
            self._watchdog_open = True
            self._current_a = self._regulate()
        dt = now - self._t
        if dt > 0:
            self.battery.step(self._current_a, dt)
            self._t = now
            self._current_a = self._regulate()
        # dt == 0: nothing moved since the last regulation. Change settings through
        # set_supply/set_contactor/set_estop/set_heartbeat (they regulate), not by
        # assigning fields.

    def _watchdog_expiry(self) -> float | None:
        """When the watchdog relay's contact opens (it is closed now), else None."""
        if self.watchdog_timeout_s is None or self._watchdog_open or self._heartbeat_t is None:
            return None
        return self._heartbeat_t + self.watchdog_timeout_s

    # --- the contactor ----------------------------------------------------------------
    @property
    def watchdog_relay_closed(self) -> bool:
        """The watchdog relay's contact (True when none is fitted): closed while the heartbeat
        toggled within ``watchdog_timeout_s``."""
        self.advance()
        return self.watchdog_timeout_s is None or not self._watchdog_open

    @property
    def contactor_closed(self) -> bool:
        """The battery contactor itself (what its auxiliary contact reports): its coil relay
        on and, when fitted, the watchdog relay's contact closed."""
        self.advance()
        return self._contactor_closed()

    def _contactor_closed(self) -> bool:
        watchdog_ok = self.watchdog_timeout_s is None or not self._watchdog_open
        return self.contactor_coil_on and watchdog_ok

    # --- what the sensors see --------------------------------------------------------
    @property
    def pack_current_a(self) -> float:
        """Current into the pack (+ charges), as the LEM sensor and the BMS see it."""
        self.advance()
        return self._current_a

    @property
    def pack_voltage_v(self) -> float:
        self.advance()
        return self.battery.voltage_at(self._current_a)

    @property
    def pack_temperature_c(self) -> float:
        self.advance()
        return self.battery.temperature_c

    @property
    def supply_energised(self) -> bool:
        return self.supply.output_on and not self.estop_pressed

    @property
    def supply_voltage_v(self) -> float:
        """What the supply measures at its terminals."""
        self.advance()
        if self._contactor_closed():
            return self.battery.voltage_at(self._current_a)
        return self.supply.volt_set_v if self.supply_energised else 0.0

    # --- commands ----------------------------------------------------------------------
    def set_supply(self, **changes: float | bool) -> None:
        """Apply new supply settings at the current instant (integrates first)."""
        self.advance()
        for k, v in changes.items():
            if not hasattr(self.supply, k):
                raise AttributeError(f"supply has no setting {k!r}")
            setattr(self.supply, k, v)
        self._current_a = self._regulate()

    def set_contactor(self, closed: bool) -> None:
        """The coil relay (the contactor closes with it unless the watchdog relay is open)."""
        self.advance()
        self.contactor_coil_on = closed
        self._current_a = self._regulate()

    def set_heartbeat(self, on: bool) -> None:
        """The heartbeat output feeding the watchdog relay: a change of state retriggers it
        (its contact closes, or stays closed, for ``watchdog_timeout_s`` more)."""
        self.advance()
        if on == self.heartbeat_on:
            return
        self.heartbeat_on = on
        self.heartbeat_toggles += 1
        self._heartbeat_t = self.clock.now()
        self._watchdog_open = False
        self._current_a = self._regulate()

    def set_estop(self, pressed: bool) -> None:
        self.advance()
        self.estop_pressed = pressed
        if pressed:
            # Losing mains drops the supply's output; it stays off until commanded on.
            self.supply.output_on = False
        self._current_a = self._regulate()

    # --- the supply's regulation ---------------------------------------------------------
    def _regulate(self) -> float:
        """Current the EA unit drives: CV at ``volt_set`` bounded by its current limits.

        No mode command exists on the unit: it sinks when its voltage set value is below
        the terminal voltage and sources when above (reference devices.md, EA section).
        """
        s = self.supply
        if not (self.supply_energised and self._contactor_closed()):
            return 0.0
        v_pack = self.battery.voltage_at
        i_src = max(0.0, s.curr_set_a)
        i_sink = max(0.0, s.sink_curr_set_a)
        if v_pack(0.0) <= 0:
            return 0.0
        # Power limits reduce the current limits at the present voltage.
        v0 = max(v_pack(0.0), 1e-3)
        i_src = min(i_src, s.pow_set_w / v0)
        i_sink = min(i_sink, s.sink_pow_set_w / v0)
        if v_pack(i_src) <= s.volt_set_v:
            return i_src  # constant-current charge
        if v_pack(-i_sink) >= s.volt_set_v:
            return -i_sink  # constant-current discharge (sink)
        lo, hi = -i_sink, i_src
        for _ in range(_BISECT_ITERATIONS):  # constant voltage: find I with V(I) = set
            mid = (lo + hi) / 2
            if v_pack(mid) < s.volt_set_v:
                lo = mid
            else:
                hi = mid
        return (lo + hi) / 2


def make_cell(cell: SimCell, ambient_c: float = 25.0) -> BatteryModel:
    """The battery model an I/O map's ``sim:`` entry describes, cooling toward the
    bench's ambient (``simulation: ambient_c``): the temperature it starts at is the
    entry's own, the temperature it relaxes to is the room's."""
    params: dict[str, float] = {
        "capacity_ah": cell.capacity_ah,
        "soc": cell.soc,
        "temperature_c": cell.temperature_c,
        "ambient_c": ambient_c,
    }
    if cell.cells_series is not None:
        params["cells_series"] = cell.cells_series
    return make_model(cell.model, **params)


def make_plant(sim: SimulationConfig | None, clock: Clock) -> BenchPlant:
    """The seed-002 plant of an I/O map's ``simulation:`` section (defaults when absent)."""
    sc = sim or SimulationConfig()
    wd = sc.watchdog_relay
    return BenchPlant(
        clock,
        make_cell(sc.pack, sc.ambient_c),
        ambient_c=sc.ambient_c,
        watchdog_timeout_s=None if wd is None else wd.timeout_s,
    )
