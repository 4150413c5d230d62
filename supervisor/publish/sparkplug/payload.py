"""Sparkplug B payloads (Eclipse Sparkplug 3.0, chapter 6) encoded with the protobuf runtime.

The schema is the published ``sparkplug_b.proto``'s ``Payload`` message, transcribed here as a
descriptor (field numbers and types as the specification gives them) rather than generated
by ``protoc``: no compiler at build time, no generated module in the repository. Only what
an edge node sends is described (metrics with their properties and flags); a DataSet or a
Template field would be an unknown field, which protobuf skips. The descriptor lives in a
pool of its own, so a process that also imports another Sparkplug library (the tests'
independent consumer registers the same file name in the default pool) has no conflict.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, Final, NamedTuple

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from supervisor.core.driver import DType, Value
from supervisor.core.quality import Quality

__all__ = [
    "BOOLEAN",
    "DOUBLE",
    "INT64",
    "QUALITY_BAD",
    "QUALITY_GOOD",
    "QUALITY_STALE",
    "SPARKPLUG_TYPES",
    "STRING",
    "MetricValue",
    "decode",
    "encode",
    "quality_code",
]

# Sparkplug B datatypes (the specification's DataType enum) used here.
INT32: Final = 3
INT64: Final = 4
DOUBLE: Final = 10
BOOLEAN: Final = 11
STRING: Final = 12

SPARKPLUG_TYPES: Final[dict[DType, int]] = {
    "float": DOUBLE,
    "int": INT64,
    "bool": BOOLEAN,
    "str": STRING,
}
"""A tag's type → its metric's datatype (a float tag is a Double: the value as the scan has
it, no rounding to 32 bits)."""

# The 'Quality' property's codes (chapter 6, "Quality Codes").
QUALITY_BAD: Final = 0
QUALITY_GOOD: Final = 192
QUALITY_STALE: Final = 500

_QUALITY_CODES: Final = {
    Quality.GOOD: QUALITY_GOOD,
    # Uncertain is what a stale input or a held last value becomes: Sparkplug's STALE.
    Quality.UNCERTAIN: QUALITY_STALE,
    Quality.BAD: QUALITY_BAD,
}


def quality_code(q: Quality) -> int:
    return _QUALITY_CODES[q]


class MetricValue(NamedTuple):
    """One metric as an edge node sends it."""

    name: str
    datatype: int  # SPARKPLUG_TYPES' values, or INT64 / BOOLEAN for the node's own
    value: Value | None  # None: is_null
    timestamp_ms: int  # acquisition time, Unix ms
    quality: int | None = None  # the 'Quality' property (None: not sent)
    unit: str = ""  # the 'engUnit' property ("" : not sent; births only)
    historical: bool = False


_F = descriptor_pb2.FieldDescriptorProto
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
_PKG = "org.eclipse.tahu.protobuf"


def _field(
    msg: Any,
    name: str,
    number: int,
    ftype: int,
    *,
    label: int = _OPT,
    ref: str = "",
    oneof: int = -1,
) -> None:
    f = msg.field.add(name=name, number=number, type=ftype, label=label)
    if ref:
        f.type_name = f".{_PKG}.{ref}"
    if oneof >= 0:
        f.oneof_index = oneof


def _schema() -> descriptor_pb2.FileDescriptorProto:
    """``Payload`` of sparkplug_b.proto (proto2), the parts an edge node writes."""
    fd = descriptor_pb2.FileDescriptorProto(name="sparkplug_b.proto", package=_PKG, syntax="proto2")
    p = fd.message_type.add(name="Payload")
    pv = p.nested_type.add(name="PropertyValue")
    pv.oneof_decl.add(name="value")
    _field(pv, "type", 1, _F.TYPE_UINT32)
    _field(pv, "is_null", 2, _F.TYPE_BOOL)
    for name, number, ftype in (
        ("int_value", 3, _F.TYPE_UINT32),
        ("long_value", 4, _F.TYPE_UINT64),
        ("float_value", 5, _F.TYPE_FLOAT),
        ("double_value", 6, _F.TYPE_DOUBLE),
        ("boolean_value", 7, _F.TYPE_BOOL),
        ("string_value", 8, _F.TYPE_STRING),
    ):
        _field(pv, name, number, ftype, oneof=0)
    _field(pv, "propertyset_value", 9, _F.TYPE_MESSAGE, ref="Payload.PropertySet", oneof=0)
    ps = p.nested_type.add(name="PropertySet")
    _field(ps, "keys", 1, _F.TYPE_STRING, label=_REP)
    _field(ps, "values", 2, _F.TYPE_MESSAGE, label=_REP, ref="Payload.PropertyValue")
    m = p.nested_type.add(name="Metric")
    m.oneof_decl.add(name="value")
    _field(m, "name", 1, _F.TYPE_STRING)
    _field(m, "alias", 2, _F.TYPE_UINT64)
    _field(m, "timestamp", 3, _F.TYPE_UINT64)
    _field(m, "datatype", 4, _F.TYPE_UINT32)
    _field(m, "is_historical", 5, _F.TYPE_BOOL)
    _field(m, "is_transient", 6, _F.TYPE_BOOL)
    _field(m, "is_null", 7, _F.TYPE_BOOL)
    _field(m, "properties", 9, _F.TYPE_MESSAGE, ref="Payload.PropertySet")
    for name, number, ftype in (
        ("int_value", 10, _F.TYPE_UINT32),
        ("long_value", 11, _F.TYPE_UINT64),
        ("float_value", 12, _F.TYPE_FLOAT),
        ("double_value", 13, _F.TYPE_DOUBLE),
        ("boolean_value", 14, _F.TYPE_BOOL),
        ("string_value", 15, _F.TYPE_STRING),
        ("bytes_value", 16, _F.TYPE_BYTES),
    ):
        _field(m, name, number, ftype, oneof=0)
    _field(p, "timestamp", 1, _F.TYPE_UINT64)
    _field(p, "metrics", 2, _F.TYPE_MESSAGE, label=_REP, ref="Payload.Metric")
    _field(p, "seq", 3, _F.TYPE_UINT64)
    _field(p, "uuid", 4, _F.TYPE_STRING)
    _field(p, "body", 5, _F.TYPE_BYTES)
    return fd


_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(_schema())
Payload: Any = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(f"{_PKG}.Payload"))

_U64 = 1 << 64


def _set_value(metric: Any, datatype: int, value: Value) -> None:
    if datatype == DOUBLE:
        metric.double_value = float(value)
    elif datatype == INT64:
        metric.long_value = int(value) % _U64  # two's complement in a uint64 (chapter 6)
    elif datatype == BOOLEAN:
        metric.boolean_value = bool(value)
    else:
        metric.string_value = str(value)


def _properties(metric: Any, m: MetricValue) -> None:
    if m.quality is None and not m.unit:
        return
    props = metric.properties
    if m.quality is not None:
        props.keys.append("Quality")
        props.values.add(type=INT32, int_value=m.quality)
    if m.unit:
        props.keys.append("engUnit")
        props.values.add(type=STRING, string_value=m.unit)


def encode(
    timestamp_ms: int, metrics: Iterable[MetricValue], seq: int | None, *, datatypes: bool = True
) -> bytes:
    """A payload: its timestamp (sending time, Unix ms), metrics and sequence number
    (None: NDEATH, which has none). ``datatypes``: births carry each metric's datatype;
    a data message may leave it out (the birth told), but sending it costs two bytes and
    helps a consumer that joined late."""
    p = Payload(timestamp=timestamp_ms)
    if seq is not None:
        p.seq = seq
    for m in metrics:
        metric = p.metrics.add(name=m.name, timestamp=m.timestamp_ms)
        if datatypes:
            metric.datatype = m.datatype
        if m.historical:
            metric.is_historical = True
        if m.value is None:
            metric.is_null = True
        else:
            _set_value(metric, m.datatype, m.value)
        _properties(metric, m)
    data: bytes = p.SerializeToString()
    return data


def decode(raw: bytes) -> Any:
    """A payload (an NCMD's), as a protobuf message; ``google.protobuf.message.DecodeError``
    for bytes that are not one."""
    p = Payload()
    p.ParseFromString(raw)
    return p


def metric_names(payload: Any) -> Sequence[str]:
    return [m.name for m in payload.metrics]
