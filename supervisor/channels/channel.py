"""One channel's per-scan logic: derived values, protection, setpoint selection."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

from supervisor.core.quality import Quality, Reason
from supervisor.tags.db import Tag, TagDB
from supervisor.tags.spec import Access, HistorySettings, TagSpec

log = logging.getLogger(__name__)


class Mode(StrEnum):
    MANUAL = "manual"
    AUTO = "auto"


@dataclass(frozen=True, slots=True)
class ChannelLimits:
    """Hard limits: requests are clamped to the current ones; crossings trip the channel."""

    current_a: tuple[float, float]  # (max discharge <= 0, max charge >= 0)
    voltage_v: tuple[float, float]
    temperature_c: tuple[float | None, float | None] = (None, None)


def _spec(name: str, **kw: object) -> TagSpec:
    return TagSpec(name=name, **kw)  # type: ignore[arg-type]


class Channel:
    """Per-channel logic, run by the scan in two phases: ``derive`` and ``drive``."""

    def __init__(
        self,
        name: str,
        db: TagDB,
        limits: ChannelLimits,
        capacity_ah: float,
        temperature_tag: str | None = None,
        *,
        voltage_tag: str | None = None,
        current_tag: str | None = None,
        contactor_tag: str | None = None,
        permissives: tuple[str, ...] = (),
        has_output_switch: bool = False,
        has_voltage_setpoint: bool = False,
    ) -> None:
        self.name = name
        self.db = db
        self.limits = limits
        self.capacity_ah = capacity_ah
        lo, hi = limits.current_a
        vr = (limits.voltage_v[0] * 0.5, limits.voltage_v[1] * 1.2)
        n = name
        hist_fast = HistorySettings(deadband=0.0, min_interval_s=0.0)

        def add(spec: TagSpec) -> Tag:
            return db.add(spec)

        # Inputs (bound by the app to the source's points).
        self.voltage = add(_spec(f"{n}.voltage", unit="V", range=vr, description="Cell voltage"))
        self.current = add(
            _spec(f"{n}.current", unit="A", range=(lo, hi), description="+ charges the cell")
        )
        self.temperature = add(_spec(f"{n}.temperature", unit="degC", description="Cell temp."))
        self._temp_src = temperature_tag
        # Measurements taken from other tags (e.g. LEM sensor, voltage board on the ADAM).
        self._copies = [
            (self.voltage, voltage_tag),
            (self.current, current_tag),
            (self.temperature, temperature_tag),
        ]
        self._contactor = db[contactor_tag] if contactor_tag else None
        self._permissives = [db[p] for p in permissives]
        # Derived values.
        self.power = add(_spec(f"{n}.power", unit="W", history=hist_fast))
        self.charge_ah = add(
            _spec(f"{n}.charge_ah", unit="Ah", retain=True, description="Net charge (+ in)")
        )
        self.charged_ah = add(_spec(f"{n}.charged_ah", unit="Ah", retain=True))
        self.discharged_ah = add(_spec(f"{n}.discharged_ah", unit="Ah", retain=True))
        self.energy_wh = add(_spec(f"{n}.energy_wh", unit="Wh", retain=True))
        self.charged_wh = add(_spec(f"{n}.charged_wh", unit="Wh", retain=True))
        self.discharged_wh = add(_spec(f"{n}.discharged_wh", unit="Wh", retain=True))
        # Operator interface.
        self.mode = add(
            _spec(
                f"{n}.mode",
                dtype="str",
                access=Access.OPERATOR,
                initial=Mode.MANUAL.value,
                choices=tuple(m.value for m in Mode),
            )
        )
        self.enable = add(_spec(f"{n}.enable", dtype="bool", access=Access.OPERATOR, initial=False))
        self.manual_current = add(
            _spec(
                f"{n}.manual_current",
                unit="A",
                access=Access.OPERATOR,
                initial=0.0,
                description="Manual setpoint, + charge / - discharge; clamped to limits",
            )
        )
        self.auto_current = add(
            _spec(f"{n}.auto_current", unit="A", initial=0.0, description="Step chain request")
        )
        self.auto_voltage = add(
            _spec(
                f"{n}.auto_voltage",
                unit="V",
                initial=0.0,
                description="CV target asked by the step chain (0: none)",
            )
        )
        self.auto_active = add(
            _spec(f"{n}.auto_active", dtype="bool", initial=False, description="Chain running")
        )
        self.ack = add(_spec(f"{n}.ack", dtype="bool", access=Access.OPERATOR, initial=False))
        # Outputs and status.
        self.current_cmd = add(
            _spec(f"{n}.current_cmd", unit="A", initial=0.0, description="Sent to the source")
        )
        self.output_cmd = (
            add(_spec(f"{n}.output_cmd", dtype="bool", initial=False, description="Output on"))
            if has_output_switch
            else None
        )
        self.voltage_cmd = (
            add(_spec(f"{n}.voltage_cmd", unit="V", initial=limits.voltage_v[1]))
            if has_voltage_setpoint
            else None
        )
        self.clamped = add(_spec(f"{n}.clamped", dtype="bool", initial=False))
        self.fault = add(_spec(f"{n}.fault", dtype="str", initial=""))
        self.state = add(_spec(f"{n}.state", dtype="str", initial="off"))
        for t in (self.charge_ah, self.charged_ah, self.discharged_ah):
            db.update(t, 0.0)
        for t in (self.energy_wh, self.charged_wh, self.discharged_wh):
            db.update(t, 0.0)
        for t in (
            self.mode,
            self.enable,
            self.manual_current,
            self.auto_current,
            self.auto_active,
            self.ack,
        ):
            db.update(t, t.value)
        if self.output_cmd is not None:
            db.update(self.output_cmd, False)
        if self.voltage_cmd is not None:
            db.update(self.voltage_cmd, limits.voltage_v[1])
        db.update(self.current_cmd, 0.0)
        db.update(self.clamped, False)
        db.update(self.fault, "")
        self._prev_i: float | None = None
        self._prev_p: float | None = None
        self._last_clamp_req: float | None = None

    # --- per scan ------------------------------------------------------------------
    # Two phases of the scan (DESIGN.md "One scan"): ``derive`` first, so interlocks and the
    # step chain see this scan's measurements and counters; ``drive`` last, so the chain's
    # request is clamped and protected before it reaches the outputs.
    def derive(self, now: float, dt: float) -> None:
        """Derived values: measurements copied from other tags, Ah/Wh, power."""
        self._guarded(self._derive, dt)

    def drive(self, now: float, dt: float) -> None:
        """Setpoint selection, protection (latched trips), clamping, the output commands."""
        self._guarded(self._drive, dt)

    def run(self, now: float, dt: float) -> None:
        """Both phases back to back: a channel with nothing between them (no step chain)."""
        self.derive(now, dt)
        self.drive(now, dt)

    def _guarded(self, phase: Callable[[float], None], dt: float) -> None:
        try:
            phase(dt)
        except Exception as exc:  # logic error: this channel goes safe, the scan goes on
            log.exception("%s: channel logic failed", self.name)
            self._trip(f"internal error: {exc}")
            self.db.update(self.current_cmd, 0.0)

    def _derive(self, dt: float) -> None:
        db = self.db
        v, i = self.voltage, self.current
        for dst, name in self._copies:
            if name is not None:
                src = db[name]
                db.update(dst, src.value, src.quality, src.reason, src.source_t)
        self._integrate(dt)
        # Power: a value computed from a Bad input is Bad.
        if v.good and i.good:
            p = v.as_float() * i.as_float()
            db.update(self.power, p)
            self._prev_p = p
        else:
            db.update(self.power, self.power.value, Quality.BAD, Reason.DERIVED_FROM_BAD)
            self._prev_p = None

    def _drive(self, dt: float) -> None:
        db = self.db
        request = self._request()
        active = self._active()
        if active:
            self._check_permissives()
        self._protect(request)
        if self.ack.value:
            self._acknowledge()
        if self.fault.value:
            request, active = 0.0, False
        db.update(self.current_cmd, self._clamp(request))
        if self.voltage_cmd is not None:
            vlo, vhi = self.limits.voltage_v
            target = self.auto_voltage.as_float() if self.mode.value == Mode.AUTO.value else 0.0
            db.update(self.voltage_cmd, min(max(target, vlo), vhi) if target > 0 else vhi)
        # Power stage: output and contactor follow "active"; current is already 0 when not.
        if self.output_cmd is not None:
            db.update(self.output_cmd, active)
        if self._contactor is not None:
            db.update(self._contactor, active)
        db.update(self.state, self._state_name())

    def _integrate(self, dt: float) -> None:
        """Ah/Wh with a zero-order hold: the current read last scan flowed during ``dt``."""
        db = self.db
        i_prev, p_prev = self._prev_i, self._prev_p
        if dt > 0 and i_prev is not None:
            dq = i_prev * dt / 3600.0
            db.update(self.charge_ah, self.charge_ah.as_float() + dq)
            side = self.charged_ah if dq >= 0 else self.discharged_ah
            db.update(side, side.as_float() + abs(dq))
            if p_prev is not None:
                de = p_prev * dt / 3600.0
                db.update(self.energy_wh, self.energy_wh.as_float() + de)
                eside = self.charged_wh if de >= 0 else self.discharged_wh
                db.update(eside, eside.as_float() + abs(de))
        self._prev_i = self.current.as_float() if self.current.good else None

    def _active(self) -> bool:
        """Whether the channel's power stage should be energised (before trips)."""
        if self.mode.value == Mode.MANUAL.value:
            return bool(self.enable.value)
        return bool(self.auto_active.value)

    def _check_permissives(self) -> None:
        for p in self._permissives:
            if not (p.good and p.value is True):
                why = "is false" if p.good else f"is {p.quality.name} ({p.reason})"
                self._trip(f"permissive {p.name} {why}")
                return

    def _request(self) -> float:
        if self.mode.value == Mode.MANUAL.value:
            if not self.enable.value:
                return 0.0
            return self.manual_current.as_float()
        if self.mode.value == Mode.AUTO.value and self.auto_active.value:
            return self.auto_current.as_float()
        return 0.0

    def _protect(self, request: float) -> None:
        """Trip (latched) on a lost input or a hard limit crossed in the driving direction."""
        if self.fault.value or request == 0.0:
            return
        v = self.voltage
        if not v.good:
            self._trip(f"voltage input {v.quality.name} ({v.reason})")
            return
        vv = v.as_float()
        vlo, vhi = self.limits.voltage_v
        if request > 0 and vv >= vhi:
            self._trip(f"voltage {vv:.3f} V at or above hard limit {vhi} V while charging")
        elif request < 0 and vv <= vlo:
            self._trip(f"voltage {vv:.3f} V at or below hard limit {vlo} V while discharging")
        tlo, thi = self.limits.temperature_c
        t = self.temperature
        if (tlo is not None or thi is not None) and self._temp_src is not None:
            if not t.good:
                self._trip(f"temperature input {t.quality.name} ({t.reason})")
                return
            tv = t.as_float()
            if thi is not None and tv >= thi:
                self._trip(f"temperature {tv:.1f} degC at or above limit {thi} degC")
            elif tlo is not None and tv <= tlo:
                self._trip(f"temperature {tv:.1f} degC at or below limit {tlo} degC")

    def _clamp(self, request: float) -> float:
        lo, hi = self.limits.current_a
        if not math.isfinite(request):
            self._trip(f"non-finite current request {request!r}")
            return 0.0
        out = min(max(request, lo), hi)
        clamped = out != request
        if clamped and request != self._last_clamp_req:
            log.warning(
                "%s: setpoint %.4f A clamped to %.4f A (hard limits [%s, %s] A)",
                self.name,
                request,
                out,
                lo,
                hi,
            )
        self._last_clamp_req = request if clamped else None
        self.db.update(self.clamped, clamped)
        return out

    def _trip(self, why: str) -> None:
        if not self.fault.value:
            log.error("%s: tripped: %s", self.name, why)
        self.db.update(self.fault, why)
        # Never re-energised on its own: the operator must enable again after ack.
        self.db.update(self.enable, False)

    def _acknowledge(self) -> None:
        self.db.update(self.ack, False)
        if self.fault.value:
            log.info("%s: fault acknowledged: %s", self.name, self.fault.value)
            self.db.update(self.fault, "")

    def _state_name(self) -> str:
        if self.fault.value:
            return "faulted"
        cmd = self.current_cmd.as_float()
        if cmd == 0.0:
            return "idle"
        return "charging" if cmd > 0 else "discharging"

    def go_safe(self) -> None:
        """Request zero current (used at shutdown before the drivers' own safe state)."""
        self.db.update(self.enable, False)
        self.db.update(self.auto_current, 0.0)
        self.db.update(self.auto_active, False)
        self.db.update(self.current_cmd, 0.0)
        if self.output_cmd is not None:
            self.db.update(self.output_cmd, False)
        if self._contactor is not None:
            self.db.update(self._contactor, False)
