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

import math
from collections.abc import Iterable, Mapping
from fractions import Fraction
from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from supervisor.config.text import Layout, Row, decode_text, decode_yaml, read_table
from supervisor.config.yamledit import YamlText, flow_mapping, yaml_float
from supervisor.config.yamlpos import Path_
from supervisor.core.errors import ConfigError, ConfigErrors
from supervisor.devices.chadeche.config import ChadecheDevice
from supervisor.devices.registry import load_bench_text

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


def _reading(text: str, layout: Layout) -> float | None:
    value = layout.number(text)
    return value if value is not None and math.isfinite(value) else None


def _pair(row: Row, layout: Layout, file: str, *, header: bool) -> tuple[float, float] | None:
    """A row's two numbers; None for a header line; a ConfigError at the bad cell."""
    cells = [c for c in row.cells if c.text]  # "0;;0,1": an empty cell is no field
    values = [_reading(c.text, layout) for c in cells]
    if len(cells) == 2 and values[0] is not None and values[1] is not None:
        return values[0], values[1]
    if header and any(v is None for v in values):
        return None
    if len(cells) != 2:
        col = cells[2].col if len(cells) > 2 else row.end_col
        raise ConfigError(f"expected 2 numbers, found {len(cells)} fields", file, row.line, col)
    bad = cells[0] if values[0] is None else cells[1]
    raise ConfigError(f"{bad.text!r} is not a number", file, row.line, bad.col)


def read_pairs_csv(path: str | Path) -> tuple[list[float], list[float]]:
    """Two numeric columns → ``(first column, second column)``.

    Separators: tab or ``;`` (then a ``,`` is a decimal comma), else ``,``, else blanks
    (:func:`supervisor.config.text.read_table`). A first line that is not numeric is a
    header; blank lines and ``#`` lines are skipped. UTF-8 or CP1252. Errors name file,
    line and column.
    """
    file = str(path)
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read readings: {exc.strerror or exc}", file) from None
    layout, rows = read_table(decode_text(data, file), file, blanks=True, comments=True)
    first: list[float] = []
    second: list[float] = []
    for k, row in enumerate(rows):
        pair = _pair(row, layout, file, header=k == 0)
        if pair is not None:
            first.append(pair[0])
            second.append(pair[1])
    if not first:
        raise ConfigError("no readings (expected lines of two numbers)", file)
    return first, second


# --------------------------------------------------------------------------------------------
# Writing the I/O map


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


def _chadeche_boards(doc: YamlText, device: str) -> SequenceNode:
    """The ``boards:`` list of Chadèche ``device``."""
    if not isinstance(doc.root, MappingNode):
        raise ConfigError("an I/O map is a mapping (bench:, devices:, ...)", doc.file, 1, 1)
    devices = doc.node(("devices",))
    if not isinstance(devices, MappingNode):
        raise doc.error(doc.root, "no 'devices:' mapping in this I/O map")
    dev_key = doc.key(("devices", device))
    if dev_key is None:
        known = ", ".join(str(k.value) for k, _ in devices.value)
        where = doc.key(("devices",)) or devices
        raise doc.error(where, f"no device {device!r} in devices: (have: {known})")
    driver = doc.node(("devices", device, "driver"))
    if not isinstance(driver, ScalarNode) or driver.value != "chadeche":
        got = driver.value if isinstance(driver, ScalarNode) else "none"
        raise doc.error(
            dev_key,
            f"device {device!r} has driver {got!r}: only Chadèche boards have a calibration",
        )
    boards = doc.node(("devices", device, "boards"))
    if not isinstance(boards, SequenceNode):
        raise doc.error(dev_key, f"device {device!r} has no 'boards:' list")
    return boards


def _is_address(node: Node | None, board: int) -> bool:
    try:
        return isinstance(node, ScalarNode) and yaml.safe_load(node.value) == board
    except yaml.YAMLError:
        return False


def _board_index(doc: YamlText, device: str, board: int) -> int:
    """Index in ``boards:`` of the board at ``address: board``, refused if shared."""
    boards = _chadeche_boards(doc, device)
    items: list[Node] = boards.value
    addresses = [doc.node(("devices", device, "boards", i, "address")) for i in range(len(items))]
    matches = [i for i, a in enumerate(addresses) if _is_address(a, board)]
    if not matches:
        known = ", ".join(str(a.value) for a in addresses if a is not None) or "none"
        boards_key = doc.key(("devices", device, "boards")) or boards
        raise doc.error(
            boards_key, f"device {device!r} has no board with address {board} (addresses: {known})"
        )
    where = f"device {device!r}, board {board}"
    if len(matches) > 1:
        raise doc.error(items[matches[1]], f"{where}: the address appears twice")
    path = ("devices", device, "boards", matches[0])
    node = items[matches[0]]
    if doc.shared(node) or doc.node((*path, "<<")) is not None:
        raise doc.error(node, f"{where}: the board is shared (anchor/alias or '<<'); edit by hand")
    return matches[0]


def _check_own_calibration(
    doc: YamlText, board_path: Path_, values: Mapping[str, str], where: str
) -> None:
    """Refuse a calibration that other boards share, or values that are not plain numbers."""
    board = doc.node(board_path)
    cal = doc.node((*board_path, "calibration"))
    assert board is not None and cal is not None
    inside = board.start_mark.index <= cal.start_mark.index < board.end_mark.index
    merged = doc.node((*board_path, "calibration", "<<")) is not None
    if doc.shared(cal) or not inside or merged:
        raise doc.error(
            cal, f"{where}: the calibration is shared (anchor/alias or '<<'); edit by hand"
        )
    for key in values:
        node = doc.node((*board_path, "calibration", key))
        if node is not None and (not isinstance(node, ScalarNode) or doc.shared(node)):
            raise doc.error(node, f"{where}: {key} is not a plain number; edit by hand")


def _edit(doc: YamlText, device: str, board: int, values: Mapping[str, float]) -> int:
    """Splice ``values`` into the board's calibration; returns its index in ``boards:``."""
    index = _board_index(doc, device, board)
    board_path: Path_ = ("devices", device, "boards", index)
    cal_path: Path_ = (*board_path, "calibration")
    texts = {k: yaml_float(v) for k, v in values.items()}
    cal = doc.node(cal_path)
    if cal is None:  # one `calibration: {...}` after the address
        doc.add_mapping(board_path, "calibration", texts, after="address")
    elif isinstance(cal, ScalarNode) and cal.tag.endswith(":null"):  # `calibration:` or `~`
        doc.set_scalar(cal_path, flow_mapping(texts))
    elif not isinstance(cal, MappingNode):
        raise doc.error(cal, f"device {device!r}, board {board}: calibration is not a mapping")
    else:
        _check_own_calibration(doc, board_path, texts, f"device {device!r}, board {board}")
        doc.set_scalars(cal_path, texts)
    return index


def _check_edit(
    old: str, new: str, file: str, device: str, board: int, index: int, values: dict[str, float]
) -> None:
    """Load the edited map like ``supervisor check``; nothing is written if it is refused."""
    try:
        cfg = load_bench_text(new, file)
    except ConfigErrors as exc:
        load_bench_text(old, file)  # already broken before the edit: report that as it is
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
    for k, v in values.items():
        if getattr(got, k) != v:  # pragma: no cover - yaml_float round-trips exactly
            raise ConfigError(f"device {device!r}, board {board}: {k} did not round-trip", file)


def _replace_file(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, then rename it over ``path``:
    a crash leaves the old map or the new one, never half of one."""
    tmp = path.with_name(f".{path.name}.calibrate.tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_calibration(
    io_map_path: str | Path, device: str, board: int, values: Mapping[str, float]
) -> None:
    """Set ``values`` (some of :data:`CALIBRATION_KEYS`) in the calibration of ``board`` of
    Chadèche ``device`` in an I/O map, editing the text in place.

    Only the numbers concerned change (or one ``calibration: {...}`` line / one key line is
    added); comments, the BOM, the line ends and every other byte stay. The result is checked
    like :func:`supervisor.config.bench.load_bench` before it replaces the file (atomically);
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
    decoded = decode_yaml(data, file)
    try:
        doc = YamlText(decoded.text, file)  # YAML syntax first, reported the usual way
    except ConfigError as exc:
        raise ConfigErrors([exc]) from None
    index = _edit(doc, device, board, vals)
    new_text = doc.edited()
    _check_edit(decoded.text, new_text, file, device, board, index, vals)
    _replace_file(path, decoded.encode(new_text))
