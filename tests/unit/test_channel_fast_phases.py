"""A channel's two phases, written for speed (issue 13's dry run: one call per phase, the
request, the stage's state and the unchanged tags' stamps inline), leave the database
exactly as the plain rules do: each decision a call of its own and every tag written with
``TagDB.update``. The plain rules are spelt out here, as the channel ran them before."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from supervisor.channels import Channel, ChannelLimits
from supervisor.channels.channel import _AUTO, _MANUAL
from supervisor.core.quality import Quality, Reason
from supervisor.tags import TagDB

LIMITS = ChannelLimits((-0.4, 0.4), (0.8, 1.9))


# --- the plain rules ---------------------------------------------------------------------
def _f(tag: Any, default: float = 0.0) -> float:
    return float(tag.as_float(default))


def plain_request(ch: Channel) -> float:
    mode = ch.mode.value
    if mode == _MANUAL:
        return _f(ch.manual_current) if ch.enable.value else 0.0
    if mode == _AUTO and ch.auto_active.value:
        return _f(ch.auto_current)
    return 0.0


def plain_active(ch: Channel) -> bool:
    if ch.mode.value == _MANUAL:
        return bool(ch.enable.value)
    return bool(ch.auto_active.value)


def plain_clamp(ch: Channel, request: float) -> float:
    lo, hi = ch.limits.current_a
    if not math.isfinite(request):
        raise ValueError(f"non-finite current request {request!r}")
    out = min(max(request, lo), hi)
    if out > 0:
        out = min(out, _f(ch.charge_limit, hi))
    if out < 0:
        out = max(out, -_f(ch.discharge_limit, -lo))
    ch.db.update(ch.clamped, out != request)
    return out


def plain_drive(ch: Channel) -> None:
    db = ch.db
    try:
        request, active = plain_request(ch), plain_active(ch)
        if ch.fault.value:
            request, active = 0.0, False
        db.update(ch.current_cmd, plain_clamp(ch, request))
        if ch.voltage_cmd is not None:
            vlo, vhi = ch.limits.voltage_v
            target = _f(ch.auto_voltage) if ch.mode.value == _AUTO else 0.0
            db.update(ch.voltage_cmd, min(max(target, vlo), vhi) if target > 0 else vhi)
        if ch.output_cmd is not None:
            db.update(ch.output_cmd, active)
        if ch.fault.value:
            state = "faulted"
        else:
            cmd = _f(ch.current_cmd)
            state = "idle" if cmd == 0.0 else "charging" if cmd > 0 else "discharging"
        db.update(ch.state, state)
    except ValueError as exc:
        ch.go_safe()
        db.update(ch.logic_error, f"{type(exc).__name__}: {exc}")
    else:
        if ch.logic_error.value:
            db.update(ch.logic_error, "")


def plain_derive(ch: Channel, dt: float, prev: dict[str, float | None]) -> None:
    db = ch.db
    i_prev, p_prev = prev["i"], prev["p"]
    if dt > 0 and i_prev is not None:
        dq = i_prev * dt / 3600.0
        db.update(ch.charge_ah, _f(ch.charge_ah) + dq)
        t = ch.charged_ah if dq >= 0 else ch.discharged_ah
        db.update(t, _f(t) + abs(dq))
        if p_prev is not None:
            de = p_prev * dt / 3600.0
            db.update(ch.energy_wh, _f(ch.energy_wh) + de)
            t = ch.charged_wh if de >= 0 else ch.discharged_wh
            db.update(t, _f(t) + abs(de))
    prev["i"] = _f(ch.current) if ch.current.good else None
    if ch.voltage.good and ch.current.good:
        p = _f(ch.voltage) * _f(ch.current)
        db.update(ch.power, p)
        prev["p"] = p
    else:
        db.update(ch.power, ch.power.value, Quality.BAD, Reason.DERIVED_FROM_BAD)
        prev["p"] = None


# --- what a scan may find --------------------------------------------------------------
finite = st.floats(-1.0, 1.0, allow_nan=False).map(lambda x: round(x, 2))
request_value = st.one_of(finite, st.sampled_from([0.0, -0.0, 0.4, -0.4, float("inf")]))
quality = st.sampled_from([Quality.GOOD, Quality.GOOD, Quality.BAD])
scan_state = st.fixed_dictionaries(
    {
        # A mode neither Manual nor Auto (only logic could write one) asks for nothing.
        "mode": st.sampled_from([_MANUAL, _AUTO, _AUTO, "maintenance"]),
        "enable": st.booleans(),
        "manual_current": request_value,
        "auto_active": st.booleans(),
        "auto_current": request_value,
        "auto_voltage": st.sampled_from([0.0, 1.2, 2.5]),
        "fault": st.sampled_from(["", "", "voltage high"]),
        "charge_limit": st.sampled_from([0.4, 0.2, 0.0]),
        "discharge_limit": st.sampled_from([0.4, 0.1, 0.0]),
        "voltage": finite.map(lambda x: 1.3 + x / 4),
        "voltage_q": quality,
        "current": finite,
        "current_q": quality,
        "force_cmd": st.sampled_from([None, None, None, 0.1]),
        "dt": st.sampled_from([0.1, 1.0, 0.0]),
    }
)


def apply(db: TagDB, ch: Channel, s: dict[str, Any]) -> None:
    for name in (
        "mode",
        "enable",
        "manual_current",
        "auto_active",
        "auto_current",
        "auto_voltage",
        "fault",
    ):
        db.update(getattr(ch, name), s[name])
    db.update(ch.charge_limit, s["charge_limit"])
    db.update(ch.discharge_limit, s["discharge_limit"])
    db.update(ch.voltage, s["voltage"], s["voltage_q"])
    db.update(ch.current, s["current"], s["current_q"])
    if s["force_cmd"] is not None and not ch.current_cmd.forced:
        db.force("ch0.current_cmd", s["force_cmd"])
    elif s["force_cmd"] is None and ch.current_cmd.forced:
        db.unforce("ch0.current_cmd")


def image(db: TagDB) -> list[tuple[Any, ...]]:
    return [
        (t.name, t.value, t.quality, t.reason, t.source_t, t.server_t, t.forced, t.version)
        for t in db
    ]


@settings(max_examples=300, deadline=None)
@given(st.lists(scan_state, min_size=1, max_size=12), st.booleans())
def test_the_channels_phases_leave_the_tags_the_plain_rules_leave(
    scans: list[dict[str, Any]], supply: bool
) -> None:
    """``supply``: a channel on a supply with an output switch and a voltage setpoint (an
    EA), else one on a Chadèche board."""
    fast_db, plain_db = TagDB(), TagDB()
    kw = {"has_output_switch": supply, "has_voltage_setpoint": supply}
    fast = Channel("ch0", fast_db, LIMITS, capacity_ah=2.0, **kw)
    plain = Channel("ch0", plain_db, LIMITS, capacity_ah=2.0, **kw)
    prev: dict[str, float | None] = {"i": None, "p": None}
    now = 0.0
    for s in scans:
        now += 1.0
        for db, ch in ((fast_db, fast), (plain_db, plain)):
            db.set_scan_time(now)
            apply(db, ch, s)
        fast.derive(now, s["dt"])
        plain_derive(plain, s["dt"], prev)
        fast.drive(now, s["dt"])
        plain_drive(plain)
        assert image(fast_db) == image(plain_db)
        assert [t.name for t in fast_db.changed_since(0)] == [
            t.name for t in plain_db.changed_since(0)
        ]
