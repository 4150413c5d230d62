"""Forcing tags (commissioning overrides, ADR 0001 / ADR 0015): which tags a force may never
touch, and how a forced value given as text becomes the tag's type.

A force replaces a tag's process value until it is unforced (``TagDB.force``): whatever
reads the tag reads the forced value. A force must never defeat the e-stop or a channel's
protection (docs/design.md "Safety": no command overrides a trip), so every tag the safety phase
reads to decide a trip — the e-stop's sense input, an interlock's tag, a channel's voltage,
current and temperature inputs, permissives, contactor feedback, cross-checks, BMS limits —
and every tag it writes to hold a channel safe (limits, fault, enable, setpoints, relays)
is refused, with what reads it named in the reason.
"""

from __future__ import annotations

from collections.abc import Iterable

from supervisor.config.models import BenchConfig, ChannelConfig, SafetyConfig
from supervisor.core.driver import Value
from supervisor.tags.spec import TagSpec, shown

# The guard's (and the channel's protective) outputs of each channel (safety/guard.py).
GUARD_OUTPUTS = (
    ("enable", "dropped by a trip, never re-energised on its own"),
    ("current_cmd", "the setpoint sent to the source, clamped to the channel's limits"),
    ("voltage_cmd", "the voltage setpoint sent to the source"),
    ("output_cmd", "the source's output switch"),
    ("limit.charge_a", "the charge current the guard allows"),
    ("limit.discharge_a", "the discharge current the guard allows"),
    ("fault", "the channel's first-out trip"),
    ("fault_action", "what the channel's trip does"),
    ("first_out", "the channel's first-out trip"),
    ("armed", "the guard's power-path check"),
    ("logic_error", "a fault in the channel's logic trips it"),
)


def channel_safety_tags(c: ChannelConfig) -> dict[str, str]:
    """Tag → what of channel ``c``'s protection reads or drives it."""
    n = c.name
    guard = f"channel {n}'s guard"
    out: dict[str, str] = {}

    def add(tag: str | None, why: str) -> None:
        if tag is not None:
            out.setdefault(tag, why)

    v_lo, v_hi = c.limits.voltage_v
    add(f"{n}.voltage", f"{guard} reads it against the hard voltage limits [{v_lo}, {v_hi}] V")
    add(c.voltage_tag, f"{guard} reads it as {n}.voltage (hard voltage limits)")
    add(f"{n}.current", f"{guard} reads it (current input and feedback checks)")
    add(c.current_tag, f"{guard} reads it as {n}.current (current input and feedback checks)")
    if c.temperature_tag is not None:
        add(f"{n}.temperature", f"{guard} reads it against the temperature limits")
        add(c.temperature_tag, f"{guard} reads it as {n}.temperature (temperature limits)")
    for p in c.permissives:
        add(p, f"{guard} needs it true to drive current (permissive)")
    add(c.contactor_tag, f"{guard} checks it against the contactor feedback")
    add(c.contactor_feedback_tag, f"{guard} reads it as the contactor's auxiliary contact")
    for vc in c.voltage_checks:
        add(vc.tag, f"{guard} cross-checks it against {n}.voltage")
    if c.bms is not None:
        for tag in (c.bms.cell_max_tag, c.bms.cell_min_tag, c.bms.temperature_tag):
            add(tag, f"{guard} reads it against the BMS limits")
    for field, why in GUARD_OUTPUTS:
        add(f"{n}.{field}", f"{guard}: {why}")
    return out


def safety_tags(channels: Iterable[ChannelConfig], safety: SafetyConfig | None) -> dict[str, str]:
    """Every tag a force may not touch → why (the e-stop's and interlocks' first)."""
    out: dict[str, str] = {}
    if safety is not None:
        if safety.estop is not None:
            out[safety.estop.tag] = "the e-stop reads it (circuit closed = true)"
            if safety.estop.relay_tag is not None:
                out.setdefault(safety.estop.relay_tag, "the e-stop opens this relay on a trip")
        for i in safety.interlocks:
            out.setdefault(i.tag, f"interlock {i.id} reads it")
        if safety.heartbeat is not None:
            out.setdefault(safety.heartbeat.tag, "the hardware watchdog's heartbeat")
    for c in channels:
        for tag, why in channel_safety_tags(c).items():
            out.setdefault(tag, why)
    return out


def bench_safety_tags(cfg: BenchConfig) -> dict[str, str]:
    return safety_tags(cfg.channels, cfg.safety)


def parse_forced(spec: TagSpec, value: object) -> Value:
    """The value to force, in the tag's type: a text is read as the tag's type ("1.5" for
    a float tag, "on" for a boolean), anything else taken as given; ``TypeError`` or
    ``ValueError`` naming the tag and what was received."""
    if isinstance(value, str) and spec.dtype in ("float", "int"):
        text = value.strip()
        try:
            number: float | int = int(text) if spec.dtype == "int" else float(text)
        except ValueError:
            kind = "an integer" if spec.dtype == "int" else "a number"
            raise TypeError(f"{spec.name}: expected {kind}, got {shown(value)}") from None
        return spec.coerce(number)
    return spec.coerce(value)
