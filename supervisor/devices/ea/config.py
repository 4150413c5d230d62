"""EA-PSB 10000: the I/O map entry, and the point catalog (the one place for its points).

The driver, the simulator and ``supervisor check`` read these points from here. Protocol
facts (SCPI headers, status bits, the unverified ones marked) are in
:mod:`supervisor.devices.ea.protocol`. The rating a model name encodes is read here too
(:func:`model_rating`), so ``supervisor check`` refuses channel limits above it before the
driver would, at connect.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar, Final, Literal, NamedTuple

from pydantic import Field, model_validator

from supervisor.config.models import NetworkDevice, SourcePoints, SourceSpec
from supervisor.core.driver import PointInfo
from supervisor.devices.ea.protocol import model_matches, normalize_model

WATCHDOG_POLL_RATIO: Final = 3.0
"""``watchdog_s`` must be at least this many poll periods: every poll is the keep-alive."""

POINTS: Final[Mapping[str, PointInfo]] = MappingProxyType(
    {
        p.name: p
        for p in (
            PointInfo("voltage", "in", "float", "V", "measured output voltage"),
            PointInfo("current", "in", "float", "A", "measured current, + charging, - discharging"),
            PointInfo("power", "in", "float", "W", "measured power, same sign as current"),
            PointInfo("output_on", "in", "bool", "", "DC output on (OUTP?)"),
            PointInfo("remote", "in", "bool", "", "remote control held (SYST:LOCK:OWN?)"),
            PointInfo("ques", "in", "int", "", "STAT:QUES:COND? (bit 0 OVP, 1 OCP, 2 OPP, 3 OT)"),
            PointInfo("error", "in", "str", "", "last non-zero SYST:ERR? entry, or ''"),
            PointInfo("output", "out", "bool", "", "DC output on/off"),
            PointInfo("current_set", "out", "float", "A", "+ charge, - discharge"),
            PointInfo("voltage_set", "out", "float", "V", "CV target while charging"),
        )
    }
)

MODEL_RATING_RE: Final = re.compile(
    r"(?P<series>[A-Z]{2,4}) 1(?P<volts>\d{4})-(?P<amps>\d{1,4})(?: (?P<variant>[0-9A-Z]+))?"
)
"""An EA 10000-series model name, after :func:`~supervisor.devices.ea.protocol.normalize_model`:
series, ``1``, the nominal voltage in four digits, ``-``, the nominal current, an optional
form-factor word (``PSB 10060-1000 4U``). UNVERIFIED rule: see :func:`model_rating`."""

MODEL_FORM: Final = "'<series> 1VVVV-A' (e.g. 'PSB 10060-60': 60 V, 60 A)"
"""How messages describe the names :data:`MODEL_RATING_RE` reads."""

DEFAULT_SIM_MODEL: Final = "PSB 10060-60"
"""The simulated unit when the I/O map names no model (60 V, 60 A, 1500 W)."""


class ModelRating(NamedTuple):
    model: str
    voltage_v: float
    current_a: float


def model_rating(model: str) -> ModelRating | None:
    """The nominal voltage and current an EA model name encodes; None when the name does
    not have the form :data:`MODEL_RATING_RE` reads (``EA-`` prefix, case and spacing
    ignored, as the driver compares models).

    The example from devices.md: ``ELR 10200-50``, the model seed 002's unit answers to
    ``*IDN?`` ("check the model to know nominal values" [V]): 200 V, 50 A. UNVERIFIED: the
    rule itself and every other name (the four digits after the series' ``1`` as volts, the
    number after the dash as amps: ``PSB 10060-60`` 60 V 60 A, ``PSB 10750-60`` 750 V 60 A)
    are read from EA's model names, not from an EA document; 9000-series and other names
    are not read. At connect the unit's own ``SYST:NOM:VOLT?``/``SYST:NOM:CURR?`` stay the
    authority (``EaDriver._check_limits``).
    """
    m = MODEL_RATING_RE.fullmatch(normalize_model(model))
    if m is None:
        return None
    volts, amps = float(m["volts"]), float(m["amps"])
    if volts <= 0 or amps <= 0:
        return None
    return ModelRating(m[0], volts, amps)


SOURCE_POINTS: Final = SourcePoints(
    voltage="voltage",
    current="current",
    current_set="current_set",
    output="output",
    output_fb="output_on",
    voltage_set="voltage_set",
)


class EaDevice(NetworkDevice):
    """EA-PSB 10000 bidirectional supply over SCPI/TCP (seed 002 §2.2)."""

    driver: Literal["ea-psb"]
    source_noun: ClassVar[str | None] = "an EA supply"
    port: int = Field(5025, ge=1, le=65535)
    expected_model: str | None = Field(
        None,
        description="refuse any other model; its rating (e.g. PSB 10060-60: 60 V, 60 A)"
        " bounds the channel's limits",
    )
    watchdog_s: float = Field(2.0, gt=0, description="interface monitoring timeout")
    sim_model: str = Field(
        DEFAULT_SIM_MODEL, description="the simulated unit's *IDN? model (default: expected_model)"
    )
    sim_nominal_v: float = Field(
        60.0, gt=0, description="the simulated unit's rating (default: expected_model's)"
    )
    sim_nominal_a: float = Field(
        60.0, gt=0, description="the simulated unit's rating (default: expected_model's)"
    )
    sim_nominal_w: float = Field(1500.0, gt=0)

    @model_validator(mode="before")
    @classmethod
    def _sim_follows_the_expected_model(cls, data: Any) -> Any:
        # The simulated unit is the expected one unless told otherwise: a simulator
        # answering another model would be refused by the driver at connect.
        if not isinstance(data, dict) or not isinstance(data.get("expected_model"), str):
            return data
        out = dict(data)
        out.setdefault("sim_model", data["expected_model"])
        rating = model_rating(data["expected_model"])
        if rating is not None:
            out.setdefault("sim_nominal_v", rating.voltage_v)
            out.setdefault("sim_nominal_a", rating.current_a)
        return out

    @model_validator(mode="after")
    def _keepalive(self) -> EaDevice:
        if self.watchdog_s < WATCHDOG_POLL_RATIO * self.poll_period_s - 1e-9:
            raise ValueError(
                f"watchdog_s ({self.watchdog_s}) must be at least 3 x poll_period_s"
                f" ({self.poll_period_s}) so the keep-alive beats the supply's timeout"
            )
        return self

    def points(self) -> Mapping[str, PointInfo]:
        return POINTS

    def channel_source(self) -> SourceSpec:
        rated_v = rated_a = None
        rating = ""
        expected = model_rating(self.expected_model) if self.expected_model else None
        if expected is not None:
            rated_v, rated_a = expected.voltage_v, expected.current_a
            rating = f"the {self.expected_model} rating"
        elif self.sim:  # the simulator answers SYST:NOM? with these: the driver checks them
            rated_v, rated_a = self.sim_nominal_v, self.sim_nominal_a
            rating = "the simulated unit's sim_nominal_v/sim_nominal_a rating"
        return SourceSpec(
            noun=self.source_noun or "",
            title="EA supply",
            regulates_voltage=True,
            owner_required=True,
            points=lambda board: SOURCE_POINTS,
            rated_voltage_v=rated_v,
            rated_current_a=rated_a,
            rating=rating,
        )

    def problems(self) -> list[tuple[tuple[str | int, ...], str]]:
        """The expected model must name its rating; a simulated unit must be that model."""
        if self.expected_model is None:
            return []
        expected = model_rating(self.expected_model)
        if expected is None:
            return [
                (
                    ("expected_model",),
                    f"cannot read a rating from expected_model {self.expected_model!r}:"
                    f" expected {MODEL_FORM} as the model",
                )
            ]
        if not self.sim:
            return []
        out: list[tuple[tuple[str | int, ...], str]] = []
        if not model_matches(self.expected_model, self.sim_model):
            out.append(
                (
                    ("sim_model",),
                    f"sim_model {self.sim_model!r} would be refused at connect (remove it:"
                    f" it defaults to expected_model): it is not the expected_model"
                    f" {self.expected_model!r}",
                )
            )
        for key, have, rated, unit in (
            ("sim_nominal_v", self.sim_nominal_v, expected.voltage_v, "V"),
            ("sim_nominal_a", self.sim_nominal_a, expected.current_a, "A"),
        ):
            if have != rated:
                out.append(
                    (
                        (key,),
                        f"{key} {have:g} {unit} differs from {rated:g} {unit} (remove it:"
                        f" it defaults to the rating), the {self.expected_model} rating",
                    )
                )
        return out
