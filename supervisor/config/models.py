"""Validated models of a bench I/O map (``io_maps/*.yaml``).

Unknown keys are errors everywhere (``extra="forbid"``): a misspelt key silently
ignored is how a limit goes missing. Names carry units (``period_s``, ``current_a``).

Types are strict (``strict=True``): YAML's ``true`` is not the number 1 (``port: true`` is
not port 1, ``capacity_ah: true`` not 1 Ah), a number is not a text; a float field takes an
int. Numbers are finite (``allow_inf_nan=False``): ``.inf`` and ``.nan`` are refused.
"""

from __future__ import annotations

import ipaddress
import os
import re
import urllib.parse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Final, Literal, Union

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    PrivateAttr,
    Tag,
    create_model,
    field_validator,
    model_validator,
)

from supervisor.config.limits import (
    MAX_SCAN_PERIOD_S,
    MIN_SCAN_PERIOD_S,
    RECIPE_CHECK_MEMORY_BYTES,
    RECIPE_CHECK_WORKERS,
    RECIPE_COMPILE_TIMEOUT_S,
)
from supervisor.config.notifications import NotificationsConfig
from supervisor.config.secrets import read_secret_file
from supervisor.core.driver import PointInfo

NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
TAG_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_]+)*$"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _list_as_tuple(v: Any) -> Any:
    # YAML has lists, no tuples; strict mode takes a tuple only: the list is the pair (its
    # items keep their strict types: ``[true, 1]`` is still refused).
    return tuple(v) if isinstance(v, list) else v


LIST_AS_TUPLE: Final = BeforeValidator(_list_as_tuple)
"""Put on a strict model's tuple field (``Annotated[tuple[float, float], LIST_AS_TUPLE]``)."""

Pair = Annotated[tuple[float, float], LIST_AS_TUPLE]
"""``[low, high]`` or ``[a, b]`` as YAML writes it."""
OpenPair = Annotated[tuple[float | None, float | None], LIST_AS_TUPLE]
"""``[low, high]`` where ``null`` leaves that side open."""


class ScanConfig(Strict):
    period_s: float = Field(
        0.1, ge=MIN_SCAN_PERIOD_S, le=MAX_SCAN_PERIOD_S, description="Scan period in seconds."
    )
    realtime_priority: int | None = Field(
        None,
        ge=1,
        le=99,
        description="Run the scan's thread at this real-time priority (SCHED_FIFO, 1-99)"
        " so that other programs of the machine neither delay its start nor interrupt it;"
        " needs CAP_SYS_NICE or LimitRTPRIO= (deploy/bench-supervisor@.service). Refused, it"
        " is logged and the scan runs at normal priority. Unset: normal priority.",
    )


HMI_SESSION_TIMEOUT_S: Final = 8 * 3600.0
"""An operator's shift: a session unused for this long logs out (issue 12 "Access")."""


def is_loopback(host: str) -> bool:
    """Is ``host`` reachable from this machine only (``localhost``, 127.0.0.0/8, ::1)?"""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


_DEFAULT_PORTS: Final = {"http": 80, "https": 443}


def web_origin(url: str) -> str | None:
    """The origin (RFC 6454) of ``url`` as browsers serialise it in an ``Origin`` header:
    ``scheme://host[:port]`` in lower case, the scheme's default port left out; None when
    ``url`` has none (not http/https, no host, ``null``)."""
    try:
        parts = urllib.parse.urlsplit(url.strip())
        port = parts.port
    except ValueError:  # a port out of range, a malformed IPv6 literal
        return None
    scheme, host = parts.scheme.lower(), parts.hostname
    if scheme not in _DEFAULT_PORTS or not host:
        return None
    if ":" in host:  # an IPv6 literal keeps its brackets
        host = f"[{host}]"
    if port is None or port == _DEFAULT_PORTS[scheme]:
        return f"{scheme}://{host}"
    return f"{scheme}://{host}:{port}"


class HmiConfig(Strict):
    """The HTTP API and the operator screens (docs/adr/0016-hmi-sessions-live-data.md)."""

    host: str = Field("127.0.0.1", description="Address the HTTP API listens on.")
    port: int = Field(8080, ge=0, le=65535, description="0 picks a free port.")
    login: bool = Field(
        False,
        description="Users log in (the OPC UA users: `supervisor opcua add-user`); viewers"
        " see, operators command, engineers edit recipes. Without it everyone on the API"
        " operates, so the host must then be loopback.",
    )
    anonymous_read: bool = Field(
        True,
        description="With login: a visitor who has not logged in sees the screens"
        " (a viewer: no command, no write).",
    )
    session_timeout_s: float = Field(
        HMI_SESSION_TIMEOUT_S,
        gt=0,
        le=7 * 86400.0,
        description="A session unused for this long expires (the page goes back to login).",
    )
    alarm_sound_repeat_s: float = Field(
        10.0,
        ge=2.0,
        le=600.0,
        description="An unacknowledged alarm of high or critical priority sounds again on"
        " each logged-in screen this often, until acknowledged or silenced there.",
    )
    publish_period_s: float = Field(
        0.2,
        ge=0.05,
        le=10.0,
        description="How often the screens get the tags that changed (WebSocket /api/ws).",
    )
    allowed_origins: list[str] = Field(
        [],
        description="Other origins (`scheme://host[:port]`) whose pages may send commands,"
        " e.g. the address of a reverse proxy in front of the HMI; the HMI's own origin"
        " (scheme and Host of each request) always may. Any other page's command is refused"
        " (403, cross-site request forgery).",
    )

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, origins: list[str]) -> list[str]:
        normal: list[str] = []
        for text in origins:
            origin = web_origin(text)
            parts = urllib.parse.urlsplit(text.strip())
            # Exactly an origin: a path or query is no part of what browsers send.
            if (
                origin is None
                or parts.path not in ("", "/")
                or parts.query
                or parts.fragment
                or parts.username is not None
            ):
                raise ValueError(
                    f"allowed origin {text!r} is not an origin: expected scheme://host[:port]"
                    " (http or https, no path), e.g. https://bench.lab.example:8443"
                )
            normal.append(origin)
        return normal

    max_connections: int = Field(
        256,
        ge=1,
        le=60000,
        description="Open HTTP connections at most (pages, API clients and screens' WebSockets"
        " together); one more is answered 503 at once and closed, so that a flood of clients"
        " never takes the file descriptors the devices need"
        ' (docs/deployment.md "Connection limits").',
    )
    max_websockets: int = Field(
        32,
        ge=1,
        le=60000,
        description="Screens (WebSocket /api/ws) connected at most; one more is answered 503.",
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        le=300.0,
        description="A connection whose request headers are not complete this long after it"
        " opened (or after the first byte of its next request) is closed (slowloris).",
    )
    idle_timeout_s: float = Field(
        60.0,
        gt=0,
        le=3600.0,
        description="A keep-alive connection without a request for this long is closed.",
    )

    @model_validator(mode="after")
    def _websockets_within_connections(self) -> HmiConfig:
        if self.max_websockets > self.max_connections:
            raise ValueError(
                f"max_websockets ({self.max_websockets}) is more than max_connections"
                f" ({self.max_connections}): each screen is one of the HTTP connections"
            )
        return self

    @model_validator(mode="after")
    def _login_off_the_loopback(self) -> HmiConfig:
        # Without login every client operates (the bench's outputs): only this machine's.
        if not self.login and not is_loopback(self.host):
            raise ValueError(
                f"host {self.host!r} is not loopback and login is false: anyone on the"
                " network could command the bench; set hmi.login: true (users:"
                " `supervisor opcua add-user`) or host: 127.0.0.1"
            )
        return self


OpcUaSecurity = Literal["none", "sign", "sign_and_encrypt"]
"""An endpoint's message security: none, or Basic256Sha256 with Sign / SignAndEncrypt."""


class IdentificationConfig(Strict):
    """Who made the bench and where it stands: what OPC UA clients read as the bench's
    Identification (OPC 40001-1 Machinery, MachineIdentificationType). Every key is
    optional; the software's own name and version are never configured here."""

    manufacturer: str = Field(
        "", max_length=200, description="Who built the bench (Machinery's Manufacturer)."
    )
    manufacturer_uri: str = Field("", max_length=200, description="The manufacturer's URI.")
    model: str = Field("", max_length=200, description="The bench's model or product name.")
    serial_number: str = Field(
        "", max_length=100, description="The bench's serial number (default: its name)."
    )
    product_instance_uri: str = Field(
        "",
        max_length=300,
        description="A URI unique to this bench (default: urn:bench-supervisor:bench:<bench>).",
    )
    asset_id: str = Field("", max_length=100, description="The lab's inventory number.")
    location: str = Field("", max_length=200, description="Where the bench stands.")
    year_of_construction: int | None = Field(
        None, ge=1900, le=9999, description="The year the bench was built."
    )


def _ip_address(v: str) -> str:
    """A Modbus writer: an IP address (each refused at its own place in the list)."""
    try:
        ipaddress.ip_address(v)
    except ValueError:
        raise ValueError(f"writer {v!r} is not an IP address") from None
    return v


class ModbusServerConfig(Strict):
    """The tag database as a Modbus TCP server (issue 36; its map: `supervisor modbus map`):
    panel HMIs and SCADA that speak only Modbus. Off unless the I/O map has this section;
    the least one writes is ``modbus_server: {port: N}``."""

    port: int = Field(ge=1, le=65535, description="TCP port (502 is Modbus's own).")
    host: str = Field("127.0.0.1", description="Address the Modbus server listens on.")
    unit_id: int = Field(
        1, ge=0, le=255, description="The unit id it answers (0 and 255 are also answered)."
    )
    word_order: Literal["big", "little"] = Field(
        "big",
        description="A 32-bit float's two registers: big = the high word first, little = the"
        " low word first (bytes within a register are always big-endian).",
    )
    writes: bool = Field(
        False,
        description="Clients may write setpoints, commands and coils (through the command"
        " path, checked like any command); off: every write answers exception 01.",
    )
    writers: list[Annotated[str, AfterValidator(_ip_address)]] = Field(
        default_factory=list,
        description="The client addresses that may write (Modbus has no authentication);"
        " a write from any other answers exception 04 and is recorded as refused.",
    )
    max_clients: int = Field(
        8, ge=1, le=256, description="Open Modbus connections at most; one more is closed."
    )
    addresses: dict[str, Annotated[int, Field(ge=0, le=65535)]] = Field(
        default_factory=dict,
        description="An explicit register (or bit) address for a tag, 0-based: overrides"
        " the generated map (`supervisor modbus map IOMAP`).",
    )
    scale: dict[str, Annotated[float, Field(gt=0, allow_inf_nan=False)]] = Field(
        default_factory=dict,
        description="A float tag as a scaled 16-bit integer instead (INT16, raw ="
        " round(value × scale), e.g. 1000 for millivolts), in the first register of its place.",
    )


class OpcUaConfig(Strict):
    """The OPC UA server (``opc.tcp://<host>:<port>/supervisor``, docs/adr/0014-opcua-server.md):
    the bench's tags, channel methods, events and alarms for SCADA and OPC UA clients."""

    enabled: bool = Field(False, description="Serve OPC UA while the bench runs.")
    host: str = Field("127.0.0.1", description="Address the OPC UA server listens on.")
    port: int = Field(4840, ge=1, le=65535, description="TCP port (4840 is OPC UA's own).")
    security: list[OpcUaSecurity] | None = Field(
        None,
        min_length=1,
        description="Endpoints offered: none (unsigned, in clear: passwords are still"
        " encrypted with the server's certificate), sign and sign_and_encrypt (Basic256Sha256"
        " with a certificate made on first start). Default: all three when host is loopback,"
        " sign and sign_and_encrypt otherwise (a client then needs a trusted certificate).",
    )
    anonymous: bool = Field(True, description="Anonymous sessions may read (never write or call).")
    users_file: str | None = Field(
        None,
        description="Users, roles and password hashes (`supervisor opcua add-user`); default"
        " <state_dir>/opcua/users.yaml. Passwords are never written here in clear.",
    )
    pki_dir: str | None = Field(
        None,
        description="The server's own certificate and key (own/), and the client certificates"
        " it trusts (trusted/; refused ones land in rejected/); default <state_dir>/opcua/pki.",
    )
    recipes_dir: str | None = Field(
        None,
        description="Deprecated: the bench's top-level `recipes: {folders: [...]}` (this"
        " key, when given alone, is read as its one folder).",
    )
    sampling_interval_s: float | None = Field(
        None,
        gt=0,
        le=60,
        description="How often the server takes the scan's changed tags, the"
        " MinimumSamplingInterval its variables advertise (s). Default: the scan period, but"
        " not under 0.05 s (a 10 ms scan would spend a third of its CPU feeding OPC UA values"
        " no SCADA client samples that fast; events and alarms are never delayed).",
    )
    max_connections: int = Field(
        64,
        ge=1,
        le=60000,
        description="Open OPC UA connections at most; one more is closed at once"
        ' (docs/deployment.md "Connection limits").',
    )
    activation_timeout_s: float = Field(
        10.0,
        gt=0,
        le=300.0,
        description="A connection without an activated session this long after it opened is"
        " closed (an idle or stalled client does not hold its descriptor).",
    )

    @field_validator("security")
    @classmethod
    def _distinct(cls, v: list[str] | None) -> list[str] | None:
        if v is not None and len(set(v)) != len(v):
            raise ValueError("each security mode once")
        return v

    @property
    def security_modes(self) -> tuple[OpcUaSecurity, ...]:
        """The endpoints offered: ``security``, or by default None only on loopback (off it,
        a None channel is unsigned and readable by anyone on the network; issue 27)."""
        if self.security is not None:
            return tuple(self.security)
        if is_loopback(self.host):
            return ("none", "sign", "sign_and_encrypt")
        return ("sign", "sign_and_encrypt")


# --- scaling, alarms, history ---------------------------------------------------------
class LinearScaling(Strict):
    """``eu = a·raw + b``."""

    a: float = 1.0
    b: float = 0.0

    @field_validator("a")
    @classmethod
    def _nonzero(cls, v: float) -> float:
        if v == 0:
            raise ValueError("scaling slope a is zero (zero span)")
        return v


class SpanScaling(Strict):
    """Two-point scaling: ``raw: [lo, hi]`` maps to ``eu: [lo, hi]`` (e.g. ±4 V ↔ ±300 A)."""

    raw: Pair
    eu: Pair

    @model_validator(mode="after")
    def _spans(self) -> SpanScaling:
        if self.raw[0] == self.raw[1]:
            raise ValueError("raw span is zero")
        if self.eu[0] == self.eu[1]:
            raise ValueError("engineering-unit span is zero")
        return self

    def linear(self) -> tuple[float, float]:
        a = (self.eu[1] - self.eu[0]) / (self.raw[1] - self.raw[0])
        return a, self.eu[0] - a * self.raw[0]


def _scaling_kind(v: Any) -> str:
    # Pick the form from its keys so an error names only the form the user meant.
    if isinstance(v, dict):
        return "span" if ("raw" in v or "eu" in v) else "linear"
    return "span" if isinstance(v, SpanScaling) else "linear"


Scaling = Annotated[
    Annotated[LinearScaling, Tag("linear")] | Annotated[SpanScaling, Tag("span")],
    Discriminator(_scaling_kind),
]


class AlarmConfig(Strict):
    hh: float | None = None
    h: float | None = None
    l: float | None = None  # noqa: E741 - ISA-18.2 name
    ll: float | None = None
    deadband: float = Field(0.0, ge=0)
    delay_s: float = Field(0.0, ge=0)


class HistoryConfig(Strict):
    enabled: bool = True
    deadband: float = Field(0.0, ge=0)
    min_interval_s: float = Field(0.0, ge=0)


class TagMapping(Strict):
    """A device point published as a tag, with optional scaling to engineering units."""

    name: str = Field(pattern=TAG_PATTERN)
    device: str
    point: str
    unit: str = ""
    description: str = ""
    scaling: Scaling | None = None
    range: Pair | None = None
    stale_after_s: float | None = Field(None, gt=0)
    alarms: AlarmConfig | None = None
    history: HistoryConfig = HistoryConfig()
    retain: bool = False
    threshold: float | None = Field(
        None, description="make a boolean tag: true when the scaled value >= threshold"
    )


# --- simulation ------------------------------------------------------------------------
class SimCell(Strict):
    """Battery model behind a simulated board or supply."""

    model: Literal["nimh-aa", "liion-pack"] = "nimh-aa"
    capacity_ah: float = Field(2.0, gt=0)
    soc: float = Field(0.5, ge=0, le=1)
    temperature_c: float = 25.0
    cells_series: int | None = Field(None, ge=1, description="Li-ion pack only")


# --- devices -----------------------------------------------------------------------------
# Each device kind's model lives in its own package (``supervisor/devices/<kind>/config.py``)
# and derives from ``DeviceConfig``; ``bench_model`` puts the registered kinds together.

LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True, slots=True)
class SourcePoints:
    """The device points a channel binds to when this device drives it."""

    voltage: str
    current: str
    current_set: str
    output: str | None = None  # an output switch (EA: ``OUTP``)
    output_fb: str | None = None  # its read-back (EA: ``OUTP?``)
    voltage_set: str | None = None  # a CV target (EA: ``VOLT`` while charging)


@dataclass(frozen=True, slots=True)
class SourceSpec:
    """What a device kind offers the channels it drives (checked before anything runs)."""

    noun: str
    """How messages name one source of this kind (the kind's ``source_noun``)."""
    title: str
    """The kind in a sentence's subject: "Chadèche device", "EA supply"."""
    addresses: range | None = None
    """Possible board addresses when one device carries several sources; None: one source."""
    boards: tuple[int, ...] = ()
    """Board addresses configured on this device."""
    max_current_a: float | None = None
    """Hardware maximum of the current, either direction; limits beyond it are refused."""
    rated_voltage_v: float | None = None
    """The unit's rated (nominal) voltage; channel voltage limits above it are refused.
    None: unknown before connect."""
    rated_current_a: float | None = None
    """The unit's rated current, either direction; channel current limits beyond it are
    refused. None: unknown before connect."""
    rating: str = ""
    """What the rating comes from, as messages name it: "the PSB 10060-60 rating"."""
    regulates_voltage: bool = False
    """Can hold a constant voltage (CV, CC-CV steps)."""
    no_cv_reason: str = ""
    owner_required: bool = False
    """The device takes its limits from the channel it drives: it must drive one."""
    points: Callable[[int | None], SourcePoints] | None = None


class DeviceConfig(Strict):
    """Base of every device kind's entry under ``devices:``."""

    driver: str
    poll_period_s: float = Field(0.1, gt=0)
    stale_after_s: float = Field(1.0, gt=0)

    source_noun: ClassVar[str | None] = None
    """How messages name one channel source of this kind ("a Chadèche board"); None when
    the kind cannot drive a channel."""

    @property
    def simulated(self) -> bool:
        """Served by an in-process simulator rather than a real device."""
        return False

    def points(self) -> Mapping[str, PointInfo]:
        """The device's point catalog: every name an I/O map may bind a tag to."""
        raise NotImplementedError

    def point_names(self) -> set[str]:
        return set(self.points())

    def channel_source(self) -> SourceSpec | None:
        """What it offers a channel it drives; None when it cannot drive one."""
        return None

    def problems(self) -> list[tuple[tuple[str | int, ...], str]]:
        """Cross-checks of this entry alone, as (path inside the entry, message)."""
        return []


class NetworkDevice(DeviceConfig):
    host: str
    poll_period_s: float = Field(0.2, gt=0)
    timeout_s: float = Field(1.0, gt=0, le=30)
    sim: bool = Field(False, description="serve a simulator of this device on host:port")

    @property
    def simulated(self) -> bool:
        return self.sim

    @model_validator(mode="after")
    def _sim_on_loopback(self) -> NetworkDevice:
        if self.sim and self.host not in LOOPBACK_HOSTS:
            raise ValueError(
                f"a simulated device listens on loopback only; host {self.host!r}"
                " must be 127.0.0.1 (or set sim: false)"
            )
        return self


# --- channels ----------------------------------------------------------------------------
class ChannelSource(Strict):
    """The device that drives the channel: a Chadèche board or an EA supply."""

    device: str
    board: int | None = Field(None, ge=0, le=3, description="Chadèche board address")


class ChannelLimits(Strict):
    """Hard limits: setpoints are clamped to them, crossings trip the channel."""

    current_a: Pair = Field(description="[max discharge (<=0), max charge (>=0)]")
    voltage_v: Pair
    temperature_c: OpenPair = (None, None)
    trip_delay_s: float = Field(
        0.0, ge=0, le=60, description="a crossing must last this long before it trips"
    )

    @model_validator(mode="after")
    def _ordered(self) -> ChannelLimits:
        lo, hi = self.current_a
        if lo > 0 or hi < 0:
            raise ValueError("current_a must be [discharge limit <= 0, charge limit >= 0]")
        if self.voltage_v[0] >= self.voltage_v[1]:
            raise ValueError("voltage_v must be [low, high] with low < high")
        tlo, thi = self.temperature_c
        if tlo is not None and thi is not None and tlo >= thi:
            raise ValueError("temperature_c must be [low, high] with low < high")
        return self


class FeedbackConfig(Strict):
    """Each output with a read-back must agree with it within ``delay_s`` (S7 discrepancy)."""

    delay_s: float = Field(1.0, gt=0, le=60, description="discrepancy time")
    current_tolerance_a: float | None = Field(
        None,
        gt=0,
        description="measured current vs setpoint, once settled (None: not checked, e.g. a"
        " source without a current sensor)",
    )


class VoltageCheck(Strict):
    """Another measurement of the channel's voltage (seed 002 measures the pack three ways:
    voltage board, supply terminals, BMS): a disagreement beyond the tolerance for the
    delay is a fault, so a broken sense wire does not go unnoticed."""

    tag: str = Field(pattern=TAG_PATTERN)
    tolerance_v: float = Field(gt=0)
    delay_s: float = Field(2.0, ge=0, le=600)


class BmsLimits(Strict):
    """Limits the BMS reports against: charge/discharge currents are derated as a cell
    approaches its limit, and the channel trips beyond it (seed 002 §2.1)."""

    cell_max_tag: str | None = Field(None, pattern=TAG_PATTERN)
    cell_min_tag: str | None = Field(None, pattern=TAG_PATTERN)
    temperature_tag: str | None = Field(None, pattern=TAG_PATTERN)
    cell_voltage_v: Pair = Field(description="[lowest, highest] cell voltage")
    derate_band_v: float = Field(0.05, gt=0, description="full current until this close")
    temperature_max_c: float | None = None
    trip_delay_s: float = Field(1.0, ge=0, le=60)

    @model_validator(mode="after")
    def _ordered(self) -> BmsLimits:
        if self.cell_voltage_v[0] >= self.cell_voltage_v[1]:
            raise ValueError("cell_voltage_v must be [low, high] with low < high")
        return self


class RecordColumn(Strict):
    """A tag recorded in a column of the channel's result files, with its header."""

    tag: str = Field(pattern=TAG_PATTERN)
    label: str = Field(
        min_length=1,
        max_length=80,
        pattern=r"^[^\r\n,\"]+$",
        description="BDF header, 'Name / unit' (e.g. 'Ambient Temperature / degC')",
    )


class ChannelConfig(Strict):
    name: str = Field(pattern=NAME_PATTERN)
    description: str = ""
    source: ChannelSource
    chemistry: Literal["nimh", "liion", "lfp", "lead-acid", "other"] = "nimh"
    capacity_ah: float = Field(gt=0, description="Rated capacity (C-rates, progress).")
    limits: ChannelLimits
    temperature_tag: str | None = Field(None, pattern=TAG_PATTERN)
    voltage_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="measure voltage here instead of the source"
    )
    current_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="measure current here instead of the source"
    )
    contactor_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="relay output tag closing the battery contactor"
    )
    permissives: list[str] = Field(
        [], description="boolean tags that must all be true and GOOD to drive current"
    )
    contactor_feedback_tag: str | None = Field(
        None,
        pattern=TAG_PATTERN,
        description="boolean tag: the contactor's auxiliary contact (true = really closed)",
    )
    feedback: FeedbackConfig = Field(
        FeedbackConfig(), description="outputs against their read-backs (S7 discrepancy)"
    )
    voltage_checks: list[VoltageCheck] = Field(
        [], description="other measurements of the same voltage that must agree with it"
    )
    bms: BmsLimits | None = Field(None, description="BMS-reported limits that clamp setpoints")
    record: list[str | RecordColumn] | None = Field(
        None,
        description="tags recorded in the result files' auxiliary columns, in this order (a"
        " tag name, headed '<tag> / <unit>', or {tag, label}); default: the measurements"
        " (tags with a unit) of the devices serving the channel, and its trip text when it"
        " has a bms: block",
    )


# --- safety (docs/design.md "Safety") --------------------------------------------------------
Severity = Literal["low", "medium", "high", "critical"]


class EstopConfig(Strict):
    """The hardware e-stop, sensed on an input (seed 002 §1.5: 5 V while the circuit is
    closed): it trips every channel at once, aborts their recipes and opens the software
    e-stop relay; it resets only once the circuit is closed again."""

    tag: str = Field(pattern=TAG_PATTERN, description="boolean tag, true while circuit closed")
    relay_tag: str | None = Field(
        None, pattern=TAG_PATTERN, description="software e-stop relay output (opened on trip)"
    )


class InterlockConfig(Strict):
    """A condition on one tag that trips channels (latched until acknowledged and reset)."""

    id: str = Field(pattern=NAME_PATTERN)
    tag: str = Field(pattern=TAG_PATTERN)
    above: float | None = None
    below: float | None = None
    equals: bool | None = Field(None, description="a boolean tag trips at this value")
    deadband: float = Field(0.0, ge=0, description="how far back it must be to reset")
    delay_s: float = Field(0.0, ge=0, le=600, description="on-delay before it trips")
    channels: list[str] | None = Field(None, description="channels it trips (default: all)")
    action: Literal["hold", "abort"] = "hold"
    severity: Severity = "high"
    message: str = ""

    @model_validator(mode="after")
    def _one_condition(self) -> InterlockConfig:
        given = [k for k in ("above", "below", "equals") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("an interlock needs exactly one of above, below or equals")
        return self


class HeartbeatConfig(Strict):
    """An output the scan toggles for a hardware watchdog relay in series with the contactor
    coil: when the supervisor dies, the toggling stops and the relay opens the contactor
    (deploy/watchdog-wiring.md)."""

    tag: str = Field(pattern=TAG_PATTERN)
    period_s: float = Field(0.5, ge=0.05, le=10, description="time between two toggles")


class SafetyConfig(Strict):
    estop: EstopConfig | None = None
    interlocks: list[InterlockConfig] = []
    heartbeat: HeartbeatConfig | None = None


class SimPoint(Strict):
    device: str
    point: str


class SimWatchdogRelay(SimPoint):
    """The hardware watchdog relay in series with the contactor coil (docs/design.md "Safety"),
    fed by the heartbeat relay output ``point`` that the supervisor toggles: its contact is
    closed only while that output changed state within ``timeout_s``."""

    timeout_s: float = Field(
        1.5, gt=0, le=60, description="watchdog time: contact opens this long after the last toggle"
    )


class SimulationConfig(Strict):
    """The simulated seed-002 plant: one pack behind the EA supply, seen by ADAM and BMS."""

    control_port: int = Field(
        0,
        ge=0,
        le=65535,
        description="`supervisor sim`'s control API (the e-stop button, the plant's state)"
        " on 127.0.0.1; 0 (default): a free port, printed at start (two simulated benches"
        " never clash).",
    )
    pack: SimCell = SimCell(model="liion-pack", capacity_ah=10.0, soc=0.5, cells_series=4)
    ambient_c: float = 25.0
    lem_current: SimPoint | None = None
    lem_volts_per_amp: float = Field(4.0 / 300.0, description="LEM HAL 300-S: 4 V at 300 A")
    voltage_board: SimPoint | None = None
    voltage_board_ratio: float = Field(0.1, gt=0, description="1:10 divider board")
    estop_sense: SimPoint | None = None
    thermocouples: list[SimPoint] = []
    contactor: SimPoint | None = Field(None, description="relay output driving the contactor coil")
    watchdog_relay: SimWatchdogRelay | None = Field(
        None,
        description="hardware watchdog relay in series with the contactor coil, fed by this"
        " heartbeat relay output; null: not fitted (the contactor follows its coil relay)",
    )
    contactor_feedback: SimPoint | None = Field(
        None,
        description="analog input wired to the contactor's auxiliary contact: 5 V while the"
        " contactor is really closed, 0 V when open",
    )


class RetainConfig(Strict):
    """Retained state (``<state_dir>/state.sqlite``) and the result summaries of live tests."""

    period_s: float = Field(
        1.0,
        ge=0.1,
        le=60.0,
        description="Save every channel's retained state at least this often (s); it is"
        " also saved at every step change, state change and alarm transition.",
    )
    summary_period_s: float = Field(
        10.0,
        ge=1.0,
        le=3600.0,
        description="Rewrite a running test's summary.json at least this often (s); it is"
        " also rewritten at every step change.",
    )


class HistorianConfig(Strict):
    """The embedded historian (``supervisor.publish.historian``, docs/adr/0013-historian.md):
    every tag's changes (deadband and minimum interval from each tag's ``history:``) and the
    bench's events, in ``<state_dir>/<path>``; the source of the screens' trends."""

    enabled: bool | None = Field(
        None,
        description="Record history. Default (null): on unless an influxdb: section is configured.",
    )
    path: str = Field(
        "history.sqlite", min_length=1, description="The SQLite file, relative to state_dir."
    )
    max_age_s: float = Field(
        90 * 86400.0,
        gt=0,
        description="Samples and events older than this are deleted (s; default 90 days).",
    )
    max_bytes: int = Field(
        1024**3,
        ge=1024**2,
        description="Bound of the file's size (bytes; default 1 GiB): above it the oldest"
        " samples and events are deleted first.",
    )
    commit_interval_s: float = Field(
        0.5,
        ge=0.01,
        le=10.0,
        description="One transaction per interval (s): what a killed process loses, unless"
        " the disk had fallen behind (then what was queued).",
    )
    queue_max_rows: int = Field(
        200_000,
        ge=1000,
        le=10_000_000,
        description="Samples waiting for the disk, at most (about 150 bytes each); past"
        " this the newest are dropped, counted and alarmed (the scan never waits).",
    )
    retention_period_s: float = Field(
        60.0, ge=1.0, le=86400.0, description="How often retention runs (s)."
    )


INFLUX_TOKEN_CHARS: Final = 4096
"""A token file longer than this is not a token (a wrong file named)."""


class InfluxConfig(Strict):
    """Publish into InfluxDB through an on-disk spool (``<state_dir>/influx-spool.sqlite``;
    docs/adr/0012-influx-spool.md). The token is never in this file: ``token_file`` names a
    file holding it, or ``token_env`` an environment variable. InfluxDB 1.8 takes
    ``bucket: db/rp`` and ``token: user:password`` (any text while its auth is off)."""

    url: str = Field(description="InfluxDB base URL, e.g. http://127.0.0.1:8086")
    org: str = Field("-", min_length=1, description="Organisation (InfluxDB 1.8: '-').")
    bucket: str = Field(min_length=1, description="Bucket (InfluxDB 1.8: database/retention).")
    token_file: str | None = Field(
        None,
        description="File holding the token (relative to the working directory, like"
        " state_dir); its surrounding white space is ignored.",
    )
    token_env: str | None = Field(
        None,
        pattern=r"^[A-Za-z_][A-Za-z0-9_]*$",
        description="Environment variable holding the token.",
    )
    batch_size: int = Field(5000, ge=1, le=100_000, description="Points per write request.")
    flush_interval_s: float = Field(
        1.0,
        gt=0,
        le=3600,
        description="Send a batch not yet full once its oldest point waited this long.",
    )
    timeout_s: float = Field(
        10.0,
        gt=0,
        le=300,
        description="A write request without an answer by then fails (and is retried).",
    )
    retry_max_s: float = Field(
        30.0,
        ge=0.1,
        le=3600,
        description="Longest wait between two attempts (backoff cap); a refused token or"
        " bucket is retried at this interval.",
    )
    alarm_after_s: float = Field(
        60.0,
        ge=0,
        le=86400,
        description="Raise influx.unreachable after this long without a write.",
    )
    stop_flush_s: float = Field(
        5.0,
        ge=0,
        le=600,
        description="A clean stop sends for at most this long; the rest stays spooled.",
    )
    spool_max_bytes: int = Field(
        256 * 1024 * 1024,
        ge=1024 * 1024,
        le=1024**4,
        description="Bound on the spooled line protocol; past it the oldest points are"
        " dropped (counted, alarmed).",
    )
    spool_commit_interval_s: float = Field(
        0.2,
        ge=0.01,
        le=10,
        description="How often queued points are committed to the spool: a crash loses at"
        " most this much.",
    )

    @field_validator("url")
    @classmethod
    def _http_url(cls, v: str) -> str:
        parts = urllib.parse.urlsplit(v)
        try:
            parts.port  # noqa: B018 - raises ValueError for a port that is not a number
        except ValueError:
            raise ValueError("the port must be a number from 1 to 65535") from None
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError("expected http://host:port or https://host[:port][/path]")
        if parts.query or parts.fragment:
            raise ValueError("no query or fragment: org and bucket are keys of their own")
        return v

    @model_validator(mode="after")
    def _one_token_source(self) -> InfluxConfig:
        if (self.token_file is None) == (self.token_env is None):
            raise ValueError("give exactly one of token_file or token_env (never the token itself)")
        return self

    @field_validator("token_file")
    @classmethod
    def _token_file_readable(cls, v: str | None) -> str | None:
        if v is not None:
            _read_token_file(v)
        return v

    @field_validator("token_env")
    @classmethod
    def _token_env_set(cls, v: str | None) -> str | None:
        if v is not None and not os.environ.get(v, "").strip():
            raise ValueError(f"environment variable {v} is not set (it must hold the token)")
        return v

    def token(self) -> str:
        """The token, read now (the file or the variable may have changed since the
        check); ValueError naming the source when it is gone."""
        if self.token_file is not None:
            return _read_token_file(self.token_file)
        assert self.token_env is not None
        text = os.environ.get(self.token_env, "").strip()
        if not text:
            raise ValueError(f"environment variable {self.token_env} is not set")
        return text


def _read_token_file(path: str) -> str:
    return read_secret_file(path, "token file")


SPARKPLUG_ID_PATTERN: Final = r"^[^/+#\s]+$"
"""A Sparkplug group or edge node id: one topic level, no MQTT wildcard (chapter 4)."""


class SparkplugCommandsConfig(Strict):
    """Commands over Sparkplug (docs/sparkplug.md "Commands"): off by default."""

    enabled: bool = Field(
        False,
        description="Take channel commands (start, hold, resume, stop, abort, reset,"
        " acknowledge) from DCMD messages of the primary host application, through the one"
        " command path with the actor sparkplug:<primary_host>.",
    )
    primary_host: str | None = Field(
        None,
        pattern=SPARKPLUG_ID_PATTERN,
        max_length=128,
        description="The primary host application's id: the edge node waits for its STATE"
        " (spBv1.0/STATE/<id>) online before its NBIRTH, ends its session when it goes"
        " offline, and takes commands only while it is online.",
    )

    @model_validator(mode="after")
    def _host_of_commands(self) -> SparkplugCommandsConfig:
        if self.enabled and not self.primary_host:
            raise ValueError("enabled: true needs primary_host (the only host that commands)")
        return self


class SparkplugConfig(Strict):
    """Publish the bench as a Sparkplug B edge node over MQTT (docs/sparkplug.md): NBIRTH
    with the bench-level tags, one device per channel and per device (DBIRTH, DDATA), the
    NDEATH as the MQTT will with a bdSeq kept in the retained state."""

    broker: str = Field(description="MQTT broker, mqtt://HOST:PORT (port 1883 when left out).")
    group: str = Field(
        pattern=SPARKPLUG_ID_PATTERN,
        max_length=128,
        description="Sparkplug group id (a topic level: no '/', '+', '#' or spaces).",
    )
    edge_node: str | None = Field(
        None,
        pattern=SPARKPLUG_ID_PATTERN,
        max_length=128,
        description="Sparkplug edge node id; default: the bench name.",
    )
    keepalive_s: int = Field(
        30,
        ge=5,
        le=3600,
        description="MQTT keep-alive: a bench that stops answering is declared dead"
        " (its NDEATH published by the broker) about 1.5 times this after its last packet.",
    )
    spool_max_mb: int = Field(
        64,
        ge=0,
        le=100_000,
        description="Store and forward: the samples not sent while the broker is"
        " unreachable wait in <state_dir>/sparkplug-spool.sqlite, at most this many MB"
        " (the oldest dropped past it, counted and alarmed); replayed after the next births"
        " with is_historical. 0: no spool (changes while disconnected are dropped).",
    )
    disconnected_alarm_s: float = Field(
        30.0,
        ge=0,
        le=86_400,
        description="Raise sparkplug.disconnected (low) once the broker has been"
        " unreachable this long.",
    )
    commands: SparkplugCommandsConfig = Field(
        default_factory=SparkplugCommandsConfig,
        description="Commands over Sparkplug and the primary host application.",
    )

    @field_validator("broker")
    @classmethod
    def _mqtt_url(cls, v: str) -> str:
        parts = urllib.parse.urlsplit(v)
        try:
            parts.port  # noqa: B018 - raises ValueError for a port that is not a number
        except ValueError:
            raise ValueError("the port must be a number from 1 to 65535") from None
        if parts.scheme != "mqtt" or not parts.hostname:
            raise ValueError("expected mqtt://host:port (TLS and credentials come later)")
        if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
            raise ValueError("expected mqtt://host:port, nothing after the port")
        return v

    @property
    def host(self) -> str:
        return urllib.parse.urlsplit(self.broker).hostname or ""

    @property
    def port(self) -> int:
        return urllib.parse.urlsplit(self.broker).port or 1883


class RecipeFoldersConfig(Strict):
    """Where the bench's clients (HTTP, OPC UA, the screens' recipe editor) find recipes,
    and the only folders they may load them from (docs/adr/0026-threat-model.md)."""

    folders: list[str] = Field(
        ["recipes"],
        min_length=1,
        description="Recipe folders, relative to the working directory (like state_dir);"
        " a recipe given over the network (HTTP, OPC UA, `supervisor ctl`) loads only when"
        " its real path (symbolic links followed) is inside one of them. A name without a"
        " folder is <folder>/<name>.yaml in the first that has it; the screens' editor"
        " saves into the first.",
    )
    check_timeout_s: float = Field(
        RECIPE_COMPILE_TIMEOUT_S,
        gt=0,
        le=600.0,
        description="A recipe text checked for the HTTP API (the screens' editor: validate,"
        " save, dry run) is refused (503) when its check takes longer; its child process is"
        " killed.",
    )
    check_memory_mib: int = Field(
        RECIPE_CHECK_MEMORY_BYTES // (1024 * 1024),
        ge=256,
        le=65536,
        description="Address space of the child process a recipe text is checked in: a"
        " text that needs more is refused (413); the supervisor's own memory never grows.",
    )
    check_workers: int = Field(
        RECIPE_CHECK_WORKERS,
        ge=1,
        le=8,
        description="Recipe texts checked at once, each in its child process (as many more"
        " wait; beyond that 503 with Retry-After).",
    )

    @field_validator("folders")
    @classmethod
    def _not_empty(cls, v: list[str]) -> list[str]:
        if any(not f.strip() for f in v):
            raise ValueError("a recipe folder is a path, not an empty text")
        return v


class BenchConfig(Strict):
    """A bench: its scan, devices, extra tag mappings and channels."""

    bench: str = Field(pattern=NAME_PATTERN, description="Bench name (InfluxDB `bench` tag).")
    description: str = ""
    scan: ScanConfig = ScanConfig()
    hmi: HmiConfig = HmiConfig()
    opcua: OpcUaConfig = OpcUaConfig()
    identification: IdentificationConfig = IdentificationConfig()
    modbus_server: ModbusServerConfig | None = Field(
        None, description="A Modbus TCP server for panel HMIs and SCADA (off when absent)."
    )
    recipes: RecipeFoldersConfig = RecipeFoldersConfig()
    state_dir: str = Field("var", description="Where retained state and results go.")
    retain: RetainConfig = RetainConfig()
    history: HistorianConfig = HistorianConfig()
    devices: dict[str, DeviceConfig] = Field(min_length=1)
    tags: list[TagMapping] = []
    channels: list[ChannelConfig] = []
    safety: SafetyConfig = SafetyConfig()
    simulation: SimulationConfig | None = None
    influxdb: InfluxConfig | None = Field(
        None, description="Publish into InfluxDB (store and forward); null: the embedded historian."
    )
    sparkplug: SparkplugConfig | None = Field(
        None, description="Publish as a Sparkplug B edge node over MQTT (off when absent)."
    )
    notifications: NotificationsConfig | None = Field(
        None,
        description="Alarms and test ends sent by e-mail and webhooks (docs/notifications.md).",
    )

    device_kinds: ClassVar[tuple[type[DeviceConfig], ...]] = ()
    """The device models this bench model accepts (set by ``bench_model``)."""
    _source_file: str = PrivateAttr("")
    _source_sha256: str = PrivateAttr("")

    def set_source(self, file: str, sha256: str) -> None:
        """The file this I/O map was loaded from and the SHA-256 of its bytes as loaded
        (each test's ``provenance.json`` names them)."""
        self._source_file, self._source_sha256 = file, sha256

    @property
    def source_file(self) -> str:
        """The I/O map's file ("" when built in code)."""
        return self._source_file

    @property
    def source_sha256(self) -> str:
        return self._source_sha256

    @model_validator(mode="after")
    def _recipes_dir_alias(self) -> BenchConfig:
        # opcua.recipes_dir was the one recipe folder before `recipes:` (issue 27).
        old = self.opcua.recipes_dir
        if old is None:
            return self
        if "recipes" in self.model_fields_set and self.recipes.folders != [old]:
            raise ValueError(
                f"opcua.recipes_dir {old!r} and recipes.folders {self.recipes.folders} disagree:"
                " keep recipes.folders only"
            )
        return self

    @model_validator(mode="after")
    def _notified_channels(self) -> BenchConfig:
        if self.notifications is None:
            return self
        known = {c.name for c in self.channels}
        for route in self.notifications.routes:
            unknown = sorted(set(route.channels or ()) - known)
            if unknown:
                raise ValueError(
                    f"notifications route {route.name}: no channel named {', '.join(unknown)}"
                    f" (channels: {', '.join(sorted(known)) or 'none'})"
                )
        return self

    @property
    def recipe_folders(self) -> list[str]:
        """The recipe folders: ``recipes.folders``, or the old ``opcua.recipes_dir``."""
        old = self.opcua.recipes_dir
        return [old] if old is not None else list(self.recipes.folders)

    @field_validator("state_dir")
    @classmethod
    def _state_dir(cls, v: str) -> str:
        # A NUL cannot be in a path: the bench lock's mkdir raised ValueError (issue 28).
        if "\0" in v:
            raise ValueError("state_dir cannot hold a NUL character ('\\0')")
        return v

    @field_validator("devices")
    @classmethod
    def _device_names(cls, v: dict[str, DeviceConfig]) -> dict[str, DeviceConfig]:
        for name in v:
            # fullmatch: ``$`` also matches before a trailing newline ("ps\n" split the
            # log lines that name the device).
            if not re.fullmatch(NAME_PATTERN, name):
                raise ValueError(f"device name {name!r} must be a plain identifier")
        return v


def bench_model(kinds: Sequence[type[DeviceConfig]]) -> type[BenchConfig]:
    """``BenchConfig`` whose ``devices`` accept exactly these kinds, told apart by ``driver``.

    The device kinds live above this layer (``supervisor/devices/<kind>/config.py``); the
    registry hands them in, so adding a kind never edits this module.
    """
    if not kinds:
        raise ValueError("a bench model needs at least one device kind")
    union: Any = kinds[0] if len(kinds) == 1 else Union[tuple(kinds)]  # noqa: UP007
    device = Annotated[union, Field(discriminator="driver")]
    model: type[BenchConfig] = create_model(
        "BenchConfig",
        __base__=BenchConfig,
        __module__=BenchConfig.__module__,
        __doc__=BenchConfig.__doc__,
        devices=(dict[str, device], Field(min_length=1)),
    )
    model.device_kinds = tuple(kinds)
    return model
