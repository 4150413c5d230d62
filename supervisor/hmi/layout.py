"""What the screens draw: the bench's layout, a channel's compiled chain, diagnostics.

- ``GET /api/bench``: the channels, devices and the mimic's tags, from the I/O map and the
  tag database (a tag the bench does not have is ``null``), so that the page never guesses
  a tag name. Each device says what it is (its kind's role: supply, BMS, I/O, cycler) and
  the lines of its mimic box (its kind's ``shows``, as the I/O map's tags), from the device
  registry: the page knows no device name and no kind.
- ``GET /api/channels/{ch}/program``: the step chain the channel runs, from its compiled
  ``Program`` (chains/program.py: what the engine executes, never the YAML re-parsed), with
  each step's transitions; the active step and the last transition's cause are tags
  (``chN.chain.step_index``, ``chN.chain.last_event``), named in the answer.
- ``GET /api/diagnostics``: devices and their communication (the driver's counters, the
  ``<device>.connected`` tag, the worst quality of the inputs the scan copies from it and
  how many of them are GOOD/UNCERTAIN/BAD), the scan's statistics (ScanStats: the last
  ``STATS_WINDOW`` scans), each publisher's tags (queues, drops) and the InfluxDB spool.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

from aiohttp import web

from supervisor.chains.engine import ChainRunner
from supervisor.chains.program import ActionKind, CompiledStep, Program, Transition
from supervisor.config.models import BenchConfig, ChannelConfig
from supervisor.core.clock import Clock
from supervisor.core.driver import Driver
from supervisor.core.quality import Quality
from supervisor.devices.kind import LINK, DeviceRole
from supervisor.devices.registry import REGISTRY, Registry
from supervisor.hmi.server import json_dumps, tag_json
from supervisor.scan.engine import ScanEngine, ScanStats
from supervisor.tags import TagDB

CHANNEL_TAGS: dict[str, str] = {
    # role on the screen -> the channel's tag (``<channel>.<suffix>``)
    "voltage": "voltage",
    "current": "current",
    "temperature": "temperature",
    "power": "power",
    # The test's charge (what the display line, ``ctl`` and OPC UA ``Charge`` show); the
    # net counter beside it is labelled as a counter.
    "charge": "chain.charge_ah",
    "charge_counter": "charge_ah",
    "charged": "charged_ah",
    "discharged": "discharged_ah",
    "energy": "energy_wh",
    "mode": "mode",
    "enable": "enable",
    "manual_current": "manual_current",
    "current_cmd": "current_cmd",
    "output": "output_fb",
    "clamped": "clamped",
    "channel_state": "state",
    "fault": "fault",
    "first_out": "first_out",
    "armed": "armed",
    "state": "chain.state",  # the step chain's; what the channel does is channel_state
    "recipe": "chain.recipe",
    "test_id": "chain.test_id",
    "step": "chain.step",
    "step_index": "chain.step_index",
    "cycle": "chain.cycle",
    "step_time": "chain.step_time",
    "test_time": "chain.test_time",
    "progress": "chain.progress",
    "eta": "chain.eta_s",
    "alarm": "chain.alarm",
    "interlock": "chain.interlock",
    "last_event": "chain.last_event",
}
"""The tags of a channel tile and screen (``null`` when a channel has none, e.g. ``output``
on a Chadèche board)."""


class BenchView(Protocol):
    """What the layout reads of a running bench (``supervisor.app.Bench`` is one)."""

    @property
    def cfg(self) -> BenchConfig: ...
    @property
    def db(self) -> TagDB: ...
    @property
    def engine(self) -> ScanEngine: ...
    @property
    def drivers(self) -> Mapping[str, Driver]: ...
    @property
    def runners(self) -> Mapping[str, ChainRunner]: ...


def _answer(body: Any, status: int = 200) -> web.Response:
    return web.json_response(body, status=status, dumps=json_dumps)


class Layout:
    def __init__(self, bench: BenchView, clock: Clock, registry: Registry = REGISTRY) -> None:
        self.bench = bench
        self.clock = clock
        self.registry = registry

    def install(self, app: web.Application) -> None:
        app.add_routes(
            [
                web.get("/api/bench", self._bench),
                web.get("/api/channels/{channel}/program", self._program),
                web.get("/api/diagnostics", self._diagnostics),
            ]
        )

    def _tag(self, name: str | None) -> str | None:
        return name if name is not None and name in self.bench.db else None

    # --- /api/bench --------------------------------------------------------------------
    def bench_json(self) -> dict[str, Any]:
        cfg = self.bench.cfg
        channels = []
        for c in cfg.channels:
            device = cfg.devices[c.source.device]
            channels.append(
                {
                    "name": c.name,
                    "description": c.description,
                    "kind": device.driver,
                    "device": c.source.device,
                    "board": c.source.board,
                    "chemistry": c.chemistry,
                    "capacity_ah": c.capacity_ah,
                    "limits": {
                        "current_a": list(c.limits.current_a),
                        "voltage_v": list(c.limits.voltage_v),
                        "temperature_c": list(c.limits.temperature_c),
                    },
                    "unit_prefix": c.name,
                    "tags": {
                        role: self._tag(f"{c.name}.{suffix}")
                        for role, suffix in CHANNEL_TAGS.items()
                    },
                    "trend": self.trend_series(c),
                }
            )
        devices = [
            {
                "name": name,
                "kind": d.driver,
                "role": self.registry.kind_of(d).role.value,
                "simulated": bool(getattr(d, "simulated", False)),
                "health_tag": self._tag(f"{name}.connected"),
                "failures_tag": self._tag(f"{name}.comm_failures"),
                "shows": self.shows(name),
            }
            for name, d in cfg.devices.items()
        ]
        return {
            "bench": cfg.bench,
            "description": cfg.description,
            "period_s": cfg.scan.period_s,
            "channels": channels,
            "devices": devices,
            "mimic": self.mimic(),
        }

    def trend_series(self, ch: ChannelConfig) -> list[dict[str, str]]:
        """The series a channel's trend draws beside its V, I and T: its BMS's lowest and
        highest cell voltage (what "Show Graphs" of seed 002 plots of the cells; this BMS
        gives only those), on a scale of their own (``cell``), each as the bench's tag."""
        if ch.bms is None:
            return []
        units = {t.name: t.unit for t in self.bench.cfg.tags}
        out = []
        for label, tag in (("cell min", ch.bms.cell_min_tag), ("cell max", ch.bms.cell_max_tag)):
            name = self._tag(tag)
            if name is not None:
                out.append(
                    {"label": label, "tag": name, "unit": units.get(name, ""), "scale": "cell"}
                )
        return out

    def shows(self, device: str) -> list[dict[str, str]]:
        """The lines of ``device``'s mimic box (its kind's ``shows``), each as the tag the
        bench has for it: the link tag, or the I/O map's tag bound to that point (a point
        the I/O map maps to no tag has no line)."""
        cfg = self.bench.cfg
        by_point = {t.point: t.name for t in cfg.tags if t.device == device}
        lines = []
        for shown in self.registry.kind_of(cfg.devices[device]).shows:
            name = f"{device}.{LINK}" if shown.point == LINK else by_point.get(shown.point)
            tag = self._tag(name)
            if tag is not None:
                lines.append({"label": shown.label, "tag": tag, "format": shown.format})
        return lines

    def mimic(self) -> dict[str, Any]:
        """The power path of the bench's mimic: the e-stop circuit, the supply's output, the
        battery contactor (its contacts and its coil) and the BMS link (the first channel
        that has each), and which devices fill the supply and BMS boxes (by their kind's
        role, see :meth:`shows`)."""
        cfg = self.bench.cfg
        estop = cfg.safety.estop
        supply = supply_device = contactor = coil = bms = bms_device = None
        channel = None
        for c in cfg.channels:
            if supply is None and self._tag(f"{c.name}.output_fb"):
                supply, channel = f"{c.name}.output_fb", channel or c.name
                supply_device = c.source.device
            if contactor is None and (c.contactor_feedback_tag or c.contactor_tag):
                contactor = self._tag(c.contactor_feedback_tag or c.contactor_tag)
                coil = self._tag(c.contactor_tag) if c.contactor_feedback_tag else None
                channel = channel or c.name
        for name, d in cfg.devices.items():
            if bms is None and self.registry.kind_of(d).role is DeviceRole.BMS:
                bms, bms_device = self._tag(f"{name}.{LINK}"), name
        return {
            "estop": self._tag(estop.tag) if estop is not None else None,
            "estop_relay": self._tag(estop.relay_tag) if estop is not None else None,
            "supply": supply,
            "supply_device": supply_device,
            "contactor": contactor,
            "coil": coil,
            "bms": bms,
            "bms_device": bms_device,
            "channel": channel,
        }

    async def _bench(self, request: web.Request) -> web.Response:
        return _answer(self.bench_json())

    # --- /api/channels/{ch}/program ----------------------------------------------------
    async def _program(self, request: web.Request) -> web.Response:
        channel = request.match_info["channel"]
        runner = self.bench.runners.get(channel)
        if runner is None:
            return _answer({"error": "unknown channel", "reason": f"no channel {channel!r}"}, 404)
        if runner.program is None:
            return _answer(
                {"error": "no recipe", "reason": f"{channel}: no recipe loaded"}, status=404
            )
        return _answer(program_json(channel, runner.program))

    # --- /api/diagnostics --------------------------------------------------------------
    def _value(self, name: str) -> Any:
        tag = self.bench.db.get(name)
        return None if tag is None else tag_json(tag, self.clock)["value"]

    def diagnostics_json(self) -> dict[str, Any]:
        bench, db = self.bench, self.bench.db
        devices = []
        for name, d in bench.cfg.devices.items():
            driver = bench.drivers.get(name)
            # The inputs the scan copies from this device (outputs are BAD until written).
            qualities = [b.tag.quality for b in bench.engine.inputs if b.driver.name == name]
            counts = {q.name: sum(1 for x in qualities if x is q) for q in Quality}
            worst = max(qualities) if qualities else None  # Quality orders by severity
            devices.append(
                {
                    "name": name,
                    "kind": d.driver,
                    "connected": self._value(f"{name}.connected"),
                    "quality": worst.name if worst is not None else None,
                    "inputs": counts,
                    "last_error": getattr(driver, "last_error", None) or None,
                    "polls": getattr(driver, "polls", None),
                    "failures": getattr(driver, "failures", None),
                    "poll_period_s": d.poll_period_s,
                }
            )
        stats = bench.engine.stats
        durations, jitters = list(stats.durations_s), list(stats.jitters_s)
        scan = {
            "period_s": bench.engine.period_s,
            "count": stats.count,
            "duration_s": self._value("scan.duration_s"),
            "duration_p50_s": ScanStats.percentile(durations, 50),
            "duration_p99_s": ScanStats.percentile(durations, 99),
            "duration_max_s": self._value("scan.duration_max_s"),
            "jitter_p99_s": ScanStats.percentile(jitters, 99),
            "overruns": stats.overruns,
            "skipped": stats.skipped,
            "stalls": stats.stalls,
            "stall_max_s": stats.stall_max_s,
            "logic_errors": stats.logic_errors,
            "realtime_priority": stats.realtime_priority,
            "realtime_refused": stats.realtime_refused,
            "window": len(durations),
        }
        publishers = []
        for pub in bench.engine.publishers:
            name = str(getattr(pub, "name", type(pub).__name__))
            prefix = name + "."
            tags = {
                t.name[len(prefix) :]: {
                    "value": self._value(t.name),
                    "description": t.spec.description,
                }
                for t in db
                if t.name.startswith(prefix)
            }
            queue = next(
                (tags[k]["value"] for k in ("queue_depth", "spool_depth") if k in tags), None
            )
            dropped = (
                tags["dropped"]["value"] if "dropped" in tags else getattr(pub, "dropped", None)
            )
            publishers.append({"name": name, "queue": queue, "dropped": dropped, "tags": tags})
        spool = None
        if "influx.spool_depth" in db:
            spool = {
                "points": self._value("influx.spool_depth"),
                "bytes": self._value("influx.spool_bytes"),
                "dead_letters": self._value("influx.dead_letters"),
                "dropped": self._value("influx.dropped"),
                "connected": self._value("influx.connected"),
            }
        return {"devices": devices, "scan": scan, "publishers": publishers, "spool": spool}

    async def _diagnostics(self, request: web.Request) -> web.Response:
        return _answer(self.diagnostics_json())


def _target(program: Program, step: CompiledStep, kind: ActionKind, target_id: str | None) -> str:
    """The step an action leads to (``end`` past the last step)."""
    if kind is ActionKind.GOTO and target_id:
        return target_id
    if kind is ActionKind.END:
        return "end"
    if kind is ActionKind.NEXT_CYCLE:
        return program.steps[0].id if program.steps else "end"
    if kind is ActionKind.HOLD:
        return "hold"
    nxt = step.index + 1
    return program.steps[nxt].id if nxt < len(program.steps) else "end"


def _transition(program: Program, step: CompiledStep, t: Transition) -> dict[str, Any]:
    return {
        "to": _target(program, step, t.action.kind, t.action.target_id),
        "condition": t.text,
        "action": str(t.action),
    }


def program_json(channel: str, program: Program) -> dict[str, Any]:
    """The compiled chain as the channel screen draws it."""
    steps = []
    for s in program.steps:
        transitions = [_transition(program, s, t) for t in s.transitions]
        if s.kind == "goto" and s.goto is not None:
            transitions.append(
                {"to": program.steps[s.goto].id, "condition": "always", "action": "goto"}
            )
        elif s.kind == "end_cycle":
            transitions.append({"to": "next cycle", "condition": "always", "action": "next_cycle"})
        elif s.kind == "end":
            transitions.append({"to": "end", "condition": "always", "action": "end"})
        elif s.duration_s is not None and s.advance is not None:
            transitions.append(
                {
                    "to": _target(program, s, s.advance.kind, s.advance.target_id),
                    "condition": f"step time >= {s.duration_s:g} s",
                    "action": str(s.advance),
                }
            )
        steps.append(
            {
                "name": s.id,
                "index": s.index,
                "kind": s.kind,
                "comment": s.comment,
                "current_a": s.current_a,
                "voltage_v": s.voltage_v,
                "power_w": s.power_w,
                "duration_s": s.duration_s,
                "max_time_s": s.max_time_s,
                "groups": [gr.id for gr in program.groups if gr.index in s.groups],
                "transitions": transitions,
            }
        )
    return {
        "channel": channel,
        "recipe": program.name,
        "file": program.file,
        "description": program.description,
        "cycles": program.cycles,
        "parameters": program.parameters,
        "steps": steps,
        # The active step is steps[step_index - 1] (0: none), the last transition's cause
        # is in last_event (chains/engine.py).
        "tags": {
            "step": f"{channel}.chain.step",
            "step_index": f"{channel}.chain.step_index",
            "step_time": f"{channel}.chain.step_time",
            "last_event": f"{channel}.chain.last_event",
            "state": f"{channel}.chain.state",
            "cycle": f"{channel}.chain.cycle",
        },
    }
