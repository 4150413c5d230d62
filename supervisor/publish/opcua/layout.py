"""The address space of a bench, planned before anything is built (pure: testable without
a server).

::

    Objects/Bench         a BenchType (objecttypes.py)
      Channels/ch0 …      ChannelType: the channel's tags under friendly names (Voltage,
                          Current, …), its StateMachine (CurrentState: the test's PackML
                          state, its Number ``chain.state_code``) and its methods
      Devices/adam …      one type per kind (``Adam5000tcpDeviceType``): each device's
                          health (Connected, CommFailures) and the tags the I/O map takes
                          from its points (``estop.ok`` → EstopOk)
      Alarms/<id> …       one AlarmConditionType object per alarm (its state, severity …)
      Diagnostics         scan.*, opcua.*, retain.* (``scan.period_s`` → ScanPeriodS)
      Tags                any tag none of the above claims

One naming rule: browse names are PascalCase (``camel`` of the tag's name where no friendly
name is fixed); every variable's NodeId is ``ns=<bench namespace>;s=<tag name>`` so
``ch0.voltage`` is addressed directly; objects, methods and types have NodeIds starting
with ``/`` (a tag name never does, config ``TAG_PATTERN``), so they can never collide with a
tag.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Final, Literal

from supervisor.config.models import BenchConfig, ChannelConfig
from supervisor.tags import Access, Tag

URN_PREFIX: Final = "urn:bench-supervisor:bench:"

Kind = Literal["analog", "int", "bool", "str", "state", "statename"]
"""``statename``: a channel's StateMachine/CurrentState (its state's PackML name, written
from its number), nowhere else."""

# A channel's tags by their suffix after ``<channel>.``: the names SCADA screens use.
CHANNEL_NAMES: Final[dict[str, str]] = {
    "voltage": "Voltage",
    "current": "Current",
    "temperature": "Temperature",
    "power": "Power",
    "chain.charge_ah": "Charge",  # the test's charge (the display line's figure)
    "charge_ah": "ChargeCounter",  # the net counter, not the test's charge
    "energy_wh": "Energy",
    "mode": "Mode",
    "chain.recipe": "Recipe",
    "chain.step_index": "Step",
    "chain.step": "StepName",
    "chain.step_time": "StepTime",
    "chain.cycle": "Cycle",
    "chain.progress": "Progress",
    "chain.eta_s": "ETA",
    "chain.test_id": "TestId",
    "chain.test_time": "TestTime",
    "state": "DriveState",  # the power stage: idle, charging, discharging, faulted
    "enable": "Enable",
    "manual_current": "ManualCurrent",
}
STATE_SUFFIX: Final = "chain.state_code"
"""The chain's state as its OPC UA number (``chains/states.py::OPCUA_CODE``): the Number of
the channel's StateMachine/CurrentState."""
STATE_NAME_SUFFIX: Final = "chain.state"
"""The chain's state by its name: the channel's StateMachine/CurrentState (one variable for
the test's state, shown by its PackML name, its number beside it)."""
STATE_MACHINE: Final = "StateMachine"
MACHINE_VARIABLES: Final[tuple[tuple[str, str, Kind], ...]] = (
    (STATE_NAME_SUFFIX, "CurrentState", "statename"),
    (STATE_SUFFIX, "Number", "state"),
)
"""A channel's StateMachine: (tag suffix, browse name, kind) of CurrentState and its Number."""

DEVICE_NAMES: Final[dict[str, str]] = {"connected": "Connected", "comm_failures": "CommFailures"}
DIAGNOSTIC_PREFIXES: Final = ("scan.", "opcua.", "retain.", "alarms.")


def namespace_uri(bench: str) -> str:
    """The bench's namespace (and the server's application URI)."""
    return URN_PREFIX + bench


def camel(text: str) -> str:
    """``limit.charge_a`` → ``LimitChargeA``."""
    return "".join(p[:1].upper() + p[1:] for p in re.split(r"[._]", text) if p)


def device_type(driver: str) -> str:
    """The object type of a device of this kind: ``adam5000tcp`` → ``Adam5000tcpDeviceType``."""
    return f"{camel(driver)}DeviceType"


def unique_names(tags: Iterable[str], used: set[str] | None = None) -> dict[str, str]:
    """Each tag's browse name in one folder: ``camel`` of its name, numbered from 2 when two
    tags would share one (``a.b_c`` and ``a_b.c``)."""
    taken = set() if used is None else used
    out: dict[str, str] = {}
    for tag in tags:
        base = camel(tag)
        name, k = base, 2
        while name in taken:
            name = f"{base}{k}"
            k += 1
        taken.add(name)
        out[tag] = name
    return out


@dataclass(frozen=True, slots=True)
class Variable:
    tag: str  # the tag name: the variable's NodeId string
    browse: str
    kind: Kind
    description: str = ""
    unit: str = ""
    range: tuple[float, float] | None = None
    writable: bool = False


@dataclass(frozen=True, slots=True)
class Folder:
    node: str  # the object's NodeId string ("/Bench/Channels/ch0")
    browse: str
    description: str = ""
    folder: bool = True  # a FolderType (else a plain object)
    variables: tuple[Variable, ...] = ()
    children: tuple[Folder, ...] = ()
    channel: str = ""  # a channel object: its methods are added here
    alarm: str = ""  # an alarm object: its state variables are added here
    typedef: str = ""  # an object type of objecttypes.py ("ChannelType"); "": standard

    def walk(self) -> Iterable[Folder]:
        yield self
        for c in self.children:
            yield from c.walk()


@dataclass(frozen=True, slots=True)
class Layout:
    bench: str
    root: Folder
    channels: tuple[str, ...]
    alarms: tuple[str, ...]
    variables: dict[str, Variable] = field(default_factory=dict)  # by tag name

    @property
    def uri(self) -> str:
        return namespace_uri(self.bench)


def kind_of(tag: Tag) -> Kind:
    dtype = tag.spec.dtype
    if dtype == "float":
        return "analog"
    if dtype == "int":
        return "state" if tag.name.endswith("." + STATE_SUFFIX) else "int"
    if dtype == "bool":
        return "bool"
    return "str"


def channel_node(channel: str) -> str:
    return f"/Bench/Channels/{channel}"


def alarm_node(alarm_id: str) -> str:
    return f"/Bench/Alarms/{alarm_id}"


def device_node(device: str) -> str:
    return f"/Bench/Devices/{device}"


class _Placement:
    """The bench's tags, each placed once: the first folder to take a tag holds its variable,
    the later ones see it ``placed`` (a device's health tag is not a point of it too)."""

    def __init__(self, tags: Iterable[Tag]) -> None:
        self.tags = list(tags)
        self.by_name = {t.name: t for t in self.tags}
        self.placed: set[str] = set()

    def variable(self, tag: Tag, browse: str) -> Variable:
        """The tag's variable under ``browse``; the tag is placed."""
        self.placed.add(tag.name)
        s = tag.spec
        return Variable(
            tag.name,
            browse,
            kind_of(tag),
            s.description,
            s.unit,
            s.range,
            s.access is not Access.READ_ONLY,
        )

    def unplaced(self) -> list[Tag]:
        return [t for t in self.tags if t.name not in self.placed]


def _channel_names(prefix: str, tags: Sequence[Tag]) -> dict[str, str]:
    """The browse names of a channel's tags (``prefix`` is ``<channel>.``): the fixed
    vocabulary first, then the others by their suffix, shortest form that is still unique
    in the channel (``chain.alarm`` → ``Alarm``, else ``ChainAlarm``)."""
    names: dict[str, str] = {}
    used: set[str] = {STATE_MACHINE}
    for t in tags:
        suffix = t.name[len(prefix) :]
        if suffix in CHANNEL_NAMES:
            names[t.name] = CHANNEL_NAMES[suffix]
            used.add(CHANNEL_NAMES[suffix])
    for t in tags:
        if t.name in names:
            continue
        suffix = t.name[len(prefix) :]
        short = camel(suffix.removeprefix("chain."))
        name = short if short not in used else camel(suffix)
        k = 2
        while name in used:
            name = f"{camel(suffix)}{k}"
            k += 1
        names[t.name] = name
        used.add(name)
    return names


def _channel_folder(channel: ChannelConfig, placement: _Placement) -> Folder:
    """A channel's object: its tags under friendly names and its StateMachine."""
    ch = channel.name
    prefix = ch + "."
    mine = [t for t in placement.tags if t.name.startswith(prefix)]
    by_name = placement.by_name
    # The test's state: one state machine (its name and its number), not two variables.
    machine = [
        replace(placement.variable(by_name[prefix + suffix], browse), kind=kind)
        for suffix, browse, kind in MACHINE_VARIABLES
        if prefix + suffix in by_name
    ]
    mine = [t for t in mine if t.name not in placement.placed]
    names = _channel_names(prefix, mine)
    return Folder(
        channel_node(ch),
        ch,
        channel.description,
        folder=False,
        variables=tuple(placement.variable(t, names[t.name]) for t in mine),
        children=(
            Folder(
                f"{channel_node(ch)}/{STATE_MACHINE}",
                STATE_MACHINE,
                "The test's state (ISA-88/PackML)",
                folder=False,
                variables=tuple(machine),
                typedef="ChannelStateMachineType",
            ),
        )
        if machine
        else (),
        channel=ch,
        typedef="ChannelType",
    )


def _device_folder(cfg: BenchConfig, dev: str, placement: _Placement) -> Folder:
    """A device's object: its health, then the tags the I/O map takes from its points."""
    by_name = placement.by_name
    health = [
        placement.variable(by_name[f"{dev}.{k}"], v)
        for k, v in DEVICE_NAMES.items()
        if f"{dev}.{k}" in by_name
    ]
    own = [
        m.name
        for m in cfg.tags
        if m.device == dev and m.name in by_name and m.name not in placement.placed
    ]
    point_names = unique_names(own, {v.browse for v in health})
    points = [placement.variable(by_name[n], point_names[n]) for n in own]
    return Folder(
        device_node(dev),
        dev,
        folder=False,
        variables=tuple(health + points),
        typedef=device_type(cfg.devices[dev].driver),
    )


def plan(cfg: BenchConfig, tags: Iterable[Tag], alarms: Sequence[str] = ()) -> Layout:
    """Where each tag goes, under which browse name."""
    placement = _Placement(tags)
    by_name = placement.by_name
    channels = [c.name for c in cfg.channels]
    channel_folders = [_channel_folder(c, placement) for c in cfg.channels]
    device_folders = [_device_folder(cfg, dev, placement) for dev in cfg.devices]
    diagnostic_names = unique_names(
        t.name for t in placement.unplaced() if t.name.startswith(DIAGNOSTIC_PREFIXES)
    )
    diagnostics = [placement.variable(by_name[n], b) for n, b in diagnostic_names.items()]
    rest_names = unique_names(t.name for t in placement.unplaced())
    rest = [placement.variable(by_name[n], b) for n, b in rest_names.items()]
    alarm_folders = [Folder(alarm_node(a), a, folder=False, alarm=a) for a in alarms]
    children = [
        Folder(
            "/Bench/Channels", "Channels", "The bench's channels", children=tuple(channel_folders)
        ),
        Folder(
            "/Bench/Devices",
            "Devices",
            "Devices: health and points",
            children=tuple(device_folders),
        ),
        Folder(
            "/Bench/Alarms",
            "Alarms",
            "Every alarm of the bench (ISA-18.2)",
            children=tuple(alarm_folders),
        ),
        Folder(
            "/Bench/Diagnostics",
            "Diagnostics",
            "Scan and publisher figures",
            variables=tuple(diagnostics),
        ),
    ]
    if rest:
        children.append(Folder("/Bench/Tags", "Tags", "Other tags", variables=tuple(rest)))
    root = Folder(
        "/Bench",
        "Bench",
        cfg.description or cfg.bench,
        folder=False,
        children=tuple(children),
        typedef="BenchType",
    )
    variables = {v.tag: v for f in root.walk() for v in f.variables}
    return Layout(cfg.bench, root, tuple(channels), tuple(alarms), variables)
