"""Load a bench I/O map: YAML with positions → pydantic model → cross-checks.

Structural errors come from pydantic; the checks here need the whole file (does the
device have that point? is a board owned twice?). Every error names file:line:col.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from supervisor.config.limits import MAX_IO_MAP_TAGS, TooLarge
from supervisor.config.modbusmap import explicit_problems
from supervisor.config.models import (
    BenchConfig,
    ChannelConfig,
    RecordColumn,
    SimPoint,
    SourceSpec,
)
from supervisor.config.text import decode_yaml
from supervisor.config.wiring import wiring_problems
from supervisor.config.yamlpos import Positions, load_yaml_text, read_yaml_bytes, validate
from supervisor.core.driver import PointInfo
from supervisor.core.errors import ConfigError, ConfigErrors

DEVICE_STATUS_SUFFIXES = ("connected", "comm_failures")
RESERVED_PREFIXES = ("scan.", "bench.", "influx.", "sparkplug.")


CHANNEL_RECORDABLE = {"fault": "Fault", "first_out": "First Out", "clamped": "Clamped"}
"""A channel's own tags (``<channel>.<field>``) a ``record:`` list may name, with the
header each gets (the others are in the BDF columns already, or are commands)."""


def record_columns(cfg: BenchConfig, ch: ChannelConfig) -> list[RecordColumn]:
    """The auxiliary columns of ``ch``'s result files, in order: its ``record:`` list, or
    by default every measurement (a tag with a unit, on an input point) of the devices that
    serve it — its source, the devices of its voltage, current, temperature and contactor
    tags and of its BMS and voltage-check tags — but those in the BDF columns already, in
    the order of ``tags:``; then its trip text when it has a BMS (the BMS's own fault bits,
    its driver's ``faults`` point, are a measurement of its device when a tag maps it)."""
    if ch.record is not None:
        return [e if isinstance(e, RecordColumn) else _column(cfg, ch, e) for e in ch.record]
    by_name = {t.name: t for t in cfg.tags}
    refs = [ch.voltage_tag, ch.current_tag, ch.temperature_tag, ch.contactor_tag]
    refs += [vc.tag for vc in ch.voltage_checks]
    if ch.bms is not None:
        refs += [ch.bms.cell_max_tag, ch.bms.cell_min_tag, ch.bms.temperature_tag]
    devices = {ch.source.device} | {by_name[r].device for r in refs if r in by_name}
    main = {ch.voltage_tag, ch.current_tag, ch.temperature_tag}
    out = []
    for t in cfg.tags:
        if t.device not in devices or t.name in main or not t.unit or t.threshold is not None:
            continue
        dev = cfg.devices.get(t.device)
        info = dev.points().get(t.point) if dev is not None else None
        if info is not None and info.direction == "in":
            out.append(_column(cfg, ch, t.name))
    if ch.bms is not None:
        out.append(_column(cfg, ch, f"{ch.name}.fault"))
    return out


def _column(cfg: BenchConfig, ch: ChannelConfig, tag: str) -> RecordColumn:
    """A tag's column headed the BDF way: ``<tag> / <unit>`` (the tag's name, unknown to
    BDF, tells the reader which measurement it is), a channel tag by its field."""
    prefix = f"{ch.name}."
    own = CHANNEL_RECORDABLE.get(tag.removeprefix(prefix)) if tag.startswith(prefix) else None
    if own is not None:
        return RecordColumn(tag=tag, label=own)
    unit = next((t.unit for t in cfg.tags if t.name == tag), "")
    return RecordColumn(tag=tag, label=f"{tag} / {unit}" if unit else tag)


def load_bench(path: str | Path, model: type[BenchConfig]) -> BenchConfig:
    """Load and fully check a bench file against ``model`` (the registry's bench model);
    raises ConfigErrors listing every problem."""
    try:
        raw = read_yaml_bytes(path)
        data, pos = load_yaml_text(decode_yaml(raw, str(path)).text, str(path))
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    cfg = _checked(data, pos, str(path), model)
    # What each test's provenance names: the bytes loaded, not the file as it is later.
    cfg.set_source(str(Path(path).resolve()), hashlib.sha256(raw).hexdigest())
    return cfg


def load_bench_text(text: str, file: str, model: type[BenchConfig]) -> BenchConfig:
    """The same checks on text not yet written (e.g. an I/O map about to be edited)."""
    try:
        data, pos = load_yaml_text(text, file)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    return _checked(data, pos, file, model)


def check_data(data: object, file: str, model: type[BenchConfig]) -> BenchConfig:
    """The same checks on data built in code (no positions: errors point at its start)."""
    return _checked(data, Positions(), file, model)


def _checked(data: object, pos: Positions, file: str, model: type[BenchConfig]) -> BenchConfig:
    tags = data.get("tags") if isinstance(data, dict) else None
    if isinstance(tags, list) and len(tags) > MAX_IO_MAP_TAGS:
        # Before the model validates them all (README: Input limits).
        mark = pos.value(("tags", MAX_IO_MAP_TAGS)) or pos.nearest(("tags",))
        raise ConfigErrors(
            [
                TooLarge(
                    f"too many tags: {len(tags):,}; an I/O map may have at most"
                    f" {MAX_IO_MAP_TAGS:,} (README: Input limits)",
                    file,
                    mark.line,
                    mark.col,
                )
            ]
        )
    cfg = validate(model, data, pos, file)
    errors = check_bench(cfg, pos, file)
    if errors:
        raise ConfigErrors(errors)
    return cfg


def check_bench(cfg: BenchConfig, pos: Positions, file: str) -> list[ConfigError]:
    """Checks that need the whole file: does the device have that point? is a board owned
    twice? Every device kind answers for itself (``DeviceConfig`` methods). Sorted by
    position."""
    checker = _Checker(cfg, pos, file)
    checker.devices()
    checker.tags()
    checker.channels()
    checker.safety()
    checker.simulation()
    checker.wiring()
    checker.modbus_server()
    return sorted(checker.errors, key=lambda e: (e.line or 0, e.col or 0))


Path_ = tuple[str | int, ...]


class _Checker:
    def __init__(self, cfg: BenchConfig, pos: Positions, file: str) -> None:
        self.cfg = cfg
        self.pos = pos
        self.file = file
        self.errors: list[ConfigError] = []
        self.tag_index: dict[str, int] = {}  # tag name -> its first index under tags:

    def err(self, path: Path_, msg: str, at_key: bool = False) -> None:
        m = self.pos.key(path) if at_key else self.pos.value(path)
        m = m or self.pos.nearest(path)
        self.errors.append(ConfigError(msg, self.file, m.line, m.col))

    # --- devices ----------------------------------------------------------------------
    def devices(self) -> None:
        for dname, dev in self.cfg.devices.items():
            for where, msg in dev.problems():
                self.err(("devices", dname, *where), f"{msg} of device {dname!r}")

    # --- tag mappings: known device and point; unique names; reserved namespaces --------
    def tags(self) -> None:
        cfg = self.cfg
        channel_names = {c.name for c in cfg.channels}
        for i, t in enumerate(cfg.tags):
            self._tag_point(i, t.device, t.point)
            if t.name in self.tag_index:
                self.err(
                    ("tags", i, "name"),
                    f"duplicate tag name {t.name!r} (also tags[{self.tag_index[t.name]}])",
                )
            self.tag_index.setdefault(t.name, i)
            head = t.name.split(".", 1)[0]
            if head in channel_names or t.name.startswith(RESERVED_PREFIXES):
                self.err(
                    ("tags", i, "name"),
                    f"tag name {t.name!r} is in a namespace the supervisor generates"
                    f" ({head}.*); choose another name",
                )
            if head in cfg.devices and t.name.split(".", 1)[-1] in DEVICE_STATUS_SUFFIXES:
                self.err(
                    ("tags", i, "name"), f"tag name {t.name!r} is generated for device {head!r}"
                )

    def _tag_point(self, i: int, device: str, point: str) -> None:
        dev = self.cfg.devices.get(device)
        if dev is None:
            known = ", ".join(sorted(self.cfg.devices))
            self.err(("tags", i, "device"), f"unknown device {device!r} (devices: {known})")
        elif point not in dev.points():
            points = sorted(dev.points())
            have = ", ".join(points[:12]) + (", ..." if len(points) > 12 else "")
            self.err(
                ("tags", i, "point"), f"device {device!r} has no point {point!r} (it has: {have})"
            )

    # --- channels: unique names; source exists; one owner per board; limits -------------
    def channels(self) -> None:
        cfg = self.cfg
        sources = {n: s for n, d in cfg.devices.items() if (s := d.channel_source()) is not None}
        owners: dict[tuple[str, int], str] = {}
        seen: set[str] = set()
        for i, ch in enumerate(cfg.channels):
            if ch.name in seen:
                self.err(("channels", i, "name"), f"duplicate channel name {ch.name!r}")
            seen.add(ch.name)
            if ch.name in cfg.devices:
                self.err(("channels", i, "name"), f"channel name {ch.name!r} is also a device name")
            spec = self._source(i, ch.source.device, sources)
            if spec is None:
                continue
            at: Path_ = ("channels", i, "source")
            key, problems = _source_key(spec, ch.source.device, ch.source.board, at)
            for path, msg in problems:
                self.err(path, msg)
            if key is None:
                continue  # no board at all: nothing more to say about this channel
            if key in owners:
                board = "" if key[1] < 0 else f" board {key[1]}"
                self.err(
                    at,
                    f"{key[0]!r}{board} is already owned by channel {owners[key]!r}"
                    " (one owner per board)",
                )
            owners.setdefault(key, ch.name)
            self._channel_refs(i, ch)
            lo, hi = ch.limits.current_a
            if spec.max_current_a is not None and max(-lo, hi) > spec.max_current_a:
                self.err(
                    ("channels", i, "limits", "current_a"),
                    f"{spec.noun} drives at most {spec.max_current_a} A;"
                    f" limits [{lo}, {hi}] A exceed it",
                )
            self._rating(i, ch, spec)
        for dname, spec in sources.items():
            if spec.owner_required and (dname, -1) not in owners:
                self.err(
                    ("devices", dname),
                    f"{spec.title} {dname!r} drives no channel; a channel gives it its limits",
                    at_key=True,
                )

    def _rating(self, i: int, ch: ChannelConfig, spec: SourceSpec) -> None:
        """Limits within the unit's rating: the driver refuses them only at connect, and
        then the source never connects."""
        at: Path_ = ("channels", i, "limits")
        vlo, vhi = ch.limits.voltage_v
        if spec.rated_voltage_v is not None and vhi > spec.rated_voltage_v:
            self.err(
                (*at, "voltage_v"),
                f"channel {ch.name!r} limits voltage_v [{vlo:g}, {vhi:g}] V exceed"
                f" {spec.rating} ({spec.rated_voltage_v:g} V)",
            )
        ilo, ihi = ch.limits.current_a
        if spec.rated_current_a is not None and max(-ilo, ihi) > spec.rated_current_a:
            self.err(
                (*at, "current_a"),
                f"channel {ch.name!r} limits current_a [{ilo:g}, {ihi:g}] A exceed"
                f" {spec.rating} ({spec.rated_current_a:g} A)",
            )

    def _source(self, i: int, device: str, sources: dict[str, SourceSpec]) -> SourceSpec | None:
        dev = self.cfg.devices.get(device)
        if dev is None:
            self.err(("channels", i, "source", "device"), f"unknown device {device!r}")
            return None
        spec = sources.get(device)
        if spec is None:
            kinds = type(self.cfg).device_kinds
            nouns = list(dict.fromkeys(k.source_noun for k in kinds if k.source_noun))
            self.err(
                ("channels", i, "source", "device"),
                f"device {device!r} ({dev.driver}) cannot drive a channel;"
                f" use {' or '.join(nouns) if nouns else 'a device that can'}",
            )
        return spec

    def _channel_tags(self, i: int, ch: ChannelConfig) -> None:
        """The channel's own tags declared, its contactor a relay output."""
        names = self.tag_index
        for field in ("temperature_tag", "voltage_tag", "current_tag", "contactor_tag"):
            ref = getattr(ch, field)
            if ref is not None and ref not in names:
                self.err(
                    ("channels", i, field), f"{field} {ref!r} is not a tag declared under tags:"
                )
        if ch.contactor_tag in names:
            m = self.cfg.tags[names[ch.contactor_tag]]
            dev = self.cfg.devices.get(m.device)
            info = dev.points().get(m.point) if dev is not None else None
            if info is None or not _is_relay(info):
                self.err(
                    ("channels", i, "contactor_tag"),
                    f"contactor_tag {ch.contactor_tag!r} must map a relay output (slotN.doK)",
                )

    def _channel_refs(self, i: int, ch: ChannelConfig) -> None:
        names = self.tag_index
        self._channel_tags(i, ch)
        for k, ref in enumerate(ch.permissives):
            if ref not in names:
                self.err(
                    ("channels", i, "permissives", k), f"permissive {ref!r} is not a declared tag"
                )
        if ch.contactor_feedback_tag is not None:
            self._declared(("channels", i, "contactor_feedback_tag"), ch.contactor_feedback_tag)
            if ch.contactor_tag is None:
                self.err(
                    ("channels", i, "contactor_feedback_tag"),
                    "a contactor feedback needs the contactor_tag it reads back",
                )
        for k, vc in enumerate(ch.voltage_checks):
            self._declared(("channels", i, "voltage_checks", k, "tag"), vc.tag)
        if ch.bms is not None:
            for field in ("cell_max_tag", "cell_min_tag", "temperature_tag"):
                ref = getattr(ch.bms, field)
                if ref is not None:
                    self._declared(("channels", i, "bms", field), ref)
        self._record(i, ch)

    def _record(self, i: int, ch: ChannelConfig) -> None:
        """A ``record:`` list names declared tags (or the channel's own recordable ones),
        each once, under headers that differ."""
        labels: set[str] = set()
        tags: set[str] = set()
        own = {f"{ch.name}.{f}" for f in CHANNEL_RECORDABLE}
        for k, entry in enumerate(ch.record or []):
            at: Path_ = ("channels", i, "record", k)
            tag = entry.tag if isinstance(entry, RecordColumn) else entry
            if isinstance(entry, RecordColumn):
                at = (*at, "tag")
            if tag not in self.tag_index and tag not in own:
                allowed = ", ".join(sorted(own))
                self.err(
                    at,
                    f"record: {tag!r} is not a tag declared under tags: (nor one of the"
                    f" channel's own: {allowed})",
                )
                continue
            if tag in tags:
                self.err(at, f"record: {tag!r} is listed twice")
                continue
            tags.add(tag)
            label = _column(self.cfg, ch, tag).label if isinstance(entry, str) else entry.label
            if label in labels:
                self.err(("channels", i, "record", k), f"record: header {label!r} used twice")
            labels.add(label)

    def _declared(self, path: Path_, ref: str) -> bool:
        if ref in self.tag_index:
            return True
        self.err(path, f"{ref!r} is not a tag declared under tags:")
        return False

    def _is_output(self, ref: str) -> bool:
        m = self.cfg.tags[self.tag_index[ref]]
        dev = self.cfg.devices.get(m.device)
        info = dev.points().get(m.point) if dev is not None else None
        return info is not None and _is_relay(info)

    # --- the bench's safety: e-stop, interlocks, heartbeat -------------------------------
    # --- modbus_server: explicit addresses that fit (config/modbusmap.py) ---------------
    def modbus_server(self) -> None:
        for where, msg, at_key in explicit_problems(self.cfg):
            self.err(where, msg, at_key=at_key)

    def safety(self) -> None:
        s = self.cfg.safety
        if s.estop is not None:
            self._declared(("safety", "estop", "tag"), s.estop.tag)
            relay = s.estop.relay_tag
            at: Path_ = ("safety", "estop", "relay_tag")
            if relay is not None and self._declared(at, relay) and not self._is_output(relay):
                self.err(at, f"relay_tag {relay!r} must map a relay output (slotN.doK)")
        channels = {c.name for c in self.cfg.channels}
        seen: set[str] = set()
        for k, il in enumerate(s.interlocks):
            if il.id in seen:
                self.err(("safety", "interlocks", k, "id"), f"duplicate interlock id {il.id!r}")
            seen.add(il.id)
            self._declared(("safety", "interlocks", k, "tag"), il.tag)
            for j, name in enumerate(il.channels or []):
                if name not in channels:
                    known = ", ".join(sorted(channels)) or "none"
                    self.err(
                        ("safety", "interlocks", k, "channels", j),
                        f"unknown channel {name!r} (channels: {known})",
                    )
        hb = s.heartbeat
        if hb is not None:
            at = ("safety", "heartbeat", "tag")
            if self._declared(at, hb.tag) and not self._is_output(hb.tag):
                self.err(at, f"heartbeat tag {hb.tag!r} must map a relay or digital output")

    # --- wiring: safety references of the right kind, unit and owner (config/wiring.py) ---
    def wiring(self) -> None:
        for path, msg in wiring_problems(self.cfg):
            self.err(path, msg)

    # --- the simulated plant's wiring ---------------------------------------------------
    def simulation(self) -> None:
        sim = self.cfg.simulation
        if sim is None:
            return
        relays = ("contactor", "watchdog_relay")
        for name in ("lem_current", "voltage_board", "estop_sense", "contactor_feedback", *relays):
            sp = getattr(sim, name)
            if sp is not None:
                self._sim_point(("simulation", name), sp, relay=name in relays)
        for k, sp in enumerate(sim.thermocouples):
            self._sim_point(("simulation", "thermocouples", k), sp, relay=False)
        wd, coil = sim.watchdog_relay, sim.contactor
        if (
            wd is not None
            and coil is not None
            and (wd.device, wd.point) == (coil.device, coil.point)
        ):
            path: Path_ = ("simulation", "watchdog_relay", "point")
            m = self.pos.value(path) or self.pos.nearest(path)
            self.errors.append(
                ConfigError(
                    f"the heartbeat {wd.point!r} is also the contactor coil relay; the watchdog"
                    " relay needs its own output (seed 002 §1.5: in series with the coil)",
                    self.file,
                    m.line,
                    m.col,
                )
            )

    def _sim_point(self, path: Path_, sp: SimPoint, relay: bool) -> None:
        dev = self.cfg.devices.get(sp.device)
        if dev is None:
            msg = f"unknown device {sp.device!r}"
        elif not dev.simulated:
            msg = f"device {sp.device!r} is not simulated (sim: true)"
        elif sp.point not in dev.points():
            msg = f"device {sp.device!r} has no point {sp.point!r}"
        elif relay != _is_relay(dev.points()[sp.point]):
            what = "a relay output (slotN.doK)" if relay else "an analog input"
            msg = f"{sp.point!r} must be {what}"
        else:
            return
        m = self.pos.value(path) or self.pos.nearest(path)
        self.errors.append(ConfigError(msg, self.file, m.line, m.col))


def _source_key(
    spec: SourceSpec, device: str, board: int | None, at: Path_
) -> tuple[tuple[str, int] | None, list[tuple[Path_, str]]]:
    """Which source of the device a channel takes, (device, board or -1) or None when it
    names none, and what is wrong with the choice."""
    if spec.addresses is None:
        problems = [((*at, "board"), f"{spec.noun} has no boards")] if board is not None else []
        return (device, -1), problems
    if board is None:
        first, last = spec.addresses[0], spec.addresses[-1]
        return None, [(at, f"device {device!r} needs a board: {first}..{last}")]
    if board not in spec.boards:
        boards = ", ".join(str(b) for b in spec.boards)
        return (device, board), [
            ((*at, "board"), f"device {device!r} has no board {board} (boards: {boards})")
        ]
    return (device, board), []


def _is_relay(info: PointInfo) -> bool:
    return info.direction == "out" and info.dtype == "bool"
