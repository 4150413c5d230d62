"""Which samples of a monitored value reach a client: OPC UA's DataChangeFilter.

Part 4 §7.22.2 and Part 8 §6.2, as asyncua does not implement them (ADR 0014, "Deadbands
and timestamps"):

- A sample is compared with the **last value reported** to the client (Part 4: "the last
  cached value is defined as the last value pushed to the queue"), not with the previous
  sample: a ramp in steps smaller than the deadband is reported each time it has moved
  more than the deadband since the last report.
- AbsoluteDeadband: reported when ``|last reported − sample| > deadband``.
- PercentDeadband: the same with ``deadband = percent / 100 × (EURange.High − EURange.Low)``,
  the EURange the item's node had when the item was created (Part 8: only for an
  AnalogItem with an EURange).
- A change of status is always reported, whatever the deadband; the trigger Status
  reports nothing else, StatusValue also value changes, StatusValueTimestamp also changes
  of the SourceTimestamp — but with a deadband it behaves as StatusValue (Part 4 §7.10).
- A floating-point value entering NaN is reported once, not at every NaN sample (§7.10).
- An array is reported whole when its size changes or any element passes the deadband.

What a filter may not be is refused when the item is created (``value_filter``), with the
status code Part 4 / Part 8 name: a deadband on a variable that is not a Number
(Bad_FilterNotAllowed: "a monitoring filter cannot be used in combination with the
attribute specified"), a percent outside 0…100 or a negative deadband
(Bad_DeadbandFilterInvalid, Part 8 §6.2), a percent deadband on a Number without EURange
— an Int64 counter — (Bad_MonitoredItemFilterUnsupported: the filter is valid, this item
cannot support it; what node-opcua's and Eclipse Milo's servers answer too), an event or
aggregate filter on a value (Bad_FilterNotAllowed / Bad_MonitoredItemFilterUnsupported).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from asyncua import ua

S = ua.StatusCodes
Trigger = ua.DataChangeTrigger
# The filter classes as decoded from the wire: ``ua.DataChangeFilter`` is a subclass with
# asyncua's own defaults (uaprotocol_hand), of which a decoded filter is no instance.
DATA_CHANGE_FILTER: Final = ua.uaprotocol_auto.DataChangeFilter
EVENT_FILTER: Final = ua.uaprotocol_auto.EventFilter
DEFAULT_TRIGGER: Final = Trigger.StatusValue
"""Part 4 §7.22.2: what an item without a DataChangeFilter reports."""


@dataclass(frozen=True, slots=True)
class ValueFilter:
    """A monitored value's filter, checked: its trigger and its deadband in the value's own
    units (None: no deadband)."""

    trigger: ua.DataChangeTrigger = DEFAULT_TRIGGER
    deadband: float | None = None


NO_FILTER: Final = ValueFilter()


def value_filter(
    flt: object,
    *,
    value_attribute: bool,
    number: bool,
    eu_range: tuple[float, float] | None,
) -> ValueFilter | int:
    """The filter a client asked for on a data item, or the status code refusing it.

    ``value_attribute``: the item monitors the Value attribute; ``number``: the variable's
    DataType is a Number; ``eu_range``: its EURange (Low, High), None when it has none."""
    if flt is None or (isinstance(flt, ua.ExtensionObject) and not flt):
        return NO_FILTER  # no filter: a null ExtensionObject on the wire
    if isinstance(flt, EVENT_FILTER):
        return int(S.BadFilterNotAllowed)  # events are monitored on EventNotifier, not a value
    if not isinstance(flt, DATA_CHANGE_FILTER):
        # An AggregateFilter (not offered), or an ExtensionObject of a type not known.
        return int(S.BadMonitoredItemFilterUnsupported)
    try:
        trigger = Trigger(int(flt.Trigger))
    except ValueError:
        return int(S.BadMonitoredItemFilterInvalid)
    kind = int(flt.DeadbandType)
    if kind == ua.DeadbandType.None_:
        return ValueFilter(trigger)
    if kind not in (ua.DeadbandType.Absolute, ua.DeadbandType.Percent):
        return int(S.BadDeadbandFilterInvalid)
    if not value_attribute or not number:
        return int(S.BadFilterNotAllowed)  # Part 4: a deadband applies to Number variables only
    amount = float(flt.DeadbandValue)
    if not amount >= 0.0 or math.isinf(amount):  # NaN fails the first test
        return int(S.BadDeadbandFilterInvalid)
    if kind == ua.DeadbandType.Absolute:
        return ValueFilter(trigger, amount)
    if amount > 100.0:
        return int(S.BadDeadbandFilterInvalid)  # Part 8 §6.2: 0.0 to 100.0 percent
    deadband = _percent_deadband(amount, eu_range)
    if deadband is None:
        return int(S.BadMonitoredItemFilterUnsupported)
    return ValueFilter(trigger, deadband)


def _percent_deadband(percent: float, eu_range: tuple[float, float] | None) -> float | None:
    """A PercentDeadband in the value's own units: ``percent`` of the EURange's span; None
    when the item has no span to take a percent of (no EURange, or one of infinities)."""
    if eu_range is None:
        return None
    low, high = eu_range
    # 0 % is "every change" even over an unbounded range (0 × inf would be NaN).
    deadband = 0.0 if percent == 0.0 else percent / 100.0 * (float(high) - float(low))
    if deadband != deadband:
        return None  # an EURange of infinities has no span
    return deadband


def reports(f: ValueFilter, last: ua.DataValue | None, sample: ua.DataValue) -> bool:
    """Whether ``sample`` is reported to the client, ``last`` being the value last reported
    (None: nothing yet, the first sample is always reported)."""
    if last is None:
        return True
    if _status(last) != _status(sample):
        return True  # Part 4: the deadband is ignored when the status changes
    trigger = f.trigger
    if trigger == Trigger.Status:
        return False
    old, new = _value(last), _value(sample)
    if f.deadband is not None:
        return _exceeds(old, new, f.deadband)
    if _differs(old, new):
        return True
    return trigger == Trigger.StatusValueTimestamp and (
        last.SourceTimestamp != sample.SourceTimestamp
        or (last.SourcePicoseconds or 0) != (sample.SourcePicoseconds or 0)
    )


def _status(dv: ua.DataValue) -> int:
    sc = dv.StatusCode
    return 0 if sc is None else int(sc.value)


def _value(dv: ua.DataValue) -> object:
    v = dv.Value
    return None if v is None else v.Value


def _is_number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _is_nan(x: object) -> bool:
    return isinstance(x, float) and x != x


def _differs(old: object, new: object) -> bool:
    """A value change without a deadband; NaN to NaN is no change (Part 4 §7.10)."""
    if isinstance(old, list) and isinstance(new, list):
        return len(old) != len(new) or any(_differs(a, b) for a, b in zip(old, new, strict=True))
    if _is_nan(old) and _is_nan(new):
        return False
    return bool(old != new)


def _exceeds(old: object, new: object, deadband: float) -> bool:
    if isinstance(old, list) and isinstance(new, list):
        return len(old) != len(new) or any(
            _exceeds(a, b, deadband) for a, b in zip(old, new, strict=True)
        )
    if not (_is_number(old) and _is_number(new)):
        return _differs(old, new)  # a null (bad status kept) or a type change
    if _is_nan(old) or _is_nan(new):
        return not (_is_nan(old) and _is_nan(new))  # entering or leaving NaN, once
    # Integers subtract exactly (an Int64 counter near 2**63 stays exact); a float mixes.
    return bool(abs(new - old) > deadband)  # type: ignore[operator]
