"""Wiring rules of a bench I/O map: each safety reference points at the right kind of signal.

A map can be well-formed and still wired wrong: every tag exists, every key is spelt right,
and the e-stop reads a current, the heartbeat toggles the contactor coil, or an alarm's HH
sits below its LL. ``supervisor check`` refuses these before anything runs (issue 28,
finding 5). Each rule is one function below; ``check_bench`` (supervisor/config/bench.py)
runs them all and locates each problem at the offending key's value.

=======================================  ==============================  ==================
Rule                                     Refused (examples)              Why unsafe (word)
=======================================  ==============================  ==================
``estop_reads_a_boolean_input``          e-stop on ``pack.current``      kind: a number is
                                         (analog) or ``contactor.cmd``   never "closed";
                                         (an output)                     direction: an
                                                                         output shows what
                                                                         we wrote, no press
``feedback_reads_the_contactor``         feedback = the contactor's own  direction: it
                                         command, an output, an analog   reads back our
                                                                         command, not the
                                                                         contact
``measurements_have_kind_and_unit``      ``voltage_tag`` a boolean, a    kind, direction,
                                         relay or in degC;               unit: limits would
                                         ``temperature_tag`` in A        compare the wrong
                                                                         quantity
``one_owner_per_output``                 heartbeat = contactor coil;     ownership: two
                                         e-stop relay = heartbeat;       writers fight over
                                         ch0 and ch4 on one contactor    one output
``one_tag_per_output_point``             a second tag on the coil's      ownership: a write
                                         output (``slot3.do0``)          through one tag is
                                                                         undone by the other
``alarm_limits_in_order``                ``hh: 10, ll: 50``              ordering: LL < L
                                                                         < H < HH, or a
                                                                         limit never raises
``interlock_ids_not_reserved``           an interlock ``id: estop``      reserved: read as
                                                                         the bench's own
                                                                         e-stop/heartbeat
``interlock_condition_fits_its_tag``     ``equals:`` on an analog tag,   kind: the condition
                                         ``above:`` on a boolean         never holds
=======================================  ==============================  ==================

A reference to a tag that is not declared, or whose device or point is unknown, is left to
the checks that already report it (one message per mistake).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Final

from supervisor.config.models import BenchConfig, ChannelConfig

Path_ = tuple[str | int, ...]
Problem = tuple[Path_, str]
"""Where (a path into the file) and what is wrong, with why it would be unsafe."""

VOLT: Final = frozenset({"V"})
AMPERE: Final = frozenset({"A"})
CELSIUS: Final = frozenset({"degC", "°C"})

RESERVED_INTERLOCK_IDS: Final = ("estop", "heartbeat", "scan", "stall")
"""The bench's own safety functions (the ``estop`` alarm, the heartbeat, ``scan.stall``):
an interlock under one of these names reads, in the alarm list and the log, as that
function tripping."""


@dataclass(frozen=True, slots=True)
class Signal:
    """What a declared tag is, as the wiring rules see it."""

    name: str
    index: int  # its entry under tags:
    device: str
    point: str
    output: bool
    boolean: bool
    number: bool  # a float or int value (analog), not a boolean
    unit: str  # the mapping's unit, else the point's own when the value is not rescaled

    def describe(self) -> str:
        """ "an output (slot3.do0 of device 'adam')", "an analog input in A", ..."""
        at = f"({self.point} of device {self.device!r})"
        if self.output:
            return f"an output {at}"
        if self.boolean:
            return f"a boolean input {at}"
        if self.number:
            return f"an analog input {at}" + (f" in {self.unit}" if self.unit else "")
        return f"a text input {at}"


def signals(cfg: BenchConfig) -> dict[str, Signal]:
    """Every declared tag whose device and point exist, by name (the first of a name)."""
    out: dict[str, Signal] = {}
    for i, t in enumerate(cfg.tags):
        dev = cfg.devices.get(t.device)
        info = dev.points().get(t.point) if dev is not None else None
        if info is None or t.name in out:
            continue
        boolean = t.threshold is not None or info.dtype == "bool"
        rescaled = t.scaling is not None or t.threshold is not None
        out[t.name] = Signal(
            name=t.name,
            index=i,
            device=t.device,
            point=t.point,
            output=info.direction == "out",
            boolean=boolean,
            number=not boolean and info.dtype in ("float", "int"),
            unit=t.unit or ("" if rescaled else info.unit),
        )
    return out


Rule = Callable[[BenchConfig, Mapping[str, Signal]], Iterator[Problem]]


# --- the e-stop ----------------------------------------------------------------------------
def estop_reads_a_boolean_input(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """The e-stop sense is a boolean input, true while the circuit is closed."""
    estop = cfg.safety.estop
    s = sig.get(estop.tag) if estop is not None else None
    if s is None:
        return
    at: Path_ = ("safety", "estop", "tag")
    if s.output:
        yield (
            at,
            (
                f"e-stop tag {s.name!r} is {s.describe()}: the e-stop must read an input"
                " (direction): an output shows what the supervisor wrote, never a press"
            ),
        )
    elif not s.boolean:
        yield (
            at,
            (
                f"e-stop tag {s.name!r} is {s.describe()}, not a boolean (kind): the e-stop reads"
                " true while its circuit is closed; map the sense input with a threshold:"
            ),
        )


# --- each channel's measurements and contactor feedback -------------------------------------
def feedback_reads_the_contactor(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """A contactor feedback is a boolean input other than the contactor's own command."""
    for i, ch in enumerate(cfg.channels):
        ref = ch.contactor_feedback_tag
        s = sig.get(ref) if ref is not None else None
        if s is None:
            continue
        at: Path_ = ("channels", i, "contactor_feedback_tag")
        cmd = sig.get(ch.contactor_tag) if ch.contactor_tag is not None else None
        if cmd is not None and (s.device, s.point) == (cmd.device, cmd.point):
            yield (
                at,
                (
                    f"contactor_feedback_tag {s.name!r} is the contactor's own command"
                    f" (contactor_tag {cmd.name!r}) (direction): it reads back what the supervisor"
                    " wrote, never whether the contactor really closed; map its auxiliary contact"
                ),
            )
        elif s.output:
            yield (
                at,
                (
                    f"contactor_feedback_tag {s.name!r} is {s.describe()} (direction): a feedback"
                    " is an input wired to the contactor's auxiliary contact"
                ),
            )
        elif not s.boolean:
            yield (
                at,
                (
                    f"contactor_feedback_tag {s.name!r} is {s.describe()}, not a boolean (kind):"
                    " it must read true while the contactor is closed (give it a threshold:)"
                ),
            )


def _measured(ch: ChannelConfig, i: int) -> Iterator[tuple[Path_, str | None, str, frozenset[str]]]:
    """(where, tag, what it measures, the units it may be in) of a channel's measurements."""
    yield ("channels", i, "voltage_tag"), ch.voltage_tag, "voltage", VOLT
    yield ("channels", i, "current_tag"), ch.current_tag, "current", AMPERE
    yield ("channels", i, "temperature_tag"), ch.temperature_tag, "temperature", CELSIUS
    for k, vc in enumerate(ch.voltage_checks):
        yield ("channels", i, "voltage_checks", k, "tag"), vc.tag, "voltage", VOLT
    if ch.bms is not None:
        at: Path_ = ("channels", i, "bms")
        yield (*at, "cell_max_tag"), ch.bms.cell_max_tag, "cell voltage", VOLT
        yield (*at, "cell_min_tag"), ch.bms.cell_min_tag, "cell voltage", VOLT
        yield (*at, "temperature_tag"), ch.bms.temperature_tag, "temperature", CELSIUS


def measurements_have_kind_and_unit(
    cfg: BenchConfig, sig: Mapping[str, Signal]
) -> Iterator[Problem]:
    """A voltage, current or temperature tag is an analog input in V, A or degC (a tag
    without a unit is taken at its word: nothing tells what it measures)."""
    for i, ch in enumerate(cfg.channels):
        for at, ref, what, units in _measured(ch, i):
            s = sig.get(ref) if ref is not None else None
            if s is None:
                continue
            field = str(at[-1]) if at[-2] != "voltage_checks" else "voltage_checks tag"
            unit = " or ".join(sorted(units))
            if s.output:
                yield (
                    at,
                    (
                        f"{field} {s.name!r} is {s.describe()} (direction): a {what} is measured"
                        f" on an input in {unit}"
                    ),
                )
            elif not s.number:
                yield (
                    at,
                    (
                        f"{field} {s.name!r} is {s.describe()}, not a number (kind): the channel's"
                        f" {what} limits would compare a {what} in {unit} with it"
                    ),
                )
            elif s.unit and s.unit not in units:
                yield (
                    at,
                    (
                        f"{field} {s.name!r} is in {s.unit}, not {unit} (unit): the channel's"
                        f" {what} limits in {unit} would compare it as if it were"
                    ),
                )


# --- outputs: one writer each ------------------------------------------------------------------
def one_owner_per_output(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """Each output point has one writer among the channels' contactors, the e-stop relay
    and the heartbeat: two writers overwrite each other every scan."""
    claims: list[tuple[Path_, str | None, str]] = []
    for i, c in enumerate(cfg.channels):
        role = f"the contactor coil of channel {c.name!r}"
        claims.append((("channels", i, "contactor_tag"), c.contactor_tag, role))
    s = cfg.safety
    if s.estop is not None:
        claims.append((("safety", "estop", "relay_tag"), s.estop.relay_tag, "the e-stop relay"))
    if s.heartbeat is not None:
        claims.append((("safety", "heartbeat", "tag"), s.heartbeat.tag, "the heartbeat"))
    owner: dict[tuple[str, str], tuple[str, str]] = {}  # (device, point) -> (tag, role)
    for at, ref, role in claims:
        out = sig.get(ref) if ref is not None else None
        if out is None or not out.output:
            continue  # not an output: the checks of each reference say so
        key = (out.device, out.point)
        if key not in owner:
            owner[key] = (out.name, role)
            continue
        first, first_role = owner[key]
        same = f"{out.name!r}" + ("" if first == out.name else f" (output of {first!r})")
        yield (
            at,
            (
                f"{same} is already {first_role}; {role} needs an output of its own"
                f" (ownership of outputs): {_fight(first_role, role)}"
            ),
        )


def _fight(first: str, second: str) -> str:
    roles = {first, second}
    if "the heartbeat" in roles:
        return "the heartbeat toggles it every period, so the other could never hold it"
    if "the e-stop relay" in roles:
        return "the e-stop closes it whenever no e-stop trip holds the bench, whatever the other"
    return "one channel would close the contactor while the other has opened it"


def one_tag_per_output_point(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """An output point is mapped by one tag: a write through the other would undo it."""
    first: dict[tuple[str, str], str] = {}
    for i, t in enumerate(cfg.tags):
        s = sig.get(t.name)
        if s is None or s.index != i or not s.output:
            continue
        key = (s.device, s.point)
        if key in first:
            yield (
                ("tags", i, "point"),
                (
                    f"tag {s.name!r} maps output {s.point} of device {s.device!r}, already mapped"
                    f" by tag {first[key]!r} (ownership of outputs): a write through one would be"
                    " undone by the other; keep one tag per output"
                ),
            )
        first.setdefault(key, s.name)


# --- alarm limits and interlocks ----------------------------------------------------------------
ALARM_ORDER: Final = ("ll", "l", "h", "hh")


def alarm_limits_in_order(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """A tag's alarm limits are ordered LL < L < H < HH (those given)."""
    for i, t in enumerate(cfg.tags):
        if t.alarms is None:
            continue
        given = [(k, v) for k in ALARM_ORDER if (v := getattr(t.alarms, k)) is not None]
        for (lo_key, lo), (hi_key, hi) in itertools.pairwise(given):
            if lo >= hi:
                yield (
                    ("tags", i, "alarms", hi_key),
                    (
                        f"alarm limit {hi_key} {hi:g} of tag {t.name!r} is not above {lo_key}"
                        f" {lo:g} (ordering of limits): the limits must be ll < l < h < hh, or one"
                        " would be raised by a normal value and another never"
                    ),
                )
                break


def interlock_ids_not_reserved(cfg: BenchConfig, sig: Mapping[str, Signal]) -> Iterator[Problem]:
    """An interlock is not named after one of the bench's own safety functions."""
    for k, il in enumerate(cfg.safety.interlocks):
        if il.id.lower() in RESERVED_INTERLOCK_IDS:
            yield (
                ("safety", "interlocks", k, "id"),
                (
                    f"interlock id {il.id!r} is reserved (reserved ids:"
                    f" {', '.join(RESERVED_INTERLOCK_IDS)}): its alarm would read as the"
                    f" bench's own {il.id.lower()} tripping; choose another id"
                ),
            )


def interlock_condition_fits_its_tag(
    cfg: BenchConfig, sig: Mapping[str, Signal]
) -> Iterator[Problem]:
    """``equals`` tests a boolean tag; ``above``/``below`` an analog one."""
    for k, il in enumerate(cfg.safety.interlocks):
        s = sig.get(il.tag)
        if s is None:
            continue
        at: Path_ = ("safety", "interlocks", k, "tag")
        if il.equals is not None and not s.boolean:
            yield (
                at,
                (
                    f"interlock {il.id!r} tests equals: on {s.name!r}, {s.describe()}, not a"
                    " boolean (kind): the condition would never hold; use above: or below:"
                ),
            )
        elif il.equals is None and not s.number:
            yield (
                at,
                (
                    f"interlock {il.id!r} tests above:/below: on {s.name!r}, {s.describe()}, not a"
                    " number (kind); a boolean tag is tested with equals:"
                ),
            )


RULES: Final[tuple[Rule, ...]] = (
    estop_reads_a_boolean_input,
    feedback_reads_the_contactor,
    measurements_have_kind_and_unit,
    one_owner_per_output,
    one_tag_per_output_point,
    alarm_limits_in_order,
    interlock_ids_not_reserved,
    interlock_condition_fits_its_tag,
)


def wiring_problems(cfg: BenchConfig) -> list[Problem]:
    """Every wiring rule's problems with ``cfg``, in the order of ``RULES``."""
    sig = signals(cfg)
    return [p for rule in RULES for p in rule(cfg, sig)]
