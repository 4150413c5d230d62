"""The values a step's conditions read are this scan's, although one dict per chain is
filled again at every scan (docs/adr/0018-scan-performance.md), and the dV/dt window
keeps a minute of readings."""

from __future__ import annotations

from supervisor.chains.compiler import Target, compile_recipe
from supervisor.chains.conditions import ConditionValues, Values
from supervisor.chains.port import ChannelPort
from supervisor.chains.run import RunState
from supervisor.channels import Channel, ChannelLimits
from supervisor.config.recipe import load_recipe_text
from supervisor.core.quality import Quality, Reason
from supervisor.core.units import Dim
from supervisor.tags import TagDB, TagSpec

RECIPE = """
recipe: values
chemistry: nimh
capacity: 2000 mAh
parameters:
  v_top: 1.6 V
steps:
  - id: charge
    charge: 0.1 C
    until:
      - voltage >= v_top and room.temp > 30 degC: next
"""


def rig() -> tuple[TagDB, ChannelPort, ConditionValues]:
    db = TagDB()
    Channel("ch0", db, ChannelLimits((-1.0, 1.0), (0.0, 2.0)), capacity_ah=2.0)
    db.add(TagSpec("room.temp", unit="degC"))
    recipe, pos = load_recipe_text(RECIPE, "values.yaml")
    program = compile_recipe(
        recipe, pos, "values.yaml", Target(tags={"room.temp": Dim.TEMPERATURE})
    )
    port = ChannelPort.from_tags(db, "ch0", "auto")
    return db, port, ConditionValues(port, db, program)


def fresh(port: ChannelPort, db: TagDB, cv: ConditionValues, now: float, r: RunState) -> Values:
    """The values as a new dict would hold them."""

    def reading(tag: object) -> float | None:
        return tag.as_float() if tag.good else None  # type: ignore[attr-defined]

    v = reading(port.voltage)
    peak = cv.peak_v
    room = db["room.temp"]
    return {
        "voltage": v,
        "current": reading(port.current),
        "temperature": reading(port.temperature),
        "power": reading(port.power),
        "charge": port.charge_ah.as_float() - r.q0_ah,
        "energy": port.energy_wh.as_float(),
        "step_charge": port.charge_ah.as_float() - r.step_q0,
        "step_energy": port.energy_wh.as_float() - r.step_e0,
        "step_time": now - r.t_step0,
        "cycle_time": now - r.t_cycle0,
        "test_time": now - r.t_test0,
        "cycle": float(r.cycle),
        "dv_dt": cv.dv_dt(),
        "delta_peak": (peak - v) if (peak is not None and v is not None) else None,
        "peak_voltage": peak,
        "v_top": 1.6,
        "room.temp": room.as_float() if room.good else None,
    }


def test_each_scan_reads_that_scans_values() -> None:
    db, port, cv = rig()
    r = RunState(t_step0=1.0, t_cycle0=0.5, step_q0=0.1)
    for k in range(30):
        now = k * 1.0
        v = 1.2 + 0.01 * (k % 7)
        if k % 5 == 3:
            db.update(port.voltage, v, Quality.BAD, Reason.STALE)
        else:
            db.update(port.voltage, v)
            cv.observe(now, v)
        db.update(port.current, 0.2 if k % 4 else -0.1)
        db.update(port.charge_ah, 0.01 * k)
        db.update(db["room.temp"], 20.0 + k)
        r.cycle = 1 + k // 10
        assert cv.values(now, r) == fresh(port, db, cv, now, r)


def test_dv_dt_spans_the_last_minute_of_readings_once_it_spans_ten_seconds() -> None:
    _, _, cv = rig()
    for k in range(10):
        cv.observe(float(k), 1.0 + 0.001 * k)
    assert cv.dv_dt() is None  # 9 s of readings
    for k in range(10, 200):
        cv.observe(float(k), 1.0 + 0.001 * k)
    assert cv.dv_dt() == (1.0 + 0.001 * 199 - (1.0 + 0.001 * 139)) / 60.0
    cv.restart()
    assert cv.dv_dt() is None and cv.peak_v is None
