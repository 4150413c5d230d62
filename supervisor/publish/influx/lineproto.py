"""InfluxDB line protocol, built directly from the change feed's samples and bench events.

Built as strings, not with influxdb-client's ``Point`` (about 4× slower: its serialisation
is the bottleneck: docs/adr/0012). The schema (everyone follows it,
the dashboards query it):

- ``channel``: tags ``bench``, ``channel``, ``recipe``, ``test_id``, ``cell_id`` (the test's
  cell, when given; issue 26); one field per tag of the
  channel, named by the tag name after ``<ch>.`` with dots replaced by ``_``
  (``ch0.chain.state`` → ``chain_state``);
- ``device``: tags ``bench``, ``device`` (the tag name before its first dot); fields the same
  way (``pack.voltage`` → device ``pack``, field ``voltage``);
- ``diagnostics``: tags ``bench``, ``source`` (``scan``, ``influx``, ``historian``,
  ``alarms``): the tags under those prefixes, not ``device``;
- ``event``: tags ``bench``, ``channel``, ``kind``, ``recipe``, ``test_id``; fields ``text``,
  ``source``, ``actor`` (strings) and ``severity`` (float): what Grafana annotates.

A tag whose value is empty is omitted (InfluxDB refuses an empty tag value). Tag keys are
written in sorted order (what InfluxDB sorts them into anyway). Values by the tag's type:
analog (``float`` and ``int``) ALWAYS as floats (``1.0``, never ``1i``: an integer field
makes every later float a "field type conflict"), booleans as booleans, text as strings; a
BAD sample, a NaN or an infinity writes no field (a gap in the trend). The timestamp is the
acquisition time in nanoseconds (``Sample.wall``): a replayed point overwrites itself
instead of duplicating, which turns the spool's at-least-once delivery into exactly-once.
Every line is its own point: a series given a timestamp it already had lately (a value
written between two scans carries the last scan's time) gets the next free nanosecond,
so no value of ours replaces another on the server.

Escaping (line protocol reference, "Special characters"; checked against InfluxDB 1.8.10):
commas, spaces and equals signs in tag keys, tag values and field keys take a backslash;
measurement names escape commas and spaces; string field values escape ``"`` and ``\\``.
Two things the protocol cannot carry are changed, not escaped: a line break anywhere
becomes a space (one point is one line; the spool splits batches on line breaks), and a
backslash in a tag key, tag value or field key becomes ``/`` (1.8 keeps ``\\\\`` as two
backslashes and reads ``\\`` before a space, a comma or the end of the value as an escape,
so no spelling of it survives the round trip).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from supervisor.core.driver import Value
from supervisor.core.encoding import storable_text
from supervisor.core.records import BenchEvent
from supervisor.publish.changes import Sample

__all__ = [
    "CHANNEL",
    "DEVICE",
    "DIAGNOSTICS",
    "DIAGNOSTIC_SOURCES",
    "EVENT",
    "MEASUREMENTS",
    "LineEncoder",
    "escape_field_key",
    "escape_measurement",
    "escape_string",
    "escape_tag",
    "format_float",
    "line_measurement",
    "timestamp_ns",
]

CHANNEL = "channel"
DEVICE = "device"
DIAGNOSTICS = "diagnostics"
EVENT = "event"
MEASUREMENTS = (CHANNEL, DEVICE, DIAGNOSTICS, EVENT)

DIAGNOSTIC_SOURCES = frozenset({"scan", "influx", "historian", "alarms"})
"""Tag-name prefixes that describe the supervisor itself: ``diagnostics``, not ``device``."""

RECENT_PER_SERIES = 256
"""Timestamps remembered per series to keep every line its own point."""
MAX_SERIES = 10_000
"""Series remembered at most (the memory is cleared past it)."""

RESERVED_FIELD_KEYS = {"time": "time_"}
"""InfluxDB refuses a field named ``time`` (every point would be dead-lettered)."""

_KEY = str.maketrans(
    {
        "\\": "/",
        ",": "\\,",
        "=": "\\=",
        " ": "\\ ",
        "\n": "\\ ",
        "\r": "\\ ",
    }
)
_MEASUREMENT = str.maketrans({"\\": "/", ",": "\\,", " ": "\\ ", "\n": "\\ ", "\r": "\\ "})
_STRING = str.maketrans({"\\": "\\\\", '"': '\\"', "\n": " ", "\r": " "})


def escape_tag(text: str) -> str:
    """A tag key or tag value (also a field key) as line protocol writes it (a character
    UTF-8 cannot encode escaped: ``core/encoding.py``)."""
    return storable_text(text).translate(_KEY)


escape_field_key = escape_tag


def escape_measurement(text: str) -> str:
    return storable_text(text).translate(_MEASUREMENT)


def escape_string(text: str) -> str:
    """A string field value, quotes included."""
    return f'"{storable_text(text).translate(_STRING)}"'


def format_float(value: float) -> str | None:
    """A float field value; None for NaN and infinities (InfluxDB refuses them)."""
    if not math.isfinite(value):
        return None
    # repr: the shortest text that reads back as the same double ("1.0", "1e-05").
    return repr(value)


def timestamp_ns(wall: float) -> int:
    """Unix seconds → the integer nanoseconds line protocol carries (a given float gives
    the same integer every time: a replay writes the same timestamp)."""
    return round(wall * 1e9)


def line_measurement(line: str | bytes) -> str:
    """The measurement a line of ours belongs to (our measurement names need no escape)."""
    text = line.decode("utf-8", "replace") if isinstance(line, bytes) else line
    end = len(text)
    for sep in (",", " "):
        k = text.find(sep)
        if 0 <= k < end:
            end = k
    return text[:end]


# --- values by tag type -------------------------------------------------------------------
Formatter = Callable[[Value], str | None]


def _as_float(value: Value) -> str | None:
    if isinstance(value, bool):
        return "1.0" if value else "0.0"
    if isinstance(value, int | float):
        try:
            return format_float(float(value))
        except OverflowError:  # an int beyond the double range
            return None
    return None


def _as_bool(value: Value) -> str | None:
    if isinstance(value, bool | int | float):
        return "true" if value else "false"
    return None


def _as_string(value: Value) -> str | None:
    return escape_string(value if isinstance(value, str) else str(value))


def _by_value(value: Value) -> str | None:
    """A value of a tag the encoder has no type for: by its Python type."""
    if isinstance(value, bool):
        return _as_bool(value)
    if isinstance(value, int | float):
        return _as_float(value)
    return _as_string(value)


_FORMATTERS: dict[str, Formatter] = {
    "float": _as_float,
    "int": _as_float,  # analog values always as floats (schema)
    "bool": _as_bool,
    "str": _as_string,
}


@dataclass(frozen=True, slots=True)
class _Route:
    """Where one tag's samples go: its measurement, its series and its field."""

    measurement: str
    channel: str  # "" unless the measurement is ``channel`` (its series tags vary)
    prefix: str  # measurement and tag set, for every measurement but ``channel``
    field: str  # the escaped field key, "=" included
    format: Formatter
    analog: bool  # a float or int tag: a float value is written as repr(value)


class LineEncoder:
    """Samples and events → lines, grouped per measurement, tag set and timestamp.

    ``dtype_of(name)`` gives a tag's declared type (``float``, ``int``, ``bool``,
    ``str``), which fixes its field type for good; None when unknown (then the value's own
    type decides). Routes are worked out once per tag name.
    """

    def __init__(
        self,
        bench: str,
        channels: Iterable[str],
        dtype_of: Callable[[str], str | None] = lambda name: None,
    ) -> None:
        self.bench = bench
        self.channels = frozenset(channels)
        self.dtype_of = dtype_of
        self._bench_tag = f"bench={escape_tag(bench)}" if bench else ""
        self._routes: dict[str, _Route] = {}
        self._channel_prefixes: dict[tuple[str, str, str, str], str] = {}
        # The timestamps each series was given lately: a line of a series at an instant it
        # already has (a value written between two scans carries the last scan's time,
        # several alarms are raised in one scan) would overwrite that point on the server.
        self._recent: dict[str, tuple[deque[int], set[int]]] = {}

    # --- samples ----------------------------------------------------------------------
    def encode(
        self, samples: Iterable[Sample], tests: Mapping[str, tuple[str, ...]] | None = None
    ) -> dict[str, list[str]]:
        """Lines by measurement. ``tests``: each channel's current (test id, recipe, cell
        id), the ``test_id``, ``recipe`` and ``cell_id`` tags of its points."""
        # The scan's thread runs this for every change: plain locals, one dict lookup per
        # sample, the float case (almost every sample) without a call.
        groups: dict[tuple[str, int], tuple[str, list[str]]] = {}
        routes = self._routes
        prefixes: dict[str, str] = {}
        finite = math.isfinite
        for s in samples:
            value = s.value
            if value is None:
                continue  # BAD: no field, a gap
            route = routes.get(s.name)
            if route is None:
                route = routes[s.name] = self._route(s.name)
            if route.analog and type(value) is float:
                if not finite(value):
                    continue
                text = route.field + repr(value)
            else:
                formatted = route.format(value)
                if formatted is None:
                    continue
                text = route.field + formatted
            channel = route.channel
            if channel:
                prefix = prefixes.get(channel)
                if prefix is None:
                    test = (tests or {}).get(channel, ())
                    prefix = prefixes[channel] = self.channel_prefix(channel, *test)
            else:
                prefix = route.prefix
            key = (prefix, round(s.wall * 1e9))  # timestamp_ns, inline
            group = groups.get(key)
            if group is None:
                groups[key] = (route.measurement, [text])
            else:
                group[1].append(text)
        out: dict[str, list[str]] = {}
        # Oldest first within one call, so that each series' points go out in time order.
        for (prefix, ts), (measurement, fields) in sorted(groups.items(), key=_by_time):
            ts = self._unique(prefix, ts)
            out.setdefault(measurement, []).append(f"{prefix} {','.join(fields)} {ts}")
        return out

    def _unique(self, prefix: str, ts: int) -> int:
        """``ts``, or the next free nanosecond when this series had a point there lately:
        every line is its own point, none replaces another (a replay of a spooled line is
        the same text, so it still overwrites only itself)."""
        recent = self._recent.get(prefix)
        if recent is None:
            if len(self._recent) >= MAX_SERIES:  # bounded: test ids come and go
                self._recent.clear()
            recent = self._recent[prefix] = (deque(), set())
        order, seen = recent
        while ts in seen:
            ts += 1
        order.append(ts)
        seen.add(ts)
        if len(order) > RECENT_PER_SERIES:
            seen.discard(order.popleft())
        return ts

    def channel_prefix(
        self, channel: str, test_id: str = "", recipe: str = "", cell_id: str = ""
    ) -> str:
        key = (channel, test_id, recipe, cell_id)
        prefix = self._channel_prefixes.get(key)
        if prefix is None:
            prefix = self._prefix(
                CHANNEL,
                {"channel": channel, "test_id": test_id, "recipe": recipe, "cell_id": cell_id},
            )
            if len(self._channel_prefixes) > MAX_SERIES:  # bounded: test ids come and go
                self._channel_prefixes.clear()
            self._channel_prefixes[key] = prefix
        return prefix

    def _route(self, name: str) -> _Route:
        head, dot, rest = name.partition(".")
        field = rest.replace(".", "_") if dot else "value"
        field = RESERVED_FIELD_KEYS.get(field, field)
        dtype = self.dtype_of(name)
        fmt = _FORMATTERS.get(dtype, _by_value) if dtype is not None else _by_value
        key = escape_field_key(field) + "="
        analog = fmt is _as_float or fmt is _by_value
        if head in self.channels and dot:
            return _Route(CHANNEL, head, "", key, fmt, analog)
        if head in DIAGNOSTIC_SOURCES and dot:
            prefix = self._prefix(DIAGNOSTICS, {"source": head})
            return _Route(DIAGNOSTICS, "", prefix, key, fmt, analog)
        return _Route(DEVICE, "", self._prefix(DEVICE, {"device": head}), key, fmt, analog)

    def _prefix(self, measurement: str, tags: Mapping[str, str]) -> str:
        parts = [escape_measurement(measurement)]
        items = dict(tags)
        if self.bench:
            items["bench"] = self.bench
        for k in sorted(items):
            v = items[k]
            if v:
                parts.append(f"{escape_tag(k)}={escape_tag(v)}")
        return ",".join(parts)

    # --- events -----------------------------------------------------------------------
    def event(self, ev: BenchEvent) -> str:
        """One ``event`` line (Grafana annotations)."""
        prefix = self._prefix(
            EVENT,
            {"kind": ev.kind, "channel": ev.channel, "test_id": ev.test_id, "recipe": ev.recipe},
        )
        ts = self._unique(prefix, timestamp_ns(ev.wall))
        severity = format_float(float(ev.severity)) or "0.0"
        fields = (
            f"actor={escape_string(ev.actor)},severity={severity},"
            f"source={escape_string(ev.source)},text={escape_string(ev.text)}"
        )
        return f"{prefix} {fields} {ts}"


def _by_time(item: tuple[tuple[str, int], tuple[str, list[str]]]) -> int:
    return item[0][1]
