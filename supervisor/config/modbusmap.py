"""Where the Modbus register map puts each tag, from the I/O map alone (ADR 0031).

The layout is a pure function of the I/O map, so that ``supervisor check`` refuses a bad
explicit address before anything runs and ``supervisor modbus map`` prints the same map
the server serves. ``supervisor.publish.modbus.regmap.plan`` turns these slots into the
register map's points (units, code tables, what a client may write) from the tag database.

Every table (coils, discrete inputs, holding registers, input registers) has the same
areas, 0-based PDU addresses::

    0       the bench block      status, heartbeat, refusal, scan figures  (100)
    100     channel k's block    at 100 + 100·k, k = its place in channels:  (100 each)
    10000   device d's block     at 10000 + 10·d, d = its place in devices:  (10 each)
    20000   the I/O map's tags   in the order of tags:, each after the one before
    40000   never generated      where explicit addresses are best put

A block's fields are a fixed list that only ever grows at its end; a float takes two
registers at an even address (the next even one: a 16-bit field before it may leave a
hole). An explicit address (``modbus_server.addresses``) moves its tag out of its
generated slot (a hole is left: no other tag moves) into the same table.

Tables and kinds are named by the values of ``regmap.Table`` and ``regmap.Kind`` (this
layer sits below the publishers; a test holds the two spellings equal).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Final

from supervisor.config.models import BenchConfig

__all__ = [
    "BENCH_FIELDS",
    "CHANNEL_BASE",
    "CHANNEL_BLOCK",
    "CHANNEL_FIELDS",
    "DEVICE_BASE",
    "DEVICE_BLOCK",
    "DEVICE_FIELDS",
    "IO_MAP_BASE",
    "MAX_ADDRESS",
    "Slot",
    "blocks",
    "explicit_problems",
    "layout",
]

COIL: Final = "coil"
DI: Final = "discrete_input"
HR: Final = "holding_register"
IR: Final = "input_register"
TABLES: Final = (COIL, DI, HR, IR)

FLOAT32: Final = "float32"
INT16: Final = "int16"
UINT16: Final = "uint16"
BOOL: Final = "bool"
CODE: Final = "code"
STATUS: Final = "status"
HEARTBEAT: Final = "heartbeat"
REFUSAL: Final = "refusal"
KINDS: Final = (FLOAT32, INT16, UINT16, BOOL, CODE, STATUS, HEARTBEAT, REFUSAL)

MAX_ADDRESS: Final = 65535
BENCH_BLOCK: Final = 100
CHANNEL_BASE: Final = 100
CHANNEL_BLOCK: Final = 100
MAX_CHANNELS: Final = 99  # 100 + 99·100 = 10000: the devices' area
DEVICE_BASE: Final = 10000
DEVICE_BLOCK: Final = 10
MAX_DEVICES: Final = 1000  # 10000 + 1000·10 = 20000: the I/O map's area
IO_MAP_BASE: Final = 20000
EXPLICIT_BASE: Final = 40000
"""Never generated: 10 000 tags of an I/O map (config ``MAX_IO_MAP_TAGS``) as floats end at
39 999."""

Field = tuple[str, str]
"""(a tag's suffix after ``<channel>.`` — or its full name in the bench block —, its kind);
a STATUS, HEARTBEAT or REFUSAL register has no tag ("")."""

# The contract: these lists only ever grow at their end (ADR 0031 has them with offsets).
BENCH_FIELDS: Final[dict[str, tuple[Field, ...]]] = {
    IR: (
        ("", STATUS),
        ("", HEARTBEAT),
        ("", REFUSAL),
        ("scan.count", UINT16),  # modulo 65536
        ("scan.period_s", FLOAT32),
        ("scan.duration_s", FLOAT32),
        ("scan.duration_max_s", FLOAT32),
        ("scan.jitter_s", FLOAT32),
        ("scan.overruns", UINT16),
        ("scan.logic_errors", UINT16),
        ("scan.stalls", UINT16),
        ("scan.stall_s", FLOAT32),
        ("scan.stall_max_s", FLOAT32),
    ),
}
CHANNEL_FIELDS: Final[dict[str, tuple[Field, ...]]] = {
    IR: (
        ("", STATUS),
        ("state", CODE),  # the power stage: off, idle, charging, discharging, faulted
        ("chain.state", CODE),  # the test's state by its OPC UA (PackML) number
        ("chain.step_index", UINT16),
        ("voltage", FLOAT32),
        ("current", FLOAT32),
        ("temperature", FLOAT32),
        ("power", FLOAT32),
        ("chain.charge_ah", FLOAT32),  # the test's charge (the display's figure)
        ("charge_ah", FLOAT32),  # the channel's net counter
        ("charged_ah", FLOAT32),
        ("discharged_ah", FLOAT32),
        ("energy_wh", FLOAT32),
        ("charged_wh", FLOAT32),
        ("discharged_wh", FLOAT32),
        ("chain.step_time", FLOAT32),
        ("chain.test_time", FLOAT32),
        ("chain.progress", FLOAT32),
        ("chain.eta_s", FLOAT32),
        ("chain.cycle", UINT16),
        ("fault_action", CODE),
        ("current_cmd", FLOAT32),
        ("voltage_cmd", FLOAT32),
        ("auto_current", FLOAT32),
        ("auto_voltage", FLOAT32),
        ("limit.charge_a", FLOAT32),
        ("limit.discharge_a", FLOAT32),
        ("chain.internal_resistance", FLOAT32),
    ),
    HR: (
        ("manual_current", FLOAT32),
        ("command", CODE),
        ("mode", CODE),
    ),
    COIL: (
        ("enable", BOOL),
        ("ack", BOOL),
    ),
    DI: (
        ("armed", BOOL),
        ("clamped", BOOL),
        ("auto_active", BOOL),
        ("output_cmd", BOOL),
        ("output_fb", BOOL),
    ),
}
DEVICE_FIELDS: Final[dict[str, tuple[Field, ...]]] = {
    IR: (("comm_failures", UINT16),),
    DI: (("connected", BOOL),),
}


@dataclass(frozen=True, slots=True)
class Slot:
    """A tag's (or a status register's) place: table, 0-based address, kind."""

    table: str
    address: int
    kind: str
    tag: str  # "" for STATUS, HEARTBEAT, REFUSAL
    channel: str = ""  # the channel whose block holds it ("" elsewhere)
    scale: float = 1.0  # a float as INT16 (``modbus_server.scale``): raw = round(value × scale)

    @property
    def words(self) -> int:
        return 2 if self.kind == FLOAT32 else 1

    @property
    def end(self) -> int:
        """The last address it takes."""
        return self.address + self.words - 1


def _aligned(address: int, kind: str) -> int:
    """A float's address: the next even one."""
    return address + (address & 1) if kind == FLOAT32 else address


def blocks(
    fields: dict[str, tuple[Field, ...]], base: int = 0, prefix: str = "", channel: str = ""
) -> Iterator[Slot]:
    """A block's slots in every table from its field lists (a float on the next even
    address)."""
    for table, table_fields in fields.items():
        at = 0
        for suffix, kind in table_fields:
            at = _aligned(at, kind)
            yield Slot(table, base + at, kind, prefix + suffix if suffix else "", channel)
            at += 2 if kind == FLOAT32 else 1


def io_map_kind(cfg: BenchConfig, index: int) -> tuple[str, str] | None:
    """(table, kind) of ``tags[index]``, None when the map cannot carry it (a text). The
    I/O map's tags are read-only: a boolean is a discrete input, a number an input
    register (a float as FLOAT32, an integer as INT16)."""
    t = cfg.tags[index]
    if t.threshold is not None:
        return DI, BOOL
    dev = cfg.devices.get(t.device)
    info = dev.points().get(t.point) if dev is not None else None
    dtype = info.dtype if info is not None else "float"
    if dtype == "bool":
        return DI, BOOL
    if dtype == "float":
        return IR, FLOAT32
    if dtype == "int":
        return IR, INT16
    return None


def generated(cfg: BenchConfig, *, scaled: bool = True) -> list[Slot]:
    """Every generated slot, before explicit addresses move any (a channel or device past
    the areas' capacity is left out: ``explicit_problems`` refuses that map); ``scaled``:
    with ``modbus_server.scale`` applied."""
    out = list(blocks(BENCH_FIELDS, 0))
    for k, ch in enumerate(cfg.channels[:MAX_CHANNELS]):
        out += blocks(CHANNEL_FIELDS, CHANNEL_BASE + CHANNEL_BLOCK * k, ch.name + ".", ch.name)
    for d, dev in enumerate(list(cfg.devices)[:MAX_DEVICES]):
        out += blocks(DEVICE_FIELDS, DEVICE_BASE + DEVICE_BLOCK * d, dev + ".")
    at = dict.fromkeys(TABLES, IO_MAP_BASE)
    for i, t in enumerate(cfg.tags):
        placed = io_map_kind(cfg, i)
        if placed is None:
            continue
        table, kind = placed
        address = _aligned(at[table], kind)
        out.append(Slot(table, address, kind, t.name))
        at[table] = address + (2 if kind == FLOAT32 else 1)
    # A float scaled to 16 bits keeps the first register of its place (the second stays
    # empty): choosing the encoding moves nothing.
    scales = cfg.modbus_server.scale if cfg.modbus_server is not None and scaled else {}
    return [
        replace(s, kind=INT16, scale=scales[s.tag]) if s.tag in scales and s.kind == FLOAT32 else s
        for s in out
    ]


def _explicit(cfg: BenchConfig) -> dict[str, int]:
    return dict(cfg.modbus_server.addresses) if cfg.modbus_server is not None else {}


def layout(cfg: BenchConfig) -> list[Slot]:
    """The map's slots, explicit addresses applied, sorted by table and address. Assumes a
    map ``explicit_problems`` accepts (a tag it does not place is left out)."""
    explicit = _explicit(cfg)
    out: list[Slot] = []
    for s in generated(cfg):
        if s.tag in explicit:
            out.append(replace(s, address=explicit[s.tag]))
        else:
            out.append(s)
    return sorted(out, key=lambda s: (TABLES.index(s.table), s.address))


def explicit_problems(cfg: BenchConfig) -> list[tuple[tuple[str | int, ...], str, bool]]:
    """What ``supervisor check`` refuses in ``modbus_server``: (where, message, at the key)
    — a channel or device past its area, an explicit address for a tag the map does not
    place, beyond 65535 (a float's second register too), a float on an odd address, two
    explicit addresses that overlap, one on a generated tag's place."""
    if cfg.modbus_server is None:
        return []
    problems: list[tuple[tuple[str | int, ...], str, bool]] = []
    where: tuple[str | int, ...] = ("modbus_server",)
    if len(cfg.channels) > MAX_CHANNELS:
        problems.append(
            (
                where,
                f"the Modbus map holds {MAX_CHANNELS} channels at most, not {len(cfg.channels)}",
                True,
            )
        )
    if len(cfg.devices) > MAX_DEVICES:
        problems.append(
            (
                where,
                f"the Modbus map holds {MAX_DEVICES} devices at most, not {len(cfg.devices)}",
                True,
            )
        )
    explicit = _explicit(cfg)
    slots = generated(cfg)
    by_tag = {s.tag: s for s in slots if s.tag}
    # Who takes each (table, address): the generated slots that stay, then each explicit
    # one accepted (an index: a map may have thousands of both).
    taken = {w: (s, False) for s in slots if s.tag not in explicit for w in _places(s)}
    for tag, address in explicit.items():
        problem = _explicit_problem(by_tag.get(tag), tag, address, taken)
        if problem is not None:
            problems.append((("modbus_server", "addresses", tag), *problem))
    floats = {s.tag for s in generated(cfg, scaled=False) if s.kind == FLOAT32}
    for tag in cfg.modbus_server.scale:
        if tag not in floats:
            problems.append(
                (
                    ("modbus_server", "scale", tag),
                    f"modbus_server.scale: {tag!r} is not a float the Modbus map places"
                    " (only a float is scaled to a 16-bit integer)",
                    True,
                )
            )
    return problems


def _places(s: Slot) -> list[tuple[str, int]]:
    return [(s.table, a) for a in range(s.address, s.end + 1)]


def _explicit_problem(
    s: Slot | None, tag: str, address: int, taken: dict[tuple[str, int], tuple[Slot, bool]]
) -> tuple[str, bool] | None:
    """Why ``tag`` may not be at ``address`` (message, at the key), or None: then it takes
    its place in ``taken``."""
    if s is None:
        return (
            f"modbus_server.addresses: {tag!r} is not a tag the Modbus map places (a"
            " channel's or device's field, a scan figure, or a number or boolean of tags:;"
            " `supervisor modbus map`)",
            True,
        )
    mine = replace(s, address=address)
    if mine.end > MAX_ADDRESS:
        return f"{tag}: a float at {address} ends beyond 65535", False
    if s.kind == FLOAT32 and address % 2:
        return (
            f"{tag}: a float at the odd address {address}; floats take an even address"
            " (panels that read 32-bit values as register pairs need it)",
            False,
        )
    clash = next((taken[w] for w in _places(mine) if w in taken), None)
    if clash is not None:
        other, moved = clash
        what = f"the explicit address of {other.tag!r}" if moved else _name(other)
        return f"{tag} at {_words(mine)} overlaps {what}", False
    taken.update(dict.fromkeys(_places(mine), (mine, True)))
    return None


def _words(s: Slot) -> str:
    what = s.table.replace("_", " ")
    if s.words == 2:
        return f"{what}s {s.address}-{s.end}"
    return f"{what} {s.address}"


def _name(s: Slot) -> str:
    """How a message names a generated slot."""
    if s.tag:
        return f"the generated place of {s.tag!r} ({_words(s)})"
    owner = f"channel {s.channel}" if s.channel else "the bench"
    return f"the {s.kind} register of {owner} ({_words(s)})"
