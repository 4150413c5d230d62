"""One channel's per-scan logic: derived values, then setpoint selection and clamping.

Protection is not decided here: the safety phase (``supervisor/safety/guard.py``) runs
between ``derive`` and ``drive`` and publishes what the outputs may do (``chN.fault``,
``chN.limit.charge_a``/``discharge_a``); ``drive`` obeys it, so no request — Manual or a
step chain's — can override a trip.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import StrEnum

from supervisor.core.driver import Value
from supervisor.core.quality import Quality, Reason
from supervisor.tags.db import Tag, TagDB
from supervisor.tags.spec import Access, HistorySettings, TagSpec

log = logging.getLogger(__name__)


class Mode(StrEnum):
    MANUAL = "manual"
    AUTO = "auto"


_MANUAL = Mode.MANUAL.value
_AUTO = Mode.AUTO.value
"""The mode values as plain texts: ``Mode.MANUAL`` is an attribute lookup on an enum
class, about seven times the cost of the comparison, and ``drive`` compares up to three
times a scan."""


_GOOD, _NONE = Quality.GOOD, Reason.NONE


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
        has_output_switch: bool = False,
        has_output_feedback: bool = False,
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
        if temperature_tag is None:
            # Only a tag read elsewhere gives a channel its temperature: without one there
            # is no sensor, which is not a fault (readers see BAD "not fitted", not "initial").
            db.update(self.temperature, None, Quality.BAD, Reason.NOT_FITTED)
        # Measurements taken from other tags (e.g. LEM sensor, voltage board on the ADAM).
        self._copies = [
            (self.voltage, voltage_tag),
            (self.current, current_tag),
            (self.temperature, temperature_tag),
        ]
        self._contactor = db[contactor_tag] if contactor_tag else None
        # Derived values.
        self.power = add(_spec(f"{n}.power", unit="W", history=hist_fast))
        # Counters of the channel, kept across tests and restarts: the test's charge (from
        # the recipe's initial_charge) is ``chN.chain.charge_ah``.
        self.charge_ah = add(
            _spec(
                f"{n}.charge_ah",
                unit="Ah",
                retain=True,
                description="Net charge counter (+ in); the test's charge is chain.charge_ah",
            )
        )
        self.charged_ah = add(
            _spec(f"{n}.charged_ah", unit="Ah", retain=True, description="Charge-side counter")
        )
        self.discharged_ah = add(
            _spec(
                f"{n}.discharged_ah",
                unit="Ah",
                retain=True,
                description="Discharge-side counter",
            )
        )
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
                # The hard limits as the tag's range: the command path refuses a setpoint
                # beyond them (and OPC UA clients read them as its EURange); one inside
                # them is still clamped each scan to what the safety phase allows.
                range=(lo, hi),
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
        self.output_fb = (
            add(_spec(f"{n}.output_fb", dtype="bool", description="Output on, read back"))
            if has_output_feedback
            else None
        )
        self.clamped = add(_spec(f"{n}.clamped", dtype="bool", initial=False))
        self.state = add(_spec(f"{n}.state", dtype="str", initial="off"))
        # What the safety phase allows (written by supervisor/safety, read here).
        self.fault = add(
            _spec(f"{n}.fault", dtype="str", initial="", description="First-out latched trip")
        )
        self.fault_action = add(
            _spec(f"{n}.fault_action", dtype="str", initial="", description="hold or abort")
        )
        self.first_out = add(_spec(f"{n}.first_out", dtype="str", initial=""))
        self.armed = add(
            _spec(
                f"{n}.armed",
                dtype="bool",
                initial=contactor_tag is None,
                description="Power path closed: recipe limits and cross-checks apply",
            )
        )
        self.charge_limit = add(
            _spec(f"{n}.limit.charge_a", unit="A", initial=hi, description="Allowed charge")
        )
        self.discharge_limit = add(
            _spec(f"{n}.limit.discharge_a", unit="A", initial=-lo, description="Allowed discharge")
        )
        self.logic_error = add(_spec(f"{n}.logic_error", dtype="str", initial=""))
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
        for t in (
            self.fault,
            self.fault_action,
            self.first_out,
            self.armed,
            self.charge_limit,
            self.discharge_limit,
            self.logic_error,
        ):
            db.update(t, t.value)
        self._scan_state()

    def _scan_state(self) -> None:
        """What the phases keep between scans, and the tags they write every scan."""
        self._sources: list[tuple[Tag, Tag]] | None = None
        self._prev_i: float | None = None
        self._prev_p: float | None = None
        self._last_clamp_req: float | None = None
        # What ``drive`` writes every scan, in its order (``TagDB.update_each``): the clamp
        # flag, the command, the voltage command, the output switch and the contactor where
        # the channel has them, the state.
        self._output_tags: tuple[Tag, ...] = tuple(
            t
            for t in (
                self.clamped,
                self.current_cmd,
                self.voltage_cmd,
                self.output_cmd,
                self._contactor,
                self.state,
            )
            if t is not None
        )
        # The counters ``_integrate`` moves, by the signs of the charge and the energy of
        # the scan (``[dq_ah >= 0][de_wh >= 0]``): the side counters only grow, charged
        # what went in, discharged what came out.
        ah = ((self.charge_ah, self.discharged_ah), (self.charge_ah, self.charged_ah))
        wh = ((self.energy_wh, self.discharged_wh), (self.energy_wh, self.charged_wh))
        self._ah_counters: tuple[tuple[Tag, ...], ...] = ah
        self._counters: tuple[tuple[tuple[Tag, ...], ...], ...] = tuple(
            tuple(a + w for w in wh) for a in ah
        )

    # --- per scan ------------------------------------------------------------------
    # Two phases of the scan (docs/design.md "One scan"): ``derive`` first, so interlocks and the
    # step chain see this scan's measurements and counters; ``drive`` last, so the chain's
    # request is clamped and protected before it reaches the outputs.
    def derive(self, now: float, dt: float) -> None:
        """Derived values: measurements copied from other tags, Ah/Wh, power."""
        # One call per phase and scan: the body is here, not in a helper (issue 13).
        try:
            db = self.db
            update = db.update
            sources = self._sources
            if sources is None:
                for dst, name in self._copies:
                    if name is not None:
                        src = db[name]  # a missing tag: a logic error, the channel safe
                        update(dst, src.value, src.quality, src.reason, src.source_t)
                # Every source tag exists: looked up by name once, not every scan.
                self._sources = [(dst, db[n]) for dst, n in self._copies if n is not None]
            else:
                for dst, src in sources:
                    update(dst, src.value, src.quality, src.reason, src.source_t)
            self._integrate(dt)
            # Power: a value computed from a Bad input is Bad.
            v, i, power = self.voltage, self.current, self.power
            if v.quality is _GOOD and i.quality is _GOOD:
                p = v.number * i.number
                # An update only when it would change the tag (ADR 0037: an unchanged one
                # is left as it is; the same most scans, no call then).
                if p != power.value or power.quality is not _GOOD or power.reason is not _NONE:
                    update(power, p)
                self._prev_p = p
            else:
                update(power, power.value, Quality.BAD, Reason.DERIVED_FROM_BAD)
                self._prev_p = None
        except Exception as exc:  # logic error: this channel goes safe, the scan goes on
            self._failed(exc)

    def drive(self, now: float, dt: float) -> None:
        """Setpoint selection, clamping to what safety allows, the output commands: the
        request, clamped, and the outputs and state that follow from it, written in one
        ``update_each`` (each tag as its ``update`` would leave it)."""
        try:
            if self.fault.value:
                request, active = 0.0, False
            else:
                # The request and whether the stage is active, in one look at the mode.
                mode = self.mode.value
                if mode == _MANUAL:
                    active = bool(self.enable.value)
                    request = self.manual_current.number if active else 0.0
                else:
                    active = bool(self.auto_active.value)
                    request = self.auto_current.number if active and mode == _AUTO else 0.0
            command, clamped = self._clamp(request)
            cmd = self.current_cmd
            outputs: list[Value] = [clamped, command]  # the values of ``_output_tags``
            if self.voltage_cmd is not None:
                vlo, vhi = self.limits.voltage_v
                target = self.auto_voltage.number if self.mode.value == _AUTO else 0.0
                cv = (
                    (vlo if target < vlo else vhi if target > vhi else target)
                    if target > 0
                    else vhi
                )
                outputs.append(cv)
            # Power stage: output and contactor follow "active"; the current is 0 when not.
            if self.output_cmd is not None:
                outputs.append(active)
            if self._contactor is not None:
                outputs.append(active)
            # The state's name, from the fault and the command the source gets: the one
            # written here (``update`` stores a number as a float that compares the same),
            # or a forced one.
            if self.fault.value:
                state = "faulted"
            else:
                c = cmd.number if cmd.forced else command
                state = "idle" if c == 0.0 else "charging" if c > 0 else "discharging"
            outputs.append(state)
            self.db.update_each(self._output_tags, outputs)
        except Exception as exc:
            self._failed(exc)
        else:
            if self.logic_error.value:  # a drive that ran through clears the logic error
                self.db.update(self.logic_error, "")

    def run(self, now: float, dt: float) -> None:
        """Both phases back to back: a channel with nothing between them (no step chain)."""
        self.derive(now, dt)
        self.drive(now, dt)

    def _failed(self, exc: Exception) -> None:
        """A phase raised (``derive`` and ``drive`` run their work inside a ``try``: one
        call less per phase and scan): the channel goes safe."""
        log.exception("%s: channel logic failed", self.name)
        self.go_safe()
        # The safety phase trips the channel on it (latched, until reset).
        self.db.update(self.logic_error, f"{type(exc).__name__}: {exc}")

    def _integrate(self, dt: float) -> None:
        """Ah/Wh with a zero-order hold: the current read last scan flowed during ``dt``."""
        i_prev, p_prev = self._prev_i, self._prev_p
        if dt > 0 and i_prev is not None:
            dq_ah = i_prev * dt / 3600.0
            # Each counter: update(tag, tag.as_float() + delta), in one call.
            if p_prev is None:
                self.db.add_each(self._ah_counters[dq_ah >= 0], (dq_ah, abs(dq_ah)))
            else:
                de_wh = p_prev * dt / 3600.0
                self.db.add_each(
                    self._counters[dq_ah >= 0][de_wh >= 0],
                    (dq_ah, abs(dq_ah), de_wh, abs(de_wh)),
                )
        current = self.current
        self._prev_i = current.number if current.quality is _GOOD else None

    def _clamp(self, request: float) -> tuple[float, bool]:
        """Into the hard current limits, and into what the safety phase allows this scan
        (nothing towards a crossed voltage limit, less near a BMS cell limit): the current
        allowed, and whether it is not the one requested (for ``chN.clamped``)."""
        lo, hi = self.limits.current_a
        if not math.isfinite(request):
            raise ValueError(f"non-finite current request {request!r}")
        # Comparisons, not min()/max(): a builtin with keyword parsing costs a few hundred
        # instructions a call, four a scan (issue 29: cachegrind of the dry run).
        out = lo if request < lo else hi if request > hi else request
        hard = out != request
        allowed = out
        if allowed > 0:
            limit = self.charge_limit.as_float(hi)
            if limit < allowed:
                allowed = limit
        if allowed < 0:
            limit = -self.discharge_limit.as_float(-lo)
            if limit > allowed:
                allowed = limit
        clamped = allowed != request
        if clamped and request != self._last_clamp_req:
            why = f"hard limits [{lo}, {hi}] A" if hard and allowed == out else "safety limits"
            log.warning(
                "%s: setpoint %.4f A clamped to %.4f A (%s)", self.name, request, allowed, why
            )
        self._last_clamp_req = request if clamped else None
        return allowed, clamped

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
