"""Chadèche board calibration (seed 000 §III.F): staircase readings → a·x + b → the I/O map.

1. Current (``-1`` slope, ``-2`` offset): run ``recipes/current-calibration.yaml`` into a
   good ammeter, note the measured current for each setpoint, and fit the **setpoint as a
   function of the measured current** (§III.F.1). The driver then commands
   ``slope·I + offset`` (mA) to get a true current I: ``current_slope``,
   ``current_offset_ma``.
2. Voltage (``-s`` slope, ``-o`` offset): run ``recipes/voltage-calibration.yaml`` into a
   5–10 Ω / 2 W resistor with a good voltmeter across it, note the meter and the ADC (shown)
   voltages, and fit the **voltmeter voltage as a function of the ADC voltage** (§III.F.2):
   ``voltage_slope``, ``voltage_offset_v``.

Run both with the board's calibration at 1 / 0 (the defaults). :func:`write_calibration`
puts the result in the I/O map with the smallest text edit: comments, layout and every
other byte of the file stay as they were.
"""

from __future__ import annotations

import codecs
import math
import re
from collections.abc import Iterable, Mapping
from fractions import Fraction
from pathlib import Path
from typing import Any

import yaml
from yaml.error import MarkedYAMLError
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from supervisor.config.yamlpos import load_yaml_text
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import ChadecheDevice
from supervisor.devices.registry import load_bench_text
from supervisor.importers.chadeche import yaml_float

__all__ = [
    "CALIBRATION_KEYS",
    "calibrate_current",
    "calibrate_voltage",
    "fit_line",
    "read_pairs_csv",
    "write_calibration",
]

CALIBRATION_KEYS = ("current_slope", "current_offset_ma", "voltage_slope", "voltage_offset_v")
_SLOPES = ("current_slope", "voltage_slope")


# --------------------------------------------------------------------------------------------
# Fits


def fit_line(xs: Iterable[float], ys: Iterable[float]) -> tuple[float, float, float]:
    """Least-squares ``y = a·x + b``; returns ``(a, b, r²)``.

    Computed in exact rational arithmetic, then rounded once: points on an exact line give
    that line back to the last bit the inputs allow. Needs at least two distinct x values.
    """
    x = [float(v) for v in xs]
    y = [float(v) for v in ys]
    if len(x) != len(y):
        raise ValueError(f"a line fit needs as many x as y values (got {len(x)} x, {len(y)} y)")
    bad = [v for v in (*x, *y) if not math.isfinite(v)]
    if bad:
        raise ValueError(f"a line fit needs finite numbers (got {bad[0]!r})")
    distinct = len(set(x))
    if distinct < 2:
        raise ValueError(
            f"a line fit needs at least 2 distinct x values (got {len(x)} point(s), "
            f"{distinct} distinct x)"
        )
    fx = [Fraction(v) for v in x]
    fy = [Fraction(v) for v in y]
    n = len(fx)
    mx = sum(fx, Fraction(0)) / n
    my = sum(fy, Fraction(0)) / n
    sxx = sum(((v - mx) ** 2 for v in fx), Fraction(0))
    sxy = sum(((u - mx) * (v - my) for u, v in zip(fx, fy, strict=True)), Fraction(0))
    syy = sum(((v - my) ** 2 for v in fy), Fraction(0))
    a = sxy / sxx
    b = my - a * mx
    r2 = 1 - (syy - a * sxy) / syy if syy else Fraction(1)
    return float(a), float(b), float(r2)


def calibrate_current(
    setpoints_ma: Iterable[float], measured_ma: Iterable[float]
) -> tuple[float, float]:
    """``(current_slope, current_offset_ma)`` — the seed's ``-1`` and ``-2``.

    Fits the setpoint as a function of the measured current (seed §III.F.1), both in mA, so
    the offset is in mA.
    """
    a, b, _ = fit_line(measured_ma, setpoints_ma)
    if a <= 0:
        raise ValueError(
            f"current fit slope {a:g} <= 0: are the setpoint and measured columns swapped, "
            "or the ammeter reversed?"
        )
    return a, b


def calibrate_voltage(adc_v: Iterable[float], meter_v: Iterable[float]) -> tuple[float, float]:
    """``(voltage_slope, voltage_offset_v)`` — the seed's ``-s`` and ``-o``.

    Fits the voltmeter voltage as a function of the ADC (displayed) voltage (§III.F.2).
    """
    a, b, _ = fit_line(adc_v, meter_v)
    if a <= 0:
        raise ValueError(
            f"voltage fit slope {a:g} <= 0: are the ADC and meter columns swapped, "
            "or the voltmeter reversed?"
        )
    return a, b


# --------------------------------------------------------------------------------------------
# Readings


def _decode(data: bytes) -> str:
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("cp1252", errors="replace")


def _number(text: str, decimal_comma: bool) -> float | None:
    t = text.strip()
    if decimal_comma:
        t = t.replace(",", ".")
    try:
        v = float(t)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def read_pairs_csv(path: str | Path) -> tuple[list[float], list[float]]:
    """Two numeric columns → ``(first column, second column)``.

    Separators: tab or ``;`` (then a ``,`` is a decimal comma), else ``,``, else blanks.
    A first line that is not numeric is a header; blank lines and ``#`` lines are skipped.
    UTF-8 or CP1252. Errors name file, line and column.
    """
    file = str(path)
    try:
        text = _decode(Path(path).read_bytes())
    except OSError as exc:
        raise ConfigError(f"cannot read readings: {exc.strerror or exc}", file) from None
    first: list[float] = []
    second: list[float] = []
    seen_line = False
    for ln, raw in enumerate(re.split(r"\r\n|\r|\n", text), start=1):
        line = raw.rstrip()
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if "\t" in line or ";" in line:
            sep: str | None = "\t" if "\t" in line else ";"
            comma = True
        elif "," in line:
            sep, comma = ",", False
        else:
            sep, comma = None, False
        cells: list[tuple[str, int]] = []
        if sep is None:
            cells = [(m.group(), m.start() + 1) for m in re.finditer(r"\S+", line)]
        else:
            pos = 0
            for part in line.split(sep):
                cells.append((part, pos + 1 + (len(part) - len(part.lstrip()))))
                pos += len(part) + 1
            cells = [c for c in cells if c[0].strip()]
        values = [_number(c, comma) for c, _ in cells]
        header = not seen_line
        seen_line = True
        if len(cells) == 2 and values[0] is not None and values[1] is not None:
            first.append(values[0])
            second.append(values[1])
            continue
        if header and any(v is None for v in values):
            continue  # a header line
        if len(cells) != 2:
            col = cells[2][1] if len(cells) > 2 else len(line) + 1
            raise ConfigError(f"expected 2 numbers, found {len(cells)} fields", file, ln, col)
        k = 0 if values[0] is None else 1
        raise ConfigError(f"{cells[k][0].strip()!r} is not a number", file, ln, cells[k][1])
    if not first:
        raise ConfigError("no readings (expected lines of two numbers)", file)
    return first, second


# --------------------------------------------------------------------------------------------
# Writing the I/O map


def _key(mapping: MappingNode, name: str) -> tuple[Node, Node] | None:
    for k, v in mapping.value:
        if isinstance(k, ScalarNode) and k.value == name:
            return k, v
    return None


def _ref_counts(root: Node) -> dict[int, int]:
    counts: dict[int, int] = {}
    stack = [root]
    while stack:
        node = stack.pop()
        counts[id(node)] = counts.get(id(node), 0) + 1
        if counts[id(node)] > 1:
            continue
        if isinstance(node, MappingNode):
            for k, v in node.value:
                stack += [k, v]
        elif isinstance(node, SequenceNode):
            stack += list(node.value)
    return counts


_PROPS = re.compile(r"(?:[&!][^\s,\[\]{}]*[ \t]+)*")


def _value_start(text: str, node: Node) -> int:
    """Where a scalar's own text starts (after an anchor or tag, which are kept)."""
    i: int = node.start_mark.index
    m = _PROPS.match(text, i)
    return m.end() if m else i


def _line_end(text: str, index: int) -> int:
    """Index just after the line break of the line holding ``index`` (or len(text))."""
    m = re.compile(r"\r\n|\r|\n").search(text, index)
    return m.end() if m else len(text)


def _flow(values: Mapping[str, float]) -> str:
    return "{" + ", ".join(f"{k}: {yaml_float(v)}" for k, v in values.items()) + "}"


def _check_values(values: Mapping[str, Any]) -> dict[str, float]:
    unknown = [k for k in values if k not in CALIBRATION_KEYS]
    if unknown:
        raise ValueError(
            f"unknown calibration key(s) {', '.join(map(repr, unknown))}; "
            f"expected: {', '.join(CALIBRATION_KEYS)}"
        )
    if not values:
        raise ValueError("no calibration values to write")
    out: dict[str, float] = {}
    for k in CALIBRATION_KEYS:
        if k in values:
            v = float(values[k])
            if not math.isfinite(v):
                raise ValueError(f"{k} must be a finite number, got {values[k]!r}")
            if k in _SLOPES and v <= 0:
                raise ValueError(f"{k} must be > 0, got {values[k]!r}")
            out[k] = v
    return out


def _edit(
    text: str, file: str, device: str, board: int, values: dict[str, float]
) -> tuple[str, int]:
    """The edited text and the index of the board in its ``boards`` list."""

    def here(node: Node, msg: str) -> ConfigError:
        return ConfigError(msg, file, node.start_mark.line + 1, node.start_mark.column + 1)

    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except MarkedYAMLError as exc:  # pragma: no cover - load_yaml_text parsed it just before
        mark = exc.problem_mark
        raise ConfigError(
            f"YAML error: {exc.problem}",
            file,
            mark.line + 1 if mark else None,
            mark.column + 1 if mark else None,
        ) from None
    if not isinstance(root, MappingNode):
        raise ConfigError("an I/O map is a mapping (bench:, devices:, ...)", file, 1, 1)
    counts = _ref_counts(root)
    where = f"device {device!r}, board {board}"

    devices = _key(root, "devices")
    if devices is None or not isinstance(devices[1], MappingNode):
        raise here(root, "no 'devices:' mapping in this I/O map")
    dev = _key(devices[1], device)
    if dev is None:
        known = ", ".join(str(k.value) for k, _ in devices[1].value)
        raise here(devices[0], f"no device {device!r} in devices: (have: {known})")
    dev_node = dev[1]
    assert isinstance(dev_node, MappingNode)
    driver = _key(dev_node, "driver")
    if driver is None or driver[1].value != "chadeche":
        got = driver[1].value if driver is not None else "none"
        raise here(
            dev[0],
            f"device {device!r} has driver {got!r}: only Chadèche boards have a calibration",
        )
    boards = _key(dev_node, "boards")
    if boards is None or not isinstance(boards[1], SequenceNode):
        raise here(dev[0], f"device {device!r} has no 'boards:' list")
    matches: list[tuple[int, MappingNode]] = []
    for idx, item in enumerate(boards[1].value):
        if isinstance(item, MappingNode):
            addr = _key(item, "address")
            if addr is not None and yaml.safe_load(addr[1].value) == board:
                matches.append((idx, item))
    if not matches:
        addresses: list[str] = []
        for item in boards[1].value:
            addr = _key(item, "address") if isinstance(item, MappingNode) else None
            if addr is not None:
                addresses.append(str(addr[1].value))
        raise here(
            boards[0],
            f"device {device!r} has no board with address {board} "
            f"(addresses: {', '.join(addresses) or 'none'})",
        )
    if len(matches) > 1:
        raise here(matches[1][1], f"{where}: the address appears twice")
    index, bnode = matches[0]
    if counts.get(id(bnode), 0) > 1 or _key(bnode, "<<") is not None:
        raise here(bnode, f"{where}: the board is shared (anchor/alias or '<<'); edit by hand")

    nl = "\r\n" if "\r\n" in text else "\n"
    edits: list[tuple[int, int, str]] = []  # (start, end, replacement)
    cal = _key(bnode, "calibration")
    if cal is None:
        addr_key, addr_val = _key(bnode, "address") or (None, None)
        assert addr_key is not None and addr_val is not None
        if bnode.flow_style:
            edits.append(
                (
                    addr_val.end_mark.index,
                    addr_val.end_mark.index,
                    f", calibration: {_flow(values)}",
                )
            )
        else:
            at = _line_end(text, addr_val.end_mark.index)
            lead = nl if at == len(text) and not text.endswith(("\n", "\r")) else ""
            indent = " " * addr_key.start_mark.column
            edits.append((at, at, f"{lead}{indent}calibration: {_flow(values)}{nl}"))
    else:
        cnode = cal[1]
        if not isinstance(cnode, MappingNode):
            if isinstance(cnode, ScalarNode) and cnode.tag.endswith(":null"):
                start = _value_start(text, cnode)
                end = cnode.end_mark.index
                if start == end:  # `calibration:` with nothing after it
                    edits.append(
                        (
                            start,
                            end,
                            f" {_flow(values)}" if text[start - 1] == ":" else _flow(values),
                        )
                    )
                else:
                    edits.append((start, end, _flow(values)))
            else:
                raise here(cnode, f"{where}: calibration is not a mapping")
        else:
            inside = bnode.start_mark.index <= cnode.start_mark.index < bnode.end_mark.index
            if counts.get(id(cnode), 0) > 1 or not inside or _key(cnode, "<<") is not None:
                raise here(
                    cnode,
                    f"{where}: the calibration is shared (anchor/alias or '<<'); edit by hand",
                )
            missing: dict[str, float] = {}
            for k, v in values.items():
                entry = _key(cnode, k)
                if entry is None:
                    missing[k] = v
                    continue
                vnode = entry[1]
                if not isinstance(vnode, ScalarNode) or counts.get(id(vnode), 0) > 1:
                    raise here(vnode, f"{where}: {k} is not a plain number; edit by hand")
                edits.append((_value_start(text, vnode), vnode.end_mark.index, yaml_float(v)))
            if missing:
                if cnode.flow_style:
                    if cnode.value:
                        last = cnode.value[-1][1].end_mark.index
                        add = "".join(f", {k}: {yaml_float(v)}" for k, v in missing.items())
                        edits.append((last, last, add))
                    else:
                        brace = text.index("{", cnode.start_mark.index) + 1
                        add = ", ".join(f"{k}: {yaml_float(v)}" for k, v in missing.items())
                        edits.append((brace, brace, add))
                else:
                    first_key = cnode.value[0][0]
                    indent = " " * first_key.start_mark.column
                    at = _line_end(text, cnode.value[-1][1].end_mark.index)
                    lead = nl if at == len(text) and not text.endswith(("\n", "\r")) else ""
                    add = "".join(f"{indent}{k}: {yaml_float(v)}{nl}" for k, v in missing.items())
                    edits.append((at, at, lead + add))
    for start, end, new in sorted(edits, reverse=True):
        text = text[:start] + new + text[end:]
    return text, index


def write_calibration(
    io_map_path: str | Path, device: str, board: int, values: Mapping[str, float]
) -> None:
    """Set ``values`` (some of :data:`CALIBRATION_KEYS`) in the calibration of ``board`` of
    Chadèche ``device`` in an I/O map, editing the text in place.

    Only the numbers concerned change (or one ``calibration: {...}`` line / one key line is
    added); comments and every other byte stay. The result is checked like
    :func:`supervisor.config.bench.load_bench` before it replaces the file (atomically);
    nothing is written when it would be refused (a map that was already broken is reported
    as it is, unless the edit is what repairs it, e.g. an empty ``calibration:``).
    Raises ConfigError/ConfigErrors naming the file (and device/board), ValueError for bad
    ``values``.
    """
    path = Path(io_map_path)
    file = str(path)
    vals = _check_values(values)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError("I/O map not found", file) from None
    except OSError as exc:
        raise ConfigError(f"cannot read I/O map: {exc.strerror or exc}", file) from None
    bom = data.startswith(codecs.BOM_UTF8)
    try:
        text = data[len(codecs.BOM_UTF8) :].decode("utf-8") if bom else data.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError("I/O map is not UTF-8", file) from None
    try:
        load_yaml_text(text, file)  # YAML syntax first, reported the usual way
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    new_text, index = _edit(text, file, device, board, vals)
    try:
        cfg = load_bench_text(new_text, file)
    except ConfigErrors as exc:
        load_bench_text(text, file)  # already broken before the edit: report that as it is
        raise ConfigErrors(  # pragma: no cover - a bug in _edit; nothing is written
            [
                ConfigError(
                    f"calibration of device {device!r}, board {board} not written: "
                    f"the edit would be refused: {e.message}",
                    e.file,
                    e.line,
                    e.col,
                )
                for e in exc.errors
            ]
        ) from None
    dev = cfg.devices[device]
    assert isinstance(dev, ChadecheDevice)
    got = dev.boards[index].calibration
    for k, v in vals.items():
        if getattr(got, k) != v:  # pragma: no cover - yaml_float round-trips exactly
            raise ConfigError(f"device {device!r}, board {board}: {k} did not round-trip", file)
    out = (codecs.BOM_UTF8 if bom else b"") + new_text.encode("utf-8")
    tmp = path.with_name(f".{path.name}.calibrate.tmp")
    try:
        tmp.write_bytes(out)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()
