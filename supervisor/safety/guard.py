"""A channel's protection: every trip that holds it, and what its outputs may do this scan.

Run in the safety phase (after the channels' derived values, before the step chains), so
it sees this scan's measurements and no recipe can override it. For each channel it

- raises its trips (latched alarms, ISA-18.2) from: a lost voltage input while driving,
  a hard voltage or temperature limit crossed, a permissive lost, an output that disagrees
  with its read-back (contactor coil vs its auxiliary contact, supply output vs ``OUTP?``,
  measured current vs setpoint once settled — S7-GRAPH discrepancy monitoring), another
  measurement of the same voltage that disagrees (a broken sense wire), BMS limits, and a
  fault in the channel's own logic;
- publishes what the outputs may do: ``chN.limit.charge_a`` / ``chN.limit.discharge_a``
  (0 in a direction blocked by a crossed limit — so no current ever flows towards it —
  derated near a BMS cell limit), ``chN.fault`` (first-out trip, "" when none),
  ``chN.fault_action`` (``abort`` when a trip aborts the recipe, e.g. the e-stop, else
  ``hold``), ``chN.armed`` (the power path is closed: recipe limits and cross-checks apply);
- takes the operator's ``chN.ack``: acknowledge, and reset the trips whose cause is gone.

A new trip drops the channel's Manual ``enable``: it is never re-energised on its own.
The channel (``supervisor/channels``) only reads these tags; it never decides a trip.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

from supervisor.config.models import ChannelConfig
from supervisor.core.delay import OnDelay
from supervisor.core.errors import OperatorError
from supervisor.core.quality import Quality
from supervisor.safety.alarms import Alarm, AlarmManager, AlarmText, Severity, signal_name
from supervisor.tags import Tag, TagDB

log = logging.getLogger(__name__)

_GOOD = Quality.GOOD
AUTO = "auto"  # the value of chN.mode under a step chain
REGULATION_MARGIN = 0.02
"""A source holding a voltage (CV, or the supply's own limit) may give less current than
set: the current-feedback check only expects the full setpoint while the voltage is more
than this fraction away from the voltage it regulates at."""


@dataclass
class _Check:
    """One trip of this channel: its alarm, its on-delay and its condition this scan."""

    alarm: Alarm
    delay: OnDelay
    condition: Callable[[], str]  # "" when fine, else why it trips
    reads: tuple[Tag, ...] | None = None
    """The tags the condition is a function of (with the request's, ``reads_request``),
    and of nothing else but the frozen configuration; None: evaluated every scan."""
    reads_request: bool = False
    seen: int = -1
    """The newest version among those tags when the condition was last evaluated."""
    why: str = ""
    active: bool = False
    """The condition and the on-delay's output at that evaluation."""


class ChannelGuard:
    """The safety check of one channel (a ``SafetyCheck`` of the safety phase)."""

    def __init__(self, cfg: ChannelConfig, db: TagDB, alarms: AlarmManager) -> None:
        self.name = cfg.name
        self.cfg = cfg
        self.db = db
        self.alarms = alarms
        n = cfg.name
        self._v = db[f"{n}.voltage"]
        self._i = db[f"{n}.current"]
        self._temp = db[f"{n}.temperature"]
        self._cmd = db[f"{n}.current_cmd"]
        self._manual = db[f"{n}.manual_current"]
        self._enable = db[f"{n}.enable"]
        self._mode = db[f"{n}.mode"]
        self._auto = db[f"{n}.auto_current"]
        self._auto_active = db[f"{n}.auto_active"]
        self._auto_voltage = db[f"{n}.auto_voltage"]
        self._ack = db[f"{n}.ack"]
        self._logic_error = db[f"{n}.logic_error"]
        self._output_cmd = db.get(f"{n}.output_cmd")
        self._output_fb = db.get(f"{n}.output_fb")
        self._fault = db[f"{n}.fault"]
        self._action = db[f"{n}.fault_action"]
        self._first_out = db[f"{n}.first_out"]
        self._armed = db[f"{n}.armed"]
        self._charge_limit = db[f"{n}.limit.charge_a"]
        self._discharge_limit = db[f"{n}.limit.discharge_a"]
        self._contactor = db[cfg.contactor_tag] if cfg.contactor_tag else None
        self._contactor_fb = db[cfg.contactor_feedback_tag] if cfg.contactor_feedback_tag else None
        self._current_tol = cfg.feedback.current_tolerance_a
        # The frozen configuration's limits, read every scan: looked up once.
        self._current_limits_a = cfg.limits.current_a
        self._vlo, self._vhi = cfg.limits.voltage_v
        # The source's status tag (declared by the scan engine after the safety phase is
        # built): found by name until it exists, then kept (tags are never removed).
        self._connected_name = f"{cfg.source.device}.connected"
        self._connected: Tag | None = None
        self._closing = OnDelay(cfg.feedback.delay_s)  # coil on, no feedback: settle time
        self._cmd_version = self._cmd.version
        self._request_tags = (
            self._mode,
            self._auto,
            self._auto_active,
            self._manual,
            self._enable,
            self._cmd,
        )
        """What ``_intended_a`` reads."""
        self._checks: list[_Check] = []
        self._build_checks()
        self._gated = True
        """The fast paths of ``evaluate`` (a check skipped while its tags did not change
        since it settled, every check skipped while none of theirs did, the trips and the
        admission computed again only when their inputs moved, unchanged tags stamped);
        False only in the tests that check them against the plain path: every check
        evaluated and every tag updated every scan."""
        # Every check skipped at once (``evaluate``) when the last pass over them
        # (``_evaluate_checks``) left each settled (``_quiet``), none of the tags a check
        # reads (``_gate_tags``; None while a check is evaluated every scan) changed since
        # that pass started (database version ``_quiet_version``), and no alarm was written
        # since the guard's last evaluation started (``AlarmManager.writes`` then,
        # ``_alarm_writes``): each check would be skipped by its own test in the pass.
        self._gate_tags = self._union_of_reads()
        self._quiet = False
        self._quiet_version = -1
        self._alarm_writes = -1
        # The trips published last, each tag with its value, and the alarm writes they were
        # found at (``_publish_trips``).
        self._trips_writes = -1
        self._trips_out: tuple[tuple[Tag, str], ...] = ()
        # The admission's charge and discharge limits, each tag with its value, and the
        # database version they were computed at, from the tags ``_admission`` reads (the
        # BMS's temperature too: one tag more to look at, never one too few).
        self._admission_reads = (self._fault, self._v, *getattr(self, "_bms_tags", {}).values())
        self._admission_version = -1
        self._limits_a: tuple[tuple[Tag, float], ...] = ()

    # --- declaration --------------------------------------------------------------------
    def _check(
        self,
        key: str,
        condition: Callable[[], str],
        delay_s: float = 0.0,
        reads: tuple[Tag, ...] | None = None,
        reads_request: bool = False,
    ) -> Alarm:
        alarm = self.alarms.declare(
            f"{self.name}.{key}", group=self.name, severity=Severity.HIGH, latched=True
        )
        self._checks.append(_Check(alarm, OnDelay(delay_s), condition, reads, reads_request))
        return alarm

    def _build_checks(self) -> None:
        cfg = self.cfg
        lim = cfg.limits
        v = (self._v,)
        # The checks that are functions of their tags only say so (``reads``): evaluated
        # only when one of those moved (issue 13). The others are evaluated every scan.
        self._check("internal", self._internal, reads=(self._logic_error,))
        self._check("voltage_input", self._voltage_input, reads=v, reads_request=True)
        self._check("current_input", self._current_input, reads=(self._i,), reads_request=True)
        # Its tag is declared after the guard: ``reads`` once found (``_source_lost``).
        self._check("source", self._source_lost)
        self._source_check = self._checks[-1]
        self._check(
            "voltage_high", self._voltage_high, lim.trip_delay_s, reads=v, reads_request=True
        )
        self._check("voltage_low", self._voltage_low, lim.trip_delay_s, reads=v, reads_request=True)
        if cfg.temperature_tag is not None and lim.temperature_c != (None, None):
            self._check(
                "temperature",
                self._temperature,
                lim.trip_delay_s,
                reads=(self._temp,),
                reads_request=True,
            )
        for tag in cfg.permissives:
            self._check(f"permissive.{tag}", self._permissive(self.db[tag], f"permissive.{tag}"))
        delay = cfg.feedback.delay_s
        if self._contactor is not None and self._contactor_fb is not None:
            self._check("contactor_feedback", self._contactor_discrepancy, delay)
        if self._output_cmd is not None and self._output_fb is not None:
            self._check("output_feedback", self._output_discrepancy, delay)
        if self._current_tol is not None:
            self._check("current_feedback", self._current_discrepancy, delay)
        for vc in cfg.voltage_checks:
            other = self.db[vc.tag]
            self._check(
                f"voltage_check.{vc.tag}",
                self._voltage_disagrees(other, vc.tolerance_v),
                vc.delay_s,
            )
        bms = cfg.bms
        if bms is not None:
            self._bms_tags = {
                k: self.db[t]
                for k, t in (
                    ("cell_max", bms.cell_max_tag),
                    ("cell_min", bms.cell_min_tag),
                    ("temperature", bms.temperature_tag),
                )
                if t is not None
            }
            self._check("bms", self._bms_limits, bms.trip_delay_s)

    def _union_of_reads(self) -> tuple[Tag, ...] | None:
        """Every tag a check reads, the request's included, the voltage first (it moves
        most); None while a check is evaluated every scan (it has no ``reads``)."""
        union: dict[Tag, None] = {self._v: None}
        for check in self._checks:
            if check.reads is None:
                return None
            union.update(dict.fromkeys(check.reads))
        union.update(dict.fromkeys(self._request_tags))
        return tuple(union)

    # --- what a start waits for ------------------------------------------------------------
    def inputs_not_good(self) -> list[str]:
        """The inputs this guard checks that do not read GOOD (yet): the channel's voltage,
        current and temperature (when it has one), its source's connection and the BMS
        values. Empty once every device answered (``supervisor run --start`` waits for
        it: a BMS's first frames come some time after its connection)."""
        tags = [self._v, self._i, *getattr(self, "_bms_tags", {}).values()]
        if self.cfg.temperature_tag is not None:
            tags.append(self._temp)
        out = [f"{t.name} {t.quality.name} ({t.reason})" for t in tags if not t.good]
        connected = self.db.get(self._connected_name)
        if connected is None or connected.value is not True:
            out.append(f"{self._connected_name} not true")
        return out

    # --- the scan -----------------------------------------------------------------------
    def evaluate(self, now: float, dt: float) -> None:
        db = self.db
        fast = self._gated
        # Without a contactor the path is always closed: no call (``_power_path_closed``).
        closed = True if self._contactor is None else self._power_path_closed(now)
        db.update(self._armed, closed)
        # Every check skipped while none of their tags changed since they all settled and no
        # alarm was written since the last pass (issue 13: nearly every scan of a slow test):
        # each would be skipped by ``_evaluate_checks``'s own test (see ``_quiet``).
        writes = self.alarms.writes
        quiet = fast and self._quiet and writes == self._alarm_writes
        if quiet:
            seen = self._quiet_version
            for tag in self._gate_tags or ():
                if tag.version > seen:
                    quiet = False
                    break
        if not quiet:
            self._evaluate_checks(now)
        if self._ack.value:
            db.update(self._ack, False)
            try:
                self.reset("operator")
            except OperatorError as exc:
                log.warning("%s", exc)
        if self.alarms.writes == self._trips_writes and fast:
            db.update_many(self._trips_out)  # ``_publish_trips``: the trips found last
        else:
            self._publish_trips()
        # The admission is a function of ``_admission_reads`` (and the frozen
        # configuration): computed again only when one of them changed since.
        seen = self._admission_version
        moved = not fast
        for tag in self._admission_reads:
            if tag.version > seen:
                moved = True
                break
        if moved:
            charge, discharge = self._admission()
            self._limits_a = ((self._charge_limit, charge), (self._discharge_limit, discharge))
            self._admission_version = db.version
        self.db.update_many(self._limits_a)
        # The count at the start: after an evaluation that wrote an alarm (a trip, a reset),
        # the next scan's pass checks each alarm against its check again.
        self._alarm_writes = writes

    def _evaluate_checks(self, now: float) -> None:
        """Evaluate the checks: each gated one only when one of its tags moved since it was
        last evaluated, or while it has not settled, or when its alarm was changed behind
        it; the others every scan."""
        db = self.db
        set_alarm = self.alarms.set
        gated = self._gated
        self._quiet = False  # until this pass is over
        start_version = db.version
        if gated:
            m, a, aa, mc, e, c = self._request_tags
            request = max(m.version, a.version, aa.version, mc.version, e.version, c.version)
        else:
            request = 0
        # All settled at the end of this pass, every check gated from its start.
        quiet = gated and self._gate_tags is not None
        for check in self._checks:
            alarm = check.alarm
            reads = check.reads
            if gated and reads is not None:
                newest = request if check.reads_request else -1
                for tag in reads:
                    if tag.version > newest:
                        newest = tag.version
                if (
                    newest <= check.seen
                    and (check.active or not check.why)
                    and alarm.active is check.active
                    and alarm.shelved_until is None
                    and (not check.active or alarm.message == check.why)
                ):
                    # None of its tags changed since it was last evaluated, and it had
                    # settled (fine, or tripped past its on-delay): the condition would
                    # say the same, the on-delay and the alarm would stay as they are.
                    continue
                check.seen = newest
            why = check.condition()
            active = check.delay.update(bool(why), now)
            check.why, check.active = why, active
            was_tripped = alarm.tripped
            set_alarm(alarm, active, why)
            if alarm.tripped and not was_tripped:
                log.error("%s: tripped: %s", self.name, why)
                # Never re-energised on its own: the operator must enable again after reset.
                db.update(self._enable, False)
                request = max(request, self._enable.version)
            if not (active or not why) or alarm.shelved_until is not None:
                quiet = False  # its on-delay runs, or its alarm is shelved: evaluated again
        self._quiet = quiet
        self._quiet_version = start_version

    def fail_safe(self, why: str) -> None:
        """The guard itself failed: hold the channel with no current in either direction."""
        self.db.update(self._charge_limit, 0.0)
        self.db.update(self._discharge_limit, 0.0)
        self.db.update(self._fault, why)
        self.db.update(self._action, "hold")
        self.db.update(self._enable, False)

    def reset_refusal(self) -> str:
        """Why ``reset`` would refuse now, "" when it would reset every trip (a screen's
        Acknowledge button asks; the same words as the refusal)."""
        alarms = self.alarms
        refused = [why for a in alarms.trips(self.name) if (why := alarms.reset_refusal(a.id))]
        return f"{self.name}: " + "; ".join(refused) if refused else ""

    def reset(self, actor: str) -> list[str]:
        """Acknowledge every alarm holding the channel and reset the trips whose cause is
        gone; raise OperatorError naming those whose cause is still present."""
        refused: list[str] = []
        done: list[str] = []
        for alarm in self.alarms.trips(self.name):
            try:
                self.alarms.reset(alarm.id, actor)
                done.append(alarm.id)
            except OperatorError as exc:
                if not alarm.acked:
                    self.alarms.acknowledge(alarm.id, actor)
                refused.append(str(exc))
        self._publish_trips()
        if refused:
            raise OperatorError(f"{self.name}: " + "; ".join(refused))
        if done:
            log.info("%s: reset by %s: %s", self.name, actor, ", ".join(done))
        return done

    def _publish_trips(self) -> None:
        alarms = self.alarms
        fast = self._gated
        # The trips are a function of the alarms (their state, and which are declared):
        # found again only when one was written since (``AlarmManager.writes``).
        writes = alarms.writes
        if writes != self._trips_writes or not fast:
            trips = alarms.trips(self.name)
            fault, action, first_out = "", "", ""
            if trips:
                fault, first_out = trips[0].message, trips[0].id
                action = "abort" if any(a.action == "abort" for a in trips) else "hold"
                if not self._fault.value and self._enable.value:
                    # A new trip, its own or a bench-wide one (the e-stop, an interlock):
                    # the Manual enable drops, so that the reset energises nothing.
                    self.db.update(self._enable, False)
            self._trips_out = (
                (self._fault, fault),
                (self._action, action),
                (self._first_out, first_out),
            )
            self._trips_writes = writes
        self.db.update_many(self._trips_out)

    # --- what the outputs may do ----------------------------------------------------------
    def _admission(self) -> tuple[float, float]:
        """Charge and discharge magnitudes allowed this scan."""
        if self._fault.value:
            return 0.0, 0.0
        lo, hi = self._current_limits_a
        charge, discharge = hi, -lo
        v = self._v
        if v.quality is _GOOD:
            vv = v.number
            if vv >= self._vhi:
                charge = 0.0
            if vv <= self._vlo:
                discharge = 0.0
        bms = self.cfg.bms
        if bms is not None:
            cmax, cmin = self._bms_tags.get("cell_max"), self._bms_tags.get("cell_min")
            lo_v, hi_v = bms.cell_voltage_v
            band = bms.derate_band_v
            if cmax is not None:
                charge *= _derate(cmax, hi_v - cmax.number, band)
            if cmin is not None:
                discharge *= _derate(cmin, cmin.number - lo_v, band)
        return charge, discharge

    # --- conditions -----------------------------------------------------------------------
    def _intended_a(self) -> float:
        """The current asked for (Manual setpoint, or the chain's request) — or flowing."""
        if self._mode.value == AUTO:
            asked = self._auto.number if self._auto_active.value else 0.0
        else:
            asked = self._manual.number if self._enable.value else 0.0
        return asked if asked != 0.0 else self._cmd.number

    def _active(self) -> bool:
        if self._mode.value == AUTO:
            return bool(self._auto_active.value)
        return bool(self._enable.value)

    def _power_path_closed(self, now: float | None = None) -> bool:
        """The battery is on the source and the readings have settled: the contactor's
        auxiliary contact (or, without one, its coil) has said closed for the discrepancy
        time — a source polled slower than the contactor still shows its old terminal
        voltage for a moment after it closes."""
        if self._contactor is None:
            return True
        if now is None:
            return bool(self._armed.value)
        fb = self._contactor_fb
        closed = fb.good and fb.value is True if fb is not None else self._contactor.value is True
        return self._closing.update(closed, now)

    def _internal(self) -> str:
        err = self._logic_error.value
        return AlarmText(f"internal error: {err}", "guard.internal", {"error": err}) if err else ""

    def _voltage_input(self) -> str:
        v = self._v
        if v.quality is _GOOD or self._intended_a() == 0.0:
            return ""
        return _reading_lost("voltage", v)

    def _current_input(self) -> str:
        i = self._i
        if i.quality is _GOOD or self._intended_a() == 0.0:
            return ""
        return _reading_lost("current", i)

    def _source_lost(self) -> str:
        connected = self._connected
        if connected is None:
            # The scan engine declares the device's status tag (after the safety phase is
            # built).
            connected = self._connected = self.db.get(self._connected_name)
            if connected is not None:
                check = self._source_check
                check.reads, check.reads_request = (connected,), True
                self._gate_tags = self._union_of_reads()
        if connected is None or connected.value is not False or self._intended_a() == 0.0:
            return ""
        device = self.cfg.source.device
        return AlarmText(
            f"Source {device}: connection lost",
            "guard.source_lost",
            {"device": device},
            f"{connected.name} is false",
        )

    def _voltage_high(self) -> str:
        v, hi = self._v, self._vhi
        if v.quality is _GOOD and self._intended_a() > 0 and v.number >= hi:
            return AlarmText(
                f"voltage {v.number:.3f} V at or above hard limit {hi} V while charging",
                "guard.voltage_high",
                {"value_v": v.number, "limit_v": hi},
            )
        return ""

    def _voltage_low(self) -> str:
        v, lo = self._v, self._vlo
        if v.quality is _GOOD and self._intended_a() < 0 and v.number <= lo:
            return AlarmText(
                f"voltage {v.number:.3f} V at or below hard limit {lo} V while discharging",
                "guard.voltage_low",
                {"value_v": v.number, "limit_v": lo},
            )
        return ""

    def _temperature(self) -> str:
        tlo, thi = self.cfg.limits.temperature_c
        t = self._temp
        if t.quality is not _GOOD:
            if self._intended_a() == 0.0:
                return ""
            return _reading_lost("temperature", t)
        tv = t.number
        if thi is not None and tv >= thi:
            return AlarmText(
                f"temperature {tv:.1f} °C at or above limit {thi} °C",
                "guard.temperature_high",
                {"value_c": tv, "limit_c": thi},
            )
        if tlo is not None and tv <= tlo:
            return AlarmText(
                f"temperature {tv:.1f} °C at or below limit {tlo} °C",
                "guard.temperature_low",
                {"value_c": tv, "limit_c": tlo},
            )
        return ""

    def _permissive(self, tag: Tag, key: str) -> Callable[[], str]:
        alarm_id = f"{self.name}.{key}"

        def condition() -> str:
            if tag.good and tag.value is True:
                return ""
            # Needed to drive; once it has tripped, its absence keeps the trip from being
            # reset (the cause is still present even though nothing drives any more).
            if not (self._active() or self.alarms[alarm_id].tripped):
                return ""
            if tag.good:
                return AlarmText(
                    f"Permissive lost: {signal_name(tag)}",
                    "guard.permissive_off",
                    {"signal": signal_name(tag)},
                    f"permissive {tag.name} is false",
                )
            return AlarmText(
                f"Permissive unknown: {signal_name(tag)} ({tag.quality.name.lower()}:"
                f" {tag.reason})",
                "guard.permissive_unknown",
                {"signal": signal_name(tag), "quality": tag.quality.name, "reason": tag.reason},
                f"permissive {tag.name} is {tag.quality.name} ({tag.reason})",
            )

        return condition

    def _contactor_discrepancy(self) -> str:
        cmd, fb = self._contactor, self._contactor_fb
        assert cmd is not None and fb is not None
        want = cmd.value is True
        if not fb.good:
            if not want:
                return ""
            return AlarmText(
                f"Contactor feedback unknown ({fb.quality.name.lower()}: {fb.reason})",
                "guard.contactor_unknown",
                {"quality": fb.quality.name, "reason": fb.reason},
                f"{fb.name} is {fb.quality.name} ({fb.reason})",
            )
        if (fb.value is True) == want:
            return ""
        state, asked = ("closed" if fb.value else "open"), ("closed" if want else "open")
        return AlarmText(
            f"Contactor {state} while commanded {asked}",
            "guard.contactor_discrepancy",
            {"state": state, "commanded": asked},
            f"{fb.name} is {str(bool(fb.value)).lower()}",
        )

    def _output_discrepancy(self) -> str:
        cmd, fb = self._output_cmd, self._output_fb
        assert cmd is not None and fb is not None
        if not fb.good:
            return ""  # a lost supply trips through its inputs; nothing to compare with
        want = cmd.value is True
        if (fb.value is True) == want:
            return ""
        state, asked = ("on" if fb.value else "off"), ("on" if want else "off")
        return AlarmText(
            f"supply output {state} while commanded {asked}",
            "guard.output_discrepancy",
            {"state": state, "commanded": asked},
            f"{fb.name} is {str(bool(fb.value)).lower()}",
        )

    def _current_discrepancy(self) -> str:
        tol = self._current_tol
        assert tol is not None
        cmd, i = self._cmd.number, self._i
        if self._cmd.version != self._cmd_version:
            # A new setpoint restarts the settling time (the on-delay restarts with it).
            self._cmd_version = self._cmd.version
            return ""
        if not i.good or not self._power_path_closed():
            return ""
        ii = i.number
        params = {"current_a": ii, "setpoint_a": cmd}
        if cmd * ii < 0 and abs(ii) > tol:
            text = f"current {ii:.3f} A flows the wrong way for a setpoint of {cmd:.3f} A"
            return AlarmText(text, "guard.current_reversed", params)
        if abs(ii) > abs(cmd) + tol:
            text = f"current {ii:.3f} A above its setpoint {cmd:.3f} A"
            return AlarmText(text, "guard.current_high", params)
        if abs(ii) < abs(cmd) - tol and not self._regulating_voltage(cmd):
            text = f"current {ii:.3f} A against {cmd:.3f} A commanded"
            return AlarmText(text, "guard.current_low", params)
        return ""

    def _regulating_voltage(self, cmd: float) -> bool:
        """Near the voltage the source regulates at, less current than set is normal."""
        v = self._v
        if not v.good:
            return False
        vlo, vhi = self.cfg.limits.voltage_v
        cv = self._auto_voltage.number if self._mode.value == AUTO else 0.0
        target = (cv if cv > 0 else vhi) if cmd > 0 else vlo
        return abs(v.number - target) <= REGULATION_MARGIN * abs(target)

    def _voltage_disagrees(self, other: Tag, tolerance_v: float) -> Callable[[], str]:
        def condition() -> str:
            v = self._v
            if not (v.good and other.good and self._power_path_closed()):
                return ""
            diff = v.number - other.number
            if abs(diff) <= tolerance_v:
                return ""
            return AlarmText(
                f"voltage {v.number:.3f} V and {signal_name(other)} {other.number:.3f} V"
                f" disagree by {abs(diff):.3f} V (tolerance {tolerance_v:g} V)",
                "guard.voltage_disagrees",
                {
                    "value_v": v.number,
                    "signal": signal_name(other),
                    "other_v": other.number,
                    "difference_v": abs(diff),
                    "tolerance_v": tolerance_v,
                },
                f"{v.name} against {other.name}",
            )

        return condition

    def _bms_limits(self) -> str:
        bms = self.cfg.bms
        assert bms is not None
        lo_v, hi_v = bms.cell_voltage_v
        for key, tag in self._bms_tags.items():
            if not tag.good:
                if self._intended_a() == 0.0:
                    continue
                return AlarmText(
                    f"BMS reading {signal_name(tag)} lost ({tag.quality.name.lower()}:"
                    f" {tag.reason})",
                    "guard.bms_reading_lost",
                    {"signal": signal_name(tag), "quality": tag.quality.name, "reason": tag.reason},
                    f"{tag.name} is {tag.quality.name} ({tag.reason})",
                )
            x = tag.number
            if key == "cell_max" and x > hi_v:
                return AlarmText(
                    f"BMS cell voltage {x:.3f} V above {hi_v:g} V",
                    "guard.bms_cell_high",
                    {"value_v": x, "limit_v": hi_v},
                )
            if key == "cell_min" and x < lo_v:
                return AlarmText(
                    f"BMS cell voltage {x:.3f} V below {lo_v:g} V",
                    "guard.bms_cell_low",
                    {"value_v": x, "limit_v": lo_v},
                )
            tmax = bms.temperature_max_c
            if key == "temperature" and tmax is not None and x >= tmax:
                return AlarmText(
                    f"BMS temperature {x:.1f} °C at or above {tmax:g} °C",
                    "guard.bms_temperature_high",
                    {"value_c": x, "limit_c": tmax},
                )
        return ""


def _derate(tag: Tag, headroom: float, band: float) -> float:
    """Full current with at least ``band`` of headroom, tapering to 0 at the limit; a BMS
    value that is not GOOD allows nothing (the BMS check trips the channel)."""
    if not tag.good or not math.isfinite(headroom):
        return 0.0
    return min(1.0, max(0.0, headroom / band))


def _reading_lost(what: str, tag: Tag) -> AlarmText:
    """A measurement the guard needs while driving, not GOOD: said in words, the tag's
    quality and reason kept as the detail."""
    return AlarmText(
        f"{what.capitalize()} reading lost while driving ({tag.quality.name.lower()}:"
        f" {tag.reason})",
        f"guard.{what}_input",
        {"quality": tag.quality.name, "reason": tag.reason},
        f"{tag.name} is {tag.quality.name} ({tag.reason})",
    )
