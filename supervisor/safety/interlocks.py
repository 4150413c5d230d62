"""Bench-wide trips and alarms: the e-stop, the I/O map's interlocks, tag alarm limits,
and the heartbeat of the contactor's hardware watchdog.

- **E-stop** (seed 002 §1.5): the sense input reads true while the circuit is closed. False
  trips every channel at once, aborts their recipes and opens the software e-stop relay; it
  resets only once the circuit is closed again. A sense that is not GOOD (the ADAM lost)
  cannot show a press: it trips every channel too (fail safe), but holds their tests rather
  than aborting them — the hardware e-stop still cuts the supply's mains on its own.
- **Software e-stop** (seed 002 §1.5, beside the hardware one): ``Estop.press`` by a person
  (HTTP, OPC UA, the screens, ``supervisor ctl estop``, all through the command path) is a
  press of the same button as far as the bench is concerned: the same ``estop`` alarm, so
  the same trip of every channel, abort and software e-stop relay. It stays pressed until
  ``Estop.release``, which follows the hardware e-stop's rule: acknowledged first, then
  reset (and not while the hardware button is still pressed).
- **Interlocks** (``safety.interlocks`` in the I/O map): a tag above, below or equal to a
  value (a value that is not GOOD trips too), with an on-delay and a deadband for the way
  back; latched; they hold (or abort) the channels they name, all by default.
- **Tag alarm limits** (``alarms:`` of a tag mapping: HH/H/L/LL with deadband and on-delay):
  plain alarms, not trips: they go away when the value comes back (ISA-18.2).
- **Heartbeat**: an output toggled every ``period_s`` for a hardware watchdog relay in series
  with the contactor coil (deploy/watchdog-wiring.md); when the supervisor dies, the
  toggling stops and the watchdog opens the contactor.
"""

from __future__ import annotations

from dataclasses import dataclass

from supervisor.config.models import EstopConfig, HeartbeatConfig, InterlockConfig
from supervisor.core.delay import OnDelay
from supervisor.core.errors import OperatorError
from supervisor.safety.alarms import Alarm, AlarmManager, AlarmText, Severity, signal_name
from supervisor.tags import Tag, TagDB
from supervisor.tags.spec import AlarmLimits

UNIT_WORDS = {"degC": "°C"}
"""Units as an operator reads them in an alarm's text (the tags keep theirs on the wire)."""


@dataclass(frozen=True, slots=True)
class SoftwarePress:
    """Who pressed the software e-stop, and when (``Clock.now()``)."""

    actor: str
    t: float


class Estop:
    name = "estop"

    def __init__(self, cfg: EstopConfig, db: TagDB, alarms: AlarmManager) -> None:
        self.sense = db[cfg.tag]
        self.relay = db[cfg.relay_tag] if cfg.relay_tag else None
        self.db = db
        self.alarm = alarms.declare(
            "estop", severity=Severity.CRITICAL, latched=True, action="abort"
        )
        self.unknown = alarms.declare(
            "estop.unknown", severity=Severity.HIGH, latched=True, action="hold"
        )
        self.alarms = alarms
        self.software: SoftwarePress | None = None
        """The software e-stop, pressed (by whom) until released; None: not pressed."""

    @property
    def hardware_pressed(self) -> bool:
        """The sense input reads the circuit open (a sense that is not GOOD shows no press:
        ``estop.unknown`` holds the bench for that)."""
        s = self.sense
        return s.good and s.value is not True

    def evaluate(self, now: float, dt: float) -> None:
        s = self.sense
        why = self._pressed_text()
        self.alarms.set(self.alarm, bool(why), why)
        unknown = AlarmText(
            f"E-stop state unknown: its input {signal_name(s)} is {s.quality.name.lower()}"
            f" ({s.reason})",
            "estop.unknown",
            {"signal": signal_name(s), "quality": s.quality.name, "reason": s.reason},
            f"{s.name} is {s.quality.name} ({s.reason})",
        )
        self.alarms.set(self.unknown, not s.good, unknown)
        if self.relay is not None:
            # The software e-stop relay is closed only while no e-stop trip holds the bench.
            self.db.update(self.relay, not (self.alarm.tripped or self.unknown.tripped))

    def _circuit(self) -> str:
        """The e-stop circuit as the I/O map describes its sense ("e-stop circuit closed":
        the circuit is named, its state said apart)."""
        return signal_name(self.sense).removesuffix(" closed")

    def _pressed_text(self) -> AlarmText | str:
        """What pressed the e-stop, in words ("" when nothing does): the button (its circuit
        open), the software e-stop (by whom), or both."""
        s, soft = self.sense, self.software
        hardware = self.hardware_pressed
        if not hardware and soft is None:
            return ""
        detail = f"{s.name} is false" if hardware else ""
        if hardware and soft is not None:
            return AlarmText(
                f"Emergency stop pressed ({self._circuit()} open),"
                f" and the software e-stop by {soft.actor}",
                "estop.both",
                {"signal": signal_name(s), "actor": soft.actor},
                detail,
            )
        if hardware:
            return AlarmText(
                f"Emergency stop pressed ({self._circuit()} open)",
                "estop.pressed",
                {"signal": signal_name(s)},
                detail,
            )
        assert soft is not None
        return AlarmText(
            f"Software e-stop pressed by {soft.actor}", "estop.software", {"actor": soft.actor}
        )

    def fail_safe(self, why: str) -> None:
        if self.relay is not None:
            self.db.update(self.relay, False)

    # --- the software e-stop (by the command path, between two scans) -------------------
    def press(self, actor: str) -> str:
        """Press the software e-stop: the ``estop`` trip activates now (the relay opens now;
        the next scan's guards take every channel safe and abort its recipe). Pressing it
        again is never refused: the first press stands, and the answer says who made it."""
        now = self.alarms.clock.now()
        first = self.software
        if first is None:
            self.software = SoftwarePress(actor, now)
        self.evaluate(now, 0.0)
        if first is not None:
            return (
                f"software e-stop already pressed by {first.actor}: every channel stays"
                " tripped (acknowledge, then reset the e-stop)"
            )
        return (
            f"software e-stop pressed by {actor}: every channel tripped, recipes aborted;"
            " acknowledge, then reset the e-stop"
        )

    def release_refusal(self) -> str:
        """Why the e-stop may not be reset now ("" when it may): the hardware e-stop's rule
        (acknowledged before reset, never while its cause is present)."""
        a = self.alarm
        if self.software is None and not a.tripped:
            return "the e-stop is not pressed: nothing to reset"
        if not a.acked:
            return f"acknowledge the e-stop first (alarm estop is unacknowledged: {a.message})"
        if self.hardware_pressed:
            return (
                f"the hardware e-stop is still pressed ({self._circuit()} open):"
                " release the button first"
            )
        return ""

    def release(self, actor: str) -> str:
        """Release the software e-stop and reset the ``estop`` trip (``OperatorError`` with
        the reason when ``release_refusal`` has one). The channels stay safe: each needs
        its own reset, and nothing is energised again on its own."""
        why = self.release_refusal()
        if why:
            raise OperatorError(f"e-stop reset refused: {why}")
        self.software = None
        self.evaluate(self.alarms.clock.now(), 0.0)
        self.alarms.reset(self.alarm.id, actor)
        return (
            f"e-stop reset by {actor}: the software e-stop is released; each channel stays"
            " safe until it is reset"
        )


class Interlock:
    def __init__(self, cfg: InterlockConfig, db: TagDB, alarms: AlarmManager) -> None:
        self.name = f"interlock.{cfg.id}"
        self.cfg = cfg
        self.tag = db[cfg.tag]
        self.delay = OnDelay(cfg.delay_s)
        self.alarms = alarms
        self.alarm = alarms.declare(
            self.name,
            severity=Severity.named(cfg.severity),
            latched=True,
            action=cfg.action,
            affects=tuple(cfg.channels) if cfg.channels is not None else None,
        )

    def evaluate(self, now: float, dt: float) -> None:
        why = self._condition()
        self.alarms.set(self.alarm, self.delay.update(bool(why), now), why)

    def _condition(self) -> str:
        cfg, t = self.cfg, self.tag
        label = cfg.message or f"interlock {cfg.id}"
        if not t.good:
            return AlarmText(
                f"{label}: {signal_name(t)} unknown ({t.quality.name.lower()}: {t.reason})",
                "interlock.unknown",
                {
                    "label": label,
                    "signal": signal_name(t),
                    "quality": t.quality.name,
                    "reason": t.reason,
                },
                f"{t.name} is {t.quality.name} ({t.reason})",
            )
        # On the way back the value must pass the deadband (no chattering at the limit).
        back = self.alarm.active
        if cfg.equals is not None:
            hit = t.value is cfg.equals
            shown = str(t.value).lower()
        else:
            x = t.as_float()
            shown = f"{x:g} {UNIT_WORDS.get(t.spec.unit, t.spec.unit)}".strip()
            if cfg.above is not None:
                hit = x > cfg.above - (cfg.deadband if back else 0.0)
            else:
                assert cfg.below is not None
                hit = x < cfg.below + (cfg.deadband if back else 0.0)
        if not hit:
            return ""
        limit = (
            f"= {str(cfg.equals).lower()}"
            if cfg.equals is not None
            else f"> {cfg.above:g}"
            if cfg.above is not None
            else f"< {cfg.below:g}"
        )
        return AlarmText(
            f"{label}: {signal_name(t)} {shown} (limit {limit})",
            "interlock.limit",
            {"label": label, "signal": signal_name(t), "value": shown, "limit": limit},
            f"{t.name} {shown} {limit}",
        )

    def fail_safe(self, why: str) -> None:
        self.alarms.set(self.alarm, True, why)


@dataclass
class _Level:
    key: str  # HH, H, L, LL
    limit: float
    high: bool
    alarm: Alarm
    delay: OnDelay


class TagAlarms:
    """HH/H/L/LL limits of every tag that declares them (plain alarms, not trips)."""

    name = "tag alarm limits"

    def __init__(self, db: TagDB, alarms: AlarmManager) -> None:
        self.alarms = alarms
        self._tags: list[tuple[Tag, AlarmLimits, list[_Level]]] = []
        for tag in db:
            lim = tag.spec.alarms
            if lim is None:
                continue
            levels: list[_Level] = []
            for key, high, severity in (
                ("HH", True, Severity.HIGH),
                ("H", True, Severity.MEDIUM),
                ("L", False, Severity.MEDIUM),
                ("LL", False, Severity.HIGH),
            ):
                value = getattr(lim, key.lower())
                if value is not None:
                    alarm = alarms.declare(f"{tag.name}.{key}", severity=severity)
                    levels.append(_Level(key, value, high, alarm, OnDelay(lim.delay_s)))
            self._tags.append((tag, lim, levels))

    @property
    def levels(self) -> int:
        """The limits it watches (HH/H/L/LL of every tag): none, it has nothing to do."""
        return sum(len(levels) for _, _, levels in self._tags)

    def evaluate(self, now: float, dt: float) -> None:
        for tag, lim, levels in self._tags:
            if not tag.good:
                continue  # its quality says it already; no limit applies to an unknown value
            x = tag.as_float()
            for lv in levels:
                back = lv.alarm.active
                db = lim.deadband if back else 0.0
                hit = x >= lv.limit - db if lv.high else x <= lv.limit + db
                # The text only when the limit is crossed: an inactive alarm's is not read.
                why = _level_text(tag, x, lv) if hit else ""
                self.alarms.set(lv.alarm, lv.delay.update(hit, now), why)

    def fail_safe(self, why: str) -> None:
        return None  # plain alarms: nothing to make safe


def _level_text(tag: Tag, x: float, lv: _Level) -> AlarmText:
    """A crossed HH/H/L/LL limit in words: "pack temperature high (H): 51 °C, limit 50 °C"."""
    unit = UNIT_WORDS.get(tag.spec.unit, tag.spec.unit)
    side = "high" if lv.high else "low"
    return AlarmText(
        f"{signal_name(tag)} {side} ({lv.key}): {x:g} {unit}, limit {lv.limit:g} {unit}",
        f"level.{lv.key}",
        {"signal": signal_name(tag), "value": x, "limit": lv.limit, "unit": unit},
        f"{tag.name} {x:g} {tag.spec.unit} {'>=' if lv.high else '<='} {lv.limit:g}",
    )


class Heartbeat:
    name = "heartbeat"

    def __init__(self, cfg: HeartbeatConfig, db: TagDB) -> None:
        self.tag = db[cfg.tag]
        self.period_s = cfg.period_s
        self.db = db
        self._next_t: float | None = None

    def evaluate(self, now: float, dt: float) -> None:
        if self._next_t is None or now >= self._next_t - 1e-9:
            self.db.update(self.tag, not bool(self.tag.value))
            self._next_t = now + self.period_s

    def fail_safe(self, why: str) -> None:
        return None  # stopping the toggling is what opens the contactor
