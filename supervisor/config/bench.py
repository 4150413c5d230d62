"""Load a bench I/O map: YAML with positions → pydantic model → cross-checks.

Structural errors come from pydantic; the checks here need the whole file (does the
device have that point? is a board owned twice?). Every error names file:line:col.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from supervisor.config.models import BenchConfig, SourceSpec
from supervisor.config.yamlpos import Positions, load_yaml, load_yaml_text, validate
from supervisor.core.driver import PointInfo
from supervisor.core.errors import ConfigError, ConfigErrors

DEVICE_STATUS_SUFFIXES = ("connected", "comm_failures")
RESERVED_PREFIXES = ("scan.", "bench.")


def load_bench(path: str | Path, model: type[BenchConfig]) -> BenchConfig:
    """Load and fully check a bench file against ``model`` (the registry's bench model);
    raises ConfigErrors listing every problem."""
    try:
        data, pos = load_yaml(path)
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    return _checked(data, pos, str(path), model)


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
    cfg = validate(model, data, pos, file)
    errors = check_bench(cfg, pos, file)
    if errors:
        raise ConfigErrors(errors)
    return cfg


def check_bench(cfg: BenchConfig, pos: Positions, file: str) -> list[ConfigError]:
    """Checks that need the whole file: does the device have that point? is a board owned
    twice? Every device kind answers for itself (``DeviceConfig`` methods)."""
    errors: list[ConfigError] = []

    def err(path: tuple[str | int, ...], msg: str, at_key: bool = False) -> None:
        m = pos.key(path) if at_key else pos.value(path)
        m = m or pos.nearest(path)
        errors.append(ConfigError(msg, file, m.line, m.col))

    for dname, dev in cfg.devices.items():
        for where, msg in dev.problems():
            err(("devices", dname, *where), f"{msg} of device {dname!r}")

    # Tag mappings: known device and point; unique names; reserved namespaces.
    channel_names = {c.name for c in cfg.channels}
    names: dict[str, int] = {}
    for i, t in enumerate(cfg.tags):
        tdev = cfg.devices.get(t.device)
        if tdev is None:
            err(
                ("tags", i, "device"),
                f"unknown device {t.device!r} (devices: {', '.join(sorted(cfg.devices))})",
            )
        elif t.point not in tdev.points():
            points = sorted(tdev.points())
            have = ", ".join(points[:12]) + (", ..." if len(points) > 12 else "")
            err(
                ("tags", i, "point"),
                f"device {t.device!r} has no point {t.point!r} (it has: {have})",
            )
        if t.name in names:
            err(("tags", i, "name"), f"duplicate tag name {t.name!r} (also tags[{names[t.name]}])")
        names.setdefault(t.name, i)
        head = t.name.split(".", 1)[0]
        if head in channel_names or t.name.startswith(RESERVED_PREFIXES):
            err(
                ("tags", i, "name"),
                f"tag name {t.name!r} is in a namespace the supervisor generates"
                f" ({head}.*); choose another name",
            )
        if head in cfg.devices and t.name.split(".", 1)[-1] in DEVICE_STATUS_SUFFIXES:
            err(("tags", i, "name"), f"tag name {t.name!r} is generated for device {head!r}")

    # Channels: unique names; source exists; one owner per board; limits within hardware.
    sources = {n: s for n, d in cfg.devices.items() if (s := d.channel_source()) is not None}
    nouns = list(dict.fromkeys(k.source_noun for k in type(cfg).device_kinds if k.source_noun))
    owners: dict[tuple[str, int], str] = {}
    ch_seen: set[str] = set()
    for i, ch in enumerate(cfg.channels):
        if ch.name in ch_seen:
            err(("channels", i, "name"), f"duplicate channel name {ch.name!r}")
        ch_seen.add(ch.name)
        if ch.name in cfg.devices:
            err(("channels", i, "name"), f"channel name {ch.name!r} is also a device name")
        src = ch.source
        cdev = cfg.devices.get(src.device)
        if cdev is None:
            err(("channels", i, "source", "device"), f"unknown device {src.device!r}")
            continue
        spec = sources.get(src.device)
        if spec is None:
            err(
                ("channels", i, "source", "device"),
                f"device {src.device!r} ({cdev.driver}) cannot drive a channel;"
                f" use {' or '.join(nouns) if nouns else 'a device that can'}",
            )
            continue
        key = _source_key(spec, src.device, src.board, ("channels", i, "source"), err)
        if key is None:
            continue
        if key in owners:
            err(
                ("channels", i, "source"),
                f"{src.device!r}{'' if key[1] < 0 else f' board {key[1]}'} is already owned"
                f" by channel {owners[key]!r} (one owner per board)",
            )
        owners.setdefault(key, ch.name)
        for field in ("temperature_tag", "voltage_tag", "current_tag", "contactor_tag"):
            ref = getattr(ch, field)
            if ref is not None and ref not in names:
                err(
                    ("channels", i, field),
                    f"{field} {ref!r} is not a tag declared under tags:",
                )
        if ch.contactor_tag in names:
            m = cfg.tags[names[ch.contactor_tag]]
            info = cfg.devices[m.device].points().get(m.point) if m.device in cfg.devices else None
            if info is None or info.direction != "out" or info.dtype != "bool":
                err(
                    ("channels", i, "contactor_tag"),
                    f"contactor_tag {ch.contactor_tag!r} must map a relay output (slotN.doK)",
                )
        for k, ref in enumerate(ch.permissives):
            if ref not in names:
                err(("channels", i, "permissives", k), f"permissive {ref!r} is not a declared tag")
        lo, hi = ch.limits.current_a
        if spec.max_current_a is not None and max(-lo, hi) > spec.max_current_a:
            err(
                ("channels", i, "limits", "current_a"),
                f"{spec.noun} drives at most {spec.max_current_a} A;"
                f" limits [{lo}, {hi}] A exceed it",
            )
    for dname, spec in sources.items():
        if spec.owner_required and (dname, -1) not in owners:
            err(
                ("devices", dname),
                f"{spec.title} {dname!r} drives no channel; a channel gives it its limits",
                at_key=True,
            )
    errors.extend(_check_simulation(cfg, pos, file))
    errors.sort(key=lambda e: (e.line or 0, e.col or 0))
    return errors


def _source_key(
    spec: SourceSpec,
    device: str,
    board: int | None,
    at: tuple[str | int, ...],
    err: Callable[[tuple[str | int, ...], str], None],
) -> tuple[str, int] | None:
    """Which source of the device a channel takes (device, board or -1); None if refused."""
    if spec.addresses is None:
        if board is not None:
            err((*at, "board"), f"{spec.noun} has no boards")
        return (device, -1)
    if board is None:
        err(at, f"device {device!r} needs a board: {spec.addresses[0]}..{spec.addresses[-1]}")
        return None
    if board not in spec.boards:
        err(
            (*at, "board"),
            f"device {device!r} has no board {board}"
            f" (boards: {', '.join(str(b) for b in spec.boards)})",
        )
    return (device, board)


def _check_simulation(cfg: BenchConfig, pos: Positions, file: str) -> list[ConfigError]:
    errors: list[ConfigError] = []
    sim = cfg.simulation
    if sim is None:
        return errors

    def check(path: tuple[str | int, ...], sp: object, relay: bool) -> None:
        device = getattr(sp, "device", "")
        point = getattr(sp, "point", "")
        m = pos.value(path) or pos.nearest(path)
        dev = cfg.devices.get(device)
        if dev is None:
            errors.append(ConfigError(f"unknown device {device!r}", file, m.line, m.col))
        elif not dev.simulated:
            errors.append(
                ConfigError(f"device {device!r} is not simulated (sim: true)", file, m.line, m.col)
            )
        elif point not in dev.points():
            errors.append(
                ConfigError(f"device {device!r} has no point {point!r}", file, m.line, m.col)
            )
        elif relay != _is_relay(dev.points()[point]):
            what = "a relay output (slotN.doK)" if relay else "an analog input"
            errors.append(ConfigError(f"{point!r} must be {what}", file, m.line, m.col))

    for name in ("lem_current", "voltage_board", "estop_sense", "contactor"):
        sp = getattr(sim, name)
        if sp is not None:
            check(("simulation", name), sp, relay=name == "contactor")
    for k, sp in enumerate(sim.thermocouples):
        check(("simulation", "thermocouples", k), sp, relay=False)
    return errors


def _is_relay(info: PointInfo) -> bool:
    return info.direction == "out" and info.dtype == "bool"
