"""The address space of a bench, planned before anything is built (pure: testable without
a server).

::

    Objects/Bench
      Channels/ch0 …      the channel's tags under friendly names (Voltage, Current, …,
                          State as the ISA-88/PackML state enumeration) and its methods
      Devices/adam …      each device's health (Connected, CommFailures) and the tags the
                          I/O map takes from its points (browse name = tag name)
      Alarms/<id> …       one object per alarm (its state, severity, message)
      Diagnostics         scan.*, opcua.*, retain.* (scan time, jitter, overruns, queues)
      Tags                any tag none of the above claims

Every variable's NodeId is ``ns=<bench namespace>;s=<tag name>`` so ``ch0.voltage`` is
addressed directly; objects, methods and types have NodeIds starting with ``/`` (a tag name
never does, config ``TAG_PATTERN``), so they can never collide with a tag.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Final, Literal

from supervisor.config.models import BenchConfig
from supervisor.tags import Access, Tag

URN_PREFIX: Final = "urn:bench-supervisor:bench:"

Kind = Literal["analog", "int", "bool", "str", "state"]

# A channel's tags by their suffix after ``<channel>.``: the names SCADA screens use.
CHANNEL_NAMES: Final[dict[str, str]] = {
    "voltage": "Voltage",
    "current": "Current",
    "temperature": "Temperature",
    "power": "Power",
    "chain.charge_ah": "Charge",  # the test's charge (the display line's figure)
    "charge_ah": "ChargeCounter",  # the net counter, not the test's charge
    "energy_wh": "Energy",
    "chain.state_code": "State",
    "chain.state": "StateName",
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
    "state": "ChannelState",
    "enable": "Enable",
    "manual_current": "ManualCurrent",
}
STATE_SUFFIX: Final = "chain.state_code"
"""The chain's state as its OPC UA number (``chains/states.py::OPCUA_CODE``): shown with the
PackML state enumeration as its DataType."""

DEVICE_NAMES: Final[dict[str, str]] = {"connected": "Connected", "comm_failures": "CommFailures"}
DIAGNOSTIC_PREFIXES: Final = ("scan.", "opcua.", "retain.")


def namespace_uri(bench: str) -> str:
    """The bench's namespace (and the server's application URI)."""
    return URN_PREFIX + bench


def camel(text: str) -> str:
    """``limit.charge_a`` → ``LimitChargeA``."""
    return "".join(p[:1].upper() + p[1:] for p in re.split(r"[._]", text) if p)


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


def plan(cfg: BenchConfig, tags: Iterable[Tag], alarms: Sequence[str] = ()) -> Layout:
    """Where each tag goes, under which browse name."""
    all_tags = list(tags)
    by_name = {t.name: t for t in all_tags}
    placed: set[str] = set()
    channels = [c.name for c in cfg.channels]

    def var(tag: Tag, browse: str) -> Variable:
        placed.add(tag.name)
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

    channel_folders = []
    for ch in channels:
        prefix = ch + "."
        mine = [t for t in all_tags if t.name.startswith(prefix)]
        names: dict[str, str] = {}
        used: set[str] = set()
        # The fixed vocabulary first, then the others by their suffix, shortest form that
        # is still unique in the channel (``chain.alarm`` → ``Alarm``, else ``ChainAlarm``).
        for t in mine:
            suffix = t.name[len(prefix) :]
            if suffix in CHANNEL_NAMES:
                names[t.name] = CHANNEL_NAMES[suffix]
                used.add(CHANNEL_NAMES[suffix])
        for t in mine:
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
        c = next(x for x in cfg.channels if x.name == ch)
        channel_folders.append(
            Folder(
                channel_node(ch),
                ch,
                c.description,
                folder=False,
                variables=tuple(var(t, names[t.name]) for t in mine),
                channel=ch,
            )
        )

    device_folders = []
    for dev in cfg.devices:
        health = [
            var(by_name[f"{dev}.{k}"], v)
            for k, v in DEVICE_NAMES.items()
            if f"{dev}.{k}" in by_name
        ]
        points = [
            var(by_name[m.name], m.name)
            for m in cfg.tags
            if m.device == dev and m.name in by_name and m.name not in placed
        ]
        device_folders.append(
            Folder(device_node(dev), dev, folder=False, variables=tuple(health + points))
        )

    diagnostics = [
        var(t, t.name)
        for t in all_tags
        if t.name not in placed and t.name.startswith(DIAGNOSTIC_PREFIXES)
    ]
    rest = [var(t, t.name) for t in all_tags if t.name not in placed]
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
        "/Bench", "Bench", cfg.description or cfg.bench, folder=False, children=tuple(children)
    )
    variables = {v.tag: v for f in root.walk() for v in f.variables}
    return Layout(cfg.bench, root, tuple(channels), tuple(alarms), variables)
